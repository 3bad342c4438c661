"""Local mapping, the VO's second thread of work: landmarks from new keyframes, and windowed bundle
adjustment over the last keyframes, their landmarks and the camera.

Tracking hands each new keyframe to :class:`LocalMapping`, which works on it in its own thread so that
frames are never blocked by mapping (``synchronous=True`` runs the same work before ``submit`` returns,
for replays that must repeat exactly). For each keyframe:

1. **Triangulation.** Tracks seen in the new keyframe that have no landmark yet are triangulated with the
   oldest keyframe of the window that saw them (the widest baseline), and kept when both rays meet in
   front of both cameras at :data:`MIN_TRIANGULATION_DEG` or more and reproject within the threshold.
2. **Bundle adjustment** (:mod:`nocal_ros.odometry.bundle_adjustment`) over the window's keyframes (the
   map's first two stay fixed while they are in it; later the window's oldest two, as ORB-SLAM fixes the
   keyframes at the edge of its local window), every landmark seen at least twice in the window, and the
   camera, with a robust loss. Observations it finds to be outliers are removed, and landmarks left with
   fewer than two observations are dropped.
3. **Online calibration.** The camera's new value and covariance go to the
   :class:`~nocal_ros.odometry.calibration.OnlineCamera`, which carries the information of the keyframes
   leaving the window over to the next windows.

An uncalibrated camera is held in the windows until a **camera initialisation** is taken: at the map's
6th, 10th, 16th, 25th and 40th keyframe (then every 20th), the window's solve is replaced by one over
all the map's keyframes (the last 40) with the camera and its lens free and only the guess as prior, as
ORB-SLAM3 initialises its inertial parameters in full solves after 2, 5 and 15 s (from the 25th on they
also try plumb_bob's tangential terms, kept where significant: :data:`TANGENTIAL_SIGNIFICANCE`; after the
first, the radial terms are held at zero where they are not significant and holding them leaves the
focal length where it was: :data:`RADIAL_SIGNIFICANCE`). The first chooses
among focal hypotheses (:mod:`nocal_ros.odometry.camera_initialisation`) and is taken once its focal
length's standard deviation is below :data:`INITIALISATION_FOCAL_STD`. Measured on 10 dev bags (six
random cameras, the held-out, fisheye and VAMR bags): windows alone from ``f = width`` left one camera
173 % off and the mean focal error at 18.9 %; with the initialisations every camera ended within 5.2 %
(mean 1.1 %), and the mean rotation error per frame fell from 0.449 to 0.404 deg.

What the camera learnt is not dropped by these solves. A map's prior is what the camera knew when its
first keyframe was mapped (``LocalMap.camera_start``: after a loss, everything the earlier maps told
it), and each refinement every 20th keyframe keeps, besides that, what the keyframes older than its
span carried as they left the windows and the earlier refinements (not the scheduled initialisations,
whose spans hold the keyframes tracked through the guess). On all 736 frames of VAMR the published
focal error went from 13.7 % to 1.0 % (a loss near frame 690, and refinements that had walked it
to 4.4 % by frame 445).

A **given calibration** (``--calibration``, ``camera_info_url``, ``~/set_camera_info``) is held as
calibrated in the windows, and checked against the stream: from the map's :data:`START_CHECK_KEYFRAMES`
th keyframe, at the initialisations' schedule until it is decided, a camera initialisation holds it only
as a guess (:meth:`LocalMapping.check_start`, decided by :meth:`OnlineCamera.check_start`). Confirmed, or
not yet decided, nothing of that solve is applied. Rejected, the solve is taken as the map's first camera
initialisation and the camera is calibrated online from there as one nobody calibrated. Given 10 % off
(long or short) on 15 dev bags, the camera was published 9.5-10 % off all through before; with the check
14 were rejected (at the 10th to 25th keyframe) and ended 0.1-3.0 % off, and KITTI's forward drive stayed
undecided (its check's focal standard deviation 3.8 %). Given the truth, none was rejected.

A camera **carried into a new map** after a loss (what the earlier maps told it, with their confidence)
is checked against the new map the same way: a camera swapped at a cut, or one that converged
confidently wrong, would otherwise be handed on (measured: swapped at a cut for another of the same
size, the focal length stayed 11-46 % off through the second bag on 6 dev swaps of 15-70 %). A given
calibration, confirmed or not yet decided, is checked again by each new map.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from nocal_ros.odometry.calibration import OnlineCamera, anchored_prior
from nocal_ros.odometry.map import Keyframe, LocalMap, parallax_deg, triangulate

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry.bundle_adjustment import WindowProblem

log = logging.getLogger(__name__)

#: A camera initialisation whose focal length has a larger relative standard deviation than this is not
#: taken: the first keyframes of a narrow camera (46 degrees) chose a focal length 68 % short, at a
#: standard deviation of 55 %, and the windows that followed built on it (measured).
INITIALISATION_FOCAL_STD = 0.15
#: Fewest keyframes of a map before the camera it started from (a given calibration, or one carried from
#: an earlier map) is checked against it (at the camera initialisations' schedule from there on, until the
#: check decides).
START_CHECK_KEYFRAMES = 10
#: Solver processes local mapping starts again after one died, at most (then its solves fail, logged).
SOLVER_RESTARTS = 3
#: Most solver processes a live stream's local mapping keeps. Its window solves take the first, and a
#: camera initialisation's twelve candidates are spread over all of them: on KITTI's clip at 10 Hz the
#: first took 336 ms in two processes against 554 ms in one, and the camera was solved two frames sooner
#: (docs/RESULTS.md). It keeps a core for tracking: at 30 Hz on a 2-core machine two processes took it,
#: and frames were dropped.
MAX_SOLVER_PROCESSES = 4


def solver_processes() -> int:
    """Solver processes for this machine: its cores (those this process may run on) but one, at least one."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_SOLVER_PROCESSES, cores - 1))


#: Keyframes each keyframe is searched from at the end of a replay (:func:`search_by_projection`).
SEARCH_SOURCES = 8
#: Fewest degrees between the two rays of a new landmark (smaller angles give depth from noise).
MIN_TRIANGULATION_DEG = 1.0
#: Fewest keyframes in a camera initialisation that tries plumb_bob's tangential terms (p1, p2). In a
#: window they trade with the principal point (a held-out 160x120 camera: cy 4 px off with them free);
#: held at zero, the principal point takes up a real lens's decentring instead (heldout_640, true p1, p2
#: 0.0007, -0.0004: cy 4.3 px off, ``dr`` 0.0113, measured).
TANGENTIAL_MIN_KEYFRAMES = 25
#: The tangential terms are kept when they differ from where they started (zero for a guessed camera) by
#: this Wald statistic or more, ``d^T Cov(d)^-1 d`` (chi-square, 2 degrees of freedom, 99 %); else the initialisation is solved
#: again without them. Free everywhere, they went 10-20 times their true size on low-distortion and
#: 160x120 cameras (r160_211: 0.0018 against 0.0001) and the principal point with them (measured).
TANGENTIAL_SIGNIFICANCE = 9.21
#: The same test for plumb_bob's radial terms (k1, k2) of a camera nobody calibrated, at each camera
#: initialisation after the map's first (which has the fewest keyframes to tell): below it they are held
#: where they started (zero for the guess) in that solve and the windows after it, until an
#: initialisation finds them significant. A lens without distortion (KITTI's rectified frames) otherwise
#: lets k1 trade with the focal length in forward motion (the clip's final focal length 4.5 % off with
#: them free, 2.8 % held; its frames 20-50 1.7 %, 1.2 %).
RADIAL_SIGNIFICANCE = 9.21
#: ... and only where holding them moves the focal length by less than this many of its standard
#: deviations (the solve with them free): a real but faint lens, held at zero, takes the focal length
#: with it (r160_205, k1 +0.039 at 160x120: 89.8 +- 3.5 px free, 85.1 px held, truth 90.1; KITTI's clip
#: 677 +- 20 px free, 682 px held, truth 719).
RADIAL_HOLD_FOCAL_MOVE = 0.5


