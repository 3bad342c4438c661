"""The VO's geometric pieces against independent references: OpenCV, closed forms, finite differences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from nocal_ros.errors import NocalError
from nocal_ros.geometry import invert_transform, make_transform, so3_exp, so3_log
from nocal_ros.lens import CameraCalibration
from nocal_ros.odometry.frontend import (
    FeatureTracker,
    TrackerSettings,
    pose_covariance,
    ray_whitening,
    reprojection_errors,
    solve_pnp,
)
from nocal_ros.odometry.initializer import rotation_ransac, two_view_map, unit_rays
from nocal_ros.odometry.map import Keyframe, parallax_deg, triangulate
from nocal_ros.odometry.scale import fit_arm_scale, fit_ground_plane, fit_ground_scale, ground_motion_ratio, umeyama

CAMERA = CameraCalibration(640, 480, np.array([[520.0, 0, 330.0], [0, 515.0, 236.0], [0, 0, 1]]),
                           np.array([-0.25, 0.08, 0.001, -0.0005, 0.0]), "plumb_bob")


def scene(n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack((rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(2.0, 6.0, n)))


def pixels_of(points_w: np.ndarray, T_w_c: np.ndarray, camera: CameraCalibration = CAMERA) -> np.ndarray:
    """OpenCV's projection (the independent reference) of world points into a camera at ``T_w_c``."""
    T_c_w = invert_transform(T_w_c)
    rvec, _ = cv2.Rodrigues(T_c_w[:3, :3])
    pixels, _ = cv2.projectPoints(points_w, rvec, T_c_w[:3, 3], camera.K, camera.D)
    return pixels.reshape(-1, 2)


