"""rclpy trainer node: field re-calibration from rosbags, recorded elsewhere or live, then a model swap.

A thin adapter over ``nocal_ros.finetune`` and ``nocal_ros.live``: parameters become a
``FinetuneConfig``, ``~/start`` and ``~/cancel`` (std_srvs/Trigger) start and stop a ``FinetuneJob`` (a
separate worker process, so a crash or out-of-memory in training cannot take this node down), a timer
drains the job's progress into ``~/progress`` (std_msgs/String, one JSON object per job message, with
the state that message left the job in) and ``/diagnostics``, and when a run publishes a new model
version the node calls the odometry node's reload service (``reload_service``, std_srvs/Trigger). The
odometry node must load from the same model store (its ``model_path`` set to this node's
``output_store``), so reloading picks up ``latest``.

``~/record`` (std_srvs/SetBool) records the camera and the arm live: ``true`` starts writing
``image_topic`` and the arm's poses (PoseStamped on ``pose_topic``, and/or the TF edge ``tf_parent ->
tf_child``, as ``pose_source`` says) into a rosbag2 under ``<output_store>/recordings/``; ``false``
stops it, as do ``record_max_bytes`` and ``record_max_duration_s``. A finished recording becomes the
``bags`` parameter, so the next ``~/start`` fine-tunes on it.
"""

from __future__ import annotations

import json
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger
from tf2_ros import Buffer, TransformException, TransformListener

from nocal_ros.data.bags import pose_msg_to_matrix, stamp_to_ns, transform_msg_to_matrix
from nocal_ros.errors import NocalError
from nocal_ros.finetune import FinetuneConfig, FinetuneJob
from nocal_ros.live.arm_poses import PendingStamps
from nocal_ros.live.recorder import LiveRecorder, RecordingLimits, RecordingSummary
from nocal_ros.live.trainer import diagnostic_level, final_record, progress_record

DEFAULT_STORE = os.path.join("~", ".ros", "nocal_ros", "models")
IDENTITY_16 = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]

# name -> (default, description); bags is declared apart (an empty list needs dynamic typing).
PARAMETERS: dict[str, tuple[object, str]] = {
    "output_store": (DEFAULT_STORE, "model store directory new versions are published to"),
    "init_model": ("", "model to start from (file, version dir or store); empty: output_store's latest or the shipped model"),
    "image_topic": ("/camera/image_raw", "image topic in the bags (and the one ~/record records)"),
    "pose_topic": ("/arm/pose", "geometry_msgs/PoseStamped arm pose topic in the bags (and the one ~/record records)"),
    "pose_source": ("auto", "auto | pose | tf | none"),
    "tf_parent": ("base", "TF parent frame of the arm (pose_source tf)"),
    "tf_child": ("tool", "TF child frame of the arm (pose_source tf)"),
    "T_tool_cam": (IDENTITY_16, "hand-eye transform, row-major 4x4 (camera pose in the tool frame)"),
    "tolerance_s": (0.02, "an image further than this from an arm pose is unlabelled"),
    "steps": (2000, "training steps"),
    "device": ("auto", "auto | cpu | cuda | cuda:N"),
    "max_frames": (0, "frames read per bag (0: all)"),
    "seed": (0, "random seed"),
    "threads": (0, "torch CPU threads in the worker (0: default)"),
    "keep_versions": (5, "versions kept in the store (0: all)"),
    "training_config": ("", "training YAML, e.g. the package's config/finetune.yaml; empty: training defaults"),
    "camera_start": ("reset", "reset: f = width (a new camera) | init: the initial model's camera (a known camera that moved)"),
    "reload_service": ("/odometry_node/reload_model", "odometry node's std_srvs/Trigger reload service; empty: do not call"),
    "reload_timeout_s": (10.0, "how long to wait for the reload service to appear"),
    "poll_period_s": (0.2, "how often the worker's progress is read"),
    "diagnostics_period_s": (1.0, "how often /diagnostics is published"),
    "cancel_grace_s": (10.0, "a cancelled worker that has not stopped after this is terminated"),
    "compressed": (False, "~/record subscribes to image_topic as sensor_msgs/CompressedImage"),
    "record_max_duration_s": (120.0, "a recording stops by itself after this much clock time"),
    "record_max_bytes": (2_000_000_000, "a recording stops by itself before its messages exceed this"),
    "record_storage": ("mcap", "rosbag2 storage of recordings: mcap | sqlite3"),
    "record_tf_wait_s": (0.5, "seconds of images a recorded frame waits for its TF arm pose"),
}


