"""The rclpy odometry node, with real rclpy: start it, publish a short rendered sequence, receive
Odometry, CameraInfo and TF with the right frames and stamps, read /diagnostics, call its services,
set and store a calibration as camera_info_manager does, feed it arm poses, and drive it by a /clock
this test publishes (sim time, including a jump back).

Every wait is on a condition (a message arrived, the node's clock reached a value); nothing sleeps to
synchronise. Skipped where rclpy cannot be imported (no ROS 2 installation); run on ROS 2 Jazzy.
"""

from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy is not installed (no ROS 2 here); run these tests on ROS 2 Jazzy")
pytest.importorskip("tf2_ros", reason="tf2_ros is not installed (no ROS 2 here); run these tests on ROS 2 Jazzy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from nav_msgs.msg import Odometry, Path  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from rclpy.time import Time  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from sensor_msgs.srv import SetCameraInfo  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402
from tf2_ros import StaticTransformBroadcaster, TransformBroadcaster  # noqa: E402

from nocal_ros.camera import CameraModel  # noqa: E402
from nocal_ros.checkpoint import save_checkpoint  # noqa: E402
from nocal_ros.data.synthetic import render_sequence  # noqa: E402
from nocal_ros.errors import ConfigError  # noqa: E402
from nocal_ros.geometry import invert_transform, make_transform, quaternion_to_matrix, so3_exp  # noqa: E402
from nocal_ros.lens import CameraCalibration  # noqa: E402
from nocal_ros.model import NOCaL  # noqa: E402
from nocal_ros.ros.conversions import matrix_to_pose, ns_to_stamp, stamp_to_ns, transform_stamped  # noqa: E402
from nocal_ros.ros.odometry_node import OdometryNode  # noqa: E402
from ros_spin import Spinner, call, wait_for  # noqa: E402

WIDTH, HEIGHT = 80, 60
START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000
T_BASE_CAM = make_transform(so3_exp(np.array([-np.pi / 2, 0.0, -np.pi / 2]) * 0.7), np.array([0.2, 0.0, 0.5]))
T_TOOL_CAM = make_transform(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([0.02, 0.0, 0.05]))


def pose_of(msg) -> np.ndarray:
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return make_transform(quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([p.x, p.y, p.z]))


def arm_pose(k: int) -> np.ndarray:
    """``T_base_tool`` of an arm moving a little between frames."""
    return make_transform(so3_exp(np.array([0.0, 0.05 * k, 0.02 * k])), np.array([0.4 + 0.01 * k, 0.1, 0.3]))


def statuses(harness) -> list[DiagnosticStatus]:
    return [status for array in harness.diagnostics for status in array.status]


def values_of(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


class Harness(Node):
    """Publishes images, the static mounting, arm poses and /clock; records what the odometry node publishes."""

    def __init__(self, context) -> None:
        super().__init__("odometry_test_harness", context=context)
        self.images = self.create_publisher(Image, "image", qos_profile_sensor_data)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10)
        self.arm = self.create_publisher(PoseStamped, "arm_pose", 10)
        self.odometry: list[Odometry] = []
        self.camera_info: list[CameraInfo] = []
        self.tf: list = []
        self.diagnostics: list[DiagnosticArray] = []
        self.paths: list[Path] = []
        self.clouds: list[PointCloud2] = []
        self.create_subscription(Odometry, "odom", self.odometry.append, 50)
        self.create_subscription(Path, "keyframe_path", self.paths.append, 10)
        self.create_subscription(PointCloud2, "map_points", self.clouds.append, 10)
        self.create_subscription(CameraInfo, "camera_info", self.camera_info.append, 50)
        self.create_subscription(TFMessage, "/tf", lambda m: self.tf.extend(m.transforms), 50)
        self.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 50)
        self.static = StaticTransformBroadcaster(self)
        self.static.sendTransform(transform_stamped(T_BASE_CAM, ns_to_stamp(START_NS), "base_link", "camera_optical"))
        self.broadcaster = TransformBroadcaster(self)

    def publish(self, image: np.ndarray, stamp_ns: int) -> None:
        msg = Image()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.header.frame_id = "camera_optical"
        msg.height, msg.width = image.shape[:2]
        msg.encoding = "rgb8"
        msg.step = image.shape[1] * 3
        msg.data = image.tobytes()
        self.images.publish(msg)


