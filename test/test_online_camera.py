"""The online camera's prior for the next window: the information the windows carried, about their estimates.

A calibration given as a file has a diagonal prior, and the windows' information here is diagonal too,
so each parameter's prior mean has the scalar closed form (sum of information times estimate over the
sum of information) to check against.
"""

from __future__ import annotations

import numpy as np
import pytest

from nocal_ros.lens import CameraCalibration
from nocal_ros.odometry.bundle_adjustment import camera_parameters
from nocal_ros.odometry.calibration import OnlineCamera, anchored_prior


def camera_with(fx: float, fy: float, k1: float = 0.0) -> CameraCalibration:
    K = np.array([[fx, 0.0, 80.0], [0.0, fy, 60.0], [0.0, 0.0, 1.0]])
    return CameraCalibration(160, 120, K, np.array([k1, 0.0, 0.0, 0.0, 0.0]), "plumb_bob", "test")


def test_the_next_windows_prior_is_the_information_weighted_mean_of_the_windows_estimates():
    start = camera_with(100.0, 100.0)
    camera = OnlineCamera(start, "file")
    start_information = np.diag(camera.initial_information).copy()
    assert np.count_nonzero(camera.initial_information - np.diag(start_information)) == 0
    window = np.diag(3.0 * start_information)  # each window knows three times what the file did
    carried = 0.25 * np.diag(window)  # the share of a window that leaves with its oldest keyframe

    first, second = camera_with(110.0, 108.0, -0.1), camera_with(120.0, 118.0, -0.2)
    camera.update(first, np.eye(8), window, kept_share=0.75)
    mean, information = camera.prior()
    expected = (start_information * camera_parameters(start) + carried * camera_parameters(first)) / (start_information + carried)
    np.testing.assert_allclose(mean, expected, rtol=1e-12)
    np.testing.assert_allclose(np.diag(information), start_information + carried, rtol=1e-12)

    camera.update(second, np.eye(8), window, kept_share=0.75)
    mean, information = camera.prior()
    expected = (start_information * camera_parameters(start) + carried * (camera_parameters(first) + camera_parameters(second))) \
        / (start_information + 2 * carried)
    np.testing.assert_allclose(mean, expected, rtol=1e-12)
    assert camera.calibration.fx == 120.0  # what is published is the latest window's estimate
    assert mean[0] == pytest.approx(100.0 + (10.0 + 20.0) * 0.75 / (1.0 + 1.5))  # not the latest, 120
    # A given calibration's window prior is the carried one as it is (no principal point anchor).
    anchored_mean, anchored_information = anchored_prior(camera)
    np.testing.assert_array_equal(anchored_mean, mean)
    np.testing.assert_array_equal(anchored_information, information)


def test_an_initialisation_replaces_what_the_windows_carried_and_a_reset_starts_again():
    start = camera_with(100.0, 100.0)
    camera = OnlineCamera(start, "file")
    start_information = np.diag(camera.initial_information).copy()
    window = np.diag(2.0 * start_information)
    camera.update(camera_with(130.0, 130.0), np.eye(8), window, kept_share=0.5)
    initialised = camera_with(104.0, 103.0)
    # The initialisation solved every keyframe the carried windows came from: they are not counted again.
    camera.update(initialised, np.eye(8), window, kept_share=0.5, initialisation=True)
    mean, _ = camera.prior()
    expected = (start_information * camera_parameters(start) + 0.5 * np.diag(window) * camera_parameters(initialised)) \
        / (start_information + 0.5 * np.diag(window))
    np.testing.assert_allclose(mean, expected, rtol=1e-12)
    assert mean[0] == pytest.approx(100.0 + 4.0 * 1.0 / 2.0)

    restart = camera_with(90.0, 90.0)
    camera.reset(restart, "file")
    mean, information = camera.prior()
    np.testing.assert_allclose(mean, camera_parameters(restart), rtol=1e-12)
    np.testing.assert_array_equal(information, camera.initial_information)


