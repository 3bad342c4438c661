"""The arm-pose epipolar term: residuals against a closed form, a camera fit against OpenCV's projection,
correspondences tracked on rendered frames, and its use in the training loop."""

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from nocal_ros import geometry as g
from nocal_ros.camera import CameraModel
from nocal_ros.data.synthetic import render_sequence
from nocal_ros.epipolar import (ArmCorrespondences, arm_correspondences, calibrate_from_arm_poses, epipolar_loss,
                                epipolar_residuals)
from nocal_ros.evaluation import calibration_errors
from nocal_ros.lens import CameraCalibration
from nocal_ros.training import sequence_correspondences, train

WIDTH, HEIGHT, FOCAL = 160, 120, 120.0
BARREL = np.array([-0.25, 0.05, 0.0, 0.0, 0.0])


def calibration(D=np.zeros(5), focal=FOCAL):
    K = np.array([[focal, 0, (WIDTH - 1) / 2 + 2.0], [0, focal, (HEIGHT - 1) / 2 - 1.5], [0, 0, 1.0]])
    return CameraCalibration(width=WIDTH, height=HEIGHT, K=K, D=np.asarray(D, float), distortion_model="plumb_bob")


def projected_correspondences(lens: CameraCalibration, pairs: int = 12, points: int = 250, translate: bool = True, seed: int = 0):
    """Random scene points seen from pairs of known camera poses, projected by OpenCV (the reference)."""
    rng = np.random.default_rng(seed)
    pixels_i, pixels_j, rotations, baselines = [], [], [], []
    for _ in range(pairs):
        T_ci_cj = g.make_transform(g.so3_exp(rng.normal(size=3) * np.deg2rad(8.0)),
                                   rng.normal(size=3) * 0.1 if translate else np.zeros(3))
        # points in front of camera i over the whole field of view, at 1-4 m
        directions = lens.unproject(rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], size=(points, 2)))
        X_i = directions * rng.uniform(1.0, 4.0, size=(points, 1))
        X_j = (np.linalg.inv(T_ci_cj) @ np.c_[X_i, np.ones(points)].T).T[:, :3]
        u_i = cv2.projectPoints(X_i, np.zeros(3), np.zeros(3), lens.K, lens.D)[0].reshape(-1, 2)
        u_j = cv2.projectPoints(X_j, np.zeros(3), np.zeros(3), lens.K, lens.D)[0].reshape(-1, 2)
        inside = (X_j[:, 2] > 0.2) & (u_j >= 0).all(1) & (u_j[:, 0] <= WIDTH - 1) & (u_j[:, 1] <= HEIGHT - 1)
        t = T_ci_cj[:3, 3]
        pixels_i.append(u_i[inside])
        pixels_j.append(u_j[inside])
        rotations.append(np.broadcast_to(T_ci_cj[:3, :3], (inside.sum(), 3, 3)))
        baselines.append(np.broadcast_to(t / np.linalg.norm(t) if translate else np.zeros(3), (inside.sum(), 3)))
    as_tensor = lambda parts: torch.from_numpy(np.concatenate(parts).astype(np.float32))  # noqa: E731
    return ArmCorrespondences(as_tensor(pixels_i), as_tensor(pixels_j), as_tensor(rotations), as_tensor(baselines), pairs)


@pytest.mark.parametrize("translate", [True, False])
def test_residuals_vanish_through_the_true_camera_and_grow_with_focal_error(translate):
    lens = calibration()
    corr = projected_correspondences(lens, translate=translate)
    K = lens.K
    true_camera = CameraModel(WIDTH, HEIGHT, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2]).double()
    residuals, usable = epipolar_residuals(true_camera, corr)
    assert usable.float().mean() > 0.9
    assert residuals[usable].abs().max() < 1e-5  # float32 pixels: about 1e-3 px
    wrong = CameraModel(WIDTH, HEIGHT, fx=1.05 * K[0, 0], fy=1.05 * K[1, 1], cx=K[0, 2], cy=K[1, 2]).double()
    wrong_residuals, wrong_usable = epipolar_residuals(wrong, corr)
    # a 5 % focal error moves points by ~0.05 f tan(8 deg) ~ 1 px: a residual of ~1 / f rad
    assert wrong_residuals[wrong_usable].abs().median() > 0.1 / FOCAL
    assert float(epipolar_loss(wrong, corr).detach()) > 10 * float(epipolar_loss(true_camera, corr).detach())


def test_fit_recovers_focal_and_barrel_distortion_only_with_the_centred_correction():
    """From f = width and a centred pinhole, the camera alone fitted to OpenCV-projected points of a
    barrel lens gets its focal within 1 % and cuts dr ten-fold; with the MLP's raw output the
    distortion absorbs part of the focal (a linear correction is a focal change)."""
    torch.manual_seed(0)
    lens = calibration(BARREL)
    corr = projected_correspondences(lens, pairs=8, points=200)
    results = {}
    for form in ("centred", "raw"):
        camera = CameraModel(WIDTH, HEIGHT, distortion_form=form)
        initial = calibration_errors(camera, lens)
        camera.set_stage("focal")
        calibrate_from_arm_poses(camera, corr, steps=200, lr=1e-2)
        camera.set_stage("full")
        losses = calibrate_from_arm_poses(camera, corr, steps=800, lr=1e-2)
        assert losses[-1] < 0.5 * losses[0]
        results[form] = calibration_errors(camera, lens)
    assert results["centred"]["focal_error_percent"] < 1.0, results
    assert results["centred"]["dr"] < 0.1 * initial["dr"], (initial["dr"], results)
    assert results["raw"]["focal_error_percent"] > 3 * results["centred"]["focal_error_percent"], results


