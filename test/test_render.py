"""The renderer images through the true lens: checked against OpenCV's projection and closed forms."""

import cv2
import numpy as np
import pytest

from nocal_ros.data.render import Renderer
from nocal_ros.data.scenes import Rectangle, Scene, random_room
from nocal_ros.data.synthetic import covers_image, random_calibration, render_sequence
from nocal_ros.data.textures import NATURAL_SOURCES, texture_bank
from nocal_ros.data.trajectory import random_trajectory
from nocal_ros.geometry import invert_transform, make_transform, so3_exp
from nocal_ros.lens import CameraCalibration

WHITE, BLACK = 0, 1
STRONG_CAMERA = CameraCalibration(
    160, 120, np.array([[92.0, 0, 81.3], [0, 91.0, 58.2], [0, 0, 1]]), [-0.34, 0.11, 0.002, -0.0015, 0.0], "plumb_bob"
)
FISHEYE_CAMERA = CameraCalibration(
    160, 120, np.array([[75.0, 0, 80.4], [0, 75.0, 59.1], [0, 0, 1]]), [0.03, -0.01, 0.002, -0.0005], "equidistant"
)


def marker_scene(T_w_c, marker_pixels, camera, wall_depth=3.0, marker_size=0.12):
    """A white wall facing the camera and small black squares whose centres image at ``marker_pixels``."""
    textures = np.stack([np.ones((4, 4, 3)), np.zeros((4, 4, 3))]).astype(np.float32)
    R, o = T_w_c[:3, :3], T_w_c[:3, 3]
    right, down, forward = R[:, 0], R[:, 1], R[:, 2]
    rectangles = [Rectangle.centred(o + wall_depth * forward, 20 * right, -20 * down, texture=WHITE)]
    centres = []
    for pixel in marker_pixels:
        ray = camera.unproject(np.asarray(pixel, dtype=np.float64)[None])[0]
        centre_cam = ray * (wall_depth - 0.01) / ray[2]
        centre = o + R @ centre_cam
        # grow off-axis markers (farther along the ray, foreshortened) so each covers a few pixels
        half = marker_size / 2 / ray[2] ** 2
        rectangles.append(Rectangle.centred(centre, half * right, -half * down, texture=BLACK))
        centres.append(centre)
    return Scene(rectangles, textures), np.array(centres)


def opencv_pixels(points_w, T_w_c, camera):
    """Independent reference: OpenCV's projection of world points through the camera at ``T_w_c``."""
    T_c_w = invert_transform(T_w_c)
    rvec, _ = cv2.Rodrigues(T_c_w[:3, :3])
    if camera.distortion_model == "equidistant":
        pixels, _ = cv2.fisheye.projectPoints(points_w[:, None], rvec, T_c_w[:3, 3], camera.K, camera.D)
    else:
        pixels, _ = cv2.projectPoints(points_w, rvec, T_c_w[:3, 3], camera.K, camera.D)
    return pixels.reshape(-1, 2)


@pytest.mark.parametrize("camera", [STRONG_CAMERA, FISHEYE_CAMERA], ids=["plumb_bob", "equidistant"])
def test_markers_render_where_opencv_projects_them(camera):
    T_w_c = make_transform(so3_exp([0.2, -0.5, 0.3]), [1.0, 2.0, 1.5])
    # centre, edges and corners, where distortion moves points by many pixels
    targets = [(80, 60), (12, 10), (148, 9), (11, 110), (150, 111), (40, 30), (120, 90), (80, 8), (152, 60)]
    scene, centres = marker_scene(T_w_c, targets, camera)
    image, _ = Renderer(scene, camera, supersample=3).render(T_w_c)
    darkness = 1.0 - image.astype(np.float64).mean(-1) / 255.0
    expected = opencv_pixels(centres, T_w_c, camera)
    pinhole_shift = []
    for (u, v), centre in zip(expected, centres):
        window = (slice(int(v) - 6, int(v) + 7), slice(int(u) - 6, int(u) + 7))
        weights = darkness[window]
        assert weights.sum() > 1.0, "marker not rendered"
        vv, uu = np.mgrid[window]
        centroid = np.array([(weights * uu).sum(), (weights * vv).sum()]) / weights.sum()
        assert np.linalg.norm(centroid - [u, v]) < 0.5
        pinhole = CameraCalibration(camera.width, camera.height, camera.K, np.zeros(5)).project(
            (invert_transform(T_w_c) @ np.append(centre, 1))[None, :3])[0]
        pinhole_shift.append(np.linalg.norm(pinhole - [u, v]))
    # the test has teeth: ignoring the distortion would put corner markers many pixels off
    assert max(pinhole_shift) > 5.0


