"""Checkpoints: exact round trip, atomic writes, and refusal of every kind of bad file."""

import hashlib
import json
import os
import pickle

import pytest
import torch
from safetensors.torch import load_file, save_file

import nocal_ros.checkpoint as ckpt
from nocal_ros.camera import CameraModel
from nocal_ros.checkpoint import load_checkpoint, save_checkpoint, sidecar_path
from nocal_ros.errors import CheckpointError
from nocal_ros.model import NOCaL

TINY = dict(encoder_channels=[8, 8, 16, 16, 16, 16, 16], latent_dim=16, scene_width=16, pose_width=16,
            hyper_width=16, hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2)


@pytest.fixture
def saved(tmp_path):
    torch.manual_seed(0)
    model = NOCaL(TINY)
    camera = CameraModel(64, 48, fx=70.0, fy=66.0, cx=30.0, cy=25.0)
    with torch.no_grad():
        camera.distortion[-1].weight.normal_(0, 0.01)
    path = save_checkpoint(tmp_path / "model.safetensors", model, [camera],
                           metadata={"training_resolution": [32, 24], "config": {"steps": 3}, "note": "x"})
    return path, model, camera


def rewrite_sidecar(path, **changes):
    side = sidecar_path(path)
    data = json.loads(side.read_text())
    data.update(changes)
    side.write_text(json.dumps(data))


def write_weights_with_valid_sidecar(path, data: bytes):
    """Replace the weights and re-sign the sidecar, so only the content checks can catch the file."""
    path.write_bytes(data)
    rewrite_sidecar(path, weights_sha256=hashlib.sha256(data).hexdigest())


def test_round_trip_is_exact(saved):
    path, model, camera = saved
    loaded = load_checkpoint(path)
    assert loaded.model.config == model.config
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.model.state_dict()[key], value), key
    assert [float(v.detach()) for v in loaded.cameras[0].intrinsics()] == [float(v.detach()) for v in camera.intrinsics()]
    u = torch.tensor([0.0, 10.0, 63.0])
    assert torch.equal(loaded.cameras[0].undistorted_normalised(u, u / 2), camera.undistorted_normalised(u, u / 2))
    side = json.loads(sidecar_path(path).read_text())
    assert side["training_resolution"] == [32, 24] and side["config"] == {"steps": 3}
    assert side["cameras"][0]["fx"] == pytest.approx(70.0) and side["cameras"][0]["cy"] == pytest.approx(25.0)
    assert loaded.metadata["metadata"]["note"] == "x"
    image = torch.rand(1, 3, 24, 32)
    assert torch.equal(loaded.model.predict_pose(image, image), model.eval().predict_pose(image, image))


def test_failed_write_keeps_the_previous_checkpoint(saved, monkeypatch):
    path, model, camera = saved
    before = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(ckpt.os, "replace", broken_replace)
    with torch.no_grad():
        model.encoder.pose_head[-1].bias.add_(1.0)
    with pytest.raises(OSError):
        save_checkpoint(path, model, [camera])
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["model.json", "model.safetensors"]
    load_checkpoint(path)


def test_missing_files_are_refused(saved, tmp_path):
    path, _, _ = saved
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nothing.safetensors")
    sidecar_path(path).unlink()
    with pytest.raises(CheckpointError, match="sidecar"):
        load_checkpoint(path)


def test_truncated_and_corrupt_weights_are_refused(saved):
    path, _, _ = saved
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="checksum"):
        load_checkpoint(path)
    # even when the sidecar is re-signed, the truncated file cannot be parsed
    write_weights_with_valid_sidecar(path, data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="safetensors"):
        load_checkpoint(path)


class _Exploit:
    def __reduce__(self):
        return (os.system, ("touch pwned_marker",))


