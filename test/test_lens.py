"""Parametric lens models against OpenCV, their exact inverses, and the YAML format."""

import cv2
import numpy as np
import pytest
import torch

from nocal_ros.errors import ConfigError
from nocal_ros.lens import CameraCalibration, pixel_grid, scale_intrinsics

K = np.array([[420.0, 0.0, 322.5], [0.0, 415.0, 236.25], [0.0, 0.0, 1.0]])
CAMERAS = {
    "plumb_bob": CameraCalibration(640, 480, K, [-0.28, 0.09, 0.0012, -0.0008, -0.012], "plumb_bob"),
    "rational_polynomial": CameraCalibration(
        640, 480, K, [0.4, -0.05, 0.001, -0.002, 0.01, 0.7, 0.02, 0.01], "rational_polynomial"
    ),
    "equidistant": CameraCalibration(640, 480, K, [-0.02, 0.01, -0.004, 0.001], "equidistant"),
}


def random_points(rng, n=500, half_angle_deg=50.0):
    """Points in front of the camera inside a cone, at 0.5..10 m."""
    angle = np.radians(half_angle_deg) * np.sqrt(rng.uniform(0, 1, n))
    azimuth = rng.uniform(-np.pi, np.pi, n)
    rays = np.stack([np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)], 1)
    return rays * rng.uniform(0.5, 10.0, (n, 1))


@pytest.mark.parametrize("model", list(CAMERAS))
def test_projection_matches_opencv(model):
    camera = CAMERAS[model]
    points = random_points(np.random.default_rng(1))
    if model == "equidistant":
        expected, _ = cv2.fisheye.projectPoints(points[:, None, :], np.zeros(3), np.zeros(3), camera.K, camera.D)
    else:
        expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, camera.D)
    pixels = camera.project(points)
    assert np.abs(pixels - expected.reshape(-1, 2)).max() < 1e-6


@pytest.mark.parametrize("model", list(CAMERAS))
def test_unproject_inverts_project(model):
    camera = CAMERAS[model]
    points = random_points(np.random.default_rng(2))
    rays = camera.unproject(camera.project(points))
    expected = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert np.abs(rays - expected).max() < 1e-10
    # and the other way round, over every pixel of the image
    pixels = pixel_grid(camera.width, camera.height).reshape(-1, 2)
    reprojected = camera.project(camera.unproject(pixels))
    assert np.abs(reprojected - pixels).max() < 1e-8


def test_undistorted_normalised_matches_opencv_undistort_points():
    camera = CAMERAS["plumb_bob"]
    pixels = np.random.default_rng(3).uniform([0, 0], [639, 479], (200, 2))
    ours = camera.undistorted_normalised(pixels)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    theirs = cv2.undistortPoints(pixels[:, None, :], camera.K, camera.D, None, None, None, criteria).reshape(-1, 2)
    assert np.abs(ours - theirs).max() < 1e-8


def test_beyond_the_fold_is_nan_not_a_wrong_ray():
    # k1 = -0.5: r_d = r (1 - 0.5 r^2) peaks at r_d = 0.5443 (r = 0.8165); nothing images beyond.
    camera = CameraCalibration.pinhole(320, 240, fx=150.0, D=[-0.5, 0, 0, 0, 0])
    pixels = pixel_grid(320, 240).reshape(-1, 2)
    radius = np.linalg.norm(camera.distorted_normalised(pixels), axis=1)
    rays = camera.unproject(pixels)
    valid = np.isfinite(rays).all(1)
    assert valid[radius < 0.544].all() and not valid[radius > 0.5444].any()
    assert np.abs(camera.project(rays[valid]) - pixels[valid]).max() < 1e-8


