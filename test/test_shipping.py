"""The shipped default model: how it is packaged from a training run, and the file we ship."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from nocal_ros import geometry
from nocal_ros.checkpoint import DEFAULT_MODEL_PATH, load_checkpoint, save_checkpoint, sidecar_path
from nocal_ros.camera import CameraModel
from nocal_ros.data.synthetic import random_calibration, render_sequence
from nocal_ros.model import NOCaL
from nocal_ros.shipping import package_model

TINY_MODEL = yaml.safe_load((Path(__file__).parents[1] / "config" / "tiny.yaml").read_text())["model"]


@pytest.fixture(scope="module")
def validation():
    rng = np.random.default_rng(3)
    return [render_sequence(random_calibration(rng, 48, 36), 6, seed=5, split="test", labelled_fraction=0.0)]


def test_packaging_replaces_cameras_by_the_prior_and_measures_pose_error(tmp_path, validation):
    torch.manual_seed(0)
    model = NOCaL(TINY_MODEL)
    trained_camera = CameraModel(48, 36, fx=30.0, fy=31.0, cx=20.0, cy=18.0)
    source = save_checkpoint(tmp_path / "run.safetensors", model, [trained_camera],
                             {"training_resolution": [32, 24], "config": {"image_size": [32, 24]}})
    facts = package_model(source, tmp_path / "shipped.safetensors", sequences=validation, prior_size=(64, 48))

    shipped = load_checkpoint(tmp_path / "shipped.safetensors")
    assert len(shipped.cameras) == 1
    fx, fy, cx, cy = (float(v.detach()) for v in shipped.cameras[0].intrinsics())
    assert (fx, fy, cx, cy) == pytest.approx((64.0, 64.0, 31.5, 23.5))
    for name, tensor in model.state_dict().items():
        assert torch.equal(shipped.model.state_dict()[name], tensor)

    # Independent computation of the per-pair error spread from the pose head and the ground truth.
    sequence = validation[0]
    small = [cv2.resize(image, (32, 24), interpolation=cv2.INTER_AREA) for image in sequence.images]
    images = torch.from_numpy(np.stack(small)).permute(0, 3, 1, 2).float() / 255.0
    with torch.no_grad():
        predicted = model.predict_pose(images[:-1], images[1:]).double().numpy()
    errors_t, errors_r = [], []
    for k, T_pred in enumerate(predicted):
        T_true = geometry.relative_transform(sequence.ground_truth[k], sequence.ground_truth[k + 1])
        error = geometry.invert_transform(T_true) @ T_pred
        errors_t.append(error[:3, 3])
        errors_r.append(geometry.so3_log(error[:3, :3]))
    assert facts["pose_error_std"]["translation_m"] == pytest.approx(np.sqrt(np.mean(np.square(errors_t))), rel=1e-4)
    assert facts["pose_error_std"]["rotation_rad"] == pytest.approx(np.sqrt(np.mean(np.square(errors_r))), rel=1e-4)
    assert shipped.metadata["metadata"]["camera_is_prior"] is True


@pytest.mark.skipif(not DEFAULT_MODEL_PATH.exists(), reason="no shipped model in this checkout")
def test_the_shipped_model_is_small_complete_and_loads():
    size = DEFAULT_MODEL_PATH.stat().st_size + sidecar_path(DEFAULT_MODEL_PATH).stat().st_size
    assert size <= 25 * 1024 * 1024
    sidecar = json.loads(sidecar_path(DEFAULT_MODEL_PATH).read_text())
    assert sidecar["training_resolution"] == [80, 60]
    assert set(sidecar["metadata"]["pose_error_std"]) == {"translation_m", "rotation_rad"}
    checkpoint = load_checkpoint()
    assert checkpoint.training is None  # inference weights only
    image = torch.rand(1, 3, 60, 80)
    T = checkpoint.model.predict_pose(image, image)
    assert torch.isfinite(T).all()
