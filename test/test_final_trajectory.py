"""The trajectory through the final map and camera (nocal_ros.odometry.trajectory and
OdometryEstimator.final_trajectory): frames posed again at the end of a replay."""

from __future__ import annotations

import cv2
import numpy as np

from nocal_ros.geometry import invert_transform
from nocal_ros.lens import CameraCalibration
from nocal_ros.odometry.map import LocalMap
from nocal_ros.odometry.trajectory import FrameRecord, final_map_poses

CAMERA = CameraCalibration(320, 240, np.array([[250.0, 0, 162.0], [0, 248.0, 118.0], [0, 0, 1]]),
                           np.array([-0.2, 0.05, 0.001, -0.0005, 0.0]), "plumb_bob", "test")


def pose(rotation_vector, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotation_vector, dtype=np.float64))[0]
    T[:3, 3] = translation
    return T


def opencv_pixels(T_w_c: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """The landmarks' pixels through CAMERA, projected by OpenCV (the independent reference)."""
    T_c_w = invert_transform(T_w_c)
    rvec = cv2.Rodrigues(T_c_w[:3, :3])[0]
    pixels, _ = cv2.projectPoints(points_w, rvec, T_c_w[:3, 3], CAMERA.K, CAMERA.D)
    return pixels.reshape(-1, 2)


def test_frames_are_posed_again_on_the_final_landmarks_through_the_final_camera():
    rng = np.random.default_rng(3)
    points = np.column_stack((rng.uniform(-1.5, 1.5, 150), rng.uniform(-1.0, 1.0, 150), rng.uniform(3.0, 6.0, 150)))
    ids = np.arange(150, dtype=np.int64)
    local_map = LocalMap()
    first = local_map.add_keyframe(0, 0, np.eye(4), ids, opencv_pixels(np.eye(4), points))
    local_map.landmarks.update({int(i): p for i, p in zip(ids, points)})

    T_true = pose([0.02, -0.05, 0.01], [0.12, -0.03, 0.05])
    # Tracked through a wrong camera, the frame's pose relative to its keyframe was 2 deg and 4 cm off.
    T_tracked = T_true @ pose([0.0, 0.035, 0.0], [0.04, 0.0, 0.0])
    pnp_record = FrameRecord(5, 1, local_map, first, T_tracked, ids, opencv_pixels(T_true, points))
    # Only 8 of its tracks have landmarks: too few to pose it again.
    few = np.arange(1000, 1150, dtype=np.int64)
    few[:8] = ids[:8]
    relative_record = FrameRecord(6, 1, local_map, first, T_tracked, few, opencv_pixels(T_true, points))
    keyframe_record = FrameRecord(0, 1, local_map, first, np.eye(4), ids, first.pixels)
    # Frames of an initialisation reference given up before the map was made: no pose relative to it.
    orphan_record = FrameRecord(2, 1, local_map, first, None, ids, opencv_pixels(T_true, points))
    orphan_unposeable = FrameRecord(3, 1, local_map, first, None, few, opencv_pixels(T_true, points))
    # Bundle adjustment moved the keyframe after the frames were tracked.
    moved = pose([0.001, 0.0, 0.0], [0.0, 0.001, 0.0])
    first.T_w_c = moved.copy()

    poses = final_map_poses([pnp_record, relative_record, keyframe_record, orphan_record, orphan_unposeable],
                            CAMERA, pixel_threshold=1.0)

    assert poses[5].how == "pnp"
    np.testing.assert_allclose(poses[5].T_map_cam, T_true, atol=1e-6)
    assert poses[6].how == "keyframe_relative"
    np.testing.assert_allclose(poses[6].T_map_cam, moved @ T_tracked, atol=1e-12)
    assert poses[0].how == "keyframe"
    np.testing.assert_allclose(poses[0].T_map_cam, moved, atol=1e-12)
    assert poses[2].how == "pnp"
    np.testing.assert_allclose(poses[2].T_map_cam, T_true, atol=1e-6)
    assert 3 not in poses  # left at its published motion
    assert all(p.map_id == 1 and p.local_map is local_map for p in poses.values())


def test_a_map_moved_into_other_units_moves_its_frames_with_it():
    """LocalMap.transform against its closed form, and a frame's keyframe-relative pose follows it."""
    local_map = LocalMap()
    first = local_map.add_keyframe(0, 0, pose([0.1, 0.0, 0.0], [0.2, 0.0, 0.1]), np.arange(3), np.zeros((3, 2)))
    local_map.landmarks[1] = np.array([0.5, -0.2, 3.0])
    T_tracked = pose([0.0, 0.02, 0.0], [0.05, 0.01, 0.0])
    record = FrameRecord(4, 1, local_map, first, T_tracked, np.arange(3), np.zeros((3, 2)), local_map.unit_scale)
    before = first.T_w_c.copy()
    R, t = cv2.Rodrigues(np.array([0.0, 0.3, 0.1]))[0], np.array([1.0, -2.0, 0.5])
    local_map.transform(2.5, R, t)
    np.testing.assert_allclose(first.T_w_c[:3, :3], R @ before[:3, :3], atol=1e-12)
    np.testing.assert_allclose(first.T_w_c[:3, 3], 2.5 * R @ before[:3, 3] + t, atol=1e-12)
    np.testing.assert_allclose(local_map.landmarks[1], 2.5 * R @ np.array([0.5, -0.2, 3.0]) + t, atol=1e-12)
    assert local_map.unit_scale == 2.5
    moved = final_map_poses([record], CAMERA, pixel_threshold=1.0)[4]
    assert moved.how == "keyframe_relative"
    # The same similarity applied to the frame's pose as it was: T_w_ref @ T_kf_cam, both moved.
    expected = np.eye(4)
    expected[:3, :3] = R @ (before @ T_tracked)[:3, :3]
    expected[:3, 3] = 2.5 * R @ (before @ T_tracked)[:3, 3] + t
    np.testing.assert_allclose(moved.T_map_cam, expected, atol=1e-12)


def test_a_map_made_after_a_loss_is_placed_in_the_map_before_it_through_their_shared_landmarks():
    """Two maps of one scene, the second in another frame and unit (a monocular map made after tracking
    was lost), sharing 40 track ids: map_similarity recovers the similarity between them (closed form),
    ignoring shared ids whose landmark one map placed badly, and link_maps moves the second map's frames
    into the first; with too few shared landmarks nothing is linked."""
    from nocal_ros.odometry.trajectory import FinalPose, link_maps, map_similarity

    rng = np.random.default_rng(4)
    points = rng.uniform([-2, -1, 3], [2, 1, 7], (60, 3))
    s, R, t = 0.4, cv2.Rodrigues(np.array([0.1, -0.4, 0.2]))[0], np.array([0.5, 0.1, -1.0])
    older, newer = LocalMap(), LocalMap()
    for landmark_id in range(0, 50):
        older.landmarks[landmark_id] = points[landmark_id]
    for landmark_id in range(10, 60):  # ids 10..49 in both; x_older = s R x_newer + t
        newer.landmarks[landmark_id] = R.T @ (points[landmark_id] - t) / s
    newer.landmarks[12] = newer.landmarks[12] + 3.0  # one badly placed landmark
    found = map_similarity(older, newer)
    assert found is not None
    np.testing.assert_allclose(found[0], s, rtol=1e-9)
    np.testing.assert_allclose(found[1], R, atol=1e-9)
    np.testing.assert_allclose(found[2], t, atol=1e-9)

    older.add_keyframe(0, 0, np.eye(4), np.arange(3), np.zeros((3, 2)))
    newer.add_keyframe(9, 0, np.eye(4), np.arange(3), np.zeros((3, 2)))
    T_true = pose([0.05, 0.2, 0.0], [0.3, 0.0, 0.2])  # a frame of the second map, in the first map's frame
    in_newer = np.eye(4)
    in_newer[:3, :3] = R.T @ T_true[:3, :3]
    in_newer[:3, 3] = R.T @ (T_true[:3, 3] - t) / s
    poses = {0: FinalPose(1, older, np.eye(4), "keyframe"), 9: FinalPose(2, newer, in_newer, "pnp")}
    linked = link_maps(poses)
    assert linked[9].map_id == 1 and linked[9].how == "pnp"
    np.testing.assert_allclose(linked[9].T_map_cam, T_true, atol=1e-9)
    assert link_maps(poses, exclude={2})[9].map_id == 2  # a map made metric by the arm stays in its frame
    # A map distorted by a wrong camera (depths stretched by half) agrees with no similarity: not linked.
    distorted = LocalMap()
    distorted.landmarks.update({i: p * np.array([1.0, 1.0, 1.5]) for i, p in newer.landmarks.items()})
    assert map_similarity(older, distorted) is None
    for landmark_id in range(10, 40):
        del newer.landmarks[landmark_id]  # 10 shared ids left
    assert map_similarity(older, newer) is None and link_maps(poses)[9].map_id == 2


def test_a_landmark_seen_again_under_a_new_track_is_fused_into_the_old_one():
    """Landmark 1's track ends at keyframe 1; landmark 7 is the same point (1 mm off) found again at
    keyframe 2: fused. Landmark 8 projects onto the same pixel there but lies 20 % deeper: kept. Landmark
    9 is landmark 3's point at keyframe 2 but 5 px off it at keyframe 3 (a mismatch): kept. Pixels are
    OpenCV's projections through CAMERA."""
    from nocal_ros.odometry.local_mapping import fuse_landmarks

    poses = [pose([0.0, 0.02 * k, 0.0], [0.1 * k, 0.0, 0.0]) for k in range(4)]
    P, S = np.array([0.2, -0.1, 4.0]), np.array([-0.6, 0.3, 5.0])
    centre = poses[2][:3, 3]
    Q = centre + 1.2 * (P - centre)  # on keyframe 2's ray through P, 20 % deeper
    points = {1: P, 3: S, 7: P + 0.001, 8: Q, 9: S}
    seen_by = {1: (0, 1), 3: (0, 1), 7: (2, 3), 8: (2, 3), 9: (2, 3)}
    local_map = LocalMap()
    for k, T in enumerate(poses):
        ids = np.array(sorted(i for i, rows in seen_by.items() if k in rows))
        pixels = opencv_pixels(T, np.array([points[i] for i in ids]))
        if k == 3:
            pixels[list(ids).index(9)] += 5.0
        local_map.add_keyframe(k, k, T, ids, pixels)
    local_map.landmarks.update(points)

    merged = fuse_landmarks(local_map, CAMERA, pixel_threshold=1.5)

    assert merged == {7: 1}
    assert 7 not in local_map.landmarks and {1, 3, 8, 9} <= set(local_map.landmarks)
    for keyframe in local_map.keyframes[2:]:
        assert keyframe.ids.tolist() == [1, 8, 9] and (np.diff(keyframe.ids) > 0).all()
        found, rows = keyframe.lookup(np.array([1]))
        np.testing.assert_allclose(keyframe.pixels[rows[0]], opencv_pixels(keyframe.T_w_c, (P + 0.001)[None])[0])


def plane_image(T_w_c: np.ndarray, K: np.ndarray, size: tuple[int, int], texture: np.ndarray, depth: float,
                texel_m: float) -> np.ndarray:
    """A pinhole camera's grey image of the textured plane z = ``depth`` (exact ray casting, bilinear)."""
    width, height = size
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack(((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)), -1) @ T_w_c[:3, :3].T
    along = (depth - T_w_c[2, 3]) / rays[..., 2]
    x = T_w_c[0, 3] + along * rays[..., 0]
    y = T_w_c[1, 3] + along * rays[..., 1]
    centre = (np.array(texture.shape[::-1]) - 1) / 2.0
    map_x = (x / texel_m + centre[0]).astype(np.float32)
    map_y = (y / texel_m + centre[1]).astype(np.float32)
    return cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR)


