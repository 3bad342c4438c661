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
    # The centred form subtracts the MLP's value at the image centre, which the last bias only shifts:
    # that bias cancels exactly, and its gradient is exactly zero. Everything else learns.
    cancelled = f"distortion.{len(camera.distortion) - 1}.bias"
    for name, parameter in camera.named_parameters():
        if name == cancelled:
            assert parameter.grad is not None and torch.count_nonzero(parameter.grad) == 0, name
        else:
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


# --------------------------------------------------------------------------------------------------
# exports: parametric fit, dense maps, YAML
# --------------------------------------------------------------------------------------------------

from nocal_ros.camera import fit_distortion_coefficients  # noqa: E402
from nocal_ros.lens import CameraCalibration  # noqa: E402

TRUE_K = np.array([[500.0, 0, 322.0], [0, 505.0, 238.0], [0, 0, 1]])
TRUE_D = np.array([-0.1, 0.02, 0.001, -0.0005, 0.0])


@pytest.fixture(scope="module")
def lens_and_camera():
    calibration = CameraCalibration(640, 480, TRUE_K, TRUE_D, "plumb_bob", "true")
    return calibration, CameraModel.from_calibration(calibration)


def image_pixels(width: int, height: int, step: int = 1) -> np.ndarray:
    vv, uu = np.mgrid[0:height:step, 0:width:step]
    return np.stack((uu.ravel(), vv.ravel()), -1).astype(np.float64)


def test_least_squares_recovers_exact_plumb_bob_coefficients():
    D = np.array([-0.21, 0.05, 0.002, -0.001, 0.01])
    calibration = CameraCalibration(640, 480, TRUE_K, D)
    pixels = image_pixels(640, 480, step=20)
    undistorted = calibration.undistorted_normalised(pixels)
    distorted = calibration.distorted_normalised(pixels)
    np.testing.assert_allclose(fit_distortion_coefficients(undistorted, distorted, "plumb_bob", 500.0, 505.0), D, atol=1e-9)
    # The rational model contains plumb_bob: it must reproduce this lens to far below a pixel.
    rational = fit_distortion_coefficients(undistorted, distorted, "rational_polynomial", 500.0, 505.0)
    reprojected = CameraCalibration(640, 480, TRUE_K, rational, "rational_polynomial").project(
        np.concatenate((undistorted, np.ones((len(undistorted), 1))), 1)
    )
    assert np.abs(reprojected - pixels).max() < 0.05


def test_least_squares_recovers_equidistant_coefficients_that_project_as_opencvs_fisheye():
    """The equidistant fit is checked against ``cv2.fisheye.projectPoints``: a lens's own distortion of its
    undistorted points returns its four coefficients."""
    import cv2

    K = np.array([[400.0, 0, 319.5], [0, 401.0, 239.5], [0, 0, 1]])  # 57 deg off axis at the corners
    D = np.array([-0.03, 0.012, -0.004, 0.0008])
    fisheye = CameraCalibration(640, 480, K, D, "equidistant")
    pixels = image_pixels(640, 480, step=20)
    undistorted = fisheye.undistorted_normalised(pixels)
    points = np.concatenate((undistorted, np.ones((len(undistorted), 1))), 1)[:, None]
    projected = cv2.fisheye.projectPoints(points, np.zeros(3), np.zeros(3), K, D)[0][:, 0]
    np.testing.assert_allclose(projected, pixels, atol=1e-6)
    distorted = np.stack(((pixels[:, 0] - K[0, 2]) / K[0, 0], (pixels[:, 1] - K[1, 2]) / K[1, 1]), -1)
    np.testing.assert_allclose(fit_distortion_coefficients(undistorted, distorted, "equidistant", 400.0, 401.0), D, atol=1e-9)


def test_camera_from_calibration_reproduces_the_lens(lens_and_camera):
    calibration, camera = lens_and_camera
    learnt = camera.undistortion_map().reshape(-1, 2)
    truth = calibration.undistorted_normalised(image_pixels(640, 480))
    shift = np.linalg.norm(learnt - truth, axis=1)
    # An 8-unit MLP is not exact; measured mean 4e-4 (0.2 px at f = 500), max about 3.5e-3.
    assert shift.mean() < 1e-3 and shift.max() < 5e-3


