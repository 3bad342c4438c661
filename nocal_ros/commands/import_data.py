"""``nocal import FORMAT SRC --out BAG``: a dataset or a recording to a rosbag2 in ``nocal synth``'s layout.

The work is :mod:`nocal_ros.data.importers` (the trainer and the tests call it too); this is its shell.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from nocal_ros.errors import BagError, ConfigError

FORMAT_HELP = {
    "kitti": "KITTI odometry sequence folder (image_0..3 or image_l/r, calib.txt, times.txt, poses)",
    "euroc": "EuRoC MAV ASL folder (mav0/cam0, sensor.yaml, state_groundtruth_estimate0)",
    "tum": "TUM RGB-D sequence folder (rgb.txt, groundtruth.txt)",
    "folder": "a folder of images (--rate or --timestamps; --poses, --calibration optional)",
    "video": "a video file read through OpenCV (--rate, --calibration optional)",
    "vamr": "UZH VAMR exercise folder (images/, K.txt, D.txt, poses.txt)",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "formats:\n" + "\n".join(f"  {name:7s} {text}" for name, text in FORMAT_HELP.items())
    parser.add_argument("format", choices=sorted(FORMAT_HELP), metavar="FORMAT", help="dataset format (see below)")
    parser.add_argument("src", type=Path, metavar="SRC", help="the dataset folder (a file for video)")
    parser.add_argument("--out", type=Path, required=True, help="output bag (a rosbag2 directory)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap)")
    parser.add_argument("--arm-fraction", type=float, default=0.0, metavar="F",
                        help="republish the ground truth of this share of the frames on /arm/pose, in runs (default 0)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the --arm-fraction runs (default 0)")
    parser.add_argument("--max-frames", type=int, default=None, help="import only the first N frames")
    parser.add_argument("--encoding", choices=("auto", "mono8", "rgb8"), default=None,
                        help="image encoding in the bag (default: the source's own; vamr: mono8)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag at --out")
    group = parser.add_argument_group("format options (each format takes those that apply)")
    group.add_argument("--rate", type=float, default=None, metavar="HZ",
                       help="frame rate: folder (or --timestamps), video (default: its own times), "
                            "kitti without times.txt (default 10), vamr (default 30)")
    group.add_argument("--timestamps", type=Path, default=None, metavar="FILE",
                       help="folder: one time in seconds per image, or 'timestamp filename' lines")
    group.add_argument("--poses", type=Path, default=None, metavar="FILE",
                       help="folder: TUM trajectory of the camera; kitti: the pose file if not found beside SRC")
    group.add_argument("--calibration", type=Path, default=None, metavar="YAML",
                       help="folder, video, tum: ROS camera_calibration YAML of the camera")
    group.add_argument("--camera", default=None,
                       help="kitti: image folder (image_0..image_3, image_l, image_r); euroc: camera folder (cam0)")
    group.add_argument("--max-difference", type=float, default=None, metavar="S",
                       help="tum, folder: association window; euroc: interpolation window (default 0.02 s)")
    group.add_argument("--body-to-camera", type=float, nargs=16, default=None, metavar="T",
                       help="tum, folder: 16 numbers, row-major T_body_cam, when the poses are of a body, not the camera")


def run(args: argparse.Namespace) -> int:
    from nocal_ros.data.importers import open_recording, write_recording

    if args.out.exists() and not args.overwrite:
        raise BagError(f"{args.out}: already exists (use --overwrite to replace it)")
    body_to_camera = None
    if args.body_to_camera is not None:
        body_to_camera = np.asarray(args.body_to_camera, dtype=np.float64).reshape(4, 4)
        R = body_to_camera[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or not np.allclose(body_to_camera[3], [0, 0, 0, 1]):
            raise ConfigError("--body-to-camera is not a rigid transform (row-major 4x4)")
    options = {"rate": args.rate, "timestamps": args.timestamps, "poses": args.poses, "calibration": args.calibration,
               "camera": args.camera, "max_difference": args.max_difference, "body_to_camera": body_to_camera,
               "encoding": args.encoding}
    recording = open_recording(args.format, args.src, **options)
    for note in recording.notes:
        print(f"note: {note}", file=sys.stderr)

    def progress(done: int, total: int) -> None:
        if sys.stderr.isatty() and (done == total or done % max(1, total // 50) == 0):
            print(f"\rimporting {done}/{total}", end="", file=sys.stderr, flush=True)

    summary = write_recording(recording, args.out, args.storage, arm_fraction=args.arm_fraction, seed=args.seed,
                              max_frames=args.max_frames, overwrite=args.overwrite, progress=progress)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    duration = (summary.last_stamp_ns - summary.first_stamp_ns) / 1e9
    calibration = recording.calibration
    camera = (f"{calibration.distortion_model} fx={calibration.fx:.2f} fy={calibration.fy:.2f}"
              if calibration is not None else "no camera_info")
    print(f"wrote {summary.path} ({args.storage}): {summary.frames} frames {summary.size[0]}x{summary.size[1]} "
          f"{summary.encoding} over {duration:.2f} s, {camera}, ground truth on {summary.ground_truth_frames} frames "
          f"({summary.path_length_m:.3f} m travelled), /arm/pose on {summary.arm_frames}")
    return 0