def test_pnp_on_rays_agrees_with_opencv_on_undistorted_points():
    rng = np.random.default_rng(1)
    T_w_c = make_transform(so3_exp(np.array([0.05, -0.1, 0.03])), np.array([0.2, -0.1, 0.3]))
    points = scene()
    pixels = pixels_of(points, T_w_c) + rng.normal(scale=0.3, size=(len(points), 2))
    outliers = rng.choice(len(points), 20, replace=False)
    pixels[outliers] += rng.uniform(20, 60, size=(20, 2))
    result = solve_pnp(points, CAMERA.undistorted_normalised(pixels), 2.0 / CAMERA.fx)
    assert result is not None
    assert not result.inliers[outliers].any() and result.inliers.sum() >= 170
    # OpenCV on the same inliers, undistorted by OpenCV itself, from OpenCV's own solver.
    inliers = result.inliers
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    undistorted = cv2.undistortPoints(pixels[inliers].reshape(-1, 1, 2), CAMERA.K, CAMERA.D, criteria=criteria).reshape(-1, 2)
    ok, rvec, tvec = cv2.solvePnP(points[inliers], undistorted, np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    R = cv2.Rodrigues(rvec)[0]
    T_opencv = make_transform(R.T, (-R.T @ tvec).ravel())
    delta = invert_transform(T_opencv) @ result.T_w_c
    # Both stop on their own convergence tolerances: agreement to micrometres on a 0.4 m pose.
    assert np.linalg.norm(delta[:3, 3]) < 1e-5 and np.linalg.norm(so3_log(delta[:3, :3])) < 1e-6
    # And both near the truth (0.3 px noise).
    error = invert_transform(T_w_c) @ result.T_w_c
    assert np.linalg.norm(error[:3, 3]) < 5e-3 and np.degrees(np.linalg.norm(so3_log(error[:3, :3]))) < 0.1


def test_pnp_keeps_a_better_guess_and_gives_up_with_too_few_points():
    points = scene(10)
    T = np.eye(4)
    x = CAMERA.undistorted_normalised(pixels_of(points, T))
    assert solve_pnp(points, x, 1e-3, min_inliers=12) is None
    result = solve_pnp(points, x, 1e-3, guess=T, min_inliers=8)
    assert result is not None and np.allclose(result.T_w_c, T, atol=1e-6)


def test_robust_pnp_takes_out_one_off_landmark_under_the_threshold_and_leaves_clean_noise_alone():
    """A 160x120 camera (f = 130 px), 40 landmarks seen with 0.1 px noise and one more at the image's
    corner 1.36 px off: under the 1.5 px threshold, so an inlier that the least-squares pose leans
    toward (the replays' case: one landmark 1.2 px off turned a frame 0.45 deg). The Cauchy refinement
    must pose as if that landmark were not there, keep the same inliers, and on clean noise agree with
    least squares to within the noise."""
    camera = CameraCalibration(160, 120, np.array([[130.0, 0, 80.0], [0, 130.0, 60.0], [0, 0, 1]]), np.zeros(5),
                               "plumb_bob")
    T = make_transform(so3_exp(np.array([0.05, -0.1, 0.03])), np.array([0.2, -0.1, 0.3]))
    threshold = 1.5 / camera.fx

    def angle_deg(estimate: np.ndarray) -> float:
        return float(np.degrees(np.linalg.norm(so3_log(T[:3, :3].T @ estimate[:3, :3]))))

    errors = {"least squares": [], "robust": [], "without it": [], "clean least squares": [], "clean robust": []}
    for seed in range(8):
        rng = np.random.default_rng(seed)
        corner = np.array([[-1.25, -0.9, 2.5]])  # camera frame: pixel (15, 13)
        points = np.vstack((scene(40, seed), corner @ T[:3, :3].T + T[:3, 3]))
        noise = rng.normal(scale=0.1, size=(len(points), 2))
        clean = camera.undistorted_normalised(pixels_of(points, T, camera) + noise)
        off = pixels_of(points, T, camera) + noise
        off[-1] += (1.1, -0.8)
        x = camera.undistorted_normalised(off)
        whitening = ray_whitening(camera, x)
        plain = solve_pnp(points, x, threshold, guess=T, whitening=whitening)
        robust = solve_pnp(points, x, threshold, guess=T, whitening=whitening, robust=True)
        alone = solve_pnp(points[:-1], x[:-1], threshold, guess=T, whitening=whitening[:-1])
        assert plain.inliers.all() and np.array_equal(robust.inliers, plain.inliers)
        errors["least squares"].append(angle_deg(plain.T_w_c))
        errors["robust"].append(angle_deg(robust.T_w_c))
        errors["without it"].append(angle_deg(alone.T_w_c))
        errors["clean least squares"].append(angle_deg(solve_pnp(points, clean, threshold, guess=T).T_w_c))
        errors["clean robust"].append(angle_deg(solve_pnp(points, clean, threshold, guess=T, robust=True).T_w_c))
    mean = {name: float(np.mean(values)) for name, values in errors.items()}
    # Measured: least squares 0.100 deg, robust 0.031, without the landmark 0.032; clean 0.03 both.
    assert mean["least squares"] > 2.5 * mean["without it"]
    assert mean["robust"] < 1.25 * mean["without it"]
    assert mean["clean robust"] < 1.25 * mean["clean least squares"]


def test_pose_covariance_is_the_inverse_of_the_numerical_gauss_newton_information():
    points = scene(60, seed=3)
    T = make_transform(so3_exp(np.array([0.1, 0.2, -0.1])), np.array([0.3, 0.1, -0.2]))
    sigma = 1e-3

    def residuals(xi: np.ndarray) -> np.ndarray:
        perturbed = T @ make_transform(so3_exp(xi[3:]), xi[:3])
        points_c = (points - perturbed[:3, 3]) @ perturbed[:3, :3]
        return (points_c[:, :2] / points_c[:, 2:]).ravel()

    step = 1e-6
    J = np.column_stack([(residuals(step * e) - residuals(-step * e)) / (2 * step) for e in np.eye(6)])
    expected = np.linalg.inv(J.T @ J / sigma**2)
    np.testing.assert_allclose(pose_covariance(T, points, sigma), expected, rtol=1e-4, atol=1e-14)


def test_pnp_covariance_through_a_fisheye_describes_its_errors_under_pixel_noise():
    """A 160x120 fisheye at f = 60 px sees 75 degrees off axis, where one pixel moves a ray's x/z six
    times as far as at the centre: the rays PnP fits are noisier at the edge. Monte Carlo over pixel
    noise (OpenCV projects, the independent reference): with the lens's whitening the reported
    covariance describes the spread of the estimates (NEES near 6 for 6 degrees of freedom); without
    it, noise is taken as alike everywhere, and the covariance is several times too small (the published
    steps of the fisheye bag were 8.5 % beyond their 99 % bound)."""
    camera = CameraCalibration(160, 120, np.array([[60.0, 0, 80.0], [0, 60.0, 60.0], [0, 0, 1]]),
                               np.array([0.02, -0.01, 0.003, -0.001]), "equidistant")
    rng = np.random.default_rng(7)
    angle = np.radians(75.0) * np.sqrt(rng.uniform(0, 1, 150))
    azimuth = rng.uniform(-np.pi, np.pi, 150)
    rays = np.column_stack((np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)))
    points = rays * rng.uniform(1.0, 4.0, (150, 1))
    inside = (np.abs(camera.project(points) - [80.0, 60.0]) < [78.0, 58.0]).all(1)
    points = points[inside]
    clean, _ = cv2.fisheye.projectPoints(points[:, None, :], np.zeros(3), np.zeros(3), camera.K, camera.D)
    clean = clean.reshape(-1, 2)
    nees = {"whitened": [], "alike": []}
    for _ in range(150):
        x = camera.undistorted_normalised(clean + rng.normal(scale=1.0, size=clean.shape))
        for name, whitening in (("whitened", ray_whitening(camera, x)), ("alike", None)):
            result = solve_pnp(points, x, 6.0 / camera.fx, guess=np.eye(4), whitening=whitening)
            assert result is not None and result.inliers.mean() > 0.8
            xi = np.concatenate((result.T_w_c[:3, 3], so3_log(result.T_w_c[:3, :3])))  # from the truth, identity
            nees[name].append(xi @ np.linalg.solve(result.covariance, xi))
    # The noise is the inliers' RMS residual per point, over both axes: twice the variance per axis, so
    # consistent here means a mean NEES of 3 (measured 2.2; without the whitening 16).
    assert 1.5 < np.mean(nees["whitened"]) < 4.5
    assert np.mean(nees["alike"]) > 3 * np.mean(nees["whitened"])


