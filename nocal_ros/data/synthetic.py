"""Synthetic sequences: a random room, an arm trajectory and a known camera, rendered to a FrameSequence.

Deterministic: the same arguments give the same bytes. The seed is split into independent streams
(scene, trajectory, labelling), so e.g. changing the labelled fraction does not move the camera.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from nocal_ros.data.render import Renderer
from nocal_ros.data.scenes import random_room
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.data.trajectory import random_trajectory
from nocal_ros.lens import CameraCalibration

log = logging.getLogger(__name__)

# Stamps start at a fixed, realistic epoch (2023-11-14) rather than 0, which some ROS tools treat as unset.
FIRST_STAMP_NS = 1_700_000_000_000_000_000


def render_sequence(
    calibration: CameraCalibration,
    num_frames: int,
    seed: int,
    split: str = "train",
    fps: float = 10.0,
    speed: float = 0.3,
    angular_speed: float = 20.0,
    supersample: int = 1,
    labelled_fraction: float = 0.1,
    return_depth: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> FrameSequence:
    """Render ``num_frames`` of a random room (``seed``, ``split``) seen through ``calibration``.

    Args:
        calibration: the true camera; images are rendered at its size.
        speed, angular_speed: RMS camera speed in m/s and deg/s (see ``trajectory.py``).
        supersample: ``k x k`` rays per pixel.
        labelled_fraction: share of frames that get an arm pose, in contiguous runs (see
            :func:`labelled_frames`).
        return_depth: put per-frame depth ``(N, H, W)`` float32 (camera z, metres) in ``extras["depth"]``.
        progress: called as ``progress(done, total)`` after each frame.

    Returns:
        A FrameSequence with ``ground_truth`` = ``T_w_cam`` for every frame, ``arm_poses`` = the same
        poses on the labelled frames (NaN elsewhere), and ``calibration``.
    """
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if not 0.0 <= labelled_fraction <= 1.0:
        raise ValueError(f"labelled_fraction must be in [0, 1], got {labelled_fraction}")
    scene_seed, trajectory_seed, label_seed = np.random.SeedSequence(seed).spawn(3)
    scene = random_room(np.random.default_rng(scene_seed), split)
    trajectory = random_trajectory(
        np.random.default_rng(trajectory_seed), scene.workspace_centre, scene.workspace_radius,
        scene.look_yaw, speed=speed, angular_speed=angular_speed,
    )
    frame_period_ns = round(1e9 / fps)
    stamps_ns = FIRST_STAMP_NS + np.arange(num_frames, dtype=np.int64) * frame_period_ns
    poses = trajectory.poses((stamps_ns - FIRST_STAMP_NS) / 1e9)

    renderer = Renderer(scene, calibration, supersample=supersample)
    images = np.empty((num_frames, calibration.height, calibration.width, 3), dtype=np.uint8)
    depths = np.empty((num_frames, calibration.height, calibration.width), dtype=np.float32) if return_depth else None
    for i, pose in enumerate(poses):
        images[i], depth = renderer.render(pose, return_depth=return_depth)
        if depths is not None:
            depths[i] = depth
        if progress is not None:
            progress(i + 1, num_frames)

    labelled = labelled_frames(num_frames, labelled_fraction, np.random.default_rng(label_seed))
    arm_poses = np.full((num_frames, 4, 4), np.nan)
    arm_poses[labelled] = poses[labelled]

    extras = {"scene": scene.name, "seed": int(seed), "split": split, "fps": float(fps)}
    if depths is not None:
        extras["depth"] = depths
    return FrameSequence(images, stamps_ns, arm_poses, ground_truth=poses, calibration=calibration,
                         name=f"synthetic:{split}:seed={seed}", extras=extras)


def labelled_frames(num_frames: int, fraction: float, rng: np.random.Generator, run_length: int = 9) -> np.ndarray:
    """Indices of the frames that get an arm pose: ``fraction`` of them, in runs of ``run_length``.

    A pair is labelled only when both of its frames have poses, so isolated labelled frames would
    give almost no labelled pairs (10% of frames at random -> about 1% of pairs). An arm recording
    logs poses over stretches of motion, so runs are both the realistic and the useful layout; the
    default run covers the trainer's largest frame gap (8) plus one.
    """
    count = int(round(fraction * num_frames))
    if fraction > 0:
        count = max(count, 1)
    if count >= num_frames:
        return np.arange(num_frames)
    chosen = np.zeros(num_frames, dtype=bool)
    while chosen.sum() < count:
        length = min(run_length, count - int(chosen.sum()))
        start = int(rng.integers(0, num_frames - length + 1))
        chosen[start:start + length] = True
    return np.flatnonzero(chosen)


# Ranges random_calibration draws from (uniform unless said otherwise), as fractions of the width
# for focal length and of the size for the principal point offset.
FOCAL_RANGE = (0.5, 1.2)  # fx / width: 90 deg .. 45 deg horizontal field of view
ASPECT_RANGE = (0.97, 1.03)  # fy / fx
PRINCIPAL_OFFSET = 0.05  # |cx - centre| <= 5% of width, likewise cy
DISTORTION_STRENGTH = (0.0, 1.0)  # 0: pinhole, 1: strongest; k1 = -0.4 s (barrel) or +0.15 s (pincushion)


def random_calibration(
    rng: np.random.Generator,
    width: int,
    height: int,
    focal_range: tuple[float, float] = FOCAL_RANGE,
    max_strength: float = 1.0,
    camera_name: str = "synthetic",
) -> CameraCalibration:
    """A random plausible ``plumb_bob`` camera for pretraining across many cameras.

    Focal length ``fx = U(focal_range) * width``, ``fy = fx * U(0.97, 1.03)``; principal point within
    5% of the size from the centre; distortion strength ``s ~ U(0, max_strength)``: 70% barrel with
    ``k1 = -0.4 s U(0.5, 1)`` and ``k2 = 1.5 k1^2 U(0, 1)``, 30% pincushion with
    ``k1 = 0.15 s U(0.5, 1)`` and ``k2 = -0.3 k1 U(0, 1)``; tangential ``|p1|, |p2| <= 0.002 s``; ``k3 = 0``. Draws are rejected
    until every pixel of the image has a ray (no fold of the radial polynomial inside the image).
    """
    for _ in range(100):
        fx = rng.uniform(*focal_range) * width
        fy = fx * rng.uniform(*ASPECT_RANGE)
        cx = (width - 1) / 2 + rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET) * width
        cy = (height - 1) / 2 + rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET) * height
        strength = rng.uniform(0.0, max_strength)
        if rng.uniform() < 0.7:
            k1 = -0.4 * strength * rng.uniform(0.5, 1.0)
            k2 = 0.6 * k1 * k1 * rng.uniform(0.0, 1.0) / 0.4
        else:
            k1 = 0.15 * strength * rng.uniform(0.5, 1.0)
            k2 = -0.3 * k1 * rng.uniform(0.0, 1.0)
        p1, p2 = rng.uniform(-0.002, 0.002, 2) * strength
        camera = CameraCalibration(width, height, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                                   np.array([k1, k2, p1, p2, 0.0]), "plumb_bob", camera_name)
        if covers_image(camera):
            return camera
    raise RuntimeError("random_calibration: no valid camera in 100 draws; widen the ranges")


def covers_image(camera: CameraCalibration, samples: int = 48) -> bool:
    """True if every pixel of the image (checked on the border and a grid) has a lens ray."""
    u = np.linspace(0, camera.width - 1, samples)
    v = np.linspace(0, camera.height - 1, samples)
    grid = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    return bool(np.isfinite(camera.unproject(grid)).all())
