"""The rclpy trainer node with real rclpy: start a fine-tuning run over a service, follow its progress
on ``~/progress`` and ``/diagnostics``, cancel one, and see the running odometry node reload the new
model from the shared store.

Skipped where rclpy cannot be imported (no ROS 2 installation); run on ROS 2 Jazzy.
"""

from __future__ import annotations

import json
import os
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy is not installed (no ROS 2 here); run these tests on ROS 2 Jazzy")
pytest.importorskip("tf2_ros", reason="tf2_ros is not installed (no ROS 2 here); run these tests on ROS 2 Jazzy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from nocal_ros.camera import CameraModel  # noqa: E402
from nocal_ros.checkpoint import save_checkpoint  # noqa: E402
from nocal_ros.commands.train import load_config  # noqa: E402
from nocal_ros.data.bags import write_sequence  # noqa: E402
from nocal_ros.data.synthetic import random_calibration, render_sequence  # noqa: E402
from nocal_ros.model import NOCaL  # noqa: E402
from nocal_ros.model_store import ModelStore  # noqa: E402
from nocal_ros.ros.odometry_node import OdometryNode  # noqa: E402
from nocal_ros.ros.trainer_node import TrainerNode  # noqa: E402

TINY_RECIPE = str(Path(__file__).resolve().parents[1] / "config" / "tiny.yaml")


def wait_for(condition, timeout: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


class Harness(Node):
    """Calls the trainer's services and records its progress and diagnostics."""

    def __init__(self, context, namespace: str) -> None:
        super().__init__("trainer_test_harness", context=context, namespace=namespace)
        self.namespace = namespace
        self.progress: list[dict] = []
        self.diagnostics: list[DiagnosticStatus] = []
        self.create_subscription(String, f"{namespace}/trainer_node/progress", lambda m: self.progress.append(json.loads(m.data)), 100)
        self.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self.diagnostics.extend(
            s for s in m.status if s.hardware_id == self.store_id), 50)
        self.store_id = ""

    def call(self, service: str, timeout: float = 30.0) -> Trigger.Response:
        client = self.create_client(Trigger, f"{self.namespace}/{service}")
        try:
            assert client.wait_for_service(timeout_sec=timeout), f"{service} not available"
            future = client.call_async(Trigger.Request())
            assert wait_for(future.done, timeout), f"{service} did not answer"
            return future.result()
        finally:
            self.destroy_client(client)

    def stages(self) -> list[str]:
        return [p.get("stage") for p in self.progress]


@pytest.fixture(scope="module")
def field_data(tmp_path_factory):
    import torch

    root = tmp_path_factory.mktemp("field")
    calibration = random_calibration(np.random.default_rng(1), 48, 36)
    bag = write_sequence(render_sequence(calibration, 8, seed=3, labelled_fraction=0.5), root / "arm.mcap")
    torch.manual_seed(0)
    init = save_checkpoint(root / "init.safetensors", NOCaL(load_config(Path(TINY_RECIPE))["model"]),
                           [CameraModel(48, 36)], {"training_resolution": [32, 24]})
    return {"bag": str(bag), "init": init}


@pytest.fixture
def nodes(tmp_path, field_data, request):
    """A trainer and an odometry node sharing one store (seeded with the initial model), both spinning."""
    steps = getattr(request, "param", 10)
    namespace = f"/t{uuid.uuid4().hex[:8]}"  # parallel test runs on one ROS domain must not meet
    store = ModelStore(tmp_path / "store")
    store.publish_file(field_data["init"], {"kind": "shipped"})
    context = Context()
    rclpy.init(context=context)
    odometry = OdometryNode(context=context, namespace=namespace, parameter_overrides=[
        Parameter("model_path", value=str(store.root)), Parameter("device", value="cpu")])
    trainer = TrainerNode(context=context, namespace=namespace, parameter_overrides=[
        Parameter("bags", value=[field_data["bag"]]),
        Parameter("output_store", value=str(store.root)),
        Parameter("training_config", value=TINY_RECIPE),
        Parameter("steps", value=steps),
        Parameter("threads", value=1),
        Parameter("device", value="cpu"),
        Parameter("reload_service", value=f"{namespace}/odometry_node/reload_model"),
        Parameter("poll_period_s", value=0.05),
        Parameter("diagnostics_period_s", value=0.2),
    ])
    harness = Harness(context, namespace)
    harness.store_id = str(store.root)
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    for node in (odometry, trainer, harness):
        executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    assert wait_for(lambda: harness.count_publishers(f"{namespace}/trainer_node/progress") > 0, 10)
    yield trainer, odometry, harness, store
    executor.shutdown()
    for node in (trainer, odometry, harness):
        node.destroy_node()
    rclpy.shutdown(context=context)
    spinner.join(timeout=5)


def test_start_reports_progress_publishes_and_the_odometry_node_reloads(nodes):
    trainer, odometry, harness, store = nodes
    assert odometry.estimator.model_id.startswith("init.safetensors@")
    response = harness.call("trainer_node/start")
    assert response.success, response.message
    assert "worker pid" in response.message
    refused = harness.call("trainer_node/start")  # one run at a time
    assert not refused.success and "already in progress" in refused.message

    assert wait_for(lambda: "reloaded" in harness.stages(), 180), harness.progress[-3:]
    training = [p for p in harness.progress if p.get("loss") is not None]
    assert training and all(p["state"] == "running" and p["total_steps"] == 10 for p in training)
    assert all(k in training[-1] for k in ("step", "loss", "fx", "fy", "cx", "cy", "eta_s"))
    done = next(p for p in harness.progress if p.get("stage") == "done")
    assert done["version"] == "v0002" == store.latest().name
    # The odometry node now runs the fine-tuned model from the store's latest version.
    assert odometry.estimator.model_id.startswith("model.safetensors@")
    assert wait_for(lambda: any(s.message == "succeeded" and s.level == DiagnosticStatus.OK for s in harness.diagnostics), 10)


@pytest.mark.parametrize("nodes", [100000], indirect=True)
def test_cancel_stops_the_run_and_keeps_the_previous_model(nodes):
    trainer, odometry, harness, store = nodes
    assert not harness.call("trainer_node/cancel").success  # nothing to cancel yet
    assert harness.call("trainer_node/start").success
    assert wait_for(lambda: any(p.get("loss") is not None for p in harness.progress), 180)
    response = harness.call("trainer_node/cancel")
    assert response.success and "previous model" in response.message
    assert wait_for(lambda: any(p.get("state") == "cancelled" for p in harness.progress), 60)
    assert trainer.job.state == "cancelled"
    with pytest.raises(ProcessLookupError):  # the worker is gone (and reaped), not left training
        os.kill(trainer.job.pid, 0)
    assert store.latest().name == "v0001" and [v.name for v in store.versions()] == ["v0001"]
    assert odometry.estimator.model_id.startswith("init.safetensors@")
    assert "reloaded" not in harness.stages()
    assert wait_for(lambda: any(s.level == DiagnosticStatus.WARN and s.message == "cancelled" for s in harness.diagnostics), 10)


def test_start_with_bad_parameters_is_refused_with_the_reason(nodes):
    trainer, odometry, harness, store = nodes
    trainer.set_parameters([Parameter("bags", value=[""])])
    response = harness.call("trainer_node/start")
    assert not response.success and "at least one bag" in response.message
    trainer.set_parameters([Parameter("bags", value=["/nonexistent/bag.mcap"]), Parameter("pose_source", value="gps")])
    response = harness.call("trainer_node/start")
    assert not response.success and "pose_source" in response.message
    # A run on a missing bag starts, fails in the worker, and says so; the node stays up.
    trainer.set_parameters([Parameter("pose_source", value="auto")])
    assert harness.call("trainer_node/start").success
    assert wait_for(lambda: any(p.get("state") == "failed" for p in harness.progress), 120)
    failed = next(p for p in harness.progress if p.get("state") == "failed")
    assert "/nonexistent/bag.mcap" in failed["error"]
    assert wait_for(lambda: any(s.level == DiagnosticStatus.ERROR for s in harness.diagnostics), 10)
    assert store.latest().name == "v0001"
