"""The odometry node's health for ``/diagnostics``: how late, how often, and whether to trust it.

All times but ``latency`` are on the node's clock (ROS time: the ``/clock`` of a bag or simulator when
``use_sim_time`` is true), compared with the images' stamps, so the figures mean the same live and on
replay:

* ``delay``: clock time at publication minus the image's stamp (capture to odometry, transport,
  queueing and inference together);
* ``age``: clock time now minus the stamp of the last odometry published (grows when images stop or
  every frame fails);
* ``rate``: odometry messages per second of clock time;
* ``latency``: wall-clock time from receiving the image to publishing its odometry (compute alone);
* ``map_correction``: the size of the last ``map -> odom`` (m and deg): how far odom has drifted from
  the refined map (a start-up on the wrong scale, a scale that changed).

Levels follow ``diagnostic_msgs/DiagnosticStatus`` (OK 0, WARN 1, ERROR 2): WARN when no image has
arrived, tracking is lost, the node falls behind (median delay above ``max_delay_s``), no odometry has
been published for ``max_age_s``, or frames were rejected or waited for TF since the last report.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

import numpy as np

from nocal_ros.geometry import rotation_angle_deg

OK, WARN, ERROR = 0, 1, 2


class OdometryHealth:
    """Collects what the odometry node publishes and turns it into diagnostic values and a level.

    Thread-safe: the worker records, the diagnostics timer reports.

    Args:
        max_delay_s: WARN when the median delay over the window exceeds this ("falling behind").
        max_age_s: WARN when the last odometry is older than this.
        window: how many publications the rate and delay statistics cover.
    """

    def __init__(self, max_delay_s: float = 0.5, max_age_s: float = 1.0, window: int = 200) -> None:
        self.max_delay_s = float(max_delay_s)
        self.max_age_s = float(max_age_s)
        self._window = int(window)
        self._lock = threading.Lock()
        self.clock_resets = 0
        self._troubles_reported = 0  # rejected + waiting-for-TF frames at the last report
        self.reset(count=False)

    def reset(self, count: bool = True) -> None:
        """Forget the statistics (a reset, or the clock jumped back: old clock times no longer compare)."""
        with self._lock:
            self._published_at: deque[int] = deque(maxlen=self._window)  # clock ns at each publication
            self._delays_ns: deque[int] = deque(maxlen=self._window)
            self._latencies_ms: deque[float] = deque(maxlen=self._window)
            self._last_stamp_ns: int | None = None
            self._tracking = "none"
            self._scale_source = "none"
            self._map_correction = (0.0, 0.0)
            if count:
                self.clock_resets += 1

    def published(self, stamp_ns: int, now_ns: int, latency_ms: float, tracking: str = "ok",
                  scale_source: str = "none", T_map_odom: np.ndarray | None = None) -> None:
        """Record one odometry message: its image stamp, the clock at publication, compute latency, and the
        ``map -> odom`` published with it."""
        correction = (0.0, 0.0)
        if T_map_odom is not None:
            correction = (float(np.linalg.norm(T_map_odom[:3, 3])), rotation_angle_deg(T_map_odom[:3, :3]))
        with self._lock:
            self._map_correction = correction
            self._published_at.append(int(now_ns))
            self._delays_ns.append(int(now_ns) - int(stamp_ns))
            self._latencies_ms.append(float(latency_ms))
            self._last_stamp_ns = int(stamp_ns)
            self._tracking = str(tracking)
            self._scale_source = str(scale_source)

    def report(self, now_ns: int, *, frames_received: int, frames_rejected: int = 0, frames_waiting_for_tf: int = 0,
               last_error: str = "", given_check: str = "") -> tuple[int, str, dict[str, Any]]:
        """``(level, message, values)`` at clock time ``now_ns``; values are plain numbers and strings.

        ``given_check``: the given calibration's check against the stream (``OnlineCamera.given_check``);
        "rejected" warns for as long as the node runs, since the calibration file it came from is stale.
        """
        with self._lock:
            published = list(self._published_at)
            delays = np.asarray(self._delays_ns, dtype=np.float64) * 1e-9
            latencies = np.asarray(self._latencies_ms, dtype=np.float64)
            last_stamp, tracking, scale_source = self._last_stamp_ns, self._tracking, self._scale_source
            correction = self._map_correction
        span = (published[-1] - published[0]) * 1e-9 if len(published) > 1 else 0.0
        values: dict[str, Any] = {
            "rate_hz": (len(published) - 1) / span if span > 0 else 0.0,
            "delay_s_median": float(np.median(delays)) if delays.size else 0.0,
            "delay_s_max": float(delays.max()) if delays.size else 0.0,
            "odometry_age_s": (int(now_ns) - last_stamp) * 1e-9 if last_stamp is not None else -1.0,
            "latency_ms_median": float(np.median(latencies)) if latencies.size else 0.0,
            "latency_ms_max": float(latencies.max()) if latencies.size else 0.0,
            "tracking": tracking,
            "scale_source": scale_source,
            "map_correction_m": correction[0],
            "map_correction_deg": correction[1],
            "clock_resets": self.clock_resets,
        }
        problems = []
        if frames_received == 0:
            problems.append("no images received")
        if tracking == "lost":
            problems.append("tracking lost: the pose is not to be trusted")
        if delays.size and values["delay_s_median"] > self.max_delay_s:
            problems.append(f"falling behind: odometry {values['delay_s_median']:.2f} s after its image "
                            f"(max_delay {self.max_delay_s:g} s)")
        if last_stamp is not None and values["odometry_age_s"] > self.max_age_s:
            problems.append(f"no odometry for {values['odometry_age_s']:.1f} s")
        troubles = int(frames_rejected) + int(frames_waiting_for_tf)
        with self._lock:
            new_troubles, self._troubles_reported = troubles > self._troubles_reported, troubles
        if new_troubles:
            problems.append(last_error or "waiting for TF")
        if given_check == "rejected":
            problems.append("the given calibration disagrees with the stream: calibrating online "
                            "(~/save_calibration stores the online one)")
        if problems:
            return WARN, "; ".join(problems), values
        return OK, "ok", values


def vo_timing_values(timings: dict[str, list[float]]) -> dict[str, float]:
    """Diagnostic values from ``OdometryEstimator.timings()``: median and max milliseconds of the VO's
    tracking per frame, local mapping per keyframe, bundle adjustment per solve and, with a camera height,
    the ground-plane fit per keyframe and the ground homography per frame pair (0 before any)."""
    values: dict[str, float] = {}
    for name in ("tracking", "mapping", "bundle_adjustment", "ground_fit", "ground_motion"):
        samples = np.asarray(timings.get(name) or [], dtype=np.float64)
        values[f"{name}_ms_median"] = float(np.median(samples)) if samples.size else 0.0
        values[f"{name}_ms_max"] = float(samples.max()) if samples.size else 0.0
    return values
