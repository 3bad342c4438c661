"""What every importer shares: the :class:`Recording` it returns, strict text parsing with the file and
line in every error, image files, timestamps, TUM-style association and pose files.

A :class:`Recording` holds everything but the pixels (stamps, ground truth, calibration), read up
front from the dataset's text files; its frames are read one at a time while the bag is written, so
an import never holds a whole dataset in memory.
"""

from __future__ import annotations

import bisect
import logging
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from nocal_ros.data.synthetic import FIRST_STAMP_NS  # recordings without absolute time start there
from nocal_ros.errors import ConfigError, DatasetError
from nocal_ros.geometry import make_transform, quaternion_to_matrix

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration

log = logging.getLogger(__name__)

#: Image file suffixes the folder-like importers list (what ``cv2.imread`` decodes).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
#: Wire encodings an import can write (``auto``: the source's own: one channel mono8, else rgb8).
ENCODINGS = ("auto", "mono8", "rgb8")


@dataclass
class Recording:
    """A dataset opened for import.

    Attributes:
        name: what was opened (format and path), for messages.
        stamps_ns: ``(N,)`` int64 image stamps, strictly increasing; None when only known while
            reading (a video).
        ground_truth: ``(N, 4, 4)`` ``T_world_cam`` of the camera's optical frame at each image stamp
            (the dataset's body-to-camera extrinsics applied), NaN where a frame has none; or None.
        calibration: the camera at native resolution, when the dataset gives it.
        size: ``(width, height)`` of the images.
        encoding: ``mono8`` or ``rgb8``: what the frames are and the bag will hold.
        notes: assumptions the importer made (printed by ``nocal import``).
        read_frames: yields ``(stamp_ns, image)`` one frame at a time: ``(H, W)`` uint8 for mono8,
            ``(H, W, 3)`` uint8 RGB for rgb8.
        length: number of frames (a video's container count may be approximate).
    """

    name: str
    stamps_ns: np.ndarray | None
    ground_truth: np.ndarray | None
    calibration: "CameraCalibration | None"
    size: tuple[int, int]
    encoding: str
    read_frames: Callable[[], Iterator[tuple[int, np.ndarray]]]
    length: int
    notes: list[str] = field(default_factory=list)

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        return self.read_frames()

    def __len__(self) -> int:
        return self.length

    def note(self, text: str) -> None:
        log.debug("%s: %s", self.name, text)
        self.notes.append(text)


# --------------------------------------------------------------------------------------------------
# text files
# --------------------------------------------------------------------------------------------------


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    return path


