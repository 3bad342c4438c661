"""Importers: public datasets and plain recordings to a rosbag2 in the layout ``nocal synth`` writes.

``open_recording(FORMAT, SRC, **options)`` reads a dataset's text files (stamps, ground truth,
calibration) into a :class:`~nocal_ros.data.importers.common.Recording`; :func:`write_recording`
streams its frames into a bag, one frame in memory at a time:

* ``/camera/image_raw``: ``sensor_msgs/Image`` at the dataset's own encoding (mono8 stays mono8),
  frame ``camera_optical``;
* ``/ground_truth/pose``: ``T_world_cam`` of the camera's optical frame (the dataset's body-to-camera
  extrinsics applied), on every frame that has one;
* ``/ground_truth/camera_info``: the dataset's calibration at native resolution, with every frame;
* ``/arm/pose`` (``arm_fraction > 0``): the ground truth of a share of the frames, in runs of 9 as an
  arm logs them (:func:`nocal_ros.data.synthetic.labelled_frames`, the renderer's rule), frame ``base``.

Formats (one module each): ``kitti``, ``euroc``, ``tum``, ``folder``, ``video``, ``vamr``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nocal_ros.data.importers.common import Recording
from nocal_ros.data.importers.euroc import open_euroc
from nocal_ros.data.importers.folder import open_folder, open_video
from nocal_ros.data.importers.kitti import open_kitti
from nocal_ros.data.importers.tum import open_tum
from nocal_ros.data.importers.vamr import open_vamr
from nocal_ros.errors import ConfigError, DatasetError

FORMATS: dict[str, Callable[..., Recording]] = {
    "kitti": open_kitti,
    "euroc": open_euroc,
    "tum": open_tum,
    "folder": open_folder,
    "video": open_video,
    "vamr": open_vamr,
}

__all__ = ["FORMATS", "ImportSummary", "Recording", "format_options", "open_recording", "write_recording"]


def format_options(fmt: str) -> list[str]:
    """The keyword options an importer takes (``rate``, ``poses``, ...)."""
    if fmt not in FORMATS:
        raise ConfigError(f"unknown dataset format {fmt!r}; one of {', '.join(FORMATS)}")
    return [name for name, p in inspect.signature(FORMATS[fmt]).parameters.items() if p.kind == p.KEYWORD_ONLY]


def open_recording(fmt: str, src: str | Path, **options: Any) -> Recording:
    """Open ``src`` as a ``fmt`` dataset; options that format does not take are refused (ConfigError)."""
    accepted = format_options(fmt)
    unknown = sorted(name for name, value in options.items() if value is not None and name not in accepted)
    if unknown:
        raise ConfigError(
            f"format {fmt} does not take {', '.join('--' + n.replace('_', '-') for n in unknown)}"
            f" (it takes: {', '.join('--' + n.replace('_', '-') for n in accepted) or 'no options'})"
        )
    return FORMATS[fmt](Path(src), **{name: value for name, value in options.items() if value is not None})


@dataclass
class ImportSummary:
    """What :func:`write_recording` wrote."""

    path: Path
    frames: int
    size: tuple[int, int]
    encoding: str
    ground_truth_frames: int
    arm_frames: int
    camera_info: bool
    first_stamp_ns: int
    last_stamp_ns: int
    path_length_m: float  # the ground-truth camera centre's travel over the frames written


def arm_frames(ground_truth: np.ndarray | None, count: int, fraction: float, seed: int) -> np.ndarray:
    """Indices (of the first ``count`` frames) republished on ``/arm/pose``: ``fraction`` of the frames
    that have ground truth, in runs, by the renderer's rule (:func:`~nocal_ros.data.synthetic.labelled_frames`)."""
    from nocal_ros.data.synthetic import labelled_frames

    if not 0.0 <= fraction <= 1.0:
        raise ConfigError(f"--arm-fraction must be in [0, 1], got {fraction}")
    if fraction == 0.0:
        return np.zeros(0, dtype=np.int64)
    if ground_truth is None:
        raise ConfigError("--arm-fraction needs ground truth, and this recording has none")
    posed = np.flatnonzero(np.isfinite(ground_truth[:count]).all(axis=(1, 2)))
    if len(posed) == 0:
        raise ConfigError("--arm-fraction needs ground truth, and no frame has any")
    # The same seed stream the renderer uses for its labels (its third spawned child).
    label_seed = np.random.SeedSequence(seed).spawn(3)[2]
    return posed[labelled_frames(len(posed), fraction, np.random.default_rng(label_seed))]


def write_recording(
    recording: Recording,
    path: str | Path,
    storage: str = "mcap",
    *,
    arm_fraction: float = 0.0,
    seed: int = 0,
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Stream ``recording`` into a bag at ``path`` (atomic: nothing is left behind on failure).

    Args:
        storage: ``mcap`` or ``sqlite3``.
        arm_fraction: share of the frames with ground truth to republish on ``/arm/pose``.
        seed: seed of the arm share's runs.
        max_frames: import only the first frames.
        progress: called as ``progress(done, total)`` after each frame.
    """
    from nocal_ros.data.bags import (
        ARM_BASE_FRAME,
        ARM_POSE_TOPIC,
        CAMERA_FRAME,
        CAMERA_INFO_TOPIC,
        GT_POSE_TOPIC,
        IMAGE_TOPIC,
        WORLD_FRAME,
        BagWriter,
    )

    if storage not in ("mcap", "sqlite3"):
        raise ConfigError(f"--storage must be mcap or sqlite3, not {storage!r}")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames must be at least 1, got {max_frames}")
    total = len(recording) if max_frames is None else min(len(recording), max_frames)
    arm = set(arm_frames(recording.ground_truth, total, arm_fraction, seed).tolist())
    ground_truth = recording.ground_truth
    written = posed = 0
    first = last = None
    centres = []
    with BagWriter(Path(path), storage, overwrite=overwrite) as writer:
        for index, (stamp, image) in enumerate(recording.frames()):
            if max_frames is not None and index >= max_frames:
                break
            if last is not None and stamp <= last:
                raise DatasetError(f"{recording.name}: frame {index} stamp {stamp} ns does not increase")
            writer.write_image(IMAGE_TOPIC, stamp, CAMERA_FRAME, image, recording.encoding)
            if recording.calibration is not None:
                writer.write_camera_info(CAMERA_INFO_TOPIC, stamp, CAMERA_FRAME, recording.calibration)
            if ground_truth is not None and index < len(ground_truth) and np.isfinite(ground_truth[index]).all():
                writer.write_pose(GT_POSE_TOPIC, stamp, WORLD_FRAME, ground_truth[index])
                centres.append(ground_truth[index][:3, 3])
                posed += 1
                if index in arm:
                    writer.write_pose(ARM_POSE_TOPIC, stamp, ARM_BASE_FRAME, ground_truth[index])
            first = stamp if first is None else first
            last = stamp
            written += 1
            if progress is not None:
                progress(written, total)
        if written == 0:
            raise DatasetError(f"{recording.name}: no frames to import")
    travel = float(np.linalg.norm(np.diff(np.array(centres), axis=0), axis=1).sum()) if len(centres) > 1 else 0.0
    return ImportSummary(path=Path(path), frames=written, size=recording.size, encoding=recording.encoding,
                         ground_truth_frames=posed, arm_frames=len(arm), camera_info=recording.calibration is not None,
                         first_stamp_ns=int(first), last_stamp_ns=int(last), path_length_m=travel)
