"""The UZH "Vision Algorithms for Mobile Robotics" exercise layout (e.g. ``shared/data/real/vamr_ex1``).

Layout::

    SRC/images/img_0001.jpg ...   grey frames stored as JPEG (RGB with equal channels)
    SRC/K.txt                     3x3 camera matrix
    SRC/D.txt                     k1 k2 of the course's radial model in pixel units: the distorted pixel is
                                  c + (1 + k1 r^2 + k2 r^4)(u - c), r^2 = |u - c|^2 of the ideal pixel u
    SRC/poses.txt                 one "wx wy wz tx ty tz" per image: world-to-camera, X_c = R(w) X_w + t
                                  (Rodrigues vector), the world being the checkerboard (metres)

No timestamps: frames at ``rate`` (default 30 Hz). The distortion becomes ROS ``plumb_bob`` with
``k1 = k1_px fx fy`` and ``k2 = k2_px (fx fy)^2`` (p1 = p2 = k3 = 0), exact when fx = fy; the
difference to the course's model over the image is stated in the import's notes. The ground truth is
``T_world_cam = inv([R(w) | t])``. The frames are written as mono8 (their channels are equal; a frame
whose channels differ is refused: import it with ``--encoding rgb8``).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from nocal_ros.data.importers.common import (
    Recording,
    image_file_recording,
    list_images,
    parse_floats,
    rate_stamps,
    read_image,
    read_lines,
    require_file,
)
from nocal_ros.errors import ConfigError, DatasetError

DEFAULT_RATE_HZ = 30.0


def read_matrix_rows(path: Path, rows: int, columns: int, what: str) -> np.ndarray:
    lines = read_lines(require_file(path, what))
    if len(lines) != rows:
        raise DatasetError(f"{path}: expected {rows} line(s) of {columns} numbers ({what}), got {len(lines)}")
    return np.stack([parse_floats(path, line, fields, columns, what) for line, fields in lines])


def course_to_plumb_bob(K: np.ndarray, k_px: np.ndarray) -> np.ndarray:
    """``[k1 fx fy, k2 (fx fy)^2, 0, 0, 0]``: the course's pixel-unit radial model as plumb_bob."""
    fxfy = K[0, 0] * K[1, 1]
    return np.array([k_px[0] * fxfy, k_px[1] * fxfy**2, 0.0, 0.0, 0.0])


def conversion_error_px(K: np.ndarray, k_px: np.ndarray, D: np.ndarray, width: int, height: int) -> float:
    """Largest distance (pixels) between the course's and the plumb_bob model's distorted pixels over
    ideal pixels of the image grid (every 8th pixel and the border)."""
    from nocal_ros.lens import distort_normalised

    u = np.unique(np.r_[np.arange(0, width, 8), width - 1]).astype(np.float64)
    v = np.unique(np.r_[np.arange(0, height, 8), height - 1]).astype(np.float64)
    uu, vv = np.meshgrid(u, v)
    du, dv = uu.ravel() - K[0, 2], vv.ravel() - K[1, 2]
    r2 = du * du + dv * dv
    factor = 1 + k_px[0] * r2 + k_px[1] * r2 * r2
    course = np.stack((K[0, 2] + factor * du, K[1, 2] + factor * dv), -1)
    xy = np.stack((du / K[0, 0], dv / K[1, 1]), -1)
    distorted = distort_normalised(xy, D, "plumb_bob")
    plumb = np.stack((K[0, 2] + K[0, 0] * distorted[:, 0], K[1, 2] + K[1, 1] * distorted[:, 1]), -1)
    return float(np.linalg.norm(course - plumb, axis=1).max())


def open_vamr(src: Path, *, rate: float | None = None, encoding: str | None = None) -> Recording:
    """Open a VAMR exercise folder (see the module notes)."""
    from nocal_ros.lens import CameraCalibration

    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: not a VAMR exercise folder")
    files = list_images(src / "images")
    K = read_matrix_rows(src / "K.txt", 3, 3, "camera matrix K")
    k_px = read_matrix_rows(src / "D.txt", 1, 2, "k1 k2 in pixel units")[0]
    D = course_to_plumb_bob(K, k_px)
    poses_path = src / "poses.txt"
    rows = read_lines(require_file(poses_path, "VAMR poses.txt"))
    if len(rows) != len(files):
        raise DatasetError(f"{poses_path}: {len(rows)} poses for {len(files)} images in {src / 'images'}")
    ground_truth = np.tile(np.eye(4), (len(rows), 1, 1))
    for k, (line, fields) in enumerate(rows):
        values = parse_floats(poses_path, line, fields, 6, "wx wy wz tx ty tz")
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = cv2.Rodrigues(values[:3])[0]
        T_cam_world[:3, 3] = values[3:]
        ground_truth[k] = np.linalg.inv(T_cam_world)

    first = read_image(files[0])
    height, width = first.shape[:2]
    try:
        calibration = CameraCalibration(width, height, K, D, "plumb_bob", "vamr")
    except ValueError as error:
        raise DatasetError(f"{src / 'K.txt'}: {error}") from None
    rate = DEFAULT_RATE_HZ if rate is None else float(rate)
    if not rate > 0:
        raise ConfigError(f"--rate must be positive, got {rate}")
    notes = [f"no timestamps: {rate:g} Hz",
             f"distortion k1 {k_px[0]:g} k2 {k_px[1]:g} px^-2 -> plumb_bob k1 {D[0]:.5f} k2 {D[1]:.5f}; "
             f"differs from the course's model by at most {conversion_error_px(K, k_px, D, width, height):.3f} px over the image"]
    # The images are grey stored as RGB: mono8 loses nothing, and a colour frame is refused rather
    # than silently turned grey.
    return image_file_recording(f"vamr:{src}", files, rate_stamps(len(files), rate), ground_truth, calibration,
                                encoding or "mono8", notes, grey_source=True)
