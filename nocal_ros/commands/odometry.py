"""``nocal odometry BAG --out DIR``: replay a bag offline through the odometry estimator.

Writes into ``DIR``:

* ``odometry``: a rosbag2 with ``/odom`` (nav_msgs/Odometry), ``/tf`` (``map -> odom`` and ``odom -> base``,
  as the node broadcasts them) and ``/camera_info`` (the learnt camera; same stamp and frame id as each image);
* ``trajectory.tum``: ``stamp x y z qx qy qz qw`` of the base frame in ``odom``, as published;
* ``trajectory_map.tum``: the same frames in ``map`` (``T_map_odom @ T_odom_base`` as of each frame: the
  maps as bundle adjustment had refined them then; see :mod:`nocal_ros.odometry.estimator`);
* ``trajectory_final.tum``: the same frames posed again through the final map and camera at the end of
  the replay (:mod:`nocal_ros.odometry.trajectory`; the VO only, when the estimator records them);
* ``keyframes.tum``: the VO's keyframes as its map held them at the end of the stream (the node's
  ``keyframe_path``; ORB-SLAM3's ``KeyFrameTrajectory.txt``), base frame in ``odom``, since the last restart;
* ``map_points.ply``: the landmarks of that map in ``odom`` (the node's ``map_points``), ASCII PLY;
* ``calibration.yaml``: the online camera at the end of the stream, in ROS ``camera_calibration`` format;
* ``calibration_final.yaml``: the camera of the final solve over the whole map, beside
  ``trajectory_final.tum``;
* when the bag has ground truth: ``report.json`` (RPE and APE with and without scale alignment,
  focal and ``dr`` errors) and ``trajectory.png``.

Nothing already in ``DIR`` is replaced unless ``--overwrite`` is given. Every output is written into
a hidden staging directory in ``DIR`` and moved into place only once all are complete, so a failure
half-way (a corrupt message, an interrupt, a full disk) leaves ``DIR`` exactly as it was; with
``--overwrite``, earlier outputs this run does not produce (a report without ground truth) are removed.

Stamps: ``/odom`` holds every pose in the order the frames came. When header stamps jump back, the
estimator restarts its odom frame (``time_reset``), so the poses form several segments, each in its
own odom frame; ``trajectory.tum`` and the report hold the longest segment (stamps strictly
increasing; the first of equally long ones), and the report says how many segments there were.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nocal_ros.commands import arguments as arg
from nocal_ros.errors import BagError, ConfigError, NocalError
from nocal_ros.geometry import (
    InvalidTransformError,
    invert_transform,
    matrix_to_quaternion,
    transform_from_translation_quaternion,
)

log = logging.getLogger(__name__)

OUTPUT_NAMES = ("odometry", "trajectory.tum", "trajectory_map.tum", "trajectory_final.tum", "keyframes.tum", "map_points.ply",
                "calibration.yaml", "calibration_final.yaml", "report.json", "trajectory.png")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="input bag (rosbag2 directory or file, or ROS 1 .bag)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--model", default="", help="checkpoint file or model store (default: the shipped model)")
    parser.add_argument("--device", default="auto", type=arg.device_name, help="auto, cpu, cuda or cuda:N")
    parser.add_argument("--image-topic", default="/camera/image_raw", help="sensor_msgs/Image or CompressedImage topic")
    parser.add_argument("--gt-topic", default="/ground_truth/pose", help="ground-truth camera poses, when the bag has them")
    parser.add_argument("--camera-info-topic", default="/ground_truth/camera_info", help="true calibration, when the bag has it")
    parser.add_argument("--odom-frame", default="odom")
    parser.add_argument("--map-frame", default="map", help="parent of the map -> odom correction in /tf (\"\": none)")
    parser.add_argument("--base-frame", default="", help="child frame of /odom (default: the images' frame id)")
    parser.add_argument(
        "--base-to-camera", type=arg.finite_float, nargs=7, metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
        help="static pose of the camera optical frame in the base frame (default: from the bag's /tf_static "
             "where it connects --base-frame to the images' frame, as the node's TF; else identity)",
    )
    parser.add_argument("--frame-period", type=arg.positive_float, default=None, help="camera frame period in s (default: from stamps)")
    parser.add_argument("--method", default="vo", choices=("vo", "pose_head"),
                        help="vo: keyframe visual odometry calibrating the camera online (default); pose_head: the "
                             "NOCaL pose head alone, pair by pair")
    parser.add_argument("--calibration", type=Path, default=None,
                        help="camera_calibration YAML to start the online camera from (default: the model's learnt camera)")
    parser.add_argument("--distortion-model", default="auto", choices=("auto", "plumb_bob", "equidistant"),
                        help="the online camera's lens model (auto: plumb_bob, or equidistant for a learnt camera plumb_bob cannot hold, as a fine-tuned fisheye's; equidistant starts from f = width)")
    parser.add_argument("--arm-topic", default="/arm/pose",
                        help="arm poses of the camera (PoseStamped) that make the scale metric, when the bag has them; '' to ignore")
    parser.add_argument("--camera-height", type=arg.positive_float, default=None, metavar="M",
                        help="the camera's height above the ground (m; KITTI: 1.65): where no arm poses fit, the "
                             "scale comes from the ground plane in the map instead of the pose head")
    parser.add_argument(
        "--ground-to-camera", type=arg.finite_float, nargs=7, metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
        help="static pose of the camera optical frame in a frame on the ground beneath it, z up (REP 120's "
             "base_footprint): the camera's height (Z) and the ground's normal for the ground-plane scale, "
             "instead of --camera-height",
    )
    parser.add_argument("--ground-frame", default="", metavar="FRAME",
                        help="a frame on the ground beneath the camera, z up (REP 120's base_footprint), in the bag's "
                             "/tf_static: --ground-to-camera read from there")
    parser.add_argument("--no-final", action="store_true",
                        help="skip trajectory_final.tum and calibration_final.yaml (the replay then keeps no "
                             "per-frame tracks: about 7 KB per frame, 0.7 GB per hour of a 30 Hz camera at 300 tracks)")
    parser.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3"), help="output bag storage")
    parser.add_argument("--max-frames", type=arg.positive_int, default=None, help="stop after this many images")
    parser.add_argument("--overwrite", action="store_true", help="replace outputs already in --out")
    parser.add_argument("--threads", type=arg.thread_count, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _mountings(args: argparse.Namespace) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(T_base_cam, T_ground_cam)`` from the command line, or from the bag's ``/tf_static`` for
    ``--base-frame`` (where it connects the frames) and ``--ground-frame``; None where not given."""
    from nocal_ros.data.bags import camera_mountings

    def typed(option: str, numbers: list[float]) -> np.ndarray:
        try:
            return transform_from_translation_quaternion(numbers[:3], numbers[3:])
        except InvalidTransformError as error:
            raise ConfigError(f"{option}: {error}") from None

    given = [name for name, value in (("--camera-height", args.camera_height is not None),
                                      ("--ground-to-camera", bool(args.ground_to_camera)),
                                      ("--ground-frame", bool(args.ground_frame))) if value]
    if len(given) > 1:
        raise ConfigError(f"give one of --camera-height, --ground-to-camera and --ground-frame, not {' and '.join(given)}")
    base_from_bag = args.base_frame if not args.base_to_camera else None
    ground_from_bag = args.ground_frame if not args.ground_to_camera else None
    mountings = None
    if base_from_bag or ground_from_bag:  # one read of the bag's first image and /tf_static for both
        try:
            mountings = camera_mountings(args.bag, [f for f in (base_from_bag, ground_from_bag) if f], args.image_topic)
        except BagError as error:
            if ground_from_bag:
                raise ConfigError(f"--ground-frame: {error}") from None
            raise

    T_base_cam = None
    if args.base_to_camera:
        T_base_cam = typed("--base-to-camera", args.base_to_camera)
    elif base_from_bag:
        T_base_cam = mountings.poses[base_from_bag]
        if T_base_cam is None and mountings.camera_frame != base_from_bag:
            log.warning("the bag's /tf_static does not connect %s to the images' frame %s: the camera is taken as "
                        "the base (give --base-to-camera)", base_from_bag, mountings.camera_frame)
    T_ground_cam = None
    if args.ground_to_camera:
        T_ground_cam = typed("--ground-to-camera", args.ground_to_camera)
    elif ground_from_bag:
        T_ground_cam = mountings.poses[ground_from_bag]
        if T_ground_cam is None:
            raise ConfigError(f"--ground-frame: {mountings.unconnected(ground_from_bag)}")
        log.info("the camera (%s) is %.3f m above %s in the bag's /tf_static", mountings.camera_frame,
                 T_ground_cam[2, 3], ground_from_bag)
    return T_base_cam, T_ground_cam