def publish_sequence(harness, frames, start_ns=START_NS) -> list[int]:
    stamps = []
    for k, image in enumerate(frames):
        stamp = start_ns + k * PERIOD_NS
        count = len(harness.odometry)
        harness.publish(image, stamp)
        stamps.append(stamp)
        assert wait_for(lambda: len(harness.odometry) > count, timeout=10.0)  # one frame at a time: none dropped
    return stamps


def set_clock(harness, node, t_ns: int) -> None:
    """Publish /clock until the node's clock reads ``t_ns`` (its /clock subscription keeps one, best effort)."""
    def reached() -> bool:
        harness.clock_pub.publish(Clock(clock=ns_to_stamp(t_ns)))
        return node.get_clock().now().nanoseconds == t_ns

    assert wait_for(reached, timeout=10.0), f"the node's clock never reached {t_ns}"


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
def ros(checkpoint, tmp_path):
    """``launch(**parameters)`` starts an odometry node and a harness on a fresh context and returns both;
    after the test every spinner is joined before its nodes are destroyed, then the context shuts down."""
    context = Context()
    rclpy.init(context=context)
    spinners = []

    def launch(**overrides):
        parameters = {
            "model_path": str(checkpoint),
            "device": "cpu",
            # The network path alone, so the expected pose below can be computed from the network;
            # the keyframe VO has its own tests (test_vo.py).
            "method": "pose_head",
            "base_frame": "base_link",
            "tf_timeout": 1.0,
            "diagnostics_period": 0.2,
            # Never ~/.ros: a calibration someone saved there must not leak into a test.
            "camera_info_url": f"file://{tmp_path}/camera_info/${{NAME}}.yaml",
            **overrides,
        }
        node = OdometryNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()])
        harness = Harness(context)
        spinners.append(Spinner(context, node, harness))
        # Wait until each publisher has matched its subscriber both ways, or the first messages are lost
        # to discovery (the node's TF broadcaster counts the harness's and the node's own /tf listeners).
        assert wait_for(lambda: harness.images.get_subscription_count() > 0
                        and node.subscription.get_publisher_count() > 0
                        and node.odom_publisher.get_subscription_count() > 0
                        and node.camera_info_publisher.get_subscription_count() > 0
                        and node.diagnostics_publisher.get_subscription_count() > 0
                        and node.tf_broadcaster.pub_tf.get_subscription_count() >= 2
                        and harness.broadcaster.pub_tf.get_subscription_count() >= 2)
        return node, harness

    yield launch
    for spinner in spinners:
        spinner.shutdown()
    rclpy.try_shutdown(context=context)


def test_node_publishes_odometry_camera_info_and_tf_with_the_image_stamps(ros, frames):
    node, harness = ros()
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
    np.testing.assert_array_equal(np.asarray(info.r).reshape(3, 3), np.eye(3))
    np.testing.assert_array_equal(np.asarray(info.p).reshape(3, 4), np.hstack((np.asarray(info.k).reshape(3, 3), np.zeros((3, 1)))))
    assert (info.binning_x, info.binning_y, info.roi.width, info.roi.height) == (0, 0, 0, 0)

    assert wait_for(lambda: len([t for t in harness.tf if t.child_frame_id == "base_link"]) == len(stamps))
    edges = [t for t in harness.tf if t.child_frame_id == "base_link"]
    assert {t.header.frame_id for t in edges} == {"odom"}
    assert [stamp_to_ns(t.header.stamp) for t in edges] == stamps
    # map -> odom in the same messages, at the same stamps: the identity for the pose head alone (no map)
    corrections = [t for t in harness.tf if t.child_frame_id == "odom"]
    assert {t.header.frame_id for t in corrections} == {"map"} and [stamp_to_ns(t.header.stamp) for t in corrections] == stamps
    assert all(t.transform.rotation.w == 1.0 and t.transform.translation.x == t.transform.translation.z == 0.0
               for t in corrections)

    # The network's camera motion on the resized frames, moved to the base frame through the static
    # TF mounting, computed here independently of the estimator.
    assert np.allclose(node.estimator.T_base_cam, T_BASE_CAM, atol=1e-6)
    assert node.estimator.method == "pose_head"  # the parameter reached the estimator
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


