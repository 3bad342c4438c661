"""The online camera: the VO's one camera, calibrated as the stream goes on.

The odometry's camera is a parametric lens (:class:`nocal_ros.lens.CameraCalibration`: ``plumb_bob``
with ``k3 = 0``, or ``equidistant``), because bundle adjustment optimises it together with poses and
landmarks. It starts from one of:

* the learnt :class:`~nocal_ros.camera.CameraModel` of the checkpoint, converted by
  :func:`calibration_from_learnt_camera` (a least-squares fit whose residual is reported);
* a calibration given by the user (``--calibration YAML``, ``camera_info_url``, ``~/set_camera_info``);
* the paper's prior, ``f = width`` and the image centre, when neither is known.

Each windowed bundle adjustment refines it and returns the marginal covariance of its parameters.
The information that the keyframes leaving the window contributed is kept as a prior for the next
windows, about the estimate of the window they left (see :meth:`OnlineCamera.update` and
:meth:`OnlineCamera.prior`), so the estimate converges over the stream rather than forgetting
everything older than the window: that is the online self-calibration. ``state`` is
``"prior"`` until the first update, ``"converging"``, then ``"converged"`` once the focal length's
standard deviation is below :data:`CONVERGED_FOCAL_STD` of its value.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from nocal_ros.lens import CameraCalibration

#: Relative standard deviation of the focal length (from the covariance) below which the camera is "converged".
CONVERGED_FOCAL_STD = 0.002
#: Distortion models the bundle adjustment optimises.
VO_MODELS = ("plumb_bob", "equidistant")
#: How far a calibration the user gives is trusted (one standard deviation): 0.2 % on the focal length,
#: 0.2 % of the width on the principal point, 0.005 on radial and 0.0005 on tangential coefficients,
#: about what a checkerboard calibration achieves. Online calibration refines it; a window's few
#: keyframes cannot wander off with it (measured: the true focal, given, drifted 1.5 % in 80 frames).
GIVEN_CALIBRATION_STD = {"focal": 0.002, "principal_point": 0.002, "radial": 0.005, "tangential": 0.0005}


#: A guessed camera's pixels are square to within this share of the width (one standard deviation of
#: ``fx - fy``): cameras' pixels are square to a fraction of a percent, and before the focal length is
#: observable the windows moved ``fx`` and ``fy`` apart freely (measured: 150 and 247 px on a camera of
#: 95 px, after 4 keyframes).
ASPECT_STD = 0.02


#: What any camera is known to be before a single window is seen (one standard deviation): focal
#: lengths within a wide range about the guess (as a share of the width), the principal point near the
#: image centre (as a share of the width), moderate distortion. Without it the first windows, which
#: cannot separate the focal length from depth, ran off (a held-out camera 4 % from the f = width guess
#: went to 130 % error, its principal point 190 px out of a 120 px image; measured). Tangential terms
#: (tried only in long initialisations, ``local_mapping.TANGENTIAL_MIN_KEYFRAMES``) within 0.002: with
#: 0.01, two dev cameras kept 0.010 and -0.014, five to seven times any dev lens's, and their principal
#: points went 38 and 4 px off (measured).
GUESS_STD = {"focal": 0.5, "principal_point": 0.05, "radial": 0.3, "tangential": 0.002, "aspect": ASPECT_STD}


#: A camera nobody calibrated has its principal point held near the image centre in every window (one
#: standard deviation, as a share of the width), where the guess's prior only starts there: a window's
#: few keyframes trade the principal point with the focal length and the distortion, and without it a
#: 160x120 camera ran off to a principal point 40 px out (measured). The radial distortion is not held
#: the same way: about none with 0.3, it cost VAMR's real barrel lens (k1 -0.30) 3 lost frames and
#: doubled its rotation error (measured on the dev bags).
PRINCIPAL_POINT_ANCHOR_STD = 0.05


#: The camera a map starts from when it came from outside the map (a given calibration, or one carried
#: from an earlier map after a loss) is checked against the map (:meth:`OnlineCamera.check_start`) by a
#: camera initialisation that holds it only as a guess. It is rejected when that solve's focal lengths
#: differ from it by this Wald statistic or more, ``d^T (C_check + C_start)^-1 d`` over ``(fx, fy)``
#: (chi-square, 2 degrees of freedom, 99.9 %), ...
START_CHECK_SIGNIFICANCE = 13.8
#: ... and by this share of the focal length or more. The check's own standard deviation is optimistic
#: on some streams: given their true calibration, the fisheye's check measured 2.5 % off at a standard
#: deviation of 0.8 % (statistic 12.4) and VAMR's 2.3 % at 1.7 %, where every calibration given 10 % off
#: was measured 6.8-12.7 % off when rejected (15 dev bags, measured). A calibration less wrong than this
#: is kept as given (or as carried).
START_CHECK_MIN_ERROR = 0.04
#: It is confirmed by a check whose focal length has a relative standard deviation of at most this (or
#: by the last check, ``final``); until then it is tried again at the next camera initialisation.
START_CHECK_DECISIVE_STD = 0.01


def anchored_prior(camera: "OnlineCamera", initial: bool = False,
                   start: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The camera prior of the next window: ``(mean parameters (8,), information (8, 8))``.

    The information carried from earlier windows, about their estimates (``initial``: only what was
    known before the map's first window, ``start`` (:meth:`OnlineCamera.begin_map` when the map
    began; the starting camera's where not given): for a camera initialisation over the whole map,
    which holds the carried windows' observations itself); for a camera that was not given calibrated,
    combined with :data:`PRINCIPAL_POINT_ANCHOR_STD` about the image centre.
    """
    if initial:
        calibration = camera.initial_calibration
        mean, information = start if start is not None else camera.starting_prior()
    else:
        calibration = camera.calibration
        mean, information = camera.prior()
    if camera.given:
        return mean, information
    return _anchored(calibration, mean, information)


