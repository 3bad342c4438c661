"""Parametric cameras: the ROS/OpenCV lens models, exactly as OpenCV defines them.

This module is the one source of truth for *known* cameras: the ground truth the renderer images
through, the calibration the evaluation compares against, and the YAML files users hand us (ROS
``camera_calibration`` format). The learnable camera (``nocal_ros.camera``) fits to these models.

Models (coefficients in ROS/OpenCV order):

* ``plumb_bob``: ``k1 k2 p1 p2 k3`` (Brown-Conrady; also accepted with 4 or 0 coefficients).
* ``rational_polynomial``: ``k1 k2 p1 p2 k3 k4 k5 k6``.
* ``equidistant``: ``k1 k2 k3 k4`` (OpenCV ``cv2.fisheye``).

Pixel centres are at integer coordinates (OpenCV convention). The distortion formulas are written
once over plain arithmetic so the same code runs on float64 numpy arrays (projection, evaluation) and
on torch tensors (differentiable and batched, for the renderer and the learnable camera).
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from nocal_ros.errors import ConfigError

DISTORTION_MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}

# Newton on the distortion stops once the distorted point is reproduced to this (normalised units,
# about 1e-11 px for any real focal length).
_UNDISTORT_TOLERANCE = 1e-14
_UNDISTORT_MAX_ITERATIONS = 60
#: Plain Newton steps on every point before the careful solve takes the rest (every pixel of a 640x480
#: image through f = 420, k1 = -0.3, k2 = 0.09 converges in five).
_UNDISTORT_PLAIN_ITERATIONS = 8


def _xp(array: Any):
    """The array module of ``array``: numpy, or torch for a tensor.

    torch is never imported here: a tensor means it is loaded already, and numpy-only users (the
    bundle adjustment's worker process) then start without it.
    """
    torch = sys.modules.get("torch")
    return torch if torch is not None and isinstance(array, torch.Tensor) else np


def normalise_coefficients(coefficients: Any, model: str) -> np.ndarray:
    """Validate distortion coefficients for ``model`` and pad ``plumb_bob`` to its 5 coefficients."""
    if model not in DISTORTION_MODELS:
        raise ValueError(f"unknown distortion model {model!r}; expected one of {sorted(DISTORTION_MODELS)}")
    D = np.asarray(coefficients if coefficients is not None else [], dtype=np.float64).reshape(-1)
    expected = DISTORTION_MODELS[model]
    if model == "plumb_bob" and len(D) in (0, 4):
        D = np.concatenate([D, np.zeros(expected - len(D))])
    if len(D) != expected:
        raise ValueError(f"{model} needs {expected} distortion coefficients, got {len(D)}")
    if not np.all(np.isfinite(D)):
        raise ValueError(f"distortion coefficients must be finite, got {D.tolist()}")
    return D


# --------------------------------------------------------------------------------------------------
# Distortion in normalised coordinates (numpy float64 or torch, same formulas)
# --------------------------------------------------------------------------------------------------


def _radial_and_derivative(s, D, model: str):
    """Radial factor ``R(s)`` of ``s = r^2`` and ``dR/ds`` for the polynomial models."""
    k1, k2, k3 = D[0], D[1], D[4]
    numerator = 1 + s * (k1 + s * (k2 + s * k3))
    d_numerator = k1 + s * (2 * k2 + 3 * s * k3)
    if model == "plumb_bob":
        return numerator, d_numerator
    k4, k5, k6 = D[5], D[6], D[7]
    denominator = 1 + s * (k4 + s * (k5 + s * k6))
    d_denominator = k4 + s * (2 * k5 + 3 * s * k6)
    radial = numerator / denominator
    return radial, (d_numerator * denominator - numerator * d_denominator) / denominator**2


def _theta_distorted(theta, D):
    """Equidistant model: ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)`` and its derivative."""
    t2 = theta * theta
    poly = 1 + t2 * (D[0] + t2 * (D[1] + t2 * (D[2] + t2 * D[3])))
    d_poly = 1 + t2 * (3 * D[0] + t2 * (5 * D[1] + t2 * (7 * D[2] + t2 * 9 * D[3])))
    return theta * poly, d_poly


def distort_normalised(xy, coefficients, model: str):
    """Distort undistorted normalised points ``(..., 2)`` (``x = X/Z``, ``y = Y/Z``).

    Works on float64 numpy arrays and on torch tensors (differentiable in points and coefficients).
    For ``equidistant`` the angle is ``atan(r)``, as in ``cv2.fisheye.projectPoints``.
    """
    xp = _xp(xy)
    D = coefficients
    x, y = xy[..., 0], xy[..., 1]
    if model == "equidistant":
        r = xp.sqrt(x * x + y * y)
        theta_d, _ = _theta_distorted(xp.arctan(r), D)
        # theta_d / r -> 1 as r -> 0; the guarded division keeps gradients finite at the centre.
        safe_r = xp.where(r > 1e-12, r, xp.ones_like(r))
        scale = xp.where(r > 1e-12, theta_d / safe_r, xp.ones_like(r))
        return xp.stack((x * scale, y * scale), -1)
    s = x * x + y * y
    radial, _ = _radial_and_derivative(s, D, model)
    return xp.stack(_polynomial_image(x, y, s, radial, D), -1)


def _polynomial_image(x, y, s, radial, D):
    """``(xd, yd)`` of the polynomial models at ``(x, y)``, given ``s = x^2 + y^2`` and its radial factor."""
    p1, p2 = D[2], D[3]
    return (x * radial + 2 * p1 * x * y + p2 * (s + 2 * x * x),
            y * radial + p1 * (s + 2 * y * y) + 2 * p2 * x * y)


def _polynomial_jacobian(x, y, radial, d_radial, D):
    """``(j00, j01, j11)`` of ``d(xd, yd) / d(x, y)`` (``j10 = j01``), given the radial factor and its
    derivative in ``s``."""
    p1, p2 = D[2], D[3]
    return (radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x,
            2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y,
            radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x)


def _inverse_jacobian_times(j00, j01, j10, j11, rx, ry):
    """``J^-1 (rx, ry)`` as ``(N, 2)``, a singular Jacobian's determinant taken as 1."""
    det = j00 * j11 - j01 * j10
    det = np.where(np.abs(det) > 1e-300, det, 1.0)
    return np.stack((j11 * rx - j01 * ry, -j10 * rx + j00 * ry), -1) / det[:, None]


