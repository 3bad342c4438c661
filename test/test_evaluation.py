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


def test_rpe_of_float32_pose_head_outputs_over_a_long_sequence():
    # The pose head's rotations are float32 (orthonormal to ~1e-7); chained over 400 pairs their drift
    # used to exceed evo's 1e-6 SO(3) tolerance and RPE raised instead of reporting.
    truth = random_trajectory(401, seed=3)
    relative = np.stack([g.relative_transform(truth[i], truth[i + 1]) for i in range(400)])
    predicted = relative.copy()
    # As the pose head makes them: an unnormalised float32 6D vector through Gram-Schmidt.
    rot6d = g.matrix_to_rotation_6d(torch.from_numpy(relative[:, :3, :3]).float()) * 1.7
    predicted[:, :3, :3] = g.rotation_6d_to_matrix(rot6d).double().numpy()
    rotations = predicted[:, :3, :3]
    assert np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max() > 1e-8
    rpe = ev.relative_pose_error_of_pairs(predicted, truth)
    assert rpe["translation_m"]["max"] < 1e-5 and rpe["rotation_deg"]["max"] < 1e-3
    chained = ev.integrate_relative_poses(predicted, start=truth[0])[:, :3, :3]
    assert np.abs(np.einsum("nji,njk->nik", chained, chained) - np.eye(3)).max() < 1e-12


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
    # Unaligned: the poses as they are, each one's distance to its true position (and rotation angle).
    unaligned = ev.absolute_pose_error(moved, truth, align=False)
    np.testing.assert_allclose(unaligned["translation_m_per_pose"], np.linalg.norm(moved[:, :3, 3] - truth[:, :3, 3], axis=1),
                               atol=1e-9)
    angles = [np.degrees(np.linalg.norm(g.so3_log(a[:3, :3].T @ b[:3, :3]))) for a, b in zip(truth, moved)]
    np.testing.assert_allclose(unaligned["rotation_deg_per_pose"], angles, atol=1e-6)
    assert unaligned["aligned"] is False and "scale" not in unaligned


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
    # Another estimate of the same frames (nocal odometry's map frame) is drawn beside it.
    other = perturb(truth_poses, seed=9, rotation=0.05, translation=0.05)
    with_other = cv2.imread(str(ev.plot_trajectory(tmp_path / "other.png", stamps, estimate, truth_poses, title="test",
                                                   others={"map frame": other})))
    assert with_other.shape == image.shape and np.abs(with_other.astype(int) - image).sum() > 0
    other[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        ev.plot_trajectory(tmp_path / "bad.png", stamps, estimate, truth_poses, others={"map frame": other})


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


# --------------------------------------------------------------------------------------------------
# ``nocal eval`` end to end on a real bag (written and read by rosbags) and a saved checkpoint
# --------------------------------------------------------------------------------------------------

from nocal_ros.checkpoint import save_checkpoint  # noqa: E402
from nocal_ros.cli import main  # noqa: E402
from nocal_ros.data.bags import write_sequence  # noqa: E402
from nocal_ros.data.synthetic import render_sequence  # noqa: E402
from nocal_ros.model import NOCaL  # noqa: E402

EVAL_WIDTH, EVAL_HEIGHT = 160, 120
TRAIN_SIZE = (40, 30)
EVAL_CAMERA = CameraCalibration(
    EVAL_WIDTH, EVAL_HEIGHT, np.array([[140.0, 0, 81.0], [0, 138.0, 58.5], [0, 0, 1]]), np.array([-0.15, 0.03, 0.001, 0.0, 0.0])
)
SMALL_MODEL = {"encoder_channels": [8] * 7, "latent_dim": 16, "scene_width": 16, "pose_width": 16,
               "hyper_width": 16, "hyper_depth": 1, "hyper_rank": 4, "lfn_width": 16, "lfn_layers": 2}


@pytest.fixture(scope="module")
def bag_and_model(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    n = 8
    sequence = render_sequence(EVAL_CAMERA, n, seed=0, split="test")
    sequence.ground_truth[3] = np.nan  # a frame without ground truth: pairs bridge it
    bag = write_sequence(sequence, root / "bag")
    torch.manual_seed(0)
    model = NOCaL(SMALL_MODEL)
    camera = CameraModel(EVAL_WIDTH, EVAL_HEIGHT)  # freshly initialised: f = width, centred, no distortion
    path = save_checkpoint(root / "model.safetensors", model, [camera], metadata={"training_resolution": list(TRAIN_SIZE)})
    return bag, path, sequence, model


def test_eval_reports_camera_and_pose_errors_against_the_bags_ground_truth(bag_and_model, tmp_path, capsys):
    bag, model_path, sequence, model = bag_and_model
    report_path = tmp_path / "out" / "report.json"
    plot_path = tmp_path / "out" / "trajectory.png"
    assert main(["eval", "--model", str(model_path), "--bag", str(bag), "--json", str(report_path), "--plot", str(plot_path)]) == 0
    printed = capsys.readouterr().out
    report = json.loads(report_path.read_text())
    assert "RPE m" in printed and "focal error" in printed

    # Camera: an untrained camera has f = width = 160 against the true 140 / 138.
    calibration = report["calibration"]
    assert calibration["fx_error_px"] == pytest.approx(20.0, abs=1e-3)
    assert calibration["fy_error_px"] == pytest.approx(22.0, abs=1e-3)
    assert calibration["principal_point_error_px"] == pytest.approx(np.hypot(81.0 - 79.5, 58.5 - 59.5), abs=1e-3)
    assert calibration["fit_residual_px"] < 1e-6  # a pinhole fits a pinhole exactly
    assert calibration["dr"] > 0.01

    # Odometry: frame 3 has no ground truth, so the pairs are (0,1), (1,2), (2,4), (4,5), (5,6), (6,7).
    frames = [0, 1, 2, 4, 5, 6, 7]
    assert report["pairs"] == 6 and report["max_pair_gap"] == 2 and report["input_size"] == "40x30"
    # Independent: run the pose head on INTER_AREA-resized frames and compare poses by hand.
    small = np.stack([cv2.resize(im, TRAIN_SIZE, interpolation=cv2.INTER_AREA) for im in sequence.images])
    tensor = torch.from_numpy(small).permute(0, 3, 1, 2).float() / 255.0
    with torch.no_grad():
        predicted = model.predict_pose(tensor[frames[:-1]], tensor[frames[1:]]).double().numpy()
    expected_t, expected_r = [], []
    for k, (i, j) in enumerate(zip(frames[:-1], frames[1:])):
        E = g.invert_transform(g.relative_transform(sequence.ground_truth[i], sequence.ground_truth[j])) @ predicted[k]
        expected_t.append(np.linalg.norm(E[:3, 3]))
        expected_r.append(g.rotation_angle_deg(E[:3, :3]))
    np.testing.assert_allclose(report["rpe"]["translation_m_per_pair"], expected_t, atol=1e-5)
    np.testing.assert_allclose(report["rpe"]["rotation_deg_per_pair"], expected_r, atol=1e-3)
    assert report["ape_sim3"]["count"] == 7 and report["duration_s"] == pytest.approx(0.7)  # 10 fps
    image = cv2.imread(str(plot_path))
    assert image is not None and image.std() > 0


def test_eval_refuses_bad_inputs_in_one_line(bag_and_model, tmp_path, capsys):
    bag, model_path, _, _ = bag_and_model
    assert main(["eval", "--model", str(tmp_path / "missing.safetensors"), "--bag", str(bag)]) == 1
    assert "missing.safetensors" in capsys.readouterr().err
    assert main(["eval", "--model", str(model_path), "--bag", str(bag), "--camera-index", "3"]) == 1
    assert "no camera 3" in capsys.readouterr().err
    assert main(["eval", "--model", str(model_path), "--bag", str(bag), "--gt-topic", "/none",
                 "--camera-info-topic", "/none"]) == 1
    error = capsys.readouterr().err
    assert "nothing to evaluate" in error and str(bag) in error
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(b"\x89MCAP0\r\n garbage")
    assert main(["eval", "--model", str(model_path), "--bag", str(corrupt)]) == 1
    assert "corrupt.mcap" in capsys.readouterr().err


def steps_with_drawn_errors(n: int, trajectory_seed: int, noise_seed: int):
    """A random trajectory's ``n - 1`` true steps, a random covariance ``(3, 3)`` per step, and an error drawn
    from each: ``(truth, steps, covariances, errors)``."""
    truth = random_trajectory(n, seed=trajectory_seed)
    rng = np.random.default_rng(noise_seed)
    factors = rng.normal(scale=0.01, size=(n - 1, 3, 3))
    covariances = factors @ factors.transpose(0, 2, 1) + 1e-6 * np.eye(3)
    errors = np.stack([rng.multivariate_normal(np.zeros(3), C) for C in covariances])
    steps = [g.relative_transform(truth[i], truth[i + 1]) for i in range(n - 1)]
    return truth, steps, covariances, errors


def test_rotation_nees_of_errors_drawn_from_the_reported_covariance_is_three():
    """Steps whose rotation errors are drawn from their covariances give a mean NEES of 3 (chi-square,
    3 degrees of freedom) and 99 % of them under the 99 % bound; covariances half as large double it.
    The errors are recovered with scipy's rotation vectors, independently of the module's so3_log."""
    from scipy.spatial.transform import Rotation

    n = 3001
    truth, steps, covariances, errors = steps_with_drawn_errors(n, 11, 12)
    noisy = [step @ g.make_transform(Rotation.from_rotvec(e).as_matrix(), np.zeros(3)) for step, e in zip(steps, errors)]
    estimate = ev.integrate_relative_poses(np.stack(noisy), start=truth[0])

    result = ev.rotation_consistency(estimate, truth, covariances)
    assert result["pairs"] == n - 1
    assert result["mean_nees"] == pytest.approx(3.0, abs=0.2)  # the mean's standard error is sqrt(6 / n) = 0.045
    assert result["within_99"] == pytest.approx(0.99, abs=0.006)
    recovered = [Rotation.from_matrix((steps[i][:3, :3]).T @ noisy[i][:3, :3]).as_rotvec() for i in range(n - 1)]
    expected = np.mean([e @ np.linalg.solve(C, e) for e, C in zip(recovered, covariances)])
    assert result["mean_nees"] == pytest.approx(expected, rel=1e-6)

    assert ev.rotation_consistency(estimate, truth, covariances / 2)["mean_nees"] == pytest.approx(2 * expected, rel=1e-6)
    unknown = covariances.copy()
    unknown[::2] = np.nan  # steps with no covariance (no pair run) are skipped
    assert ev.rotation_consistency(estimate, truth, unknown)["pairs"] == (n - 1) // 2
    with pytest.raises(ValueError, match="step covariances"):
        ev.rotation_consistency(estimate, truth, covariances[1:])


def test_translation_nees_of_errors_drawn_from_the_reported_covariance_is_three():
    """Steps whose translations are moved by errors drawn from their covariances (in the later camera's
    frame) give a mean NEES of 3 and 99 % under the bound; a step 10 % too long with a covariance that
    leaves out the scale is far outside it, and one whose covariance holds the scale's 10 % is not. The
    rotations are exact, so the rotation errors play no part."""
    n = 3001
    truth, steps, covariances, errors = steps_with_drawn_errors(n, 13, 14)
    noisy = [step @ g.make_transform(np.eye(3), e) for step, e in zip(steps, errors)]
    estimate = ev.integrate_relative_poses(np.stack(noisy), start=truth[0])

    result = ev.translation_consistency(estimate, truth, covariances)
    assert result["pairs"] == n - 1
    assert result["mean_nees"] == pytest.approx(3.0, abs=0.2)
    assert result["within_99"] == pytest.approx(0.99, abs=0.006)
    expected = np.mean([e @ np.linalg.solve(C, e) for e, C in zip(errors, covariances)])
    assert result["mean_nees"] == pytest.approx(expected, rel=1e-6)

    longer = [g.make_transform(step[:3, :3], 1.1 * step[:3, 3]) for step in steps]
    scaled = ev.integrate_relative_poses(np.stack(longer), start=truth[0])
    lengths = np.array([np.linalg.norm(step[:3, 3]) for step in steps])
    tight = np.stack([np.eye(3) * (0.001 * length) ** 2 for length in lengths])
    assert ev.translation_consistency(scaled, truth, tight)["within_99"] == 0.0
    along = [step[:3, :3].T @ step[:3, 3] for step in steps]  # the step's direction in the later frame
    with_scale = tight + np.stack([0.1**2 * np.outer(a, a) for a in along])
    assert ev.translation_consistency(scaled, truth, with_scale)["mean_nees"] == pytest.approx(1.0, rel=0.02)
