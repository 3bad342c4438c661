"""The trajectory through the final map and camera, for replays (what ORB-SLAM writes at shutdown).

Live, each frame is posed once, against the map and camera of that moment, and published; nothing later
changes it. A replay can do better at its end: the camera has converged and bundle adjustment has moved
the keyframes and landmarks, so every frame tracked in a map is posed again from its own tracks. ORB-SLAM
saves its frame trajectory the same way, each frame relative to its reference keyframe as the keyframes
stand at shutdown; here the frames are posed again by PnP on their tracks' final landmarks through the
final camera (the frames tracked through the first guess of an uncalibrated camera were measured through
the wrong camera, and their keyframe-relative motions carry that error), and their keyframe-relative
pose, with the keyframe as it stands, is the fallback and the PnP's start.

The frames' records (and the keyframes' images, which the search for landmarks a keyframe never tracked
needs) are kept only when asked for (``VisualOdometry(record=True)``): a live node would hold every
frame's tracks for as long as it runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nocal_ros.odometry.frontend import ray_whitening, solve_pnp
from nocal_ros.odometry.map import Keyframe, LocalMap


@dataclass
class FrameRecord:
    """One frame tracked in a map, as needed to pose it again at the end.

    Attributes:
        frame: the stream's frame counter.
        map_id: the tracking's id of that map.
        local_map: the map it was tracked in (or, while initialising, the map its tracks then made).
        reference: the keyframe it was posed relative to (itself for a keyframe).
        T_kf_cam: ``(4, 4)`` its pose relative to ``reference`` when tracked (while initialising, the
            rotation from the reference, with no translation); None for a frame of an initialisation
            reference given up before this map was made, which only PnP can place in it.
        ids, pixels: its tracks, ``(N,)`` and ``(N, 2)`` native pixels.
        unit_scale: the map's ``unit_scale`` then (``T_kf_cam``'s unit).
    """

    frame: int
    map_id: int
    local_map: LocalMap
    reference: Keyframe
    T_kf_cam: np.ndarray | None
    ids: np.ndarray
    pixels: np.ndarray
    unit_scale: float = 1.0


@dataclass
class FinalPose:
    """A frame's pose in its map at the end: ``how`` it was found (see :func:`final_map_poses`)."""

    map_id: int
    local_map: LocalMap
    T_map_cam: np.ndarray
    how: str


def final_map_poses(records: list[FrameRecord], calibration, pixel_threshold: float,
                    min_inliers: int = 15) -> dict[int, FinalPose]:
    """Each recorded frame's pose in its map as the map and ``calibration`` stand now.

    Returns ``{frame: FinalPose}`` with ``how`` one of ``"keyframe"`` (the keyframe's own,
    bundle-adjusted pose), ``"pnp"`` (posed again on its tracks' landmarks), or ``"keyframe_relative"``
    (too few of its tracks have landmarks: its pose relative to its reference keyframe, as tracked). A
    frame with no pose relative to the map (``T_kf_cam`` None) that PnP cannot pose is left out.
    """
    threshold = pixel_threshold / calibration.fx
    poses: dict[int, FinalPose] = {}
    for record in records:
        with record.local_map.lock:
            T_w_ref = record.reference.T_w_c.copy()
            if record.reference.frame == record.frame:
                poses[record.frame] = FinalPose(record.map_id, record.local_map, T_w_ref, "keyframe")
                continue
            mask, positions = record.local_map.landmark_positions(record.ids)
        guess = None
        if record.T_kf_cam is not None:
            T_kf_cam = record.T_kf_cam.copy()
            T_kf_cam[:3, 3] *= record.local_map.unit_scale / record.unit_scale  # the map moved into other units since
            guess = T_w_ref @ T_kf_cam
        x = calibration.undistorted_normalised(record.pixels[mask])
        pnp = solve_pnp(positions, x, threshold, guess=guess, min_inliers=min_inliers, covariance=False,
                        whitening=ray_whitening(calibration, x), robust=True)
        if pnp is None and guess is None:
            continue
        if pnp is None:
            poses[record.frame] = FinalPose(record.map_id, record.local_map, guess, "keyframe_relative")
        else:
            poses[record.frame] = FinalPose(record.map_id, record.local_map, pnp.T_w_c, "pnp")
    return poses