def distortion_jacobians(xy: np.ndarray, coefficients: np.ndarray, model: str) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of :func:`distort_normalised` at float64 points ``xy`` ``(N, 2)``.

    Returns ``d(xd, yd) / d(x, y)`` ``(N, 2, 2)`` and ``d(xd, yd) / d(first four coefficients)``
    ``(N, 2, 4)``: ``(k1, k2, p1, p2)`` for ``plumb_bob`` (``k3`` is not differentiated), ``(k1..k4)`` for
    ``equidistant``.
    """
    D = np.asarray(coefficients, dtype=np.float64)
    x, y = xy[:, 0], xy[:, 1]
    d_point = np.empty((len(xy), 2, 2))
    d_coefficients = np.empty((len(xy), 2, 4))
    if model == "equidistant":
        r2 = x * x + y * y
        r = np.sqrt(r2)
        centre = r < 1e-12
        safe_r = np.where(centre, 1.0, r)
        theta = np.arctan(r)
        theta_d, d_poly = _theta_distorted(theta, D)
        scale = np.where(centre, 1.0, theta_d / safe_r)
        # d(scale)/dr / r: (theta_d' theta' r - theta_d) / r^3, with theta_d' = d_poly, theta' = 1 / (1 + r^2).
        d_scale = np.where(centre, 0.0, (d_poly / (1.0 + r2) * safe_r - theta_d) / safe_r**3)
        d_point[:, 0, 0] = scale + x * x * d_scale
        d_point[:, 0, 1] = d_point[:, 1, 0] = x * y * d_scale
        d_point[:, 1, 1] = scale + y * y * d_scale
        power = theta.copy()
        for n in range(4):  # d theta_d / d k_n = theta^(2n + 3)
            power = power * theta * theta
            ratio = np.where(centre, 0.0, power / safe_r)
            d_coefficients[:, 0, n] = x * ratio
            d_coefficients[:, 1, n] = y * ratio
        return d_point, d_coefficients
    j00, j01, j10, j11 = _distortion_jacobian(x, y, D, model)
    d_point[:, 0, 0], d_point[:, 0, 1], d_point[:, 1, 0], d_point[:, 1, 1] = j00, j01, j10, j11
    s = x * x + y * y
    xy2 = 2 * x * y
    d_coefficients[:, 0, 0], d_coefficients[:, 1, 0] = x * s, y * s
    d_coefficients[:, 0, 1], d_coefficients[:, 1, 1] = x * s * s, y * s * s
    d_coefficients[:, 0, 2], d_coefficients[:, 1, 2] = xy2, s + 2 * y * y
    d_coefficients[:, 0, 3], d_coefficients[:, 1, 3] = s + 2 * x * x, xy2
    if model != "plumb_bob":  # rational_polynomial's k1, k2 enter through its denominator too
        raise ValueError(f"distortion_jacobians supports plumb_bob and equidistant, got {model!r}")
    return d_point, d_coefficients


def _distortion_jacobian(x, y, D, model: str):
    """``d(xd, yd) / d(x, y)`` of the polynomial models, as four arrays."""
    s = x * x + y * y
    radial, d_radial = _radial_and_derivative(s, D, model)
    j00, j01, j11 = _polynomial_jacobian(x, y, radial, d_radial, D)
    return j00, j01, j01, j11


def _newton_step(x, residual, D, model: str):
    """``J(x)^-1 residual`` for float64 numpy points ``(N, 2)``: what a Newton step on ``distort(x) = target``
    subtracts (a singular Jacobian's determinant taken as 1)."""
    j00, j01, j10, j11 = _distortion_jacobian(x[:, 0], x[:, 1], D, model)
    return _inverse_jacobian_times(j00, j01, j10, j11, residual[:, 0], residual[:, 1])


def _residual_and_jacobian(x, target, D, model: str):
    """``distort(x) - target`` and ``d distort / d x`` of the polynomial models for float64 numpy points
    ``(N, 2)``, the radial factor evaluated once for both (:func:`distort_normalised`'s and
    :func:`_distortion_jacobian`'s expressions, so the same bits at about half the cost). Returns
    ``(rx, ry, j00, j01, j11, s, radial, d_radial)``; ``j10 = j01``."""
    px, py = x[:, 0], x[:, 1]
    s = px * px + py * py
    radial, d_radial = _radial_and_derivative(s, D, model)
    xd, yd = _polynomial_image(px, py, s, radial, D)
    j00, j01, j11 = _polynomial_jacobian(px, py, radial, d_radial, D)
    return xd - target[:, 0], yd - target[:, 1], j00, j01, j11, s, radial, d_radial


def _polynomial_newton_step(x, target, D, model: str):
    """:func:`_newton_step` on ``distort(x) - target``, from :func:`_residual_and_jacobian`."""
    rx, ry, j00, j01, j11, _, _, _ = _residual_and_jacobian(x, target, D, model)
    return _inverse_jacobian_times(j00, j01, j01, j11, rx, ry)


def _newton_undistort(target, D, model: str, checked: bool = False):
    """Newton on ``distort(x) = target`` for float64 numpy points ``(N, 2)``.

    First plain Newton steps on every point at once; the points that did not converge to a root inside
    the lens's fold that way are solved again with backtracking (:func:`_newton_undistort_careful`).
    Inside the fold the root is unique, so both reach the same one, and the plain steps take about half
    the careful solve's time (the VO undistorts every frame's tracks; BENCHMARKS.md).

    ``checked``: the result of :func:`_check_undistorted` (NaN where no imaged root), checking only the
    points the careful solve took: the others passed a stricter test here already.
    """
    x = target.copy()
    for _ in range(_UNDISTORT_PLAIN_ITERATIONS):
        step = _polynomial_newton_step(x, target, D, model)
        x = x - step
        if not (np.abs(step) > 1e-9).any():  # quadratic: the next residual is far below 1e-14 (NaN: careful solve)
            break
    # Plain steps can land on a root past the fold (where the radial curve rises again), which the lens
    # does not image; only roots before the first fold count.
    solved = _imaged_roots(x, target, D, model, _UNDISTORT_TOLERANCE**2)
    if not solved.all():
        rest = np.flatnonzero(~solved)
        x[rest] = _newton_undistort_careful(target[rest], D, model)
        if checked:
            x[rest] = _check_undistorted(x[rest], target[rest], D, model)
    return x


def _first_fold(D, model: str) -> float:
    """:func:`_first_fold_uncached`, remembered for the last lens (tracking asks every frame)."""
    global _last_fold
    key = (model, np.asarray(D, dtype=np.float64).tobytes())
    cached_key, fold = _last_fold  # one tuple, read and written whole: threads share it
    if cached_key != key:
        fold = _first_fold_uncached(D, model)
        _last_fold = (key, fold)
    return fold


_last_fold: tuple = (None, math.inf)


def _first_fold_uncached(D, model: str) -> float:
    """The smallest ``s = r^2 > 0`` where the radial map ``r -> r R(r^2)`` stops rising (``R + 2 s R'``
    or ``R`` reaches zero), or inf: the roots of the polynomials whose signs those are."""
    P = np.polynomial.polynomial
    numerator = np.array([1.0, D[0], D[1], D[4]])
    denominator = np.array([1.0, D[5], D[6], D[7]]) if model == "rational_polynomial" else np.array([1.0])
    # R + 2 s R' = (N Dn + 2 s (N' Dn - N Dn')) / Dn^2
    rising = P.polyadd(P.polymul(numerator, denominator),
                       P.polymulx(2 * P.polysub(P.polymul(P.polyder(numerator), denominator),
                                                P.polymul(numerator, P.polyder(denominator)))))
    fold = np.inf
    for polynomial in (rising, numerator, denominator):
        polynomial = P.polytrim(polynomial, 0.0)
        if len(polynomial) < 2:
            continue
        roots = P.polyroots(polynomial)
        real = roots.real[(np.abs(roots.imag) <= 1e-9 * np.abs(roots)) & (roots.real > 0)]
        if real.size:
            fold = min(fold, float(real.min()))
    return fold


def _newton_undistort_careful(target, D, model: str):
    """Newton with backtracking on ``distort(x) = target`` for float64 numpy points ``(N, 2)``.

    Only points not yet converged are iterated, so a few hopeless ones (beyond the fold) cost little.
    """
    x = target.copy()
    residual = distort_normalised(x, D, model) - target
    error = (residual**2).sum(-1)
    active = np.flatnonzero(error > _UNDISTORT_TOLERANCE**2)
    for _ in range(_UNDISTORT_MAX_ITERATIONS):
        if active.size == 0:
            break
        xa, ra, ea = x[active], residual[active], error[active]
        step = -_newton_step(xa, ra, D, model)
        alpha = np.ones(len(active))
        pending = np.ones(len(active), dtype=bool)
        # Backtracking: strong distortion bends the map enough for a full step to overshoot.
        for _ in range(40):
            candidate = xa[pending] + alpha[pending, None] * step[pending]
            candidate_residual = distort_normalised(candidate, D, model) - target[active[pending]]
            candidate_error = (candidate_residual**2).sum(-1)
            improved = candidate_error < ea[pending]
            index = np.flatnonzero(pending)[improved]
            xa[index], ra[index], ea[index] = candidate[improved], candidate_residual[improved], candidate_error[improved]
            pending[index] = False
            alpha[pending] *= 0.5
            if not pending.any():
                break
        previous = error[active]
        x[active], residual[active], error[active] = xa, ra, ea
        # Past a fold there is no root: Newton points at the fold, the Jacobian is nearly singular,
        # and only tiny steps help. Give up on points that needed ten halvings or made no progress
        # (an overshooting first step still counts as progress); the final check marks them NaN.
        stalled = pending | (alpha < 2.0**-10) | (ea > 0.999 * previous)
        active = active[(ea > _UNDISTORT_TOLERANCE**2) & ~stalled]
    return x


def _undistort_polynomial(xy_d, D, model: str):
    """Exact inverse of the polynomial models; NaN where it fails or lands past a fold."""
    xp = _xp(xy_d)
    if xp is not np:
        # Solve in float64 numpy, then one Newton step in torch: at the solution that step is the
        # identity in value but carries the implicit-function gradient w.r.t. points and coefficients.
        flat = xy_d.detach().reshape(-1, 2).cpu().double().numpy()
        solved = _newton_undistort(flat, D.detach().cpu().double().numpy(), model)
        x0 = xp.from_numpy(solved).to(xy_d).reshape(xy_d.shape)
        j00, j01, j10, j11 = _distortion_jacobian(x0[..., 0], x0[..., 1], D, model)
        r = distort_normalised(x0, D, model) - xy_d
        det = j00 * j11 - j01 * j10
        step = xp.stack((j11 * r[..., 0] - j01 * r[..., 1], -j10 * r[..., 0] + j00 * r[..., 1]), -1) / det[..., None]
        x = x0 - step
        ok = xp.from_numpy(np.isfinite(_check_undistorted(solved, flat, D.detach().cpu().double().numpy(), model)[:, 0]))
        ok = ok.to(xy_d.device).reshape(xy_d.shape[:-1])
        return xp.where(ok[..., None], x, xp.full_like(x, float("nan")))
    shape = xy_d.shape
    flat = np.asarray(xy_d, dtype=np.float64).reshape(-1, 2)
    return _newton_undistort(flat, D, model, checked=True).reshape(shape)


def _imaged_roots(x, target, D, model: str, max_squared_residual: float):
    """Which points ``x`` solve ``distort(x) = target`` to ``max_squared_residual`` where the lens images
    them: before the fold (Jacobian det > 0). The polynomial models only."""
    rx, ry, j00, j01, j11, s, radial, d_radial = _residual_and_jacobian(x, target, D, model)
    # Past the fold r_d(r) = r R(r^2) turns back (R + 2 s R' <= 0), and further out R < 0 mirrors
    # points through the centre; roots there satisfy the equation but are not what the lens images.
    return (
        (rx * rx + ry * ry <= max_squared_residual)
        & ((j00 * j11 - j01 * j01) > 0)
        & (radial > 0)
        & (radial + 2 * s * d_radial > 0)
        & (s < _first_fold(D, model))  # a root where the curve rises again, past a fold, is no image either
    )


def _check_undistorted(x, target, D, model: str):
    """NaN out points that do not reproduce ``target`` or lie past the fold (:func:`_imaged_roots`)."""
    return np.where(_imaged_roots(x, target, D, model, 1e-18)[:, None], x, np.nan)


def _undistort_theta(theta_d, D):
    """Solve ``theta_d = theta (1 + k1 theta^2 + ...)`` for theta by Newton; NaN where not monotone."""
    xp = _xp(theta_d)
    theta = theta_d * 1
    for _ in range(_UNDISTORT_MAX_ITERATIONS):
        value, derivative = _theta_distorted(theta, D)
        residual = value - theta_d
        if not (xp.abs(residual) > _UNDISTORT_TOLERANCE).any():
            break
        safe = xp.where(xp.abs(derivative) > 1e-12, derivative, xp.ones_like(derivative))
        theta = xp.clip(theta - residual / safe, 0.0, math.pi) if xp is np else (theta - residual / safe).clamp(0.0, math.pi)
    value, derivative = _theta_distorted(theta, D)
    ok = (xp.abs(value - theta_d) <= 1e-9) & (derivative > 0)
    return xp.where(ok, theta, xp.full_like(theta, float("nan")))


def undistort_rays(xy_d, coefficients, model: str):
    """Unit ray directions ``(..., 3)`` whose images are the distorted normalised points ``(..., 2)``.

    Exact inverse of :func:`distort_normalised` (Newton to 1e-14); NaN where the lens maps nothing
    to that point (beyond the fold of a strongly distorting polynomial). Equidistant rays may point
    more than 90 degrees off axis.
    """
    xp = _xp(xy_d)
    if model == "equidistant":
        x_d, y_d = xy_d[..., 0], xy_d[..., 1]
        r_d = xp.sqrt(x_d * x_d + y_d * y_d)
        theta = _undistort_theta(r_d, coefficients)
        safe_r = xp.where(r_d > 1e-15, r_d, xp.ones_like(r_d))
        sin_ratio = xp.where(r_d > 1e-15, xp.sin(theta) / safe_r, xp.ones_like(r_d))
        return xp.stack((x_d * sin_ratio, y_d * sin_ratio, xp.cos(theta)), -1)
    xy = _undistort_polynomial(xy_d, coefficients, model)
    rays = xp.stack((xy[..., 0], xy[..., 1], xp.ones_like(xy[..., 0])), -1)
    return rays / xp.sqrt((rays * rays).sum(-1, keepdims=True) if xp is np else (rays * rays).sum(-1, keepdim=True))


def undistort_normalised(xy_d, coefficients, model: str):
    """Undistorted normalised points ``(..., 2)`` (``X/Z``, ``Y/Z``) of distorted ones; NaN behind."""
    xp = _xp(xy_d)
    if model != "equidistant":
        return _undistort_polynomial(xy_d, coefficients, model)
    rays = undistort_rays(xy_d, coefficients, model)
    z = rays[..., 2]
    z = xp.where(z > 1e-12, z, xp.full_like(z, float("nan")))
    return rays[..., :2] / z[..., None]


# --------------------------------------------------------------------------------------------------
# Intrinsics
# --------------------------------------------------------------------------------------------------


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after resizing an image by ``sx`` horizontally and ``sy`` vertically.

    Pixel centres sit at integer coordinates, so a resize maps ``u -> (u + 0.5) sx - 0.5``:
    ``fx' = sx fx`` and ``cx' = (cx + 0.5) sx - 0.5`` (likewise for y).
    """
    K = np.asarray(K, dtype=np.float64)
    scaled = K.copy()
    scaled[0, 0] = K[0, 0] * sx
    scaled[0, 1] = K[0, 1] * sx
    scaled[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    scaled[1, 1] = K[1, 1] * sy
    scaled[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return scaled


def pixel_grid(width: int, height: int, supersample: int = 1) -> np.ndarray:
    """Pixel coordinates ``(H, W, k*k, 2)`` (u, v) of ``k x k`` subpixel sample points per pixel.

    With ``k = 1`` the single sample is the pixel centre (integer coordinates); with ``k > 1`` the
    samples are the centres of a regular ``k x k`` subdivision of the pixel square.
    """
    k = int(supersample)
    if k < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    offsets = (np.arange(k) + 0.5) / k - 0.5
    du, dv = np.meshgrid(offsets, offsets, indexing="xy")
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    grid = np.empty((height, width, k * k, 2))
    grid[..., 0] = u[..., None] + du.reshape(-1)
    grid[..., 1] = v[..., None] + dv.reshape(-1)
    return grid


# --------------------------------------------------------------------------------------------------
# CameraCalibration
# --------------------------------------------------------------------------------------------------


@dataclass
class CameraCalibration:
    """A known camera: image size, intrinsics ``K`` and lens distortion, in ROS/OpenCV conventions.

    Attributes:
        width, height: native image size in pixels.
        K: 3x3 float64 intrinsic matrix (pixel centres at integer coordinates).
        D: float64 distortion coefficients in ROS order for ``distortion_model``.
        distortion_model: ``plumb_bob``, ``rational_polynomial`` or ``equidistant``.
        camera_name: free text, kept through YAML round trips.
        R: 3x3 rectification matrix (stereo), or None for the identity of a monocular camera.
        P: 3x4 projection matrix of the rectified image, or None for ``[K | 0]``. camera_calibration
            writes a P that differs from K (the undistorted image's camera); image_proc rectifies to it.
            Both are kept through YAML and CameraInfo so a calibration round-trips unchanged.
    """

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"
    camera_name: str = "camera"
    R: np.ndarray | None = None
    P: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        if not np.all(np.isfinite(self.K)) or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError(f"camera matrix needs finite values and positive focal lengths, got {self.K.tolist()}")
        if not np.allclose(self.K[1, 0], 0) or not np.allclose(self.K[2], [0, 0, 1]):
            raise ValueError(f"camera matrix must be upper triangular with last row [0, 0, 1], got {self.K.tolist()}")
        self.D = normalise_coefficients(self.D, self.distortion_model)
        if self.R is not None:
            self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
            if not np.all(np.isfinite(self.R)):
                raise ValueError("rectification matrix R holds non-finite values")
            if np.array_equal(self.R, np.eye(3)) or not self.R.any():  # all zeros: what uncalibrated drivers send
                self.R = None
        if self.P is not None:
            self.P = np.asarray(self.P, dtype=np.float64).reshape(3, 4)
            if not np.all(np.isfinite(self.P)):
                raise ValueError("projection matrix P holds non-finite values")
            if np.array_equal(self.P, np.hstack([self.K, np.zeros((3, 1))])) or not self.P.any():
                self.P = None

    # ---- construction ------------------------------------------------------------------------

    @classmethod
    def pinhole(cls, width: int, height: int, fx: float, fy: float | None = None, cx: float | None = None,
                cy: float | None = None, **kwargs) -> "CameraCalibration":
        """A camera from focal lengths and principal point (default: the image centre)."""
        fy = fx if fy is None else fy
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        return cls(width, height, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), **kwargs)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def rectification(self) -> np.ndarray:
        """R (3x3): the identity for a monocular camera."""
        return np.eye(3) if self.R is None else self.R.copy()

    @property
    def projection(self) -> np.ndarray:
        """P (3x4): ``[K | 0]`` unless the calibration gave another."""
        return np.hstack([self.K, np.zeros((3, 1))]) if self.P is None else self.P.copy()

    def scaled(self, width: int, height: int) -> "CameraCalibration":
        """The same lens at another image size (distortion is in normalised units, so unchanged)."""
        sx, sy = width / self.width, height / self.height
        K = scale_intrinsics(self.K, sx, sy)
        P = None
        if self.P is not None:  # P's left 3x3 is a camera matrix; its last column (-fx' B) scales with fx
            P = np.hstack([scale_intrinsics(self.P[:, :3], sx, sy), self.P[:, 3:] * np.array([[sx], [sy], [1.0]])])
        return CameraCalibration(width, height, K, self.D.copy(), self.distortion_model, self.camera_name, self.R, P)

    # ---- projection --------------------------------------------------------------------------

    def _normalised_to_pixels(self, xy_d):
        K = self.K
        u = K[0, 0] * xy_d[..., 0] + K[0, 1] * xy_d[..., 1] + K[0, 2]
        v = K[1, 1] * xy_d[..., 1] + K[1, 2]
        return _xp(xy_d).stack((u, v), -1)

    def distorted_normalised(self, pixels):
        """Distorted normalised coordinates ``((u - cx) / fx, (v - cy) / fy)`` (skew removed)."""
        K = self.K
        y_d = (pixels[..., 1] - K[1, 2]) / K[1, 1]
        x_d = (pixels[..., 0] - K[0, 2] - K[0, 1] * y_d) / K[0, 0]
        return _xp(pixels).stack((x_d, y_d), -1)

    def project(self, points_cam):
        """Pixels ``(N, 2)`` of camera-frame points ``(N, 3)``; NaN for points the lens cannot see.

        Same result as ``cv2.projectPoints`` (``plumb_bob``, ``rational_polynomial``) and
        ``cv2.fisheye.projectPoints`` (``equidistant``) with zero rotation and translation.
        Accepts numpy (float64) or torch (differentiable) input.
        """
        xp = _xp(points_cam)
        D = self.D if xp is np else xp.as_tensor(self.D, dtype=points_cam.dtype, device=points_cam.device)
        X, Y, Z = points_cam[..., 0], points_cam[..., 1], points_cam[..., 2]
        if self.distortion_model == "equidistant":
            # atan2 of the off-axis distance keeps points beyond 90 degrees on the right side.
            rho = xp.sqrt(X * X + Y * Y)
            theta_d, _ = _theta_distorted(xp.arctan2(rho, Z), D)
            safe = xp.where(rho > 1e-300, rho, xp.ones_like(rho))
            scale = xp.where(rho > 1e-300, theta_d / safe, 1.0 / Z)
            xy_d = xp.stack((X * scale, Y * scale), -1)
        else:
            front = Z > 0
            safe_z = xp.where(front, Z, xp.ones_like(Z))
            xy_d = distort_normalised(xp.stack((X / safe_z, Y / safe_z), -1), D, self.distortion_model)
            xy_d = xp.where(front[..., None], xy_d, xp.full_like(xy_d, float("nan")))
        return self._normalised_to_pixels(xy_d)

    def unproject(self, pixels):
        """Unit camera-frame ray directions ``(N, 3)`` of pixels ``(N, 2)``; exact inverse of project.

        NaN where no ray maps to the pixel (outside the valid range of a strong distortion).
        """
        xp = _xp(pixels)
        D = self.D if xp is np else xp.as_tensor(self.D, dtype=pixels.dtype, device=pixels.device)
        return undistort_rays(self.distorted_normalised(pixels), D, self.distortion_model)

    def undistorted_normalised(self, pixels):
        """Undistorted normalised coordinates ``(N, 2)`` (``x/z``, ``y/z``) of pixels ``(N, 2)``."""
        xp = _xp(pixels)
        D = self.D if xp is np else xp.as_tensor(self.D, dtype=pixels.dtype, device=pixels.device)
        return undistort_normalised(self.distorted_normalised(pixels), D, self.distortion_model)

    def pixel_jacobians(self, undistorted: np.ndarray) -> np.ndarray | None:
        """``d(pixel) / d(undistorted normalised)`` ``(N, 2, 2)`` at undistorted normalised points ``(N, 2)``.

        How many pixels a move of a ray's ``(x/z, y/z)`` makes: ``f`` at a pinhole's centre, a sixth of
        that radially near a 120-degree fisheye's edge. None for ``rational_polynomial`` (no analytic
        Jacobian here).
        """
        if self.distortion_model not in ("plumb_bob", "equidistant"):
            return None
        d_distorted, _ = distortion_jacobians(np.asarray(undistorted, dtype=np.float64).reshape(-1, 2), self.D,
                                              self.distortion_model)
        return self.K[:2, :2] @ d_distorted  # pixel = K[:2, :2] distorted + principal point

    def pixel_rays(self, width: int | None = None, height: int | None = None, supersample: int = 1) -> np.ndarray:
        """The per-pixel ray table: unit directions ``(H, W, k*k, 3)`` through each subpixel sample.

        ``width``/``height`` default to the native size; another size images the same field of view
        (intrinsics scaled with :func:`scale_intrinsics`). NaN rays mark pixels the lens maps nothing to.
        """
        camera = self if width is None or (width == self.width and height == self.height) else self.scaled(width, height)
        grid = pixel_grid(camera.width, camera.height, supersample)
        return camera.unproject(grid)

    # ---- YAML (ROS camera_calibration format) -------------------------------------------------

    def to_dict(self) -> dict:
        """The ROS ``camera_calibration`` YAML mapping, as camera_calibration_parsers writes it."""
        matrix = lambda m: {"rows": int(m.shape[0]), "cols": int(m.shape[1]), "data": [float(x) for x in m.reshape(-1)]}
        return {
            "image_width": self.width,
            "image_height": self.height,
            "camera_name": self.camera_name,
            "camera_matrix": matrix(self.K),
            "distortion_model": self.distortion_model,
            "distortion_coefficients": matrix(self.D.reshape(1, -1)),
            "rectification_matrix": matrix(self.rectification),
            "projection_matrix": matrix(self.projection),
        }

    @classmethod
    def from_dict(cls, data: Any, source: str = "<dict>") -> "CameraCalibration":
        """Build from a ROS ``camera_calibration`` mapping; raises ConfigError naming ``source``."""

        def fail(problem: str) -> ConfigError:
            return ConfigError(f"{source}: {problem}")

        if not isinstance(data, dict):
            raise fail(f"expected a camera_calibration mapping, got {type(data).__name__}")
        missing = [k for k in ("image_width", "image_height", "camera_matrix") if k not in data]
        if missing:
            raise fail(f"missing key(s) {', '.join(missing)}")

        def integer(key: str) -> int:
            value = data[key]
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise fail(f"{key} must be a positive integer, got {value!r}")
            return value

        def matrix(key: str, rows: int, cols: int | None) -> np.ndarray:
            entry = data[key]
            values = entry.get("data") if isinstance(entry, dict) else entry
            if not isinstance(values, (list, tuple)):
                raise fail(f"{key} must have a 'data' list")
            try:
                array = np.array(values, dtype=np.float64)
            except (TypeError, ValueError):
                raise fail(f"{key} data must be numbers, got {values!r}") from None
            if array.ndim != 1 or (cols is not None and array.size != rows * cols):
                raise fail(f"{key} must hold {rows}x{cols} numbers, got {array.size}")
            if not np.all(np.isfinite(array)):
                raise fail(f"{key} holds non-finite values")
            return array

        width, height = integer("image_width"), integer("image_height")
        K = matrix("camera_matrix", 3, 3).reshape(3, 3)
        model = data.get("distortion_model") or "plumb_bob"
        if model not in DISTORTION_MODELS:
            raise fail(f"unsupported distortion_model {model!r} (supported: {', '.join(DISTORTION_MODELS)})")
        D = matrix("distortion_coefficients", 1, None) if data.get("distortion_coefficients") is not None else np.zeros(0)
        R = matrix("rectification_matrix", 3, 3) if data.get("rectification_matrix") is not None else None
        P = matrix("projection_matrix", 3, 4) if data.get("projection_matrix") is not None else None
        name = data.get("camera_name", "camera")
        try:
            return cls(width, height, K, D, model, str(name) if name is not None else "camera", R, P)
        except ValueError as error:
            raise fail(str(error)) from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> "CameraCalibration":
        """Read a ROS ``camera_calibration`` YAML file; ConfigError names the file and the problem."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError(f"{path}: camera file not found") from None
        except (OSError, UnicodeDecodeError) as error:
            raise ConfigError(f"{path}: cannot read camera file ({error})") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise ConfigError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
        return cls.from_dict(data, source=str(path))

    def save(self, path: str | os.PathLike) -> None:
        """Write a ROS ``camera_calibration`` YAML file atomically (never a half-written file)."""
        from nocal_ros.files import write_atomic

        write_atomic(path, yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraCalibration):
            return NotImplemented
        return (
            (self.width, self.height, self.distortion_model, self.camera_name)
            == (other.width, other.height, other.distortion_model, other.camera_name)
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.D, other.D)
            and np.array_equal(self.rectification, other.rectification)
            and np.array_equal(self.projection, other.projection)
        )
