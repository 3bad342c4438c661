"""Evaluation metrics checked against independent numpy / OpenCV computations and the paper's sanity figure."""

import json
import sys

import cv2
import numpy as np
import pytest
import torch

from nocal_ros import evaluation as ev
from nocal_ros import geometry as g
from nocal_ros.camera import CameraModel
from nocal_ros.lens import CameraCalibration, scale_intrinsics


def grid(width: int, height: int) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack((u.ravel(), v.ravel()), -1)


def test_paper_sanity_check_pinhole_600_modelled_as_640():
    truth = CameraCalibration.pinhole(640, 480, 600.0)
    # Independent: for pinholes with the same centre, the shift at pixel p is |p - c| (1/600 - 1/640).
    pixels = grid(640, 480)
    expected = np.mean(np.hypot(pixels[:, 0] - 319.5, pixels[:, 1] - 239.5)) * (1 / 600 - 1 / 640)
    for estimate in (CameraCalibration.pinhole(640, 480, 640.0), CameraModel(640, 480, fx=640.0)):
        dr = ev.mean_radial_shift(estimate, truth)
        assert dr == pytest.approx(expected, rel=1e-6)
    assert 0.018 < dr < 0.023  # the paper: "about 0.02" (its Table I: 0.0225)
    focal = ev.focal_error(CameraModel(640, 480), truth)  # default focal = image width
    assert focal["fx_px"] == pytest.approx(40.0) and focal["fx_percent"] == pytest.approx(100 * 40 / 600)


def test_radial_shift_of_an_ignored_distortion_matches_opencv():
    K = np.array([[300.0, 0, 161.0], [0, 310.0, 118.0], [0, 0, 1]])
    D = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    truth = CameraCalibration(320, 240, K, D)
    pinhole = CameraModel(320, 240, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    pixels = grid(320, 240)[:, None, :]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    true_xy = cv2.undistortPoints(pixels, K, D, criteria=criteria)[:, 0]
    pinhole_xy = cv2.undistortPoints(pixels, K, np.zeros(5))[:, 0]
    expected = np.linalg.norm(true_xy - pinhole_xy, axis=1).mean()
    assert ev.mean_radial_shift(pinhole, truth) == pytest.approx(expected, rel=1e-5)
    assert ev.mean_radial_shift(truth, truth) == 0.0


def test_camera_metrics_compare_at_the_truths_native_resolution():
    truth = CameraCalibration(640, 480, np.array([[520.0, 0, 330.0], [0, 515.0, 236.0], [0, 0, 1]]))
    small = scale_intrinsics(truth.K, 0.25, 0.25)
    camera = CameraModel(160, 120, fx=small[0, 0], fy=small[1, 1], cx=small[0, 2], cy=small[1, 2])
    errors = ev.calibration_errors(camera, truth)
    assert errors["focal_error_px"] < 1e-3 and errors["principal_point_error_px"] < 1e-3
    assert errors["dr"] < 1e-6
    shifted = CameraModel(640, 480, fx=530.0, fy=515.0, cx=333.0, cy=232.0)
    errors = ev.calibration_errors(shifted, truth)
    assert errors["fx_error_px"] == pytest.approx(10.0, abs=1e-3) and errors["fy_error_px"] == pytest.approx(0.0, abs=1e-3)
    assert errors["focal_error_percent"] == pytest.approx(50 * 10 / 520, rel=1e-4)
    assert errors["principal_point_error_px"] == pytest.approx(5.0, abs=1e-3)
    json.dumps(errors)


def random_trajectory(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        step = g.make_transform(g.so3_exp(rng.normal(scale=0.05, size=3)), rng.normal(scale=0.1, size=3) + [0, 0, 0.1])
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def perturb(poses: np.ndarray, seed: int, rotation: float = 0.01, translation: float = 0.01) -> np.ndarray:
    rng = np.random.default_rng(seed)
    relative = [g.relative_transform(poses[i], poses[i + 1]) for i in range(len(poses) - 1)]
    noisy = [r @ g.make_transform(g.so3_exp(rng.normal(scale=rotation, size=3)), rng.normal(scale=translation, size=3)) for r in relative]
    return ev.integrate_relative_poses(np.stack(noisy), start=poses[0])


def numpy_rpe(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    translation, rotation = [], []
    for i in range(len(truth) - 1):
        E = np.linalg.inv(np.linalg.inv(truth[i]) @ truth[i + 1]) @ (np.linalg.inv(estimate[i]) @ estimate[i + 1])
        translation.append(np.linalg.norm(E[:3, 3]))
        rotation.append(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))))
    return np.array(translation), np.array(rotation)


