"""rclpy odometry node: images in, ``nav_msgs/Odometry``, ``CameraInfo`` and ``map -> odom -> base`` TF out, and
the VO's keyframes (``keyframe_path``, ``nav_msgs/Path``) and landmarks (``map_points``,
``sensor_msgs/PointCloud2``) in ``odom`` as bundle adjustment refines them.

A thin adapter: every decision about poses, gaps and resets is :class:`nocal_ros.odometry.OdometryEstimator`'s;
calibration files follow camera_info_manager (:mod:`nocal_ros.live.calibration_url`), and the
diagnostics are :class:`nocal_ros.live.health.OdometryHealth`'s.

Threading (why the executor never backs up): the image callback only puts the message into a
one-slot "latest frame" mailbox and returns; a worker thread takes the newest message and runs the
estimator. When frames arrive faster than inference, the frame waiting in the mailbox is replaced
(and counted as dropped), so the node always works on the newest image and its latency does not
grow. Services, arm poses and the diagnostics timer run in the executor, unaffected by inference time.

Time: stamps come from the images; "now" is the node's clock, which follows ``/clock`` when
``use_sim_time`` is true (a bag played with ``--clock``, a simulator), so the diagnostics timer,
rate, delay and age follow the bag's time. When that clock jumps back (a bag loop), TF is cleared,
waiting frames and arm stamps are dropped and odometry restarts at the identity, as on ``~/reset``.

Parameters (see config/odometry.yaml):
    model_path: checkpoint, model version directory or model store ("" = the shipped model).
        ``~/reload_model`` re-reads this parameter, so a store's newest version is picked up.
    device: auto | cpu | cuda | cuda:N;  precision: fp32 | fp16 | bf16 (CUDA only)
    odom_frame (odom), base_frame (base_link; "" = the camera frame), publish_tf (true)
    map_frame (map): with publish_tf, ``map -> odom`` is broadcast at each frame's stamp beside ``odom -> base``:
        the map frame's correction of odom from the refined keyframes (REP 105, as rtabmap does;
        ``OdometryResult.T_map_odom``); "" = none (another node owns ``map``, e.g. a localiser)
    camera_frame: overrides the images' header frame id ("" = use it)
    method: vo (keyframe VO calibrating the camera online) | pose_head (the pose head alone)
    camera_name, camera_info_url: camera_info_manager's: the online camera starts from the calibration
        at the URL (default ``file://${ROS_HOME}/camera_info/${NAME}.yaml``) when it exists, instead of the
        learnt camera; ``~/set_camera_info`` and ``~/save_calibration`` write it (read once at start).
    camera_height: m of the camera above the floor or road (0 = unknown), or ground_frame: a frame on the
        ground beneath the camera, z up (REP 120's base_footprint), whose TF to the camera gives its height
        and the ground's normal: the scale from the ground plane where no arm poses fit
    arm_pose_source: none | pose (PoseStamped on ``arm_pose``) | tf (``arm_base_frame -> arm_tool_frame``);
        T_tool_cam: hand-eye, row-major 4x4;  arm_tf_wait: seconds of images a frame waits for its TF pose
    queue_size: subscription depth (sensor-data QoS, best effort);  latest_only: true = drop stale
        frames (the mailbox), false = process every frame in order (a bounded queue of queue_size)
    frame_period: camera frame period in s (0 = from the stamps);  distortion_model: the online camera's
        lens, auto (plumb_bob; equidistant for a learnt fisheye) | plumb_bob | equidistant;  tf_timeout: seconds to wait for base -> camera at a frame;
        diagnostics_period: seconds;  max_delay, max_age: seconds before /diagnostics warns;
        map_period: seconds between ``keyframe_path`` and ``map_points`` messages (0 = none; sent only while
            something subscribes; :meth:`~nocal_ros.odometry.OdometryEstimator.map_snapshot`);
        threads: torch CPU threads (0 = torch's default; 1 is fastest for one pair at a time on small
        loaded machines, see BENCHMARKS.md).
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from typing import Any

import numpy as np
import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from sensor_msgs.srv import SetCameraInfo
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from tf2_ros import Buffer, TransformBroadcaster, TransformException, TransformListener

from nocal_ros.data.bags import camera_info_to_calibration, pose_msg_to_matrix
from nocal_ros.errors import ConfigError, NocalError
from nocal_ros.geometry import InvalidTransformError
from nocal_ros.live.arm_poses import PendingStamps, hand_eye_matrix
from nocal_ros.live.calibration_url import check_camera_name, load_calibration, save_calibration
from nocal_ros.live.health import OdometryHealth, vo_timing_values
from nocal_ros.odometry import FrameMailbox, OdometryEstimator
from nocal_ros.ros.conversions import (
    camera_info_message,
    decode_compressed_image,
    decode_image,
    diagnostic_status,
    ns_to_stamp,
    odometry_message,
    path_message,
    point_cloud_message,
    stamp_to_ns,
    transform_msg_to_matrix,
    transform_stamped,
)

IDENTITY_16 = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
ARM_POSE_SOURCES = ("none", "pose", "tf")

PARAMETERS: dict[str, Any] = {
    "model_path": "",
    "device": "auto",
    "precision": "fp32",
    "method": "vo",
    "odom_frame": "odom",
    "map_frame": "map",
    "base_frame": "base_link",
    "camera_frame": "",
    "publish_tf": True,
    "queue_size": 2,
    "latest_only": True,
    "frame_period": 0.0,
    "distortion_model": "auto",
    "tf_timeout": 0.0,
    "diagnostics_period": 1.0,
    "map_period": 1.0,
    "compressed": False,
    "threads": 0,
    "camera_name": "camera",
    "camera_info_url": "",
    "camera_height": 0.0,
    "ground_frame": "",
    "arm_pose_source": "none",
    "arm_base_frame": "base",
    "arm_tool_frame": "tool",
    "T_tool_cam": IDENTITY_16,
    "arm_tf_wait": 0.5,
    "max_delay": 0.5,
    "max_age": 1.0,
}


class OdometryNode(Node):
    """See the module notes."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("odometry_node", **kwargs)
        try:
            self._start()
        except BaseException:
            Node.destroy_node(self)  # a node that cannot start (bad parameter or file) leaves nothing behind
            raise

    def _start(self) -> None:
        for name, default in PARAMETERS.items():
            self.declare_parameter(name, default)
        p = {name: self.get_parameter(name).value for name in PARAMETERS}
        if int(p["threads"]) > 0:
            torch.set_num_threads(int(p["threads"]))
        self.odom_frame = str(p["odom_frame"])
        self.map_frame = str(p["map_frame"])
        if self.map_frame and self.map_frame == self.odom_frame:
            raise ConfigError(f"map_frame and odom_frame must differ (both {self.map_frame!r}); \"\" turns map -> odom off")
        self.base_frame = str(p["base_frame"])
        self.camera_frame = str(p["camera_frame"])
        self.publish_tf = bool(p["publish_tf"])
        self.tf_timeout = float(p["tf_timeout"])
        self.camera_name = check_camera_name(str(p["camera_name"]))
        self.camera_info_url = str(p["camera_info_url"])
        self.arm_pose_source = str(p["arm_pose_source"])
        if self.arm_pose_source not in ARM_POSE_SOURCES:
            raise ConfigError(f"arm_pose_source must be one of {', '.join(ARM_POSE_SOURCES)}, not {self.arm_pose_source!r}")
        self.arm_base_frame, self.arm_tool_frame = str(p["arm_base_frame"]), str(p["arm_tool_frame"])
        self.T_tool_cam = hand_eye_matrix(p["T_tool_cam"])
        self.ground_frame = str(p["ground_frame"])
        if self.ground_frame and float(p["camera_height"]) > 0:
            raise ConfigError("set camera_height or ground_frame, not both: the ground frame gives the height")
        calibration, self.calibration_path = load_calibration(self.camera_info_url, self.camera_name)

        self.estimator = OdometryEstimator(
            p["model_path"] or None, p["device"], frame_period_s=float(p["frame_period"]) or None,
            distortion_model=str(p["distortion_model"]), precision=str(p["precision"]),
            method=str(p["method"]), calibration=calibration, camera_height=float(p["camera_height"]) or None,
        )
        self.get_logger().info(
            f"model {self.estimator.model_id} on {self.estimator.model.device}, input "
            f"{self.estimator.input_size[0]}x{self.estimator.input_size[1]}"
        )
        if calibration is not None:
            self.get_logger().info(f"camera calibration from {self.calibration_path}")
            if calibration.camera_name != self.camera_name:  # camera_info_manager warns alike
                self.get_logger().warning(f"[{self.camera_name}] does not match {calibration.camera_name} in {self.calibration_path}")
        else:
            self.get_logger().info(f"no calibration at {self.calibration_path}: publishing the model's camera "
                                   "(~/set_camera_info and ~/save_calibration write one there)")

        self.tf_buffer = Buffer()
        self.tf_listener = TransformListener(self.tf_buffer, self)
        self.tf_broadcaster = TransformBroadcaster(self)
        self.odom_publisher = self.create_publisher(Odometry, "odom", 10)
        self.camera_info_publisher = self.create_publisher(CameraInfo, "camera_info", 10)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.path_publisher = self.create_publisher(Path, "keyframe_path", 1)
        self.map_points_publisher = self.create_publisher(PointCloud2, "map_points", 1)

        self.mailbox = FrameMailbox(bool(p["latest_only"]), int(p["queue_size"]))
        qos = QoSProfile(
            history=qos_profile_sensor_data.history, depth=max(1, int(p["queue_size"])),
            reliability=qos_profile_sensor_data.reliability, durability=qos_profile_sensor_data.durability,
        )
        image_type = CompressedImage if p["compressed"] else Image
        topic = "image/compressed" if p["compressed"] else "image"
        self.subscription = self.create_subscription(image_type, topic, self._on_image, qos,
                                                     callback_group=MutuallyExclusiveCallbackGroup())
        self.arm_subscription = None  # arm poses on a topic (arm_pose_source "pose"); TF is looked up instead
        if self.arm_pose_source == "pose":
            # Best effort matches both reliable and best-effort arm drivers; 50 deep rides out a busy executor.
            arm_qos = QoSProfile(history=qos_profile_sensor_data.history, depth=50,
                                 reliability=qos_profile_sensor_data.reliability)
            self.arm_subscription = self.create_subscription(PoseStamped, "arm_pose", self._on_arm_pose, arm_qos,
                                                             callback_group=MutuallyExclusiveCallbackGroup())
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=services)
        self.create_service(Trigger, "~/reload_model", self._on_reload, callback_group=services)
        self.create_service(SetCameraInfo, "~/set_camera_info", self._on_set_camera_info, callback_group=services)
        self.create_service(Trigger, "~/save_calibration", self._on_save_calibration, callback_group=services)
        self.create_timer(float(p["diagnostics_period"]), self._publish_diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())
        map_period = float(p["map_period"])
        if not map_period >= 0:
            raise ConfigError(f"map_period must be 0 (off) or a positive number of seconds, not {map_period!r}")
        if map_period > 0:
            self.create_timer(map_period, self._publish_map, callback_group=MutuallyExclusiveCallbackGroup())
        # A jump back of the clock (sim time: a bag loop) makes every stamp held so far meaningless.
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=True),
            post_callback=self._on_time_jump)

        self.health = OdometryHealth(max_delay_s=float(p["max_delay"]), max_age_s=float(p["max_age"]))
        self._pending_arm = PendingStamps(max_wait_s=float(p["arm_tf_wait"]))
        self._T_base_cam: dict[str, np.ndarray] = {}  # camera frame -> static mounting, once found
        self._ground_camera_frame = ""  # the camera frame the ground frame's mounting was found for
        self._reset_requested = threading.Event()
        self.time_jumps = 0  # clock jumps the worker has finished resetting for
        self._waiting_for_tf = 0
        self._rejected = 0
        self._camera_info_failures = 0
        self._arm_poses_received = 0
        self._arm_poses_rejected = 0
        self._last_error = ""
        self._running = True
        self._worker = threading.Thread(target=self._work, name="nocal_odometry", daemon=True)
        self._worker.start()

    # -- executor side: cheap --------------------------------------------------------------------

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on_image(self, msg: Any) -> None:
        self.mailbox.put((time.perf_counter(), msg))

    def _on_arm_pose(self, msg: PoseStamped) -> None:
        try:
            self.estimator.add_arm_pose(stamp_to_ns(msg.header.stamp), pose_msg_to_matrix(msg.pose) @ self.T_tool_cam)
        except ValueError as error:  # e.g. a zero quaternion from a driver that is starting up
            self._arm_poses_rejected += 1
            self.get_logger().warning(f"arm pose rejected: {error}", throttle_duration_sec=5.0)
            return
        self._arm_poses_received += 1

    def _on_time_jump(self, jump: TimeJump) -> None:
        # Runs inside the /clock callback, which must not block: clear what is quick to clear here,
        # and let the worker reset the estimator before its next frame.
        self.mailbox.clear()
        self.tf_buffer.clear()  # tf2 keeps /tf_static through a clear, so the mounting stays known
        self._pending_arm.clear()
        self.health.reset()
        self._reset_requested.set()
        self.get_logger().warning(f"clock jumped by {jump.delta.nanoseconds * 1e-9:.3f} s ({jump.clock_change}): "
                                  "odometry restarts at the identity")

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.mailbox.clear()
        self.estimator.reset()
        self._pending_arm.clear()
        self._T_base_cam.clear()
        return self._reply(response, True, "odometry reset: pose is the identity at the next frame")

    def _reply(self, response: Any, success: bool, message: str, field: str = "message") -> Any:
        """A service's response filled in (``success`` and its ``field`` message) and logged: info when it
        succeeded, error when not."""
        response.success = success
        setattr(response, field, message)
        (self.get_logger().info if success else self.get_logger().error)(message)
        return response

    def _on_reload(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        path = str(self.get_parameter("model_path").value)
        try:
            model_id = self.estimator.reload(path or None)
        except NocalError as error:  # the running model stays in place
            return self._reply(response, False, f"reload failed, keeping {self.estimator.model_id}: {error}")
        return self._reply(response, True, f"loaded {model_id}")

    def _on_set_camera_info(self, request: SetCameraInfo.Request,
                            response: SetCameraInfo.Response) -> SetCameraInfo.Response:
        """camera_info_manager's service: use the calibration from now on, and store it at the URL
        (success says whether it was stored; it is used either way, as camera_info_manager does)."""
        try:
            calibration = camera_info_to_calibration(request.camera_info)
        except NocalError as error:
            return self._reply(response, False, f"calibration refused: {error}", "status_message")
        calibration = dataclasses.replace(calibration, camera_name=self.camera_name)
        self.estimator.set_calibration(calibration)
        try:
            path = save_calibration(calibration, self.camera_info_url, self.camera_name)
        except NocalError as error:
            return self._reply(response, False, f"calibration in use but not stored: {error}", "status_message")
        return self._reply(response, True, f"calibration in use and stored in {path}", "status_message")

    def _on_save_calibration(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            calibration, residual = self.estimator.camera_info()
            path = save_calibration(calibration, self.camera_info_url, self.camera_name)
        except NocalError as error:
            return self._reply(response, False, f"calibration not saved: {error}")
        return self._reply(response, True, f"saved the {calibration.width}x{calibration.height} "
                           f"{calibration.distortion_model} calibration ({self.estimator.calibration_status()['source']}, "
                           f"fit residual {residual:.3f} px) to {path}")

    # -- worker side -----------------------------------------------------------------------------

    def _work(self) -> None:
        while self._running:
            item = self.mailbox.get(timeout=0.1)
            if self._reset_requested.is_set():  # the clock jumped back: restart before the next frame
                self._reset_requested.clear()
                self.estimator.reset()
                self.time_jumps += 1
            if item is None:
                continue
            received, msg = item
            try:
                self._process(msg, received)
            except (NocalError, ValueError) as error:  # a bad frame: say so, keep running
                self._rejected += 1
                self._last_error = f"frame rejected: {error}"
                self.get_logger().error(self._last_error, throttle_duration_sec=5.0)
            except Exception as error:  # noqa: BLE001 - never let the worker die silently
                self._rejected += 1
                self._last_error = f"{type(error).__name__}: {error}"
                self.get_logger().error(f"unexpected error: {self._last_error}", throttle_duration_sec=5.0)

    def _mounting(self, camera_frame: str) -> np.ndarray | None:
        """``T_base_cam`` from TF (static, so looked up once per camera frame); identity for one frame."""
        base = self.base_frame or camera_frame
        if base == camera_frame:
            return np.eye(4)
        T = self._T_base_cam.get(camera_frame)
        if T is None:
            try:
                transform = self.tf_buffer.lookup_transform(base, camera_frame, Time(), timeout=Duration(seconds=self.tf_timeout))
            except TransformException as error:
                self._waiting_for_tf += 1
                self._last_error = f"waiting for TF {base} -> {camera_frame}"
                self.get_logger().warning(
                    f"waiting for TF {base} -> {camera_frame} ({error}); frames are skipped until it exists",
                    throttle_duration_sec=5.0,
                )
                return None
            try:
                T = transform_msg_to_matrix(transform.transform)
            except InvalidTransformError as error:  # a zero quaternion would make every pose NaN
                self._waiting_for_tf += 1
                self.get_logger().error(
                    f"TF {base} -> {camera_frame} is no transform ({error}); frames are skipped until it is fixed",
                    throttle_duration_sec=5.0,
                )
                return None
            self._T_base_cam[camera_frame] = T
        return T

    def _find_ground(self, camera_frame: str) -> None:
        """The camera's height and the ground's normal from TF ``ground_frame -> camera frame`` (static, so
        looked up until found). Frames go on meanwhile, on the scale the estimator has without it."""
        try:
            transform = self.tf_buffer.lookup_transform(self.ground_frame, camera_frame, Time(),
                                                        timeout=Duration(seconds=self.tf_timeout))
            self.estimator.set_ground_to_camera(transform_msg_to_matrix(transform.transform))
        except TransformException as error:
            self._last_error = f"waiting for TF {self.ground_frame} -> {camera_frame}"
            self.get_logger().warning(f"waiting for TF {self.ground_frame} -> {camera_frame} ({error}): no "
                                      "ground-plane scale until it exists", throttle_duration_sec=5.0)
            return
        except (InvalidTransformError, NocalError) as error:
            self._last_error = f"ground_frame {self.ground_frame}: {error}"
            self.get_logger().error(f"ground_frame {self.ground_frame} -> {camera_frame}: {error}; no ground-plane "
                                    "scale", throttle_duration_sec=5.0)
            return
        self._ground_camera_frame = camera_frame
        self.get_logger().info(f"camera {self.estimator.camera_height:.3f} m above {self.ground_frame}: the scale "
                               "comes from the ground plane where no arm poses fit")

    def _arm_pose_at(self, stamp_ns: int) -> np.ndarray | None:
        """``T_base_cam`` of the arm at ``stamp_ns`` from TF, or None while TF cannot say yet."""
        try:
            transform = self.tf_buffer.lookup_transform(self.arm_base_frame, self.arm_tool_frame, Time(nanoseconds=stamp_ns))
        except TransformException:
            return None
        return transform_msg_to_matrix(transform.transform) @ self.T_tool_cam

    def _process(self, msg: Any, received: float) -> None:
        camera_frame = self.camera_frame or msg.header.frame_id
        T_base_cam = self._mounting(camera_frame)
        if T_base_cam is None:
            return
        self.estimator.set_base_to_camera(T_base_cam)
        if self.ground_frame and self._ground_camera_frame != camera_frame:
            self._find_ground(camera_frame)
        if isinstance(msg, CompressedImage):
            rgb, encoding = decode_compressed_image(msg), str(msg.format)
        else:
            rgb, encoding = decode_image(msg), str(msg.encoding)
        stamp_ns = stamp_to_ns(msg.header.stamp)
        result = self.estimator.process(stamp_ns, rgb, encoding=encoding)
        if result is not None:
            base = self.base_frame or camera_frame
            self.odom_publisher.publish(odometry_message(result, msg.header.stamp, self.odom_frame, base))
            if self.publish_tf:
                transforms = [transform_stamped(result.T_odom_base, msg.header.stamp, self.odom_frame, base)]
                if self.map_frame:
                    transforms.append(transform_stamped(result.T_map_odom, msg.header.stamp, self.map_frame, self.odom_frame))
                self.tf_broadcaster.sendTransform(transforms)
            self.health.published(stamp_ns, self._now_ns(), (time.perf_counter() - received) * 1e3,
                                  result.tracking, result.scale_source, result.T_map_odom)
        self._publish_camera_info(Header(stamp=msg.header.stamp, frame_id=camera_frame), rgb.shape[1], rgb.shape[0])
        if self.arm_pose_source == "tf":
            self._pending_arm.add(stamp_ns)
            for stamp, T in self._pending_arm.resolve(self._arm_pose_at):
                self.estimator.add_arm_pose(stamp, T)
                self._arm_poses_received += 1

    def _publish_camera_info(self, header: Header, width: int, height: int) -> None:
        """CameraInfo for every image, full size, with its stamp and frame; after the odometry, so a
        camera that cannot be published (a model without one) never costs a pose."""
        try:
            calibration, _ = self.estimator.camera_info(width, height)
        except NocalError as error:
            self._camera_info_failures += 1
            self.get_logger().warning(f"no CameraInfo: {error}", throttle_duration_sec=10.0)
            return
        self.camera_info_publisher.publish(camera_info_message(calibration, header))

    def _publish_map(self) -> None:
        """The keyframes and landmarks as they stand, stamped with the newest keyframe's stamp (the image
        time of the rest of the node's output), or now when there is no keyframe (after a reset)."""
        if self.path_publisher.get_subscription_count() == 0 and self.map_points_publisher.get_subscription_count() == 0:
            return
        snapshot = self.estimator.map_snapshot()
        stamp = ns_to_stamp(int(snapshot.stamps_ns[-1])) if len(snapshot.stamps_ns) else self.get_clock().now().to_msg()
        header = Header(stamp=stamp, frame_id=self.odom_frame)
        self.path_publisher.publish(path_message(snapshot.stamps_ns, snapshot.T_odom_base, header))
        self.map_points_publisher.publish(point_cloud_message(snapshot.points, header))

    # -- diagnostics -----------------------------------------------------------------------------

    def diagnostics(self) -> tuple[int, str, dict[str, Any]]:
        """``(level, message, values)`` now (on the node's clock)."""
        calibration = self.estimator.calibration_status()
        level, message, health = self.health.report(
            self._now_ns(), frames_received=self.mailbox.received, frames_rejected=self._rejected,
            frames_waiting_for_tf=self._waiting_for_tf, last_error=self._last_error,
            given_check=calibration.get("given_check", ""))
        values = {
            "model_id": self.estimator.model_id,
            "device": str(self.estimator.model.device),
            **health,
            "frames_received": self.mailbox.received,
            "frames_dropped_stale": self.mailbox.dropped,
            "frames_waiting_for_tf": self._waiting_for_tf,
            "frames_rejected": self._rejected,
            **{f"estimator_{k}": v for k, v in vars(self.estimator.counters).items()},
            **{f"calibration_{k}": ("" if v is None else v) for k, v in calibration.items()},
            **vo_timing_values(self.estimator.timings()),
            **{f"mapping_{k}": v for k, v in self.estimator.mapping_status().items()},
            "calibration_file": str(self.calibration_path),
            "camera_info_failures": self._camera_info_failures,
            "camera_height_m": self.estimator.camera_height or 0.0,
            "ground_frame": self.ground_frame,
            "arm_pose_source": self.arm_pose_source,
            "arm_poses_received": self._arm_poses_received,
            "arm_poses_rejected": self._arm_poses_rejected,
            "arm_tf_given_up": self._pending_arm.given_up,
            "time_jumps": self.time_jumps,
            "last_error": self._last_error,
        }
        return level, message, values

    def _publish_diagnostics(self) -> None:
        level, message, values = self.diagnostics()
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [diagnostic_status(f"{self.get_name()}: odometry", values["model_id"], level, message, values)]
        self.diagnostics_publisher.publish(array)

    def destroy_node(self) -> None:
        self._running = False
        self.mailbox.close()
        if self._worker.is_alive():
            self._worker.join(timeout=5.0)
        self.estimator.close()  # local mapping's thread and its solver process
        self._jump_handle.unregister()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = executor = None
    code = 0
    try:
        node = OdometryNode()
        executor = MultiThreadedExecutor(num_threads=3)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except NocalError as error:  # e.g. a bad model or calibration file at start: one clear line, not a traceback
        print(f"odometry_node: error: {error}", file=sys.stderr)
        code = 1
    finally:
        # rclpy's order: stop the executor (no callback runs after), then the node, then the context.
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
