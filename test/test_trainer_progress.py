"""The trainer node's progress records, without ROS: the race real Jazzy showed (issue 12).

When the last training step, the saving, the done record and the result all land in one poll, the
node used to label every record with the state at the end of the batch, so step 10 went out as
"succeeded". Each record now carries the state the job was in when it handled that message.
"""

from __future__ import annotations

import time
from pathlib import Path

from nocal_ros.finetune import FinetuneConfig, FinetuneJob
from nocal_ros.live.health import ERROR, OK, WARN
from nocal_ros.live.trainer import diagnostic_level, final_record, progress_record


def worker_that_finishes_in_one_batch(config_values, messages, cancel, log_level):
    """The end of a real run, sent at once: the batch the failing trace showed, then a marker file once
    the queue has flushed every message into the pipe (so the caller's next poll sees all of them)."""
    for message in (
        {"type": "progress", "stage": "full", "step": 10, "total_steps": 10, "loss": 0.5},
        {"type": "progress", "stage": "saving", "step": 10, "total_steps": 10},
        {"type": "progress", "stage": "done", "step": 10, "total_steps": 10, "version": "v0002"},
        {"type": "result", "version": "v0002", "model_path": "/store/v0002/model.safetensors", "warnings": [],
         "steps": 10, "seconds": 1.0, "final": {}},
    ):
        messages.put(message)
    messages.close()
    messages.join_thread()
    Path(config_values["output"], "batch-sent").touch()


def test_a_batch_drained_in_one_poll_keeps_each_records_own_state(tmp_path):
    config = FinetuneConfig(bags=["arm.mcap"], output=str(tmp_path))
    job = FinetuneJob(config, worker=worker_that_finishes_in_one_batch)
    job.start()
    deadline = time.monotonic() + 60
    while not (tmp_path / "batch-sent").exists():
        assert time.monotonic() < deadline, "the worker never sent its batch"
        time.sleep(0.02)
    batch = job.poll()
    assert [m["type"] for m in batch] == ["progress", "progress", "progress", "result"]  # one poll, the whole batch
    assert job.state == "succeeded"
    records = [progress_record(config, m) for m in batch if m["type"] == "progress"]
    assert [(r["stage"], r["state"]) for r in records] == [("full", "running"), ("saving", "running"), ("done", "running")]
    assert all(r["total_steps"] == 10 and r["output"] == str(tmp_path) and r["bags"] == ["arm.mcap"] for r in records)
    assert "type" not in records[0] and records[2]["version"] == "v0002"
    assert batch[-1]["state"] == "succeeded" and job.status()["state"] == "succeeded"
    # The record that ends the run says how it ended, and carries none of the last step's fields.
    final = final_record(job.status())
    assert final == {"state": "succeeded", "stage": "succeeded", "output": str(tmp_path), "bags": ["arm.mcap"],
                     "version": "v0002", "model_path": "/store/v0002/model.safetensors"}
    job.close()


def test_diagnostic_levels():
    assert diagnostic_level({"state": "idle"}) == (OK, "idle")
    assert diagnostic_level({"state": "succeeded"}) == (OK, "succeeded")
    assert diagnostic_level({"state": "failed", "error": "no bag"}) == (ERROR, "failed: no bag")
    assert diagnostic_level({"state": "cancelled"}) == (WARN, "cancelled")
    assert diagnostic_level({"state": "succeeded", "warnings": ["x"]}) == (WARN, "succeeded; scale not metric (no arm poses)")
    recording = {"frames": 12, "arm_poses": 0, "seconds": 1.25}
    assert diagnostic_level({"state": "idle"}, recording)[0] == WARN
    assert diagnostic_level({"state": "idle"}, {**recording, "expects_poses": False}) == (OK, "recording: 12 frames, 0 arm poses, 1.2 s")
    assert diagnostic_level({"state": "idle"}, {**recording, "arm_poses": 12}) == (OK, "recording: 12 frames, 12 arm poses, 1.2 s")
