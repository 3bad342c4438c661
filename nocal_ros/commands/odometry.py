"""``nocal odometry BAG --out DIR``: replay a bag offline through the odometry estimator.

Writes into ``DIR``:

* ``odometry``: a rosbag2 with ``/odom`` (nav_msgs/Odometry), ``/tf`` (``odom -> base``) and
  ``/camera_info`` (the learnt camera; same stamp and frame id as each image);
* ``trajectory.tum``: ``stamp x y z qx qy qz qw`` of the base frame in ``odom``;
* ``calibration.yaml``: the learnt camera in ROS ``camera_calibration`` format;
* when the bag has ground truth: ``report.json`` (RPE and APE with and without scale alignment,
  focal and ``dr`` errors) and ``trajectory.png``.

Nothing already in ``DIR`` is replaced unless ``--overwrite`` is given, and a failure half-way
(a corrupt message, an interrupt) leaves no partial odometry bag behind.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nocal_ros.errors import BagError, NocalError
from nocal_ros.geometry import invert_transform, make_transform, matrix_to_quaternion, quaternion_to_matrix

log = logging.getLogger(__name__)

OUTPUT_NAMES = ("odometry", "trajectory.tum", "calibration.yaml", "report.json", "trajectory.png")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="input bag (rosbag2 directory or file, or ROS 1 .bag)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--model", default="", help="checkpoint file or model store (default: the shipped model)")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--image-topic", default="/camera/image_raw", help="sensor_msgs/Image or CompressedImage topic")
    parser.add_argument("--gt-topic", default="/ground_truth/pose", help="ground-truth camera poses, when the bag has them")
    parser.add_argument("--camera-info-topic", default="/ground_truth/camera_info", help="true calibration, when the bag has it")
    parser.add_argument("--odom-frame", default="odom")
    parser.add_argument("--base-frame", default="", help="child frame of /odom (default: the images' frame id)")
    parser.add_argument(
        "--base-to-camera", type=float, nargs=7, metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
        help="static pose of the camera optical frame in the base frame (default: identity)",
    )
    parser.add_argument("--frame-period", type=float, default=None, help="camera frame period in s (default: from stamps)")
    parser.add_argument("--distortion-model", default="auto", choices=("auto", "plumb_bob", "rational_polynomial"))
    parser.add_argument("--no-two-view", action="store_true",
                        help="pose head only: no rotation and direction from tracked corners through the learnt camera")
    parser.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3"), help="output bag storage")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many images")
    parser.add_argument("--overwrite", action="store_true", help="replace outputs already in --out")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import torch

    from nocal_ros.odometry import OdometryEstimator

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    T_base_cam = None
    if args.base_to_camera:
        x, y, z, qx, qy, qz, qw = args.base_to_camera
        T_base_cam = make_transform(quaternion_to_matrix(np.array([qx, qy, qz, qw])), np.array([x, y, z]))
    estimator = OdometryEstimator(
        args.model or None, args.device, T_base_cam=T_base_cam, frame_period_s=args.frame_period,
        distortion_model=args.distortion_model, two_view=not args.no_two_view,
    )
    result = replay_bag(
        args.bag, args.out, estimator,
        image_topic=args.image_topic, gt_topic=args.gt_topic, camera_info_topic=args.camera_info_topic,
        odom_frame=args.odom_frame, base_frame=args.base_frame or None, storage=args.storage,
        max_frames=args.max_frames, overwrite=args.overwrite, progress=not args.no_progress,
    )
    print(result.summary())
    return 0


@dataclass
class ReplayResult:
    """What a replay produced: the output paths, the estimate, and the report when there was truth."""

    out_dir: Path
    outputs: dict[str, Path]
    stamps_ns: np.ndarray
    T_odom_cam: np.ndarray
    frames_in: int
    counters: dict[str, int]
    model_id: str
    calibration_residual_px: float | None
    seconds: float
    cpu_seconds: float | None = None  # this process's CPU time over the replay: repeatable on a shared machine
    report: dict | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        lines = [
            f"model {self.model_id}: {self.frames_in} frames -> {len(self.stamps_ns)} poses in {self.seconds:.1f} s "
            f"({1e3 * self.seconds / max(self.frames_in, 1):.1f} ms per frame)",
        ]
        skipped = {k: v for k, v in self.counters.items() if k not in ("frames", "pairs") and v}
        if skipped:
            lines.append("events: " + ", ".join(f"{k} {v}" for k, v in skipped.items()))
        if self.report:
            from nocal_ros.evaluation import format_report

            lines.append(format_report(self.report))
        lines += [f"  {name:<17} {path}" for name, path in self.outputs.items()]
        return "\n".join(lines)


def _image_count(bag: Path, topic: str) -> int | None:
    """The bag index's message count on ``topic``: only a progress bar total, so never an error."""
    from nocal_ros.data.bags import bag_topics

    try:
        info = bag_topics(bag).get(topic)
    except NocalError:
        return None
    return None if info is None else info[1]


