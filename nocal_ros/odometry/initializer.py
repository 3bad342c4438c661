"""Map initialisation from two views: the relative pose of a reference frame and the current one, and
the first landmarks.

Monocular geometry sees the motion between two frames only up to scale, and only once the camera has
moved enough for the parallax to stand out of the tracking noise. While the tracks are explained by a
rotation alone (a camera that turns, or does not move at all), there is no translation to measure, so
:func:`two_view_map` returns None and the caller waits for more parallax. Otherwise an essential matrix
is fitted by RANSAC (rays through the online camera, as undistorted normalised points), decomposed, and
its inliers are triangulated; the map's unit of length is the baseline between the two frames.

Conventions: ``T_ref_cur`` is the current camera's pose in the reference camera's frame. With OpenCV's
``X_cur = R X_ref + t``, ``R_ref_cur = R^T`` and the current centre in the reference frame is ``-R^T t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from nocal_ros.geometry import nearest_rotation
from nocal_ros.odometry.map import parallax_deg, triangulate

#: Tracks a rotation explains to within this share of the inlier threshold (median) show no parallax:
#: a camera that turns or stands still. A fraction, not a share of inliers: with a pixel of parallax
#: per frame (3 cm steps at 160x120) 90 % of the tracks fit a rotation within a pixel, and the rotation
#: fitted through the parallax was 0.3-0.4 deg off per frame (measured) where the essential matrix's
#: is not.
STILL_RESIDUAL = 0.25


@dataclass
class TwoViewMap:
    """The first two keyframes' relative pose (unit baseline) and the landmarks triangulated from them.

    Attributes:
        T_ref_cur: ``(4, 4)`` pose of the current camera in the reference camera (``|t| = 1``).
        inliers: ``(N,)`` mask over the given tracks: triangulated, in front of both cameras, with parallax.
        points: ``(M, 3)`` landmarks in the reference camera's frame, one per inlier.
        median_parallax_deg: median angle between the two rays of the landmarks.
        ready: enough landmarks with enough parallax to start a map; otherwise only the motion is usable.
    """

    T_ref_cur: np.ndarray
    inliers: np.ndarray
    points: np.ndarray
    median_parallax_deg: float
    ready: bool = True


def unit_rays(normalised: np.ndarray) -> np.ndarray:
    """Undistorted normalised points ``(N, 2)`` -> unit ray directions ``(N, 3)``."""
    rays = np.concatenate((normalised, np.ones((len(normalised), 1))), 1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def rotation_from_rays(rays_i: np.ndarray, rays_j: np.ndarray) -> np.ndarray:
    """Least-squares ``R`` with ``rays_j ~ R @ rays_i`` (Kabsch): ``(N, 3)`` unit rays x 2 -> ``(3, 3)``."""
    return nearest_rotation(rays_j.T @ rays_i)


def rotation_ransac(rays_i: np.ndarray, rays_j: np.ndarray, threshold: float, seed: int = 0,
                    iterations: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Pure-rotation model ``rays_j = R rays_i`` by RANSAC on pairs of rays; returns ``R`` and the inlier mask."""
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, len(rays_i), (iterations, 2))  # a repeated ray makes a hypothesis that loses
    # Every hypothesis at once: batched Kabsch on (iterations, 3, 3) cross-covariances.
    hypotheses = nearest_rotation(np.einsum("sni,snj->sij", rays_j[samples], rays_i[samples]))
    residuals = np.linalg.norm(np.einsum("sij,nj->sni", hypotheses, rays_i) - rays_j[None], axis=2)
    best = residuals[np.argmax((residuals < threshold).sum(1))] < threshold
    if best.sum() < 2:
        return np.eye(3), best
    R = rotation_from_rays(rays_i[best], rays_j[best])
    return R, np.linalg.norm(rays_i @ R.T - rays_j, axis=1) < threshold


