"""The model store: versions appear whole or not at all, and ``latest`` always names a complete one.

Kills are real: a child Python process publishes a version and is SIGKILLed at each point of the commit
sequence (held there by the store's pause hook), and at random moments while it publishes in a loop.
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

from nocal_ros.errors import CheckpointError
from nocal_ros.model_store import MODEL_NAME, PAUSE_POINTS, POINTER_NAME, ModelStore, resolve_model_path

WRITER = r"""
import os, sys
from nocal_ros.model_store import ModelStore
store = ModelStore(sys.argv[1])
payload = sys.argv[2].encode()
count = int(sys.argv[3])
for i in range(count):
    with store.new_version({"payload": sys.argv[2], "i": i}) as staging:
        with open(staging / "model.safetensors", "wb") as f:
            # large enough that a random kill often lands inside the write
            for _ in range(64):
                f.write(payload * (4096 // len(payload) + 1))
        (staging / "model.json").write_text('{"i": %d}' % i)
"""


def publish_bytes(store: ModelStore, data: bytes, metadata: dict | None = None):
    with store.new_version(metadata) as staging:
        (staging / MODEL_NAME).write_bytes(data)
        (staging / "model.json").write_text("{}")
    return store.last_published


def spawn_writer(root: Path, payload: str, count: int, env_extra: dict | None = None) -> subprocess.Popen:
    env = dict(os.environ, **(env_extra or {}))
    return subprocess.Popen([sys.executable, "-c", WRITER, str(root), payload, str(count)], env=env)


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert proc.poll() is None, f"writer exited early with {proc.returncode}"
        assert time.monotonic() < deadline, "writer never reached the pause point"
        time.sleep(0.02)


def test_publish_versions_and_resolve(tmp_path):
    store = ModelStore(tmp_path / "store")
    assert store.latest() is None
    with pytest.raises(CheckpointError, match="no published model"):
        (tmp_path / "store" / "v0009").mkdir()
        resolve_model_path(tmp_path / "store")
    first = publish_bytes(store, b"first", {"run": 1})
    second = publish_bytes(store, b"second", {"run": 2})
    # v0009 was an incomplete leftover, so numbering continues after it and it is not a version.
    assert [v.name for v in store.versions()] == [first.name, second.name] == ["v0010", "v0011"]
    assert store.latest().name == second.name and store.latest().metadata == {"run": 2}
    assert resolve_model_path(store.root).read_bytes() == b"second"
    assert resolve_model_path(first.path).read_bytes() == b"first"
    assert resolve_model_path(first.model_path) == first.model_path
    store.verify(store.latest())
    assert not [p for p in store.root.iterdir() if p.name.startswith(".")]


def test_failed_write_leaves_latest_and_no_debris(tmp_path):
    store = ModelStore(tmp_path)
    good = publish_bytes(store, b"good")
    with pytest.raises(RuntimeError):
        with store.new_version() as staging:
            (staging / MODEL_NAME).write_bytes(b"half")
            raise RuntimeError("training blew up")
    with pytest.raises(CheckpointError, match="nothing to publish"):
        with store.new_version():
            pass
    assert store.latest().name == good.name
    assert sorted(p.name for p in tmp_path.iterdir()) == [POINTER_NAME, good.name]


def test_verify_detects_corruption_and_bad_pointers(tmp_path):
    store = ModelStore(tmp_path)
    version = publish_bytes(store, b"0123456789")
    version.model_path.write_bytes(b"0123456780")
    with pytest.raises(CheckpointError, match="does not match its manifest"):
        store.verify(version)
    store.pointer_path.write_text("{not json")
    with pytest.raises(CheckpointError, match="malformed model pointer"):
        resolve_model_path(tmp_path)
    store.pointer_path.write_text(json.dumps({"version": "../etc"}))
    with pytest.raises(CheckpointError, match="invalid version"):
        store.latest()
    store.pointer_path.write_text(json.dumps({"version": "v0042"}))
    with pytest.raises(CheckpointError, match="incomplete model version"):
        store.latest()
    with pytest.raises(CheckpointError, match="does not exist"):
        resolve_model_path(tmp_path / "nowhere")
    with pytest.raises(CheckpointError, match="neither"):
        (tmp_path / "empty").mkdir()
        resolve_model_path(tmp_path / "empty")


@pytest.mark.parametrize("pause_at", PAUSE_POINTS)
def test_sigkill_at_every_commit_step_keeps_previous_model(tmp_path, pause_at):
    store = ModelStore(tmp_path / "store")
    previous = publish_bytes(store, b"previous model")
    signal_file = tmp_path / "paused"
    proc = spawn_writer(store.root, "new", 1, {"NOCAL_STORE_PAUSE_AT": pause_at, "NOCAL_STORE_PAUSE_FILE": str(signal_file)})
    try:
        wait_for(signal_file, proc)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
    latest = store.latest()
    assert latest.name == previous.name
    store.verify(latest)
    assert resolve_model_path(store.root).read_bytes() == b"previous model"
    # The dead writer's staging is cleaned by the next writer, whose version becomes latest.
    after = publish_bytes(store, b"after the crash")
    assert store.latest().name == after.name and after.name > previous.name
    assert not [p for p in store.root.iterdir() if p.name.startswith(".staging-")]
    assert resolve_model_path(store.root).read_bytes() == b"after the crash"


def test_sigkill_at_random_moments_never_breaks_latest(tmp_path):
    store = ModelStore(tmp_path / "store")
    publish_bytes(store, b"seed model")
    for delay in (0.15, 0.3, 0.45, 0.6):
        proc = spawn_writer(store.root, f"d{delay}", 1000)
        time.sleep(delay)
        proc.kill()
        proc.wait(timeout=30)
        latest = store.latest()
        store.verify(latest)
        data = resolve_model_path(store.root).read_bytes()
        assert data == b"seed model" or data.startswith(f"d{delay}".encode())


def test_prune_keeps_latest_and_dead_writers_debris_is_cleaned(tmp_path):
    store = ModelStore(tmp_path)
    versions = [publish_bytes(store, str(i).encode()) for i in range(4)]
    # A dead writer (pid 0 is never a live process) left a staging directory and a pointer temp file.
    (tmp_path / ".staging-0-deadbeef").mkdir()
    (tmp_path / f".{POINTER_NAME}.999999999.abcd.tmp").write_text("{}")
    assert [p.name for p in store.prune(keep=2)] == [versions[0].name, versions[1].name]
    assert [v.name for v in store.versions()] == [versions[2].name, versions[3].name]
    assert len(store.clean_stale_staging()) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([POINTER_NAME, versions[2].name, versions[3].name])
    assert resolve_model_path(tmp_path).read_bytes() == b"3"
