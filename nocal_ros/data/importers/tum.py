"""TUM RGB-D: the colour camera, with the ground truth associated by timestamp as TUM's tools do.

Layout::

    SRC/rgb.txt           "# ..." comments, then "timestamp filename" (seconds since the epoch, rgb/<stamp>.png)
    SRC/rgb/*.png         640x480 colour
    SRC/groundtruth.txt   "timestamp tx ty tz qx qy qz qw": the colour camera's optical centre and
                          orientation in the motion-capture world (TUM's file format page), so it is
                          already ``T_world_cam`` of the optical frame

Each image gets the ground-truth sample that ``associate.py rgb.txt groundtruth.txt`` pairs with it
(closest first, each sample used once, ``|difference| < max_difference``, default 0.02 s as there);
an image with none has no ``/ground_truth/pose``. The calibration: ``--calibration YAML`` if given,
else TUM's published calibration of the Freiburg camera named in the folder name
(``rgbd_dataset_freiburg1_xyz`` -> freiburg1, as in ORB-SLAM's TUM1/2/3.yaml), else none.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from nocal_ros.data.importers.common import (
    Recording,
    apply_extrinsics,
    associated_poses,
    check_increasing,
    image_file_recording,
    read_lines,
    read_tum_poses,
    require_file,
    seconds_to_ns,
)
from nocal_ros.errors import DatasetError

#: TUM's intrinsic calibration of the colour cameras (fx, fy, cx, cy; plumb_bob d0..d4), 640x480.
#: freiburg3's images are already undistorted.
FREIBURG_CAMERAS = {
    "freiburg1": ((517.306408, 516.469215, 318.643040, 255.313989), (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)),
    "freiburg2": ((520.908620, 521.007327, 325.141442, 249.701764), (0.231222, -0.784899, -0.003257, -0.000105, 0.917205)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}


def read_file_list(path: Path, folder: Path) -> tuple[list[Path], np.ndarray]:
    """``rgb.txt``-style lists: ``(files, stamps_ns)`` in file order (stamps must increase)."""
    rows = read_lines(require_file(path, "TUM image list"))
    if not rows:
        raise DatasetError(f"{path}: no images listed (expected 'timestamp filename' lines)")
    files, stamps, lines = [], [], []
    for line, fields in rows:
        if len(fields) != 2:
            raise DatasetError(f"{path}:{line}: expected 'timestamp filename', got {len(fields)} fields")
        stamps.append(seconds_to_ns(path, line, fields[0]))
        files.append(folder / fields[1])
        lines.append(line)
    return files, check_increasing(path, lines, stamps)


def freiburg_calibration(src: Path):
    """TUM's published calibration of the Freiburg camera named in ``src``'s folder name, or None."""
    from nocal_ros.lens import CameraCalibration

    match = re.search(r"freiburg([123])", src.resolve().name)
    if match is None:
        return None
    name = f"freiburg{match.group(1)}"
    (fx, fy, cx, cy), D = FREIBURG_CAMERAS[name]
    return CameraCalibration(640, 480, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.array(D), "plumb_bob", name)


def open_tum(
    src: Path,
    *,
    calibration: Path | None = None,
    encoding: str = "auto",
    max_difference: float = 0.02,
    body_to_camera: np.ndarray | None = None,
) -> Recording:
    """Open a TUM RGB-D sequence folder.

    Args:
        calibration: a ROS camera_calibration YAML for the colour camera (overrides the Freiburg table).
        max_difference: association window in seconds (TUM's default 0.02).
        body_to_camera: ``T_body_cam`` applied to the ground truth, for pose files of something
            other than the optical centre (identity for TUM's own files).
    """
    from nocal_ros.lens import CameraCalibration

    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: not a TUM RGB-D sequence folder")
    files, stamps = read_file_list(src / "rgb.txt", src)
    notes = []
    ground_truth = None
    gt_path = src / "groundtruth.txt"
    if gt_path.is_file():
        pose_stamps, poses = read_tum_poses(gt_path)
        ground_truth = apply_extrinsics(associated_poses(stamps, pose_stamps, poses, max_difference), body_to_camera)
        missing = int((~np.isfinite(ground_truth).all(axis=(1, 2))).sum())
        if missing:
            notes.append(f"{missing} of {len(files)} images have no ground truth within {max_difference} s")
    else:
        notes.append("no groundtruth.txt: no ground truth")
    if calibration is not None:
        camera = CameraCalibration.load(calibration)
    else:
        camera = freiburg_calibration(src)
        if camera is None:
            notes.append("no --calibration and no freiburg1/2/3 in the folder name: no camera_info")
        else:
            notes.append(f"calibration: TUM's published {camera.camera_name} camera")
    return image_file_recording(f"tum:{src}", files, stamps, ground_truth, camera, encoding, notes)
