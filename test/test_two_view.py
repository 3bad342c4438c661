"""Two-view geometry through a camera model: closed-form checks, then a rendered camera motion."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nocal_ros.camera import CameraModel
from nocal_ros.geometry import make_transform, relative_transform, rotation_angle_deg, so3_exp
from nocal_ros.odometry import OdometryEstimator, PoseModel, combine_motion
from nocal_ros.two_view import TwoViewTracker, relative_motion, rotation_from_rays


def _project(T_c_w: np.ndarray, points: np.ndarray) -> np.ndarray:
    camera = points @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    return camera[:, :2] / camera[:, 2:]


def _scene(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    return np.column_stack((rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 1, n), rng.uniform(1.5, 4.0, n)))


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_essential_fit_recovers_the_relative_pose_of_known_cameras():
    rng = np.random.default_rng(1)
    points = _scene(rng)
    T_ci_cj = make_transform(so3_exp(np.radians([1.5, -2.0, 0.7])), np.array([0.08, -0.02, 0.05]))
    x_i = _project(np.eye(4), points)
    x_j = _project(np.linalg.inv(T_ci_cj), points)  # camera j sees points through inv(T_ci_cj)
    x_j[:20] += rng.uniform(-0.05, 0.05, (20, 2))  # 10 % gross mismatches

    motion = relative_motion(x_i, x_j, threshold=1.0 / 600)

    assert motion is not None and motion.model == "essential"
    assert rotation_angle_deg(motion.rotation.T @ T_ci_cj[:3, :3]) < 1e-3
    assert _angle_between(motion.direction, T_ci_cj[:3, 3]) < 0.05
    assert 180 <= motion.inliers <= 190  # every clean track; a mismatch can land on its epipolar line


def test_a_camera_that_only_turns_is_fitted_as_a_rotation():
    rng = np.random.default_rng(2)
    points = _scene(rng)
    T_ci_cj = make_transform(so3_exp(np.radians([-3.0, 1.0, 2.0])), np.zeros(3))
    motion = relative_motion(_project(np.eye(4), points), _project(np.linalg.inv(T_ci_cj), points), threshold=1.0 / 600)

    assert motion is not None and motion.model == "rotation" and motion.direction is None
    assert rotation_angle_deg(motion.rotation.T @ T_ci_cj[:3, :3]) < 1e-6


def test_kabsch_matches_a_known_rotation_and_too_few_tracks_give_none():
    rng = np.random.default_rng(3)
    rays = rng.normal(size=(30, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    R = so3_exp(np.array([0.3, -0.2, 0.1]))
    assert np.abs(rotation_from_rays(rays, rays @ R.T) - R).max() < 1e-12
    assert relative_motion(rng.normal(size=(5, 2)), rng.normal(size=(5, 2)), 1e-3) is None
    assert relative_motion(rng.normal(size=(100, 2)), rng.normal(size=(100, 2)), 1e-3) is None  # no model fits noise


def test_combine_motion_takes_the_pose_heads_distance_and_the_geometrys_direction():
    T_head = make_transform(so3_exp(np.array([0.1, 0.0, 0.0])), np.array([0.0, 0.03, 0.04]))
    R = so3_exp(np.array([0.0, 0.02, 0.0]))
    direction = np.array([1.0, 0.0, 0.0])
    T = combine_motion(T_head, R, direction)
    assert np.allclose(T[:3, :3], R) and np.allclose(T[:3, 3], [0.05, 0.0, 0.0]) and np.allclose(T[3], [0, 0, 0, 1])
    assert np.allclose(combine_motion(T_head, R, None)[:3, 3], T_head[:3, 3])


@pytest.fixture(scope="module")
def rendered():
    from nocal_ros.commands.demo import DEMO_SEED, demo_camera
    from nocal_ros.data.synthetic import render_sequence

    calibration = demo_camera(640, 480)
    return calibration, render_sequence(calibration, 12, seed=DEMO_SEED, split="test", fps=10.0)


def _rmse(values) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def test_tracking_a_rendered_motion_through_the_true_camera_measures_rotation(rendered):
    calibration, sequence = rendered
    tracker = TwoViewTracker(CameraModel.from_calibration(calibration))
    assert tracker.update(sequence.images[0]) is None  # nothing to pair with yet
    errors, no_motion, directions = [], [], []
    for k in range(1, len(sequence)):
        motion = tracker.update(sequence.images[k])
        truth = relative_transform(sequence.ground_truth[k - 1], sequence.ground_truth[k])
        assert motion is not None
        errors.append(rotation_angle_deg(motion.rotation.T @ truth[:3, :3]))
        no_motion.append(rotation_angle_deg(truth[:3, :3]))
        if motion.direction is not None:
            directions.append(_angle_between(motion.direction, truth[:3, 3]))
    assert _rmse(errors) < 0.5 * _rmse(no_motion)
    assert directions and np.median(directions) < 25.0


def test_estimator_with_two_view_beats_its_pose_head_and_can_be_switched_off(rendered):
    calibration, sequence = rendered
    camera = CameraModel.from_calibration(calibration)

    def standing_still(image_i: torch.Tensor, image_j: torch.Tensor) -> torch.Tensor:
        T = torch.eye(4).repeat(len(image_i), 1, 1)
        T[:, 2, 3] = 0.03  # a constant 3 cm forward: the length two-view geometry keeps
        return T

    model = PoseModel(predict_pose=standing_still, input_size=(32, 24), camera=camera, model_id="constant")
    for two_view in (True, False):
        estimator = OdometryEstimator(model, two_view=two_view)
        results = [estimator.process(int(s), image) for s, image in zip(sequence.stamps_ns, sequence.images)]
        errors = [rotation_angle_deg(r.T_prev_curr[:3, :3].T @ relative_transform(a, b)[:3, :3])
                  for r, a, b in zip(results[1:], sequence.ground_truth[:-1], sequence.ground_truth[1:])]
        no_motion = [rotation_angle_deg(relative_transform(a, b)[:3, :3])
                     for a, b in zip(sequence.ground_truth[:-1], sequence.ground_truth[1:])]
        lengths = [np.linalg.norm(r.T_prev_curr[:3, 3]) for r in results[1:]]
        assert np.allclose(lengths, 0.03)
        if two_view:
            assert estimator.counters.two_view_pairs == len(sequence) - 1
            assert {r.motion_source for r in results[1:]} <= {"essential", "rotation"}
            assert _rmse(errors) < 0.5 * _rmse(no_motion)
        else:
            assert estimator.counters.two_view_pairs == 0
            assert np.allclose(errors, no_motion)
