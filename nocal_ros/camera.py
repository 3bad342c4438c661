"""The learnable camera: pinhole intrinsics plus a small distortion MLP, producing Pluecker rays.

Conventions (DESIGN.md, docs/INTERFACES.md):

* Intrinsics live at the NATIVE image resolution. A lower training resolution ``(w, h)`` is served by
  mapping its pixel centres to native pixel coordinates, ``u_native = (u_train + 0.5) * W / w - 0.5``,
  so one model serves every training size and the learnt values never need rescaling.
* A pixel ``(u, v)`` is addressed at its centre (OpenCV). Distorted normalised coordinates are
  ``x_d = (u - cx) / fx``, ``y_d = (v - cy) / fy``. The distortion MLP takes centred native pixel
  coordinates scaled to ``[-1, 1]`` (image edges at +-1, independent of the learnt principal point so
  its input never moves) and returns a correction ``(dx, dy)``; undistorted ``x = x_d + dx``,
  ``y = y_d + dy``; the camera-frame ray is ``normalize([x, y, 1])``.

Parameterisation of the intrinsics (why: the optimiser's step must not depend on image size):

* ``fx = W * exp(log_fx_rel)``, ``fy = W * exp(log_fy_rel)``: with Adam, whose step is about ``lr``
  in parameter units whatever the gradient scale, one step changes the focal length by the fraction
  ``lr`` of itself, at any resolution, and the focal length can never become negative.
* ``cx = (W - 1) / 2 + W * cx_offset_rel``, ``cy = (H - 1) / 2 + W * cy_offset_rel``: one step moves
  the principal point by ``lr * W`` pixels. Both axes use the width so one learning rate moves both
  coordinates by the same number of pixels.

Mapping from the paper's learning rate: the paper uses Adam lr 0.5 on the raw focal length in pixels of
an 80x60 training image, i.e. steps of 0.5 / 80 = 0.625 % of the width. In this parameterisation the
same steps come from ``lr = 0.5 / 80 = 6.25e-3`` (:data:`PAPER_EQUIVALENT_INTRINSICS_LR`) for the
parameters returned by :meth:`CameraModel.intrinsic_parameters`, at any native or training resolution.
The distortion MLP outputs normalised image-plane units, so the paper's distortion lr (5e-6) applies as is.
"""

from __future__ import annotations

import copy
import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from nocal_ros.geometry import pluecker_from_rays, rays_camera_to_world

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration

#: Adam learning rate for :meth:`CameraModel.intrinsic_parameters` that reproduces the paper's focal
#: steps (lr 0.5 on focal pixels at 80 px width) in this size-independent parameterisation.
PAPER_EQUIVALENT_INTRINSICS_LR = 0.5 / 80.0

#: Curriculum stages (paper Sec. III-E): what :meth:`CameraModel.set_stage` lets the optimiser change.
STAGES = ("fixed", "focal", "full")

DISTORTION_HIDDEN_UNITS = 8
DISTORTION_LAYERS = 4


