"""``nocal odometry``: a real bag in, every output written and readable by rosbags, stamps preserved.

The bag holds frames whose pixels carry their index and the true poses of a known trajectory; the
estimator runs with a pose source that answers the true relative pose (see test_odometry.py), so the
whole chain (bag decoding, ordering, integration, message writing, evaluation) must reproduce the
truth: any mix-up of frames, stamps or conventions shows as an error.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from nocal_ros.camera import CameraModel
from nocal_ros.data.bags import BagWriter, camera_info_to_calibration, write_sequence
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.errors import BagError, NocalError
from nocal_ros.geometry import invert_transform, quaternion_to_matrix
from nocal_ros.lens import CameraCalibration
from nocal_ros.odometry import OdometryEstimator, PoseModel

sys.path.insert(0, str(Path(__file__).parent))
from test_odometry import PERIOD_NS, START_NS, TrajectoryPoses, random_trajectory  # noqa: E402

WIDTH, HEIGHT = 80, 60
TRUE_CAMERA = CameraCalibration(
    WIDTH, HEIGHT, np.array([[70.0, 0, 40.5], [0, 68.0, 29.0], [0, 0, 1]]), np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
)


@pytest.fixture(scope="module")
def learnt_camera() -> CameraModel:
    """A camera whose distortion MLP learnt a real lens (a short fit: a residual of a few tenths of a pixel)."""
    return CameraModel.from_calibration(TRUE_CAMERA, iterations=40, samples=(20, 15))


def sequence_bag(path: Path, n: int = 12, drop: tuple[int, ...] = ()) -> tuple[Path, np.ndarray, np.ndarray]:
    T_w_c = random_trajectory(n, seed=11)
    keep = [k for k in range(n) if k not in drop]
    images = np.stack([np.full((HEIGHT, WIDTH, 3), k, np.uint8) for k in keep])
    stamps = START_NS + PERIOD_NS * np.asarray(keep, dtype=np.int64) + 1234  # not on whole periods
    sequence = FrameSequence(
        images=images, stamps_ns=stamps, arm_poses=np.full((len(keep), 4, 4), np.nan),
        ground_truth=T_w_c[keep], calibration=TRUE_CAMERA, name="test",
    )
    return write_sequence(sequence, path), T_w_c, stamps


def make_estimator(T_w_c, camera) -> OdometryEstimator:
    model = PoseModel(predict_pose=TrajectoryPoses(T_w_c), input_size=(32, 24), camera=camera, model_id="truth")
    return OdometryEstimator(model, method="pose_head")


def read_topics(bag: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    messages: dict[str, list] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for connection, stamp, raw in reader.messages():
            messages.setdefault(connection.topic, []).append((stamp, reader.deserialize(raw, connection.msgtype)))
    return messages


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_replay_writes_every_output_readable_by_rosbags(tmp_path, learnt_camera):
    from nocal_ros.commands.odometry import replay_bag

    bag, T_w_c, stamps = sequence_bag(tmp_path / "in", drop=(5,))
    replay = replay_bag(bag, tmp_path / "out", make_estimator(T_w_c, learnt_camera), progress=False)
    out = tmp_path / "out"
    for name in ("odometry", "trajectory.tum", "calibration.yaml"):
        assert (out / name).exists(), name

    topics = read_topics(out / "odometry")
    odom = [msg for _, msg in topics["/odom"]]
    infos = [msg for _, msg in topics["/camera_info"]]
    tfs = [msg for _, msg in topics["/tf"]]
    assert [stamp_ns(m.header) for m in odom] == stamps.tolist()
    assert [stamp_ns(m.header) for m in infos] == stamps.tolist()
    assert [stamp_ns(m.transforms[0].header) for m in tfs] == stamps.tolist()
    assert {m.header.frame_id for m in odom} == {"odom"} and {m.child_frame_id for m in odom} == {"camera_optical"}
    assert {m.header.frame_id for m in infos} == {"camera_optical"}
    assert {(t.transforms[0].header.frame_id, t.transforms[0].child_frame_id) for t in tfs} == {("odom", "camera_optical")}
    # map -> odom beside it, at the same stamp: the identity for the pose head alone (no map to correct odom by)
    assert {(t.transforms[1].header.frame_id, t.transforms[1].child_frame_id) for t in tfs} == {("map", "odom")}
    assert all(stamp_ns(t.transforms[1].header) == stamp_ns(t.transforms[0].header) for t in tfs)
    assert all(t.transforms[1].transform.rotation.w == 1.0 and t.transforms[1].transform.translation.x == 0.0 for t in tfs)

    # Poses: the true trajectory from the first frame, through the dropped frame (gap of 2).
    kept = [k for k in range(12) if k != 5]
    for msg, k in zip(odom, kept):
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        T = np.eye(4)
        T[:3, :3] = quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w]))
        T[:3, 3] = [p.x, p.y, p.z]
        np.testing.assert_allclose(T, invert_transform(T_w_c[0]) @ T_w_c[k], atol=1e-4)
        covariance = np.asarray(msg.pose.covariance).reshape(6, 6)
        assert np.allclose(covariance, covariance.T)
    assert replay.counters["bridged_gaps"] == 1

    # TUM file: one line per pose, same stamps, same poses.
    rows = np.loadtxt(out / "trajectory.tum")
    assert rows.shape == (11, 8)
    np.testing.assert_allclose(rows[:, 0], stamps * 1e-9, rtol=0, atol=1e-9 * 1e9 * 1e-9 + 1e-6)
    assert (out / "trajectory.tum").read_text().split()[0] == f"{stamps[0] // 10**9}.{stamps[0] % 10**9:09d}"
    np.testing.assert_allclose(rows[:, 1:4], np.stack([(invert_transform(T_w_c[0]) @ T_w_c[k])[:3, 3] for k in kept]), atol=1e-4)

    # calibration.yaml is the camera_calibration format, same camera as the CameraInfo messages.
    saved = CameraCalibration.load(out / "calibration.yaml")
    from_msg = camera_info_to_calibration(infos[0])
    np.testing.assert_allclose(saved.K, from_msg.K)
    np.testing.assert_allclose(saved.D, from_msg.D)
    assert yaml.safe_load((out / "calibration.yaml").read_text())["distortion_model"] == infos[0].distortion_model
    assert np.asarray(infos[0].p).reshape(3, 4)[:, :3].tolist() == np.asarray(infos[0].k).reshape(3, 3).tolist()

    # The bag has ground truth: report and plot. The estimate is the truth, so every error is ~0
    # (a frame or stamp mismatch anywhere would show as centimetres here).
    assert (out / "trajectory.png").stat().st_size > 10_000
    report = json.loads((out / "report.json").read_text())
    assert report == replay.report and report["evaluated_poses"] == 11
    assert report["rpe"]["translation_m"]["rmse"] < 1e-4 and report["rpe"]["rotation_deg"]["rmse"] < 1e-2
    assert report["ape_se3"]["translation_m"]["rmse"] < 1e-4
    assert abs(report["ape_sim3"]["scale"] - 1) < 1e-3
    # The first frame starts the odometry: 9 of the 10 pairs are between tracked frames.
    assert report["tracking"] == {"initialising": 1, "ok": 10, "lost": 0}
    assert (report["rpe_tracked"]["pairs"], report["rpe_tracked"]["of_pairs"]) == (9, 10)
    assert report["rpe_tracked"]["rotation_deg"]["max"] < 1e-2
    # Every step's rotation and translation error against its published covariance: the pose head's own
    # spread, and no error.
    for part in ("rotation", "translation"):
        assert report[f"{part}_consistency"]["pairs"] == 10 and report[f"{part}_consistency"]["mean_nees"] < 1e-3
    assert report["scale_source"] == {"pose_head": 11} and report["arm_poses"] == 0
    calibration = report["calibration"]
    assert calibration["focal_error_px"] < 1e-6  # the learnt camera was built from the true K
    assert 0 < calibration["dr"] < 0.01 and calibration["fit_residual_px"] == replay.calibration_residual_px


def test_camera_info_reprojects_like_the_learnt_camera_within_the_fit_residual(tmp_path, learnt_camera):
    from nocal_ros.commands.odometry import replay_bag

    bag, T_w_c, _ = sequence_bag(tmp_path / "in", n=3)
    replay = replay_bag(bag, tmp_path / "out", make_estimator(T_w_c, learnt_camera), progress=False, gt_topic=None)
    info = read_topics(tmp_path / "out" / "odometry")["/camera_info"][0][1]
    K = np.asarray(info.k).reshape(3, 3)
    D = np.asarray(info.d)

    # Every pixel's learnt ray, projected by OpenCV through the published K and D, lands back on it.
    u, v = np.meshgrid(np.linspace(0, WIDTH - 1, 29), np.linspace(0, HEIGHT - 1, 23))
    pixels = np.stack((u.ravel(), v.ravel()), -1)
    with torch.no_grad():
        xy = learnt_camera.undistorted_normalised(torch.from_numpy(pixels[:, 0]).float(), torch.from_numpy(pixels[:, 1]).float()).double().numpy()
    rays = np.concatenate((xy, np.ones((len(xy), 1))), 1)
    projected, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, D)
    rms = np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - pixels) ** 2, -1)))
    assert replay.calibration_residual_px is not None
    assert rms <= 1.2 * replay.calibration_residual_px + 0.01
    # ...and the lens matters: dropping D reprojects far worse, so the check above has teeth.
    pinhole, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.zeros(5))
    assert np.sqrt(np.mean(np.sum((pinhole.reshape(-1, 2) - pixels) ** 2, -1))) > 5 * rms


def test_existing_outputs_are_kept_unless_overwrite(tmp_path, learnt_camera):
    from nocal_ros.commands.odometry import replay_bag

    bag, T_w_c, _ = sequence_bag(tmp_path / "in", n=3)
    out = tmp_path / "out"
    replay_bag(bag, out, make_estimator(T_w_c, learnt_camera), progress=False, gt_topic=None)
    before = (out / "trajectory.tum").read_bytes()
    with pytest.raises(NocalError, match="--overwrite"):
        replay_bag(bag, out, make_estimator(T_w_c, learnt_camera), progress=False, gt_topic=None)
    assert (out / "trajectory.tum").read_bytes() == before
    replay_bag(bag, out, make_estimator(T_w_c, learnt_camera), progress=False, gt_topic=None, overwrite=True)


def test_a_bag_that_fails_half_way_leaves_no_partial_output(tmp_path, learnt_camera):
    from nocal_ros.commands.odometry import replay_bag

    bag = tmp_path / "in"
    T_w_c = random_trajectory(4)
    with BagWriter(bag) as writer:
        for k in range(3):
            writer.write_image("/camera/image_raw", START_NS + k * PERIOD_NS, "cam", np.full((HEIGHT, WIDTH, 3), k, np.uint8))
        writer.write_image("/camera/image_raw", START_NS + 3 * PERIOD_NS, "cam", np.zeros((HEIGHT // 2, WIDTH, 3), np.uint8))
    with pytest.raises(BagError, match="size changes"):
        replay_bag(bag, tmp_path / "out", make_estimator(T_w_c, learnt_camera), progress=False)
    assert not (tmp_path / "out" / "odometry").exists()
    assert not any(p.name.startswith(".odometry") for p in (tmp_path / "out").iterdir())


SMALL_MODEL = {"encoder_channels": [8] * 7, "latent_dim": 16, "scene_width": 16, "pose_width": 16,
               "hyper_width": 16, "hyper_rank": 4, "lfn_width": 16}


def test_cli_runs_a_saved_checkpoint_end_to_end(tmp_path, capsys):
    from nocal_ros.checkpoint import save_checkpoint
    from nocal_ros.cli import main
    from nocal_ros.model import NOCaL

    bag, _, stamps = sequence_bag(tmp_path / "in", n=6)
    checkpoint = save_checkpoint(tmp_path / "model.safetensors", NOCaL(SMALL_MODEL), [CameraModel(WIDTH, HEIGHT)],
                                 metadata={"training_resolution": [40, 30]})
    assert main(["odometry", str(bag), "--out", str(tmp_path / "out"), "--model", str(checkpoint), "--method", "pose_head",
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "model.safetensors@" in printed and "6 frames -> 6 poses" in printed and "RPE" in printed
    rows = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    assert rows.shape == (6, 8) and np.isfinite(rows).all()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["calibration"]["distortion_model"] == "plumb_bob"  # an untrained camera is a pinhole
    assert report["calibration"]["focal_error_px"] == pytest.approx(abs(WIDTH - 69.0), abs=1.0)


def test_cli_reports_a_missing_model_in_one_line(tmp_path, capsys):
    from nocal_ros.cli import main

    bag, _, _ = sequence_bag(tmp_path / "in", n=2)
    model = tmp_path / "missing.safetensors"
    assert main(["odometry", str(bag), "--out", str(tmp_path / "out"), "--model", str(model), "--no-progress"]) == 1
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and str(model) in error


def test_demo_renders_an_unseen_camera_and_reports_errors(tmp_path, capsys):
    from nocal_ros.checkpoint import save_checkpoint
    from nocal_ros.cli import main
    from nocal_ros.model import NOCaL

    checkpoint = save_checkpoint(tmp_path / "model.safetensors", NOCaL(SMALL_MODEL), [CameraModel(WIDTH, HEIGHT)],
                                 metadata={"training_resolution": [40, 30]})
    out = tmp_path / "demo"
    arguments = ["demo", "--out", str(out), "--model", str(checkpoint), "--frames", "5", "--size", "64x48", "--no-progress"]
    assert main(arguments) == 0
    printed = capsys.readouterr().out
    assert "RPE" in printed and "reporting no motion at all" in printed and str(out / "result") in printed
    report = json.loads((out / "result" / "report.json").read_text())
    assert report["evaluated_poses"] == 5 and report["calibration"]["fx_true"] == pytest.approx(0.83 * 64)
    # The online camera's story: the start camera first (the model's, f = width here), then each keyframe's.
    history = report["calibration_history"]
    assert history[0]["frame"] == 0 and history[0]["state"] == "prior" and history[0]["fx"] == pytest.approx(64)
    assert history[0]["focal_error_percent"] > 15  # f = width against the demo camera's 0.83 width
    assert "online calibration (true fx 53.1" in printed and "start camera -> end of replay" in printed
    assert main(arguments) == 0  # a second run replaces the demo's own directory

    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    assert main(["demo", "--out", str(foreign), "--model", str(checkpoint), "--frames", "3", "--no-progress"]) == 1
    assert (foreign / "notes.txt").read_text() == "keep me"


def test_a_camera_of_another_aspect_ratio_gets_a_camera_info_of_its_own_shape(tmp_path, learnt_camera, caplog):
    """The learnt camera (4:3) does not apply to 2:1 frames: the online camera starts from f = width at
    the frames' own size, and every frame still gets a CameraInfo of that size."""
    from nocal_ros.commands.odometry import replay_bag
    from nocal_ros.lens import CameraCalibration

    bag = tmp_path / "in"
    T_w_c = random_trajectory(3)
    with BagWriter(bag) as writer:
        for k in range(3):  # 80x40 (2:1) while the learnt camera is 80x60 (4:3)
            writer.write_image("/camera/image_raw", START_NS + k * PERIOD_NS, "cam", np.full((40, 80, 3), k, np.uint8))
    replay = replay_bag(bag, tmp_path / "out", make_estimator(T_w_c, learnt_camera), progress=False)
    assert len(replay.stamps_ns) == 3 and "another shape" in caplog.text
    saved = CameraCalibration.load(tmp_path / "out" / "calibration.yaml")
    assert (saved.width, saved.height) == (80, 40) and saved.fx == pytest.approx(80.0)
    infos = read_topics(tmp_path / "out" / "odometry")["/camera_info"]
    assert len(infos) == 3 and all((m.width, m.height) == (80, 40) for _, m in infos)

