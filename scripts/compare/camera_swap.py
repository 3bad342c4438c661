"""A camera swapped at a cut: bag A's frames, a few black frames, then bag B's, through one estimator.

    python scripts/compare/camera_swap.py BAG_A BAG_B [--black 3] [--calibration A.yaml]

Measures what the odometry does with the camera it carries into the map after the cut when the camera
itself changed there (a lens swapped or refocused while the view was covered): the focal length at the
cut against A's true one, at the end against B's, and the new map's check of the carried camera
(``OnlineCamera.check_start``); with ``--calibration`` (A's, say, as ``camera_info_url`` gives it) the
check of that given calibration instead. Both bags need ``/ground_truth/camera_info`` (``nocal synth`` and
``nocal import`` write it) and frames of one size. Synchronous mapping, so a run repeats.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag_a", type=Path)
    parser.add_argument("bag_b", type=Path)
    parser.add_argument("--black", type=int, default=3, help="black frames at the cut")
    parser.add_argument("--camera-info-topic", default="/ground_truth/camera_info")
    parser.add_argument("--calibration", type=Path, help="camera_calibration YAML to start the online camera from")
    args = parser.parse_args(argv)

    import numpy as np

    from nocal_ros.data.bags import iter_images, read_camera_info
    from nocal_ros.errors import NocalError
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry import OdometryEstimator

    try:
        truth_a, truth_b = (read_camera_info(bag, args.camera_info_topic) for bag in (args.bag_a, args.bag_b))
        given = CameraCalibration.load(args.calibration) if args.calibration else None
    except NocalError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    if (truth_a.width, truth_a.height) != (truth_b.width, truth_b.height):
        print(f"error: the bags' cameras differ in size ({truth_a.width}x{truth_a.height} and "
              f"{truth_b.width}x{truth_b.height}): a swap here keeps the size", file=sys.stderr)
        return 2
    estimator = OdometryEstimator(calibration=given, synchronous_mapping=True)
    period_ns, stamp_ns = 100_000_000, 0

    def process(image: np.ndarray) -> float:
        nonlocal stamp_ns
        stamp_ns += period_ns
        estimator.process(stamp_ns, image)
        return estimator.camera_info()[0].fx

    try:
        at_cut = image = None
        for _, _, image in iter_images(args.bag_a):
            at_cut = process(image)
        for _ in range(args.black):
            process(np.zeros_like(image))
        at_end = at_cut
        for _, _, image in iter_images(args.bag_b):
            at_end = process(image)
    except NocalError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    finally:
        estimator.close()
    status = estimator.calibration_status()
    statistic = status.get("check_statistic")
    print(f"{args.bag_a.name} fx {truth_a.fx:.1f} -> {args.bag_b.name} fx {truth_b.fx:.1f} "
          f"({100 * (truth_b.fx / truth_a.fx - 1):+.1f} %): focal at the cut {at_cut:.1f} px "
          f"({100 * (at_cut / truth_a.fx - 1):+.2f} % of A's), at the end {at_end:.1f} px "
          f"({100 * (at_end / truth_b.fx - 1):+.2f} % of B's); maps {estimator.counters.maps}; "
          + (f"given calibration {status.get('given_check')}" if given is not None else
             f"carried camera {status.get('carried_check') or 'not checked'}")
          + ("" if statistic is None else f" (statistic {statistic:.1f})"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
