"""Rigid-body geometry: the one place that defines our pose and rotation conventions.

Conventions (see DESIGN.md):

* ``T_a_b`` is the pose of frame ``b`` in frame ``a``; it maps points from ``b`` to ``a``.
  Interfaces exchange 4x4 ``float64`` numpy arrays.
* The pose head predicts ``T_ci_cj = inv(T_w_ci) @ T_w_cj`` for a pair ``(i, j)``, ``j`` after ``i``.
* Quaternions are ``(x, y, z, w)``, as in ROS messages.
* The 6D rotation representation (Zhou et al. 2019) holds the first two *columns* of ``R``.

Torch functions take batched tensors ``(..., N)`` and are differentiable; numpy functions are for
message conversion and evaluation in float64. Torch is imported inside the torch functions, not with
the module: the VO's solver process uses the numpy functions, and torch loaded with them took 1.5 s
of that process at the first camera initialisation of a live stream (measured).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

# --------------------------------------------------------------------------------------------------
# torch: rotations and rays (differentiable, batched)
# --------------------------------------------------------------------------------------------------


def rotation_6d_to_matrix(rot6d: torch.Tensor) -> torch.Tensor:
    """Map a 6D rotation ``(..., 6)`` to a rotation matrix ``(..., 3, 3)`` by Gram-Schmidt.

    The first three numbers are the (unnormalised) first column, the next three the second column.
    """
    import torch
    import torch.nn.functional as F

    a1, a2 = rot6d[..., :3], rot6d[..., 3:6]
    b1 = F.normalize(a1, dim=-1)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


def matrix_to_rotation_6d(rotation: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rotation_6d_to_matrix` for a proper rotation ``(..., 3, 3)`` -> ``(..., 6)``."""
    import torch

    return torch.cat((rotation[..., :, 0], rotation[..., :, 1]), dim=-1)