def _check_outputs(out_dir: Path, overwrite: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise NocalError(f"{out_dir}: exists and is not a directory")
    existing = [name for name in OUTPUT_NAMES if (out_dir / name).exists()]
    if existing and not overwrite:
        raise NocalError(f"{out_dir}: already holds {', '.join(existing)}; pass --overwrite to replace them")
    out_dir.mkdir(parents=True, exist_ok=True)


def write_tum(path: Path, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """TUM trajectory (``stamp_s x y z qx qy qz qw``), written atomically."""
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "w", encoding="utf-8") as handle:
        for stamp, T in zip(stamps_ns.tolist(), poses):
            q = matrix_to_quaternion(T[:3, :3])
            seconds, nanos = divmod(int(stamp), 1_000_000_000)
            handle.write(f"{seconds}.{nanos:09d} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)) + "\n")
    os.replace(temporary, path)


def _frames(bag: Path, image_topic: str, max_frames: int | None, progress: bool) -> Iterator[tuple[int, str, np.ndarray]]:
    from nocal_ros.data.bags import iter_images

    frames = iter_images(bag, image_topic)
    total = _image_count(bag, image_topic)
    if max_frames is not None:
        total = min(total, max_frames) if total is not None else max_frames
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=total, unit="frame", desc="odometry", leave=False)
    for index, item in enumerate(frames):
        if max_frames is not None and index >= max_frames:
            break
        yield item


def replay_bag(
    bag: str | Path,
    out_dir: str | Path,
    estimator: Any,
    *,
    image_topic: str = "/camera/image_raw",
    gt_topic: str | None = "/ground_truth/pose",
    camera_info_topic: str | None = "/ground_truth/camera_info",
    odom_frame: str = "odom",
    base_frame: str | None = None,
    storage: str = "mcap",
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: bool = True,
    plot: bool = True,
) -> ReplayResult:
    """Run ``estimator`` over a bag's images and write the outputs (see the module notes)."""
    from nocal_ros.data.bags import BagWriter
    from nocal_ros.odometry import FrameError, FrameSizeError

    bag, out_dir = Path(bag), Path(out_dir)
    if not bag.exists():
        raise BagError(f"{bag}: no such bag (file or directory does not exist)")
    _check_outputs(out_dir, overwrite)
    outputs = {"odometry": out_dir / "odometry", "trajectory.tum": out_dir / "trajectory.tum"}
    stamps: list[int] = []
    poses_base: list[np.ndarray] = []
    poses_cam: list[np.ndarray] = []
    calibration = residual = None
    camera_known = estimator.model.camera is not None
    frames_in = 0
    start, start_cpu = time.perf_counter(), time.process_time()
    with BagWriter(outputs["odometry"], storage=storage, overwrite=overwrite) as writer:
        writer.declare_topic("/odom", "nav_msgs/msg/Odometry")
        writer.declare_topic("/tf", "tf2_msgs/msg/TFMessage")
        writer.declare_topic("/camera_info", "sensor_msgs/msg/CameraInfo")
        for stamp_ns, frame_id, image in _frames(bag, image_topic, max_frames, progress):
            frames_in += 1
            try:
                result = estimator.process(stamp_ns, image)
            except FrameError as error:
                raise BagError(f"{bag}: {image_topic} frame {frames_in - 1}: {error}") from None
            camera_frame = frame_id or "camera_optical"
            if calibration is None and camera_known:
                try:
                    calibration, residual = estimator.camera_info(image.shape[1], image.shape[0])
                except FrameSizeError as error:  # the model's camera has another aspect ratio
                    log.warning("no camera_info: %s", error)
                    camera_known = False
            if calibration is not None:
                writer.write_camera_info("/camera_info", stamp_ns, camera_frame, calibration)
            if result is None:
                continue
            child = base_frame or camera_frame
            writer.write_odometry(
                "/odom", stamp_ns, odom_frame, child, result.T_odom_base, result.twist,
                result.pose_covariance.reshape(-1), result.twist_covariance.reshape(-1),
            )
            writer.write_tf("/tf", stamp_ns, [(odom_frame, child, result.T_odom_base)])
            stamps.append(stamp_ns)
            poses_base.append(result.T_odom_base)
            poses_cam.append(result.T_odom_cam)
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
    stamps_ns = np.asarray(stamps, dtype=np.int64)
    write_tum(outputs["trajectory.tum"], stamps_ns, np.asarray(poses_base).reshape(-1, 4, 4))
    if calibration is not None:
        outputs["calibration.yaml"] = out_dir / "calibration.yaml"
        calibration.save(outputs["calibration.yaml"])
    elif estimator.model.camera is None:
        log.warning("model %s has no learnt camera: no camera_info or calibration.yaml", estimator.model_id)

    replay = ReplayResult(
        out_dir=out_dir, outputs=outputs, stamps_ns=stamps_ns, T_odom_cam=np.asarray(poses_cam).reshape(-1, 4, 4),
        frames_in=frames_in, counters=dict(vars(estimator.counters)), model_id=estimator.model_id,
        calibration_residual_px=residual, seconds=seconds, cpu_seconds=cpu_seconds,
    )
    truth = _ground_truth(bag, gt_topic, camera_info_topic, stamps_ns)
    if truth is not None:
        replay.report = evaluate_replay(replay, truth, calibration, estimator)
        outputs["report.json"] = out_dir / "report.json"
        temporary = out_dir / ".report.json.tmp"
        temporary.write_text(json.dumps(replay.report, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        os.replace(temporary, outputs["report.json"])
        if plot and len(truth.stamps_ns) >= 2:
            outputs["trajectory.png"] = out_dir / "trajectory.png"
            plot_replay(replay, truth, outputs["trajectory.png"])
    return replay


@dataclass
class GroundTruth:
    stamps_ns: np.ndarray  # (N,) image stamps with a true pose
    T_w_cam: np.ndarray  # (N, 4, 4)
    calibration: Any  # CameraCalibration at native resolution, or None


def _ground_truth(bag: Path, gt_topic: str | None, camera_info_topic: str | None, stamps_ns: np.ndarray) -> GroundTruth | None:
    """True camera poses at the estimate's stamps and the true calibration, when the bag has them."""
    from nocal_ros.data.bags import bag_topics, read_camera_info, read_poses

    if not gt_topic or len(stamps_ns) < 2:
        return None
    topics = bag_topics(bag)
    if gt_topic not in topics:
        return None
    T_w_cam = read_poses(bag, gt_topic, stamps_ns)
    valid = np.isfinite(T_w_cam).all(axis=(1, 2))
    if valid.sum() < 2:
        return None
    calibration = None
    if camera_info_topic and camera_info_topic in topics:
        try:
            calibration = read_camera_info(bag, camera_info_topic)
        except BagError as error:  # e.g. an all-zero K: the pose errors are still worth reporting
            log.warning("no camera errors in the report: %s", error)
    return GroundTruth(stamps_ns[valid], T_w_cam[valid], calibration)


def _matched(replay: ReplayResult, truth: GroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Estimated and true camera poses at the stamps both have, both starting at the identity."""
    common, est_index, gt_index = np.intersect1d(replay.stamps_ns, truth.stamps_ns, return_indices=True)
    estimate = replay.T_odom_cam[est_index]
    T_gt = truth.T_w_cam[gt_index]
    if len(common):
        # Both in the first matched camera frame, so the unaligned start is shared.
        estimate = invert_transform(estimate[0]) @ estimate
        T_gt = invert_transform(T_gt[0]) @ T_gt
    return common, estimate, T_gt


def evaluate_replay(replay: ReplayResult, truth: GroundTruth, calibration: Any, estimator: Any) -> dict:
    """RPE, APE with SE(3) and Sim(3) alignment, and the camera errors (focal, principal point, dr)
    with the fit residual of the published distortion model.

    Per-pair series are left out of the report (a long bag would make it huge); the plot has them.
    """
    from nocal_ros import evaluation

    stamps, estimate, T_gt = _matched(replay, truth)
    report: dict[str, Any] = {
        "bag_frames": int(replay.frames_in),
        "poses": int(len(replay.stamps_ns)),
        "evaluated_poses": int(len(stamps)),
        "model": replay.model_id,
        "events": {k: int(v) for k, v in replay.counters.items()},
        # Wall time of the replay (decoding, estimation, writing the bag), for tables beside other methods.
        "seconds": float(replay.seconds),
        "cpu_seconds": None if replay.cpu_seconds is None else float(replay.cpu_seconds),
        "ms_per_frame": float(1e3 * replay.seconds / max(replay.frames_in, 1)),
    }
    if len(stamps) >= 2:
        report.update(evaluation.summary(evaluation.trajectory_errors(stamps, estimate, T_gt)))
    camera = estimator.model.camera
    if truth.calibration is not None and camera is not None:
        report["calibration"] = evaluation.calibration_errors(camera, truth.calibration)
        if replay.calibration_residual_px is not None:
            report["calibration"]["fit_residual_px"] = float(replay.calibration_residual_px)
            report["calibration"]["distortion_model"] = calibration.distortion_model
    return report


def plot_replay(replay: ReplayResult, truth: GroundTruth, path: Path) -> None:
    """Top view of estimate vs truth and the per-pair error over time."""
    from nocal_ros import evaluation

    stamps, estimate, T_gt = _matched(replay, truth)
    evaluation.plot_trajectory(path, stamps, estimate, T_gt, title=f"nocal odometry: {replay.model_id}")
