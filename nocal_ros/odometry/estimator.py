"""OdometryEstimator: camera frames in, integrated poses, twist and covariances out. No ROS here.

The odometry node, ``nocal odometry`` and ``nocal demo`` all feed frames to this one class, so every
rule about dropped frames, time jumps, lost tracking and bad network output lives in one place.

Methods (``method=``)
    ``"vo"`` (the default): keyframe visual odometry through the online camera
    (:mod:`nocal_ros.odometry.tracking`, :mod:`~nocal_ros.odometry.local_mapping`): persistent tracks,
    PnP against a local map, windowed bundle adjustment over keyframes, landmarks and the camera in a
    worker thread, metric scale from arm poses, the ground plane and a known camera height, or the NOCaL
    pose head (:mod:`~nocal_ros.odometry.scale`).
    The pose head also bridges frames where geometry fails (``tracking="lost"``), with the rotation
    the tracks show from the previous frame where they go on.
    ``"pose_head"``: the NOCaL pose head alone, integrated pair by pair (the paper's odometry).

Frames and poses
    Odometry is published for ``base_frame`` (REP 105), which is rigidly attached to the camera by the
    static ``T_base_cam``. The ``odom`` frame is the base frame's pose at the first frame, so::

        T_odom_base(t) = T_base_cam @ T_cam0_camt @ inv(T_base_cam)
        T_bi_bj        = T_base_cam @ T_ci_cj  @ inv(T_base_cam)      (one pair, base frame)
        T_odom_base_j  = T_odom_base_i @ T_bi_bj

    With ``T_base_cam = I`` (the default) the base frame is the camera optical frame. A VO map is
    anchored in ``odom`` at the camera pose published for its first keyframe; its poses are scaled to
    metres by the current scale estimate. When the estimate changes, the anchor moves so that the pose
    published at that moment does not jump: a new scale applies to the motion from then on.

    ``odom`` is continuous and drifts: a published pose is never taken back. The ``map`` frame (REP 105's,
    as rtabmap publishes it) holds the maps as bundle adjustment refines them, at the current scale:
    each map's first keyframe stays where odometry published it, and ``T_map_odom``
    (``OdometryResult.T_map_odom``) is how far ``odom`` has drifted from the map's newest keyframe::

        T_map_odom = T_map_cam(newest keyframe) @ inv(T_odom_cam(published at that keyframe))

    ``map`` starts as ``odom`` (the identity before the first map), and a new map's first keyframe is placed
    through the correction its predecessor left. The correction jumps where the map moves (bundle
    adjustment, a new scale) and where a map starts. ``map`` is the better frame for where the camera is
    (on the 19 dev replays with a camera height, the position error from the start, unaligned, fell on
    17 and the rotation error on 18; docs/RESULTS.md), ``odom`` for how it moved between two frames.

States (``OdometryResult.tracking``)
    ``"initialising"``: no map yet (a still camera never leaves this state). The rotation is measured
    from the tracks; no translation is reported (monocular geometry sees none without parallax).
    ``"ok"``: posed by the VO. ``"lost"``: geometry failed (too few tracks or PnP inliers, or a frame
    with no texture at all). The motion is the pose head's when the frame has texture, else none, and
    the covariance is inflated by :data:`LOST_STD` per frame so that no consumer trusts the pose; a new
    map is initialised from the next frames and continues from the pose reached.

Twist
    ``nav_msgs/Odometry`` gives the twist in the child (base) frame. For the pair ``i -> j`` over
    ``dt`` seconds: linear ``R_bi_bj^T t_bi_bj / dt`` (the displacement seen from ``j``), angular
    ``log(R_bi_bj) / dt`` (the rotation vector is the same in ``i`` and ``j``).

Covariance (how it is derived)
    Each pair's error is modelled as a right perturbation ``T_bi_bj Exp(xi)``, ``xi = (rho, theta)``,
    zero-mean Gaussian, moved to the base frame by the adjoint of ``T_base_cam``. Its covariance is:
    for a VO frame, the PnP pose's covariance from the inliers' reprojection information (the
    information of a motion-only bundle adjustment against the map), each ray's noise the image noise
    through the lens at its pixel (:func:`~nocal_ros.odometry.frontend.pose_covariance`) and, through
    the guessed camera or one whose focal length is still uncertain, the distance between PnP's and the
    tracks' rotation of the step added to each rotation axis (:func:`~nocal_ros.odometry.tracking.blend_rotation`), with the translation scaled
    to metres; while initialising and for the pose head, the spread of the pose head's error per frame
    recorded by training (``pose_error_std`` in the checkpoint, else :data:`DEFAULT_POSE_ERROR_STD`),
    times the gap ``g`` in frames; when lost, :data:`LOST_STD`. A step measured by geometry through the
    online camera (``"vo"``, ``"two_view"``, ``"rotation"``) adds what the camera's focal length does
    not know (:func:`~nocal_ros.odometry.covariance.focal_step_covariance`): before the first window,
    35 % of the step's size through the f = width guess (:data:`~nocal_ros.odometry.calibration.GUESS_STD`).
    Without it, steps measured through the guess were published at 0.07-0.1 deg per axis where they
    were 1.8-2.3 deg off, and the mean rotation NEES of a replay (3 when consistent) had a median of
    27 over 23 replays; with it 1.4 (docs/RESULTS.md). A step's length is also only as good as its
    scale (:func:`~nocal_ros.odometry.covariance.scale_step_covariance`, along the step): the map's
    scale's ``relative_std`` for a VO frame (the arm fit's least-squares spread, the ground plane's
    :data:`~nocal_ros.odometry.scale.GROUND_SCALE_STD` or its fits' wider spread, wider while fewer than
    three fits or only fits through the guess stand behind it, the pose head's
    :data:`~nocal_ros.odometry.scale.POSE_HEAD_SCALE_STD`), the pose head's where its length is used.
    Without it, a replay on the pose head's scale (heldout_160, x0.7) had 51 % of its steps' translation
    errors within the 99 % bound; with it all. A step measured through the guessed camera on the pose
    head's scale knows its direction no better than its length: the step's length, or the pose head's
    length of a step at the map's start where that is longer (a map made through the guess shrank the
    fisheye's steps to x0.01-0.09), times ``1 + POSE_HEAD_SCALE_STD``, is added on every axis
    (:func:`~nocal_ros.odometry.covariance.direction_free_step_covariance`). The pose covariance, in ROS order
    ``(x, y, z, rot_x, rot_y, rot_z)`` with position in ``odom`` and rotation about ``odom``'s axes, is
    propagated to first order::

        Sigma_j = A Sigma_i A^T + B Sigma_xi B^T,
        A = [[I, -[R_i t_ij]x], [0, I]],   B = [[R_j, 0], [0, R_j]]

    The twist covariance is ``Sigma_xi / dt^2``. A frame with no motion estimate (the first frame, or
    one after a reset) reports a twist covariance of :data:`UNKNOWN_VARIANCE`, ROS's "unknown".

Dropped frames and resets
    The frame period is the smallest stamp step seen recently (drops only lengthen steps). A step of
    ``g = round(dt / period)`` frames is one pair. The pose head cannot pair frames more than ``max_gap``
    (the largest gap training used) apart: in ``"pose_head"`` mode a longer step starts a new pair chain
    from the current frame with a warning, keeping the pose (``status="gap_reset"``); the VO tracks
    across it or, failing that, re-initialises. Time going backwards resets everything (pose to identity,
    ``status="time_reset"``), as ROS does on a clock jump; a repeated stamp is skipped. A change of image
    encoding starts a new pose head chain (a pair across encodings would be meaningless). A change of
    image size raises :class:`FrameSizeError`, leaving the state untouched, until
    :meth:`OdometryEstimator.reset` accepts the new size. A non-finite network output skips the frame in
    ``"pose_head"`` mode (counted); the next frame pairs with the last good one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import torch

from nocal_ros.errors import NocalError
from nocal_ros.geometry import invert_transform, nearest_rotation, so3_log
from nocal_ros.odometry.calibration import (
    OnlineCamera,
    as_vo_calibration,
    calibration_from_learnt_camera,
    calibration_status,
    prior_calibration,
)
from nocal_ros.odometry.covariance import (
    UNKNOWN_VARIANCE,
    adjoint,
    direction_free_step_covariance,
    focal_step_covariance,
    propagate_covariance,
    scale_step_covariance,
)
from nocal_ros.odometry.pose_head import PoseModel, PoseRunner
from nocal_ros.odometry.scale import (
    FEW_GROUND_FITS_SCALE_STD,
    GROUND_MOTION_SCALE_STD,
    GROUND_SCALE_STD,
    GUESS_GROUND_SCALE_STD,
    MIN_GROUND_FITS_SPREAD,
    MIN_GROUND_POINTS,
    MIN_HOMOGRAPHY_INLIERS,
    POSE_HEAD_SCALE_STD,
    UNKNOWN_SCALE_STD,
    ScaleEstimate,
    fit_arm_scale,
    fit_arm_similarity,
    fit_ground_scale,
    ground_motion_ratio,
)
from nocal_ros.odometry.tracking import TrackingSettings, VisualOdometry, VOFrame

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry.frontend import TrackedFrame
    from nocal_ros.odometry.map import LocalMap

log = logging.getLogger(__name__)

#: How many recent stamp steps the frame period is estimated from.
PERIOD_HISTORY = 32
#: Per-frame standard deviation of a lost frame's motion: 1 m and 0.5 rad, so nobody trusts it.
LOST_STD = {"translation_m": 1.0, "rotation_rad": 0.5}
#: Published poses kept per frame, for anchoring a new map at its first keyframe.
POSE_HISTORY = 256
#: The most recent keyframes with arm poses that the scale is fitted to: a monocular map's scale drifts
#: (and moves while the online camera converges), so the newest part of the map is the one to match.
ARM_FIT_KEYFRAMES = 10
#: The live ground-plane scale is fitted to this many newest keyframes' landmarks (a road is a plane locally).
GROUND_FIT_KEYFRAMES = 10
#: Fewest landmarks on the plane for a live window's fit through a solved camera. The whole map's fit at the
#: end, and a window's through the guess, need MIN_GROUND_POINTS. Over 21 dev replays, windows' fits through a
#: solved camera on 20-29 landmarks were x1.02-1.05 of the window's true scale at the median (log robust std
#: 0.10, against 0.05-0.08 on 30 or more), on 10-19 x1.09-1.33 (0.37-0.41); through the guess, those on 20-29
#: were x1.0-20 (measured). Where windows show only 20-29 of the floor's landmarks, a map's first fit comes
#: that much sooner (r640_306's at frame 40 instead of 70).
LIVE_MIN_GROUND_POINTS = 20
#: Fewest keyframes for a ground-plane fit.
MIN_GROUND_KEYFRAMES = 3
#: Relative standard deviation of a map's first scale from the arm's positions at its first two keyframes:
#: two positions leave no residual to measure it by, so it is taken as 10 % (not measured) until the arm's
#: fit replaces it from three keyframes.
ARM_PAIR_SCALE_STD = 0.1
#: The live ground-plane scale is the median of the map's newest fits, this many: one fit in 20-40 takes a
#: plane that is not the floor (heldout_160's last keyframe x3.5, its fifth x1.7; measured).
GROUND_FIT_HISTORY = 5
#: A map's scale from the ground plane's homography between consecutive frames (before any window's plane
#: fit: :meth:`OdometryEstimator._update_ground_motion`) is the median of its newest samples, this many at most,
#: made within the last :data:`GROUND_FIT_KEYFRAMES` keyframes (the live plane fit's span: a monocular map's
#: scale drifts, and the camera moves while it converges; r640_307's sample of frame 17, x2.26 in a map tracked
#: through a camera 27-89 % off, made the median of frame 86's three x1.86, measured). It is taken from the
#: second sample: one sample alone was x2.3 on test_vo's room (9 tracks), where frames published on two were
#: off by log RMS 0.21 over the 21 dev replays (11 frames; on three or more 0.27, 78 frames), and the pose
#: head's scale they replaced was x0.08 on KITTI's frames 11-14 (measured).
GROUND_MOTION_HISTORY = 9
MIN_GROUND_MOTION_SAMPLES = 2
#: Arm poses kept, and how far from a keyframe's stamp one may be to count for it.
ARM_POSE_HISTORY = 10000
ARM_TOLERANCE_NS = 20_000_000
METHODS = ("vo", "pose_head")
#: Keyframes of the maps before the current one kept for :meth:`OdometryEstimator.map_snapshot`'s path (the
#: newest): 0.19-0.43 of the frames were keyframes on the dev replays, so 13-30 minutes at 30 Hz.
PATH_HISTORY = 10_000


class FrameError(NocalError):
    """A frame the estimator cannot use (wrong shape or type)."""


class FrameSizeError(FrameError):
    """The image size changed mid-stream; the learnt calibration and the pair chain no longer apply."""


# --------------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------------


@dataclass
class OdometryResult:
    """The estimate at one frame.

    Attributes:
        stamp_ns: the frame's stamp.
        T_odom_base: ``(4, 4)`` base pose in ``odom``.
        T_odom_cam: ``(4, 4)`` camera pose in ``odom`` (``T_odom_base @ T_base_cam``).
        T_prev_curr: ``(4, 4)`` base motion since the previous frame used (identity after a reset).
        twist: ``(6,)`` ``(vx, vy, vz, wx, wy, wz)`` in the base frame, m/s and rad/s.
        pose_covariance, twist_covariance: ``(6, 6)`` in ROS order (see the module notes).
        status: ``"ok"``; ``"start"`` for the first frame of a chain (first frame, after a reset or a
            model reload); ``"gap_reset"``, ``"time_reset"`` or ``"encoding_reset"`` for a chain
            started for that reason.
        gap: frames spanned by the pair (0 when no pair was run).
        inference_ms: time spent in the pose head for this frame.
        motion_source: where the pair's motion came from: ``"vo"``; while there is no map
            ``"two_view"`` (the essential matrix's rotation and direction, the pose head's length) or
            ``"rotation"`` (a rotation explains the tracks: no translation); ``"pose_head"`` or
            ``"none"`` (held still) when lost.
        tracking: ``"initialising"``, ``"ok"`` or ``"lost"`` (see the module notes).
        scale_source: what made the translation metric: ``"arm"``, ``"ground"``, ``"pose_head"`` or ``"none"``.
        keyframe: the frame became a VO keyframe.
        T_map_odom: ``(4, 4)`` the ``map`` frame's correction of ``odom`` as of this frame (see the module
            notes; the identity before the first map and for ``method="pose_head"``).
    """

    stamp_ns: int
    T_odom_base: np.ndarray
    T_odom_cam: np.ndarray
    T_prev_curr: np.ndarray
    twist: np.ndarray
    pose_covariance: np.ndarray
    twist_covariance: np.ndarray
    status: str
    gap: int
    inference_ms: float = 0.0
    motion_source: str = "pose_head"
    tracking: str = "ok"
    scale_source: str = "pose_head"
    keyframe: bool = False
    T_map_odom: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass
class OdometryCounters:
    """What happened to the frames so far (for diagnostics and reports)."""

    frames: int = 0  # frames given to process()
    pairs: int = 0  # motions integrated
    bridged_gaps: int = 0  # pairs spanning more than one frame period
    gap_resets: int = 0
    time_resets: int = 0
    encoding_resets: int = 0
    nonfinite_skipped: int = 0
    duplicate_stamps: int = 0
    size_rejected: int = 0
    keyframes: int = 0
    maps: int = 0  # VO maps initialised (more than one: re-initialised after losing track)
    initialising_frames: int = 0
    lost_frames: int = 0
    pose_head_fallbacks: int = 0  # lost frames bridged by the pose head
    guess_rescues: int = 0  # frames PnP posed through the guessed camera only with a wider threshold


@dataclass(frozen=True)
class MapSnapshot:
    """The VO's keyframes and landmarks in ``odom`` and metres, as they stand (what ORB-SLAM3's viewer and
    rviz show: the node publishes them as ``nav_msgs/Path`` and ``sensor_msgs/PointCloud2``).

    The current map is placed so that its newest keyframe sits where odometry published that frame, so
    the path ends where ``/odom`` was then; its older keyframes and its landmarks are where bundle
    adjustment has since put them, at the current scale. The keyframes of the maps before it (since the
    last reset; lost and re-initialised) stay as they were when their map was left.

    Attributes:
        stamps_ns: ``(N,)`` the keyframes' stamps, oldest first.
        T_odom_base: ``(N, 4, 4)`` their base poses in ``odom``.
        map_ids: ``(N,)`` the VO map each keyframe belongs to.
        points: ``(M, 3)`` the current map's landmarks in ``odom`` (m).
        point_ids: ``(M,)`` their ids (the ids of the tracks they were triangulated from).
        map_id: the current map's id (0: no map yet).
        scale_source: what made the current map metric: ``"arm"``, ``"ground"``, ``"pose_head"`` or ``"none"``.
        T_map_odom: ``(4, 4)`` the ``map`` frame's correction of ``odom`` that places the current map's keyframes
            and landmarks where ``map`` holds them (``T_map_odom @ T_odom_base``; see the estimator's module notes).
    """

    stamps_ns: np.ndarray
    T_odom_base: np.ndarray
    map_ids: np.ndarray
    points: np.ndarray
    point_ids: np.ndarray
    map_id: int = 0
    scale_source: str = "none"
    T_map_odom: np.ndarray = field(default_factory=lambda: np.eye(4))


# --------------------------------------------------------------------------------------------------
# the estimator
# --------------------------------------------------------------------------------------------------


class OdometryEstimator:
    """Odometry over a stream of frames (see the module notes).

    Args:
        checkpoint: a checkpoint path, a model store directory, a loaded ``Checkpoint``, a
            :class:`PoseModel` (any pose function, e.g. for tests), or None for the shipped model.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``... (ignored for a :class:`PoseModel`).
        T_base_cam: static ``(4, 4)`` pose of the camera optical frame in the base frame.
        frame_period_s: the camera's frame period; None estimates it from the stamps.
        distortion_model: the online camera's lens model: ``"plumb_bob"`` or ``"equidistant"`` (fisheye);
            ``"auto"``: plumb_bob, except a learnt camera (a fine-tuned model's) that plumb_bob cannot
            hold and equidistant can (:func:`~nocal_ros.odometry.calibration.calibration_from_learnt_camera`).
            ``"equidistant"`` starts from ``f = width``.
        precision: ``"fp32"``, or ``"fp16"`` / ``"bf16"`` autocast on CUDA.
        cuda_graphs: capture the pose head in CUDA graphs on CUDA (falls back to eager if capture fails).
        channels_last: run the convolutions in channels-last layout (faster on CPU; see BENCHMARKS.md).
        method: ``"vo"`` or ``"pose_head"`` (see the module notes).
        calibration: a ``CameraCalibration`` to start the online camera from (else the model's learnt
            camera, else ``f = width``).
        synchronous_mapping: run local mapping before :meth:`process` returns (replays that must repeat
            exactly) instead of in its worker thread.
        settings: VO thresholds (:class:`~nocal_ros.odometry.tracking.TrackingSettings`).
        record_trajectory: keep what :meth:`final_trajectory` needs (every frame's tracks: for replays,
            not for a node that runs for hours).
        camera_height: the camera's height above the ground (m), where it moves over a floor or road at a
            known height (KITTI: 1.65): where no arm poses fit, the scale comes from the ground plane in
            the map (:func:`~nocal_ros.odometry.scale.fit_ground_scale`) instead of the pose head. The
            ground's normal is expected near ``base_frame``'s -z (REP 103) through ``T_base_cam``, or near
            the image's down direction where ``T_base_cam`` is the identity (the camera is the base).
            :meth:`set_ground_to_camera` gives both from a frame on the ground instead.

    Thread-safe: :meth:`process`, :meth:`reset` and :meth:`reload` may be called from different threads.
    """

    def __init__(
        self,
        checkpoint: Any = None,
        device: str | torch.device = "auto",
        *,
        T_base_cam: np.ndarray | None = None,
        frame_period_s: float | None = None,
        distortion_model: str = "auto",
        precision: str = "fp32",
        cuda_graphs: bool = True,
        channels_last: bool = True,
        method: str = "vo",
        calibration: "CameraCalibration | None" = None,
        synchronous_mapping: bool = False,
        settings: TrackingSettings | None = None,
        record_trajectory: bool = False,
        camera_height: float | None = None,
    ) -> None:
        if method not in METHODS:
            raise NocalError(f"odometry method must be one of {', '.join(METHODS)}, got {method!r}")
        if distortion_model not in ("auto", "plumb_bob", "equidistant"):
            raise NocalError(f"the online camera is plumb_bob or equidistant, got {distortion_model!r}")
        self._lock = threading.RLock()
        # OpenCV's RANSACs draw from one generator per thread: with its thread pool, a replay did not
        # repeat (the calibration of one held-out bag ended 0.7 % or 30 % off from run to run), and on
        # small per-frame problems the pool is slower anyway (LK tracking 13.6 vs 22 ms at 640x480 on a
        # busy 2-core machine). Process-wide, as OpenCV's setting is.
        cv2.setNumThreads(1)
        self.method = method
        self.channels_last = channels_last
        self.device_request = device
        self.frame_period_s = frame_period_s
        self.distortion_model = distortion_model
        self.precision = precision
        self.cuda_graphs = cuda_graphs
        self.synchronous_mapping = bool(synchronous_mapping)
        self.record_trajectory = bool(record_trajectory)
        self.settings = settings or TrackingSettings()
        if camera_height is not None and not (np.isfinite(camera_height) and camera_height > 0):
            raise NocalError(f"the camera height must be a positive number of metres, got {camera_height!r}")
        self.camera_height = None if camera_height is None else float(camera_height)
        self._down_cam: np.ndarray | None = None  # the ground's down in the camera frame, where a ground frame gave it
        #: What made each map of :meth:`final_trajectory` metric (map id -> ``"arm"``, ``"ground"``, or the
        #: live source of its last published scale).
        self.final_scale_sources: dict[int, str] = {}
        self.counters = OdometryCounters()
        #: Observations :meth:`final_trajectory` found by searching keyframes for landmarks they never tracked.
        self.final_observations_found = 0
        self._T_base_cam = np.eye(4) if T_base_cam is None else np.asarray(T_base_cam, dtype=np.float64)
        self._T_cam_base = invert_transform(self._T_base_cam)
        self._given_calibration = calibration
        self._given_vo_calibration = as_vo_calibration(calibration) if calibration is not None else None
        self._camera: OnlineCamera | None = None
        self._vo: VisualOdometry | None = None
        self._arm_stamps: deque[int] = deque(maxlen=ARM_POSE_HISTORY)
        self._arm_poses: deque[np.ndarray] = deque(maxlen=ARM_POSE_HISTORY)
        self.model: PoseModel
        self._runner: PoseRunner
        self._load(checkpoint)
        if method == "vo":
            # Tracking's first map is refined at once, in this process: its solver's imports belong here,
            # not in the middle of a stream.
            from nocal_ros.odometry.bundle_adjustment import load_libraries

            load_libraries()
        self.reset()

    # -- model -------------------------------------------------------------------------------------

    def _load(self, checkpoint: Any) -> None:
        model = checkpoint if isinstance(checkpoint, PoseModel) else PoseModel.from_checkpoint(checkpoint, self.device_request)
        self.model, self._runner = model, self._make_runner(model)

    def _make_runner(self, model: PoseModel) -> PoseRunner:
        return PoseRunner(model, self.precision, self.cuda_graphs, self.channels_last, history=model.max_gap + 1)

    def reload(self, checkpoint: Any = None) -> str:
        """Swap in another model without losing the pose; returns the new model's id.

        The new model is loaded before the old one is dropped, so a bad file raises (CheckpointError)
        and leaves the running model in place. The pose head's pair chain restarts from the next frame
        (the previous frame was preprocessed for the old model). The online camera is kept unless it
        is still the prior, in which case the new model's learnt camera replaces it.
        """
        model = checkpoint if isinstance(checkpoint, PoseModel) else PoseModel.from_checkpoint(checkpoint, self.device_request)
        runner = self._make_runner(model)
        with self._lock:
            self.model, self._runner = model, runner
            self._has_previous = False
            if self._camera is not None and self._camera.state() == "prior" and self._given_calibration is None:
                self._camera = None  # rebuilt from the new model at the next frame
                self._close_vo()
        log.info("odometry: loaded model %s", model.model_id)
        return model.model_id

    @property
    def model_id(self) -> str:
        return self.model.model_id

    @property
    def input_size(self) -> tuple[int, int]:
        return self.model.input_size

    @property
    def T_base_cam(self) -> np.ndarray:
        return self._T_base_cam.copy()

    def set_base_to_camera(self, T_base_cam: np.ndarray) -> None:
        """Set the static camera mounting; a change restarts odometry (the odom frame moves with it)."""
        T = np.asarray(T_base_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"T_base_cam must be a finite 4x4 transform, got {T.shape}")
        with self._lock:
            if np.allclose(T, self._T_base_cam, atol=1e-12):
                return
            self._T_base_cam, self._T_cam_base = T.copy(), invert_transform(T)
            self.reset()

    # -- state -------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the motion: pose to identity, no previous frame, any image size. The camera is kept
        for frames of the same size (it is the same camera)."""
        with self._lock:
            self._T_odom_base = np.eye(4)
            self._pose_cov = np.zeros((6, 6))
            self._has_previous = False
            self._previous_stamp: int | None = None
            self._previous_key: int | None = None
            self._image_shape: tuple[int, int] | None = None
            self._encoding: str | None = None
            self._steps: deque[int] = deque(maxlen=PERIOD_HISTORY)
            self._frame = 0
            self._published: OrderedDict[int, np.ndarray] = OrderedDict()  # frame -> T_odom_cam
            self._frame_stamps: OrderedDict[int, int] = OrderedDict()
            self._anchor: np.ndarray | None = None  # T_odom_map of the current map
            self._anchor_map_id = -1
            self._scale = ScaleEstimate()
            self._head_step_length: float | None = None  # the pose head's length of one step at the map's start (m)
            # (metres per unit of the map as made, made through the guessed camera) per live ground fit
            self._ground_fits: deque[tuple[float, bool]] = deque(maxlen=GROUND_FIT_HISTORY)
            self._ground_fit_ms: deque[float] = deque(maxlen=500)
            # metres per unit of the map as made, per frame pair's ground homography (through a solved camera)
            self._ground_motions: deque[tuple[float, int]] = deque(maxlen=GROUND_MOTION_HISTORY)  # (value, keyframes then)
            self._ground_motion_ms: deque[float] = deque(maxlen=500)
            self._previous_tracks: tuple[int, int, "TrackedFrame"] | None = None  # (frame, map id, tracks)
            self._arm_stamps.clear()
            self._arm_poses.clear()
            # (frame, stamp, published T_odom_cam, VO map id or None) per frame, for final_trajectory
            self._trajectory_log: list[tuple[int, int, np.ndarray, int | None]] = []
            self._map_scales: dict[int, float] = {}  # map id -> the last scale its poses were published with
            self._map_scale_sources: dict[int, str] = {}  # map id -> where that scale came from
            self._previous_focal_std = 0.0  # the online camera's relative focal std when the last frame was published
            # map_snapshot's path: the maps left behind, (stamp, map id, T_odom_cam) per keyframe, and the current
            # map (the anchored one, _anchor_map_id) with its last placement in odom (T_odom_map, metres)
            self._earlier_path: deque[tuple[int, int, np.ndarray]] = deque(maxlen=PATH_HISTORY)
            self._path_map: LocalMap | None = None
            self._path_placement: np.ndarray | None = None
            # the map frame: its correction of odom as of the last tracked frame, and where it holds the current
            # map's first keyframe (T_map_cam, metres; None until the map is first placed)
            self._T_map_odom = np.eye(4)
            self._map_origin: np.ndarray | None = None
            if self._vo is not None:
                self._vo.reset()

    def _close_vo(self) -> None:
        if self._vo is not None:
            self._vo.close()
            self._vo = None

    def close(self) -> None:
        """Stop the mapping thread (the estimator can still be used; it starts again when needed)."""
        with self._lock:
            self._close_vo()

    @property
    def image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the frames accepted since the last reset, or None."""
        return None if self._image_shape is None else (self._image_shape[1], self._image_shape[0])

    def frame_period_ns(self) -> int | None:
        if self.frame_period_s:
            return int(round(self.frame_period_s * 1e9))
        return min(self._steps) if self._steps else None

    # -- calibration -------------------------------------------------------------------------------

    def _online_camera(self, width: int, height: int) -> OnlineCamera:
        """The online camera for ``width x height`` frames, made on first use (see the module notes)."""
        camera = self._camera
        if camera is not None and (camera.calibration.width, camera.calibration.height) == (width, height):
            return camera
        self._close_vo()
        calibration, source, residual = self._starting_calibration(width, height)
        self._camera = OnlineCamera(calibration, source, residual)
        return self._camera

    def _starting_calibration(self, width: int, height: int) -> tuple["CameraCalibration", str, float]:
        given = self._given_calibration
        if given is not None:
            calibration, residual = self._given_vo_calibration
            return _resized(calibration, width, height, "the given calibration"), "file", residual * width / calibration.width
        learnt = self.model.camera
        if learnt is not None and self.distortion_model in ("auto", "plumb_bob"):
            if abs(learnt.width / learnt.height - width / height) < 1e-3:
                calibration, residual = calibration_from_learnt_camera(learnt, self.distortion_model)
                return calibration.scaled(width, height), "model", residual * width / learnt.width
            log.warning("odometry: the model's camera is %dx%d, the images %dx%d (another shape): starting from f = width",
                        learnt.width, learnt.height, width, height)
        prior_model = "equidistant" if self.distortion_model == "equidistant" else "plumb_bob"  # auto's prior: plumb_bob
        return prior_calibration(width, height, prior_model), "prior", 0.0

    def set_calibration(self, calibration: "CameraCalibration") -> None:
        """Restart the online camera from ``calibration`` (scaled to the frames' size); the pose is kept.

        The calibration is kept through :meth:`reset` and :meth:`reload` (it is the camera's, not the
        model's). A lens the bundle adjustment does not optimise is converted (:func:`as_vo_calibration`),
        and :meth:`camera_info` reports the conversion's residual.
        """
        converted = as_vo_calibration(calibration)
        with self._lock:
            self._given_calibration, self._given_vo_calibration = calibration, converted
            size = self.image_size
            self._close_vo()
            self._camera = None
            if size is not None:
                self._online_camera(*size)

    def camera_info(self, width: int | None = None, height: int | None = None) -> tuple["CameraCalibration", float]:
        """The current online camera and the residual of the conversion it started from (pixels).

        At ``width x height`` (default: the size of the frames seen, else the model camera's native size);
        a size of another aspect ratio than the frames seen raises :class:`FrameSizeError`.
        """
        with self._lock:
            size = self.image_size
            if size is None:
                if width and height:
                    size = (int(width), int(height))
                elif self.model.camera is not None:
                    size = (int(self.model.camera.width), int(self.model.camera.height))
                elif self._given_calibration is not None:
                    size = (self._given_calibration.width, self._given_calibration.height)
                else:
                    raise NocalError(f"model {self.model.model_id} has no learnt camera and no frame was seen yet: "
                                     "no camera to publish")
            camera = self._online_camera(*size)
            calibration, residual = camera.calibration, camera.residual_px
        if width and height and (int(width), int(height)) != (calibration.width, calibration.height):
            calibration = _resized(calibration, int(width), int(height), "the camera")
            residual *= int(width) / size[0]
        return calibration, residual

    def calibration_status(self) -> dict:
        """``{"state": "prior"|"converging"|"converged", "source", "focal_std_px", "keyframes", ...}``."""
        with self._lock:
            camera = self._camera
            if camera is None:
                given = self._given_calibration is not None
                return calibration_status("prior", "file" if given else "model",
                                          given_check="pending" if given else "")
            status = camera.status()
            status["keyframes"] = self.counters.keyframes
            return status

    def timings(self) -> dict[str, list[float]]:
        """The VO's recent costs in milliseconds (empty lists before the first frame or with ``pose_head``):
        ``tracking`` per frame (frontend, PnP, keyframe decision; inline mapping excluded), ``mapping`` per
        mapped batch of keyframes (triangulation and bundle adjustment), ``bundle_adjustment`` per
        solve (in the worker process when mapping is asynchronous, the hand-over included) and, with a
        camera height, ``ground_fit`` per live ground-plane fit (in the tracking thread, at keyframes) and
        ``ground_motion`` per frame pair's ground homography (in the tracking thread, before a window's plane)."""
        with self._lock:
            vo = self._vo
            if vo is None:
                return {"tracking": [], "mapping": [], "bundle_adjustment": [], "ground_fit": [], "ground_motion": []}
            return {"tracking": list(vo.milliseconds), "mapping": list(vo.mapping.milliseconds),
                    "bundle_adjustment": list(vo.mapping.solve_milliseconds), "ground_fit": list(self._ground_fit_ms),
                    "ground_motion": list(self._ground_motion_ms)}

    @property
    def keyframes_merged(self) -> int:
        """Keyframes whose bundle adjustment local mapping folded into a later one (it fell behind)."""
        return self.mapping_status()["keyframes_merged"]

    def mapping_status(self) -> dict[str, int]:
        """Local mapping's counts since the first frame: keyframes merged into a later solve, windows it
        could not solve (left as they were), and solver processes started again after one died."""
        vo = self._vo
        if vo is None:
            return {"keyframes_merged": 0, "failed_windows": 0, "solver_restarts": 0}
        return {"keyframes_merged": int(vo.mapping.merged), "failed_windows": int(vo.mapping.failures),
                "solver_restarts": int(vo.mapping.solver_restarts)}

    def wait_for_mapping(self, timeout: float | None = None) -> bool:
        """Block until local mapping has taken every submitted keyframe; False on timeout."""
        vo = self._vo
        return True if vo is None else vo.mapping.wait(timeout)

    def set_ground_to_camera(self, T_ground_cam: np.ndarray) -> None:
        """The camera's static pose in a frame on the ground with its z up (REP 120's ``base_footprint``, a
        robot's URDF): the camera's height above the ground is its z there, and the ground's normal is that
        frame's z, for the ground-plane scale. Replaces ``camera_height`` and the down direction it takes
        from ``T_base_cam`` or the image: a camera pitched more than the plane fit's tilt
        (:data:`~nocal_ros.odometry.scale.GROUND_MAX_TILT_DEG`) towards the floor finds no floor through
        the image's down."""
        T = np.asarray(T_ground_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"T_ground_cam must be a finite 4x4 transform, got {T.shape}")
        height = float(T[2, 3])
        if not height > 0:
            raise NocalError(f"the camera is {height:.3f} m above the ground frame's z = 0: the ground frame must "
                             "lie on the ground beneath the camera, z up (REP 120's base_footprint)")
        with self._lock:
            self.camera_height = height
            self._down_cam = T[:3, :3].T @ np.array([0.0, 0.0, -1.0])

    def add_arm_pose(self, stamp_ns: int, T_base_cam: np.ndarray) -> None:
        """The camera optical frame's pose in the arm's base frame at ``stamp_ns`` (hand-eye applied).

        The last :data:`ARM_POSE_HISTORY` are kept; :meth:`reset` forgets them. Raises ValueError for
        anything but a finite rigid transform.
        """
        T = np.asarray(T_base_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"an arm pose must be a finite 4x4 transform, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError("an arm pose must be a rigid transform (a rotation and a translation)")
        with self._lock:
            self._arm_stamps.append(int(stamp_ns))
            self._arm_poses.append(T.copy())

    @property
    def arm_poses(self) -> list[tuple[int, np.ndarray]]:
        """The arm poses kept, ``[(stamp_ns, T_base_cam)]`` oldest first."""
        with self._lock:
            return list(zip(self._arm_stamps, (T.copy() for T in self._arm_poses)))

    def _arm_position(self, stamp_ns: int) -> np.ndarray | None:
        if not self._arm_stamps:
            return None
        stamps = np.fromiter(self._arm_stamps, dtype=np.int64)
        nearest = int(np.argmin(np.abs(stamps - stamp_ns)))
        if abs(int(stamps[nearest]) - stamp_ns) > ARM_TOLERANCE_NS:
            return None
        return self._arm_poses[nearest][:3, 3]

    # -- the per-frame path ------------------------------------------------------------------------

    def process(self, stamp_ns: int, image: np.ndarray, encoding: str | None = None) -> OdometryResult | None:
        """Take one frame (``(H, W, 3)`` uint8 RGB, or ``(H, W)`` mono) and return the estimate at it.

        Returns None when the frame is skipped (a repeated stamp, or a non-finite network output).
        Raises :class:`FrameSizeError` when the size differs from the frames before it.
        """
        image = _as_rgb(image)
        stamp_ns = int(stamp_ns)
        with self._lock:
            self.counters.frames += 1
            shape = image.shape[:2]
            if self._image_shape is not None and shape != self._image_shape:
                self.counters.size_rejected += 1
                raise FrameSizeError(
                    f"image size changed from {self._image_shape[1]}x{self._image_shape[0]} to "
                    f"{shape[1]}x{shape[0]} at stamp {stamp_ns}; the calibration and pose chain no longer "
                    "apply (reset the estimator to accept the new size)"
                )
            self._image_shape = shape

            status = "ok"
            if self._previous_stamp is not None and stamp_ns < self._previous_stamp:
                log.warning("odometry: time went backwards (%d -> %d ns): resetting", self._previous_stamp, stamp_ns)
                self.counters.time_resets += 1
                self.reset()
                self._image_shape = shape
                status = "time_reset"
            if encoding is not None and self._encoding is not None and encoding != self._encoding:
                log.warning("odometry: image encoding changed %s -> %s: new pair chain", self._encoding, encoding)
                self.counters.encoding_resets += 1
                self._previous_key = None
                if self.method == "pose_head":
                    self._has_previous = False
                    status = "encoding_reset"
            if encoding is not None:
                self._encoding = encoding

            if self._has_previous and stamp_ns == self._previous_stamp:
                self.counters.duplicate_stamps += 1
                return None

            gap = 0
            if self._has_previous:
                step = stamp_ns - self._previous_stamp
                self._steps.append(step)
                period = self.frame_period_ns() or step
                gap = max(1, int(round(step / period)))
                if gap > self.model.max_gap:
                    self._previous_key = None  # the pose head cannot pair across it
                    if self.method == "pose_head":
                        log.warning("odometry: %.3f s without frames (%d frames > trained gap %d): new pair chain",
                                    step * 1e-9, gap, self.model.max_gap)
                        self.counters.gap_resets += 1
                        self._has_previous = False
                        status = "gap_reset"
                        gap = 0

            key = self._runner.load_frame(image)
            if self.method == "pose_head":
                return self._process_pose_head(stamp_ns, key, gap, status)
            return self._process_vo(stamp_ns, image, key, gap, status)

    # -- pose head alone ---------------------------------------------------------------------------

    def _process_pose_head(self, stamp_ns: int, key: int, gap: int, status: str) -> OdometryResult | None:
        if not self._has_previous or self._previous_key is None:
            self._previous_key = key
            return self._start_chain(stamp_ns, "start" if status == "ok" else status)
        start = time.perf_counter()
        T_ci_cj = self._runner.run(self._previous_key, key)
        inference_ms = (time.perf_counter() - start) * 1e3
        if not np.isfinite(T_ci_cj).all():
            self.counters.nonfinite_skipped += 1
            log.warning("odometry: non-finite pose head output at stamp %d: frame skipped", stamp_ns)
            return None  # the previous key stays: the next frame pairs with the last good one
        self._previous_key = key
        sigma = self._pose_head_sigma(gap)
        return self._integrate(stamp_ns, T_ci_cj, gap, inference_ms, status, "pose_head", sigma)

    def _pose_head_sigma(self, gap: int, std: dict | None = None) -> np.ndarray:
        """Camera-frame ``(6, 6)`` pair covariance from per-frame standard deviations, times the gap."""
        std = std or self.model.pose_error_std
        g = max(int(gap), 1)
        return np.diag([std["translation_m"] ** 2 * g] * 3 + [std["rotation_rad"] ** 2 * g] * 3)

    # -- visual odometry ---------------------------------------------------------------------------

    def _process_vo(self, stamp_ns: int, image: np.ndarray, key: int, gap: int, status: str) -> OdometryResult:
        height, width = image.shape[:2]
        camera = self._online_camera(width, height)
        if self._vo is None:
            self._vo = VisualOdometry(camera, self.settings, self.synchronous_mapping, record=self.record_trajectory)
        frame = self._frame
        self._frame += 1
        self._frame_stamps[frame] = stamp_ns
        _trim(self._frame_stamps)
        vo_frame = self._vo.process(frame, stamp_ns, image)
        previous_key, self._previous_key = self._previous_key, key
        if vo_frame.keyframe:
            self.counters.keyframes += 1
        if vo_frame.new_map:
            self.counters.maps += 1
        if vo_frame.guess_rescued:
            self.counters.guess_rescues += 1

        if not self._has_previous:
            self._has_previous = True
            self._previous_stamp = stamp_ns
            T = self._T_odom_base @ self._T_base_cam
            self._remember(frame, T)
            self._log_frame(frame, stamp_ns, T, None)
            unknown = np.eye(6) * UNKNOWN_VARIANCE
            return self._result(stamp_ns, np.eye(4), np.zeros(6), unknown, "start" if status == "ok" else status, 0,
                                0.0, "none", vo_frame.state, keyframe=vo_frame.keyframe)

        T_prev = self._T_odom_base @ self._T_base_cam
        inference_ms = 0.0
        if vo_frame.state == "ok":
            if vo_frame.new_map or self._anchor_map_id != vo_frame.map_id:
                self._start_map(vo_frame, frame, key)
            self._update_scale(vo_frame)
            self._update_ground_motion(vo_frame, frame)
            if vo_frame.T_prev_cur is None:
                T_new = self._anchor @ self._metric_pose(vo_frame.T_map_cam)
            else:
                T_new = T_prev @ self._metric_pose(vo_frame.T_prev_cur)
            if vo_frame.covariance is not None:
                s = self._scale.scale
                J = np.diag([s, s, s, 1.0, 1.0, 1.0])
                sigma = J @ vo_frame.covariance @ J.T
            else:
                sigma = self._pose_head_sigma(gap)
            source = "vo"
        else:
            if vo_frame.state == "initialising":
                self.counters.initialising_frames += 1
                sigma = self._pose_head_sigma(gap)
            else:
                self.counters.lost_frames += 1
                sigma = self._pose_head_sigma(gap, LOST_STD)
            if vo_frame.rotation_from_reference is not None:
                T_new, source, ms = self._two_view_pose(vo_frame, frame, key, T_prev)
                inference_ms += ms
            else:
                T_new, source = T_prev, "none"
                # The pose head bridges a frame that shows the previous frame's scene (some tracks
                # survived into it) but not one after a cut or of noise: 40 frames of noise moved the
                # camera 0.15 m on the pose head's guesses (measured), and nothing is there to measure.
                continuous = vo_frame.tracks >= self.settings.min_tracks
                if vo_frame.textured and continuous and previous_key is not None and self._runner.holds(previous_key):
                    start = time.perf_counter()
                    T_ci_cj = self._runner.run(previous_key, key)
                    inference_ms += (time.perf_counter() - start) * 1e3
                    if np.isfinite(T_ci_cj).all():
                        if vo_frame.rotation_from_previous is not None:  # the tracks' turn, the pose head's length
                            T_ci_cj = T_ci_cj.copy()
                            T_ci_cj[:3, :3] = vo_frame.rotation_from_previous
                        T_new, source = T_prev @ T_ci_cj, "pose_head"
                        self.counters.pose_head_fallbacks += 1
        self._remember(frame, T_new)
        if vo_frame.state == "ok":
            self._T_map_odom, self._map_origin = self._map_correction()
            self._map_scales[vo_frame.map_id] = self._scale.scale
            self._map_scale_sources[vo_frame.map_id] = self._scale.source
        self._log_frame(frame, stamp_ns, T_new, vo_frame.map_id if vo_frame.state == "ok" else None)
        T_ci_cj = invert_transform(T_prev) @ T_new
        focal_std = self._vo.camera.relative_focal_std()
        if source in ("vo", "two_view", "rotation"):
            # Geometry through the online camera is only as good as its focal length (see the module notes).
            # A step's earlier pose was measured through the camera as it was then: where a window has just
            # replaced the guess, the step still carries the guess's error (heldout_640's first step through
            # its first window: 0.95 deg off, published at 0.16 deg through the new camera's 3 %).
            sigma = sigma + focal_step_covariance(T_ci_cj, max(focal_std, self._previous_focal_std))
        # A step is as long as its scale says: the map's (arm, ground, or the pose head's first guess), or
        # the pose head's own length before a map or where it bridges one.
        scale_std = self._scale.relative_std if source == "vo" else (
            POSE_HEAD_SCALE_STD if source in ("two_view", "pose_head") else 0.0)
        if scale_std > 0:
            sigma = sigma + scale_step_covariance(T_ci_cj, scale_std)
        if self._direction_unknown(vo_frame, source):
            # A two-view step's length is the pose head's already; a map's step, also the pose head's at its start.
            head_length = None
            if source == "vo" and self._head_step_length is not None:
                head_length = self._head_step_length * max(gap, 1)
            sigma = sigma + direction_free_step_covariance(T_ci_cj, POSE_HEAD_SCALE_STD, head_length)
        self._previous_focal_std = focal_std
        return self._integrate(stamp_ns, T_ci_cj, max(gap, 1), inference_ms, status, source, sigma,
                               tracking=vo_frame.state, keyframe=vo_frame.keyframe)

    def _direction_unknown(self, vo_frame: VOFrame, source: str) -> bool:
        """Whether a step knows neither its direction nor its length: measured through the guessed camera
        (before its first initialisation; PnP against a map made through it, or two-view geometry) and
        as long as the pose head says (the map on the pose head's scale, or two-view geometry's length).
        Over the first 40 frames of 21 dev replays the 206 such steps were 51 deg off in direction at the
        median (more than 90 deg on 22 %) and 1.56 steps off RMS; through the guess on a ground plane's
        scale, 0.52 steps (36 steps, 14 deg at the median; docs/RESULTS.md)."""
        if not vo_frame.through_guess:
            return False
        return source == "two_view" or (source == "vo" and self._scale.source in ("pose_head", "none"))

    def _two_view_pose(self, vo_frame: VOFrame, frame: int, key: int, T_prev: np.ndarray) -> tuple[np.ndarray, str, float]:
        """The pose from the motion since the reference frame while there is no map: the rotation, and
        the direction of travel scaled by the pose head's length for the same pair when the parallax
        shows one (a rotation alone explains the tracks: no translation)."""
        reference = self._published.get(vo_frame.reference_frame, T_prev)
        T_new = reference.copy()
        T_new[:3, :3] = reference[:3, :3] @ vo_frame.rotation_from_reference
        if vo_frame.direction_from_reference is None:
            return T_new, "rotation", 0.0
        length, ms = self._pose_head_length(vo_frame.reference_frame, frame, key)
        if length is None:
            return T_new, "rotation", ms
        T_new[:3, 3] = reference[:3, 3] + reference[:3, :3] @ (length * vo_frame.direction_from_reference)
        return T_new, "two_view", ms

    def _pose_head_length(self, older: int, frame: int, key: int) -> tuple[float | None, float]:
        """The pose head's translation length (m) between two frames, when both are in its ring, and its ms."""
        older_key = key - (frame - older)
        if older >= frame or not self._runner.holds(older_key):
            return None, 0.0
        start = time.perf_counter()
        T = self._runner.run(older_key, key)
        ms = (time.perf_counter() - start) * 1e3
        length = float(np.linalg.norm(T[:3, 3]))
        return (length if np.isfinite(length) else None), ms

    def _log_frame(self, frame: int, stamp_ns: int, T_odom_cam: np.ndarray, map_id: int | None) -> None:
        if self.record_trajectory:
            self._trajectory_log.append((frame, stamp_ns, T_odom_cam.copy(), map_id))

    def final_trajectory(self) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """The frames since the last reset posed through the final map and camera (replays; see
        :mod:`nocal_ros.odometry.trajectory`): ``(stamps (N,), T_odom_cam (N, 4, 4), how (N,))``.

        Call it at the end of a stream: it first fuses each map's duplicate landmarks
        (:func:`~nocal_ros.odometry.local_mapping.fuse_landmarks`), solves it whole, searches every
        keyframe for the landmarks it never tracked
        (:func:`~nocal_ros.odometry.local_mapping.search_by_projection`, counted in
        :attr:`final_observations_found`) and solves it whole again, with the camera (which
        :meth:`camera_info` then reports).

        Needs ``record_trajectory=True``. A frame tracked in a map, or whose tracks made it, is posed in
        it again and placed in ``odom`` by that map's origin and scale (where three or more of its
        keyframes have arm poses, the map is solved with them and is metric; else the last scale
        published; the map's first frame goes where the frames before it lead, unless the map shares
        landmarks with the map before it: then it is placed in that map,
        :func:`~nocal_ros.odometry.trajectory.link_maps`). A frame of an initialisation reference given up
        before a map was made is posed in that map by PnP where its tracks' landmarks allow. Any other
        frame (lost, or initialising a map never made) keeps its published motion from the frame before it.
        ``how`` says which: ``"keyframe"``, ``"pnp"``, ``"keyframe_relative"`` or ``"published"``.
        """
        from nocal_ros.odometry.local_mapping import fuse_landmarks, search_by_projection
        from nocal_ros.odometry.trajectory import final_map_poses, link_maps

        with self._lock:
            if not self.record_trajectory:
                raise NocalError("final_trajectory needs an estimator made with record_trajectory=True")
            log_ = list(self._trajectory_log)
            scales = dict(self._map_scales)
            self.final_scale_sources = {}
            metric: set[int] = set()
            map_poses = {}
            if self._vo is not None:
                self._vo.mapping.wait()
                # Keyframes outside the last windows were solved through an older camera, and their
                # landmarks moved since (measured on heldout_160: the old keyframes' own observations
                # posed them 1.4 deg from where they stood): first a camera initialisation's solve over
                # each whole map (every keyframe, the camera and lens free from the guess's prior).
                maps = {r.map_id: r.local_map for r in self._vo.records}
                if self.settings.mapping.search_landmarks and self._vo.keyframe_images_dropped:
                    log.warning("the end-of-replay search covers the newest %d keyframes only: %d keyframe "
                                "images were let go (tracking.KEYFRAME_IMAGE_BUDGET_BYTES)",
                                len(self._vo.keyframe_images), self._vo.keyframe_images_dropped)
                # One camera for every map: the map with the most keyframes solves it, and the others are
                # solved through it, held (each solved with the camera free, the last one solved set the
                # camera that posed every map's frames, whose landmarks another camera had placed:
                # measured on r640_304, a 5-keyframe first map took the camera 4.8 % off before the
                # 33-keyframe map took it back, and its frames were posed 1.6-2.6 deg off per pair).
                # After a camera swapped at a cut (the last map rejected the camera carried into it),
                # the last map's is the camera now.
                owner = max(maps, key=lambda map_id: (len(maps[map_id].keyframes), map_id), default=None)
                if maps and self._vo.camera.carried_check == "rejected":
                    owner = max(maps)
                for map_id in sorted(maps, key=lambda map_id: map_id != owner):
                    local_map, hold = maps[map_id], map_id != owner
                    # Landmarks that are one scene point seen again tie the map's stretches together.
                    merged = fuse_landmarks(local_map, self._vo.camera.calibration, self.settings.pixel_threshold)
                    for record in self._vo.records:
                        if merged and record.map_id == map_id:
                            record.ids = np.array([merged.get(i, i) for i in record.ids.tolist()], dtype=np.int64)
                    if self.settings.mapping.search_landmarks and len(local_map.keyframes) >= 3:
                        # Solved whole first: the landmarks are searched for where that map projects them.
                        self._vo.mapping.bundle_adjust(local_map, initialise=True, whole_map=True, hold_camera=hold)
                        self.final_observations_found += search_by_projection(
                            local_map, self._vo.camera.calibration, self._vo.keyframe_images,
                            self.settings.pixel_threshold, self._vo.tracker.work_scale)
                    arm_scale = self._solve_whole_map(local_map, hold)
                    if arm_scale is not None:
                        scales[map_id] = arm_scale
                        metric.add(map_id)
                        self.final_scale_sources[map_id] = "arm"
                        continue
                    ground = self._ground_scale(local_map) if self.camera_height is not None else None
                    if ground is not None:
                        scales[map_id] = ground.scale
                        self.final_scale_sources[map_id] = "ground"
                    else:
                        self.final_scale_sources[map_id] = self._map_scale_sources.get(map_id, "none")
                map_poses = final_map_poses(self._vo.records, self._vo.camera.calibration,
                                            self.settings.pixel_threshold, self.settings.min_pnp_inliers)
                # A map made after a loss and sharing landmarks with the one before goes into its frame.
                map_poses = link_maps(map_poses, exclude=metric)
        stamps, poses, how = [], [], []
        origins: dict[int, np.ndarray] = {}  # map id -> T_odom_map
        previous: tuple[np.ndarray, np.ndarray] | None = None  # (published, final) of the frame before
        for frame, stamp_ns, T_published, _ in log_:
            chained = T_published if previous is None else previous[1] @ invert_transform(previous[0]) @ T_published
            T, source = chained, "published"
            pose = map_poses.get(frame)
            if pose is not None:
                T_metric = _scaled(pose.T_map_cam, scales.get(pose.map_id, 1.0))
                # A map is placed in odom where the frames before its first one lead (as published).
                origin = origins.setdefault(pose.map_id, chained @ invert_transform(T_metric))
                T, source = origin @ T_metric, pose.how
            T = T.copy()
            T[:3, :3] = nearest_rotation(T[:3, :3])
            previous = (T_published, T)
            stamps.append(stamp_ns)
            poses.append(T)
            how.append(source)
        return np.asarray(stamps, dtype=np.int64), np.asarray(poses).reshape(-1, 4, 4), how

    def map_snapshot(self) -> MapSnapshot:
        """The keyframes and landmarks as they stand, in ``odom`` and metres (see :class:`MapSnapshot`;
        empty before the first map and for ``method="pose_head"``). Live, between frames: after
        :meth:`final_trajectory` a map may stand in the arm's frame and units instead of the live scale's."""
        with self._lock:
            rows = list(self._earlier_path)
            points, point_ids = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
            T_map_odom = self._T_map_odom
            if self._path_map is not None:
                with self._path_map.lock:  # the correction through the same placement as the keyframes
                    current, points, point_ids = self._placed_map(self._anchor_map_id, self._path_map)
                    T_map_odom = self._map_correction()[0]
                rows += current
            poses = np.array([T @ self._T_cam_base for _, _, T in rows]).reshape(-1, 4, 4)
            return MapSnapshot(np.array([stamp for stamp, _, _ in rows], dtype=np.int64), poses,
                               np.array([map_id for _, map_id, _ in rows], dtype=np.int64), points, point_ids,
                               self._anchor_map_id if self._path_map is not None else 0, self._scale.source,
                               T_map_odom.copy())

    def _placed_map(self, map_id: int, local_map: "LocalMap") -> tuple[list[tuple[int, int, np.ndarray]], np.ndarray, np.ndarray]:
        """One map's keyframes ``[(stamp, map id, T_odom_cam)]``, landmarks ``(M, 3)`` and their ids, in odom at
        the current scale, placed by :meth:`_placement`."""
        scale = self._scale.scale
        with local_map.lock:
            T_odom_map, _, _ = self._placement(local_map)
            keyframes = [(keyframe.stamp_ns, _scaled(keyframe.T_w_c, scale)) for keyframe in local_map.keyframes]
            point_ids = np.fromiter(local_map.landmarks, dtype=np.int64, count=len(local_map.landmarks))
            points = np.array(list(local_map.landmarks.values()), dtype=np.float64).reshape(-1, 3) * scale
        if T_odom_map is None:
            return [], np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        return ([(stamp, map_id, T_odom_map @ T_map_cam) for stamp, T_map_cam in keyframes],
                points @ T_odom_map[:3, :3].T + T_odom_map[:3, 3], point_ids)

    def _placement(self, local_map: "LocalMap") -> tuple[np.ndarray | None, int | None, np.ndarray | None]:
        """``(T_odom_map, the first keyframe's frame, its T_map_cam)`` in metres at the current scale: the map
        placed in odom by its newest keyframe whose published pose is kept (else as last placed; None before that)."""
        scale = self._scale.scale
        oldest_kept = next(iter(self._published), None)
        with local_map.lock:
            keyframes = local_map.keyframes
            if not keyframes:
                return self._path_placement, None, None
            for keyframe in reversed(keyframes):
                if oldest_kept is None or keyframe.frame < oldest_kept:
                    break  # published poses are kept for the newest frames only
                published = self._published.get(keyframe.frame)
                if published is not None:
                    self._path_placement = published @ invert_transform(_scaled(keyframe.T_w_c, scale))
                    break
            return self._path_placement, keyframes[0].frame, _scaled(keyframes[0].T_w_c, scale)

    def _map_correction(self) -> tuple[np.ndarray, np.ndarray | None]:
        """``(T_map_odom, the map's origin)`` for the current map as it stands: the map frame holds the map's
        first keyframe at its origin, where odometry published that frame, through the correction before the
        map (set where the map is first placed)."""
        if self._path_map is None:
            return self._T_map_odom, self._map_origin
        T_odom_map, first_frame, T_map_first = self._placement(self._path_map)
        if T_odom_map is None or T_map_first is None:
            return self._T_map_odom, self._map_origin
        T_odom_first = T_odom_map @ T_map_first
        origin = self._map_origin
        if origin is None:
            # The first keyframe as published, not as placed through the newest: it was published before the
            # map's first steps through the guessed camera (r160_205's map agreed with the truth to 1 deg
            # from its first keyframe to its newest, where odom's chain was 7 deg off; measured).
            published = self._published.get(first_frame)
            origin = self._T_map_odom @ (T_odom_first if published is None else published)
        correction = origin @ invert_transform(T_odom_first)
        if not np.isfinite(correction).all():  # a keyframe a failed solve left non-finite: keep the last one
            return self._T_map_odom, self._map_origin
        return correction, origin

    def _remember(self, frame: int, T_odom_cam: np.ndarray) -> None:
        self._published[frame] = T_odom_cam
        _trim(self._published)

    def _metric_pose(self, T_map_cam: np.ndarray) -> np.ndarray:
        return _scaled(T_map_cam, self._scale.scale)

    def _start_map(self, vo_frame: VOFrame, frame: int, key: int) -> None:
        """Anchor a new map in odom at the pose published for its first keyframe, turned about the frame it
        starts at to that frame's chained rotation; its first scale guess."""
        if self._path_map is not None and self._path_map is not self._vo.map:  # at the old map's id and last scale
            self._earlier_path.extend(self._placed_map(self._anchor_map_id, self._path_map)[0])
        self._path_map, self._path_placement = self._vo.map, None
        self._map_origin = None  # placed through the correction the last map left (self._T_map_odom)
        reference = vo_frame.reference_frame
        self._anchor = self._published.get(reference, self._T_odom_base @ self._T_base_cam).copy()
        self._anchor_map_id = vo_frame.map_id
        self._ground_fits.clear()
        self._ground_motions.clear()
        # One step's length as the pose head reads it, for the steps the map measures through the guess
        # (_direction_unknown): once per map, not per step (the pose head per step cost 3 ms a frame over a
        # 30 Hz replay's first 73 frames, measured), and only for a map started through the guess.
        self._head_step_length = self._pose_head_length(frame - 1, frame, key)[0] if vo_frame.through_guess else None
        # The map's unit is the baseline between its first two keyframes; measure it in metres.
        baseline = np.linalg.norm(vo_frame.T_map_cam[:3, 3])
        first_guess = None
        arm_ref = self._arm_position(self._frame_stamps.get(reference, -1)) if reference is not None else None
        arm_cur = self._arm_position(self._frame_stamps[frame])
        if arm_ref is not None and arm_cur is not None and baseline > 0:
            first_guess = float(np.linalg.norm(arm_cur - arm_ref)) / baseline
        elif reference is not None and baseline > 0:
            older = max(reference, frame - self.model.max_gap)
            length, _ = self._pose_head_length(older, frame, key)
            if length:
                # Frames between the reference and the pair's first one: assume a steady speed.
                first_guess = length * (frame - reference) / (frame - older) / baseline
        usable = bool(first_guess and np.isfinite(first_guess) and first_guess > 0)
        if not usable:
            self._scale = ScaleEstimate(1.0, "none", 0, UNKNOWN_SCALE_STD)
        elif arm_ref is not None and arm_cur is not None:
            self._scale = ScaleEstimate(first_guess, "arm", 0, ARM_PAIR_SCALE_STD)
        else:
            self._scale = ScaleEstimate(first_guess, "pose_head", 0, POSE_HEAD_SCALE_STD)
        if vo_frame.rotation_from_reference is not None:
            # The frame the map starts at keeps the rotation chained frame to frame since the reference,
            # as the frames published before it had, and the map turns about it to match: odometry must
            # not jump. Its two-view rotation from the reference, through a guessed camera, differed from
            # the chained one by 1.1-23 deg (25 dev bags; a 21 deg step in one frame pair, measured).
            T_map = self._metric_pose(vo_frame.T_map_cam)
            T_continued = T_map.copy()
            T_continued[:3, :3] = vo_frame.rotation_from_reference
            self._anchor = self._anchor @ T_continued @ invert_transform(T_map)

    def _update_scale(self, vo_frame: VOFrame) -> None:
        """At keyframes, refit the scale to the arm poses of the map's keyframes, else (with a camera height,
        and no arm fit in this map yet) to its ground plane: the median of the map's newest
        :data:`GROUND_FIT_HISTORY` fits (see :mod:`~nocal_ros.odometry.scale`)."""
        if not (vo_frame.keyframe and self._vo is not None and self._vo.map is not None):
            return
        estimate = None
        if self._arm_stamps:
            pairs = self._arm_keyframes(self._vo.map)[-ARM_FIT_KEYFRAMES:]
            estimate = fit_arm_scale(np.array([p for _, p, _ in pairs]), np.array([a for _, _, a in pairs])) if pairs else None
        if estimate is None and self.camera_height is not None and self._scale.source != "arm":
            start = time.perf_counter()
            through_guess = self._vo.camera.is_guess
            fit = self._ground_scale(self._vo.map, GROUND_FIT_KEYFRAMES,
                                     MIN_GROUND_POINTS if through_guess else LIVE_MIN_GROUND_POINTS)
            self._ground_fit_ms.append((time.perf_counter() - start) * 1e3)
            if fit is not None:
                unit = self._vo.map.unit_scale  # fits made before a move of the map are in its earlier unit
                if not through_guess:
                    # A fit through a solved camera replaces those through the guess: the median of the two
                    # kinds put heldout_640's first solved fit (x0.99 of the truth) beside one of x1.58.
                    kept = [(value, guess) for value, guess in self._ground_fits if not guess]
                    self._ground_fits.clear()
                    self._ground_fits.extend(kept)
                self._ground_fits.append((fit.scale * unit, through_guess))
                values = [value for value, _ in self._ground_fits]
                logs = np.log(values)  # the fits' spread: their MAD as a normal's standard deviation
                measured = len(logs) >= MIN_GROUND_FITS_SPREAD
                spread = 1.4826 * float(np.median(np.abs(logs - np.median(logs)))) if measured else 0.0
                if through_guess:
                    floor = GUESS_GROUND_SCALE_STD
                else:
                    floor = GROUND_SCALE_STD if measured else FEW_GROUND_FITS_SCALE_STD
                voters = values
                if not measured:
                    # Until three fits can outvote a plane that is not the ground, the map's homography samples
                    # vote with them: KITTI's first window plane was x3.9 of the truth on one machine, and alone
                    # it made the steps 4x too long where nine samples had held them at x0.86-0.96 (measured).
                    voters = values + [value for value, _ in self._ground_motions]
                estimate = ScaleEstimate(float(np.median(voters)) / unit, "ground", fit.samples, max(floor, spread))
        if estimate is not None:
            self._scale = estimate

    def _ground_scale(self, local_map: "LocalMap", newest: int | None = None,
                      min_points: int = MIN_GROUND_POINTS) -> ScaleEstimate | None:
        """The scale from ``local_map``'s ground plane and :attr:`camera_height`, fitted to the landmarks its
        ``newest`` keyframes (all: None) observe; None where the map shows no ground plane.

        The end of a replay fits the whole map: over the rendered rooms, windows of
        :data:`GROUND_FIT_KEYFRAMES` keyframes found a plane that was not the floor in 3 of 20 maps (scale
        x1.2-2.4), the whole map in none of them (measured; a long drive over hills would need windows).
        """
        with local_map.lock:
            keyframes = local_map.keyframes[-newest:] if newest else list(local_map.keyframes)
            if len(keyframes) < MIN_GROUND_KEYFRAMES:
                return None
            ids = np.unique(np.concatenate([kf.ids for kf in keyframes])).tolist()
            points = np.array([local_map.landmarks[i] for i in ids if i in local_map.landmarks]).reshape(-1, 3)
            poses = np.array([kf.T_w_c for kf in keyframes])
        return fit_ground_scale(points, poses[:, :3, 3], (poses[:, :3, :3] @ self._down_in_camera()).mean(0),
                                self.camera_height, min_points=min_points)

    def _down_in_camera(self) -> np.ndarray:
        """The ground's expected down direction in the camera frame: a ground frame's, else the base's -z, or the
        image's down where the camera is its own base."""
        if self._down_cam is not None:
            return self._down_cam
        if np.allclose(self._T_base_cam, np.eye(4)):
            return np.array([0.0, 1.0, 0.0])
        return self._T_base_cam[:3, :3].T @ np.array([0.0, 0.0, -1.0])

    def _update_ground_motion(self, vo_frame: VOFrame, frame: int) -> None:
        """With a camera height, no plane fitted in this map's windows yet and no arm poses, the scale from
        the ground's homography between this frame and the previous one (:func:`~nocal_ros.odometry.scale.ground_motion_ratio`:
        the tracks below the horizon, given the map's rotation and direction for the pair): the median of the
        map's newest :data:`GROUND_MOTION_HISTORY` samples, once :data:`MIN_GROUND_MOTION_SAMPLES` are in.

        It needs no landmark on the ground, only tracks that last a frame: KITTI's road is tracked for about
        one frame (its corners stretch as they near), so the clip's first window plane came at frame 22 while
        the pose head's scale was x0.06-0.09 (docs/RESULTS.md). Through a solved camera only: through the
        guess the samples were off by log RMS 0.42 against 0.29 (measured).
        """
        previous, self._previous_tracks = self._previous_tracks, None
        if (self.camera_height is None or self._ground_fits or self._arm_stamps or self._vo is None
                or self._vo.camera.is_guess):
            return
        tracks = self._vo.tracker.current()
        self._previous_tracks = (frame, vo_frame.map_id, tracks)
        if (previous is None or previous[0] != frame - 1 or previous[1] != vo_frame.map_id or vo_frame.new_map
                or vo_frame.T_prev_cur is None or self._vo.map is None):
            return
        T = vo_frame.T_prev_cur  # the current camera in the previous one's frame, in map units
        length = float(np.linalg.norm(T[:3, 3]))
        if not (np.isfinite(length) and length > 0):
            return
        start = time.perf_counter()
        _, before, after = np.intersect1d(previous[2].ids, tracks.ids, return_indices=True)
        if len(before) < MIN_HOMOGRAPHY_INLIERS:
            return
        calibration = self._vo.camera.calibration
        rotation = T[:3, :3].T
        motion = ground_motion_ratio(calibration.undistorted_normalised(previous[2].pixels[before]),
                                     calibration.undistorted_normalised(tracks.pixels[after]), rotation,
                                     -rotation @ T[:3, 3], self._down_in_camera())
        self._ground_motion_ms.append((time.perf_counter() - start) * 1e3)
        if motion is None:
            return
        unit = self._vo.map.unit_scale
        keyframes = self.counters.keyframes
        self._ground_motions.append((motion.ratio * self.camera_height / length * unit, keyframes))
        while self._ground_motions[0][1] < keyframes - GROUND_FIT_KEYFRAMES:
            self._ground_motions.popleft()
        if len(self._ground_motions) >= MIN_GROUND_MOTION_SAMPLES:
            values = [value for value, _ in self._ground_motions]
            self._scale = ScaleEstimate(float(np.median(values)) / unit, "ground", len(values), GROUND_MOTION_SCALE_STD)

    def _arm_keyframes(self, local_map: "LocalMap") -> list[tuple[int, np.ndarray, np.ndarray]]:
        """``(keyframe index, map position, arm position)`` of the map's keyframes with an arm pose, oldest first."""
        with local_map.lock:
            keyframes = [(kf.index, kf.stamp_ns, kf.T_w_c[:3, 3].copy()) for kf in local_map.keyframes]
        pairs = [(index, position, self._arm_position(stamp)) for index, stamp, position in keyframes]
        return [(index, position, arm) for index, position, arm in pairs if arm is not None]

    def _keyframes_at_arm_poses(self, local_map: "LocalMap") -> int:
        """Make this map's recorded frames with an arm pose keyframes, posed by PnP on their tracks'
        landmarks through the map as it stands; returns how many.

        Arm poses seldom fall on keyframes (heldout bags: 7 of 20 on the fisheye one), and the solve that
        follows holds the arm only at keyframes: where none had one, the map's drift stayed (the fisheye
        bag's final Sim(3) scale 0.86 with 7 arm keyframes, all in two stretches, measured).
        """
        from nocal_ros.odometry.trajectory import final_map_poses

        if not self._arm_stamps:
            return 0
        stamps = {frame: stamp_ns for frame, stamp_ns, _, _ in self._trajectory_log}
        with local_map.lock:
            keyframes = {keyframe.frame for keyframe in local_map.keyframes}
        records = [record for record in self._vo.records
                   if record.local_map is local_map and record.frame not in keyframes and record.frame in stamps
                   and self._arm_position(stamps[record.frame]) is not None]
        poses = final_map_poses(records, self._vo.camera.calibration, self.settings.pixel_threshold,
                                self.settings.min_pnp_inliers)
        added = 0
        for record in records:
            pose = poses.get(record.frame)
            if pose is not None and pose.how == "pnp":  # a frame the map cannot pose would only hold it wrong
                local_map.add_keyframe(record.frame, stamps[record.frame], pose.T_map_cam,
                                       record.ids, record.pixels)
                added += 1
        return added

    def _solve_whole_map(self, local_map: "LocalMap", hold_camera: bool = False) -> float | None:
        """The end of a replay's solve of one map (see :meth:`final_trajectory`; ``hold_camera``: through
        the camera as it stands); with arm poses at three or more of its keyframes, the map is moved into
        the arm's frame and metres and solved again with them as factors, and 1.0 (its scale now) is
        returned, else None."""
        mapping = self._vo.mapping
        if len(local_map.keyframes) < 3:
            return None
        mapping.bundle_adjust(local_map, initialise=True, whole_map=True, hold_camera=hold_camera)
        self._keyframes_at_arm_poses(local_map)
        arm = self._arm_keyframes(local_map)
        similarity = fit_arm_similarity(np.array([p for _, p, _ in arm]), np.array([a for _, _, a in arm])) if arm else None
        if similarity is None:
            return None
        # A scale fitted to the arm at a few keyframes leaves the map's own drift between them (measured
        # on heldout_160, arm poses on 10 % of frames: path length 0.85-1.16 of the truth per stretch):
        # as factors of the whole map's solve, the arm's positions take the drift out.
        local_map.transform(*similarity)
        mapping.bundle_adjust(local_map, initialise=True, whole_map=True, hold_camera=hold_camera,
                              positions={index: a for index, _, a in arm})
        return 1.0

    def _start_chain(self, stamp_ns: int, status: str) -> OdometryResult:
        self._has_previous = True
        self._previous_stamp = stamp_ns
        unknown = np.eye(6) * UNKNOWN_VARIANCE
        return self._result(stamp_ns, np.eye(4), np.zeros(6), unknown, status, 0, 0.0, tracking="initialising")

    def _integrate(self, stamp_ns: int, T_ci_cj: np.ndarray, gap: int, inference_ms: float, status: str,
                   source: str, sigma_cam: np.ndarray, tracking: str = "ok", keyframe: bool = False) -> OdometryResult:
        dt = (stamp_ns - self._previous_stamp) * 1e-9
        T_ci_cj = T_ci_cj.copy()
        T_ci_cj[:3, :3] = nearest_rotation(T_ci_cj[:3, :3])  # float32 rotations would drift off SO(3) when chained
        T_bi_bj = self._T_base_cam @ T_ci_cj @ self._T_cam_base
        ad = adjoint(self._T_base_cam)
        sigma_pair = ad @ sigma_cam @ ad.T
        self._pose_cov = propagate_covariance(self._pose_cov, self._T_odom_base, T_bi_bj, sigma_pair)
        self._T_odom_base = self._T_odom_base @ T_bi_bj
        twist = np.concatenate((T_bi_bj[:3, :3].T @ T_bi_bj[:3, 3], so3_log(T_bi_bj[:3, :3]))) / dt
        self._previous_stamp = stamp_ns
        self.counters.pairs += 1
        if gap > 1:
            self.counters.bridged_gaps += 1
        return self._result(stamp_ns, T_bi_bj, twist, sigma_pair / dt**2, status, gap, inference_ms, source,
                            tracking, keyframe)

    def _result(self, stamp_ns, T_prev_curr, twist, twist_cov, status, gap, inference_ms,
                source: str = "pose_head", tracking: str = "ok", keyframe: bool = False) -> OdometryResult:
        scale_source = "pose_head" if self.method == "pose_head" else self._scale.source
        return OdometryResult(
            stamp_ns=stamp_ns,
            T_odom_base=self._T_odom_base.copy(),
            T_odom_cam=self._T_odom_base @ self._T_base_cam,
            T_prev_curr=T_prev_curr,
            twist=twist,
            pose_covariance=self._pose_cov.copy(),
            twist_covariance=twist_cov,
            status=status,
            gap=gap,
            inference_ms=inference_ms,
            motion_source=source,
            tracking=tracking,
            scale_source=scale_source,
            keyframe=keyframe,
            T_map_odom=self._T_map_odom.copy(),
        )


def _scaled(T: np.ndarray, scale: float) -> np.ndarray:
    """A map pose with its translation in metres."""
    T = np.array(T, dtype=np.float64)
    T[:3, 3] *= scale
    return T


def _trim(history: OrderedDict) -> None:
    while len(history) > POSE_HISTORY:
        history.popitem(last=False)


def _resized(calibration: "CameraCalibration", width: int, height: int, what: str) -> "CameraCalibration":
    """``calibration`` at ``width x height``, which must have its aspect ratio."""
    if (calibration.width, calibration.height) == (width, height):
        return calibration
    if abs(calibration.width / calibration.height - width / height) > 1e-3:
        raise FrameSizeError(f"{what} is for {calibration.width}x{calibration.height} images; "
                             f"{width}x{height} has another aspect ratio")
    return calibration.scaled(width, height)


def fit_calibration(camera: Any, distortion_model: str = "auto") -> tuple["CameraCalibration", float]:
    """Fit a ROS distortion model to a learnt ``CameraModel``: ``(calibration, rms residual in pixels)``.

    ``"auto"`` keeps plumb_bob (what most ROS consumers handle) unless rational_polynomial halves the
    residual and plumb_bob is off by more than a tenth of a pixel.
    """
    if distortion_model != "auto":
        return camera.to_calibration(distortion_model)
    plumb = camera.to_calibration("plumb_bob")
    if plumb[1] <= 0.1:
        return plumb
    rational = camera.to_calibration("rational_polynomial")
    return rational if rational[1] < 0.5 * plumb[1] else plumb


def _as_rgb(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise FrameError(f"frames must be uint8 numpy images, got {type(image).__name__} {getattr(image, 'dtype', '')}")
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 2 or image.shape[1] < 2:
        raise FrameError(f"frames must be (H, W, 3) RGB or (H, W) mono, got shape {image.shape}")
    return image
