"""COLMAP cameras as ROS calibrations: the same pixels through pycolmap, CameraCalibration and OpenCV."""

import cv2
import numpy as np
import pytest

from nocal_ros.colmap_camera import SUPPORTED_MODELS, calibration_from_colmap, calibration_from_pycolmap, colmap_from_calibration
from nocal_ros.errors import ConfigError
from nocal_ros.lens import CameraCalibration

# Values by parameter name (pycolmap's params_info); fisheye and rational models get their own ranges.
VALUES = {"f": 410.0, "fx": 410.0, "fy": 404.0, "cx": 327.3, "cy": 236.8, "k": -0.08, "k1": -0.08, "k2": 0.012,
          "p1": 0.001, "p2": -0.0007}
FISHEYE = {"k": -0.02, "k1": -0.02, "k2": 0.01, "k3": -0.004, "k4": 0.001}
RATIONAL = {"k1": 0.2, "k2": -0.03, "k3": 0.004, "k4": 0.3, "k5": 0.02, "k6": 0.01}


def colmap_camera(pycolmap, model, width=640, height=480):
    camera = pycolmap.Camera.create_from_model_name(1, model, 400.0, width, height)
    values = dict(VALUES, **(FISHEYE if "FISHEYE" in model else RATIONAL if model == "FULL_OPENCV" else {}))
    camera.params = [values[name] for name in camera.params_info.split(", ")]
    return camera


def points_in_view(rng, n=400, half_angle_deg=45.0):
    angle = np.radians(half_angle_deg) * np.sqrt(rng.uniform(0, 1, n))
    azimuth = rng.uniform(-np.pi, np.pi, n)
    rays = np.stack([np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)], 1)
    return rays * rng.uniform(0.5, 10.0, (n, 1))


def opencv_project(calibration, points):
    if calibration.distortion_model == "equidistant":
        pixels, _ = cv2.fisheye.projectPoints(points[:, None, :], np.zeros(3), np.zeros(3), calibration.K, calibration.D)
    else:
        pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), calibration.K, calibration.D)
    return pixels.reshape(-1, 2)


@pytest.mark.parametrize("model", SUPPORTED_MODELS)
def test_conversion_projects_like_pycolmap_and_opencv(model):
    pycolmap = pytest.importorskip("pycolmap")
    camera = colmap_camera(pycolmap, model)
    calibration = calibration_from_pycolmap(camera)
    points = points_in_view(np.random.default_rng(4))
    # COLMAP's pixel origin is the image corner: its pixels are ours plus half a pixel.
    colmap_pixels = camera.img_from_cam(points) - 0.5
    assert np.abs(calibration.project(points) - colmap_pixels).max() < 1e-9
    assert np.abs(opencv_project(calibration, points) - colmap_pixels).max() < 1e-6
    expected_model = {"FULL_OPENCV": "rational_polynomial"}.get(model, "equidistant" if "FISHEYE" in model else "plumb_bob")
    assert calibration.distortion_model == expected_model


@pytest.mark.parametrize("model", ["OPENCV", "SIMPLE_RADIAL", "OPENCV_FISHEYE"])
def test_native_size_matches_colmaps_own_rescale(model):
    pycolmap = pytest.importorskip("pycolmap")
    small = colmap_camera(pycolmap, model, 160, 120)
    native = calibration_from_pycolmap(small, native_size=(640, 480))
    big = colmap_camera(pycolmap, model, 160, 120)
    big.rescale(640, 480)
    points = points_in_view(np.random.default_rng(5))
    assert (native.width, native.height) == (640, 480)
    assert np.abs(native.project(points) - (big.img_from_cam(points) - 0.5)).max() < 1e-9


@pytest.mark.parametrize("calibration", [
    CameraCalibration(640, 480, [[455.0, 0, 331.4], [0, 457.3, 231.6], [0, 0, 1]], [-0.19, 0.055, 0.0007, -0.0004, 0.0]),
    CameraCalibration(640, 480, [[455.0, 0, 331.4], [0, 457.3, 231.6], [0, 0, 1]], [-0.19, 0.055, 0.0007, -0.0004, 0.01]),
    CameraCalibration(640, 480, [[240.0, 0, 322.0], [0, 240.0, 238.0], [0, 0, 1]], [0.02, -0.01, 0.003, -0.001], "equidistant"),
    CameraCalibration(640, 480, [[400.0, 0, 320.0], [0, 401.0, 240.0], [0, 0, 1]], [0.2, -0.03, 0.001, 0.002, 0.004, 0.3, 0.02, 0.01],
                      "rational_polynomial"),
], ids=["plumb_bob", "plumb_bob_k3", "equidistant", "rational_polynomial"])
def test_round_trip_through_colmap_parameters(calibration):
    model, params = colmap_from_calibration(calibration)
    back = calibration_from_colmap(model, params, calibration.width, calibration.height)
    points = points_in_view(np.random.default_rng(6))
    assert np.abs(back.project(points) - calibration.project(points)).max() < 1e-9
    np.testing.assert_allclose(back.K, calibration.K, atol=1e-12)


def test_unconvertible_cameras_fail_with_one_clear_line():
    with pytest.raises(ConfigError, match="FOV has no ROS distortion model"):
        calibration_from_colmap("FOV", [400, 400, 320, 240, 0.1], 640, 480)
    with pytest.raises(ConfigError, match="OPENCV takes 8 parameters, got 4"):
        calibration_from_colmap("OPENCV", [400, 400, 320, 240], 640, 480)
    skewed = CameraCalibration(640, 480, [[400.0, 2.0, 320], [0, 400, 240], [0, 0, 1]])
    with pytest.raises(ConfigError, match="no skew"):
        colmap_from_calibration(skewed)
