"""The learnable camera: pinhole intrinsics plus a small distortion MLP, producing Pluecker rays.

Conventions (DESIGN.md, docs/INTERFACES.md):

* Intrinsics live at the NATIVE image resolution. A lower training resolution ``(w, h)`` is served by
  mapping its pixel centres to native pixel coordinates with :mod:`nocal_ros.network_input`,
  ``u_native = (u_train + 0.5) * W / w - 0.5`` and ``v_native = (v_train + 0.5) * H / h - 0.5`` (each
  axis its own scale, so any aspect ratio), so one model serves every training size and camera shape,
  and the learnt values never need rescaling.
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

import contextlib
import copy
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from nocal_ros.geometry import pluecker_from_rays, rays_camera_to_world
from nocal_ros.network_input import input_mapping

if TYPE_CHECKING:
    from nocal_ros.lens import CameraCalibration

#: Adam learning rate for :meth:`CameraModel.intrinsic_parameters` that reproduces the paper's focal
#: steps (lr 0.5 on focal pixels at 80 px width) in this size-independent parameterisation.
PAPER_EQUIVALENT_INTRINSICS_LR = 0.5 / 80.0

#: Curriculum stages (paper Sec. III-E): what :meth:`CameraModel.set_stage` lets the optimiser change.
STAGES = ("fixed", "focal", "full")

DISTORTION_HIDDEN_UNITS = 8
DISTORTION_LAYERS = 4


#: How the distortion MLP's output becomes the correction. ``"centred"``: minus the output's value and
#: first derivative at the image centre, so the correction starts at second order, as in every
#: parametric lens model (plumb_bob's included). Why: an MLP that adds ``e * x`` is indistinguishable
#: from a focal length ``(1 + e)`` times larger (and a constant from a shifted principal point); with
#: the raw output, fitting the Table I barrel lens (true f 600) from arm-pose geometry alone took the
#: focal from 573 px after the focal stage to 457 / 470 px while the MLP absorbed the difference; centred,
#: to within 0.1-0.6 % of 600 px (``scripts/epipolar/fit_camera.py``, docs/RESULTS.md). ``"raw"``: the output as is,
#: the form of models saved before the centred one (checkpoint distortion type ``mlp``). The centred
#: form cancels the last layer's bias exactly: it is kept so that both forms share one state dict.
DISTORTION_FORMS = ("centred", "raw")


def mlp_value_and_jacobian_at_zero(mlp: nn.Sequential) -> tuple[torch.Tensor, torch.Tensor]:
    """Output ``(out,)`` and Jacobian ``(out, in)`` of a Linear/Tanh MLP at the zero input (differentiable)."""
    first = next(m for m in mlp if isinstance(m, nn.Linear))
    activation = torch.zeros(first.in_features, dtype=first.weight.dtype, device=first.weight.device)
    jacobian = torch.eye(first.in_features, dtype=first.weight.dtype, device=first.weight.device)
    for module in mlp:
        if isinstance(module, nn.Linear):
            activation = module(activation)
            jacobian = module.weight @ jacobian
        elif isinstance(module, nn.Tanh):
            activation = torch.tanh(activation)
            jacobian = (1.0 - activation.square())[:, None] * jacobian
        else:
            raise TypeError(f"distortion MLP layer {type(module).__name__} has no Jacobian rule")
    return activation, jacobian


@contextlib.contextmanager
def _one_thread():
    """Run tiny full-batch fits on one thread: on a busy 2-core machine, thread synchronisation made
    :meth:`CameraModel.from_calibration` 5-8x slower with 2 threads (measured 12-18 s vs 2.4 s)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


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
        distortion_form: str = "centred",
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
        if distortion_form not in DISTORTION_FORMS:
            raise ValueError(f"unknown distortion form {distortion_form!r}; expected one of {DISTORTION_FORMS}")
        self.distortion_form = distortion_form
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
        """The correction ``(dx, dy)`` ``(..., 2)`` in normalised units at native pixels ``(u, v)``.

        In the centred form, the MLP's output less its first-order Taylor expansion at the image
        centre (see :data:`DISTORTION_FORMS`).
        """
        inputs = self.distortion_input(u, v)
        correction = self.distortion(inputs)
        if self.distortion_form == "centred":
            value, jacobian = mlp_value_and_jacobian_at_zero(self.distortion)
            correction = correction - value - inputs @ jacobian.T
        return correction

    def undistorted_normalised(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Undistorted normalised image-plane points ``(x, y)`` ``(..., 2)`` of native pixels ``(u, v)``."""
        fx, fy, cx, cy = self.intrinsics()
        distorted = torch.stack(((u - cx) / fx, (v - cy) / fy), dim=-1)
        return distorted + self.distortion_correction(u, v)

    def native_coordinates(self, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Native pixel coordinates ``(u, v)`` ``(h * w,)`` of the pixel centres of a ``w x h`` network image.

        The network image is the native frame mapped by :func:`nocal_ros.network_input.network_input`
        (the whole frame, area-resized); this is the same map, so each network pixel gets the ray of
        the native pixels it shows, for a camera of any aspect ratio.
        """
        dtype = self.log_fx_rel.dtype
        device = self.log_fx_rel.device
        u, v = pixel_grid(width, height, dtype=dtype, device=device)
        return input_mapping((self.width, self.height), (width, height)).to_native(u, v)

    def directions(self, width: int | None = None, height: int | None = None) -> torch.Tensor:
        """Camera-frame unit ray directions ``(h * w, 3)`` (row-major) for a ``w x h`` image of this camera."""
        width = self.width if width is None else int(width)
        height = self.height if height is None else int(height)
        return self.pixel_rays(*self.native_coordinates(width, height))

    def pixel_rays(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Camera-frame unit ray directions ``(..., 3)`` of native pixels ``(u, v)`` (differentiable)."""
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

    # ---------------------------------------------------------------------------------------------
    # exports: dense maps, parametric calibration
    # ---------------------------------------------------------------------------------------------

    @torch.no_grad()
    def undistortion_map(self) -> np.ndarray:
        """Undistorted normalised ``(x, y)`` of every native pixel: ``(H, W, 2)`` float64."""
        camera = self.float64_copy()
        u, v = pixel_grid(self.width, self.height, dtype=torch.float64)
        return camera.undistorted_normalised(u, v).reshape(self.height, self.width, 2).numpy()

    @torch.no_grad()
    def rectification_maps(
        self,
        new_K: np.ndarray | None = None,
        size: tuple[int, int] | None = None,
        iterations: int = 30,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps ``(map_x, map_y)`` (float32, ``(h, w)``) that rectify this camera's images.

        The rectified image is a pinhole camera ``new_K`` (default: the learnt K, no distortion) of size
        ``(w, h)`` (default native). Each rectified pixel's normalised point is pushed back through the
        learnt distortion by the fixed-point iteration ``x_d <- x - dx(u(x_d))`` (the MLP maps distorted
        pixels to corrections, so its inverse is found numerically, as OpenCV does for undistortPoints).
        """
        camera = self.float64_copy()
        new_K = self.K() if new_K is None else np.asarray(new_K, dtype=np.float64)
        width, height = (self.width, self.height) if size is None else (int(size[0]), int(size[1]))
        fx, fy, cx, cy = camera.intrinsics()
        u, v = pixel_grid(width, height, dtype=torch.float64)
        target = torch.stack(((u - new_K[0, 2]) / new_K[0, 0], (v - new_K[1, 2]) / new_K[1, 1]), dim=-1)
        distorted = target.clone()
        for _ in range(iterations):
            source_u = cx + fx * distorted[:, 0]
            source_v = cy + fy * distorted[:, 1]
            previous, distorted = distorted, target - camera.distortion_correction(source_u, source_v)
            if float((distorted - previous).abs().max()) * float(max(fx, fy)) < 1e-6:  # pixels
                break
        map_x = (cx + fx * distorted[:, 0]).reshape(height, width).numpy().astype(np.float32)
        map_y = (cy + fy * distorted[:, 1]).reshape(height, width).numpy().astype(np.float32)
        return map_x, map_y

    def float64_copy(self) -> "CameraModel":
        """A detached float64 copy on the CPU, for exports and evaluation in double precision."""
        return copy.deepcopy(self).to(device="cpu", dtype=torch.float64).requires_grad_(False)

    def fit_parametric(
        self, distortion_model: str = "plumb_bob", samples: tuple[int, int] = (64, 48), camera_name: str = "nocal",
        fix_k3: bool = False,
    ) -> "ParametricFit":
        """Least-squares fit of the learnt distortion by an OpenCV/ROS parametric model.

        Keeps the learnt K and finds ``D`` so that distorting the learnt undistorted point of each sampled
        native pixel lands back on that pixel (``plumb_bob``: linear least squares; ``rational_polynomial``:
        Levenberg-Marquardt started from the plumb_bob solution; ``fix_k3``: plumb_bob with ``k3 = 0``).
        Residuals are measured in pixels.
        """
        from nocal_ros.lens import CameraCalibration, distort_normalised

        columns, rows = samples
        u = torch.linspace(0.0, self.width - 1.0, int(columns), dtype=torch.float64)
        v = torch.linspace(0.0, self.height - 1.0, int(rows), dtype=torch.float64)
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        with torch.no_grad():
            undistorted = self.float64_copy().undistorted_normalised(uu.reshape(-1), vv.reshape(-1)).numpy()
        K = self.K()
        distorted = np.stack(((uu.reshape(-1).numpy() - K[0, 2]) / K[0, 0], (vv.reshape(-1).numpy() - K[1, 2]) / K[1, 1]), -1)
        D = fit_distortion_coefficients(undistorted, distorted, distortion_model, K[0, 0], K[1, 1], fix_k3)
        residual = distort_normalised(undistorted, D, distortion_model) - distorted
        residual_px = residual * np.array([K[0, 0], K[1, 1]])
        calibration = CameraCalibration(
            width=self.width, height=self.height, K=K, D=D, distortion_model=distortion_model, camera_name=camera_name
        )
        return ParametricFit(
            calibration=calibration,
            rms_px=float(np.sqrt(np.mean(np.sum(residual_px**2, -1)))),
            rms_normalised=float(np.sqrt(np.mean(np.sum(residual**2, -1)))),
            max_px=float(np.max(np.linalg.norm(residual_px, axis=-1))),
        )

    def to_calibration(self, model: str = "plumb_bob", camera_name: str = "nocal") -> tuple["CameraCalibration", float]:
        """``(CameraCalibration, rms residual in pixels)`` of the best parametric fit (see :meth:`fit_parametric`)."""
        fit = self.fit_parametric(model, camera_name=camera_name)
        return fit.calibration, fit.rms_px

    @classmethod
    def from_calibration(
        cls, calibration: "CameraCalibration", iterations: int = 200, samples: tuple[int, int] = (40, 30), seed: int = 0
    ) -> "CameraModel":
        """A camera with the calibration's K and its MLP fitted to the calibration's distortion.

        Full-batch L-BFGS in float64 on a grid of native pixels (far better than Adam on this tiny
        regression). An 8-unit MLP cannot represent a lens exactly: for k1 = -0.25 at 640x480 the mean
        error is about 1 px, for k1 = -0.05 about 0.15 px (measured; see the tests).
        """
        K = np.asarray(calibration.K, dtype=np.float64)
        camera = cls(calibration.width, calibration.height, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
        columns, rows = samples
        u = np.linspace(0.0, calibration.width - 1.0, int(columns))
        v = np.linspace(0.0, calibration.height - 1.0, int(rows))
        vv, uu = np.meshgrid(v, u, indexing="ij")
        pixels = np.stack((uu.ravel(), vv.ravel()), -1)
        true_xy = np.asarray(calibration.undistorted_normalised(pixels), dtype=np.float64)
        # Pixels beyond the fold of a strong polynomial lens see nothing (NaN): fit the rest.
        valid = np.isfinite(true_xy).all(-1)
        if valid.mean() < 0.5:
            raise ValueError("the calibration's distortion is undefined over most of the image")
        pixels, true_xy = pixels[valid], true_xy[valid]
        distorted = np.stack(((pixels[:, 0] - K[0, 2]) / K[0, 0], (pixels[:, 1] - K[1, 2]) / K[1, 1]), -1)
        target = torch.from_numpy(true_xy - distorted)
        u_t, v_t = torch.from_numpy(pixels[:, 0]), torch.from_numpy(pixels[:, 1])
        fitted = camera.float64_copy()
        mlp = fitted.distortion
        mlp.requires_grad_(True)
        generator = torch.Generator().manual_seed(seed)
        # The zero last layer is the right start for training but a dead start for a regression.
        with torch.no_grad():
            mlp[-1].weight.copy_((torch.rand(mlp[-1].weight.shape, generator=generator, dtype=torch.float64) - 0.5) * 0.1)
        optimiser = torch.optim.LBFGS(
            mlp.parameters(), lr=1.0, max_iter=int(iterations), history_size=50,
            line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-16,
        )

        def closure() -> torch.Tensor:
            optimiser.zero_grad(set_to_none=True)
            loss = ((fitted.distortion_correction(u_t, v_t) - target) ** 2).sum(-1).mean()
            loss.backward()
            return loss

        # L-BFGS sometimes stops early on a flat stretch; a few restarts of the same state make the fit
        # consistent across seeds (measured mean error 4-5e-4 instead of 5e-4..1.7e-3).
        with _one_thread():
            for _ in range(3):
                optimiser.step(closure)
        camera.distortion.load_state_dict(mlp.state_dict())
        return camera


@dataclass
class ParametricFit:
    """A parametric calibration fitted to a learnt camera, and how well it fits it (over sampled pixels)."""

    calibration: "CameraCalibration"
    rms_px: float
    rms_normalised: float
    max_px: float


def fit_distortion_coefficients(
    undistorted: np.ndarray, distorted: np.ndarray, distortion_model: str, fx: float, fy: float, fix_k3: bool = False
) -> np.ndarray:
    """Coefficients ``D`` with ``lens.distort_normalised(undistorted, D) ~ distorted``, least squares in pixels.

    ``plumb_bob`` is linear in ``(k1, k2, p1, p2, k3)`` (``fix_k3``: ``k3 = 0``, the form bundle adjusters
    such as GTSAM's Cal3DS2 use); ``rational_polynomial`` is refined by Levenberg-Marquardt from the
    plumb_bob solution (``k4 = k5 = k6 = 0``); ``equidistant`` is linear in ``(k1, k2, k3, k4)``.
    """
    x, y = undistorted[:, 0], undistorted[:, 1]
    r2 = x * x + y * y
    if distortion_model == "equidistant":
        # x_d = x theta (1 + k1 theta^2 + ... + k4 theta^8) / r with theta = atan(r), as cv2.fisheye.
        r = np.sqrt(r2)
        theta = np.arctan(r)
        along = np.where(r > 1e-12, theta / np.where(r > 1e-12, r, 1.0), 1.0)
        powers = np.stack([theta ** (2 * k) for k in range(1, 5)], -1) * along[:, None]
        A = np.concatenate((powers * x[:, None] * fx, powers * y[:, None] * fy))
        b = np.concatenate(((distorted[:, 0] - x * along) * fx, (distorted[:, 1] - y * along) * fy))
        return np.linalg.lstsq(A, b, rcond=None)[0]
    # plumb_bob is linear in (k1, k2, p1, p2, k3): stack the x rows (weighted by fx) and y rows (by fy).
    rows_x = np.stack((x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3), -1) * fx
    rows_y = np.stack((y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3), -1) * fy
    A = np.concatenate((rows_x, rows_y))
    b = np.concatenate(((distorted[:, 0] - x) * fx, (distorted[:, 1] - y) * fy))
    if fix_k3:
        if distortion_model != "plumb_bob":
            raise ValueError("fix_k3 applies to plumb_bob only")
        return np.append(np.linalg.lstsq(A[:, :4], b, rcond=None)[0], 0.0)
    plumb_bob = np.linalg.lstsq(A, b, rcond=None)[0]
    if distortion_model == "plumb_bob":
        return plumb_bob
    if distortion_model != "rational_polynomial":
        raise ValueError(f"cannot fit distortion model {distortion_model!r}; use plumb_bob or rational_polynomial")
    from scipy.optimize import least_squares

    from nocal_ros.lens import distort_normalised

    # Numerator and denominator of the rational model can grow together without changing the map
    # much; a weak ridge penalty (a unit coefficient costs like 0.01 px of RMS error) picks the small
    # solution instead of one with coefficients of 1e5.
    ridge = 0.01 * np.sqrt(2 * len(undistorted))
    radial = [0, 1, 4, 5, 6, 7]

    def residual(D: np.ndarray) -> np.ndarray:
        error = (distort_normalised(undistorted, D, "rational_polynomial") - distorted) * np.array([fx, fy])
        return np.concatenate((error.ravel(), ridge * D[radial]))

    start = np.concatenate((plumb_bob, np.zeros(3)))
    return least_squares(residual, start, method="lm").x