class TrainerNode(Node):
    """Fine-tunes on request and hands the result to the running odometry node."""

    def __init__(self, node_name: str = "trainer_node", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("bags", [], ParameterDescriptor(dynamic_typing=True, description="rosbag paths to fine-tune on"))
        for name, (default, description) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(description=description))
        self.job: FinetuneJob | None = None
        self.recorder: LiveRecorder | None = None
        self.last_recording: RecordingSummary | None = None
        self._recording_subscriptions: list = []
        self._recording_timer = None
        self._pending_tf: PendingStamps | None = None
        self._tf_buffer: Buffer | None = None
        self._tf_listener: TransformListener | None = None
        self._reload_pending_since: float | None = None
        self._reload_client = None
        self._reload_client_name = ""
        self._progress_pub = self.create_publisher(String, "~/progress", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/cancel", self._on_cancel)
        self.create_service(SetBool, "~/record", self._on_record)
        self.create_timer(float(self._param("poll_period_s")), self._poll)
        self.create_timer(float(self._param("diagnostics_period_s")), self._publish_diagnostics)
        self.get_logger().info(f"trainer ready; models go to {self._store()}")

    # ---- parameters --------------------------------------------------------------------------

    def _param(self, name: str):
        return self.get_parameter(name).value

    def _store(self) -> str:
        return os.path.expanduser(str(self._param("output_store")))

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _bags(self) -> list[str]:
        value = self._param("bags")
        if isinstance(value, str):  # accept "a.mcap,b.mcap" from a launch argument
            value = value.split(",")
        return [os.path.expanduser(str(b).strip()) for b in (value or []) if isinstance(b, str) and b.strip()]

    def build_config(self) -> FinetuneConfig:
        """The job's settings from the current parameters (ConfigError when they are invalid)."""
        max_frames = int(self._param("max_frames"))
        return FinetuneConfig(
            bags=self._bags(),
            output=self._store(),
            init=os.path.expanduser(str(self._param("init_model"))),
            image_topic=str(self._param("image_topic")),
            pose_topic=str(self._param("pose_topic")),
            pose_source=str(self._param("pose_source")),
            tf_parent=str(self._param("tf_parent")),
            tf_child=str(self._param("tf_child")),
            T_tool_cam=[float(v) for v in self._param("T_tool_cam")],
            tolerance_s=float(self._param("tolerance_s")),
            steps=int(self._param("steps")),
            device=str(self._param("device")),
            max_frames=max_frames if max_frames > 0 else None,
            seed=int(self._param("seed")),
            threads=int(self._param("threads")),
            keep_versions=int(self._param("keep_versions")),
            camera_start=str(self._param("camera_start")),
            training_config=os.path.expanduser(str(self._param("training_config"))),
        )

    # ---- fine-tuning services ----------------------------------------------------------------

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.job is not None and self.job.running:
            response.success = False
            response.message = "a fine-tuning run is already in progress; call ~/cancel first"
            return response
        if self.recorder is not None:
            response.success = False
            response.message = f"recording into {self.recorder.path}; stop it first (~/record false)"
            return response
        try:
            config = self.build_config()
        except NocalError as error:
            response.success = False
            response.message = str(error)
            self.get_logger().error(response.message)
            return response
        if self.job is not None:
            self.job.close()
        self.job = FinetuneJob(config)
        self.job.start()
        self._reload_pending_since = None
        response.success = True
        response.message = f"fine-tuning {len(config.bags)} bag(s) for {config.steps} steps into {config.output} (worker pid {self.job.pid})"
        self.get_logger().info(response.message)
        self._publish_record({**self._summary(), "stage": "started", "pid": self.job.pid})
        return response

    def _on_cancel(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.job is None or not self.job.running:
            response.success = False
            response.message = "no fine-tuning run in progress"
            return response
        self.job.cancel()
        response.success = True
        response.message = "cancel requested; the previous model stays in use"
        self.get_logger().info(response.message)
        return response

    # ---- live recording ----------------------------------------------------------------------

    def _on_record(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        if not request.data:
            if self.recorder is None:
                response.success, response.message = False, "not recording"
                return response
            self._resolve_tf_poses()
            summary = self.recorder.stop(self._now_ns())
            response.success, response.message = self._recording_finished(summary)
            return response
        if self.recorder is not None:
            response.success, response.message = False, f"already recording into {self.recorder.path}"
            return response
        if self.job is not None and self.job.running:
            response.success, response.message = False, "a fine-tuning run is in progress; record after it"
            return response
        try:
            self._start_recording()
        except (NocalError, OSError) as error:
            response.success, response.message = False, f"cannot record: {error}"
            self.get_logger().error(response.message)
            return response
        limits = self.recorder.limits
        response.success = True
        response.message = (f"recording {self.recorder.image_topic} and arm poses ({self._param('pose_source')}) into "
                            f"{self.recorder.path}, for at most {limits.max_duration_s:g} s or {limits.max_bytes} bytes; "
                            "~/record false stops it")
        self.get_logger().info(response.message)
        self._publish_record({**self._summary(), "stage": "recording", "bag": str(self.recorder.path)})
        return response

    def _start_recording(self) -> None:
        pose_source = str(self._param("pose_source"))
        image_topic, pose_topic = str(self._param("image_topic")), str(self._param("pose_topic"))
        limits = RecordingLimits(int(self._param("record_max_bytes")), float(self._param("record_max_duration_s")))
        folder = Path(self._store()) / "recordings"
        folder.mkdir(parents=True, exist_ok=True)
        name = datetime.now(timezone.utc).strftime("recording-%Y%m%d-%H%M%S")
        path = folder / name
        for suffix in range(1, 100):  # two recordings in one second get distinct names
            if not path.exists():
                break
            path = folder / f"{name}-{suffix}"
        self.recorder = LiveRecorder(path, image_topic, pose_topic, limits, self._now_ns(),
                                     tf_parent=str(self._param("tf_parent")), tf_child=str(self._param("tf_child")),
                                     storage=str(self._param("record_storage")))
        # Best effort matches every publisher; deep enough that a busy executor drops nothing.
        qos = QoSProfile(history=qos_profile_sensor_data.history, depth=50, reliability=qos_profile_sensor_data.reliability)
        image_type = CompressedImage if self._param("compressed") else Image
        self._recording_subscriptions = [self.create_subscription(image_type, image_topic, self._on_record_image, qos)]
        if pose_source in ("pose", "auto"):
            self._recording_subscriptions.append(self.create_subscription(PoseStamped, pose_topic, self._on_record_pose, qos))
        self._pending_tf = None
        if pose_source in ("tf", "auto"):
            if self._tf_buffer is None:
                self._tf_buffer = Buffer()
                self._tf_listener = TransformListener(self._tf_buffer, self)
            self._pending_tf = PendingStamps(max_wait_s=float(self._param("record_tf_wait_s")))
        self._recording_timer = self.create_timer(0.1, self._recording_tick)

    def _on_record_image(self, msg: Any) -> None:
        recorder = self.recorder
        if recorder is not None and recorder.add_image(msg, self._now_ns()) and self._pending_tf is not None:
            self._pending_tf.add(stamp_to_ns(msg.header.stamp))

    def _on_record_pose(self, msg: PoseStamped) -> None:
        recorder = self.recorder
        if recorder is not None:
            recorder.add_pose(stamp_to_ns(msg.header.stamp), str(msg.header.frame_id), pose_msg_to_matrix(msg.pose), self._now_ns())

    def _tf_pose_at(self, stamp_ns: int):
        try:
            transform = self._tf_buffer.lookup_transform(str(self._param("tf_parent")), str(self._param("tf_child")),
                                                         Time(nanoseconds=stamp_ns))
        except TransformException:
            return None
        return transform_msg_to_matrix(transform.transform)

    def _resolve_tf_poses(self) -> None:
        if self._pending_tf is None or self.recorder is None:
            return
        for stamp, T_base_tool in self._pending_tf.resolve(self._tf_pose_at):
            self.recorder.add_tf(stamp, T_base_tool, self._now_ns())

    def _recording_tick(self) -> None:
        if self.recorder is None:
            return
        self._resolve_tf_poses()
        summary = self.recorder.check(self._now_ns())  # the duration limit, even with no frame arriving
        if summary is not None:  # a limit ended it (here or in a callback)
            self._recording_finished(summary)

    def _recording_finished(self, summary: RecordingSummary) -> tuple[bool, str]:
        """Tear the recording's subscriptions down; a bag with frames becomes the ``bags`` parameter."""
        for subscription in self._recording_subscriptions:
            self.destroy_subscription(subscription)
        self._recording_subscriptions = []
        if self._recording_timer is not None:
            self.destroy_timer(self._recording_timer)
            self._recording_timer = None
        self.recorder = None
        self.last_recording = summary
        record = {**self._summary(), "stage": "recorded", **summary.to_dict()}
        if summary.path is None:
            message = f"nothing recorded: no image arrived on {self._param('image_topic')} (stopped by {summary.stopped_by})"
            self.get_logger().warning(message)
            self._publish_record(record)
            return False, message
        self.set_parameters([Parameter("bags", Parameter.Type.STRING_ARRAY, [summary.path])])
        message = (f"recorded {summary.frames} frames and {summary.arm_poses} arm poses ({summary.duration_s:.1f} s, "
                   f"{summary.bytes} bytes, stopped by {summary.stopped_by}) into {summary.path}; "
                   "it is now the bags parameter: ~/start fine-tunes on it")
        if summary.rejected:
            message += f"; {summary.rejected} frame(s) skipped: {summary.problems[0]}"
        self.get_logger().info(message)
        self._publish_record(record)
        return True, message

    # ---- progress ----------------------------------------------------------------------------

    def _summary(self) -> dict:
        return self.job.status() if self.job is not None else {"state": "idle"}

    def _publish_record(self, record: dict) -> None:
        self._progress_pub.publish(String(data=json.dumps(record, default=str)))

    def _poll(self) -> None:
        if self.job is None:
            return
        was_running = self.job.running
        if was_running:
            for message in self.job.poll(grace_s=float(self._param("cancel_grace_s"))):
                if message.get("type") == "progress":
                    if message.get("stage") == "warning":
                        self.get_logger().warning(message.get("message", ""))
                    self._publish_record(progress_record(self.job.config, message))
        if was_running and not self.job.running:
            self._finished()
        if self._reload_pending_since is not None:
            self._try_reload()

    def _finished(self) -> None:
        job = self.job
        if job.state == "succeeded":
            self.get_logger().info(f"fine-tuning finished: {job.result['model_path']}")
            if str(self._param("reload_service")):
                self._reload_pending_since = time.monotonic()
        elif job.state == "cancelled":
            self.get_logger().info("fine-tuning cancelled; previous model kept")
        else:
            self.get_logger().error(f"fine-tuning failed: {job.error}")
        self._publish_record(final_record(job.status()))
        self._publish_diagnostics()

    def _try_reload(self) -> None:
        name = str(self._param("reload_service"))
        if self._reload_client is None or self._reload_client_name != name:
            if self._reload_client is not None:
                self.destroy_client(self._reload_client)
            self._reload_client = self.create_client(Trigger, name)
            self._reload_client_name = name
        if not self._reload_client.service_is_ready():
            if time.monotonic() - self._reload_pending_since > float(self._param("reload_timeout_s")):
                self._reload_pending_since = None
                self.get_logger().warning(f"{name} is not available; the odometry node was not told about the new model")
                self._publish_record({**self._summary(), "stage": "reload_failed", "reload_message": f"{name} not available"})
            return
        self._reload_pending_since = None
        future = self._reload_client.call_async(Trigger.Request())
        future.add_done_callback(self._reload_done)

    def _reload_done(self, future) -> None:
        try:
            reply = future.result()
        except Exception as error:  # a failed call must not take the node down
            reply = Trigger.Response(success=False, message=str(error))
        if reply is None:
            reply = Trigger.Response(success=False, message="no reply")
        if reply.success:
            self.get_logger().info(f"odometry node reloaded the model: {reply.message}")
        else:
            self.get_logger().error(f"odometry node refused the new model: {reply.message}")
        stage = "reloaded" if reply.success else "reload_failed"
        self._publish_record({**self._summary(), "stage": stage, "reload_message": reply.message})

    # ---- diagnostics -------------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        summary = self._summary()
        recording = None
        if self.recorder is not None:
            recording = {"frames": self.recorder.frames, "arm_poses": self.recorder.arm_poses,
                         "seconds": (self._now_ns() - self.recorder.start_ns) * 1e-9,
                         "expects_poses": str(self._param("pose_source")) != "none"}
        level, message = diagnostic_level(summary, recording)
        values = {**summary, **({f"recording_{k}": v for k, v in recording.items()} if recording else {})}
        status = DiagnosticStatus(name=f"{self.get_name()}: fine-tuning", hardware_id=self._store(),
                                  level=bytes([level]), message=message)
        status.values = [KeyValue(key=str(k), value=json.dumps(v) if not isinstance(v, str) else v) for k, v in values.items()]
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self._diagnostics_pub.publish(array)

    def destroy_node(self) -> None:
        if self.recorder is not None:
            self.recorder.stop(self._now_ns())  # keep what was recorded: the bag is complete on disk
            self.recorder = None
        if self.job is not None:
            self.job.close()  # never leave a worker training unattended
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        node = TrainerNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
