"""Windowed bundle adjustment over keyframe poses, landmarks AND the camera, solved with GTSAM 4.3.

The VO's backend worker calls :func:`bundle_adjust` on each new keyframe with the last N keyframes,
their landmarks and the current camera. The camera is a parametric
:class:`~nocal_ros.lens.CameraCalibration` (the learnt ``CameraModel`` is converted to it by
``CameraModel.to_calibration``, which reports the fit's residual):

* ``plumb_bob`` with ``k3 = 0``: GTSAM's ``Cal3DS2`` (fx fy s u0 v0 k1 k2 p1 p2), exactly OpenCV's
  ``cv2.projectPoints`` with ``(k1, k2, p1, p2, 0)``;
* ``equidistant``: GTSAM's ``Cal3Fisheye`` (fx fy s u0 v0 k1..k4), exactly
  ``cv2.fisheye.projectPoints`` for points in front of the camera.

Both agree with ``CameraCalibration.project`` and OpenCV to below 1e-12 px (``solver_project``;
``test/test_bundle_adjustment.py`` asserts 1e-9).
GTSAM's skew ``s`` is no parameter of these models: it is pinned at 0.

Why GTSAM (measured by ``scripts/compare/bundle_adjustment_solvers.py``; BENCHMARKS.md, "Windowed
bundle adjustment"): of the candidates only GTSAM takes a prior with a full information matrix on the
intrinsics, and that prior is how the camera's information carries over from window to window, i.e.
the online self-calibration. It also gives the marginal covariances the VO needs (``gtsam.Marginals``)
and both lens models. pycolmap's bundle adjuster (Ceres) reaches the same minimum to the digit 2.2-4.5x
faster in CPU time but can only fix or free the intrinsics, never weigh them against a prior. scipy's
``least_squares`` (trust region on a sparse Jacobian, lsmr) did not converge in 20 evaluations.
iSAM2 failed from cold starts (indeterminate Gauss-Newton steps) and was no faster from warm ones.

Cost, one thread, CPU time on the shared 2-core machine (load ~10): 10 keyframes, 300 landmarks
(~1880 observations), warm start, ``relative_tolerance=1e-3``: 83 ms plus 34 ms for the camera's
covariance; 150 landmarks: 30 + 8 ms, inside the VO's 50 ms per keyframe. Building the graph in
Python is 7-13 ms of it. GTSAM holds the GIL for the whole solve: run the backend in a process
(problem and solution pickle), not a thread, or the frontend stalls for the length of each solve.

Conventions:

* Poses are ``T_w_c`` (camera to world), optical frame, 4x4 float64. ``gtsam.Pose3`` is the same
  matrix; its tangent is ``(omega, v)`` (rotation first) with a right perturbation
  ``T Exp(xi)``. Pose covariances here are reordered to ``(rho, theta)`` (translation first), as in
  :mod:`nocal_ros.odometry.covariance`.
* Camera parameters: ``camera_parameters`` below; the covariance is over that vector (GTSAM's
  calibration tangent is the plain difference of its parameter vector, so no Jacobian is needed;
  the skew row and column are dropped).
* Pixels are native, distorted, with pixel centres at integer coordinates (OpenCV's convention).
* The gauge: at least two keyframes are held fixed (monocular gauge and scale), or one and the
  distance between two (``scale_pair``, a range factor), which leaves their relative rotation free. Fixed poses and
  pinned camera parameters are held by priors with sigmas of 1e-8 (a pose's residual stays below
  1e-8 m and rad; their covariances are returned as zeros; 1e-9 made the normal equations indeterminate).

Robustness: each observation has a Cauchy loss with scale ``robust_threshold_px`` (``robust_loss``
selects Huber instead). With 0.5 px noise and 5 % outliers of 10-40 px, Huber's linear influence
lets the outliers bias the camera. On the benchmark's windows (BENCHMARKS.md) Cauchy at 2 px gave
0.64 % focal, 3.6 px principal point, 0.107 deg and 53 mm landmarks against Huber's 0.70 %, 6.1 px,
0.149 deg and 89 mm. On 12 of the tests' smaller windows per lens (cold start 15 % off), the median
focal error was 0.50 % (plumb_bob) and 1.5 % (fisheye) against Huber's 1.7 % and 3.0 %, and the
errors were 1.0 and 1.5 reported standard deviations (rms over windows) against Huber's 2.1 and 1.9:
with Cauchy the covariance describes the error.
For the covariances, landmarks carry a weak prior (sigma 100 times the median camera-landmark
distance) so that a track of nearly parallel rays leaves the system determinate without informing
anything else (without it 3 of 12 plumb_bob and 2 of 12 fisheye test windows failed on one such
landmark).

Bad input (NaN, wrong shapes, an index out of range, fewer than two fixed poses without a ``scale_pair``
or three measured ``positions``, a camera model or
``k3`` GTSAM cannot represent, a free keyframe without observations) raises
:class:`BundleAdjustmentInputError` naming the field. A failure inside the solver does NOT raise:
the solution carries the start values, ``success = False`` and GTSAM's message, so the worker can
drop that window and carry on. GTSAM's Levenberg-Marquardt absorbs a singular step by raising its
damping, so the indeterminacy shows where the covariance is computed (``gtsam.Marginals`` raises):
whenever a covariance is asked for. Without one (``camera="fixed"`` or ``camera_covariance=False``,
and no ``covariance_of``) an indeterminate direction (a keyframe seeing two landmarks) is not
detected. Observations whose landmark starts behind its keyframe are left out of the solve and come
back as non-inliers (GTSAM's factor would zero them anyway and print a line per landmark on stdout);
a landmark that crosses behind a camera during the solve is zeroed the same way (GTSAM prints a
``CheiralityException`` line for it).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from nocal_ros.errors import NocalError
from nocal_ros.lens import CameraCalibration

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

# Sigma of the priors that hold fixed poses, pinned camera parameters and the skew. Small enough to
# move nothing the tests can see, large enough to keep the normal equations well conditioned.
_PINNED_SIGMA = 1e-8
# Sigma of "free" camera parameters in the pinning prior: no information at all, to double precision.
_FREE_SIGMA = 1e8
_LANDMARK_PRIOR_SCALE = 100.0
# Relative sigma of the distance a scale_pair holds. Tighter (1e-6, 1e-8) made gtsam.Marginals report an
# indeterminate system beside the 1e-8 pose prior (measured on VO windows); 1e-4 of the baseline is far
# below what one window can tell about its scale.
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
            f"bundle adjustment's plumb_bob camera has k3 = 0 (GTSAM Cal3DS2), got k3 = {calibration.D[4]}"
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
    covariance_cpu_seconds: float = 0.0  # CPU time of the calling thread in gtsam.Marginals (part of seconds)


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


def _gtsam_calibration(gtsam, model: str, parameters: np.ndarray):
    fx, fy, cx, cy = parameters[:4]
    if model == "equidistant":
        return gtsam.Cal3Fisheye(fx, fy, 0.0, cx, cy, *parameters[4:])
    return gtsam.Cal3DS2(fx, fy, 0.0, cx, cy, *parameters[4:])


# GTSAM's calibration vector is (fx, fy, s, u0, v0, d1..d4): ours without the skew.
_TANGENT_OF_PARAMETER = np.array([0, 1, 3, 4, 5, 6, 7, 8])


def solver_project(calibration: CameraCalibration, T_w_c: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` of world points as the solver projects them (GTSAM ``PinholeCamera``).

    The solver's own measurement model, for checking it against ``CameraCalibration.project`` and
    OpenCV. NaN for points not in front of the camera (GTSAM raises a cheirality error there).
    """
    import gtsam

    parameters = camera_parameters(calibration)
    model = calibration.distortion_model
    Camera = gtsam.PinholeCameraCal3Fisheye if model == "equidistant" else gtsam.PinholeCameraCal3DS2
    camera = Camera(gtsam.Pose3(np.asarray(T_w_c, dtype=np.float64)), _gtsam_calibration(gtsam, model, parameters))
    points_w = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    depth = (points_w - T_w_c[:3, 3]) @ np.asarray(T_w_c, dtype=np.float64)[:3, 2]
    pixels = np.full((len(points_w), 2), np.nan)
    for n in np.flatnonzero(depth > 0):
        pixels[n] = camera.project(points_w[n])
    return pixels


