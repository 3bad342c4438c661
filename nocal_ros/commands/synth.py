"""``nocal synth --out BAG``: render a synthetic rosbag2 with ground truth.

Layout (``nocal_ros.data.bags.write_sequence``): ``/camera/image_raw`` (Image rgb8, every frame),
``/arm/pose`` (PoseStamped, the labelled fraction), ``/ground_truth/pose`` (every frame) and
``/ground_truth/camera_info`` (the true K and distortion).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from nocal_ros.commands import arguments as arg
from nocal_ros.errors import BagError, ConfigError
from nocal_ros.lens import CameraCalibration, scale_intrinsics

# The built-in camera when no --camera is given; config/cameras/default_640x480.yaml holds the same.
DEFAULT_CAMERA = CameraCalibration(
    640, 480, np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]]),
    np.array([-0.25, 0.08, 0.0, 0.0, 0.0]), "plumb_bob", "default_640x480",
)


def camera_at_size(calibration: CameraCalibration, width: int, height: int) -> CameraCalibration:
    """The same lens on a ``width x height`` sensor with square pixels kept.

    The same aspect ratio is a plain rescale (same field of view). Another aspect ratio scales by the
    width (so the horizontal field of view and the pixel aspect stay) and keeps the principal point's
    offset from the image centre: a 1280x720 render of a 640x480 camera is the middle 720 rows of its
    1280x960 render. (Scaling each axis by its own ratio would make fy differ from fx, a camera
    nobody builds.)
    """
    if width * calibration.height == height * calibration.width:
        return calibration.scaled(width, height)
    scale = width / calibration.width
    K = scale_intrinsics(calibration.K, scale, scale)
    K[1, 2] += (height - calibration.height * scale) / 2.0
    return CameraCalibration(width, height, K, calibration.D.copy(), calibration.distortion_model, calibration.camera_name)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output bag (a rosbag2 directory)")
    parser.add_argument("--camera", type=Path, default=None,
                        help="true camera, ROS camera_calibration YAML (default: built-in 640x480, f=520, "
                             "k1=-0.25 k2=0.08; see config/cameras/)")
    parser.add_argument("--random-camera", action="store_true",
                        help="draw a random plumb_bob camera from --seed instead (see synthetic.random_calibration)")
    parser.add_argument("--size", type=arg.image_size, default=None, metavar="WxH",
                        help="render at this size: the camera scaled to it (another aspect ratio keeps square pixels and "
                             "the horizontal field of view, e.g. 1280x720 or 1241x376)")
    parser.add_argument("--frames", type=arg.positive_int, default=200, help="number of frames (default 200)")
    parser.add_argument("--fps", type=arg.positive_float, default=10.0, help="frame rate in Hz; sets the stamps (default 10)")
    parser.add_argument("--seed", type=arg.non_negative_int, default=0, help="scene, trajectory and labelling seed (default 0)")
    parser.add_argument("--split", choices=("train", "test"), default="train",
                        help="texture set: train and test scenes share no textures (default train)")
    parser.add_argument("--supersample", type=arg.positive_int, default=1, metavar="K",
                        help="average KxK rays per pixel (anti-aliasing; cost grows as K^2; default 1)")
    parser.add_argument("--labelled-fraction", type=arg.fraction, default=0.1,
                        help="share of frames with an /arm/pose (default 0.1)")
    parser.add_argument("--speed", type=arg.non_negative_float, default=0.3, help="RMS camera speed in m/s (default 0.3)")
    parser.add_argument("--angular-speed", type=arg.non_negative_float, default=20.0, help="RMS angular speed in deg/s (default 20)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag at --out")
    parser.add_argument("--threads", type=arg.thread_count, default=None,
                        help="torch CPU threads for rendering (default: torch's choice; 1 suits busy shared machines)")


def run(args: argparse.Namespace) -> int:
    from nocal_ros.data.bags import write_sequence
    from nocal_ros.data.synthetic import random_calibration, render_sequence

    if args.out.exists() and not args.overwrite:
        raise BagError(f"{args.out}: already exists (use --overwrite to replace it)")
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)

    if args.random_camera:
        if args.camera is not None:
            raise ConfigError("give either --camera or --random-camera, not both")
        width, height = args.size or (DEFAULT_CAMERA.width, DEFAULT_CAMERA.height)
        calibration = random_calibration(np.random.default_rng([args.seed, 7]), width, height)
    else:
        calibration = CameraCalibration.load(args.camera) if args.camera is not None else DEFAULT_CAMERA
        if args.size is not None:
            calibration = camera_at_size(calibration, *args.size)

    frame_times: list[float] = []

    def progress(done: int, total: int) -> None:
        frame_times.append(time.perf_counter())
        if sys.stderr.isatty() and (done == total or done % max(1, total // 20) == 0):
            print(f"\rrendering {done}/{total}", end="", file=sys.stderr, flush=True)

    start = time.perf_counter()
    sequence = render_sequence(
        calibration, args.frames, args.seed, split=args.split, fps=args.fps, speed=args.speed,
        angular_speed=args.angular_speed, supersample=args.supersample, labelled_fraction=args.labelled_fraction,
        progress=progress,
    )
    write_sequence(sequence, args.out, storage=args.storage, overwrite=args.overwrite)
    written = time.perf_counter()
    if sys.stderr.isatty():
        print(file=sys.stderr)
    # steady-state rate: frames after the first, so scene, texture and ray-table setup are excluded
    steady = (len(frame_times) - 1) / (frame_times[-1] - frame_times[0]) if len(frame_times) > 1 else float("nan")
    median_ms = 1000 * float(np.median(np.diff(frame_times))) if len(frame_times) > 1 else float("nan")
    print(
        f"wrote {args.out} ({args.storage}): {args.frames} frames {calibration.width}x{calibration.height} "
        f"{calibration.distortion_model} fx={calibration.fx:.1f}, {int(sequence.labelled.sum())} labelled, "
        f"split {args.split}, seed {args.seed}"
    )
    print(
        f"rendered {steady:.1f} frames/s, median {median_ms:.1f} ms/frame (supersample {args.supersample}; "
        f"setup {frame_times[0] - start:.2f} s), "
        f"{args.frames / max(written - start, 1e-9):.1f} frames/s overall including setup and the bag"
    )
    return 0

