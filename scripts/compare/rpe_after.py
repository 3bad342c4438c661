"""RPE per consecutive pair of a ``trajectory.tum`` from a given frame on, against a bag's ground truth.

    python scripts/compare/rpe_after.py BAG TRAJECTORY.tum --from-frame N

For comparing methods on the same frames after a start-up phase (the keyframe VO's online camera
converging from the prior): ``nocal odometry``'s and ``scripts/compare/colmap.py``'s trajectories
alike. The pairs are consecutive poses of the file whose stamps the bag's ``/ground_truth/pose`` has;
``--from-frame`` counts those poses from 0. Rotation RMSE (deg), and translation RMSE after a Sim(3)
alignment of the whole trajectory (the scale of a monocular estimate is not what is compared here).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag")
    parser.add_argument("trajectory")
    parser.add_argument("--from-frame", type=int, default=0)
    parser.add_argument("--gt-topic", default="/ground_truth/pose")
    args = parser.parse_args(argv)

    from nocal_ros import evaluation
    from nocal_ros.data.bags import read_poses
    from nocal_ros.data.importers.common import read_tum_poses

    stamps, estimate = read_tum_poses(Path(args.trajectory))
    truth = read_poses(args.bag, args.gt_topic, stamps)
    valid = np.isfinite(truth).all(axis=(1, 2))
    stamps, estimate, truth = stamps[valid], estimate[valid], truth[valid]
    rpe = evaluation.relative_pose_error(estimate, truth, correct_scale=True)
    rotation = np.asarray(rpe["rotation_deg_per_pair"])[args.from_frame:]
    translation = np.asarray(rpe["translation_m_per_pair"])[args.from_frame:]
    print(f"{args.trajectory}: {len(rotation)} pairs from frame {args.from_frame}: RPE rotation RMSE "
          f"{np.sqrt(np.mean(rotation**2)):.3f} deg, translation RMSE {np.sqrt(np.mean(translation**2)):.4f} m "
          f"(Sim(3)-aligned, scale {rpe['scale']:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