def _to_tangent_information(information: np.ndarray, skew_information: float) -> np.ndarray:
    full = np.zeros((9, 9))
    full[np.ix_(_TANGENT_OF_PARAMETER, _TANGENT_OF_PARAMETER)] = information
    full[2, 2] = skew_information
    return full


def _reprojection_errors(calibration: CameraCalibration, poses, points, keyframe_index, point_index, pixels):
    """(M,) pixel errors through ``CameraCalibration.project``; inf for points not in front."""
    R = poses[keyframe_index, :3, :3]
    points_c = np.einsum("mji,mj->mi", R, points[point_index] - poses[keyframe_index, :3, 3])
    projected = calibration.project(points_c)
    error = np.linalg.norm(projected - pixels, axis=1)
    return np.where((points_c[:, 2] > 0) & np.isfinite(error), error, np.inf)


def bundle_adjust(problem: WindowProblem) -> WindowSolution:
    """Refine the window's poses, landmarks and camera by robust Levenberg-Marquardt (GTSAM).

    Returns the refined values, the marginal covariances asked for, the inlier mask and the
    reprojection RMS before and after. See the module notes for conventions and failure handling.
    """
    started = time.perf_counter()
    start, poses, fixed, points, keyframe_index, point_index, pixels = _validate(problem)
    import gtsam
    from gtsam.symbol_shorthand import K, L, X

    model = problem.calibration.distortion_model
    fisheye = model == "equidistant"
    free = np.zeros(8, bool)
    free[list(CAMERA_MODES[problem.camera])] = True
    calibration = _gtsam_calibration(gtsam, model, start)

    # Observations whose landmark starts behind its camera cannot be linearised: leave them out.
    start_errors = _reprojection_errors(problem.calibration, poses, points, keyframe_index, point_index, pixels)
    used = np.flatnonzero(np.isfinite(start_errors))

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    estimator = gtsam.noiseModel.mEstimator.Cauchy if problem.robust_loss == "cauchy" else gtsam.noiseModel.mEstimator.Huber
    robust = estimator.Create(problem.robust_threshold_px / problem.pixel_sigma)
    noise = gtsam.noiseModel.Robust.Create(robust, gtsam.noiseModel.Isotropic.Sigma(2, problem.pixel_sigma))
    if problem.camera == "fixed":
        Factor = gtsam.GenericProjectionFactorCal3Fisheye if fisheye else gtsam.GenericProjectionFactorCal3DS2
        for m in used:
            graph.add(Factor(pixels[m], noise, X(int(keyframe_index[m])), L(int(point_index[m])), calibration, False, False))
    else:
        Factor = gtsam.GeneralSFMFactor2Cal3Fisheye if fisheye else gtsam.GeneralSFMFactor2Cal3DS2
        for m in used:
            graph.add(Factor(pixels[m], noise, X(int(keyframe_index[m])), L(int(point_index[m])), K(0)))
        PriorCalibration = gtsam.PriorFactorCal3Fisheye if fisheye else gtsam.PriorFactorCal3DS2
        # Pinned parameters and the skew stay at their start values; free ones get no information.
        sigmas = np.full(9, _PINNED_SIGMA)
        sigmas[_TANGENT_OF_PARAMETER[free]] = _FREE_SIGMA
        graph.add(PriorCalibration(K(0), calibration, gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
        if problem.camera_prior is not None:
            prior_mean = _gtsam_calibration(gtsam, model, camera_parameters(problem.camera_prior.calibration))
            information = _to_tangent_information(np.asarray(problem.camera_prior.information, dtype=np.float64), 0.0)
            information = 0.5 * (information + information.T)
            # A semi-definite prior (information on some parameters only) is fine: its square root
            # from the eigen-decomposition has zero rows for the directions it does not inform.
            eigenvalues, eigenvectors = np.linalg.eigh(information)
            root = np.sqrt(np.clip(eigenvalues, 0.0, None))[:, None] * eigenvectors.T
            if eigenvalues.max() > 0:
                graph.add(PriorCalibration(K(0), prior_mean, gtsam.noiseModel.Gaussian.SqrtInformation(root, False)))
        values.insert(K(0), calibration)
    pinned = gtsam.noiseModel.Isotropic.Sigma(6, _PINNED_SIGMA)
    for k, T in enumerate(poses):
        values.insert(X(k), gtsam.Pose3(T))
        if fixed[k]:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T), pinned))
    for j, point in enumerate(points):
        values.insert(L(j), point)
    if problem.scale_pair is not None:
        i, j = (int(r) for r in problem.scale_pair)
        distance = float(np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3]))
        graph.add(gtsam.RangeFactorPose3(X(i), X(j), distance, gtsam.noiseModel.Isotropic.Sigma(1, _SCALE_SIGMA * distance)))
    if problem.positions is not None:
        position_noise = gtsam.noiseModel.Isotropic.Sigma(3, float(problem.position_sigma))
        for row, position in zip(np.asarray(problem.positions[0]).tolist(), np.asarray(problem.positions[1], dtype=np.float64)):
            graph.add(gtsam.GPSFactor(X(int(row)), position, position_noise))

    parameters = gtsam.LevenbergMarquardtParams.CeresDefaults()
    parameters.setMaxIterations(int(problem.max_iterations))
    parameters.setRelativeErrorTol(float(problem.relative_tolerance))
    parameters.setAbsoluteErrorTol(0.0)
    try:
        with _quiet_native_stdout():
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, parameters)
            result = optimizer.optimize()
        iterations = int(optimizer.iterations())
    except RuntimeError as error:
        return _failed(problem, start_errors, f"GTSAM: {' '.join(str(error).split())[:300]}", started)

    solved_parameters = start.copy()
    if problem.camera != "fixed":
        fitted = result.atCal3Fisheye(K(0)) if fisheye else result.atCal3DS2(K(0))
        # The calibration's tangent is the plain difference of parameter vectors.
        solved_parameters = start + calibration.localCoordinates(fitted)[_TANGENT_OF_PARAMETER]
        solved_parameters[~free] = start[~free]
    solved = calibration_from_parameters(solved_parameters, problem.calibration)
    solved_poses = np.stack([result.atPose3(X(k)).matrix() for k in range(len(poses))])
    solved_poses[fixed] = poses[fixed]
    solved_points = np.stack([result.atPoint3(L(j)) for j in range(len(points))]) if len(points) else points.copy()

    errors = _reprojection_errors(solved, solved_poses, solved_points, keyframe_index, point_index, pixels)
    inliers = errors < problem.robust_threshold_px

    camera_covariance = None
    pose_covariances: dict[int, np.ndarray] = {}
    camera_wanted = problem.camera != "fixed" and problem.camera_covariance
    covariance_started = time.thread_time()
    if camera_wanted or problem.covariance_of:
        try:
            distance = np.linalg.norm(points[point_index] - poses[keyframe_index, :3, 3], axis=1)
            landmark_sigma = _LANDMARK_PRIOR_SCALE * max(float(np.median(distance)), 1e-6)
            with _quiet_native_stdout():
                try:
                    marginals = _marginals(gtsam, graph, result, used, errors, len(points), landmark_sigma)
                except RuntimeError:
                    # Too poorly conditioned for Cholesky with the weak prior (a whole map of 32
                    # keyframes, measured): once more with landmarks held to their median distance.
                    marginals = _marginals(gtsam, graph, result, used, errors, len(points),
                                           landmark_sigma / _LANDMARK_PRIOR_SCALE)
            if camera_wanted:
                tangent = marginals.marginalCovariance(K(0))
                camera_covariance = tangent[np.ix_(_TANGENT_OF_PARAMETER, _TANGENT_OF_PARAMETER)]
                camera_covariance[~free] = 0.0
                camera_covariance[:, ~free] = 0.0
            for row in problem.covariance_of:
                row = int(row)
                if fixed[row]:
                    pose_covariances[row] = np.zeros((6, 6))
                    continue
                # GTSAM orders the Pose3 tangent (omega, v); ours is (rho, theta).
                order = [3, 4, 5, 0, 1, 2]
                pose_covariances[row] = marginals.marginalCovariance(X(row))[np.ix_(order, order)]
        except RuntimeError as error:
            # An indeterminate system at the solution: the values along its null space are
            # arbitrary, so none of them is returned.
            return _failed(problem, start_errors, f"GTSAM: {' '.join(str(error).split())[:300]}", started)

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


