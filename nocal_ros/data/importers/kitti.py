"""KITTI odometry: one camera of a sequence folder, its poses, stamps and rectified calibration.

Layout (the official one, and excerpts of it)::

    SRC/image_0/000000.png ...   (image_0, image_1: grey left, right; image_2, image_3: colour left, right;
                                  image_l / image_r in some excerpts: grey left / right)
    SRC/calib.txt                P0 .. P3 (and Tr) rows, each 12 numbers of a 3x4 projection,
                                 with "P0:" prefixes (official) or without (rows in the order P0, P1, P2, P3)
    SRC/times.txt                seconds since the first frame, one per image (absent: 10 Hz, said so)
    SRC/poses.txt or SRC/../../poses/NN.txt (dataset/sequences/NN -> dataset/poses/NN.txt)
                                 one 3x4 row-major [R | t] per image: T_world_cam0, where the world is the
                                 first frame's camera 0 (the KITTI devkit's convention)

The images are rectified: the calibration is K (from the camera's P) with no distortion. The poses are
of camera 0 (the left grey camera); camera i's pose is ``T_world_cam0 @ T_cam0_cami``, with
``T_cam0_cami`` the translation ``-inv(K) P_i[:, 3]`` of the rectified rig (0.54 m to the right for
camera 1), so ``/ground_truth/pose`` is the pose of the camera imported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nocal_ros.data.importers.common import (
    Recording,
    apply_extrinsics,
    check_increasing,
    image_file_recording,
    list_images,
    parse_floats,
    rate_stamps,
    read_lines,
    require_file,
    seconds_to_ns,
)
from nocal_ros.data.synthetic import FIRST_STAMP_NS
from nocal_ros.errors import DatasetError

#: Image folders, the projection row each one uses, in the order a camera is chosen when none is named.
CAMERAS = {"image_0": 0, "image_2": 2, "image_l": 0, "image_1": 1, "image_3": 3, "image_r": 1}
DEFAULT_RATE_HZ = 10.0


def read_calibration(path: Path) -> dict[str, np.ndarray]:
    """``{"P0": 3x4, ...}`` from a calib.txt with ``P0:`` prefixes or without (then rows are P0, P1, P2, P3, Tr)."""
    rows = read_lines(require_file(path, "KITTI calib.txt"))
    if not rows:
        raise DatasetError(f"{path}: empty; expected rows of 12 numbers (P0, P1, ...)")
    matrices = {}
    for index, (line, fields) in enumerate(rows):
        if fields[0].endswith(":"):
            name, numbers = fields[0][:-1], fields[1:]
        elif ":" in fields[0]:  # "P0:7.18e+02" with no space after the colon
            name, first = fields[0].split(":", 1)
            numbers = [first, *fields[1:]]
        else:
            name, numbers = (["P0", "P1", "P2", "P3", "Tr"][index] if index < 5 else f"row{index}"), fields
        if (name.startswith("P") and name[1:].isdigit()) or name == "Tr":
            matrices[name] = parse_floats(path, line, numbers, 12, f"{name}, a 3x4 matrix").reshape(3, 4)
    return matrices


def read_kitti_poses(path: Path) -> np.ndarray:
    """``(N, 4, 4)`` from a KITTI pose file (12 numbers per line, row-major 3x4)."""
    rows = read_lines(require_file(path, "KITTI pose file"))
    if not rows:
        raise DatasetError(f"{path}: no poses (expected lines of 12 numbers, a row-major 3x4 [R | t])")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for k, (line, fields) in enumerate(rows):
        poses[k, :3] = parse_floats(path, line, fields, 12, "a row-major 3x4 pose [R | t]").reshape(3, 4)
        R = poses[k, :3, :3]
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
            raise DatasetError(f"{path}:{line}: the 3x3 part is not a rotation (det {np.linalg.det(R):.4f})")
    return poses


def _find_poses(src: Path) -> Path | None:
    candidates = [src / "poses.txt", src.parent.parent / "poses" / f"{src.name}.txt"]
    return next((path for path in candidates if path.is_file()), None)


def open_kitti(
    src: Path,
    *,
    camera: str | None = None,
    poses: Path | None = None,
    encoding: str = "auto",
    rate: float | None = None,
) -> Recording:
    """Open a KITTI odometry sequence folder.

    Args:
        camera: image folder to import (``image_0`` ... ``image_3``, ``image_l``, ``image_r``); default:
            the first present of :data:`CAMERAS`.
        poses: the pose file, when it is not at ``SRC/poses.txt`` or ``SRC/../../poses/NN.txt``.
        rate: frame rate when the sequence has no ``times.txt`` (default 10 Hz, KITTI's).
    """
    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: not a KITTI sequence folder")
    if camera is None:
        camera = next((name for name in CAMERAS if (src / name).is_dir()), None)
        if camera is None:
            raise DatasetError(f"{src}: no image folder ({', '.join(CAMERAS)})")
    elif camera not in CAMERAS:
        raise DatasetError(f"{src}: unknown KITTI camera {camera!r}; one of {', '.join(CAMERAS)}")
    files = list_images(src / camera)
    notes = []

    calibration_path = src / "calib.txt"
    projections = read_calibration(calibration_path)
    row = f"P{CAMERAS[camera]}"
    if row not in projections:
        raise DatasetError(f"{calibration_path}: no {row} row for {camera} (rows: {', '.join(projections)})")
    P = projections[row]
    K = P[:, :3].copy()
    if abs(K[2, 2] - 1) > 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DatasetError(f"{calibration_path}: {row} is not a rectified projection K [I | t] (K = {K.tolist()})")
    offset = np.linalg.solve(K, P[:, 3])  # camera 0's points in this camera's frame: X + offset
    T_cam0_cam = np.eye(4)
    T_cam0_cam[:3, 3] = -offset

    times = src / "times.txt"
    if times.is_file():
        rows = read_lines(times)
        if len(rows) != len(files):
            raise DatasetError(f"{times}: {len(rows)} times for {len(files)} images in {src / camera}")
        for line, fields in rows:
            if len(fields) != 1:
                raise DatasetError(f"{times}:{line}: expected one time in seconds, got {len(fields)} fields")
        stamps = check_increasing(times, [line for line, _ in rows],
                                  [FIRST_STAMP_NS + seconds_to_ns(times, line, fields[0]) for line, fields in rows])
        if rate is not None:
            notes.append(f"--rate ignored: {times} gives the stamps")
    else:
        rate = DEFAULT_RATE_HZ if rate is None else float(rate)
        stamps = rate_stamps(len(files), rate)
        notes.append(f"no {times.name}: stamps at {rate:g} Hz")

    ground_truth = None
    pose_path = Path(poses) if poses is not None else _find_poses(src)
    if pose_path is not None:
        world_cam0 = read_kitti_poses(pose_path)
        if len(world_cam0) != len(files):
            raise DatasetError(f"{pose_path}: {len(world_cam0)} poses for {len(files)} images in {src / camera}")
        ground_truth = apply_extrinsics(world_cam0, T_cam0_cam)
    else:
        notes.append("no poses.txt: no ground truth")

    from nocal_ros.lens import CameraCalibration

    def calibration(size: tuple[int, int]) -> CameraCalibration:  # rectified: K, no distortion
        return CameraCalibration(size[0], size[1], K, np.zeros(5), "plumb_bob", f"kitti_{camera}")

    return image_file_recording(f"kitti:{src / camera}", files, stamps, ground_truth, calibration, encoding, notes)
