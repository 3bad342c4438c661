"""Whether VAMR's checkerboard moves against the desk: the median pixel motion of the board's corners
and of the desk's corners from frame k to k + GAP, with OpenCV alone.

    python scripts/compare/vamr_board_motion.py ../shared/data/real/vamr_ex1 [--gap 10] [--every 30 | --frames K ...]

The recording's poses are the camera's against the board, so where a hand moves the board they are not
the camera's motion against the rest of the scene, which is what a VO measures. Desk corners are taken
outside the board (its hull grown by 60 %) and above row 300, where hands and arms enter; tracks must
pass a forward-backward check of 0.5 px. Under a camera's own motion both move alike (ratio near 1,
depth aside); a board moved by hand moves much more than the desk.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="the vamr_ex1 folder (images/img_0001.jpg ...)")
    parser.add_argument("--gap", type=int, default=10)
    parser.add_argument("--every", type=int, default=30)
    parser.add_argument("--frames", type=int, nargs="+", help="these start frames instead of every --every")
    args = parser.parse_args(argv)
    images = sorted((Path(args.folder) / "images").glob("img_*.jpg"))
    if not images:
        parser.error(f"no images/img_*.jpg under {args.folder}")

    def grey(k: int) -> np.ndarray:
        return cv2.imread(str(images[k]), cv2.IMREAD_GRAYSCALE)

    starts = args.frames if args.frames else range(0, len(images) - args.gap, args.every)
    for k in starts:
        if not 0 <= k < len(images) - args.gap:
            parser.error(f"frame {k} and {k} + {args.gap} must be among the {len(images)} frames")
        a, b = grey(k), grey(k + args.gap)
        found_a, corners_a = cv2.findChessboardCorners(a, (9, 6))
        found_b, corners_b = cv2.findChessboardCorners(b, (9, 6))
        if not (found_a and found_b):
            print(f"{k}->{k + args.gap}: board not found")
            continue
        board = float(np.median(np.linalg.norm(corners_b.reshape(-1, 2) - corners_a.reshape(-1, 2), axis=1)))
        mask = np.full(a.shape, 255, np.uint8)
        hull = cv2.convexHull(corners_a.reshape(-1, 2))
        centre = hull.mean(0)
        cv2.fillConvexPoly(mask, (centre + 1.6 * (hull - centre)).astype(np.int32), 0)
        mask[300:, :] = 0
        points = cv2.goodFeaturesToTrack(a, 300, 0.01, 8, mask=mask)
        tracked, status, _ = cv2.calcOpticalFlowPyrLK(a, b, points, None)
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(b, a, tracked, None)
        good = (status.ravel() == 1) & (status_back.ravel() == 1) & (np.linalg.norm(back - points, axis=2).ravel() < 0.5)
        desk = float(np.median(np.linalg.norm((tracked - points).reshape(-1, 2)[good], axis=1)))
        print(f"{k}->{k + args.gap}: board corners moved {board:6.1f} px, desk corners {desk:6.1f} px "
              f"({int(good.sum())} tracked), ratio {board / max(desk, 1e-3):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
