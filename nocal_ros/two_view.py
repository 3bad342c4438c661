"""Two-view geometry through the learnt camera: the relative rotation and the direction of travel.

The pose head gives a metric relative pose from an image pair, but on cameras it never saw its
rotation is no better than reporting no motion (docs/RESULTS.md). Once the camera is calibrated,
which is what NOCaL learns, classical two-view geometry measures rotation far more precisely: track
corners from the previous frame into the current one, turn them into rays with the learnt camera
(intrinsics and freeform distortion, the same :class:`~nocal_ros.camera.CameraModel` training
learnt), and fit an essential matrix. Monocular geometry cannot give the length of the translation;
the estimator takes it from the pose head (see :mod:`nocal_ros.odometry`).

Conventions as everywhere else: the result is ``T_ci_cj``, the pose of the current camera ``j`` in the
previous camera ``i`` (optical frame). With ``X_j = R X_i + t`` (OpenCV's ``recoverPose``),
``R_ci_cj = R^T`` and the camera centre of ``j`` in ``i`` is ``-R^T t``.

When the translation is too small for an essential matrix (a camera that only turns), the rays are
related by the rotation alone; :func:`relative_motion` then fits that rotation (Kabsch on ray pairs,
inside RANSAC) and reports no direction. When neither model explains most tracks, it returns None and
the estimator uses the pose head alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from nocal_ros.geometry import nearest_rotation, rotation_angle_deg

#: Fewest tracks, and fewest model inliers, that a motion estimate needs.
MIN_TRACKS = 20
#: Share of the tracks a model must explain to be believed.
MIN_INLIER_RATIO = 0.5
#: A relative rotation above this between two frames (degrees) is taken as a failed fit.
MAX_ROTATION_DEG = 45.0
#: Lucas-Kanade window and pyramid levels (each level halves the image).
WINDOW = (15, 15)
PYRAMID_LEVELS = 3


@dataclass
class TwoViewMotion:
    """A relative motion ``T_ci_cj`` measured from tracked points.

    Attributes:
        rotation: ``R_ci_cj`` ``(3, 3)``.
        direction: unit vector from camera ``i``'s centre to camera ``j``'s, in frame ``i``; None when
            the motion was fitted as a pure rotation (too little parallax to see the translation).
        tracks: points tracked from ``i`` into ``j``.
        inliers: tracks the fitted model explains.
        model: ``"essential"`` or ``"rotation"``.
    """

    rotation: np.ndarray
    direction: np.ndarray | None
    tracks: int
    inliers: int
    model: str


def rotation_from_rays(rays_i: np.ndarray, rays_j: np.ndarray) -> np.ndarray:
    """Least-squares ``R`` with ``rays_j ~ R @ rays_i`` (Kabsch): ``(N, 3)`` unit rays x 2 -> ``(3, 3)``.

    Kabsch's answer is the rotation nearest to the cross-covariance ``sum_n rays_j[n] rays_i[n]^T``.
    """
    return nearest_rotation(rays_j.T @ rays_i)


def _rotation_ransac(rays_i: np.ndarray, rays_j: np.ndarray, threshold: float, rng: np.random.Generator,
                     iterations: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Pure-rotation model ``rays_j = R rays_i`` by RANSAC on pairs of rays; returns ``R`` and the inlier mask."""
    samples = rng.integers(0, len(rays_i), (iterations, 2))  # a repeated ray makes a hypothesis that loses
    # Every hypothesis at once: batched Kabsch on (iterations, 3, 3) cross-covariances.
    hypotheses = nearest_rotation(np.einsum("sni,snj->sij", rays_j[samples], rays_i[samples]))
    residuals = np.linalg.norm(np.einsum("sij,nj->sni", hypotheses, rays_i) - rays_j[None], axis=2)
    best = residuals[np.argmax((residuals < threshold).sum(1))] < threshold
    if best.sum() < 2:
        return np.eye(3), best
    R = rotation_from_rays(rays_i[best], rays_j[best])
    return R, np.linalg.norm(rays_i @ R.T - rays_j, axis=1) < threshold


