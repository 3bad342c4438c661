"""scripts/compare: COLMAP on a rendered bag scored like nocal odometry, the table of reports, and the other helpers.

The COLMAP test needs the optional pycolmap (``pip install -r requirements-compare.txt``) and skips
without it; the others run everywhere.
"""

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from real_recordings import REAL, needs_real

from nocal_ros import evaluation
from nocal_ros.data.bags import read_camera_info, write_sequence
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.geometry import make_transform, so3_log
from nocal_ros.lens import CameraCalibration

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts" / "compare"
# The held-out camera of the comparison (config/cameras/heldout_640x480.yaml) at 160x120.
CAMERA = CameraCalibration(640, 480, [[455.0, 0, 331.4], [0, 457.3, 231.6], [0, 0, 1]], [-0.19, 0.055, 0.0007, -0.0004, 0.0]).scaled(160, 120)


def load_script(name):
    spec = importlib.util.spec_from_file_location(f"compare_{name}", SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_colmap_on_a_rendered_bag_registers_frames_and_calibrates(tmp_path):
    pytest.importorskip("pycolmap")
    from nocal_ros.data.synthetic import render_sequence

    bag = write_sequence(render_sequence(CAMERA, 30, seed=5, split="test"), tmp_path / "bag")
    out = tmp_path / "colmap"
    run = subprocess.run([sys.executable, str(SCRIPTS / "colmap.py"), str(bag), "--out", str(out), "--threads", "1"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert report["bag_frames"] == 30 and report["events"]["registered"] >= 25
    assert report["events"]["unregistered"] == 30 - report["events"]["registered"]
    # Measured on this bag: focal 0.36 %, RPE 0.095 deg, APE Sim(3) 0.0067 m (COLMAP's prior focal, 1.2 x 160,
    # is 69 % off); the bounds leave a factor of 3-4 for other builds.
    assert report["calibration"]["focal_error_percent"] < 1.5
    assert report["calibration"]["fx_true"] == pytest.approx(CAMERA.fx)
    # The trajectory is scored over the registered frames, scale-corrected, with nocal odometry's code.
    assert report["evaluated_poses"] == report["events"]["registered"] and report["scale_correction"] > 0
    assert report["rpe"]["rotation_deg"]["rmse"] < 0.3 and report["ape_sim3"]["translation_m"]["rmse"] < 0.02
    saved = CameraCalibration.load(out / "calibration.yaml")
    assert (saved.width, saved.height) == (160, 120) and saved.distortion_model == "plumb_bob"
    assert "registered" in run.stdout and "scale" in run.stdout
    table = subprocess.run([sys.executable, str(SCRIPTS / "table.py"), str(out / "report.json")], capture_output=True, text=True)
    assert table.returncode == 0 and f"{report['calibration']['focal_error_percent']:.2f} %" in table.stdout


def test_colmap_script_without_pycolmap_says_how_to_install(tmp_path, monkeypatch, capsys):
    script = load_script("colmap")
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap now raises ImportError
    assert script.main([str(tmp_path / "bag"), "--out", str(tmp_path / "out")]) == 1
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "pip install pycolmap==4.2.1" in error


def test_colmap_script_refuses_bad_input_in_one_line(tmp_path, capsys):
    pytest.importorskip("pycolmap")
    script = load_script("colmap")
    assert script.main([str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 1
    assert "no such bag" in capsys.readouterr().err
    (tmp_path / "corrupt.mcap").write_bytes(b"not a bag at all")
    assert script.main([str(tmp_path / "corrupt.mcap"), "--out", str(tmp_path / "out")]) == 1
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "corrupt.mcap" in error
    assert not [p for p in (tmp_path / "out").iterdir()]  # the frames' workspace is removed
    assert script.main([str(tmp_path / "corrupt.mcap"), "--out", str(tmp_path / "out"), "--camera-model", "FOV"]) == 1
    assert "FOV: no ROS equivalent" in capsys.readouterr().err


def moving_sequence(n=12):
    """Tiny frames with known camera poses: a curve with rotation about y."""
    poses = np.stack([make_transform(
        np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]), np.array([0.03 * i, 0.01 * i**1.5, 0.0]))
        for i, a in enumerate(np.radians(2.0) * np.arange(n))])
    images = np.random.default_rng(0).integers(0, 255, (n, 6, 8, 3), dtype=np.uint8)
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000
    return FrameSequence(images, stamps, np.full((n, 4, 4), np.nan), poses, CameraCalibration.pinhole(8, 6, 7.0))


def test_table_rows_and_the_no_motion_row_from_the_ground_truth(tmp_path, capsys):
    sequence = moving_sequence()
    bag = write_sequence(sequence, tmp_path / "bag")
    truth = sequence.ground_truth
    # A report as nocal odometry writes one (the same evaluation code), with a slightly wrong trajectory.
    estimate = truth.copy()
    estimate[:, :3, 3] *= 0.9
    report = {"bag_frames": 12, "poses": 12, "evaluated_poses": 12, "model": "m", "events": {"two_view_pairs": 11},
              "seconds": 1.5, **evaluation.summary(evaluation.trajectory_errors(sequence.stamps_ns, estimate, truth)),
              "calibration": evaluation.calibration_errors(CameraCalibration.pinhole(8, 6, 7.7), sequence.calibration)}
    (tmp_path / "report.json").write_text(json.dumps(report))
    table = load_script("table")
    assert table.main([f"mine={tmp_path / 'report.json'}", str(tmp_path / "report.json"), "--no-motion", str(bag)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 5 and lines[2].startswith("| mine | 10.00 % |") and lines[3].startswith("| nocal odometry (two-view) |")
    assert f"{report['rpe']['translation_m']['rmse']:.4f} / {report['rpe']['rotation_deg']['rmse']:.3f}" in lines[2]
    # A keyframe VO report is labelled as one, with where its scale came from.
    vo = {**report, "method": "vo", "scale_source": {"none": 2, "arm": 10}}
    assert table.default_label(vo) == "nocal odometry (keyframe VO, arm-pose scale)"
    assert table.default_label({**vo, "scale_source": {"pose_head": 12}}) == "nocal odometry (keyframe VO)"
    # No motion: the RPE is the true step itself; the APE the positions' RMS distance from their centroid.
    steps = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    positions = truth[:, :3, 3]
    spread = np.sqrt(np.mean(np.sum((positions - positions.mean(0)) ** 2, axis=1)))
    assert lines[4].startswith("| no motion") and f"| {np.sqrt(np.mean(steps**2)):.4f} / 2.000 | {spread:.4f} |" in lines[4]
    assert lines[4].endswith("| 12/12 |")
    # REPORT#final: the final trajectory's figures, labelled as such; a report without one is refused.
    final = {**evaluation.summary(evaluation.trajectory_errors(sequence.stamps_ns, truth, truth)), "seconds": 0.25,
             "poses": 12, "calibration": evaluation.calibration_errors(sequence.calibration, sequence.calibration)}
    (tmp_path / "final.json").write_text(json.dumps({**vo, "final_trajectory": final}))
    assert table.main([f"{tmp_path / 'final.json'}#final", f"{tmp_path / 'report.json'}#final"]) == 1
    out, err = capsys.readouterr()
    assert "no final trajectory" in err and len(err.strip().splitlines()) == 1
    assert table.main([f"{tmp_path / 'final.json'}#final"]) == 0
    row = capsys.readouterr().out.strip().splitlines()[2]
    assert row.startswith("| nocal odometry (keyframe VO, arm-pose scale), final | 0.00 % | 0.0000 | 0.0000 / 0.000 |")
    assert "| 0.2 s | 12/12 |" in row


def test_rpe_after_a_frame_reads_exact_stamps_and_scores_only_the_later_pairs(tmp_path, capsys):
    from nocal_ros.commands.odometry import write_tum
    from nocal_ros.geometry import so3_exp

    sequence = moving_sequence()
    bag = write_sequence(sequence, tmp_path / "bag")
    truth = sequence.ground_truth
    # The estimate: the truth at half the scale, with a 1 deg rotation error added to frame 3 only
    # (it spoils pairs 2-3 and 3-4), so the pairs from frame 4 on have no rotation error.
    estimate = truth.copy()
    estimate[:, :3, 3] *= 0.5
    estimate[3, :3, :3] = estimate[3, :3, :3] @ so3_exp(np.radians([1.0, 0.0, 0.0]))
    write_tum(tmp_path / "trajectory.tum", sequence.stamps_ns, estimate)
    from nocal_ros.data.importers.common import read_tum_poses

    rpe_after = load_script("rpe_after")
    stamps, poses = read_tum_poses(tmp_path / "trajectory.tum")  # what the script reads the file with
    assert stamps.tolist() == sequence.stamps_ns.tolist()  # nanoseconds exactly, not through a float
    assert rpe_after.main([str(bag), str(tmp_path / "trajectory.tum"), "--from-frame", "4"]) == 0
    printed = capsys.readouterr().out
    assert "7 pairs from frame 4" in printed and "RPE rotation RMSE 0.000 deg" in printed and "scale 2.000" in printed
    assert rpe_after.main([str(bag), str(tmp_path / "trajectory.tum"), "--from-frame", "3"]) == 0
    # pair 3-4 alone is off by 1 deg: RMSE over 8 pairs 1 / sqrt(8)
    assert "RPE rotation RMSE 0.354 deg" in capsys.readouterr().out


def test_pose_head_lengths_against_a_pose_head_that_measures_twice_the_length(tmp_path, capsys):
    """A pose function that returns twice the true translation for any pair: the ratio is 2 at every
    gap (the closed form), and the command prints one line per bag."""
    import torch

    from nocal_ros.odometry.pose_head import PoseModel

    frames = 12
    poses = np.stack([make_transform(np.eye(3), [0.03 * k, 0.01 * k * k, 0.0]) for k in range(frames)])
    images = np.stack([np.full((24, 32, 3), 10 * k, dtype=np.uint8) for k in range(frames)])
    stamps = np.arange(frames, dtype=np.int64) * 100_000_000
    bag = write_sequence(FrameSequence(images, stamps, np.full_like(poses, np.nan), ground_truth=poses), tmp_path / "bag")

    def twice(image_i, image_j):  # each frame's index is its grey level / 10
        i, j = (int(round(float(image.mean()) * 255 / 10)) for image in (image_i, image_j))
        T = np.linalg.inv(poses[i]) @ poses[j]
        T[:3, 3] *= 2.0
        return torch.as_tensor(T, dtype=torch.float32)[None]

    script = load_script("pose_head_lengths")
    ratios = script.length_ratios(bag, [1, 2, 4], PoseModel(predict_pose=twice, input_size=(32, 24), max_gap=4))
    assert sorted(ratios) == [1, 2, 4] and [len(ratios[g]) for g in (1, 2, 4)] == [frames - 1, frames - 2, frames - 4]
    for gap in (1, 2, 4):
        np.testing.assert_allclose(ratios[gap], 2.0, rtol=1e-5)
    assert script.main([str(bag), "--gaps", "1", "2"]) == 0  # the shipped model
    assert capsys.readouterr().out.startswith("bag: pose head length / true length, median: gap 1: ")


@needs_real("vamr_ex1")
def test_vamr_board_motion_sees_the_hand_move_the_board_and_not_the_camera_alone(capsys):
    """Frames 150 -> 160: the camera moves, board and desk alike; 420 -> 430: a hand moves the board."""
    script = load_script("vamr_board_motion")
    assert script.main([str(REAL / "vamr_ex1"), "--gap", "10", "--frames", "150", "420"]) == 0
    lines = capsys.readouterr().out.splitlines()
    ratios = {line.split(":")[0]: float(line.rsplit("ratio", 1)[1]) for line in lines}
    print(ratios)
    assert set(ratios) == {"150->160", "420->430"}
    assert 0.5 < ratios["150->160"] < 2.0  # measured 1.1
    assert ratios["420->430"] > 4.0  # measured 8.6
    with pytest.raises(SystemExit):
        script.main([str(REAL)])  # no images there: refused


def test_scaled_calibration_writes_the_bags_true_camera_with_its_focal_lengths_scaled(tmp_path, capsys):
    bag = write_sequence(moving_sequence(), tmp_path / "bag")
    truth = read_camera_info(bag, "/ground_truth/camera_info")
    scaled_calibration = load_script("scaled_calibration")
    assert scaled_calibration.main([str(bag), "--focal-scale", "1.1", "--out", str(tmp_path / "wrong.yaml")]) == 0
    wrong = CameraCalibration.load(tmp_path / "wrong.yaml")  # as nocal odometry --calibration reads it
    assert (wrong.fx, wrong.fy) == pytest.approx((1.1 * truth.fx, 1.1 * truth.fy), rel=1e-12)
    assert (wrong.cx, wrong.cy, wrong.width, wrong.height) == (truth.cx, truth.cy, truth.width, truth.height)
    np.testing.assert_array_equal(wrong.D, truth.D)
    assert scaled_calibration.main([str(bag), "--focal-scale", "0", "--out", str(tmp_path / "x.yaml")]) == 2
    assert scaled_calibration.main([str(bag), "--focal-scale", "1.1", "--out", str(tmp_path / "x.yaml"),
                                    "--camera-info-topic", "/nothing"]) == 1
    assert "no camera info topic '/nothing'" in capsys.readouterr().err and not (tmp_path / "x.yaml").exists()


def test_camera_swap_runs_one_estimator_through_both_bags_and_refuses_bags_of_two_sizes(tmp_path, capsys):
    camera_swap = load_script("camera_swap")
    a = write_sequence(moving_sequence(), tmp_path / "a")
    b = write_sequence(moving_sequence(), tmp_path / "b")
    assert camera_swap.main([str(a), str(b), "--black", "2"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("a fx 7.0 -> b fx 7.0 (+0.0 %): focal at the cut") and "maps " in line  # 12 + 2 + 12 frames
    wider = moving_sequence()
    wider = FrameSequence(np.zeros((12, 6, 10, 3), np.uint8), wider.stamps_ns, wider.arm_poses, wider.ground_truth,
                          CameraCalibration.pinhole(10, 6, 7.0))
    c = write_sequence(wider, tmp_path / "c")
    assert camera_swap.main([str(a), str(c)]) == 2
    assert "differ in size (8x6 and 10x6)" in capsys.readouterr().err


def test_dev_replays_replays_a_bag_and_compares_two_replays_pair_by_pair(tmp_path):
    """``dev_replays.py replay`` runs nocal odometry on a bag of the folder; ``compare`` reads both replays'
    reports and trajectories: a copy whose published poses from frame 12 on are turned by 1 deg about the
    world's z axis has, from pair 12 on, the same rotation errors (the turn is common to both poses of each
    pair) but pair 11 gains the degree; the figures of the report itself are passed through."""
    from nocal_ros.commands.odometry import write_tum
    from nocal_ros.data.bags import read_poses
    from nocal_ros.data.importers.common import read_tum_poses
    from nocal_ros.data.synthetic import render_sequence
    from nocal_ros.geometry import so3_exp

    bags = tmp_path / "bags"
    bags.mkdir()
    write_sequence(render_sequence(CAMERA, 24, seed=5, split="test"), bags / "heldout_160")
    script = [sys.executable, str(SCRIPTS / "dev_replays.py")]
    run = subprocess.run([*script, "replay", str(bags), str(tmp_path / "a"), "--bags", "heldout_160", "kitti_clip"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert "heldout_160: done" in run.stdout and "kitti_clip: no bag" in run.stdout
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    trajectory = tmp_path / "b" / "heldout_160" / "trajectory.tum"
    stamps, poses = read_tum_poses(trajectory)
    turned = poses.copy()
    turned[12:] = make_transform(so3_exp(np.array([0.0, 0.0, np.radians(1.0)])), np.zeros(3)) @ poses[12:]
    write_tum(trajectory, stamps, turned)

    dev = load_script("dev_replays")
    truth = read_poses(bags / "heldout_160", "/ground_truth/pose", stamps)
    a = dev.replay_figures(tmp_path / "a" / "heldout_160", bags / "heldout_160", 12)
    b = dev.replay_figures(tmp_path / "b" / "heldout_160", bags / "heldout_160", 12)
    report = json.loads((tmp_path / "a" / "heldout_160" / "report.json").read_text())
    assert a["focal %"] == report["calibration"]["focal_error_percent"]
    assert a["rotation"] == report["rpe"]["rotation_deg"]["rmse"]
    # From pair 12 on, the closed form of each pair's error; pair 11 moved by the degree.
    steps = [(truth[k, :3, :3].T @ truth[k + 1, :3, :3], poses[k, :3, :3].T @ poses[k + 1, :3, :3])
             for k in range(12, len(poses) - 1)]
    expected = [np.degrees(np.linalg.norm(so3_log(true.T @ estimated))) for true, estimated in steps]
    assert a["rotation from 12"] == pytest.approx(np.sqrt(np.mean(np.square(expected))), abs=1e-6)
    assert b["rotation from 12"] == pytest.approx(a["rotation from 12"], abs=1e-4)  # the file's 9 decimals
    whole_a = dev.replay_figures(tmp_path / "a" / "heldout_160", bags / "heldout_160", 0)
    whole_b = dev.replay_figures(tmp_path / "b" / "heldout_160", bags / "heldout_160", 0)
    pair_11 = np.sqrt((len(poses) - 1) * (whole_b["rotation from 0"] ** 2 - whole_a["rotation from 0"] ** 2))
    assert 0.5 < pair_11 < 1.5  # the degree, give or take that pair's own error
    rows = dev.compare_table({"heldout_160": whole_a}, {"heldout_160": whole_b})
    assert rows[-1].split("|")[list(whole_a).index("rotation from 0") + 2].strip() == "0 / 1"
    compared = subprocess.run([*script, "compare", str(tmp_path / "a"), str(tmp_path / "b"), "--bags-from", str(bags),
                               "--from-pair", "12"], capture_output=True, text=True, timeout=120)
    assert compared.returncode == 0 and "| heldout_160 |" in compared.stdout and "| median |" in compared.stdout


def test_dev_replays_runs_the_checkout_it_is_given_even_from_the_repository_root(tmp_path):
    """``replay --checkout`` must run that checkout's nocal_ros, not the repository's: ``python -m`` puts the
    working directory first on ``sys.path``, so run from the repository's root (as CI runs the tests) the
    root's package would win. A stand-in checkout whose ``nocal_ros.cli`` only leaves a mark shows which ran."""
    checkout = tmp_path / "checkout" / "nocal_ros"
    checkout.mkdir(parents=True)
    (checkout / "__init__.py").write_text("")
    (checkout / "cli.py").write_text(
        "import sys\nfrom pathlib import Path\n"
        "out = Path(sys.argv[sys.argv.index('--out') + 1])\nout.mkdir(parents=True)\n"
        "(out / 'ran').write_text(str(Path(__file__).resolve()))\n")
    (tmp_path / "bags" / "heldout_160").mkdir(parents=True)
    run = subprocess.run([sys.executable, str(SCRIPTS / "dev_replays.py"), "replay", str(tmp_path / "bags"),
                          str(tmp_path / "out"), "--checkout", str(tmp_path / "checkout"), "--bags", "heldout_160"],
                         capture_output=True, text=True, timeout=120, cwd=SCRIPTS.parents[1])
    assert run.returncode == 0, run.stdout + run.stderr
    assert (tmp_path / "out" / "heldout_160" / "ran").read_text() == str((checkout / "cli.py").resolve())


def test_startup_steps_groups_the_steps_through_the_guess_and_finds_them_within_their_covariance(tmp_path, capsys):
    """r160_207's camera (the f = width guess 85 % long), 16 frames: the steps tracked through the guess
    on the pose head's scale are more than half a step off, and within their published covariance's
    99 % bound (it knows no direction for them); every step is counted once."""
    from nocal_ros.data.bags import write_sequence as write
    from nocal_ros.data.synthetic import random_calibration, render_sequence

    camera = random_calibration(np.random.default_rng([207, 7]), 160, 120)
    bag = write(render_sequence(camera, 16, 207, split="test"), tmp_path / "r160_207.mcap")
    script = load_script("startup_steps")
    records = script.startup_steps(bag, 16)
    assert [r["frame"] for r in records] == list(range(1, 16))
    through = [r for r in records if r["guess"] and r["scale"] in ("pose_head", "none") and r["motion"] in ("vo", "two_view")]
    assert len(through) >= 5 and any(not r["guess"] for r in records)
    assert np.sqrt(np.mean([r["error_steps"] ** 2 for r in through])) > 0.5
    assert all(r["within_99"] for r in through)
    rows = script.summary(records)
    assert sum(row["steps"] for row in rows) == 15
    assert script.main([str(bag), "--frames", "16"]) == 0
    assert "camera  scale      steps" in capsys.readouterr().out


def test_the_real_time_replay_scores_a_bag_and_says_where_its_scale_came_from(tmp_path):
    """scripts/compare/realtime.py replays a rendered bag at 30 Hz the node's way and prints the frames
    processed and dropped; with a camera height (the rendered floor is the world's z = 0) it also counts the
    frames per scale source, which cover every processed frame, and the APE without a scale correction."""
    import re

    from nocal_ros.data.synthetic import render_sequence

    sequence = render_sequence(CAMERA, 30, seed=5, split="test")
    bag = write_sequence(sequence, tmp_path / "bag")
    height = float(np.mean(sequence.ground_truth[:, 2, 3]))
    run = subprocess.run([sys.executable, str(SCRIPTS / "realtime.py"), str(bag), "--rate", "30",
                          "--camera-height", f"{height:.3f}"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    processed = int(re.search(r"(\d+) of 30 frames processed", run.stdout).group(1))
    sources = re.search(r"scale sources \(frames\): (\{.*\}); APE SE\(3\) ([\d.]+) m", run.stdout)
    assert sources, run.stdout
    counts = {name: int(count) for name, count in re.findall(r"'(\w+)': (\d+)", sources.group(1))}
    assert sum(counts.values()) == processed >= 20
    assert set(counts) <= {"arm", "ground", "pose_head", "none"} and float(sources.group(2)) >= 0
