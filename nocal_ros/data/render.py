"""A pure-PyTorch ray caster of textured rectangles, imaging through the true distorted lens.

Every pixel (or each of its ``k x k`` subpixel samples) gets the exact ray of the lens from
:meth:`nocal_ros.lens.CameraCalibration.pixel_rays`, so distortion is rendered exactly, not by warping
a pinhole image. Per frame, the rays are rotated to the world and intersected with all rectangles at
once; the nearest hit is textured with trilinear mip-mapping (the footprint of a pixel on the surface
picks the level), which keeps 80x60 renders free of the aliasing a photometric loss would chase.

Cost is dominated by the (rays x rectangles) intersection. Two things keep it small: back faces are
culled per frame (the origin is on the wrong side of their plane), and in-plane coordinates are
computed as ``c + t * (d @ A.T)`` from three (rays x rectangles) matrices instead of materialising
(rays x rectangles x 3) hit points.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from nocal_ros.data.scenes import Scene
from nocal_ros.lens import CameraCalibration

_CHUNK_RAYS = 1 << 15


def _mip_pyramid(textures: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flattened mip levels of square power-of-two textures ``(T, S, S, 3)`` by 2x2 box filtering.

    Returns ``(texels (total, 3), level_offsets (L,), level_sizes (L,))``.
    """
    count, size = textures.shape[0], textures.shape[1]
    if textures.shape[2] != size or size & (size - 1):
        raise ValueError(f"textures must be square with a power-of-two side, got {textures.shape}")
    level = torch.from_numpy(np.ascontiguousarray(textures, dtype=np.float32))
    levels, offsets, sizes, offset = [], [], [], 0
    while True:
        levels.append(level.reshape(-1, 3))
        offsets.append(offset)
        sizes.append(level.shape[1])
        offset += level.shape[0] * level.shape[1] * level.shape[2]
        if level.shape[1] == 1:
            break
        level = level.reshape(count, level.shape[1] // 2, 2, level.shape[2] // 2, 2, 3).mean(dim=(2, 4))
    return torch.cat(levels), torch.tensor(offsets), torch.tensor(sizes)


class Renderer:
    """Renders a :class:`~nocal_ros.data.scenes.Scene` through a calibrated camera.

    Args:
        scene: rectangles and textures.
        calibration: the true camera; rendering happens at its size.
        supersample: ``k``: average ``k x k`` subpixel rays per pixel (anti-aliasing at edges).
    """

    def __init__(self, scene: Scene, calibration: CameraCalibration, supersample: int = 1) -> None:
        self.scene, self.calibration, self.supersample = scene, calibration, int(supersample)
        width, height = calibration.width, calibration.height
        rays = calibration.pixel_rays(supersample=self.supersample).reshape(-1, 3)
        self._rays, self._valid_rays = self._ray_tensor(rays)
        self._footprint = self._angular_footprint(calibration) / self.supersample
        self._footprint = self._footprint.repeat_interleave(self.supersample**2)
        self._centre_rays: tuple[torch.Tensor, torch.Tensor] | None = None
        self.size = (width, height)

        rects = scene.rectangles
        self._corner = torch.tensor(np.stack([r.corner for r in rects]), dtype=torch.float64)
        self._corners = torch.tensor(np.stack([[r.corner, r.corner + r.edge_u, r.corner + r.edge_v,
                                                r.corner + r.edge_u + r.edge_v] for r in rects]), dtype=torch.float64)
        self._normal = torch.tensor(np.stack([r.normal for r in rects]), dtype=torch.float64)
        # edge / |edge|^2: a hit point's in-plane coordinate along the edge is (p - corner) . axis
        self._axis_u = torch.tensor(np.stack([r.edge_u / np.dot(r.edge_u, r.edge_u) for r in rects]), dtype=torch.float64)
        self._axis_v = torch.tensor(np.stack([r.edge_v / np.dot(r.edge_v, r.edge_v) for r in rects]), dtype=torch.float64)
        texture_size = scene.textures.shape[1]
        texture = np.array([r.texture for r in rects])
        if texture.min() < 0 or texture.max() >= len(scene.textures):
            raise ValueError("a rectangle refers to a texture the scene does not have")
        # One row of shading attributes per rectangle, gathered once per ray: texture repeats per unit
        # in-plane coordinate (2), texture offset (2), world size of a level-0 texel (1), RGB gain (3),
        # texture index (1).
        self._attributes = torch.tensor(np.stack([
            np.concatenate([[np.linalg.norm(r.edge_u) / r.repeat, np.linalg.norm(r.edge_v) / r.repeat], r.offset,
                            [r.repeat / texture_size], r.gain, [r.texture]]) for r in rects]), dtype=torch.float32)
        self._texels, self._level_offsets, self._level_sizes = _mip_pyramid(scene.textures)
        self._levels = len(self._level_sizes)
        self._frustum = self._frustum_planes(rays)

    @staticmethod
    def _ray_tensor(rays: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        valid = np.isfinite(rays).all(-1)
        return torch.from_numpy(np.where(valid[:, None], rays, 0.0).astype(np.float32)), torch.from_numpy(valid)

    @staticmethod
    def _frustum_planes(rays: np.ndarray) -> torch.Tensor:
        """Camera-frame half-spaces ``n . p >= 0`` that contain every ray of the lens (``(M, 3)``).

        Bounds the horizontal and vertical ray angles (``atan2(x, z)``, ``atan2(y, z)``); a side is
        left out when the lens sees 180 degrees or more that way (fisheye). A rectangle with all four
        corners outside one half-space cannot be hit, so it is culled before the per-pixel work.
        """
        rays = rays[np.isfinite(rays).all(-1)]
        planes = []
        margin = 1e-3
        for axis in (0, 1):
            angle = np.arctan2(rays[:, axis], rays[:, 2])
            low, high = angle.min() - margin, angle.max() + margin
            if high - low >= np.pi or low <= -np.pi / 2 or high >= np.pi / 2:
                continue
            for bound, sign in ((low, 1.0), (high, -1.0)):
                # sign * (p_axis cos(bound) - p_z sin(bound)) >= 0 <=> angle on the inner side of bound
                normal = np.zeros(3)
                normal[axis], normal[2] = sign * np.cos(bound), -sign * np.sin(bound)
                planes.append(normal)
        return torch.tensor(np.array(planes).reshape(-1, 3), dtype=torch.float64)

    @staticmethod
    def _angular_footprint(calibration: CameraCalibration) -> torch.Tensor:
        """Angle (radians) between neighbouring pixel rays, per pixel: the size of its footprint."""
        table = calibration.pixel_rays()[:, :, 0]
        du = np.linalg.norm(np.diff(table, axis=1), axis=-1)
        dv = np.linalg.norm(np.diff(table, axis=0), axis=-1)
        du = np.concatenate([du, du[:, -1:]], axis=1)
        dv = np.concatenate([dv, dv[-1:]], axis=0)
        footprint = np.sqrt(du * dv)
        fallback = np.nanmedian(footprint) if np.isfinite(footprint).any() else 1e-3
        return torch.from_numpy(np.where(np.isfinite(footprint), footprint, fallback).astype(np.float32).reshape(-1))

    def render(self, T_w_c: np.ndarray, return_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Image ``(H, W, 3)`` uint8 seen from camera pose ``T_w_c``, and optionally its depth.

        Depth ``(H, W)`` float32 is the z coordinate (metres, camera frame) of the surface hit by the
        ray through each pixel centre; NaN where nothing is hit or the lens maps no ray.
        """
        width, height = self.size
        k2 = self.supersample**2
        colour, _ = self._cast(T_w_c, self._rays, self._valid_rays, self._footprint)
        image = colour.reshape(height, width, k2, 3).mean(2)
        image = (image.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        if not return_depth:
            return image, None
        if self.supersample == 1:
            rays, valid = self._rays, self._valid_rays
        else:
            if self._centre_rays is None:
                self._centre_rays = self._ray_tensor(self.calibration.pixel_rays().reshape(-1, 3))
            rays, valid = self._centre_rays
        _, distance = self._cast(T_w_c, rays, valid, None)
        depth = (distance * rays[:, 2]).reshape(height, width).numpy()
        return image, depth

    @torch.no_grad()
    def _cast(self, T_w_c, rays, valid_rays, footprint):
        T = np.asarray(T_w_c, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"camera pose must be a finite 4x4 transform, got {T.shape}")
        origin = torch.from_numpy(T[:3, 3])
        rotation64 = torch.from_numpy(T[:3, :3])
        rotation = rotation64.float()
        # Back-face culling: a one-sided rectangle is visible only from the side its normal faces.
        visible = ((origin - self._corner) * self._normal).sum(1) > 1e-9
        # Frustum culling: all corners outside one bounding half-space of the lens's rays.
        if len(self._frustum):
            corners_cam = (self._corners - origin) @ rotation64  # R^T (p - o), row-vector form
            outside = (corners_cam @ self._frustum.T < 0).all(dim=1).any(dim=1)
            visible &= ~outside
        index = torch.nonzero(visible).squeeze(1)
        count = len(index)
        to_corner = self._corner[index] - origin
        # Per-rectangle constants in float64 (they carry the large world coordinates), then float32.
        plane_distance = (to_corner * self._normal[index]).sum(1).float()  # negative: camera in front
        # in-plane coordinates are shifted by -1/2 so that "inside" is |u| <= 1/2
        start_u = ((-to_corner) * self._axis_u[index]).sum(1).float() - 0.5
        start_v = ((-to_corner) * self._axis_v[index]).sum(1).float() - 0.5
        axes = torch.cat((self._normal[index], self._axis_u[index], self._axis_v[index])).float().T  # (3, 3R)

        colours, distances = [], []
        for start in range(0, len(rays), _CHUNK_RAYS):
            directions = rays[start : start + _CHUNK_RAYS] @ rotation.T
            valid = valid_rays[start : start + _CHUNK_RAYS]
            if count == 0:
                distance = torch.full((len(directions),), math.inf)
                nearest = torch.zeros(len(directions), dtype=torch.long)
            else:
                projections = directions @ axes
                along_normal, along_u, along_v = projections.split(count, dim=1)
                # Rays moving away from the front face get a tiny negative component, hence a huge
                # positive t whose in-plane coordinates fall far outside: no separate t > 0 test.
                t = plane_distance / along_normal.clamp_(max=-1e-12)
                u = along_u.mul_(t).add_(start_u).abs_()
                v = along_v.mul_(t).add_(start_v).abs_()
                t.masked_fill_(torch.maximum(u, v, out=u) > 0.5, math.inf)
                distance, nearest = t.min(dim=1)
            distance = torch.where(valid, distance, torch.full_like(distance, math.inf))
            if footprint is not None:
                rect = index[nearest] if count else nearest
                colours.append(self._shade(rect, origin, directions, distance, footprint[start : start + _CHUNK_RAYS]))
            distances.append(distance)
        distance = torch.cat(distances)
        distance = torch.where(torch.isfinite(distance), distance, torch.full_like(distance, math.nan))
        return (torch.cat(colours) if footprint is not None else None), distance

    def _shade(self, rect, origin, directions, distance, footprint):
        """Trilinear, mip-mapped texture colour times the rectangle's fixed gain; black for misses."""
        hit = torch.isfinite(distance)
        # misses carry inf distances; park them on a harmless texel before integer indexing
        distance = torch.where(hit, distance, torch.ones_like(distance))
        # in-plane coordinates and incidence of the winning rectangle only (cheap: one per ray)
        hit_point = directions.double() * distance.double().unsqueeze(1) + origin - self._corner[rect]
        uv = torch.stack(((hit_point * self._axis_u[rect]).sum(1), (hit_point * self._axis_v[rect]).sum(1)), 1).float()
        cosine = -(directions * self._normal[rect].float()).sum(1)
        attributes = self._attributes[rect]
        repeats, offset, texel, gain = attributes[:, 0:2], attributes[:, 2:4], attributes[:, 4], attributes[:, 5:8]
        texture = attributes[:, 8].long()
        coords = uv * repeats + offset
        # footprint on the surface, stretched by the grazing angle (geometric mean of the two axes)
        world = distance * footprint / cosine.clamp(min=0.05).sqrt()
        level = torch.log2((world / texel).clamp(min=1e-6)).clamp(0, self._levels - 1)
        level = torch.nan_to_num(level, nan=0.0, posinf=self._levels - 1)
        low = level.floor().long().clamp(max=self._levels - 1)
        high = (low + 1).clamp(max=self._levels - 1)
        blend = (level - low).unsqueeze(1)
        colour = (1 - blend) * self._bilinear(texture, coords, low) + blend * self._bilinear(texture, coords, high)
        colour = colour * gain
        return torch.where(hit.unsqueeze(1), colour, torch.zeros_like(colour))

    def _bilinear(self, texture, coords, level):
        size = self._level_sizes[level]
        base = self._level_offsets[level] + texture * size * size
        frac = coords - coords.floor()  # textures repeat
        xy = frac * size.unsqueeze(1) - 0.5
        x0y0 = xy.floor()
        w = xy - x0y0
        mask = size - 1  # power-of-two sizes: wrap-around by bit mask (also maps -1 to size - 1)
        x0 = x0y0[:, 0].long() & mask
        y0 = x0y0[:, 1].long() & mask
        x1, y1 = (x0 + 1) & mask, (y0 + 1) & mask
        texels = self._texels

        def fetch(x, y):
            return texels[base + y * size + x]

        wx, wy = w[:, :1], w[:, 1:]
        top = fetch(x0, y0) * (1 - wx) + fetch(x1, y0) * wx
        bottom = fetch(x0, y1) * (1 - wx) + fetch(x1, y1) * wx
        return top * (1 - wy) + bottom * wy
