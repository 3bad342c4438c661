"""The one NOCaL training loop: pretraining, fine-tuning on a new camera, and the trainer node's job.

Read top to bottom: config -> cameras and model -> optimisers -> the step (render both views of a
pair, weigh the paper's losses) -> the loop (curriculum stage, step, log, checkpoint, stop).

* One :class:`~nocal_ros.camera.CameraModel` per sequence (each sequence is one camera); one NOCaL
  model for all of them.
* View ``i`` is rendered at the identity (camera ``i`` is the world frame), view ``j`` at ``T_ci_cj``:
  predicted, or the ground truth on labelled pairs (as in the authors' code), on a random subset of
  ``rays_per_image`` pixels per image so that a step stays cheap at any resolution.
* Four Adam optimisers (encoder, hypernetwork, distortion, intrinsics) as in the paper. The intrinsics'
  rate is for the camera's size-independent parameterisation (see :mod:`nocal_ros.camera`).
* Curriculum (paper Sec. III-E): ``fixed`` intrinsics, then ``focal``, then ``full`` (principal point and
  distortion), with configurable lengths.
* Exact resume: model, cameras, optimiser moments, step, and every random generator are checkpointed.
* Distributed data parallel under ``torchrun`` (gloo on CPU, nccl on GPU): the model is wrapped in
  DistributedDataParallel; the few camera parameters, whose trainable set changes with the curriculum,
  have their gradients averaged explicitly.
"""

from __future__ import annotations

import copy
import csv
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from nocal_ros.camera import PAPER_EQUIVALENT_INTRINSICS_LR, CameraModel
from nocal_ros.errors import ConfigError, NocalError
from nocal_ros.epipolar import ArmCorrespondences, arm_correspondences, epipolar_loss
from nocal_ros.losses import PAPER_WEIGHTS, TERM_NAMES, LossTerms, nocal_loss
from nocal_ros.model import NOCaL, model_config

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------
# configuration
# ------------------------------------------------------------------------------------------------

DEFAULT_TRAINING_CONFIG: dict[str, Any] = {
    "seed": 0,
    "steps": 20000,
    "image_size": [80, 60],  # training resolution (width, height); cameras stay at native size
    "batch_size": 4,
    "gap_range": [1, 8],
    "labelled_every": 5,  # every n-th batch is a labelled one
    "rays_per_image": 1024,
    # curriculum: steps with fixed intrinsics, then steps learning focal only, then everything
    "curriculum": {"fixed": 2000, "focal": 6000},
    "learning_rates": {
        "encoder": 5e-5,
        "hypernetwork": 8e-5,
        "distortion": 5e-6,
        "intrinsics": PAPER_EQUIVALENT_INTRINSICS_LR,
    },
    "loss_weights": dict(PAPER_WEIGHTS),
    "camera_from_labelled_only": True,
    "square_pixels_until_full": True,  # the focal stage learns one focal (fx, fy move together)  # camera parameters step on labelled batches only (see loop)
    "grad_clip": None,  # max global grad norm of the network groups, or None
    "mixed_precision": True,  # bf16 autocast on CUDA only; CPU always runs float32
    "log_every": 50,
    "checkpoint_every": 1000,
    "model": {},  # overrides of nocal_ros.model.DEFAULT_MODEL_CONFIG
    "synthetic": None,  # used by `nocal train` without --bag (see commands/train.py)
    "camera_init": None,  # {"focal_ratio": r}: initial f = r * true f (experiments and tests only)
    # Block-coordinate schedule once the camera learns (focal and full stages): {"network": N, "camera": M}
    # repeats N steps that train only the networks, then M steps that train only the camera (network
    # frozen). None trains both on every step (the paper). See camera_phase().
    "alternate": None,
    # Arm-pose epipolar term on the camera (nocal_ros.epipolar): points tracked between arm-posed frames
    # at most max_gap apart must satisfy the epipolar constraint through the learnt camera. It steps the
    # camera on every step of the focal and full stages (it needs no labelled batch). weight 0: off.
    # max_points: over all sequences together.
    "epipolar": {"weight": 1.0, "max_gap": 8, "max_points": 6000},
    # After the last step, scale the pose head's translation so that its lengths on consecutive
    # arm-posed frames (the gap the odometry runs at) match the arm's, by least squares
    # (fit_translation_scale). Why: the pose head's length is near-constant per model, and training
    # over gaps 1..8 with unlabelled pairs left it 6x too long at gap 1 (measured, docs/RESULTS.md).
    "translation_scale_fit": True,
}

