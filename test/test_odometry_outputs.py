"""``nocal odometry`` and ``nocal eval`` on recordings that once broke them: a still camera with ground
truth, a full disk, ``--overwrite`` onto a bag without ground truth, header stamps that jump back, a
corrupt ``metadata.yaml``. Real bags written with rosbags, the shipped model, the real command line."""

from __future__ import annotations

import errno
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nocal_ros.cli import main
from nocal_ros.data.bags import BagWriter, write_sequence
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.lens import CameraCalibration

CAMERA = CameraCalibration.pinhole(64, 48, 50.0)
START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000


def tree(directory: Path) -> dict[str, str]:
    """Every entry under ``directory`` (hidden ones too) with its content's SHA-256."""
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(directory.rglob("*"))}


def odometry(bag: Path, out: Path, *extra: str) -> int:
    return main(["odometry", str(bag), "--out", str(out), "--device", "cpu", "--threads", "1", "--no-progress", *extra])


@pytest.fixture(scope="module")
def moving_bag(tmp_path_factory):
    from nocal_ros.data.synthetic import render_sequence

    return write_sequence(render_sequence(CAMERA, 6, seed=2, split="test"), tmp_path_factory.mktemp("moving") / "moving.mcap")


@pytest.fixture(scope="module")
def still_bag(tmp_path_factory):
    """A camera that does not move: six copies of one rendered frame, one true pose, the true camera."""
    from nocal_ros.data.synthetic import render_sequence

    rendered = render_sequence(CAMERA, 1, seed=2, split="test")
    sequence = FrameSequence(
        images=np.repeat(rendered.images, 6, axis=0), stamps_ns=START_NS + PERIOD_NS * np.arange(6),
        arm_poses=np.full((6, 4, 4), np.nan), ground_truth=np.repeat(rendered.ground_truth, 6, axis=0),
        calibration=CAMERA, name="still",
    )
    return write_sequence(sequence, tmp_path_factory.mktemp("still") / "still.mcap")


# ---- a still recording with ground truth -------------------------------------------------------------


def test_odometry_on_a_still_recording_reports_the_alignment_undefined(still_bag, tmp_path, capsys):
    out = tmp_path / "out"
    assert odometry(still_bag, out) == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    for key in ("ape_se3", "ape_sim3"):
        assert "alignment undefined" in report[key]["undefined"] and "Degenerate covariance rank" in report[key]["undefined"]
        assert "rmse" not in report[key]
    assert report["rpe"]["translation_m"]["count"] == 5  # the pair errors are still there
    assert (out / "trajectory.png").stat().st_size > 0 and (out / "trajectory.tum").is_file()
    assert "alignment undefined" in capsys.readouterr().out


def test_eval_on_a_still_recording_reports_the_alignment_undefined(still_bag, tmp_path, capsys):
    assert main(["eval", "--bag", str(still_bag), "--json", str(tmp_path / "r.json"),
                 "--plot", str(tmp_path / "p.png")]) == 0, capsys.readouterr().err
    report = json.loads((tmp_path / "r.json").read_text())
    assert "alignment undefined" in report["ape_sim3"]["undefined"] and report["rpe"]["rotation_deg"]["count"] == 5
    assert (tmp_path / "p.png").stat().st_size > 0


# ---- a full disk ----------------------------------------------------------------------------------


def test_full_disk_while_writing_the_trajectory_keeps_earlier_results(moving_bag, tmp_path, monkeypatch, capsys):
    """ENOSPC simulated deterministically: the TUM writer writes half its file, then the disk is 'full'."""
    import nocal_ros.commands.odometry as command

    out = tmp_path / "out"
    assert odometry(moving_bag, out) == 0
    earlier = tree(out)
    capsys.readouterr()

    def full_disk(path, stamps_ns, poses):
        Path(path).write_text("1700000000.000000000 0.0 0.0")  # a partial line, as a real full disk leaves
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(command, "write_tum", full_disk)
    assert odometry(moving_bag, out, "--overwrite") == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "Traceback" not in err
    assert err == f"nocal odometry: error: {out}: No space left on device writing trajectory.tum; " \
                  "partial outputs were removed and earlier results kept"
    assert tree(out) == earlier  # the earlier bag, trajectory, report and plot as they were; nothing partial