def test_ray_whitening_is_the_identity_at_an_undistorted_pinholes_centre():
    camera = CameraCalibration.pinhole(640, 480, 500.0)
    x = np.array([[0.0, 0.0], [0.3, -0.2]])
    whitening = ray_whitening(camera, x)
    np.testing.assert_allclose(whitening, np.broadcast_to(np.eye(2), (2, 2, 2)), atol=1e-12)
    points = scene(80, seed=5)
    T = make_transform(so3_exp(np.array([0.02, 0.01, -0.03])), np.array([0.1, 0.0, -0.1]))
    sigma = 2e-3
    np.testing.assert_allclose(pose_covariance(T, points, sigma, np.broadcast_to(np.eye(2), (80, 2, 2))),
                               pose_covariance(T, points, sigma), rtol=1e-9, atol=1e-18)


def test_two_view_map_recovers_the_motion_and_waits_for_parallax():
    points = scene(150, seed=4)
    T_ref = np.eye(4)
    T_cur = make_transform(so3_exp(np.array([0.02, -0.05, 0.01])), np.array([0.12, 0.02, 0.03]))
    x_ref = CAMERA.undistorted_normalised(pixels_of(points, T_ref))
    x_cur = CAMERA.undistorted_normalised(pixels_of(points, T_cur))
    result = two_view_map(x_ref, x_cur, 1.0 / CAMERA.fx)
    assert result is not None and result.inliers.mean() > 0.85
    np.testing.assert_allclose(result.T_ref_cur[:3, :3], T_cur[:3, :3], atol=1e-6)
    direction = T_cur[:3, 3] / np.linalg.norm(T_cur[:3, 3])
    np.testing.assert_allclose(result.T_ref_cur[:3, 3], direction, atol=1e-6)
    # Landmarks in units of the baseline: the true points divided by the true baseline length.
    np.testing.assert_allclose(result.points, points[result.inliers] / np.linalg.norm(T_cur[:3, 3]), rtol=1e-5)

    # A camera that only turns shows no parallax: no map, and the rotation from rays is exact.
    T_turn = make_transform(so3_exp(np.array([0.02, -0.05, 0.01])), np.zeros(3))
    x_turn = CAMERA.undistorted_normalised(pixels_of(points, T_turn))
    assert two_view_map(x_ref, x_turn, 1.0 / CAMERA.fx) is None
    R, inliers = rotation_ransac(unit_rays(x_ref), unit_rays(x_turn), 1.0 / CAMERA.fx)
    assert inliers.all()
    np.testing.assert_allclose(R.T, T_turn[:3, :3], atol=1e-9)


def test_triangulation_and_parallax_against_the_truth():
    points = scene(30, seed=5)
    T_i = np.eye(4)
    T_j = make_transform(so3_exp(np.array([0.0, 0.1, 0.0])), np.array([0.5, 0.0, 0.0]))
    x_i = CAMERA.undistorted_normalised(pixels_of(points, T_i))
    x_j = CAMERA.undistorted_normalised(pixels_of(points, T_j))
    np.testing.assert_allclose(triangulate(T_i, T_j, x_i, x_j), points, rtol=1e-7)
    # Closed form for one point straight ahead of the first camera at depth 4, baseline 0.5 sideways.
    angle = parallax_deg(T_i, T_j, np.array([[0.0, 0.0, 4.0]]))
    assert angle[0] == pytest.approx(np.degrees(np.arctan2(0.5, 4.0)), abs=1e-9)
    assert np.isinf(reprojection_errors(T_i, np.array([[0.0, 0.0, -1.0]]), np.zeros((1, 2))))[0]