def read_lines(path: Path, comment: str = "#") -> list[tuple[int, list[str]]]:
    """Non-empty, non-comment lines of a text file as ``(line number, fields)``; fields split on
    whitespace and commas (TUM's associate.py reads its files the same way)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DatasetError(f"{path}: not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: cannot read it as text ({error})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or (comment and stripped.startswith(comment)):
            continue
        rows.append((number, [field for field in re.split(r"[\s,]+", stripped) if field]))
    return rows


def parse_floats(path: Path, line: int, fields: Sequence[str], count: int | None, what: str) -> np.ndarray:
    """``fields`` as float64; DatasetError naming ``path:line`` when they are not ``count`` finite numbers."""
    if count is not None and len(fields) != count:
        raise DatasetError(f"{path}:{line}: expected {count} numbers ({what}), got {len(fields)}")
    try:
        values = np.array([float(field) for field in fields], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}:{line}: not a number in {' '.join(fields)!r} ({what})") from None
    if not np.isfinite(values).all():
        raise DatasetError(f"{path}:{line}: non-finite value in {what}")
    return values


def seconds_to_ns(path: Path, line: int, text: str) -> int:
    """A decimal number of seconds as integer nanoseconds, exactly (a float64 would round
    ``1305031102.175304`` by hundreds of nanoseconds)."""
    try:
        value = Decimal(text)
    except InvalidOperation:
        raise DatasetError(f"{path}:{line}: {text!r} is not a time in seconds") from None
    if not value.is_finite():
        raise DatasetError(f"{path}:{line}: {text!r} is not a finite time")
    return int((value * 1_000_000_000).to_integral_value())


def check_increasing(path: Path, lines: Sequence[int], stamps_ns: Sequence[int]) -> np.ndarray:
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    for k in range(1, len(stamps)):
        if stamps[k] <= stamps[k - 1]:
            raise DatasetError(
                f"{path}:{lines[k]}: time {stamps[k] / 1e9:.9f} s does not increase (previous line: {stamps[k - 1] / 1e9:.9f} s)"
            )
    return stamps


def rate_stamps(count: int, rate_hz: float) -> np.ndarray:
    """Stamps of ``count`` frames at ``rate_hz``, from :data:`FIRST_STAMP_NS` (the renderer's epoch,
    2023-11-14: a zero stamp reads as "unset" to some ROS tools)."""
    if not rate_hz > 0:
        raise ConfigError(f"the frame rate must be positive, got {rate_hz}")
    return FIRST_STAMP_NS + np.round(np.arange(count) * (1e9 / rate_hz)).astype(np.int64)


def quaternion_pose(values: np.ndarray) -> np.ndarray:
    """``tx ty tz qx qy qz qw`` -> 4x4 (the quaternion normalised)."""
    q = values[3:7]
    return make_transform(quaternion_to_matrix(q / np.linalg.norm(q)), values[:3])


def read_tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory (``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments): ``(stamps_ns, T (M, 4, 4))``."""
    rows = read_lines(require_file(path, "pose file"))
    if not rows:
        raise DatasetError(f"{path}: no poses (expected lines 'timestamp tx ty tz qx qy qz qw')")
    stamps, poses, lines = [], [], []
    for line, fields in rows:
        values = parse_floats(path, line, fields, 8, "timestamp tx ty tz qx qy qz qw")
        if np.linalg.norm(values[4:8]) < 1e-9:
            raise DatasetError(f"{path}:{line}: zero quaternion")
        stamps.append(seconds_to_ns(path, line, fields[0]))
        poses.append(quaternion_pose(values[1:]))
        lines.append(line)
    return check_increasing(path, lines, stamps), np.stack(poses)


def associate(first_ns: Sequence[int], second_ns: Sequence[int], max_difference_ns: int, offset_ns: int = 0) -> dict[int, int]:
    """TUM's ``associate.py``: ``{index in first: index in second}``.

    Every pair within ``max_difference`` (``|a - (b + offset)|``) is a candidate; candidates are
    taken closest first, each stamp at most once. Same result as the original's all-pairs search,
    but each stamp only looks at the other list's stamps within the window (sorted lists).
    """
    second = np.asarray(second_ns, dtype=np.int64) + int(offset_ns)
    candidates = []
    for i, a in enumerate(np.asarray(first_ns, dtype=np.int64).tolist()):
        low = bisect.bisect_left(second, a - max_difference_ns)
        high = bisect.bisect_right(second, a + max_difference_ns)
        for j in range(low, high):
            difference = abs(a - int(second[j]))
            if difference < max_difference_ns or (max_difference_ns == 0 and difference == 0):
                candidates.append((difference, i, j))
    candidates.sort()
    used_first: set[int] = set()
    used_second: set[int] = set()
    matches = {}
    for _, i, j in candidates:
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            matches[i] = j
    return matches


def associated_poses(stamps_ns: np.ndarray, pose_stamps_ns: np.ndarray, poses: np.ndarray, max_difference_s: float) -> np.ndarray:
    """``(N, 4, 4)`` poses associated to image stamps (NaN where none), by :func:`associate`."""
    if not max_difference_s >= 0:
        raise ConfigError(f"--max-difference must be non-negative, got {max_difference_s}")
    matches = associate(stamps_ns, pose_stamps_ns, int(round(max_difference_s * 1e9)))
    out = np.full((len(stamps_ns), 4, 4), np.nan)
    for i, j in matches.items():
        out[i] = poses[j]
    return out


