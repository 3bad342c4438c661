"""NOCaL: the encoder, hypernetwork and light field network tied together.

The camera models are not part of this module: one :class:`nocal_ros.camera.CameraModel` exists per
camera, while one NOCaL model serves every camera (pretraining runs across many). The training loop
asks a camera for Pluecker rays and this model for colours along them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from nocal_ros.geometry import pose_from_translation_rot6d
from nocal_ros.networks import HyperNetwork, LightFieldNetwork, PairEncoder

# The architecture of the paper (Sec. IV-B) with our shared-basis hypernetwork; a checkpoint's JSON
# sidecar stores the config it was built with, so a model is rebuilt exactly from its file.
DEFAULT_MODEL_CONFIG: dict[str, Any] = {
    "encoder_channels": [16, 32, 64, 128, 256, 256, 256],
    "latent_dim": 256,
    "scene_width": 256,
    "pose_width": 256,
    "pose_scale": 0.01,
    "hyper_width": 256,
    "hyper_depth": 3,
    "hyper_rank": 32,
    "lfn_width": 128,
    "lfn_layers": 6,
    "lfn_frequencies": 8,
}


def model_config(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The default model config with ``overrides`` applied; unknown keys are refused."""
    config = dict(DEFAULT_MODEL_CONFIG)
    for key, value in (overrides or {}).items():
        if key not in config:
            raise KeyError(f"unknown model config key {key!r}; known: {sorted(config)}")
        config[key] = value
    config["encoder_channels"] = [int(c) for c in config["encoder_channels"]]
    return config


class NOCaL(nn.Module):
    """Relative pose and a scene light field from an image pair.

    Args:
        config: model shape (see :data:`DEFAULT_MODEL_CONFIG`); missing keys take the defaults.
    """

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.config = model_config(config)
        c = self.config
        self.encoder = PairEncoder(
            channels=tuple(c["encoder_channels"]),
            latent_dim=c["latent_dim"],
            scene_width=c["scene_width"],
            pose_width=c["pose_width"],
            pose_scale=c["pose_scale"],
        )
        self.light_field = LightFieldNetwork(
            width=c["lfn_width"], layers=c["lfn_layers"], num_frequencies=c["lfn_frequencies"]
        )
        self.hypernetwork = HyperNetwork(
            latent_dim=c["latent_dim"],
            layer_shapes=self.light_field.layer_shapes(),
            width=c["hyper_width"],
            depth=c["hyper_depth"],
            rank=c["hyper_rank"],
        )

    def encode(self, image_i: torch.Tensor, image_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Images ``(B, 3, H, W)`` in [0, 1] -> ``(T_ci_cj (B, 4, 4), z (B, latent_dim))``."""
        translation, rot6d, z = self.encoder(image_i, image_j)
        return pose_from_translation_rot6d(translation, rot6d), z

    def predict_pose(self, image_i: torch.Tensor, image_j: torch.Tensor) -> torch.Tensor:
        """Pose-only path for odometry: ``T_ci_cj (B, 4, 4)``; no scene head, hypernetwork or LFN."""
        translation, rot6d = self.encoder.pose(image_i, image_j)
        return pose_from_translation_rot6d(translation, rot6d)

    def render(self, z: torch.Tensor, pluecker: torch.Tensor) -> torch.Tensor:
        """Colours ``(B, N, 3)`` of Pluecker rays ``(B, N, 6)`` in the scenes described by ``z (B, L)``."""
        return self.light_field(pluecker, self.hypernetwork(z))

    def forward(
        self,
        image_i: torch.Tensor,
        image_j: torch.Tensor,
        rays_for_pose: Callable[[torch.Tensor], torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The training path: encode the pair, ask ``rays_for_pose(T_ci_cj)`` for the Pluecker rays to
        render (they depend on the predicted pose), render them. Returns ``(T_ci_cj, z, rgb (B, N, 3))``.

        One forward call covers every parameter, as DistributedDataParallel requires.
        """
        T_ci_cj, z = self.encode(image_i, image_j)
        return T_ci_cj, z, self.render(z, rays_for_pose(T_ci_cj))

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The model's share of the paper's optimiser groups: encoder and hypernetwork."""
        return {
            "encoder": list(self.encoder.parameters()),
            "hypernetwork": list(self.hypernetwork.parameters()),
        }
