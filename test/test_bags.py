"""Bags: real rosbag2 (mcap, sqlite3) and ROS 1 files written and read back with rosbags."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from nocal_ros.data import bags
from nocal_ros.data.bags import BagWriter, decode_compressed_image, decode_image, iter_images, read_sequence, write_sequence
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.errors import BagError
from nocal_ros.geometry import invert_transform, make_transform, matrix_to_quaternion, so3_exp
from nocal_ros.lens import CameraCalibration

JAZZY = get_typestore(Stores.ROS2_JAZZY)
W, H = 16, 12
S = 1_000_000_000  # ns per second


def tool_pose(t: float) -> np.ndarray:
    """A closed-form arm trajectory on which slerp/linear interpolation is exact: constant angular
    velocity about a fixed axis and constant linear velocity."""
    return make_transform(so3_exp(np.array([0.2, -0.5, 0.3]) * t), np.array([0.5, 1.0, -0.25]) * t + [0.1, 0.2, 0.3])


HAND_EYE = make_transform(so3_exp([0.3, 0.1, -0.2]), [0.02, -0.05, 0.1])


def make_sequence(n: int = 10, seed: int = 0) -> FrameSequence:
    rng = np.random.default_rng(seed)
    stamps = (1_700_000_000 * S + np.arange(n) * 100_000_000 + rng.integers(0, 1000, n)).astype(np.int64)
    arm = np.full((n, 4, 4), np.nan)
    for i in range(0, n, 3):
        arm[i] = tool_pose(i * 0.1)
    truth = np.stack([make_transform(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)])
    calibration = CameraCalibration(W, H, np.array([[14.5, 0, 7.25], [0, 13.0, 5.5], [0, 0, 1]]),
                                    np.array([-0.1, 0.02, 0.001, -0.002, 0.003]), "plumb_bob", "camera_optical")
    images = rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8)
    return FrameSequence(images, stamps, arm, truth, calibration, name="synthetic")


def bag_path(tmp_path: Path, storage: str) -> Path:
    return tmp_path / ("seq.bag" if storage == "ros1" else f"seq_{storage}")


# --------------------------------------------------------------------------------------------------
# round trip
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_write_read_round_trip_is_exact(tmp_path, storage):
    sequence = make_sequence()
    path = write_sequence(sequence, bag_path(tmp_path, storage), storage=storage)

    with AnyReader([path], default_typestore=JAZZY) as reader:
        topics = {name: (info.msgtype, info.msgcount) for name, info in reader.topics.items()}
        image_stamps = [stamp for c, stamp, _ in reader.messages() if c.topic == "/camera/image_raw"]
    n, labelled = len(sequence), int(sequence.labelled.sum())
    assert topics == {
        "/camera/image_raw": ("sensor_msgs/msg/Image", n),
        "/arm/pose": ("geometry_msgs/msg/PoseStamped", labelled),
        "/ground_truth/pose": ("geometry_msgs/msg/PoseStamped", n),
        "/ground_truth/camera_info": ("sensor_msgs/msg/CameraInfo", n),
    }
    assert image_stamps == sequence.stamps_ns.tolist()
    assert bags.bag_topics(path) == topics

    back = read_sequence(path)
    np.testing.assert_array_equal(back.images, sequence.images)
    np.testing.assert_array_equal(back.stamps_ns, sequence.stamps_ns)
    np.testing.assert_array_equal(back.labelled, sequence.labelled)
    np.testing.assert_allclose(back.arm_poses[back.labelled], sequence.arm_poses[sequence.labelled], atol=1e-12)
    np.testing.assert_allclose(back.ground_truth, sequence.ground_truth, atol=1e-12)
    assert back.calibration == sequence.calibration
    assert back.extras["native_size"] == (W, H)


def test_rosbag2_storage_file_reads_directly(tmp_path):
    """A bare .mcap or .db3 (no metadata.yaml beside it) is a bag too."""
    sequence = make_sequence(4)
    for storage, suffix in (("mcap", ".mcap"), ("sqlite3", ".db3")):
        directory = write_sequence(sequence, tmp_path / storage, storage=storage)
        back = read_sequence(directory / f"{storage}{suffix}")
        np.testing.assert_array_equal(back.images, sequence.images)


def test_writer_is_atomic_and_refuses_to_overwrite(tmp_path):
    path = tmp_path / "bag"
    with pytest.raises(RuntimeError):
        with BagWriter(path) as writer:
            writer.write_image("/camera/image_raw", S, "cam", np.zeros((H, W, 3), np.uint8))
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []  # nothing half-written, no staging left over

    sequence = make_sequence(3)
    write_sequence(sequence, path)
    with pytest.raises(BagError, match="already exists"):
        write_sequence(make_sequence(5, seed=1), path)
    assert len(read_sequence(path)) == 3
    write_sequence(make_sequence(5, seed=1), path, overwrite=True)
    assert len(read_sequence(path)) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


def test_resize_and_max_frames_scale_the_calibration(tmp_path):
    sequence = make_sequence(6)
    path = write_sequence(sequence, tmp_path / "bag")
    back = read_sequence(path, resize=(8, 6), max_frames=4)
    assert back.images.shape == (4, 6, 8, 3)
    expected = cv2.resize(sequence.images[2], (8, 6), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(back.images[2], expected)
    np.testing.assert_array_equal(back.stamps_ns, sequence.stamps_ns[:4])
    assert (back.calibration.width, back.calibration.height) == (8, 6)
    assert back.calibration.K[0, 0] == pytest.approx(14.5 / 2)
    assert back.calibration.K[0, 2] == pytest.approx((7.25 + 0.5) / 2 - 0.5)
    assert back.extras["native_size"] == (W, H)


def test_iter_images_streams_compressed_and_raw(tmp_path):
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(3)]
    path = tmp_path / "bag"
    with BagWriter(path, "sqlite3") as writer:
        for k, image in enumerate(images):
            writer.write_compressed_image("/camera/image_raw/compressed", (k + 1) * S, "cam", image, "png")
    frames = list(iter_images(path, "/camera/image_raw/compressed"))
    assert [f[0] for f in frames] == [S, 2 * S, 3 * S]
    assert [f[1] for f in frames] == ["cam"] * 3
    for (_, _, rgb), image in zip(frames, images):
        np.testing.assert_array_equal(rgb, image)


# --------------------------------------------------------------------------------------------------
# decoding: messages built here, independently of the writer
# --------------------------------------------------------------------------------------------------


def image_msg(encoding: str, pixels: np.ndarray, step: int | None = None, bigendian: bool = False, pad_value: int = 77):
    height, width = pixels.shape[:2]
    rows = pixels.reshape(height, -1).view(np.uint8) if pixels.dtype != np.uint8 else pixels.reshape(height, -1)
    row_bytes = rows.shape[1]
    step = row_bytes if step is None else step
    data = np.full((height, step), pad_value, np.uint8)
    data[:, :row_bytes] = rows
    header = JAZZY.types["std_msgs/msg/Header"](stamp=JAZZY.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="c")
    return JAZZY.types["sensor_msgs/msg/Image"](header=header, height=height, width=width, encoding=encoding,
                                                 is_bigendian=int(bigendian), step=step, data=data.reshape(-1))


RGB = np.random.default_rng(7).integers(0, 256, (5, 7, 3), dtype=np.uint8)
GRAY = RGB[:, :, 0]


@pytest.mark.parametrize(
    "encoding, pixels, step, bigendian, expected",
    [
        ("rgb8", RGB, None, False, RGB),
        ("rgb8", RGB, 7 * 3 + 5, False, RGB),  # padded rows
        ("bgr8", RGB[:, :, ::-1].copy(), 7 * 3 + 3, False, RGB),
        ("rgba8", np.dstack([RGB, np.full((5, 7), 9, np.uint8)]), None, False, RGB),
        ("bgra8", np.dstack([RGB[:, :, ::-1], np.full((5, 7), 9, np.uint8)]), 7 * 4 + 4, False, RGB),
        ("mono8", GRAY, 8, False, np.dstack([GRAY] * 3)),
        ("mono16", (GRAY.astype(">u2") * 257), None, True, np.dstack([GRAY] * 3)),
        ("mono16", (GRAY.astype("<u2") * 257 + 100), 7 * 2 + 2, False, np.dstack([GRAY] * 3)),
    ],
)
def test_decode_image_encodings(encoding, pixels, step, bigendian, expected):
    rgb = decode_image(image_msg(encoding, np.ascontiguousarray(pixels), step, bigendian))
    assert rgb.dtype == np.uint8 and rgb.shape == (5, 7, 3)
    np.testing.assert_array_equal(rgb, expected)


def test_decode_compressed_jpeg_and_png():
    smooth = np.dstack([*np.meshgrid(np.linspace(0, 255, 32), np.linspace(40, 200, 24)), np.full((24, 32), 128.0)])
    smooth = smooth.astype(np.uint8)
    for fmt, ext, tolerance in (("jpeg", ".jpg", 4.0), ("png", ".png", 0.0)):
        ok, buffer = cv2.imencode(ext, cv2.cvtColor(smooth, cv2.COLOR_RGB2BGR))
        header = JAZZY.types["std_msgs/msg/Header"](stamp=JAZZY.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
        msg = JAZZY.types["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=buffer.reshape(-1))
        rgb = decode_compressed_image(msg)
        assert rgb.shape == smooth.shape
        assert np.abs(rgb.astype(float) - smooth).mean() <= tolerance
        if fmt == "jpeg":  # channel order: red ramps along x, blue is constant
            assert rgb[12, -1, 0] > 200 and rgb[12, 0, 0] < 50 and abs(int(rgb[12, 16, 2]) - 128) < 8


def test_writer_encodings_round_trip_through_a_bag(tmp_path):
    path = tmp_path / "bag"
    with BagWriter(path, "mcap") as writer:
        for encoding in bags.IMAGE_ENCODINGS:
            writer.write_image(f"/img/{encoding}", S, "cam", RGB, encoding)
        writer.write_compressed_image("/img/png", S, "cam", RGB, "png")
    gray = cv2.cvtColor(RGB, cv2.COLOR_RGB2GRAY)
    for encoding in list(bags.IMAGE_ENCODINGS) + ["png"]:
        (_, _, rgb), = iter_images(path, f"/img/{encoding}")
        np.testing.assert_array_equal(rgb, np.dstack([gray] * 3) if encoding.startswith("mono") else RGB)


def test_decode_rejects_bad_data():
    with pytest.raises(BagError, match=r"yuv422.*supported: rgb8"):
        decode_image(image_msg("yuv422", RGB[:, :, :2].copy()))
    msg = image_msg("rgb8", RGB)
    msg.data = msg.data[:-1]
    with pytest.raises(BagError, match="104 bytes, expected height\\*step = 105"):
        decode_image(msg)
    msg = image_msg("rgb8", RGB)
    msg.step = 20
    with pytest.raises(BagError, match="step 20 is less than a row"):
        decode_image(msg)


# --------------------------------------------------------------------------------------------------
# arm poses: PoseStamped and TF, hand-eye, interpolation, tolerance
# --------------------------------------------------------------------------------------------------

# images at 0.1 s steps from t=0 to 1.0; arm samples at 100 Hz over [0.25, 0.75] with a gap (0.4, 0.6)
IMAGE_TIMES = np.round(np.arange(11) * 0.1 + 0.003, 6)
ARM_TIMES = [t for t in np.round(np.arange(25, 76) * 0.01, 6) if not 0.4 < t < 0.6]


# a static link -> tool edge after the dynamic base -> link edge, so the TF chain has two links
LINK_TOOL = make_transform(so3_exp([0.0, 0.0, 0.4]), [0.0, 0.1, 0.5])
T_WORLD_BASE = make_transform(np.eye(3), [1.0, 2.0, 3.0])
ARM_LABELLED = np.isin(np.arange(11), [3, 6, 7])


def true_base_tool(t: float, source: str = "tf") -> np.ndarray:
    """Arm poses are written where interpolation is exact: the pose topic carries ``tool_pose``,
    TF carries it on its one dynamic edge (base -> link)."""
    return tool_pose(t) @ LINK_TOOL if source == "tf" else tool_pose(t)


def write_arm_bag(path: Path, storage: str, source: str) -> None:
    with BagWriter(path, storage) as writer:
        for t in IMAGE_TIMES:
            writer.write_image("/cam", int(round(t * S)) + S, "cam", np.full((4, 6, 3), int(t * 100), np.uint8))
        if source == "tf":
            # a chain: world -> base (static), base -> link (dynamic), link -> tool (static)
            writer.write_tf("/tf_static", S, [("world", "base", T_WORLD_BASE), ("link", "tool", LINK_TOOL)])
        for t in ARM_TIMES:
            stamp = int(round(t * S)) + S
            if source == "pose":
                writer.write_pose("/arm/pose", stamp, "base", true_base_tool(t, "pose"))
            else:
                writer.write_tf("/tf", stamp, [("base", "link", tool_pose(t))])


@pytest.mark.parametrize("storage, source", [("mcap", "pose"), ("sqlite3", "tf"), ("ros1", "tf"), ("ros1", "pose")])
def test_arm_poses_interpolated_with_hand_eye(tmp_path, storage, source):
    path = tmp_path / ("arm.bag" if storage == "ros1" else "arm")
    write_arm_bag(path, storage, source)
    sequence = read_sequence(path, image_topic="/cam", pose_source="auto", tf_parent="base", tf_child="tool",
                             T_tool_cam=HAND_EYE, tolerance_s=0.02)
    assert sequence.extras["pose_source"] == ("topic /arm/pose" if source == "pose" else "tf base->tool")
    labelled = sequence.labelled
    # 0.303 lies between samples 0.30 and 0.31 (interpolated); 0.403 is 3 ms after the last sample
    # before the gap but 197 ms before the next: unlabelled; 0.203 and 0.803 are outside the arm's range.
    np.testing.assert_array_equal(labelled, ARM_LABELLED)
    for t, T in zip(IMAGE_TIMES[labelled], sequence.arm_poses[labelled]):
        np.testing.assert_allclose(T, true_base_tool(t, source) @ HAND_EYE, atol=1e-9)
    assert np.isnan(sequence.arm_poses[~labelled]).all()
    assert sequence.ground_truth is None and sequence.calibration is None


def test_tolerance_bounds_interpolation(tmp_path):
    path = tmp_path / "arm"
    write_arm_bag(path, "mcap", "pose")
    # an image 3 ms after one sample and 7 ms before the next needs both within the tolerance
    np.testing.assert_array_equal(read_sequence(path, image_topic="/cam", tolerance_s=0.008).labelled, ARM_LABELLED)
    assert not read_sequence(path, image_topic="/cam", tolerance_s=0.006).labelled.any()
    loose = read_sequence(path, image_topic="/cam", tolerance_s=0.25)
    # 0.403 and 0.503 are now bracketed by samples 0.40 and 0.60, 0.2 s apart
    np.testing.assert_array_equal(loose.labelled, np.isin(np.arange(11), [3, 4, 5, 6, 7]))
    np.testing.assert_allclose(loose.arm_poses[4], true_base_tool(0.403, "pose"), atol=1e-9)
    none = read_sequence(path, image_topic="/cam", pose_source="none")
    assert not none.labelled.any()


def test_tf_errors_name_the_frames(tmp_path):
    path = tmp_path / "arm"
    write_arm_bag(path, "mcap", "tf")
    with pytest.raises(BagError, match=r"does not connect 'base' to 'gripper'.*base->link"):
        read_sequence(path, image_topic="/cam", pose_source="tf", tf_child="gripper")
    with pytest.raises(BagError, match=r"no arm pose topic '/arm/pose'.*/tf \(tf2_msgs/msg/TFMessage\)"):
        read_sequence(path, image_topic="/cam", pose_source="pose")
    # a frame reached through a common ancestor: tool seen from world
    sequence = read_sequence(path, image_topic="/cam", pose_source="tf", tf_parent="world", tf_child="tool")
    np.testing.assert_allclose(sequence.arm_poses[3], T_WORLD_BASE @ true_base_tool(IMAGE_TIMES[3]), atol=1e-9)
    # and backwards up the tree: base seen from tool
    sequence = read_sequence(path, image_topic="/cam", pose_source="tf", tf_parent="tool", tf_child="base")
    np.testing.assert_allclose(sequence.arm_poses[6], invert_transform(true_base_tool(IMAGE_TIMES[6])), atol=1e-9)


# --------------------------------------------------------------------------------------------------
# bad input: one clear BagError naming the file
# --------------------------------------------------------------------------------------------------


def test_missing_path(tmp_path):
    missing = tmp_path / "nothing_here"
    with pytest.raises(BagError, match=f"{missing}: no such bag"):
        read_sequence(missing)
    with pytest.raises(BagError, match="no such bag"):
        next(iter_images(missing))


def test_not_a_bag(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    fake = tmp_path / "fake.bag"
    fake.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    for path in (text, empty_dir, fake):
        with pytest.raises(BagError, match=f"{path}: cannot read the bag"):
            read_sequence(path)


def test_truncated_mcap(tmp_path):
    path = write_sequence(make_sequence(8), tmp_path / "bag", storage="mcap")
    data_file = path / "bag.mcap"
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    with pytest.raises(BagError, match=f"{path}: cannot read the bag"):
        read_sequence(path)
    with pytest.raises(BagError, match="cannot read the bag"):
        list(iter_images(path))


def test_corrupt_sqlite3(tmp_path):
    path = write_sequence(make_sequence(8), tmp_path / "bag", storage="sqlite3")
    data_file = path / "bag.db3"
    raw = bytearray(data_file.read_bytes())
    raw[100:4096] = b"\xde\xad\xbe\xef" * ((4096 - 100) // 4)  # wreck the schema page
    data_file.write_bytes(bytes(raw))
    with pytest.raises(BagError, match=f"{path}: cannot read the bag"):
        read_sequence(path)


def test_missing_image_topic_lists_topics(tmp_path):
    path = write_sequence(make_sequence(3), tmp_path / "bag")
    with pytest.raises(BagError, match=r"no image topic '/camera/color'; topics in the bag: /arm/pose \(geometry_msgs/msg/PoseStamped\)"):
        read_sequence(path, image_topic="/camera/color")
    with pytest.raises(BagError, match="holds geometry_msgs/msg/PoseStamped, not sensor_msgs/Image"):
        read_sequence(path, image_topic="/arm/pose")


def test_unsupported_encoding_in_bag(tmp_path):
    path = tmp_path / "bag"
    with BagWriter(path) as writer:
        msg = writer.types["sensor_msgs/msg/Image"](header=writer.header(S, "cam"), height=2, width=2, encoding="yuv422",
                                                    is_bigendian=0, step=4, data=np.zeros(8, np.uint8))
        writer.write_message("/camera/image_raw", S, msg)
    with pytest.raises(BagError, match=rf"{path}: /camera/image_raw message 0 .*unsupported image encoding 'yuv422'; supported: rgb8, bgr8"):
        read_sequence(path)


def test_no_frames(tmp_path):
    path = tmp_path / "bag"
    with BagWriter(path) as writer:
        writer.declare_topic("/camera/image_raw", "sensor_msgs/msg/Image")
        writer.write_pose("/arm/pose", S, "base", np.eye(4))
    with pytest.raises(BagError, match=f"{path}: no usable frames"):
        read_sequence(path)
    with pytest.raises(BagError, match="has no messages"):
        list(iter_images(path))


def test_image_size_change(tmp_path):
    path = tmp_path / "bag"
    with BagWriter(path) as writer:
        writer.write_image("/camera/image_raw", S, "cam", np.zeros((H, W, 3), np.uint8))
        writer.write_image("/camera/image_raw", 2 * S, "cam", np.zeros((H, W + 2, 3), np.uint8))
    with pytest.raises(BagError, match=f"{path}: image size changes mid-bag .* message 1 .* is 18x12, earlier images are 16x12"):
        read_sequence(path)


def test_uncalibrated_camera_info_is_unknown_not_fatal(tmp_path):
    """Uncalibrated drivers publish K = 0; that is what nocal is for, so the bag still reads."""
    path = tmp_path / "bag"
    with BagWriter(path) as writer:
        writer.write_image("/camera/image_raw", S, "cam", np.zeros((H, W, 3), np.uint8))
        zeros = type("Cal", (), {"width": W, "height": H, "K": np.zeros((3, 3)), "D": np.zeros(5), "distortion_model": "plumb_bob"})
        writer.write_camera_info("/ground_truth/camera_info", S, "cam", zeros)
    sequence = read_sequence(path)
    assert sequence.calibration is None
    assert "positive focal" in sequence.extras["camera_info_problem"]


# --------------------------------------------------------------------------------------------------
# odds and ends of real recordings
# --------------------------------------------------------------------------------------------------


def test_out_of_order_and_repeated_stamps_are_sorted_and_dropped(tmp_path):
    """Header stamps (sensor time) order the frames, not receive times; a repeated stamp keeps its first frame."""
    path = tmp_path / "bag"
    with BagWriter(path) as writer:
        for k, stamp in enumerate([3, 1, 2, 2]):
            msg = writer.types["sensor_msgs/msg/Image"](
                header=writer.header(stamp * S, "cam"), height=H, width=W, encoding="mono8", is_bigendian=0,
                step=W, data=np.full(H * W, 10 * k, np.uint8))
            writer.write_message("/camera/image_raw", (k + 1) * S, msg)
    sequence = read_sequence(path)
    np.testing.assert_array_equal(sequence.stamps_ns, [S, 2 * S, 3 * S])
    np.testing.assert_array_equal(sequence.images[:, 0, 0, 0], [10, 20, 0])
    assert sequence.extras["dropped_repeated_stamps"] == 1


def test_read_poses_of_other_pose_types(tmp_path):
    path = tmp_path / "bag"
    T0, T1 = tool_pose(0.0), tool_pose(0.01)
    with BagWriter(path, "sqlite3") as writer:
        t = writer.types

        def pose(T):
            x, y, z, w = matrix_to_quaternion(T[:3, :3])
            return t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                               orientation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))

        for stamp, T in ((S, T0), (S + 10_000_000, T1)):
            transform = t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=pose(T).orientation)
            writer.write_message("/tracker", stamp, t["geometry_msgs/msg/TransformStamped"](
                header=writer.header(stamp, "world"), child_frame_id="cam", transform=transform))
            writer.write_message("/amcl", stamp, t["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=writer.header(stamp, "map"),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose(T), covariance=np.zeros(36))))
    stamps = [S, S + 5_000_000, S + 20_000_000]
    for topic in ("/tracker", "/amcl"):
        poses = bags.read_poses(path, topic, stamps, tolerance_s=0.02)
        np.testing.assert_allclose(poses[0], T0, atol=1e-12)
        np.testing.assert_allclose(poses[1], tool_pose(0.005), atol=1e-9)
        assert np.isnan(poses[2]).all()  # after the last sample: no extrapolation
    with pytest.raises(BagError, match="no pose topic '/gps'"):
        bags.read_poses(path, "/gps", stamps)


def test_decoder_takes_rclpy_style_messages():
    """rclpy gives ``data`` as array.array (Image) and plain attributes; the one decoder serves both."""
    from array import array
    from types import SimpleNamespace

    msg = SimpleNamespace(height=5, width=7, encoding="bgr8", is_bigendian=0, step=21,
                          data=array("B", RGB[:, :, ::-1].tobytes()))
    np.testing.assert_array_equal(decode_image(msg), RGB)
    ok, png = cv2.imencode(".png", cv2.cvtColor(RGB, cv2.COLOR_RGB2BGR))
    np.testing.assert_array_equal(decode_compressed_image(SimpleNamespace(format="png", data=png.tobytes())), RGB)


def test_camera_info_keeps_the_projection_and_rectification(tmp_path):
    from nocal_ros.data.bags import read_camera_info

    R = np.array([[0.9998, -0.0175, 0.0], [0.0175, 0.9998, 0.0], [0.0, 0.0, 1.0]])
    P = np.array([[600.0, 0, 320.0, -42.0], [0, 600.0, 240.0, 0.0], [0, 0, 1.0, 0.0]])
    written = CameraCalibration(640, 480, [[590.0, 0, 321.0], [0, 591.0, 239.0], [0, 0, 1]], [0.1, -0.2, 0, 0, 0],
                                camera_name="camera_optical", R=R, P=P)
    for storage, name in (("mcap", "bag"), ("ros1", "bag.bag")):
        path = tmp_path / name
        with BagWriter(path, storage) as writer:
            writer.write_camera_info("/camera_info", S, "camera_optical", written)
        assert read_camera_info(path, "/camera_info") == written


def test_bytes_written_counts_what_lands_in_the_bag(tmp_path):
    path = tmp_path / "sized.mcap"
    rng = np.random.default_rng(0)
    with BagWriter(path) as writer:
        for k in range(20):  # random pixels: mcap's chunk compression cannot shrink them
            writer.write_image("/camera/image_raw", S + k, "cam", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
        counted = writer.bytes_written
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size
    assert counted >= 20 * 48 * 64 * 3
    assert counted <= size <= counted + 20_000  # the index, schema and metadata are small
