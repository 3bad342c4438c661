"""rclpy trainer node: field re-calibration from recorded rosbags, then a live model swap.

A thin adapter over ``nocal_ros.finetune``: parameters become a ``FinetuneConfig``, ``~/start`` and
``~/cancel`` (std_srvs/Trigger) start and stop a ``FinetuneJob`` (a separate worker process, so a
crash or out-of-memory in training cannot take this node down), a timer drains the job's progress
into ``~/progress`` (std_msgs/String, one JSON object per message) and ``/diagnostics``, and when a
run publishes a new model version the node calls the odometry node's reload service
(``reload_service``, std_srvs/Trigger). The odometry node must load from the same model store
(its ``model_path`` set to this node's ``output_store``), so reloading picks up ``latest``.
"""

from __future__ import annotations

import json
import os
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from nocal_ros.errors import NocalError
from nocal_ros.finetune import FinetuneConfig, FinetuneJob

DEFAULT_STORE = os.path.join("~", ".ros", "nocal_ros", "models")
IDENTITY_16 = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]

# name -> (default, description); bags is declared apart (an empty list needs dynamic typing).
PARAMETERS: dict[str, tuple[object, str]] = {
    "output_store": (DEFAULT_STORE, "model store directory new versions are published to"),
    "init_model": ("", "model to start from (file, version dir or store); empty: output_store's latest or the shipped model"),
    "image_topic": ("/camera/image_raw", "image topic in the bags"),
    "pose_topic": ("/arm/pose", "geometry_msgs/PoseStamped arm pose topic in the bags"),
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
}


class TrainerNode(Node):
    """Fine-tunes on request and hands the result to the running odometry node."""

    def __init__(self, node_name: str = "trainer_node", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("bags", [], ParameterDescriptor(dynamic_typing=True, description="rosbag paths to fine-tune on"))
        for name, (default, description) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(description=description))
        self.job: FinetuneJob | None = None
        self._reload_pending_since: float | None = None
        self._reload_client = None
        self._reload_client_name = ""
        self._progress_pub = self.create_publisher(String, "~/progress", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/cancel", self._on_cancel)
        self.create_timer(float(self._param("poll_period_s")), self._poll)
        self.create_timer(float(self._param("diagnostics_period_s")), self._publish_diagnostics)
        self.get_logger().info(f"trainer ready; models go to {self._store()}")

    # ---- parameters --------------------------------------------------------------------------

    def _param(self, name: str):
        return self.get_parameter(name).value

    def _store(self) -> str:
        return os.path.expanduser(str(self._param("output_store")))

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

    # ---- services ----------------------------------------------------------------------------

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.job is not None and self.job.running:
            response.success = False
            response.message = "a fine-tuning run is already in progress; call ~/cancel first"
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
        self._publish_progress({"stage": "started", "pid": self.job.pid})
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

    # ---- progress ----------------------------------------------------------------------------

    def _publish_progress(self, extra: dict | None = None) -> None:
        record = self.job.status() if self.job is not None else {"state": "idle"}
        record.update(extra or {})
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
                    self._publish_progress({k: v for k, v in message.items() if k != "type"})
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
        self._publish_progress()
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
                self._publish_progress({"stage": "reload_failed", "reload_message": f"{name} not available"})
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
        self._publish_progress({"stage": stage, "reload_message": reply.message})

    # ---- diagnostics -------------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name=f"{self.get_name()}: fine-tuning", hardware_id=self._store())
        summary = self.job.status() if self.job is not None else {"state": "idle"}
        state = summary["state"]
        if state == "failed":
            status.level, status.message = DiagnosticStatus.ERROR, f"failed: {summary.get('error', '')}"
        elif state == "cancelled" or summary.get("warnings"):
            status.level = DiagnosticStatus.WARN
            status.message = state if state == "cancelled" else f"{state}; scale not metric (no arm poses)"
        else:
            status.level, status.message = DiagnosticStatus.OK, state
        status.values = [KeyValue(key=str(k), value=json.dumps(v) if not isinstance(v, str) else v) for k, v in summary.items()]
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self._diagnostics_pub.publish(array)

    def destroy_node(self) -> None:
        if self.job is not None:
            self.job.close()  # never leave a worker training unattended
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = TrainerNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
