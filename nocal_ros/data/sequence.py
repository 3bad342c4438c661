"""FrameSequence: the in-memory form of one camera's recording, whatever it came from.

The synthetic renderer produces one, the bag reader produces one, and the pair datasets, the
trainer and the evaluation consume one, so synthetic and real recordings take the same code path.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration


@dataclass
class FrameSequence:
    """Images of one camera with stamps, and whatever poses are known.

    Attributes:
        images: ``(N, H, W, 3)`` uint8 RGB.
        stamps_ns: ``(N,)`` int64 nanoseconds, strictly increasing.
        arm_poses: ``(N, 4, 4)`` float64 camera poses ``T_base_cam`` from the arm (hand-eye applied);
            NaN where a frame has no arm pose. These are the labels training may use.
        ground_truth: ``(N, 4, 4)`` float64 true camera poses ``T_w_cam`` for evaluation only, or None.
        calibration: the true camera (evaluation only), or None when unknown.
        name: where the sequence came from (a bag path, a synthetic seed), for messages.
    """

    images: np.ndarray
    stamps_ns: np.ndarray
    arm_poses: np.ndarray
    ground_truth: np.ndarray | None = None
    calibration: "CameraCalibration | None" = None
    name: str = ""
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.images)
        if self.images.ndim != 4 or self.images.shape[-1] != 3 or self.images.dtype != np.uint8:
            raise ValueError(f"{self.name}: images must be (N, H, W, 3) uint8, got {self.images.shape} {self.images.dtype}")
        if self.stamps_ns.shape != (n,) or self.arm_poses.shape != (n, 4, 4):
            raise ValueError(f"{self.name}: stamps/arm_poses do not match {n} images")
        if self.ground_truth is not None and self.ground_truth.shape != (n, 4, 4):
            raise ValueError(f"{self.name}: ground_truth does not match {n} images")

    def __len__(self) -> int:
        return len(self.images)

    @property
    def labelled(self) -> np.ndarray:
        """``(N,)`` bool: frames that have an arm pose."""
        return np.isfinite(self.arm_poses).all(axis=(1, 2))

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of the images."""
        return int(self.images.shape[2]), int(self.images.shape[1])