@pytest.mark.parametrize(("size", "mono"), [((1241, 376), True), ((1280, 720), False)])
def test_camera_info_of_a_kitti_and_a_16_9_camera_reprojects_like_their_learnt_camera(tmp_path, size, mono):
    """Issue 13: a camera learnt at 1241x376 (mono8 frames) or 1280x720 publishes, from frames of that
    shape, a CameraInfo of that shape whose K and D reproject its learnt rays within the fit residual."""
    from nocal_ros.commands.odometry import replay_bag

    width, height = size
    f = 0.58 * width
    truth = CameraCalibration(width, height, np.array([[f, 0, 0.51 * width], [0, 1.01 * f, 0.48 * height], [0, 0, 1]]),
                              np.array([-0.18, 0.04, 0.0008, -0.0005, 0.0]))
    camera = CameraModel.from_calibration(truth, iterations=40, samples=(24, 12))
    T_w_c = random_trajectory(3)
    bag = tmp_path / "in"
    with BagWriter(bag) as writer:
        for k in range(3):
            image = np.full((height, width) if mono else (height, width, 3), k, np.uint8)  # the fake pose head reads k
            writer.write_image("/camera/image_raw", START_NS + k * PERIOD_NS, "cam", image)
    replay = replay_bag(bag, tmp_path / "out", make_estimator(T_w_c, camera), progress=False, gt_topic=None)
    info = read_topics(tmp_path / "out" / "odometry")["/camera_info"][0][1]
    assert (info.width, info.height) == size
    K, D = np.asarray(info.k).reshape(3, 3), np.asarray(info.d)
    u, v = np.meshgrid(np.linspace(0, width - 1, 31), np.linspace(0, height - 1, 17))
    pixels = np.stack((u.ravel(), v.ravel()), -1)
    with torch.no_grad():
        xy = camera.undistorted_normalised(torch.from_numpy(pixels[:, 0]).float(), torch.from_numpy(pixels[:, 1]).float()).double().numpy()
    rays = np.concatenate((xy, np.ones((len(xy), 1))), 1)
    projected, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, D)
    rms = np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - pixels) ** 2, -1)))
    assert replay.calibration_residual_px is not None and rms <= 1.2 * replay.calibration_residual_px + 0.01
    # The learnt camera itself, not the f = width prior: K is within a few percent of the true one.
    assert K[0, 0] == pytest.approx(truth.fx, rel=0.05) and K[1, 1] == pytest.approx(truth.fy, rel=0.05)


