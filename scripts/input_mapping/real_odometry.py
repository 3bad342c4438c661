"""The shipped pose head on real non-4:3 recordings, with the frames cropped or stretched (the core's map).

Replays a bag imported by ``nocal import`` through ``nocal odometry`` (pose head only, ``--method pose_head``,
so every figure is the pose head's) with the pose head's runner fed by either mapping, and prints
the relative pose error per pair against the bag's ground truth, and the translation length ratio
(predicted / true; the shipped head's length is not metric on unseen cameras, so both are shown).

python scripts/input_mapping/real_odometry.py BAG [BAG ...] [--max-frames N]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

import nocal_ros.odometry.pose_head as pose_head
from nocal_ros.cli import main
from nocal_ros.network_input import network_input

from measure import mapping_for  # noqa: E402  (this folder)


def policy_input(policy):
    def mapped(image, size, out=None):
        mapping = mapping_for(policy, (image.shape[1], image.shape[0]), tuple(size))
        return mapping.apply(image, out), mapping

    return mapped


parser = argparse.ArgumentParser()
parser.add_argument("bags", nargs="+", type=Path)
parser.add_argument("--max-frames", type=int, default=None)
args = parser.parse_args()
print(f"{'bag':24s} {'mapping':8s} {'RPE m':>8s} {'RPE deg':>8s} {'length ratio':>13s} {'pairs':>6s}")
for bag in args.bags:
    for name in ("crop", "stretch"):
        pose_head.network_input = policy_input(name)
        with tempfile.TemporaryDirectory() as out:
            argv = ["odometry", str(bag), "--out", out, "--method", "pose_head", "--threads", "1", "--no-progress", "--overwrite"]
            if args.max_frames:
                argv += ["--max-frames", str(args.max_frames)]
            assert main(argv) == 0
            report = json.loads((Path(out) / "report.json").read_text())
            estimate = np.loadtxt(Path(out) / "trajectory.tum")
        steps_est = np.linalg.norm(np.diff(estimate[:, 1:4], axis=0), axis=1)
        rpe = report["rpe"]
        print(f"{bag.name:24s} {name:8s} {rpe['translation_m']['mean']:8.4f} {rpe['rotation_deg']['mean']:8.3f} "
              f"{steps_est.sum() / report['path_length_m']:13.3f} {rpe['translation_m']['count']:6d}")
pose_head.network_input = network_input
