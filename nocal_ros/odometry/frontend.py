"""Tracking, the VO's per-frame thread of work: persistent corner tracks and PnP on rays.

Corners are followed from frame to frame by pyramidal Lucas-Kanade with a forward-backward check, so a
track stays on one scene point for as long as it is in view: its id is the id of the landmark it
becomes once triangulated. New corners are detected only in the cells of a grid that hold too few
tracks, which keeps the tracks spread over the image (a cluster in one corner would leave the pose and
the camera's distortion poorly constrained elsewhere). Frames at least :data:`SHRINK_FROM` times
``work_width`` wide are tracked at that width, frames narrower than ``min_work_width`` enlarged by a
whole factor; coordinates handed out are always native pixels.

Each frame is posed against the local map by PnP inside RANSAC on the tracks that have a landmark. The
pixels become rays through the online camera (``CameraCalibration.undistorted_normalised``: the one
pixel -> ray map of the VO), so a better calibration pays off at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from nocal_ros.geometry import make_transform, so3_exp

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration

#: Lucas-Kanade window and pyramid levels (each level halves the image): the window of the search between
#: keyframes far apart in the stream (``local_mapping.search_by_projection``) and the default.
WINDOW = (15, 15)
PYRAMID_LEVELS = 3
#: The window of frame-to-frame tracking. Lucas-Kanade's cost is per corner and window pixel: 11x11 took
#: the forward and backward calls from 7.2 to 3.4 ms at 640x480 (300 corners) and tracking from 10.8 to
#: 7.5-7.8 ms a frame (``nocal bench``). Against rendered ground truth its tracks are as close (median
#: 0.043 px either way, 90th percentile 0.18 against 0.22 px) and 2.4 % fewer pass the forward-backward
#: check; over 23 dev replays the accuracy stayed within the replays' own spread (docs/RESULTS.md,
#: "Tracking within 8 ms").
TRACKING_WINDOW = 11
#: Lucas-Kanade's iterations per pyramid level at most, and its step size (px) that ends them: OpenCV's defaults.
LK_ITERATIONS = 30
LK_EPSILON = 0.01
#: Frames at least this many times ``TrackerSettings.work_width`` wide are tracked shrunk to it; narrower
#: ones at their own size. Lucas-Kanade's cost is per track, not per pixel, and shrinking by a fraction
#: is OpenCV's slow area resize: a 752x480 frame took 2.4 ms to shrink to 640 px, and VAMR's frames
#: tracked as they are took 1.3 ms less CPU each (at 30 Hz, two runs each, measured).
SHRINK_FROM = 1.5
#: A track whose backward track does not return within this many pixels (work pixels, native ones on an
#: enlarged image) is a mismatch.
FORWARD_BACKWARD_PX = 0.5
#: The Cauchy loss's scale in PnP's robust refinement, in robust standard deviations of the residuals
#: (2.385: 95 % efficiency on Gaussian noise), its reweightings at most, and the floor of that standard
#: deviation as a share of the inlier threshold.
CAUCHY_SCALE = 2.385
ROBUST_ITERATIONS = 10
ROBUST_MIN_NOISE_SHARE = 0.05
#: A reweighting that moves no projection by more than this share of the noise has converged.
CONVERGED_SHIFT = 1e-3
#: The median of a 2-D isotropic Gaussian's length over its standard deviation per axis, ``sqrt(2 ln 2)``.
RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))


def gray_image(image: np.ndarray) -> np.ndarray:
    """RGB or mono uint8 ``(H, W[, 3])`` -> mono uint8 ``(H, W)``."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def detect_corners(gray: np.ndarray, max_corners: int, mask: np.ndarray | None = None,
                   min_distance: float | None = None) -> np.ndarray | None:
    """Up to ``max_corners`` Shi-Tomasi corners ``(N, 1, 2)`` float32 of a mono image, or None.

    Corners at full resolution: detected at half resolution they doubled the rotation error (measured).
    """
    distance = max(3, gray.shape[1] // 40) if min_distance is None else min_distance
    return cv2.goodFeaturesToTrack(gray, int(max_corners), 0.01, distance, mask=mask)


def forward_backward_px(work_scale: tuple[float, float]) -> float:
    """The forward-backward threshold in work pixels for images tracked at ``work_scale`` (native pixels
    per work pixel): :data:`FORWARD_BACKWARD_PX` work pixels, or as many native ones on an enlarged image."""
    return FORWARD_BACKWARD_PX / min(1.0, float(min(work_scale)))


def track_corners(gray_i: np.ndarray, gray_j: np.ndarray, corners: np.ndarray,
                  guess: np.ndarray | None = None, window: int = WINDOW[0],
                  iterations: int = LK_ITERATIONS,
                  max_return_px: float = FORWARD_BACKWARD_PX) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track ``corners`` ``(N, 2)`` of image ``i`` into image ``j`` (pyramidal Lucas-Kanade, forward and back).

    ``guess`` ``(N, 2)``: where each corner is expected in ``j`` (a motion prediction), else its position in ``i``.
    Returns the matched pixels ``(M, 2)`` float64 in ``i`` and in ``j`` and the indices ``(M,)`` of the
    corners kept: only tracks that come back to within ``max_return_px`` of where they started.
    """
    points = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    if len(points) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    flags = 0
    tracked = None
    if guess is not None:
        tracked = np.ascontiguousarray(guess, dtype=np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    size = (int(window), int(window))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(iterations), LK_EPSILON)
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(gray_i, gray_j, points, tracked, winSize=size,
                                                  maxLevel=PYRAMID_LEVELS, criteria=criteria, flags=flags)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(gray_j, gray_i, tracked, points.copy(), winSize=size,
                                                    maxLevel=PYRAMID_LEVELS, criteria=criteria,
                                                    flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    height, width = gray_j.shape[:2]
    moved = tracked.reshape(-1, 2)
    inside = (moved[:, 0] >= 0) & (moved[:, 1] >= 0) & (moved[:, 0] <= width - 1) & (moved[:, 1] <= height - 1)
    returned = np.linalg.norm((back - points).reshape(-1, 2), axis=1) < max_return_px
    good = np.flatnonzero((status.ravel() == 1) & (status_back.ravel() == 1) & returned & inside)
    return points.reshape(-1, 2)[good].astype(np.float64), moved[good].astype(np.float64), good


def native_pixels(work: np.ndarray, work_scale: tuple[float, float]) -> np.ndarray:
    """Work-image pixels -> native pixels (``work_scale`` native pixels per work pixel; pixel centres at
    integers in both)."""
    return (np.asarray(work, dtype=np.float64) + 0.5) * np.asarray(work_scale, dtype=np.float64) - 0.5


def work_pixels(native: np.ndarray, work_scale: tuple[float, float]) -> np.ndarray:
    """Native pixels -> work-image pixels (the inverse of :func:`native_pixels`)."""
    return (np.asarray(native, dtype=np.float64) + 0.5) / np.asarray(work_scale, dtype=np.float64) - 0.5


@dataclass
class TrackerSettings:
    """How many tracks, and how they are spread.

    Attributes:
        max_tracks: tracks kept at most.
        grid: ``(columns, rows)`` of cells that new corners are spread over.
        work_width: frames :data:`SHRINK_FROM` times wider than this or more are tracked at this width
            (speed: a 1241x376 KITTI frame at 640x194).
        min_work_width: frames narrower than this are tracked enlarged by the smallest whole factor that
            reaches it (bilinear): the Lucas-Kanade window then covers less of the scene, and tracks
            live longer (r160_201 at 160x120: 13.5 % of the tracks lost per frame, 4.5 % at 320x240;
            heldout_160 12.2 %, 8.2 %; measured over 40 frames).
    """

    max_tracks: int = 300
    grid: tuple[int, int] = (8, 6)
    work_width: int = 640
    min_work_width: int = 320
    window: int = TRACKING_WINDOW
    lk_iterations: int = LK_ITERATIONS


@dataclass
class TrackedFrame:
    """The tracks alive in a frame: ``ids`` ``(N,)`` int64 (increasing) and native ``pixels`` ``(N, 2)``."""

    ids: np.ndarray
    pixels: np.ndarray

    def select(self, mask: np.ndarray) -> "TrackedFrame":
        return TrackedFrame(self.ids[mask], self.pixels[mask])


class FeatureTracker:
    """Corner tracks that persist from frame to frame, each with an id that never repeats.

    Call :meth:`track` with each frame, then :meth:`top_up` when more tracks are wanted (at keyframes).
    """

    def __init__(self, settings: TrackerSettings | None = None) -> None:
        self.settings = settings or TrackerSettings()
        self._next_id = 0
        self.reset()

    def reset(self) -> None:
        """Drop every track (ids keep increasing, so an old id never names a new point)."""
        self._gray: np.ndarray | None = None
        self._ids = np.zeros(0, dtype=np.int64)
        self._points = np.zeros((0, 2), dtype=np.float32)  # work pixels in the last frame
        self._scale = (1.0, 1.0)

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def ids(self) -> np.ndarray:
        """The ids of the live tracks (a read-only view)."""
        view = self._ids.view()
        view.flags.writeable = False
        return view

    @property
    def gray(self) -> np.ndarray | None:
        """The last frame's grey image at the work size (None before the first frame)."""
        return self._gray

    @property
    def work_scale(self) -> tuple[float, float]:
        """Native pixels per work pixel, along x and y."""
        return self._scale

    def _work_gray(self, image: np.ndarray) -> np.ndarray:
        gray = gray_image(image)
        height, width = gray.shape
        if width >= SHRINK_FROM * self.settings.work_width:
            work_height = max(1, round(height * self.settings.work_width / width))
            gray = cv2.resize(gray, (self.settings.work_width, work_height), interpolation=cv2.INTER_AREA)
        elif width < self.settings.min_work_width:
            factor = -(-self.settings.min_work_width // width)
            gray = cv2.resize(gray, (width * factor, height * factor), interpolation=cv2.INTER_LINEAR)
        self._scale = (width / gray.shape[1], height / gray.shape[0])
        return gray

    def to_native(self, pixels: np.ndarray) -> np.ndarray:
        """Work-image pixels -> native pixels (:func:`native_pixels` at this stream's size)."""
        return native_pixels(pixels, self._scale)

    def to_work(self, pixels: np.ndarray) -> np.ndarray:
        return work_pixels(pixels, self._scale)

    def current(self) -> TrackedFrame:
        return TrackedFrame(self._ids.copy(), self.to_native(self._points))

    def track(self, image: np.ndarray, predicted: dict[int, np.ndarray] | None = None) -> TrackedFrame:
        """Follow the tracks into ``image``; returns the tracks that survived, in native pixels.

        ``predicted``: native pixel positions expected for some track ids (from a motion guess); they seed
        Lucas-Kanade, which matters when the image moves by more than its pyramid reaches.
        """
        gray = self._work_gray(image)
        previous, self._gray = self._gray, gray
        if previous is None or previous.shape != gray.shape or len(self._ids) == 0:
            self._ids = np.zeros(0, dtype=np.int64)
            self._points = np.zeros((0, 2), dtype=np.float32)
            return self.current()
        guess = None
        if predicted:
            guess = self._points.astype(np.float64).copy()
            rows = [row for row, track_id in enumerate(self._ids.tolist()) if track_id in predicted]
            if rows:
                guess[rows] = self.to_work(np.array([predicted[int(self._ids[row])] for row in rows]))
        _, moved, kept = track_corners(previous, gray, self._points, guess, self.settings.window,
                                       self.settings.lk_iterations, forward_backward_px(self._scale))
        self._ids = self._ids[kept]
        self._points = moved.astype(np.float32)
        return self.current()

    def drop(self, ids: np.ndarray) -> None:
        """Forget these tracks (outliers: a mismatch never comes back right)."""
        keep = ~np.isin(self._ids, ids)
        self._ids, self._points = self._ids[keep], self._points[keep]

    def top_up(self, image: np.ndarray | None = None) -> int:
        """Detect new corners in the grid cells short of tracks; returns how many were added.

        Uses the last tracked frame (``image`` is only needed when none was tracked yet).
        """
        if image is not None and self._gray is None:
            self._gray = self._work_gray(image)
        gray = self._gray
        if gray is None:
            return 0
        settings = self.settings
        wanted = settings.max_tracks - len(self._ids)
        if wanted <= 0:
            return 0
        height, width = gray.shape
        columns, rows = settings.grid
        per_cell = max(1, int(np.ceil(settings.max_tracks / (columns * rows))))
        min_distance = max(3, width // 40)
        # Existing tracks block their neighbourhood, so a corner is never tracked twice.
        mask = np.full((height, width), 255, dtype=np.uint8)
        for x, y in np.rint(self._points).astype(np.int64).tolist():
            cv2.circle(mask, (x, y), min_distance, 0, -1)
        cell_w, cell_h = width / columns, height / rows
        counts = np.zeros((rows, columns), dtype=np.int64)
        if len(self._points):
            cells_x = np.clip((self._points[:, 0] / cell_w).astype(int), 0, columns - 1)
            cells_y = np.clip((self._points[:, 1] / cell_h).astype(int), 0, rows - 1)
            np.add.at(counts, (cells_y, cells_x), 1)
        new_points = []
        for row in range(rows):
            for column in range(columns):
                room = per_cell - counts[row, column]
                if room <= 0:
                    continue
                x0, x1 = int(round(column * cell_w)), int(round((column + 1) * cell_w))
                y0, y1 = int(round(row * cell_h)), int(round((row + 1) * cell_h))
                corners = detect_corners(gray[y0:y1, x0:x1], room, mask[y0:y1, x0:x1], min_distance)
                if corners is not None:
                    new_points.append(corners.reshape(-1, 2) + np.array([x0, y0], dtype=np.float32))
        if not new_points:
            return 0
        points = np.concatenate(new_points)[:wanted]
        ids = np.arange(self._next_id, self._next_id + len(points), dtype=np.int64)
        self._next_id += len(points)
        self._ids = np.concatenate((self._ids, ids))
        self._points = np.concatenate((self._points, points.astype(np.float32)))
        return len(points)


# --------------------------------------------------------------------------------------------------
# PnP on rays
# --------------------------------------------------------------------------------------------------


@dataclass
class PnPResult:
    """A camera pose from 3D-2D matches: ``T_w_c`` ``(4, 4)``, the inlier mask, and the pose's covariance.

    ``covariance``: ``(6, 6)`` for a right perturbation ``T_w_c Exp(xi)``, ``xi = (rho, theta)``, from the
    inliers' reprojection Jacobian with the given noise (the information of a motion-only bundle adjustment).
    """

    T_w_c: np.ndarray
    inliers: np.ndarray
    covariance: np.ndarray | None


def _pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """OpenCV's ``X_c = R X_w + t`` -> ``T_w_c``."""
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ tvec.ravel()
    return T


def _opencv_pose(T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R = T_w_c[:3, :3].T
    t = -R @ T_w_c[:3, 3]
    rvec, _ = cv2.Rodrigues(R)
    return rvec, t.reshape(3, 1)


def reprojection_errors(T_w_c: np.ndarray, points_w: np.ndarray, normalised: np.ndarray) -> np.ndarray:
    """Distances ``(N,)`` between normalised points and the projections of ``points_w`` (inf behind the camera)."""
    points_c = (points_w - T_w_c[:3, 3]) @ T_w_c[:3, :3]
    z = points_c[:, 2]
    safe = np.where(z > 1e-9, z, 1.0)
    errors = np.linalg.norm(points_c[:, :2] / safe[:, None] - normalised, axis=1)
    return np.where(z > 1e-9, errors, np.inf)


def _pose_jacobians(T_w_c: np.ndarray, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normalised projections ``(N, 2)`` of ``points_w`` in ``T_w_c`` and their Jacobians ``(N, 2, 6)``
    for a right perturbation ``T_w_c Exp(xi)``, ``xi = (rho, theta)``."""
    points_c = (points_w - T_w_c[:3, 3]) @ T_w_c[:3, :3]
    inv_z = 1.0 / points_c[:, 2]
    u, v = points_c[:, 0] * inv_z, points_c[:, 1] * inv_z  # the normalised point
    # Each residual's row: the pinhole projection's Jacobian times d(points_c)/d(xi) = [-I | [points_c]x],
    # multiplied out (two einsums over (N, 2, 3) x (N, 3, 6) cost 0.5 ms a frame).
    J = np.zeros((len(inv_z), 2, 6))
    J[:, 0, 0], J[:, 0, 2] = -inv_z, u * inv_z
    J[:, 1, 1], J[:, 1, 2] = -inv_z, v * inv_z
    J[:, 0, 3], J[:, 0, 4], J[:, 0, 5] = u * v, -1.0 - u * u, v
    J[:, 1, 3], J[:, 1, 4], J[:, 1, 5] = 1.0 + v * v, -u * v, -u
    return np.column_stack((u, v)), J


def pose_covariance(T_w_c: np.ndarray, points_w: np.ndarray, sigma: float,
                    whitening: np.ndarray | None = None) -> np.ndarray:
    """``(6, 6)`` covariance of ``T_w_c`` (right perturbation, ``(rho, theta)``) from normalised-point noise ``sigma``.

    The Gauss-Newton information ``J^T J / sigma^2`` of the reprojection residuals at the solution.

    With ``whitening`` ``(N, 2, 2)`` (:func:`ray_whitening`), ``sigma`` is image noise in pixels over
    ``fx`` and each point's normalised noise its own, ``sigma^2 W^-1 W^-T``: the covariance of the
    unweighted least-squares pose is then the sandwich ``A^-1 B A^-1``, ``A = sum J^T J``,
    ``B = sum J^T sigma^2 W^-1 W^-T J`` (equal to the plain form where every ``W`` is the identity).
    """
    return _covariance_of(_pose_jacobians(T_w_c, points_w)[1], sigma, whitening)


def _covariance_of(J: np.ndarray, sigma: float, whitening: np.ndarray | None) -> np.ndarray:
    """:func:`pose_covariance` from the residuals' Jacobians ``J`` ``(N, 2, 6)``."""
    stacked = J.reshape(-1, 6)
    if whitening is None:
        return np.linalg.pinv(stacked.T @ stacked / sigma**2)
    # W^-1, how far one unit of image noise moves each normalised point, as the closed 2x2 inverse
    # (a fifth of np.linalg.inv's time on 300 points).
    a, b, c, d = whitening[:, 0, 0], whitening[:, 0, 1], whitening[:, 1, 0], whitening[:, 1, 1]
    spread = np.stack((np.stack((d, -b), -1), np.stack((-c, a), -1)), -2) / (a * d - b * c)[:, None, None]
    noise_rows = np.matmul(np.swapaxes(J, 1, 2), spread).transpose(1, 0, 2).reshape(6, -1)  # J^T W^-1
    A_inv = np.linalg.pinv(stacked.T @ stacked)
    return A_inv @ (sigma**2 * noise_rows @ noise_rows.T) @ A_inv


def solve_pnp(points_w: np.ndarray, normalised: np.ndarray, threshold: float, *,
              guess: np.ndarray | None = None, min_inliers: int = 12, seed: int = 0,
              covariance: bool = True, whitening: np.ndarray | None = None, robust: bool = False) -> PnPResult | None:
    """Pose a camera from landmarks ``points_w`` ``(N, 3)`` and their rays as undistorted normalised points ``(N, 2)``.

    RANSAC over minimal sets (OpenCV's P3P family with ``K = I``, so the threshold is in normalised units:
    ``pixels / f``), then Levenberg-Marquardt on the inliers. ``guess`` (``T_w_c``) is kept when RANSAC's
    best hypothesis explains fewer points than it does. Returns None with fewer than ``min_inliers``.
    ``covariance=False`` leaves :attr:`PnPResult.covariance` None (for callers that only want the pose).

    ``whitening`` ``(N, 2, 2)`` (:func:`ray_whitening`): each point's normalised residual turned into image
    noise, for the covariance alone. A lens that stretches pixels unevenly (a fisheye's edge moves six
    times as far in ``x/z`` per pixel as its centre) gives each point its own noise in the rays PnP
    fits; the pose's covariance is then :func:`pose_covariance`'s sandwich, with the noise measured
    on the whitened residuals. The pose itself weighs every ray alike: weighing them by their noise
    (the edge's rays more) published a worse camera and final trajectory on the fisheye and on
    heldout_160 (docs/RESULTS.md).

    ``robust``: the least-squares pose then refined with a Cauchy loss (:func:`robust_pose_refinement`;
    ``whitening`` sets its weights), so that an inlier far out in the noise does not hold the pose. The
    inliers stay the least-squares pose's, and the covariance is evaluated at the refined pose.
    """
    points_w = np.ascontiguousarray(points_w, dtype=np.float64).reshape(-1, 3)
    normalised = np.ascontiguousarray(normalised, dtype=np.float64).reshape(-1, 2)
    finite = np.isfinite(points_w).all(1) & np.isfinite(normalised).all(1)
    if finite.sum() < max(min_inliers, 4):
        return None
    index = np.flatnonzero(finite)
    object_points, image_points = points_w[index], normalised[index]
    K = np.eye(3)
    cv2.setRNGSeed(seed)  # OpenCV's RANSAC draws from a global generator: a replay must repeat exactly
    ok, rvec, tvec, ransac_inliers = cv2.solvePnPRansac(
        object_points, image_points, K, None, iterationsCount=100, reprojectionError=threshold,
        confidence=0.999, flags=cv2.SOLVEPNP_AP3P,
    )
    best = None
    if ok and ransac_inliers is not None and len(ransac_inliers) >= 4:
        best = _pose_matrix(rvec, tvec)
    if guess is not None:
        guess_inliers = reprojection_errors(guess, object_points, image_points) < threshold
        if best is None or guess_inliers.sum() > (reprojection_errors(best, object_points, image_points) < threshold).sum():
            best = np.asarray(guess, dtype=np.float64)
    if best is None:
        return None
    # Levenberg-Marquardt on the inliers, twice: the second pass sees the inliers of the refined pose.
    for _ in range(2):
        inliers = reprojection_errors(best, object_points, image_points) < threshold
        if inliers.sum() < max(min_inliers, 4):
            return None
        rvec, tvec = _opencv_pose(best)
        rvec, tvec = cv2.solvePnPRefineLM(object_points[inliers], image_points[inliers], K, None, rvec, tvec)
        best = _pose_matrix(rvec, tvec)
    errors = reprojection_errors(best, object_points, image_points)
    inliers = errors < threshold
    if inliers.sum() < min_inliers:
        return None
    weights = None if whitening is None else np.asarray(whitening, dtype=np.float64).reshape(-1, 2, 2)[index[inliers]]
    if weights is not None and not _usable_whitening(weights):
        weights = None  # a ray at a lens's fold has no noise model: every point alike, as without one
    if robust:
        # The inliers stay the least-squares fit's: the points the robust pose moves past the threshold
        # are the ones it weighs least, and classed as outliers here they would leave the tracker for good.
        best = robust_pose_refinement(best, object_points[inliers], image_points[inliers], weights,
                                      ROBUST_MIN_NOISE_SHARE * threshold)
    mask = np.zeros(len(points_w), dtype=bool)
    mask[index[inliers]] = True
    if not covariance:
        return PnPResult(best, mask, None)
    projected, J = _pose_jacobians(best, object_points[inliers])
    residuals = projected - image_points[inliers]
    if weights is not None:  # the residuals as image noise
        residuals = np.einsum("nij,nj->ni", weights, residuals)
    # Noise from the inliers' own spread (at least a tenth of the threshold: a perfect fit is not certainty).
    sigma = max(float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))), 0.1 * threshold)
    return PnPResult(best, mask, _covariance_of(J, sigma, weights))


def _usable_whitening(whitening: np.ndarray) -> bool:
    determinants = whitening[:, 0, 0] * whitening[:, 1, 1] - whitening[:, 0, 1] * whitening[:, 1, 0]
    return bool(np.isfinite(whitening).all() and (np.abs(determinants) > 1e-12).all())


def robust_pose_refinement(T_w_c: np.ndarray, points_w: np.ndarray, normalised: np.ndarray,
                           whitening: np.ndarray | None = None, min_noise: float = 0.0,
                           iterations: int = ROBUST_ITERATIONS) -> np.ndarray:
    """``T_w_c`` refined by iteratively reweighted least squares with a Cauchy loss on the residuals.

    Every point within the inlier threshold counts fully in a least-squares fit, and a few of them can
    hold the pose: on a 160x120 camera one landmark near the camera with a 1.2 px residual (the
    threshold 1.5 px, the others' RMS 0.25 px) turned the pose 0.45 deg, which it lost the next frame
    when that track left the inliers (measured on a rendered replay). The Cauchy weight
    ``1 / (1 + (e / c)^2)``, with ``c`` :data:`CAUCHY_SCALE` times the start's residuals' robust
    standard deviation per axis (their median length over 1.1774, a Rayleigh's), takes such points most
    of the way out while the bulk keeps its weight. The correction is small (a least-squares fit on
    inliers is the start), so the residuals are linearised once at the start and each reweighting is a
    6x6 solve: the same pose to 1e-4 deg as re-projecting at every step, at a fraction of its cost.

    Args:
        T_w_c: ``(4, 4)`` starting pose (a least-squares fit on the inliers).
        points_w: ``(N, 3)`` landmarks; ``normalised``: ``(N, 2)`` their undistorted normalised rays.
        whitening: ``(N, 2, 2)`` (:func:`ray_whitening`), so that the loss weighs each residual as image
            noise; None: as normalised.
        min_noise: floor of the robust standard deviation (normalised units), so that a near-perfect
            fit does not turn every small residual into an outlier.
        iterations: reweightings at most; they stop once none moves a projection by more than
            :data:`CONVERGED_SHIFT` of the noise.
    Returns the refined ``(4, 4)`` pose (the start where fewer than 6 points or a singular system).
    """
    if len(points_w) < 6:
        return T_w_c
    if whitening is not None and not _usable_whitening(whitening):
        whitening = None
    T_w_c = np.asarray(T_w_c, dtype=np.float64)
    projected, J = _pose_jacobians(T_w_c, points_w)
    residuals = projected - normalised
    # The weights see each residual as image noise; the fit itself stays in normalised units, as the
    # least-squares start's does.
    seen, J_seen = residuals, J
    if whitening is not None:
        seen = (whitening @ residuals[:, :, None])[:, :, 0]
        J_seen = whitening @ J
    noise = max(float(np.median(np.sqrt(np.einsum("ni,ni->n", seen, seen)))) / RAYLEIGH_MEDIAN, min_noise)
    rows, flat = J.reshape(-1, 6), residuals.reshape(-1)
    xi, shifted = np.zeros(6), np.zeros_like(seen)
    for _ in range(iterations):
        moved = seen + shifted
        weights = 1.0 / (1.0 + np.einsum("ni,ni->n", moved, moved) / (CAUCHY_SCALE * noise) ** 2)
        weighted = rows * np.repeat(weights, 2)[:, None]
        try:
            xi_new = -np.linalg.solve(weighted.T @ rows, weighted.T @ flat)
        except np.linalg.LinAlgError:
            return T_w_c
        if not np.isfinite(xi_new).all():
            return T_w_c
        shifted_new = J_seen @ xi_new
        converged = float(np.abs(shifted_new - shifted).max()) < CONVERGED_SHIFT * noise
        xi, shifted = xi_new, shifted_new
        if converged:
            break
    return T_w_c @ make_transform(so3_exp(xi[3:]), xi[:3])


def ray_whitening(calibration: CameraCalibration, undistorted: np.ndarray) -> np.ndarray | None:
    """``(N, 2, 2)`` whitening of the rays ``undistorted`` (normalised) for :func:`solve_pnp`.

    How many pixels a move of each ray makes (``CameraCalibration.pixel_jacobians``), over ``fx``: the
    identity at an undistorted pinhole's centre, so thresholds stay ``pixels / fx``. None where the lens
    model has no analytic Jacobian (PnP then weighs every point alike).
    """
    jacobians = calibration.pixel_jacobians(undistorted)
    return None if jacobians is None else jacobians / calibration.fx