def test_search_by_projection_finds_the_landmarks_a_keyframe_never_tracked_where_they_are():
    """Keyframe 0 observes corners of a textured plane; keyframes 1 and 2 (moved 8 and 15 cm, turned)
    observed none of them. Searched for by projection, they are found in both within 0.1 px of their
    true pixels (the exact projection of the plane point), at the tracker's work size or half of it; a
    landmark whose position is 5 cm off (its projection 15 px from its texture) is not added anywhere."""
    from nocal_ros.odometry.local_mapping import search_by_projection

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur((rng.random((1200, 1200)) * 255).astype(np.float32), (0, 0), 2.0)
    K = np.array([[300.0, 0, 160.0], [0, 300.0, 120.0], [0, 0, 1]])
    camera = CameraCalibration(320, 240, K, np.zeros(5), "plumb_bob", "test")
    depth, texel = 1.5, 0.002
    poses = [np.eye(4), pose([0.0, 0.03, 0.01], [0.08, 0.02, 0.0]), pose([0.02, -0.04, 0.0], [-0.12, 0.09, 0.05])]
    native = [plane_image(T, K, (320, 240), texture, depth, texel) for T in poses]
    corners = cv2.goodFeaturesToTrack(native[0].astype(np.uint8), 80, 0.01, 12).reshape(-1, 2).astype(np.float64)
    points = np.column_stack(((corners - K[:2, 2]) / K[0, 0] * depth, np.full(len(corners), depth)))
    decoy = len(points)
    points = np.vstack((points, points[5] + [0.05, 0.0, 0.0]))
    pixels0 = np.vstack((corners, corners[5]))
    for scale in (1, 2):
        local_map = LocalMap()
        local_map.add_keyframe(0, 0, poses[0], np.arange(len(points)), pixels0)
        for k in (1, 2):
            local_map.add_keyframe(k, k, poses[k], np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        local_map.landmarks.update(dict(enumerate(points)))
        images = {k: cv2.resize(image, (320 // scale, 240 // scale), interpolation=cv2.INTER_AREA).astype(np.uint8)
                  for k, image in enumerate(native)}

        added = search_by_projection(local_map, camera, images, pixel_threshold=1.5, work_scale=(scale, scale))

        assert added == sum(len(kf.ids) for kf in local_map.keyframes[1:])
        for keyframe in local_map.keyframes[1:]:
            truth = opencv_pixels_pinhole(keyframe.T_w_c, points[keyframe.ids], K)
            visible = ((opencv_pixels_pinhole(keyframe.T_w_c, points[:decoy], K) > 10)
                       & (opencv_pixels_pinhole(keyframe.T_w_c, points[:decoy], K) < [310, 230])).all(1).sum()
            assert decoy not in keyframe.ids.tolist()
            assert len(keyframe.ids) >= 0.8 * visible and (np.diff(keyframe.ids) > 0).all()
            errors = np.linalg.norm(keyframe.pixels - truth, axis=1)
            assert np.median(errors) < 0.1 * scale and errors.max() < 1.5


def opencv_pixels_pinhole(T_w_c: np.ndarray, points_w: np.ndarray, K: np.ndarray) -> np.ndarray:
    T_c_w = invert_transform(T_w_c)
    pixels, _ = cv2.projectPoints(points_w, cv2.Rodrigues(T_c_w[:3, :3])[0], T_c_w[:3, 3], K, np.zeros(5))
    return pixels.reshape(-1, 2)
