"""``nocal train --init``: the trainer node's fine-tuning job from the command line, on real bags."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from nocal_ros.cli import build_parser, main
from nocal_ros.data.bags import BagWriter, write_sequence
from nocal_ros.model_store import ModelStore

REPO = Path(__file__).resolve().parents[1]
TINY_RECIPE = REPO / "config" / "tiny.yaml"


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """A rendered 48x36 camera's bag (half the frames with arm poses), a tiny initial model, and a
    recipe that logs every step (so a test can see training under way)."""
    import torch

    from nocal_ros.camera import CameraModel
    from nocal_ros.checkpoint import save_checkpoint
    from nocal_ros.config import load_config
    from nocal_ros.data.synthetic import random_calibration, render_sequence
    from nocal_ros.model import NOCaL

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("train_cli")
    calibration = random_calibration(np.random.default_rng(1), 48, 36)
    sequence = render_sequence(calibration, 8, seed=3, labelled_fraction=0.5)
    bag = write_sequence(sequence, root / "arm.mcap")
    recipe = load_config(TINY_RECIPE)
    torch.manual_seed(0)
    init = save_checkpoint(root / "init.safetensors", NOCaL(recipe["model"]), [CameraModel(48, 36)],
                           {"training_resolution": [32, 24]})
    chatty = root / "tiny_every_step.yaml"
    chatty.write_text(yaml.safe_dump({**recipe, "log_every": 1, "checkpoint_every": 1000}))
    return {"bag": str(bag), "init": str(init), "recipe": str(chatty), "calibration": calibration,
            "labelled": int(sequence.labelled.sum())}


def weights_equal(a, b) -> bool:
    import torch

    a, b = a.model.state_dict(), b.model.state_dict()
    return all(torch.equal(a[key], b[key]) for key in a)


def test_train_init_publishes_versions_like_the_trainer_node(tmp_path, field, capsys):
    from nocal_ros.checkpoint import load_checkpoint

    store_dir = tmp_path / "store"
    common = ["--config", field["recipe"], "--out", str(store_dir), "--threads", "1", "--device", "cpu"]
    assert main(["train", "--init", field["init"], "--bag", field["bag"], "--steps", "4", "--max-frames", "6",
                 "--pose-source", "pose", *common]) == 0
    store = ModelStore(store_dir)
    first = store.latest()
    assert first.name == "v0001" and "published v0001" in capsys.readouterr().out
    store.verify(first)
    facts = first.metadata  # written by finetune.run_finetune, the trainer node's job
    assert facts["kind"] == "finetune" and facts["init"] == field["init"] and facts["steps"] == 4
    assert facts["frames"] == 6 and 0 < facts["labelled_frames"] <= field["labelled"] and facts["metric_scale"] is True
    tuned = load_checkpoint(store_dir)
    assert not weights_equal(tuned, load_checkpoint(field["init"]))
    assert not list(first.path.glob("last.*"))

    # Continue from the store's latest, without labels, keeping one version: the pruned store holds the new one.
    assert main(["train", "--init", str(store_dir), "--bag", field["bag"], "--steps", "2", "--pose-source", "none",
                 "--keep", "1", *common]) == 0
    output = capsys.readouterr().out
    assert "published v0002" in output and "scale is not metric" in output
    assert [v.name for v in store.versions()] == ["v0002"] and store.latest().name == "v0002"
    facts = store.latest().metadata
    assert facts["init"] == str(first.model_path) and facts["labelled_frames"] == 0 and facts["metric_scale"] is False
    assert facts["frames"] == 8


def test_every_bag_option_reaches_the_job_config(tmp_path, field):
    from nocal_ros.commands.train import finetune_config

    hand_eye = np.array([[0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]], dtype=float)
    args = build_parser("train").parse_args([
        "train", "--init", field["init"], "--bag", "a.mcap", "--bag", "b.mcap", "--out", str(tmp_path / "store"),
        "--config", str(TINY_RECIPE), "--image-topic", "/cam/image", "--pose-topic", "/robot/pose",
        "--pose-source", "tf", "--tf-parent", "world", "--tf-child", "flange", "--hand-eye", *map(str, hand_eye.ravel()),
        "--tolerance", "0.05", "--max-frames", "30", "--camera-start", "init", "--keep", "2", "--threads", "3",
        "--device", "cpu"])
    config = finetune_config(args)
    assert config.bags == ["a.mcap", "b.mcap"] and config.output == str(tmp_path / "store")
    assert (config.init, config.training_config) == (field["init"], str(TINY_RECIPE))
    assert (config.image_topic, config.pose_topic, config.pose_source) == ("/cam/image", "/robot/pose", "tf")
    assert (config.tf_parent, config.tf_child, config.tolerance_s, config.max_frames) == ("world", "flange", 0.05, 30)
    assert np.array_equal(config.hand_eye, hand_eye)
    assert (config.camera_start, config.keep_versions, config.threads, config.device) == ("init", 2, 3, "cpu")
    # Steps and seed come from the recipe unless given, as when pretraining.
    assert (config.steps, config.seed) == (20, 0)
    args.steps, args.seed = 7, 5
    assert (finetune_config(args).steps, finetune_config(args).seed) == (7, 5)


def test_bad_fine_tuning_commands_fail_in_one_line(tmp_path, field, capsys):
    store = str(tmp_path / "store")
    cases = [
        (["--init", str(tmp_path / "missing.safetensors"), "--bag", field["bag"], "--out", store], "missing.safetensors: model file or store does not exist"),
        (["--init", field["init"], "--bag", field["bag"]], "pass --out STORE"),
        (["--init", field["init"], "--out", store], "at least one --bag"),
        (["--init", field["init"], "--bag", field["bag"], "--out", store, "--resume"], "not resumable"),
        (["--init", field["init"], "--bag", field["bag"], "--out", store, "--hand-eye", *["1"] * 16], "not a rigid transform"),
        (["--bag", field["bag"]], "pretraining needs --config"),
    ]
    for arguments, message in cases:
        assert main(["train", *arguments]) == 1, arguments
        error = capsys.readouterr().err.strip().splitlines()
        assert error[-1].startswith("nocal train: error: ") and message in error[-1], (arguments, error)
    assert not Path(store).exists()
    # A bag without images fails in the worker; the message names the bag and nothing is published.
    poses_only = tmp_path / "poses_only.mcap"
    with BagWriter(poses_only) as bag:
        bag.write_pose("/arm/pose", 1_000_000_000, "base", np.eye(4))
    assert main(["train", "--init", field["init"], "--bag", str(poses_only), "--out", store, "--threads", "1"]) == 1
    assert "poses_only.mcap" in capsys.readouterr().err
    assert ModelStore(store).latest() is None
    # One way to fine-tune: the separate subcommand is gone.
    with pytest.raises(SystemExit):
        main(["finetune", "--bag", field["bag"], "--store", store])


def live_processes_in_group(group: int, wait_s: float = 10.0) -> list[str]:
    """Command lines of the running (not zombie) processes of a process group, from /proc (a container's
    PID 1 may never reap orphans' zombies), after giving them ``wait_s`` to exit: multiprocessing's
    resource tracker only notices its parent is gone a moment later."""
    deadline = time.monotonic() + wait_s
    while True:
        live = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()  # after the name: state, ppid, pgrp
                if int(fields[2]) == group and fields[0] != "Z":
                    live.append((stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode())
            except OSError:  # exited meanwhile
                continue
        if not live or time.monotonic() > deadline:
            return live
        time.sleep(0.1)


def test_ctrl_c_cancels_the_job_and_keeps_the_previous_model(tmp_path, field):
    from nocal_ros.checkpoint import load_checkpoint

    store = ModelStore(tmp_path / "store")
    store.publish_file(Path(field["init"]), {"kind": "shipped"})
    env = dict(os.environ, OMP_NUM_THREADS="1")
    # A session of its own, so the test can send SIGINT to the whole process group as a terminal does.
    # Output goes to files, not pipes: a progress bar filling an unread pipe would block the CLI.
    with open(tmp_path / "stdout.txt", "w") as out, open(tmp_path / "stderr.txt", "w") as err:
        process = subprocess.Popen(
            [sys.executable, "-m", "nocal_ros.cli", "train", "--init", "--bag", field["bag"], "--out", str(store.root),
             "--config", field["recipe"], "--steps", "100000", "--threads", "1", "--device", "cpu"],
            stdout=out, stderr=err, text=True, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while True:  # training is under way once its staging directory logs a few steps
            logged = [p for p in store.root.glob(".staging-*/metrics.csv") if len(p.read_text().splitlines()) >= 3]
            if logged:
                break
            assert process.poll() is None, (tmp_path / "stderr.txt").read_text()[-2000:]
            assert time.monotonic() < deadline, "training never started"
            time.sleep(0.2)
        os.killpg(process.pid, signal.SIGINT)
        process.wait(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    stdout, stderr = (tmp_path / "stdout.txt").read_text(), (tmp_path / "stderr.txt").read_text()
    assert process.returncode == 130, stderr[-2000:]
    assert "cancelled" in stdout and "previous model kept" in stdout
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    assert live_processes_in_group(process.pid) == []  # the worker went too
    assert [v.name for v in store.versions()] == ["v0001"] and store.latest().name == "v0001"
    assert not list(store.root.glob(".staging-*"))
    assert weights_equal(load_checkpoint(store.root), load_checkpoint(field["init"]))