def test_a_new_map_starts_from_all_the_camera_was_told_and_its_initialisations_keep_it():
    start = camera_with(100.0, 100.0)
    camera = OnlineCamera(start, "file")
    mean, information = camera.begin_map()  # nothing told yet: the start exactly
    np.testing.assert_array_equal(mean, camera_parameters(start))
    np.testing.assert_array_equal(information, camera.initial_information)

    start_information = np.diag(camera.initial_information).copy()
    window = np.diag(2.0 * start_information)
    first = camera_with(110.0, 108.0, -0.1)
    camera.update(first, np.eye(8), window, kept_share=0.75)
    # The old map's last window is seen by no later window: all of it counts, once.
    mean, information = camera.begin_map()
    np.testing.assert_allclose(np.diag(information), 3.0 * start_information, rtol=1e-12)
    np.testing.assert_allclose(mean, (camera_parameters(start) + 2.0 * camera_parameters(first)) / 3.0, rtol=1e-12)
    carried_mean, carried_information = camera.prior()
    np.testing.assert_allclose(carried_mean, mean, rtol=1e-12)
    np.testing.assert_allclose(carried_information, information, rtol=1e-12)

    # The new map's initialisation replaces what its own windows carried, and keeps the map's start.
    camera.update(camera_with(150.0, 150.0), np.eye(8), window, kept_share=0.5)
    second = camera_with(114.0, 112.0, -0.12)
    camera.update(second, np.eye(8), window, kept_share=0.5, initialisation=True, start=(mean, information))
    prior_mean, prior_information = camera.prior()
    np.testing.assert_allclose(np.diag(prior_information), 4.0 * start_information, rtol=1e-12)
    np.testing.assert_allclose(prior_mean, (3.0 * mean + camera_parameters(second)) / 4.0, rtol=1e-12)
    # A map's initialisation prior is its start, the principal point anchor aside (a file's has none).
    anchored_mean, anchored_information = anchored_prior(camera, initial=True, start=(mean, information))
    np.testing.assert_array_equal(anchored_mean, mean)
    np.testing.assert_array_equal(anchored_information, information)


def test_a_refinement_keeps_what_the_keyframes_older_than_its_span_told_the_camera():
    start = camera_with(100.0, 100.0)
    camera = OnlineCamera(start, "file")
    s = np.diag(camera.initial_information).copy()
    window = np.diag(2.0 * s)
    estimates = [camera_with(104.0 + k, 103.0 + k, -0.1 * k) for k in range(3)]
    for k, estimate in enumerate(estimates):  # each window leaves its oldest keyframe k with a quarter
        camera.update(estimate, np.eye(8), window, kept_share=0.75, leaving=[k])
    # An initialisation from keyframe 0 on holds them all: the start alone, as it is.
    mean, information = camera.initialisation_start(None, 0)
    np.testing.assert_array_equal(mean, camera_parameters(start))
    np.testing.assert_array_equal(information, camera.initial_information)
    # From keyframe 2 on: the start and what keyframes 0 and 1 carried.
    mean, information = camera.initialisation_start(None, 2)
    np.testing.assert_allclose(np.diag(information), 2.0 * s, rtol=1e-12)
    expected = (camera_parameters(start) + 0.5 * (camera_parameters(estimates[0]) + camera_parameters(estimates[1]))) / 2.0
    np.testing.assert_allclose(mean, expected, rtol=1e-12)

    # It replaces what keyframe 2 on carried and keeps the older keyframes' share.
    solved = camera_with(108.0, 107.0, -0.05)
    camera.update(solved, np.eye(8), window, kept_share=0.5, initialisation=True, first_keyframe=2, leaving=[2, 3])
    prior_mean, prior_information = camera.prior()
    np.testing.assert_allclose(np.diag(prior_information), 3.0 * s, rtol=1e-12)
    np.testing.assert_allclose(prior_mean, (2.0 * mean + camera_parameters(solved)) / 3.0, rtol=1e-12)
    # A later refinement, from keyframe 4 on, starts from all of it.
    later_mean, later_information = camera.initialisation_start(None, 4)
    np.testing.assert_allclose(later_mean, prior_mean, rtol=1e-12)
    np.testing.assert_allclose(later_information, prior_information, rtol=1e-12)


