"""The learnable camera checked against OpenCV and closed forms: rays, gradients, curriculum, exports."""

import cv2
import numpy as np
import pytest
import torch

from nocal_ros import geometry as g
from nocal_ros.camera import CameraModel, PAPER_EQUIVALENT_INTRINSICS_LR


def random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return g.make_transform(g.so3_exp(rng.normal(size=3)), rng.normal(size=3))


def randomise_distortion(camera: CameraModel, seed: int = 0, scale: float = 0.05) -> None:
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in camera.distortion_parameters():
            parameter.add_(torch.randn(parameter.shape, generator=generator) * scale)


def test_default_camera_is_the_papers_initialisation():
    camera = CameraModel(640, 480)
    fx, fy, cx, cy = (float(t.detach()) for t in camera.intrinsics())
    assert (fx, fy, cx, cy) == pytest.approx((640.0, 640.0, 319.5, 239.5))
    u = torch.tensor([0.0, 100.0, 639.0])
    assert torch.count_nonzero(camera.distortion_correction(u, u)) == 0  # starts as a pinhole


def test_pinhole_directions_match_opencv_at_native_and_training_resolution():
    K = np.array([[600.0, 0, 330.2], [0, 590.0, 228.7], [0, 0, 1]])
    camera = CameraModel(640, 480, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2]).double()
    for w, h in [(640, 480), (80, 60), (160, 120)]:
        s = w / 640.0
        # Independent reference: OpenCV undistortPoints with the K of the resized image (D = 0),
        # scaled with the pixel-centre rule fx' = s fx, cx' = (cx + 0.5) s - 0.5.
        K_train = np.array([[K[0, 0] * s, 0, (K[0, 2] + 0.5) * s - 0.5], [0, K[1, 1] * s, (K[1, 2] + 0.5) * s - 0.5], [0, 0, 1]])
        vv, uu = np.mgrid[0:h, 0:w]
        pixels = np.stack((uu.ravel(), vv.ravel()), -1).astype(np.float64)
        xy = cv2.undistortPoints(pixels[:, None, :], K_train, np.zeros(5))[:, 0, :]
        expected = np.concatenate((xy, np.ones((len(xy), 1))), 1)
        expected /= np.linalg.norm(expected, axis=1, keepdims=True)
        got = camera.directions(w, h).detach().numpy()
        # float32 parameters hold the intrinsics to ~1e-7 relative
        np.testing.assert_allclose(got, expected, atol=1e-8)


def test_rays_are_the_lines_through_back_projected_world_points():
    camera = CameraModel(160, 120, fx=150.0, fy=155.0, cx=81.0, cy=58.0).double()
    randomise_distortion(camera)
    poses = np.stack([random_pose(1), random_pose(2)])
    pluecker = camera.rays(torch.from_numpy(poses), 80, 60).detach()
    assert pluecker.shape == (2, 80 * 60, 6)
    d, m = pluecker[..., :3], pluecker[..., 3:]
    assert torch.allclose(d.norm(dim=-1), torch.ones(1, dtype=torch.float64))
    assert torch.allclose((d * m).sum(-1), torch.zeros(1, dtype=torch.float64), atol=1e-12)
    # A point at any depth along a pixel's camera ray, moved to the world, lies on that pixel's line:
    # X_w x d = m (the origin-independence of Pluecker coordinates).
    directions = camera.directions(80, 60).detach().numpy()
    depth = np.random.default_rng(0).uniform(0.5, 10.0, size=(len(directions), 1))
    for b, T in enumerate(poses):
        points_world = (depth * directions) @ T[:3, :3].T + T[:3, 3]
        moment = np.cross(points_world, d[b].numpy())
        np.testing.assert_allclose(moment, m[b].numpy(), atol=1e-9)


def test_pixel_index_selects_the_same_rays():
    camera = CameraModel(160, 120)
    randomise_distortion(camera)
    T = torch.from_numpy(np.stack([random_pose(3), random_pose(4)])).float()
    everything = camera.rays(T, 40, 30)
    shared = torch.tensor([0, 5, 1199, 600])
    assert torch.allclose(camera.rays(T, 40, 30, shared), everything[:, shared], atol=1e-6)
    per_view = torch.tensor([[1, 2, 3], [7, 8, 1199]])
    got = camera.rays(T, 40, 30, per_view)
    assert torch.allclose(got[1], everything[1, per_view[1]], atol=1e-6)
    assert torch.allclose(got[0], everything[0, per_view[0]], atol=1e-6)


def test_gradient_reaches_every_camera_parameter_only_in_the_learnt_stages():
    camera = CameraModel(80, 60)
    T = torch.eye(4).expand(2, 4, 4)

    def backward() -> None:
        camera.zero_grad(set_to_none=True)
        target = torch.randn(2, 80 * 60, 6, generator=torch.Generator().manual_seed(0))
        loss = ((camera.rays(T, 80, 60) - target) ** 2).mean()
        if loss.requires_grad:
            loss.backward()

    # The zero-initialised last layer blocks gradients to the earlier layers until it moves: one step.
    camera.set_stage("full")
    optimiser = torch.optim.Adam(camera.parameters(), lr=1e-2)
    backward()
    optimiser.step()
    backward()
    for name, parameter in camera.named_parameters():
        assert parameter.grad is not None and torch.count_nonzero(parameter.grad) > 0, name

    camera.set_stage("focal")
    backward()
    learnt = {n for n, p in camera.named_parameters() if p.grad is not None and torch.count_nonzero(p.grad) > 0}
    assert learnt == {"log_fx_rel", "log_fy_rel"}

    camera.set_stage("fixed")
    backward()
    assert all(p.grad is None for p in camera.parameters())


def test_focal_step_is_the_same_fraction_of_the_focal_at_any_resolution():
    steps = []
    for width in (80, 640):
        camera = CameraModel(width, width * 3 // 4)
        optimiser = torch.optim.Adam(camera.intrinsic_parameters(), lr=PAPER_EQUIVALENT_INTRINSICS_LR)
        fx0 = float(camera.intrinsics()[0].detach())
        (-camera.intrinsics()[0]).backward()  # ask for a longer focal
        optimiser.step()
        steps.append((float(camera.intrinsics()[0].detach()) - fx0) / width)
    # The paper: lr 0.5 on focal pixels at 80 px width -> 0.5 px per step = 0.625 % of the width.
    assert steps[0] == pytest.approx(0.5 / 80, rel=1e-2)  # exp(lr) - 1 ~ lr
    assert steps[1] == pytest.approx(steps[0], rel=1e-3)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError):
        CameraModel(0, 10)
    with pytest.raises(ValueError):
        CameraModel(10, 10, fx=float("nan"))
    with pytest.raises(ValueError):
        CameraModel(10, 10).set_stage("distortion")
    with pytest.raises(ValueError):
        CameraModel(10, 10).rays(torch.eye(4), 10, 10)