def pose_from_translation_rot6d(translation: torch.Tensor, rot6d: torch.Tensor) -> torch.Tensor:
    """Build homogeneous transforms ``(..., 4, 4)`` from translation ``(..., 3)`` and 6D rotation."""
    import torch

    rotation = rotation_6d_to_matrix(rot6d)
    top = torch.cat((rotation, translation.unsqueeze(-1)), dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


def transform_inverse(transform: torch.Tensor) -> torch.Tensor:
    """Invert rigid transforms ``(..., 4, 4)`` in closed form (no general matrix inverse)."""
    import torch

    rotation_t = transform[..., :3, :3].transpose(-1, -2)
    translation = -(rotation_t @ transform[..., :3, 3:4])
    top = torch.cat((rotation_t, translation), dim=-1)
    return torch.cat((top, transform[..., 3:4, :]), dim=-2)


def pluecker_from_rays(origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Pluecker coordinates ``(d, o x d)`` ``(..., 6)`` of rays; ``directions`` are normalised here.

    The moment ``o x d`` is the same for every point ``o`` on the ray, so the encoding depends on
    the ray alone, not on where along it the origin was taken.
    """
    import torch
    import torch.nn.functional as F

    d = F.normalize(directions, dim=-1)
    moment = torch.linalg.cross(origins.expand_as(d), d, dim=-1)
    return torch.cat((d, moment), dim=-1)


def rays_camera_to_world(
    directions_cam: torch.Tensor, T_w_c: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Move camera-frame ray directions ``(B, N, 3)`` into the world by poses ``T_w_c`` ``(B, 4, 4)``.

    Returns ``(origins (B, 1, 3), directions (B, N, 3))``.
    """
    rotation = T_w_c[..., :3, :3]
    directions = directions_cam @ rotation.transpose(-1, -2)
    origins = T_w_c[..., None, :3, 3]
    return origins, directions


def rotation_angle(rotation: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in radians of rotation matrices ``(..., 3, 3)``."""
    import torch

    trace = rotation[..., 0, 0] + rotation[..., 1, 1] + rotation[..., 2, 2]
    return torch.acos(((trace - 1.0) / 2.0).clamp(-1.0, 1.0))


# --------------------------------------------------------------------------------------------------
# numpy, float64: interfaces, messages, evaluation
# --------------------------------------------------------------------------------------------------


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 float64 transform from a 3x3 rotation and a 3-vector."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return transform


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The proper rotation nearest to each ``(..., 3, 3)`` matrix (Frobenius norm), by SVD.

    Network rotations are float32, orthonormal to ~1e-7 only; chained over ~100 pairs they leave SO(3)
    by more than evo's 1e-6 tolerance, so every chain of them goes through this first.
    """
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    flip = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)  # det +1: a rotation, not a reflection
    u[..., :, -1] *= flip[..., None]
    return u @ vt


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a rigid 4x4 transform."""
    inverse = np.eye(4)
    rotation_t = transform[:3, :3].T
    inverse[:3, :3] = rotation_t
    inverse[:3, 3] = -rotation_t @ transform[:3, 3]
    return inverse


def relative_transform(T_w_ci: np.ndarray, T_w_cj: np.ndarray) -> np.ndarray:
    """``T_ci_cj = inv(T_w_ci) @ T_w_cj``: pose of ``j`` seen from ``i``."""
    return invert_transform(T_w_ci) @ T_w_cj


class InvalidTransformError(ValueError):
    """Numbers that describe no pose: a zero-length quaternion, or NaN or infinite components."""


#: Shortest quaternion accepted as a rotation. Shorter ones are zero up to rounding: their direction,
#: and so the rotation, is noise (an unset ``geometry_msgs/Quaternion`` is all zeros).
MIN_QUATERNION_NORM = 1e-6


def unit_quaternion(quaternion_xyzw: np.ndarray) -> np.ndarray:
    """``(x, y, z, w)`` scaled to unit length.

    Raises:
        InvalidTransformError: the quaternion is not 4 finite numbers, or is (nearly) zero. Normalising
            it would give NaN, and a NaN pose poisons every pose chained after it.
    """
    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all():
        raise InvalidTransformError(f"quaternion (x, y, z, w) must be 4 finite numbers, got {np.asarray(quaternion_xyzw).tolist()}")
    norm = float(np.linalg.norm(q))
    if norm < MIN_QUATERNION_NORM:
        raise InvalidTransformError(f"quaternion (x, y, z, w) {q.tolist()} has length {norm:.3g}: it is no rotation")
    return q / norm


def quaternion_to_matrix(quaternion_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion ``(x, y, z, w)``.

    Raises:
        InvalidTransformError: zero-length or non-finite quaternion (see :func:`unit_quaternion`).
    """
    x, y, z, w = unit_quaternion(quaternion_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def transform_from_translation_quaternion(translation_xyz: np.ndarray, quaternion_xyzw: np.ndarray) -> np.ndarray:
    """4x4 ``float64`` transform of a translation and a (not necessarily unit) quaternion ``(x, y, z, w)``,
    as ``geometry_msgs/Pose``, ``Transform`` and the command line give them.

    Raises:
        InvalidTransformError: a non-finite translation, or a zero-length or non-finite quaternion.
    """
    translation = np.asarray(translation_xyz, dtype=np.float64)
    if translation.shape != (3,) or not np.isfinite(translation).all():
        raise InvalidTransformError(f"translation (x, y, z) must be 3 finite numbers, got {np.asarray(translation_xyz).tolist()}")
    return make_transform(quaternion_to_matrix(quaternion_xyzw), translation)


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def slerp_quaternion(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions ``(x, y, z, w)``, shortest arc."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: lerp is exact to float precision and avoids 0/0
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)


def interpolate_transform(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """Pose at fraction ``alpha`` between ``T0`` and ``T1``: slerp rotation, linear translation."""
    q = slerp_quaternion(matrix_to_quaternion(T0[:3, :3]), matrix_to_quaternion(T1[:3, :3]), alpha)
    translation = (1 - alpha) * T0[:3, 3] + alpha * T1[:3, 3]
    return make_transform(quaternion_to_matrix(q), translation)


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Geodesic angle in degrees of a 3x3 rotation matrix."""
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (axis times angle, radians), by
    Rodrigues' formula (its Taylor series below 1e-8 rad)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec, axis=-1)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0 - angle**2 / 6.0, np.sin(angle) / safe)
    b = np.where(small, 0.5 - angle**2 / 24.0, (1.0 - np.cos(angle)) / safe**2)
    K = np.zeros(rotvec.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -rotvec[..., 2], rotvec[..., 1], -rotvec[..., 0]
    K -= np.swapaxes(K, -1, -2)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of :func:`so3_exp` for angles below pi)."""
    angle = np.radians(rotation_angle_deg(rotation))
    if angle < 1e-12:
        return np.zeros(3)
    axis = np.array(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )
    norm = np.linalg.norm(axis)
    if norm < 1e-9:  # angle close to pi: take the axis from the symmetric part
        sym = (rotation + np.eye(3)) / 2.0
        axis = sym[:, int(np.argmax(np.diag(sym)))]
        norm = np.linalg.norm(axis)
    return axis / norm * angle