def run(args: argparse.Namespace) -> int:
    import torch

    from nocal_ros.odometry import OdometryEstimator

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    T_base_cam, T_ground_cam = _mountings(args)
    calibration = None
    if args.calibration is not None:
        from nocal_ros.lens import CameraCalibration

        calibration = CameraCalibration.load(args.calibration)
    estimator = OdometryEstimator(
        args.model or None, args.device, T_base_cam=T_base_cam, frame_period_s=args.frame_period,
        distortion_model=args.distortion_model, method=args.method, calibration=calibration,
        synchronous_mapping=True, record_trajectory=not args.no_final, camera_height=args.camera_height,
    )
    if T_ground_cam is not None:
        try:
            estimator.set_ground_to_camera(T_ground_cam)
        except NocalError as error:
            estimator.close()
            raise ConfigError(f"{'--ground-frame' if args.ground_frame else '--ground-to-camera'}: {error}") from None
    result = replay_bag(
        args.bag, args.out, estimator,
        image_topic=args.image_topic, gt_topic=args.gt_topic, camera_info_topic=args.camera_info_topic,
        odom_frame=args.odom_frame, map_frame=args.map_frame, base_frame=args.base_frame or None, storage=args.storage,
        arm_topic=args.arm_topic or None,
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
        poses = self.extras.get("poses", len(self.stamps_ns))
        lines = [
            f"model {self.model_id}: {self.frames_in} frames -> {poses} poses in {self.seconds:.1f} s "
            f"({1e3 * self.seconds / max(self.frames_in, 1):.1f} ms per frame)",
        ]
        if self.extras.get("time_segments", 1) > 1:
            lines.append(f"stamps went back: trajectory.tum and the report hold the longest of "
                         f"{self.extras['time_segments']} segments ({len(self.stamps_ns)} poses; /odom has all {poses})")
        skipped = {k: v for k, v in self.counters.items() if k not in ("frames", "pairs") and v}
        if skipped:
            lines.append("events: " + ", ".join(f"{k} {v}" for k, v in skipped.items()))
        if self.report:
            from nocal_ros.evaluation import format_report

            lines.append(format_report(self.report))
            final = self.report.get("final_trajectory")
            if final and "rpe" in final:
                lines.append(_errors_line("through the final map and camera (trajectory_final.tum)", final, "pair"))
            map_frame = self.report.get("map_frame")
            if map_frame and "rmse" in map_frame.get("ape_unaligned", {}):
                line = _errors_line("in the map frame as of each frame (trajectory_map.tum)", map_frame, "pair")
                lines.append(f"{line}, APE unaligned {map_frame['ape_unaligned']['rmse']:.4f} m "
                             f"(odom {self.report['ape_unaligned']['rmse']:.4f} m)")
            keyframes = self.report.get("keyframes")
            if keyframes and "rpe" in keyframes:
                lines.append(_errors_line(f"the {keyframes['poses']} keyframes as the map held them at the end "
                                          "(keyframes.tum)", keyframes, "keyframe pair"))
        lines += [f"  {name:<17} {path}" for name, path in self.outputs.items()]
        return "\n".join(lines)


def _errors_line(what: str, errors: dict[str, Any], pair: str) -> str:
    """One line of a trajectory's errors: RPE per ``pair``, APE Sim(3) and its scale, the focal error where known."""
    line = (f"{what}: RPE {errors['rpe']['translation_m']['rmse'] * 100:.2f} cm, "
            f"{errors['rpe']['rotation_deg']['rmse']:.3f} deg RMSE per {pair}")
    if "rmse" in errors.get("ape_sim3", {}):
        line += f", APE Sim(3) {errors['ape_sim3']['rmse']:.4f} m (scale {errors['ape_sim3']['scale']:.3f})"
    if errors.get("calibration"):
        line += f", focal error {errors['calibration']['focal_error_percent']:.2f} %"
    return line


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


STAGING_PREFIX = ".nocal-odometry-"


class StagedOutputs:
    """A hidden directory in ``out_dir`` that a replay writes every output into; :meth:`commit` moves them
    into place together (renames: no space needed), and leaving the block by an exception deletes it,
    so ``out_dir`` keeps exactly what it held before. ``stage[name]`` is where output ``name`` goes."""

    def __init__(self, out_dir: Path) -> None:
        from nocal_ros.files import pid_alive

        self.out_dir = out_dir
        for stale in out_dir.glob(f"{STAGING_PREFIX}*"):  # left by a replay that was killed
            pid = stale.name[len(STAGING_PREFIX):].split("-", 1)[0]
            if pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(stale, ignore_errors=True)
        self.path = out_dir / f"{STAGING_PREFIX}{os.getpid()}-{uuid.uuid4().hex[:8]}"

    def __enter__(self) -> "StagedOutputs":
        self.path.mkdir()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        shutil.rmtree(self.path, ignore_errors=True)

    def __getitem__(self, name: str) -> Path:
        return self.path / name

    def commit(self) -> dict[str, Path]:
        """Replace every earlier output in ``out_dir`` by this run's; returns the outputs' final paths."""
        from nocal_ros.files import fsync_dir

        produced = [name for name in OUTPUT_NAMES if self[name].exists()]
        replaced = self.path / ".replaced"
        replaced.mkdir()
        moved_away: list[str] = []
        moved_in: list[str] = []
        try:
            for name in OUTPUT_NAMES:  # also the ones this run does not produce: no stale report beside new results
                if (self.out_dir / name).exists() or (self.out_dir / name).is_symlink():
                    os.replace(self.out_dir / name, replaced / name)
                    moved_away.append(name)
            for name in produced:
                os.replace(self[name], self.out_dir / name)
                moved_in.append(name)
        except BaseException:  # undo, so the staging directory takes only this run's outputs with it
            for name in moved_in:
                os.replace(self.out_dir / name, self[name])
            for name in moved_away:
                os.replace(replaced / name, self.out_dir / name)
            raise
        fsync_dir(self.out_dir)
        return {name: self.out_dir / name for name in produced}


def write_tum(path: Path, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """TUM trajectory (``stamp_s x y z qx qy qz qw``), written atomically."""
    from nocal_ros.files import write_atomic

    lines = []
    for stamp, T in zip(stamps_ns.tolist(), poses):
        q = matrix_to_quaternion(T[:3, :3])
        seconds, nanos = divmod(int(stamp), 1_000_000_000)
        lines.append(f"{seconds}.{nanos:09d} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)) + "\n")
    write_atomic(path, "".join(lines))


def write_ply(path: Path, points: np.ndarray) -> None:
    """Points ``(N, 3)`` as an ASCII PLY of vertices (what MeshLab, CloudCompare and Open3D read), written atomically."""
    from nocal_ros.files import write_atomic

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    write_atomic(path, header + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points.tolist()))


def time_segments(stamps_ns: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` index ranges of ``stamps_ns`` whose stamps strictly increase: a stamp at or before
    the one before it (time went back, so the estimator restarted its odom frame) starts a new range."""
    breaks = (np.flatnonzero(np.diff(np.asarray(stamps_ns, dtype=np.int64)) <= 0) + 1).tolist()
    bounds = [0, *breaks, len(stamps_ns)]
    return [(start, end) for start, end in zip(bounds[:-1], bounds[1:]) if end > start]


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
    arm_topic: str | None = "/arm/pose",
    odom_frame: str = "odom",
    map_frame: str = "map",
    base_frame: str | None = None,
    storage: str = "mcap",
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: bool = True,
    plot: bool = True,
) -> ReplayResult:
    """Run ``estimator`` over a bag's images and write the outputs (see the module notes).

    Arm poses on ``arm_topic`` are handed to the estimator in stamp order, each before the first image
    at or after its stamp (as they would arrive live), to make the odometry's scale metric.
    """
    bag, out_dir = Path(bag), Path(out_dir)
    if not bag.exists():
        raise BagError(f"{bag}: no such bag (file or directory does not exist)")
    _check_outputs(out_dir, overwrite)
    if gt_topic and gt_topic in _topics(bag):
        from nocal_ros.evaluation import _evo

        _evo()  # evaluation needs evo: say so now, not after the whole bag was replayed
    try:
        with StagedOutputs(out_dir) as stage:
            replay = _replay_into(stage, bag, estimator, image_topic=image_topic, gt_topic=gt_topic,
                                  camera_info_topic=camera_info_topic, arm_topic=arm_topic, odom_frame=odom_frame,
                                  map_frame=map_frame, base_frame=base_frame, storage=storage, max_frames=max_frames, progress=progress,
                                  plot=plot)
            replay.outputs = stage.commit()
    except OSError as error:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        written = Path(str(error.filename)).name if error.filename else ""  # its staging path is gone already
        where = f" writing {written}" if written else " while writing the outputs"
        raise NocalError(f"{out_dir}: {error.strerror or 'no space left on device'}{where}; "
                         "partial outputs were removed and earlier results kept") from error
    return replay


def _topics(bag: Path) -> dict[str, tuple[str, int]]:
    from nocal_ros.data.bags import bag_topics

    return bag_topics(bag)


def _arm_poses(bag: Path, arm_topic: str | None) -> tuple[np.ndarray, np.ndarray]:
    """The bag's arm poses of the camera, ``(stamps, poses)`` sorted by stamp; empty without the topic."""
    from nocal_ros.data.bags import read_pose_messages

    if not arm_topic or arm_topic not in _topics(bag):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4))
    return read_pose_messages(bag, arm_topic)


def _replay_into(stage: StagedOutputs, bag: Path, estimator: Any, *, image_topic: str, gt_topic: str | None,
                 camera_info_topic: str | None, arm_topic: str | None, odom_frame: str, map_frame: str,
                 base_frame: str | None,
                 storage: str, max_frames: int | None, progress: bool, plot: bool) -> ReplayResult:
    """The replay itself, writing every output into ``stage``."""
    from nocal_ros.data.bags import BagWriter
    from nocal_ros.odometry import FrameError
    from nocal_ros.odometry.covariance import adjoint

    arm_stamps, arm_poses = _arm_poses(bag, arm_topic)
    next_arm = 0
    stamps: list[int] = []
    poses_base: list[np.ndarray] = []
    poses_cam: list[np.ndarray] = []
    corrections: list[np.ndarray] = []  # T_map_odom as of each pose
    tracking: list[str] = []
    scale_sources: list[str] = []
    # Each step's covariance (rho, theta) in the camera frame (NaN where no pair was run), for the report's NEES.
    step_covariances: list[np.ndarray] = []
    ad_cam_base = adjoint(invert_transform(estimator.T_base_cam))
    camera_history: list[dict[str, Any]] = []  # the online camera after the first frame and at each keyframe
    frames_in = 0
    start, start_cpu = time.perf_counter(), time.process_time()
    with BagWriter(stage["odometry"], storage=storage) as writer:
        writer.declare_topic("/odom", "nav_msgs/msg/Odometry")
        writer.declare_topic("/tf", "tf2_msgs/msg/TFMessage")
        writer.declare_topic("/camera_info", "sensor_msgs/msg/CameraInfo")
        for stamp_ns, frame_id, image in _frames(bag, image_topic, max_frames, progress):
            frames_in += 1
            while next_arm < len(arm_stamps) and arm_stamps[next_arm] <= stamp_ns:
                estimator.add_arm_pose(int(arm_stamps[next_arm]), arm_poses[next_arm])
                next_arm += 1
            try:
                result = estimator.process(stamp_ns, image)
            except FrameError as error:
                raise BagError(f"{bag}: {image_topic} frame {frames_in - 1}: {error}") from None
            camera_frame = frame_id or "camera_optical"
            calibration, _ = estimator.camera_info(image.shape[1], image.shape[0])
            writer.write_camera_info("/camera_info", stamp_ns, camera_frame, calibration)
            if result is None:
                continue
            if not camera_history or result.keyframe:
                camera_history.append({"frame": frames_in - 1, "stamp_ns": int(stamp_ns), "fx": float(calibration.fx),
                                       "fy": float(calibration.fy), "cx": float(calibration.cx),
                                       "cy": float(calibration.cy), "D": [float(d) for d in calibration.D],
                                       "state": estimator.calibration_status()["state"]})
            child = base_frame or camera_frame
            writer.write_odometry(
                "/odom", stamp_ns, odom_frame, child, result.T_odom_base, result.twist,
                result.pose_covariance.reshape(-1), result.twist_covariance.reshape(-1),
            )
            transforms = [(odom_frame, child, result.T_odom_base)]
            if map_frame:
                transforms.append((map_frame, odom_frame, result.T_map_odom))
            writer.write_tf("/tf", stamp_ns, transforms)
            stamps.append(stamp_ns)
            poses_base.append(result.T_odom_base)
            poses_cam.append(result.T_odom_cam)
            corrections.append(result.T_map_odom)
            if result.gap and len(stamps) >= 2:
                dt = (stamps[-1] - stamps[-2]) * 1e-9
                step_covariances.append(ad_cam_base @ result.twist_covariance @ ad_cam_base.T * dt * dt)
            else:
                step_covariances.append(np.full((6, 6), np.nan))
            tracking.append(result.tracking)
            scale_sources.append(result.scale_source)
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
    all_stamps = np.asarray(stamps, dtype=np.int64)
    segments = time_segments(all_stamps)
    first, last = max(segments, key=lambda segment: segment[1] - segment[0]) if segments else (0, 0)
    if len(segments) > 1:
        log.warning("%s: image stamps went back %d time(s), so the odometry restarted; trajectory.tum and the "
                    "report hold the longest of the %d segments (poses %d to %d)", bag, len(segments) - 1,
                    len(segments), first, last - 1)
    stamps_ns = all_stamps[first:last]
    write_tum(stage["trajectory.tum"], stamps_ns, np.asarray(poses_base[first:last]).reshape(-1, 4, 4))
    T_map_odom = np.asarray(corrections[first:last]).reshape(-1, 4, 4)
    write_tum(stage["trajectory_map.tum"], stamps_ns, T_map_odom @ np.asarray(poses_base[first:last]).reshape(-1, 4, 4))
    snapshot = estimator.map_snapshot()  # before the final solve moves the map
    keyframes = None
    if len(snapshot.stamps_ns):
        write_tum(stage["keyframes.tum"], snapshot.stamps_ns, snapshot.T_odom_base)
        write_ply(stage["map_points.ply"], snapshot.points)
        keyframes = (snapshot.stamps_ns, snapshot.T_odom_base @ estimator.T_base_cam)
    calibration = residual = None
    if frames_in:
        calibration, residual = estimator.camera_info()  # the online camera at the end of the bag
        calibration.save(stage["calibration.yaml"])
    final = _final_trajectory(estimator, stamps_ns)
    if final is not None:
        T_cam_base = invert_transform(estimator.T_base_cam)
        write_tum(stage["trajectory_final.tum"], stamps_ns, final[0] @ T_cam_base)
        final[2].save(stage["calibration_final.yaml"])

    replay = ReplayResult(
        out_dir=stage.out_dir, outputs={}, stamps_ns=stamps_ns,
        T_odom_cam=np.asarray(poses_cam[first:last]).reshape(-1, 4, 4),
        frames_in=frames_in, counters=dict(vars(estimator.counters)), model_id=estimator.model_id,
        calibration_residual_px=residual, seconds=seconds, cpu_seconds=cpu_seconds,
        extras={"poses": len(all_stamps), "time_segments": len(segments),
                "trajectory_segment": [int(first), int(last)], "tracking": tracking[first:last],
                "scale_source": scale_sources[first:last], "arm_poses": int(next_arm),
                "step_covariances": step_covariances[first:last],
                "camera_history": camera_history,
                "calibration_status": estimator.calibration_status(), "final_trajectory": final,
                "keyframes": keyframes, "T_map_odom": T_map_odom},
    )
    truth = _ground_truth(bag, gt_topic, camera_info_topic, stamps_ns)
    if truth is not None:
        from nocal_ros.files import write_atomic

        replay.report = evaluate_replay(replay, truth, calibration, estimator)
        write_atomic(stage["report.json"], json.dumps(replay.report, indent=2, sort_keys=True) + "\n")
        if plot and len(truth.stamps_ns) >= 2:
            plot_replay(replay, truth, stage["trajectory.png"])
    return replay


def _final_trajectory(estimator: Any, stamps_ns: np.ndarray) -> tuple[np.ndarray, list[str], Any, float, int] | None:
    """``(T_odom_cam (N, 4, 4), how (N,), calibration, seconds, observations found by the search)``
    through the final map and camera at
    ``stamps_ns``, or None when the estimator does not record them or they do not cover those stamps (a
    restart mid-bag)."""
    if not getattr(estimator, "record_trajectory", False) or getattr(estimator, "method", "vo") != "vo":
        return None
    start = time.perf_counter()
    try:
        stamps, poses, how = estimator.final_trajectory()
    except Exception as error:  # noqa: BLE001 - the replay's own outputs are complete: keep them
        log.warning("no trajectory_final.tum: the end-of-replay solve failed (%s: %s); the published "
                    "trajectory and calibration are written", type(error).__name__, error)
        return None
    if len(stamps) != len(stamps_ns) or not np.array_equal(stamps, stamps_ns):
        return None
    return poses, how, estimator.camera_info()[0], time.perf_counter() - start, estimator.final_observations_found


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


def _matched(stamps_ns: np.ndarray, T_odom_cam: np.ndarray, truth: GroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Estimated and true camera poses at the stamps both have, both starting at the identity."""
    common, est_index, gt_index = np.intersect1d(stamps_ns, truth.stamps_ns, return_indices=True)
    estimate = T_odom_cam[est_index]
    T_gt = truth.T_w_cam[gt_index]
    if len(common):
        # Both in the first matched camera frame, so the unaligned start is shared.
        estimate = invert_transform(estimate[0]) @ estimate
        T_gt = invert_transform(T_gt[0]) @ T_gt
    return common, estimate, T_gt


def _map_frame_poses(replay: ReplayResult, truth: GroundTruth) -> np.ndarray | None:
    """The replay's camera poses in the map frame as of each frame, matched to the truth as :func:`_matched`
    matches odom's (None when the replay kept no corrections)."""
    corrections = replay.extras.get("T_map_odom")
    if corrections is None or len(corrections) != len(replay.stamps_ns):
        return None
    return _matched(replay.stamps_ns, corrections @ replay.T_odom_cam, truth)[1]


def evaluate_replay(replay: ReplayResult, truth: GroundTruth, calibration: Any, estimator: Any) -> dict:
    """RPE, APE with SE(3) and Sim(3) alignment, and the camera errors (focal, principal point, dr)
    with the fit residual of the published distortion model.

    Per-pair series are left out of the report (a long bag would make it huge); the plot has them.
    """
    from nocal_ros import evaluation

    stamps, estimate, T_gt = _matched(replay.stamps_ns, replay.T_odom_cam, truth)
    report: dict[str, Any] = {
        "bag_frames": int(replay.frames_in),
        "odom_poses": int(replay.extras.get("poses", len(replay.stamps_ns))),
        "time_segments": int(replay.extras.get("time_segments", 1)),
        "trajectory_poses": int(len(replay.stamps_ns)),
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
        if len(stamps) >= 3:
            report["ape_unaligned"] = evaluation.summary(evaluation.absolute_pose_error(estimate, T_gt, align=False))
    map_estimate = _map_frame_poses(replay, truth)
    if map_estimate is not None and len(stamps) >= 3:
        # The same frames in the map frame (trajectory_map.tum): where the map had them then, not how they moved.
        report["map_frame"] = evaluation.summary(evaluation.trajectory_errors(stamps, map_estimate, T_gt))
        report["map_frame"]["ape_unaligned"] = evaluation.summary(
            evaluation.absolute_pose_error(map_estimate, T_gt, align=False))
    final = replay.extras.get("final_trajectory")
    if final is not None and len(stamps) >= 2:
        # The frames posed again through the final map and camera (what a replay can do at its end).
        final_stamps, final_estimate, final_truth = _matched(replay.stamps_ns, final[0], truth)
        report["final_trajectory"] = evaluation.summary(
            evaluation.trajectory_errors(final_stamps, final_estimate, final_truth))
        report["final_trajectory"]["posed"] = {how: int(sum(h == how for h in final[1])) for how in sorted(set(final[1]))}
        report["final_trajectory"]["seconds"] = float(final[3])  # the whole-map solves and the frames' PnP
        report["final_trajectory"]["observations_found"] = int(final[4])  # by searching the keyframes
        sources = list(getattr(estimator, "final_scale_sources", {}).values())
        if sources:  # what made each final map metric: arm, ground, or the live scale it was published with
            report["final_trajectory"]["scale_source"] = {source: sources.count(source) for source in sorted(set(sources))}
        if truth.calibration is not None:
            report["final_trajectory"]["calibration"] = evaluation.calibration_errors(final[2], truth.calibration)
    keyframes = replay.extras.get("keyframes")
    if keyframes is not None:
        # The keyframes as the live map held them at the end (keyframes.tum; RPE per keyframe pair).
        keyframe_stamps, keyframe_estimate, keyframe_truth = _matched(keyframes[0], keyframes[1], truth)
        if len(keyframe_stamps) >= 2:
            report["keyframes"] = evaluation.summary(
                evaluation.trajectory_errors(keyframe_stamps, keyframe_estimate, keyframe_truth))
    covariances = replay.extras.get("step_covariances")
    if covariances is not None and len(covariances) == len(replay.stamps_ns) and len(stamps) >= 2:
        report["rotation_consistency"] = _step_consistency(replay, stamps, estimate, T_gt, covariances, "rotation")
        report["translation_consistency"] = _step_consistency(replay, stamps, estimate, T_gt, covariances, "translation")
    report["method"] = getattr(estimator, "method", "vo")
    tracking = replay.extras.get("tracking") or []
    if tracking:
        report["tracking"] = {state: int(sum(t == state for t in tracking)) for state in ("initialising", "ok", "lost")}
        if len(stamps) >= 2 and len(tracking) == len(replay.stamps_ns):
            report["rpe_tracked"] = _tracked_rpe(replay, stamps, estimate, T_gt, tracking)
    scale_sources = replay.extras.get("scale_source") or []
    if scale_sources:
        # What made the translation metric, per published pose: the arm's similarity fit, the pose head's
        # lengths, or nothing (unit-less map).
        report["scale_source"] = {source: int(sum(s == source for s in scale_sources))
                                  for source in sorted(set(scale_sources))}
        report["arm_poses"] = int(replay.extras.get("arm_poses", 0))
    if getattr(estimator, "camera_height", None) is not None:
        report["camera_height_m"] = float(estimator.camera_height)  # the ground-plane scale's, as given
    if replay.extras.get("calibration_status"):
        report["calibration_status"] = replay.extras["calibration_status"]
    history = replay.extras.get("camera_history") or []
    if history and truth.calibration is not None and calibration is not None:
        report["calibration_history"] = _camera_history_errors(history, calibration, truth.calibration)
    if truth.calibration is not None and calibration is not None:
        report["calibration"] = evaluation.calibration_errors(calibration, truth.calibration)
        report["calibration"]["fit_residual_px"] = float(replay.calibration_residual_px or 0.0)
        report["calibration"]["distortion_model"] = calibration.distortion_model
    return report


#: The history's ``dr`` is taken over about this many pixel columns (and rows in proportion): the full
#: native grid for every keyframe cost 104 s on VAMR's 752x480 frames (measured), this well under 1 s.
HISTORY_GRID_COLUMNS = 96


def _camera_history_errors(history: list[dict[str, Any]], like: Any, truth: Any) -> list[dict[str, Any]]:
    """The online camera's focal error (%) and ``dr`` at each recorded frame (the first is the start camera).

    ``dr`` here is the mean radial shift over a grid of every k-th native pixel (about
    :data:`HISTORY_GRID_COLUMNS` columns), not every pixel as the report's final ``calibration.dr``.
    """
    from nocal_ros import evaluation
    from nocal_ros.lens import CameraCalibration

    step = max(1, round(truth.width / HISTORY_GRID_COLUMNS))
    rows = []
    for entry in history:
        K = np.array([[entry["fx"], 0.0, entry["cx"]], [0.0, entry["fy"], entry["cy"]], [0.0, 0.0, 1.0]])
        camera = CameraCalibration(like.width, like.height, K, np.asarray(entry["D"]), like.distortion_model,
                                   like.camera_name)
        try:
            dr = evaluation.radial_shift(camera, truth, step)["mean"]
        except ValueError:  # no pixel maps through both lenses
            dr = float("nan")
        rows.append({"frame": entry["frame"], "stamp_ns": entry["stamp_ns"], "state": entry["state"],
                     "fx": entry["fx"], "fy": entry["fy"],
                     "focal_error_percent": evaluation.focal_error(camera, truth)["mean_percent"], "dr": dr})
    return rows


def _step_consistency(replay: ReplayResult, stamps: np.ndarray, estimate: np.ndarray, T_gt: np.ndarray,
                      covariances: list[np.ndarray], part: str) -> dict[str, Any]:
    """The published steps' ``part`` ("rotation" or "translation") NEES
    (:func:`nocal_ros.evaluation.rotation_consistency`, :func:`~nocal_ros.evaluation.translation_consistency`)
    over the matched poses; a step between matched poses that were not consecutive in the replay is skipped."""
    from nocal_ros import evaluation

    block = slice(3, 6) if part == "rotation" else slice(0, 3)
    position = {int(stamp): k for k, stamp in enumerate(replay.stamps_ns.tolist())}
    steps = []
    for earlier, later in zip(stamps[:-1].tolist(), stamps[1:].tolist()):
        k = position[int(later)]
        consecutive = k > 0 and int(replay.stamps_ns[k - 1]) == int(earlier)
        steps.append(covariances[k][block, block] if consecutive else np.full((3, 3), np.nan))
    consistency = evaluation.rotation_consistency if part == "rotation" else evaluation.translation_consistency
    return consistency(estimate, T_gt, np.array(steps))


def _tracked_rpe(replay: ReplayResult, stamps: np.ndarray, estimate: np.ndarray, T_gt: np.ndarray,
                 tracking: list[str]) -> dict[str, Any]:
    """RPE over the consecutive pairs both of whose poses came from a tracked map ("ok"), with their count.

    The frames of an initialisation and the lost frames are bridged by rotation-only geometry or the
    pose head; this separates the map's own accuracy from theirs.
    """
    from nocal_ros import evaluation

    state = dict(zip(replay.stamps_ns.tolist(), tracking))
    ok = np.array([state.get(int(stamp)) == "ok" for stamp in stamps])
    both = ok[:-1] & ok[1:]
    result: dict[str, Any] = {"pairs": int(both.sum()), "of_pairs": int(len(both))}
    if both.any():
        rpe = evaluation.relative_pose_error(estimate, T_gt, delta=1)
        for key in ("translation_m", "rotation_deg"):
            errors = np.asarray(rpe[key + "_per_pair"])[both]
            result[key] = {"rmse": float(np.sqrt(np.mean(errors**2))), "mean": float(errors.mean()),
                           "median": float(np.median(errors)), "max": float(errors.max())}
    return result


def plot_replay(replay: ReplayResult, truth: GroundTruth, path: Path) -> None:
    """Top view of estimate vs truth and the per-pair error over time."""
    from nocal_ros import evaluation

    stamps, estimate, T_gt = _matched(replay.stamps_ns, replay.T_odom_cam, truth)
    map_estimate = _map_frame_poses(replay, truth)
    others = {} if map_estimate is None else {"map frame": map_estimate}
    evaluation.plot_trajectory(path, stamps, estimate, T_gt, title=f"nocal odometry: {replay.model_id}", others=others,
                               calibration_history=(replay.report or {}).get("calibration_history"))