OPTIMISER_GROUPS = ("encoder", "hypernetwork", "distortion", "intrinsics")


def training_config(overrides: dict[str, Any] | None = None, source: str = "config") -> dict[str, Any]:
    """Defaults with ``overrides`` applied (nested dicts merged); unknown keys raise ConfigError."""
    config = copy.deepcopy(DEFAULT_TRAINING_CONFIG)
    for key, value in (overrides or {}).items():
        if key not in config:
            raise ConfigError(f"{source}: unknown training key {key!r}; known: {sorted(config)}")
        if isinstance(config[key], dict) and key not in ("model",):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {key} must be a mapping")
            unknown = set(value) - set(config[key])
            if unknown:
                raise ConfigError(f"{source}: unknown {key} keys {sorted(unknown)}; known: {sorted(config[key])}")
            config[key].update(value)
        else:
            config[key] = value
    try:
        config["model"] = model_config(config["model"])
    except KeyError as error:
        raise ConfigError(f"{source}: model: {error.args[0]}") from None
    _validate(config, source)
    return config


def _validate(config: dict[str, Any], source: str) -> None:
    def positive_int(name: str, value: Any) -> None:
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise ConfigError(f"{source}: {name} must be a positive integer, got {value!r}")

    for name in ("steps", "batch_size", "labelled_every", "rays_per_image", "log_every", "checkpoint_every"):
        positive_int(name, config[name])
    size = config["image_size"]
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(isinstance(s, int) and s >= 8 for s in size)):
        raise ConfigError(f"{source}: image_size must be [width, height] of at least 8 pixels, got {size!r}")
    gap = config["gap_range"]
    if not (isinstance(gap, (list, tuple)) and len(gap) == 2 and 1 <= gap[0] <= gap[1]):
        raise ConfigError(f"{source}: gap_range must be [min, max] with 1 <= min <= max, got {gap!r}")
    for name, value in config["curriculum"].items():
        if not isinstance(value, int) or value < 0:
            raise ConfigError(f"{source}: curriculum.{name} must be a non-negative integer, got {value!r}")
    alternate = config["alternate"]
    if alternate is not None and not (
        isinstance(alternate, dict) and set(alternate) == {"network", "camera"}
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in alternate.values())
    ):
        raise ConfigError(f"{source}: alternate must be null or {{network: N, camera: M}} with positive integers, got {alternate!r}")
    epipolar = config["epipolar"]
    positive_int("epipolar.max_gap", epipolar["max_gap"])
    positive_int("epipolar.max_points", epipolar["max_points"])
    for name, value in {**config["learning_rates"], **config["loss_weights"], "epipolar.weight": epipolar["weight"]}.items():
        if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ConfigError(f"{source}: {name} must be a finite non-negative number, got {value!r}")


def camera_phase(step: int, curriculum: dict[str, int], alternate: dict[str, int] | None) -> str:
    """Which parameters step at ``step``: ``"both"``, ``"network"`` or ``"camera"``.

    Why alternate (measured on a 640x480 camera, true f 600, start 640; docs/RESULTS.md, Table I):
    under simultaneous training the focal gradient's sign flips from step to step, because the
    network keeps re-fitting its rendering to the current rays, and the focal stays near its start
    (632-647 px after 1300-1500 steps). On a frozen network the gradient is consistent (24 of 24
    labelled batches agreed) and a camera phase moves the focal to that network's optimum within
    about 15 camera steps; each network phase then re-fits the network to the new camera. The frozen
    network's optimum is only as good as the network: trained from scratch it lay towards the truth
    (640 -> 616 -> 608 px), from an early pretrained model it lay away from it (640 -> 687 px).
    """
    if not alternate or step < curriculum["fixed"]:
        return "both"
    position = (step - curriculum["fixed"]) % (alternate["network"] + alternate["camera"])
    return "network" if position < alternate["network"] else "camera"


def curriculum_stage(step: int, curriculum: dict[str, int]) -> str:
    """The camera stage at ``step``: ``fixed`` for the first steps, then ``focal``, then ``full``."""
    if step < curriculum["fixed"]:
        return "fixed"
    if step < curriculum["fixed"] + curriculum["focal"]:
        return "focal"
    return "full"


# ------------------------------------------------------------------------------------------------
# the training step: render both views of each pair and weigh the losses
# ------------------------------------------------------------------------------------------------


