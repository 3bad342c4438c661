"""Checkpoints: safetensors weights plus a JSON sidecar, written atomically, loaded suspiciously.

A checkpoint ``model.safetensors`` has a sidecar ``model.json`` holding:

* ``format_version``; ``weights_file`` (the safetensors file's name) and ``weights_sha256``, so a sidecar
  copied beside other weights, or weights replaced under a sidecar, is refused;
* ``model_config`` (rebuilds :class:`~nocal_ros.model.NOCaL` exactly); ``cameras``: per camera its native
  size, intrinsics ``fx, fy, cx, cy`` at native resolution, and its distortion MLP's shape (the MLP's
  weights are tensors in the safetensors file); ``training_resolution``; ``config``; free ``metadata``;
* for a resumable checkpoint, ``training``: step, stage, sampler counter and optimiser hyperparameters.

Tensors (never pickles): ``model.*``, ``camera.<k>.*``, and for resumable checkpoints ``optim.*``
(Adam moments and step counts) and ``rng.*`` (generator states as uint8).

Writing goes to a temporary file in the same directory, is fsynced and moved into place with
``os.replace``: weights first, sidecar last, so a crash leaves either the old pair or a new weights file
whose hash the old sidecar does not match (refused, never silently mixed).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as safetensors_load
from safetensors.torch import save as safetensors_save

from nocal_ros.camera import CameraModel
from nocal_ros.errors import CheckpointError
from nocal_ros.model import NOCaL, model_config

FORMAT_VERSION = 1
DEFAULT_MODEL_PATH = Path(__file__).resolve().parent / "models" / "default.safetensors"


@dataclass
class Checkpoint:
    """A loaded checkpoint: the model, one camera per trained sequence, and the sidecar's facts."""

    model: NOCaL
    cameras: list[CameraModel]
    metadata: dict[str, Any]
    path: Path | None = None
    training: dict[str, Any] | None = field(default=None, repr=False)


def sidecar_path(path: str | os.PathLike) -> Path:
    return Path(path).with_suffix(".json")


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------


