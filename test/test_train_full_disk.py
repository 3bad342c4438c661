"""``nocal train`` on a full disk: one line, no partial checkpoint files, and the last complete
checkpoint still loads and resumes. ENOSPC is made two ways: a deterministic one (the checkpoint
writer's file object fills up half-way through the second save) and the kernel's own, on a tiny tmpfs
(needs root to mount; skipped otherwise)."""

from __future__ import annotations

import builtins
import errno
import subprocess
import sys
from pathlib import Path

import pytest

import nocal_ros.checkpoint as checkpoint_module
from nocal_ros.checkpoint import load_checkpoint
from nocal_ros.cli import main

REPO = Path(__file__).resolve().parents[1]
TINY_RECIPE = REPO / "config" / "tiny.yaml"  # 20 steps, checkpoint every 10; last.safetensors is ~260 KB


class _FillsUp:
    """A file whose disk fills up after ``room`` bytes."""

    def __init__(self, handle, room: int) -> None:
        self.handle, self.room = handle, room

    def write(self, data) -> int:
        if len(data) > self.room:
            self.handle.write(data[: self.room])
            self.handle.flush()
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.handle.write(data)

    def __getattr__(self, name):
        return getattr(self.handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.handle.close()


def test_full_disk_during_a_checkpoint_save(tmp_path, monkeypatch, capsys):
    saves = []

    def open_filling_up(file, mode="r", *args, **kwargs):
        handle = builtins.open(file, mode, *args, **kwargs)
        if "w" in mode and Path(file).name.startswith(".last.safetensors."):
            saves.append(file)
            if len(saves) == 2:  # the second save of last.safetensors (step 20) meets a full disk
                return _FillsUp(handle, room=100_000)
        return handle

    monkeypatch.setattr(checkpoint_module, "open", open_filling_up, raising=False)
    out = tmp_path / "run"
    assert main(["train", "--config", str(TINY_RECIPE), "--out", str(out), "--threads", "1"]) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("nocal train")]  # the others are the progress bar
    assert lines == [f"nocal train: error: {out / 'last.safetensors'}: No space left on device while saving the "
                     "checkpoint; no partial file was left and the previous checkpoint is kept"], err[-2000:]
    assert "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["last.json", "last.safetensors", "metrics.csv"]  # no temporaries
    assert load_checkpoint(out / "last.safetensors").training["step"] == 10

    monkeypatch.undo()  # space freed: the run resumes from step 10 and finishes
    assert main(["train", "--config", str(TINY_RECIPE), "--out", str(out), "--threads", "1", "--resume"]) == 0
    assert load_checkpoint(out / "last.safetensors").training["step"] == 20 and (out / "model.safetensors").is_file()


@pytest.fixture
def small_tmpfs(tmp_path):
    mount = tmp_path / "tmpfs"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(mount)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_real_full_disk_during_training(small_tmpfs):
    """400 KiB: room for one resumable checkpoint (~260 KB) but not for its replacement beside it."""
    out = small_tmpfs / "run"
    done = subprocess.run([sys.executable, "-m", "nocal_ros.cli", "train", "--config", str(TINY_RECIPE), "--out", str(out),
                           "--threads", "1"], capture_output=True, text=True, timeout=600)
    lines = [line for line in done.stderr.splitlines() if line.startswith("nocal train")]
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert len(lines) == 1 and f"{out / 'last.safetensors'}: No space left on device" in lines[0], lines
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert load_checkpoint(out / "last.safetensors").training["step"] == 10
