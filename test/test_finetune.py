"""Field re-calibration job: real bags, real training steps, real worker processes killed for real.

The store's own crash safety is in test_model_store.py; here the whole job is exercised: a worker
process reading rosbags written with rosbags, fine-tuning, publishing a version, being cancelled,
dying mid-run, or misbehaving, while the caller (the CLI or the trainer node) carries on.
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from nocal_ros.data.bags import BagWriter
from nocal_ros.errors import BagError, ConfigError
from nocal_ros.finetune import FinetuneConfig, FinetuneJob, load_sequences
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
