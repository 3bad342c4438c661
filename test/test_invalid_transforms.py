"""A zero or NaN quaternion is no rotation: refused on the command line and in the TF path, skipped in
bags, never turned into a NaN pose that poisons a whole trajectory (``geometry.unit_quaternion`` is
the one check)."""

from __future__ import annotations

import numpy as np
import pytest

from nocal_ros.cli import main
from nocal_ros.data.bags import BagWriter, read_poses, read_sequence, transform_msg_to_matrix
from nocal_ros.geometry import InvalidTransformError, make_transform, quaternion_to_matrix, so3_exp, unit_quaternion

STAMP0 = 2_000_000_000
PERIOD = 100_000_000


@pytest.mark.parametrize("q", [[0, 0, 0, 0], [np.nan, 0, 0, 1], [0, 0, np.inf, 1], [1e-9, 0, 0, 0]])
def test_no_rotation_quaternions_are_refused(q):
    with pytest.raises(InvalidTransformError, match="quaternion"):
        quaternion_to_matrix(np.array(q, dtype=float))


def test_unnormalised_quaternions_still_mean_their_rotation():
    half = np.sqrt(0.5)
    assert np.allclose(unit_quaternion([0, 0, 3, 3]), [0, 0, half, half])
    # 90 degrees about z, against an independent closed form (Rodrigues)
    assert np.allclose(quaternion_to_matrix([0, 0, 3, 3]), so3_exp(np.array([0, 0, np.pi / 2])))


def _transform_msg(types, translation, quaternion):
    vector = types["geometry_msgs/msg/Vector3"](x=float(translation[0]), y=float(translation[1]), z=float(translation[2]))
    rotation = types["geometry_msgs/msg/Quaternion"](x=float(quaternion[0]), y=float(quaternion[1]),
                                                       z=float(quaternion[2]), w=float(quaternion[3]))
    return types["geometry_msgs/msg/Transform"](translation=vector, rotation=rotation)


def test_tf_transforms_with_no_rotation_or_nan_translation_are_refused():
    """``transform_msg_to_matrix`` is what the odometry node turns its base -> camera TF into a matrix with."""
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_JAZZY).types
    good = transform_msg_to_matrix(_transform_msg(types, [1, 2, 3], [0, 0, 0, 2]))
    assert np.allclose(good, make_transform(np.eye(3), [1, 2, 3]))
    with pytest.raises(InvalidTransformError):
        transform_msg_to_matrix(_transform_msg(types, [1, 2, 3], [0, 0, 0, 0]))
    with pytest.raises(InvalidTransformError):
        transform_msg_to_matrix(_transform_msg(types, [np.nan, 2, 3], [0, 0, 0, 1]))


def _pose_stamped(writer, stamp, position, quaternion):
    types = writer.types
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(quaternion[0]), y=float(quaternion[1]),
                                                          z=float(quaternion[2]), w=float(quaternion[3])))
    return types["geometry_msgs/msg/PoseStamped"](header=writer.header(stamp, "world"), pose=pose)


def test_pose_samples_with_no_rotation_are_skipped_and_bridged(tmp_path):
    """Five frames; the ground-truth sample at frame 2 has a zero quaternion, the one at frame 3 a NaN
    position. They are skipped: frame 2 is interpolated from frames 1 and 3... which is skipped too, so
    from 1 and 4 when the tolerance allows, and no NaN rotation reaches any frame."""
    path = tmp_path / "glitch.mcap"
    truth_x = 0.1 * np.arange(5)
    with BagWriter(path) as writer:
        for k in range(5):
            stamp = STAMP0 + k * PERIOD
            writer.write_image("/camera/image_raw", stamp, "camera_optical", np.full((6, 8, 3), k, np.uint8))
            quaternion = [0, 0, 0, 0] if k == 2 else [0, 0, 0, 1]
            position = [np.nan if k == 3 else truth_x[k], 0, 0]
            writer.write_message("/ground_truth/pose", stamp, _pose_stamped(writer, stamp, position, quaternion))
    stamps = STAMP0 + PERIOD * np.arange(5)
    poses = read_poses(path, "/ground_truth/pose", stamps, tolerance_s=0.35)
    assert np.isfinite(poses).all()
    assert poses[:, 0, 3] == pytest.approx(truth_x)
    assert np.allclose(poses[:, :3, :3], np.eye(3))
    sequence = read_sequence(path, pose_source="none", tolerance_s=0.35)
    assert sequence.extras["invalid_pose_samples"] == 2
    assert np.isfinite(sequence.ground_truth).all() and sequence.ground_truth[:, 0, 3] == pytest.approx(truth_x)


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    from nocal_ros.data.bags import write_sequence
    from nocal_ros.data.synthetic import render_sequence
    from nocal_ros.lens import CameraCalibration

    sequence = render_sequence(CameraCalibration.pinhole(64, 48, 50.0), 4, seed=1, split="test")
    return write_sequence(sequence, tmp_path_factory.mktemp("bag") / "small.mcap")


def test_odometry_refuses_a_zero_quaternion_mounting(tmp_path, small_bag, capsys):
    out = tmp_path / "out"
    code = main(["odometry", str(small_bag), "--out", str(out), "--threads", "1", "--no-progress",
                 "--base-to-camera", "0.1", "0", "0", "0", "0", "0", "0"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert err.strip().splitlines() == [err.strip()] and "--base-to-camera" in err and "quaternion" in err
    assert not (out / "trajectory.tum").exists()


@pytest.mark.parametrize("mounting, message", [
    (["0", "0", "1.2", "0", "0", "0", "0"], "quaternion"),
    (["0", "0", "-0.4", "0", "0", "0", "1"], "ground frame"),
    (["0", "0", "1.2", "0", "0", "0", "1", "--camera-height", "1.2"], "give one of"),
], ids=["zero quaternion", "ground above the camera", "with --camera-height"])
def test_odometry_refuses_a_ground_frame_it_cannot_use(tmp_path, small_bag, capsys, mounting, message):
    out = tmp_path / "out"
    code = main(["odometry", str(small_bag), "--out", str(out), "--threads", "1", "--no-progress",
                 "--ground-to-camera", *mounting])
    err = capsys.readouterr().err
    assert code == 1, err
    assert err.strip().splitlines() == [err.strip()] and "--ground-to-camera" in err and message in err
    assert not out.exists() or not any(out.iterdir())