def test_relative_pose_error_matches_numpy_and_leaves_inputs_alone():
    truth = random_trajectory(30, seed=0)
    estimate = perturb(truth, seed=1)
    truth_copy, estimate_copy = truth.copy(), estimate.copy()
    rpe = ev.relative_pose_error(estimate, truth)
    translation, rotation = numpy_rpe(estimate, truth)
    np.testing.assert_allclose(rpe["translation_m_per_pair"], translation, atol=1e-9)
    np.testing.assert_allclose(rpe["rotation_deg_per_pair"], rotation, atol=1e-6)
    assert rpe["translation_m"]["rmse"] == pytest.approx(np.sqrt(np.mean(translation**2)), rel=1e-9)
    assert rpe["translation_m"]["std"] == pytest.approx(translation.std(), rel=1e-9)
    assert rpe["rotation_deg"]["mean"] == pytest.approx(rotation.mean(), rel=1e-6)
    assert rpe["translation_m"]["count"] == 29
    np.testing.assert_array_equal(truth, truth_copy)
    np.testing.assert_array_equal(estimate, estimate_copy)
    # The same errors from predicted relative poses (what the pose head outputs).
    predicted = np.stack([g.relative_transform(estimate[i], estimate[i + 1]) for i in range(29)])
    pairs = ev.relative_pose_error_of_pairs(predicted, truth)
    np.testing.assert_allclose(pairs["translation_m_per_pair"], translation, atol=1e-9)


def test_relative_pose_error_with_scale_correction_forgives_a_monocular_scale():
    truth = random_trajectory(20, seed=2)
    half_scale = truth.copy()
    half_scale[:, :3, 3] *= 0.5
    assert ev.relative_pose_error(half_scale, truth)["translation_m"]["mean"] > 0.01
    corrected = ev.relative_pose_error(half_scale, truth, correct_scale=True)
    assert corrected["translation_m"]["max"] < 1e-9 and corrected["scale"] == pytest.approx(2.0)


def numpy_umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Umeyama (1991), eqs. 34-42: target ~ s R source + t."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = np.trace(np.diag(d) @ S) / ((source - mu_s) ** 2).sum(1).mean() if with_scale else 1.0
    return R, mu_t - s * R @ mu_s, s


def test_absolute_pose_error_matches_an_independent_umeyama():
    truth = random_trajectory(40, seed=3)
    estimate = perturb(truth, seed=4, rotation=0.02, translation=0.02)
    # Put the estimate in another frame at another scale, as a monocular odometry would.
    T = g.make_transform(g.so3_exp([0.3, -0.2, 1.0]), [1.0, 2.0, -0.5])
    moved = np.einsum("ij,njk->nik", T, estimate)
    moved[:, :3, 3] *= 0.7
    for with_scale in (False, True):
        ape = ev.absolute_pose_error(moved, truth, correct_scale=with_scale)
        R, t, s = numpy_umeyama(moved[:, :3, 3], truth[:, :3, 3], with_scale)
        aligned = (s * moved[:, :3, 3] @ R.T) + t
        errors = np.linalg.norm(aligned - truth[:, :3, 3], axis=1)
        np.testing.assert_allclose(ape["translation_m_per_pose"], errors, atol=1e-9)
        assert ape["scale"] == pytest.approx(s, rel=1e-9)
    exact = np.einsum("ij,njk->nik", T, truth)
    exact[:, :3, 3] *= 0.7
    assert ev.absolute_pose_error(exact, truth, correct_scale=True)["translation_m"]["max"] < 1e-9
    assert ev.absolute_pose_error(exact, truth, correct_scale=False)["translation_m"]["max"] > 0.01


def test_report_is_json_table_and_plot(tmp_path):
    truth_poses = random_trajectory(15, seed=5)
    estimate = perturb(truth_poses, seed=6)
    stamps = np.arange(15, dtype=np.int64) * 100_000_000
    truth = CameraCalibration(160, 120, np.array([[150.0, 0, 80.0], [0, 150.0, 60.0], [0, 0, 1]]), [-0.1, 0.01, 0, 0, 0])
    report = {"model": "test", **ev.trajectory_errors(stamps, estimate, truth_poses)}
    report["calibration"] = ev.calibration_errors(CameraModel(160, 120), truth)
    assert report["duration_s"] == pytest.approx(1.4)
    assert report["ape_sim3"]["rmse"] == report["ape_sim3"]["translation_m"]["rmse"]
    assert report["ape_se3"]["rmse"] >= report["ape_sim3"]["rmse"] - 1e-12  # a similarity fits at least as well
    assert json.loads(json.dumps(report))["rpe"]["translation_m"]["count"] == 14
    table = ev.format_report(report)
    assert "RPE m" in table and f"{report['rpe']['translation_m']['rmse']:.4f}" in table
    assert f"{report['calibration']['fx_error_px']:.2f}" in table and "model: test" in table
    assert "per_pair" not in json.dumps(ev.summary(report))
    path = ev.plot_trajectory(tmp_path / "plots" / "trajectory.png", stamps, estimate, truth_poses, title="test")
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 100 and image.std() > 0


def test_bad_poses_and_missing_evo_are_reported(monkeypatch):
    truth = random_trajectory(5, seed=7)
    broken = truth.copy()
    broken[2, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        ev.relative_pose_error(broken, truth)
    with pytest.raises(ValueError, match="length"):
        ev.relative_pose_error(truth[:4], truth)
    monkeypatch.setitem(sys.modules, "evo.core", None)
    with pytest.raises(ev.MissingDependencyError, match="pip install evo"):
        ev.relative_pose_error(truth, truth)