def test_the_calibration_history_matches_the_full_camera_errors_on_its_coarser_grid():
    """The history's dr is taken on every k-th pixel (a 752x480 bag's history cost 104 s on every pixel)."""
    from nocal_ros import evaluation
    from nocal_ros.commands.odometry import _camera_history_errors

    truth = CameraCalibration(752, 480, np.array([[420.5, 0, 355.2], [0, 420.6, 250.3], [0, 0, 1]]),
                              np.array([-0.29, 0.08, 0.0, 0.0, 0.0]))
    estimate = CameraCalibration(752, 480, np.array([[431.0, 0, 362.0], [0, 428.0, 246.0], [0, 0, 1]]),
                                 np.array([-0.25, 0.05, 0.0, 0.0, 0.0]))
    entry = {"frame": 7, "stamp_ns": 123, "state": "converging", "fx": estimate.fx, "fy": estimate.fy,
             "cx": estimate.cx, "cy": estimate.cy, "D": list(estimate.D)}
    (row,) = _camera_history_errors([entry], estimate, truth)
    full = evaluation.calibration_errors(estimate, truth)
    assert row["focal_error_percent"] == pytest.approx(full["focal_error_percent"], rel=1e-9)
    assert row["dr"] == pytest.approx(full["dr"], rel=0.02) and full["dr"] > 0.01
    assert (row["frame"], row["stamp_ns"], row["state"]) == (7, 123, "converging")
