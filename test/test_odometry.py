"""OdometryEstimator: integration against closed forms, and every frame-stream failure path.

The integration tests inject a pose source that returns the true relative pose of a pair: frame k is
an image filled with the value k, so the pose function reads the frame numbers back from the pixels
(after the estimator's real resize and normalisation) and answers ``inv(T_w_ci) @ T_w_cj`` from the
trajectory. What is tested is the estimator's own work: slot handling, composition with the mounting
transform, twist, covariance, drops and resets.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nocal_ros.errors import NocalError
from nocal_ros.geometry import invert_transform, make_transform, so3_exp, so3_log
from nocal_ros.odometry import (
    FrameError,
    FrameSizeError,
    OdometryEstimator,
    PoseModel,
    UNKNOWN_VARIANCE,
    propagate_covariance,
)

PERIOD_NS = 100_000_000  # 10 Hz
START_NS = 1_700_000_000_000_000_000


def random_trajectory(n: int, seed: int = 0, rotation_step: float = 0.03) -> np.ndarray:
    """``(n, 4, 4)`` camera poses ``T_w_c`` with a few cm and (by default) degrees between frames."""
    rng = np.random.default_rng(seed)
    poses = [make_transform(so3_exp(rng.normal(size=3)), rng.normal(size=3))]
    for _ in range(n - 1):
        step = make_transform(so3_exp(rng.normal(scale=rotation_step, size=3)), rng.normal(scale=0.05, size=3))
        poses.append(poses[-1] @ step)
    return np.stack(poses)


class TrajectoryPoses:
    """Pose source answering the true ``T_ci_cj`` for frames whose pixels hold their index."""

    def __init__(self, T_w_c: np.ndarray, nan_frames: set[int] = frozenset()) -> None:
        self.T_w_c = T_w_c
        self.nan_frames = set(nan_frames)
        self.calls: list[tuple[int, int]] = []

    def __call__(self, image_i: torch.Tensor, image_j: torch.Tensor) -> torch.Tensor:
        i = int(round(float(image_i.mean()) * 255))
        j = int(round(float(image_j.mean()) * 255))
        self.calls.append((i, j))
        if j in self.nan_frames:
            return torch.full((1, 4, 4), float("nan"))
        T = invert_transform(self.T_w_c[i]) @ self.T_w_c[j]
        return torch.from_numpy(T)[None].float()


def frame(k: int, size=(64, 48)) -> np.ndarray:
    return np.full((size[1], size[0], 3), k, dtype=np.uint8)


def make_estimator(T_w_c, nan_frames=(), T_base_cam=None, **kwargs) -> tuple[OdometryEstimator, TrajectoryPoses]:
    poses = TrajectoryPoses(T_w_c, set(nan_frames))
    model = PoseModel(predict_pose=poses, input_size=(32, 24), max_gap=8, model_id="trajectory")
    return OdometryEstimator(model, T_base_cam=T_base_cam, method="pose_head", **kwargs), poses


def expected_T_odom_base(T_w_c, k0, k, T_base_cam):
    return T_base_cam @ invert_transform(T_w_c[k0]) @ T_w_c[k] @ invert_transform(T_base_cam)


MOUNT = make_transform(so3_exp(np.array([0.3, -1.2, 0.5])), np.array([0.1, 0.02, 0.3]))


def test_composes_known_relative_poses_exactly():
    T_w_c = random_trajectory(30)
    estimator, poses = make_estimator(T_w_c, T_base_cam=MOUNT)
    results = [estimator.process(START_NS + k * PERIOD_NS, frame(k)) for k in range(30)]
    assert results[0].status == "start" and np.allclose(results[0].T_odom_base, np.eye(4))
    assert poses.calls == [(k - 1, k) for k in range(1, 30)]
    for k, result in enumerate(results):
        assert result.stamp_ns == START_NS + k * PERIOD_NS
        np.testing.assert_allclose(result.T_odom_base, expected_T_odom_base(T_w_c, 0, k, MOUNT), atol=2e-5)
        # The camera's pose in odom follows from the base pose and the mounting.
        np.testing.assert_allclose(result.T_odom_cam, result.T_odom_base @ MOUNT, atol=1e-12)
    assert all(r.status == "ok" and r.gap == 1 for r in results[1:])
    assert estimator.counters.pairs == 29


def test_a_long_chain_of_float32_rotations_stays_a_rotation():
    # The pose head's rotations are float32; 300 of them chained as they came left SO(3) by more than
    # evo's 1e-6 and `nocal odometry --no-two-view` raised on a 200-frame bag.
    T_w_c = random_trajectory(300, seed=5)
    estimator, _ = make_estimator(T_w_c)
    for k in range(300):
        result = estimator.process(START_NS + k * PERIOD_NS, frame(k % 256))
    R = result.T_odom_base[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12


def test_twist_is_the_pair_motion_over_the_stamp_step_in_the_base_frame():
    T_w_c = random_trajectory(3, seed=1)
    estimator, _ = make_estimator(T_w_c, T_base_cam=MOUNT)
    estimator.process(START_NS, frame(0))
    result = estimator.process(START_NS + PERIOD_NS, frame(1))
    T_b0_b1 = MOUNT @ invert_transform(T_w_c[0]) @ T_w_c[1] @ invert_transform(MOUNT)
    dt = PERIOD_NS * 1e-9
    # Closed form: a constant body twist over dt reproduces the pair, so integrating it for dt must
    # land on T_b0_b1 (checked through the rotation and the displacement seen from frame 1).
    np.testing.assert_allclose(so3_exp(result.twist[3:] * dt), T_b0_b1[:3, :3], atol=1e-5)
    np.testing.assert_allclose(T_b0_b1[:3, :3] @ result.twist[:3] * dt, T_b0_b1[:3, 3], atol=1e-5)
    assert np.allclose(estimator.process(START_NS, frame(0)).twist, 0)  # time reset: no motion known


def test_gap_within_training_range_is_one_pair_and_longer_gap_resets_keeping_pose(caplog):
    T_w_c = random_trajectory(40, seed=2)
    estimator, poses = make_estimator(T_w_c)
    stamp = lambda k: START_NS + k * PERIOD_NS  # noqa: E731
    for k in range(5):
        estimator.process(stamp(k), frame(k))
    bridged = estimator.process(stamp(8), frame(8))  # frames 5..7 dropped: a gap of 4 frames
    assert bridged.status == "ok" and bridged.gap == 4 and poses.calls[-1] == (4, 8)
    np.testing.assert_allclose(bridged.T_odom_base, expected_T_odom_base(T_w_c, 0, 8, np.eye(4)), atol=2e-5)
    assert estimator.counters.bridged_gaps == 1
    # Its covariance grows by four frames' worth, not one.
    one = estimator.process(stamp(9), frame(9)).twist_covariance * 1e-2
    assert np.allclose(bridged.twist_covariance * (0.4**2), one * 4, rtol=1e-9)

    held = estimator.process(stamp(9 + 12), frame(21))  # 12 frames missing: more than max_gap 8
    assert held.status == "gap_reset" and held.gap == 0
    assert "new pair chain" in caplog.text
    np.testing.assert_allclose(held.T_odom_base, expected_T_odom_base(T_w_c, 0, 9, np.eye(4)), atol=2e-5)
    assert np.all(np.diag(held.twist_covariance) == UNKNOWN_VARIANCE)
    after = estimator.process(stamp(22), frame(22))
    assert poses.calls[-1] == (21, 22)
    # The chain restarts at frame 21 from the pose held at frame 9.
    expected = expected_T_odom_base(T_w_c, 0, 9, np.eye(4)) @ expected_T_odom_base(T_w_c, 21, 22, np.eye(4))
    np.testing.assert_allclose(after.T_odom_base, expected, atol=2e-5)
    assert estimator.counters.gap_resets == 1


def test_fixed_frame_period_decides_the_gap():
    T_w_c = random_trajectory(20, seed=3)
    estimator, _ = make_estimator(T_w_c, frame_period_s=0.05)  # the camera runs at 20 Hz
    estimator.process(START_NS, frame(0))
    assert estimator.process(START_NS + PERIOD_NS, frame(1)).gap == 2
    assert estimator.process(START_NS + 6 * PERIOD_NS, frame(2)).status == "gap_reset"  # 10 frames


def test_time_going_backwards_resets_to_identity():
    T_w_c = random_trajectory(10, seed=4)
    estimator, _ = make_estimator(T_w_c)
    for k in range(5):
        estimator.process(START_NS + k * PERIOD_NS, frame(k))
    restart = estimator.process(START_NS, frame(5))
    assert restart.status == "time_reset"
    np.testing.assert_allclose(restart.T_odom_base, np.eye(4))
    np.testing.assert_allclose(restart.pose_covariance, 0)
    nxt = estimator.process(START_NS + PERIOD_NS, frame(6))
    np.testing.assert_allclose(nxt.T_odom_base, expected_T_odom_base(T_w_c, 5, 6, np.eye(4)), atol=2e-5)
    assert estimator.counters.time_resets == 1
    assert estimator.process(START_NS + PERIOD_NS, frame(7)) is None  # a repeated stamp is skipped
    assert estimator.counters.duplicate_stamps == 1


def test_size_change_is_a_clear_error_that_loses_nothing():
    T_w_c = random_trajectory(6, seed=5)
    estimator, _ = make_estimator(T_w_c)
    for k in range(3):
        estimator.process(START_NS + k * PERIOD_NS, frame(k))
    with pytest.raises(FrameSizeError, match=r"64x48 to 80x60"):
        estimator.process(START_NS + 3 * PERIOD_NS, frame(3, size=(80, 60)))
    assert isinstance(FrameSizeError("x"), NocalError)
    result = estimator.process(START_NS + 4 * PERIOD_NS, frame(4))
    assert result.status == "ok" and result.gap == 2
    np.testing.assert_allclose(result.T_odom_base, expected_T_odom_base(T_w_c, 0, 4, np.eye(4)), atol=2e-5)
    estimator.reset()  # accepts another size
    assert estimator.process(START_NS + 5 * PERIOD_NS, frame(5, size=(80, 60))).status == "start"
    assert estimator.counters.size_rejected == 1


@pytest.mark.parametrize("bad", [np.zeros((48, 64, 3), np.float32), np.zeros((48, 64, 4), np.uint8), [[1, 2]]])
def test_malformed_frames_are_rejected(bad):
    estimator, _ = make_estimator(random_trajectory(2))
    with pytest.raises(FrameError):
        estimator.process(START_NS, bad)


def test_mono_frames_are_accepted_and_an_encoding_change_restarts_the_chain():
    T_w_c = random_trajectory(5, seed=6)
    estimator, poses = make_estimator(T_w_c)
    estimator.process(START_NS, frame(0)[:, :, 0], encoding="mono8")
    assert estimator.process(START_NS + PERIOD_NS, frame(1)[:, :, 0], encoding="mono8").status == "ok"
    changed = estimator.process(START_NS + 2 * PERIOD_NS, frame(2), encoding="rgb8")
    assert changed.status == "encoding_reset" and poses.calls == [(0, 1)]
    np.testing.assert_allclose(changed.T_odom_base, expected_T_odom_base(T_w_c, 0, 1, np.eye(4)), atol=2e-5)


def test_non_finite_output_skips_the_frame_and_pairs_the_next_with_the_last_good_one(caplog):
    T_w_c = random_trajectory(8, seed=7)
    estimator, poses = make_estimator(T_w_c, nan_frames={3})
    results = [estimator.process(START_NS + k * PERIOD_NS, frame(k)) for k in range(6)]
    assert results[3] is None and "non-finite" in caplog.text
    assert estimator.counters.nonfinite_skipped == 1
    assert poses.calls[2:4] == [(2, 3), (2, 4)]
    assert results[4].gap == 2
    for k in (4, 5):
        np.testing.assert_allclose(results[k].T_odom_base, expected_T_odom_base(T_w_c, 0, k, np.eye(4)), atol=2e-5)
        assert np.isfinite(results[k].pose_covariance).all()


def test_pose_covariance_matches_monte_carlo_propagation():
    """First-order propagation against sampling the modelled pair noise through the composition."""
    T_w_c = random_trajectory(4, seed=8, rotation_step=0.5)  # large turns: the Jacobians must be right
    std = {"translation_m": 0.02, "rotation_rad": 0.01}
    poses = TrajectoryPoses(T_w_c)
    model = PoseModel(predict_pose=poses, input_size=(32, 24), pose_error_std=std)
    estimator = OdometryEstimator(model, T_base_cam=MOUNT, method="pose_head")
    results = [estimator.process(START_NS + k * PERIOD_NS, frame(k)) for k in range(4)]
    covariance = results[-1].pose_covariance
    assert np.allclose(covariance, covariance.T) and np.linalg.eigvalsh(covariance).min() > 0

    rng = np.random.default_rng(0)
    samples = 100_000
    pairs = [MOUNT @ invert_transform(T_w_c[k]) @ T_w_c[k + 1] @ invert_transform(MOUNT) for k in range(3)]
    ad = np.zeros((6, 6))
    ad[:3, :3] = ad[3:, 3:] = MOUNT[:3, :3]
    t = MOUNT[:3, 3]
    ad[:3, 3:] = skew(t) @ MOUNT[:3, :3]
    T = np.broadcast_to(np.eye(4), (samples, 4, 4))
    for pair in pairs:
        sigmas = [std["translation_m"]] * 3 + [std["rotation_rad"]] * 3
        xi = rng.normal(scale=sigmas, size=(samples, 6)) @ ad.T  # camera-frame noise seen in the base frame
        noise = np.zeros((samples, 4, 4))
        noise[:, :3, :3] = so3_exp(xi[:, 3:])
        noise[:, :3, 3] = xi[:, :3]
        noise[:, 3, 3] = 1.0
        T = T @ pair @ noise
    mean = results[-1].T_odom_base
    errors = np.concatenate(
        (T[:, :3, 3] - mean[:3, 3], [so3_log(R @ mean[:3, :3].T) for R in T[:, :3, :3]]), axis=1
    )
    empirical = np.cov(errors.T)
    # Every entry, relative to its scale sqrt(var_i var_j): the sampling error is about 1/sqrt(samples).
    scale = np.sqrt(np.outer(np.diag(covariance), np.diag(covariance)))
    assert (np.abs(empirical - covariance) / scale).max() < 0.02


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def test_propagation_of_a_zero_pair_keeps_the_covariance():
    sigma = np.diag([1.0, 2, 3, 0.1, 0.2, 0.3])
    out = propagate_covariance(sigma, np.eye(4), np.eye(4), np.zeros((6, 6)))
    np.testing.assert_allclose(out, sigma)


def test_focal_step_covariance_covers_a_turn_measured_through_a_wrong_focal_length():
    """The premise of :func:`focal_step_covariance`: a rotation read from rays through a focal length 30 %
    long comes out short by about ``e / (1 + e)`` of its angle for a pan or a tilt (closed form,
    ``atan(tan(theta) / (1 + e))`` at the image centre), and not at all for a roll; with that share as the
    focal length's relative standard deviation the error is within one standard deviation per axis."""
    import cv2

    from nocal_ros.odometry.covariance import focal_step_covariance
    from nocal_ros.odometry.initializer import rotation_from_rays, unit_rays

    rng = np.random.default_rng(3)
    K = np.array([[300.0, 0, 320], [0, 300.0, 240], [0, 0, 1]])
    e = 0.3
    points = np.c_[rng.uniform(-1.0, 1.0, (400, 2)), rng.uniform(2.0, 5.0, 400)]
    theta = np.radians(3.0)
    for axis, expected_share in (([0, 1, 0], e / (1 + e)), ([1, 0, 0], e / (1 + e)), ([0, 0, 1], 0.0)):
        R = so3_exp(theta * np.array(axis, float))  # X_cur = R^T X_ref: the camera turns by R
        pixels = [cv2.projectPoints(points @ rotation.T, np.zeros(3), np.zeros(3), K, None)[0].reshape(-1, 2)
                  for rotation in (np.eye(3), R.T)]
        rays = [unit_rays((p - K[:2, 2]) / (K[0, 0] * (1 + e))) for p in pixels]  # through the long focal length
        R_cur_ref = rotation_from_rays(rays[0], rays[1])
        error = so3_log(R @ R_cur_ref)  # the measured turn R_ref_cur = R_cur_ref^T against the true R
        assert np.linalg.norm(error) == pytest.approx(expected_share * theta, abs=0.08 * expected_share * theta + 1e-4)
        step = make_transform(R, np.zeros(3))
        sigma = focal_step_covariance(step, e / (1 + e))[3:, 3:]
        assert (np.abs(error) <= np.sqrt(np.diag(sigma)) * 1.01).all()


