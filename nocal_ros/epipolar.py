"""A geometric calibration signal from arm poses: the epipolar constraint through the learnt camera.

Why: the photometric loss pulls the focal towards the truth only weakly, because the light field keeps
re-fitting its rendering to whatever rays the camera currently produces (docs/RESULTS.md, Table I).
Frames that both carry an arm pose have a known relative pose ``T_ci_cj``, and every point tracked from
frame ``i`` into frame ``j`` then constrains the camera directly: its ray ``d_i`` must lie in the plane
spanned by the baseline ``t`` and the ray ``R d_j`` of the same point seen from ``j`` (both in frame
``i``). A focal error of 1 % moves a point by ``0.01 f tan(rotation)`` pixels off that plane, several
pixels at the rotations between arm-pose frames, and the lens distortion is constrained the same way
across the whole image. The constraint needs no depth and no scene model; it uses the very arm poses
that NOCaL already uses for metric scale, and the same :class:`~nocal_ros.camera.CameraModel`.

The residual of a correspondence is ``d_i . n``, ``n = normalize(t x R d_j)``: the sine of the angle
between ``d_i`` and the epipolar plane (radians for small errors). Where the arm did not translate
(``t = 0``) the rays are related by the rotation alone and the residual is ``|d_i - R d_j|``.

The focal length is only separable from the distortion because the camera's correction starts at
second order at the image centre (:data:`nocal_ros.camera.DISTORTION_FORMS`); with the MLP's raw
output the fit traded focal for distortion freely (measured on the Table I barrel lens, true f 600:
raw 457 / 470 px, centred within 0.1-0.6 %; docs/RESULTS.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from nocal_ros.odometry.frontend import detect_corners, gray_image, track_corners

log = logging.getLogger(__name__)

#: Residual scale of the robust loss, in pixels at the camera's native focal (about its tracking noise).
RESIDUAL_SCALE_PX = 1.0
#: Residuals beyond this many robust standard deviations (1.4826 x median) of all residuals, and beyond
#: :data:`MIN_GATE_FRACTION` of the image width, are mismatched tracks and left out. Measured on the
#: Table I bags (640x480): about 6 % of tracks between arm-pose frames are off by 30-100 px even through
#: the true camera, and with a bounded but non-zero pull they biased the distortion; a tight gate (3 px)
#: also dropped the corner points of a pinhole fit to a barrel lens (5-20 px off), the very points that
#: carry the distortion, so the floor is 3 % of the width (19 px at 640).
GATE_SIGMAS = 5.0
MIN_GATE_FRACTION = 0.03
#: Correspondences whose ray makes less than this sine with the baseline sit near the epipole, where
#: the epipolar plane is undefined; they are left out of the loss.
MIN_EPIPOLE_SINE = 0.05


@dataclass
class ArmCorrespondences:
    """Points tracked between frames whose relative pose the arm gives.

    Attributes:
        pixels_i, pixels_j: ``(N, 2)`` native pixel coordinates of the same scene point in frames ``i`` and ``j``.
        rotation: ``(N, 3, 3)`` ``R_ci_cj`` of each correspondence's frame pair.
        baseline: ``(N, 3)`` unit direction of ``t_ci_cj`` (camera ``j``'s centre in frame ``i``), zero
            where the arm did not translate.
        pairs: frame pairs the points came from.
    """

    pixels_i: torch.Tensor
    pixels_j: torch.Tensor
    rotation: torch.Tensor
    baseline: torch.Tensor
    pairs: int

    def __len__(self) -> int:
        return len(self.pixels_i)

    def in_native_pixels(self, image_size: tuple[int, int], native_size: tuple[int, int]) -> "ArmCorrespondences":
        """The same points, tracked on ``image_size`` frames, in the pixels of a ``native_size`` camera
        (pixel centres map as ``u -> (u + 0.5) W / w - 0.5``, the camera's own rule)."""
        if tuple(image_size) == tuple(native_size):
            return self
        scale = torch.tensor([native_size[0] / image_size[0], native_size[1] / image_size[1]])
        return ArmCorrespondences((self.pixels_i + 0.5) * scale - 0.5, (self.pixels_j + 0.5) * scale - 0.5,
                                  self.rotation, self.baseline, self.pairs)

    def to(self, device: torch.device | str) -> "ArmCorrespondences":
        return ArmCorrespondences(self.pixels_i.to(device), self.pixels_j.to(device), self.rotation.to(device),
                                  self.baseline.to(device), self.pairs)


def arm_correspondences(
    images: np.ndarray,
    arm_poses: np.ndarray,
    max_gap: int = 8,
    max_corners: int = 300,
    max_points: int = 6000,
    max_pairs: int = 400,
) -> ArmCorrespondences | None:
    """Track corners between every pair of arm-posed frames at most ``max_gap`` frames apart.

    Args:
        images: ``(N, H, W, 3)`` uint8 RGB frames at native resolution.
        arm_poses: ``(N, 4, 4)`` camera poses from the arm (hand-eye applied), NaN where a frame has none.
        max_gap: largest frame gap of a pair (wider pairs rotate more, which constrains the focal more,
            but track less reliably).
        max_corners: corners detected per frame.
        max_points: at most this many correspondences are kept, evenly over the pairs' points, so one
            evaluation of the loss stays cheap.
        max_pairs: at most this many frame pairs are tracked, evenly over the candidates, so that a
            long bag with an arm pose on every frame is not tracked 8 times over (each pair gives up
            to ``max_corners`` points; a few hundred pairs already give far more than ``max_points``).

    Returns:
        The correspondences, or None when no two arm-posed frames are within ``max_gap`` of each other.
    """
    labelled = np.flatnonzero(np.isfinite(arm_poses).all(axis=(1, 2)))
    candidates = [(i, j) for a, i in enumerate(labelled) for j in labelled[a + 1:] if j - i <= max_gap]
    if len(candidates) > max_pairs:
        candidates = [candidates[k] for k in np.linspace(0, len(candidates) - 1, max_pairs).round().astype(int)]
    pixels_i, pixels_j, rotations, baselines = [], [], [], []
    pairs = 0
    grays: dict[int, np.ndarray] = {}
    corners: dict[int, np.ndarray | None] = {}
    for i, j in candidates:
        for k in (i, j):
            if k not in grays:
                grays[k] = gray_image(images[k])
                corners[k] = detect_corners(grays[k], max_corners)
        if corners[i] is None:
            continue
        points_i, points_j, _ = track_corners(grays[i], grays[j], corners[i])
        if len(points_i) == 0:
            continue
        T_ci_cj = np.linalg.inv(arm_poses[i]) @ arm_poses[j]
        t = T_ci_cj[:3, 3]
        norm = np.linalg.norm(t)
        direction = t / norm if norm > 1e-9 else np.zeros(3)
        pixels_i.append(points_i)
        pixels_j.append(points_j)
        rotations.append(np.broadcast_to(T_ci_cj[:3, :3], (len(points_i), 3, 3)))
        baselines.append(np.broadcast_to(direction, (len(points_i), 3)))
        pairs += 1
    if not pairs:
        return None
    pixels_i, pixels_j = np.concatenate(pixels_i), np.concatenate(pixels_j)
    rotations, baselines = np.concatenate(rotations), np.concatenate(baselines)
    if len(pixels_i) > max_points:
        keep = np.linspace(0, len(pixels_i) - 1, max_points).round().astype(int)
        pixels_i, pixels_j, rotations, baselines = pixels_i[keep], pixels_j[keep], rotations[keep], baselines[keep]
    log.info("arm correspondences: %d points from %d frame pairs", len(pixels_i), pairs)
    as_tensor = lambda array: torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))  # noqa: E731
    return ArmCorrespondences(as_tensor(pixels_i), as_tensor(pixels_j), as_tensor(rotations), as_tensor(baselines), pairs)


