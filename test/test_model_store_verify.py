"""Loading from a model store verifies what it loads: no path may leave the store, and every file must
match the SHA-256 its version's manifest recorded (a tampered store is refused, not loaded with exit 0)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch

from nocal_ros.camera import CameraModel
from nocal_ros.checkpoint import load_checkpoint, save_checkpoint
from nocal_ros.errors import CheckpointError
from nocal_ros.model import NOCaL
from nocal_ros.model_store import MANIFEST_NAME, POINTER_NAME, ModelStore, resolve_model_path

TINY = dict(encoder_channels=[8] * 7, latent_dim=16, scene_width=16, pose_width=16, hyper_width=16,
            hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2)


def checkpoint(path: Path, seed: int) -> Path:
    torch.manual_seed(seed)
    return save_checkpoint(path, NOCaL(TINY), [CameraModel(32, 24)], {"training_resolution": [32, 24], "seed": seed})


@pytest.fixture
def store(tmp_path):
    """A store with two published versions of different weights (seeds 1 and 2); latest is v0002."""
    store = ModelStore(tmp_path / "store")
    for seed in (1, 2):
        store.publish_file(checkpoint(tmp_path / f"source{seed}" / "model.safetensors", seed))
    return store


def seed_of(path) -> int:
    return load_checkpoint(path).metadata["metadata"]["seed"]


def rewrite(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_an_untouched_store_loads_its_latest_version(store):
    assert resolve_model_path(store.root) == store.root / "v0002" / "model.safetensors"
    assert seed_of(store.root) == 2 and seed_of(store.root / "v0001") == 1


def test_a_manifest_pointing_out_of_the_store_is_refused(store, tmp_path):
    """The attacker writes a model outside, and edits both the manifest and the pointer to name it."""
    outside = checkpoint(tmp_path / "outside" / "model.safetensors", 7)
    escape = os.path.relpath(outside, store.root / "v0002")
    manifest = store.root / "v0002" / MANIFEST_NAME

    def to_outside(data):
        data["model"] = escape
        data["files"][escape] = {"size": outside.stat().st_size, "sha256": json.loads(outside.with_suffix(".json").read_text())["weights_sha256"]}

    rewrite(manifest, to_outside)
    rewrite(store.pointer_path, lambda data: data.update(model=escape))
    for target in (store.root, store.root / "v0002"):
        with pytest.raises(CheckpointError, match="not a file name in the version directory"):
            load_checkpoint(target)


def test_a_version_directory_symlinked_out_of_the_store_is_refused(store, tmp_path):
    outside = tmp_path / "elsewhere" / "v0003"
    shutil.copytree(store.root / "v0001", outside)
    (store.root / "v0003").symlink_to(outside, target_is_directory=True)
    rewrite(store.pointer_path, lambda data: data.update(version="v0003"))
    with pytest.raises(CheckpointError, match="symlink or lies outside the store"):
        load_checkpoint(store.root)
    assert [v.name for v in store.versions()] == ["v0001", "v0002"]  # a symlink is no version


def test_a_model_file_symlinked_out_of_its_version_is_refused(store, tmp_path):
    outside = checkpoint(tmp_path / "outside" / "model.safetensors", 7)
    weights = store.root / "v0002" / "model.safetensors"
    weights.unlink()
    weights.symlink_to(outside)
    with pytest.raises(CheckpointError, match="leaves model version v0002"):
        load_checkpoint(store.root)


@pytest.mark.parametrize("target", ["store", "version"])
def test_swapped_version_files_are_refused(store, target):
    """v0001's and v0002's checkpoints swapped: each pair is self-consistent (its sidecar holds its weights'
    hash), so only the manifests' SHA-256 can tell that v0002 no longer holds v0002's model."""
    first, second = store.root / "v0001", store.root / "v0002"
    for name in ("model.safetensors", "model.json"):
        (first / name).rename(first / (name + ".swap"))
        (second / name).rename(first / name)
        (first / (name + ".swap")).rename(second / name)
    assert seed_of(second / "model.safetensors") == 1  # the file itself is a valid checkpoint
    with pytest.raises(CheckpointError, match="does not match its manifest"):
        load_checkpoint(store.root if target == "store" else second)


def test_the_odometry_refuses_a_tampered_store_too(store):
    from nocal_ros.odometry import PoseModel

    (store.root / "v0002" / "model.json").write_text((store.root / "v0002" / "model.json").read_text() + " ")
    with pytest.raises(CheckpointError, match="does not match its manifest"):
        PoseModel.from_checkpoint(str(store.root), "cpu")
    rewrite(store.pointer_path, lambda data: data.update(sha256="0" * 64))
    with pytest.raises(CheckpointError, match="pointer and the manifest of v0002 disagree"):
        resolve_model_path(store.root)
    assert (store.root / POINTER_NAME).is_file()
