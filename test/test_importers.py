"""`nocal import`: each format on a small fixture written in the dataset's own layout, checked against
hand-computed stamps, poses and extrinsics, written to a real rosbag2 and read back; malformed files
fail with one line naming the file and the line; the real sequences in ../shared/data/real/."""

from __future__ import annotations

import weakref
from pathlib import Path

import cv2
import numpy as np
import pytest
from real_recordings import REAL, needs_real
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from nocal_ros.cli import main
from nocal_ros.data.bags import bag_topics, read_poses, read_sequence
from nocal_ros.data.importers import Recording, open_recording, write_recording
from nocal_ros.data.importers.common import associate
from nocal_ros.data.synthetic import FIRST_STAMP_NS
from nocal_ros.errors import ConfigError, DatasetError
from nocal_ros.lens import CameraCalibration

JAZZY = get_typestore(Stores.ROS2_JAZZY)


def image_messages(bag: Path) -> list:
    with AnyReader([bag], default_typestore=JAZZY) as reader:
        connections = [c for c in reader.connections if c.topic == "/camera/image_raw"]
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=connections)]


def pose(rotvec, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


def frame(index: int, width: int, height: int, colour: bool) -> np.ndarray:
    """A textured frame whose top-left pixel holds its index (BGR when colour, as cv2.imwrite wants)."""
    rng = np.random.default_rng(index)
    image = rng.integers(0, 256, (height, width, 3) if colour else (height, width), dtype=np.uint8)
    image[0, 0] = index
    return image


def assert_one_line_error(capsys, argv, *fragments):
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for fragment in fragments:
        assert fragment in err[0], err[0]


# --------------------------------------------------------------------------------------------------
# KITTI
# --------------------------------------------------------------------------------------------------

K_KITTI = np.array([[100.0, 0, 19.5], [0, 100.0, 5.5], [0, 0, 1]])
KITTI_POSES = [pose([0, 0.05 * k, 0], [0.1 * k, 0, 1.0 * k]) for k in range(5)]


def projection(baseline_x: float) -> np.ndarray:
    """A rectified P = K [I | t] whose camera sits ``baseline_x`` metres along x from camera 0."""
    return np.hstack((K_KITTI, (K_KITTI @ np.array([-baseline_x, 0, 0]))[:, None]))


def write_kitti(root: Path, camera: str = "image_2", prefixes: bool = True, times: bool = True, layout: str = "official") -> Path:
    sequence = root / "dataset" / "sequences" / "07" if layout == "official" else root / "clip"
    (sequence / camera).mkdir(parents=True)
    for k in range(5):
        cv2.imwrite(str(sequence / camera / f"{k:06d}.png"), frame(k, 40, 12, colour=camera in ("image_2", "image_3")))
    rows = [projection(0.0), projection(0.54), projection(-0.06), projection(0.48)]
    with open(sequence / "calib.txt", "w") as f:
        for index, P in enumerate(rows):
            f.write((f"P{index}: " if prefixes else "") + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n")
        if prefixes:
            f.write("Tr: " + " ".join(["1", "0", "0", "0"] * 3) + "\n")
    if times:
        (sequence / "times.txt").write_text("".join(f"{0.1037 * k:.6e}\n" for k in range(5)))
    pose_file = root / "dataset" / "poses" / "07.txt" if layout == "official" else sequence / "poses.txt"
    pose_file.parent.mkdir(parents=True, exist_ok=True)
    pose_file.write_text("".join(" ".join(f"{v:.12e}" for v in T[:3].ravel()) + "\n" for T in KITTI_POSES))
    return sequence


def test_kitti_official_layout_colour_camera_with_its_baseline(tmp_path):
    sequence = write_kitti(tmp_path)
    out = tmp_path / "bag"
    assert main(["import", "kitti", str(sequence), "--out", str(out)]) == 0
    replay = read_sequence(out)
    # times.txt seconds since the start, from the epoch the renderer uses
    expected_stamps = FIRST_STAMP_NS + np.array([round(0.1037 * k * 1e9) for k in range(5)])
    assert replay.stamps_ns.tolist() == expected_stamps.tolist()
    # image_2 sits 6 cm left of camera 0 (P2[0,3] = +0.06 fx): its centre is T_w_c0 @ (-0.06, 0, 0)
    for k, T_w_c0 in enumerate(KITTI_POSES):
        centre = T_w_c0[:3, 3] + T_w_c0[:3, :3] @ np.array([-0.06, 0, 0])
        np.testing.assert_allclose(replay.ground_truth[k][:3, 3], centre, atol=1e-9)
        np.testing.assert_allclose(replay.ground_truth[k][:3, :3], T_w_c0[:3, :3], atol=1e-9)
    assert replay.calibration.width == 40 and replay.calibration.height == 12
    np.testing.assert_allclose(replay.calibration.K, K_KITTI)
    assert replay.calibration.distortion_model == "plumb_bob" and not replay.calibration.D.any()
    messages = image_messages(out)
    assert {m.encoding for m in messages} == {"rgb8"}
    first = cv2.imread(str(sequence / "image_2" / "000000.png"))
    np.testing.assert_array_equal(replay.images[0], first[:, :, ::-1])


def test_kitti_clip_layout_without_prefixes_or_times_is_mono8_at_10_hz(tmp_path):
    sequence = write_kitti(tmp_path, camera="image_l", prefixes=False, times=False, layout="clip")
    recording = open_recording("kitti", sequence)
    assert recording.encoding == "mono8" and recording.size == (40, 12)
    assert any("10 Hz" in note for note in recording.notes)
    assert np.diff(recording.stamps_ns).tolist() == [100_000_000] * 4
    np.testing.assert_allclose(recording.ground_truth, np.stack(KITTI_POSES), atol=1e-12)  # image_l is camera 0
    out = tmp_path / "bag"
    summary = write_recording(recording, out, "sqlite3")
    assert summary.frames == 5 and summary.encoding == "mono8"
    messages = image_messages(out)
    assert {m.encoding for m in messages} == {"mono8"} and messages[0].step == 40
    grey = cv2.imread(str(sequence / "image_l" / "000003.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(np.asarray(messages[3].data).reshape(12, 40), grey)
    # the right grey camera of the same clip (P1): 0.54 m to the right of camera 0, same orientation
    (sequence / "image_l").rename(sequence / "image_r")
    right = open_recording("kitti", sequence, camera="image_r")
    for T_w_c0, T_w_c1 in zip(KITTI_POSES, right.ground_truth):
        np.testing.assert_allclose(T_w_c1[:3, 3], T_w_c0[:3, 3] + T_w_c0[:3, :3] @ [0.54, 0, 0], atol=1e-12)
        np.testing.assert_allclose(T_w_c1[:3, :3], T_w_c0[:3, :3], atol=1e-12)


@pytest.mark.parametrize(("target", "line", "text", "fragment"), [
    ("calib.txt", 2, "P1: 1 2 3", "calib.txt:2: expected 12 numbers"),
    ("poses", 3, "1 0 0 0 0 1 0 0 0 0 1 x", "07.txt:3: not a number"),
    ("times.txt", 4, "0.3 0.4", "times.txt:4: expected one time"),
])
def test_kitti_malformed_files_name_file_and_line(tmp_path, capsys, target, line, text, fragment):
    sequence = write_kitti(tmp_path)
    path = tmp_path / "dataset" / "poses" / "07.txt" if target == "poses" else sequence / target
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")
    assert_one_line_error(capsys, ["import", "kitti", str(sequence), "--out", str(tmp_path / "bag")], fragment, str(path.parent))
    assert not (tmp_path / "bag").exists()


def test_kitti_pose_count_must_match_images(tmp_path):
    sequence = write_kitti(tmp_path)
    pose_file = tmp_path / "dataset" / "poses" / "07.txt"
    pose_file.write_text("\n".join(pose_file.read_text().splitlines()[:4]) + "\n")
    with pytest.raises(DatasetError, match="4 poses for 5 images"):
        open_recording("kitti", sequence)


# --------------------------------------------------------------------------------------------------
# EuRoC
# --------------------------------------------------------------------------------------------------

T_BS = pose([0.1, -0.2, 1.4], [-0.02, -0.06, 0.01])
EUROC_T0 = 1403636579763555584


def body_pose(t_s: float) -> np.ndarray:
    """The body's true motion: constant-axis rotation and constant velocity (interpolation is exact)."""
    return pose(np.array([0.0, 0.0, 1.0]) * 0.5 * t_s, np.array([0.3, -0.1, 0.05]) * t_s + np.array([4.0, -2.0, 1.0]))


def write_euroc(root: Path, model: str = "radial-tangential") -> Path:
    cam = root / "MH_01" / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    image_offsets_ms = [-10.0, 2.5, 52.5, 102.5, 152.5]  # the first image is before the ground truth starts
    lines = ["#timestamp [ns],filename"]
    for k, offset in enumerate(image_offsets_ms):
        stamp = EUROC_T0 + int(offset * 1e6)
        cv2.imwrite(str(cam / "data" / f"{stamp}.png"), frame(k, 32, 20, colour=False))
        lines.append(f"{stamp},{stamp}.png")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    coefficients = "[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]"
    (cam / "sensor.yaml").write_text(
        "# General sensor definitions.\nsensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034)\n"
        "T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ", ".join(f"{v:.15f}" for v in T_BS.ravel()) + "]\n"
        "rate_hz: 20\nresolution: [32, 20]\ncamera_model: pinhole\nintrinsics: [30.5, 30.1, 15.2, 9.8]\n"
        f"distortion_model: {model}\ndistortion_coefficients: {coefficients}\n"
    )
    gt = root / "MH_01" / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
            "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
            "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    for k in range(0, 45):  # 200 Hz from t0 to t0 + 220 ms
        t = k * 0.005
        T = body_pose(t)
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        rows.append(f"{EUROC_T0 + k * 5_000_000},{T[0, 3]},{T[1, 3]},{T[2, 3]},{w},{x},{y},{z}," + ",".join(["0"] * 9))
    (gt / "data.csv").write_text("\n".join(rows) + "\n")
    (gt / "sensor.yaml").write_text("sensor_type: visual-inertial\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, "
                                    "0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n")
    return root / "MH_01"


def test_euroc_interpolates_ground_truth_and_applies_T_BS(tmp_path):
    src = write_euroc(tmp_path)
    out = tmp_path / "bag"
    assert main(["import", "euroc", str(src), "--out", str(out), "--storage", "sqlite3"]) == 0
    replay = read_sequence(out)
    assert replay.stamps_ns[0] == EUROC_T0 - 10_000_000  # EuRoC stamps are absolute: kept as they are
    assert replay.images.shape == (5, 20, 32, 3)
    assert not np.isfinite(replay.ground_truth[0]).all()  # before the ground truth starts: none
    for k, offset_ms in enumerate([2.5, 52.5, 102.5, 152.5], start=1):
        expected = body_pose(offset_ms / 1000) @ T_BS  # T_R_cam = T_R_B T_B_cam
        np.testing.assert_allclose(replay.ground_truth[k], expected, atol=1e-9)
    calibration = replay.calibration
    np.testing.assert_allclose(calibration.K, [[30.5, 0, 15.2], [0, 30.1, 9.8], [0, 0, 1]])
    assert calibration.distortion_model == "plumb_bob"
    np.testing.assert_allclose(calibration.D, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    assert {m.encoding for m in image_messages(out)} == {"mono8"}
    assert bag_topics(out)["/ground_truth/pose"] == ("geometry_msgs/msg/PoseStamped", 4)


def test_euroc_equidistant_stays_equidistant(tmp_path):
    recording = open_recording("euroc", write_euroc(tmp_path, "equidistant") / "mav0")
    assert recording.calibration.distortion_model == "equidistant"
    np.testing.assert_allclose(recording.calibration.D, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])


def test_euroc_malformed_rows_name_file_and_line(tmp_path, capsys):
    src = write_euroc(tmp_path)
    data = src / "mav0" / "cam0" / "data.csv"
    lines = data.read_text().splitlines()
    lines[2] = lines[2] + ",extra"
    data.write_text("\n".join(lines) + "\n")
    assert_one_line_error(capsys, ["import", "euroc", str(src), "--out", str(tmp_path / "bag")], f"{data}:3:")
    data.write_text("\n".join(lines[:2] + lines[3:]) + "\n")
    gt = src / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    rows = gt.read_text().splitlines()
    rows[5] = rows[5].replace(",", ",nan,", 1)
    gt.write_text("\n".join(rows) + "\n")
    with pytest.raises(DatasetError, match=f"{gt}:6: non-finite"):
        open_recording("euroc", src)


# --------------------------------------------------------------------------------------------------
# TUM RGB-D and TUM-style association
# --------------------------------------------------------------------------------------------------


def tum_reference_associate(first: dict, second: dict, offset: float, max_difference: float) -> list:
    """TUM's associate.py, as published (all pairs, closest first, each stamp once)."""
    first_keys, second_keys = list(first), list(second)
    potential = [(abs(a - (b + offset)), a, b) for a in first_keys for b in second_keys if abs(a - (b + offset)) < max_difference]
    potential.sort()
    matches = []
    for _, a, b in potential:
        if a in first_keys and b in second_keys:
            first_keys.remove(a)
            second_keys.remove(b)
            matches.append((a, b))
    matches.sort()
    return matches


def test_association_matches_tums_associate_py():
    rng = np.random.default_rng(4)
    images = np.cumsum(rng.uniform(0.02, 0.05, 60))
    truth = np.sort(rng.uniform(0, images[-1], 150))
    reference = tum_reference_associate(dict.fromkeys(images.tolist()), dict.fromkeys(truth.tolist()), 0.0, 0.02)
    ours = associate((images * 1e9).round().astype(np.int64), (truth * 1e9).round().astype(np.int64), 20_000_000)
    assert sorted((images[i], truth[j]) for i, j in ours.items()) == reference
    assert 0 < len(reference) < len(images)


def write_tum(root: Path, name: str = "rgbd_dataset_freiburg1_xyz", size=(64, 48)) -> Path:
    src = root / name
    (src / "rgb").mkdir(parents=True)
    stamps = ["1305031102.175304", "1305031102.211214", "1305031102.243211", "1305031102.275326", "1305031102.311267"]
    lines = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    for k, stamp in enumerate(stamps):
        cv2.imwrite(str(src / "rgb" / f"{stamp}.png"), frame(k, *size, colour=True))
        lines.append(f"{stamp} rgb/{stamp}.png")
    (src / "rgb.txt").write_text("\n".join(lines) + "\n")
    # samples: 3 ms after images 0 and 1, 1 ms before image 2, none near image 3 (30 ms away), 5 ms after image 4
    gt_times = ["1305031102.1783", "1305031102.2142", "1305031102.2422", "1305031102.3053", "1305031102.3163"]
    rows = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for k, t in enumerate(gt_times):
        x, y, z, w = Rotation.from_rotvec([0.1 * k, 0.0, 0.02]).as_quat()
        rows.append(f"{t} {0.1 * k:.4f} {1.0 + k:.4f} {-0.5:.4f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}")
    (src / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    return src


def test_tum_associates_ground_truth_and_knows_freiburg_cameras(tmp_path):
    src = write_tum(tmp_path, size=(640, 480))
    recording = open_recording("tum", src)
    # stamps parsed exactly (decimal seconds -> integer nanoseconds)
    assert recording.stamps_ns[0] == 1305031102175304000
    sample_of_image = {0: 0, 1: 1, 2: 2, 4: 4}  # image 3's nearest sample is 30 ms away: none
    for image, sample in sample_of_image.items():
        expected = Rotation.from_rotvec([0.1 * sample, 0.0, 0.02]).as_matrix()
        np.testing.assert_allclose(recording.ground_truth[image][:3, :3], expected, atol=1e-8)
        np.testing.assert_allclose(recording.ground_truth[image][:3, 3], [0.1 * sample, 1.0 + sample, -0.5], atol=1e-12)
    assert not np.isfinite(recording.ground_truth[3]).any()
    assert recording.calibration.camera_name == "freiburg1"
    np.testing.assert_allclose(recording.calibration.K[0], [517.306408, 0, 318.643040])
    out = tmp_path / "bag"
    summary = write_recording(recording, out, arm_fraction=0.5, seed=2)
    assert summary.ground_truth_frames == 4 and summary.arm_frames == 2 and summary.encoding == "rgb8"
    replay = read_sequence(out)
    assert replay.labelled.sum() == 2
    np.testing.assert_allclose(replay.arm_poses[replay.labelled], replay.ground_truth[replay.labelled], atol=1e-12)


def test_tum_calibration_option_and_size_check(tmp_path):
    src = write_tum(tmp_path, name="my_sequence")
    assert open_recording("tum", src).calibration is None
    yaml = tmp_path / "camera.yaml"
    CameraCalibration.pinhole(64, 48, 50.0).save(yaml)
    assert open_recording("tum", src, calibration=yaml).calibration.fx == 50.0
    CameraCalibration.pinhole(640, 480, 500.0).save(yaml)
    with pytest.raises(DatasetError, match="calibration is for 640x480"):
        open_recording("tum", src, calibration=yaml)


def test_tum_malformed_files_name_file_and_line(tmp_path):
    src = write_tum(tmp_path)
    gt = src / "groundtruth.txt"
    rows = gt.read_text().splitlines()
    rows[4] = " ".join(rows[4].split()[:7])
    gt.write_text("\n".join(rows) + "\n")
    with pytest.raises(DatasetError, match=f"{gt}:5: expected 8 numbers"):
        open_recording("tum", src)
    rgb = src / "rgb.txt"
    lines = rgb.read_text().splitlines()
    lines[4], lines[5] = lines[5], lines[4]
    rgb.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=f"{rgb}:6: time .* does not increase"):
        open_recording("tum", src)


# --------------------------------------------------------------------------------------------------
# folder of images, video
# --------------------------------------------------------------------------------------------------


def write_folder(root: Path, count: int = 11) -> Path:
    folder = root / "frames"
    folder.mkdir()
    for k in range(count):  # img_2 must come before img_10
        cv2.imwrite(str(folder / f"img_{k}.png"), frame(k, 24, 16, colour=False))
    return folder


def test_folder_natural_order_rate_poses_and_calibration(tmp_path):
    folder = write_folder(tmp_path)
    poses = tmp_path / "trajectory.tum"
    truth = [pose([0, 0.01 * k, 0], [0.02 * k, 0, 0]) for k in range(11)]
    # relative times in the pose file, 1 ms after each frame of a 20 Hz camera
    poses.write_text("".join(
        f"{0.05 * k + 0.001:.4f} " + " ".join(f"{v:.12f}" for v in (*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_quat())) + "\n"
        for k, T in enumerate(truth)))
    yaml = tmp_path / "camera.yaml"
    CameraCalibration(24, 16, np.array([[20.0, 0, 11.5], [0, 20.0, 7.5], [0, 0, 1]]), np.array([-0.1, 0.01, 0, 0, 0])).save(yaml)
    out = tmp_path / "bag"
    assert main(["import", "folder", str(folder), "--rate", "20", "--poses", str(poses), "--calibration", str(yaml),
                 "--out", str(out), "--arm-fraction", "1.0"]) == 0
    replay = read_sequence(out)
    assert [int(image[0, 0, 0]) for image in replay.images] == list(range(11))  # natural order
    assert np.diff(replay.stamps_ns).tolist() == [50_000_000] * 10
    np.testing.assert_allclose(replay.ground_truth, np.stack(truth), atol=1e-9)
    np.testing.assert_allclose(replay.arm_poses, np.stack(truth), atol=1e-9)
    assert replay.calibration.D[0] == -0.1


def test_folder_timestamps_file_with_names_and_option_errors(tmp_path):
    folder = write_folder(tmp_path, count=4)
    stamps = tmp_path / "times.txt"
    stamps.write_text("# t name\n1700000001.5 img_3.png\n1700000001.6 img_1.png\n")
    recording = open_recording("folder", folder, timestamps=stamps)
    assert recording.stamps_ns.tolist() == [1700000001500000000, 1700000001600000000]
    assert [int(image[0, 0]) for _, image in recording.frames()] == [3, 1]
    with pytest.raises(ConfigError, match="exactly one of --rate HZ and --timestamps"):
        open_recording("folder", folder)
    with pytest.raises(ConfigError, match="format kitti does not take --timestamps"):
        open_recording("kitti", folder, timestamps=stamps)
    stamps.write_text("0.0\n0.1\n0.1\n0.3\n")
    with pytest.raises(DatasetError, match=f"{stamps}:3: time"):
        open_recording("folder", folder, timestamps=stamps)


def test_video_through_opencv(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (48, 32))
    assert writer.isOpened()
    for k in range(6):
        writer.write(np.full((32, 48, 3), (20 * k, 100, 200), np.uint8))  # BGR
    writer.release()
    recording = open_recording("video", path)
    assert recording.encoding == "rgb8" and recording.size == (48, 32) and recording.ground_truth is None
    out = tmp_path / "bag"
    summary = write_recording(recording, out)
    assert summary.frames == 6
    replay = read_sequence(out)
    np.testing.assert_allclose(np.diff(replay.stamps_ns), 1e9 / 15, atol=1e3)
    # MJPG is lossy: the colour comes back within a few levels, in RGB order
    np.testing.assert_allclose(replay.images[3].reshape(-1, 3).mean(0), [200, 100, 60], atol=4)
    mono = open_recording("video", path, rate=5.0, encoding="mono8")
    stamps = [stamp for stamp, image in mono.frames() if image.ndim == 2]
    assert len(stamps) == 6 and np.diff(stamps).tolist() == [200_000_000] * 5
    with pytest.raises(ConfigError, match="--arm-fraction needs ground truth"):
        write_recording(recording, tmp_path / "arm", arm_fraction=0.1)
    (tmp_path / "broken.avi").write_bytes(b"not a video")
    with pytest.raises(DatasetError, match="broken.avi"):
        open_recording("video", tmp_path / "broken.avi")


# --------------------------------------------------------------------------------------------------
# VAMR exercise layout
# --------------------------------------------------------------------------------------------------


def write_vamr(root: Path, count: int = 4) -> Path:
    src = root / "vamr"
    (src / "images").mkdir(parents=True)
    for k in range(count):
        grey = frame(k + 1, 40, 30, colour=False)
        cv2.imwrite(str(src / "images" / f"img_{k + 1:04d}.jpg"), cv2.merge([grey, grey, grey]))
    (src / "K.txt").write_text("40.5 0. 19.2\n0. 40.1 14.8\n0. 0. 1.\n")
    (src / "D.txt").write_text("-1.6774e-04 2.5847e-08\n")
    (src / "poses.txt").write_text("".join(f"{0.1 * k} -0.2 0.05 {0.01 * k} 0.02 0.4\n" for k in range(count)))
    return src


def test_vamr_world_to_camera_poses_and_pixel_unit_distortion(tmp_path):
    src = write_vamr(tmp_path)
    out = tmp_path / "bag"
    assert main(["import", "vamr", str(src), "--out", str(out)]) == 0
    replay = read_sequence(out)
    for k in range(4):
        R = Rotation.from_rotvec([0.1 * k, -0.2, 0.05]).as_matrix()
        t = np.array([0.01 * k, 0.02, 0.4])
        np.testing.assert_allclose(replay.ground_truth[k][:3, :3], R.T, atol=1e-9)  # X_c = R X_w + t
        np.testing.assert_allclose(replay.ground_truth[k][:3, 3], -R.T @ t, atol=1e-9)
    np.testing.assert_allclose(replay.calibration.D, [-1.6774e-04 * 40.5 * 40.1, 2.5847e-08 * (40.5 * 40.1) ** 2, 0, 0, 0])
    steps = np.diff(replay.stamps_ns)  # 30 Hz, rounded to whole nanoseconds
    assert np.abs(steps - 1e9 / 30).max() < 1 and replay.stamps_ns[0] == FIRST_STAMP_NS
    assert {m.encoding for m in image_messages(out)} == {"mono8"}
    jpeg = cv2.imread(str(src / "images" / "img_0002.jpg"))
    np.testing.assert_array_equal(replay.images[1][..., 0], jpeg[..., 0])  # grey kept exactly


def test_vamr_colour_frame_refused_as_mono8(tmp_path):
    src = write_vamr(tmp_path)
    image = cv2.imread(str(src / "images" / "img_0003.jpg"))
    image[5:25, 5:25] = (0, 0, 255)
    cv2.imwrite(str(src / "images" / "img_0003.png"), image)
    (src / "images" / "img_0003.jpg").unlink()
    with pytest.raises(DatasetError, match="img_0003.png: a colour image"):
        write_recording(open_recording("vamr", src), tmp_path / "bag")
    assert not (tmp_path / "bag").exists()
    assert write_recording(open_recording("vamr", src, encoding="rgb8"), tmp_path / "bag").encoding == "rgb8"


# --------------------------------------------------------------------------------------------------
# streaming, arm runs
# --------------------------------------------------------------------------------------------------


def test_write_recording_streams_one_frame_at_a_time(tmp_path):
    alive: list[weakref.ref] = []

    def frames():
        for k in range(12):
            assert sum(ref() is not None for ref in alive[:-1]) == 0, "earlier frames are still held"
            image = np.full((8, 10), k, np.uint8)
            alive.append(weakref.ref(image))
            yield FIRST_STAMP_NS + k * 1000, image

    truth = np.stack([pose([0, 0, 0], [k, 0, 0]) for k in range(12)])
    recording = Recording("stream", FIRST_STAMP_NS + np.arange(12) * 1000, truth, None, (10, 8), "mono8", frames, 12)
    summary = write_recording(recording, tmp_path / "bag", arm_fraction=0.75, seed=1)
    assert summary.frames == 12 and summary.arm_frames == 9 and summary.path_length_m == pytest.approx(11.0)
    arm = read_poses(tmp_path / "bag", "/arm/pose", recording.stamps_ns, tolerance_s=0)
    labelled = np.flatnonzero(np.isfinite(arm).all(axis=(1, 2)))
    assert len(labelled) == 9 and np.ptp(labelled) == 8  # one run of 9, as an arm logs
    np.testing.assert_allclose(arm[labelled], truth[labelled])


# --------------------------------------------------------------------------------------------------
# the real sequences (../shared/data/real/README.md)
# --------------------------------------------------------------------------------------------------


@needs_real("kitti_clip")
def test_real_kitti_clip(tmp_path):
    recording = open_recording("kitti", REAL / "kitti_clip")
    assert len(recording) == 51 and recording.size == (1241, 376) and recording.encoding == "mono8"
    np.testing.assert_allclose(recording.calibration.K[:2], [[718.856, 0, 607.1928], [0, 718.856, 185.2157]])
    travel = np.linalg.norm(np.diff(recording.ground_truth[:, :3, 3], axis=0), axis=1).sum()
    assert 50 < travel < 54  # "about 52 m"
    heading = np.degrees(np.arctan2(recording.ground_truth[-1][0, 2], recording.ground_truth[-1][2, 2]))
    assert abs(heading) > 20  # "a strong left curve"
    summary = write_recording(recording, tmp_path / "kitti", max_frames=10)
    replay = read_sequence(tmp_path / "kitti")
    assert summary.frames == 10 and replay.images.shape == (10, 376, 1241, 3)
    # the file's rotations are orthonormal to 1e-7; the bag's quaternions are exact rotations
    np.testing.assert_allclose(replay.ground_truth, recording.ground_truth[:10], atol=1e-6)


@needs_real("vamr_ex1")
def test_real_vamr_ex1(tmp_path):
    recording = open_recording("vamr", REAL / "vamr_ex1")
    assert len(recording) == 736 and recording.size == (752, 480) and recording.encoding == "mono8"
    centres = recording.ground_truth[:, :3, 3]
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert 2.2 < steps.sum() < 2.6  # "about 2.4 m in all"
    assert 2.5e-3 < np.median(steps) < 3.1e-3  # "median 2.8 mm per frame"
    assert recording.calibration.D[0] == pytest.approx(-0.2967, abs=5e-4)
    assert recording.calibration.D[1] == pytest.approx(0.0809, abs=5e-4)
    # checkerboard in view: the world origin lies in front of the first camera
    T_cam_world = np.linalg.inv(recording.ground_truth[0])
    assert T_cam_world[2, 3] > 0
    write_recording(recording, tmp_path / "vamr", max_frames=5, arm_fraction=0.1)
    replay = read_sequence(tmp_path / "vamr")
    jpeg = cv2.imread(str(REAL / "vamr_ex1" / "images" / "img_0005.jpg"))
    np.testing.assert_array_equal(replay.images[4][..., 0], jpeg[..., 0])
    assert replay.calibration.distortion_model == "plumb_bob"
