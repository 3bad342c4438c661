"""The trainer node's progress records and diagnostics summary, without ROS.

Each record the node publishes on ``~/progress`` is built from one message of the fine-tuning job
(:meth:`nocal_ros.finetune.FinetuneJob.poll`), with the state that message left the job in: a batch of
messages drained in one poll (the last training step, saving, done, the result) is published as it
happened, never labelled with the state at the end of the batch.
"""

from __future__ import annotations

from typing import Any

from nocal_ros.live.health import ERROR, OK, WARN


def progress_record(config: Any, message: dict) -> dict:
    """The ``~/progress`` record of one job message: the run's store and bags, then the message's own
    fields (stage, step, loss, camera..., and ``state``, set by the job when it handled the message)."""
    record = {"output": config.output, "bags": list(config.bags)}
    record.update({key: value for key, value in message.items() if key != "type"})
    return record


def final_record(summary: dict) -> dict:
    """The ``~/progress`` record that ends a run: its stage is the final state, and it carries the
    outcome (version or error) but none of the last step's fields, which belong to that step's record."""
    record = {key: summary[key] for key in ("state", "output", "bags", "warnings", "error", "version", "model_path")
              if key in summary}
    record["stage"] = summary["state"]
    return record


def diagnostic_level(summary: dict, recording: dict | None = None) -> tuple[int, str]:
    """``(level, message)`` for ``/diagnostics`` from a job summary (:meth:`FinetuneJob.status`, or
    ``{"state": "idle"}``) and, while one runs, the live recording's counts.

    ERROR when the last run failed; WARN when it was cancelled, trained without arm poses, or a
    recording has frames but no arm pose; else OK with the state.
    """
    if recording is not None:
        text = (f"recording: {recording['frames']} frames, {recording['arm_poses']} arm poses, "
                f"{recording['seconds']:.1f} s")
        if recording["frames"] >= 10 and recording["arm_poses"] == 0 and recording.get("expects_poses", True):
            return WARN, f"{text}; no arm pose yet (the fine-tune's scale will not be metric)"
        return OK, text
    state = summary["state"]
    if state == "failed":
        return ERROR, f"failed: {summary.get('error', '')}"
    if state == "cancelled":
        return WARN, state
    if summary.get("warnings"):
        return WARN, f"{state}; scale not metric (no arm poses)"
    return OK, state
