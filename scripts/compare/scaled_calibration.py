"""A bag's true calibration with its focal lengths scaled: a stale or wrong calibration file to give
``nocal odometry --calibration`` (or the node's ``camera_info_url``), to measure the check of a given
calibration against the stream.

    python scripts/compare/scaled_calibration.py BAG --focal-scale 1.1 --out wrong.yaml

Reads the bag's ``/ground_truth/camera_info`` (what ``nocal synth`` and ``nocal import`` write) and
writes it, fx and fy times the scale and all else as it was, in ROS camera_calibration YAML.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--focal-scale", type=float, required=True, help="fx and fy are multiplied by this")
    parser.add_argument("--out", type=Path, required=True, help="the calibration YAML to write")
    parser.add_argument("--camera-info-topic", default="/ground_truth/camera_info")
    args = parser.parse_args(argv)

    from nocal_ros.data.bags import read_camera_info
    from nocal_ros.errors import NocalError
    from nocal_ros.lens import CameraCalibration

    if not args.focal_scale > 0:
        print(f"error: --focal-scale must be positive, got {args.focal_scale}", file=sys.stderr)
        return 2
    try:
        truth = read_camera_info(args.bag, args.camera_info_topic)
    except NocalError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    K = truth.K.copy()
    K[:2, :2] *= args.focal_scale
    scaled = CameraCalibration(truth.width, truth.height, K, truth.D, truth.distortion_model, truth.camera_name)
    scaled.save(args.out)
    print(f"{args.out}: fx {truth.fx:.2f} -> {scaled.fx:.2f}, fy {truth.fy:.2f} -> {scaled.fy:.2f} ({truth.width}x{truth.height})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
