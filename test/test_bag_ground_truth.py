"""Ground truth read beside a bag's images without decoding them (``nocal odometry``'s report)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from nocal_ros.commands.odometry import _ground_truth, _image_count
from nocal_ros.data.bags import BagWriter, iter_images, read_camera_info
from nocal_ros.data.synthetic import random_calibration
from nocal_ros.errors import BagError

STAMPS = 1_000_000_000 + 100_000_000 * np.arange(3)
TRUE_CAMERA = random_calibration(np.random.default_rng(1), 48, 36)


def write_truth_bag(path, image_encoding, K=None, calibration=TRUE_CAMERA):
    """Three frames whose images are in ``image_encoding`` (raw bytes), with ground-truth poses and camera."""
    with BagWriter(path) as bag:
        types = bag.types
        for index in range(3):
            stamp = 1_000_000_000 + index * 100_000_000
            bag.write_message("/camera/image_raw", stamp, types["sensor_msgs/msg/Image"](
                header=bag.header(stamp, "camera_optical"), height=6, width=8, encoding=image_encoding,
                is_bigendian=0, step=8, data=np.zeros(48, dtype=np.uint8)))
            T = np.eye(4)
            T[0, 3] = 0.1 * index
            bag.write_pose("/ground_truth/pose", stamp, "world", T)
        # The writer only reads these fields, so it can also write what a driver without a calibration sends.
        written = calibration if K is None else SimpleNamespace(
            width=calibration.width, height=calibration.height, K=K, D=calibration.D,
            distortion_model=calibration.distortion_model)
        bag.write_camera_info("/ground_truth/camera_info", 1_000_000_000, "camera_optical", written)
    return path


def test_odometry_ground_truth_reads_no_image(tmp_path):
    # bayer images are not decodable here: any image decoding on this path would raise.
    bag = write_truth_bag(tmp_path / "bayer.mcap", "bayer_rggb8")
    with pytest.raises(BagError, match="bayer"):
        next(iter_images(bag))
    ground_truth = _ground_truth(bag, "/ground_truth/pose", "/ground_truth/camera_info", STAMPS)
    assert np.array_equal(ground_truth.stamps_ns, STAMPS)
    assert ground_truth.T_w_cam[:, 0, 3] == pytest.approx([0.0, 0.1, 0.2])
    assert np.allclose(ground_truth.calibration.K, TRUE_CAMERA.K) and np.allclose(ground_truth.calibration.D, TRUE_CAMERA.D)
    assert ground_truth.calibration.distortion_model == TRUE_CAMERA.distortion_model
    assert _image_count(bag, "/camera/image_raw") == 3 and _image_count(bag, "/nothing") is None
    assert _image_count(tmp_path / "missing.mcap", "/camera/image_raw") is None


def test_read_camera_info_names_the_bag_and_the_problem(tmp_path):
    assert np.allclose(read_camera_info(write_truth_bag(tmp_path / "good.mcap", "rgb8")).K, TRUE_CAMERA.K)
    bag = write_truth_bag(tmp_path / "zero_k.mcap", "rgb8", K=np.zeros((3, 3)))
    with pytest.raises(BagError, match=r"zero_k\.mcap: /ground_truth/camera_info: CameraInfo is not a usable calibration"):
        read_camera_info(bag)
    with pytest.raises(BagError, match=r"zero_k\.mcap: no camera info topic '/camera_info'"):
        read_camera_info(bag, "/camera_info")
    with pytest.raises(BagError, match=r"zero_k\.mcap: topic /ground_truth/pose holds geometry_msgs/msg/PoseStamped"):
        read_camera_info(bag, "/ground_truth/pose")
    # The odometry report still gets its pose errors, just no camera errors.
    ground_truth = _ground_truth(bag, "/ground_truth/pose", "/ground_truth/camera_info", STAMPS)
    assert ground_truth.calibration is None and len(ground_truth.stamps_ns) == 3
