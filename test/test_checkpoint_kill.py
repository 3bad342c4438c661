"""A checkpoint's weights and sidecar are replaced as a pair: a SIGKILL at any point of ``save_checkpoint``
leaves a complete pair that loads (the new one, or the previous one), and ``--resume`` still works.

Kills are real: a child process is held at a named point of the commit by the test hook
``NOCAL_CHECKPOINT_PAUSE_AT`` (``nocal_ros.files.pause_point``) and SIGKILLed there.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nocal_ros.checkpoint import load_checkpoint, previous_paths, sidecar_path

REPO = Path(__file__).resolve().parents[1]
TINY_RECIPE = REPO / "config" / "tiny.yaml"
PAUSE_POINTS = ("previous-kept", "weights-replaced", "sidecar-replaced")  # nocal_ros.checkpoint.PAUSE_POINTS

WRITER = r"""
import sys, torch
from nocal_ros.camera import CameraModel
from nocal_ros.checkpoint import save_checkpoint
from nocal_ros.model import NOCaL
tiny = dict(encoder_channels=[8] * 7, latent_dim=16, scene_width=16, pose_width=16, hyper_width=16,
            hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2)

def save(path, seed):
    torch.manual_seed(seed)
    save_checkpoint(path, NOCaL(tiny), [CameraModel(32, 24)], {"training_resolution": [32, 24], "seed": seed})

if __name__ == "__main__":
    save(sys.argv[1], int(sys.argv[2]))
"""
namespace: dict = {}
exec(WRITER, namespace)  # the same writer in this process, for the saves that are not killed
save = namespace["save"]


def hooked_env(pause_at: str, pause_file: Path) -> dict:
    return dict(os.environ, NOCAL_CHECKPOINT_PAUSE_AT=pause_at, NOCAL_CHECKPOINT_PAUSE_FILE=str(pause_file))


def kill_at_pause(proc: subprocess.Popen, pause_file: Path, timeout: float = 240.0) -> None:
    """Wait until ``proc`` is held at its pause point, then SIGKILL it."""
    deadline = time.monotonic() + timeout
    try:
        while not pause_file.exists():
            assert proc.poll() is None, f"the writer exited ({proc.returncode}) without reaching the pause point"
            assert time.monotonic() < deadline, "the writer never reached the pause point"
            time.sleep(0.02)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def debris(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


@pytest.mark.parametrize("pause_at", PAUSE_POINTS)
def test_sigkill_inside_save_leaves_a_complete_pair(tmp_path, pause_at):
    path = tmp_path / "last.safetensors"
    save(path, 1)
    pause_file = tmp_path / "paused"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path), "2"], env=hooked_env(pause_at, pause_file))
    kill_at_pause(proc, pause_file)

    expected = 2 if pause_at == "sidecar-replaced" else 1  # the old pair until the new sidecar is in place
    loaded = load_checkpoint(path)
    assert loaded.metadata["metadata"]["seed"] == expected
    if pause_at == "weights-replaced":  # the window: new weights under the old sidecar; the previous pair holds
        assert json.loads(sidecar_path(path).read_text())["metadata"]["seed"] == 1
        assert all(p.is_file() for p in previous_paths(path))

    # The next save completes the protocol and leaves no debris (no .previous pair, no temporary files).
    save(path, 3)
    assert load_checkpoint(path).metadata["metadata"]["seed"] == 3
    assert debris(tmp_path) == []


def test_sigkill_of_a_resumed_run_between_the_renames_keeps_it_resumable(tmp_path):
    """``nocal train`` finishes 4 steps; a ``--resume`` to 8 steps is killed while replacing
    last.safetensors, between the weights and the sidecar (the issue's lost checkpoint); a second
    ``--resume`` continues from step 4 and finishes."""
    from nocal_ros.cli import main

    out = tmp_path / "run"
    arguments = ["train", "--config", str(TINY_RECIPE), "--out", str(out), "--threads", "1"]
    command = [sys.executable, "-m", "nocal_ros.cli", *arguments]
    assert main(arguments + ["--steps", "4"]) == 0
    assert json.loads((out / "last.json").read_text())["training"]["step"] == 4

    pause_file = tmp_path / "paused"
    proc = subprocess.Popen(command + ["--steps", "8", "--resume"], env=hooked_env("weights-replaced", pause_file),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_at_pause(proc, pause_file, timeout=600)
    assert json.loads((out / "last.json").read_text())["training"]["step"] == 4  # the old sidecar...
    assert load_checkpoint(out / "last.safetensors").training["step"] == 4  # ...and its weights, kept aside

    assert main(arguments + ["--steps", "8", "--resume"]) == 0
    assert load_checkpoint(out / "last.safetensors").training["step"] == 8
    assert load_checkpoint(out / "model.safetensors").metadata["config"]["steps"] == 8
    assert debris(out) == []