@dataclass
class MappingSettings:
    """Window and thresholds of local mapping.

    Attributes:
        window: keyframes in each bundle adjustment.
        fixed_keyframes: older keyframes added to the window, held fixed, whose observations anchor
            its landmarks (ORB-SLAM's fixed covisible keyframes). Off: on 10 dev bags 3 of them lowered
            the aligned APE on 6 but raised the focal error from 1.9 % to 12 % on average (they hold
            poses made through an older camera).
        relative_tolerance: the bundle adjustment stops when an iteration lowers the cost by less
            than this share.
        scale_baseline: the window's scale is held by the distance from its oldest keyframe to this
            many keyframes later. 1: a longer baseline (5) was better on 6 of 10 dev bags and worse
            on 4 (measured; the VO's chaotic sensitivity to small changes left it undecided).
        pixel_threshold: inlier threshold in native pixels (triangulation checks and the robust loss).
        camera_stages: keyframe counts from which the camera's focal length, then its intrinsics, then
            its radial distortion are free in the windows (a curriculum). One stage: the focal length
            freed alone is biased by the lens held at none (measured on the held-out 160x120 camera,
            114 px: 172 px with the lens held, 117 with it free). An uncalibrated camera stays fixed in
            the windows until its first initialisation is taken.
        camera_initialisation: the map's keyframe counts at which, instead of the window's, a bundle
            adjustment over all the map's keyframes (the last ``initialisation_keyframes``) solves the
            camera with its lens from what was known before any window (see
            :meth:`LocalMapping.bundle_adjust`); the first one taken chooses among focal hypotheses
            (:mod:`nocal_ros.odometry.camera_initialisation`).
        camera_refinement_interval: after the last of ``camera_initialisation``, the same solve every
            this many keyframes (0: never).
        initialisation_keyframes: most keyframes in a camera initialisation.
        bundle_adjustment: run it at all (off: triangulation only, the camera stays as given).
        rebuild_initialisations: a camera initialisation after the first (and each refinement) also
            rebuilds the map through the camera it starts from and keeps whichever of the two solves
            reprojects better, as the end of a replay does. The map's first keyframes were placed through
            the guess: on a narrow camera (r640_301, f = 1.18 width, guessed short) the initialisations
            solved in that map's basin, 16 % and then 4 % off at a standard deviation of 1.3 % and 0.4 %,
            and the published focal length ended 3.95 % off; with the rebuild 0.49 %. Over 23 replays the
            published focal error's mean went 0.80 -> 0.63 % (median 0.33 -> 0.32 %); it costs those
            solves about three times as long (``nocal bench``: bundle adjustment p90 85 -> 229-245 ms per
            keyframe, median unchanged; docs/RESULTS.md).
        search_landmarks: at the end of a replay, search every keyframe for the landmarks it never tracked
            before the whole map is solved (:func:`search_by_projection`; needs the keyframes' images).
    """

    window: int = 10
    fixed_keyframes: int = 0
    scale_baseline: int = 1
    relative_tolerance: float = 1e-5
    pixel_threshold: float = 1.5
    camera_stages: tuple[int, int, int] = (6, 6, 6)
    camera_initialisation: tuple[int, ...] = (6, 10, 16, 25, 40)
    camera_refinement_interval: int = 20
    initialisation_keyframes: int = 40
    bundle_adjustment: bool = True
    rebuild_initialisations: bool = True
    search_landmarks: bool = True


