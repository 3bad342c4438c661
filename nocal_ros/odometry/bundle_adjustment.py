"""Windowed bundle adjustment over keyframe poses, landmarks AND the camera: robust Levenberg-Marquardt on
the Schur complement, in numpy and scipy.

The VO's backend worker calls :func:`bundle_adjust` on each new keyframe with the last N keyframes,
their landmarks and the current camera. The camera is a parametric
:class:`~nocal_ros.lens.CameraCalibration` (the learnt ``CameraModel`` is converted to it by
``CameraModel.to_calibration``, which reports the fit's residual), projected by the same function as
everywhere else, ``lens.distort_normalised``, with its derivatives ``lens.distortion_jacobians``:

* ``plumb_bob`` with ``k3 = 0`` (fx fy cx cy k1 k2 p1 p2), exactly OpenCV's ``cv2.projectPoints`` with
  ``(k1, k2, p1, p2, 0)``;
* ``equidistant`` (fx fy cx cy k1..k4), exactly ``cv2.fisheye.projectPoints`` for points in front of the
  camera.

``solver_project`` (the solver's measurement model) agrees with OpenCV to below 1e-9 px and its
Jacobians with finite differences (``test/test_bundle_adjustment.py``).

The solver: each iteration linearises every observation (analytic Jacobians, vectorised), reweights
it by its robust loss, eliminates the landmarks (3x3 blocks) and solves the reduced system over the
free poses and camera parameters by Cholesky, with Ceres' Levenberg-Marquardt damping; the landmarks
follow by back-substitution. Why this and not a library (measured; BENCHMARKS.md, "Windowed bundle
adjustment"; ``scripts/compare/bundle_adjustment_solvers.py``): the camera's information must carry
over from window to window as a prior with a full information matrix (the online
self-calibration), and its marginal covariance must come back. GTSAM 4.3 does both and was the
solver until 2026-12-02. On the 174 problems of two replays (the demo camera's, VAMR's) this one takes
the same number of iterations on 172, ends within 4.5 mm and a relative focal difference of 7e-5 of
GTSAM's where both converged, and needs half the CPU time per window (median 89 against 177 ms and
105 against 212 ms; covariance 9-10 against 25-28 ms); the initialisations' and whole maps' solves
took 10.0 against 13.9 s in all. pycolmap's bundle adjuster (Ceres) was 2.2-4.5x
faster than GTSAM but can only fix or free the intrinsics, never weigh them against a prior; scipy's
``least_squares`` did not converge in 20 evaluations; GTSAM's iSAM2 failed from cold starts.

Conventions:

* Poses are ``T_w_c`` (camera to world), optical frame, 4x4 float64, perturbed on the right:
  ``R Exp(omega)``, ``t + R v``; the solver's pose tangent is ``(omega, v)``, and pose covariances are
  returned reordered to ``(rho, theta)`` (translation first), as in :mod:`nocal_ros.odometry.covariance`.
* Camera parameters: ``camera_parameters`` below; the covariance is over that vector, zero in the
  rows and columns of parameters the problem's ``camera`` mode does not free.
* Pixels are native, distorted, with pixel centres at integer coordinates (OpenCV's convention).
* The gauge: at least two keyframes are held fixed (monocular gauge and scale), or one and the
  distance between two (``scale_pair``, within 1e-4 of it), which leaves their relative rotation
  free; or three or more measured ``positions``. Fixed poses and pinned camera parameters are not
  variables: they do not move, and their covariances are returned as zeros.

Robustness: each observation has a Cauchy loss with scale ``robust_threshold_px`` (``robust_loss``
selects Huber instead). With 0.5 px noise and 5 % outliers of 10-40 px, Huber's linear influence
lets the outliers bias the camera. On the benchmark's windows (BENCHMARKS.md) Cauchy at 2 px gave
0.64 % focal, 3.6 px principal point, 0.107 deg and 53 mm landmarks against Huber's 0.70 %, 6.1 px,
0.149 deg and 89 mm. On 12 of the tests' smaller windows per lens (cold start 15 % off), the median
focal error was 0.50 % (plumb_bob) and 1.5 % (fisheye) against Huber's 1.7 % and 3.0 %, and the
errors were 1.0 and 1.5 reported standard deviations (rms over windows) against Huber's 2.1 and 1.9:
with Cauchy the covariance describes the error (measured with GTSAM; the tests hold this solver to
the same bounds).
For the covariances, landmarks carry a weak prior (sigma 100 times the median camera-landmark
distance) so that a track of nearly parallel rays leaves the system determinate without informing
anything else (without it 3 of 12 plumb_bob and 2 of 12 fisheye test windows failed on one such
landmark).

Bad input (NaN, wrong shapes, an index out of range, fewer than two fixed poses without a ``scale_pair``
or three measured ``positions``, a camera model or ``k3`` the solver cannot represent, a free keyframe
without observations) raises :class:`BundleAdjustmentInputError` naming the field. A failure inside
the solver does NOT raise: the solution carries the start values, ``success = False`` and a message,
so the worker can drop that window and carry on. Levenberg-Marquardt absorbs a singular step by
raising its damping, so an indeterminate system shows where the covariance is computed (the reduced
system's scaled eigenvalues): whenever a covariance is asked for. Without one (``camera="fixed"`` or
``camera_covariance=False``, and no ``covariance_of``) an indeterminate direction (a keyframe seeing
two landmarks) is not detected. Observations whose landmark starts behind its keyframe are left out
of the solve and come back as non-inliers; a landmark that crosses behind a camera during the solve
contributes no residual there (as GTSAM's factor did).
"""

from __future__ import annotations

import contextlib
import importlib
import time
from dataclasses import dataclass, field

import numpy as np

from nocal_ros.errors import NocalError
from nocal_ros.geometry import so3_exp
from nocal_ros.lens import CameraCalibration, distort_normalised, distortion_jacobians

