"""EuRoC MAV (ASL folder format): one camera, its calibration, and the ground truth moved onto it.

Layout::

    SRC/mav0/cam0/data.csv        "#timestamp [ns],filename" then one "stamp_ns,name.png" per image
    SRC/mav0/cam0/data/*.png      8-bit grey images
    SRC/mav0/cam0/sensor.yaml     T_BS (the camera's pose in the body frame, 4x4 row-major), resolution,
                                  camera_model: pinhole, intrinsics [fu, fv, cu, cv],
                                  distortion_model: radial-tangential [k1, k2, p1, p2] or equidistant [k1..k4]
    SRC/mav0/state_groundtruth_estimate0/data.csv
                                  "#timestamp, p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y, q_RS_z, ..."
                                  (the body's pose in the world R, quaternion w first), with its own
                                  sensor.yaml T_BS when present (identity in the published data)

(``SRC`` may also be the ``mav0`` folder itself.) The ground truth is interpolated to each image stamp
(slerp and linear, from the two samples that bracket it, both within ``max_difference``; never
extrapolated) and moved onto the camera: ``T_R_cam = T_R_S @ inv(T_B_S_gt) @ T_B_cam``.
radial-tangential becomes ROS ``plumb_bob`` (k3 = 0); equidistant stays ``equidistant`` (OpenCV's fisheye).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from nocal_ros.data.importers.common import (
    Recording,
    check_increasing,
    image_file_recording,
    parse_floats,
    read_lines,
    require_file,
)
from nocal_ros.errors import DatasetError
from nocal_ros.geometry import make_transform, quaternion_to_matrix

DISTORTION_MODELS = {"radial-tangential": ("plumb_bob", 4), "radtan": ("plumb_bob", 4),
                     "equidistant": ("equidistant", 4)}
GROUND_TRUTH_FOLDERS = ("state_groundtruth_estimate0", "vicon0")


def read_sensor_yaml(path: Path) -> dict:
    require_file(path, "EuRoC sensor.yaml")
    text = path.read_text(encoding="utf-8")
    # Some copies carry OpenCV's "%YAML:1.0" directive, which is not YAML.
    text = "\n".join(line for line in text.splitlines() if not line.startswith("%YAML"))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise DatasetError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping of sensor settings")
    return data


def _matrix(path: Path, data: dict, key: str) -> np.ndarray:
    value = data.get(key)
    numbers = value.get("data") if isinstance(value, dict) else value
    try:
        matrix = np.asarray(numbers, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {key} must be a 4x4 matrix ({{rows: 4, cols: 4, data: [16 numbers]}})") from None
    R = matrix[:3, :3]
    if not np.isfinite(matrix).all() or np.abs(R.T @ R - np.eye(3)).max() > 1e-4 or not np.allclose(matrix[3], [0, 0, 0, 1]):
        raise DatasetError(f"{path}: {key} is not a rigid transform")
    return matrix


def _numbers(path: Path, data: dict, key: str, count: int | None) -> np.ndarray:
    value = data.get(key)
    try:
        numbers = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        numbers = None
    if numbers is None or (count is not None and len(numbers) != count) or not np.isfinite(numbers).all():
        raise DatasetError(f"{path}: {key} must be {count or 'a list of'} numbers, got {value!r}")
    return numbers


def camera_from_sensor_yaml(path: Path):
    """``(CameraCalibration, T_B_cam)`` from a camera's sensor.yaml."""
    from nocal_ros.lens import CameraCalibration

    data = read_sensor_yaml(path)
    if str(data.get("camera_model", "pinhole")) != "pinhole":
        raise DatasetError(f"{path}: camera_model {data.get('camera_model')!r}; only pinhole is imported")
    width, height = (int(v) for v in _numbers(path, data, "resolution", 2))
    fu, fv, cu, cv = _numbers(path, data, "intrinsics", 4)
    model = str(data.get("distortion_model", "radial-tangential"))
    if model not in DISTORTION_MODELS:
        raise DatasetError(f"{path}: distortion_model {model!r}; supported: {', '.join(DISTORTION_MODELS)}")
    ros_model, count = DISTORTION_MODELS[model]
    D = _numbers(path, data, "distortion_coefficients", count)
    if ros_model == "plumb_bob":
        D = np.concatenate((D, [0.0]))
    try:
        calibration = CameraCalibration(width, height, np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]]), D, ros_model,
                                        str(data.get("comment") or path.parent.name))
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from None
    return calibration, _matrix(path, data, "T_BS")


