"""The three networks of NOCaL: a pair encoder, a hypernetwork, and the light field network it drives.

* :class:`PairEncoder`: SfMLearner's pose net on the stacked pair ``(B, 6, H, W)``: seven stride-2 3x3
  convolutions, a pose head of 1x1 convolutions averaged over the image (translation + 6D rotation),
  and a scene head (3 fully connected layers) that emits the scene latent ``z``.
* :class:`HyperNetwork`: maps ``z`` to the weights of one light field network per sample. The authors'
  hypernetwork was one MLP per LFN weight tensor (about 55M parameters); ours factorises the last layer
  through a shared basis: each LFN layer's weights are ``W0 + sum_k c_k(z) B_k`` with ``rank`` basis
  tensors ``B_k`` per layer. Its size is about ``rank`` times the LFN's, which keeps shipped weights small.
* :class:`LightFieldNetwork`: a Pluecker ray ``(d, o x d)`` with a sin/cos encoding -> RGB, an MLP with
  LayerNorm whose weights come per sample from the hypernetwork. It renders ``(B, N)`` rays with batched
  matrix products; no Python loop runs over samples.

All layers start from Xavier-uniform weights and zero biases, as in the paper.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

# 6D rotation of the identity: first two columns of I.
IDENTITY_ROT6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def xavier_init(module: nn.Module) -> None:
    """Xavier-uniform weights and zero biases for every conv and linear layer under ``module``."""
    for layer in module.modules():
        if isinstance(layer, (nn.Conv2d, nn.Linear)):
            nn.init.xavier_uniform_(layer.weight)
            if layer.bias is not None:
                nn.init.zeros_(layer.bias)


class PairEncoder(nn.Module):
    """Encode an image pair into the relative pose ``T_ci_cj`` (as translation + 6D) and a scene latent.

    Args:
        channels: output channels of the seven stride-2 3x3 convolutions.
        latent_dim: size of the scene latent ``z``.
        scene_width: width of the scene head's hidden layers.
        pose_width: width of the pose head's hidden 1x1 convolutions.
        pose_scale: the pose head's raw output is multiplied by this (SfMLearner uses 0.01) so that
            training starts near the identity pose rather than at a random one.
    """

    def __init__(
        self,
        channels: tuple[int, ...] = (16, 32, 64, 128, 256, 256, 256),
        latent_dim: int = 256,
        scene_width: int = 256,
        pose_width: int = 256,
        pose_scale: float = 0.01,
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        in_channels = 6
        for out_channels in channels:
            layers += [nn.Conv2d(in_channels, out_channels, 3, stride=2, padding=1), nn.LeakyReLU(0.1)]
            in_channels = out_channels
        self.features = nn.Sequential(*layers)
        self.pose_head = nn.Sequential(
            nn.Conv2d(in_channels, pose_width, 1), nn.LeakyReLU(0.1),
            nn.Conv2d(pose_width, pose_width, 1), nn.LeakyReLU(0.1),
            nn.Conv2d(pose_width, 9, 1),
        )
        self.scene_head = nn.Sequential(
            nn.Linear(in_channels, scene_width), nn.LeakyReLU(0.1),
            nn.Linear(scene_width, scene_width), nn.LeakyReLU(0.1),
            nn.Linear(scene_width, latent_dim),
        )
        self.pose_scale = pose_scale
        self.register_buffer("identity_rot6d", torch.tensor(IDENTITY_ROT6D), persistent=False)
        xavier_init(self)

    def _features(self, image_i: torch.Tensor, image_j: torch.Tensor) -> torch.Tensor:
        # Centre the [0, 1] images on zero so the first layer sees signed inputs.
        return self.features(torch.cat((image_i, image_j), dim=1) * 2.0 - 1.0)

    def _pose(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raw = self.pose_head(features).mean(dim=(2, 3)) * self.pose_scale
        return raw[:, :3], raw[:, 3:] + self.identity_rot6d

    def forward(
        self, image_i: torch.Tensor, image_j: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(B, 3, H, W)`` x 2 in [0, 1] -> ``translation (B, 3), rot6d (B, 6), z (B, latent_dim)``."""
        features = self._features(image_i, image_j)
        translation, rot6d = self._pose(features)
        z = self.scene_head(features.mean(dim=(2, 3)))
        return translation, rot6d, z

    @torch.no_grad()
    def scale_translation(self, factor: float) -> None:
        """Multiply every predicted translation by ``factor`` (exactly: the pose head's last layer is
        linear, and its first three outputs are the translation)."""
        last = self.pose_head[-1]
        last.weight[:3].mul_(factor)
        last.bias[:3].mul_(factor)

    def pose(self, image_i: torch.Tensor, image_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose only: ``translation (B, 3), rot6d (B, 6)``, skipping the scene head."""
        return self._pose(self._features(image_i, image_j))


def fourier_encoding(x: torch.Tensor, num_frequencies: int) -> torch.Tensor:
    """``(..., D) -> (..., D * (1 + 2 F))``: the input, then ``sin`` and ``cos`` of ``2^k x``, k < F."""
    frequencies = 2.0 ** torch.arange(num_frequencies, dtype=x.dtype, device=x.device)
    scaled = (x[..., None, :] * frequencies[:, None]).flatten(-2)
    return torch.cat((x, torch.sin(scaled), torch.cos(scaled)), dim=-1)


class LightFieldNetwork(nn.Module):
    """A light field MLP whose weights are given per sample: Pluecker rays ``(B, N, 6)`` -> RGB ``(B, N, 3)``.

    It owns no parameters; :meth:`layer_shapes` tells the hypernetwork what to emit. Hidden layers are
    linear -> LayerNorm (no affine: the hypernetwork already sets each layer's scale) -> ReLU; the
    output is a sigmoid so colours stay in [0, 1].
    """

    def __init__(self, width: int = 128, layers: int = 6, num_frequencies: int = 8) -> None:
        super().__init__()
        if layers < 2:
            raise ValueError("the light field network needs at least 2 layers")
        self.width = width
        self.layers = layers
        self.num_frequencies = num_frequencies
        self.input_dim = 6 * (1 + 2 * num_frequencies)

    def layer_shapes(self) -> list[tuple[int, int]]:
        """``(out_features, in_features)`` of each linear layer, input to output."""
        sizes = [self.input_dim] + [self.width] * (self.layers - 1) + [3]
        return [(sizes[k + 1], sizes[k]) for k in range(self.layers)]

    def forward(
        self, pluecker: torch.Tensor, params: list[tuple[torch.Tensor, torch.Tensor]]
    ) -> torch.Tensor:
        """Render rays ``(B, N, 6)`` with per-sample ``[(weight (B, out, in), bias (B, out)), ...]``."""
        hidden = fourier_encoding(pluecker, self.num_frequencies)
        for index, (weight, bias) in enumerate(params):
            # bias + hidden @ weight^T, one matrix product per sample, all samples at once.
            hidden = torch.baddbmm(bias.unsqueeze(1), hidden, weight.transpose(1, 2))
            if index < len(params) - 1:
                hidden = F.relu(F.layer_norm(hidden, hidden.shape[-1:]))
        return torch.sigmoid(hidden)


class HyperNetwork(nn.Module):
    """``z (B, latent_dim)`` -> per-sample weights of a :class:`LightFieldNetwork`, via a shared basis.

    A trunk MLP maps ``z`` to ``rank`` coefficients per LFN layer; each layer's weight is its base
    tensor plus the coefficient-weighted sum of its ``rank`` basis tensors (bias likewise). This is
    a hypernetwork whose last linear layer is factorised through a ``rank``-wide bottleneck per layer.

    Args:
        latent_dim: size of ``z``.
        layer_shapes: ``(out, in)`` of each LFN layer (:meth:`LightFieldNetwork.layer_shapes`).
        width: trunk width.
        depth: number of trunk layers (hidden layers with LeakyReLU).
        rank: basis tensors per LFN layer.
    """

    def __init__(
        self,
        latent_dim: int,
        layer_shapes: list[tuple[int, int]],
        width: int = 256,
        depth: int = 3,
        rank: int = 32,
    ) -> None:
        super().__init__()
        trunk: list[nn.Module] = []
        in_features = latent_dim
        for _ in range(depth):
            trunk += [nn.Linear(in_features, width), nn.LeakyReLU(0.1)]
            in_features = width
        self.trunk = nn.Sequential(*trunk)
        self.layer_shapes = [tuple(shape) for shape in layer_shapes]
        self.rank = rank
        self.coefficients = nn.Linear(in_features, rank * len(layer_shapes))
        self.base_weights = nn.ParameterList()
        self.base_biases = nn.ParameterList()
        self.basis_weights = nn.ParameterList()
        self.basis_biases = nn.ParameterList()
        for out_features, in_features_lfn in self.layer_shapes:
            self.base_weights.append(nn.Parameter(torch.empty(out_features, in_features_lfn)))
            self.base_biases.append(nn.Parameter(torch.zeros(out_features)))
            self.basis_weights.append(nn.Parameter(torch.empty(rank, out_features * in_features_lfn)))
            self.basis_biases.append(nn.Parameter(torch.zeros(rank, out_features)))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        xavier_init(self)
        # The emitted weights start Xavier-distributed: the base is Xavier, and each basis tensor is a
        # Xavier draw shrunk by sqrt(rank) so that a unit-variance coefficient vector adds a
        # perturbation of the same order, whatever the rank.
        for (out_features, in_features), base, basis in zip(
            self.layer_shapes, self.base_weights, self.basis_weights
        ):
            nn.init.xavier_uniform_(base)
            bound = math.sqrt(6.0 / (in_features + out_features)) / math.sqrt(self.rank)
            nn.init.uniform_(basis, -bound, bound)

    def forward(self, z: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``z (B, latent_dim)`` -> ``[(weight (B, out, in), bias (B, out)), ...]`` per LFN layer."""
        coefficients = self.coefficients(self.trunk(z)).view(z.shape[0], len(self.layer_shapes), self.rank)
        params = []
        for index, (out_features, in_features) in enumerate(self.layer_shapes):
            c = coefficients[:, index]
            weight = self.base_weights[index] + (c @ self.basis_weights[index]).view(-1, out_features, in_features)
            bias = self.base_biases[index] + c @ self.basis_biases[index]
            params.append((weight, bias))
        return params
