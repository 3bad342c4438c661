"""``nocal bench``'s keyframe VO figures on a short rendered motion: every figure present and consistent."""

from __future__ import annotations

import argparse

import pytest


def test_bench_times_the_keyframe_vo_and_counts_every_frame_of_the_real_time_replay():
    from nocal_ros.commands.bench import add_arguments, format_bench, run_bench

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--untrained", "--native", "160x120", "--iterations", "3", "--warmup", "1",
                              "--vo-frames", "30", "--rate", "30", "--devices", "cpu", "--camera-height", "auto"])
    report = run_bench(args)
    vo = report["devices"]["cpu"]["vo"]
    assert vo["frames"] == 30 and vo["keyframes"] >= 3
    # Tracking is timed on every frame after the warm-up; mapping on every keyframe it mapped.
    assert vo["tracking"]["count"] == 29 and 0 < vo["tracking"]["median_ms"] <= vo["tracking"]["p90_ms"]
    assert vo["mapping"]["count"] == vo["keyframes"]
    assert vo["bundle_adjustment"]["count"] >= 1 and vo["bundle_adjustment"]["median_ms"] > 0
    # The rendered room's floor is the world's z = 0: its mean camera height runs the ground-plane fit,
    # timed at each keyframe of the map.
    assert 0.5 < vo["camera_height_m"] < 3.0
    assert 1 <= vo["ground_fit"]["count"] <= vo["keyframes"] and vo["ground_fit"]["median_ms"] > 0
    realtime = vo["realtime"]
    # Every frame sent is either processed or counted as dropped, none lost silently.
    assert realtime["frames_processed"] + realtime["frames_dropped"] == realtime["frames_sent"] == 30
    assert realtime["latency"]["count"] == realtime["frames_processed"]
    assert realtime["worker_cpu"]["count"] == realtime["frames_processed"] and realtime["worker_cpu"]["median_ms"] > 0
    text = format_bench(report)
    assert "tracking (frontend + PnP)" in text and "real time at 30 Hz" in text and "worker CPU" in text
    assert "ground-plane fit" in text and "ground homography" in text


def test_bench_rejects_a_non_positive_rate():
    from nocal_ros.commands.bench import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(["--rate", "0"])