def test_depth_lies_on_the_rendered_surfaces():
    camera = STRONG_CAMERA
    T_w_c = make_transform(so3_exp([0.1, 0.2, -0.4]), [0.3, -0.2, 1.0])
    scene, centres = marker_scene(T_w_c, [(80, 60)], camera, wall_depth=2.5)
    _, depth = Renderer(scene, camera, supersample=2).render(T_w_c, return_depth=True)
    assert np.isfinite(depth).all()
    pixels = np.stack(np.meshgrid(np.arange(160.0), np.arange(120.0)), -1).reshape(-1, 2)
    rays = camera.unproject(pixels)
    points_cam = rays * (depth.reshape(-1) / rays[:, 2])[:, None]
    # every 3D point lies on the wall (z = 2.5 in the camera) or on the marker just in front of it
    on_wall = np.abs(points_cam[:, 2] - 2.5) < 1e-4
    on_marker = np.abs(points_cam[:, 2] - 2.49) < 1e-4
    assert (on_wall | on_marker).all() and on_marker.sum() >= 4
    # and reprojects to its own pixel through OpenCV
    points_w = (T_w_c[:3, :3] @ points_cam.T).T + T_w_c[:3, 3]
    assert np.abs(opencv_pixels(points_w[::97], T_w_c, camera) - pixels[::97]).max() < 1e-3


def test_occlusion_nearest_surface_wins_and_back_faces_are_culled():
    textures = np.stack([np.ones((2, 2, 3)), np.zeros((2, 2, 3))]).astype(np.float32)
    camera = CameraCalibration.pinhole(32, 24, fx=30.0)
    # a black square 2 m away in front of a white wall 4 m away; camera looks along +z
    wall = Rectangle.centred([0, 0, 4.0], [5, 0, 0], [0, -5, 0], texture=WHITE)
    near = Rectangle.centred([0, 0, 2.0], [0.3, 0, 0], [0, -0.3, 0], texture=BLACK)
    image, depth = Renderer(Scene([wall, near], textures), camera).render(np.eye(4), return_depth=True)
    assert image[12, 16].max() == 0 and image[0, 0].min() == 255
    assert depth[12, 16] == pytest.approx(2.0, abs=1e-5) and depth[0, 0] == pytest.approx(4.0, abs=1e-5)
    # the same square turned away from the camera is invisible (one-sided)
    back = Rectangle.centred([0, 0, 2.0], [0.3, 0, 0], [0, 0.3, 0], texture=BLACK)
    image, _ = Renderer(Scene([wall, back], textures), camera).render(np.eye(4))
    assert image.min() == 255


def test_render_sequence_is_deterministic_and_seeded():
    camera = STRONG_CAMERA.scaled(64, 48)
    first = render_sequence(camera, 4, seed=11, labelled_fraction=0.5)
    second = render_sequence(camera, 4, seed=11, labelled_fraction=0.5)
    other = render_sequence(camera, 4, seed=12, labelled_fraction=0.5)
    assert first.images.tobytes() == second.images.tobytes()
    assert np.array_equal(first.ground_truth, second.ground_truth)
    assert np.array_equal(first.labelled, second.labelled) and first.labelled.sum() == 2
    assert first.images.tobytes() != other.images.tobytes()
    assert np.allclose(first.arm_poses[first.labelled], first.ground_truth[first.labelled])
    assert first.calibration == camera and first.image_size == (64, 48)
    assert np.all(np.diff(first.stamps_ns) == 100_000_000)