def test_the_vo_publishes_its_keyframe_path_and_map_points_in_odom(ros):
    """method vo with the shipped model on a rendered room: ``keyframe_path`` holds the keyframes (stamps of
    published images, increasing) in odom, the newest where /odom was at its stamp once the map stands
    still, and ``map_points`` the landmarks, read back by sensor_msgs_py (the independent reader)."""
    point_cloud2 = pytest.importorskip("sensor_msgs_py.point_cloud2", reason="sensor_msgs_py is not installed")
    camera = CameraCalibration.pinhole(160, 120, 118.0)
    sequence = render_sequence(camera, 30, seed=7, split="test")
    node, harness = ros(method="vo", model_path="", map_period=0.2)
    stamps = publish_sequence(harness, sequence.images)
    assert wait_for(lambda: node.estimator.wait_for_mapping(0.1) and node.estimator.map_snapshot().map_id > 0, timeout=30.0)
    snapshot = node.estimator.map_snapshot()
    paths, clouds = len(harness.paths), len(harness.clouds)  # the next messages are made after the snapshot
    assert wait_for(lambda: len(harness.paths) > paths + 1 and len(harness.clouds) > clouds + 1, timeout=10.0)
    path, cloud = harness.paths[-1], harness.clouds[-1]
    assert path.header.frame_id == "odom" and cloud.header.frame_id == "odom"
    path_stamps = [stamp_to_ns(pose.header.stamp) for pose in path.poses]
    assert len(path_stamps) == len(snapshot.stamps_ns) >= 3 and set(path_stamps) <= set(stamps)
    assert path_stamps == sorted(set(path_stamps)) and stamp_to_ns(path.header.stamp) == path_stamps[-1]
    published = {stamp_to_ns(m.header.stamp): pose_of(m) for m in harness.odometry}
    newest = path.poses[-1].pose
    T_newest = make_transform(quaternion_to_matrix(np.array([newest.orientation.x, newest.orientation.y, newest.orientation.z,
                                                             newest.orientation.w])),
                              np.array([newest.position.x, newest.position.y, newest.position.z]))
    np.testing.assert_allclose(T_newest, published[path_stamps[-1]], atol=1e-6)
    points = point_cloud2.read_points_numpy(cloud, field_names=("x", "y", "z"))
    assert points.shape == (len(snapshot.points), 3) and len(points) > 20
    np.testing.assert_allclose(points, snapshot.points, atol=1e-4)
    # map -> odom at every published frame's stamp, as the estimator gave it with that frame's pose
    corrections = {stamp_to_ns(t.header.stamp): t for t in harness.tf if t.child_frame_id == "odom"}
    assert set(corrections) == set(published) and {t.header.frame_id for t in corrections.values()} == {"map"}
    moved = [np.linalg.norm([t.transform.translation.x, t.transform.translation.y, t.transform.translation.z])
             for t in corrections.values()]
    assert np.isfinite(moved).all() and max(moved) > 0  # the map corrected odom somewhere


