"""Static mountings from a bag's ``/tf_static`` (a robot's URDF, as robot_state_publisher latches it), as
the odometry node takes them from TF: ``nocal odometry --ground-frame`` (REP 120's base_footprint: the
camera's height and the ground's normal, so the scale comes from the ground plane) and ``--base-frame``
(the base's odometry through the camera's mounting). Real bags, written and read by rosbags."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from nocal_ros.cli import build_parser, main
from nocal_ros.data.bags import BagWriter, camera_mounting, camera_mountings
from nocal_ros.data.synthetic import render_sequence
from nocal_ros.errors import BagError
from nocal_ros.geometry import invert_transform, make_transform, so3_exp
from nocal_ros.lens import CameraCalibration

CAMERA = CameraCalibration(160, 120, np.array([[118.0, 0, 81.0], [0, 117.0, 58.5], [0, 0, 1]]),
                           np.array([-0.12, 0.03, 0.0005, -0.0003, 0.0]), "plumb_bob", "test")
FOOTPRINT_TO_BASE = make_transform(np.eye(3), np.array([0.05, 0.0, 0.3]))


def write_robot_bag(path, sequence, T_base_cam: np.ndarray, edges=True):
    """The rendered frames (camera_optical), their truth, and a URDF's static TF: base_footprint ->
    base_link -> camera_optical (only base_link -> camera_optical without ``edges``)."""
    stamps = np.asarray(sequence.stamps_ns, dtype=np.int64)
    with BagWriter(path) as writer:
        static = [("base_link", "camera_optical", T_base_cam)]
        if edges:
            static.append(("base_footprint", "base_link", FOOTPRINT_TO_BASE))
        writer.write_tf("/tf_static", int(stamps[0]), static)
        for index, stamp in enumerate(stamps.tolist()):
            writer.write_image("/camera/image_raw", stamp, "camera_optical", sequence.images[index])
            writer.write_pose("/ground_truth/pose", stamp, "world", sequence.ground_truth[index])
    return path


@pytest.fixture(scope="module")
def rendered():
    return render_sequence(CAMERA, 80, seed=7, split="test")


def mounting_of(sequence) -> np.ndarray:
    """The camera in base_link: the first frame's orientation in the z-up world, at the mean height over
    the floor (z = 0) less base_link's 0.3 m (the rendered arm moves it 0.1 m about that)."""
    height = float(sequence.ground_truth[:, 2, 3].mean())
    return make_transform(sequence.ground_truth[0][:3, :3], np.array([-0.05, 0.0, height - 0.3]))


