"""Hostile sidecars: every field is checked for type, finiteness and range before anything is built,
and the shapes a sidecar declares are compared with the safetensors header before a tensor is allocated.

Real sidecars are edited (the shipped model's, and a tiny one's). The cases that would allocate
gigabytes run in a subprocess under an address-space limit (``RLIMIT_AS``), so a regression fails the
test with a MemoryError instead of taking the machine down.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from nocal_ros.camera import CameraModel
from nocal_ros.checkpoint import DEFAULT_MODEL_PATH, load_checkpoint, save_checkpoint, sidecar_path
from nocal_ros.errors import CheckpointError
from nocal_ros.model import NOCaL

TINY = dict(encoder_channels=[8, 8, 16, 16, 16, 16, 16], latent_dim=16, scene_width=16, pose_width=16,
            hyper_width=16, hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2)
# Address space allowed above what the interpreter holds once torch is imported (~0.6 GiB here with the
# CPU wheel; a CUDA build maps more, hence relative): loading the shipped model and running odometry
# on it peaks ~0.5 GiB above that, while each hostile case below asks for 3.6 GB or more at once.
ADDRESS_SPACE_HEADROOM = 3 << 30


@pytest.fixture
def tiny(tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(
        tmp_path / "model.safetensors", NOCaL(TINY), [CameraModel(64, 48, fx=70.0)],
        metadata={"training_resolution": [32, 24], "config": {"gap_range": [1, 8], "image_size": [32, 24]},
                  "pose_error_std": {"translation_m": 0.01, "rotation_rad": 0.01}},
    )
    return path


def edit(path: Path, change) -> None:
    side = sidecar_path(path)
    data = json.loads(side.read_text())
    change(data)
    side.write_text(json.dumps(data))  # json writes float("nan") as NaN and inf as Infinity, as a hostile file would


def setter(*keys, value):
    def change(data):
        target = data
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value
    return change


NAN, INF = float("nan"), float("inf")
FIELD_CASES = {
    "pose_error_std NaN": (setter("metadata", "pose_error_std", "translation_m", value=NAN), "pose_error_std.translation_m"),
    "pose_error_std Infinity": (setter("metadata", "pose_error_std", "rotation_rad", value=INF), "pose_error_std.rotation_rad"),
    "pose_error_std negative": (setter("metadata", "pose_error_std", "translation_m", value=-0.01), "pose_error_std.translation_m"),
    "pose_error_std string": (setter("metadata", "pose_error_std", "translation_m", value="0.01"), "pose_error_std.translation_m"),
    "pose_error_std list": (setter("metadata", "pose_error_std", value=[0.01]), "pose_error_std"),
    "training_resolution huge": (setter("training_resolution", value=[40000, 30000]), "training_resolution"),
    "training_resolution negative": (setter("training_resolution", value=[-32, 24]), "training_resolution"),
    "training_resolution strings": (setter("training_resolution", value=["32", "24"]), "training_resolution"),
    "training_resolution NaN": (setter("training_resolution", value=[NAN, 24]), "training_resolution"),
    "training_resolution scalar": (setter("training_resolution", value=32), "training_resolution"),
    "config image_size float": (setter("config", "image_size", value=[32.5, 24]), "config.image_size"),
    "config gap_range zero": (setter("config", "gap_range", value=[0, 8]), "config.gap_range"),
    "config gap_range reversed": (setter("config", "gap_range", value=[8, 1]), "config.gap_range"),
    "metadata max_gap NaN": (setter("metadata", "max_gap", value=NAN), "metadata.max_gap"),
    "latent_dim 1e7": (setter("model_config", "latent_dim", value=1e7), "model_config.latent_dim"),
    "latent_dim 10000000": (setter("model_config", "latent_dim", value=10_000_000), "model_config.latent_dim"),
    "latent_dim negative": (setter("model_config", "latent_dim", value=-16), "model_config.latent_dim"),
    "latent_dim string": (setter("model_config", "latent_dim", value="16"), "model_config.latent_dim"),
    "pose_scale NaN": (setter("model_config", "pose_scale", value=NAN), "model_config.pose_scale"),
    "encoder_channels empty": (setter("model_config", "encoder_channels", value=[]), "model_config.encoder_channels"),
    "encoder_channels strings": (setter("model_config", "encoder_channels", value=["8"] * 7), "model_config.encoder_channels"),
    "model_config unknown key": (setter("model_config", "layers", value=3), "model_config"),
    "camera fx NaN": (setter("cameras", 0, "fx", value=NAN), "cameras[0].fx"),
    "camera fx negative": (setter("cameras", 0, "fx", value=-70.0), "cameras[0].fx"),
    "camera width huge": (setter("cameras", 0, "width", value=10**9), "cameras[0].width"),
    "camera width float": (setter("cameras", 0, "width", value=64.5), "cameras[0].width"),
    "camera not an object": (setter("cameras", 0, value="camera"), "cameras[0]"),
    "camera stage unknown": (setter("cameras", 0, "stage", value="everything"), "cameras[0].stage"),
    "cameras not a list": (setter("cameras", value={"0": {}}), "cameras"),
    "format_version string": (setter("format_version", value="1"), "format version"),
    "weights_sha256 number": (setter("weights_sha256", value=12345), "weights_sha256"),
    "training step negative": (setter("training", value={"step": -1, "stage": "full", "batches_drawn": 0, "optimisers": {}}),
                               "training.step"),
    "training lr NaN": (setter("training", value={"step": 1, "stage": "full", "batches_drawn": 1,
                                                  "optimisers": {"encoder": [{"lr": NAN}]}}), "training.optimisers.encoder[0].lr"),
}


@pytest.mark.parametrize("case", sorted(FIELD_CASES))
def test_hostile_field_is_refused_naming_it(tiny, case):
    change, field = FIELD_CASES[case]
    edit(tiny, change)
    with pytest.raises(CheckpointError) as refused:
        load_checkpoint(tiny)
    message = str(refused.value)
    assert str(sidecar_path(tiny)) in message and field in message, message
    assert "\n" not in message


def test_odometry_refuses_nan_pose_error_std_instead_of_publishing_nan_covariances(tmp_path):
    """The shipped model with its pose_error_std set to NaN: its /odom covariances would be NaN."""
    from nocal_ros.odometry import OdometryEstimator

    model = copy_shipped(tmp_path)
    edit(model, setter("metadata", "pose_error_std", "translation_m", value=NAN))
    with pytest.raises(CheckpointError, match=r"metadata\.pose_error_std\.translation_m must be finite"):
        OdometryEstimator(str(model), "cpu")


@pytest.mark.parametrize("content", [
    b'{"metadata": ' + b"[" * 100_000 + b"]" * 100_000 + b"}",
    b"[" * 100_000,
    b'{"format_version": 1, "x": ' + b"1" * 5000 + b"}",
    b"\xff\xfe not utf-8",
], ids=["nested 100000 deep in metadata", "unclosed 100000 deep", "5000-digit integer", "binary"])
def test_unparseable_sidecars_are_one_clean_error(tiny, content):
    sidecar_path(tiny).write_bytes(content)
    with pytest.raises(CheckpointError, match="sidecar"):
        load_checkpoint(tiny)


def test_a_sidecar_model_unlike_the_weights_is_refused_before_allocating(tiny, tmp_path):
    """A sidecar that describes a 124 M parameter model (within every bound) beside the tiny weights:
    its shapes are compared with the safetensors header on the meta device, so nothing near the 495 MB
    the model would take is allocated (measured as the process's peak resident memory)."""
    edit(tiny, setter("model_config", value=dict(TINY, hyper_width=4096, hyper_depth=8)))
    script = (
        "import resource, sys\n"
        "from nocal_ros.checkpoint import load_checkpoint\n"
        "from nocal_ros.errors import CheckpointError\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "try:\n"
        "    load_checkpoint(sys.argv[1])\n"
        "except CheckpointError as error:\n"
        "    print('refused:', error)\n"
        "print('grew_kib', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)\n"
    )
    done = subprocess.run([sys.executable, "-c", script, str(tiny)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "refused:" in done.stdout and "the sidecar's model needs" in done.stdout, done.stdout
    grew_kib = int(done.stdout.split("grew_kib")[-1])
    assert grew_kib < 100 * 1024, f"peak memory grew by {grew_kib / 1024:.0f} MiB while refusing"


# ---- the memory-hungry cases, as the user meets them: `nocal odometry` with the edited shipped model ----

LIMITED_CLI = (
    "import resource, sys\n"
    "import torch\n"
    "from nocal_ros.cli import main\n"
    "mapped = next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmSize:'))\n"
    "limit = mapped + int(sys.argv[1])\n"
    "resource.setrlimit(resource.RLIMIT_AS, (limit, limit))\n"
    "sys.exit(main(sys.argv[2:]))\n"
)


def copy_shipped(tmp_path: Path) -> Path:
    model = tmp_path / "model" / DEFAULT_MODEL_PATH.name
    model.parent.mkdir()
    shutil.copyfile(DEFAULT_MODEL_PATH, model)
    shutil.copyfile(sidecar_path(DEFAULT_MODEL_PATH), sidecar_path(model))
    return model


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    from nocal_ros.data.bags import write_sequence
    from nocal_ros.data.synthetic import render_sequence
    from nocal_ros.lens import CameraCalibration

    sequence = render_sequence(CameraCalibration.pinhole(64, 48, 50.0), 4, seed=1, split="test")
    return write_sequence(sequence, tmp_path_factory.mktemp("bag") / "small.mcap")


@pytest.mark.parametrize("change, field", [
    (setter("training_resolution", value=[40000, 30000]), "training_resolution"),  # 3.6 GB per frame buffer
    (setter("model_config", "latent_dim", value=10_000_000), "model_config.latent_dim"),  # a 10 GB model
    (setter("model_config", "latent_dim", value=1e7), "model_config.latent_dim"),
], ids=["training_resolution 40000x30000", "latent_dim 10000000", "latent_dim 1e7"])
def test_memory_hungry_sidecars_are_refused_under_an_address_space_limit(tmp_path, small_bag, change, field):
    model = copy_shipped(tmp_path)
    edit(model, change)
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-c", LIMITED_CLI, str(ADDRESS_SPACE_HEADROOM), "odometry", str(small_bag), "--out", str(out),
         "--model", str(model), "--device", "cpu", "--threads", "1", "--no-progress"],
        capture_output=True, text=True, timeout=300,
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1, done.stderr[-3000:]
    assert lines[0].startswith("nocal odometry: error: ") and field in lines[0], lines[0]
    assert not (out / "trajectory.tum").exists()


def test_the_shipped_model_passes_every_check():
    checkpoint = load_checkpoint(None)
    assert np.isfinite(checkpoint.metadata["metadata"]["pose_error_std"]["translation_m"])