def test_parametric_fit_recovers_the_lens_and_round_trips_through_yaml(lens_and_camera, tmp_path):
    calibration, camera = lens_and_camera
    fit = camera.fit_parametric("plumb_bob", camera_name="fitted")
    D = fit.calibration.D
    assert D[0] == pytest.approx(TRUE_D[0], abs=0.01)
    np.testing.assert_allclose(D[2:4], TRUE_D[2:4], atol=2e-4)
    np.testing.assert_allclose(fit.calibration.K, TRUE_K, atol=1e-3)
    assert fit.rms_px < 0.5 and fit.rms_normalised == pytest.approx(fit.rms_px / 500, rel=0.05)
    # What matters to a user: the fitted lens images the world where the true lens does.
    rays = calibration.unproject(image_pixels(640, 480, step=8))
    error = np.linalg.norm(fit.calibration.project(rays) - calibration.project(rays), axis=1)
    assert np.sqrt(np.mean(error**2)) < 0.6
    rational, rms = camera.to_calibration("rational_polynomial")
    assert rational.distortion_model == "rational_polynomial" and rms <= fit.rms_px + 1e-6
    assert np.abs(rational.D).max() < 100  # the ridge keeps the ambiguous ratio small

    path = tmp_path / "camera.yaml"
    fit.calibration.save(path)
    loaded = CameraCalibration.load(path)
    assert loaded == fit.calibration and loaded.camera_name == "fitted"


def test_rectification_maps_match_opencv(lens_and_camera):
    calibration, camera = lens_and_camera
    map_x, map_y = camera.rectification_maps()
    assert map_x.shape == (480, 640) and map_x.dtype == np.float32
    ref_x, ref_y = cv2.initUndistortRectifyMap(TRUE_K, TRUE_D, None, camera.K(), (640, 480), cv2.CV_32FC1)
    inside = (ref_x >= 0) & (ref_x <= 639) & (ref_y >= 0) & (ref_y <= 479)
    error = np.hypot(map_x - ref_x, map_y - ref_y)[inside]
    assert error.mean() < 0.5 and error.max() < 2.0
    # and the maps work with cv2.remap as they are
    image = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    assert cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR).shape == image.shape


def test_centred_distortion_starts_at_second_order_at_the_image_centre():
    """The centred correction has zero value and zero first derivative at the image centre (checked with
    autograd, independently of the closed-form Jacobian the camera uses); the raw form is the MLP itself."""
    torch.manual_seed(3)
    camera = CameraModel(64, 48).double()
    with torch.no_grad():
        for module in camera.distortion:
            if isinstance(module, torch.nn.Linear):
                module.weight.normal_(0, 0.7)
                module.bias.normal_(0, 0.3)
    centre = torch.tensor([(64 - 1) / 2.0, (48 - 1) / 2.0], dtype=torch.float64, requires_grad=True)
    correction = camera.distortion_correction(centre[0:1], centre[1:2])[0]
    assert torch.allclose(correction, torch.zeros(2, dtype=torch.float64), atol=1e-12)
    jacobian = torch.stack([torch.autograd.grad(correction[k], centre, retain_graph=True)[0] for k in range(2)])
    assert torch.allclose(jacobian, torch.zeros(2, 2, dtype=torch.float64), atol=1e-12)
    # Away from the centre it is not zero, and it differs from the raw MLP by an affine map only.
    u, v = torch.tensor([3.0, 50.0, 20.0], dtype=torch.float64), torch.tensor([7.0, 40.0, 10.0], dtype=torch.float64)
    centred = camera.distortion_correction(u, v)
    raw = camera.distortion(camera.distortion_input(u, v))
    assert centred.abs().max() > 1e-3
    camera.distortion_form = "raw"
    assert torch.equal(camera.distortion_correction(u, v), raw)
    inputs = camera.distortion_input(u, v)
    affine = torch.linalg.lstsq(torch.cat((inputs, torch.ones(3, 1, dtype=torch.float64)), 1), raw - centred).residuals
    assert affine.numel() == 0 or affine.abs().max() < 1e-20  # 3 points, 3 unknowns: exact


def test_unknown_distortion_form_is_refused():
    with pytest.raises(ValueError, match="distortion form"):
        CameraModel(64, 48, distortion_form="spline")