def test_fast_undistortion_finds_the_careful_solves_root_and_none_past_the_fold():
    # Plain Newton on every point first, backtracking only for the rest: on 400 random strong lenses it
    # must give the backtracking solve's root wherever that one is valid, and never a root past the
    # radial curve's first fold (where the careful solve sometimes lands and is NaN'd; plain steps from
    # the same start reach the root before the fold there).
    from nocal_ros.lens import _check_undistorted, _first_fold, _newton_undistort, _newton_undistort_careful

    rng = np.random.default_rng(4)
    found_past_fold = 0
    for trial in range(400):
        model = ("plumb_bob", "rational_polynomial")[trial % 2]
        D = [rng.uniform(-0.45, 0.3), rng.uniform(-0.2, 0.3), rng.normal(0, 0.003), rng.normal(0, 0.003),
             rng.uniform(-0.1, 0.1)]
        if model == "rational_polynomial":
            D += list(rng.uniform(-0.2, 0.4, 3))
        D = np.array(D)
        target = rng.uniform(-1.2, 1.2, (200, 2))
        fast = _check_undistorted(_newton_undistort(target, D, model), target, D, model)
        careful = _check_undistorted(_newton_undistort_careful(target, D, model), target, D, model)
        both = np.isfinite(fast[:, 0]) & np.isfinite(careful[:, 0])
        assert np.array_equal(np.isfinite(careful[:, 0]), both)  # valid wherever the careful solve is
        assert np.abs(fast[both] - careful[both]).max(initial=0.0) < 1e-12
        valid = np.isfinite(fast[:, 0])
        assert ((fast[valid] ** 2).sum(1) < _first_fold(D, model)).all()
        found_past_fold += int((valid & ~both).sum())
    assert found_past_fold < 0.001 * 400 * 200  # the careful solve's misses are rare


def test_the_fused_newton_step_and_root_check_give_the_separate_formulas_bits():
    """Undistortion evaluates the residual and the Jacobian together (the radial factor once): the same
    bits as distort_normalised and _distortion_jacobian apart, NaN included, so replays repeat exactly;
    and checking only the careful solve's points gives what checking every point gave."""
    from nocal_ros.lens import (_check_undistorted, _distortion_jacobian, _first_fold, _imaged_roots,
                                _newton_step, _newton_undistort, _polynomial_newton_step,
                                _radial_and_derivative, distort_normalised)

    rng = np.random.default_rng(5)
    for trial in range(200):
        model = ("plumb_bob", "rational_polynomial")[trial % 2]
        D = rng.normal(0, [0.3, 0.3, 0.01, 0.01, 0.2, 0.3, 0.3, 0.2][: 5 if model == "plumb_bob" else 8])
        x, target = rng.uniform(-1.5, 1.5, (100, 2)), rng.uniform(-1.5, 1.5, (100, 2))
        x[0] = np.nan
        separate = _newton_step(x, distort_normalised(x, D, model) - target, D, model)
        np.testing.assert_array_equal(_polynomial_newton_step(x, target, D, model), separate)
        residual = distort_normalised(x, D, model) - target
        j00, j01, j10, j11 = _distortion_jacobian(x[:, 0], x[:, 1], D, model)
        s = (x**2).sum(-1)
        radial, d_radial = _radial_and_derivative(s, D, model)
        for tolerance in (1e-28, 1e-18, 1e-2):
            expected = (((residual**2).sum(-1) <= tolerance) & (j00 * j11 - j01 * j10 > 0) & (radial > 0)
                        & (radial + 2 * s * d_radial > 0) & (s < _first_fold(D, model)))
            np.testing.assert_array_equal(_imaged_roots(x, target, D, model, tolerance), expected)
        everywhere = _check_undistorted(_newton_undistort(target, D, model), target, D, model)
        np.testing.assert_array_equal(_newton_undistort(target, D, model, checked=True), everywhere)


@pytest.mark.parametrize("model", list(CAMERAS))
def test_torch_matches_numpy_and_is_differentiable(model):
    camera = CAMERAS[model]
    points = random_points(np.random.default_rng(4), n=50)
    points_t = torch.tensor(points, requires_grad=True)
    pixels_t = camera.project(points_t)
    assert torch.allclose(pixels_t, torch.from_numpy(camera.project(points)), atol=1e-9)
    pixels_t.sum().backward()
    assert torch.isfinite(points_t.grad).all() and points_t.grad.abs().sum() > 0
    rays_t = camera.unproject(torch.from_numpy(camera.project(points)))
    assert torch.allclose(rays_t, torch.from_numpy(points / np.linalg.norm(points, axis=1, keepdims=True)), atol=1e-10)