def test_a_given_calibrations_check_rejects_it_by_its_wald_statistic_and_then_holds_it_as_a_guess():
    """The check's statistic is ``d^T (C_check + C_given)^-1 d`` over (fx, fy), computed here by hand:
    a calibration that the stream contradicts beyond it (and by 4 % or more) becomes a guess, one it
    does not is confirmed once the check's focal length is known to 1 %, and stays pending before."""
    from nocal_ros.odometry.calibration import (GIVEN_CALIBRATION_STD, START_CHECK_SIGNIFICANCE, GUESS_STD,
                                                calibration_information)

    given = camera_with(100.0, 100.0)
    given_variance = (GIVEN_CALIBRATION_STD["focal"] * 100.0) ** 2

    def check(fx: float, fy: float, std: float, final: bool = False) -> tuple[OnlineCamera, str]:
        camera = OnlineCamera(given, "file")
        covariance = np.diag([std**2, std**2, 1.0, 1.0, 0.01, 0.01, 1e-6, 1e-6])
        return camera, camera.check_start(camera_with(fx, fy), covariance, final=final)

    camera, decision = check(106.0, 105.0, 0.8)  # 5.5 % off, the check's focal known to 0.8 %
    expected = (6.0**2 + 5.0**2) / (0.8**2 + given_variance)
    assert camera.check_detail["statistic"] == pytest.approx(expected, rel=1e-12)
    assert expected > START_CHECK_SIGNIFICANCE and decision == "rejected" and camera.given_check == "rejected"
    assert not camera.given and camera.status()["given_check"] == "rejected"
    np.testing.assert_array_equal(camera.initial_information, calibration_information(given, GUESS_STD))
    np.testing.assert_array_equal(camera.prior()[1], camera.initial_information)  # nothing carried of the file's trust

    camera, decision = check(106.0, 105.0, 3.0)  # the same difference, but the check's focal only to 3 %
    assert (36.0 + 25.0) / (9.0 + given_variance) < START_CHECK_SIGNIFICANCE
    assert decision == "pending" and camera.given
    assert check(106.0, 105.0, 3.0, final=True)[1] == "confirmed"  # the last check confirms what it does not reject
    camera, decision = check(103.0, 103.0, 0.1)  # a significant 3 %, below GIVEN_CHECK_MIN_ERROR: kept as given
    assert camera.check_detail["statistic"] > START_CHECK_SIGNIFICANCE and decision == "confirmed"
    assert check(101.0, 99.5, 0.9)[1] == "confirmed"
    assert OnlineCamera(given, "model").given_check == ""  # nothing given, nothing to check