#: Which camera parameters each ``WindowProblem.camera`` mode frees (indices into camera_parameters).
CAMERA_MODES = {
    "fixed": (),
    "focal": (0, 1),
    "intrinsics": (0, 1, 2, 3),
    "radial": (0, 1, 2, 3, 4, 5),  # plumb_bob without p1, p2 (equidistant: k1, k2)
    "full": tuple(range(8)),
}
SUPPORTED_MODELS = ("plumb_bob", "equidistant")
ROBUST_LOSSES = ("huber", "cauchy")

# Levenberg-Marquardt as Ceres runs it: the damping's start, bounds and the clamp of the diagonal it
# scales, and the share of the linear model's predicted decrease a step must achieve to be taken.
_LAMBDA_INITIAL, _LAMBDA_MIN, _LAMBDA_MAX = 1e-4, 1e-16, 1e32
_MIN_DIAGONAL, _MAX_DIAGONAL = 1e-6, 1e32
_MIN_MODEL_FIDELITY = 1e-3
# The smallest eigenvalue of the diagonally scaled reduced system below which it is indeterminate.
_INDETERMINATE = 1e-12
_LANDMARK_PRIOR_SCALE = 100.0
# Relative sigma of the distance a scale_pair holds: far below what one window can tell about its scale
# (tighter ones made GTSAM's covariance indeterminate beside its 1e-8 pose priors, measured).
_SCALE_SIGMA = 1e-4


class BundleAdjustmentError(NocalError):
    """The bundle adjustment cannot run on what it was given."""


class BundleAdjustmentInputError(BundleAdjustmentError):
    """A ``WindowProblem`` field is malformed (shape, NaN, index, gauge, camera model)."""


def camera_parameters(calibration: CameraCalibration) -> np.ndarray:
    """The optimised camera vector ``(P,) = (8,)``.

    ``plumb_bob``: ``(fx, fy, cx, cy, k1, k2, p1, p2)`` (``k3`` must be 0); ``equidistant``:
    ``(fx, fy, cx, cy, k1, k2, k3, k4)``. Raises :class:`BundleAdjustmentInputError` for other
    models, a non-zero ``k3`` or a skewed camera matrix.
    """
    model = calibration.distortion_model
    if model not in SUPPORTED_MODELS:
        raise BundleAdjustmentInputError(
            f"bundle adjustment supports the {' and '.join(SUPPORTED_MODELS)} camera models, got {model!r}"
        )
    if calibration.K[0, 1] != 0.0:
        raise BundleAdjustmentInputError(f"bundle adjustment needs a camera matrix without skew, got K[0, 1] = {calibration.K[0, 1]}")
    if model == "plumb_bob" and calibration.D[4] != 0.0:
        raise BundleAdjustmentInputError(
            f"bundle adjustment's plumb_bob camera has k3 = 0, got k3 = {calibration.D[4]}"
        )
    return np.concatenate([[calibration.fx, calibration.fy, calibration.cx, calibration.cy], calibration.D[:4]])


def calibration_from_parameters(parameters: np.ndarray, like: CameraCalibration) -> CameraCalibration:
    """The camera with ``parameters`` (see :func:`camera_parameters`) and ``like``'s size, model and name."""
    parameters = np.asarray(parameters, dtype=np.float64).reshape(-1)
    if parameters.shape != (8,) or not np.all(np.isfinite(parameters)):
        raise BundleAdjustmentInputError(f"camera parameters must be 8 finite numbers, got {parameters.tolist()}")
    D = np.zeros_like(like.D)
    D[:4] = parameters[4:]
    fx, fy, cx, cy = parameters[:4]
    return CameraCalibration(like.width, like.height, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), D,
                             like.distortion_model, like.camera_name)


@dataclass
class CameraPrior:
    """A Gaussian prior on the camera: the mean and its information over ``camera_parameters``."""

    calibration: CameraCalibration
    information: np.ndarray  # (P, P), P = 8, symmetric positive semi-definite


@dataclass
class WindowProblem:
    calibration: CameraCalibration  # start value (plumb_bob with k3 = 0, or equidistant)
    poses: np.ndarray  # (K, 4, 4) T_w_c start values of the window's keyframes
    fixed: np.ndarray  # (K,) bool: poses held fixed (>= 2: the monocular gauge and scale)
    points: np.ndarray  # (L, 3) landmark start values, world frame
    keyframe_index: np.ndarray  # (M,) int, observation -> keyframe row
    point_index: np.ndarray  # (M,) int, observation -> landmark row
    pixels: np.ndarray  # (M, 2) observed native pixels (distorted, as in the image)
    camera: str = "full"  # free camera parameters: "fixed" | "focal" | "intrinsics" | "full"
    camera_prior: CameraPrior | None = None
    pixel_sigma: float = 1.0
    robust_threshold_px: float = 2.0  # scale of the robust loss
    max_iterations: int = 20
    covariance_of: tuple[int, ...] = ()  # keyframe rows whose marginal pose covariance is wanted
    relative_tolerance: float = 1e-5  # stop when the cost falls by less than this fraction
    robust_loss: str = "cauchy"  # "cauchy" | "huber" (measured: module notes)
    camera_covariance: bool = True  # False: skip the camera's marginal (saves its cost, BENCHMARKS.md)
    scale_pair: tuple[int, int] | None = None  # keyframe rows whose distance is held: with one fixed pose, the gauge
    # Measured camera positions (an arm's): (keyframe rows (P,), positions (P, 3)) in the poses' frame and
    # unit, each held within position_sigma; three or more not on one line fix the gauge and the scale.
    positions: tuple[np.ndarray, np.ndarray] | None = None
    position_sigma: float = 0.002


@dataclass
class WindowSolution:
    poses: np.ndarray  # (K, 4, 4)
    points: np.ndarray  # (L, 3)
    calibration: CameraCalibration
    camera_covariance: np.ndarray | None  # (P, P) over camera_parameters, zeros for fixed ones; None when camera == "fixed" (or not asked for)
    pose_covariances: dict[int, np.ndarray]  # row -> (6, 6), right perturbation, (rho, theta); zeros for fixed rows
    inliers: np.ndarray  # (M,) bool: in front of its camera, reprojection error below robust_threshold_px
    initial_rms_px: float  # over the final inliers, at the start values
    final_rms_px: float  # over the final inliers
    iterations: int
    seconds: float
    success: bool = True  # False: the solver failed; poses, points and camera are the start values
    message: str = ""
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) final reprojection error, inf behind
    covariance_cpu_seconds: float = 0.0  # CPU time of the calling thread in the covariance (part of seconds)