def test_keyframe_lookup_finds_ids_in_any_order():
    keyframe = Keyframe(0, 0, 0, np.eye(4), np.array([2, 5, 9, 14]), np.arange(8.0).reshape(4, 2))
    found, rows = keyframe.lookup(np.array([14, 3, 2, 20]))
    assert found.tolist() == [True, False, True, False] and rows.tolist() == [3, 0]


def test_umeyama_recovers_a_similarity_exactly():
    rng = np.random.default_rng(6)
    source = rng.normal(size=(20, 3))
    R = so3_exp(np.array([0.3, -0.2, 0.9]))
    target = 2.5 * source @ R.T + np.array([1.0, -2.0, 0.5])
    s, R_fit, t = umeyama(source, target)
    assert s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-12)
    with pytest.raises(ValueError):
        umeyama(np.zeros((3, 3)), target[:3])


def test_arm_scale_is_the_similarity_fit_and_needs_three_keyframes():
    map_positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 1.0]])
    arm = 0.3 * map_positions @ so3_exp(np.array([0, 0, 1.0])).T + 4.0
    assert fit_arm_scale(map_positions[:2], arm[:2]) is None  # two keyframes fix no similarity
    assert fit_arm_scale(np.zeros((4, 3)), arm) is None  # a map that has not moved has no scale
    fitted = fit_arm_scale(map_positions, arm)
    assert fitted.source == "arm" and fitted.scale == pytest.approx(0.3, rel=1e-12) and fitted.samples == 4
    assert fitted.relative_std < 1e-9  # no residual: exact


def test_arm_scale_spread_is_the_spread_of_the_fitted_scale_under_noise():
    """With arm positions 1 cm noisy, the fit's relative standard deviation (least squares, from one fit's
    residuals) matches the spread of the scale over 2000 noisy draws to 10 %, and the scale is unbiased."""
    rng = np.random.default_rng(21)
    map_positions = rng.normal(scale=2.0, size=(8, 3))
    R = so3_exp(np.array([0.2, 0.5, -0.3]))
    clean = 0.25 * map_positions @ R.T + np.array([0.5, 1.0, 0.2])
    fits = [fit_arm_scale(map_positions, clean + rng.normal(scale=0.01, size=clean.shape)) for _ in range(2000)]
    scales = np.array([f.scale for f in fits])
    predicted = np.median([f.relative_std for f in fits])
    assert np.mean(scales) == pytest.approx(0.25, rel=2e-3)
    assert np.std(scales) / 0.25 == pytest.approx(predicted, rel=0.1)


def test_scale_step_covariance_lies_along_the_step_seen_from_the_later_camera():
    """A step whose scale is off by ``e`` has its translation error ``e R^T t`` in the later camera's
    frame (the translation of ``T_true^-1 T_est``); the covariance is ``std^2`` times that direction's
    outer product, and nothing in the rotation."""
    from nocal_ros.odometry.covariance import scale_step_covariance

    R = so3_exp(np.array([0.1, -0.4, 0.2]))
    step = np.eye(4)
    step[:3, :3], step[:3, 3] = R, [0.3, -0.1, 0.05]
    longer = step.copy()
    longer[:3, 3] *= 1.2
    error = (np.linalg.inv(step) @ longer)[:3, 3]
    covariance = scale_step_covariance(step, 0.2)
    np.testing.assert_allclose(covariance[:3, :3], np.outer(error, error), atol=1e-15)
    assert not covariance[3:].any() and not covariance[:, 3:].any()