def _write_atomic(path: Path, data: bytes) -> None:
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(temporary, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        if temporary.exists():
            temporary.unlink()
    # Make the rename itself durable.
    try:
        directory = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(directory)
    except OSError:
        pass
    finally:
        os.close(directory)


#: Sidecar name of each :data:`~nocal_ros.camera.DISTORTION_FORMS` entry (``mlp``: the raw output, the
#: only form before the centred one, so older files keep their meaning).
DISTORTION_TYPES = {"raw": "mlp", "centred": "mlp_centred"}


def _camera_facts(camera: CameraModel) -> dict[str, Any]:
    fx, fy, cx, cy = (float(v.detach()) for v in camera.intrinsics())
    linear = [m for m in camera.distortion if isinstance(m, torch.nn.Linear)]
    return {
        "width": camera.width,
        "height": camera.height,
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "distortion": {"type": DISTORTION_TYPES[camera.distortion_form], "layers": len(linear), "hidden": linear[0].out_features},
        "stage": camera.stage,
    }


def _optimiser_tensors(optimisers: dict[str, torch.optim.Optimizer]) -> tuple[dict[str, torch.Tensor], dict]:
    """Adam states as flat tensors ``optim.<group>.<param index>.<name>`` plus JSON hyperparameters."""
    tensors: dict[str, torch.Tensor] = {}
    hyper: dict[str, Any] = {}
    for name, optimiser in optimisers.items():
        state = optimiser.state_dict()
        hyper[name] = [{k: v for k, v in group.items() if k != "params"} for group in state["param_groups"]]
        for index, values in state["state"].items():
            for key, value in values.items():
                tensors[f"optim.{name}.{index}.{key}"] = torch.as_tensor(value).detach().cpu().contiguous()
    return tensors, hyper


def save_checkpoint(
    path: str | os.PathLike,
    model: NOCaL,
    cameras: list[CameraModel],
    metadata: dict[str, Any] | None = None,
    training_state: dict[str, Any] | None = None,
) -> Path:
    """Write ``path`` (.safetensors) and its ``.json`` sidecar atomically; returns ``path``.

    ``metadata`` may hold ``config`` and ``training_resolution`` (stored at the sidecar's top level) and
    anything JSON-able. ``training_state`` (from the training loop: step, stage, sampler, generators,
    optimisers) makes the checkpoint resumable.
    """
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(f"{path}: checkpoint files must end in .safetensors")
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = dict(metadata or {})
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    for index, camera in enumerate(cameras):
        tensors.update({f"camera.{index}.{k}": v.detach().cpu().contiguous() for k, v in camera.state_dict().items()})
    training_json = None
    if training_state is not None:
        optimiser_tensors, hyper = _optimiser_tensors(training_state["optimisers"])
        tensors.update(optimiser_tensors)
        tensors["rng.sampler"] = training_state["sampler"]["generator"]
        tensors["rng.pixels"] = training_state["pixel_generator"]
        tensors["rng.torch"] = training_state["torch_rng"]
        training_json = {
            "step": int(training_state["step"]),
            "stage": training_state["stage"],
            "batches_drawn": int(training_state["sampler"]["batches_drawn"]),
            "optimisers": hyper,
        }
    data = safetensors_save(tensors)
    sidecar = {
        "format_version": FORMAT_VERSION,
        "weights_file": path.name,
        "weights_sha256": hashlib.sha256(data).hexdigest(),
        "model_config": model.config,
        "cameras": [_camera_facts(camera) for camera in cameras],
        "training_resolution": metadata.pop("training_resolution", None),
        "config": metadata.pop("config", None),
        "metadata": metadata,
        "training": training_json,
    }
    text = json.dumps(sidecar, indent=1, sort_keys=True, default=_json_default)
    _write_atomic(path, data)
    _write_atomic(sidecar_path(path), text.encode())
    return path


def _json_default(value: Any) -> Any:
    if isinstance(value, (tuple, set)):
        return list(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------


def _read(path: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The sidecar and the tensors of ``path``, after every consistency check that needs no model."""
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file does not exist")
    side = sidecar_path(path)
    if not side.is_file():
        raise CheckpointError(f"{path}: JSON sidecar {side.name} is missing")
    try:
        sidecar = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CheckpointError(f"{side}: sidecar is not valid JSON ({error})") from None
    if not isinstance(sidecar, dict):
        raise CheckpointError(f"{side}: sidecar is not a JSON object")
    version = sidecar.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(f"{side}: checkpoint format version {version!r}, this software reads {FORMAT_VERSION}")
    if sidecar.get("weights_file") != path.name:
        raise CheckpointError(
            f"{side}: sidecar describes {sidecar.get('weights_file')!r}, not {path.name!r}")
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != sidecar.get("weights_sha256"):
        raise CheckpointError(f"{path}: weights do not match the sidecar's checksum (changed, truncated or replaced)")
    try:
        # safetensors parses a JSON header and raw arrays: a pickle or other file fails here, unexecuted.
        tensors = safetensors_load(data)
    except (SafetensorError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: not a readable safetensors file ({error})") from None
    for name, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path}: tensor {name} holds NaN or infinite values")
    return sidecar, tensors


def _load_strict(module: torch.nn.Module, tensors: dict[str, torch.Tensor], prefix: str, path: Path) -> None:
    expected = module.state_dict()
    given = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
    missing = sorted(set(expected) - set(given))
    extra = sorted(set(given) - set(expected))
    if missing or extra:
        raise CheckpointError(
            f"{path}: tensors do not match the model described by the sidecar "
            f"(missing {[prefix + k for k in missing][:5]}, unexpected {[prefix + k for k in extra][:5]})")
    for key, value in expected.items():
        if given[key].shape != value.shape or given[key].dtype != value.dtype:
            raise CheckpointError(
                f"{path}: tensor {prefix + key} is {tuple(given[key].shape)} {given[key].dtype}, "
                f"the model needs {tuple(value.shape)} {value.dtype}")
    module.load_state_dict(given, strict=True)


def _build(path: Path, sidecar: dict[str, Any], tensors: dict[str, torch.Tensor]) -> tuple[NOCaL, list[CameraModel]]:
    try:
        model = NOCaL(model_config(sidecar.get("model_config") or {}))
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{sidecar_path(path)}: invalid model_config ({error})") from None
    _load_strict(model, tensors, "model.", path)
    cameras = []
    facts = sidecar.get("cameras")
    if not isinstance(facts, list):
        raise CheckpointError(f"{sidecar_path(path)}: 'cameras' must be a list")
    for index, fact in enumerate(facts):
        try:
            distortion_type = (fact.get("distortion") or {}).get("type", "mlp")
            forms = {name: form for form, name in DISTORTION_TYPES.items()}
            if distortion_type not in forms:
                raise ValueError(f"unknown distortion type {distortion_type!r}; this software reads {sorted(forms)}")
            camera = CameraModel(int(fact["width"]), int(fact["height"]), distortion_form=forms[distortion_type])
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise CheckpointError(f"{sidecar_path(path)}: camera {index} is malformed ({error})") from None
        _load_strict(camera, tensors, f"camera.{index}.", path)
        intrinsics = [float(v.detach()) for v in camera.intrinsics()]
        stated = [fact.get(k) for k in ("fx", "fy", "cx", "cy")]
        if not all(isinstance(s, (int, float)) and math.isclose(a, s, rel_tol=1e-5, abs_tol=1e-3)
                   for a, s in zip(intrinsics, stated)):
            raise CheckpointError(
                f"{sidecar_path(path)}: camera {index} intrinsics {stated} disagree with the weights {intrinsics}")
        camera.set_stage(fact.get("stage", "full") if fact.get("stage") in ("fixed", "focal", "full") else "full")
        cameras.append(camera)
    known = {k for k in tensors if k.startswith(("model.", "camera.", "optim.", "rng."))}
    stray_cameras = {k for k in tensors if k.startswith("camera.") and int(k.split(".")[1]) >= len(facts)}
    if stray_cameras or known != set(tensors):
        raise CheckpointError(f"{path}: unexpected tensors {sorted(stray_cameras | (set(tensors) - known))[:5]}")
    return model, cameras


def load_checkpoint(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> Checkpoint:
    """Load a checkpoint (a file, a model-store version or store directory; None: the shipped default).

    Raises:
        CheckpointError: missing, corrupt, truncated, hostile or inconsistent files, with the reason.
    """
    if path is None:
        path = DEFAULT_MODEL_PATH
    else:
        from nocal_ros.model_store import resolve_model_path

        path = resolve_model_path(path)
    path = Path(path)
    sidecar, tensors = _read(path)
    model, cameras = _build(path, sidecar, tensors)
    model.to(device)
    for camera in cameras:
        camera.to(device)
    metadata = {k: v for k, v in sidecar.items() if k not in ("training",)}
    return Checkpoint(model=model.eval(), cameras=cameras, metadata=metadata, path=path, training=sidecar.get("training"))


def load_training_state(
    path: str | os.PathLike,
    model: NOCaL,
    cameras: list[CameraModel],
    optimisers: dict[str, torch.optim.Optimizer],
    device: str | torch.device = "cpu",
) -> dict[str, Any]:
    """Restore a resumable checkpoint into live objects (model, cameras, optimisers) for exact resume.

    Returns ``step``, ``stage``, ``sampler`` state, ``pixel_generator`` and ``torch_rng`` states.
    """
    path = Path(path)
    sidecar, tensors = _read(path)
    training = sidecar.get("training")
    if not isinstance(training, dict):
        raise CheckpointError(f"{path}: not a resumable checkpoint (no training state)")
    if model_config(sidecar.get("model_config") or {}) != model.config:
        raise CheckpointError(f"{path}: model_config differs from the run being resumed")
    if len(sidecar.get("cameras") or []) != len(cameras):
        raise CheckpointError(f"{path}: holds {len(sidecar.get('cameras') or [])} cameras, the run has {len(cameras)}")
    _load_strict(model, tensors, "model.", path)
    for index, camera in enumerate(cameras):
        _load_strict(camera, tensors, f"camera.{index}.", path)
    for name, optimiser in optimisers.items():
        hyper = training.get("optimisers", {}).get(name)
        current = optimiser.state_dict()
        if not isinstance(hyper, list) or len(hyper) != len(current["param_groups"]):
            raise CheckpointError(f"{path}: optimiser {name!r} state is missing or malformed")
        state: dict[int, dict[str, torch.Tensor]] = {}
        prefix = f"optim.{name}."
        for key, value in tensors.items():
            if key.startswith(prefix):
                index, field_name = key[len(prefix):].split(".", 1)
                state.setdefault(int(index), {})[field_name] = value.to(device) if field_name != "step" else value
        groups = [dict(h, params=g["params"]) for h, g in zip(hyper, current["param_groups"])]
        try:
            optimiser.load_state_dict({"state": state, "param_groups": groups})
        except (ValueError, KeyError, RuntimeError) as error:
            raise CheckpointError(f"{path}: optimiser {name!r} state does not fit ({error})") from None
    try:
        return {
            "step": int(training["step"]),
            "stage": str(training["stage"]),
            "sampler": {"generator": tensors["rng.sampler"], "batches_drawn": int(training["batches_drawn"])},
            "pixel_generator": tensors["rng.pixels"],
            "torch_rng": tensors["rng.torch"],
        }
    except KeyError as error:
        raise CheckpointError(f"{path}: training state lacks {error}") from None
