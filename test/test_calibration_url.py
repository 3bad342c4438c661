"""camera_info_manager's URL rules and the calibration files they point at, without ROS.

The expected paths are written out from camera_info_manager's rules (image_common,
camera_info_manager.cpp: resolveURL, parseURL, getPackageFileName, saveCalibrationFile), not computed
by the code under test.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nocal_ros.errors import ConfigError
from nocal_ros.lens import CameraCalibration
from nocal_ros.live.calibration_url import (
    DEFAULT_URL,
    check_camera_name,
    load_calibration,
    resolve_url,
    save_calibration,
    url_path,
)

ENV = {"HOME": "/home/robot"}
SHARES = {"robot_description": "/opt/ros/jazzy/share/robot_description"}


def test_variables_are_substituted_as_camera_info_manager_does():
    assert resolve_url("file://${ROS_HOME}/camera_info/${NAME}.yaml", "wrist_cam", ENV) == \
        "file:///home/robot/.ros/camera_info/wrist_cam.yaml"
    assert resolve_url("file://${ROS_HOME}/c/${NAME}.yaml", "wrist_cam", {**ENV, "ROS_HOME": "/data/ros"}) == \
        "file:///data/ros/c/wrist_cam.yaml"
    assert resolve_url("", "cam", ENV) == resolve_url(DEFAULT_URL, "cam", ENV) == "file:///home/robot/.ros/camera_info/cam.yaml"
    assert resolve_url("file:///tmp/$HOME/x.yaml", "cam", ENV) == "file:///tmp/$HOME/x.yaml"  # no braces: kept
    with pytest.raises(ConfigError, match=r"unknown variable \$\{USER\}"):
        resolve_url("file:///tmp/${USER}.yaml", "cam", ENV)


def test_file_and_package_urls_name_their_files():
    assert url_path("file:///etc/cams/left.yaml", "cam", environ=ENV) == Path("/etc/cams/left.yaml")
    assert str(url_path("FILE:///etc/cams/left.yaml", "cam", environ=ENV)) == "/etc/cams/left.yaml"
    assert str(url_path("package://robot_description/calibration/${NAME}.yaml", "wrist", package_share=SHARES.__getitem__,
                        environ=ENV)) == "/opt/ros/jazzy/share/robot_description/calibration/wrist.yaml"
    for bad in ("package://robot_description", "package://robot_description/", "package:///x.yaml",
                "/etc/cams/left.yaml", "flash:///cam", "http://host/cam.yaml", "file://relative/x.yaml"):
        with pytest.raises(ConfigError, match="camera_info_url"):
            url_path(bad, "cam", package_share=SHARES.__getitem__, environ=ENV)


def test_a_package_that_is_not_installed_is_a_clear_error():
    # Without ROS the ament index is missing; on ROS the package is: both are one ConfigError line.
    with pytest.raises(ConfigError, match="no_such_package_for_nocal"):
        url_path("package://no_such_package_for_nocal/cam.yaml", "cam")


def test_camera_names_follow_camera_info_manager():
    assert check_camera_name("wrist_cam_2") == "wrist_cam_2"
    for bad in ("", "wrist-cam", "a/b", "cam name", "${NAME}"):
        with pytest.raises(ConfigError, match="letters, digits and '_'"):
            check_camera_name(bad)


def test_save_then_load_round_trips_and_makes_directories(tmp_path):
    R = np.eye(3)
    P = np.array([[410.0, 0, 321.0, 0], [0, 412.0, 239.5, 0], [0, 0, 1, 0]])
    calibration = CameraCalibration(640, 480, [[400.0, 0, 320.0], [0, 401.0, 240.0], [0, 0, 1]],
                                    [0.1, -0.05, 0.001, 0.0, 0.0], camera_name="whatever", R=R, P=P)
    url = f"file://{tmp_path}/ros_home/camera_info/${{NAME}}.yaml"
    assert load_calibration(url, "wrist") == (None, tmp_path / "ros_home/camera_info/wrist.yaml")
    path = save_calibration(calibration, url, "wrist")
    assert path == tmp_path / "ros_home/camera_info/wrist.yaml" and path.is_file()
    loaded, where = load_calibration(url, "wrist")
    assert where == path and loaded.camera_name == "wrist"  # camera_info_manager writes its own name
    np.testing.assert_array_equal(loaded.K, calibration.K)
    np.testing.assert_array_equal(loaded.D, calibration.D)
    np.testing.assert_array_equal(loaded.projection, P)
    assert not list(path.parent.glob("*.tmp"))


def test_a_corrupt_file_and_an_unwritable_place_name_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("image_width: [oops\n")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML"):
        load_calibration(f"file://{bad}", "cam")
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("a file where the calibration's directory should go")
    with pytest.raises(ConfigError, match=f"{blocker}/cam.yaml: cannot write the calibration"):
        save_calibration(CameraCalibration.pinhole(64, 48, 50.0), f"file://{blocker}/${{NAME}}.yaml", "cam")
