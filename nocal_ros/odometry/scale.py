"""Metric scale for monocular VO: from arm poses by a similarity fit, from the ground plane and a known
camera height, else from the pose head.

A monocular map is correct up to one scale factor ``s`` (metres per map unit). Three sources measure it:

* **Arm poses** (a bag topic, or TF base -> tool on a live robot): the camera positions the arm reports
  at keyframes, against the same keyframes' map positions. A similarity (Umeyama) fit gives ``s``; it
  needs three keyframes with arm poses that do not all sit at one point. It is refitted at every
  keyframe, as the map's keyframes move and more arm poses arrive.
* **The NOCaL pose head**: trained with arm poses, it predicts a metric translation for a frame pair.
  The estimator measures it once, on the pair that defines the map's unit (its first two keyframes),
  and keeps it: a scale that changes mid-stream makes the trajectory inconsistent with itself, and more
  pose head pairs did not make it more accurate (measured on five held-out bags: its error is a bias
  per camera and scene, x1.3-4.4 there; APE Sim(3) 4.6 cm mean when kept, 7.8 cm when refined).

* **The ground plane** (a robot whose camera's height above the floor or road is known, as KITTI's
  1.65 m or a ground robot's ``base_footprint -> camera`` transform gives it): the map's landmarks
  below the cameras are searched by RANSAC for a plane whose normal is near the expected down
  direction, and beneath it again where many landmarks lie far beneath it (the top of a table or box:
  :func:`fit_ground_plane`); the cameras' median height above it, in map units, against the known
  height gives ``s`` (:func:`fit_ground_scale`). Measured on the final maps of the dev bags with
  the bag's mean true height: 0.976-1.021 of the true scale on 18 rendered maps, 1.058 on r160_202's
  (found beneath a plane rejected), none on r640_304's first five keyframes, and 0.997 on KITTI's frames
  20-50 with its 1.65 m, where the pose head's scale was off by x0.2-51.
  Before a window shows enough of the ground for a plane (a road's landmarks are few: its tracks stretch
  as they near and last about a frame), the ground's homography between consecutive frames measures the
  step over the height from the tracks alone (:func:`ground_motion_ratio`, its normal within the same
  tilt of the expected down).

Arm poses win whenever a fit is possible, then the ground plane; ``source`` says which was used.

Live, the fit moves the map's scale but not its shape, which drifts between arm poses. At the end of a
replay (:meth:`~nocal_ros.odometry.estimator.OdometryEstimator.final_trajectory`) a map with arm poses at
three or more keyframes is moved into the arm's frame by this fit and solved whole with the arm's
positions as factors (``WindowProblem.positions``), so the drift between them goes too (measured on
heldout_640, arm poses on 10 % of frames: Sim(3) alignment scale 0.26 live, 0.995 after).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Fewest keyframes with arm poses for a similarity fit.
MIN_ARM_KEYFRAMES = 3
#: Relative standard deviation of a scale nothing measured (source ``"none"``: a map unit taken as a metre).
UNKNOWN_SCALE_STD = 1.0e3
#: Relative standard deviation of the pose head's scale on a camera it never saw: over 19 rendered dev
#: replays the true lengths were x0.21-4.6 of those it published (relative error RMS 1.23, measured), so
#: they are known to about their own size. (KITTI's drive is outside it: x50.)
POSE_HEAD_SCALE_STD = 1.2
#: Relative standard deviation of a live ground-plane scale: over 21 dev replays a window's fit was off the
#: map's true scale at its newest keyframes by a median 5 % (log), and the median of five fits by as much
#: (their windows overlap; measured).
GROUND_SCALE_STD = 0.075
#: The same for a fit made through the f = width guess (before the camera's first initialisation): the
#: 11 such fits over 21 dev replays were x0.89-1.65 of the window's true scale (log RMS 0.26, median x1.15),
#: against log RMS 0.08 for the 401 made through a solved camera (measured). Kept only until the first
#: fit through a solved camera replaces them.
GUESS_GROUND_SCALE_STD = 0.26
#: The same for a live scale from only one or two fits through a solved camera, which no spread measures
#: yet: over 21 dev replays its log error was RMS 0.21 with one fit (21 keyframes) and 0.15 with two (21),
#: against 0.064 with three or more (359), where a single fit was up to x1.4 off (measured).
FEW_GROUND_FITS_SCALE_STD = 0.2
#: Fewest fits whose spread measures the live ground scale's.
MIN_GROUND_FITS_SPREAD = 3
#: The same for a live scale from the ground's homography between consecutive frames (the median of the newest
#: three to nine frame pairs, through a solved camera, before any window's plane fit): over the 21 dev replays
#: the 107 frames published on it (6 replays) were off the true scale of the map's newest 10 keyframes by log
#: RMS 0.27 (KITTI's 0.06, r160_206's 0.34; measured).
GROUND_MOTION_SCALE_STD = 0.27


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``target ~ s R source + t`` (Umeyama 1991): ``(s, R (3, 3), t (3,))``.

    ``source``, ``target``: ``(N, 3)`` corresponding points, ``N >= 3`` not all on one point.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    mean_s, mean_t = source.mean(0), target.mean(0)
    a, b = source - mean_s, target - mean_t
    variance_s = (a**2).sum() / len(a)
    if variance_s <= 0:
        raise ValueError("umeyama: the source points all coincide")
    covariance = b.T @ a / len(a)
    U, d, Vt = np.linalg.svd(covariance)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / variance_s) if with_scale else 1.0
    t = mean_t - s * R @ mean_s
    return s, R, t


@dataclass
class ScaleEstimate:
    """Metres per map unit, where it came from (``"arm"``, ``"ground"``, ``"pose_head"`` or ``"none"``), and
    its relative standard deviation (what a published step's length is known to)."""

    scale: float = 1.0
    source: str = "none"
    samples: int = 0
    relative_std: float = UNKNOWN_SCALE_STD


def fit_arm_similarity(map_positions: np.ndarray, arm_positions: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
    """``(s, R, t)`` with ``arm ~ s R map + t``, fitted to the camera positions (``(N, 3)`` each); None
    until possible (fewer than :data:`MIN_ARM_KEYFRAMES`, all at one point, or no positive scale)."""
    map_positions = np.asarray(map_positions, dtype=np.float64).reshape(-1, 3)
    arm_positions = np.asarray(arm_positions, dtype=np.float64).reshape(-1, 3)
    if len(map_positions) < MIN_ARM_KEYFRAMES:
        return None
    if np.linalg.norm(map_positions - map_positions.mean(0), axis=1).max() <= 1e-9:
        return None
    s, R, t = umeyama(map_positions, arm_positions)
    if not np.isfinite(s) or s <= 0:
        return None
    return s, R, t


def fit_arm_scale(map_positions: np.ndarray, arm_positions: np.ndarray) -> ScaleEstimate | None:
    """Similarity fit of the arm's camera positions to the map's (``(N, 3)`` each); None until possible.

    The relative standard deviation is least squares': the residuals' variance (``3N - 7`` degrees of
    freedom) over the map positions' spread, ``sqrt(sigma^2 / sum |a_i|^2) / s``.
    """
    similarity = fit_arm_similarity(map_positions, arm_positions)
    if similarity is None:
        return None
    s, R, t = similarity
    map_positions = np.asarray(map_positions, dtype=np.float64).reshape(-1, 3)
    arm_positions = np.asarray(arm_positions, dtype=np.float64).reshape(-1, 3)
    residuals = arm_positions - (s * map_positions @ R.T + t)
    variance = float((residuals**2).sum()) / max(3 * len(map_positions) - 7, 1)
    spread = float(((map_positions - map_positions.mean(0)) ** 2).sum())
    return ScaleEstimate(s, "arm", len(map_positions), float(np.sqrt(variance / spread)) / s)


#: The ground's normal is searched within this angle of the expected down direction: a camera looking
#: ahead, pitched or rolled up to this much against the ground (KITTI's: about 1 deg; the rendered arm's:
#: about 11 deg on average, measured).
GROUND_MAX_TILT_DEG = 20.0
#: A ground candidate is seen at least this far below the horizontal from its nearest camera: the ground
#: near the cameras, whose landmarks are triangulated best (a plane through distant landmarks just below
#: the horizon took KITTI's scale 25 % off, measured).
GROUND_MIN_DEPRESSION_DEG = 3.0
#: Every camera is at least this share of the cameras' median height above the ground: a plane that nearly
#: meets a camera is not the floor it moves over (one through landmarks just under the moving camera
#: took r640_302's scale x9, measured; the floor's share is 0.86 and KITTI's road's 0.96 there).
MIN_HEIGHT_SHARE = 0.5
#: Fewest landmarks on the ground plane for a scale from it.
MIN_GROUND_POINTS = 30
#: Half the RANSAC inlier band, as a share of the candidate landmarks' median distance from their nearest
#: camera (a landmark's triangulation error grows with its distance).
GROUND_BAND_SHARE = 0.015
#: RANSAC plane hypotheses drawn (seeded: a replay repeats).
GROUND_HYPOTHESES = 400
#: A floor has little far beneath it: a plane with landmarks deeper than this share of the cameras' height
#: above it, as many as half its own inliers (:data:`GROUND_BELOW_RATIO`), is the top of something on the
#: floor, and the floor is searched for beneath it. Over 454 live fits of 21 dev replays, 51 of the 64 that
#: were more than 20 % off the map's true scale had that many (an object's top, x1.3-19) and 1 of the 390
#: within 20 % (measured); KITTI's road has 0.07-0.29 of its inliers there.
GROUND_BELOW_SHARE = 0.25
GROUND_BELOW_RATIO = 0.5
#: Planes tried, each beneath the last one found to have too much below it.
GROUND_SEARCHES = 3


@dataclass(frozen=True)
class GroundPlane:
    """A plane ``normal @ x == offset`` in the map frame; ``normal`` (unit) points from the cameras to it."""

    normal: np.ndarray
    offset: float
    inliers: int

    def heights(self, centres: np.ndarray) -> np.ndarray:
        """Distances of camera centres ``(N, 3)`` above the plane (positive on the cameras' side)."""
        return self.offset - np.asarray(centres, dtype=np.float64).reshape(-1, 3) @ self.normal


def _plane_through(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane ``(unit normal, offset)`` through ``(N, 3)`` points (N >= 3)."""
    centre = points.mean(0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    return normal, float(normal @ centre)


def fit_ground_plane(points: np.ndarray, centres: np.ndarray, down: np.ndarray, *,
                     max_tilt_deg: float = GROUND_MAX_TILT_DEG, min_depression_deg: float = GROUND_MIN_DEPRESSION_DEG,
                     min_points: int = MIN_GROUND_POINTS,
                     band_share: float = GROUND_BAND_SHARE, hypotheses: int = GROUND_HYPOTHESES,
                     seed: int = 0) -> GroundPlane | None:
    """The ground plane among a map's landmarks, or None where there is none to trust.

    Args:
        points: ``(N, 3)`` landmark positions in the map frame.
        centres: ``(K, 3)`` the cameras' centres in the map frame.
        down: ``(3,)`` the expected down direction in the map frame (the cameras' mean).
        max_tilt_deg: largest angle between the plane's normal and ``down``.
        min_depression_deg: least angle below the horizontal (against ``down``) at which a candidate is seen
            from its nearest camera.
        min_points: fewest landmarks within the plane's band.
        band_share: half the inlier band, as a share of the candidates' median distance from the cameras.
        hypotheses: RANSAC hypotheses (three landmarks each), drawn with ``seed``.

    Only landmarks seen below the horizontal from their nearest camera are candidates, so a ceiling is
    never taken for the floor. The plane with most landmarks in its band wins, and is refitted to them by
    least squares. Where the floor is out of view, or shows fewer landmarks than the top of something on
    it, that plane is the top: then as many landmarks as half its inliers lie far beneath it
    (:data:`GROUND_BELOW_SHARE`, :data:`GROUND_BELOW_RATIO`), and the search is repeated among them
    (:data:`GROUND_SEARCHES` planes at most). The plane found must lie below every camera by at least
    :data:`MIN_HEIGHT_SHARE` of their median height.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    down = np.asarray(down, dtype=np.float64).reshape(3)
    if len(centres) == 0 or len(points) < max(3, min_points) or not np.linalg.norm(down) > 0:
        return None
    down = down / np.linalg.norm(down)
    from scipy.spatial import cKDTree

    # A tree, not a (landmarks, cameras) table: a long map's would take gigabytes.
    relative = points - centres[cKDTree(centres).query(points)[1]]
    distances = np.linalg.norm(relative, axis=1)
    below = relative @ down > np.sin(np.radians(min_depression_deg)) * distances
    candidates = points[below]
    if len(candidates) < min_points:
        return None
    band = band_share * float(np.median(distances[below]))
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    rng = np.random.default_rng(seed)
    for _ in range(GROUND_SEARCHES):
        plane = _most_supported_plane(candidates, down, band, cos_tilt, min_points, hypotheses, rng)
        if plane is None:
            return None
        depth_below = GROUND_BELOW_SHARE * float(np.median(plane.heights(centres)))
        beneath = points @ plane.normal - plane.offset > depth_below
        if beneath.sum() < GROUND_BELOW_RATIO * plane.inliers:
            break
        candidates = candidates[candidates @ plane.normal - plane.offset > depth_below]  # the floor is lower
        if len(candidates) < min_points:
            return None
    else:
        return None
    heights = plane.heights(centres)
    if not (heights > MIN_HEIGHT_SHARE * np.median(heights)).all():
        return None
    return plane


def _most_supported_plane(candidates: np.ndarray, down: np.ndarray, band: float, cos_tilt: float, min_points: int,
                          hypotheses: int, rng: np.random.Generator) -> GroundPlane | None:
    """RANSAC (``hypotheses`` triples of ``candidates``) for the plane within the tilt of ``down`` with most
    candidates within ``band``, refitted twice by least squares; None under ``min_points`` inliers."""
    triples = candidates[rng.integers(0, len(candidates), (hypotheses, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    normals = normals / np.where(lengths > 0, lengths, 1.0)[:, None]
    normals *= np.where(normals @ down < 0, -1.0, 1.0)[:, None]
    usable = (lengths > 0) & (normals @ down >= cos_tilt)
    if not usable.any():
        return None
    normals, anchors = normals[usable], triples[usable, 0]
    plane_offsets = (normals * anchors).sum(1)
    counts = (np.abs(candidates @ normals.T - plane_offsets) < band).sum(0)
    best = int(np.argmax(counts))
    normal, offset = normals[best], float(plane_offsets[best])
    for _ in range(2):  # least squares on the band, then on the refitted plane's band
        inside = np.abs(candidates @ normal - offset) < band
        if inside.sum() < min_points:
            return None
        normal, offset = _plane_through(candidates[inside])
        if normal @ down < 0:
            normal, offset = -normal, -offset
    inliers = int((np.abs(candidates @ normal - offset) < band).sum())
    if inliers < min_points or normal @ down < cos_tilt:
        return None
    return GroundPlane(normal, offset, inliers)


def fit_ground_scale(points: np.ndarray, centres: np.ndarray, down: np.ndarray, camera_height: float,
                     **plane_settings) -> ScaleEstimate | None:
    """Metres per map unit from the ground plane (:func:`fit_ground_plane`) and the camera's known
    height above it (m): the height over the cameras' median height in map units. None where no plane
    is found. ``samples`` is the plane's landmark count."""
    if not (np.isfinite(camera_height) and camera_height > 0):
        raise ValueError(f"the camera height must be a positive number of metres, got {camera_height!r}")
    plane = fit_ground_plane(points, centres, down, **plane_settings)
    if plane is None:
        return None
    scale = float(camera_height / np.median(plane.heights(centres)))
    return ScaleEstimate(scale, "ground", plane.inliers, GROUND_SCALE_STD) if np.isfinite(scale) and scale > 0 else None


#: Fewest tracks on the ground plane that must agree on a frame pair's ratio of distance moved to height.
MIN_HOMOGRAPHY_INLIERS = 8
#: A track agrees with the ground plane's homography when its transfer error is below this, in normalised
#: image units (radians near the image centre; 3 px at KITTI's 719 px focal length).
HOMOGRAPHY_THRESHOLD = 0.004
#: RANSAC hypotheses (three tracks each) for the ground plane's homography, drawn with a fixed seed.
HOMOGRAPHY_HYPOTHESES = 300


@dataclass(frozen=True)
class GroundMotion:
    """A frame pair's distance moved over the camera's height above the ground (``ratio``, ``|t| / d``), the
    plane's unit ``normal`` (earlier camera's coordinates, pointing down to it), the tracks that agreed, and
    the ratio's standard error (least squares', from their scatter)."""

    ratio: float
    normal: np.ndarray
    inliers: int
    std: float


def ground_motion_ratio(previous: np.ndarray, current: np.ndarray, rotation: np.ndarray, direction: np.ndarray,
                        down: np.ndarray, threshold: float = HOMOGRAPHY_THRESHOLD,
                        min_inliers: int = MIN_HOMOGRAPHY_INLIERS, max_tilt_deg: float = GROUND_MAX_TILT_DEG,
                        min_depression_deg: float = GROUND_MIN_DEPRESSION_DEG,
                        hypotheses: int = HOMOGRAPHY_HYPOTHESES, seed: int = 0) -> GroundMotion | None:
    """The distance a camera moved over its height above the ground plane, ``|t| / d``, from tracks on the
    plane in two frames (:class:`GroundMotion`), or None where fewer than ``min_inliers`` tracks agree.

    A point on the plane ``n . X = d`` moves between the frames by the plane's homography
    ``R + t n^T / d`` (``X_current = R X_previous + t``). With ``R`` and the direction of ``t`` known (from
    the VO: a monocular map measures everything but the length), each track gives one linear equation in
    ``m = (|t| / d) n`` (three unknowns): the ``m`` that most tracks agree with (transfer error below
    ``threshold``; RANSAC over triples, its normal within ``max_tilt_deg`` of ``down``), refitted to them by
    least squares, gives ``|m| = |t| / d``. With the height ``d`` known the step is metric. It needs no
    landmark: tracks that live one frame are enough (a road's, which stretch as they near).

    Args:
        previous, current: ``(N, 2)`` normalised image coordinates (undistorted ``x / z, y / z``) of the same
            tracks in the earlier and the later frame.
        rotation: ``(3, 3)`` ``R`` taking the earlier camera's coordinates to the later one's.
        direction: ``(3,)`` the direction of ``t`` (normalised here), in the later camera's coordinates.
        down: ``(3,)`` the expected down direction in the earlier camera's coordinates.
        threshold: largest transfer error of an agreeing track (normalised units).
        min_inliers: fewest agreeing tracks.
        max_tilt_deg: largest angle between the plane's normal and ``down``.
        min_depression_deg: only tracks seen at least this far below the horizontal (against ``down``) in
            the earlier frame are candidates, as in :func:`fit_ground_plane`.
        hypotheses: RANSAC triples, drawn with ``seed``.
    """
    previous = np.asarray(previous, dtype=np.float64).reshape(-1, 2)
    current = np.asarray(current, dtype=np.float64).reshape(-1, 2)
    rotation = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    direction = np.asarray(direction, dtype=np.float64).reshape(3)
    down = np.asarray(down, dtype=np.float64).reshape(3)
    if not (np.linalg.norm(direction) > 0 and np.linalg.norm(down) > 0):
        return None
    direction, down = direction / np.linalg.norm(direction), down / np.linalg.norm(down)
    rays = np.c_[previous, np.ones(len(previous))]
    finite = np.isfinite(rays).all(1) & np.isfinite(current).all(1)
    below = np.zeros(len(rays), dtype=bool)
    below[finite] = rays[finite] @ down > np.sin(np.radians(min_depression_deg)) * np.linalg.norm(rays[finite], axis=1)
    if below.sum() < max(3, min_inliers):
        return None
    rays, u, v = rays[below], current[below, 0], current[below, 1]
    # x_current ~ R x + (m . x) direction: each track's two image equations in the one scalar m . x.
    turned = rays @ rotation.T
    cu, du = u * direction[2] - direction[0], turned[:, 0] - u * turned[:, 2]
    cv, dv = v * direction[2] - direction[1], turned[:, 1] - v * turned[:, 2]
    weights = cu**2 + cv**2  # how much the track's image moves with m . x
    usable = weights > 1e-12
    along = np.zeros(len(rays))
    along[usable] = (cu[usable] * du[usable] + cv[usable] * dv[usable]) / weights[usable]
    # The weighted least squares' rows rays . m = along, each scaled by sqrt(weight): for the refits and the std.
    weighted_rays, weighted_along = rays * np.sqrt(weights)[:, None], along * np.sqrt(weights)

    def transfer_errors(m: np.ndarray) -> np.ndarray:
        """``(H, M)`` transfer error of each track for each ``m`` ``(H, 3)`` (inf behind the camera)."""
        moved = turned[None] + (m @ rays.T)[..., None] * direction
        depth = moved[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            errors = np.hypot(moved[..., 0] / depth - u, moved[..., 1] / depth - v)
        return np.where(depth > 0, errors, np.inf)

    def plane_of(inliers: np.ndarray) -> np.ndarray | None:
        """Weighted least squares ``m`` of ``rays[inliers] . m = along[inliers]``."""
        solution, *_ = np.linalg.lstsq(weighted_rays[inliers], weighted_along[inliers], rcond=None)
        return solution if np.isfinite(solution).all() else None

    cos_tilt = np.cos(np.radians(max_tilt_deg))
    candidates = np.flatnonzero(usable)
    if len(candidates) < 3:
        return None
    triples = np.random.default_rng(seed).integers(0, len(candidates), (hypotheses, 3))
    distinct = (triples[:, 0] != triples[:, 1]) & (triples[:, 0] != triples[:, 2]) & (triples[:, 1] != triples[:, 2])
    triples = candidates[triples[distinct]]
    if len(triples) == 0:
        return None
    A = rays[triples]
    solvable = np.abs(np.linalg.det(A)) > 1e-12
    if not solvable.any():
        return None
    m = np.linalg.solve(A[solvable], along[triples[solvable]][..., None])[..., 0]
    lengths = np.linalg.norm(m, axis=1)
    upright = (lengths > 0) & ((m @ down) >= cos_tilt * lengths)
    if not upright.any():
        return None
    m = m[upright]
    agree = transfer_errors(m) < threshold
    inliers = agree[int(np.argmax(agree.sum(1)))]
    for _ in range(2):  # least squares on the agreeing tracks, then on the refitted plane's
        if inliers.sum() < max(3, min_inliers):
            return None
        best = plane_of(inliers)
        if best is None:
            return None
        inliers = transfer_errors(best[None])[0] < threshold
    count = int(inliers.sum())
    ratio = float(np.linalg.norm(best))
    if count < min_inliers or not ratio > 0 or best @ down < cos_tilt * ratio:
        return None
    normal = best / ratio
    # The least squares' own standard error along the normal: the tracks' scatter over their information.
    A = weighted_rays[inliers]
    residuals = A @ best - weighted_along[inliers]
    variance = float(residuals @ residuals) / max(count - 3, 1)
    information = A.T @ A
    try:
        std = float(np.sqrt(variance * normal @ np.linalg.solve(information, normal)))
    except np.linalg.LinAlgError:
        return None
    return GroundMotion(ratio, normal, count, std)