@pytest.fixture(scope="module")
def rendered():
    lens = calibration(BARREL)
    return lens, render_sequence(lens, 24, seed=3, labelled_fraction=0.5, angular_speed=40.0)


def test_tracked_correspondences_agree_with_the_true_camera(rendered):
    lens, sequence = rendered
    corr = arm_correspondences(sequence.images, sequence.arm_poses, max_gap=4)
    assert corr is not None and len(corr) > 200 and corr.pairs > 5
    labelled = set(np.flatnonzero(sequence.labelled))
    assert labelled, "the rendered sequence has arm poses"
    truth = CameraModel.from_calibration(lens).float()
    start = CameraModel(WIDTH, HEIGHT)
    true_residuals, usable = epipolar_residuals(truth, corr)
    start_residuals, _ = epipolar_residuals(start, corr)
    # tracking error well under a pixel through the true camera; several pixels through f = width
    assert true_residuals[usable].abs().median() * FOCAL < 0.5
    assert start_residuals[usable].abs().median() > 3 * true_residuals[usable].abs().median()


def test_no_correspondences_without_two_nearby_arm_poses(rendered):
    _, sequence = rendered
    poses = np.full_like(sequence.arm_poses, np.nan)
    assert arm_correspondences(sequence.images, poses) is None
    poses[[0, 20]] = sequence.ground_truth[[0, 20]]  # two poses, 20 frames apart
    assert arm_correspondences(sequence.images, poses, max_gap=8) is None


def test_correspondences_follow_the_camera_resolution(rendered):
    """Tracked on the bag's frames, the points are handed to a camera of another size in its own pixels."""
    _, sequence = rendered
    settings = {"weight": 1.0, "max_gap": 4, "max_points": 500}
    same, = sequence_correspondences([sequence], [CameraModel(WIDTH, HEIGHT)], settings, torch.device("cpu"))
    double, = sequence_correspondences([sequence], [CameraModel(2 * WIDTH, 2 * HEIGHT)], settings, torch.device("cpu"))
    assert torch.allclose(double.pixels_i, 2 * same.pixels_i + 0.5)
    assert sequence_correspondences([sequence], [CameraModel(WIDTH, HEIGHT)], {**settings, "weight": 0.0}, "cpu") is None
    # the point budget is shared by the sequences with arm poses (a step costs the same with many cameras)
    unposed = dataclasses.replace(sequence, arm_poses=np.full_like(sequence.arm_poses, np.nan))
    first, second, third = sequence_correspondences([sequence, sequence, unposed], [CameraModel(WIDTH, HEIGHT)] * 3,
                                                    settings, torch.device("cpu"))
    assert len(same) == 500 and len(first) == len(second) == 250 and third is None


def test_training_with_the_epipolar_term_moves_the_focal_without_labelled_batches(rendered, tmp_path):
    """With every batch unlabelled (the camera takes no photometric step), the arm-pose term alone
    steps the camera and brings the focal towards the truth; it is logged on its own."""
    lens, sequence = rendered
    torch.set_num_threads(1)
    config = dict(steps=60, image_size=[32, 24], batch_size=2, gap_range=[1, 2], labelled_every=1000, rays_per_image=64,
                  curriculum={"fixed": 10, "focal": 1000}, log_every=10, checkpoint_every=1000,
                  model=dict(encoder_channels=[8, 8, 16, 16, 16, 16, 16], latent_dim=16, scene_width=16, pose_width=16,
                             hyper_width=16, hyper_depth=2, hyper_rank=4, lfn_width=16, lfn_layers=3, lfn_frequencies=2),
                  learning_rates={"encoder": 1e-3, "hypernetwork": 1e-3, "distortion": 1e-3, "intrinsics": 1e-2},
                  epipolar={"weight": 1.0, "max_gap": 4, "max_points": 2000})
    result = train(config, [sequence], device="cpu", out_dir=tmp_path)
    fx, fy, _, _ = (float(v.detach()) for v in result.cameras[0].intrinsics())
    start_error = WIDTH - FOCAL  # f = width at the start
    assert abs((fx + fy) / 2 - FOCAL) < 0.5 * start_error, (fx, fy)
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "epipolar" in header
    assert result.history[0]["epipolar"] == 0.0 and result.history[-1]["epipolar"] > 0  # off in the fixed stage


def test_long_bags_track_at_most_max_pairs_and_degenerate_points_give_a_zero_loss(rendered):
    _, sequence = rendered
    few = arm_correspondences(sequence.images, sequence.ground_truth, max_gap=8, max_pairs=5)
    assert few is not None and few.pairs <= 5
    # every point on the baseline (at the epipole): no constraint, a finite zero loss with a gradient path
    corr = ArmCorrespondences(torch.tensor([[79.5, 59.5]] * 3), torch.tensor([[79.5, 59.5]] * 3),
                              torch.eye(3).expand(3, 3, 3), torch.tensor([[0.0, 0.0, 1.0]] * 3), 1)
    camera = CameraModel(WIDTH, HEIGHT)
    camera.set_stage("focal")
    loss = epipolar_loss(camera, corr)
    assert float(loss.detach()) == 0.0
    loss.backward()
    assert torch.isfinite(camera.log_fx_rel.grad)