#: Fewest landmarks two maps must share, and agree on, for one to be placed in the other.
MIN_SHARED_LANDMARKS = 12
#: The median distance between the shared landmarks of two maps after the fit, as a share of their
#: median depth from the older map's last keyframe, above which the maps do not agree (measured: 0.9 %
#: and 2.7 % for two right links, 25 % for a map distorted by a wrong camera, whose link turned the
#: trajectory by 55 deg).
MAX_LINK_RESIDUAL_SHARE = 0.05


def map_similarity(older: LocalMap, newer: LocalMap) -> tuple[float, np.ndarray, np.ndarray] | None:
    """``(s, R, t)`` with ``x_older = s R x_newer + t``, from the landmarks both maps hold, or None.

    A map started after tracking was lost keeps the tracks that lived through the loss, and a landmark's
    id is its track's, so the same id in two maps is the same scene point. The fit is repeated on the
    landmarks within three median residuals of the last one (a landmark badly placed in either map is
    left out); it needs :data:`MIN_SHARED_LANDMARKS` of them, and their median residual within
    :data:`MAX_LINK_RESIDUAL_SHARE` of their depth.
    """
    from nocal_ros.odometry.scale import umeyama

    with older.lock, newer.lock:
        common = sorted(set(older.landmarks) & set(newer.landmarks))
        if len(common) < MIN_SHARED_LANDMARKS:
            return None
        in_older = np.array([older.landmarks[i] for i in common])
        in_newer = np.array([newer.landmarks[i] for i in common])
        viewpoint = older.keyframes[-1].T_w_c[:3, 3].copy() if older.keyframes else np.zeros(3)
    finite = np.isfinite(in_older).all(1) & np.isfinite(in_newer).all(1)
    keep = finite
    for _ in range(3):
        if keep.sum() < MIN_SHARED_LANDMARKS or np.ptp(in_newer[keep], axis=0).max() <= 0:
            return None
        s, R, t = umeyama(in_newer[keep], in_older[keep])
        residual = np.linalg.norm(in_older - (s * in_newer @ R.T + t), axis=1)
        residual[~finite] = np.inf
        keep = residual <= 3.0 * max(float(np.median(residual[keep])), 1e-12)
    if keep.sum() < MIN_SHARED_LANDMARKS or not (np.isfinite(s) and s > 0):
        return None
    depth = float(np.median(np.linalg.norm(in_older[keep] - viewpoint, axis=1)))
    if not np.median(residual[keep]) <= MAX_LINK_RESIDUAL_SHARE * depth:
        return None
    return s, R, t


def link_maps(poses: dict[int, FinalPose], exclude: set[int] = frozenset()) -> dict[int, FinalPose]:
    """The frames of each map that shares landmarks with the map before it (:func:`map_similarity`) moved
    into that map's frame and unit, and given its id, so that both are placed by one origin and scale.

    Maps in ``exclude`` (made metric in another frame, the arm's) are neither moved nor moved into.
    Without this, a map made after a loss is placed where the published frames of the loss lead.
    """
    maps: dict[int, LocalMap] = {}
    for pose in poses.values():
        maps.setdefault(pose.map_id, pose.local_map)
    into: dict[int, tuple[int, float, np.ndarray, np.ndarray]] = {}  # map id -> (root id, s, R, t)
    ids = sorted(maps)
    for older, newer in zip(ids[:-1], ids[1:]):
        if older in exclude or newer in exclude:
            continue
        similarity = map_similarity(maps[older], maps[newer])
        if similarity is None:
            continue
        s, R, t = similarity
        root, s0, R0, t0 = into.get(older, (older, 1.0, np.eye(3), np.zeros(3)))
        into[newer] = (root, s0 * s, R0 @ R, s0 * R0 @ t + t0)
    linked = {}
    for frame, pose in poses.items():
        if pose.map_id not in into:
            linked[frame] = pose
            continue
        root, s, R, t = into[pose.map_id]
        T = np.eye(4)
        T[:3, :3] = R @ pose.T_map_cam[:3, :3]
        T[:3, 3] = s * R @ pose.T_map_cam[:3, 3] + t
        linked[frame] = FinalPose(root, pose.local_map, T, pose.how)
    return linked
