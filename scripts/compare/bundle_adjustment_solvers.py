"""Which solver runs the VO's windowed bundle adjustment: the module's own (since 2026-12-02), GTSAM (the
module's before), pycolmap (Ceres) or scipy, measured. GTSAM and pycolmap come with the compare extra
(requirements-compare.txt).

Builds windowed BA problems like the VO backend's: K keyframes along an arm-like path (a few cm
apart, a degree or two of rotation each), L landmarks at 1-5 m, each tracked by 3-10 consecutive
keyframes, pixels from ``cv2.projectPoints`` (plumb_bob, 640x480, f = 520, k1 = -0.25) or
``cv2.fisheye.projectPoints`` (equidistant, 160x120, f = 60), 0.5 px noise, 5 % gross outliers
(10-40 px), and start values perturbed: focal 10-20 % off, principal point at the image centre,
distortion zero, non-fixed poses 1 cm / 0.5 deg off, points 5 % of their depth off. The first two
keyframes are fixed at the truth (the monocular gauge and scale), so errors need no alignment.
``--start warm`` is the VO's steady state instead: the camera carried over from the last window.

Every solver gets the same problem and the same robust loss, on one thread, and is timed from the
numpy arrays to the numpy result (building the problem in Python included). Printed per solver:
median ms per solve after warm-up (wall, and CPU: on a shared machine wall time is mostly waiting),
focal error %, rotation and position error of the free
keyframes, median landmark error, median reprojection error of the true inliers, the fraction of outliers flagged (error > 2 px
after the solve), and the extra CPU cost of the camera's marginal covariance.

    python scripts/compare/bundle_adjustment_solvers.py --model plumb_bob --start cold --loss cauchy
    python scripts/compare/bundle_adjustment_solvers.py --model equidistant --start warm --loss cauchy
    (solvers: module = nocal_ros.odometry.bundle_adjustment (the VO's own solver), gtsam-lm, gtsam-lm-ceres, gtsam-isam2,
    pycolmap, scipy-trf; --solvers picks some)
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from nocal_ros.lens import CameraCalibration

ROOT = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------------------------------
# The problems
# --------------------------------------------------------------------------------------------------


def true_camera(model: str) -> CameraCalibration:
    if model == "plumb_bob":
        camera = CameraCalibration.load(ROOT / "config/cameras/default_640x480.yaml")
        camera.D[4] = 0.0  # GTSAM's Cal3DS2 and COLMAP's OPENCV have no k3
        return camera
    return CameraCalibration.load(ROOT / "config/cameras/fisheye_640x480.yaml").scaled(160, 120)


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_w_c`` of an optical-frame camera at ``position`` looking at ``target`` (y down)."""
    z = target - position
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, -1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack((x, np.cross(z, x), z), 1)
    T[:3, 3] = position
    return T


