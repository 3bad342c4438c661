"""Camera initialisation: the first estimate of an uncalibrated camera, chosen among focal hypotheses.

The first keyframes of a map are posed through the starting camera (``f = width`` for a camera nobody
calibrated), which can be far from the truth. A bundle adjustment that starts from those poses keeps
their projective distortion and settles in the wrong basin: on a 160x120 camera with a 95 px focal
length (80 degrees across), six keyframes posed at ``f = 160`` led a solve with the lens free to
224 px and ``k1 = +0.7``; rebuilt from their tracks at ``f = 96`` the same observations solved to
95 px (measured).

So :func:`initialise_camera` rebuilds the map from its observations alone once per focal hypothesis
(two-view geometry between the first keyframe and the one that sees the most of its tracks moved
furthest, PnP on rays for the others, triangulation), bundle-adjusts each with the focal length,
principal point and lens free, and keeps the one whose every observation, re-triangulated through the
solved camera and poses, reprojects best (a truncated quadratic, so no hypothesis gains from the
observations it failed to rebuild). The map as tracking built it, solved the same way, is one of the
candidates: the result is never worse by that score than the plain solve. At the end of a replay the
same choice, between the plain solve of a whole map and its rebuild through the converged camera
(``starts``), takes the frames tracked through an early wrong camera out of their basin.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace
from functools import partial

import numpy as np

from nocal_ros.lens import CameraCalibration
from nocal_ros.odometry.bundle_adjustment import WindowProblem, WindowSolution, bundle_adjust
from nocal_ros.odometry.frontend import solve_pnp
from nocal_ros.odometry.initializer import two_view_map
from nocal_ros.odometry.map import triangulate

#: Starting focal lengths as shares of the image width, a factor 1.12 apart from 0.404 to 1.254 (about
#: 110 down to 44 degrees across). The right basin can be that narrow: on KITTI's drive (1241 px wide,
#: 719 px focal, turning 2.7 degrees per frame) only starts from 670 to 757 px rebuilt into it and beat
#: the plain solve (measured: a scan of starts 0.52-0.66 x width). The earlier six hypotheses (0.4, 0.5,
#: 0.65, 0.8, 1.0, 1.25) started at 620 and 807 px and missed it, and the plain solve's 1366 px (k1 +0.45
#: for a lens with none) was chosen: published focal error 71 %; 4.8 % with these eleven.
FOCAL_HYPOTHESES = tuple(round(1.12 ** k, 3) for k in range(-8, 3))
#: Fewest tracks the first keyframe must share with the other keyframe of the two-view start.
MIN_SHARED_TRACKS = 40


def _observations(problem: WindowProblem, normalised: np.ndarray) -> list[dict[int, int]]:
    """Per keyframe row: landmark row -> observation row (finite rays only)."""
    seen: list[dict[int, int]] = [{} for _ in range(len(problem.poses))]
    finite = np.isfinite(normalised).all(1)
    for m in np.flatnonzero(finite):
        seen[int(problem.keyframe_index[m])][int(problem.point_index[m])] = int(m)
    return seen


def _triangulate_missing(points: np.ndarray, poses: np.ndarray, posed: np.ndarray, seen: list[dict[int, int]],
                         normalised: np.ndarray) -> None:
    """Landmarks without a position, from the first and last posed keyframes that see them (in place).

    One triangulation per pair of keyframes, not per landmark: a landmark's point depends on its own two
    rays alone, and per landmark this was a third of a camera initialisation's time (measured).
    """
    rows = np.flatnonzero(posed)
    missing = np.flatnonzero(~np.isfinite(points).all(1))
    if len(rows) < 2 or len(missing) == 0:
        return
    observation = np.full((len(rows), len(points)), -1, dtype=np.int64)  # posed row, landmark -> observation
    for r, k in enumerate(rows.tolist()):
        if seen[k]:
            observation[r, list(seen[k].keys())] = list(seen[k].values())
    views = observation[:, missing] >= 0
    twice = views.sum(0) >= 2
    missing, views = missing[twice], views[:, twice]
    first = views.argmax(0)
    last = len(rows) - 1 - views[::-1].argmax(0)
    for a, b in sorted(set(zip(first.tolist(), last.tolist()))):
        group = missing[(first == a) & (last == b)]
        i, j = int(rows[a]), int(rows[b])
        found = triangulate(poses[i], poses[j], normalised[observation[a, group]], normalised[observation[b, group]])
        ok = np.isfinite(found).all(1)
        for k in (i, j):
            ok &= ((found - poses[k][:3, 3]) @ poses[k][:3, :3])[:, 2] > 0
        points[group[ok]] = found[ok]


def rebuild(problem: WindowProblem, calibration) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Poses ``(K, 4, 4)`` and landmarks ``(L, 3)`` (NaN where not rebuilt) from the observations alone,
    seen through ``calibration``, in the first keyframe's frame with a unit baseline to keyframe ``j``;
    returns ``(poses, points, j)``, or None when the keyframes cannot all be posed."""
    count, landmarks = len(problem.poses), len(problem.points)
    normalised = calibration.undistorted_normalised(problem.pixels)
    seen = _observations(problem, normalised)
    threshold = problem.robust_threshold_px / calibration.fx
    best, best_score = None, 0.0
    for j in range(1, count):
        shared = [q for q in seen[0] if q in seen[j]]
        if len(shared) < MIN_SHARED_TRACKS:
            continue
        a = normalised[[seen[0][q] for q in shared]]
        b = normalised[[seen[j][q] for q in shared]]
        score = float(np.median(np.linalg.norm(a - b, axis=1))) * np.sqrt(len(shared))
        if score > best_score:
            best, best_score = j, score
    if best is None:
        return None
    shared = np.array([q for q in seen[0] if q in seen[best]])
    start = two_view_map(normalised[[seen[0][q] for q in shared]], normalised[[seen[best][q] for q in shared]],
                         threshold, min_points=20, min_parallax_deg=0.3)
    if start is None:
        return None
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[best] = start.T_ref_cur
    posed = np.zeros(count, dtype=bool)
    posed[[0, best]] = True
    points = np.full((landmarks, 3), np.nan)
    points[shared[start.inliers]] = start.points
    _triangulate_missing(points, poses, posed, seen, normalised)
    while not posed.all():
        # The keyframe that sees the most rebuilt landmarks next.
        known = np.isfinite(points).all(1)
        candidates = np.flatnonzero(~posed)
        counts = [sum(1 for q in seen[k] if known[q]) for k in candidates]
        k = int(candidates[int(np.argmax(counts))])
        rows = np.array([q for q in seen[k] if known[q]], dtype=np.int64)
        if len(rows) < 12:
            return None
        pnp = solve_pnp(points[rows], normalised[[seen[k][q] for q in rows]], threshold, covariance=False)
        if pnp is None:
            return None
        poses[k] = pnp.T_w_c
        posed[k] = True
        _triangulate_missing(points, poses, posed, seen, normalised)
    return poses, points, best