def relative_motion(points_i: np.ndarray, points_j: np.ndarray, threshold: float,
                    seed: int = 0) -> TwoViewMotion | None:
    """``T_ci_cj``'s rotation and direction of travel from matched undistorted normalised points.

    Args:
        points_i, points_j: ``(N, 2)`` undistorted normalised image points ``(x, y)`` (``z = 1``) of the
            same scene points in the previous and the current camera.
        threshold: inlier threshold in normalised units (about one pixel: ``1 / f``).
        seed: seed of both RANSACs, so that the same points always give the same motion.

    Returns:
        The motion, or None when fewer than :data:`MIN_TRACKS` points are given or no model explains
        :data:`MIN_INLIER_RATIO` of them.
    """
    points_i = np.ascontiguousarray(points_i, dtype=np.float64).reshape(-1, 2)
    points_j = np.ascontiguousarray(points_j, dtype=np.float64).reshape(-1, 2)
    finite = np.isfinite(points_i).all(1) & np.isfinite(points_j).all(1)
    points_i, points_j = points_i[finite], points_j[finite]
    n = len(points_i)
    if n < MIN_TRACKS:
        return None
    needed = max(MIN_TRACKS, int(np.ceil(MIN_INLIER_RATIO * n)))

    rays_i = np.concatenate((points_i, np.ones((n, 1))), 1)
    rays_j = np.concatenate((points_j, np.ones((n, 1))), 1)
    rays_i /= np.linalg.norm(rays_i, axis=1, keepdims=True)
    rays_j /= np.linalg.norm(rays_j, axis=1, keepdims=True)
    # A rotation that explains nearly every track wins: the parallax is then below the noise, and an
    # essential matrix fitted to it is ill-conditioned (at 160x120 it doubled the rotation error: measured).
    R_rot, rotation_inliers = _rotation_ransac(rays_i, rays_j, threshold, np.random.default_rng(seed))
    if rotation_inliers.sum() >= max(needed, int(0.9 * n)):
        return _checked(TwoViewMotion(R_rot.T, None, n, int(rotation_inliers.sum()), "rotation"))

    # OpenCV's five-point RANSAC is given the points in units of the threshold (about pixels): with
    # normalised coordinates and a threshold of ~1e-3 it found no inliers on clean tracks (measured).
    scale = 1.0 / threshold
    cv2.setRNGSeed(seed)  # OpenCV's RANSAC draws from a global generator: seed it so a replay repeats exactly
    E, mask = cv2.findEssentialMat(points_i * scale, points_j * scale, np.diag([scale, scale, 1.0]),
                                   method=cv2.RANSAC, prob=0.999, threshold=1.0)
    if E is not None and E.shape[0] >= 3 and E.shape[1] == 3 and mask is not None:
        # The distance bound is far beyond OpenCV's default of 50 baselines: a 3 cm step seen at 2 m
        # puts every point past 50 baselines, and the cheirality count would drop them all.
        count, R, t, _, _ = cv2.recoverPose(E[:3], points_i, points_j, np.eye(3), distanceThresh=1e9, mask=mask.copy())
        if count >= needed:
            direction = (-R.T @ t).ravel()
            return _checked(TwoViewMotion(R.T, direction / np.linalg.norm(direction), n, int(count), "essential"))
    if rotation_inliers.sum() >= needed:
        return _checked(TwoViewMotion(R_rot.T, None, n, int(rotation_inliers.sum()), "rotation"))
    return None


def _checked(motion: TwoViewMotion) -> TwoViewMotion | None:
    return motion if rotation_angle_deg(motion.rotation) <= MAX_ROTATION_DEG else None


