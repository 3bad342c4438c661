"""Arm-like camera trajectories: smooth motion in a small workspace, looking into the scene.

Position and viewing direction are sums of sinusoids with random amplitudes, frequencies and phases:
smooth at every order (like a well-tuned arm), bounded (the camera stays in its workspace ball and
keeps looking towards the scene's content), and never periodic over a sequence. Rotation happens about
all three axes: yaw and pitch of the viewing direction, and roll about it.

Speeds are root-mean-square over time and known in closed form: for ``a sin(w t + phi)`` the RMS rate
is ``a w / sqrt(2)``, so the frequencies are scaled to hit the requested ``speed`` (m/s) and
``angular_speed`` (deg/s, yaw/pitch/roll rates combined) exactly in expectation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nocal_ros.geometry import make_transform

_COMPONENTS = 3  # sinusoids per coordinate


@dataclass
class ArmTrajectory:
    """Camera poses ``T_w_c`` (optical frame: x right, y down, z forward) as a function of time."""

    centre: np.ndarray  # (3,) workspace centre, world frame (z up)
    position_amplitude: np.ndarray  # (3, C) metres
    position_frequency: np.ndarray  # (3, C) rad/s
    position_phase: np.ndarray  # (3, C)
    base_yaw: float
    base_pitch: float
    angle_amplitude: np.ndarray  # (3, C) radians: yaw, pitch, roll
    angle_frequency: np.ndarray  # (3, C) rad/s
    angle_phase: np.ndarray  # (3, C)

    def positions(self, times: np.ndarray) -> np.ndarray:
        t = np.asarray(times, dtype=np.float64)[:, None, None]
        offsets = (self.position_amplitude * np.sin(self.position_frequency * t + self.position_phase)).sum(-1)
        return self.centre + offsets

    def angles(self, times: np.ndarray) -> np.ndarray:
        """``(N, 3)`` yaw, pitch, roll in radians."""
        t = np.asarray(times, dtype=np.float64)[:, None, None]
        angles = (self.angle_amplitude * np.sin(self.angle_frequency * t + self.angle_phase)).sum(-1)
        return angles + np.array([self.base_yaw, self.base_pitch, 0.0])

    def poses(self, times: np.ndarray) -> np.ndarray:
        """``(N, 4, 4)`` float64 camera poses ``T_w_c`` at ``times`` (seconds)."""
        return np.stack([make_transform(camera_rotation(*angles), position)
                         for position, angles in zip(self.positions(times), self.angles(times))])


def camera_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Optical-frame camera orientation in a z-up world: looking along (yaw, pitch), rolled by ``roll``.

    Pitch is positive upwards; with zero roll the image's x axis stays horizontal.
    """
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    # roll about the optical axis: rotate x and y within the image plane
    x_axis, y_axis = c * right + s * down, -s * right + c * down
    return np.stack([x_axis, y_axis, forward], axis=1)


def _random_sinusoids(rng: np.random.Generator, amplitude: np.ndarray, rms_rate: float):
    """Random sinusoid sums per row with peak ``sum |a| = amplitude[row]``, scaled to an RMS rate."""
    weights = rng.uniform(0.3, 1.0, (len(amplitude), _COMPONENTS))
    amplitudes = amplitude[:, None] * weights / weights.sum(1, keepdims=True)
    # incommensurate relative frequencies, so the motion does not repeat within a sequence
    frequencies = rng.uniform(0.5, 1.5, amplitudes.shape) * np.array([1.0, 1.618, 2.414])
    phases = rng.uniform(-np.pi, np.pi, amplitudes.shape)
    rms = np.sqrt(((amplitudes * frequencies) ** 2).sum() / 2)
    return amplitudes, frequencies * (rms_rate / rms if rms > 0 else 0.0), phases


def random_trajectory(rng: np.random.Generator, centre: np.ndarray, radius: float = 0.35,
                      look_yaw: float = 0.0, speed: float = 0.3, angular_speed: float = 20.0,
                      yaw_range_deg: float = 45.0, pitch_range_deg: float = 20.0,
                      roll_range_deg: float = 25.0) -> ArmTrajectory:
    """A random arm trajectory around ``centre`` looking roughly along ``look_yaw``.

    Args:
        speed: RMS linear speed in m/s. At 10 fps the default 0.3 m/s moves ~3 cm a frame.
        angular_speed: RMS angular speed in deg/s (default 20: ~2 degrees a frame at 10 fps).
        radius: the camera stays within this distance of ``centre`` (each axis within radius/sqrt(3)).
        *_range_deg: peak deviation of yaw, pitch (from a slight downward tilt) and roll.
    """
    if speed < 0 or angular_speed < 0:
        raise ValueError("speed and angular_speed must be non-negative")
    position = _random_sinusoids(rng, np.full(3, radius / np.sqrt(3)), speed)
    angles = _random_sinusoids(rng, np.radians([yaw_range_deg, pitch_range_deg, roll_range_deg]),
                               np.radians(angular_speed))
    return ArmTrajectory(np.asarray(centre, dtype=np.float64), *position,
                         base_yaw=float(look_yaw), base_pitch=float(np.radians(-10.0)), angle_amplitude=angles[0],
                         angle_frequency=angles[1], angle_phase=angles[2])
