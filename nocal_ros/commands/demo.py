"""``nocal demo``: render a short bag from a camera the shipped model never saw, replay it through
offline odometry with the shipped model, print the errors and where everything was written.

No ROS needed; about a minute on a 2-core laptop. The demo camera is hand-picked (its own focal
length, off-centre principal point and barrel distortion, not one of the random training cameras)
and the room comes from the renderer's ``test`` split, which training does not draw from.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from nocal_ros.commands import arguments as arg
from nocal_ros.errors import NocalError

log = logging.getLogger(__name__)

MARKER = ".nocal_demo"  # a directory holding this file was written by the demo and may be replaced
DEMO_SEED = 20240917


def demo_camera(width: int, height: int):
    """The demo's camera: 62 degrees horizontal field of view, principal point 3 % off centre, barrel."""
    from nocal_ros.lens import CameraCalibration

    fx = 0.83 * width
    K = np.array([[fx, 0.0, 0.53 * (width - 1)], [0.0, 0.99 * fx, 0.48 * (height - 1)], [0.0, 0.0, 1.0]])
    return CameraCalibration(width, height, K, np.array([-0.12, 0.02, 0.0005, -0.0003, 0.0]), "plumb_bob", "nocal_demo")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("nocal_demo"), help="output directory (default: ./nocal_demo)")
    parser.add_argument("--model", default="", help="checkpoint or model store (default: the shipped model)")
    parser.add_argument("--device", default="auto", type=arg.device_name, help="auto, cpu, cuda or cuda:N")
    parser.add_argument("--frames", type=arg.positive_int, default=80, help="frames to render (10 per second)")
    parser.add_argument("--size", default=(640, 480), type=arg.image_size, help="demo camera resolution WxH")
    parser.add_argument("--method", default="vo", choices=("vo", "pose_head"), help="see nocal odometry --help")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _prepare(out: Path) -> None:
    if out.exists():
        if not out.is_dir():
            raise NocalError(f"{out}: exists and is not a directory")
        if any(out.iterdir()) and not (out / MARKER).exists():
            raise NocalError(f"{out}: exists and was not written by nocal demo; choose another --out")
        shutil.rmtree(out)  # a previous demo's outputs only (it holds the marker)
    out.mkdir(parents=True)
    (out / MARKER).write_text("written by nocal demo; the directory is replaced by the next run\n")


def run(args: argparse.Namespace) -> int:
    from nocal_ros.commands.odometry import replay_bag
    from nocal_ros.data.bags import write_sequence
    from nocal_ros.data.synthetic import render_sequence
    from nocal_ros.odometry import OdometryEstimator

    width, height = args.size
    if args.frames < 3:
        raise NocalError("--frames must be at least 3")
    start = time.perf_counter()
    # Load the model first: a missing or broken model fails before any rendering.
    estimator = OdometryEstimator(args.model or None, args.device, method=args.method, synchronous_mapping=True,
                                  record_trajectory=True)
    out = Path(args.out)
    _prepare(out)

    camera = demo_camera(width, height)
    print(f"rendering {args.frames} frames of an unseen room through an unseen {width}x{height} camera "
          f"(fx {camera.fx:.1f} px, k1 {camera.D[0]:+.2f})...")
    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=args.frames, unit="frame", desc="render", leave=False)
        progress = lambda done, total: bar.update(done - bar.n)  # noqa: E731
    sequence = render_sequence(camera, args.frames, seed=DEMO_SEED, split="test", fps=10.0, progress=progress)
    if progress is not None:
        bar.close()
    bag = write_sequence(sequence, out / "input_bag")

    print(f"running odometry with {estimator.model_id}...")
    replay = replay_bag(bag, out / "result", estimator, progress=not args.no_progress)
    print(replay.summary())
    print(_calibration_over_the_replay(replay.report, camera))
    print(_standing_still(replay, sequence))
    print(f"demo finished in {time.perf_counter() - start:.0f} s; input bag: {bag}; outputs: {out / 'result'}")
    return 0


def _calibration_over_the_replay(report: dict | None, truth) -> str:
    """The online camera from the start camera to the end of the replay, against the demo camera's truth."""
    history = (report or {}).get("calibration_history") or []
    final = (report or {}).get("calibration")
    if not history or not final:
        return "no calibration history (the odometry published no camera)"
    lines = [f"online calibration (true fx {truth.fx:.1f}, fy {truth.fy:.1f} px):",
             "   frame    time     fx (px)   fy (px)   focal error       dr   state"]
    start_ns = history[0]["stamp_ns"]
    picks = sorted({round(i) for i in np.linspace(0, len(history) - 1, min(len(history), 8))})
    for i in picks:
        row = history[i]
        lines.append(f"  {row['frame']:>6} {(row['stamp_ns'] - start_ns) * 1e-9:>6.1f} s {row['fx']:>10.1f} {row['fy']:>9.1f} "
                     f"{row['focal_error_percent']:>11.2f} % {row['dr']:>8.4f}   {row['state']}")
    first = history[0]
    lines.append(f"  start camera -> end of replay: focal error {first['focal_error_percent']:.2f} % -> "
                 f"{final['focal_error_percent']:.2f} %, dr {first['dr']:.4f} -> {final['dr']:.4f}")
    return "\n".join(lines)


def _standing_still(replay, sequence) -> str:
    """The RPE of an estimate that never moves, for scale: a model must do better than this."""
    from nocal_ros import evaluation

    truth = sequence.ground_truth
    rpe = evaluation.relative_pose_error(np.broadcast_to(np.eye(4), truth.shape), truth, delta=1)
    return (f"for comparison, reporting no motion at all: RPE {rpe['translation_m']['rmse'] * 100:.2f} cm, "
            f"{rpe['rotation_deg']['rmse']:.3f} deg RMSE per pair")
