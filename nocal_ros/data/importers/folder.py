"""A folder of images (any camera), and a video file: stamps from a rate or a timestamps file,
optional poses in TUM format and an optional ROS camera_calibration YAML.

Images are the folder's image files in natural order (``img_2`` before ``img_10``). A timestamps file
holds either one time in seconds per line (one per image, in that order) or ``timestamp filename``
lines (TUM's ``rgb.txt``; then the file names the images). Times below 1e9 s (before 2001: not Unix
times) are taken as relative to the start and moved to the renderer's epoch, like ``--rate`` stamps.
A pose file is a TUM trajectory (``timestamp tx ty tz qx qy qz qw``, the camera's optical frame in the
world unless ``body_to_camera`` says otherwise), associated to the images as TUM's tools do.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from nocal_ros.data.importers.common import (
    Recording,
    apply_extrinsics,
    associated_poses,
    check_increasing,
    convert,
    image_file_recording,
    list_images,
    rate_stamps,
    read_lines,
    read_tum_poses,
    resolve_encoding,
    seconds_to_ns,
)
from nocal_ros.data.synthetic import FIRST_STAMP_NS
from nocal_ros.errors import ConfigError, DatasetError

#: Below this many seconds a time is not a Unix time (2001-09-09) but one relative to the start.
RELATIVE_TIME_LIMIT_S = 1e9


def read_timestamps(path: Path, folder: Path, images: list[Path]) -> tuple[list[Path], np.ndarray, bool]:
    """``(files, stamps_ns, relative)`` from a timestamps file (see the module notes)."""
    rows = read_lines(path)
    if not rows:
        raise DatasetError(f"{path}: no timestamps")
    widths = {len(fields) for _, fields in rows}
    if widths == {1}:
        if len(rows) != len(images):
            raise DatasetError(f"{path}: {len(rows)} timestamps for {len(images)} images in {folder}")
        files = images
    elif widths == {2}:
        files = [folder / fields[1] for _, fields in rows]
    else:
        line, fields = next((line, fields) for line, fields in rows if len(fields) != len(rows[0][1]) or len(fields) > 2)
        raise DatasetError(f"{path}:{line}: expected 'timestamp' or 'timestamp filename' on every line, got {len(fields)} fields")
    stamps = [seconds_to_ns(path, line, fields[0]) for line, fields in rows]
    relative = stamps[0] < RELATIVE_TIME_LIMIT_S * 1e9
    if relative:
        stamps = [FIRST_STAMP_NS + stamp for stamp in stamps]
    return files, check_increasing(path, [line for line, _ in rows], stamps), relative


def _load_calibration(path: Path | None):
    if path is None:
        return None
    from nocal_ros.lens import CameraCalibration

    return CameraCalibration.load(path)


def open_folder(
    src: Path,
    *,
    rate: float | None = None,
    timestamps: Path | None = None,
    poses: Path | None = None,
    calibration: Path | None = None,
    encoding: str = "auto",
    max_difference: float = 0.02,
    body_to_camera: np.ndarray | None = None,
) -> Recording:
    """Open a folder of images; exactly one of ``rate`` (Hz) and ``timestamps`` (a file) sets the stamps."""
    src = Path(src)
    if (rate is None) == (timestamps is None):
        raise ConfigError("a folder of images needs exactly one of --rate HZ and --timestamps FILE")
    notes = []
    if timestamps is not None:
        files, stamps, relative = read_timestamps(Path(timestamps), src, list_images(src) if src.is_dir() else [])
        if relative:
            notes.append(f"times in {Path(timestamps).name} are relative: stamps start at {FIRST_STAMP_NS} ns")
    else:
        files = list_images(src)
        stamps = rate_stamps(len(files), float(rate))
    ground_truth = None
    if poses is not None:
        pose_stamps, T = read_tum_poses(Path(poses))
        if timestamps is None or relative:
            if pose_stamps[0] < RELATIVE_TIME_LIMIT_S * 1e9:
                pose_stamps = pose_stamps + FIRST_STAMP_NS  # the same time base as the images
        ground_truth = apply_extrinsics(associated_poses(stamps, pose_stamps, T, max_difference), body_to_camera)
        missing = int((~np.isfinite(ground_truth).all(axis=(1, 2))).sum())
        if missing == len(files):
            raise DatasetError(f"{poses}: no pose within {max_difference} s of any image stamp (times in different bases?)")
        if missing:
            notes.append(f"{missing} of {len(files)} images have no pose within {max_difference} s")
    return image_file_recording(f"folder:{src}", files, stamps, ground_truth, _load_calibration(calibration), encoding, notes)


def open_video(
    src: Path,
    *,
    rate: float | None = None,
    calibration: Path | None = None,
    encoding: str = "auto",
) -> Recording:
    """Open a video file through OpenCV (FFmpeg). Stamps: each frame's presentation time
    (``CAP_PROP_POS_MSEC``), or ``index / rate`` with ``rate``; from the renderer's epoch."""
    src = Path(src)
    if not src.is_file():
        raise DatasetError(f"{src}: video file not found")

    def open_capture() -> cv2.VideoCapture:
        capture = cv2.VideoCapture(str(src))
        if not capture.isOpened():
            raise DatasetError(f"{src}: OpenCV cannot open this video")
        return capture

    capture = open_capture()
    ok, first = capture.read()
    fps = capture.get(cv2.CAP_PROP_FPS)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    capture.release()
    if not ok or first is None:
        raise DatasetError(f"{src}: no frame could be decoded")
    first = cv2.cvtColor(first, cv2.COLOR_BGR2RGB)
    wire = resolve_encoding(encoding, first)
    size = (int(first.shape[1]), int(first.shape[0]))
    camera = _load_calibration(calibration)
    if camera is not None and (camera.width, camera.height) != size:
        raise DatasetError(f"{calibration}: the calibration is for {camera.width}x{camera.height}, {src} is {size[0]}x{size[1]}")
    if rate is not None and not rate > 0:
        raise ConfigError(f"--rate must be positive, got {rate}")
    period_ns = 1e9 / rate if rate else (1e9 / fps if fps > 0 else None)

    def read_frames() -> Iterator[tuple[int, np.ndarray]]:
        video = open_capture()
        previous = None
        index = 0
        try:
            while True:
                ok, frame = video.read()
                if not ok:
                    break
                position_ms = video.get(cv2.CAP_PROP_POS_MSEC)
                if rate is None and position_ms >= 0 and (previous is None or position_ms * 1e6 > previous):
                    offset = int(round(position_ms * 1e6))
                elif period_ns is not None:
                    offset = int(round(index * period_ns))
                else:
                    raise DatasetError(f"{src}: frame {index} has no time and the video no frame rate; give --rate")
                if previous is not None and offset <= previous:
                    offset = previous + 1  # never a repeated stamp
                previous = offset
                if frame.shape[:2] != (size[1], size[0]):
                    raise DatasetError(f"{src}: frame {index} is {frame.shape[1]}x{frame.shape[0]}, the first is {size[0]}x{size[1]}")
                yield FIRST_STAMP_NS + offset, convert(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB), wire)
                index += 1
        finally:
            video.release()

    recording = Recording(name=f"video:{src}", stamps_ns=None, ground_truth=None, calibration=camera, size=size,
                          encoding=wire, read_frames=read_frames, length=max(count, 0))
    if rate is None and fps <= 0:
        recording.note("the video reports no frame rate: stamps from the frames' presentation times only")
    return recording