@contextlib.contextmanager
def _quiet_native_stdout():
    """Send the C++ library's standard output to /dev/null for the block.

    GTSAM's GeneralSFMFactor prints a line to ``std::cout`` for every landmark that a trial step moves
    behind a camera (hundreds per replay on the fisheye bag), which it then handles itself.
    """
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError, AttributeError):  # no file descriptor 1 (an embedding host): leave it
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _marginals(gtsam, graph, result, used: np.ndarray, errors: np.ndarray, landmarks: int, landmark_sigma: float):
    """``gtsam.Marginals`` at the solution.

    GTSAM zeroes the Jacobian of an observation behind its camera; such rows carry no information,
    so they are left out (which also keeps GTSAM from printing a line for each). A landmark the data
    cannot place (a track of nearly parallel rays that ran off to kilometres, or one left with a
    single view) would make the system indeterminate: a weak prior (``landmark_sigma``, 100 times
    the median viewing distance) holds it without informing the rest. The solve itself has no such
    prior, so noiseless data is fitted exactly.
    """
    from gtsam.symbol_shorthand import L

    kept = gtsam.NonlinearFactorGraph()
    for position in np.flatnonzero(np.isfinite(errors[used])):
        kept.add(graph.at(int(position)))
    for position in range(len(used), graph.size()):
        kept.add(graph.at(position))
    weak = gtsam.noiseModel.Isotropic.Sigma(3, landmark_sigma)
    for j in range(landmarks):
        kept.add(gtsam.PriorFactorPoint3(L(j), result.atPoint3(L(j)), weak))
    return gtsam.Marginals(kept, result)


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
