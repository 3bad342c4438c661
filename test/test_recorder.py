"""LiveRecorder: real bags written with rosbags, read back by the fine-tuning job's own reader.

Images come in as message objects with the ``sensor_msgs`` fields (what rclpy hands a callback), arm
poses as matrices; the bag is read with ``nocal_ros.data.bags.read_sequence`` exactly as ``~/start``
reads it.
"""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from nocal_ros.data.bags import read_sequence
from nocal_ros.errors import BagError, NocalError
from nocal_ros.geometry import make_transform, so3_exp
from nocal_ros.live.recorder import LiveRecorder, RecordingLimits

START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000
W, H = 32, 24
HAND_EYE = make_transform(so3_exp(np.array([0.2, -0.1, 0.3])), np.array([0.01, 0.02, 0.05]))


def stamp(ns: int) -> SimpleNamespace:
    return SimpleNamespace(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def image_msg(image: np.ndarray, stamp_ns: int, encoding: str = "rgb8") -> SimpleNamespace:
    pixels = image if encoding == "rgb8" else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    channels = 1 if pixels.ndim == 2 else 3
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp(stamp_ns), frame_id="camera_optical"),
                           height=image.shape[0], width=image.shape[1], encoding=encoding, is_bigendian=0,
                           step=image.shape[1] * channels, data=pixels.tobytes())


def compressed_msg(image: np.ndarray, stamp_ns: int) -> SimpleNamespace:
    ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    assert ok
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp(stamp_ns), frame_id="camera_optical"),
                           format="rgb8; png compressed bgr8", data=png.tobytes())


def frames(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


def arm_pose(k: int) -> np.ndarray:
    return make_transform(so3_exp(np.array([0.0, 0.02 * k, 0.01 * k])), np.array([0.3 + 0.01 * k, 0.0, 0.5]))


def recorder(path, limits=RecordingLimits(), start_ns=START_NS) -> LiveRecorder:
    return LiveRecorder(path, "/camera/image_raw", "/arm/pose", limits, start_ns, tf_parent="base", tf_child="tool")


def test_a_recording_reads_back_as_the_fine_tune_reads_it(tmp_path):
    images = frames(6)
    rec = recorder(tmp_path / "rec")
    for k, image in enumerate(images):
        t = START_NS + k * PERIOD_NS
        assert rec.add_image(image_msg(image, t), now_ns=t)
        assert rec.add_pose(t, "base", arm_pose(k), now_ns=t)
    summary = rec.stop(START_NS + 6 * PERIOD_NS)
    assert summary.path == str(tmp_path / "rec") and summary.stopped_by == "request"
    assert (summary.frames, summary.arm_poses, summary.rejected) == (6, 6, 0)
    assert summary.duration_s == pytest.approx(0.6) and summary.bytes >= 6 * W * H * 3
    assert not rec.active and not rec.add_image(image_msg(images[0], START_NS + 10 * PERIOD_NS), START_NS)

    sequence = read_sequence(summary.path, "/camera/image_raw", "/arm/pose", T_tool_cam=HAND_EYE)
    np.testing.assert_array_equal(sequence.images, np.stack(images))
    assert sequence.stamps_ns.tolist() == [START_NS + k * PERIOD_NS for k in range(6)]
    assert sequence.labelled.all()
    for k in range(6):  # the job applies the hand-eye transform to what was recorded
        np.testing.assert_allclose(sequence.arm_poses[k], arm_pose(k) @ HAND_EYE, atol=1e-12)


def test_tf_arm_poses_are_recorded_as_the_tf_edge(tmp_path):
    rec = recorder(tmp_path / "rec_tf")
    for k, image in enumerate(frames(4, seed=1)):
        t = START_NS + k * PERIOD_NS
        rec.add_image(image_msg(image, t), now_ns=t)
        if k != 2:  # one frame's TF never came: that frame is unlabelled
            rec.add_tf(t, arm_pose(k), now_ns=t)
    summary = rec.stop()
    sequence = read_sequence(summary.path, pose_source="tf", tf_parent="base", tf_child="tool")
    assert sequence.labelled.tolist() == [True, True, False, True]
    np.testing.assert_allclose(sequence.arm_poses[3], arm_pose(3), atol=1e-12)
    assert sequence.extras["pose_source"] == "tf base->tool"


def test_mono_and_compressed_frames_are_kept_as_they_came(tmp_path):
    images = frames(3, seed=2)
    rec = recorder(tmp_path / "mono")
    for k, image in enumerate(images):
        rec.add_image(image_msg(image, START_NS + k * PERIOD_NS, "mono8"), now_ns=START_NS)
    sequence = read_sequence(rec.stop().path)
    gray = [cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) for image in images]
    np.testing.assert_array_equal(sequence.images, np.stack([np.repeat(g[:, :, None], 3, axis=2) for g in gray]))

    rec = recorder(tmp_path / "png")
    for k, image in enumerate(images):
        rec.add_image(compressed_msg(image, START_NS + k * PERIOD_NS), now_ns=START_NS)
    np.testing.assert_array_equal(read_sequence(rec.stop().path).images, np.stack(images))  # png is lossless