def pair_rays(
    cameras: Sequence[CameraModel],
    camera_index: torch.Tensor,
    T_w_c: torch.Tensor,
    size: tuple[int, int],
    pixel_index: torch.Tensor,
) -> torch.Tensor:
    """Pluecker rays ``(B, N, 6)`` of each sample's own camera, posed at ``T_w_c (B, 4, 4)``.

    One call per distinct camera in the batch (not per sample); rows are put back in batch order.
    """
    width, height = size
    # Rays carry the focal gradient: keep them float32 even under autocast.
    with torch.autocast(device_type=T_w_c.device.type, enabled=False):
        indices = torch.unique(camera_index)
        if len(indices) == 1:
            return cameras[int(indices[0])].rays(T_w_c.float(), width, height, pixel_index)
        parts, rows = [], []
        for index in indices.tolist():
            selected = torch.nonzero(camera_index == index).squeeze(1)
            parts.append(cameras[index].rays(T_w_c[selected].float(), width, height, pixel_index))
            rows.append(selected)
        order = torch.argsort(torch.cat(rows))
        return torch.cat(parts)[order]


def gather_pixels(images: torch.Tensor, pixel_index: torch.Tensor) -> torch.Tensor:
    """Colours ``(B, N, 3)`` of row-major pixels ``pixel_index (N,)`` of images ``(B, 3, H, W)``."""
    return images.flatten(2)[:, :, pixel_index].transpose(1, 2)


def pair_loss(
    model: nn.Module,
    cameras: Sequence[CameraModel],
    batch: dict[str, torch.Tensor],
    pixel_index: torch.Tensor,
    loss_weights: dict[str, float] | None = None,
) -> tuple[LossTerms, torch.Tensor]:
    """The paper's loss on one batch of pairs; returns the loss terms and the predicted ``T_ci_cj``.

    ``model`` is a :class:`NOCaL` or a DistributedDataParallel wrapping one (its forward does encode,
    rays at the pose to render, render).
    """
    image_i, image_j = batch["image_i"], batch["image_j"]
    T_true, labelled, camera_index = batch["T_ci_cj"], batch["labelled"], batch["camera_index"]
    batch_size = image_i.shape[0]
    size = (image_i.shape[-1], image_i.shape[-2])
    identity = torch.eye(4, device=image_i.device).expand(batch_size, 4, 4)

    def rays_for(T_pred: torch.Tensor) -> torch.Tensor:
        # View j is rendered at the labelled pose where there is one, else at the predicted pose.
        T_render = torch.where(labelled[:, None, None], T_true, T_pred)
        rays_i = pair_rays(cameras, camera_index, identity, size, pixel_index)
        rays_j = pair_rays(cameras, camera_index, T_render, size, pixel_index)
        return torch.cat((rays_i, rays_j), dim=1)

    T_pred, z, rendered = model(image_i, image_j, rays_for)
    target = torch.cat((gather_pixels(image_i, pixel_index), gather_pixels(image_j, pixel_index)), dim=1)
    terms = nocal_loss(rendered.float(), target, T_pred.float(), T_true, labelled, z.float(), loss_weights)
    return terms, T_pred


# ------------------------------------------------------------------------------------------------
# parameter groups and optimisers
# ------------------------------------------------------------------------------------------------


def parameter_groups(model: NOCaL, cameras: Sequence[CameraModel]) -> dict[str, list[nn.Parameter]]:
    """The paper's four groups: encoder, hypernetwork, distortion (all cameras), intrinsics (all cameras)."""
    groups = model.parameter_groups()
    groups["distortion"] = [p for camera in cameras for p in camera.distortion_parameters()]
    groups["intrinsics"] = [p for camera in cameras for p in camera.intrinsic_parameters()]
    return groups


def make_optimisers(
    model: NOCaL, cameras: Sequence[CameraModel], learning_rates: dict[str, float]
) -> dict[str, torch.optim.Adam]:
    groups = parameter_groups(model, cameras)
    return {name: torch.optim.Adam(groups[name], lr=learning_rates[name]) for name in OPTIMISER_GROUPS}


# ------------------------------------------------------------------------------------------------
# pairs
# ------------------------------------------------------------------------------------------------


