"""NOCaL's losses (paper Sec. III-D): ``100 L_ph + 30 L_trans + 20 L_rot + 1e-6 L_enc``.

Departures from the paper's formulas, and why:

* Each term is a mean rather than a sum (over rays, over labelled pairs), so the weights mean the same
  at any image size, ray count and batch size.
* ``L_enc`` is ``mean(z^2)``: the paper writes ``mean(z)``, which is unbounded below and would push the
  latent to minus infinity; the Gaussian prior it cites (Sitzmann et al. 2021) is the squared norm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

PAPER_WEIGHTS = {"photometric": 100.0, "translation": 30.0, "rotation": 20.0, "latent": 1e-6}


def photometric_loss(rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared colour error over rays and channels: ``(B, N, 3)`` x 2 -> scalar."""
    return (rendered - target).square().mean()


def translation_loss(T_pred: torch.Tensor, T_true: torch.Tensor, labelled: torch.Tensor) -> torch.Tensor:
    """Mean squared translation error ``|x - x_hat|^2`` over labelled pairs (zero when none are)."""
    error = (T_pred[:, :3, 3] - T_true[:, :3, 3]).square().sum(-1)
    return _masked_mean(error, labelled)


def rotation_loss(T_pred: torch.Tensor, T_true: torch.Tensor, labelled: torch.Tensor) -> torch.Tensor:
    """Mean squared Frobenius error ``|R - R_hat|^2`` of rotation matrices over labelled pairs."""
    error = (T_pred[:, :3, :3] - T_true[:, :3, :3]).square().sum((-1, -2))
    return _masked_mean(error, labelled)


def latent_loss(z: torch.Tensor) -> torch.Tensor:
    """Gaussian prior on the scene latent: ``mean(z^2)``."""
    return z.square().mean()


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    mask = mask.to(values.dtype)
    # Clamped denominator: a batch without labels contributes an exact zero with a valid gradient.
    return (values * mask).sum() / mask.sum().clamp(min=1.0)


@dataclass
class LossTerms:
    """The weighted total and its unweighted parts (for logging)."""

    total: torch.Tensor
    photometric: torch.Tensor
    translation: torch.Tensor
    rotation: torch.Tensor
    latent: torch.Tensor
    #: The arm-pose epipolar term on the camera (:mod:`nocal_ros.epipolar`), unweighted; zero when off.
    epipolar: torch.Tensor = field(default_factory=lambda: torch.zeros(()))

    def as_floats(self) -> dict[str, float]:
        return {name: float(getattr(self, name).detach()) for name in TERM_NAMES}


#: Logged names of :class:`LossTerms`, in CSV column order.
TERM_NAMES = ("total", "photometric", "translation", "rotation", "latent", "epipolar")


def nocal_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    T_pred: torch.Tensor,
    T_true: torch.Tensor,
    labelled: torch.Tensor,
    z: torch.Tensor,
    weights: dict[str, float] | None = None,
) -> LossTerms:
    """The paper's weighted sum. ``labelled (B,)`` bool selects the pairs whose ``T_true`` is known."""
    w = dict(PAPER_WEIGHTS, **(weights or {}))
    terms = {
        "photometric": photometric_loss(rendered, target),
        "translation": translation_loss(T_pred, T_true, labelled),
        "rotation": rotation_loss(T_pred, T_true, labelled),
        "latent": latent_loss(z),
    }
    total = sum(w[name] * value for name, value in terms.items())
    return LossTerms(total=total, **terms)
