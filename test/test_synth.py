"""`nocal synth` end to end: real rosbag2 files written by the command and read back with rosbags directly."""

from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from nocal_ros.cli import main
from nocal_ros.commands.synth import DEFAULT_CAMERA
from nocal_ros.geometry import quaternion_to_matrix
from nocal_ros.lens import CameraCalibration

JAZZY = get_typestore(Stores.ROS2_JAZZY)
CONFIG = Path(__file__).resolve().parents[1] / "config" / "cameras"


def read_bag(path):
    """``{topic: [(msgtype, bag_time_ns, message), ...]}`` of a bag, via rosbags only."""
    topics = {}
    with AnyReader([Path(path)], default_typestore=JAZZY) as reader:
        for connection, timestamp, raw in reader.messages(connections=reader.connections):
            message = reader.deserialize(raw, connection.msgtype)
            topics.setdefault(connection.topic, []).append((connection.msgtype, timestamp, message))
    return topics


def stamp_ns(message):
    return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec


@pytest.fixture(scope="module")
def mcap_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "bag"
    assert main(["synth", "--out", str(out), "--size", "80x60", "--frames", "20", "--seed", "3",
                 "--labelled-fraction", "0.25", "--fps", "20"]) == 0
    return out


def test_synth_writes_the_standard_layout(mcap_bag):
    assert list(mcap_bag.glob("*.mcap"))
    topics = read_bag(mcap_bag)
    assert set(topics) == {"/camera/image_raw", "/arm/pose", "/ground_truth/pose", "/ground_truth/camera_info"}
    types = {topic: {m[0] for m in messages} for topic, messages in topics.items()}
    assert types == {
        "/camera/image_raw": {"sensor_msgs/msg/Image"},
        "/arm/pose": {"geometry_msgs/msg/PoseStamped"},
        "/ground_truth/pose": {"geometry_msgs/msg/PoseStamped"},
        "/ground_truth/camera_info": {"sensor_msgs/msg/CameraInfo"},
    }
    images = topics["/camera/image_raw"]
    assert len(images) == 20 and len(topics["/ground_truth/pose"]) == 20 and len(topics["/arm/pose"]) == 5
    stamps = np.array([stamp_ns(m) for _, _, m in images])
    assert np.all(np.diff(stamps) == 50_000_000)  # 20 fps
    assert [t for _, t, _ in images] == stamps.tolist()
    arm_stamps = {stamp_ns(m) for _, _, m in topics["/arm/pose"]}
    assert arm_stamps <= set(stamps.tolist())
    image = images[0][2]
    assert (image.width, image.height, image.encoding, image.step) == (80, 60, "rgb8", 240)
    pixels = np.frombuffer(bytes(image.data), np.uint8).reshape(60, 80, 3)
    assert pixels.std() > 10  # a textured scene, not a blank frame
    # the arm pose of a labelled frame equals the ground truth at the same stamp
    truth = {stamp_ns(m): m.pose for _, _, m in topics["/ground_truth/pose"]}
    for _, _, arm in topics["/arm/pose"]:
        gt = truth[stamp_ns(arm)]
        assert gt.position.x == pytest.approx(arm.pose.position.x)
        q = [arm.pose.orientation.x, arm.pose.orientation.y, arm.pose.orientation.z, arm.pose.orientation.w]
        assert np.isclose(np.linalg.det(quaternion_to_matrix(q)), 1.0)
    info = topics["/ground_truth/camera_info"][0][2]
    expected = DEFAULT_CAMERA.scaled(80, 60)
    assert (info.width, info.height, info.distortion_model) == (80, 60, "plumb_bob")
    assert np.allclose(np.asarray(info.k).reshape(3, 3), expected.K)
    assert np.allclose(info.d, expected.D)


def test_same_seed_same_bytes_and_sqlite3_storage(mcap_bag, tmp_path, capsys):
    out = tmp_path / "again"
    assert main(["synth", "--out", str(out), "--size", "80x60", "--frames", "20", "--seed", "3",
                 "--labelled-fraction", "0.25", "--fps", "20", "--storage", "sqlite3"]) == 0
    assert list(out.glob("*.db3"))
    assert "rendered" in capsys.readouterr().out  # the command reports its frame rate
    first, second = read_bag(mcap_bag), read_bag(out)
    data = lambda topics: [bytes(m.data) for _, _, m in topics["/camera/image_raw"]]
    assert data(first) == data(second)
    assert [stamp_ns(m) for _, _, m in second["/arm/pose"]] == [stamp_ns(m) for _, _, m in first["/arm/pose"]]


def test_camera_yaml_is_used_and_scaled(tmp_path):
    out = tmp_path / "fisheye"
    assert main(["synth", "--out", str(out), "--camera", str(CONFIG / "fisheye_640x480.yaml"), "--size", "64x48",
                 "--frames", "3", "--split", "test", "--supersample", "2"]) == 0
    info = read_bag(out)["/ground_truth/camera_info"][0][2]
    expected = CameraCalibration.load(CONFIG / "fisheye_640x480.yaml").scaled(64, 48)
    assert info.distortion_model == "equidistant" and np.allclose(np.asarray(info.k).reshape(3, 3), expected.K)


def test_shipped_default_camera_matches_the_built_in_one():
    assert CameraCalibration.load(CONFIG / "default_640x480.yaml") == DEFAULT_CAMERA


def test_bad_inputs_fail_clearly_and_write_nothing(tmp_path, capsys):
    bad = tmp_path / "broken.yaml"
    bad.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: {data: [1, 2]}\n")
    out = tmp_path / "never"
    assert main(["synth", "--out", str(out), "--camera", str(bad), "--frames", "2"]) == 1
    assert "broken.yaml" in capsys.readouterr().err and not out.exists()
    # an existing bag is not overwritten unless asked
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("precious")
    assert main(["synth", "--out", str(existing), "--size", "16x12", "--frames", "2"]) == 1
    assert "already exists" in capsys.readouterr().err and (existing / "keep.txt").read_text() == "precious"
    with pytest.raises(SystemExit):
        main(["synth", "--out", str(out), "--size", "80by60"])


def test_random_camera_is_drawn_from_the_seed(tmp_path):
    from nocal_ros.data.synthetic import random_calibration

    out = tmp_path / "random"
    assert main(["synth", "--out", str(out), "--random-camera", "--size", "48x36", "--frames", "2", "--seed", "9",
                 "--threads", "1"]) == 0
    info = read_bag(out)["/ground_truth/camera_info"][0][2]
    expected = random_calibration(np.random.default_rng([9, 7]), 48, 36)
    assert np.allclose(np.asarray(info.k).reshape(3, 3), expected.K) and np.allclose(info.d, expected.D)
    assert not np.allclose(expected.K, DEFAULT_CAMERA.scaled(48, 36).K)