class PairSampler:
    """Batches from a :class:`~nocal_ros.data.pairs.PairDataset` in an order fixed by one seeded
    generator, so that a resumed run draws exactly the batches an uninterrupted one would.

    Every ``labelled_every``-th batch holds labelled pairs only; the others hold any pairs with their
    labels hidden (they train by rendering alone).
    """

    def __init__(self, dataset, batch_size: int, labelled_every: int, seed: int) -> None:
        self.dataset = dataset
        self.batch_size = batch_size
        self.labelled_every = labelled_every
        self.generator = torch.Generator().manual_seed(seed)
        self.has_labels = len(dataset.labelled_indices()) > 0
        self.batches_drawn = 0

    def next_batch(self, device: torch.device) -> dict[str, torch.Tensor]:
        self.batches_drawn += 1
        labelled = self.has_labels and self.batches_drawn % self.labelled_every == 0
        batch = self.dataset.sample(self.batch_size, labelled, self.generator)
        return {key: value.to(device) for key, value in batch.items()}

    def state(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state(), "batches_drawn": self.batches_drawn}

    def load_state(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.batches_drawn = int(state["batches_drawn"])


def optimisation_step(
    network: nn.Module,
    cameras: Sequence[CameraModel],
    optimisers: dict[str, torch.optim.Optimizer],
    batch: dict[str, torch.Tensor],
    pixel_index: torch.Tensor,
    cfg: dict[str, Any],
    world: "_DistributedContext | None" = None,
    phase: str = "both",
    correspondences: Sequence[ArmCorrespondences | None] | None = None,
) -> LossTerms | None:
    """One step of every optimiser on one batch. A non-finite loss changes nothing and is returned.

    ``phase`` (see :func:`camera_phase`): ``"network"`` steps only the encoder and hypernetwork (and
    the camera by the epipolar term alone), ``"camera"`` only the camera's intrinsics and distortion,
    ``"both"`` all four. ``correspondences`` (one entry per camera, None where a camera has none) adds
    ``cfg["epipolar"]["weight"]`` times :func:`~nocal_ros.epipolar.epipolar_loss` to every trainable
    camera of the batch on every step. Returns None when nothing would step (an unlabelled batch in a camera phase
    with ``camera_from_labelled_only`` and no epipolar term).
    """
    device = batch["image_i"].device
    camera_skipped = cfg["camera_from_labelled_only"] and not bool(batch["labelled"].any())
    epipolar_weight = float(cfg["epipolar"]["weight"]) if correspondences else 0.0
    # Whether the term is on at this step is the same on every rank (the collectives below depend on
    # it); which cameras it covers is not: those of this rank's batch, as for the photometric loss
    # (every camera on every step: 346 vs 222 ms per step with 16 pretraining cameras; BENCHMARKS.md).
    epipolar_on = [(index, camera, corr) for index, (camera, corr) in enumerate(zip(cameras, correspondences or []))
                   if corr is not None and epipolar_weight > 0 and camera.stage != "fixed"]
    in_batch = set(batch["camera_index"].tolist())
    geometric = [(camera, corr) for index, camera, corr in epipolar_on if index in in_batch]
    photometric_step = not (phase == "camera" and camera_skipped)
    if not photometric_step and not epipolar_on:
        # Nothing would step: skip the forward pass (the sampler has already drawn the batch).
        return None
    for optimiser in optimisers.values():
        optimiser.zero_grad(set_to_none=True)
    camera_parameters = [p for camera in cameras for p in camera.parameters()]
    if photometric_step:
        with _autocast(device, cfg["mixed_precision"]):
            terms, _ = pair_loss(network, cameras, batch, pixel_index, cfg["loss_weights"])
        if not torch.isfinite(terms.total):
            return terms
        terms.total.backward()
        if camera_skipped or phase == "network":
            # A predicted pose can absorb a focal error (image shift ~ f * angle), so an unlabelled
            # pair's focal gradient follows the encoder's bias; only known poses anchor the camera.
            # (Every rank draws a labelled batch at the same step, so all ranks skip together.)
            for parameter in camera_parameters:
                parameter.grad = None
    else:
        zero = torch.zeros((), device=device)
        terms = LossTerms(total=zero, photometric=zero, translation=zero, rotation=zero, latent=zero)
    if geometric:
        # Every correspondence of each camera, every step: deterministic given the batch, so exact on resume.
        geometric_loss = sum(epipolar_loss(camera, corr) for camera, corr in geometric) / len(geometric)
        if not torch.isfinite(geometric_loss):
            terms.total = terms.total + geometric_loss.detach()
            return terms
        (epipolar_weight * geometric_loss).backward()
        terms.epipolar = geometric_loss.detach()
        terms.total = terms.total.detach() + epipolar_weight * terms.epipolar
    if world is not None and (epipolar_on or not (camera_skipped or phase == "network")):
        world.average_gradients(camera_parameters)
    if cfg["square_pixels_until_full"] and cameras and cameras[0].stage == "focal":
        # One focal length until the full stage: the mean focal is well constrained by known poses
        # long before the aspect ratio is (measured: fx and fy drift apart in opposite directions).
        # Equal gradients and equal starting values keep Adam's updates of fx and fy equal.
        for camera in cameras:
            if camera.log_fx_rel.grad is not None and camera.log_fy_rel.grad is not None:
                mean = (camera.log_fx_rel.grad + camera.log_fy_rel.grad) / 2
                camera.log_fx_rel.grad = mean.clone()
                camera.log_fy_rel.grad = mean.clone()
    if cfg["grad_clip"]:
        nn.utils.clip_grad_norm_([p for o in optimisers.values() for g in o.param_groups for p in g["params"]
                                  if p.grad is not None], cfg["grad_clip"])
    for name, optimiser in optimisers.items():
        if name in ("encoder", "hypernetwork") and (phase == "camera" or not photometric_step):
            continue
        optimiser.step()
    return terms


# ------------------------------------------------------------------------------------------------
# the loop
# ------------------------------------------------------------------------------------------------


@dataclass
class TrainResult:
    """What a training run produced."""

    model: NOCaL
    cameras: list[CameraModel]
    step: int
    stage: str
    stopped: bool  # True when should_stop() ended the run early
    history: list[dict[str, Any]] = field(default_factory=list)
    checkpoint: Path | None = None  # the final model file (no optimiser state), when out_dir was given
    translation_scale: dict[str, float] | None = None  # fit_translation_scale's result, when it ran


def default_cameras(sequences: Sequence[Any], camera_init: dict[str, Any] | None = None) -> list[CameraModel]:
    """One camera per sequence at its native size: f = width and a centred principal point (the paper's
    initialisation), or ``camera_init["focal_ratio"]`` times the true focal when the sequence has one."""
    cameras = []
    for sequence in sequences:
        width, height = sequence.image_size
        if camera_init and camera_init.get("focal_ratio") and sequence.calibration is not None:
            ratio = float(camera_init["focal_ratio"])
            K = sequence.calibration.K
            cameras.append(CameraModel(width, height, fx=ratio * K[0, 0], fy=ratio * K[1, 1]))
        else:
            cameras.append(CameraModel(width, height))
    return cameras


def sequence_correspondences(
    sequences: Sequence[Any], cameras: Sequence[CameraModel], settings: dict[str, Any], device: torch.device
) -> list[ArmCorrespondences | None] | None:
    """Arm-pose correspondences of each sequence in its camera's native pixels (None where it has none),
    or None when the epipolar term is off or no sequence has any. Tracked once before training: a few
    seconds per sequence.

    ``settings["max_points"]`` is shared by the sequences with arm poses, so that the term's points
    do not grow with the number of cameras.
    """
    if not settings["weight"]:
        return None
    posed = sum(int(sequence.labelled.sum()) >= 2 for sequence in sequences)
    budget = max(1, settings["max_points"] // max(1, posed))
    found = []
    for sequence, camera in zip(sequences, cameras):
        corr = arm_correspondences(sequence.images, sequence.arm_poses, max_gap=settings["max_gap"], max_points=budget)
        if corr is None:
            log.info("%s: no two arm-posed frames within %d frames; no epipolar term for its camera", sequence.name, settings["max_gap"])
            found.append(None)
            continue
        width, height = sequence.image_size
        found.append(corr.in_native_pixels((width, height), (camera.width, camera.height)).to(device))
    return found if any(c is not None for c in found) else None


class _DistributedContext:
    """Rank, world size and the gradient averaging of whatever DDP does not own."""

    def __init__(self) -> None:
        self.enabled = dist.is_available() and dist.is_initialized()
        self.rank = dist.get_rank() if self.enabled else 0
        self.world_size = dist.get_world_size() if self.enabled else 1

    def average_gradients(self, parameters: Sequence[nn.Parameter]) -> None:
        if not self.enabled:
            return
        # Every rank reduces the same list (each trainable camera parameter, in order), even when its
        # own batch did not see that camera: collectives must match across ranks.
        for parameter in parameters:
            if not parameter.requires_grad:
                continue
            if parameter.grad is None:
                parameter.grad = torch.zeros_like(parameter)
            dist.all_reduce(parameter.grad)
            parameter.grad /= self.world_size

    def average(self, value: float) -> float:
        if not self.enabled:
            return value
        tensor = torch.tensor([value], dtype=torch.float64)
        dist.all_reduce(tensor)
        return float(tensor) / self.world_size


def _autocast(device: torch.device, enabled: bool):
    # Mixed precision on GPU only: bf16 where supported (no loss scaling needed), else full precision.
    use = enabled and device.type == "cuda" and torch.cuda.is_bf16_supported()
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=use)


def train(
    config: dict[str, Any],
    sequences: Sequence[Any],
    init: Any = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    out_dir: str | os.PathLike | None = None,
    resume: bool = False,
    cameras: list[CameraModel] | None = None,
    device: str | torch.device = "auto",
    metadata: dict[str, Any] | None = None,
) -> TrainResult:
    """Train NOCaL on ``sequences`` (a list of FrameSequence, one camera each).

    Args:
        config: training config (see :data:`DEFAULT_TRAINING_CONFIG`); missing keys take the defaults.
        sequences: the data; each sequence gets its own camera model.
        init: a checkpoint path or a loaded :class:`~nocal_ros.checkpoint.Checkpoint` whose encoder and
            hypernetwork start this run (fine-tuning); its cameras are not used, a new camera starts
            at f = width with a centred principal point, as for any unseen camera.
        progress: called every ``log_every`` steps with a dict: stage, step, steps, loss (and each
            term), fx, fy, cx, cy (first camera, native pixels), eta_s, elapsed_s.
        should_stop: polled every step; when it returns True the run checkpoints and returns.
        out_dir: where ``metrics.csv``, ``last.safetensors`` (resumable) and ``model.safetensors``
            (final, no optimiser state) go; None writes nothing.
        resume: continue exactly from ``out_dir/last.safetensors``.
        cameras: camera models to train instead of :func:`default_cameras` (one per sequence).
        device: "auto" (CUDA when available), "cpu", "cuda", ...
        metadata: extra JSON-able facts for the checkpoint sidecar.
    """
    from nocal_ros.data.pairs import PairDataset

    cfg = training_config(config)
    world = _DistributedContext()
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if str(device) == "auto" else device)
    if device.type == "cuda" and world.enabled:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    out_dir = Path(out_dir) if out_dir is not None else None
    if not sequences:
        raise NocalError("training needs at least one sequence")
    resume_path = out_dir / "last.safetensors" if (resume and out_dir is not None) else None
    if resume and (resume_path is None or not resume_path.exists()):
        raise NocalError(f"{resume_path or out_dir}: nothing to resume from (no last.safetensors)")

    # -------- model, cameras, optimisers --------
    # Same seed on every rank: identical initial weights; the data order differs by rank below.
    torch.manual_seed(cfg["seed"])
    if init is not None:
        from nocal_ros.checkpoint import load_checkpoint

        pretrained = init if hasattr(init, "model") else load_checkpoint(init)
        cfg["model"] = dict(pretrained.model.config)
        model = NOCaL(cfg["model"])
        model.load_state_dict(pretrained.model.state_dict())
    else:
        model = NOCaL(cfg["model"])
    cameras = list(cameras) if cameras is not None else default_cameras(sequences, cfg["camera_init"])
    if len(cameras) != len(sequences):
        raise NocalError(f"{len(cameras)} cameras given for {len(sequences)} sequences")
    model.to(device)
    for camera in cameras:
        camera.to(device)
    optimisers = make_optimisers(model, cameras, cfg["learning_rates"])
    width, height = cfg["image_size"]
    dataset = PairDataset(sequences, size=(width, height), gap_range=tuple(cfg["gap_range"]),
                          labelled_every=cfg["labelled_every"], seed=cfg["seed"])
    sampler = PairSampler(dataset, cfg["batch_size"], cfg["labelled_every"], seed=cfg["seed"] + 1000 * world.rank)
    correspondences = sequence_correspondences(sequences, cameras, cfg["epipolar"], device)
    pixel_generator = torch.Generator().manual_seed(cfg["seed"] + 1 + 1000 * world.rank)
    step = 0
    if resume_path is not None:
        from nocal_ros.checkpoint import load_training_state

        state = load_training_state(resume_path, model, cameras, optimisers, device=device)
        step = state["step"]
        sampler.load_state(state["sampler"])
        pixel_generator.set_state(state["pixel_generator"])
        torch.set_rng_state(state["torch_rng"])
        log.info("resumed %s at step %d", resume_path, step)
    stage = curriculum_stage(step, cfg["curriculum"])
    for camera in cameras:
        camera.set_stage(stage)
    network = (
        nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
        if world.enabled
        else model
    )

    def training_state() -> dict[str, Any]:
        return {
            "step": step,
            "stage": stage,
            "sampler": sampler.state(),
            "pixel_generator": pixel_generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "optimisers": optimisers,
        }

    def save(name: str, with_state: bool) -> Path | None:
        if out_dir is None or world.rank != 0:
            return None
        from nocal_ros.checkpoint import save_checkpoint

        return save_checkpoint(
            out_dir / name,
            model,
            cameras,
            metadata={**(metadata or {}), "config": cfg, "world_size": world.world_size, "training_resolution": [width, height],
                      "sequences": [getattr(s, "name", "") for s in sequences]},
            training_state=training_state() if with_state else None,
        )

    # -------- metrics --------
    csv_file = None
    if out_dir is not None and world.rank == 0:
        out_dir.mkdir(parents=True, exist_ok=True)
        metrics_path = out_dir / "metrics.csv"
        new_file = not (resume and metrics_path.exists())
        csv_file = open(metrics_path, "w" if new_file else "a", newline="")
        csv_writer = csv.writer(csv_file)
        if new_file:
            csv_writer.writerow(["step", "stage", "loss", *TERM_NAMES[1:], "fx", "fy", "cx", "cy", "elapsed_s"])

    # -------- loop --------
    history: list[dict[str, Any]] = []
    start_step, start_time = step, time.monotonic()
    window: list[dict[str, float]] = []
    stopped = False
    model.train()
    try:
        while step < cfg["steps"]:
            if should_stop is not None and should_stop():
                stopped = True
                break
            new_stage = curriculum_stage(step, cfg["curriculum"])
            if new_stage != stage:
                stage = new_stage
                for camera in cameras:
                    camera.set_stage(stage)
                log.info("step %d: curriculum stage %s", step, stage)

            batch = sampler.next_batch(device)
            pixel_index = torch.randperm(width * height, generator=pixel_generator)[: cfg["rays_per_image"]].to(device)
            phase = camera_phase(step, cfg["curriculum"], cfg["alternate"])
            terms = optimisation_step(network, cameras, optimisers, batch, pixel_index, cfg, world, phase, correspondences)
            if terms is not None and not torch.isfinite(terms.total):
                raise NocalError(
                    f"training diverged at step {step}: loss is {float(terms.total.detach())}"
                    + (f"; the last good checkpoint is {out_dir / 'last.safetensors'}" if out_dir else "")
                )
            step += 1

            if terms is not None:
                window.append(terms.as_floats())
            if window and (step % cfg["log_every"] == 0 or step == cfg["steps"]):
                means = {k: world.average(sum(w[k] for w in window) / len(window)) for k in window[0]}
                window = []
                fx, fy, cx, cy = (float(v.detach()) for v in cameras[0].intrinsics())
                elapsed = time.monotonic() - start_time
                rate = (step - start_step) / max(elapsed, 1e-9)
                record = {"stage": stage, "step": step, "steps": cfg["steps"], "loss": means["total"], **means,
                          "fx": fx, "fy": fy, "cx": cx, "cy": cy, "elapsed_s": elapsed,
                          "eta_s": (cfg["steps"] - step) / rate if rate > 0 else float("inf")}
                history.append(record)
                if csv_file is not None:
                    csv_writer.writerow([step, stage] + [f"{means[k]:.6g}" for k in TERM_NAMES]
                                        + [f"{v:.4f}" for v in (fx, fy, cx, cy)] + [f"{elapsed:.1f}"])
                    csv_file.flush()
                if progress is not None:
                    progress(record)
            if step % cfg["checkpoint_every"] == 0:
                save("last.safetensors", with_state=True)
    finally:
        if csv_file is not None:
            csv_file.close()

    save("last.safetensors", with_state=True)  # before the scale fit: resuming continues the run as it was
    scale_fit = None
    if cfg["translation_scale_fit"] and not stopped:  # a finishing step: a stopped run is one to resume
        scale_fit = fit_translation_scale(model, sequences, (width, height), device=device)
        if scale_fit is None:
            log.info("no two consecutive arm-posed frames: the pose head's translation scale is left as trained")
        else:
            model.encoder.scale_translation(scale_fit["factor"])
            log.info("translation scale x%.4f from %d arm-posed consecutive pairs (length RMS %.4f -> %.4f m)",
                     scale_fit["factor"], scale_fit["pairs"], scale_fit["rms_before_m"], scale_fit["rms_after_m"])
    metadata = {**(metadata or {}), **({"translation_scale": scale_fit} if scale_fit else {})}
    final = save("model.safetensors", with_state=False)
    return TrainResult(model=model, cameras=cameras, step=step, stage=stage, stopped=stopped,
                       history=history, checkpoint=final, translation_scale=scale_fit)