def test_diagnostics_report_latency_rate_drops_model_and_calibration(ros, frames):
    node, harness = ros()
    publish_sequence(harness, frames[:4])
    assert wait_for(lambda: any(values_of(s).get("frames_received") == "4" for s in statuses(harness)))
    status = next(s for s in statuses(harness) if values_of(s).get("frames_received") == "4")
    values = values_of(status)
    assert values["model_id"].startswith("model.safetensors@")
    for key in ("latency_ms_median", "rate_hz", "delay_s_median", "odometry_age_s", "frames_dropped_stale",
                "estimator_nonfinite_skipped", "tracking_ms_median", "bundle_adjustment_ms_median",
                "mapping_keyframes_merged", "mapping_failed_windows", "mapping_solver_restarts",
                "map_correction_m", "map_correction_deg"):
        assert key in values
    assert values["mapping_solver_restarts"] == "0"
    assert float(values["latency_ms_median"]) > 0
    # The calibration status issue 11 asks for, and where the camera comes from.
    assert (values["calibration_state"], values["calibration_source"]) == ("prior", "model")
    assert values["tracking"] == "ok" and values["scale_source"] == "pose_head"
    assert float(values["map_correction_m"]) == 0.0  # the pose head alone: no map to correct odom by


def test_reset_and_reload_model_services(ros, frames, tmp_path):
    node, harness = ros()
    publish_sequence(harness, frames[:4])
    response = call(harness, Trigger, "/odometry_node/reset")
    assert response.success
    count = len(harness.odometry)
    publish_sequence(harness, frames[4:6], start_ns=START_NS + 10 * PERIOD_NS)
    assert wait_for(lambda: len(harness.odometry) >= count + 2)
    np.testing.assert_allclose(pose_of(harness.odometry[count]), np.eye(4), atol=1e-9)

    response = call(harness, Trigger, "/odometry_node/reload_model")
    assert response.success and "model.safetensors@" in response.message

    # A bad model file: the service says why, and the running model keeps working.
    missing = tmp_path / "missing.safetensors"
    node.set_parameters([Parameter("model_path", value=str(missing))])
    response = call(harness, Trigger, "/odometry_node/reload_model")
    assert not response.success and str(missing) in response.message
    count = len(harness.odometry)
    publish_sequence(harness, frames[6:8], start_ns=START_NS + 20 * PERIOD_NS)
    assert wait_for(lambda: len(harness.odometry) >= count + 2)


def test_a_flood_of_frames_is_dropped_not_queued(ros, frames):
    node, harness = ros()
    for k in range(60):  # far faster than inference: the node must keep only the newest
        harness.publish(frames[k % len(frames)], START_NS + k * PERIOD_NS)
    last = START_NS + 59 * PERIOD_NS
    assert wait_for(lambda: harness.odometry and stamp_to_ns(harness.odometry[-1].header.stamp) == last, timeout=20)
    # Every received frame was either processed or dropped as stale, never queued behind inference.
    _, _, values = node.diagnostics()
    assert values["frames_received"] == values["frames_dropped_stale"] + node.estimator.counters.frames


def camera_info_request(K, D, P, width=640, height=480) -> SetCameraInfo.Request:
    request = SetCameraInfo.Request()
    info = request.camera_info
    info.header.frame_id = "camera_optical"
    info.width, info.height = width, height
    info.distortion_model = "plumb_bob"
    info.d = [float(v) for v in D]
    info.k = [float(v) for v in np.asarray(K).reshape(-1)]
    info.r = [float(v) for v in np.eye(3).reshape(-1)]
    info.p = [float(v) for v in np.asarray(P).reshape(-1)]
    return request


