"""Pose covariance propagation for integrated odometry (the model is in :mod:`nocal_ros.odometry.estimator`)."""

from __future__ import annotations

import numpy as np

#: Variance meaning "unknown" in ROS covariance fields.
UNKNOWN_VARIANCE = 1.0e6


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def adjoint(T: np.ndarray) -> np.ndarray:
    """``6x6`` adjoint of ``T`` for twists ordered ``(rho, theta)``: ``T Exp(xi) T^-1 = Exp(Ad_T xi)``."""
    R, t = T[:3, :3], T[:3, 3]
    ad = np.zeros((6, 6))
    ad[:3, :3] = R
    ad[:3, 3:] = _skew(t) @ R
    ad[3:, 3:] = R
    return ad


def propagate_covariance(
    sigma_i: np.ndarray, T_odom_i: np.ndarray, T_i_j: np.ndarray, sigma_pair: np.ndarray
) -> np.ndarray:
    """First-order pose covariance of ``T_odom_i @ T_i_j`` (see the module notes for the model)."""
    R_j = T_odom_i[:3, :3] @ T_i_j[:3, :3]
    A = np.eye(6)
    A[:3, 3:] = -_skew(T_odom_i[:3, :3] @ T_i_j[:3, 3])
    B = np.zeros((6, 6))
    B[:3, :3] = R_j
    B[3:, 3:] = R_j
    sigma = A @ sigma_i @ A.T + B @ sigma_pair @ B.T
    return 0.5 * (sigma + sigma.T)