def _anchored(calibration: CameraCalibration, mean: np.ndarray, information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A prior ``(mean, information)`` combined with :data:`PRINCIPAL_POINT_ANCHOR_STD` about the image centre."""
    anchor = np.zeros_like(information)
    anchor[2, 2] = anchor[3, 3] = 1.0 / (PRINCIPAL_POINT_ANCHOR_STD * calibration.width) ** 2
    centre = mean.copy()
    centre[2:4] = ((calibration.width - 1) / 2.0, (calibration.height - 1) / 2.0)
    total = information + anchor
    return np.linalg.solve(total, information @ mean + anchor @ centre), total


def calibration_information(calibration: CameraCalibration, std: dict) -> np.ndarray:
    """``(8, 8)`` diagonal information over the bundle adjustment's camera vector, from standard deviations
    (focal as a share of the focal length for a given calibration, of the width for a guess)."""
    focal = std["focal"] * (calibration.fx if std is GIVEN_CALIBRATION_STD else calibration.width)
    centre = std["principal_point"] * calibration.width
    if calibration.distortion_model == "equidistant":
        lens = [std["radial"]] * 4
    else:
        lens = [std["radial"]] * 2 + [std["tangential"]] * 2
    information = np.diag(1.0 / np.square([focal, focal, centre, centre, *lens]))
    if "aspect" in std:
        square = np.zeros(8)
        square[:2] = (1.0, -1.0)
        information += np.outer(square, square) / (std["aspect"] * calibration.width) ** 2
    return information


#: ``"auto"`` starts the VO from a learnt camera as ``equidistant`` where ``plumb_bob`` (``k3 = 0``) misses it
#: by more than this RMS in the learnt camera's pixels and ``equidistant`` by at most half as much. A third
#: of tracking's PnP threshold (1.5 px); the shipped model's pinhole fits both to 0.000 px, the field
#: bag's fine-tuned fisheye plumb_bob 9.2 px, equidistant 1.8 px (docs/RESULTS.md).
AUTO_EQUIDISTANT_PX = 0.5


def calibration_from_learnt_camera(camera: Any, distortion_model: str = "plumb_bob") -> tuple[CameraCalibration, float]:
    """A learnt ``CameraModel`` as a VO camera: ``(calibration, rms residual px)``, ``plumb_bob`` with
    ``k3 = 0`` or ``equidistant``; ``"auto"``: plumb_bob unless equidistant fits a lens plumb_bob cannot
    hold (:data:`AUTO_EQUIDISTANT_PX`).

    The camera's own least-squares fit (:meth:`~nocal_ros.camera.CameraModel.fit_parametric`).
    """
    if distortion_model == "auto":
        plumb_bob = calibration_from_learnt_camera(camera, "plumb_bob")
        if plumb_bob[1] <= AUTO_EQUIDISTANT_PX:
            return plumb_bob
        fisheye = calibration_from_learnt_camera(camera, "equidistant")
        return fisheye if fisheye[1] <= 0.5 * plumb_bob[1] else plumb_bob
    if distortion_model not in VO_MODELS:
        raise ValueError(f"the VO's camera is one of {VO_MODELS} or auto, got {distortion_model!r}")
    fit = camera.fit_parametric(distortion_model, camera_name="nocal", fix_k3=distortion_model == "plumb_bob")
    return fit.calibration, fit.rms_px


def prior_calibration(width: int, height: int, distortion_model: str = "plumb_bob") -> CameraCalibration:
    """The paper's initialisation: ``f = width``, the image centre, no distortion."""
    D = np.zeros(5 if distortion_model == "plumb_bob" else 4)
    return CameraCalibration.pinhole(width, height, float(width), distortion_model=distortion_model, D=D, camera_name="nocal")


def as_vo_calibration(calibration: CameraCalibration) -> tuple[CameraCalibration, float]:
    """A user's calibration as the VO camera: ``(calibration, rms residual in pixels)``.

    ``equidistant`` and ``plumb_bob`` with ``k3 = 0`` are taken as they are (residual 0). Other lenses
    (``plumb_bob`` with ``k3``, ``rational_polynomial``) are refitted as ``plumb_bob`` with ``k3 = 0``,
    the model the bundle adjustment optimises, by least squares on a grid of native pixels (the same
    fit as for a learnt camera); the residual says how well it fits.
    """
    if not isinstance(calibration, CameraCalibration):
        raise TypeError(f"a calibration must be a CameraCalibration, got {type(calibration).__name__}")
    model = calibration.distortion_model
    if model == "equidistant" or (model == "plumb_bob" and calibration.D[4] == 0.0):
        return calibration, 0.0
    from nocal_ros.camera import fit_distortion_coefficients
    from nocal_ros.lens import distort_normalised, pixel_grid

    pixels = pixel_grid(calibration.width, calibration.height).reshape(-1, 2)[::7]
    undistorted = calibration.undistorted_normalised(pixels)
    distorted = calibration.distorted_normalised(pixels)
    valid = np.isfinite(undistorted).all(1)
    K = calibration.K
    D = fit_distortion_coefficients(undistorted[valid], distorted[valid], "plumb_bob", K[0, 0], K[1, 1], fix_k3=True)
    residual = (distort_normalised(undistorted[valid], D, "plumb_bob") - distorted[valid]) * np.array([K[0, 0], K[1, 1]])
    fitted = CameraCalibration(calibration.width, calibration.height, K, D, "plumb_bob", calibration.camera_name)
    return fitted, float(np.sqrt(np.mean(np.sum(residual**2, -1))))


def initial_information(calibration: CameraCalibration, source: str) -> np.ndarray:
    """A user's calibration is trusted as calibrated; a learnt camera or the f = width guess as a guess."""
    return calibration_information(calibration, GIVEN_CALIBRATION_STD if source == "file" else GUESS_STD)


def _with_gains(mean: np.ndarray, information: np.ndarray, gains) -> tuple[np.ndarray, np.ndarray]:
    """``(information, information-weighted sum of estimates)`` of a prior ``(mean, information)`` and the
    carried ``gains`` (``(information, weighted)`` pairs) added to it."""
    weighted = information @ mean
    for gained, gained_weighted in gains:
        information = information + gained
        weighted = weighted + gained_weighted
    return information, weighted


def calibration_status(state: str, source: str, *, focal_std_px: float | None = None, keyframes: int = 0,
                       updates: int = 0, fit_residual_px: float | None = None, given_check: str = "",
                       carried_check: str = "", check_detail: dict | None = None) -> dict:
    """The calibration's status as the report, ``/diagnostics`` and the CLI show it: the one place its keys
    are written, whether the online camera exists yet or not.

    ``state``: ``"prior"``, ``"converging"`` or ``"converged"``; ``source``: where the camera came from
    (``"model"``, ``"file"``, ``"online"``, ...); ``given_check`` / ``carried_check``: ``""``,
    ``"pending"``, ``"confirmed"`` or ``"rejected"``; ``check_detail``: the latest check's solve (its
    ``measured_fx``, ``measured_focal_std`` and Wald ``statistic``), absent keys None.
    """
    detail = check_detail or {}
    return {
        "state": state,
        "source": source,
        "focal_std_px": focal_std_px,
        "keyframes": int(keyframes),
        "updates": int(updates),
        "fit_residual_px": fit_residual_px,
        "given_check": given_check,
        "carried_check": carried_check,
        **{f"check_{key}": detail.get(key) for key in ("measured_fx", "measured_focal_std", "statistic")},
    }


class OnlineCamera:
    """The current calibration, its covariance and the information carried between windows (thread-safe)."""

    def __init__(self, calibration: CameraCalibration, source: str, residual_px: float = 0.0) -> None:
        self._lock = threading.Lock()
        self._start(calibration, source, residual_px)

    def _start(self, calibration: CameraCalibration, source: str, residual_px: float) -> None:
        """Everything known about the camera is what ``calibration`` (from ``source``) says (hold the lock)."""
        self._calibration = calibration
        self.source = source
        self.residual_px = float(residual_px)
        self.covariance: np.ndarray | None = None
        self.initial_calibration = calibration
        self.initial_information: np.ndarray = initial_information(calibration, source)
        self._carry_from_start()
        self.given = source == "file"
        self.updates = 0
        self.keyframes = 0
        #: How far the last update moved the focal length, over its new value.
        self.last_focal_move = 0.0
        #: Whether plumb_bob's tangential terms are estimated: a camera initialisation found them
        #: significant (``local_mapping.TANGENTIAL_SIGNIFICANCE``); else they stay where they started.
        self.tangential = False
        #: Whether plumb_bob's radial terms are estimated in the windows: until a camera initialisation after
        #: the first holds them where they started (``local_mapping.RADIAL_SIGNIFICANCE``).
        self.radial = True
        #: A given calibration's check against the stream (:meth:`check_start`): "pending" until decided,
        #: then "confirmed" (checked again at each new map) or "rejected"; "" for a camera that was not given.
        self.given_check = "pending" if self.given else ""
        #: A camera carried into a new map after a loss, checked against that map (:meth:`check_start`):
        #: "pending", "confirmed" or "rejected" for the latest map; "" before a second map.
        self.carried_check = ""
        self._carried_start: tuple[np.ndarray, np.ndarray] | None = None
        #: The latest check's solve (either kind): stated and measured fx, relative std, statistic, error.
        self.check_detail: dict = {}
        #: The start a map takes on after its check rejected what it started from: that start as a guess.
        self.rejected_start: tuple[np.ndarray, np.ndarray] | None = None

    def starting_prior(self) -> tuple[np.ndarray, np.ndarray]:
        """What was known before any window: ``(the starting camera's parameters (8,), information (8, 8))``."""
        from nocal_ros.odometry.bundle_adjustment import camera_parameters

        return camera_parameters(self.initial_calibration), self.initial_information

    def _carry_from_start(self, start: tuple[np.ndarray, np.ndarray] | None = None,
                          gains: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> None:
        """Carry only ``start`` (``(mean, information)``; the starting camera's by default) and ``gains``
        (keyframe index -> what the windows carried when it left them) from here on."""
        mean, information = start if start is not None else self.starting_prior()
        self._gains: dict[int, tuple[np.ndarray, np.ndarray]] = dict(gains or {})
        # _prior_weighted: the information-weighted sum of the estimates the carried information is about.
        self.prior_information, self._prior_weighted = _with_gains(mean, information, self._gains.values())
        # The last window's share that the next window holds again (so it is not carried yet).
        self._held_information = np.zeros_like(information)
        self._held_weighted = np.zeros_like(self._prior_weighted)

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """What the windows so far tell the next one: ``(mean parameters (8,), information (8, 8))``.

        The mean is the information-weighted mean of the estimates the carried information was gained
        about (the starting camera's, and each window's when its oldest keyframe left it), not the
        latest window's estimate: centred on the latest estimate, the prior let a keyframe's pull move
        the camera once in every window that held it, and the windows walked the camera away from the
        initialisation over the stream (measured: heldout_160's focal length 0.2 % -> 1.6 % off in the
        last 40 frames, 0.2 % with this mean).
        """
        with self._lock:
            return np.linalg.solve(self.prior_information, self._prior_weighted), self.prior_information

    def begin_map(self) -> tuple[np.ndarray, np.ndarray]:
        """A new map begins: what the stream has told the camera so far, as ``(mean parameters (8,),
        information (8, 8))``, with the last window's held share now carried (no later window holds its
        keyframes again).

        The new map's prior (``LocalMap.camera_start``): its camera initialisations hold none of the
        earlier maps' observations, and started again from the f = width guess's information, the first
        initialisation of a map after a loss moved a converged focal length by 1.4-5.4 % (measured on
        rendered 160x120 rooms, a cut after 80 frames).
        """
        with self._lock:
            if self.updates == 0:  # nothing yet: the start as it is
                return self.starting_prior()
            self.prior_information = self.prior_information + self._held_information
            self._prior_weighted = self._prior_weighted + self._held_weighted
            self._held_information = np.zeros_like(self._held_information)
            self._held_weighted = np.zeros_like(self._held_weighted)
            self._gains = {}  # the old map's keyframes: no initialisation of the new map holds them
            start = np.linalg.solve(self.prior_information, self._prior_weighted), self.prior_information
            # Carried with its confidence, a camera swapped at a cut (or one confidently wrong) stayed
            # 11-46 % off through the next map (6 dev swaps of 15-70 %, measured): the map checks it. A
            # given calibration confirmed by an earlier map is checked again for the same reason.
            # Each map's first check chooses among focal hypotheses (check_detail empty): the map was
            # tracked through what it checks.
            if not self.given:
                self.carried_check, self._carried_start, self.check_detail = "pending", start, {}
            elif self.given_check in ("confirmed", "pending"):
                self.given_check, self.check_detail = "pending", {}
            return start

    def initialisation_start(self, start: tuple[np.ndarray, np.ndarray] | None,
                             first_keyframe: int) -> tuple[np.ndarray, np.ndarray]:
        """The prior of a camera initialisation over the map's keyframes from ``first_keyframe`` on, as
        ``(mean parameters (8,), information (8, 8))``: the map's ``start`` (the starting camera's where
        None) and what the windows carried as the map's older keyframes left them.

        Without the older keyframes, each refinement over the map's last 40 keyframes started again from
        the map's start, and the camera forgot everything older than its span: on all 736 frames of VAMR
        one refinement moved the focal length from 1.2 % to 4.4 % off, and it stayed there (measured).
        """
        mean, information = start if start is not None else self.starting_prior()
        with self._lock:
            older = self._gains_before(first_keyframe)
        if not older:
            return mean, information
        information, weighted = _with_gains(mean, information, older)
        return np.linalg.solve(information, weighted), information

    def start_check(self) -> str:
        """What the current map checks: "given" (a given calibration, until decided), "carried" (the camera
        carried into this map from an earlier one, until decided), or "" (nothing pending)."""
        with self._lock:
            if self.given_check == "pending":
                return "given"
            return "carried" if self.carried_check == "pending" else ""

    def _checked_start(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """``(mean parameters (8,), information (8, 8))`` of what ``kind`` checks (the caller holds the lock)."""
        if kind == "carried" and self._carried_start is not None:
            return self._carried_start
        from nocal_ros.odometry.bundle_adjustment import camera_parameters

        return camera_parameters(self.initial_calibration), self.initial_information

    def check_prior(self) -> tuple[np.ndarray, np.ndarray]:
        """The prior of a check (:meth:`start_check`): ``(mean parameters (8,), information (8, 8))``, what
        the map started from held only as a guess (:data:`GUESS_STD` about it, the principal point anchored
        near the centre as for a camera nobody calibrated)."""
        kind = self.start_check()
        with self._lock:
            mean, _ = self._checked_start(kind)
        calibration = self.initial_calibration
        return _anchored(calibration, mean, calibration_information(calibration, GUESS_STD))

    def check_start(self, calibration: CameraCalibration, covariance: np.ndarray, final: bool = False) -> str:
        """Decide the pending check (:meth:`start_check`) from the check solve's ``calibration`` and
        ``covariance``: returns "pending" (the solve could not tell yet), "confirmed" (a decisive solve,
        or the ``final`` one, that does not reject) or "rejected".

        A rejected start is no longer trusted: from here on it is a guess (:data:`GUESS_STD` about it,
        :attr:`rejected_start`) and the camera is calibrated online as one nobody calibrated. Trusted as
        calibrated, a calibration 10 % off in focal length stayed 9.5 % off over a 200-frame bag and was
        reported converged (measured).
        """
        kind = self.start_check()
        if not kind:
            return ""
        with self._lock:
            mean, information = self._checked_start(kind)
        measured = np.array([calibration.fx, calibration.fy])
        stated = np.asarray(mean[:2], dtype=np.float64)
        block = np.asarray(covariance, dtype=np.float64)[:2, :2] + np.linalg.inv(information)[:2, :2]
        relative_std = float(np.sqrt(max(covariance[0, 0], covariance[1, 1], 0.0)) / calibration.fx)
        difference = measured - stated
        statistic = float(difference @ np.linalg.solve(block, difference)) if np.all(np.isfinite(block)) else 0.0
        error = float(np.mean(np.abs(difference) / stated))
        # No bar on the check's own spread: its statistic counts it, and a rejection's camera is only
        # where the map's later initialisations start (a gate at 15 % kept a camera swapped at a cut
        # 28 % off, its first check measured 21 % uncertain and 6 standard deviations away; measured).
        rejected = statistic >= START_CHECK_SIGNIFICANCE and error >= START_CHECK_MIN_ERROR
        decision = "rejected" if rejected else "confirmed" if final or relative_std <= START_CHECK_DECISIVE_STD else "pending"
        guess = calibration_information(self.initial_calibration, GUESS_STD)
        with self._lock:
            self.check_detail = {"check": kind, "stated_fx": float(stated[0]), "measured_fx": float(calibration.fx),
                                 "measured_focal_std": relative_std, "statistic": statistic, "error": error}
            if kind == "given":
                self.given_check = decision
            else:
                self.carried_check = decision
            if rejected:
                if kind == "given":
                    self.given = False
                    self.initial_information = guess
                self.rejected_start = (np.array(mean, dtype=np.float64), guess)
                self._carry_from_start(self.rejected_start)
        return decision

    def _gains_before(self, first_keyframe: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The carried gains of the map's keyframes before ``first_keyframe`` (the caller holds the lock)."""
        return [gain for index, gain in self._gains.items() if index < first_keyframe]

    @property
    def calibration(self) -> CameraCalibration:
        with self._lock:
            return self._calibration

    def focal_std_px(self) -> float | None:
        with self._lock:
            if self.covariance is None:
                return None
            return float(np.sqrt(max(self.covariance[0, 0], self.covariance[1, 1], 0.0)))

    def relative_focal_std(self) -> float:
        """The focal length's standard deviation over its value: the last window's, or before any window
        what the starting camera is known to (:data:`GUESS_STD`, :data:`GIVEN_CALIBRATION_STD`).

        No less than the last update's move: a window reports the spread its own observations allow,
        which is too small while the estimate is still moving (heldout_640's first initialisation, 501 px
        at 3.1 % for a 455 px camera; r640_301's windows at 642-653 px and 2.1 % for a 752 px one).
        """
        with self._lock:
            if self.covariance is not None:
                variance = max(self.covariance[0, 0], self.covariance[1, 1], 0.0)
            else:
                variance = np.linalg.inv(self.initial_information)[0, 0]
            return max(float(np.sqrt(variance) / self._calibration.fx), self.last_focal_move)

    @property
    def is_guess(self) -> bool:
        """Still what it started as, and not given: no window has refined the guess (f = width or a learnt
        camera) yet, so what is measured through it is only as good as that guess."""
        return self.updates == 0 and not self.given

    def state(self) -> str:
        std = self.focal_std_px()
        if self.updates == 0 or std is None:
            return "prior"
        return "converged" if std < CONVERGED_FOCAL_STD * self.calibration.fx else "converging"

    def status(self) -> dict:
        return calibration_status(self.state(), self.source, focal_std_px=self.focal_std_px(),
                                  keyframes=self.keyframes, updates=self.updates, fit_residual_px=self.residual_px,
                                  given_check=self.given_check, carried_check=self.carried_check,
                                  check_detail=self.check_detail)

    def update(self, calibration: CameraCalibration, covariance: np.ndarray | None,
               window_information: np.ndarray | None = None, kept_share: float = 0.0,
               initialisation: bool = False, start: tuple[np.ndarray, np.ndarray] | None = None,
               first_keyframe: int = 0, leaving: tuple[int, ...] | list[int] = ()) -> None:
        """Take a bundle adjustment's camera.

        ``window_information``: the information about the camera that the window's observations alone
        gave (the posterior's minus the prior's). The share that leaves with the oldest keyframe
        (``1 - kept_share``) is added to the prior of the next windows, about this window's estimate:
        counting the window's observations only once, since the next window holds the rest of them
        again.
        ``leaving``: the map's keyframes that share leaves with (it is split evenly among them), so that
        an initialisation can keep what keyframes older than its span told the camera.
        ``initialisation``: the solve covered the keyframes from ``first_keyframe`` on, so it replaces
        what they carried instead of adding to it; ``start``: what was known before the map's first
        keyframe (its prior), which it does not replace (the starting camera's by default).
        """
        from nocal_ros.odometry.bundle_adjustment import camera_parameters

        with self._lock:
            self.last_focal_move = max(abs(calibration.fx - self._calibration.fx) / calibration.fx,
                                       abs(calibration.fy - self._calibration.fy) / calibration.fy)
            self._calibration = calibration
            self.covariance = covariance
            if initialisation:
                # Later initialisations start later still: the older keyframes' gains are kept as one.
                older = self._gains_before(first_keyframe)
                merged = {-1: (sum(g[0] for g in older), sum(g[1] for g in older))} if older else {}
                self._carry_from_start(start, merged)
            if window_information is not None:
                parameters = camera_parameters(calibration)
                gained = (1.0 - float(kept_share)) * window_information
                self.prior_information = self.prior_information + gained
                self._prior_weighted = self._prior_weighted + gained @ parameters
                for index in leaving:
                    share = gained / len(leaving)
                    before, before_weighted = self._gains.get(index, (0.0, 0.0))
                    self._gains[int(index)] = (before + share, before_weighted + share @ parameters)
                self._held_information = float(kept_share) * window_information
                self._held_weighted = self._held_information @ parameters
            self.updates += 1
            self.source = "online"

    def reset(self, calibration: CameraCalibration, source: str, residual_px: float = 0.0) -> None:
        with self._lock:
            self._start(calibration, source, residual_px)
