"""The block-coordinate schedule (config key ``alternate``): network-only and camera-only phases."""

import numpy as np
import pytest
import torch

from nocal_ros.camera import CameraModel
from nocal_ros.data.pairs import PairDataset
from nocal_ros.data.synthetic import render_sequence
from nocal_ros.errors import ConfigError
from nocal_ros.lens import CameraCalibration
from nocal_ros.model import NOCaL
from nocal_ros.training import camera_phase, make_optimisers, optimisation_step, train, training_config

TINY_MODEL = dict(encoder_channels=[8, 8, 16, 16, 16, 16, 16], latent_dim=16, scene_width=16, pose_width=16,
                  hyper_width=16, hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2)


@pytest.fixture(scope="module")
def sequence():
    calibration = CameraCalibration(width=48, height=36, K=np.array([[40.0, 0, 23.5], [0, 40.0, 17.5], [0, 0, 1]]),
                                    D=np.zeros(5), distortion_model="plumb_bob")
    return render_sequence(calibration, 10, seed=3, labelled_fraction=1.0)


@pytest.fixture
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_camera_phase_cycles_after_the_fixed_stage():
    curriculum = {"fixed": 3, "focal": 10}
    phases = [camera_phase(step, curriculum, {"network": 2, "camera": 3}) for step in range(12)]
    assert phases == ["both"] * 3 + ["network"] * 2 + ["camera"] * 3 + ["network"] * 2 + ["camera"] * 2
    assert {camera_phase(step, curriculum, None) for step in range(12)} == {"both"}


@pytest.mark.parametrize("bad", [{"network": 2}, {"network": 0, "camera": 1}, {"network": 1.5, "camera": 1}, 3])
def test_bad_alternate_is_a_config_error(bad):
    with pytest.raises(ConfigError, match="alternate"):
        training_config({"alternate": bad})


def _snapshot(module):
    return [p.detach().clone() for p in module.parameters()]


def _changed(before, module):
    return any(not torch.equal(a, p.detach()) for a, p in zip(before, module.parameters()))


def test_each_phase_steps_only_its_own_block(sequence, one_thread):
    torch.manual_seed(0)
    cfg = training_config({"model": TINY_MODEL, "image_size": [32, 24], "rays_per_image": 64,
                           "learning_rates": {"encoder": 1e-3, "hypernetwork": 1e-3, "distortion": 1e-3,
                                              "intrinsics": 5e-3}})
    model = NOCaL(cfg["model"])
    camera = CameraModel(48, 36)
    camera.set_stage("full")
    optimisers = make_optimisers(model, [camera], cfg["learning_rates"])
    dataset = PairDataset([sequence], size=(32, 24), gap_range=(1, 2))
    generator = torch.Generator().manual_seed(0)
    pixels = torch.randperm(32 * 24, generator=generator)[:64]

    labelled = dataset.sample(2, True, generator)
    network_before, camera_before = _snapshot(model), _snapshot(camera)
    assert optimisation_step(model, [camera], optimisers, labelled, pixels, cfg, phase="camera") is not None
    assert _changed(camera_before, camera) and not _changed(network_before, model)

    network_before, camera_before = _snapshot(model), _snapshot(camera)
    optimisation_step(model, [camera], optimisers, labelled, pixels, cfg, phase="network")
    assert _changed(network_before, model) and not _changed(camera_before, camera)

    # An unlabelled batch in a camera phase would step nothing: it is skipped without a forward pass.
    unlabelled = dataset.sample(2, False, generator)
    network_before, camera_before = _snapshot(model), _snapshot(camera)
    assert optimisation_step(model, [camera], optimisers, unlabelled, pixels, cfg, phase="camera") is None
    assert not _changed(network_before, model) and not _changed(camera_before, camera)


def test_training_moves_the_focal_only_in_camera_phases(sequence, one_thread):
    records = []
    config = dict(steps=14, image_size=[32, 24], batch_size=2, gap_range=[1, 2], labelled_every=1, rays_per_image=64,
                  curriculum={"fixed": 2, "focal": 100}, log_every=1, checkpoint_every=100, model=TINY_MODEL,
                  learning_rates={"encoder": 1e-3, "hypernetwork": 1e-3, "distortion": 1e-3, "intrinsics": 5e-3},
                  alternate={"network": 3, "camera": 3},
                  epipolar={"weight": 0.0})  # the arm-pose term steps the camera in every phase: off here
    result = train(config, [sequence], progress=records.append, device="cpu")
    assert result.step == 14 and len(records) == 14
    focal = [48.0] + [r["fx"] for r in records]  # focal after each step; starts at f = width
    for step in range(14):
        moved = focal[step + 1] != focal[step]
        phase = camera_phase(step, config["curriculum"], config["alternate"])
        assert moved == (phase == "camera"), (step, phase, focal)
    assert all(np.isfinite(r["loss"]) for r in records)