def test_a_direction_free_step_covariance_holds_a_step_of_that_length_in_any_direction():
    """A step whose direction is not known may lie anywhere about the measured one: the covariance is
    isotropic, each axis the measured length times ``1 + std``, and nothing in the rotation. The true
    step opposite the measured one and as long (an error of twice the length) has a NEES of
    ``(2 / (1 + std))^2``; a true step of no length, ``(1 / (1 + std))^2``, from any direction."""
    from nocal_ros.odometry.covariance import direction_free_step_covariance

    rng = np.random.default_rng(3)
    for _ in range(20):
        measured = np.eye(4)
        measured[:3, :3], measured[:3, 3] = so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.05, 3)
        covariance = direction_free_step_covariance(measured, 1.2)
        assert not covariance[3:].any() and not covariance[:, 3:].any()
        for true_translation, nees in ((-measured[:3, 3], (2 / 2.2) ** 2), (np.zeros(3), (1 / 2.2) ** 2)):
            true = measured.copy()
            true[:3, 3] = true_translation
            error = (np.linalg.inv(true) @ measured)[:3, 3]
            assert error @ np.linalg.solve(covariance[:3, :3], error) == pytest.approx(nees, rel=1e-9)
        # Another measure of the length (the pose head's): the longer one sizes the error, so a step the
        # map measured at a thirtieth of its length is held by the other; a shorter or NaN one changes nothing.
        longer = 30 * float(np.linalg.norm(measured[:3, 3]))
        np.testing.assert_allclose(direction_free_step_covariance(measured, 1.2, longer)[:3, :3],
                                   (longer * 2.2) ** 2 * np.eye(3), rtol=1e-12)
        for other in (0.5 * float(np.linalg.norm(measured[:3, 3])), float("nan"), None):
            np.testing.assert_array_equal(direction_free_step_covariance(measured, 1.2, other), covariance)