@torch.no_grad()
def fit_translation_scale(
    model: NOCaL, sequences: Sequence[Any], image_size: tuple[int, int], gap: int = 1,
    device: str | torch.device = "cpu", batch_size: int = 32,
) -> dict[str, float] | None:
    """Least-squares factor on the pose head's translation length over arm-posed pairs ``gap`` apart.

    ``factor = sum |t_pred| |t_arm| / sum |t_pred|^2`` minimises ``sum (factor |t_pred| - |t_arm|)^2``.
    Lengths, not vectors: the keyframe VO takes the motion from its map and only the scale from the
    pose head's lengths. Returns ``{factor, pairs, rms_before_m, rms_after_m}``, or None when
    no such pairs exist (or the head predicts no translation at all).
    """
    from nocal_ros.data.pairs import PairDataset

    dataset = PairDataset(sequences, size=image_size, gap_range=(gap, gap))
    labelled = dataset.labelled_indices()
    if len(labelled) == 0:
        return None
    was_training = model.training
    model.eval()
    predicted, true = [], []
    for start in range(0, len(labelled), batch_size):
        batch = dataset.collate(labelled[start:start + batch_size])
        T = model.predict_pose(batch["image_i"].to(device), batch["image_j"].to(device))
        predicted.append(T[:, :3, 3].norm(dim=-1).double().cpu())
        true.append(batch["T_ci_cj"][:, :3, 3].norm(dim=-1).double())
    model.train(was_training)
    predicted, true = torch.cat(predicted), torch.cat(true)
    energy = float((predicted * predicted).sum())
    if not math.isfinite(energy) or energy <= 0.0:
        return None
    factor = float((predicted * true).sum()) / energy
    rms = lambda lengths: float((lengths - true).square().mean().sqrt())  # noqa: E731
    return {"factor": factor, "pairs": int(len(true)), "rms_before_m": rms(predicted), "rms_after_m": rms(factor * predicted)}