@pytest.mark.parametrize("model", ["plumb_bob", "equidistant"])
def test_pixel_jacobians_are_finite_differences_of_opencvs_projection(model):
    camera = CAMERAS[model]
    points = random_points(np.random.default_rng(4), n=50, half_angle_deg=60.0)
    xy = points[:, :2] / points[:, 2:]

    def opencv_pixels(normalised):
        rays = np.column_stack((normalised, np.ones(len(normalised))))[:, None, :]
        if model == "equidistant":
            pixels, _ = cv2.fisheye.projectPoints(rays, np.zeros(3), np.zeros(3), camera.K, camera.D)
        else:
            pixels, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.K, camera.D)
        return pixels.reshape(-1, 2)

    step = 1e-6
    expected = np.stack([(opencv_pixels(xy + step * e) - opencv_pixels(xy - step * e)) / (2 * step) for e in np.eye(2)], 2)
    np.testing.assert_allclose(camera.pixel_jacobians(xy), expected, rtol=1e-5, atol=1e-3)
    assert CAMERAS["rational_polynomial"].pixel_jacobians(xy) is None


def test_scale_intrinsics_keeps_pixel_areas_aligned():
    # Downsampling 2x: the centre of the top-left 2x2 block (u = 0.5) becomes pixel 0.
    scaled = scale_intrinsics(K, 0.5, 0.5)
    assert scaled[0, 0] == pytest.approx(210.0) and scaled[0, 2] == pytest.approx((322.5 + 0.5) * 0.5 - 0.5)
    camera = CAMERAS["rational_polynomial"]
    small = camera.scaled(160, 120)
    points = random_points(np.random.default_rng(5), n=20)
    # same field of view: the 4x smaller image sees each point at (u + 0.5) / 4 - 0.5
    assert np.allclose(small.project(points), (camera.project(points) + 0.5) / 4 - 0.5, atol=1e-9)


def test_pixel_rays_table_shape_and_subpixels():
    camera = CAMERAS["plumb_bob"].scaled(16, 12)
    table = camera.pixel_rays(supersample=2)
    assert table.shape == (12, 16, 4, 3)
    assert np.allclose(np.linalg.norm(table, axis=-1), 1.0)
    # the mean subpixel of pixel (3, 5) projects to the pixel centre (3, 5) to first order
    centre_samples = camera.project(table[5, 3])
    assert np.allclose(centre_samples.mean(0), [3, 5], atol=1e-6)
    assert np.allclose(np.sort(centre_samples[:, 0]), [2.75, 2.75, 3.25, 3.25], atol=1e-9)


@pytest.mark.parametrize("model", list(CAMERAS))
def test_yaml_round_trip(tmp_path, model):
    camera = CAMERAS[model]
    path = tmp_path / "camera.yaml"
    camera.save(path)
    loaded = CameraCalibration.load(path)
    assert loaded == camera
    assert "camera_matrix:" in path.read_text() and "projection_matrix:" in path.read_text()


@pytest.mark.parametrize(
    "text, problem",
    [
        ("image_width: 640\nimage_height: 480\n", "camera_matrix"),
        ("image_width: [oops\n", "not valid YAML"),
        ("- 1\n- 2\n", "mapping"),
        ("image_width: -3\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [1,0,0,0,1,0,0,0,1]}\n", "image_width"),
        ("image_width: 64\nimage_height: 48\ncamera_matrix: {rows: 3, cols: 3, data: [1,0,0,0,1]}\n", "camera_matrix"),
        ("image_width: 64\nimage_height: 48\ncamera_matrix: {data: [.nan,0,0,0,1,0,0,0,1]}\n", "non-finite"),
        ("image_width: 64\nimage_height: 48\ncamera_matrix: {data: [0,0,0,0,1,0,0,0,1]}\n", "focal"),
        ("image_width: 64\nimage_height: 48\ncamera_matrix: {data: [50,0,30,0,50,20,0,0,1]}\n"
         "distortion_model: kannala\n", "kannala"),
        ("image_width: 64\nimage_height: 48\ncamera_matrix: {data: [50,0,30,0,50,20,0,0,1]}\n"
         "distortion_model: equidistant\ndistortion_coefficients: {data: [0.1, 0.2]}\n", "4 distortion"),
        ("image_width: 64\nimage_height: 48\ncamera_matrix: {data: [50,0,30,0,50,20,0,0,1]}\n"
         "distortion_coefficients: {data: [a, b, c, d, e]}\n", "numbers"),
    ],
)
def test_malformed_yaml_raises_config_error_naming_the_file(tmp_path, text, problem):
    path = tmp_path / "bad_camera.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=problem) as info:
        CameraCalibration.load(path)
    assert "bad_camera.yaml" in str(info.value)