def apply_extrinsics(poses: np.ndarray | None, T_body_cam: np.ndarray | None) -> np.ndarray | None:
    """``T_world_cam = T_world_body @ T_body_cam`` for every pose (NaN rows stay NaN)."""
    if poses is None or T_body_cam is None:
        return poses
    return poses @ np.asarray(T_body_cam, dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------------------


def natural_key(name: str) -> list:
    """Sort key that orders ``img_2`` before ``img_10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise DatasetError(f"{folder}: image folder not found")
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise DatasetError(f"{folder}: no image files ({', '.join(IMAGE_SUFFIXES)})")
    return files


def read_image(path: Path) -> np.ndarray:
    """An 8-bit image file as ``(H, W)`` mono or ``(H, W, 3)`` RGB (alpha dropped)."""
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: OpenCV cannot decode this image file")
    if image.dtype != np.uint8:
        raise DatasetError(f"{path}: {image.dtype} pixels; only 8-bit images are imported")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return image
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    raise DatasetError(f"{path}: {image.shape[2]} channels; expected grey, colour or colour with alpha")


def source_encoding(image: np.ndarray) -> str:
    return "mono8" if image.ndim == 2 else "rgb8"


def convert(image: np.ndarray, encoding: str) -> np.ndarray:
    """An image read by :func:`read_image` in the wire encoding (mono8 of colour: luma)."""
    if encoding == "mono8":
        return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image


def resolve_encoding(requested: str, first: np.ndarray) -> str:
    if requested not in ENCODINGS:
        raise ConfigError(f"--encoding must be one of {', '.join(ENCODINGS)}, not {requested!r}")
    return source_encoding(first) if requested == "auto" else requested


def image_file_recording(
    name: str,
    files: Sequence[Path],
    stamps_ns: np.ndarray,
    ground_truth: np.ndarray | None,
    calibration: "CameraCalibration | Callable[[tuple[int, int]], CameraCalibration] | None",
    encoding: str = "auto",
    notes: Sequence[str] = (),
    grey_source: bool = False,
) -> Recording:
    """A :class:`Recording` of image files with known stamps: the first image sets the size and
    (with ``encoding="auto"``) the encoding; every later image must match its size.

    ``calibration`` may be a function of the image size ``(width, height)``, for datasets whose
    calibration files do not say it (KITTI). ``grey_source``: the dataset's colour files hold grey
    images; writing them as mono8 then refuses a frame whose channels differ instead of losing its colour."""
    if len(files) != len(stamps_ns):
        raise DatasetError(f"{name}: {len(files)} images but {len(stamps_ns)} stamps")
    first = read_image(files[0])
    size = (int(first.shape[1]), int(first.shape[0]))
    wire = resolve_encoding(encoding, first)
    if callable(calibration):
        calibration = calibration(size)
    if calibration is not None and (calibration.width, calibration.height) != size:
        raise DatasetError(
            f"{name}: the calibration is for {calibration.width}x{calibration.height} images, "
            f"{files[0]} is {size[0]}x{size[1]}"
        )

    def read_frames() -> Iterator[tuple[int, np.ndarray]]:
        for path, stamp in zip(files, np.asarray(stamps_ns, dtype=np.int64).tolist()):
            image = read_image(path)
            if (image.shape[1], image.shape[0]) != size:
                raise DatasetError(
                    f"{path}: {image.shape[1]}x{image.shape[0]}, but the first image ({files[0].name}) is {size[0]}x{size[1]}"
                )
            if grey_source and wire == "mono8" and image.ndim == 3 and not (
                np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 0], image[..., 2])
            ):
                raise DatasetError(f"{path}: a colour image (its channels differ); import it with --encoding rgb8")
            yield stamp, convert(image, wire)

    recording = Recording(name=name, stamps_ns=np.asarray(stamps_ns, dtype=np.int64), ground_truth=ground_truth,
                          calibration=calibration, size=size, encoding=wire, read_frames=read_frames,
                          length=len(files))
    for text in notes:
        recording.note(text)
    return recording