def test_set_camera_info_is_used_and_stored_as_camera_calibration_yaml(ros, frames, tmp_path):
    node, harness = ros()
    K = np.array([[500.0, 0.0, 321.5], [0.0, 502.0, 238.5], [0.0, 0.0, 1.0]])
    D = [-0.11, 0.02, 0.0005, -0.0003, 0.0]
    P = np.array([[480.0, 0.0, 320.0, 0.0], [0.0, 485.0, 240.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    response = call(harness, SetCameraInfo, "/odometry_node/set_camera_info", camera_info_request(K, D, P))
    stored = tmp_path / "camera_info" / "camera.yaml"  # camera_info_url with ${NAME} = camera_name
    assert response.success and str(stored) in response.status_message
    saved = CameraCalibration.load(stored)  # camera_calibration's YAML, read back by the one reader
    assert (saved.width, saved.height, saved.camera_name, saved.distortion_model) == (640, 480, "camera", "plumb_bob")
    np.testing.assert_array_equal(saved.K, K)
    np.testing.assert_array_equal(saved.D, D)
    np.testing.assert_array_equal(saved.projection, P)
    assert node.estimator.calibration_status()["source"] == "file"

    # Published at the images' size (80x60, an eighth): pixel centres at integers, so c' = (c + 0.5) / 8 - 0.5.
    publish_sequence(harness, frames[:2])
    assert wait_for(lambda: len(harness.camera_info) >= 2)
    info = harness.camera_info[-1]
    assert (info.width, info.height) == (WIDTH, HEIGHT)
    np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3),
                               [[500.0 / 8, 0, (321.5 + 0.5) / 8 - 0.5], [0, 502.0 / 8, (238.5 + 0.5) / 8 - 0.5], [0, 0, 1]])
    np.testing.assert_allclose(np.asarray(info.p).reshape(3, 4)[:, :3],
                               [[480.0 / 8, 0, (320.0 + 0.5) / 8 - 0.5], [0, 485.0 / 8, (240.0 + 0.5) / 8 - 0.5], [0, 0, 1]])
    np.testing.assert_allclose(info.d, D)

    # ~/save_calibration writes what is published now (at the frames' size) to the same file.
    response = call(harness, Trigger, "/odometry_node/save_calibration")
    assert response.success and str(stored) in response.message
    now = CameraCalibration.load(stored)
    assert (now.width, now.height) == (WIDTH, HEIGHT)
    np.testing.assert_allclose(now.K, np.asarray(info.k).reshape(3, 3))

    # A driver's "uncalibrated" CameraInfo (K = 0) is refused and changes nothing.
    refused = call(harness, SetCameraInfo, "/odometry_node/set_camera_info", camera_info_request(np.zeros((3, 3)), D, P))
    assert not refused.success and "calibration refused" in refused.status_message
    assert CameraCalibration.load(stored) == now


def test_camera_info_url_starts_the_node_from_a_calibration_file(ros, frames, tmp_path):
    K = np.array([[70.0, 0.0, 39.0], [0.0, 71.0, 30.5], [0.0, 0.0, 1.0]])
    CameraCalibration(WIDTH, HEIGHT, K, [0.05, -0.01, 0.0, 0.0, 0.0], camera_name="wrist").save(tmp_path / "wrist.yaml")
    node, harness = ros(camera_name="wrist", camera_info_url=f"file://{tmp_path}/${{NAME}}.yaml")
    assert node.estimator.calibration_status()["source"] == "file"
    publish_sequence(harness, frames[:2])
    assert wait_for(lambda: len(harness.camera_info) >= 2)
    np.testing.assert_array_equal(np.asarray(harness.camera_info[-1].k).reshape(3, 3), K)
    np.testing.assert_allclose(harness.camera_info[-1].d, [0.05, -0.01, 0.0, 0.0, 0.0])


def test_a_url_camera_info_manager_would_not_accept_stops_the_node_with_one_line():
    context = Context()
    rclpy.init(context=context)
    try:
        for url, problem in (("http://example.com/cam.yaml", "not a file:/// or package://"),
                             ("file:///tmp/${USER}.yaml", "unknown variable")):
            with pytest.raises(ConfigError, match=problem):
                OdometryNode(context=context, parameter_overrides=[Parameter("camera_info_url", value=url),
                                                                   Parameter("device", value="cpu")])
    finally:
        rclpy.try_shutdown(context=context)


def test_a_ground_frame_in_tf_gives_the_estimator_the_cameras_height_and_the_grounds_down(ros, frames):
    """``ground_frame`` (REP 120's base_footprint, beneath base_link here): the camera's height and the
    ground's down come from TF ``base_footprint -> camera_optical``, composed through base_link; with
    ``camera_height`` as well the node refuses to start."""
    node, harness = ros(ground_frame="base_footprint")
    T_footprint_base = make_transform(np.eye(3), np.array([0.1, -0.2, 0.4]))
    harness.static.sendTransform([  # both at once: the child frames' one parent each
        transform_stamped(T_BASE_CAM, ns_to_stamp(START_NS), "base_link", "camera_optical"),
        transform_stamped(T_footprint_base, ns_to_stamp(START_NS), "base_footprint", "base_link")])
    publish_sequence(harness, frames[:3])
    T_ground_cam = T_footprint_base @ T_BASE_CAM
    assert wait_for(lambda: node.estimator.camera_height is not None)
    assert node.estimator.camera_height == pytest.approx(T_ground_cam[2, 3], abs=1e-6)  # 0.9 m
    np.testing.assert_allclose(node.estimator._down_cam, T_ground_cam[:3, :3].T @ [0.0, 0.0, -1.0], atol=1e-6)
    _, _, values = node.diagnostics()
    assert values["ground_frame"] == "base_footprint" and values["camera_height_m"] == pytest.approx(0.9, abs=1e-6)
    with pytest.raises(ConfigError, match="not both"):
        ros(ground_frame="base_footprint", camera_height=1.2)


def test_arm_poses_from_a_pose_topic_reach_the_estimator_with_the_hand_eye(ros):
    node, harness = ros(arm_pose_source="pose", T_tool_cam=T_TOOL_CAM.ravel().tolist())
    assert wait_for(lambda: harness.arm.get_subscription_count() > 0 and node.arm_subscription.get_publisher_count() > 0)
    stamps = [START_NS + k * PERIOD_NS for k in range(3)]
    for k, stamp in enumerate(stamps):
        msg = PoseStamped()
        msg.header.stamp = ns_to_stamp(stamp)
        msg.header.frame_id = "base"
        msg.pose = matrix_to_pose(arm_pose(k))
        harness.arm.publish(msg)
    assert wait_for(lambda: len(node.estimator.arm_poses) == 3)
    for (stamp, T), k in zip(node.estimator.arm_poses, range(3)):
        assert stamp == stamps[k]
        np.testing.assert_allclose(T, arm_pose(k) @ T_TOOL_CAM, atol=1e-9)


def test_sim_time_drives_tf_twist_and_diagnostics_and_a_jump_back_resets(ros, frames):
    node, harness = ros(use_sim_time=True, arm_pose_source="tf", arm_base_frame="arm_base", arm_tool_frame="tool0",
                        T_tool_cam=T_TOOL_CAM.ravel().tolist(), max_delay=0.5, max_age=1.0)
    published_clock: set[int] = set()

    def clock(t_ns: int) -> None:
        set_clock(harness, node, t_ns)
        published_clock.add(t_ns)

    def play(start_ns: int, count: int) -> list[int]:
        """A bag's worth of frames: the arm's TF, then /clock 50 ms past the frame, then the image."""
        stamps = []
        for k in range(count):
            stamp = start_ns + k * PERIOD_NS
            harness.broadcaster.sendTransform(transform_stamped(arm_pose(k), ns_to_stamp(stamp), "arm_base", "tool0"))
            assert wait_for(lambda: node.tf_buffer.can_transform("arm_base", "tool0", Time(nanoseconds=stamp)))
            clock(stamp + 50_000_000)
            published = len(harness.odometry)
            harness.publish(frames[k], stamp)
            assert wait_for(lambda: len(harness.odometry) > published)
            stamps.append(stamp)
        return stamps

    def diagnostics_at(t_ns: int) -> dict:
        """The /diagnostics the node publishes once its clock reads ``t_ns`` (its timer runs on that clock)."""
        clock(t_ns)
        assert wait_for(lambda: any(stamp_to_ns(a.header.stamp) == t_ns for a in harness.diagnostics))
        array = next(a for a in harness.diagnostics if stamp_to_ns(a.header.stamp) == t_ns)
        return {"level": array.status[0].level, "message": array.status[0].message, **values_of(array.status[0])}

    first = START_NS + 20_000_000_000  # 20 s into the "bag"; the loop below goes back to its start
    stamps = play(first, 4)
    odometry = harness.odometry[-4:]
    assert [stamp_to_ns(m.header.stamp) for m in odometry] == stamps

    # Twist over the stamps' 0.1 s, however long the frames took on the wall clock.
    for previous, current in zip(odometry, odometry[1:]):
        T = invert_transform(pose_of(previous)) @ pose_of(current)
        linear = T[:3, :3].T @ T[:3, 3] / 0.1
        twist = current.twist.twist.linear
        np.testing.assert_allclose([twist.x, twist.y, twist.z], linear, atol=1e-6)

    # TF arm poses were looked up at the image stamps (bag time), hand-eye applied (just after each frame).
    assert wait_for(lambda: [stamp for stamp, _ in node.estimator.arm_poses] == stamps)
    arm = node.estimator.arm_poses
    for k, (_, T) in enumerate(arm):
        np.testing.assert_allclose(T, arm_pose(k) @ T_TOOL_CAM, atol=1e-9)

    # Diagnostics on the bag's clock: each odometry came 50 ms of clock time after its image.
    values = diagnostics_at(stamps[-1] + 750_000_000)
    assert values["level"] == DiagnosticStatus.OK, values["message"]
    assert float(values["delay_s_median"]) == pytest.approx(0.05, abs=1e-3)
    assert float(values["odometry_age_s"]) == pytest.approx(0.75, abs=1e-3)
    values = diagnostics_at(stamps[-1] + 1_500_000_000)  # the bag paused with no frames: stale
    assert values["level"] == DiagnosticStatus.WARN and "no odometry for 1.5 s" in values["message"]
    assert {stamp_to_ns(a.header.stamp) for a in harness.diagnostics} <= published_clock

    # The bag loops: /clock jumps 20 s back. TF is cleared (its 10 s cache would refuse the old stamps
    # otherwise), and odometry restarts at the identity at the first frame after the jump.
    clock(START_NS)
    assert wait_for(lambda: node.time_jumps == 1)
    before = len(harness.odometry)
    stamps = play(START_NS, 3)
    again = harness.odometry[before:]
    assert [stamp_to_ns(m.header.stamp) for m in again] == stamps
    np.testing.assert_allclose(pose_of(again[0]), np.eye(4), atol=1e-9)
    assert wait_for(lambda: [stamp for stamp, _ in node.estimator.arm_poses] == stamps)
    # Past the diagnostics timer's next tick, which restarted from the jump (period 0.2 s).
    values = diagnostics_at(stamps[-1] + 400_000_000)
    assert values["level"] == DiagnosticStatus.OK, values["message"]
    assert (values["time_jumps"], values["clock_resets"]) == ("1", "1")
    assert float(values["odometry_age_s"]) == pytest.approx(0.4, abs=1e-3)


def test_diagnostics_warn_when_odometry_falls_behind_its_images(ros, frames):
    node, harness = ros(use_sim_time=True, max_delay=0.5, max_age=10.0)
    for k in range(3):  # every image reaches the node 2 s of clock time after it was taken
        stamp = START_NS + k * PERIOD_NS
        set_clock(harness, node, stamp + 2_000_000_000)
        published = len(harness.odometry)
        harness.publish(frames[k], stamp)
        assert wait_for(lambda: len(harness.odometry) > published)
    t = START_NS + 2 * PERIOD_NS + 2_500_000_000  # past the diagnostics timer's next tick (period 0.2 s)
    set_clock(harness, node, t)
    assert wait_for(lambda: any(stamp_to_ns(a.header.stamp) == t for a in harness.diagnostics))
    status = next(a for a in harness.diagnostics if stamp_to_ns(a.header.stamp) == t).status[0]
    assert status.level == DiagnosticStatus.WARN
    assert "falling behind: odometry 2.00 s after its image" in status.message
    assert float(values_of(status)["delay_s_median"]) == pytest.approx(2.0, abs=1e-3)
