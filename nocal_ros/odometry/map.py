"""The local map: keyframes with the tracks they saw, and landmarks triangulated from them.

A landmark has the id of the track it came from (track ids never repeat), so a keyframe's observations
are simply the ``(id, pixel)`` pairs of the tracks alive in it, whether or not they have a landmark yet.
Poses and landmarks are in the map's own frame and scale (monocular: the scale is fixed once, at
initialisation; :mod:`nocal_ros.odometry.scale` maps it to metres).

The tracking thread reads the map (landmark positions for PnP), the mapping thread writes it (new
keyframes' landmarks, bundle adjustment): every access goes through the map's lock.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass
class Keyframe:
    """A frame kept for mapping.

    Attributes:
        index: the keyframe's number in its map (0, 1, ...).
        frame: the stream's frame counter at this keyframe.
        stamp_ns: the frame's stamp.
        T_w_c: ``(4, 4)`` camera pose in the map frame.
        ids: ``(N,)`` increasing track ids seen in this frame.
        pixels: ``(N, 2)`` their native pixels.
        map_version: the map's :attr:`LocalMap.version` that ``T_w_c`` was measured in.
    """

    index: int
    frame: int
    stamp_ns: int
    T_w_c: np.ndarray
    ids: np.ndarray
    pixels: np.ndarray
    map_version: int = 0

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of ``ids`` in this keyframe: ``(found mask (len(ids),), rows of the found ones)``."""
        ids = np.asarray(ids, dtype=np.int64)
        rows = np.searchsorted(self.ids, ids)
        rows = np.clip(rows, 0, max(len(self.ids) - 1, 0))
        found = (self.ids[rows] == ids) if len(self.ids) else np.zeros(len(ids), dtype=bool)
        return found, rows[found]


@dataclass
class LocalMap:
    """Keyframes (oldest first) and landmarks (id -> position) of one map."""

    keyframes: list[Keyframe] = field(default_factory=list)
    landmarks: dict[int, np.ndarray] = field(default_factory=dict)
    lock: threading.RLock = field(default_factory=threading.RLock)
    #: Counts the changes applied (bundle adjustments, similarity moves): tracking poses its previous frame
    #: again when it changed, and local mapping a keyframe posed in an older version.
    version: int = 0
    #: What the camera was known to be before this map's first keyframe was mapped, ``(mean parameters
    #: (8,), information (8, 8))`` (``OnlineCamera.begin_map``): the prior of the map's camera
    #: initialisations, which hold none of the earlier maps' observations. None: the starting camera's.
    camera_start: tuple[np.ndarray, np.ndarray] | None = None
    #: The map's unit now in units of the map as it was made (:meth:`transform` changes it).
    unit_scale: float = 1.0

    def landmark_positions(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(mask (N,), positions (M, 3))`` of the ids that have a landmark."""
        keys = np.asarray(ids).tolist()
        with self.lock:
            landmarks = self.landmarks
            mask = np.array([key in landmarks for key in keys], dtype=bool)
            positions = np.array([landmarks[key] for key in keys if key in landmarks]).reshape(-1, 3)
        return mask, positions

    def add_keyframe(self, frame: int, stamp_ns: int, T_w_c: np.ndarray, ids: np.ndarray, pixels: np.ndarray,
                     map_version: int | None = None) -> Keyframe:
        """``map_version``: the version ``T_w_c`` was measured in (default: the map's version now)."""
        with self.lock:
            order = np.argsort(ids, kind="stable")
            keyframe = Keyframe(len(self.keyframes), frame, stamp_ns, np.array(T_w_c, dtype=np.float64),
                                np.asarray(ids, dtype=np.int64)[order], np.asarray(pixels, dtype=np.float64)[order],
                                self.version if map_version is None else int(map_version))
            self.keyframes.append(keyframe)
            return keyframe

    def window(self, size: int) -> list[Keyframe]:
        with self.lock:
            return list(self.keyframes[-size:])

    def transform(self, scale: float, R: np.ndarray, t: np.ndarray) -> None:
        """Move the whole map by the similarity ``x -> scale R x + t`` (keyframes and landmarks)."""
        with self.lock:
            for keyframe in self.keyframes:
                T = np.eye(4)
                T[:3, :3] = R @ keyframe.T_w_c[:3, :3]
                T[:3, 3] = scale * R @ keyframe.T_w_c[:3, 3] + t
                keyframe.T_w_c = T
            for landmark_id, point in self.landmarks.items():
                self.landmarks[landmark_id] = scale * R @ point + t
            self.unit_scale *= scale
            self.version += 1

    def remove_observations(self, keyframe: Keyframe, ids: np.ndarray) -> None:
        """Drop some observations from a keyframe (outliers found by bundle adjustment)."""
        with self.lock:
            keep = ~np.isin(keyframe.ids, ids)
            keyframe.ids, keyframe.pixels = keyframe.ids[keep], keyframe.pixels[keep]


def triangulate(T_w_ci: np.ndarray, T_w_cj: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Points ``(N, 3)`` in the world from undistorted normalised points ``(N, 2)`` in two cameras (linear DLT).

    NaN where the solution is at infinity.
    """
    P_i = np.linalg.inv(T_w_ci)[:3]
    P_j = np.linalg.inv(T_w_cj)[:3]
    X = cv2.triangulatePoints(P_i, P_j, np.ascontiguousarray(x_i, dtype=np.float64).T,
                              np.ascontiguousarray(x_j, dtype=np.float64).T)
    w = np.where(np.abs(X[3]) > 1e-12, X[3], np.nan)
    return (X[:3] / w).T


def parallax_deg(T_w_ci: np.ndarray, T_w_cj: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Angle ``(N,)`` in degrees between the rays from the two camera centres to each point."""
    a = points_w - T_w_ci[:3, 3]
    b = points_w - T_w_cj[:3, 3]
    cosine = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-300)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