def gray_image(image: np.ndarray) -> np.ndarray:
    """RGB or mono uint8 ``(H, W[, 3])`` -> mono uint8 ``(H, W)``."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def detect_corners(gray: np.ndarray, max_corners: int) -> np.ndarray | None:
    """Up to ``max_corners`` Shi-Tomasi corners ``(N, 1, 2)`` float32 of a mono image, or None.

    Corners at full resolution: detected at half resolution they doubled the rotation error (measured).
    """
    return cv2.goodFeaturesToTrack(gray, int(max_corners), 0.01, max(3, gray.shape[1] // 40))


def track_corners(gray_i: np.ndarray, gray_j: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Track ``corners`` of image ``i`` into image ``j`` (pyramidal Lucas-Kanade, forward and back).

    Returns the matched pixels ``(M, 2)`` float64 in ``i`` and in ``j``: only tracks that come back to
    within half a pixel of where they started (a track that does not is a mismatch).
    """
    points = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    if len(points) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(gray_i, gray_j, points, None, winSize=WINDOW, maxLevel=PYRAMID_LEVELS)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(gray_j, gray_i, tracked, None, winSize=WINDOW, maxLevel=PYRAMID_LEVELS)
    good = (status.ravel() == 1) & (status_back.ravel() == 1) & (np.linalg.norm((back - points).reshape(-1, 2), axis=1) < 0.5)
    return points.reshape(-1, 2)[good].astype(np.float64), tracked.reshape(-1, 2)[good].astype(np.float64)


class TwoViewTracker:
    """Tracks corners from frame to frame and measures each pair's motion through a camera model.

    Args:
        camera: the learnt camera (:class:`~nocal_ros.camera.CameraModel`, native resolution); frames of
            another size with the same aspect ratio are mapped onto its native pixels.
        max_corners: corners detected per frame.
        work_width: frames wider than this are tracked at this width (speed), the coordinates scaled back.
    """

    def __init__(self, camera: Any, max_corners: int = 300, work_width: int = 640) -> None:
        self.camera = camera.float64_copy() if hasattr(camera, "float64_copy") else camera
        self.max_corners = int(max_corners)
        self.work_width = int(work_width)
        self._previous: tuple[np.ndarray, np.ndarray | None] | None = None
        self._frame_size: tuple[int, int] | None = None

    def reset(self) -> None:
        """Forget the previous frame (a new pair chain)."""
        self._previous = None

    def _gray(self, image: np.ndarray) -> np.ndarray:
        gray = gray_image(image)
        width = gray.shape[1]
        if width > self.work_width:
            height = round(gray.shape[0] * self.work_width / width)
            gray = cv2.resize(gray, (self.work_width, height), interpolation=cv2.INTER_AREA)
        return gray

    def _normalised(self, pixels: np.ndarray, width: int, height: int) -> np.ndarray:
        """Pixels ``(N, 2)`` of a ``width x height`` image -> undistorted normalised points through the learnt camera."""
        sx, sy = self.camera.width / width, self.camera.height / height
        u = torch.from_numpy((pixels[:, 0] + 0.5) * sx - 0.5)
        v = torch.from_numpy((pixels[:, 1] + 0.5) * sy - 0.5)
        with torch.no_grad():
            return self.camera.undistorted_normalised(u, v).numpy()

    def update(self, image: np.ndarray) -> TwoViewMotion | None:
        """Take the next frame (RGB or mono uint8); return the motion from the previous frame, or None."""
        height, width = image.shape[:2]
        if self._frame_size != (width, height):
            self._previous, self._frame_size = None, (width, height)
        gray = self._gray(image)
        corners = detect_corners(gray, self.max_corners)
        previous, self._previous = self._previous, (gray, corners)
        if previous is None or previous[1] is None or len(previous[1]) < MIN_TRACKS:
            return None
        points_i, points_j = track_corners(previous[0], gray, previous[1])
        if len(points_i) < MIN_TRACKS:
            return None
        work_height, work_width = gray.shape
        x_i = self._normalised(points_i, work_width, work_height)
        x_j = self._normalised(points_j, work_width, work_height)
        fx = float(self.camera.intrinsics()[0]) * work_width / self.camera.width  # focal in tracked pixels
        return relative_motion(x_i, x_j, threshold=1.0 / fx)  # one tracked pixel
