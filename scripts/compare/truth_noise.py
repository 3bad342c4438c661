"""How much of two trajectories' rotation error per pair is the ground truth's own (a three-cornered hat).

    python scripts/compare/truth_noise.py BAG A.tum B.tum [--truth-topic /ground_truth/pose]

A and B are two estimates of the same frames (COLMAP's ``trajectory.tum``, ``nocal odometry``'s
``trajectory.tum`` or ``trajectory_final.tum``). Over the frames both hold, each consecutive pair's
rotation is compared three ways: A against the truth, B against the truth, and A against B. If the three
errors are independent, their mean squares are ``a + g``, ``b + g`` and ``a + b``, so the truth's own
``g`` is ``(|A-GT|^2 + |B-GT|^2 - |A-B|^2) / 2``. A recording's ground truth (a motion capture, a GPS/INS)
is not exact: a consistency check (NEES) against it counts its noise as the estimator's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def rotation_steps_deg(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The angle, in degrees, between X's and Y's rotation over each consecutive pair (``(N, 4, 4)`` each)."""
    from nocal_ros.geometry import so3_log

    def steps(T):
        return np.einsum("kji,kjl->kil", T[:-1, :3, :3], T[1:, :3, :3])

    return np.degrees([np.linalg.norm(so3_log(x.T @ y)) for x, y in zip(steps(X), steps(Y))])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag")
    parser.add_argument("a", help="a TUM trajectory")
    parser.add_argument("b", help="another TUM trajectory of the same frames")
    parser.add_argument("--truth-topic", default="/ground_truth/pose")
    args = parser.parse_args(argv)

    from nocal_ros.data.bags import read_poses
    from nocal_ros.data.importers.common import read_tum_poses

    stamps_a, A = read_tum_poses(Path(args.a))
    stamps_b, B = read_tum_poses(Path(args.b))
    common = np.intersect1d(stamps_a, stamps_b)
    A, B = A[np.searchsorted(stamps_a, common)], B[np.searchsorted(stamps_b, common)]
    truth = read_poses(args.bag, args.truth_topic, common)
    keep = np.isfinite(truth).all(axis=(1, 2))
    A, B, truth = A[keep], B[keep], truth[keep]
    if len(truth) < 3:
        parser.error(f"{len(truth)} frames are in both trajectories with a true pose: at least 3 are needed")

    errors = {"A - truth": rotation_steps_deg(A, truth), "B - truth": rotation_steps_deg(B, truth),
              "A - B": rotation_steps_deg(A, B)}
    print(f"{len(truth) - 1} consecutive pairs; the truth turns {rotation_steps_deg(truth, np.tile(np.eye(4), (len(truth), 1, 1))).mean():.3f} deg per pair")
    for name, e in errors.items():
        print(f"  {name:10s} rotation per pair: mean {e.mean():.4f}, RMS {np.sqrt(np.mean(e**2)):.4f} deg")
    va, vb, vab = (np.mean(e**2) for e in errors.values())
    g = (va + vb - vab) / 2
    print("three-cornered hat, RMS per pair (a negative share is printed as 0: the errors are not independent "
          "or the pairs too few)")
    for name, v in (("truth", g), ("A", va - g), ("B", vb - g)):
        print(f"  {name:6s} {np.sqrt(max(v, 0.0)):.4f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
