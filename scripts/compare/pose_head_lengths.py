"""Does the pose head measure translation length? Its length against the truth, per frame gap.

    python scripts/compare/pose_head_lengths.py BAG [BAG ...] [--model STORE] [--gaps 1 2 4 8]

For every frame of each bag and every gap ``g``, the pose head runs on the pair (frame - g, frame) and
its translation length is divided by the true distance between the two cameras (the bag's
``/ground_truth/pose``). A pose head that measures length gives the same median ratio at every gap; one
that predicts about one step per pair gives a ratio that halves as the gap doubles. docs/RESULTS.md
("The trajectory through the final map and camera") has the figures for the shipped model.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def length_ratios(bag: Path, gaps: list[int], model=None) -> dict[int, np.ndarray]:
    """``{gap: ratios (N,)}``: the pose head's length over the true length for each pair ``gap`` apart."""
    import torch

    from nocal_ros.commands.odometry import _frames
    from nocal_ros.data.bags import read_poses
    from nocal_ros.odometry.pose_head import PoseModel, PoseRunner

    torch.set_num_threads(1)
    model = model or PoseModel.from_checkpoint(None, "cpu")
    if max(gaps) > model.max_gap:
        raise SystemExit(f"gaps must be at most the model's max_gap ({model.max_gap}), got {max(gaps)}")
    runner = PoseRunner(model, "fp32", False, True, history=model.max_gap + 1)
    keys, stamps, pairs = [], [], {gap: [] for gap in gaps}
    for index, (stamp, _, image) in enumerate(_frames(bag, "/camera/image_raw", None, False)):
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        keys.append(runner.load_frame(image))
        stamps.append(stamp)
        for gap in gaps:
            if index >= gap:
                T = runner.run(keys[-1 - gap], keys[-1])
                pairs[gap].append((index - gap, index, float(np.linalg.norm(T[:3, 3]))))
    truth = read_poses(bag, "/ground_truth/pose", np.asarray(stamps, dtype=np.int64))
    ratios = {}
    for gap, rows in pairs.items():
        true_lengths = np.array([np.linalg.norm(truth[b, :3, 3] - truth[a, :3, 3]) for a, b, _ in rows])
        lengths = np.array([length for _, _, length in rows])
        moving = true_lengths > 1e-9
        ratios[gap] = lengths[moving] / true_lengths[moving]
    return ratios


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--model", default=None, help="checkpoint or model store (default: the shipped model)")
    parser.add_argument("--gaps", nargs="+", type=int, default=[1, 2, 4, 8])
    args = parser.parse_args(argv)
    from nocal_ros.odometry.pose_head import PoseModel

    model = PoseModel.from_checkpoint(args.model, "cpu")
    for bag in args.bags:
        ratios = length_ratios(bag, args.gaps, model)
        cells = [f"gap {gap}: {np.median(r):.2f} ({len(r)} pairs)" for gap, r in ratios.items()]
        print(f"{bag.name}: pose head length / true length, median: " + ", ".join(cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
