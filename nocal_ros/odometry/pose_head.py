"""The NOCaL pose head as the odometry uses it: the model (:class:`PoseModel`) and its runner.

The pose head predicts ``T_ci_cj`` (pose of the current camera in the previous camera's frame) from an
image pair. :class:`PoseRunner` runs it on consecutive frames with preallocated buffers (and CUDA graphs
where available), so the per-frame path allocates nothing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nocal_ros.errors import NocalError
from nocal_ros.network_input import network_input

log = logging.getLogger(__name__)

#: Per-frame pose head error (1 sigma) used when a checkpoint records none: 1 cm, 0.5 degrees.
DEFAULT_POSE_ERROR_STD = {"translation_m": 0.01, "rotation_rad": float(np.radians(0.5))}
#: Largest frame gap (in frames) the shipped training curriculum draws pairs from.
DEFAULT_MAX_GAP = 8

PoseFunction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class PoseModel:
    """What the estimator needs from a trained model.

    Attributes:
        predict_pose: ``(image_i, image_j)`` float32 ``(B, 3, h, w)`` in ``[0, 1]`` -> ``T_ci_cj``
            ``(B, 4, 4)``; runs under ``torch.inference_mode``.
        input_size: ``(width, height)`` the pose head was trained at; frames are resized to it.
        device: where ``predict_pose`` runs.
        max_gap: largest frame gap (frames) seen in training; longer gaps reset the chain.
        model_id: names the model in diagnostics (file name and SHA-256 prefix for checkpoints).
        pose_error_std: per-frame ``{"translation_m", "rotation_rad"}`` (see the module notes).
        camera: the learnt camera (``CameraModel``, native resolution) or None when unknown.
        module: the ``nn.Module`` behind ``predict_pose``, when there is one (for precision changes).
    """

    predict_pose: PoseFunction
    input_size: tuple[int, int]
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    max_gap: int = DEFAULT_MAX_GAP
    model_id: str = "unnamed"
    pose_error_std: dict = field(default_factory=lambda: dict(DEFAULT_POSE_ERROR_STD))
    camera: Any = None
    module: torch.nn.Module | None = None

    @classmethod
    def from_checkpoint(cls, checkpoint: Any = None, device: str | torch.device = "auto") -> "PoseModel":
        """Load a checkpoint (a path, a model store, a loaded ``Checkpoint``, or None for the shipped one)."""
        device = resolve_device(device)
        model_id = "shipped default"
        if checkpoint is None or isinstance(checkpoint, (str, Path)):
            path = None
            if checkpoint not in (None, ""):
                from nocal_ros.model_store import resolve_model_path

                path = resolve_model_path(checkpoint)
            from nocal_ros.checkpoint import load_checkpoint  # the learning core; imported when needed

            checkpoint = load_checkpoint(path, device=str(device))
        metadata = dict(getattr(checkpoint, "metadata", {}) or {})
        # The sidecar keeps training facts at its top level, the run's config under "config", and
        # whatever the trainer added (e.g. pose_error_std from validation) under "metadata".
        facts = {**(metadata.get("config") or {}), **(metadata.get("metadata") or {}), **metadata}
        model = checkpoint.model.to(device).eval()
        size = _training_size(facts)
        cameras = list(getattr(checkpoint, "cameras", []) or [])
        std = dict(DEFAULT_POSE_ERROR_STD)
        std.update({k: float(v) for k, v in (facts.get("pose_error_std") or {}).items() if k in std})
        gap = facts.get("gap_range") or facts.get("max_gap")
        max_gap = int(gap[-1] if isinstance(gap, (list, tuple)) else gap or DEFAULT_MAX_GAP)
        source = getattr(checkpoint, "path", None)
        if facts.get("weights_sha256"):
            model_id = f"{Path(source).name if source else 'checkpoint'}@{facts['weights_sha256'][:12]}"
        return cls(
            predict_pose=model.predict_pose,
            input_size=size,
            device=device,
            max_gap=max_gap,
            model_id=str(facts.get("model_id") or model_id),
            pose_error_std=std,
            camera=cameras[0].cpu() if cameras else None,  # only exported, never run per frame
            module=model,
        )


def resolve_device(device: str | torch.device) -> torch.device:
    """``"auto"`` -> CUDA when present, else CPU; anything else as torch understands it."""
    if isinstance(device, torch.device):
        return device
    if device in ("", "auto", None):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise NocalError(f"device {device!r} requested but CUDA is not available on this machine")
    return torch.device(device)


def _training_size(metadata: dict) -> tuple[int, int]:
    for key in ("training_resolution", "input_size", "image_size", "resolution"):
        value = metadata.get(key)
        if isinstance(value, dict):
            value = (value.get("width"), value.get("height"))
        if value is not None and len(value) == 2 and all(v for v in value):
            return int(value[0]), int(value[1])
    return 80, 60  # the paper's training resolution


class PoseRunner:
    """Runs the pose head on any two of the last ``history`` frames with no per-frame allocation.

    Each frame is kept (a copy) until a pair with it runs, and only then resized into a ring of
    ``history`` slots (on the model's device): the keyframe VO runs the pose head on a few frames in a
    hundred, and mapping every frame onto the network's input cost 0.5 ms at 640x480, 1.6 ms at 752x480
    and 2.4 ms at 1241x376 (one OpenCV thread, measured), against 0.06-0.08 ms for the copy. A pair is
    copied into two fixed input buffers and run. On CUDA one graph is captured over those buffers, frames
    are staged in pinned host memory (a slot each) and uploaded without blocking, and the uint8 -> float
    conversion runs on the device inside the graph. Frames are named by the key :meth:`load_frame` returns.
    """

    def __init__(self, model: PoseModel, precision: str = "fp32", cuda_graphs: bool = True, channels_last: bool = True,
                 history: int = DEFAULT_MAX_GAP + 1) -> None:
        self.model = model
        self.width, self.height = model.input_size
        self.device = model.device
        self.cuda = self.device.type == "cuda"
        if precision not in ("fp32", "fp16", "bf16"):
            raise NocalError(f"precision must be fp32, fp16 or bf16, got {precision!r}")
        self.autocast_dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}.get(precision) if self.cuda else None
        # Channels-last convolutions measured 25 % faster at 80x60 on CPU (1 thread), and the frames
        # arrive as HWC, so the layout change costs nothing. Only the memory layout of the weights changes.
        memory_format = torch.channels_last if channels_last and model.module is not None else torch.contiguous_format
        if memory_format == torch.channels_last:
            model.module.to(memory_format=memory_format)
        self.history = max(2, int(history))
        self.frames: list[np.ndarray | None] = [None] * self.history  # native frames not yet in the ring
        self.host = torch.empty((self.history, self.height, self.width, 3), dtype=torch.uint8, pin_memory=self.cuda)
        self.ring = torch.empty((self.history, self.height, self.width, 3), dtype=torch.uint8, device=self.device)
        self.pair = torch.zeros((2, self.height, self.width, 3), dtype=torch.uint8, device=self.device)
        self.inputs = [
            torch.empty((1, 3, self.height, self.width), dtype=torch.float32, device=self.device).contiguous(memory_format=memory_format)
            for _ in range(2)
        ]
        self.loaded = 0  # frames loaded so far; the newest has key loaded - 1
        self.graph: Any = None
        self.graph_output: torch.Tensor | None = None
        if self.cuda and cuda_graphs:
            self._capture()

    def _forward(self) -> torch.Tensor:
        for slot in (0, 1):
            self.inputs[slot].copy_(self.pair[slot].permute(2, 0, 1).unsqueeze(0)).mul_(1.0 / 255.0)
        with torch.autocast(self.device.type, dtype=self.autocast_dtype, enabled=self.autocast_dtype is not None):
            return self.model.predict_pose(self.inputs[0], self.inputs[1]).float()

    def _capture(self) -> None:
        try:
            stream = torch.cuda.Stream()
            stream.wait_stream(torch.cuda.current_stream())
            with torch.inference_mode(), torch.cuda.stream(stream):
                for _ in range(3):  # warm-up on a side stream, as CUDA graph capture requires
                    self._forward()
            torch.cuda.current_stream().wait_stream(stream)
            graph = torch.cuda.CUDAGraph()
            with torch.inference_mode(), torch.cuda.graph(graph):
                output = self._forward()
            self.graph, self.graph_output = graph, output
        except Exception as error:  # noqa: BLE001 - any capture failure leaves eager mode working
            log.warning("odometry: CUDA graph capture failed (%s); running eagerly", error)
            self.graph = None

    @property
    def graphs(self) -> Any:
        """The captured CUDA graph, or None (eager)."""
        return self.graph

    def load_frame(self, image: np.ndarray) -> int:
        """Keep a native RGB frame ``(H, W, 3)`` uint8 for the pose head; returns its key.

        A copy is kept, so the caller may reuse its buffer.
        """
        key = self.loaded
        self.frames[key % self.history] = np.array(image, dtype=np.uint8, copy=True)
        self.loaded += 1
        return key

    def network_image(self, key: int) -> torch.Tensor:
        """The frame ``key`` as the network sees it: ``(h, w, 3)`` uint8 on the model's device."""
        if not self.holds(key):
            raise ValueError(f"frame {key} is not among the last {self.history} loaded")
        slot = key % self.history
        frame = self.frames[slot]
        if frame is not None:
            # The training data's map (nocal_ros.network_input: the whole frame, INTER_AREA), for any frame shape.
            network_input(frame, (self.width, self.height), out=self.host[slot].numpy())
            self.ring[slot].copy_(self.host[slot], non_blocking=self.cuda)
            self.frames[slot] = None
        return self.ring[slot]

    def holds(self, key: int) -> bool:
        """The frame ``key`` is still in the ring."""
        return 0 <= key < self.loaded and self.loaded - key <= self.history

    def run(self, older: int, newer: int) -> np.ndarray:
        """``T_ci_cj`` ``(4, 4)`` float64 of the frames with keys ``older`` (i) and ``newer`` (j)."""
        if not (self.holds(older) and self.holds(newer)):
            raise ValueError(f"frames {older} and {newer} are not both among the last {self.history} loaded")
        with torch.inference_mode():
            self.pair[0].copy_(self.network_image(older))
            self.pair[1].copy_(self.network_image(newer))
            if self.graph is not None:
                self.graph.replay()
                out = self.graph_output
            else:
                out = self._forward()
            return out[0].double().cpu().numpy()
