"""Field re-calibration job: real bags, real training steps, real worker processes killed for real.

The store's own crash safety is in test_model_store.py; here the whole job is exercised: a worker
process reading rosbags written with rosbags, fine-tuning, publishing a version, being cancelled,
dying mid-run, or misbehaving, while the caller (the CLI or the trainer node) carries on.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from nocal_ros.data.bags import BagWriter
from nocal_ros.errors import BagError, ConfigError
from nocal_ros.finetune import FinetuneConfig, FinetuneJob, load_sequences, run_finetune
from nocal_ros.model_store import ModelStore


# ---- workers that misbehave (module level: the spawn context imports them by name) -------------


def worker_that_dies(config_values, messages, cancel, log_level):
    """Reports some progress, then vanishes like a process the OOM killer took."""
    messages.put({"type": "progress", "stage": "training", "step": 1})
    time.sleep(0.2)
    os.kill(os.getpid(), signal.SIGKILL)


def worker_that_ignores_cancel(config_values, messages, cancel, log_level):
    """Stuck in something that never polls should_stop (a hung data loader, a CUDA call)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # only SIGKILL gets it: the job must escalate
    messages.put({"type": "progress", "stage": "training", "step": 1})
    while True:
        time.sleep(0.05)


def worker_that_lingers_after_cancelling(config_values, messages, cancel, log_level):
    """Says it was cancelled, then does not exit (a slow interpreter teardown on a loaded machine)."""
    messages.put({"type": "cancelled", "message": "cancelled during training; previous model kept"})
    while True:
        time.sleep(0.05)


# ---- helpers -----------------------------------------------------------------------------------


def write_bag(path, images=True, poses=True, frames=4):
    rng = np.random.default_rng(0)
    with BagWriter(path) as bag:
        for i in range(frames):
            stamp = 1_000_000_000 + i * 100_000_000
            if images:
                bag.write_image("/camera/image_raw", stamp, "camera_optical", rng.integers(0, 255, (12, 16, 3), dtype=np.uint8))
            if poses:
                T = np.eye(4)
                T[0, 3] = 0.01 * i
                bag.write_pose("/arm/pose", stamp, "base", T)
    return path


# ---- configuration and input -------------------------------------------------------------------


def test_config_rejects_bad_settings(tmp_path):
    good = dict(bags=[str(tmp_path / "a.mcap")], output=str(tmp_path / "store"))
    assert FinetuneConfig.from_dict(good).hand_eye.shape == (4, 4)
    assert FinetuneConfig.from_dict({**good, "bags": str(tmp_path / "a.mcap")}).bags == [str(tmp_path / "a.mcap")]
    cases = [
        ({"bags": []}, "at least one bag"),
        ({"pose_source": "gps"}, "pose_source"),
        ({"T_tool_cam": [1.0] * 16}, "not a rigid transform"),
        ({"T_tool_cam": [float("nan")] * 16}, "16 finite numbers"),
        ({"T_tool_cam": [1.0, 0.0]}, "16 finite numbers"),
        ({"steps": 0}, "steps must be positive"),
        ({"tolerance_s": -1.0}, "tolerance_s"),
        ({"camera_start": "guess"}, "camera_start"),
        ({"learning_rate": 1.0}, "unknown fine-tuning settings: learning_rate"),
    ]
    for change, message in cases:
        with pytest.raises(ConfigError, match=message):
            FinetuneConfig.from_dict({**good, **change})
    # A hand-eye rotation about z by 90 degrees with an offset is a valid rigid transform.
    T = np.array([[0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]], dtype=float)
    assert np.array_equal(FinetuneConfig.from_dict({**good, "T_tool_cam": T.ravel().tolist()}).hand_eye, T)


def test_bag_without_images_fails_clearly(tmp_path):
    bag = write_bag(tmp_path / "poses_only.mcap", images=False)
    config = FinetuneConfig(bags=[str(bag)], output=str(tmp_path / "store"))
    with pytest.raises(BagError, match=r"poses_only\.mcap.*image topic '/camera/image_raw'"):
        load_sequences(config, [])


def test_bag_without_images_fails_in_worker_and_keeps_store(tmp_path):
    store = ModelStore(tmp_path / "store")
    with store.new_version() as staging:
        (staging / "model.safetensors").write_bytes(b"previous")
    bag = write_bag(tmp_path / "poses_only.mcap", images=False)
    job = FinetuneJob(FinetuneConfig(bags=[str(bag)], output=str(store.root)))
    job.start()
    assert job.wait(timeout=120) == "failed"
    assert "poses_only.mcap" in job.error and "image topic" in job.error
    assert job.status()["state"] == "failed"
    assert store.latest().name == "v0001" and [v.name for v in store.versions()] == ["v0001"]


