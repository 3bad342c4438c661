"""How a camera frame of any size and shape becomes the network's fixed-size input, with the exact map
between the network's pixels and the camera's native pixels.

The network takes images of one size (the checkpoint's training resolution, 80x60: 4:3). Cameras are
4:3, 16:9, 5:4 or 3.3:1 (KITTI), mono8 or colour. :func:`network_input` is the one place a frame is
mapped onto the network's input; :func:`input_mapping` gives the same map without an image, and
:meth:`~nocal_ros.camera.CameraModel.native_coordinates` uses it to turn network pixels into native
pixels, so the rays the network's pixels are rendered with are the rays of the native pixels they
show, and the camera's intrinsics stay at native resolution, exact.

The mapping is the **whole frame, resized** to the network's size (``cv2.INTER_AREA``;
``cv2.INTER_LINEAR`` for the rare camera smaller than the network's input): a frame of another
aspect ratio is stretched, and the map keeps each axis' own scale, so it stays exact. Why not a
centred crop to 4:3 or padding to 4:3 (``scripts/input_mapping/``; numbers in docs/RESULTS.md,
"Cameras of any shape"): padding leaves a KITTI frame 40 % of the network's pixels and more than
tripled the shipped pose head's rotation error on rendered 3.3:1 cameras. Fine-tuned from the
shipped model on rendered 3.3:1 cameras (4 seeds), the crop and the whole frame tied on the lens
(dr), the photometric loss and the pose head, but the crop's focal error was larger on every seed
(0.42 % against 0.16 % on average); the crop's photometric loss never sees the sides of the frame.
A 4:3 frame is resized as before by every mapping.

Pixel centres are at integer coordinates (OpenCV). The network image covers the native window
``[x0, x0 + width) x [y0, y0 + height)`` (pixel edges, integers), so a resize by ``s = width / w``
maps the network pixel centre ``u`` to the native point ``x0 + (u + 0.5) * s - 0.5``, the centre of
the box of native pixels it averages, likewise for ``v``. That is exact for whole-number scales
(640x480 -> 80x60). At other scales INTER_AREA weighs a native pixel the box covers in part by its
coverage, which moves the footprint's centroid off the box centre by at most ``1 / (8 s)`` native
pixels (0.008 px for KITTI's 15.5 horizontally, 0.016 px for its 6.27 vertically;
test/test_any_shape.py measures it against OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np


@dataclass(frozen=True)
class InputMapping:
    """The affine map between network pixels and native pixels of one (native size, network size).

    Attributes:
        native_size: ``(W, H)`` of the camera's frames.
        network_size: ``(w, h)`` of the network's input.
        window: ``(x0, y0, width, height)``: the native window, in pixel edges, that the network image
            covers (the whole frame for :func:`input_mapping`; a crop in the measurement scripts).
            Integers; inside the image.
    """

    native_size: tuple[int, int]
    network_size: tuple[int, int]
    window: tuple[int, int, int, int]

    @property
    def scale(self) -> tuple[float, float]:
        """Native pixels per network pixel, ``(sx, sy)``."""
        return self.window[2] / self.network_size[0], self.window[3] / self.network_size[1]

    @property
    def is_identity(self) -> bool:
        return tuple(self.native_size) == tuple(self.network_size)

    def to_native(self, u: Any, v: Any) -> tuple[Any, Any]:
        """Native pixel coordinates of network pixel coordinates (numpy arrays, torch tensors or floats)."""
        sx, sy = self.scale
        return self.window[0] + (u + 0.5) * sx - 0.5, self.window[1] + (v + 0.5) * sy - 0.5

    def to_network(self, u: Any, v: Any) -> tuple[Any, Any]:
        """Network pixel coordinates of native pixel coordinates (the inverse of :meth:`to_native`)."""
        sx, sy = self.scale
        return (u + 0.5 - self.window[0]) / sx - 0.5, (v + 0.5 - self.window[1]) / sy - 0.5

    def apply(self, image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The network image of a native frame ``(H, W)`` or ``(H, W, C)``: the window, area-resized.

        ``out``, when given, receives the result (``(h, w[, C])``, the image's dtype) and is returned.
        """
        height, width = image.shape[:2]
        if (width, height) != tuple(self.native_size):
            raise ValueError(f"frame is {width}x{height}, this mapping is for {self.native_size[0]}x{self.native_size[1]}")
        x0, y0, window_width, window_height = self.window
        window = image[y0:y0 + window_height, x0:x0 + window_width]
        if (window_width, window_height) == tuple(self.network_size):
            if out is None:
                return np.ascontiguousarray(window)
            out[...] = window
            return out
        # Shrinking: INTER_AREA averages the native pixels each network pixel covers (no aliasing),
        # centred on the box to_native gives. Enlarging (a camera smaller than the network's input):
        # INTER_LINEAR, whose samples sit exactly at to_native (INTER_AREA's would not).
        shrinking = window_width >= self.network_size[0] and window_height >= self.network_size[1]
        interpolation = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
        if out is None:
            return cv2.resize(window, self.network_size, interpolation=interpolation)
        cv2.resize(window, self.network_size, dst=out, interpolation=interpolation)
        return out


def input_mapping(native_size: tuple[int, int], network_size: tuple[int, int]) -> InputMapping:
    """The map :func:`network_input` applies to ``native_size`` frames for a ``network_size`` network:
    the whole frame (see the module notes for why)."""
    native = (int(native_size[0]), int(native_size[1]))
    network = (int(network_size[0]), int(network_size[1]))
    if min(*native, *network) <= 0:
        raise ValueError(f"sizes must be positive, got native {native_size} and network {network_size}")
    return InputMapping(native, network, (0, 0, native[0], native[1]))


def network_input(
    image: np.ndarray, network_size: tuple[int, int], out: np.ndarray | None = None
) -> tuple[np.ndarray, InputMapping]:
    """A native frame as the network sees it, and the exact pixel map between the two.

    Args:
        image: ``(H, W)`` mono or ``(H, W, C)`` frame at native resolution, any size and aspect ratio.
        network_size: ``(w, h)`` of the network's input.
        out: optional destination ``(h, w[, C])`` (the odometry reuses one buffer per slot).

    Returns:
        ``(network_image, mapping)``: the image at ``(h, w)`` (same dtype and channels) and the
        :class:`InputMapping` whose :meth:`~InputMapping.to_native` gives each network pixel's native
        coordinates.
    """
    height, width = image.shape[:2]
    mapping = input_mapping((width, height), network_size)
    return mapping.apply(image, out), mapping
