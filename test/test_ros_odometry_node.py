"""The rclpy odometry node, with real rclpy: start it, publish a short rendered sequence, receive
Odometry, CameraInfo and TF with the right frames and stamps, read /diagnostics, call both services.

Skipped where rclpy cannot be imported (no ROS 2 installation); run on ROS 2 Jazzy.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy is not installed (no ROS 2 here); run these tests on ROS 2 Jazzy")
pytest.importorskip("tf2_ros", reason="tf2_ros is not installed (no ROS 2 here); run these tests on ROS 2 Jazzy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402
from tf2_ros import StaticTransformBroadcaster  # noqa: E402

from nocal_ros.camera import CameraModel  # noqa: E402
from nocal_ros.checkpoint import save_checkpoint  # noqa: E402
from nocal_ros.data.synthetic import render_sequence  # noqa: E402
from nocal_ros.geometry import invert_transform, make_transform, quaternion_to_matrix, so3_exp  # noqa: E402
from nocal_ros.lens import CameraCalibration  # noqa: E402
from nocal_ros.model import NOCaL  # noqa: E402
from nocal_ros.ros.conversions import ns_to_stamp, stamp_to_ns, transform_stamped  # noqa: E402
from nocal_ros.ros.odometry_node import OdometryNode  # noqa: E402

WIDTH, HEIGHT = 80, 60
START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000
T_BASE_CAM = make_transform(so3_exp(np.array([-np.pi / 2, 0.0, -np.pi / 2]) * 0.7), np.array([0.2, 0.0, 0.5]))


def wait_for(condition, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def pose_of(msg) -> np.ndarray:
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return make_transform(quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([p.x, p.y, p.z]))


class Harness(Node):
    """Publishes images and the static mounting; records what the odometry node publishes."""

    def __init__(self, context) -> None:
        super().__init__("odometry_test_harness", context=context)
        self.images = self.create_publisher(Image, "image", qos_profile_sensor_data)
        self.odometry: list[Odometry] = []
        self.camera_info: list[CameraInfo] = []
        self.tf: list = []
        self.diagnostics: list[DiagnosticArray] = []
        self.create_subscription(Odometry, "odom", lambda m: self.odometry.append(m), 50)
        self.create_subscription(CameraInfo, "camera_info", lambda m: self.camera_info.append(m), 50)
        self.create_subscription(TFMessage, "/tf", lambda m: self.tf.extend(m.transforms), 50)
        self.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self.diagnostics.append(m), 10)
        self.static = StaticTransformBroadcaster(self)
        self.static.sendTransform(transform_stamped(T_BASE_CAM, ns_to_stamp(START_NS), "base_link", "camera_optical"))

    def publish(self, image: np.ndarray, stamp_ns: int) -> None:
        msg = Image()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.header.frame_id = "camera_optical"
        msg.height, msg.width = image.shape[:2]
        msg.encoding = "rgb8"
        msg.step = image.shape[1] * 3
        msg.data = image.tobytes()
        self.images.publish(msg)

    def call(self, service: str, timeout: float = 30.0) -> Trigger.Response:
        client = self.create_client(Trigger, service)
        assert client.wait_for_service(timeout_sec=10.0), f"{service} not available"
        future = client.call_async(Trigger.Request())
        assert wait_for(future.done, timeout), f"{service} did not answer"
        return future.result()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    small = {"encoder_channels": [8] * 7, "latent_dim": 16, "scene_width": 16, "pose_width": 16,
             "hyper_width": 16, "hyper_rank": 4, "lfn_width": 16}
    path = tmp_path_factory.mktemp("model") / "model.safetensors"
    return save_checkpoint(path, NOCaL(small), [CameraModel(WIDTH, HEIGHT)], metadata={"training_resolution": [40, 30]})


@pytest.fixture(scope="module")
def frames():
    camera = CameraCalibration.pinhole(WIDTH, HEIGHT, 60.0)
    return render_sequence(camera, 8, seed=3, split="test").images


@pytest.fixture
def running(checkpoint):
    context = Context()
    rclpy.init(context=context)
    node = OdometryNode(
        context=context,
        parameter_overrides=[
            Parameter("model_path", value=str(checkpoint)),
            Parameter("device", value="cpu"),
            # The network path alone, so the expected pose below can be computed from the network;
            # two-view geometry has its own tests (test_two_view.py).
            Parameter("two_view", value=False),
            Parameter("base_frame", value="base_link"),
            Parameter("tf_timeout", value=1.0),
            Parameter("diagnostics_period", value=0.2),
        ],
    )
    harness = Harness(context)
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    executor.add_node(node)
    executor.add_node(harness)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    # Wait for the image subscription to match, or the first frames are lost to discovery.
    assert wait_for(lambda: harness.images.get_subscription_count() > 0)
    yield node, harness
    executor.shutdown()
    node.destroy_node()
    harness.destroy_node()
    rclpy.shutdown(context=context)
    spinner.join(timeout=5)


def publish_sequence(harness, frames, start_ns=START_NS) -> list[int]:
    stamps = []
    for k, image in enumerate(frames):
        stamp = start_ns + k * PERIOD_NS
        harness.publish(image, stamp)
        stamps.append(stamp)
        count = len(harness.odometry)
        wait_for(lambda: len(harness.odometry) > count, timeout=5.0)  # one frame at a time: none dropped
    return stamps


def test_node_publishes_odometry_camera_info_and_tf_with_the_image_stamps(running, frames):
    node, harness = running
    stamps = publish_sequence(harness, frames)
    assert wait_for(lambda: len(harness.odometry) == len(stamps) and len(harness.camera_info) >= len(stamps))

    assert [stamp_to_ns(m.header.stamp) for m in harness.odometry] == stamps
    assert {(m.header.frame_id, m.child_frame_id) for m in harness.odometry} == {("odom", "base_link")}
    np.testing.assert_allclose(pose_of(harness.odometry[0]), np.eye(4), atol=1e-9)
    for msg in harness.odometry:
        covariance = np.asarray(msg.pose.covariance).reshape(6, 6)
        assert np.allclose(covariance, covariance.T) and np.isfinite(covariance).all()

    info_stamps = [stamp_to_ns(m.header.stamp) for m in harness.camera_info]
    assert info_stamps == stamps and {m.header.frame_id for m in harness.camera_info} == {"camera_optical"}
    info = harness.camera_info[0]
    assert (info.width, info.height) == (WIDTH, HEIGHT) and info.distortion_model == "plumb_bob"
    assert info.k[0] == pytest.approx(WIDTH)  # the untrained camera's focal length: f = width

    assert wait_for(lambda: len([t for t in harness.tf if t.child_frame_id == "base_link"]) == len(stamps))
    edges = [t for t in harness.tf if t.child_frame_id == "base_link"]
    assert {t.header.frame_id for t in edges} == {"odom"}
    assert [stamp_to_ns(t.header.stamp) for t in edges] == stamps

    # The network's camera motion on the resized frames, moved to the base frame through the static
    # TF mounting, computed here independently of the estimator.
    assert np.allclose(node.estimator.T_base_cam, T_BASE_CAM, atol=1e-6)
    assert node.estimator.two_view is False  # the parameter reached the estimator
    T_cam = np.eye(4)
    for k in range(len(frames) - 1):
        T_cam = T_cam @ predict(node.estimator.model.module, frames[k], frames[k + 1])
    expected = T_BASE_CAM @ T_cam @ invert_transform(T_BASE_CAM)
    np.testing.assert_allclose(pose_of(harness.odometry[-1]), expected, atol=1e-5)


def predict(network, image_i, image_j) -> np.ndarray:
    import cv2
    import torch

    def tensor(image):
        small = cv2.resize(image, (40, 30), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(small).permute(2, 0, 1)[None].float() / 255.0

    with torch.no_grad():
        return network.predict_pose(tensor(image_i), tensor(image_j))[0].double().numpy()


def test_diagnostics_report_latency_rate_drops_and_model(running, frames):
    node, harness = running
    publish_sequence(harness, frames[:4])
    assert wait_for(lambda: any(
        {kv.key: kv.value for kv in s.values}.get("frames_received") == "4"
        for array in harness.diagnostics for s in array.status))
    status = harness.diagnostics[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert values["model_id"].startswith("model.safetensors@")
    for key in ("latency_ms_median", "rate_hz", "frames_dropped_stale", "estimator_nonfinite_skipped"):
        assert key in values
    assert float(values["latency_ms_median"]) > 0


def test_reset_and_reload_model_services(running, frames, tmp_path):
    node, harness = running
    publish_sequence(harness, frames[:4])
    response = harness.call("/odometry_node/reset")
    assert response.success
    count = len(harness.odometry)
    publish_sequence(harness, frames[4:6], start_ns=START_NS + 10 * PERIOD_NS)
    assert wait_for(lambda: len(harness.odometry) >= count + 2)
    np.testing.assert_allclose(pose_of(harness.odometry[count]), np.eye(4), atol=1e-9)

    response = harness.call("/odometry_node/reload_model")
    assert response.success and "model.safetensors@" in response.message

    # A bad model file: the service says why, and the running model keeps working.
    missing = tmp_path / "missing.safetensors"
    node.set_parameters([Parameter("model_path", value=str(missing))])
    response = harness.call("/odometry_node/reload_model")
    assert not response.success and str(missing) in response.message
    count = len(harness.odometry)
    publish_sequence(harness, frames[6:8], start_ns=START_NS + 20 * PERIOD_NS)
    assert wait_for(lambda: len(harness.odometry) >= count + 2)


def test_a_flood_of_frames_is_dropped_not_queued(running, frames):
    node, harness = running
    for k in range(60):  # far faster than inference: the node must keep only the newest
        harness.publish(frames[k % len(frames)], START_NS + k * PERIOD_NS)
    last = START_NS + 59 * PERIOD_NS
    assert wait_for(lambda: harness.odometry and stamp_to_ns(harness.odometry[-1].header.stamp) == last, timeout=20)
    # Every received frame was either processed or dropped as stale, never queued behind inference.
    values = node.diagnostics()
    assert values["frames_received"] == values["frames_dropped_stale"] + node.estimator.counters.frames