def benchmark_steps(
    config: dict[str, Any], sequences: Sequence[Any], steps: int = 30, warmup: int = 5,
    device: str | torch.device = "auto",
) -> dict[str, Any]:
    """Time full optimisation steps (forward, backward, four Adam steps) on real pairs.

    Returns the median, mean and spread in milliseconds, with the device, threads, size and batch, so
    the printed figures say what they measured. Batches are drawn before timing; every other batch is
    labelled so both kinds of step are in the sample. The epipolar term is timed as configured (its
    one-off tracking before the loop is not: ``epipolar_points`` says how many points each step fits).
    """
    from nocal_ros.data.pairs import PairDataset

    cfg = training_config(config)
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if str(device) == "auto" else device)
    torch.manual_seed(cfg["seed"])
    model = NOCaL(cfg["model"]).to(device)
    cameras = [camera.to(device) for camera in default_cameras(sequences)]
    for camera in cameras:
        camera.set_stage("full")
    optimisers = make_optimisers(model, cameras, cfg["learning_rates"])
    width, height = cfg["image_size"]
    dataset = PairDataset(sequences, size=(width, height), gap_range=tuple(cfg["gap_range"]), seed=cfg["seed"])
    sampler = PairSampler(dataset, cfg["batch_size"], labelled_every=2, seed=cfg["seed"])
    correspondences = sequence_correspondences(sequences, cameras, cfg["epipolar"], device)
    generator = torch.Generator().manual_seed(cfg["seed"])
    batches = [sampler.next_batch(device) for _ in range(warmup + steps)]
    timings = []
    for index, batch in enumerate(batches):
        pixel_index = torch.randperm(width * height, generator=generator)[: cfg["rays_per_image"]].to(device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        optimisation_step(model, cameras, optimisers, batch, pixel_index, cfg, correspondences=correspondences)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if index >= warmup:
            timings.append((time.perf_counter() - start) * 1000.0)
    timings_array = np.array(timings)
    return {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({torch.get_num_threads()} threads)",
        "image_size": [width, height],
        "batch_size": cfg["batch_size"],
        "rays_per_image": cfg["rays_per_image"],
        "parameters": sum(p.numel() for p in model.parameters()),
        "epipolar_points": sum(len(c) for c in correspondences or [] if c is not None),
        "steps": steps,
        "median_ms": float(np.median(timings_array)),
        "mean_ms": float(timings_array.mean()),
        "p10_ms": float(np.percentile(timings_array, 10)),
        "p90_ms": float(np.percentile(timings_array, 90)),
    }
