"""Tracking: each frame posed against the local map, and the VO's states.

:class:`VisualOdometry` is the geometric core the estimator drives, one frame at a time:

* ``"initialising"``: no map yet. Tracks are followed from a reference frame. While a rotation alone
  explains them (a camera that turns or stands still) there is no translation to see: the frame gets
  the fitted rotation and no translation. Once the parallax allows, :func:`two_view_map` gives the
  first two keyframes and landmarks, and the map's unit of length (their baseline).
* ``"ok"``: the frame is posed by PnP on its tracks that have landmarks (constant-velocity guess), and
  becomes a keyframe when the tracks have moved enough since the last one (parallax), when too few of
  the last keyframe's landmarks are still tracked, or when too many frames have passed. Keyframes go to
  :class:`~nocal_ros.odometry.local_mapping.LocalMapping`.
* ``"lost"``: too few tracks, or PnP found too few inliers. The map is dropped and a new one is
  initialised from the next frames (re-initialisation); the estimator bridges the gap with the pose
  head and says so.

Poses here are in the current map's frame and unit; the map's frame is its first keyframe's camera.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from nocal_ros.geometry import invert_transform, nearest_rotation, so3_exp, so3_log
from nocal_ros.odometry.calibration import OnlineCamera
from nocal_ros.odometry.frontend import FeatureTracker, TrackedFrame, TrackerSettings, ray_whitening, solve_pnp
from nocal_ros.odometry.initializer import rotation_ransac, two_view_map, unit_rays
from nocal_ros.odometry.local_mapping import LocalMapping, MappingSettings, refine_two_keyframes
from nocal_ros.odometry.map import Keyframe, LocalMap
from nocal_ros.odometry.trajectory import FrameRecord

#: Most bytes of keyframe images a recording VO keeps (about 1700 keyframes at 640x480); beyond it the
#: oldest are let go, and those keyframes are not searched at the end (``keyframe_images_dropped``).
KEYFRAME_IMAGE_BUDGET_BYTES = 512 * 2**20
#: Most frames of given-up initialisation references a recording VO keeps for the next map (the newest).
MAX_ABANDONED_FRAMES = 60


@dataclass
class TrackingSettings:
    """Thresholds of tracking (native pixels unless said otherwise).

    Attributes:
        tracker: corner tracks (how many, how spread).
        mapping: local mapping (window, curriculum of the camera).
        pixel_threshold: PnP and initialisation inlier threshold.
        min_tracks: fewer tracks than this (after a top-up) and the frame cannot be posed.
        min_pnp_inliers: fewer PnP inliers and tracking is lost.
        keyframe_parallax_deg: median angle between a track's rays at the last keyframe and now, with the
            rotation between the frames taken out, that makes a keyframe.
        keyframe_landmark_share: a keyframe when fewer than this share of the landmarks tracked at the
            last keyframe are still inliers.
        guess_keyframe_parallax_deg: ``keyframe_parallax_deg`` through the guessed camera (before its first
            window, no calibration given). Angles through ``f = width`` are the true ones times
            ``f_true / width``: half of them for a 90 degree lens. At the calibrated threshold a wide
            camera made its 6th keyframe, and so its first camera window, late (frame 35 on r160_201,
            f = 0.5 width), and every frame until then was published through the guess, 0.5-1 deg off per
            step. At half of it the first window came at frame 10 instead of 15 (median over 23 replays),
            and the published rotation per pair went 0.248 -> 0.208 deg (median; docs/RESULTS.md).
        max_keyframe_interval: frames after which a keyframe is made anyway.
        max_waiting_keyframes: while this many keyframes wait for local mapping, a keyframe is made only
            when tracking needs one to go on (too few landmarks or tracks left), not for parallax or
            interval, as ORB-SLAM's tracking asks whether local mapping accepts keyframes: in a 30 Hz
            replay a camera initialisation took 2.7 s, and the 38 keyframes made meanwhile were mapped
            through the camera it replaced (measured on VAMR). Never reached in synchronous mode.
        init_min_points: landmarks the first two keyframes need.
        init_parallax_deg, init_parallax_px: the median ray angle they need, at least, and at least this
            many pixels' worth of it (at low resolution a degree is one or two pixels: too few for depth).
        guess_pnp_threshold_factor: a frame posed through the guessed camera (before its first
            initialisation, and no calibration given) that PnP cannot pose within ``pixel_threshold`` is
            tried again within this many times it. A guess tens of percent off bends correct tracks by
            more than the threshold: KITTI's forward drive, through f = width 73 % long, lost its first
            maps at their second or fifth frame with fewer than 15 PnP inliers (docs/RESULTS.md).
        guess_rotation_blend: through the guessed camera (before its first window, no calibration
            given), a step's published rotation is PnP's moved this share of the way (on SO(3)) to the
            rotation the tracks fit frame to frame; 0 publishes PnP's. Only what is published: the map,
            the motion model and the camera never see it. Half the way was better on as many replays
            but lost up to 25 % on the others, the demo's included (docs/RESULTS.md).
        uncertain_focal_share: while the online camera's focal length is known to worse than this share of
            its value (after its first window; through the guess always), a step's rotation from PnP is
            compared with the one the tracks fit frame to frame and their distance widens its covariance
            (:func:`blend_rotation`): both read the image through that focal length, and where they part,
            one is wrong by as much. It covered r640_307's steps after a first initialisation 64-89 % off
            (rotation NEES 2.30 -> 0.90); at 5 % the tracks' own error (the parallax they take for a turn)
            published r160_205's steps 0.05-0.17 deg off at 0.6-0.85 deg (docs/RESULTS.md). A settled
            camera never pays for it.
        robust_pnp: once the camera is solved, refine each frame's PnP pose with a Cauchy loss
            (:func:`~nocal_ros.odometry.frontend.robust_pose_refinement`; the end's final poses always
            are). Off: over five draws of the 23 replays it lowered the published rotation from pair 20
            on by 15-20 % (better on 15-17 replays), but raised the published focal error's median from
            0.37-0.40 % to 0.43-0.59 % in every draw (heldout_160 within 0.5 % in none of five draws,
            against two of three), and r640_302 failed in all five, against one of three
            (docs/RESULTS.md).
        init_min_reference_tracks: while initialising, a reference with fewer of its tracks left is
            replaced by the current frame, as ORB-SLAM's initialiser replaces its reference with fewer than
            100 matches: the essential matrix keeps only a share of them (through a guessed camera half or
            less), and a reference whose tracks die faster than parallax grows never makes a map.
    """

    tracker: TrackerSettings = field(default_factory=TrackerSettings)
    mapping: MappingSettings = field(default_factory=MappingSettings)
    pixel_threshold: float = 1.5
    min_tracks: int = 30
    min_pnp_inliers: int = 15
    keyframe_parallax_deg: float = 1.0
    keyframe_landmark_share: float = 0.6
    guess_keyframe_parallax_deg: float = 0.5
    max_keyframe_interval: int = 20
    max_waiting_keyframes: int = 2
    init_min_points: int = 40
    init_parallax_deg: float = 1.0
    init_parallax_px: float = 5.0
    init_min_reference_tracks: int = 80
    guess_pnp_threshold_factor: float = 3.0
    guess_rotation_blend: float = 0.33
    uncertain_focal_share: float = 0.10
    robust_pnp: bool = False


@dataclass
class VOFrame:
    """What tracking made of one frame.

    Attributes:
        state: ``"initialising"``, ``"ok"`` or ``"lost"`` (see the module notes).
        T_map_cam: ``(4, 4)`` pose in the map (``"ok"`` only).
        covariance: ``(6, 6)`` of ``T_map_cam`` (right perturbation, ``(rho, theta)``, map units); through the
            guessed camera, or one whose focal length is still uncertain (``uncertain_focal_share``),
            widened by the step's two rotations' distance (:func:`blend_rotation`).
        rotation_from_reference: ``R_ref_cur`` chained frame to frame while initialising, and at the frame a
            new map starts at (None when unknown).
        direction_from_reference: the unit direction of travel from the reference while initialising,
            when the parallax shows it (None: a rotation alone explains the tracks).
        map_id: the map the pose is in (a new id after each initialisation).
        reference_frame: the frame counter of the map's first keyframe (while initialising: the
            reference frame the rotation is relative to).
        new_map: this frame completed an initialisation.
        keyframe: this frame became a keyframe.
        tracks, inliers: tracks alive, and tracks that PnP (or initialisation) used.
        textured: the frame had corners to track at all.
        T_prev_cur: ``(4, 4)`` motion from the previous frame posed in the same map, with the previous
            frame posed again in the map and camera as they stand now: local mapping moves keyframes,
            landmarks and the camera between frames, and the motion must not absorb those corrections.
        guess_rescued: posed only with ``TrackingSettings.guess_pnp_threshold_factor`` (through the
            guessed camera).
        rotation_from_previous: ``R_prev_cur`` fitted to the tracks a frame that lost the map shares with
            the previous frame (PnP failed; None when unknown).
        through_guess: the online camera was still the guess when this frame was tracked
            (:attr:`~nocal_ros.odometry.calibration.OnlineCamera.is_guess`).
    """

    state: str
    T_map_cam: np.ndarray | None = None
    covariance: np.ndarray | None = None
    rotation_from_reference: np.ndarray | None = None
    direction_from_reference: np.ndarray | None = None
    map_id: int = 0
    reference_frame: int | None = None
    new_map: bool = False
    keyframe: bool = False
    tracks: int = 0
    inliers: int = 0
    textured: bool = True
    T_prev_cur: np.ndarray | None = None
    guess_rescued: bool = False
    rotation_from_previous: np.ndarray | None = None
    through_guess: bool = False


class VisualOdometry:
    """Frames in, poses in the local map out (see the module notes). Not thread-safe: one caller.

    ``record``: keep every tracked frame's tracks in :attr:`records`, to pose them again through the
    final map and camera (:mod:`nocal_ros.odometry.trajectory`; replays only, as they grow with the stream),
    and each keyframe's grey image at the tracker's work size in :attr:`keyframe_images` (by frame), to
    search it for the landmarks it never tracked (:func:`~nocal_ros.odometry.local_mapping.search_by_projection`;
    at most ``image_budget_bytes`` of them, the newest).
    """

    def __init__(self, camera: OnlineCamera, settings: TrackingSettings | None = None, synchronous: bool = False,
                 record: bool = False, image_budget_bytes: int = KEYFRAME_IMAGE_BUDGET_BYTES) -> None:
        self.camera = camera
        self.settings = settings or TrackingSettings()
        self.tracker = FeatureTracker(self.settings.tracker)
        self.mapping = LocalMapping(camera, self.settings.mapping, synchronous)
        self.map: LocalMap | None = None
        self.map_id = 0
        self.state = "initialising"
        self._reference: tuple[int, int, TrackedFrame] | None = None  # frame, stamp, its tracks
        self._chain: tuple[TrackedFrame, np.ndarray] | None = None  # previous frame's tracks, R_ref_prev
        self._poses: deque[tuple[int, np.ndarray]] = deque(maxlen=3)  # (frame, T_map_cam) of the last frames
        self._last_keyframe_inliers = 0
        self._last: tuple[Keyframe, np.ndarray] | None = None  # previous frame: reference keyframe, T_kf_cam
        self._previous: TrackedFrame | None = None  # previous frame's tracks
        self._poses_version = 0  # the map version the motion model (_poses, _last) is in
        #: Milliseconds per frame of tracking alone (frontend, PnP, keyframe decision): local mapping run
        #: inline in synchronous mode is left out, so the figure is what a frame costs the tracking thread.
        self.milliseconds: deque[float] = deque(maxlen=500)
        self._mapping_inline_s = 0.0
        self.record = record
        self.records: list[FrameRecord] = []
        self.keyframe_images: dict[int, np.ndarray] = {}
        self.keyframe_images_dropped = 0
        self.image_budget_bytes = int(image_budget_bytes)
        self._image_bytes = 0
        self._reference_image: np.ndarray | None = None  # the initialisation reference's, when recording
        self._rays_cache: tuple | None = None  # (keyframe, calibration, its pixels, their rays)
        self._initialising: list[tuple[int, np.ndarray, TrackedFrame]] = []  # (frame, R_ref_cur, tracks) since the reference
        #: When recording: the frames of references given up before a map was made, (frame, tracks), for
        #: the end of a replay to pose them in the next map by PnP (see :func:`final_map_poses`).
        self._abandoned: deque[tuple[int, TrackedFrame]] = deque(maxlen=MAX_ABANDONED_FRAMES)

    def reset(self) -> None:
        self.mapping.wait()
        self.tracker.reset()
        self.records.clear()
        self._abandoned.clear()
        self.keyframe_images.clear()
        self._image_bytes = 0
        self.map = None
        self.state = "initialising"
        self._reference = None
        self._poses.clear()
        self._last = None
        self._previous = None

    def close(self) -> None:
        self.mapping.close()

    # -- per frame ---------------------------------------------------------------------------------

    def process(self, frame: int, stamp_ns: int, image: np.ndarray) -> VOFrame:
        start = time.perf_counter()
        self._mapping_inline_s = 0.0
        through_guess = self.camera.is_guess  # before a solve can land during this frame
        result = self._process(frame, stamp_ns, image)
        result.through_guess = through_guess
        self.milliseconds.append((time.perf_counter() - start - self._mapping_inline_s) * 1e3)
        return result

    def _submit(self, local_map: LocalMap, keyframe: Keyframe) -> None:
        start = time.perf_counter()
        self.mapping.submit(local_map, keyframe)
        if self.mapping.synchronous:
            self._mapping_inline_s += time.perf_counter() - start

    def _process(self, frame: int, stamp_ns: int, image: np.ndarray) -> VOFrame:
        settings = self.settings
        self._pose_previous_again()
        guess = self._predicted_pose(frame)
        predicted = self._predicted_pixels(guess) if guess is not None else None
        tracked = self.tracker.track(image, predicted)
        if len(tracked.ids) < settings.min_tracks:
            added = self.tracker.top_up(image)
            textured = len(tracked.ids) + added >= settings.min_tracks
            return self._lose(frame, stamp_ns, textured, len(tracked.ids))
        if self.state != "ok":
            return self._initialise(frame, stamp_ns, tracked)
        return self._track(frame, stamp_ns, tracked, guess)

    def _lose(self, frame: int, stamp_ns: int, textured: bool, tracks: int,
              rotation_from_previous: np.ndarray | None = None) -> VOFrame:
        """No pose from geometry this frame; the next frames start a new map. An untextured frame is "lost"."""
        if self.state == "ok":
            self.state = "lost"
        self.map = None
        self._poses.clear()
        self._last = None
        self._previous = None
        # The corners just detected make this frame the reference of the next initialisation.
        self._abandon_reference()
        if textured:
            self._set_reference(frame, stamp_ns)
        # No motion is measured for this frame itself (its tracks start here): the estimator bridges it.
        return VOFrame(self.state if textured else "lost", map_id=self.map_id, tracks=tracks, textured=textured,
                       rotation_from_previous=rotation_from_previous)

    def _abandon_reference(self) -> None:
        """Give up the initialisation's reference; when recording, keep its frames' tracks for the next map."""
        if self.record and self._reference is not None:
            self._abandoned.append((self._reference[0], self._reference[2]))
            self._abandoned.extend((frame, tracks) for frame, _, tracks in self._initialising)
        self._reference = None
        self._initialising.clear()

    def _set_reference(self, frame: int, stamp_ns: int) -> None:
        """Make this frame (its tracks topped up) the reference of the next initialisation."""
        self.tracker.top_up()
        current = self.tracker.current()
        self._reference = (frame, stamp_ns, current)
        if self.record:
            self._reference_image = self.tracker.gray
        self._chain = (current, np.eye(3))
        self._initialising.clear()

    def _chained_rotation(self, tracked: TrackedFrame, threshold: float) -> np.ndarray:
        """``R_ref_cur`` as the product of frame-to-frame rotations fitted to the tracks.

        Between consecutive frames the parallax is a fraction of what it is from the reference, so a
        rotation explains the tracks far better there: fitted from the reference through 1-2 pixels of
        parallax per frame, the rotation was 0.3-0.4 deg off per frame, and the essential matrix's
        1-2 deg (measured on held-out 160x120 bags); chained frame to frame, about 0.1 deg.
        """
        previous, R_ref_prev = self._chain
        R_prev_cur = _frame_rotation(previous, tracked, self.camera.calibration, threshold)
        R_ref_cur = R_ref_prev if R_prev_cur is None else R_ref_prev @ R_prev_cur
        self._chain = (tracked, R_ref_cur)
        return R_ref_cur

    def _initialise(self, frame: int, stamp_ns: int, tracked: TrackedFrame) -> VOFrame:
        settings = self.settings
        calibration = self.camera.calibration
        threshold = settings.pixel_threshold / calibration.fx
        state = "lost" if self.state == "lost" else "initialising"
        reference_frame, reference_stamp, reference = self._reference or (None, None, None)
        found, rows = _lookup(reference, tracked.ids) if reference is not None else (None, None)
        if reference is None or found.sum() < max(settings.min_tracks, settings.init_min_reference_tracks):
            # No reference yet, or too few of its tracks are left to make a map: start again from this frame.
            self._abandon_reference()
            self._set_reference(frame, stamp_ns)
            return VOFrame(state, rotation_from_reference=np.eye(3), map_id=self.map_id, reference_frame=frame,
                           tracks=len(self.tracker))
        rotation = self._chained_rotation(tracked, threshold)
        if self.record:
            self._initialising.append((frame, rotation, tracked))
        x_ref = calibration.undistorted_normalised(reference.pixels[rows])
        x_cur = calibration.undistorted_normalised(tracked.pixels[found])
        min_parallax = max(settings.init_parallax_deg, np.degrees(settings.init_parallax_px / calibration.fx))
        result = two_view_map(x_ref, x_cur, threshold, min_points=settings.init_min_points, min_parallax_deg=min_parallax)
        if result is None or not result.ready:
            # The direction of travel, once the parallax shows one, comes from the essential matrix.
            direction = None if result is None else result.T_ref_cur[:3, 3]
            return VOFrame(state, rotation_from_reference=rotation, direction_from_reference=direction,
                           map_id=self.map_id, reference_frame=reference_frame, tracks=len(tracked.ids))

        # A new map: the reference frame and this one are its first keyframes, fixed (its gauge and unit).
        # Mapping may still be busy with the old map's keyframes: it finishes them on the old map while
        # tracking goes on (waiting here stalled a 30 Hz replay for the whole first solve, 6 s measured).
        local_map = LocalMap()
        ids = tracked.ids[found]
        local_map.add_keyframe(reference_frame, reference_stamp, np.eye(4), reference.ids, reference.pixels)
        self.tracker.top_up()
        current = self.tracker.current()
        keyframe = local_map.add_keyframe(frame, stamp_ns, result.T_ref_cur, current.ids, current.pixels)
        for landmark_id, point in zip(ids[result.inliers].tolist(), result.points):
            local_map.landmarks[landmark_id] = point
        # Refined at once (two keyframes, the camera held): the essential matrix's motion from a small
        # parallax is noisy, and every later pose builds on it.
        refine_two_keyframes(local_map, calibration, settings.pixel_threshold)
        self.map = local_map
        self.map_id += 1
        self.state = "ok"
        self._reference = None
        self._poses.clear()
        self._poses.append((frame, keyframe.T_w_c.copy()))
        self._poses_version = local_map.version
        self._last_keyframe_inliers = int(result.inliers.sum())
        self._last = (keyframe, np.eye(4))
        # The next step's rotation through the guess is blended with the tracks' from this frame, as every
        # later step's (without, the first step of each map kept PnP's: 2.66 deg off on r160_206's camera,
        # 1.89 with).
        self._previous = tracked
        first = local_map.keyframes[0]
        self._keep_image(first.frame, self._reference_image)
        self._keep_image(frame, self.tracker.gray)
        self._record(first.frame, local_map, first, np.eye(4), reference)
        for between, R_ref_between, tracks in self._initialising[:-1]:  # the last one is this frame
            T_ref_between = np.eye(4)
            T_ref_between[:3, :3] = R_ref_between
            self._record(between, local_map, first, T_ref_between, tracks)
        self._initialising.clear()
        for between, tracks in self._abandoned:  # no pose relative to the map: PnP alone places them
            self._record(between, local_map, first, None, tracks)
        self._abandoned.clear()
        self._record(frame, local_map, keyframe, np.eye(4), current)
        self._submit(local_map, keyframe)
        return VOFrame("ok", T_map_cam=keyframe.T_w_c.copy(), covariance=None, map_id=self.map_id,
                       reference_frame=reference_frame, new_map=True, keyframe=True, tracks=len(tracked.ids),
                       inliers=int(result.inliers.sum()), rotation_from_reference=rotation)

    def _track(self, frame: int, stamp_ns: int, tracked: TrackedFrame, guess: np.ndarray | None) -> VOFrame:
        settings = self.settings
        # One consistent state of the map and camera: local mapping may move keyframes, landmarks and
        # the camera at any time (reading them at different moments put a bundle adjustment's whole
        # correction into one frame's motion: 2.2 deg RPE per frame in a 30 Hz replay, measured).
        with self.map.lock:
            T_w_prev = self._pose_previous_again()  # again, if a solve landed while this frame was tracked
            calibration = self.camera.calibration
            version = self.map.version
            mask, positions = self.map.landmark_positions(tracked.ids)
            anchor = self.map.keyframes[-1]
            T_w_anchor = anchor.T_w_c.copy()
        threshold = settings.pixel_threshold / calibration.fx
        # Every track's ray once: PnP takes those with landmarks, the keyframe decision the rest.
        rays = calibration.undistorted_normalised(tracked.pixels)
        whitening = ray_whitening(calibration, rays[mask])
        # The robust refinement only through a solved camera: through the guess the residuals hold the
        # camera's own error, which a loss scaled to the noise would take for outliers.
        robust = settings.robust_pnp and not self.camera.is_guess
        pnp = solve_pnp(positions, rays[mask], threshold, guess=guess, min_inliers=settings.min_pnp_inliers,
                        whitening=whitening, robust=robust)
        rescued = False
        if pnp is None and self.camera.is_guess:
            # Only as a rescue: a wider threshold on every frame through the guess broke three dev maps.
            pnp = solve_pnp(positions, rays[mask], settings.guess_pnp_threshold_factor * threshold, guess=guess,
                            min_inliers=settings.min_pnp_inliers, whitening=whitening)
            rescued = pnp is not None
        if pnp is None:
            # The map is lost, not the tracks: the rotation they show from the previous frame is still
            # measured (the pose head's, which bridged such a frame alone, was 3.1 deg off on r640_304).
            rotation = None if self._previous is None else _frame_rotation(self._previous, tracked, calibration, threshold)
            return self._lose(frame, stamp_ns, True, len(tracked.ids), rotation)
        previous_tracks, self._previous = self._previous, tracked
        # A track whose landmark does not fit the pose is a mismatch (or a bad landmark): never use it again.
        outliers = tracked.ids[mask][~pnp.inliers]
        if len(outliers):
            self.tracker.drop(outliers)
        T_anchor_cur = invert_transform(T_w_anchor) @ pnp.T_w_c
        T_prev_cur = None if T_w_prev is None else invert_transform(T_w_prev) @ pnp.T_w_c
        covariance = pnp.covariance
        guess = self.camera.is_guess
        if T_prev_cur is not None and previous_tracks is not None and (
                guess or self.camera.relative_focal_std() > settings.uncertain_focal_share):
            # Through an uncertain camera the step's rotation has two estimates with errors of their own:
            # PnP's, against a map made through that camera (through the guess its translation 49-146 deg
            # off on 11 of 22 first maps), and the tracks' rotation frame to frame, which takes the
            # translation's parallax for a turn. Through the guess, a third of the way from PnP's
            # published a better rotation on 16 of 23 replays, a worse one on 3 (at most 12 %); the
            # frame-to-frame rotation alone, on 14 and 5 (docs/RESULTS.md).
            R_chained = _frame_rotation(previous_tracks, tracked, calibration, threshold)
            if R_chained is not None:
                blend = settings.guess_rotation_blend if guess else 0.0
                T_prev_cur, covariance = blend_rotation(T_prev_cur, covariance, R_chained, blend)
        with self.map.lock:  # the pose in the map as it is now, through the newest keyframe
            T = anchor.T_w_c @ T_anchor_cur
        T[:3, :3] = nearest_rotation(T[:3, :3])  # products of poses drift off SO(3) in the last digits
        # The motion model and a new keyframe keep the pose in the state it was measured in, with that
        # state's version: a change that landed since (moving the anchor) makes the next frame, and local
        # mapping, pose them again. Through the moved anchor, a keyframe that local mapping had posed again
        # put its correction (14 cm, measured) into the velocity, and the next frame's predicted pixels
        # 55 px off (heldout_160 at 10 Hz: tracking lost).
        T_measured = pnp.T_w_c.copy()
        T_measured[:3, :3] = nearest_rotation(T_measured[:3, :3])
        self._poses.append((frame, T_measured))
        self._poses_version = version
        inliers = int(pnp.inliers.sum())
        keyframe = self._is_keyframe(frame, tracked, rays, inliers, T, calibration)
        if keyframe:
            self.tracker.top_up()
            current = self.tracker.current()
            new_keyframe = self.map.add_keyframe(frame, stamp_ns, T_measured, current.ids, current.pixels, map_version=version)
            self._last = (new_keyframe, np.eye(4))  # before mapping moves it
            self._last_keyframe_inliers = inliers
            self._keep_image(frame, self.tracker.gray)
            self._record(frame, self.map, new_keyframe, np.eye(4), current)
            self._submit(self.map, new_keyframe)
        else:
            self._last = (anchor, T_anchor_cur)
            self._record(frame, self.map, anchor, T_anchor_cur, tracked)
        return VOFrame("ok", T_map_cam=T.copy(), covariance=covariance, map_id=self.map_id,
                       reference_frame=self.map.keyframes[0].frame, keyframe=keyframe,
                       tracks=len(tracked.ids), inliers=inliers, T_prev_cur=T_prev_cur, guess_rescued=rescued)

    def _keep_image(self, frame: int, image: np.ndarray | None) -> None:
        """Keep a keyframe's image while recording, within the budget (the oldest go first)."""
        if not self.record or image is None:
            return
        previous = self.keyframe_images.pop(frame, None)
        self._image_bytes += image.nbytes - (0 if previous is None else previous.nbytes)
        self.keyframe_images[frame] = image
        while self._image_bytes > self.image_budget_bytes and self.keyframe_images:
            oldest = next(iter(self.keyframe_images))
            self._image_bytes -= self.keyframe_images.pop(oldest).nbytes
            self.keyframe_images_dropped += 1

    def _record(self, frame: int, local_map: LocalMap, reference: Keyframe, T_kf_cam: np.ndarray | None,
                tracks: TrackedFrame) -> None:
        if self.record:
            self.records.append(FrameRecord(frame, self.map_id, local_map, reference,
                                            None if T_kf_cam is None else T_kf_cam.copy(),
                                            tracks.ids.copy(), tracks.pixels.copy(), local_map.unit_scale))

    def _is_keyframe(self, frame: int, tracked: TrackedFrame, rays: np.ndarray, inliers: int, T_w_c: np.ndarray,
                     calibration) -> bool:
        settings = self.settings
        last = self.map.keyframes[-1]
        if inliers < settings.keyframe_landmark_share * self._last_keyframe_inliers:
            return True
        found, rows = last.lookup(tracked.ids)
        if found.sum() < settings.min_tracks:
            return True
        if self.mapping.waiting >= settings.max_waiting_keyframes:
            return False
        if frame - last.frame >= settings.max_keyframe_interval:
            return True
        # Parallax is what triangulation needs: the angle between a track's rays once the rotation
        # between the frames is taken out (a camera that only turns moves pixels but adds no depth).
        rays_last = unit_rays(self._keyframe_rays(last, calibration)[rows])
        rays_now = unit_rays(rays[found])
        R_now_last = T_w_c[:3, :3].T @ last.T_w_c[:3, :3]
        cosine = np.sum((rays_last @ R_now_last.T) * rays_now, axis=1)
        angles = np.degrees(np.arccos(np.clip(cosine[np.isfinite(cosine)], -1.0, 1.0)))
        parallax = settings.guess_keyframe_parallax_deg if self.camera.is_guess else settings.keyframe_parallax_deg
        return len(angles) > 0 and float(np.median(angles)) >= parallax

    def _keyframe_rays(self, keyframe: Keyframe, calibration) -> np.ndarray:
        """The undistorted normalised points of ``keyframe``'s pixels through ``calibration``, kept until
        either changes (every frame's keyframe decision needs them: 0.4 ms each time at 640x480)."""
        cached = self._rays_cache
        if cached is None or cached[0] is not keyframe or cached[1] is not calibration or cached[2] is not keyframe.pixels:
            cached = (keyframe, calibration, keyframe.pixels, calibration.undistorted_normalised(keyframe.pixels))
            self._rays_cache = cached
        return cached[3]

    # -- motion prediction -------------------------------------------------------------------------

    def _pose_previous_again(self) -> np.ndarray | None:
        """The previous frame's pose in the map and camera as they are now (None without one), and the
        motion model brought into the same state.

        Local mapping moves keyframes, landmarks and the camera between frames. The previous frame's
        pose measured before a bundle adjustment landed is posed again by PnP on its tracks: else the
        difference of the two states, the camera's change included, would count as the next frame's
        motion. The motion model follows (its last pose replaced, its step kept): a velocity taken from
        two states put the next frame's predicted pixels, which seed Lucas-Kanade, off by the change of
        state (measured in real time on VAMR, the frames after the first camera initialisation landed
        with the focal length from 79 % to 9 % off: 25 of their 67 landmarks fitted, and tracking was
        lost two frames later).
        """
        if self.map is None or self._last is None:
            return None
        with self.map.lock:
            reference, T_kf_prev = self._last
            T_w_prev = reference.T_w_c @ T_kf_prev
            version = self.map.version
            if version == self._poses_version:
                return T_w_prev
            if self._previous is not None:
                calibration = self.camera.calibration
                mask, positions = self.map.landmark_positions(self._previous.ids)
                rays = calibration.undistorted_normalised(self._previous.pixels[mask])
                robust = self.settings.robust_pnp and not self.camera.is_guess
                again = solve_pnp(positions, rays, self.settings.pixel_threshold / calibration.fx, guess=T_w_prev,
                                  min_inliers=self.settings.min_pnp_inliers, covariance=False,
                                  whitening=ray_whitening(calibration, rays) if robust else None, robust=robust)
                if again is not None:
                    T_w_prev = again.T_w_c
                    self._last = (reference, invert_transform(reference.T_w_c) @ T_w_prev)
            if self._poses:
                last_frame, T_last = self._poses[-1]
                moved = T_w_prev @ invert_transform(T_last)
                kept = [(f, moved @ T) for f, T in list(self._poses)[:-1]]
                self._poses.clear()
                self._poses.extend(kept + [(last_frame, T_w_prev)])
            self._poses_version = version
            return T_w_prev

    def _predicted_pose(self, frame: int) -> np.ndarray | None:
        """Constant velocity from the last two posed frames (None without two)."""
        if self.state != "ok" or len(self._poses) < 1:
            return None
        if len(self._poses) < 2:
            return self._poses[-1][1]
        (f0, T0), (f1, T1) = self._poses[-2], self._poses[-1]
        if f1 == f0:
            return T1
        step = invert_transform(T0) @ T1
        if frame - f1 != f1 - f0:
            return T1  # an irregular gap: velocity is not known in frames
        return T1 @ step

    def _predicted_pixels(self, T_w_c: np.ndarray) -> dict[int, np.ndarray] | None:
        """Where the landmarks of the live tracks project at pose ``T_w_c`` (the map's other landmarks are not
        tracked); None when the map changed since the motion model was brought up to date: the guess and the
        landmarks must be of one state (:meth:`_pose_previous_again`), and without a prediction Lucas-Kanade
        starts where the tracks were."""
        if self.map is None:
            return None
        with self.map.lock:
            if self.map.version != self._poses_version:
                return None
            calibration = self.camera.calibration
            landmarks = self.map.landmarks
            ids = [i for i in self.tracker.ids.tolist() if i in landmarks]
            if not ids:
                return None
            points = np.array([landmarks[i] for i in ids])
        points_c = (points - T_w_c[:3, 3]) @ T_w_c[:3, :3]
        pixels = calibration.project(points_c)
        ok = np.isfinite(pixels).all(1)
        return dict(zip(np.asarray(ids)[ok].tolist(), pixels[ok]))