def epipolar_residuals(camera, correspondences: ArmCorrespondences) -> tuple[torch.Tensor, torch.Tensor]:
    """Angular residuals ``(N,)`` of the correspondences through ``camera``, and a mask of usable ones.

    A correspondence is unusable when its ray lies within :data:`MIN_EPIPOLE_SINE` of the baseline
    (near the epipole the plane it must lie in is undefined).
    """
    dtype = camera.log_fx_rel.dtype
    pixels_i, pixels_j = correspondences.pixels_i.to(dtype), correspondences.pixels_j.to(dtype)
    rays_i = camera.pixel_rays(pixels_i[:, 0], pixels_i[:, 1])
    rays_j = camera.pixel_rays(pixels_j[:, 0], pixels_j[:, 1])
    rotated_j = torch.einsum("nab,nb->na", correspondences.rotation.to(dtype), rays_j)
    baseline = correspondences.baseline.to(dtype)
    normal = torch.linalg.cross(baseline, rotated_j)
    sine = normal.norm(dim=-1)
    translated = baseline.norm(dim=-1) > 0.5
    usable = ~translated | (sine.detach() > MIN_EPIPOLE_SINE)
    plane = (rays_i * normal).sum(-1) / sine.clamp(min=MIN_EPIPOLE_SINE)
    rotation_only = (rays_i - rotated_j).norm(dim=-1)
    return torch.where(translated, plane, rotation_only), usable


def epipolar_loss(camera, correspondences: ArmCorrespondences, residual_scale_px: float = RESIDUAL_SCALE_PX) -> torch.Tensor:
    """Robust mean epipolar error through ``camera``, in units of the residual scale.

    The robust function is Charbonnier's ``sqrt(1 + (r / s)^2) - 1``: quadratic within the scale ``s``
    (``residual_scale_px`` pixels at the camera's width taken as focal), linear beyond, so a camera far
    from the truth still gets a gradient. Residuals beyond a gate that follows the median residual
    (:data:`GATE_SIGMAS`, at least :data:`MIN_GATE_FRACTION`) are mismatched tracks and do not count.
    """
    residuals, usable = epipolar_residuals(camera, correspondences)
    if not bool(usable.any()):  # every point at an epipole: no constraint, and no NaN from an empty mean
        return residuals.sum() * 0.0
    scale = residual_scale_px / camera.width
    magnitude = residuals.detach().abs()
    gate = max(MIN_GATE_FRACTION, GATE_SIGMAS * 1.4826 * float(magnitude[usable].median()))
    usable = usable & (magnitude < gate)
    return (torch.sqrt(1.0 + (residuals[usable] / scale).square()) - 1.0).mean()


def calibrate_from_arm_poses(camera, correspondences: ArmCorrespondences, steps: int = 300, lr: float = 3e-3) -> list[float]:
    """Fit ``camera``'s trainable parameters to the correspondences alone (no light field); returns the losses.

    Full-batch Adam with a cosine decay; only parameters with ``requires_grad`` move, so the curriculum
    stage set on the camera applies. A diagnostic and a test of the signal; training uses
    :func:`epipolar_loss` inside the NOCaL loop.
    """
    parameters = [p for p in camera.parameters() if p.requires_grad]
    optimiser = torch.optim.Adam(parameters, lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps)
    losses = []
    for _ in range(steps):
        optimiser.zero_grad(set_to_none=True)
        loss = epipolar_loss(camera, correspondences)
        loss.backward()
        optimiser.step()
        schedule.step()
        losses.append(float(loss.detach()))
    return losses
