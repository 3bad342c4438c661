"""OdometryEstimator: camera frames in, integrated poses, twist and covariances out. No ROS here.

The odometry node, ``nocal odometry`` and ``nocal demo`` all feed frames to this one class, so every
rule about dropped frames, time jumps and bad network output lives in one place.

Frames and poses
    The pose head predicts ``T_ci_cj`` (pose of the current camera in the previous camera's frame).
    Odometry is published for ``base_frame`` (REP 105), which is rigidly attached to the camera by the
    static ``T_base_cam``. The ``odom`` frame is the base frame's pose at the first frame, so::

        T_odom_base(t) = T_base_cam @ T_cam0_camt @ inv(T_base_cam)
        T_bi_bj        = T_base_cam @ T_ci_cj  @ inv(T_base_cam)      (one pair, base frame)
        T_odom_base_j  = T_odom_base_i @ T_bi_bj

    With ``T_base_cam = I`` (the default) the base frame is the camera optical frame.

Twist
    ``nav_msgs/Odometry`` gives the twist in the child (base) frame. For the pair ``i -> j`` over
    ``dt`` seconds: linear ``R_bi_bj^T t_bi_bj / dt`` (the displacement seen from ``j``), angular
    ``log(R_bi_bj) / dt`` (the rotation vector is the same in ``i`` and ``j``).

Covariance (how it is derived)
    Each pair's error is modelled as a right perturbation ``T_bi_bj Exp(xi)``, ``xi = (rho, theta)``,
    zero-mean Gaussian. In the camera frame ``xi`` is isotropic with per-frame standard deviations
    ``sigma_t`` (m) and ``sigma_r`` (rad); a gap of ``g`` frames used as one pair gets ``g`` times the
    variance (the motion, and so the error, of a ``g``-frame pair is about ``g`` single-frame pairs).
    The values come from the checkpoint's metadata ``pose_error_std`` (``{"translation_m": ...,
    "rotation_rad": ...}``, the spread of the pose head's error per frame on labelled validation pairs,
    written by training) when present, else :data:`DEFAULT_POSE_ERROR_STD`. The camera-frame
    covariance is moved to the base frame by the adjoint of ``T_base_cam``. The pose covariance, in
    ROS order ``(x, y, z, rot_x, rot_y, rot_z)`` with position in ``odom`` and rotation about ``odom``'s
    axes, is propagated to first order::

        Sigma_j = A Sigma_i A^T + B Sigma_xi B^T,
        A = [[I, -[R_i t_ij]x], [0, I]],   B = [[R_j, 0], [0, R_j]]

    The twist covariance is ``Sigma_xi / dt^2``. A frame with no motion estimate (the first frame, or
    one after a reset) reports a twist covariance of :data:`UNKNOWN_VARIANCE`, ROS's "unknown".

Two-view geometry (on by default: ``two_view=True``)
    On cameras it never saw, the pose head's rotation is no better than reporting no motion
    (docs/RESULTS.md), while the learnt camera is good enough for classical geometry. So, when the model
    carries a camera, each pair is also measured by :mod:`nocal_ros.two_view`: corners tracked from the
    previous frame, turned into rays by the learnt camera (intrinsics and distortion MLP), and an
    essential matrix (or a pure rotation when the parallax is below a pixel). Its rotation replaces the
    pose head's; its direction of travel, scaled to the length of the pose head's translation, replaces
    the translation (monocular geometry has no scale). A pair where no geometric model explains at least
    half of the tracks keeps the pose head's estimate (``OdometryResult.motion_source`` says which).
    The covariance still uses the pose head's recorded error, an upper bound for the rotation.

Dropped frames and resets
    The frame period is the smallest stamp step seen recently (drops only lengthen steps). A step of
    ``g = round(dt / period)`` frames with ``g <= max_gap`` (the largest gap training used) is run as one
    pair; a longer one starts a new pair chain from the current frame with a warning, keeping the pose
    (the motion across the gap is lost: ``status="gap_reset"``). Time going backwards resets everything
    (pose to identity, ``status="time_reset"``), as ROS does on a clock jump; a repeated stamp is
    skipped. A change of image encoding starts a new chain (a pair across encodings would be
    meaningless). A change of image size raises :class:`FrameSizeError`, leaving the state untouched,
    until :meth:`OdometryEstimator.reset` accepts the new size. A non-finite network output skips the
    frame (counted); the next frame pairs with the last good one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from nocal_ros.errors import NocalError
from nocal_ros.geometry import invert_transform, nearest_rotation, so3_log
from nocal_ros.odometry.covariance import UNKNOWN_VARIANCE, adjoint, propagate_covariance
from nocal_ros.odometry.pose_head import PoseModel, PoseRunner

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.two_view import TwoViewTracker

log = logging.getLogger(__name__)

#: How many recent stamp steps the frame period is estimated from.
PERIOD_HISTORY = 32
#: How many arm poses :meth:`OdometryEstimator.add_arm_pose` keeps (the newest).
ARM_POSE_HISTORY = 1000


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
        motion_source: where the pair's motion came from: ``"pose_head"``, or ``"essential"`` /
            ``"rotation"`` when two-view geometry gave the rotation (see the module notes).
        tracking: ``"initialising"`` for the first frame of a chain (no motion measured yet), else
            ``"ok"``; the keyframe VO adds ``"lost"`` (docs: ESTIMATOR_API).
        scale_source: where the translation's length comes from: ``"pose_head"`` here (the VO adds
            ``"arm"`` and ``"none"``).
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


@dataclass
class OdometryCounters:
    """What happened to the frames so far (for diagnostics and reports)."""

    frames: int = 0  # frames given to process()
    pairs: int = 0  # pose head outputs integrated
    bridged_gaps: int = 0  # pairs spanning more than one frame period
    gap_resets: int = 0
    time_resets: int = 0
    encoding_resets: int = 0
    nonfinite_skipped: int = 0
    duplicate_stamps: int = 0
    size_rejected: int = 0
    two_view_pairs: int = 0  # pairs whose rotation came from two-view geometry


# --------------------------------------------------------------------------------------------------
# the estimator
# --------------------------------------------------------------------------------------------------


class OdometryEstimator:
    """Integrates the pose head over a stream of frames.

    Args:
        checkpoint: a checkpoint path, a model store directory, a loaded ``Checkpoint``, a
            :class:`PoseModel` (any pose function, e.g. for tests), or None for the shipped model.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``... (ignored for a :class:`PoseModel`).
        T_base_cam: static ``(4, 4)`` pose of the camera optical frame in the base frame.
        frame_period_s: the camera's frame period; None estimates it from the stamps.
        distortion_model: for :meth:`camera_info`: ``"auto"`` (plumb_bob unless rational_polynomial fits
            clearly better), ``"plumb_bob"`` or ``"rational_polynomial"``.
        precision: ``"fp32"``, or ``"fp16"`` / ``"bf16"`` autocast on CUDA.
        cuda_graphs: capture the pose head in CUDA graphs on CUDA (falls back to eager if capture fails).
        channels_last: run the convolutions in channels-last layout (faster on CPU; see BENCHMARKS.md).
        two_view: measure each pair's rotation and direction of travel by two-view geometry through the
            model's learnt camera (see the module notes); ignored for a model without a camera.
        calibration: a ``CameraCalibration`` that :meth:`camera_info` reports instead of the model's
            learnt camera (see :meth:`set_calibration`).

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
        two_view: bool = True,
        calibration: "CameraCalibration | None" = None,
    ) -> None:
        self._lock = threading.RLock()
        self._calibration: "CameraCalibration | None" = None
        self._calibration_source = "model"
        self._arm_poses: deque[tuple[int, np.ndarray]] = deque(maxlen=ARM_POSE_HISTORY)
        self.two_view = bool(two_view)
        self.channels_last = channels_last
        self.device_request = device
        self.frame_period_s = frame_period_s
        self.distortion_model = distortion_model
        self.precision = precision
        self.cuda_graphs = cuda_graphs
        self.counters = OdometryCounters()
        self._T_base_cam = np.eye(4) if T_base_cam is None else np.asarray(T_base_cam, dtype=np.float64)
        self._T_cam_base = invert_transform(self._T_base_cam)
        self._calibration_cache: dict[tuple[int, int], tuple["CameraCalibration", float]] = {}
        self.model: PoseModel
        self._runner: PoseRunner
        self._load(checkpoint)
        self.reset()
        if calibration is not None:
            self.set_calibration(calibration)

    # -- model -------------------------------------------------------------------------------------

    def _load(self, checkpoint: Any) -> None:
        model = checkpoint if isinstance(checkpoint, PoseModel) else PoseModel.from_checkpoint(checkpoint, self.device_request)
        runner = PoseRunner(model, self.precision, self.cuda_graphs, self.channels_last)
        self.model, self._runner, self._tracker = model, runner, self._make_tracker(model)
        self._calibration_cache.clear()

    def _make_tracker(self, model: PoseModel) -> "TwoViewTracker | None":
        if not self.two_view or model.camera is None:
            return None
        from nocal_ros.two_view import TwoViewTracker

        return TwoViewTracker(model.camera)

    def reload(self, checkpoint: Any = None) -> str:
        """Swap in another model without losing the pose; returns the new model's id.

        The new model is loaded before the old one is dropped, so a bad file raises (CheckpointError)
        and leaves the running model in place. The pair chain restarts from the next frame because
        the previous frame was preprocessed for the old model.
        """
        model = checkpoint if isinstance(checkpoint, PoseModel) else PoseModel.from_checkpoint(checkpoint, self.device_request)
        runner = PoseRunner(model, self.precision, self.cuda_graphs, self.channels_last)
        tracker = self._make_tracker(model)
        with self._lock:
            self.model, self._runner, self._tracker = model, runner, tracker
            self._calibration_cache.clear()
            self._has_previous = False
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
        """Forget everything but the model: pose to identity, no previous frame, any image size."""
        with self._lock:
            self._T_odom_base = np.eye(4)
            self._pose_cov = np.zeros((6, 6))
            self._has_previous = False
            self._previous_stamp: int | None = None
            self._image_shape: tuple[int, int] | None = None
            self._encoding: str | None = None
            self._steps: deque[int] = deque(maxlen=PERIOD_HISTORY)
            self._arm_poses.clear()

    @property
    def image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the frames accepted since the last reset, or None."""
        return None if self._image_shape is None else (self._image_shape[1], self._image_shape[0])

    def frame_period_ns(self) -> int | None:
        if self.frame_period_s:
            return int(round(self.frame_period_s * 1e9))
        return min(self._steps) if self._steps else None

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
                    log.warning(
                        "odometry: %.3f s without frames (%d frames > trained gap %d): new pair chain",
                        step * 1e-9, gap, self.model.max_gap,
                    )
                    self.counters.gap_resets += 1
                    self._has_previous = False
                    status = "gap_reset"
                    gap = 0

            slot = self._runner.load_frame(image)
            tracker = self._tracker
            if not self._has_previous:
                if tracker is not None:
                    tracker.reset()
                    tracker.update(image)  # the chain's first frame becomes the tracker's reference
                return self._start_chain(stamp_ns, "start" if status == "ok" else status)

            start = time.perf_counter()
            T_ci_cj = self._runner.run()
            inference_ms = (time.perf_counter() - start) * 1e3
            if not np.isfinite(T_ci_cj).all():
                self.counters.nonfinite_skipped += 1
                self._runner.discard(slot)  # the tracker has not seen this frame, so it pairs the next one alike
                log.warning("odometry: non-finite pose head output at stamp %d: frame skipped", stamp_ns)
                return None
            source = "pose_head"
            motion = tracker.update(image) if tracker is not None else None
            if motion is not None:
                T_ci_cj = combine_motion(T_ci_cj, motion.rotation, motion.direction)
                source = motion.model
                self.counters.two_view_pairs += 1
            return self._integrate(stamp_ns, T_ci_cj, gap, inference_ms, status, source)

    def _start_chain(self, stamp_ns: int, status: str) -> OdometryResult:
        self._has_previous = True
        self._previous_stamp = stamp_ns
        unknown = np.eye(6) * UNKNOWN_VARIANCE
        result = self._result(stamp_ns, np.eye(4), np.zeros(6), unknown, status, 0, 0.0)
        result.tracking = "initialising"
        return result

    def _integrate(self, stamp_ns: int, T_ci_cj: np.ndarray, gap: int, inference_ms: float, status: str,
                   source: str = "pose_head") -> OdometryResult:
        dt = (stamp_ns - self._previous_stamp) * 1e-9
        T_ci_cj = T_ci_cj.copy()
        T_ci_cj[:3, :3] = nearest_rotation(T_ci_cj[:3, :3])  # float32 rotations would drift off SO(3) when chained
        T_bi_bj = self._T_base_cam @ T_ci_cj @ self._T_cam_base
        sigma_t2 = self.model.pose_error_std["translation_m"] ** 2 * gap
        sigma_r2 = self.model.pose_error_std["rotation_rad"] ** 2 * gap
        ad = adjoint(self._T_base_cam)
        sigma_pair = ad @ np.diag([sigma_t2] * 3 + [sigma_r2] * 3) @ ad.T
        self._pose_cov = propagate_covariance(self._pose_cov, self._T_odom_base, T_bi_bj, sigma_pair)
        self._T_odom_base = self._T_odom_base @ T_bi_bj
        twist = np.concatenate((T_bi_bj[:3, :3].T @ T_bi_bj[:3, 3], so3_log(T_bi_bj[:3, :3]))) / dt
        self._previous_stamp = stamp_ns
        self.counters.pairs += 1
        if gap > 1:
            self.counters.bridged_gaps += 1
        return self._result(stamp_ns, T_bi_bj, twist, sigma_pair / dt**2, status, gap, inference_ms, source)

    def _result(self, stamp_ns, T_prev_curr, twist, twist_cov, status, gap, inference_ms,
                source: str = "pose_head") -> OdometryResult:
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
        )

    # -- calibration -------------------------------------------------------------------------------

    def camera_info(self, width: int | None = None, height: int | None = None) -> tuple["CameraCalibration", float]:
        """The learnt camera as a ``CameraCalibration`` (K, P, D, distortion_model) and the fit's RMS residual.

        At ``width x height`` (default: the size of the frames seen, else the camera's native size).
        Fitting the distortion model to the learnt MLP takes a moment, so results are cached per size.
        A calibration given to :meth:`set_calibration` replaces the learnt camera (scaled to the size,
        residual 0). Raises NocalError when there is neither.
        """
        with self._lock:
            override = self._calibration
        if override is not None:
            size = (int(width), int(height)) if width and height else (self.image_size or (override.width, override.height))
            return (override if size == (override.width, override.height) else override.scaled(*size)), 0.0
        camera = self.model.camera
        if camera is None:
            raise NocalError(f"model {self.model.model_id} has no learnt camera to publish")
        native = (int(camera.width), int(camera.height))
        size = (int(width), int(height)) if width and height else (self.image_size or native)
        with self._lock:
            cached = self._calibration_cache.get(size)
        if cached is not None:
            return cached
        calibration, residual = fit_calibration(camera, self.distortion_model)
        if size != native:
            if abs(size[0] / size[1] - native[0] / native[1]) > 1e-3:
                raise FrameSizeError(
                    f"model {self.model.model_id} learnt a {native[0]}x{native[1]} camera; "
                    f"{size[0]}x{size[1]} images have another aspect ratio"
                )
            residual *= size[0] / native[0]
            calibration = calibration.scaled(*size)
        with self._lock:
            self._calibration_cache[size] = (calibration, residual)
        return calibration, residual

    def set_calibration(self, calibration: "CameraCalibration") -> None:
        """Report ``calibration`` from :meth:`camera_info` from now on (camera_info_url, ~/set_camera_info).

        The pose and the pair chain are kept. This frame-to-frame estimator has no online camera, so
        the calibration is a parametric override of the model's camera for CameraInfo only; the
        keyframe VO restarts its online camera from it instead. It survives :meth:`reset` and
        :meth:`reload`.
        """
        from nocal_ros.lens import CameraCalibration

        if not isinstance(calibration, CameraCalibration):
            raise TypeError(f"set_calibration wants a CameraCalibration, got {type(calibration).__name__}")
        with self._lock:
            self._calibration = calibration
            self._calibration_source = "file"

    def calibration_status(self) -> dict:
        """Where the published camera comes from: ``{"state", "source", "focal_std_px", "keyframes"}``.

        Always ``"prior"`` here: nothing refines the camera online, so there is no uncertainty to report.
        """
        with self._lock:
            return {"state": "prior", "source": self._calibration_source, "focal_std_px": None, "keyframes": 0}

    def add_arm_pose(self, stamp_ns: int, T_base_cam: np.ndarray) -> None:
        """Record the camera optical frame's pose in the arm's base frame at ``stamp_ns`` (hand-eye applied).

        Kept in a bounded buffer (the newest :data:`ARM_POSE_HISTORY`), cleared by :meth:`reset`; the
        keyframe VO fits its metric scale to them. Raises ValueError for anything but a finite rigid 4x4.
        """
        T = np.array(T_base_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"arm pose must be a finite 4x4 transform, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("arm pose is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
        with self._lock:
            self._arm_poses.append((int(stamp_ns), T))

    @property
    def arm_poses(self) -> list[tuple[int, np.ndarray]]:
        """The recorded ``(stamp_ns, T_base_cam)`` pairs, oldest first (copies)."""
        with self._lock:
            return [(stamp, T.copy()) for stamp, T in self._arm_poses]


def combine_motion(T_pose_head: np.ndarray, rotation: np.ndarray, direction: np.ndarray | None) -> np.ndarray:
    """``T_ci_cj`` with two-view geometry's rotation and direction of travel and the pose head's distance.

    Monocular geometry sees the direction of the translation but not its length; the pose head, trained
    with metric arm poses, gives the length. Without a direction (a pure-rotation fit) the pose head's
    translation is kept.
    """
    T = np.array(T_pose_head, dtype=np.float64)
    T[:3, :3] = rotation
    if direction is not None:
        T[:3, 3] = np.linalg.norm(T[:3, 3]) * np.asarray(direction, dtype=np.float64)
    return T


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