def two_view_map(x_ref: np.ndarray, x_cur: np.ndarray, threshold: float, *, min_points: int = 40,
                 min_parallax_deg: float = 1.0, seed: int = 0) -> TwoViewMap | None:
    """Initialise from matched undistorted normalised points ``(N, 2)`` of the reference and current frames.

    ``threshold``: inlier threshold in normalised units (about one pixel: ``1 / f``). Returns None while a
    pure rotation explains the tracks, or when no essential matrix explains ``min_points`` of them. With
    fewer than ``min_points`` landmarks triangulated at a median parallax of ``min_parallax_deg``, the
    result is the motion only (``ready=False``).
    """
    x_ref = np.ascontiguousarray(x_ref, dtype=np.float64).reshape(-1, 2)
    x_cur = np.ascontiguousarray(x_cur, dtype=np.float64).reshape(-1, 2)
    finite = np.isfinite(x_ref).all(1) & np.isfinite(x_cur).all(1)
    if finite.sum() < min_points:
        return None
    rays_ref, rays_cur = unit_rays(x_ref[finite]), unit_rays(x_cur[finite])
    R, _ = rotation_ransac(rays_ref, rays_cur, threshold, seed)
    if np.median(np.linalg.norm(rays_ref @ R.T - rays_cur, axis=1)) < STILL_RESIDUAL * threshold:
        return None

    index = np.flatnonzero(finite)
    a, b = x_ref[index], x_cur[index]
    # OpenCV's five-point RANSAC is given the points in units of the threshold (about pixels): with
    # normalised coordinates and a threshold of ~1e-3 it found no inliers on clean tracks (measured).
    scale = 1.0 / threshold
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(a * scale, b * scale, np.diag([scale, scale, 1.0]), method=cv2.RANSAC,
                                   prob=0.999, threshold=1.0)
    if E is None or E.shape[0] < 3 or mask is None:
        return None
    # The distance bound is far beyond OpenCV's default of 50 baselines: a 3 cm step seen at 2 m puts
    # every point past 50 baselines, and the cheirality count would drop them all.
    count, R, t, _, _ = cv2.recoverPose(E[:3], a, b, np.eye(3), distanceThresh=1e9, mask=mask.copy())
    if count < min_points:
        return None
    T_ref_cur = np.eye(4)
    T_ref_cur[:3, :3] = R.T
    T_ref_cur[:3, 3] = (-R.T @ t).ravel()
    T_ref_cur[:3, 3] /= np.linalg.norm(T_ref_cur[:3, 3])

    points = triangulate(np.eye(4), T_ref_cur, a, b)
    ok = np.isfinite(points).all(1) & (mask.ravel() > 0)
    depth_ref = np.where(ok, points[:, 2], -1.0)
    points_cur = (np.where(ok[:, None], points, 0.0) - T_ref_cur[:3, 3]) @ T_ref_cur[:3, :3]
    depth_cur = np.where(ok, points_cur[:, 2], -1.0)
    ok &= (depth_ref > 0) & (depth_cur > 0)
    # Reprojection in both views, as a check that the triangulation agrees with the tracks.
    safe_ref = np.where(ok, depth_ref, 1.0)
    safe_cur = np.where(ok, depth_cur, 1.0)
    error_ref = np.linalg.norm(np.where(ok[:, None], points, 0.0)[:, :2] / safe_ref[:, None] - a, axis=1)
    error_cur = np.linalg.norm(points_cur[:, :2] / safe_cur[:, None] - b, axis=1)
    ok &= (error_ref < 2 * threshold) & (error_cur < 2 * threshold)
    parallax = parallax_deg(np.eye(4), T_ref_cur, np.where(ok[:, None], points, 0.0))
    median = float(np.median(parallax[ok])) if ok.any() else 0.0
    inliers = np.zeros(len(x_ref), dtype=bool)
    inliers[index[ok]] = True
    ready = bool(ok.sum() >= min_points and median >= min_parallax_deg)
    return TwoViewMap(T_ref_cur, inliers, points[ok], median, ready)
