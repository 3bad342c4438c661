"""A wrong ground plane injected into a live estimator, for the ground-scale tests (test_vo, test_vo_real)."""

from __future__ import annotations

import dataclasses

from nocal_ros.odometry import OdometryEstimator


def wrong_live_plane(estimator: OdometryEstimator, fit: int, factor: float) -> list[float]:
    """Make the estimator's ``fit``-th live window plane (1 = the first) ``factor`` times the scale it
    found, as a plane that is not the ground would be; returns the live fits' scales as found, filled
    in as the stream goes (the end of a replay's whole-map fits are left alone)."""
    live_fits: list[float] = []
    fit_ground = estimator._ground_scale

    def with_a_wrong_plane(local_map, newest=None, *args):
        estimate = fit_ground(local_map, newest, *args)
        if estimate is not None and newest is not None:
            live_fits.append(estimate.scale)
            if len(live_fits) == fit:
                estimate = dataclasses.replace(estimate, scale=factor * estimate.scale)
        return estimate

    estimator._ground_scale = with_a_wrong_plane
    return live_fits