def test_full_disk_while_writing_the_bag_keeps_earlier_results(moving_bag, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    assert odometry(moving_bag, out) == 0
    earlier = tree(out)
    written = []
    original = BagWriter.write_odometry

    def fills_up(self, *args, **kwargs):
        written.append(1)
        if len(written) > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(BagWriter, "write_odometry", fills_up)
    capsys.readouterr()
    assert odometry(moving_bag, out, "--overwrite") == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "No space left on device" in err
    assert tree(out) == earlier


def test_a_failure_while_moving_outputs_into_place_puts_the_earlier_ones_back(moving_bag, tmp_path, monkeypatch, capsys):
    import os

    out = tmp_path / "out"
    assert odometry(moving_bag, out) == 0
    earlier = tree(out)
    real_replace = os.replace
    failed = []

    def replace(source, destination):  # the new trajectory.tum cannot be moved into place, once
        if not failed and ".nocal-odometry-" in str(source) and Path(destination) == out / "trajectory.tum":
            failed.append(source)
            raise OSError(errno.EIO, "Input/output error", str(destination))
        return real_replace(source, destination)

    monkeypatch.setattr(os, "replace", replace)
    assert odometry(moving_bag, out, "--overwrite") == 1
    assert failed and "Input/output error" in capsys.readouterr().err
    monkeypatch.undo()
    assert tree(out) == earlier


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 176 KiB tmpfs: room for one replay's outputs (~150 KiB in 4 KiB pages) but not for a second copy beside them
    (nor, before the staged outputs, for the old code's --overwrite, which then ended in a traceback)."""
    mount = tmp_path / "tmpfs"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=176k", "tmpfs", str(mount)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_real_full_disk_keeps_earlier_results(moving_bag, small_tmpfs):
    """The kernel's own ENOSPC, on a tiny tmpfs, in a subprocess like a user's run."""
    out = small_tmpfs / "out"
    command = [sys.executable, "-m", "nocal_ros.cli", "odometry", str(moving_bag), "--out", str(out),
               "--device", "cpu", "--threads", "1", "--no-progress"]
    first = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-2000:]
    earlier = tree(out)
    second = subprocess.run(command + ["--overwrite"], capture_output=True, text=True, timeout=600)
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 1 and len(lines) == 1, second.stderr[-3000:]
    assert lines[0].startswith(f"nocal odometry: error: {out}: No space left on device") and "earlier results kept" in lines[0]
    assert tree(out) == earlier


# ---- --overwrite onto a bag without ground truth ------------------------------------------------------


def test_overwrite_with_a_bag_without_ground_truth_removes_the_old_report(moving_bag, tmp_path):
    from nocal_ros.data.bags import read_sequence

    sequence = read_sequence(moving_bag)
    plain = FrameSequence(sequence.images, sequence.stamps_ns, np.full((len(sequence), 4, 4), np.nan), name="no truth")
    no_truth = write_sequence(plain, tmp_path / "plain.mcap")
    out = tmp_path / "out"
    assert odometry(moving_bag, out) == 0
    assert (out / "report.json").is_file() and (out / "trajectory.png").is_file()
    assert odometry(no_truth, out, "--overwrite") == 0
    assert sorted(p.name for p in out.iterdir()) == ["calibration.yaml", "calibration_final.yaml", "odometry", "trajectory.tum",
                                                     "trajectory_final.tum", "trajectory_map.tum"]


# ---- header stamps that jump back ---------------------------------------------------------------------


def test_stamps_that_jump_back_never_go_back_in_the_trajectory(moving_bag, tmp_path, capsys):
    """Frames 0-5 at 10 Hz, then the camera clock jumps back by 0.35 s and frames 6-11 follow (a driver
    restart). /odom keeps all 12 poses; trajectory.tum and the report hold the longer segment."""
    from nocal_ros.data.bags import iter_images, read_poses

    frames = [image for _, _, image in iter_images(moving_bag)]
    truth = read_poses(moving_bag, "/ground_truth/pose", START_NS + PERIOD_NS * np.arange(6))
    stamps = [START_NS + PERIOD_NS * k for k in range(6)] + [START_NS + PERIOD_NS * k + 150_000_000 for k in range(6)]
    recorded = tmp_path / "jump.mcap"
    with BagWriter(recorded) as bag:
        for index, (stamp, image) in enumerate(zip(stamps, frames + frames)):
            log_time = START_NS + PERIOD_NS * index  # the recorder's clock goes on; the header stamps jump back
            image_msg = bag.types["sensor_msgs/msg/Image"](
                header=bag.header(stamp, "camera_optical"), height=48, width=64, encoding="rgb8", is_bigendian=0,
                step=64 * 3, data=np.ascontiguousarray(image).reshape(-1))
            bag.write_message("/camera/image_raw", log_time, image_msg)
            bag.write_pose("/ground_truth/pose", stamp, "world", truth[index % 6])
    out = tmp_path / "out"
    assert odometry(recorded, out) == 0, capsys.readouterr().err
    tum = np.loadtxt(out / "trajectory.tum")
    assert len(tum) == 6 and np.all(np.diff(tum[:, 0]) > 0)
    report = json.loads((out / "report.json").read_text())
    assert report["odom_poses"] == 12 and report["time_segments"] == 2 and report["trajectory_poses"] == 6
    assert report["evaluated_poses"] == 6
    from nocal_ros.data.bags import bag_topics

    assert bag_topics(out / "odometry")["/odom"][1] == 12


# ---- a corrupt metadata.yaml ----------------------------------------------------------------------------


@pytest.mark.parametrize("content", [
    b"rosbag2_bagfile_information:\n  version: 9\n  relative_file_paths: [a.mcap\n   : : bad\n\t tab",
    b"\x00\xff\xfe",
    b"just a string",
    b"rosbag2_bagfile_information:\n  version: 9\n",
], ids=["broken yaml", "binary", "a string", "keys missing"])
def test_corrupt_metadata_yaml_is_one_line(moving_bag, tmp_path, capsys, content):
    bag = tmp_path / "bag"
    write_sequence(FrameSequence(np.zeros((2, 8, 8, 3), np.uint8), np.array([1, 2]) * PERIOD_NS,
                                 np.full((2, 4, 4), np.nan), name="x"), bag)
    (bag / "metadata.yaml").write_bytes(content)
    assert odometry(bag, tmp_path / "out") == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and str(bag) in err and "Traceback" not in err
    assert not (tmp_path / "out" / "odometry").exists()


def test_the_final_trajectory_has_the_published_frames_and_its_own_report(moving_bag, tmp_path):
    import json

    out = tmp_path / "out"
    assert odometry(moving_bag, out) == 0
    published, final = np.loadtxt(out / "trajectory.tum"), np.loadtxt(out / "trajectory_final.tum")
    assert final.shape == published.shape and np.array_equal(final[:, 0], published[:, 0])
    report = json.loads((out / "report.json").read_text())["final_trajectory"]
    assert sum(report["posed"].values()) == len(published)
    assert {"rpe", "ape_sim3", "calibration", "seconds"} <= set(report) and report["observations_found"] >= 0


def test_no_final_writes_only_what_was_published(moving_bag, tmp_path):
    import json

    out = tmp_path / "out"
    assert odometry(moving_bag, out, "--no-final") == 0
    assert not (out / "trajectory_final.tum").exists() and not (out / "calibration_final.yaml").exists()
    assert "final_trajectory" not in json.loads((out / "report.json").read_text())
    assert (out / "trajectory.tum").is_file() and (out / "calibration.yaml").is_file()


def test_a_failing_final_solve_keeps_the_published_outputs(moving_bag, tmp_path, monkeypatch, caplog):
    from nocal_ros.odometry import OdometryEstimator

    def broken(self):
        raise RuntimeError("GTSAM: indeterminate system")

    monkeypatch.setattr(OdometryEstimator, "final_trajectory", broken)
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        assert odometry(moving_bag, out) == 0
    assert (out / "trajectory.tum").is_file() and (out / "report.json").is_file()
    assert not (out / "trajectory_final.tum").exists()
    assert any("end-of-replay solve failed (RuntimeError: GTSAM: indeterminate system)" in r.getMessage() for r in caplog.records)