def reprojection_score(problem: WindowProblem, solution: WindowSolution) -> float:
    """Mean truncated squared reprojection error (px^2, at most the robust threshold squared) of every
    observation, its landmark re-triangulated from its first and last views through the solution."""
    calibration, poses = solution.calibration, solution.poses
    normalised = calibration.undistorted_normalised(problem.pixels)
    seen = _observations(problem, normalised)
    points = np.full((len(problem.points), 3), np.nan)
    _triangulate_missing(points, poses, np.ones(len(poses), dtype=bool), seen, normalised)
    k, q = problem.keyframe_index, problem.point_index
    points_c = np.einsum("mji,mj->mi", poses[k, :3, :3], points[q] - poses[k, :3, 3])
    valid = np.isfinite(points_c).all(1) & (points_c[:, 2] > 0)
    errors = np.full(len(k), np.inf)
    errors[valid] = np.linalg.norm(calibration.project(points_c[valid]) - problem.pixels[valid], axis=1)
    errors[~np.isfinite(errors)] = np.inf
    return float(np.mean(np.minimum(errors, problem.robust_threshold_px) ** 2))


def _in_frame_of(problem: WindowProblem, poses: np.ndarray, points: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
    """A rebuild moved into the problem's frame and scale: its keyframe 0 at the problem's, and the
    distance of the problem's scale pair kept."""
    i0, i1 = problem.scale_pair if problem.scale_pair is not None else (0, j)
    scale = (np.linalg.norm(problem.poses[i1, :3, 3] - problem.poses[i0, :3, 3])
             / max(np.linalg.norm(poses[i1, :3, 3] - poses[i0, :3, 3]), 1e-12))
    anchor = problem.poses[0]
    moved = poses.copy()
    moved[:, :3, 3] *= scale
    moved = anchor @ moved
    moved_points = (points * scale) @ anchor[:3, :3].T + anchor[:3, 3]
    return moved, moved_points


def initialise_camera(problem: WindowProblem, focal_shares: tuple[float, ...] = FOCAL_HYPOTHESES,
                      starts: tuple[CameraCalibration, ...] = (),
                      map_candidates: Callable[..., Iterable] = map) -> tuple[WindowSolution, list[tuple[float, float, float]]]:
    """The best of the plain solve of ``problem`` and a rebuild-and-solve per focal hypothesis.

    ``problem``: every keyframe of the map with keyframe 0 fixed and a ``scale_pair``, the camera free.
    ``starts``: cameras to rebuild through besides the hypotheses' (the end of a replay rebuilds its map
    through the converged camera alone, ``focal_shares=()``).
    ``map_candidates``: ``map``'s signature, applied to :func:`camera_candidate` over the candidates' starts
    (``None``, the plain solve, first); the local mapping of a live stream spreads them over its solver
    processes. Each candidate seeds its own draws, so the choice is the same either way.
    Returns the chosen solution (its ``points`` NaN and its ``inliers`` False where a rebuild left a
    landmark out) and ``(start focal, solved focal, score)`` per candidate, the plain solve first.
    """
    like = problem.calibration
    hypotheses = [CameraCalibration.pinhole(like.width, like.height, share * like.width, D=np.zeros_like(like.D),
                                            distortion_model=like.distortion_model, camera_name=like.camera_name)
                  for share in focal_shares]
    candidates = list(map_candidates(partial(camera_candidate, problem), [None, *hypotheses, *starts]))
    report = [row for row, _ in candidates]
    plain = candidates[0][1]
    scored = [(row[2], solution) for row, solution in candidates
              if solution is not None and (solution is not plain or plain.success)]
    if not scored:
        return plain, report
    return min(scored, key=lambda pair: pair[0])[1], report


def camera_candidate(problem: WindowProblem, start: CameraCalibration | None
                     ) -> tuple[tuple[float, float, float], WindowSolution | None]:
    """One candidate of :func:`initialise_camera`: the plain solve of ``problem`` (``start`` None) or its
    rebuild through ``start``, solved; ``((start focal, solved focal, score), solution)``, the score
    infinite where the solve failed (the plain solve is returned all the same, the rebuild is None)."""
    if start is None:
        plain = bundle_adjust(problem)
        score = reprojection_score(problem, plain) if plain.success else np.inf
        return (problem.calibration.fx, plain.calibration.fx, score), plain
    solution = _rebuilt_solution(problem, start)
    if solution is None:
        return (start.fx, np.nan, np.inf), None
    return (start.fx, solution.calibration.fx, reprojection_score(problem, solution)), solution


def _rebuilt_solution(problem: WindowProblem, start: CameraCalibration) -> WindowSolution | None:
    """The map of ``problem`` rebuilt through ``start`` and solved, in the problem's frame and rows
    (landmarks the rebuild left out: NaN, and their observations not inliers); None when it failed."""
    rebuilt = rebuild(problem, start)
    if rebuilt is None:
        return None
    poses, points, j = rebuilt
    poses, points = _in_frame_of(problem, poses, points, j)
    known = np.isfinite(points).all(1)
    index = np.full(len(points), -1)
    index[known] = np.arange(known.sum())
    used = known[problem.point_index]
    subproblem = replace(problem, calibration=start, poses=poses, points=points[known],
                         keyframe_index=problem.keyframe_index[used], point_index=index[problem.point_index[used]],
                         pixels=problem.pixels[used])
    try:
        solution = bundle_adjust(subproblem)
    except Exception:  # noqa: BLE001 - a rebuild the solver rejects is a hypothesis that lost
        return None
    if not solution.success:
        return None
    full_points = np.full((len(problem.points), 3), np.nan)
    full_points[known] = solution.points
    inliers = np.zeros(len(problem.pixels), dtype=bool)
    inliers[used] = solution.inliers
    residuals = np.full(len(problem.pixels), np.inf)
    residuals[used] = solution.residuals_px
    return replace(solution, points=full_points, inliers=inliers, residuals_px=residuals)