def project_opencv(camera: CameraCalibration, T_w_c: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Pixels by OpenCV itself (the independent reference); NaN behind the camera."""
    T_c_w = np.linalg.inv(T_w_c)
    rvec, _ = cv2.Rodrigues(T_c_w[:3, :3])
    tvec = T_c_w[:3, 3]
    if camera.distortion_model == "equidistant":
        pixels, _ = cv2.fisheye.projectPoints(points_w.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.D)
    else:
        pixels, _ = cv2.projectPoints(points_w.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.D)
    pixels = pixels.reshape(-1, 2)
    depth = points_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    pixels[depth[:, 2] <= 0.05] = np.nan
    return pixels


@dataclass
class Problem:
    truth: CameraCalibration
    start: CameraCalibration
    poses_true: np.ndarray
    poses_start: np.ndarray
    points_true: np.ndarray
    points_start: np.ndarray
    keyframe_index: np.ndarray
    point_index: np.ndarray
    pixels: np.ndarray
    outlier: np.ndarray
    fixed: np.ndarray


def make_problem(model: str, seed: int, keyframes: int = 10, landmarks: int = 300, noise_px: float = 0.5,
                 outlier_fraction: float = 0.05, focal_error: tuple[float, float] = (0.10, 0.20),
                 pose_noise: tuple[float, float] = (0.01, 0.5), point_noise: float = 0.05,
                 warm: bool = False) -> Problem:
    rng = np.random.default_rng(seed)
    truth = true_camera(model)
    # Arm-like path: a gently curving sweep, 3-5 cm between keyframes, the view turning toward a
    # point ~3 m ahead plus a little wobble (a degree or two between keyframes).
    target = np.array([0.0, 0.0, 3.0]) + rng.normal(0, 0.2, 3)
    steps = rng.uniform(0.03, 0.05, keyframes)
    heading = rng.normal(0, 1, 3)
    heading[2] *= 0.3
    heading /= np.linalg.norm(heading)
    bend = rng.normal(0, 0.3, 3)
    poses = []
    position = np.zeros(3)
    for k in range(keyframes):
        direction = heading + bend * k / keyframes
        position = position + steps[k] * direction / np.linalg.norm(direction)
        T = look_at(position, target)
        T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(rng.normal(0, np.radians(1.0), 3)).as_matrix()
        poses.append(T)
    poses_true = np.stack(poses)
    # Landmarks seen by a middle keyframe: a random pixel at a random depth, through the true lens.
    middle = keyframes // 2
    pixels_seed = np.stack((rng.uniform(0, truth.width - 1, 3 * landmarks), rng.uniform(0, truth.height - 1, 3 * landmarks)), -1)
    rays = truth.unproject(pixels_seed)
    # GTSAM projects through X/Z: keep rays within ~75 deg of the axis (the fisheye sees past 90).
    rays = rays[rays[:, 2] > 0.25][:landmarks]
    depth = rng.uniform(1.0, 5.0, landmarks)
    points_c = rays / rays[:, 2:3] * depth[:, None]
    points_true = points_c @ poses_true[middle, :3, :3].T + poses_true[middle, :3, 3]
    # Tracks: 3-10 consecutive keyframes around the middle one, kept where OpenCV sees them.
    keyframe_index, point_index = [], []
    for j in range(landmarks):
        length = rng.integers(3, 11)
        first = rng.integers(max(0, middle - length + 1), min(middle, keyframes - length) + 1)
        for k in range(first, first + length):
            keyframe_index.append(k)
            point_index.append(j)
    keyframe_index, point_index = np.array(keyframe_index), np.array(point_index)
    pixels = np.empty((len(keyframe_index), 2))
    for k in range(keyframes):
        rows = keyframe_index == k
        pixels[rows] = project_opencv(truth, poses_true[k], points_true[point_index[rows]])
    visible = np.isfinite(pixels).all(1) & (pixels[:, 0] > -0.5) & (pixels[:, 0] < truth.width - 0.5) \
        & (pixels[:, 1] > -0.5) & (pixels[:, 1] < truth.height - 0.5)
    keyframe_index, point_index, pixels = keyframe_index[visible], point_index[visible], pixels[visible]
    # Landmarks left with fewer than three views are dropped (the frontend would not keep them).
    kept = np.flatnonzero(np.bincount(point_index, minlength=landmarks) >= 3)
    renumber = -np.ones(landmarks, int)
    renumber[kept] = np.arange(len(kept))
    rows = renumber[point_index] >= 0
    keyframe_index, point_index, pixels = keyframe_index[rows], renumber[point_index[rows]], pixels[rows]
    points_true, depth = points_true[kept], depth[kept]
    pixels = pixels + rng.normal(0, noise_px, pixels.shape)
    outlier = rng.random(len(pixels)) < outlier_fraction
    offset = rng.uniform(10, 40, outlier.sum()) * np.exp(1j * rng.uniform(0, 2 * np.pi, outlier.sum()))
    pixels[outlier] += np.stack((offset.real, offset.imag), -1)
    # Start values: the prior camera (centre, no distortion, focal off), noisy poses and points.
    factor = 1 + rng.choice([-1, 1]) * rng.uniform(*focal_error)
    if warm:
        # The VO's steady state: the camera carried over from the last window (focal 0.5-1 % off,
        # distortion 10 % off), the window's poses and landmarks refined before, a new keyframe.
        factor = 1 + rng.choice([-1, 1]) * rng.uniform(0.005, 0.01)
        D0 = truth.D * rng.uniform(0.9, 1.1, truth.D.shape)
        centre = (truth.cx + rng.normal(0, 1.0), truth.cy + rng.normal(0, 1.0))
        pose_noise, point_noise = (0.002, 0.1), 0.01
    else:
        D0 = np.zeros_like(truth.D)
        centre = ((truth.width - 1) / 2, (truth.height - 1) / 2)
    start = CameraCalibration.pinhole(truth.width, truth.height, truth.fx * factor, truth.fy * factor, *centre,
                                      D=D0, distortion_model=truth.distortion_model)
    fixed = np.zeros(keyframes, bool)
    fixed[:2] = True
    poses_start = poses_true.copy()
    for k in np.flatnonzero(~fixed):
        poses_start[k, :3, 3] += rng.normal(0, pose_noise[0] / np.sqrt(3), 3)
        poses_start[k, :3, :3] = poses_start[k, :3, :3] @ Rotation.from_rotvec(rng.normal(0, np.radians(pose_noise[1]) / np.sqrt(3), 3)).as_matrix()
    points_start = points_true + rng.normal(0, 1, points_true.shape) * depth[:, None] * point_noise / np.sqrt(3)
    return Problem(truth, start, poses_true, poses_start, points_true, points_start, keyframe_index, point_index,
                   pixels, outlier, fixed)


@dataclass
class Result:
    params: np.ndarray  # (fx, fy, cx, cy, d1..d4), OpenCV pixel convention
    poses: np.ndarray
    points: np.ndarray
    iterations: int
    seconds: float
    cpu_seconds: float = float("nan")
    covariance_seconds: float = float("nan")
    camera_covariance: np.ndarray | None = None


def camera_vector(camera: CameraCalibration) -> np.ndarray:
    return np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], camera.D[:4]])


def calibration_of(params: np.ndarray, like: CameraCalibration) -> CameraCalibration:
    D = np.zeros_like(like.D)
    D[:4] = params[4:]
    return CameraCalibration.pinhole(like.width, like.height, params[0], params[1], params[2], params[3],
                                     D=D, distortion_model=like.distortion_model)


# --------------------------------------------------------------------------------------------------
# GTSAM 4.3: GeneralSFMFactor2 with Cal3DS2 / Cal3Fisheye, Levenberg-Marquardt (and iSAM2)
# --------------------------------------------------------------------------------------------------


def solve_gtsam(problem: Problem, loss: str, threshold: float, iterations: int, tolerance: float, covariance: bool,
                isam2: bool = False, ceres_lm: bool = False) -> Result:
    import gtsam
    from gtsam.symbol_shorthand import K, L, X

    started = time.perf_counter()
    p = problem
    fisheye = p.start.distortion_model == "equidistant"
    Cal, Factor = (gtsam.Cal3Fisheye, gtsam.GeneralSFMFactor2Cal3Fisheye) if fisheye else (gtsam.Cal3DS2, gtsam.GeneralSFMFactor2Cal3DS2)
    v = camera_vector(p.start)
    calibration = Cal(v[0], v[1], 0.0, v[2], v[3], *v[4:])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    robust = (gtsam.noiseModel.mEstimator.Huber if loss == "huber" else gtsam.noiseModel.mEstimator.Cauchy).Create(threshold)
    noise = gtsam.noiseModel.Robust.Create(robust, gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    for m in range(len(p.pixels)):
        graph.add(Factor(p.pixels[m], noise, X(int(p.keyframe_index[m])), L(int(p.point_index[m])), K(0)))
    for k, T in enumerate(p.poses_start):
        values.insert(X(k), gtsam.Pose3(T))
        if p.fixed[k]:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for j, point in enumerate(p.points_start):
        values.insert(L(j), point)
    values.insert(K(0), calibration)
    # The skew is no parameter of OpenCV's models: pin it. A weak prior on the rest stands in for
    # the camera information the VO carries from window to window (here: 30 % of f on the focal).
    sigmas = np.array([0.3 * v[0], 0.3 * v[1], 1e-6, 0.1 * v[0], 0.1 * v[1], 1.0, 1.0, 1.0, 1.0])
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    graph.add((gtsam.PriorFactorCal3Fisheye if fisheye else gtsam.PriorFactorCal3DS2)(K(0), calibration, prior_noise))
    if isam2:
        parameters = gtsam.ISAM2Params()
        # Relinearise everything on every update: without it iSAM2 (relinearizeSkip 10) stalls here.
        parameters.setRelinearizeThreshold(0.0)
        parameters.relinearizeSkip = 1
        solver = gtsam.ISAM2(parameters)
        count = 0
        try:
            solver.update(graph, values)
            count = 1
            for count in range(2, iterations + 1):
                before = graph.error(solver.calculateEstimate())
                solver.update()
                after = graph.error(solver.calculateEstimate())
                if before - after < tolerance * before:
                    break
            result = solver.calculateEstimate()
        except RuntimeError:
            # Gauss-Newton without damping (Dogleg too) met an indeterminate system: counted as a
            # failure, scored at the start values.
            result, count = values, -1
        iterations_done = count
    else:
        # Ceres' LM policy (damping scaled by the Hessian's diagonal, lambda from 1e-4) against
        # GTSAM's default (identity damping, lambda from 1e-5): measured in BENCHMARKS.md.
        parameters = gtsam.LevenbergMarquardtParams.CeresDefaults() if ceres_lm else gtsam.LevenbergMarquardtParams()
        parameters.setMaxIterations(iterations)
        parameters.setRelativeErrorTol(tolerance)
        parameters.setAbsoluteErrorTol(1e-9)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, parameters)
        result = optimizer.optimize()
        iterations_done = optimizer.iterations()
    fitted = result.atCal3Fisheye(K(0)) if fisheye else result.atCal3DS2(K(0))
    # localCoordinates from the zero-skew start is (fx, fy, s, u0, v0, d1..d4) minus the start's.
    params = np.delete(calibration.localCoordinates(fitted), 2) + v
    poses = np.stack([result.atPose3(X(k)).matrix() for k in range(len(p.poses_start))])
    points = np.stack([result.atPoint3(L(j)) for j in range(len(p.points_start))])
    seconds = time.perf_counter() - started
    out = Result(params, poses, points, iterations_done, seconds)
    if covariance:
        started = time.process_time()
        # A landmark that ended behind a camera has a zero Jacobian there (GTSAM's cheirality
        # guard): the covariance is taken over the observations in front of their cameras.
        depth = np.einsum("mji,mj->mi", poses[p.keyframe_index, :3, :3],
                          points[p.point_index] - poses[p.keyframe_index, :3, 3])[:, 2]
        front = depth > 0
        seen = np.bincount(p.point_index[front], minlength=len(points)) >= 2
        kept = gtsam.NonlinearFactorGraph()
        for m in np.flatnonzero(front & seen[p.point_index]):
            kept.add(graph.at(int(m)))
        for m in range(len(p.pixels), graph.size()):
            kept.add(graph.at(m))
        kept_values = gtsam.Values()
        for k in range(len(poses)):
            kept_values.insert(X(k), result.atPose3(X(k)))
        # A landmark the data cannot place (a track of nearly parallel rays, run off to kilometres)
        # would make the system indeterminate: a 100 m prior holds it without informing the rest.
        weak = gtsam.noiseModel.Isotropic.Sigma(3, 100.0)
        for j in np.flatnonzero(seen):
            kept_values.insert(L(int(j)), points[j])
            kept.add(gtsam.PriorFactorPoint3(L(int(j)), points[j], weak))
        kept_values.insert(K(0), fitted)
        marginals = gtsam.Marginals(kept, kept_values)
        full = marginals.marginalCovariance(K(0))
        keep = [0, 1, 3, 4, 5, 6, 7, 8]
        out.camera_covariance = full[np.ix_(keep, keep)]
        out.covariance_seconds = time.process_time() - started
    return out


# --------------------------------------------------------------------------------------------------
# pycolmap 4.2.1: COLMAP's bundle adjuster (Ceres), OPENCV / OPENCV_FISHEYE
# --------------------------------------------------------------------------------------------------


def solve_pycolmap(problem: Problem, loss: str, threshold: float, iterations: int, tolerance: float,
                   covariance: bool) -> Result:
    import pycolmap

    started = time.perf_counter()
    p = problem
    fisheye = p.start.distortion_model == "equidistant"
    v = camera_vector(p.start)
    # COLMAP puts pixel centres at +0.5 (image corner at 0, 0); OpenCV at integers.
    params = v.copy()
    params[2:4] += 0.5
    camera = pycolmap.Camera(model="OPENCV_FISHEYE" if fisheye else "OPENCV", width=p.start.width,
                             height=p.start.height, params=params, camera_id=1)
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(camera)
    order = np.argsort(p.keyframe_index, kind="stable")
    observation_slot = np.empty(len(order), int)
    config = pycolmap.BundleAdjustmentConfig()
    for k, T in enumerate(p.poses_start):
        rows = order[p.keyframe_index[order] == k]
        observation_slot[rows] = np.arange(len(rows))
        image = pycolmap.Image(name=f"{k}", keypoints=p.pixels[rows] + 0.5, camera_id=1, image_id=k + 1)
        T_c_w = np.linalg.inv(T)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(T_c_w[:3]))
        config.add_image(k + 1)
        if p.fixed[k]:
            config.set_constant_rig_from_world_pose(k + 1)
    tracks = [[] for _ in range(len(p.points_start))]
    for m in range(len(p.pixels)):
        tracks[p.point_index[m]].append(pycolmap.TrackElement(int(p.keyframe_index[m]) + 1, int(observation_slot[m])))
    point_ids = [reconstruction.add_point3D(xyz, pycolmap.Track(track)) for xyz, track in zip(p.points_start, tracks)]
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = True
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER if loss == "huber" else pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = threshold
    options.ceres.solver_options.num_threads = 1
    options.ceres.solver_options.max_num_iterations = iterations
    options.ceres.solver_options.function_tolerance = tolerance  # as GTSAM's relative error tolerance
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)
    summary = adjuster.solve()
    fitted = reconstruction.cameras[1].params.copy()
    fitted[2:4] -= 0.5
    poses = np.stack([np.linalg.inv(np.vstack([reconstruction.images[k + 1].cam_from_world().matrix(), [0, 0, 0, 1]]))
                      for k in range(len(p.poses_start))])
    points = np.stack([reconstruction.points3D[i].xyz for i in point_ids])
    ceres = summary.todict()["ceres_summary"]
    iterations_done = ceres["num_successful_steps"] + ceres["num_unsuccessful_steps"]
    seconds = time.perf_counter() - started
    out = Result(fitted, poses, points, iterations_done, seconds)
    if covariance:
        started = time.process_time()
        estimate = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), reconstruction, adjuster)
        if estimate is not None:
            out.camera_covariance = estimate.get_other_params_cov(reconstruction.cameras[1].params)
        out.covariance_seconds = time.process_time() - started
    return out


# --------------------------------------------------------------------------------------------------
# scipy least_squares (trf, sparse finite-difference Jacobian, lsmr) through CameraCalibration.project
# --------------------------------------------------------------------------------------------------


def solve_scipy(problem: Problem, loss: str, threshold: float, iterations: int, tolerance: float,
                covariance: bool) -> Result:
    started = time.perf_counter()
    p = problem
    free = np.flatnonzero(~p.fixed)
    K, L, M = len(free), len(p.points_start), len(p.pixels)
    row_of = -np.ones(len(p.fixed), int)
    row_of[free] = np.arange(K)
    v0 = camera_vector(p.start)

    def unpack(x):
        params = x[:8]
        poses = p.poses_start.copy()
        rv = x[8:8 + 6 * K].reshape(K, 6)
        poses[free, :3, :3] = Rotation.from_rotvec(rv[:, :3]).as_matrix()
        poses[free, :3, 3] = rv[:, 3:]
        return params, poses, x[8 + 6 * K:].reshape(L, 3)

    def residual(x):
        params, poses, points = unpack(x)
        camera = calibration_of(params, p.start)
        R = poses[p.keyframe_index, :3, :3]
        t = poses[p.keyframe_index, :3, 3]
        points_c = np.einsum("mji,mj->mi", R, points[p.point_index] - t)
        pixels = camera.project(points_c)
        return np.nan_to_num(pixels - p.pixels, nan=1e3).ravel()

    x0 = np.concatenate([v0, np.concatenate([Rotation.from_matrix(p.poses_start[free, :3, :3]).as_rotvec(),
                                             p.poses_start[free, :3, 3]], 1).ravel(), p.points_start.ravel()])
    rows = np.arange(2 * M)
    sparsity = scipy.sparse.lil_matrix((2 * M, len(x0)), dtype=int)
    sparsity[:, :8] = 1
    pose_row = row_of[p.keyframe_index]
    for d in range(6):
        has = np.repeat(pose_row >= 0, 2)
        sparsity[rows[has], 8 + 6 * np.repeat(pose_row, 2)[has] + d] = 1
    for d in range(3):
        sparsity[rows, 8 + 6 * K + 3 * np.repeat(p.point_index, 2) + d] = 1
    solution = least_squares(residual, x0, jac_sparsity=sparsity.tocsr(), method="trf", loss=loss, f_scale=threshold,
                             x_scale="jac", max_nfev=iterations, ftol=tolerance, tr_solver="lsmr")
    params, poses, points = unpack(solution.x)
    seconds = time.perf_counter() - started
    out = Result(params, poses, points, solution.nfev, seconds)
    if covariance:
        started = time.process_time()
        # Gauss-Newton information with the robust weights at the solution, then the camera block
        # of its inverse (dense: ~1000 unknowns).
        J = solution.jac.toarray()
        r = solution.fun.reshape(-1, 2)
        s = (r**2).sum(1) / threshold**2
        weight = np.where(s <= 1, 1.0, 1 / np.sqrt(s)) if loss == "huber" else 1 / (1 + s)
        W = np.repeat(weight, 2)
        information = J.T @ (J * W[:, None])
        out.camera_covariance = np.linalg.pinv(information)[:8, :8]
        out.covariance_seconds = time.process_time() - started
    return out


# --------------------------------------------------------------------------------------------------
# The module itself (GTSAM, what the VO calls): validation, inlier mask and RMS included
# --------------------------------------------------------------------------------------------------


def solve_module(problem: Problem, loss: str, threshold: float, iterations: int, tolerance: float,
                 covariance: bool) -> Result:
    from nocal_ros.odometry.bundle_adjustment import WindowProblem, bundle_adjust

    started = time.perf_counter()
    p = problem
    window = WindowProblem(p.start, p.poses_start, p.fixed, p.points_start, p.keyframe_index, p.point_index, p.pixels,
                           robust_threshold_px=threshold, robust_loss=loss, max_iterations=iterations,
                           relative_tolerance=tolerance, camera_covariance=covariance, pixel_sigma=0.5)
    solution = bundle_adjust(window)
    out = Result(camera_vector(solution.calibration), solution.poses, solution.points, solution.iterations,
                 time.perf_counter() - started)
    if covariance:
        out.covariance_seconds = solution.covariance_cpu_seconds
        out.camera_covariance = solution.camera_covariance
    return out


# --------------------------------------------------------------------------------------------------
# Scoring and the loop
# --------------------------------------------------------------------------------------------------


def score(problem: Problem, result: Result) -> dict:
    truth = camera_vector(problem.truth)
    focal = 100 * np.mean(np.abs(result.params[:2] / truth[:2] - 1))
    free = np.flatnonzero(~problem.fixed)
    rotation = [np.degrees(Rotation.from_matrix(result.poses[k, :3, :3].T @ problem.poses_true[k, :3, :3]).magnitude()) for k in free]
    position = np.linalg.norm(result.poses[free, :3, 3] - problem.poses_true[free, :3, 3], axis=1)
    point = np.linalg.norm(result.points - problem.points_true, axis=1)
    camera = calibration_of(result.params, problem.start)
    R = result.poses[problem.keyframe_index, :3, :3]
    t = result.poses[problem.keyframe_index, :3, 3]
    points_c = np.einsum("mji,mj->mi", R, result.points[problem.point_index] - t)
    error = np.linalg.norm(camera.project(points_c) - problem.pixels, axis=1)
    inlier = ~problem.outlier
    return {
        "focal_pct": focal,
        "pp_px": float(np.linalg.norm(result.params[2:4] - truth[2:4])),
        "rot_deg": float(np.max(rotation)),
        "pos_mm": 1000 * float(np.max(position)),
        "point_mm": 1000 * float(np.median(point)),
        # Median, not RMS: a far landmark that ran off behind a camera (the fisheye's distant,
        # low-parallax tracks) would dominate an RMS with one observation.
        "med_px": float(np.nanmedian(error[inlier])),
        "outliers_flagged": float(np.mean(error[problem.outlier] > 2.0)),
    }


SOLVERS = {
    "module": lambda pr, a, cov: solve_module(pr, a.loss, a.threshold, a.iterations, a.tolerance, cov),
    "gtsam-lm": lambda pr, a, cov: solve_gtsam(pr, a.loss, a.threshold, a.iterations, a.tolerance, cov),
    "gtsam-lm-ceres": lambda pr, a, cov: solve_gtsam(pr, a.loss, a.threshold, a.iterations, a.tolerance, cov, ceres_lm=True),
    "gtsam-isam2": lambda pr, a, cov: solve_gtsam(pr, a.loss, a.threshold, a.iterations, a.tolerance, cov, isam2=True),
    "pycolmap": lambda pr, a, cov: solve_pycolmap(pr, a.loss, a.threshold, a.iterations, a.tolerance, cov),
    "scipy-trf": lambda pr, a, cov: solve_scipy(pr, a.loss, a.threshold, a.iterations, a.tolerance, cov),
}


def timed(solve):
    """The solver with its process (CPU) time recorded: on a shared machine wall time includes waiting."""
    def run(problem, args, covariance):
        started = time.process_time()
        result = solve(problem, args, covariance)
        result.cpu_seconds = time.process_time() - started
        return result
    return run


def python_overhead(problem: Problem) -> float:
    """CPU seconds to build the module's GTSAM graph and values in Python (one factor per observation)."""
    import gtsam
    from gtsam.symbol_shorthand import K, L, X

    started = time.process_time()
    p = problem
    v = camera_vector(p.start)
    fisheye = p.start.distortion_model == "equidistant"
    Factor = gtsam.GeneralSFMFactor2Cal3Fisheye if fisheye else gtsam.GeneralSFMFactor2Cal3DS2
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(4.0), gtsam.noiseModel.Isotropic.Sigma(2, 0.5))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for m in range(len(p.pixels)):
        graph.add(Factor(p.pixels[m], noise, X(int(p.keyframe_index[m])), L(int(p.point_index[m])), K(0)))
    for k, T in enumerate(p.poses_start):
        values.insert(X(k), gtsam.Pose3(T))
    for j, point in enumerate(p.points_start):
        values.insert(L(j), point)
    values.insert(K(0), (gtsam.Cal3Fisheye if fisheye else gtsam.Cal3DS2)(v[0], v[1], 0.0, v[2], v[3], *v[4:]))
    return time.process_time() - started


