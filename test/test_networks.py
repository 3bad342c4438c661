"""Networks, model and losses: shapes, the batched renderer against a per-sample reference, gradients."""

import math

import pytest
import torch
import torch.nn.functional as F

from nocal_ros.camera import CameraModel
from nocal_ros.geometry import pose_from_translation_rot6d
from nocal_ros.losses import latent_loss, nocal_loss, photometric_loss, rotation_loss, translation_loss
from nocal_ros.model import DEFAULT_MODEL_CONFIG, NOCaL
from nocal_ros.networks import fourier_encoding
from nocal_ros.training import pair_loss

TINY = dict(encoder_channels=[8, 8, 16, 16, 16, 16, 16], latent_dim=16, scene_width=16, pose_width=16,
            hyper_width=16, hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2)


def images(batch=2, width=32, height=24, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return (torch.rand(batch, 3, height, width, generator=generator),
            torch.rand(batch, 3, height, width, generator=generator))


def test_encode_gives_rigid_poses_near_identity_and_pose_path_agrees():
    torch.manual_seed(0)
    model = NOCaL(TINY)
    image_i, image_j = images(3)
    T, z = model.encode(image_i, image_j)
    assert T.shape == (3, 4, 4) and z.shape == (3, 16)
    R = T[:, :3, :3]
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3).expand(3, 3, 3), atol=1e-5)
    assert torch.allclose(T[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(3, 4))
    # pose_scale keeps the untrained pose head close to the identity
    assert torch.allclose(T, torch.eye(4).expand(3, 4, 4), atol=0.05)
    assert torch.equal(model.predict_pose(image_i, image_j), T)


def test_pose_path_skips_scene_head_hypernetwork_and_lfn():
    model = NOCaL(TINY)
    called = []
    for module in (model.encoder.scene_head, model.hypernetwork):
        module.register_forward_hook(lambda *args: called.append(1))
    model.predict_pose(*images(1))
    assert called == []


def test_fourier_encoding_closed_form():
    x = torch.tensor([[0.3, -1.2]])
    encoded = fourier_encoding(x, 3)
    expected = [0.3, -1.2] + [math.sin(f * v) for f in (1, 2, 4) for v in (0.3, -1.2)] \
        + [math.cos(f * v) for f in (1, 2, 4) for v in (0.3, -1.2)]
    assert torch.allclose(encoded, torch.tensor([expected]), atol=1e-6)


def reference_render(model, z, pluecker):
    """One sample at a time with F.linear: the weights built from the basis by explicit sums."""
    hyper = model.hypernetwork
    outputs = []
    for b in range(z.shape[0]):
        coefficients = hyper.coefficients(hyper.trunk(z[b:b + 1]))[0].view(len(hyper.layer_shapes), hyper.rank)
        hidden = fourier_encoding(pluecker[b], model.light_field.num_frequencies)
        for index, (out_f, in_f) in enumerate(hyper.layer_shapes):
            weight = hyper.base_weights[index].clone()
            bias = hyper.base_biases[index].clone()
            for k in range(hyper.rank):
                weight = weight + coefficients[index, k] * hyper.basis_weights[index][k].view(out_f, in_f)
                bias = bias + coefficients[index, k] * hyper.basis_biases[index][k]
            hidden = F.linear(hidden, weight, bias)
            if index < len(hyper.layer_shapes) - 1:
                hidden = F.relu(F.layer_norm(hidden, (out_f,)))
        outputs.append(torch.sigmoid(hidden))
    return torch.stack(outputs)


def test_batched_render_matches_per_sample_reference():
    torch.manual_seed(1)
    model = NOCaL(TINY)
    with torch.no_grad():  # biases start at zero; make them matter for the check
        for p in model.hypernetwork.parameters():
            p.add_(0.1 * torch.randn_like(p))
    z = torch.randn(3, 16)
    pluecker = torch.randn(3, 50, 6)
    rendered = model.render(z, pluecker)
    assert rendered.shape == (3, 50, 3)
    assert torch.allclose(rendered, reference_render(model, z, pluecker), atol=1e-5)
    # different scene latents render different light fields
    assert (rendered[0] - rendered[1]).abs().max() > 1e-3


def test_default_model_fits_the_shipping_budget():
    model = NOCaL()
    camera = CameraModel(640, 480)
    total_bytes = sum(p.numel() * p.element_size() for p in list(model.parameters()) + list(camera.parameters()))
    assert total_bytes <= 25 * 1024 * 1024
    # a hypernetwork, not a single light field: it must emit every LFN weight
    lfn_weights = sum(o * i + o for o, i in model.light_field.layer_shapes())
    assert lfn_weights > 50_000 and DEFAULT_MODEL_CONFIG["lfn_layers"] == 6


def test_losses_against_closed_forms():
    angle = 0.3
    c, s = math.cos(angle), math.sin(angle)
    R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T_pred = torch.eye(4).repeat(2, 1, 1)
    T_true = torch.eye(4).repeat(2, 1, 1)
    T_true[0, :3, :3] = R
    T_true[0, :3, 3] = torch.tensor([1.0, 2.0, 2.0])
    T_true[1, :3, 3] = torch.tensor([5.0, 0.0, 0.0])  # unlabelled: must not count
    labelled = torch.tensor([True, False])
    assert math.isclose(float(rotation_loss(T_pred, T_true, labelled)), 4 - 4 * c, rel_tol=1e-5)
    assert math.isclose(float(translation_loss(T_pred, T_true, labelled)), 9.0, rel_tol=1e-6)
    assert float(translation_loss(T_pred, T_true, torch.tensor([False, False]))) == 0.0
    assert math.isclose(float(photometric_loss(torch.zeros(1, 4, 3), torch.full((1, 4, 3), 0.5))), 0.25)
    assert math.isclose(float(latent_loss(torch.tensor([[3.0, -1.0]]))), 5.0)
    terms = nocal_loss(torch.zeros(2, 4, 3), torch.full((2, 4, 3), 0.5), T_pred, T_true, labelled,
                       torch.tensor([[3.0, -1.0]]))
    assert math.isclose(float(terms.total), 100 * 0.25 + 30 * 9.0 + 20 * (4 - 4 * c) + 1e-6 * 5.0, rel_tol=1e-5)


def pair_batch(labelled: bool, width=32, height=24):
    image_i, image_j = images(2, width, height)
    T = pose_from_translation_rot6d(torch.tensor([[0.1, 0.0, 0.05]] * 2), torch.tensor([[1.0, 0.1, 0, 0, 1, 0]] * 2))
    return {"image_i": image_i, "image_j": image_j, "T_ci_cj": T if labelled else torch.eye(4).repeat(2, 1, 1),
            "labelled": torch.tensor([labelled] * 2), "camera_index": torch.tensor([0, 1])}


def test_gradient_reaches_every_parameter_group():
    torch.manual_seed(0)
    model = NOCaL(TINY)
    cameras = [CameraModel(64, 48), CameraModel(32, 24, fx=40.0)]
    for camera in cameras:
        camera.set_stage("full")
        with torch.no_grad():  # the zero-initialised last layer blocks gradient to the inner layers
            camera.distortion[-1].weight.normal_(0, 0.01)
    pixels = torch.randperm(32 * 24)[:100]
    total = sum(pair_loss(model, cameras, pair_batch(labelled), pixels)[0].total for labelled in (True, False))
    total.backward()
    for name, parameter in list(model.named_parameters()) + [
        (f"camera{k}.{n}", p) for k, c in enumerate(cameras) for n, p in c.named_parameters()
    ]:
        if name.endswith(f"distortion.{len(cameras[0].distortion) - 1}.bias"):
            # the centred distortion subtracts the MLP's value at the image centre: the last bias cancels
            assert parameter.grad is not None and parameter.grad.abs().sum() == 0, name
        else:
            assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name


def test_fixed_stage_freezes_the_camera_but_not_the_pose():
    model = NOCaL(TINY)
    camera = CameraModel(32, 24)
    camera.set_stage("fixed")
    terms, _ = pair_loss(model, [camera, camera], pair_batch(False), torch.arange(200))
    terms.total.backward()
    assert all(p.grad is None for p in camera.parameters())
    # unlabelled pairs train the pose head through the rendering of view j alone
    assert model.encoder.pose_head[-1].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("width,height", [(80, 60), (64, 48), (50, 30)])
def test_model_accepts_other_image_sizes(width, height):
    model = NOCaL(TINY)
    T, z = model.encode(*images(1, width, height))
    assert T.shape == (1, 4, 4) and torch.isfinite(z).all()
