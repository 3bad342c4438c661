"""COLMAP camera models as :class:`nocal_ros.lens.CameraCalibration`, and back: one exact conversion.

COLMAP (and pycolmap) put the centre of the top-left pixel at (0.5, 0.5); OpenCV and ROS put it at
(0, 0). So ``cx_ros = cx_colmap - 0.5`` (likewise cy); focal lengths and distortion coefficients are
the same numbers. Which COLMAP model becomes which ROS model (``params`` in COLMAP's order):

=====================  ==========================  =====================================================
COLMAP model           params                      ROS ``distortion_model``, ``D``
=====================  ==========================  =====================================================
SIMPLE_PINHOLE         f, cx, cy                   plumb_bob, all zero
PINHOLE                fx, fy, cx, cy              plumb_bob, all zero
SIMPLE_RADIAL          f, cx, cy, k                plumb_bob ``[k, 0, 0, 0, 0]``
RADIAL                 f, cx, cy, k1, k2           plumb_bob ``[k1, k2, 0, 0, 0]``
OPENCV                 fx, fy, cx, cy, k1 k2 p1 p2 plumb_bob ``[k1, k2, p1, p2, 0]``
FULL_OPENCV            fx .. cy, k1 k2 p1 p2 k3-k6 rational_polynomial ``[k1, k2, p1, p2, k3, k4, k5, k6]``
SIMPLE_FISHEYE         f, cx, cy                   equidistant, all zero
FISHEYE                fx, fy, cx, cy              equidistant, all zero
SIMPLE_RADIAL_FISHEYE  f, cx, cy, k                equidistant ``[k, 0, 0, 0]``
RADIAL_FISHEYE         f, cx, cy, k1, k2           equidistant ``[k1, k2, 0, 0]``
OPENCV_FISHEYE         fx, fy, cx, cy, k1 .. k4    equidistant ``[k1, k2, k3, k4]``
=====================  ==========================  =====================================================

Each row is checked in ``test/test_colmap_camera.py`` by projecting points through pycolmap and through
``CameraCalibration.project`` (which matches OpenCV). Other COLMAP models (FOV, THIN_PRISM_FISHEYE, ...)
have no ROS equivalent and raise :class:`~nocal_ros.errors.ConfigError`.

Plain numbers in and out: pycolmap is not imported here, so the core never depends on it.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from nocal_ros.errors import ConfigError
from nocal_ros.lens import CameraCalibration

# model -> (ROS distortion model, index of fx, of fy (the same for one focal), of cx, number of distortion
# coefficients). COLMAP's coefficients follow the intrinsics in ROS order, so they fill D from the start.
_MODELS: dict[str, tuple[str, int, int, int, int]] = {
    "SIMPLE_PINHOLE": ("plumb_bob", 0, 0, 1, 0),
    "PINHOLE": ("plumb_bob", 0, 1, 2, 0),
    "SIMPLE_RADIAL": ("plumb_bob", 0, 0, 1, 1),
    "RADIAL": ("plumb_bob", 0, 0, 1, 2),
    "OPENCV": ("plumb_bob", 0, 1, 2, 4),
    "FULL_OPENCV": ("rational_polynomial", 0, 1, 2, 8),
    "SIMPLE_FISHEYE": ("equidistant", 0, 0, 1, 0),
    "FISHEYE": ("equidistant", 0, 1, 2, 0),
    "SIMPLE_RADIAL_FISHEYE": ("equidistant", 0, 0, 1, 1),
    "RADIAL_FISHEYE": ("equidistant", 0, 0, 1, 2),
    "OPENCV_FISHEYE": ("equidistant", 0, 1, 2, 4),
}
_COEFFICIENTS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}

SUPPORTED_MODELS = tuple(_MODELS)

# COLMAP's pixel origin is the top-left corner of the image; ROS/OpenCV's is the top-left pixel's centre.
PIXEL_OFFSET = 0.5


def calibration_from_colmap(
    model: str,
    params: Sequence[float] | np.ndarray,
    width: int,
    height: int,
    native_size: tuple[int, int] | None = None,
    camera_name: str = "colmap",
) -> CameraCalibration:
    """A COLMAP camera (model name, params in COLMAP's order, image size) as a CameraCalibration.

    ``native_size`` ``(width, height)``: the camera is returned at that size (intrinsics scaled with the
    pixel-centre rule, :func:`nocal_ros.lens.scale_intrinsics`), for a reconstruction run on resized
    frames. Raises ConfigError for a model without a ROS equivalent or a wrong number of parameters.
    """
    model = str(model).upper()
    if model not in _MODELS:
        raise ConfigError(f"COLMAP camera model {model} has no ROS distortion model; use one of {', '.join(SUPPORTED_MODELS)}")
    ros_model, fx_index, fy_index, cx_index, coefficients = _MODELS[model]
    params = np.asarray(params, dtype=np.float64).reshape(-1)
    first = cx_index + 2
    expected = first + coefficients
    if params.size != expected:
        raise ConfigError(f"COLMAP camera model {model} takes {expected} parameters, got {params.size}")
    K = np.array([
        [params[fx_index], 0.0, params[cx_index] - PIXEL_OFFSET],
        [0.0, params[fy_index], params[cx_index + 1] - PIXEL_OFFSET],
        [0.0, 0.0, 1.0],
    ])
    D = np.zeros(_COEFFICIENTS[ros_model])
    D[:coefficients] = params[first:]
    calibration = CameraCalibration(width, height, K, D, ros_model, camera_name)
    if native_size is not None and tuple(native_size) != (calibration.width, calibration.height):
        calibration = calibration.scaled(*native_size)
    return calibration


def calibration_from_pycolmap(camera: Any, native_size: tuple[int, int] | None = None, camera_name: str = "colmap") -> CameraCalibration:
    """:func:`calibration_from_colmap` of a ``pycolmap.Camera``."""
    return calibration_from_colmap(camera.model.name, np.asarray(camera.params), camera.width, camera.height, native_size, camera_name)


def colmap_from_calibration(calibration: CameraCalibration) -> tuple[str, np.ndarray]:
    """The COLMAP model name and params that image exactly like ``calibration`` (at its size).

    plumb_bob -> OPENCV (a non-zero ``k3`` -> FULL_OPENCV), rational_polynomial -> FULL_OPENCV,
    equidistant -> OPENCV_FISHEYE. A skewed K has no COLMAP equivalent and raises ConfigError.
    """
    K = calibration.K
    if abs(K[0, 1]) > 1e-12:
        raise ConfigError(f"camera {calibration.camera_name}: COLMAP cameras have no skew, K[0,1] = {K[0, 1]}")
    intrinsics = [K[0, 0], K[1, 1], K[0, 2] + PIXEL_OFFSET, K[1, 2] + PIXEL_OFFSET]
    D = calibration.D
    if calibration.distortion_model == "equidistant":
        return "OPENCV_FISHEYE", np.array(intrinsics + list(D[:4]))
    if calibration.distortion_model == "plumb_bob" and D[4] == 0.0:
        return "OPENCV", np.array(intrinsics + list(D[:4]))
    full = np.zeros(8)
    full[: len(D)] = D
    return "FULL_OPENCV", np.array(intrinsics + list(full))
