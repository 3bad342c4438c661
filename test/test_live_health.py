"""The odometry node's diagnostics core and its arm-pose helpers, without ROS."""

from __future__ import annotations

import numpy as np
import pytest

from nocal_ros.errors import ConfigError
from nocal_ros.geometry import make_transform, so3_exp
from nocal_ros.live.arm_poses import PendingStamps, hand_eye_matrix
from nocal_ros.live.health import OK, WARN, OdometryHealth

S = 1_000_000_000
T0 = 1_700_000_000 * S


def feed(health: OdometryHealth, n: int, delay_s: float, start_ns: int = T0, period_ns: int = S // 10, **kwargs) -> int:
    """``n`` odometry messages at 10 Hz of clock time, each published ``delay_s`` after its image."""
    for k in range(n):
        stamp = start_ns + k * period_ns
        health.published(stamp, stamp + int(delay_s * S), latency_ms=20.0 + k, **kwargs)
    return start_ns + (n - 1) * period_ns


def test_rate_delay_and_age_are_measured_on_the_clock_against_the_stamps():
    health = OdometryHealth(max_delay_s=0.5, max_age_s=1.0)
    last = feed(health, 11, delay_s=0.05, tracking="ok", scale_source="pose_head")
    level, message, values = health.report(last + int(0.3 * S), frames_received=11)
    assert (level, message) == (OK, "ok")
    assert values["rate_hz"] == pytest.approx(10.0)
    assert values["delay_s_median"] == pytest.approx(0.05) and values["delay_s_max"] == pytest.approx(0.05)
    assert values["odometry_age_s"] == pytest.approx(0.3)
    assert values["latency_ms_median"] == pytest.approx(25.0) and values["latency_ms_max"] == pytest.approx(30.0)
    assert (values["tracking"], values["scale_source"]) == ("ok", "pose_head")


def test_warns_when_the_node_falls_behind_stops_publishing_or_loses_tracking():
    health = OdometryHealth(max_delay_s=0.5, max_age_s=1.0)
    level, message, values = health.report(T0, frames_received=0)
    assert level == WARN and message == "no images received" and values["odometry_age_s"] == -1.0

    last = feed(health, 5, delay_s=0.8)
    level, message, _ = health.report(last + int(0.8 * S), frames_received=5)
    assert level == WARN and message.startswith("falling behind: odometry 0.80 s after its image")

    health = OdometryHealth(max_delay_s=0.5, max_age_s=1.0)
    last = feed(health, 5, delay_s=0.05)
    assert health.report(last + int(0.9 * S), frames_received=5)[0] == OK
    level, message, _ = health.report(last + int(2.5 * S), frames_received=5)  # the camera went quiet
    assert level == WARN and message == "no odometry for 2.5 s"

    feed(health, 1, delay_s=0.05, start_ns=last + S, tracking="lost")
    level, message, values = health.report(last + S + int(0.1 * S), frames_received=6)
    assert level == WARN and "tracking lost" in message and values["tracking"] == "lost"


def test_rejected_frames_warn_until_the_next_report_only():
    health = OdometryHealth()
    last = feed(health, 3, delay_s=0.01)
    now = last + S // 10
    level, message, _ = health.report(now, frames_received=4, frames_rejected=1, last_error="frame rejected: bad")
    assert level == WARN and message == "frame rejected: bad"
    assert health.report(now, frames_received=4, frames_rejected=1, last_error="frame rejected: bad")[0] == OK
    level, message, _ = health.report(now, frames_received=5, frames_rejected=1, frames_waiting_for_tf=1)
    assert level == WARN and message == "waiting for TF"


def test_a_rejected_given_calibration_warns_for_as_long_as_the_node_runs():
    health = OdometryHealth()
    now = feed(health, 3, delay_s=0.01) + S // 10
    for check in ("", "pending", "confirmed"):
        assert health.report(now, frames_received=3, given_check=check)[:2] == (OK, "ok")
    for _ in range(2):  # not once: the file it came from stays stale
        level, message, _ = health.report(now, frames_received=3, given_check="rejected")
        assert level == WARN and message.startswith("the given calibration disagrees with the stream")


def test_the_map_correction_is_reported_as_a_distance_and_an_angle():
    """How far odom has drifted from the map: the last map -> odom's translation and rotation angle."""
    health = OdometryHealth()
    _, _, values = health.report(T0, frames_received=0)
    assert (values["map_correction_m"], values["map_correction_deg"]) == (0.0, 0.0)
    T_map_odom = make_transform(so3_exp(np.radians(12.0) * np.array([0.6, 0.0, 0.8])), np.array([0.3, -0.4, 1.2]))
    last = feed(health, 3, delay_s=0.05, T_map_odom=T_map_odom)
    _, _, values = health.report(last, frames_received=3)
    assert values["map_correction_m"] == pytest.approx(1.3) and values["map_correction_deg"] == pytest.approx(12.0)
    health.reset()
    assert health.report(last, frames_received=3)[2]["map_correction_m"] == 0.0


def test_reset_forgets_clock_times_from_before_a_jump():
    health = OdometryHealth()
    feed(health, 5, delay_s=0.05)
    health.reset()
    level, _, values = health.report(T0 - 60 * S, frames_received=5)  # the bag looped: the clock is earlier
    assert level == OK and values["rate_hz"] == 0.0 and values["odometry_age_s"] == -1.0
    assert values["clock_resets"] == 1


def test_pending_stamps_wait_for_tf_and_give_up_on_old_ones():
    pending = PendingStamps(max_wait_s=0.5)
    available: dict[int, np.ndarray] = {}
    for k in range(3):
        pending.add(T0 + k * S // 10)
    assert pending.resolve(available.get) == [] and len(pending) == 3  # TF has nothing yet
    available[T0 + S // 10] = np.eye(4)
    found = pending.resolve(available.get)
    assert [s for s, _ in found] == [T0 + S // 10] and len(pending) == 2
    pending.add(T0 + 7 * S // 10)  # 0.7 s after the first stamp: the first is given up, the third waits
    assert pending.resolve(available.get) == [] and len(pending) == 2
    assert (pending.resolved, pending.given_up) == (1, 1)
    pending.clear()
    assert len(pending) == 0

    bounded = PendingStamps(max_wait_s=10.0, capacity=4)
    for k in range(6):
        bounded.add(T0 + k)
    assert len(bounded) == 4 and bounded.given_up == 2


def test_hand_eye_must_be_a_rigid_transform():
    T = make_transform(so3_exp(np.array([0.1, 0.2, -0.3])), np.array([0.01, 0.0, 0.1]))
    np.testing.assert_array_equal(hand_eye_matrix(T.ravel().tolist()), T)
    for bad, problem in (([1.0] * 16, "not a rigid"), ([0.0] * 15, "16 finite"), ([float("nan")] * 16, "16 finite"),
                         (np.diag([-1.0, 1.0, 1.0, 1.0]).ravel(), "not a rigid")):
        with pytest.raises(ConfigError, match=problem):
            hand_eye_matrix(bad)


def test_vo_timings_become_median_and_max_milliseconds_and_zero_before_any():
    from nocal_ros.live.health import vo_timing_values

    values = vo_timing_values({"tracking": [3.0, 1.0, 2.0, 10.0], "mapping": [], "bundle_adjustment": [40.0],
                               "ground_fit": [1.5, 2.5, 1.0], "ground_motion": [1.2, 0.8]})
    assert values["tracking_ms_median"] == 2.5 and values["tracking_ms_max"] == 10.0
    assert values["mapping_ms_median"] == 0.0 and values["mapping_ms_max"] == 0.0
    assert values["bundle_adjustment_ms_median"] == 40.0
    assert values["ground_fit_ms_median"] == 1.5 and values["ground_fit_ms_max"] == 2.5
    assert values["ground_motion_ms_median"] == 1.0 and values["ground_motion_ms_max"] == 1.2
    assert vo_timing_values({})["tracking_ms_median"] == 0.0