def test_pickle_renamed_safetensors_is_refused_without_running_it(saved, monkeypatch, tmp_path):
    path, _, _ = saved
    monkeypatch.chdir(tmp_path)
    write_weights_with_valid_sidecar(path, pickle.dumps({"model": _Exploit()}))
    with pytest.raises(CheckpointError, match="safetensors"):
        load_checkpoint(path)
    assert not (tmp_path / "pwned_marker").exists()
    # torch.save's zip format renamed is refused the same way
    buffer = tmp_path / "t.pt"
    torch.save({"x": torch.zeros(2)}, buffer)
    write_weights_with_valid_sidecar(path, buffer.read_bytes())
    with pytest.raises(CheckpointError, match="safetensors"):
        load_checkpoint(path)


def test_sidecar_problems_are_refused(saved, tmp_path):
    path, model, camera = saved
    other = save_checkpoint(tmp_path / "other.safetensors", model, [camera])
    # a sidecar copied beside other weights
    sidecar_path(other).write_text(sidecar_path(path).read_text())
    with pytest.raises(CheckpointError, match="describes"):
        load_checkpoint(other)
    rewrite_sidecar(path, format_version=99)
    with pytest.raises(CheckpointError, match="format version"):
        load_checkpoint(path)
    sidecar_path(path).write_text("{not json")
    with pytest.raises(CheckpointError, match="JSON"):
        load_checkpoint(path)


def test_inconsistent_intrinsics_in_sidecar_are_refused(saved):
    path, _, _ = saved
    side = json.loads(sidecar_path(path).read_text())
    side["cameras"][0]["fx"] = 500.0
    sidecar_path(path).write_text(json.dumps(side))
    with pytest.raises(CheckpointError, match="intrinsics"):
        load_checkpoint(path)


def test_mismatched_tensors_are_refused(saved):
    path, _, _ = saved
    original = load_file(path)
    # shape mismatch: the sidecar describes a wider light field than the weights hold
    rewrite_sidecar(path, model_config=dict(TINY, lfn_width=32))
    with pytest.raises(CheckpointError, match="tensor"):
        load_checkpoint(path)
    rewrite_sidecar(path, model_config=TINY)
    for name, tensors in {
        "missing": {k: v for k, v in original.items() if k != "model.encoder.pose_head.0.weight"},
        "unexpected": dict(original, **{"model.extra": torch.zeros(3)}),
        "stray camera": dict(original, **{"camera.1.log_fx_rel": torch.zeros(())}),
        "dtype": dict(original, **{"model.encoder.pose_head.0.bias": original["model.encoder.pose_head.0.bias"].double()}),
    }.items():
        save_file(tensors, path)
        write_weights_with_valid_sidecar(path, path.read_bytes())
        with pytest.raises(CheckpointError, match="missing|unexpected|float64"):
            load_checkpoint(path)


def test_nan_weights_are_refused(saved):
    path, _, _ = saved
    tensors = load_file(path)
    tensors["model.hypernetwork.base_biases.0"][0] = float("nan")
    save_file(tensors, path)
    write_weights_with_valid_sidecar(path, path.read_bytes())
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(path)


def test_resolves_model_store_directories(saved):
    path, _, _ = saved
    loaded = load_checkpoint(path.parent)  # a version directory holding model.safetensors
    assert loaded.path == path


def test_distortion_form_is_kept_and_older_files_read_as_the_raw_form(saved):
    path, _, camera = saved
    side = json.loads(sidecar_path(path).read_text())
    assert side["cameras"][0]["distortion"]["type"] == "mlp_centred"
    assert load_checkpoint(path).cameras[0].distortion_form == "centred"
    # Files written before the centred form say "mlp": the MLP's output is the correction as it stands.
    side["cameras"][0]["distortion"]["type"] = "mlp"
    sidecar_path(path).write_text(json.dumps(side))
    old = load_checkpoint(path).cameras[0]
    assert old.distortion_form == "raw"
    u, v = torch.tensor([0.0, 10.0, 63.0]), torch.tensor([5.0, 40.0, 47.0])
    assert torch.equal(old.distortion_correction(u, v), camera.distortion(camera.distortion_input(u, v)))
    side["cameras"][0]["distortion"]["type"] = "spline"
    sidecar_path(path).write_text(json.dumps(side))
    with pytest.raises(CheckpointError, match="unknown distortion type 'spline'"):
        load_checkpoint(path)