def test_the_size_limit_is_never_exceeded(tmp_path):
    images = frames(10, seed=3)
    frame_bytes = W * H * 3
    limits = RecordingLimits(max_bytes=3 * frame_bytes + 3 * 200, max_duration_s=60.0)
    rec = recorder(tmp_path / "sized", limits)
    written = [rec.add_image(image_msg(image, START_NS + k * PERIOD_NS), now_ns=START_NS) for k, image in enumerate(images)]
    assert written == [True, True, True] + [False] * 7
    summary = rec.summary
    assert summary is not None and summary.stopped_by == "max_bytes" and summary.frames == 3
    assert summary.bytes <= limits.max_bytes
    files = [f for f in (tmp_path / "sized").rglob("*") if f.is_file()]
    assert sum(f.stat().st_size for f in files) <= limits.max_bytes + 20_000  # mcap index and metadata
    np.testing.assert_array_equal(read_sequence(summary.path).images, np.stack(images[:3]))
    assert rec.stop() is summary  # stopping again reports how it ended


def test_the_duration_limit_stops_on_the_clock_even_without_frames(tmp_path):
    rec = recorder(tmp_path / "timed", RecordingLimits(max_duration_s=1.0), start_ns=0)
    assert rec.add_image(image_msg(frames(1)[0], START_NS), now_ns=400_000_000)
    assert rec.check(999_999_999) is None and rec.active
    summary = rec.check(1_000_000_000)  # a timer's tick: the camera may have gone quiet
    assert summary.stopped_by == "max_duration" and summary.frames == 1 and summary.duration_s == pytest.approx(1.0)
    assert len(read_sequence(summary.path)) == 1
    # A frame arriving after the limit ends a recording the timer has not yet stopped.
    late = recorder(tmp_path / "late", RecordingLimits(max_duration_s=1.0), start_ns=0)
    late.add_image(image_msg(frames(1)[0], START_NS), now_ns=0)
    assert not late.add_image(image_msg(frames(1)[0], START_NS + PERIOD_NS), now_ns=2_000_000_000)
    assert late.summary.stopped_by == "max_duration" and late.summary.frames == 1


def test_unreadable_frames_are_skipped_and_counted(tmp_path):
    images = frames(3, seed=4)
    rec = recorder(tmp_path / "mixed")
    assert rec.add_image(image_msg(images[0], START_NS), now_ns=START_NS)
    bayer = image_msg(images[1], START_NS + PERIOD_NS)
    bayer.encoding = "bayer_rggb8"
    assert not rec.add_image(bayer, now_ns=START_NS)
    bigger = image_msg(cv2.resize(images[1], (W * 2, H * 2)), START_NS + PERIOD_NS)
    assert not rec.add_image(bigger, now_ns=START_NS)  # the job refuses a size change mid-bag
    truncated = image_msg(images[2], START_NS + 2 * PERIOD_NS)
    truncated.data = truncated.data[:-5]
    assert not rec.add_image(truncated, now_ns=START_NS)
    assert rec.add_image(image_msg(images[2], START_NS + 2 * PERIOD_NS), now_ns=START_NS)
    summary = rec.stop()
    assert summary.frames == 2 and summary.rejected == 3
    assert "bayer_rggb8" in summary.problems[0] and "size changed from 32x24 to 64x48" in summary.problems[1]
    np.testing.assert_array_equal(read_sequence(summary.path).images, np.stack([images[0], images[2]]))


def test_a_recording_without_images_leaves_nothing_and_an_existing_bag_is_kept(tmp_path):
    rec = recorder(tmp_path / "empty")
    rec.add_pose(START_NS, "base", arm_pose(0), now_ns=START_NS)
    summary = rec.stop()
    assert summary.path is None and summary.frames == 0 and summary.arm_poses == 1
    assert list(tmp_path.iterdir()) == []  # neither the bag nor its staging directory
    done = recorder(tmp_path / "done")
    done.add_image(image_msg(frames(1)[0], START_NS), now_ns=START_NS)
    done.stop()
    with pytest.raises(BagError, match="already exists"):
        recorder(tmp_path / "done")
    with pytest.raises(NocalError, match="must be positive"):
        RecordingLimits(max_bytes=0)