def test_a_camera_carried_into_a_new_map_is_checked_against_its_statistic_and_dropped_to_a_guess():
    """At a new map a calibrated camera (not a given one) carries what the earlier maps told it; the new
    map checks it: the statistic is ``d^T (C_check + C_carried)^-1 d`` with ``C_carried`` the inverse of
    the carried information, computed here by hand."""
    from nocal_ros.odometry.calibration import START_CHECK_SIGNIFICANCE, GUESS_STD, calibration_information

    def carried_camera(source: str) -> tuple[OnlineCamera, tuple[np.ndarray, np.ndarray]]:
        camera = OnlineCamera(camera_with(160.0, 160.0), source)
        window = np.diag(1.0 / np.square([0.5, 0.5, 1.0, 1.0, 0.01, 0.01, 1e-3, 1e-3]))  # the focal to 0.5 px
        camera.update(camera_with(100.0, 100.0), np.eye(8), window, kept_share=0.0)
        assert camera.carried_check == "" and camera.start_check() == ("given" if source == "file" else "")
        return camera, camera.begin_map()

    camera, start = carried_camera("model")
    assert camera.carried_check == "pending" and camera.start_check() == "carried"
    carried_variance = np.linalg.inv(start[1])[0, 0]
    covariance = np.diag([1.0, 1.0, 1.0, 1.0, 0.01, 0.01, 1e-6, 1e-6])
    assert camera.check_start(camera_with(85.0, 86.0), covariance) == "rejected"  # a swapped lens
    d = camera_parameters(camera_with(85.0, 86.0))[:2] - start[0][:2]
    expected = d @ np.linalg.solve(covariance[:2, :2] + np.linalg.inv(start[1])[:2, :2], d)
    assert camera.check_detail["statistic"] == pytest.approx(expected, rel=1e-9) and expected > START_CHECK_SIGNIFICANCE
    assert carried_variance < 1.0 and camera.status()["carried_check"] == "rejected"
    guess = calibration_information(camera.initial_calibration, GUESS_STD)
    np.testing.assert_allclose(camera.rejected_start[0], start[0], rtol=1e-12)  # about the carried camera ...
    np.testing.assert_array_equal(camera.prior()[1], guess)  # ... as a guess: the old maps' confidence is gone
    assert camera.start_check() == ""

    camera, start = carried_camera("model")
    assert camera.check_start(camera_with(101.0, 100.5), covariance) == "confirmed"  # 1 % of the focal known
    np.testing.assert_array_equal(camera.prior()[1], start[1])  # kept as carried
    camera, _ = carried_camera("file")  # a given calibration's own check comes first; nothing carried to check
    assert camera.carried_check == "" and camera.start_check() == "given"

    given = OnlineCamera(camera_with(100.0, 100.0), "file")  # confirmed in one map, checked again in the next
    assert given.check_start(camera_with(100.5, 100.2), covariance) == "confirmed" and given.start_check() == ""
    given.update(camera_with(100.1, 100.1), np.eye(8), np.eye(8), kept_share=0.0)
    given.begin_map()
    assert given.given_check == "pending" and given.start_check() == "given" and given.carried_check == ""
    assert given.check_start(camera_with(85.0, 85.0), covariance) == "rejected" and not given.given
    undecided = OnlineCamera(camera_with(100.0, 100.0), "file")  # undecided at a cut: the new map starts over
    assert undecided.check_start(camera_with(104.0, 104.0), np.diag([9.0, 9.0, 1, 1, 0.01, 0.01, 1e-6, 1e-6])) == "pending"
    undecided.update(camera_with(100.1, 100.1), np.eye(8), np.eye(8), kept_share=0.0)
    assert undecided.check_detail
    undecided.begin_map()
    assert undecided.given_check == "pending" and undecided.check_detail == {}  # its first check: focal hypotheses


def test_the_relative_focal_std_is_no_less_than_the_last_move_of_the_focal_length():
    from nocal_ros.odometry.calibration import GUESS_STD, calibration_information

    camera = OnlineCamera(camera_with(160.0, 160.0), "guess")
    # Before any window: the guess's prior (its focal std, tied to the other focal by the aspect prior).
    guess_std = np.sqrt(np.linalg.inv(calibration_information(camera_with(160.0, 160.0), GUESS_STD))[0, 0]) / 160.0
    assert 0.5 * GUESS_STD["focal"] < guess_std <= GUESS_STD["focal"]
    assert camera.relative_focal_std() == pytest.approx(guess_std, rel=1e-12)
    tight = np.diag([0.01] * 8)  # a window that claims 0.1 px
    camera.update(camera_with(120.0, 121.0), tight)
    assert camera.relative_focal_std() == pytest.approx(40.0 / 120.0, rel=1e-12)  # the move, not the 0.08 %
    camera.update(camera_with(121.2, 121.0), tight)
    assert camera.relative_focal_std() == pytest.approx(1.2 / 121.2, rel=1e-12)
    loose = np.diag([9.0] * 8)  # 3 px, more than the last move
    camera.update(camera_with(121.2, 121.0), loose)
    assert camera.relative_focal_std() == pytest.approx(3.0 / 121.2, rel=1e-12)
    camera.reset(camera_with(160.0, 160.0), "guess")
    assert camera.relative_focal_std() == pytest.approx(guess_std, rel=1e-12)