def test_reload_keeps_the_pose_and_restarts_the_chain():
    T_w_c = random_trajectory(6, seed=9)
    estimator, _ = make_estimator(T_w_c)
    for k in range(3):
        estimator.process(START_NS + k * PERIOD_NS, frame(k))
    poses = TrajectoryPoses(T_w_c)
    assert estimator.reload(PoseModel(predict_pose=poses, input_size=(16, 12), model_id="other")) == "other"
    restart = estimator.process(START_NS + 3 * PERIOD_NS, frame(3))
    assert restart.status == "start"
    np.testing.assert_allclose(restart.T_odom_base, expected_T_odom_base(T_w_c, 0, 2, np.eye(4)), atol=2e-5)
    estimator.process(START_NS + 4 * PERIOD_NS, frame(4))
    assert poses.calls == [(3, 4)] and estimator.model_id == "other"


def test_real_pose_head_sees_the_resized_frames_in_order():
    """With the real network: the estimator's pair motion is the network's answer on (previous, current)
    resized by OpenCV, computed here independently, in the contiguous layout the estimator does not use."""
    import cv2

    from nocal_ros.model import NOCaL

    torch.manual_seed(0)
    network = NOCaL({"pose_scale": 300.0}).eval()  # a large output scale: poses far from the identity
    reference = NOCaL({"pose_scale": 300.0}).eval()
    reference.load_state_dict(network.state_dict())
    estimator = OdometryEstimator(PoseModel(predict_pose=network.predict_pose, input_size=(40, 30), module=network),
                                  method="pose_head")
    rng = np.random.default_rng(0)
    images = [cv2.resize(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), (160, 120)) for _ in range(3)]
    results = [estimator.process(START_NS + k * PERIOD_NS, image) for k, image in enumerate(images)]

    def tensor(image):
        small = cv2.resize(image, (40, 30), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(small).permute(2, 0, 1)[None].float() / 255.0

    with torch.no_grad():
        expected = [reference.predict_pose(tensor(images[k]), tensor(images[k + 1]))[0].double().numpy() for k in range(2)]
    assert not np.allclose(expected[0], np.eye(4), atol=1e-2) and not np.allclose(expected[0], expected[1], atol=1e-3)
    for k in range(2):
        np.testing.assert_allclose(results[k + 1].T_prev_curr, expected[k], atol=1e-5)
    np.testing.assert_allclose(results[2].T_odom_base, expected[0] @ expected[1], atol=1e-5)


def test_mailbox_keeps_only_the_newest_frame_and_counts_the_rest():
    import threading

    from nocal_ros.odometry import FrameMailbox

    latest = FrameMailbox(latest_only=True)
    for k in range(5):
        latest.put(k)
    assert latest.get(timeout=0) == 4 and latest.get(timeout=0) is None
    assert (latest.received, latest.dropped) == (5, 4)

    fifo = FrameMailbox(latest_only=False, capacity=3)
    for k in range(5):
        fifo.put(k)
    assert [fifo.get(timeout=0) for _ in range(3)] == [2, 3, 4] and fifo.dropped == 2

    # A waiting consumer wakes for a new frame, and for close().
    got = []
    consumer = threading.Thread(target=lambda: got.append(latest.get(timeout=5)))
    consumer.start()
    latest.put("frame")
    consumer.join(timeout=5)
    assert got == ["frame"]
    consumer = threading.Thread(target=lambda: got.append(latest.get(timeout=5)))
    consumer.start()
    latest.close()
    consumer.join(timeout=1)
    assert not consumer.is_alive() and got[-1] is None


# ---- the interface the keyframe VO keeps (ESTIMATOR_API): calibration, arm poses, tracking ---------


def test_set_calibration_replaces_the_published_camera_and_keeps_the_pose():
    from nocal_ros.camera import CameraModel
    from nocal_ros.lens import CameraCalibration

    T_w_c = random_trajectory(6, seed=11)
    poses = TrajectoryPoses(T_w_c)
    model = PoseModel(predict_pose=poses, input_size=(32, 24), model_id="trajectory", camera=CameraModel(64, 48))
    estimator = OdometryEstimator(model, method="pose_head")
    status = estimator.calibration_status()
    assert (status["state"], status["source"], status["focal_std_px"], status["keyframes"]) == ("prior", "model", None, 0)
    # Before the online camera exists the status has its keys (diagnostics list the same fields throughout).
    from nocal_ros.odometry.calibration import OnlineCamera
    assert status.keys() == OnlineCamera(CameraCalibration(64, 48, np.eye(3), np.zeros(5)), "model").status().keys()
    learnt, _ = estimator.camera_info(64, 48)
    assert learnt.fx == pytest.approx(64.0)  # the untrained camera: f = width
    for k in range(3):
        before = estimator.process(START_NS + k * PERIOD_NS, frame(k))

    given = CameraCalibration(640, 480, [[500.0, 0, 321.5], [0, 502.0, 238.0], [0, 0, 1]], [0.1, -0.2, 0.001, 0.002, 0.0])
    estimator.set_calibration(given)
    assert estimator.calibration_status()["source"] == "file"
    published, residual = estimator.camera_info()  # at the frames' size: the same lens scaled by 1/10
    assert residual == 0.0 and (published.width, published.height) == (64, 48)
    assert published.fx == pytest.approx(50.0) and published.cy == pytest.approx((238.0 + 0.5) / 10 - 0.5)
    np.testing.assert_array_equal(published.D, given.D)
    native = estimator.camera_info(640, 480)[0]
    np.testing.assert_allclose(native.K, given.K, rtol=1e-12)
    np.testing.assert_array_equal(native.D, given.D)
    # The pose chain goes on where it was, and a reset or a reload keeps the calibration.
    after = estimator.process(START_NS + 3 * PERIOD_NS, frame(3))
    assert after.status == "ok"
    np.testing.assert_allclose(after.T_odom_base, before.T_odom_base @ after.T_prev_curr, atol=1e-9)
    estimator.reset()
    estimator.reload(model)
    np.testing.assert_allclose(estimator.camera_info(640, 480)[0].K, given.K, rtol=1e-12)
    with pytest.raises(TypeError, match="CameraCalibration"):
        estimator.set_calibration({"fx": 1.0})


def test_a_given_lens_the_bundle_adjustment_cannot_hold_is_converted_with_its_residual():
    """plumb_bob's k3 (and rational_polynomial) is refitted as plumb_bob with k3 = 0, the camera the VO
    optimises; the residual of that fit, checked here against OpenCV's projection, is reported."""
    import cv2

    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry.calibration import as_vo_calibration

    given = CameraCalibration(640, 480, [[500.0, 0, 321.5], [0, 502.0, 238.0], [0, 0, 1]], [-0.2, 0.05, 0.001, 0.002, 0.01])
    converted, residual = as_vo_calibration(given)
    assert converted.distortion_model == "plumb_bob" and converted.D[4] == 0.0
    np.testing.assert_array_equal(converted.K, given.K)
    rays = np.column_stack((np.random.default_rng(0).uniform(-0.55, 0.55, (500, 2)), np.ones(500)))
    projected = [cv2.projectPoints(rays, np.zeros(3), np.zeros(3), c.K, c.D)[0].reshape(-1, 2) for c in (given, converted)]
    rms = float(np.sqrt(np.mean(np.sum((projected[0] - projected[1]) ** 2, 1))))
    assert 0.0 < residual < 0.5 and rms < 2 * residual + 0.05
    estimator, _ = make_estimator(random_trajectory(2), calibration=given)
    published, published_residual = estimator.camera_info()
    assert published == converted and published_residual == pytest.approx(residual, rel=1e-12)


def test_auto_starts_a_learnt_fisheye_as_equidistant_and_a_learnt_pinhole_as_plumb_bob():
    """``distortion_model="auto"`` (the default) with a learnt camera: a fisheye (a fine-tuned model's
    camera, here learnt from an equidistant lens 97 degrees off axis at its corners) that plumb_bob
    (k3 = 0) cannot hold starts the online camera as equidistant, at the learnt focal length; a barrel
    pinhole stays plumb_bob. ``plumb_bob`` asked for keeps plumb_bob, and ``equidistant`` starts from
    f = width as before."""
    from nocal_ros.camera import CameraModel
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry.calibration import AUTO_EQUIDISTANT_PX, calibration_from_learnt_camera

    fisheye = CameraCalibration(160, 120, np.array([[60.0, 0, 79.5], [0, 60.0, 59.5], [0, 0, 1]]), np.zeros(4), "equidistant")
    pinhole = CameraCalibration(160, 120, np.array([[120.0, 0, 79.5], [0, 121.0, 59.5], [0, 0, 1]]),
                                np.array([-0.2, 0.05, 0.0, 0.0, 0.0]), "plumb_bob")
    learnt_fisheye, learnt_pinhole = CameraModel.from_calibration(fisheye), CameraModel.from_calibration(pinhole)
    plumb_bob, plumb_bob_px = calibration_from_learnt_camera(learnt_fisheye, "plumb_bob")
    equidistant, equidistant_px = calibration_from_learnt_camera(learnt_fisheye, "equidistant")
    assert plumb_bob_px > AUTO_EQUIDISTANT_PX and equidistant_px < 0.5 * plumb_bob_px
    assert calibration_from_learnt_camera(learnt_fisheye, "auto")[0].distortion_model == "equidistant"
    assert calibration_from_learnt_camera(learnt_pinhole, "auto")[0].distortion_model == "plumb_bob"

    def started(camera, distortion_model):
        model = PoseModel(predict_pose=TrajectoryPoses(random_trajectory(3, seed=2)), input_size=(32, 24), camera=camera)
        estimator = OdometryEstimator(model, distortion_model=distortion_model, synchronous_mapping=True)
        try:
            return estimator._starting_calibration(160, 120)
        finally:
            estimator.close()

    calibration, source, residual = started(learnt_fisheye, "auto")
    assert (calibration.distortion_model, source) == ("equidistant", "model")
    assert calibration.fx == pytest.approx(60.0, rel=1e-3) and residual == pytest.approx(equidistant_px)
    np.testing.assert_allclose(calibration.D, equidistant.D)
    assert started(learnt_fisheye, "plumb_bob")[0].distortion_model == "plumb_bob"
    calibration, source, _ = started(learnt_fisheye, "equidistant")
    assert (calibration.distortion_model, source, calibration.fx) == ("equidistant", "prior", 160.0)
    assert started(learnt_pinhole, "auto")[0].distortion_model == "plumb_bob"


def test_calibration_given_at_construction_is_published_without_a_learnt_camera():
    from nocal_ros.lens import CameraCalibration

    given = CameraCalibration.pinhole(64, 48, 40.0)
    estimator, _ = make_estimator(random_trajectory(2), calibration=given)
    assert estimator.camera_info() == (given, 0.0)  # the trajectory model carries no camera at all
    without, _ = make_estimator(random_trajectory(2))
    with pytest.raises(NocalError, match="no learnt camera"):
        without.camera_info()


def test_arm_poses_are_kept_bounded_validated_and_cleared_by_reset():
    from nocal_ros.odometry.estimator import ARM_POSE_HISTORY

    estimator, _ = make_estimator(random_trajectory(2))
    T = make_transform(so3_exp(np.array([0.1, 0.2, 0.3])), np.array([0.4, 0.5, 0.6]))
    for k in range(ARM_POSE_HISTORY + 5):
        estimator.add_arm_pose(START_NS + k, T)
    kept = estimator.arm_poses
    assert len(kept) == ARM_POSE_HISTORY and kept[0][0] == START_NS + 5 and kept[-1][0] == START_NS + ARM_POSE_HISTORY + 4
    np.testing.assert_array_equal(kept[-1][1], T)
    for bad in (np.eye(3), np.full((4, 4), np.nan), np.diag([2.0, 1.0, 1.0, 1.0]), np.diag([-1.0, 1.0, 1.0, 1.0])):
        with pytest.raises(ValueError):
            estimator.add_arm_pose(START_NS, bad)
    estimator.reset()
    assert estimator.arm_poses == []


def test_results_say_tracking_initialises_at_a_chain_start_and_the_scale_source():
    T_w_c = random_trajectory(4, seed=3)
    estimator, _ = make_estimator(T_w_c)
    results = [estimator.process(START_NS + k * PERIOD_NS, frame(k)) for k in range(3)]
    assert [r.tracking for r in results] == ["initialising", "ok", "ok"]
    assert {r.scale_source for r in results} == {"pose_head"}
    assert estimator.process(START_NS, frame(0)).tracking == "initialising"  # time went back: a new chain


def test_replay_at_rate_hands_the_newest_item_to_a_busy_worker_and_counts_the_rest():
    import time

    from nocal_ros.odometry import replay_at_rate

    seen: list[int] = []
    # 25 ms between items: the worker thread must be scheduled within that, which a loaded 2-core
    # machine missed once at 5 ms (200 Hz; CI beside two replays, measured).
    quick = replay_at_rate(list(range(10)), 40.0, lambda index, item: seen.append(item))
    assert (quick.handled, quick.dropped) == (10, 0) and seen == list(range(10))
    assert len(quick.latencies_ms) == 10 and min(quick.latencies_ms) >= 0

    seen.clear()
    # A worker five times slower than the items arrive: it sees the first item, then only the newest.
    slow = replay_at_rate(list(range(20)), 100.0, lambda index, item: (seen.append(item), time.sleep(0.05)))
    assert slow.handled + slow.dropped == 20 and slow.dropped >= 10
    assert seen[0] == 0 and seen == sorted(seen) and len(seen) == slow.handled
    # The worker's CPU time counts the handling's work, not its waiting: 50 ms asleep is almost no CPU,
    # 20 ms of arithmetic is about 20 ms.
    assert len(slow.cpu_ms) == slow.handled and max(slow.cpu_ms) < 25

    def busy(index, item, seconds=0.02):
        end = time.thread_time() + seconds
        while time.thread_time() < end:
            pass

    worked = replay_at_rate(list(range(3)), 10.0, busy)
    assert worked.handled == 3 and min(worked.cpu_ms) >= 19.0