def test_missing_file_raises_config_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        CameraCalibration.load(tmp_path / "nope.yaml")


# A file as camera_calibration's monocular calibrator writes it (camera_calibration_parsers' layout):
# P is the rectified image's camera, not [K | 0].
OST_YAML = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [  617.3,    0.  ,  327.2,
             0.  ,  617.1,  239.8,
             0.  ,    0.  ,    1.  ]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.101, -0.223, 0.0012, -0.0004, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1., 0., 0.,
         0., 1., 0.,
         0., 0., 1.]
projection_matrix:
  rows: 3
  cols: 4
  data: [  623.5,    0.  ,  326.9,    0.  ,
             0.  ,  626.2,  239.1,    0.  ,
             0.  ,    0.  ,    1.  ,    0.  ]
"""


def test_camera_calibration_files_keep_their_projection_and_rectification(tmp_path):
    source = tmp_path / "ost.yaml"
    source.write_text(OST_YAML)
    camera = CameraCalibration.load(source)
    assert camera.camera_name == "narrow_stereo" and camera.R is None  # the identity is not stored
    np.testing.assert_array_equal(camera.projection[:, :3], [[623.5, 0, 326.9], [0, 626.2, 239.1], [0, 0, 1]])
    np.testing.assert_array_equal(camera.rectification, np.eye(3))
    copy = tmp_path / "copy.yaml"
    camera.save(copy)
    assert CameraCalibration.load(copy) == camera
    # A stereo camera's R and P (baseline in P[0, 3]) survive too, and differ from the monocular default.
    R = np.array([[0.9998, -0.0175, 0.0], [0.0175, 0.9998, 0.0], [0.0, 0.0, 1.0]])
    P = np.array([[600.0, 0, 320.0, -42.0], [0, 600.0, 240.0, 0.0], [0, 0, 1.0, 0.0]])
    stereo = CameraCalibration(640, 480, camera.K, camera.D, camera_name="right", R=R, P=P)
    stereo.save(copy)
    loaded = CameraCalibration.load(copy)
    assert loaded == stereo and loaded != CameraCalibration(640, 480, camera.K, camera.D, camera_name="right")
    np.testing.assert_array_equal(loaded.P, P)
    np.testing.assert_array_equal(loaded.R, R)


def test_scaling_moves_the_projection_like_the_camera_matrix():
    P = np.array([[600.0, 0, 320.0, -42.0], [0, 610.0, 240.0, 0.0], [0, 0, 1.0, 0.0]])
    camera = CameraCalibration(640, 480, [[590.0, 0, 321.0], [0, 591.0, 239.0], [0, 0, 1]], P=P)
    half = camera.scaled(320, 240)
    np.testing.assert_allclose(half.P[:, :3], scale_intrinsics(P[:, :3], 0.5, 0.5))
    assert half.P[0, 3] == pytest.approx(-21.0)  # -fx' B: the baseline is unchanged, fx halves
    np.testing.assert_allclose(half.K, scale_intrinsics(camera.K, 0.5, 0.5))
    assert CameraCalibration.pinhole(64, 48, 50.0).scaled(32, 24).P is None


def test_non_finite_projection_is_refused(tmp_path):
    path = tmp_path / "bad_projection.yaml"
    path.write_text(OST_YAML.replace("623.5", ".nan"))
    with pytest.raises(ConfigError, match="bad_projection.yaml: projection_matrix holds non-finite"):
        CameraCalibration.load(path)