def test_bag_without_poses_reads_unlabelled_and_warns(tmp_path, caplog):
    bag = write_bag(tmp_path / "images_only.mcap", poses=False)
    config = FinetuneConfig(bags=[str(bag)], output=str(tmp_path / "store"))
    warnings = []
    with caplog.at_level("WARNING", logger="nocal_ros.finetune"):
        sequences = load_sequences(config, warnings)
    assert len(sequences) == 1 and len(sequences[0]) == 4 and not sequences[0].labelled.any()
    assert len(warnings) == 1 and "scale is not metric" in warnings[0] and "images_only.mcap" in warnings[0]
    assert "scale is not metric" in caplog.text
    # With arm poses there is nothing to warn about.
    warnings = []
    labelled = load_sequences(FinetuneConfig(bags=[str(write_bag(tmp_path / "arm.mcap"))], output=str(tmp_path)), warnings)
    assert labelled[0].labelled.all() and warnings == []


# ---- worker supervision ------------------------------------------------------------------------


def test_worker_killed_by_the_system_is_reported_and_caller_survives(tmp_path):
    job = FinetuneJob(FinetuneConfig(bags=["unused.mcap"], output=str(tmp_path / "store")), worker=worker_that_dies)
    job.start()
    assert job.wait(timeout=60) == "failed"
    assert job.last_progress["step"] == 1
    assert "signal 9" in job.error and "previous model kept" in job.error
    assert not job.running


def test_cancel_escalates_to_kill_when_worker_ignores_it(tmp_path):
    job = FinetuneJob(FinetuneConfig(bags=["unused.mcap"], output=str(tmp_path / "store")), worker=worker_that_ignores_cancel)
    job.start()
    deadline = time.monotonic() + 60
    while not job.last_progress and time.monotonic() < deadline:
        job.poll()
        time.sleep(0.05)
    assert job.last_progress["step"] == 1
    pid = job.pid
    job.cancel()
    job.poll(grace_s=0.5)
    assert job.running  # still within the grace period
    time.sleep(0.7)
    job.poll(grace_s=0.5)
    assert job.state == "cancelled" and "terminated" in job.error
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    job.close()


def test_a_finished_jobs_worker_is_gone_even_when_it_lingers_after_its_result(tmp_path):
    job = FinetuneJob(FinetuneConfig(bags=["unused.mcap"], output=str(tmp_path / "store")),
                      worker=worker_that_lingers_after_cancelling)
    job.exit_grace_s = 0.5
    job.start()
    assert job.wait(timeout=60) == "cancelled" and "previous model kept" in job.error
    with pytest.raises(ProcessLookupError):  # reaped, not a zombie the trainer node's test would find
        os.kill(job.pid, 0)
    job.close()


# ---- the real job: bags rendered through a known camera, a tiny model, real training steps -------

TINY_RECIPE = str(Path(__file__).resolve().parents[1] / "config" / "tiny.yaml")


@pytest.fixture(scope="module")
def field_data(tmp_path_factory):
    """A rendered 48x36 camera's bag with arm poses, the same footage without, and a tiny initial model."""
    import torch

    from nocal_ros.camera import CameraModel
    from nocal_ros.checkpoint import save_checkpoint
    from nocal_ros.config import load_config
    from nocal_ros.data.bags import write_sequence
    from nocal_ros.data.synthetic import random_calibration, render_sequence
    from nocal_ros.model import NOCaL

    root = tmp_path_factory.mktemp("field")
    calibration = random_calibration(np.random.default_rng(1), 48, 36)
    sequence = render_sequence(calibration, 8, seed=3, labelled_fraction=0.5)
    labelled_bag = write_sequence(sequence, root / "arm.mcap")
    sequence.arm_poses[:] = np.nan
    unlabelled_bag = write_sequence(sequence, root / "walk.mcap")
    torch.manual_seed(0)
    model = NOCaL(load_config(Path(TINY_RECIPE))["model"])
    init = save_checkpoint(root / "init.safetensors", model, [CameraModel(48, 36)], {"training_resolution": [32, 24]})
    return {"arm": str(labelled_bag), "walk": str(unlabelled_bag), "init": init, "calibration": calibration}


def seeded_store(path, init):
    store = ModelStore(path)
    store.publish_file(init, {"kind": "shipped"})
    return store


def tiny_config(bags, store, **changes):
    values = dict(bags=bags, output=str(store.root), steps=30, threads=1, training_config=TINY_RECIPE,
                  training={"log_every": 5})
    values.update(changes)
    return FinetuneConfig(**values)