class LocalMapping:
    """Runs the mapping of each submitted keyframe in a worker thread (see the module notes).

    A solve is Python and numpy on small arrays, which hold Python's global interpreter lock for most
    of their time (GTSAM, the solver before, held it for a whole solve: a thread beside it stalled;
    BENCHMARKS.md), so in a thread a bundle adjustment would slow tracking down. The worker thread
    therefore hands each solve to a worker process and waits for it without the lock; on a machine with
    cores to spare (:func:`solver_processes`) a camera initialisation's candidates go to several. They are
    spawned, so each first runs the program's main script again, its top-level imports included: a program
    that runs the estimator asynchronously should import torch (or rclpy) inside functions, not at the top
    of its main script, as the ROS executables do (:mod:`nocal_ros.ros.entry_points`).
    When keyframes arrive faster than they are mapped, the waiting ones are all triangulated and one
    bundle adjustment covers them (counted in ``merged``), so mapping never falls further behind.
    """

    def __init__(self, camera: OnlineCamera, settings: MappingSettings | None = None, synchronous: bool = False) -> None:
        self.camera = camera
        self.settings = settings or MappingSettings()
        self.synchronous = synchronous
        self.milliseconds: deque[float] = deque(maxlen=500)
        self.solve_milliseconds: deque[float] = deque(maxlen=500)
        self.failures = 0
        self.merged = 0
        #: Solver processes started again after one died.
        self.solver_restarts = 0
        self.initialisation_report: list[tuple[float, float, float]] = []
        self._queue: queue.Queue = queue.Queue()
        self._idle = threading.Event()
        self._idle.set()
        self._thread: threading.Thread | None = None
        self._solvers: list[Any] = []
        if not synchronous:
            # Start the solver processes now, before the first keyframe: spawning one and importing the
            # solver would otherwise delay the first bundle adjustment (seconds under load, measured).
            self._solvers = [start_solver() for _ in range(solver_processes())]

    # -- thread handling ---------------------------------------------------------------------------

    def submit(self, local_map: LocalMap, keyframe: Keyframe) -> None:
        if self.synchronous:
            self._run([(local_map, keyframe)])
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._work, name="nocal_local_mapping", daemon=True)
            self._thread.start()
        self._idle.clear()
        self._queue.put((local_map, keyframe))

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every submitted keyframe is mapped; False on timeout."""
        return self._idle.wait(timeout)

    @property
    def busy(self) -> bool:
        return not self._idle.is_set()

    @property
    def waiting(self) -> int:
        """Keyframes submitted and not yet taken up by the worker (0 when synchronous)."""
        return self._queue.qsize()

    def close(self) -> None:
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=10.0)
            self._thread = None
        for solver in self._solvers:
            solver.shutdown(wait=True, cancel_futures=True)
        self._solvers = []

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            batch = [item]
            while not self._queue.empty():
                more = self._queue.get_nowait()
                if more is None:
                    self._queue.put(None)
                    break
                batch.append(more)
            try:
                self._run(batch)
            except Exception:  # noqa: BLE001 - a mapping bug must not kill the thread; tracking goes on
                self.failures += 1
                log.exception("local mapping failed on a keyframe")
            finally:
                if self._queue.empty():
                    self._idle.set()

    def _solve(self, problem: Any, hypotheses: bool = False, rebuild: bool = False) -> Any:
        """``hypotheses``: the first camera initialisation's choice; ``rebuild``: the plain solve or the map
        rebuilt through the problem's camera and solved, whichever reprojects better (both:
        :mod:`nocal_ros.odometry.camera_initialisation`)."""
        from functools import partial

        from nocal_ros.odometry.bundle_adjustment import bundle_adjust
        from nocal_ros.odometry.camera_initialisation import initialise_camera

        start = time.perf_counter()
        if hypotheses:
            solve = initialise_camera
        elif rebuild:
            solve = partial(initialise_camera, focal_shares=(), starts=(problem.calibration,))
        else:
            solve = bundle_adjust
        if self.synchronous:
            solution = solve(problem)
        elif solve is not bundle_adjust and len(self._solvers) > 1:
            # A camera initialisation's candidates side by side, one per solver process; each seeds its
            # own draws, so the choice is the one a single process makes.
            solution = solve(problem, map_candidates=self._map_in_processes)
        else:
            solution = self._run_in_process(0, solve, problem)
        if hypotheses:
            solution, self.initialisation_report = solution
        elif rebuild:
            solution = solution[0]
        self.solve_milliseconds.append((time.perf_counter() - start) * 1e3)
        return solution

    def _run_in_process(self, index: int, solve: Any, *args: Any) -> Any:
        """``solve(*args)`` in solver process ``index``; a process that died (killed, out of memory) is
        replaced, up to :data:`SOLVER_RESTARTS` times, so that mapping goes on instead of failing every
        later keyframe."""
        from concurrent.futures.process import BrokenProcessPool

        try:
            return self._solver_pool(index).submit(solve, *args).result()
        except BrokenProcessPool as error:
            self._replace_solver(index, error)
            return self._solver_pool(index).submit(solve, *args).result()

    def _map_in_processes(self, function: Any, items: Any) -> list[Any]:
        """``[function(item) for item in items]`` over the solver processes, each taking the next item
        when it is done with one; a process that died is replaced as in :meth:`_run_in_process`."""
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        items = list(items)
        results: list[Any] = [None] * len(items)
        todo = list(range(len(items)))
        running: dict[Any, tuple[int, int]] = {}  # future -> (item, process)
        idle = list(range(max(1, len(self._solvers))))
        while todo or running:
            while idle and todo:
                index, item = idle.pop(0), todo.pop(0)
                try:
                    future = self._solver_pool(index).submit(function, items[item])
                except BrokenProcessPool as error:  # the pool already knows its process died
                    self._replace_solver(index, error)
                    future = self._solver_pool(index).submit(function, items[item])
                running[future] = (item, index)
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                item, index = running.pop(future)
                try:
                    results[item] = future.result()
                except BrokenProcessPool as error:
                    self._replace_solver(index, error)
                    todo.insert(0, item)
                idle.append(index)
        return results

    def _replace_solver(self, index: int, error: Exception) -> None:
        if self.solver_restarts >= SOLVER_RESTARTS:
            raise error  # one that dies again and again is a fault to report, not to hide
        self.solver_restarts += 1
        log.warning("local mapping: a bundle adjustment's process died; starting a new one")
        self._solvers[index].shutdown(wait=False, cancel_futures=True)
        self._solvers[index] = start_solver()

    def _solver_pool(self, index: int = 0) -> Any:
        while len(self._solvers) <= index:
            self._solvers.append(start_solver())
        return self._solvers[index]

    # -- the work ----------------------------------------------------------------------------------

    def _run(self, batch: list[tuple[LocalMap, Keyframe]]) -> None:
        start = time.perf_counter()
        for local_map, keyframe in batch:
            if local_map.camera_start is None:  # the map's first keyframe here: the earlier maps are done
                local_map.camera_start = self.camera.begin_map()
            self.camera.keyframes += 1
            self.pose_again(local_map, keyframe)
            self.triangulate(local_map, keyframe)
        self.merged += len(batch) - 1
        local_map = batch[-1][0]
        if self.settings.bundle_adjustment and len(local_map.keyframes) >= 3:
            # Any count the batch's keyframes reached, not only the last: merged keyframes (mapping behind
            # a real-time stream) skipped scheduled initialisations, the first one included (measured on
            # VAMR at 30 Hz: the map reached 7 keyframes in one batch, and the camera was first solved at 10).
            counts = [keyframe.index + 1 for mapped, keyframe in batch if mapped is local_map]
            scheduled = any(self.initialises_at(count) for count in counts)
            # A rejecting check's solve is the map's camera initialisation: no window solve after it.
            rejected = (scheduled and START_CHECK_KEYFRAMES <= max(counts) and self.camera.start_check() != ""
                        and self.check_start(local_map, counts))
            if not rejected:
                self.bundle_adjust(local_map, initialise=scheduled and not self.camera.given)
        self.milliseconds.append((time.perf_counter() - start) * 1e3)

    def pose_again(self, local_map: LocalMap, keyframe: Keyframe) -> bool:
        """Pose a keyframe again on the map's landmarks and through the camera as they are now, when a
        solve landed after tracking posed it; returns whether it was.

        Landmarks triangulated from a pose of an older state mix the two states: measured in real time
        on VAMR, after the first camera initialisation landed (the focal length from 79 % to 25 % off),
        the next frame tracked 122 landmarks, and only the 66 that were not triangulated from the
        keyframes tracking had posed meanwhile fitted it.
        """
        from nocal_ros.odometry.frontend import solve_pnp

        with local_map.lock:
            if keyframe.map_version == local_map.version:
                return False
            calibration = self.camera.calibration
            version = local_map.version
            mask, positions = local_map.landmark_positions(keyframe.ids)
            guess = keyframe.T_w_c.copy()
        rays = calibration.undistorted_normalised(keyframe.pixels[mask])
        pnp = solve_pnp(positions, rays, self.settings.pixel_threshold / calibration.fx, guess=guess, covariance=False)
        if pnp is None:
            return False
        with local_map.lock:
            if local_map.version != version:
                # Changed by another thread meanwhile: none does today (the map's other changes are local
                # mapping's own, or the end of a replay's after mapping finished); the PnP is of an older state.
                return False
            # A new version: tracking poses its previous frame again when the keyframe it is relative to moved.
            local_map.version += 1
            keyframe.T_w_c = pnp.T_w_c
            keyframe.map_version = local_map.version
        return True

    def triangulate(self, local_map: LocalMap, keyframe: Keyframe) -> int:
        """New landmarks from the tracks of ``keyframe`` that have none; returns how many."""
        calibration = self.camera.calibration
        threshold = self.settings.pixel_threshold / calibration.fx
        window = local_map.window(self.settings.window)
        with local_map.lock:
            pending = np.array([i for i in keyframe.ids.tolist() if i not in local_map.landmarks], dtype=np.int64)
        added = 0
        for older in window[:-1]:  # oldest first: the widest baseline wins
            if len(pending) == 0 or older is keyframe:
                break
            found, rows_old = older.lookup(pending)
            if not found.any():
                continue
            ids = pending[found]
            _, rows_new = keyframe.lookup(ids)
            x_old = calibration.undistorted_normalised(older.pixels[rows_old])
            x_new = calibration.undistorted_normalised(keyframe.pixels[rows_new])
            points = triangulate(older.T_w_c, keyframe.T_w_c, x_old, x_new)
            ok = np.isfinite(points).all(1) & np.isfinite(x_old).all(1) & np.isfinite(x_new).all(1)
            points = np.where(ok[:, None], points, 0.0)
            ok &= parallax_deg(older.T_w_c, keyframe.T_w_c, points) >= MIN_TRIANGULATION_DEG
            for T, x in ((older.T_w_c, x_old), (keyframe.T_w_c, x_new)):
                points_c = (points - T[:3, 3]) @ T[:3, :3]
                z = points_c[:, 2]
                ok &= z > 0
                error = np.linalg.norm(points_c[:, :2] / np.where(z > 0, z, 1.0)[:, None] - x, axis=1)
                ok &= error < threshold
            with local_map.lock:
                for landmark_id, point in zip(ids[ok].tolist(), points[ok]):
                    local_map.landmarks[landmark_id] = point
            added += int(ok.sum())
            # Tracks that failed with this keyframe may still triangulate with a later one.
            pending = pending[~np.isin(pending, ids[ok])]
        return added

    def initialises_at(self, keyframes: int) -> bool:
        """Whether a map with this many keyframes gets a camera initialisation (the settings' schedule)."""
        schedule, interval = self.settings.camera_initialisation, self.settings.camera_refinement_interval
        if keyframes in schedule:
            return True
        last = max(schedule, default=0)
        return bool(schedule) and interval > 0 and keyframes > last and (keyframes - last) % interval == 0

    def camera_freedom(self, initialise: bool = False, solve_keyframes: int = 0, whole_map: bool = False) -> str:
        """Which camera parameters the next bundle adjustment frees (the curriculum of the settings).

        ``solve_keyframes``: the keyframes of a camera initialisation; from
        :data:`TANGENTIAL_MIN_KEYFRAMES` on, an uncalibrated plumb_bob camera's tangential terms are
        tried there (:meth:`bundle_adjust` keeps them only where they are significant), and a whole
        map's solve frees them only where an initialisation kept them.
        """
        focal, intrinsics, lens = self.settings.camera_stages
        keyframes = self.camera.keyframes
        if not initialise and self.settings.camera_initialisation and self.camera.is_guess:
            return "fixed"  # an uncalibrated camera waits for its initialisation
        if keyframes >= lens or initialise:
            if self.camera.calibration.distortion_model == "equidistant":
                return "full"
            # plumb_bob's tangential terms stay where they are in the windows (TANGENTIAL_MIN_KEYFRAMES).
            tangential = initialise and not self.camera.given and solve_keyframes >= TANGENTIAL_MIN_KEYFRAMES
            if tangential and (self.camera.tangential or not whole_map):
                return "full"
            # The radial terms: tried at each initialisation, free elsewhere unless one held them.
            radial = self.camera.given or self.camera.radial or (initialise and not whole_map)
            return "radial" if radial else "intrinsics"
        if keyframes >= intrinsics:
            return "intrinsics"
        return "focal" if keyframes >= focal else "fixed"

    def check_start(self, local_map: LocalMap, counts: list[int]) -> bool:
        """Check the camera the map started from against it (:meth:`OnlineCamera.check_start`: a given
        calibration, or one carried from an earlier map): a camera initialisation with it held only as a
        guess, at the initialisations' schedule from the map's :data:`START_CHECK_KEYFRAMES` th keyframe to
        the last scheduled one, which decides. Returns whether it was rejected, in which case that
        initialisation is taken as the map's first and the camera is calibrated online from there as one
        nobody calibrated."""
        kind = self.camera.start_check()
        final = max(counts) >= max(self.settings.camera_initialisation, default=0)
        self.bundle_adjust(local_map, initialise=True, check="final" if final else "check")
        return (self.camera.given_check if kind == "given" else self.camera.carried_check) == "rejected"

    def bundle_adjust(self, local_map: LocalMap, initialise: bool = False, whole_map: bool = False,
                      positions: dict[int, np.ndarray] | None = None, check: str = "",
                      hold_camera: bool = False) -> None:
        """Windowed bundle adjustment over keyframes, landmarks and the camera (see the module notes).

        ``initialise``: a camera initialisation instead: every keyframe of the map (up to
        ``initialisation_keyframes``), the camera's focal length, principal point and lens all free,
        and only what was known before any window as its prior. Windows of a few keyframes cannot
        separate the focal length from the lens and the depths, and the information they carry forward
        is linearised about their own drifting estimates (measured on a 160x120 camera with a focal
        length of 95 px: the windows took it to 190 px, aspect 2:1, and then on to 330 px with k1 of
        1.9; a solve over its first 9 keyframes with the lens free found 117 px against 114 true on the
        held-out camera where the windows then held 154).

        ``whole_map`` (with ``initialise``): the initialisation's solve over every keyframe of the map (the
        end of a replay: :mod:`nocal_ros.odometry.trajectory`), without hypotheses or covariance (the
        camera keeps the last one); a camera never initialised stays as it is. ``positions``: measured
        camera positions of keyframes (``{keyframe index: position}``, an arm's, in the map's frame and
        unit), three or more: they hold the map's gauge and scale instead of its first keyframe.
        ``hold_camera`` (with ``whole_map``): the camera as it stands, not solved (another map's solve
        gave it); the map is still rebuilt through it.
        """
        from nocal_ros.odometry.bundle_adjustment import CameraPrior, WindowProblem, calibration_from_parameters, camera_parameters

        if whole_map:
            window = local_map.window(len(local_map.keyframes))
            held = 0
        elif initialise:
            window = local_map.window(self.settings.initialisation_keyframes)
            held = 0
        else:
            window = local_map.window(self.settings.window + self.settings.fixed_keyframes)
            held = max(0, len(window) - self.settings.window)  # older keyframes that only anchor the landmarks
        with local_map.lock:
            observations = []  # (keyframe row, landmark id, pixel)
            for row, keyframe in enumerate(window):
                has_landmark = np.fromiter((int(i) in local_map.landmarks for i in keyframe.ids), dtype=bool,
                                           count=len(keyframe.ids))
                for landmark_id, pixel in zip(keyframe.ids[has_landmark].tolist(), keyframe.pixels[has_landmark]):
                    observations.append((row, landmark_id, pixel))
            if not observations:
                return
            rows = np.array([o[0] for o in observations])
            ids = np.array([o[1] for o in observations], dtype=np.int64)
            pixels = np.array([o[2] for o in observations])
            # Landmarks seen at least twice in the window; the rest are not constrained by it. All of them:
            # solving for some and leaving the others where they were made the next frames' PnP mix two
            # states of the map (measured on a held-out 160x120 bag: rotation error per frame 1.0-3.3 deg
            # with the 200 most observed, 0.09 deg with all).
            unique, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
            keep = counts[inverse] >= 2
            rows, ids, pixels = rows[keep], ids[keep], pixels[keep]
            landmark_ids, point_index = np.unique(ids, return_inverse=True)
            points = np.array([local_map.landmarks[int(i)] for i in landmark_ids]).reshape(-1, 3)
            poses = np.array([kf.T_w_c for kf in window])
        if len(landmark_ids) < 10:
            return
        # The gauge of a monocular window: its oldest keyframe fixed, and its distance to the next one
        # held (the scale). The rest, the relative rotation of those two included, is free: their
        # poses were estimated through an older, worse camera, and fixing both would hold that error.
        fixed = np.zeros(len(window), dtype=bool)
        measured = None
        if positions and len(positions) >= 3:
            rows_measured = [row for row, kf in enumerate(window) if kf.index in positions]
            measured = (np.array(rows_measured, dtype=np.int64), np.array([positions[window[r].index] for r in rows_measured]))
        if measured is None or len(measured[0]) < 3:
            measured = None
            fixed[: max(1, held)] = True
        # A keyframe none of whose observations made it into the window's landmarks cannot be moved.
        fixed |= np.bincount(rows, minlength=len(window)) == 0
        calibration = self.camera.calibration
        # A refinement over the map's last keyframes keeps what its older keyframes told the camera.
        first = window[0].index if initialise and not whole_map else 0
        start = self.camera.initialisation_start(local_map.camera_start, first) if initialise else None
        kind = self.camera.start_check() if check else ""
        if kind:
            prior_mean, prior_information = self.camera.check_prior()
        else:
            prior_mean, prior_information = anchored_prior(self.camera, initial=initialise, start=start)
        prior = CameraPrior(calibration_from_parameters(prior_mean, calibration), prior_information)
        freedom = self.camera_freedom(initialise, len(window), whole_map)
        if whole_map and self.camera.is_guess:
            freedom = "fixed"  # no initialisation was taken: the stream did not tell the camera
        held_camera = whole_map and hold_camera and freedom != "fixed"
        if held_camera:
            freedom = "fixed"
        # Two or more held keyframes fix the gauge, scale included; otherwise the distance from the
        # oldest keyframe to a later one is held at its value from the previous windows.
        scale_pair = None if held >= 2 or measured is not None else (0, min(held + self.settings.scale_baseline, len(window) - 1))
        problem = WindowProblem(
            calibration=calibration, poses=poses, fixed=fixed, points=points, keyframe_index=rows,
            point_index=point_index, pixels=pixels, camera=freedom, camera_prior=prior,
            robust_threshold_px=self.settings.pixel_threshold, scale_pair=scale_pair,
            relative_tolerance=self.settings.relative_tolerance,
            # A whole map's solve is too poorly conditioned for a covariance now and then (the
            # fisheye bag's 66 keyframes, measured), and the end of a replay has no use for it.
            camera_covariance=not whole_map, positions=measured,
        )
        # The first initialisation chooses among focal hypotheses (camera_initialisation's notes).
        # A map's first check too: the map was tracked through what it checks, right or wrong.
        first_check = bool(kind) and not self.camera.check_detail
        hypotheses = initialise and (self.camera.updates == 0 or first_check) and not whole_map
        # A whole map at the end of a replay holds keyframes posed through the cameras of their time (the
        # first ones through the guess): rebuilt through the converged camera it can leave that basin
        # (measured on 10 dev bags: chosen on one, r160_202, final rotation per frame 1.06 -> 0.49 deg;
        # the plain solve reprojected better on the others).
        rebuild = whole_map and measured is None and (freedom != "fixed" or held_camera)
        if (self.settings.rebuild_initialisations and initialise and not whole_map and not kind
                and self.camera.updates > 0 and freedom != "fixed"):
            rebuild = True  # a later initialisation: also the map rebuilt through the camera it starts from
        solution = self._solve(problem, hypotheses=hypotheses, rebuild=rebuild)
        if freedom == "full" and calibration.distortion_model == "plumb_bob" and not whole_map:
            # The tangential terms were tried: kept if significant, else solved again without them.
            initial = camera_parameters(self.camera.initial_calibration)[6:8]
            significance = lens_significance(solution, initial, slice(6, 8)) if solution.success else 0.0
            self.camera.tangential = significance >= TANGENTIAL_SIGNIFICANCE
            self.camera.radial |= self.camera.tangential  # a lens decentred enough to show is a lens
            if not self.camera.tangential:
                freedom = "radial"
                problem = held_at_start(problem, slice(6, 8), initial, freedom)
                solution = self._solve(problem, hypotheses=hypotheses, rebuild=rebuild)
        if (freedom == "radial" and calibration.distortion_model == "plumb_bob" and initialise and not whole_map
                and not kind and not self.camera.given):
            # The radial terms were tried: after the first initialisation they are held where they started
            # when they are not significant and holding them leaves the focal length where it was.
            initial = camera_parameters(self.camera.initial_calibration)[4:6]
            self.camera.radial = (self.camera.updates == 0 or not solution.success
                                  or lens_significance(solution, initial, slice(4, 6)) >= RADIAL_SIGNIFICANCE)
            if not self.camera.radial:
                without_problem = held_at_start(problem, slice(4, 6), initial, "intrinsics")
                without = self._solve(without_problem, hypotheses=hypotheses, rebuild=rebuild)
                moved = focal_move(solution, without)
                if without.success and moved < RADIAL_HOLD_FOCAL_MOVE:
                    freedom, problem, solution = "intrinsics", without_problem, without
                else:
                    self.camera.radial = True
        if hypotheses and not kind and solution.success and solution.camera_covariance is not None:
            focal_std = np.sqrt(max(solution.camera_covariance[0, 0], 0.0)) / solution.calibration.fx
            if focal_std > INITIALISATION_FOCAL_STD:
                # Too few keyframes, or too little motion, to tell the focal length yet: the camera stays
                # as it was, the window is solved without it, and the next initialisation tries again.
                self.bundle_adjust(local_map)
                return
        if not solution.success:
            self.failures += 1
            log.warning("local mapping: bundle adjustment failed (%s); the window is left as it was", solution.message)
            return
        if kind:
            if solution.camera_covariance is None:
                return
            decision = self.camera.check_start(solution.calibration, solution.camera_covariance, check == "final")
            detail = self.camera.check_detail
            what = "the given calibration" if kind == "given" else "the camera carried into this map"
            if decision != "rejected":
                log.info("local mapping: %s (fx %.1f) checked against %d keyframes: %s (the stream's fx %.1f, std "
                         "%.1f %%, statistic %.1f)", what, detail["stated_fx"], len(window), decision,
                         detail["measured_fx"], 100 * detail["measured_focal_std"], detail["statistic"])
                return
            log.warning("local mapping: %s (fx %.1f) disagrees with the stream (fx %.1f, fy %.1f over %d keyframes): "
                        "it is now a guess, and the camera is calibrated online", what, detail["stated_fx"],
                        solution.calibration.fx, solution.calibration.fy, len(window))
            local_map.camera_start = self.camera.rejected_start
        outliers = ~solution.inliers
        with local_map.lock:
            local_map.version += 1
            for row, keyframe in enumerate(window):
                if not fixed[row]:
                    keyframe.T_w_c = solution.poses[row]
                bad = ids[outliers & (rows == row)]
                if len(bad):
                    local_map.remove_observations(keyframe, bad)
            for landmark_id, point in zip(landmark_ids.tolist(), solution.points):
                if landmark_id in local_map.landmarks:  # not dropped by tracking meanwhile
                    local_map.landmarks[landmark_id] = point
            # A landmark none of whose window observations fit is a mismatch: drop it.
            good_counts = np.bincount(point_index[solution.inliers], minlength=len(landmark_ids))
            for landmark_id in landmark_ids[good_counts < 2].tolist():
                local_map.landmarks.pop(landmark_id, None)
            # The camera changes with the map it was solved with, under the same lock: tracking reads
            # both at once, and landmarks of the new camera with pixels undistorted by the old one
            # gave a 10.8 deg jump in a real-time replay (measured).
            if freedom != "fixed" and whole_map:
                self.camera.update(solution.calibration, self.camera.covariance)
            elif freedom != "fixed" and solution.camera_covariance is not None:
                # The next window holds the last keyframes of this solve again: their share stays out of
                # the carried information.
                kept = min(len(window) - held, self.settings.window) - 1
                leaving = [keyframe.index for keyframe in window[held:len(window) - kept]]
                if initialise and first == 0:
                    # A scheduled initialisation's span holds the keyframes tracked through the guess: its
                    # estimate is not carried into the refinements (kept, it held VAMR's camera at 30 Hz
                    # 1.7-2.2 % off in 4 of 5 runs; without, 0.7-1.9 % in 5 and 0.2-4.2 % in 9 before; measured).
                    leaving = []
                self.camera.update(solution.calibration, solution.camera_covariance,
                                   window_information(solution.camera_covariance, prior_information),
                                   kept_share=kept / (len(window) - held), initialisation=initialise,
                                   start=local_map.camera_start, first_keyframe=first, leaving=leaving)


def start_solver() -> Any:
    """A solver process (a one-worker ``ProcessPoolExecutor``, spawned), already loading the solver: also
    the one that replaces a process that died, whose first solve would otherwise pay the imports."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    solver = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    solver.submit(_import_solver)
    return solver


def _import_solver() -> None:
    """Load the solver, the camera initialisation and their libraries in the solver process, before its
    first solve: imported there, they made the first initialisation of a live stream later."""
    import importlib

    from nocal_ros.odometry.bundle_adjustment import load_libraries

    importlib.import_module("nocal_ros.odometry.camera_initialisation")
    load_libraries()


def held_at_start(problem: WindowProblem, terms: slice, start: np.ndarray, freedom: str) -> WindowProblem:
    """``problem`` with the camera parameters ``terms`` (``camera_parameters`` order) put back at
    ``start`` and the camera freedom ``freedom``, which leaves them out: to solve again without them."""
    from nocal_ros.odometry.bundle_adjustment import calibration_from_parameters, camera_parameters

    parameters = camera_parameters(problem.calibration)
    parameters[terms] = start
    return replace(problem, calibration=calibration_from_parameters(parameters, problem.calibration), camera=freedom)


def focal_move(free: Any, held: Any) -> float:
    """How far a solve with some camera terms held moved ``fx`` from the solve with them free, in the free
    solve's standard deviations of ``fx`` (infinite without its covariance: nothing says it is small)."""
    covariance = free.camera_covariance
    if covariance is None or not np.isfinite(covariance[0, 0]) or covariance[0, 0] <= 0:
        return float("inf")
    return float(abs(held.calibration.fx - free.calibration.fx) / np.sqrt(covariance[0, 0]))


def lens_significance(solution: Any, start: np.ndarray, terms: slice) -> float:
    """The Wald statistic ``d^T Cov(d)^-1 d`` of two of a plumb_bob solution's camera parameters
    (:func:`~nocal_ros.odometry.bundle_adjustment.camera_parameters` order: ``slice(4, 6)`` the radial
    ``k1, k2``, ``slice(6, 8)`` the tangential ``p1, p2``) against where they ``start`` ed, ``d`` their
    difference (0 without a camera covariance: nothing shows them)."""
    from nocal_ros.odometry.bundle_adjustment import camera_parameters

    covariance = solution.camera_covariance
    if covariance is None:
        return 0.0
    d = camera_parameters(solution.calibration)[terms] - np.asarray(start, dtype=np.float64)
    block = covariance[terms, terms]
    if not np.all(np.isfinite(block)) or np.linalg.matrix_rank(block) < len(d):
        return 0.0
    return float(d @ np.linalg.solve(block, d))


def window_information(covariance: np.ndarray, prior_information: np.ndarray | None) -> np.ndarray:
    """The camera information a window's observations alone gave: the posterior's less the prior's.

    Over the parameters the window freed (non-zero variance); the others gained nothing. Projected onto
    the positive semi-definite cone, since a difference of two estimates can dip below zero by rounding.
    """
    free = np.diag(covariance) > 0
    gained = np.zeros_like(covariance)
    block = np.ix_(free, free)
    gained[block] = np.linalg.inv(covariance[block])
    if prior_information is not None:
        gained[block] -= prior_information[block]
    values, vectors = np.linalg.eigh(0.5 * (gained + gained.T))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def refine_two_keyframes(local_map: LocalMap, calibration: "CameraCalibration", pixel_threshold: float) -> bool:
    """Bundle adjustment of a new map's first two keyframes and their landmarks, the camera held.

    The first keyframe and the distance between the two (the map's unit) fix the gauge. Observations
    found to be outliers are removed and their landmarks dropped. Returns whether the solve succeeded.
    """
    from nocal_ros.odometry.bundle_adjustment import WindowProblem, bundle_adjust

    first, second = local_map.keyframes[:2]
    ids = np.array(sorted(local_map.landmarks), dtype=np.int64)
    found_first, rows_first = first.lookup(ids)
    found_second, rows_second = second.lookup(ids)
    both = found_first & found_second
    ids = ids[both]
    rows_first = first.lookup(ids)[1]
    rows_second = second.lookup(ids)[1]
    n = len(ids)
    problem = WindowProblem(
        calibration=calibration, poses=np.array([first.T_w_c, second.T_w_c]), fixed=np.array([True, False]),
        points=np.array([local_map.landmarks[int(i)] for i in ids]).reshape(-1, 3),
        keyframe_index=np.repeat([0, 1], n), point_index=np.tile(np.arange(n), 2),
        pixels=np.concatenate((first.pixels[rows_first], second.pixels[rows_second])), camera="fixed",
        robust_threshold_px=pixel_threshold, scale_pair=(0, 1),
    )
    solution = bundle_adjust(problem)
    if not solution.success:
        return False
    good = solution.inliers[:n] & solution.inliers[n:]
    with local_map.lock:
        second.T_w_c = solution.poses[1]
        for landmark_id, point, ok in zip(ids.tolist(), solution.points, good):
            if ok:
                local_map.landmarks[landmark_id] = point
            else:
                local_map.landmarks.pop(landmark_id, None)
    return True


#: Landmark fusion: a new landmark this close in space to an older one, as a share of its depth, may
#: be the older one seen again (then checked by reprojection, see :func:`fuse_landmarks`).
FUSE_DEPTH_SHARE = 0.05


def fuse_landmarks(local_map: LocalMap, calibration: "CameraCalibration", pixel_threshold: float,
                   depth_share: float = FUSE_DEPTH_SHARE) -> dict[int, int]:
    """Merge each landmark into an older one it duplicates; returns ``{merged id: kept id}``.

    A track that Lucas-Kanade lost and a corner detected later on the same scene point become two
    landmarks, and nothing in the map ties the two stretches of keyframes that saw them (on heldout_640,
    804 of 2006 landmarks lay, at the keyframe that first saw them, within 1.5 px of an older, no longer
    tracked landmark's projection and within 5 % of its depth). So, as ORB-SLAM fuses map points by
    projection: at the keyframe that first saw each landmark, the older landmarks whose tracks had ended
    before it are projected there; the nearest within ``pixel_threshold`` of its pixel and
    ``depth_share`` of its depth is a candidate, taken when each of the two points reprojects within
    ``pixel_threshold`` onto every observation of the other (an inlier of the bundle adjustment either
    way). Its observations pass to the older landmark; keyframes are renamed and it is dropped.
    Measured on 16 dev bags, before the whole-map solve at the end of a replay: APE Sim(3) median
    0.0257 -> 0.0221 m, final focal error median 0.87 -> 0.57 %, rotation per frame unchanged; without
    the reprojection check the 160x120 bags lost (r160_204 0.027 -> 0.049 m).
    """
    from scipy.spatial import cKDTree

    with local_map.lock:
        keyframes = list(local_map.keyframes)
        first: dict[int, int] = {}
        last: dict[int, int] = {}
        seen: dict[int, list[tuple[int, np.ndarray]]] = {}
        for row, keyframe in enumerate(keyframes):
            for landmark_id, pixel in zip(keyframe.ids.tolist(), keyframe.pixels):
                if landmark_id in local_map.landmarks:
                    first.setdefault(landmark_id, row)
                    last[landmark_id] = row
                    seen.setdefault(landmark_id, []).append((row, pixel))

        def fits(point: np.ndarray, observations: list[tuple[int, np.ndarray]]) -> bool:
            """The point reprojects onto every one of these observations within the threshold."""
            for row, pixel in observations:
                T = keyframes[row].T_w_c
                in_camera = (point - T[:3, 3]) @ T[:3, :3]
                if in_camera[2] <= 0 or not np.linalg.norm(calibration.project(in_camera[None])[0] - pixel) < pixel_threshold:
                    return False
            return True

        ids = np.array(sorted(first), dtype=np.int64)
        if len(ids) == 0:
            return {}
        positions = np.array([local_map.landmarks[int(i)] for i in ids])
        last_row = np.array([last[int(i)] for i in ids])
        merged: dict[int, int] = {}
        for row, keyframe in enumerate(keyframes):
            born = [(i, pixel) for i, pixel in zip(keyframe.ids.tolist(), keyframe.pixels) if first.get(i) == row]
            older = np.flatnonzero(last_row < row)
            if not born or len(older) == 0:
                continue
            T = keyframe.T_w_c
            in_camera = (positions[older] - T[:3, 3]) @ T[:3, :3]
            older, in_camera = older[in_camera[:, 2] > 0], in_camera[in_camera[:, 2] > 0]
            if len(older) == 0:
                continue
            pixels = calibration.project(in_camera)
            inside = np.isfinite(pixels).all(1)
            older, pixels = older[inside], pixels[inside]
            if len(older) == 0:
                continue
            tree = cKDTree(pixels)
            for landmark_id, pixel in born:
                distance, nearest = tree.query(pixel, distance_upper_bound=pixel_threshold)
                if not np.isfinite(distance):
                    continue
                kept = int(ids[older[nearest]])
                while kept in merged:
                    kept = merged[kept]
                depth = np.linalg.norm(local_map.landmarks[landmark_id] - T[:3, 3])
                if np.linalg.norm(local_map.landmarks[kept] - local_map.landmarks[landmark_id]) >= depth_share * depth:
                    continue
                if fits(local_map.landmarks[kept], seen[landmark_id]) and fits(local_map.landmarks[landmark_id], seen[kept]):
                    merged[landmark_id] = kept
        for keyframe in keyframes:
            renamed = np.array([merged.get(i, i) for i in keyframe.ids.tolist()], dtype=np.int64)
            order = np.argsort(renamed, kind="stable")
            renamed, pixels = renamed[order], keyframe.pixels[order]
            unique = np.concatenate(([True], renamed[1:] != renamed[:-1])) if len(renamed) else np.zeros(0, bool)
            keyframe.ids, keyframe.pixels = renamed[unique], pixels[unique]
        for landmark_id in merged:
            local_map.landmarks.pop(landmark_id, None)
        local_map.version += 1
    return merged


def search_by_projection(local_map: LocalMap, calibration: "CameraCalibration", images: dict[int, np.ndarray],
                         pixel_threshold: float, work_scale: tuple[float, float] = (1.0, 1.0),
                         max_sources: int = SEARCH_SOURCES) -> int:
    """Find in each keyframe the map's landmarks it sees but never tracked; returns the observations added.

    Tracks are followed from frame to frame only, so a scene point seen again after its track ended, by
    keyframes far apart in the stream, is observed by one stretch of keyframes alone; the stretches are
    tied only through their neighbours, and the map's scale drifts along it (heldout_160, the camera of
    the end fixed at the truth: path length 0.94 -> 1.04 of the truth from the first to the last sixth).
    ORB-SLAM searches each keyframe for the local map's points by projection; here each landmark in
    front of a keyframe and inside its image is projected there, and Lucas-Kanade follows it into the
    keyframe, seeded at the projection, from a keyframe that observed it (its pixel there;
    ``images[frame]`` at the tracker's work size, ``work_scale`` native pixels per work pixel): the one
    nearest in the stream among the ``max_sources`` keyframes that are the nearest observer of the most
    landmarks (each call builds both images' pyramids, so the sources are few). An observation is added
    when the track survives the forward-backward check and lands within ``pixel_threshold`` of the
    projection (an inlier of the solve that follows). Measured on 16 dev bags, before the whole-map solve
    at the end of a replay: APE Sim(3) lower on 13 (median 0.0221 -> 0.0150 m), the final focal error on
    14 (median 0.57 -> 0.34 %).
    """
    from nocal_ros.odometry.frontend import WINDOW, forward_backward_px, native_pixels, track_corners, work_pixels

    margin = WINDOW[0] // 2 + 1  # a window that would leave the image is not followed

    with local_map.lock:
        keyframes = [keyframe for keyframe in local_map.keyframes if keyframe.frame in images]
        ids = np.array(sorted(local_map.landmarks), dtype=np.int64)
        if len(ids) == 0 or len(keyframes) < 2:
            return 0
        points = np.array([local_map.landmarks[int(i)] for i in ids])
        count = len(keyframes)
        # Every observation of a map landmark as a key landmark row * count + keyframe row, sorted, with
        # its pixel: a sparse table of who observed what (a dense one grows with the product of the two).
        keys, pixels = [], []
        for r, keyframe in enumerate(keyframes):
            rows = np.clip(np.searchsorted(ids, keyframe.ids), 0, len(ids) - 1)
            known = ids[rows] == keyframe.ids
            keys.append(rows[known] * count + r)
            pixels.append(keyframe.pixels[known])
        keys = np.concatenate(keys)
        order = np.argsort(keys, kind="stable")
        keys, pixels = keys[order], np.concatenate(pixels)[order]
        landmark_of = keys // count
        observed_any = np.zeros(len(ids), dtype=bool)
        observed_any[landmark_of] = True

        def observation(landmarks: np.ndarray, rows: np.ndarray) -> np.ndarray:
            """Index into keys of each (landmark, keyframe row) observation, -1 where there is none."""
            wanted_keys = landmarks * count + rows
            at = np.clip(np.searchsorted(keys, wanted_keys), 0, len(keys) - 1)
            return np.where(keys[at] == wanted_keys, at, -1)

        def nearest_observer(landmarks: np.ndarray, r: int) -> np.ndarray:
            """Each landmark's observing keyframe row nearest to row ``r`` (it has one)."""
            at = np.searchsorted(keys, landmarks * count + r)
            before = np.clip(at - 1, 0, len(keys) - 1)
            after = np.clip(at, 0, len(keys) - 1)
            before_ok = (at > 0) & (landmark_of[before] == landmarks)
            after_ok = (at < len(keys)) & (landmark_of[after] == landmarks)
            before_row = np.where(before_ok, keys[before] % count, -count)
            after_row = np.where(after_ok, keys[after] % count, 3 * count)
            return np.where(r - before_row <= after_row - r, before_row, after_row)

        # A point further from the optical axis than every pixel of the image border is outside it: a
        # cheap test before the lens's projection of every landmark into every keyframe.
        u = np.arange(calibration.width, dtype=np.float64)
        v = np.arange(calibration.height, dtype=np.float64)
        border = np.concatenate([np.stack((u, np.zeros_like(u)), 1), np.stack((u, np.full_like(u, calibration.height - 1)), 1),
                                 np.stack((np.zeros_like(v), v), 1), np.stack((np.full_like(v, calibration.width - 1), v), 1)])
        border_xy = calibration.undistorted_normalised(border)
        widest = 1.05 * np.linalg.norm(border_xy, axis=1).max() if np.isfinite(border_xy).all() else np.inf
        found_ids: list[np.ndarray] = []
        found_pixels: list[np.ndarray] = []
        for r, keyframe in enumerate(keyframes):
            image = images[keyframe.frame]
            height, width = image.shape[:2]
            T = keyframe.T_w_c
            in_camera = (points - T[:3, 3]) @ T[:3, :3]
            in_view = (in_camera[:, 2] > 0) & (np.linalg.norm(in_camera[:, :2], axis=1) <= widest * in_camera[:, 2])
            wanted = np.flatnonzero(in_view & observed_any)
            wanted = wanted[observation(wanted, np.full(len(wanted), r)) < 0]
            projected = calibration.project(in_camera[wanted]) if len(wanted) else np.zeros((0, 2))
            work = work_pixels(projected, work_scale)
            inside = (np.isfinite(work).all(1) & (work[:, 0] >= margin) & (work[:, 1] >= margin)
                      & (work[:, 0] <= width - 1 - margin) & (work[:, 1] <= height - 1 - margin))
            wanted, projected, work = wanted[inside], projected[inside], work[inside]
            # Each landmark from the keyframe that observed it nearest in the stream (the most alike
            # view); each Lucas-Kanade call builds both images' pyramids whatever the number of points,
            # so only the max_sources keyframes nearest to the most landmarks are sources, and a landmark
            # whose nearest observer is not one of them is followed from the nearest that is (with all
            # sources, VAMR's search took 12 657 calls and 15.7 s, and was no more accurate: measured).
            nearest = nearest_observer(wanted, r)
            chosen = np.argsort(-np.bincount(nearest, minlength=count), kind="stable")[:max_sources]
            at = np.stack([observation(wanted, np.full(len(wanted), c)) for c in chosen], 1)
            far = np.iinfo(np.int64).max
            distance = np.where(at >= 0, np.abs(chosen - r)[None], far)
            pick = np.argmin(distance, 1)
            source = np.where(distance.min(1) < far, chosen[pick], -1)
            source_at = at[np.arange(len(wanted)), pick]
            new_ids, new_pixels = [], []
            for s in chosen.tolist():
                rows = np.flatnonzero(source == s)
                if len(rows) == 0:
                    continue
                start = work_pixels(pixels[source_at[rows]], work_scale)
                _, moved, kept = track_corners(images[keyframes[s].frame], image, start, work[rows],
                                               max_return_px=forward_backward_px(work_scale))
                landed = native_pixels(moved, work_scale)
                close = np.linalg.norm(landed - projected[rows[kept]], axis=1) < pixel_threshold
                new_ids.append(ids[wanted[rows[kept[close]]]])
                new_pixels.append(landed[close])
            found_ids.append(np.concatenate(new_ids) if new_ids else np.zeros(0, dtype=np.int64))
            found_pixels.append(np.concatenate(new_pixels) if new_pixels else np.zeros((0, 2)))
        added = 0
        for keyframe, new_ids, new_pixels in zip(keyframes, found_ids, found_pixels):
            if len(new_ids):
                all_ids = np.concatenate((keyframe.ids, new_ids))
                order = np.argsort(all_ids, kind="stable")
                keyframe.ids, keyframe.pixels = all_ids[order], np.concatenate((keyframe.pixels, new_pixels))[order]
                added += len(new_ids)
        if added:
            local_map.version += 1
    return added
