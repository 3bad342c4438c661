"""rclpy odometry node: images in, ``nav_msgs/Odometry``, ``CameraInfo`` and ``odom -> base`` TF out.

A thin adapter: every decision about poses, gaps and resets is :class:`nocal_ros.odometry.OdometryEstimator`'s.

Threading (why the executor never backs up): the image callback only puts the message into a
one-slot "latest frame" mailbox and returns; a worker thread takes the newest message and runs the
estimator. When frames arrive faster than inference, the frame waiting in the mailbox is replaced
(and counted as dropped), so the node always works on the newest image and its latency does not
grow. Services and the diagnostics timer run in the executor, unaffected by inference time.

Parameters (see config/odometry.yaml):
    model_path: checkpoint, model version directory or model store ("" = the shipped model).
        ``~/reload_model`` re-reads this parameter, so a store's newest version is picked up.
    device: auto | cpu | cuda | cuda:N;  precision: fp32 | fp16 | bf16 (CUDA only)
    odom_frame (odom), base_frame (base_link; "" = the camera frame), publish_tf (true)
    camera_frame: overrides the images' header frame id ("" = use it)
    queue_size: subscription depth (sensor-data QoS, best effort);  latest_only: true = drop stale
        frames (the mailbox), false = process every frame in order (a bounded queue of queue_size)
    frame_period: camera frame period in s (0 = from the stamps);  distortion_model: auto | plumb_bob
        | rational_polynomial;  tf_timeout: seconds to wait for base -> camera at a frame;
        diagnostics_period: seconds;  threads: torch CPU threads (0 = torch's default; 1 is fastest
        for one pair at a time on small loaded machines, see BENCHMARKS.md).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any

import numpy as np
import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from tf2_ros import Buffer, TransformBroadcaster, TransformException, TransformListener

from nocal_ros.errors import NocalError
from nocal_ros.geometry import InvalidTransformError
from nocal_ros.odometry import FrameMailbox, OdometryEstimator
from nocal_ros.ros.conversions import (
    camera_info_message,
    decode_compressed_image,
    decode_image,
    diagnostic_status,
    odometry_message,
    stamp_to_ns,
    transform_msg_to_matrix,
    transform_stamped,
)

PARAMETERS: dict[str, Any] = {
    "model_path": "",
    "device": "auto",
    "precision": "fp32",
    "method": "vo",
    "odom_frame": "odom",
    "base_frame": "base_link",
    "camera_frame": "",
    "publish_tf": True,
    "queue_size": 2,
    "latest_only": True,
    "frame_period": 0.0,
    "distortion_model": "auto",
    "tf_timeout": 0.0,
    "diagnostics_period": 1.0,
    "compressed": False,
    "threads": 0,
}


class OdometryNode(Node):
    """See the module notes."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("odometry_node", **kwargs)
        for name, default in PARAMETERS.items():
            self.declare_parameter(name, default)
        p = {name: self.get_parameter(name).value for name in PARAMETERS}
        if int(p["threads"]) > 0:
            torch.set_num_threads(int(p["threads"]))
        self.odom_frame = str(p["odom_frame"])
        self.base_frame = str(p["base_frame"])
        self.camera_frame = str(p["camera_frame"])
        self.publish_tf = bool(p["publish_tf"])
        self.tf_timeout = float(p["tf_timeout"])

        self.estimator = OdometryEstimator(
            p["model_path"] or None, p["device"], frame_period_s=float(p["frame_period"]) or None,
            distortion_model=str(p["distortion_model"]), precision=str(p["precision"]),
            method=str(p["method"]),
        )
        self.get_logger().info(
            f"model {self.estimator.model_id} on {self.estimator.model.device}, input "
            f"{self.estimator.input_size[0]}x{self.estimator.input_size[1]}"
        )

        self.tf_buffer = Buffer()
        self.tf_listener = TransformListener(self.tf_buffer, self)
        self.tf_broadcaster = TransformBroadcaster(self)
        self.odom_publisher = self.create_publisher(Odometry, "odom", 10)
        self.camera_info_publisher = self.create_publisher(CameraInfo, "camera_info", 10)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)

        self.mailbox = FrameMailbox(bool(p["latest_only"]), int(p["queue_size"]))
        qos = QoSProfile(
            history=qos_profile_sensor_data.history, depth=max(1, int(p["queue_size"])),
            reliability=qos_profile_sensor_data.reliability, durability=qos_profile_sensor_data.durability,
        )
        image_type = CompressedImage if p["compressed"] else Image
        topic = "image/compressed" if p["compressed"] else "image"
        self.subscription = self.create_subscription(image_type, topic, self._on_image, qos,
                                                     callback_group=MutuallyExclusiveCallbackGroup())
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=services)
        self.create_service(Trigger, "~/reload_model", self._on_reload, callback_group=services)
        self.create_timer(float(p["diagnostics_period"]), self._publish_diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())

        self._T_base_cam: dict[str, np.ndarray] = {}  # camera frame -> static mounting, once found
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=200)
        self._published: collections.deque[float] = collections.deque(maxlen=200)
        self._waiting_for_tf = 0
        self._rejected = 0
        self._last_error = ""
        self._running = True
        self._worker = threading.Thread(target=self._work, name="nocal_odometry", daemon=True)
        self._worker.start()

    # -- executor side: cheap --------------------------------------------------------------------

    def _on_image(self, msg: Any) -> None:
        self.mailbox.put((time.perf_counter(), msg))

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.mailbox.clear()
        self.estimator.reset()
        self._T_base_cam.clear()
        response.success, response.message = True, "odometry reset: pose is the identity at the next frame"
        self.get_logger().info(response.message)
        return response

    def _on_reload(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        path = str(self.get_parameter("model_path").value)
        try:
            model_id = self.estimator.reload(path or None)
        except NocalError as error:  # the running model stays in place
            response.success, response.message = False, f"reload failed, keeping {self.estimator.model_id}: {error}"
            self.get_logger().error(response.message)
            return response
        response.success, response.message = True, f"loaded {model_id}"
        self.get_logger().info(response.message)
        return response

    # -- worker side -----------------------------------------------------------------------------

    def _work(self) -> None:
        while self._running:
            item = self.mailbox.get(timeout=0.1)
            if item is None:
                continue
            received, msg = item
            try:
                self._process(msg, received)
            except (NocalError, ValueError) as error:  # a bad frame: say so, keep running
                self._rejected += 1
                self._last_error = str(error)
                self.get_logger().error(f"frame rejected: {error}", throttle_duration_sec=5.0)
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

    def _process(self, msg: Any, received: float) -> None:
        camera_frame = self.camera_frame or msg.header.frame_id
        T_base_cam = self._mounting(camera_frame)
        if T_base_cam is None:
            return
        self.estimator.set_base_to_camera(T_base_cam)
        if isinstance(msg, CompressedImage):
            rgb, encoding = decode_compressed_image(msg), str(msg.format)
        else:
            rgb, encoding = decode_image(msg), str(msg.encoding)
        result = self.estimator.process(stamp_to_ns(msg.header.stamp), rgb, encoding=encoding)
        header = Header(stamp=msg.header.stamp, frame_id=camera_frame)
        if self.estimator.model.camera is not None:
            calibration, _ = self.estimator.camera_info(rgb.shape[1], rgb.shape[0])
            self.camera_info_publisher.publish(camera_info_message(calibration, header))
        if result is None:
            return
        base = self.base_frame or camera_frame
        self.odom_publisher.publish(odometry_message(result, msg.header.stamp, self.odom_frame, base))
        if self.publish_tf:
            self.tf_broadcaster.sendTransform(transform_stamped(result.T_odom_base, msg.header.stamp, self.odom_frame, base))
        now = time.perf_counter()
        self._latencies_ms.append((now - received) * 1e3)
        self._published.append(now)

    # -- diagnostics -----------------------------------------------------------------------------

    def diagnostics(self) -> dict[str, Any]:
        latencies = np.asarray(self._latencies_ms) if self._latencies_ms else np.zeros(1)
        published = list(self._published)
        rate = (len(published) - 1) / (published[-1] - published[0]) if len(published) > 1 and published[-1] > published[0] else 0.0
        counters = vars(self.estimator.counters)
        return {
            "model_id": self.estimator.model_id,
            "device": str(self.estimator.model.device),
            "rate_hz": float(rate),
            "latency_ms_median": float(np.median(latencies)),
            "latency_ms_max": float(latencies.max()),
            "frames_received": self.mailbox.received,
            "frames_dropped_stale": self.mailbox.dropped,
            "frames_waiting_for_tf": self._waiting_for_tf,
            "frames_rejected": self._rejected,
            **{f"estimator_{k}": v for k, v in counters.items()},
            "last_error": self._last_error,
        }

    def _publish_diagnostics(self) -> None:
        values = self.diagnostics()
        level = DiagnosticStatus.OK
        message = "ok"
        if values["frames_received"] == 0:
            level, message = DiagnosticStatus.WARN, "no images received"
        elif values["frames_rejected"] or values["frames_waiting_for_tf"]:
            level, message = DiagnosticStatus.WARN, values["last_error"] or "waiting for TF"
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [diagnostic_status(f"{self.get_name()}: odometry", values["model_id"], level, message, values)]
        self.diagnostics_publisher.publish(array)

    def destroy_node(self) -> None:
        self._running = False
        self.mailbox.close()
        if self._worker.is_alive():
            self._worker.join(timeout=2.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = OdometryNode()
        executor = MultiThreadedExecutor(num_threads=3)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except NocalError as error:  # e.g. a bad model file at start: one clear line, not a traceback
        print(f"odometry_node: error: {error}")
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    main()