def read_ground_truth_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps_ns, T_R_S (M, 4, 4))`` from an ASL pose CSV (timestamp, position, quaternion w x y z, ...)."""
    rows = read_lines(require_file(path, "EuRoC ground truth data.csv"))
    if not rows:
        raise DatasetError(f"{path}: no ground truth rows")
    stamps, poses, lines = [], [], []
    for line, fields in rows:
        if len(fields) < 8:
            raise DatasetError(f"{path}:{line}: expected at least 8 columns (timestamp [ns], p x y z, q w x y z), got {len(fields)}")
        if not fields[0].isdigit():
            raise DatasetError(f"{path}:{line}: timestamp {fields[0]!r} is not an integer number of nanoseconds")
        values = parse_floats(path, line, fields[1:8], 7, "position and quaternion w x y z")
        q_wxyz = values[3:7]
        if np.linalg.norm(q_wxyz) < 1e-9:
            raise DatasetError(f"{path}:{line}: zero quaternion")
        q_xyzw = np.array([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]]) / np.linalg.norm(q_wxyz)
        stamps.append(int(fields[0]))
        poses.append(make_transform(quaternion_to_matrix(q_xyzw), values[:3]))
        lines.append(line)
    return check_increasing(path, lines, stamps), np.stack(poses)


def _image_list(path: Path, folder: Path) -> tuple[list[Path], np.ndarray]:
    rows = read_lines(require_file(path, "EuRoC camera data.csv"))
    if not rows:
        raise DatasetError(f"{path}: no images listed")
    files, stamps, lines = [], [], []
    for line, fields in rows:
        if len(fields) != 2:
            raise DatasetError(f"{path}:{line}: expected 'timestamp [ns],filename', got {len(fields)} fields")
        if not fields[0].isdigit():
            raise DatasetError(f"{path}:{line}: timestamp {fields[0]!r} is not an integer number of nanoseconds")
        files.append(folder / fields[1])
        stamps.append(int(fields[0]))
        lines.append(line)
    return files, check_increasing(path, lines, stamps)


def open_euroc(
    src: Path,
    *,
    camera: str | None = None,
    encoding: str = "auto",
    max_difference: float = 0.02,
) -> Recording:
    """Open a EuRoC ASL sequence (``SRC/mav0`` or ``SRC`` = ``mav0``).

    Args:
        camera: camera folder under ``mav0`` (default ``cam0``).
        max_difference: interpolate the ground truth to an image only from samples within this many
            seconds of it (the ground truth runs at 200 Hz; default 0.02 s).
    """
    src = Path(src)
    mav = src / "mav0" if (src / "mav0").is_dir() else src
    camera = camera or "cam0"
    camera_dir = mav / camera
    if not camera_dir.is_dir():
        raise DatasetError(f"{src}: no {camera} folder (expected {mav / camera}, the ASL layout)")
    files, stamps = _image_list(camera_dir / "data.csv", camera_dir / "data")
    calibration, T_B_cam = camera_from_sensor_yaml(camera_dir / "sensor.yaml")

    ground_truth = None
    notes = []
    folder = next((mav / name for name in GROUND_TRUTH_FOLDERS if (mav / name / "data.csv").is_file()), None)
    if folder is None:
        notes.append(f"no ground truth ({' or '.join(f'{n}/data.csv' for n in GROUND_TRUTH_FOLDERS)})")
    else:
        gt_stamps, T_R_S = read_ground_truth_csv(folder / "data.csv")
        T_B_S = ground_truth_T_BS(folder / "sensor.yaml")
        T_R_B = T_R_S @ np.linalg.inv(T_B_S)
        ground_truth = interpolate_poses(stamps, gt_stamps, T_R_B, max_difference) @ T_B_cam
        missing = int((~np.isfinite(ground_truth).all(axis=(1, 2))).sum())
        if missing:
            notes.append(f"{missing} of {len(files)} images have no ground truth within {max_difference} s "
                         f"({folder.name} covers {gt_stamps[0]} .. {gt_stamps[-1]} ns)")
    return image_file_recording(f"euroc:{camera_dir}", files, stamps, ground_truth, calibration, encoding, notes)


def ground_truth_T_BS(path: Path) -> np.ndarray:
    """A ground-truth sensor's ``T_BS`` (identity when its sensor.yaml is absent or has none)."""
    if not path.is_file():
        return np.eye(4)
    data = read_sensor_yaml(path)
    return _matrix(path, data, "T_BS") if "T_BS" in data else np.eye(4)


def interpolate_poses(stamps_ns: np.ndarray, sample_stamps_ns: np.ndarray, poses: np.ndarray, max_difference_s: float) -> np.ndarray:
    """Poses at ``stamps_ns`` by the bag reader's rule (:class:`nocal_ros.data.bags.PoseTrack`), NaN where none."""
    from nocal_ros.data.bags import PoseTrack

    track = PoseTrack()
    for stamp, T in zip(sample_stamps_ns.tolist(), poses):
        track.add(stamp, T)
    tolerance = int(round(max_difference_s * 1e9))
    out = np.full((len(stamps_ns), 4, 4), np.nan)
    for row, stamp in enumerate(np.asarray(stamps_ns, dtype=np.int64).tolist()):
        T = track.at(stamp, tolerance)
        if T is not None:
            out[row] = T
    return out