def gil_stall(problem: Problem, args) -> None:
    """Does a solve hold the GIL? The longest gap of a thread sleeping 1 ms in a loop beside it."""
    import threading

    for name in ("module", "pycolmap"):
        solve = SOLVERS[name]
        solve(problem, args, True)
        stop, gaps = threading.Event(), []

        def tick():
            last = time.perf_counter()
            while not stop.is_set():
                time.sleep(0.001)
                now = time.perf_counter()
                gaps.append(now - last)
                last = now

        thread = threading.Thread(target=tick)
        thread.start()
        started = time.perf_counter()
        solve(problem, args, True)
        seconds = time.perf_counter() - started
        stop.set()
        thread.join()
        print(f"GIL: {name} solve (with covariance) {1000 * seconds:.0f} ms wall; the other thread's longest "
              f"gap {1000 * max(gaps):.0f} ms (median {1000 * statistics.median(gaps):.1f} ms)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=("plumb_bob", "equidistant"), default="plumb_bob")
    parser.add_argument("--problems", type=int, default=10, help="problems (seeds) per solver")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--solvers", default=",".join(SOLVERS))
    parser.add_argument("--loss", choices=("huber", "cauchy"), default="huber")
    parser.add_argument("--threshold", type=float, default=2.0, help="robust loss scale, px")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--tolerance", type=float, default=1e-5,
                        help="stop when the cost falls by less than this fraction (GTSAM relativeErrorTol, Ceres "
                             "function_tolerance, scipy ftol)")
    parser.add_argument("--start", choices=("cold", "warm"), default="cold",
                        help="cold: the prior camera (focal 10-20 %% off, no distortion), poses 1 cm / 0.5 deg and "
                             "points 5 %% off; warm: the VO's steady state (focal 0.5-1 %% off, poses 2 mm / 0.1 deg, "
                             "points 1 %%)")
    parser.add_argument("--gil", action="store_true", help="only measure whether a solve blocks another Python thread")
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--landmarks", type=int, default=300)
    args = parser.parse_args()

    problems = [make_problem(args.model, seed, args.keyframes, args.landmarks, warm=args.start == "warm")
                for seed in range(args.problems)]
    observations = statistics.median(len(p.pixels) for p in problems)
    load = os.getloadavg()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {load[0]:.1f} "
          f"{load[1]:.1f} {load[2]:.1f}; one thread")
    print(f"problem: {args.model} {problems[0].truth.width}x{problems[0].truth.height}, K={args.keyframes}, "
          f"L={args.landmarks}, {args.start} start, median M={observations:.0f} observations, {args.problems} problems, "
          f"loss {args.loss} {args.threshold} px, max {args.iterations} iterations, tolerance {args.tolerance:g}")
    if args.gil:
        gil_stall(problems[0], args)
        return
    overhead = [python_overhead(p) for p in problems]
    print(f"python overhead: building the GTSAM graph and values: median {1000 * statistics.median(overhead):.1f} ms CPU")
    print(f"{'solver':14s} {'ms/solve':>9s} {'cpu ms':>7s} {'cov cpu':>7s} {'iters':>5s} {'focal %':>8s} {'pp px':>6s} "
          f"{'rot deg':>8s} {'pos mm':>7s} {'pt mm':>6s} {'med px':>6s} {'outl':>5s}  (median over problems; rot/pos: worst keyframe)")
    for name in args.solvers.split(","):
        solve = timed(SOLVERS[name])
        for problem in problems[: args.warmup]:
            solve(problem, args, True)
        runs = [solve(problem, args, False) for problem in problems]
        covariances = [solve(problem, args, True) for problem in problems[: max(3, args.problems // 3)]]
        scores = [score(problem, run) for problem, run in zip(problems, runs)]
        med = lambda key: statistics.median(s[key] for s in scores)
        cov_ms = 1000 * statistics.median(c.covariance_seconds for c in covariances)
        print(f"{name:14s} {1000 * statistics.median(r.seconds for r in runs):9.1f} "
              f"{1000 * statistics.median(r.cpu_seconds for r in runs):7.1f} {cov_ms:7.1f} "
              f"{statistics.median(r.iterations for r in runs):5.0f} {med('focal_pct'):8.3f} {med('pp_px'):6.2f} "
              f"{med('rot_deg'):8.3f} {med('pos_mm'):7.2f} {med('point_mm'):6.1f} {med('med_px'):6.3f} "
              f"{med('outliers_flagged'):5.2f}   worst focal {max(s['focal_pct'] for s in scores):.3f} %")


if __name__ == "__main__":
    main()