def _validate(problem: WindowProblem) -> tuple[np.ndarray, ...]:
    def fail(text: str) -> BundleAdjustmentInputError:
        return BundleAdjustmentInputError(f"bundle adjustment: {text}")

    if not isinstance(problem.calibration, CameraCalibration):
        raise fail(f"calibration must be a CameraCalibration, got {type(problem.calibration).__name__}")
    start = camera_parameters(problem.calibration)
    poses = np.asarray(problem.poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise fail(f"poses must be (K, 4, 4), got shape {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise fail("poses hold non-finite values")
    rotation_error = np.abs(np.einsum("kji,kjl->kil", poses[:, :3, :3], poses[:, :3, :3]) - np.eye(3)).max()
    if rotation_error > 1e-6 or np.abs(poses[:, 3] - [0, 0, 0, 1]).max() > 0:
        raise fail(f"poses must be rigid transforms (rotation off by {rotation_error:.1e})")
    fixed = np.asarray(problem.fixed)
    if fixed.shape != (len(poses),) or fixed.dtype != bool:
        raise fail(f"fixed must be a ({len(poses)},) bool array, got {fixed.dtype} {fixed.shape}")
    if problem.scale_pair is not None:
        i, j = (int(r) for r in problem.scale_pair)
        if not (0 <= i < len(poses) and 0 <= j < len(poses)) or i == j:
            raise fail(f"scale_pair must name two keyframe rows in 0..{len(poses) - 1}, got {problem.scale_pair}")
        if np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3]) <= 0:
            raise fail("scale_pair names two keyframes at one position: no scale to hold")
    position_rows = np.zeros(0, dtype=np.int64)
    if problem.positions is not None:
        position_rows = np.asarray(problem.positions[0])
        measured = np.asarray(problem.positions[1], dtype=np.float64)
        if (position_rows.ndim != 1 or measured.shape != (len(position_rows), 3) or len(position_rows) == 0
                or position_rows.dtype.kind not in "iu"):
            raise fail(f"positions must be (rows (P,) ints, (P, 3)), got {position_rows.shape} and {measured.shape}")
        if position_rows.min() < 0 or position_rows.max() >= len(poses) or not np.isfinite(measured).all():
            raise fail(f"positions must name keyframe rows in 0..{len(poses) - 1} with finite values")
        if not problem.position_sigma > 0:
            raise fail(f"position_sigma must be positive, got {problem.position_sigma}")
    # Three or more measured positions fix the gauge and the scale; otherwise fixed poses must.
    if len(np.unique(position_rows)) < 3 and fixed.sum() < (1 if problem.scale_pair is not None else 2):
        raise fail("a monocular window needs two fixed poses, or one and a scale_pair (gauge and scale), "
                   f"got {int(fixed.sum())}")
    points = np.asarray(problem.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise fail(f"points must be (L, 3), got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise fail("points hold non-finite values")
    pixels = np.asarray(problem.pixels, dtype=np.float64)
    if pixels.ndim != 2 or pixels.shape[1] != 2 or len(pixels) == 0:
        raise fail(f"pixels must be (M, 2) with M >= 1, got shape {pixels.shape}")
    if not np.all(np.isfinite(pixels)):
        raise fail(f"pixels hold {int((~np.isfinite(pixels)).any(1).sum())} non-finite observations")
    indices = []
    for name, count in (("keyframe_index", len(poses)), ("point_index", len(points))):
        index = np.asarray(getattr(problem, name))
        if index.shape != (len(pixels),) or not np.issubdtype(index.dtype, np.integer):
            raise fail(f"{name} must be ({len(pixels)},) integers, got {index.dtype} {index.shape}")
        if len(index) and (index.min() < 0 or index.max() >= count):
            raise fail(f"{name} runs from {index.min()} to {index.max()}, outside 0..{count - 1}")
        indices.append(index.astype(np.int64))
    unobserved = np.setdiff1d(np.flatnonzero(~fixed), indices[0])
    if len(unobserved):
        raise fail(f"free keyframe row(s) {unobserved.tolist()} have no observations")
    if problem.camera not in CAMERA_MODES:
        raise fail(f"camera must be one of {', '.join(CAMERA_MODES)}, got {problem.camera!r}")
    for name in ("pixel_sigma", "robust_threshold_px", "relative_tolerance"):
        value = getattr(problem, name)
        if not np.isfinite(value) or value <= 0:
            raise fail(f"{name} must be a positive number, got {value}")
    if problem.robust_loss not in ROBUST_LOSSES:
        raise fail(f"robust_loss must be one of {', '.join(ROBUST_LOSSES)}, got {problem.robust_loss!r}")
    if int(problem.max_iterations) < 1:
        raise fail(f"max_iterations must be >= 1, got {problem.max_iterations}")
    for row in problem.covariance_of:
        if not 0 <= int(row) < len(poses):
            raise fail(f"covariance_of names keyframe row {row}, outside 0..{len(poses) - 1}")
    if problem.camera_prior is not None:
        prior = problem.camera_prior
        if prior.calibration.distortion_model != problem.calibration.distortion_model:
            raise fail(f"the camera prior is {prior.calibration.distortion_model}, the camera "
                       f"{problem.calibration.distortion_model}")
        camera_parameters(prior.calibration)
        information = np.asarray(prior.information, dtype=np.float64)
        if information.shape != (8, 8) or not np.all(np.isfinite(information)):
            raise fail(f"the camera prior's information must be a finite (8, 8) matrix, got shape {information.shape}")
        if not np.allclose(information, information.T, rtol=1e-9, atol=1e-12 * np.abs(information).max()):
            raise fail("the camera prior's information is not symmetric")
        if np.linalg.eigvalsh(information).min() < -1e-9 * max(np.abs(information).max(), 1e-300):
            raise fail("the camera prior's information is not positive semi-definite")
    return start, poses, fixed, points, indices[0], indices[1], pixels


def solver_project(calibration: CameraCalibration, T_w_c: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` of world points as the solver projects them (its own measurement model).

    For checking the solver against ``CameraCalibration.project`` and OpenCV. NaN for points not in
    front of the camera (the solver gives them no residual).
    """
    T_w_c = np.asarray(T_w_c, dtype=np.float64)
    points_w = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    count = len(points_w)
    rotations = np.broadcast_to(T_w_c[:3, :3], (count, 3, 3))
    translations = np.broadcast_to(T_w_c[:3, 3], (count, 3))
    pixels, _, front = _project(camera_parameters(calibration), calibration.distortion_model,
                                rotations, translations, points_w)
    pixels[~front] = np.nan
    return pixels


def _distortion_vector(parameters: np.ndarray, model: str) -> np.ndarray:
    """The lens coefficients in ``lens.distort_normalised``'s order (plumb_bob gets its k3 = 0)."""
    return parameters[4:].copy() if model == "equidistant" else np.concatenate([parameters[4:], [0.0]])


def _project(parameters: np.ndarray, model: str, rotations: np.ndarray, translations: np.ndarray,
             points_w: np.ndarray, jacobians: bool = False):
    """Pixels ``(M, 2)`` of world points seen from cameras ``(R, t)`` (``T_w_c``), through
    ``lens.distort_normalised`` (the camera model's one definition).

    Returns ``(pixels, jacobians, front)``. With ``jacobians``: ``d pixel / d (omega, v)`` ``(M, 2, 6)``
    for the right perturbation ``R Exp(omega)``, ``t + R v``; ``d pixel / d point`` ``(M, 2, 3)``;
    ``d pixel / d camera_parameters`` ``(M, 2, 8)``. Points not in front (``front`` False) get
    zero pixels and zero Jacobians.
    """
    rotations_t = rotations.transpose(0, 2, 1)
    points_c = np.matmul(rotations_t, (points_w - translations)[:, :, None])[:, :, 0]
    z = points_c[:, 2]
    front = z > 1e-9
    inverse_z = np.where(front, 1.0 / np.where(front, z, 1.0), 0.0)
    normalised = points_c[:, :2] * inverse_z[:, None]
    D = _distortion_vector(parameters, model)
    distorted = distort_normalised(normalised, D, model)
    fx, fy, cx, cy = parameters[:4]
    pixels = np.stack((fx * distorted[:, 0] + cx, fy * distorted[:, 1] + cy), -1)
    pixels[~front] = 0.0
    if not jacobians:
        return pixels, None, front
    d_point, d_coefficients = distortion_jacobians(normalised, D, model)
    focal = np.array([fx, fy])
    d_pixel_normalised = focal[None, :, None] * d_point  # (M, 2, 2)
    d_normalised_c = np.zeros((len(z), 2, 3))
    d_normalised_c[:, 0, 0] = d_normalised_c[:, 1, 1] = inverse_z
    d_normalised_c[:, :, 2] = -normalised * inverse_z[:, None]
    d_pixel_c = d_pixel_normalised @ d_normalised_c  # (M, 2, 3)
    d_pose = np.empty((len(z), 2, 6))
    # points_c' = Exp(-omega) (points_c - v): d/d omega = [points_c]x, d/d v = -I.
    x, y, w = points_c[:, 0:1], points_c[:, 1:2], points_c[:, 2:3]
    d_pose[:, :, 0] = d_pixel_c[:, :, 1] * w - d_pixel_c[:, :, 2] * y
    d_pose[:, :, 1] = d_pixel_c[:, :, 2] * x - d_pixel_c[:, :, 0] * w
    d_pose[:, :, 2] = d_pixel_c[:, :, 0] * y - d_pixel_c[:, :, 1] * x
    d_pose[:, :, 3:] = -d_pixel_c
    d_points = np.matmul(d_pixel_c, rotations_t)  # points_c = R^T (X - t)
    d_camera = np.zeros((len(z), 2, 8))
    d_camera[:, 0, 0], d_camera[:, 1, 1] = distorted[:, 0], distorted[:, 1]
    d_camera[:, 0, 2] = d_camera[:, 1, 3] = 1.0
    d_camera[:, :, 4:] = focal[None, :, None] * d_coefficients
    for array in (d_pose, d_points, d_camera):
        array[~front] = 0.0
    return pixels, (d_pose, d_points, d_camera), front


def _reprojection_errors(calibration: CameraCalibration, poses, points, keyframe_index, point_index, pixels):
    """(M,) pixel errors through ``CameraCalibration.project``; inf for points not in front."""
    R = poses[keyframe_index, :3, :3]
    points_c = np.einsum("mji,mj->mi", R, points[point_index] - poses[keyframe_index, :3, 3])
    projected = calibration.project(points_c)
    error = np.linalg.norm(projected - pixels, axis=1)
    return np.where((points_c[:, 2] > 0) & np.isfinite(error), error, np.inf)


#: Windows with at most this many (free keyframe, landmark) pairs build the Schur complement's pose
#: blocks by one dense product; larger ones (whole maps) by a block-sparse one (measured on a window of
#: the demo camera, 10 keyframes and 350 landmarks: 1.4 ms dense, 4.5 ms block-sparse, 11 ms with scipy's
#: scalar-sparse product; a whole map's dense product would be GFLOPs).
DENSE_SCHUR_PAIRS = 40_000


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^T b`` per observation for two-row Jacobians ``(M, 2, i)``, ``(M, 2, j)`` -> ``(M, i, j)``."""
    return a[:, 0, :, None] * b[:, 0, None, :] + a[:, 1, :, None] * b[:, 1, None, :]


class _Window:
    """One window's least-squares problem in the solver's variables: the free poses (``(omega, v)``
    each), the free camera parameters, and the observed landmarks.

    The landmarks are eliminated by the Schur complement (each couples only to its observations'
    poses and the camera), so each step solves a dense system of ``6 x free poses + free camera
    parameters`` unknowns: the reduced camera system of Ceres and COLMAP. Observations are kept
    sorted by keyframe, then landmark, so that a keyframe's are one slice.
    """

    def __init__(self, problem: WindowProblem, poses: np.ndarray, fixed: np.ndarray, points: np.ndarray,
                 keyframe_index: np.ndarray, point_index: np.ndarray, pixels: np.ndarray, used: np.ndarray) -> None:
        from scipy import sparse

        self.problem = problem
        self.model = problem.calibration.distortion_model
        self.camera_free = np.array(CAMERA_MODES[problem.camera], dtype=np.int64)
        # A free keyframe none of whose observations can be used (all behind it at the start) has
        # nothing to move it: it stays where it is, as a fixed one.
        movable = ~fixed & np.isin(np.arange(len(poses)), keyframe_index[used])
        self.pose_variable = np.full(len(poses), -1)
        self.pose_variable[movable] = np.arange(int(movable.sum()))
        self.free_poses = int(movable.sum())
        self.pose_size = 6 * self.free_poses
        self.size = self.pose_size + len(self.camera_free)
        order = used[np.lexsort((point_index[used], keyframe_index[used]))]
        self.order = order  # the problem's index of each of the window's observations
        self.keyframe = keyframe_index[order]
        self.point_row = point_index[order]
        self.pixels = pixels[order]
        self.observed_points = np.unique(self.point_row)
        self.point_variable = np.full(len(points), -1)
        self.point_variable[self.observed_points] = np.arange(len(self.observed_points))
        self.point = self.point_variable[self.point_row]
        count, landmarks = len(self.keyframe), len(self.observed_points)
        self.sum_by_point = sparse.csr_matrix((np.ones(count), (self.point, np.arange(count))), shape=(landmarks, count))
        # Observations on free keyframes: one contiguous slice per free keyframe.
        variable = self.pose_variable[self.keyframe]
        self.on_free_pose = np.flatnonzero(variable >= 0)
        self.free_variable = variable[self.on_free_pose]
        self.free_point = self.point[self.on_free_pose]
        self.pose_bounds = np.searchsorted(self.free_variable, np.arange(self.free_poses + 1))
        free_count = len(self.on_free_pose)
        self.sum_free_by_point = sparse.csr_matrix(
            (np.ones(free_count), (self.free_point, np.arange(free_count))), shape=(landmarks, free_count))
        self.sum_free_by_pose = sparse.csr_matrix(
            (np.ones(free_count), (self.free_variable, np.arange(free_count))), shape=(self.free_poses, free_count))
        # A keyframe that observes one landmark twice (two tracks fused into it) needs its blocks summed,
        # which the block-sparse product does and the dense assignment would not.
        repeated = bool(np.any((np.diff(self.free_variable) == 0) & (np.diff(self.free_point) == 0)))
        self.dense_schur = self.free_poses * landmarks <= DENSE_SCHUR_PAIRS and not repeated
        self.k = problem.robust_threshold_px / problem.pixel_sigma
        self.cauchy = problem.robust_loss == "cauchy"
        self.prior = None
        if problem.camera_prior is not None and len(self.camera_free):
            information = np.asarray(problem.camera_prior.information, dtype=np.float64)
            information = 0.5 * (information + information.T)
            if np.abs(information).max() > 0:
                # 0.5 d^T I d as a residual r = R d with R^T R = I (from I's eigen-decomposition; a
                # semi-definite I gives zero rows for what it does not inform).
                eigenvalues, eigenvectors = np.linalg.eigh(information)
                root = np.sqrt(np.clip(eigenvalues, 0.0, None))[:, None] * eigenvectors.T
                self.prior = (camera_parameters(problem.camera_prior.calibration), root)
        self._last = None
        self.scale_distance = 0.0
        if problem.scale_pair is not None:
            i, j = (int(r) for r in problem.scale_pair)
            self.scale_distance = float(np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3]))

    # -- the cost and its linearisation -----------------------------------------------------------

    def _residuals(self, state):
        """Whitened residuals ``(M, 2)`` and the Jacobians at ``state``, kept for the state last asked:
        a step's cost is evaluated at the state the next linearisation (or the covariance) starts
        from, so the projection is done once per iteration, not twice."""
        if self._last is not None and self._last[0] is state:
            return self._last[1]
        rotations, translations, points, parameters = state
        pixels, derivatives, front = _project(parameters, self.model, rotations[self.keyframe],
                                              translations[self.keyframe], points[self.point_row], True)
        # A landmark behind its camera has no residual (as GTSAM's factor did, which this solver replaced).
        residuals = np.where(front[:, None], pixels - self.pixels, 0.0) / self.problem.pixel_sigma
        self._last = (state, (residuals, derivatives))
        return residuals, derivatives

    def _loss(self, squared: np.ndarray) -> np.ndarray:
        k2 = self.k * self.k
        if self.cauchy:
            return 0.5 * k2 * np.log1p(squared / k2)
        norm = np.sqrt(squared)
        return np.where(norm <= self.k, 0.5 * squared, self.k * norm - 0.5 * k2)

    def _weights(self, squared: np.ndarray) -> np.ndarray:
        if self.cauchy:
            return 1.0 / (1.0 + squared / (self.k * self.k))
        norm = np.sqrt(squared)
        return np.where(norm <= self.k, 1.0, self.k / np.maximum(norm, 1e-300))

    def _extra_residuals(self, state):
        """The residuals and Jacobians (over the pose and camera variables) of the camera prior, the
        scale pair and the measured positions: ``[(residual (r,), jacobian (r, size))]``."""
        rotations, translations, _, parameters = state
        problem = self.problem
        terms = []
        if self.prior is not None:
            mean, root = self.prior
            jacobian = np.zeros((8, self.size))
            jacobian[:, self.pose_size:] = root[:, self.camera_free]
            terms.append((root @ (parameters - mean), jacobian))
        if problem.scale_pair is not None:
            i, j = (int(r) for r in problem.scale_pair)
            difference = translations[i] - translations[j]
            distance = float(np.linalg.norm(difference))
            sigma = _SCALE_SIGMA * self.scale_distance
            jacobian = np.zeros((1, self.size))
            direction = difference / max(distance, 1e-300)
            for row, sign in ((i, 1.0), (j, -1.0)):
                if self.pose_variable[row] >= 0:
                    column = 6 * self.pose_variable[row] + 3
                    jacobian[0, column: column + 3] = sign * direction @ rotations[row] / sigma
            terms.append((np.array([(distance - self.scale_distance) / sigma]), jacobian))
        if problem.positions is not None:
            sigma = float(problem.position_sigma)
            for row, position in zip(np.asarray(problem.positions[0]).tolist(), np.asarray(problem.positions[1], dtype=np.float64)):
                jacobian = np.zeros((3, self.size))
                if self.pose_variable[row] >= 0:
                    column = 6 * self.pose_variable[row] + 3
                    jacobian[:, column: column + 3] = rotations[row] / sigma
                terms.append(((translations[row] - position) / sigma, jacobian))
        return terms

    def cost(self, state) -> float:
        residuals, _ = self._residuals(state)
        total = float(self._loss((residuals**2).sum(1)).sum())
        return total + sum(0.5 * float(r @ r) for r, _ in self._extra_residuals(state))

    def linearise(self, state, weak_point_information: float = 0.0, keep: np.ndarray | None = None) -> dict:
        """The robustly reweighted normal equations, landmarks kept apart for the Schur complement.

        ``keep``: a mask over the window's observations (``order``) of those that count.
        """
        residuals, (d_pose, d_points, d_camera) = self._residuals(state)
        # Iteratively reweighted: each observation's whitened system times the square root of its weight.
        root_weight = np.sqrt(self._weights((residuals**2).sum(1)))
        if keep is not None:
            root_weight = np.where(keep, root_weight, 0.0)
        r = residuals * root_weight[:, None]
        scale = (root_weight / self.problem.pixel_sigma)[:, None, None]
        B = d_points * scale
        C = d_camera[:, :, self.camera_free] * scale
        n_camera = len(self.camera_free)
        U = np.zeros((self.size, self.size))
        g = np.zeros(self.size)
        pose_point = np.zeros((0, 6, 3))
        if self.pose_size:
            free = self.on_free_pose
            A = d_pose[free] * scale[free]
            A_flat, C_flat, r_flat = A.reshape(-1, 6), C[free].reshape(len(free) * 2, n_camera), r[free].reshape(-1)
            for p in range(self.free_poses):
                rows = slice(2 * self.pose_bounds[p], 2 * self.pose_bounds[p + 1])
                block = slice(6 * p, 6 * p + 6)
                U[block, block] = A_flat[rows].T @ A_flat[rows]
                if n_camera:
                    U[block, self.pose_size:] = A_flat[rows].T @ C_flat[rows]
                g[block] = A_flat[rows].T @ r_flat[rows]
            U[self.pose_size:, : self.pose_size] = U[: self.pose_size, self.pose_size:].T
            pose_point = _gram(A, B[free])
        if n_camera:
            flat = C.reshape(-1, n_camera)
            U[self.pose_size:, self.pose_size:] = flat.T @ flat
            g[self.pose_size:] = flat.T @ r.reshape(-1)
        for residual, jacobian in self._extra_residuals(state):
            U += jacobian.T @ jacobian
            g += jacobian.T @ residual
        points = len(self.observed_points)
        V = (self.sum_by_point @ _gram(B, B).reshape(-1, 9)).reshape(points, 3, 3)
        V += weak_point_information * np.eye(3)
        g_points = self.sum_by_point @ (B[:, 0, :] * r[:, 0:1] + B[:, 1, :] * r[:, 1:2])
        camera_point = np.zeros((points, 0, 3))
        if n_camera:
            camera_point = (self.sum_by_point @ _gram(C, B).reshape(-1, 3 * n_camera)).reshape(points, n_camera, 3)
        # Levenberg-Marquardt damps by the diagonal, clamped as Ceres does (the same for every damping tried).
        return {"U": U, "g": g, "V": V, "g_points": g_points, "pose_point": pose_point, "camera_point": camera_point,
                "U_diagonal": np.clip(np.diag(U), _MIN_DIAGONAL, _MAX_DIAGONAL),
                "V_diagonal": np.clip(np.diagonal(V, axis1=1, axis2=2), _MIN_DIAGONAL, _MAX_DIAGONAL)}

    def _pose_schur(self, weighted: np.ndarray, pose_point: np.ndarray) -> np.ndarray:
        """``sum over landmarks of (E_a V^-1)(E_b)^T`` for every pair of free keyframes ``(a, b)``."""
        from scipy import sparse

        n, landmarks = self.pose_size, len(self.observed_points)
        if self.dense_schur:
            left = np.zeros((self.free_poses, landmarks, 6, 3))
            right = np.zeros((self.free_poses, landmarks, 6, 3))
            left[self.free_variable, self.free_point] = weighted
            right[self.free_variable, self.free_point] = pose_point
            left = left.transpose(0, 2, 1, 3).reshape(n, 3 * landmarks)
            right = right.transpose(0, 2, 1, 3).reshape(n, 3 * landmarks)
            return left @ right.T
        shape = (n, 3 * landmarks)
        left = sparse.bsr_matrix((weighted, self.free_point, self.pose_bounds), shape=shape)
        right = sparse.bsr_matrix((pose_point, self.free_point, self.pose_bounds), shape=shape)
        return (left @ right.T).toarray()

    def reduced_system(self, system: dict, damping: float):
        """The Schur complement ``S`` and right-hand side of the damped system (LM: ``H + damping
        diag(H)``, the linearisation's clamped diagonal), and the landmark blocks' inverses."""
        U, V = system["U"], system["V"]
        S = U.copy()
        V_damped = V
        if damping > 0:
            S[np.diag_indices_from(S)] += damping * system["U_diagonal"]
            V_damped = V.copy()
            V_damped[:, np.arange(3), np.arange(3)] += damping * system["V_diagonal"]
        V_inverse = np.linalg.inv(V_damped)
        g_points = system["g_points"]
        rhs = -system["g"].copy()
        n = self.pose_size
        camera_point = system["camera_point"]
        n_camera = camera_point.shape[1]
        if n:
            pose_point = system["pose_point"]
            weighted = np.matmul(pose_point, V_inverse[self.free_point])  # (free observations, 6, 3)
            S[:n, :n] -= self._pose_schur(weighted, pose_point)
            rhs[:n] += (self.sum_free_by_pose @ np.matmul(weighted, g_points[self.free_point][:, :, None])[:, :, 0]).ravel()
            if n_camera:
                coupling = np.matmul(weighted, camera_point[self.free_point].transpose(0, 2, 1))  # (., 6, C)
                pose_camera = (self.sum_free_by_pose @ coupling.reshape(len(coupling), -1)).reshape(n, n_camera)
                S[:n, n:] -= pose_camera
                S[n:, :n] -= pose_camera.T
        if n_camera:
            weighted_camera = np.matmul(camera_point, V_inverse)  # (L, C, 3)
            left = weighted_camera.transpose(1, 0, 2).reshape(n_camera, -1)
            S[n:, n:] -= left @ camera_point.transpose(1, 0, 2).reshape(n_camera, -1).T
            rhs[n:] += left @ g_points.ravel()
        return S, rhs, V_inverse

    def step(self, system: dict, damping: float):
        """The LM step ``(pose and camera step, landmark step, model decrease)``; raises
        ``np.linalg.LinAlgError`` where the damped system is not positive definite."""
        from scipy.linalg import cho_factor, cho_solve

        S, rhs, V_inverse = self.reduced_system(system, damping)
        step = cho_solve(cho_factor(S, check_finite=False), rhs, check_finite=False) if len(rhs) else rhs
        back = system["g_points"].copy()
        if self.pose_size:
            pose_steps = step[: self.pose_size].reshape(-1, 6)[self.free_variable]
            back += self.sum_free_by_point @ np.matmul(pose_steps[:, None, :], system["pose_point"])[:, 0, :]
        if system["camera_point"].shape[1]:
            back += np.matmul(step[self.pose_size:], system["camera_point"])
        point_step = -np.matmul(V_inverse, back[:, :, None])[:, :, 0]
        # The linear model's decrease: -g.d - d^T H d / 2 = (-g.d + damping d^T D d) / 2.
        decrease = -0.5 * (system["g"] @ step + np.sum(system["g_points"] * point_step))
        if damping > 0:
            decrease += 0.5 * damping * (system["U_diagonal"] @ step**2)
            decrease += 0.5 * damping * np.sum(system["V_diagonal"] * point_step**2)
        return step, point_step, float(decrease)

    def retract(self, state, step: np.ndarray, point_step: np.ndarray):
        rotations, translations, points, parameters = (array.copy() for array in state)
        if self.pose_size:
            free = np.flatnonzero(self.pose_variable >= 0)
            pose_step = step[: self.pose_size].reshape(-1, 6)
            translations[free] += np.matmul(rotations[free], pose_step[:, 3:, None])[:, :, 0]
            rotations[free] = rotations[free] @ so3_exp(pose_step[:, :3])
        points[self.observed_points] += point_step
        parameters[self.camera_free] += step[self.pose_size:]
        return rotations, translations, points, parameters


_blas_pool = None


def _one_blas_thread():
    """A context in which numpy's and scipy's BLAS run on one thread.

    The solver's matrices are small: OpenBLAS's second thread made a step 2.5x slower on the 2-core
    machine (17.8 against 44 ms for a VAMR window's linearisation and step, measured), as torch's did.
    """
    global _blas_pool
    if _blas_pool is None:
        importlib.import_module("scipy.linalg")  # scipy's BLAS must be loaded before the controller looks
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:  # a ROS install without pip's requirements: correct, only slower
            _blas_pool = False
        else:
            _blas_pool = ThreadpoolController()
    return _blas_pool.limit(limits=1, user_api="blas") if _blas_pool else contextlib.nullcontext()


def load_libraries() -> None:
    """Import what a solve needs (scipy's linear algebra, the BLAS controller) ahead of the first one.

    Imported at a new map's first solve, they took 0.6 s of the tracking thread (a first-frame stall
    that dropped 18 frames of a 30 Hz replay, measured).
    """
    importlib.import_module("scipy.sparse")
    _one_blas_thread()


def bundle_adjust(problem: WindowProblem) -> WindowSolution:
    """Refine the window's poses, landmarks and camera by robust Levenberg-Marquardt.

    Returns the refined values, the marginal covariances asked for, the inlier mask and the
    reprojection RMS before and after. See the module notes for conventions and failure handling.
    """
    with _one_blas_thread():
        return _bundle_adjust(problem)


def _bundle_adjust(problem: WindowProblem) -> WindowSolution:
    started = time.perf_counter()
    start, poses, fixed, points, keyframe_index, point_index, pixels = _validate(problem)

    # Observations whose landmark starts behind its camera cannot be linearised: leave them out.
    start_errors = _reprojection_errors(problem.calibration, poses, points, keyframe_index, point_index, pixels)
    used = np.flatnonzero(np.isfinite(start_errors))
    window = _Window(problem, poses, fixed, points, keyframe_index, point_index, pixels, used)
    state = (poses[:, :3, :3].copy(), poses[:, :3, 3].copy(), points.copy(), start.copy())

    # Levenberg-Marquardt with Ceres' damping policy (a step is taken when the cost falls by at least
    # a thousandth of what the linear model predicted; the damping then shrinks by the model's fidelity).
    cost = window.cost(state)
    damping, factor = _LAMBDA_INITIAL, 2.0
    iterations = 0
    while iterations < int(problem.max_iterations) and cost > 0:
        iterations += 1
        system = window.linearise(state)
        taken = None
        while damping < _LAMBDA_MAX:
            try:
                step, point_step, decrease = window.step(system, damping)
            except np.linalg.LinAlgError:
                step = None
            if step is not None and np.all(np.isfinite(step)) and decrease > 0:
                candidate = window.retract(state, step, point_step)
                new_cost = window.cost(candidate)
                fidelity = (cost - new_cost) / decrease
                if np.isfinite(new_cost) and fidelity > _MIN_MODEL_FIDELITY:
                    damping = max(damping * max(1.0 / 3.0, 1.0 - (2.0 * fidelity - 1.0) ** 3), _LAMBDA_MIN)
                    factor = 2.0
                    taken = (candidate, new_cost)
                    break
            damping *= factor
            factor *= 2.0
        if taken is None:
            break
        relative = (cost - taken[1]) / cost
        state, cost = taken
        if relative < problem.relative_tolerance:
            break

    rotations, translations, solved_points, solved_parameters = state  # only the mode's parameters moved
    if not np.all(np.isfinite(solved_parameters)) or not np.all(np.isfinite(solved_points)):
        return _failed(problem, start_errors, "the solve left non-finite values", started)
    try:
        solved = calibration_from_parameters(solved_parameters, problem.calibration)
    except (BundleAdjustmentInputError, ValueError) as error:
        return _failed(problem, start_errors, f"the solve left an invalid camera ({error})", started)
    solved_poses = np.tile(np.eye(4), (len(poses), 1, 1))
    solved_poses[:, :3, :3], solved_poses[:, :3, 3] = rotations, translations
    solved_poses[fixed] = poses[fixed]

    errors = _reprojection_errors(solved, solved_poses, solved_points, keyframe_index, point_index, pixels)
    inliers = errors < problem.robust_threshold_px

    camera_covariance = None
    pose_covariances: dict[int, np.ndarray] = {}
    camera_wanted = problem.camera != "fixed" and problem.camera_covariance
    covariance_started = time.thread_time()
    if camera_wanted or problem.covariance_of:
        distance = np.linalg.norm(points[point_index] - poses[keyframe_index, :3, 3], axis=1)
        landmark_sigma = _LANDMARK_PRIOR_SCALE * max(float(np.median(distance)), 1e-6)
        covariance = _marginal_covariance(window, state, np.isfinite(errors[window.order]), landmark_sigma)
        if covariance is None:
            # Too poorly conditioned with the weak prior (a whole map, measured): once more with the
            # landmarks held to their median distance.
            covariance = _marginal_covariance(window, state, np.isfinite(errors[window.order]), landmark_sigma / _LANDMARK_PRIOR_SCALE)
        if covariance is None:
            # An indeterminate system at the solution: the values along its null space are arbitrary,
            # so none of them is returned.
            return _failed(problem, start_errors, "Indeterminate system: the window does not determine every "
                           "free pose and camera parameter (a keyframe with too few landmarks?)", started)
        if camera_wanted:
            camera_covariance = np.zeros((8, 8))
            camera_covariance[np.ix_(window.camera_free, window.camera_free)] = covariance[window.pose_size:, window.pose_size:]
        for row in problem.covariance_of:
            row = int(row)
            if fixed[row]:
                pose_covariances[row] = np.zeros((6, 6))
                continue
            if window.pose_variable[row] < 0:
                return _failed(problem, start_errors, f"Indeterminate system: keyframe row {row} has no observation "
                               "in front of it, and its covariance was asked for", started)
            # The solver orders a pose's tangent (omega, v); ours is (rho, theta).
            block = slice(6 * window.pose_variable[row], 6 * window.pose_variable[row] + 6)
            order = [3, 4, 5, 0, 1, 2]
            pose_covariances[row] = covariance[block, block][np.ix_(order, order)]

    return WindowSolution(
        poses=solved_poses,
        points=solved_points,
        calibration=solved,
        camera_covariance=camera_covariance,
        pose_covariances=pose_covariances,
        inliers=inliers,
        initial_rms_px=_rms(start_errors[inliers]),
        final_rms_px=_rms(errors[inliers]),
        iterations=iterations,
        seconds=time.perf_counter() - started,
        success=True,
        message="",
        residuals_px=errors,
        covariance_cpu_seconds=time.thread_time() - covariance_started,
    )


def _marginal_covariance(window: _Window, state, keep: np.ndarray, landmark_sigma: float) -> np.ndarray | None:
    """The marginal covariance of the pose and camera variables at the solution, or None where the
    system is indeterminate.

    An observation behind its camera at the solution carries no information, so it is left out. A
    landmark the data cannot place (a track of nearly parallel rays that ran off to kilometres, or one
    left with a single view) would make the system indeterminate: a weak prior (``landmark_sigma``,
    100 times the median viewing distance) holds it without informing the rest. The solve itself has
    no such prior, so noiseless data is fitted exactly.
    """
    system = window.linearise(state, weak_point_information=1.0 / landmark_sigma**2, keep=keep)
    try:
        S, _, _ = window.reduced_system(system, 0.0)
    except np.linalg.LinAlgError:
        return None
    if not len(S):
        return S
    # Indeterminate directions show as (relative) zero eigenvalues of the diagonally scaled system.
    diagonal = np.sqrt(np.clip(np.diag(S), 1e-300, None))
    scaled = S / diagonal[:, None] / diagonal[None, :]
    if not np.all(np.isfinite(scaled)) or np.linalg.eigvalsh(0.5 * (scaled + scaled.T)).min() < _INDETERMINATE:
        return None
    covariance = np.linalg.inv(scaled) / diagonal[:, None] / diagonal[None, :]
    return 0.5 * (covariance + covariance.T)


def _rms(errors: np.ndarray) -> float:
    errors = errors[np.isfinite(errors)]
    return float(np.sqrt(np.mean(errors**2))) if len(errors) else float("nan")


def _failed(problem: WindowProblem, start_errors: np.ndarray, message: str, started: float) -> WindowSolution:
    inliers = start_errors < problem.robust_threshold_px
    return WindowSolution(
        poses=np.array(problem.poses, dtype=np.float64),
        points=np.array(problem.points, dtype=np.float64),
        calibration=calibration_from_parameters(camera_parameters(problem.calibration), problem.calibration),
        camera_covariance=None,
        pose_covariances={},
        inliers=inliers,
        initial_rms_px=_rms(start_errors[inliers]),
        final_rms_px=_rms(start_errors[inliers]),
        iterations=0,
        seconds=time.perf_counter() - started,
        success=False,
        message=message,
        residuals_px=start_errors,
    )
