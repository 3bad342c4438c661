"""Arm poses for live nodes: the hand-eye transform, and image stamps waiting for their TF arm pose.

A robot arm's driver publishes the tool's pose in the arm's base frame (``T_base_tool``), as a
``geometry_msgs/PoseStamped`` or on TF. The camera sits on the tool at the static hand-eye transform
``T_tool_cam``, so the camera's pose in the base frame is ``T_base_cam = T_base_tool @ T_tool_cam``.

TF describes the past: the transform at an image's stamp can be looked up only once TF data newer
than that stamp has arrived, which is usually after the image. :class:`PendingStamps` keeps the image
stamps whose pose could not be looked up yet and retries them, giving up on a stamp once images
``max_wait_s`` newer have arrived (stamp time, so it works the same in sim time and on replay).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from nocal_ros.errors import ConfigError


def hand_eye_matrix(values: Sequence[float]) -> np.ndarray:
    """``T_tool_cam`` from 16 row-major numbers; ConfigError unless it is a finite rigid transform."""
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size != 16 or not np.isfinite(array).all():
        raise ConfigError("T_tool_cam must be 16 finite numbers (a row-major 4x4 transform)")
    T = array.reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise ConfigError("T_tool_cam is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return T


class PendingStamps:
    """Image stamps waiting for an arm pose that TF does not hold yet.

    Thread-safe. ``lookup(stamp_ns)`` returns the pose at that stamp or None when TF cannot give it
    (yet); :meth:`resolve` calls it for every waiting stamp, oldest first.

    Args:
        max_wait_s: a stamp is given up once a stamp this much newer has been added.
        capacity: at most this many stamps wait (the oldest are given up first).
    """

    def __init__(self, max_wait_s: float = 0.5, capacity: int = 256) -> None:
        self.max_wait_ns = int(round(max_wait_s * 1e9))
        self._stamps: deque[int] = deque()
        self._capacity = int(capacity)
        self._lock = threading.Lock()
        self.resolved = 0
        self.given_up = 0

    def __len__(self) -> int:
        with self._lock:
            return len(self._stamps)

    def add(self, stamp_ns: int) -> None:
        with self._lock:
            self._stamps.append(int(stamp_ns))
            while len(self._stamps) > self._capacity:
                self._stamps.popleft()
                self.given_up += 1

    def resolve(self, lookup: Callable[[int], np.ndarray | None]) -> list[tuple[int, np.ndarray]]:
        """``(stamp_ns, pose)`` for every waiting stamp ``lookup`` can answer now; the others wait on
        unless they are ``max_wait_s`` older than the newest stamp."""
        with self._lock:
            stamps = list(self._stamps)
        if not stamps:
            return []
        newest = max(stamps)
        found, keep = [], []
        for stamp in stamps:
            pose = lookup(stamp)
            if pose is not None:
                found.append((stamp, pose))
            elif newest - stamp <= self.max_wait_ns:
                keep.append(stamp)
        with self._lock:
            added_meanwhile = list(self._stamps)[len(stamps):]
            self._stamps = deque(keep + added_meanwhile)
            self.resolved += len(found)
            self.given_up += len(stamps) - len(found) - len(keep)
        return found

    def clear(self) -> None:
        """Forget every waiting stamp (a reset, or the clock jumped back)."""
        with self._lock:
            self._stamps.clear()