def test_train_and_test_textures_are_disjoint():
    train, train_names = texture_bank("train")
    test, test_names = texture_bank("test")
    assert not set(NATURAL_SOURCES["train"]) & set(NATURAL_SOURCES["test"])
    assert not set(train_names) & set(test_names)
    small = lambda bank: np.stack([cv2.resize(t, (32, 32), interpolation=cv2.INTER_AREA) for t in bank])
    a, b = small(train), small(test)
    difference = np.abs(a[:, None] - b[None]).mean(axis=(2, 3, 4))
    assert difference.min() > 0.05
    # a test scene only uses test textures
    scene = random_room(5, "test")
    assert all(np.abs(test - texture).max(axis=(1, 2, 3)).min() == 0 for texture in scene.textures)
    # textures carry detail at the scales an 80x60 view samples (no flat, featureless surfaces)
    for texture in np.concatenate([train, test]):
        coarse = cv2.resize(texture, (32, 32), interpolation=cv2.INTER_AREA)
        assert coarse.std() > 0.05


def test_trajectory_stays_in_free_space_looks_at_content_and_has_the_requested_speed():
    for seed in range(3):
        rng = np.random.default_rng(seed)
        scene = random_room(rng, "train")
        trajectory = random_trajectory(rng, scene.workspace_centre, scene.workspace_radius, scene.look_yaw,
                                       speed=0.3, angular_speed=20.0)
        times = np.arange(0, 120, 0.01)
        positions = trajectory.positions(times)
        assert np.linalg.norm(positions - scene.workspace_centre, axis=1).max() <= scene.workspace_radius + 1e-9
        # well clear of the walls; the arm works at table height, at least half a metre from floor and ceiling
        assert (positions[:, :2] > 0.9).all() and (positions[:, :2] < scene.room_size[:2] - 0.9).all()
        assert (positions[:, 2] > 0.5).all() and (positions[:, 2] < scene.room_size[2] - 0.5).all()
        speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / 0.01
        assert np.sqrt((speed**2).mean()) == pytest.approx(0.3, rel=0.1)
        rates = np.degrees(np.diff(trajectory.angles(times), axis=0) / 0.01)
        assert np.sqrt((rates**2).sum(1).mean()) == pytest.approx(20.0, rel=0.1)
        # rotation about all three axes over the sequence
        assert (np.ptp(trajectory.angles(times), axis=0) > np.radians(10)).all()
        # the view centre meets content at a reasonable distance (not a wall 5 cm away)
        camera = CameraCalibration.pinhole(16, 12, fx=12.0)
        renderer = Renderer(scene, camera)
        for pose in trajectory.poses(times[::1000]):
            _, depth = renderer.render(pose, return_depth=True)
            assert np.isfinite(depth).all() and np.nanmin(depth) > 0.3 and depth[6, 8] > 0.7


def test_random_calibration_is_diverse_valid_and_deterministic():
    cameras = [random_calibration(np.random.default_rng(seed), 80, 60) for seed in range(20)]
    again = random_calibration(np.random.default_rng(3), 80, 60)
    assert again == cameras[3]
    focal = np.array([c.fx for c in cameras]) / 80
    assert focal.min() >= 0.5 and focal.max() <= 1.2 and np.ptp(focal) > 0.3
    k1 = np.array([c.D[0] for c in cameras])
    assert k1.min() < -0.15 and np.abs(k1).min() < 0.05
    assert all(covers_image(c) for c in cameras)
    assert all(abs(c.cx - 39.5) <= 4.0 and abs(c.cy - 29.5) <= 3.0 for c in cameras)