def test_finetune_publishes_a_loadable_version_and_learns(tmp_path, field_data):
    from nocal_ros.checkpoint import load_checkpoint

    store = seeded_store(tmp_path / "store", field_data["init"])
    records = []
    result = run_finetune(tiny_config([field_data["arm"], field_data["walk"]], store), progress=records.append)
    assert result.version == "v0002" and store.latest().name == "v0002" and result.warnings == []
    store.verify(store.latest())
    assert not [p for p in store.root.iterdir() if p.name.startswith(".")]
    assert not list(store.latest().path.glob("last.*"))  # no optimiser state shipped to the nodes
    stages = [r["stage"] for r in records]
    assert stages[:2] == ["loading_bags", "loading_model"] and stages[-2:] == ["saving", "done"]
    training = [r for r in records if r.get("loss") is not None]
    assert [r["step"] for r in training] == [5, 10, 15, 20, 25, 30]
    assert all(r["total_steps"] == 30 and r["eta_s"] >= 0 and r["fx"] > 0 and r["cy"] > 0 for r in training)
    # Real training: the loss falls from the first logged window to the last.
    assert training[-1]["loss"] < training[0]["loss"]
    # Curriculum scaled to 30 steps: the focal stage started, so focal moved off its f = width start.
    assert {r["stage"] for r in training} >= {"fixed", "full"}
    loaded = load_checkpoint(store.root)
    fx, fy, cx, cy = (float(v.detach()) for v in loaded.cameras[0].intrinsics())
    assert (fx, fy, cx, cy) == pytest.approx((training[-1]["fx"], training[-1]["fy"], training[-1]["cx"], training[-1]["cy"]), rel=1e-6)
    assert fx != pytest.approx(48.0, abs=1e-3)
    facts = store.latest().metadata
    assert facts["metric_scale"] is True and facts["labelled_frames"] == 4 and facts["frames"] == 16
    previous = load_checkpoint(store.versions()[0].path)
    assert not torch_equal(previous.model.state_dict(), loaded.model.state_dict())


def torch_equal(a, b):
    import torch

    return all(torch.equal(a[k], b[k]) for k in a)


def test_bag_without_arm_poses_still_finetunes_but_warns_scale(tmp_path, field_data):
    store = seeded_store(tmp_path / "store", field_data["init"])
    result = run_finetune(tiny_config([field_data["walk"]], store, steps=10))
    assert result.version == "v0002"
    assert len(result.warnings) == 1 and "scale is not metric" in result.warnings[0]
    assert store.latest().metadata["metric_scale"] is False


def wait_for_training(job, timeout=120):
    deadline = time.monotonic() + timeout
    while not (job.last_progress.get("stage") in ("fixed", "focal", "full") and job.last_progress.get("step")):
        job.poll()
        assert job.running, job.error
        assert time.monotonic() < deadline, "training never reported progress"
        time.sleep(0.05)


def test_cancel_stops_the_worker_and_keeps_the_previous_model(tmp_path, field_data):
    from nocal_ros.checkpoint import load_checkpoint

    store = seeded_store(tmp_path / "store", field_data["init"])
    job = FinetuneJob(tiny_config([field_data["arm"]], store, steps=100000))
    job.start()
    wait_for_training(job)
    job.cancel()
    assert job.wait(timeout=60) == "cancelled"
    assert "previous model kept" in job.error
    with pytest.raises(ProcessLookupError):
        os.kill(job.pid, 0)
    assert [v.name for v in store.versions()] == ["v0001"] and store.latest().name == "v0001"
    assert not [p for p in store.root.iterdir() if p.name.startswith(".staging-")]
    load_checkpoint(store.root)
    job.close()


def test_worker_killed_mid_write_leaves_latest_complete_and_loadable(tmp_path, field_data, monkeypatch):
    from nocal_ros.checkpoint import load_checkpoint

    store = seeded_store(tmp_path / "store", field_data["init"])
    paused = tmp_path / "paused"
    # The spawned worker inherits these: it stops inside the commit, after training wrote the new model
    # into its staging directory, until the test SIGKILLs it.
    monkeypatch.setenv("NOCAL_STORE_PAUSE_AT", "manifest-written")
    monkeypatch.setenv("NOCAL_STORE_PAUSE_FILE", str(paused))
    job = FinetuneJob(tiny_config([field_data["arm"]], store, steps=5))
    job.start()
    deadline = time.monotonic() + 120
    while not paused.exists():
        job.poll()
        assert job.running, job.error
        assert time.monotonic() < deadline
        time.sleep(0.05)
    staging = [p for p in store.root.iterdir() if p.name.startswith(".staging-")]
    assert len(staging) == 1 and (staging[0] / "model.safetensors").is_file()
    os.kill(job.pid, signal.SIGKILL)
    assert job.wait(timeout=30) == "failed" and "signal 9" in job.error
    assert store.latest().name == "v0001"
    store.verify(store.latest())
    assert load_checkpoint(store.root).metadata.get("training_resolution") == [32, 24]
    # The next run (no pause this time) cleans the dead worker's staging and publishes.
    monkeypatch.delenv("NOCAL_STORE_PAUSE_AT")
    assert run_finetune(tiny_config([field_data["arm"]], store, steps=2)).version == "v0002"
    assert not [p for p in store.root.iterdir() if p.name.startswith(".staging-")]
    load_checkpoint(store.root)
