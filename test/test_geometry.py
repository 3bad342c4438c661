"""Geometry conventions checked against closed forms and an independent reference (scipy)."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from nocal_ros import geometry as g


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_matrix()


def test_rotation_6d_round_trip():
    rotations = torch.from_numpy(random_rotations(64))
    back = g.rotation_6d_to_matrix(g.matrix_to_rotation_6d(rotations))
    assert torch.allclose(back, rotations, atol=1e-12)


def test_rotation_6d_of_any_vector_is_a_rotation():
    rot6d = torch.randn(100, 6, dtype=torch.float64)
    rotation = g.rotation_6d_to_matrix(rot6d)
    eye = torch.eye(3, dtype=torch.float64).expand(100, 3, 3)
    assert torch.allclose(rotation.transpose(-1, -2) @ rotation, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(100, dtype=torch.float64))


def test_pluecker_invariant_to_origin_along_ray():
    origin = torch.randn(50, 3, dtype=torch.float64)
    direction = torch.randn(50, 3, dtype=torch.float64)
    shift = torch.randn(50, 1, dtype=torch.float64) * 5
    a = g.pluecker_from_rays(origin, direction)
    b = g.pluecker_from_rays(origin + shift * direction, direction * 3.0)
    assert torch.allclose(a, b, atol=1e-10)


def test_transform_inverse_matches_linalg():
    T = torch.from_numpy(np.stack([g.make_transform(r, np.random.randn(3)) for r in random_rotations(8)]))
    assert torch.allclose(g.transform_inverse(T), torch.linalg.inv(T), atol=1e-12)


def test_quaternions_match_scipy():
    rotations = random_rotations(32, seed=1)
    for rotation in rotations:
        q = g.matrix_to_quaternion(rotation)
        q_ref = Rotation.from_matrix(rotation).as_quat()  # (x, y, z, w)
        q_ref = q_ref if q_ref[3] >= 0 else -q_ref
        assert np.allclose(q, q_ref, atol=1e-12)
        assert np.allclose(g.quaternion_to_matrix(q), rotation, atol=1e-12)


@pytest.mark.parametrize("alpha", [0.0, 0.25, 0.5, 0.9, 1.0])
def test_interpolation_matches_scipy_slerp(alpha):
    r0, r1 = random_rotations(2, seed=3)
    T0 = g.make_transform(r0, [0, 0, 0])
    T1 = g.make_transform(r1, [1, 2, 3])
    T = g.interpolate_transform(T0, T1, alpha)
    ref = Slerp([0, 1], Rotation.from_matrix([r0, r1]))([alpha]).as_matrix()[0]
    assert np.allclose(T[:3, :3], ref, atol=1e-10)
    assert np.allclose(T[:3, 3], alpha * np.array([1, 2, 3]))


def test_so3_exp_log_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        rotvec = rng.normal(size=3)
        rotvec *= rng.uniform(0.01, 3.0) / np.linalg.norm(rotvec)
        rotation = g.so3_exp(rotvec)
        assert np.allclose(rotation, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
        assert np.allclose(g.so3_log(rotation), rotvec, atol=1e-9)


def test_relative_transform_convention():
    T_w_ci = g.make_transform(g.so3_exp([0, 0, 0.3]), [1, 0, 0])
    T_w_cj = g.make_transform(g.so3_exp([0, 0, 0.5]), [1, 1, 0])
    T_ci_cj = g.relative_transform(T_w_ci, T_w_cj)
    assert np.allclose(T_w_ci @ T_ci_cj, T_w_cj)
