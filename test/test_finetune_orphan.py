"""A SIGKILLed ``nocal train --init`` leaves no worker behind that trains on and publishes later.

Real processes: the CLI runs as a subprocess, its fine-tuning worker (a spawn child) starts training
into a staging directory of the store, the CLI is SIGKILLed, and the worker must end by itself within
seconds, with ``latest`` and the versions as they were.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
TINY_RECIPE = REPO / "config" / "tiny.yaml"


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # an exited child not yet reaped by its new parent is a zombie: gone for our purpose
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    import torch

    from nocal_ros.camera import CameraModel
    from nocal_ros.checkpoint import save_checkpoint
    from nocal_ros.config import load_config
    from nocal_ros.data.bags import write_sequence
    from nocal_ros.data.synthetic import random_calibration, render_sequence
    from nocal_ros.model import NOCaL
    from nocal_ros.model_store import ModelStore

    root = tmp_path_factory.mktemp("orphan")
    sequence = render_sequence(random_calibration(np.random.default_rng(1), 48, 36), 8, seed=3, labelled_fraction=0.5)
    bag = write_sequence(sequence, root / "arm.mcap")
    recipe = load_config(TINY_RECIPE)
    torch.manual_seed(0)
    init = save_checkpoint(root / "init.safetensors", NOCaL(recipe["model"]), [CameraModel(48, 36)],
                           {"training_resolution": [32, 24]})
    chatty = root / "tiny_every_step.yaml"
    chatty.write_text(yaml.safe_dump({**recipe, "log_every": 1, "checkpoint_every": 1000}))
    store = root / "store"
    ModelStore(store).publish_file(init)  # v0001: the model a robot runs now
    return {"bag": str(bag), "recipe": str(chatty), "store": store}


def test_sigkill_of_train_init_stops_its_worker_without_publishing(field):
    from nocal_ros.model_store import ModelStore

    store = ModelStore(field["store"])
    before = (store.pointer_path.read_text(), [v.name for v in store.versions()])
    cli = subprocess.Popen(
        [sys.executable, "-m", "nocal_ros.cli", "train", "--init", "--bag", field["bag"], "--out", str(store.root),
         "--config", field["recipe"], "--steps", "100000", "--threads", "1", "--keep", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    worker = None
    try:
        deadline = time.monotonic() + 300
        while worker is None:  # the worker trains into .staging-<its pid>-*; metrics.csv shows steps done
            assert cli.poll() is None, f"nocal train exited early ({cli.returncode})"
            assert time.monotonic() < deadline, "training never started"
            for staging in store.root.glob(".staging-*"):
                metrics = staging / "metrics.csv"
                if metrics.is_file() and len(metrics.read_text().splitlines()) >= 3:
                    worker = int(staging.name.split("-")[1])
            time.sleep(0.1)
        assert worker != cli.pid and alive(worker)

        os.kill(cli.pid, signal.SIGKILL)
        cli.wait(timeout=30)
        deadline = time.monotonic() + 20
        while alive(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not alive(worker), "the fine-tuning worker outlived the killed nocal train"
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.wait()
        if worker is not None and alive(worker):
            os.kill(worker, signal.SIGKILL)  # the old behaviour: end it so it cannot publish later
    time.sleep(1.0)
    assert (store.pointer_path.read_text(), [v.name for v in store.versions()]) == before
    assert json.loads(store.pointer_path.read_text())["version"] == "v0001"
    removed = store.clean_stale_staging()  # the next writer tidies what the dead worker left
    assert removed and not list(store.root.glob(".staging-*"))
