"""``nocal eval --model M --bag B``: a model's calibration and odometry errors against a bag's ground truth.

* Camera: the learnt camera's focal error (native px and %), principal point error (px) and mean radial
  shift ``dr`` against ``/ground_truth/camera_info``, and the RMS residual of its plumb_bob fit.
* Odometry: the pose head (pose-only path, at the model's training resolution, frames mapped onto its
  input as the training data are: ``nocal_ros.network_input``) on every consecutive pair of frames that have a
  ``/ground_truth/pose``; relative pose error per pair (metres, degrees), and APE of the chained poses
  with SE(3) and Sim(3) alignment.

Prints a table; ``--json`` writes the full report (with per-pair errors), ``--plot`` a trajectory PNG.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from nocal_ros.commands import arguments as arg
from nocal_ros.errors import BagError, CheckpointError

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default="", help="checkpoint file or model store (default: the shipped model)")
    parser.add_argument("--bag", type=Path, required=True, help="bag with images and ground truth")
    parser.add_argument("--json", type=Path, default=None, help="write the full report here")
    parser.add_argument("--plot", type=Path, default=None, help="write a trajectory plot (PNG) here")
    parser.add_argument("--image-topic", default="/camera/image_raw")
    parser.add_argument("--gt-topic", default="/ground_truth/pose", help="true camera poses T_w_cam")
    parser.add_argument("--camera-info-topic", default="/ground_truth/camera_info", help="true calibration")
    parser.add_argument("--camera-index", type=arg.non_negative_int, default=0, help="which of the checkpoint's cameras to evaluate")
    parser.add_argument("--max-frames", type=arg.positive_int, default=None, help="use only the first frames")
    parser.add_argument("--batch-size", type=arg.positive_int, default=32, help="pairs per pose-head call")
    parser.add_argument("--device", default="cpu", type=arg.device_name, help="cpu, cuda, cuda:N or auto")


def run(args: argparse.Namespace) -> int:
    report = evaluate_bag(
        args.model or None, args.bag, image_topic=args.image_topic, gt_topic=args.gt_topic,
        camera_info_topic=args.camera_info_topic, camera_index=args.camera_index, max_frames=args.max_frames,
        batch_size=args.batch_size, device=args.device, plot_path=args.plot,
    )
    from nocal_ros.evaluation import format_report

    print(format_report({k: v for k, v in report.items() if k != "plot"}))
    if args.json is not None:
        write_json(args.json, report)
        print(f"report: {args.json}")
    if args.plot is not None and report.get("plot"):
        print(f"plot: {report['plot']}")
    return 0


def write_json(path: Path, report: dict[str, Any]) -> None:
    """Write atomically: a reader (or a crash) never sees half a report."""
    from nocal_ros.files import write_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(report, indent=1))


def predict_consecutive_poses(
    predict_pose: Any, images: np.ndarray, pairs: np.ndarray, batch_size: int, device: Any
) -> np.ndarray:
    """``T_ci_cj`` ``(M, 4, 4)`` float64 for index pairs ``(M, 2)`` of uint8 images ``(N, h, w, 3)``."""
    import torch

    frames = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2)
    results = []
    with torch.inference_mode():
        for start in range(0, len(pairs), max(1, int(batch_size))):
            chunk = pairs[start : start + batch_size]
            image_i = frames[chunk[:, 0]].to(device=device, dtype=torch.float32) / 255.0
            image_j = frames[chunk[:, 1]].to(device=device, dtype=torch.float32) / 255.0
            results.append(predict_pose(image_i, image_j).double().cpu().numpy())
    return np.concatenate(results) if results else np.zeros((0, 4, 4))


def evaluate_bag(
    model_path: str | os.PathLike | None,
    bag: Path,
    *,
    image_topic: str = "/camera/image_raw",
    gt_topic: str = "/ground_truth/pose",
    camera_info_topic: str = "/ground_truth/camera_info",
    camera_index: int = 0,
    max_frames: int | None = None,
    batch_size: int = 32,
    device: str = "cpu",
    plot_path: Path | None = None,
) -> dict[str, Any]:
    """The report ``nocal eval`` prints: ``calibration`` and ``rpe`` / ``ape_se3`` / ``ape_sim3`` parts."""
    from nocal_ros import evaluation
    from nocal_ros.checkpoint import load_checkpoint
    from nocal_ros.data.bags import read_sequence
    from nocal_ros.odometry import PoseModel, resolve_device

    torch_device = resolve_device(device)
    checkpoint = load_checkpoint(model_path, device=str(torch_device))
    model_name = str(checkpoint.path or "shipped default")
    pose_model = PoseModel.from_checkpoint(checkpoint, torch_device)  # the odometry path's training size and id
    width, height = pose_model.input_size
    sequence = read_sequence(
        bag, image_topic=image_topic, pose_source="none", gt_topic=gt_topic,
        camera_info_topic=camera_info_topic, network_size=(width, height), max_frames=max_frames,
    )
    report: dict[str, Any] = {
        "model": pose_model.model_id,
        "bag": str(bag),
        "frames": len(sequence),
        "input_size": f"{width}x{height}",
    }

    truth = sequence.calibration
    native = sequence.extras.get("native_size")
    if truth is not None and native is not None and (truth.width, truth.height) != tuple(native):
        truth = truth.scaled(*native)  # back to the recorded resolution: the metrics are defined there
    if truth is not None:
        if not checkpoint.cameras:
            log.warning("%s has no camera; skipping calibration errors", model_name)
        elif not 0 <= camera_index < len(checkpoint.cameras):
            raise CheckpointError(f"{model_name}: no camera {camera_index} (it has {len(checkpoint.cameras)})")
        else:
            camera = checkpoint.cameras[camera_index].cpu()
            if not all(np.isfinite(float(t.detach())) for t in camera.intrinsics()):
                raise CheckpointError(f"{model_name}: camera {camera_index} has non-finite intrinsics")
            report["camera_index"] = camera_index
            report["calibration"] = evaluation.calibration_errors(camera, truth)
            _, residual = camera.to_calibration("plumb_bob")
            report["calibration"]["fit_residual_px"] = residual
            report["calibration"]["distortion_model"] = "plumb_bob"

    ground_truth = sequence.ground_truth
    valid = np.zeros(len(sequence), bool) if ground_truth is None else np.isfinite(ground_truth).all(axis=(1, 2))
    if valid.sum() >= 2:
        frames = np.flatnonzero(valid)
        pairs = np.stack((frames[:-1], frames[1:]), -1)
        predicted = predict_consecutive_poses(pose_model.predict_pose, sequence.images, pairs, batch_size, torch_device)
        if not np.isfinite(predicted).all():
            raise CheckpointError(f"{model_name}: the pose head produced non-finite poses on {bag}")
        truth_poses = ground_truth[frames]
        estimate = evaluation.integrate_relative_poses(predicted, start=truth_poses[0])
        report["pairs"] = int(len(pairs))
        report["max_pair_gap"] = int(np.diff(frames).max())
        report.update(evaluation.trajectory_errors(sequence.stamps_ns[frames], estimate, truth_poses))
        if plot_path is not None and len(frames) >= 3:
            report["plot"] = str(evaluation.plot_trajectory(
                plot_path, sequence.stamps_ns[frames], estimate, truth_poses, title=f"nocal eval: {pose_model.model_id}"))
    if "calibration" not in report and "rpe" not in report:
        raise BagError(
            f"{bag}: nothing to evaluate against: no ground-truth poses on {gt_topic} (need two or more) "
            f"and no calibration on {camera_info_topic}"
        )
    return report