def street(noise_m: float = 0.0, seed: int = 0, ceiling: bool = False, pitch_deg: float = 3.0) -> dict:
    """A drive down a street, world z up: cameras 1.65 m above a road (z = 0), pitched ``pitch_deg`` down,
    facing +y; building fronts at x = +-7 m from 0.5 m up; with ``ceiling``, a denser plane 5 m up (an
    overpass). Returned in a map frame that is the world moved by a known similarity (``scale`` metres per
    map unit), as a monocular map holds it, with the cameras' poses in it (``poses``)."""
    rng = np.random.default_rng(seed)
    pitch = np.radians(pitch_deg)
    # optical axes in the world: x right, y down, z forward (+y), turned about x by the pitch
    level = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    R_w_c = so3_exp(np.array([-pitch, 0, 0])) @ level
    centres = np.stack([np.zeros(12), np.linspace(0, 11, 12), np.full(12, 1.65)], axis=1)
    road = np.stack([rng.uniform(-4, 4, 150), rng.uniform(5, 40, 150), np.zeros(150)], axis=1)
    walls = np.stack([rng.choice([-7.0, 7.0], 250), rng.uniform(0, 45, 250), rng.uniform(0.5, 9, 250)], axis=1)
    points = [road, walls]
    if ceiling:
        points.append(np.stack([rng.uniform(-6, 6, 300), rng.uniform(5, 30, 300), np.full(300, 5.0)], axis=1))
    points = np.concatenate(points) + rng.normal(0, noise_m, (sum(len(p) for p in points), 3))
    scale, R, t = 0.37, so3_exp(np.array([0.4, -1.1, 0.3])), np.array([2.0, -1.0, 5.0])  # world = scale R map + t
    to_map = lambda x: (x - t) @ R / scale  # noqa: E731
    down = R.T @ (R_w_c @ np.array([0.0, 1.0, 0.0]))
    poses = np.tile(np.eye(4), (len(centres), 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = R.T @ R_w_c, to_map(centres)
    return dict(points=to_map(points), centres=to_map(centres), down=down, scale=scale, road_normal=R.T @ [0, 0, -1.0],
                poses=poses, world=dict(road=road, centres=centres, down=R_w_c @ np.array([0.0, 1.0, 0.0]), R_w_c=R_w_c))


def test_ground_scale_is_the_camera_height_over_its_height_above_the_road_in_the_map():
    exact = street()
    plane = fit_ground_plane(exact["points"], exact["centres"], exact["down"])
    np.testing.assert_allclose(plane.normal, exact["road_normal"], atol=1e-9)
    np.testing.assert_allclose(plane.heights(exact["centres"]) * exact["scale"], 1.65, rtol=1e-9)
    fitted = fit_ground_scale(exact["points"], exact["centres"], exact["down"], 1.65)
    assert fitted.source == "ground" and fitted.scale == pytest.approx(exact["scale"], rel=1e-9)
    # the road's landmarks seen at least 3 deg below the cameras' horizontal, counted in the world
    world = exact["world"]
    offsets = world["road"][:, None, :] - world["centres"][None]
    nearest = offsets[np.arange(len(offsets)), np.argmin(np.linalg.norm(offsets, axis=2), axis=1)]
    seen_below = nearest @ world["down"] > np.sin(np.radians(3.0)) * np.linalg.norm(nearest, axis=1)
    assert fitted.samples == plane.inliers == seen_below.sum() > 50
    # 2 cm of noise on every landmark: within 1 % (the road's 150 landmarks average it out)
    noisy = street(noise_m=0.02, seed=1)
    assert fit_ground_scale(noisy["points"], noisy["centres"], noisy["down"], 1.65).scale == pytest.approx(noisy["scale"], rel=0.01)


def test_ground_plane_is_below_the_cameras_and_absent_where_the_map_shows_none():
    overpass = street(noise_m=0.01, ceiling=True)  # more landmarks above than on the road
    fitted = fit_ground_scale(overpass["points"], overpass["centres"], overpass["down"], 1.65)
    assert fitted.scale == pytest.approx(overpass["scale"], rel=0.01)
    walls_only = street()
    walls_only["points"] = walls_only["points"][150:]
    assert fit_ground_plane(walls_only["points"], walls_only["centres"], walls_only["down"]) is None
    # a plane that almost meets one of the cameras is not the floor they move over
    low = street()
    low["centres"][5] += 0.9 * 1.65 / low["scale"] * low["road_normal"]  # 0.17 m above the road
    assert fit_ground_plane(low["points"], low["centres"], low["down"]) is None
    for height in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="camera height"):
            fit_ground_scale(overpass["points"], overpass["centres"], overpass["down"], height)


def test_a_ground_frame_gives_the_height_and_the_down_of_a_camera_pitched_towards_the_road():
    """A camera pitched 35 deg down, more than the plane fit's tilt (``GROUND_MAX_TILT_DEG``): through the
    image's down (the camera as its own base) the road's normal is 35 deg off, and no plane is taken.
    Through a ground frame beneath the camera (``set_ground_to_camera``: REP 120's base_footprint) the
    height is the camera's z there and the down that frame's -z: the road is found and the scale exact. A
    ground frame above the camera is refused."""
    from nocal_ros.odometry import OdometryEstimator
    from nocal_ros.odometry.map import LocalMap
    from nocal_ros.odometry.scale import GROUND_MAX_TILT_DEG

    pitched = street(pitch_deg=35.0)
    assert 35.0 > GROUND_MAX_TILT_DEG
    local_map = LocalMap()
    ids = np.arange(len(pitched["points"]))
    for k, pose in enumerate(pitched["poses"]):
        local_map.add_keyframe(k, k, pose, ids, np.zeros((len(ids), 2)))
    local_map.landmarks.update(enumerate(pitched["points"]))
    estimator = OdometryEstimator(camera_height=1.65)
    assert estimator._ground_scale(local_map) is None
    T_ground_cam = np.eye(4)
    T_ground_cam[:3, :3], T_ground_cam[2, 3] = pitched["world"]["R_w_c"], 1.65
    estimator.set_ground_to_camera(T_ground_cam)
    assert estimator.camera_height == 1.65
    assert estimator._ground_scale(local_map).scale == pytest.approx(pitched["scale"], rel=1e-9)
    below = T_ground_cam.copy()
    below[2, 3] = -0.3
    with pytest.raises(NocalError, match="ground frame"):
        estimator.set_ground_to_camera(below)
    with pytest.raises(ValueError, match="4x4"):
        estimator.set_ground_to_camera(np.full((4, 4), np.nan))
    assert estimator.camera_height == 1.65
    estimator.close()



def test_the_roads_homography_gives_the_distance_moved_over_the_height_as_opencvs_decomposition_does():
    """Two frames 1 m apart down the street (cameras 1.65 m above the road, pitched 3 deg down, the second
    turned 2.6 deg), the road's landmarks and the building fronts' projected into both: given the motion's rotation and direction, the
    road's tracks agree on ``|t| / d`` = 1 / 1.65 exactly, the walls' do not, and OpenCV's decomposition of
    the road's homography gives the same ``|t| / d``. Half a pixel of noise at 700 px moves it by under
    2 %. A direction pointing back, or walls alone, give nothing."""
    world = street()["world"]
    R_w_c, centres = world["R_w_c"], world["centres"]
    rng = np.random.default_rng(3)
    walls = np.stack([rng.choice([-7.0, 7.0], 250), rng.uniform(0, 45, 250), rng.uniform(0.5, 9, 250)], axis=1)

    R_w_c2 = R_w_c @ so3_exp(np.array([0.01, 0.04, -0.02]))  # the second camera turned a little

    def seen(points: np.ndarray, centre: np.ndarray, R: np.ndarray = R_w_c) -> np.ndarray:
        return (points - centre) @ R  # camera coordinates (x right, y down, z forward)

    def normalised(cam: np.ndarray) -> np.ndarray:
        return cam[:, :2] / cam[:, 2:]

    points = np.concatenate([world["road"], walls])
    first, second = seen(points, centres[0]), seen(points, centres[1], R_w_c2)
    visible = (first[:, 2] > 0.5) & (second[:, 2] > 0.5)
    first, second = first[visible], second[visible]
    on_road = np.arange(len(points))[visible] < len(world["road"])
    rotation = R_w_c2.T @ R_w_c  # X_second = rotation X_first + t
    t = (centres[0] - centres[1]) @ R_w_c2
    down = R_w_c.T @ np.array([0.0, 0.0, -1.0])
    exact = ground_motion_ratio(normalised(first), normalised(second), rotation, t, down)
    assert exact.ratio == pytest.approx(1.0 / 1.65, rel=1e-9)
    np.testing.assert_allclose(exact.normal, down, atol=1e-9)
    depressed = first @ down > np.sin(np.radians(3.0)) * np.linalg.norm(first, axis=1)
    assert exact.inliers == (on_road & depressed).sum() > 50
    assert exact.std < 1e-9
    # OpenCV: the road's homography decomposed; the solution whose normal is the road's has |t| / d
    H, _ = cv2.findHomography(normalised(first[on_road]), normalised(second[on_road]), 0)
    count, rotations, translations, normals = cv2.decomposeHomographyMat(H, np.eye(3))
    match = [k for k in range(count) if normals[k].ravel() @ down > 0.999]
    assert len(match) == 1
    np.testing.assert_allclose(rotations[match[0]], rotation, atol=1e-6)
    assert float(np.linalg.norm(translations[match[0]])) == pytest.approx(exact.ratio, rel=1e-6)
    # half a pixel of noise at 700 px
    noise = rng.normal(0.0, 0.5 / 700.0, (len(second), 2))
    noisy = ground_motion_ratio(normalised(first), normalised(second) + noise, rotation, t, down)
    assert noisy.ratio == pytest.approx(1.0 / 1.65, rel=0.02)
    assert 0 < noisy.std < 0.02 * noisy.ratio
    assert abs(noisy.ratio - 1.0 / 1.65) < 4 * noisy.std + 1e-3
    assert ground_motion_ratio(normalised(first), normalised(second), rotation, -t, down) is None
    assert ground_motion_ratio(normalised(first[~on_road]), normalised(second[~on_road]), rotation, t, down) is None

def test_the_floor_beneath_a_table_with_more_landmarks_is_the_ground():
    """A room, world z up: cameras 1.5 m above the floor looking ahead and down, a table top 0.75 m
    high in front with 120 landmarks, the floor beyond it with 100, walls from 0.3 m up. The table has
    most support, but more than half as many landmarks lie far beneath it (the floor's and the walls'), so
    the floor is searched for beneath it and found: the scale is exact. With nothing beneath (the map
    shows the table alone) the table is all there is to take."""
    rng = np.random.default_rng(4)
    centres = np.stack([np.linspace(0, 2, 8), np.zeros(8), np.full(8, 1.5)], axis=1)
    table = np.stack([rng.uniform(-1, 3, 120), rng.uniform(1.5, 3, 120), np.full(120, 0.75)], axis=1)
    floor = np.stack([rng.uniform(-3, 5, 100), rng.uniform(3.5, 8, 100), np.zeros(100)], axis=1)
    walls = np.stack([rng.choice([-4.0, 6.0], 200), rng.uniform(0, 8, 200), rng.uniform(0.3, 2.5, 200)], axis=1)
    scale, R, t = 0.21, so3_exp(np.array([-0.7, 0.2, 1.3])), np.array([1.0, 3.0, -2.0])  # world = scale R map + t
    to_map = lambda x: (x - t) @ R / scale  # noqa: E731
    down = R.T @ np.array([0.0, 0.0, -1.0])  # the base's -z through TF
    points = to_map(np.concatenate([table, floor, walls]))
    plane = fit_ground_plane(points, to_map(centres), down)
    np.testing.assert_allclose(plane.normal, R.T @ [0, 0, -1.0], atol=1e-9)
    assert plane.inliers == 100
    assert fit_ground_scale(points, to_map(centres), down, 1.5).scale == pytest.approx(scale, rel=1e-9)
    table_alone = fit_ground_plane(to_map(table), to_map(centres), down)
    np.testing.assert_allclose(table_alone.heights(to_map(centres)) * scale, 0.75, rtol=1e-9)


def shifted(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    return cv2.warpAffine(image, np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]]), (image.shape[1], image.shape[0]),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def textured_image(width: int = 320, height: int = 240, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(cv2.resize(rng.integers(0, 256, (height // 8, width // 8), dtype=np.uint8), (width, height),
                                       interpolation=cv2.INTER_NEAREST), (5, 5), 1.5)


def test_tracks_keep_their_ids_follow_the_motion_and_spread_over_the_grid():
    image = textured_image()
    tracker = FeatureTracker(TrackerSettings(max_tracks=120, grid=(4, 3)))
    assert len(tracker.track(image).ids) == 0
    assert tracker.top_up() > 60
    start = tracker.current()
    cells = {(int(u // 80), int(v // 80)) for u, v in start.pixels}
    assert len(cells) == 12  # every cell of the 4x3 grid has tracks
    moved = tracker.track(shifted(image, 3.0, -2.0))
    common = np.isin(start.ids, moved.ids)
    assert common.mean() > 0.9
    np.testing.assert_allclose(moved.pixels - start.pixels[common], [[3.0, -2.0]] * int(common.sum()), atol=0.1)
    tracker.drop(moved.ids[:5])
    assert not np.isin(moved.ids[:5], tracker.current().ids).any()
    # A frame 1.5 times the work width or wider is tracked smaller; coordinates stay native.
    somewhat_wide = FeatureTracker(TrackerSettings(max_tracks=80, work_width=240))
    somewhat_wide.track(image)
    assert somewhat_wide.gray.shape == (240, 320) and somewhat_wide.work_scale == (1.0, 1.0)
    wide = FeatureTracker(TrackerSettings(max_tracks=80, work_width=160))
    wide.track(image)
    assert wide.gray.shape == (120, 160) and wide.work_scale == (2.0, 2.0)
    wide.top_up()
    before = wide.current()
    after = wide.track(shifted(image, 4.0, 0.0))
    common = np.isin(before.ids, after.ids)
    assert np.abs(np.median(after.pixels[:, 0] - before.pixels[common, 0]) - 4.0) < 0.3


def test_a_small_frame_is_tracked_enlarged_and_its_tracks_come_back_in_native_pixels():
    """160x120 frames are tracked at 320x240 (``min_work_width``): the shift of a frame moved by a known
    sub-pixel amount (OpenCV's warp) comes back in native pixels, and the forward-backward check keeps its
    half native pixel (a whole work pixel)."""
    from nocal_ros.odometry.frontend import FORWARD_BACKWARD_PX, forward_backward_px

    image = textured_image(160, 120, seed=3)
    tracker = FeatureTracker(TrackerSettings(max_tracks=100, grid=(4, 3)))
    tracker.track(image)
    assert tracker.gray.shape == (240, 320) and tracker.work_scale == (0.5, 0.5)
    assert tracker.top_up() > 50
    before = tracker.current()
    assert before.pixels.max(0)[0] <= 159.5 and before.pixels.max(0)[1] <= 119.5
    after = tracker.track(shifted(image, 1.25, -0.75))
    common = np.isin(before.ids, after.ids)
    assert common.mean() > 0.8
    np.testing.assert_allclose(np.median(after.pixels - before.pixels[common], axis=0), [1.25, -0.75], atol=0.05)
    assert forward_backward_px(tracker.work_scale) == 2 * FORWARD_BACKWARD_PX
    assert forward_backward_px((1.0, 1.0)) == forward_backward_px((1.175, 1.175)) == FORWARD_BACKWARD_PX
    native = FeatureTracker(TrackerSettings(min_work_width=0))
    native.track(image)
    assert native.gray.shape == (120, 160) and native.work_scale == (1.0, 1.0)


def test_blend_rotation_moves_along_the_geodesic_and_widens_the_rotation_by_the_disagreement():
    from nocal_ros.odometry.tracking import blend_rotation

    step = make_transform(so3_exp(np.array([0.01, 0.03, -0.02])), np.array([0.1, 0.0, 0.02]))
    offset = np.array([0.0, np.radians(2.0), np.radians(1.0)])  # the tracks' rotation, in the step's frame
    R_tracks = step[:3, :3] @ so3_exp(offset)
    covariance = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    blended, widened = blend_rotation(step, covariance, R_tracks, 0.33)
    np.testing.assert_allclose(so3_log(step[:3, :3].T @ blended[:3, :3]), 0.33 * offset, atol=1e-12)
    np.testing.assert_allclose(blended[:3, 3], step[:3, 3])
    np.testing.assert_allclose(widened - covariance, np.diag([0, 0, 0] + [offset @ offset] * 3), atol=1e-15)
    assert np.array_equal(covariance, np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6]))  # not modified in place
    same, unchanged = blend_rotation(step, covariance, step[:3, :3], 0.33)
    np.testing.assert_allclose(same, step, atol=1e-15)
    np.testing.assert_allclose(unchanged, covariance)