def test_the_mounting_is_composed_through_the_urdfs_frames_and_refused_where_unconnected(tmp_path):
    sequence = render_sequence(CAMERA, 2, seed=1, split="test")
    T_base_cam = make_transform(so3_exp(np.array([-1.2, 0.1, -1.5])), np.array([0.1, 0.0, 0.8]))
    bag = write_robot_bag(tmp_path / "robot.mcap", sequence, T_base_cam)
    T, frame = camera_mounting(bag, "base_footprint", "/camera/image_raw")
    assert frame == "camera_optical"
    np.testing.assert_allclose(T, FOOTPRINT_TO_BASE @ T_base_cam, atol=1e-12)
    T, _ = camera_mounting(bag, "camera_optical", "/camera/image_raw")
    np.testing.assert_allclose(T, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(camera_mounting(bag, "base_link", "/camera/image_raw")[0], T_base_cam, atol=1e-12)
    lone = write_robot_bag(tmp_path / "lone.mcap", sequence, T_base_cam, edges=False)
    with pytest.raises(BagError, match="does not connect base_footprint.*base_link->camera_optical"):
        camera_mounting(lone, "base_footprint", "/camera/image_raw")


def test_both_mountings_come_from_one_read_of_the_bag(tmp_path, monkeypatch):
    """``--base-frame`` and ``--ground-frame`` together: the bag's first image and /tf_static are read once,
    and each mounting is what a read of its own gives."""
    from nocal_ros.commands import odometry
    from nocal_ros.data import bags

    sequence = render_sequence(CAMERA, 2, seed=1, split="test")
    T_base_cam = make_transform(so3_exp(np.array([-1.2, 0.1, -1.5])), np.array([0.1, 0.0, 0.8]))
    bag = write_robot_bag(tmp_path / "robot.mcap", sequence, T_base_cam)
    both = camera_mountings(bag, ["base_link", "base_footprint", "nowhere"], "/camera/image_raw")
    assert both.camera_frame == "camera_optical" and both.poses["nowhere"] is None
    for parent in ("base_link", "base_footprint"):
        np.testing.assert_array_equal(both.poses[parent], camera_mounting(bag, parent, "/camera/image_raw")[0])
    opened = []
    real_open = bags._open_bag
    monkeypatch.setattr(bags, "_open_bag", lambda path: opened.append(path) or real_open(path))
    args = build_parser("odometry").parse_args(["odometry", str(bag), "--out", str(tmp_path / "out"),
                                                "--base-frame", "base_link", "--ground-frame", "base_footprint"])
    T_base, T_ground = odometry._mountings(args)
    assert len(opened) == 1
    np.testing.assert_array_equal(T_base, both.poses["base_link"])
    np.testing.assert_array_equal(T_ground, both.poses["base_footprint"])


def test_a_replay_with_a_ground_frame_is_metric_through_the_ground_plane(rendered, tmp_path):
    """The camera's height from the bag's URDF: the trajectory is metric without an arm pose or a height
    typed in (measured: 75 of 80 published frames scaled from the ground; the final trajectory's APE
    SE(3) 0.0057 m, Sim(3) scale 1.026, where the pose head's scale is x2.5 on this camera, test_vo)."""
    bag = write_robot_bag(tmp_path / "robot.mcap", rendered, mounting_of(rendered))
    out = tmp_path / "out"
    assert main(["odometry", str(bag), "--out", str(out), "--threads", "1", "--no-progress", "--arm-topic", "",
                 "--ground-frame", "base_footprint"]) == 0
    report = json.loads((out / "report.json").read_text())
    print({k: report[k] for k in ("scale_source",)}, report["final_trajectory"]["scale_source"],
          report["final_trajectory"]["ape_se3"]["rmse"], report["final_trajectory"]["ape_sim3"]["scale"])
    assert report["camera_height_m"] == pytest.approx(float(rendered.ground_truth[:, 2, 3].mean()), abs=1e-9)
    assert report["final_trajectory"]["scale_source"] == {"ground": 1}
    assert report["scale_source"].get("ground", 0) > 40
    assert report["final_trajectory"]["ape_se3"]["rmse"] < 0.015
    assert abs(report["final_trajectory"]["ape_sim3"]["scale"] - 1.0) < 0.05


@pytest.mark.parametrize("extra, message", [
    (["--ground-frame", "base_footprint", "--camera-height", "1.2"], "give one of"),
    (["--ground-frame", "nowhere"], "--ground-frame: .*does not connect nowhere"),
], ids=["with --camera-height", "no such frame"])
def test_a_ground_frame_the_bag_cannot_give_is_one_line(tmp_path, capsys, extra, message):
    sequence = render_sequence(CAMERA, 2, seed=1, split="test")
    bag = write_robot_bag(tmp_path / "robot.mcap", sequence, invert_transform(FOOTPRINT_TO_BASE))
    out = tmp_path / "out"
    code = main(["odometry", str(bag), "--out", str(out), "--threads", "1", "--no-progress", *extra])
    err = capsys.readouterr().err
    assert code == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    assert re.search(message, lines[0]), lines[0]
    assert not out.exists() or not any(out.iterdir())


def test_a_base_frame_takes_its_mounting_from_the_bags_tf_static_as_the_node_does_from_tf(tmp_path, caplog):
    """``--base-frame base_link`` on a bag whose URDF gives base_link -> camera_optical publishes the base's
    odometry through that mounting, as ``--base-to-camera`` with the same numbers does; a base frame the
    bag does not connect keeps the camera as the base, with a warning."""
    from nocal_ros.geometry import matrix_to_quaternion

    sequence = render_sequence(CAMERA, 6, seed=2, split="test")
    T_base_cam = make_transform(so3_exp(np.array([-1.2, 0.1, -1.5])), np.array([0.1, 0.0, 0.8]))
    bag = write_robot_bag(tmp_path / "robot.mcap", sequence, T_base_cam)
    numbers = [str(v) for v in (*T_base_cam[:3, 3], *matrix_to_quaternion(T_base_cam[:3, :3]))]
    runs = {"tf_static": ["--base-frame", "base_link"], "typed": ["--base-frame", "base_link", "--base-to-camera", *numbers],
            "camera": [], "unconnected": ["--base-frame", "nowhere"]}
    trajectories = {}
    for name, extra in runs.items():
        out = tmp_path / name
        assert main(["odometry", str(bag), "--out", str(out), "--threads", "1", "--no-progress", "--no-final", *extra]) == 0
        trajectories[name] = np.loadtxt(out / "trajectory.tum")
    np.testing.assert_allclose(trajectories["tf_static"], trajectories["typed"], atol=1e-9)
    np.testing.assert_array_equal(trajectories["unconnected"], trajectories["camera"])
    moved = np.linalg.norm(trajectories["camera"][-1, 1:4])
    assert moved > 0 and np.abs(trajectories["tf_static"][:, 1:4] - trajectories["camera"][:, 1:4]).max() > 0.1 * moved
    assert "does not connect nowhere" in caplog.text