def blend_rotation(T_prev_cur: np.ndarray, covariance: np.ndarray, R_tracks: np.ndarray,
                   blend: float) -> tuple[np.ndarray, np.ndarray]:
    """A step's rotation moved ``blend`` of the way from PnP's to the tracks' ``R_tracks``, and its covariance.

    Returns the step ``(4, 4)`` (translation kept) and ``covariance`` ``(6, 6)`` (``(rho, theta)``) with the
    squared angle between the two rotations added to each rotation axis. The published rotation lies
    between two estimates each off by a bias of its own, so their distance is how far it may be off, in
    any direction: along the disagreement alone, r640_307's steps 3-6 stayed 0.7-1.2 deg off and
    published at 0.07-0.15 deg (docs/RESULTS.md).
    """
    disagreement = so3_log(T_prev_cur[:3, :3].T @ R_tracks)
    blended = T_prev_cur.copy()
    blended[:3, :3] = T_prev_cur[:3, :3] @ so3_exp(blend * disagreement)
    widened = covariance.copy()
    widened[3:, 3:] += np.eye(3) * float(disagreement @ disagreement)
    return blended, widened


def _frame_rotation(previous: TrackedFrame, tracked: TrackedFrame, calibration, threshold: float) -> np.ndarray | None:
    """``R_prev_cur`` fitted to the tracks two frames share (rays through ``calibration``, RANSAC at
    ``threshold`` in normalised units), or None with fewer than 3 of them."""
    found, rows = _lookup(previous, tracked.ids)
    x_prev = calibration.undistorted_normalised(previous.pixels[rows])
    x_cur = calibration.undistorted_normalised(tracked.pixels[found])
    finite = np.isfinite(x_prev).all(1) & np.isfinite(x_cur).all(1)
    if finite.sum() < 3:
        return None
    R, _ = rotation_ransac(unit_rays(x_prev[finite]), unit_rays(x_cur[finite]), threshold)
    return R.T


def _lookup(tracked: TrackedFrame, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``ids`` in a (sorted-id) tracked frame: ``(found mask over ids, rows of the found)``."""
    order = np.argsort(tracked.ids, kind="stable")
    sorted_ids = tracked.ids[order]
    position = np.clip(np.searchsorted(sorted_ids, ids), 0, max(len(sorted_ids) - 1, 0))
    found = sorted_ids[position] == ids if len(sorted_ids) else np.zeros(len(ids), dtype=bool)
    return found, order[position[found]]