def pixel_grid(width: int, height: int, dtype: torch.dtype = torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates ``(u, v)``, each ``(H * W,)``, row-major (index = v * W + u)."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return u.reshape(-1), v.reshape(-1)


def make_distortion_mlp(hidden: int = DISTORTION_HIDDEN_UNITS, layers: int = DISTORTION_LAYERS) -> nn.Sequential:
    """``layers`` linear layers, ``hidden`` units, tanh between them (a smooth lens needs a smooth map).

    Xavier-uniform weights, zero biases, and a zero last layer so that training starts from a pinhole
    (the paper initialises every layer with Xavier; a random initial distortion would fight the scene).
    """
    modules: list[nn.Module] = []
    width_in = 2
    for _ in range(layers - 1):
        linear = nn.Linear(width_in, hidden)
        nn.init.xavier_uniform_(linear.weight)
        nn.init.zeros_(linear.bias)
        modules += [linear, nn.Tanh()]
        width_in = hidden
    last = nn.Linear(width_in, 2)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    modules.append(last)
    return nn.Sequential(*modules)


class CameraModel(nn.Module):
    """Learnable ``fx, fy, cx, cy`` at native resolution and a freeform distortion MLP.

    Args:
        width, height: native image size in pixels.
        fx, fy, cx, cy: initial intrinsics in native pixels; default ``f = width`` (the paper's
            initialisation) and the image centre ``((W - 1) / 2, (H - 1) / 2)``.
    """

    def __init__(
        self,
        width: int,
        height: int,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
    ) -> None:
        super().__init__()
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"camera size must be positive, got {width}x{height}")
        self.width = int(width)
        self.height = int(height)
        fx = float(width) if fx is None else float(fx)
        fy = fx if fy is None else float(fy)
        if not (math.isfinite(fx) and math.isfinite(fy) and fx > 0 and fy > 0):
            raise ValueError(f"focal lengths must be positive and finite, got fx={fx}, fy={fy}")
        cx = (width - 1) / 2.0 if cx is None else float(cx)
        cy = (height - 1) / 2.0 if cy is None else float(cy)
        self.log_fx_rel = nn.Parameter(torch.tensor(math.log(fx / width), dtype=torch.float32))
        self.log_fy_rel = nn.Parameter(torch.tensor(math.log(fy / width), dtype=torch.float32))
        self.cx_offset_rel = nn.Parameter(torch.tensor((cx - (width - 1) / 2.0) / width, dtype=torch.float32))
        self.cy_offset_rel = nn.Parameter(torch.tensor((cy - (height - 1) / 2.0) / width, dtype=torch.float32))
        self.distortion = make_distortion_mlp()
        self.stage = "full"
        self.set_stage("full")

    # ---------------------------------------------------------------------------------------------
    # parameters and curriculum
    # ---------------------------------------------------------------------------------------------

    def intrinsic_parameters(self) -> list[nn.Parameter]:
        """The four intrinsic parameters (for their own optimiser; see the module docstring for lr)."""
        return [self.log_fx_rel, self.log_fy_rel, self.cx_offset_rel, self.cy_offset_rel]

    def distortion_parameters(self) -> list[nn.Parameter]:
        """The distortion MLP's weights and biases (for their own optimiser)."""
        return list(self.distortion.parameters())

    def set_stage(self, stage: str) -> None:
        """Curriculum stage: ``"fixed"`` learns nothing, ``"focal"`` learns fx and fy, ``"full"`` learns
        fx, fy, cx, cy and the distortion MLP. Frozen parameters get no gradient at all."""
        if stage not in STAGES:
            raise ValueError(f"unknown camera stage {stage!r}; expected one of {STAGES}")
        self.stage = stage
        focal = stage in ("focal", "full")
        full = stage == "full"
        self.log_fx_rel.requires_grad_(focal)
        self.log_fy_rel.requires_grad_(focal)
        self.cx_offset_rel.requires_grad_(full)
        self.cy_offset_rel.requires_grad_(full)
        for parameter in self.distortion.parameters():
            parameter.requires_grad_(full)

    # ---------------------------------------------------------------------------------------------
    # intrinsics and distortion
    # ---------------------------------------------------------------------------------------------

    def intrinsics(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(fx, fy, cx, cy)`` as differentiable scalar tensors in native pixels."""
        fx = self.width * torch.exp(self.log_fx_rel)
        fy = self.width * torch.exp(self.log_fy_rel)
        cx = (self.width - 1) / 2.0 + self.width * self.cx_offset_rel
        cy = (self.height - 1) / 2.0 + self.width * self.cy_offset_rel
        return fx, fy, cx, cy

    def K(self) -> np.ndarray:
        """3x3 float64 camera matrix at native resolution (a detached copy)."""
        fx, fy, cx, cy = (float(t.detach()) for t in self.intrinsics())
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def distortion_input(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Native pixel-centre coordinates -> MLP input ``(..., 2)``, image edges at -1 and +1."""
        return torch.stack((2.0 * (u + 0.5) / self.width - 1.0, 2.0 * (v + 0.5) / self.height - 1.0), dim=-1)

    def distortion_correction(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """The MLP's correction ``(dx, dy)`` ``(..., 2)`` in normalised units at native pixels ``(u, v)``."""
        return self.distortion(self.distortion_input(u, v))

    def undistorted_normalised(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Undistorted normalised image-plane points ``(x, y)`` ``(..., 2)`` of native pixels ``(u, v)``."""
        fx, fy, cx, cy = self.intrinsics()
        distorted = torch.stack(((u - cx) / fx, (v - cy) / fy), dim=-1)
        return distorted + self.distortion_correction(u, v)

    def native_coordinates(self, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Native pixel coordinates ``(u, v)`` ``(h * w,)`` of the pixel centres of a ``w x h`` image."""
        dtype = self.log_fx_rel.dtype
        device = self.log_fx_rel.device
        u, v = pixel_grid(width, height, dtype=dtype, device=device)
        return (u + 0.5) * (self.width / width) - 0.5, (v + 0.5) * (self.height / height) - 0.5

    def directions(self, width: int | None = None, height: int | None = None) -> torch.Tensor:
        """Camera-frame unit ray directions ``(h * w, 3)`` (row-major) for a ``w x h`` image of this camera."""
        width = self.width if width is None else int(width)
        height = self.height if height is None else int(height)
        u, v = self.native_coordinates(width, height)
        xy = self.undistorted_normalised(u, v)
        rays = torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1)
        return torch.nn.functional.normalize(rays, dim=-1)

    def rays(
        self,
        T_w_c: torch.Tensor,
        width: int | None = None,
        height: int | None = None,
        pixel_index: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """World Pluecker rays ``(B, N, 6)`` of a ``w x h`` image taken from poses ``T_w_c`` ``(B, 4, 4)``.

        ``pixel_index`` (``(N,)`` shared by the batch, or ``(B, N)`` per view) selects row-major pixels
        ``v * w + u``; ``None`` takes all ``w * h`` pixels.
        """
        T_w_c = torch.as_tensor(T_w_c, device=self.log_fx_rel.device)
        if T_w_c.ndim != 3 or T_w_c.shape[-2:] != (4, 4):
            raise ValueError(f"T_w_c must be (B, 4, 4), got {tuple(T_w_c.shape)}")
        directions = self.directions(width, height)
        T_w_c = T_w_c.to(directions.dtype)
        batch = T_w_c.shape[0]
        if pixel_index is None:
            directions = directions.expand(batch, -1, -1)
        else:
            pixel_index = torch.as_tensor(pixel_index, device=directions.device)
            if pixel_index.ndim == 1:
                directions = directions[pixel_index].expand(batch, -1, -1)
            else:
                directions = directions[pixel_index]
        origins, directions_w = rays_camera_to_world(directions, T_w_c)
        return pluecker_from_rays(origins, directions_w)
