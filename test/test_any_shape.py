"""Cameras of any shape: the one map from native frames to the network's input (the whole frame,
area-resized, each axis at its own scale), checked against OpenCV; the odometry and the training see
the same network image; `nocal synth` renders non-4:3 cameras with square pixels; `nocal train`
pretrains and fine-tunes on non-4:3 mono8 and colour bags."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from scipy.spatial.transform import Rotation

from nocal_ros.camera import CameraModel, pixel_grid
from nocal_ros.cli import main
from nocal_ros.data.bags import read_sequence
from nocal_ros.data.pairs import PairDataset
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.lens import CameraCalibration
from nocal_ros.network_input import InputMapping, input_mapping, network_input
from nocal_ros.odometry import PoseModel
from nocal_ros.odometry.pose_head import PoseRunner

REPO = Path(__file__).resolve().parents[1]
NETWORK = (80, 60)


@pytest.mark.parametrize(("native", "scale"), [
    ((1241, 376), (15.5125, 6.266666666666667)),  # KITTI: 3.3:1 onto 4:3, each axis its own scale
    ((1280, 720), (16.0, 12.0)),
    ((640, 512), (8.0, 8.533333333333333)),
    ((640, 480), (8.0, 8.0)),  # 4:3: a plain resize
    ((60, 45), (0.75, 0.75)),  # smaller than the network: enlarged
])
def test_the_map_covers_the_whole_frame(native, scale):
    mapping = input_mapping(native, NETWORK)
    assert mapping.window == (0, 0, *native) and mapping.scale == pytest.approx(scale, rel=1e-12)
    # the outer network pixel edges are the outer native pixel edges
    assert mapping.to_native(-0.5, -0.5) == pytest.approx((-0.5, -0.5))
    assert mapping.to_native(79.5, 59.5) == pytest.approx((native[0] - 0.5, native[1] - 0.5))


@pytest.mark.parametrize("native", [(1241, 376), (1280, 720), (640, 512), (320, 240), (60, 45)])
def test_network_pixel_map_is_exact_for_opencvs_area_resampling(native):
    """A native image that is an affine ramp in u and v: each network pixel's value must be the ramp
    at the native point the map gives it (OpenCV's INTER_AREA resampling is the reference).

    Exact for whole-number scales (640x480 -> 80x60); for others INTER_AREA weighs a native pixel the
    box covers in part by its coverage, which moves the pixel's footprint centroid off the box centre
    by at most 1/(8 s) native pixels at scale s (0.016 px for KITTI, 1/400 of a network pixel)."""
    width, height = native
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    ramp = np.stack((u, v, 0.25 * u - 0.5 * v + 7.0), -1).astype(np.float32)
    image, mapping = network_input(ramp, NETWORK)
    assert image.shape == (60, 80, 3) and mapping == input_mapping(native, NETWORK)
    un, vn = pixel_grid(*NETWORK, dtype=torch.float64)
    expected_u, expected_v = mapping.to_native(un.numpy(), vn.numpy())
    sx, sy = mapping.scale
    bound = lambda s: (1 / (8 * s) if s > 1 and s != int(s) else 0.0) + 1e-3  # noqa: E731
    # Enlarging, the outermost network pixels lie beyond the outer native pixel centres: no data there.
    inside = (expected_u >= 0) & (expected_u <= width - 1) & (expected_v >= 0) & (expected_v <= height - 1)
    assert inside.mean() > 0.9
    np.testing.assert_allclose(image[..., 0].ravel()[inside], expected_u[inside], atol=bound(sx))
    np.testing.assert_allclose(image[..., 1].ravel()[inside], expected_v[inside], atol=bound(sy))
    back_u, back_v = mapping.to_network(expected_u, expected_v)
    np.testing.assert_allclose(back_u, un.numpy(), atol=1e-9)
    np.testing.assert_allclose(back_v, vn.numpy(), atol=1e-9)


def undistort_rays(calibration: CameraCalibration, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit rays of native pixels by OpenCV (the independent reference)."""
    points = np.stack((u, v), -1).reshape(-1, 1, 2).astype(np.float64)
    xy = cv2.undistortPoints(points, calibration.K, calibration.D, P=None).reshape(-1, 2)
    rays = np.concatenate((xy, np.ones((len(xy), 1))), -1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


@pytest.mark.parametrize("native", [(1241, 376), (1280, 720), (640, 512)])
def test_rays_of_network_pixels_are_the_rays_of_their_native_pixels(native):
    width, height = native
    f = 0.55 * width
    pinhole = CameraCalibration(width, height, np.array([[f, 0, width / 2 - 3.2], [0, 1.01 * f, height / 2 + 1.7], [0, 0, 1]]))
    mapping = input_mapping(native, NETWORK)
    un, vn = pixel_grid(*NETWORK, dtype=torch.float64)
    u_native, v_native = mapping.to_native(un.numpy(), vn.numpy())

    # A pinhole CameraModel (its distortion MLP starts at zero): exact, to its float32 parameters.
    model = CameraModel(width, height, fx=pinhole.fx, fy=pinhole.fy, cx=pinhole.cx, cy=pinhole.cy).float64_copy()
    with torch.no_grad():
        rays = model.directions(*NETWORK).numpy()
    np.testing.assert_allclose(rays, undistort_rays(pinhole, u_native, v_native), atol=1e-6)  # 1e-3 is a pixel

    # A barrel lens fitted by the distortion MLP: as close as the MLP fits the lens (~0.2 px).
    lens = CameraCalibration(width, height, pinhole.K, np.array([-0.05, 0.01, 0.0005, -0.0003, 0.0]))
    fitted = CameraModel.from_calibration(lens).float64_copy()
    with torch.no_grad():
        rays = fitted.directions(*NETWORK).numpy()
    reference = undistort_rays(lens, u_native, v_native)
    angle = np.arccos(np.clip((rays * reference).sum(1), -1, 1))
    assert angle.max() < 1.5e-3  # radians; ~1 native pixel at this focal

    # The check can fail: the pixel-corner convention (u * W / w, half a network pixel off) gives other rays.
    corner = InputMapping(native, NETWORK, (0, 0, width, height))
    cu, cv = corner.to_native(un.numpy() - 0.5, vn.numpy() - 0.5)
    assert np.arccos(np.clip((undistort_rays(lens, cu + 0.5, cv + 0.5) * reference).sum(1), -1, 1)).max() > 3 * 1.5e-3


@pytest.mark.parametrize(("native", "mono"), [((1241, 376), True), ((1280, 720), False), ((640, 512), False)])
def test_odometry_and_training_see_the_same_network_image(native, mono):
    width, height = native
    rng = np.random.default_rng(width)
    frames = rng.integers(0, 256, (2, height, width) if mono else (2, height, width, 3), dtype=np.uint8)
    rgb = np.repeat(frames[..., None], 3, -1) if mono else frames  # a mono8 bag decodes to equal channels
    sequence = FrameSequence(rgb, np.array([1, 2]) * 10**8, np.full((2, 4, 4), np.nan))
    pairs = PairDataset([sequence], size=NETWORK, gap_range=(1, 1))
    training_image = (pairs.collate([0])["image_j"][0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)

    seen = []
    runner = PoseRunner(PoseModel(predict_pose=lambda a, b: seen.append(b.clone()) or torch.eye(4)[None],
                                  input_size=NETWORK), cuda_graphs=False)
    older = runner.load_frame(rgb[0])
    buffer = rgb[1].copy()
    key = runner.load_frame(buffer)
    buffer[...] = 0  # the caller reuses its buffer before the pair runs
    runner.run(older, key)
    odometry_image = (seen[0][0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)

    expected, mapping = network_input(rgb[1], NETWORK)
    np.testing.assert_array_equal(odometry_image, expected)
    np.testing.assert_array_equal(training_image, expected)
    # and it is the whole frame, area-resized
    np.testing.assert_array_equal(expected, cv2.resize(rgb[1], NETWORK, interpolation=cv2.INTER_AREA))


# --------------------------------------------------------------------------------------------------
# `nocal synth` at other aspect ratios
# --------------------------------------------------------------------------------------------------


def test_synth_another_aspect_ratio_keeps_square_pixels_and_is_the_middle_of_the_4_3_render(tmp_path):
    wide, tall = tmp_path / "wide", tmp_path / "tall"
    common = ["--frames", "3", "--seed", "5", "--threads", "1"]
    assert main(["synth", "--out", str(wide), "--size", "128x72", *common]) == 0
    assert main(["synth", "--out", str(tall), "--size", "128x96", *common]) == 0
    a, b = read_sequence(wide), read_sequence(tall)
    assert a.calibration.fx == pytest.approx(a.calibration.fy) == pytest.approx(b.calibration.fx)
    assert a.calibration.cy == pytest.approx(b.calibration.cy - 12)
    # The same lens on a sensor 24 rows shorter: the 16:9 frames are rows 12..83 of the 4:3 frames.
    difference = np.abs(a.images.astype(int) - b.images[:, 12:84].astype(int))
    assert difference.mean() < 0.5 and np.percentile(difference, 99) <= 2


def test_synth_kitti_shape(tmp_path):
    out = tmp_path / "kitti"
    assert main(["synth", "--out", str(out), "--size", "124x38", "--frames", "2", "--threads", "1"]) == 0
    calibration = read_sequence(out).calibration
    assert (calibration.width, calibration.height) == (124, 38)
    assert calibration.fx == pytest.approx(calibration.fy) == pytest.approx(520 * 124 / 640)
    assert calibration.cy == pytest.approx(18.5) and calibration.cx == pytest.approx(61.5)


# --------------------------------------------------------------------------------------------------
# training on non-4:3 cameras, mono8 and colour
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def shaped_bags(tmp_path_factory):
    """A 124x38 (KITTI-shaped) mono8 bag made by `nocal import folder` from grey frames and a TUM
    trajectory, a 128x72 colour bag from `nocal synth`, and a tiny initial model trained at 32x24."""
    from nocal_ros.checkpoint import save_checkpoint
    from nocal_ros.commands.train import load_config
    from nocal_ros.model import NOCaL

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("shapes")
    colour = root / "colour"
    assert main(["synth", "--out", str(colour), "--size", "128x72", "--frames", "10", "--seed", "2",
                 "--labelled-fraction", "0.6", "--threads", "1"]) == 0
    rendered = root / "kitti_rgb"
    assert main(["synth", "--out", str(rendered), "--size", "124x38", "--frames", "10", "--seed", "4", "--threads", "1"]) == 0
    sequence = read_sequence(rendered)
    frames = root / "frames"
    frames.mkdir()
    lines = []
    for k, (image, T) in enumerate(zip(sequence.images, sequence.ground_truth)):
        cv2.imwrite(str(frames / f"{k:04d}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        lines.append(f"{0.1 * k:.3f} {T[0, 3]:.9f} {T[1, 3]:.9f} {T[2, 3]:.9f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}")
    (root / "poses.tum").write_text("\n".join(lines) + "\n")
    sequence.calibration.save(root / "camera.yaml")
    mono = root / "mono"
    assert main(["import", "folder", str(frames), "--rate", "10", "--poses", str(root / "poses.tum"),
                 "--calibration", str(root / "camera.yaml"), "--arm-fraction", "0.6", "--out", str(mono)]) == 0
    recipe = load_config(REPO / "config" / "tiny.yaml")
    recipe.update(log_every=1, checkpoint_every=1000, steps=12)
    config = root / "tiny.yaml"
    config.write_text(yaml.safe_dump(recipe))
    torch.manual_seed(0)
    init = save_checkpoint(root / "init.safetensors", NOCaL(recipe["model"]), [CameraModel(32, 24)],
                           {"training_resolution": [32, 24]})
    return {"mono": mono, "colour": colour, "config": config, "init": init}


def test_pretraining_on_a_kitti_shaped_mono8_bag(tmp_path, shaped_bags):
    from nocal_ros.checkpoint import load_checkpoint

    out = tmp_path / "run"
    assert main(["train", "--config", str(shaped_bags["config"]), "--bag", str(shaped_bags["mono"]), "--out", str(out),
                 "--threads", "1", "--device", "cpu"]) == 0
    checkpoint = load_checkpoint(out / "model.safetensors")
    camera = checkpoint.cameras[0]
    assert (camera.width, camera.height) == (124, 38)  # the camera lives at native resolution
    metrics = np.genfromtxt(out / "metrics.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert np.isfinite(metrics["loss"]).all() and len(metrics) == 12
    assert metrics["photometric"][-4:].mean() < metrics["photometric"][:4].mean()


def test_fine_tuning_on_a_16_9_colour_bag(tmp_path, shaped_bags, capsys):
    from nocal_ros.checkpoint import load_checkpoint

    store = tmp_path / "store"
    assert main(["train", "--init", str(shaped_bags["init"]), "--bag", str(shaped_bags["colour"]), "--config",
                 str(shaped_bags["config"]), "--out", str(store), "--steps", "6", "--threads", "1", "--device", "cpu"]) == 0
    assert "published v0001" in capsys.readouterr().out
    camera = load_checkpoint(store).cameras[0]
    assert (camera.width, camera.height) == (128, 72)


def test_reading_a_bag_at_the_network_size_maps_frames_as_training_does(shaped_bags):
    """`nocal eval` reads bags this way: the frames the pose head is scored on are those it trains on."""
    native = read_sequence(shaped_bags["colour"], max_frames=3)
    mapped = read_sequence(shaped_bags["colour"], max_frames=3, network_size=(32, 24))
    assert mapped.images.shape == (3, 24, 32, 3) and mapped.extras["network_size"] == (32, 24)
    for frame, image in zip(native.images, mapped.images):
        np.testing.assert_array_equal(image, network_input(frame, (32, 24))[0])
    assert mapped.calibration == native.calibration  # intrinsics stay at native resolution
