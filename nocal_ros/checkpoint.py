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

The weights and the sidecar are replaced as a pair. Both are written to temporary files first
(fsynced); the current pair is kept as ``.<name>.previous`` (hard links, so no copy) until the new
weights and then the new sidecar have been moved into place with ``os.replace``; only then is the
previous pair removed. A crash, a kill or a full disk at any moment therefore leaves a complete pair:
the new one, the old one, or (inside the window between the two renames) the old one as
``.previous``, which the loader falls back to when the pair under the real names does not match.
Weights and sidecar are never silently mixed: the sidecar carries the weights' SHA-256.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as safetensors_load
from safetensors.torch import save as safetensors_save

from nocal_ros.camera import STAGES, CameraModel
from nocal_ros.errors import CheckpointError
from nocal_ros.files import fsync_dir, pause_point, remove_stale_temporaries, temporary_name
from nocal_ros.model import DEFAULT_MODEL_CONFIG, NOCaL, model_config

log = logging.getLogger(__name__)

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


#: Points of the pair commit where the test hook ``NOCAL_CHECKPOINT_PAUSE_AT`` can hold a writer (see
#: :func:`nocal_ros.files.pause_point`); "weights-replaced" is inside the window between the two renames.
PAUSE_POINTS = ("previous-kept", "weights-replaced", "sidecar-replaced")


def previous_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """Where the pair being replaced is kept until the new pair is complete: ``(weights, sidecar)``."""
    path = Path(path)
    side = sidecar_path(path)
    return path.with_name(f".{path.name}.previous"), side.with_name(f".{side.name}.previous")


def _keep_copy(source: Path, destination: Path) -> None:
    """``destination`` becomes a copy of ``source`` in one rename: a hard link where the filesystem has
    them (no data copied), else a real copy."""
    temporary = temporary_name(destination)
    try:
        try:
            os.link(source, temporary)
        except OSError:  # FAT, some network filesystems
            shutil.copyfile(source, temporary)
        os.replace(temporary, destination)
    finally:
        with contextlib.suppress(OSError):
            temporary.unlink()


def _pair_matches(weights: Path, side: Path) -> bool:
    """True when ``side`` holds the SHA-256 of ``weights`` (a complete pair)."""
    try:
        recorded = json.loads(side.read_text(encoding="utf-8")).get("weights_sha256")
        digest = hashlib.sha256()
        with open(weights, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except (OSError, ValueError, AttributeError, RecursionError):
        return False
    return digest.hexdigest() == recorded


def _replace_pair(path: Path, data: bytes, sidecar_text: str) -> None:
    """Replace ``path`` and its sidecar so that a complete pair exists at every moment (module notes)."""
    side = sidecar_path(path)
    previous_weights, previous_side = previous_paths(path)
    for name in (path, side, previous_weights, previous_side):
        remove_stale_temporaries(name)  # a writer killed mid-save leaves its temporary files
    weights_tmp, side_tmp = temporary_name(path), temporary_name(side)
    try:
        for temporary, content in ((weights_tmp, data), (side_tmp, sidecar_text.encode())):
            with open(temporary, "wb") as handle:
                handle.write(content)
                handle.flush()
                os.fsync(handle.fileno())
        if path.is_file() and side.is_file():
            # A previous pair left behind means an earlier save stopped between its two renames: the
            # pair under the real names may then be the mismatched one, and the previous pair the good one.
            stale = previous_weights.exists() or previous_side.exists()
            if not stale or _pair_matches(path, side):
                _keep_copy(path, previous_weights)
                _keep_copy(side, previous_side)
                fsync_dir(path.parent)
        pause_point("CHECKPOINT", "previous-kept")
        os.replace(weights_tmp, path)
        pause_point("CHECKPOINT", "weights-replaced")
        os.replace(side_tmp, side)
        fsync_dir(path.parent)
        pause_point("CHECKPOINT", "sidecar-replaced")
    finally:
        for temporary in (weights_tmp, side_tmp):
            with contextlib.suppress(OSError):
                temporary.unlink()
    for kept in (previous_weights, previous_side):
        kept.unlink(missing_ok=True)
    fsync_dir(path.parent)


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
    try:
        _replace_pair(path, data, text)
    except OSError as error:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        raise CheckpointError(f"{path}: {error.strerror or 'no space left on device'} while saving the checkpoint; "
                              "no partial file was left and the previous checkpoint is kept") from error
    return path


def _json_default(value: Any) -> Any:
    if isinstance(value, (tuple, set)):
        return list(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


# ------------------------------------------------------------------------------------------------
# validating: a sidecar and a safetensors header are untrusted input until every field is checked
# ------------------------------------------------------------------------------------------------
#
# Nothing is built from a sidecar before it passes these checks, and no tensor is allocated before the
# shapes it declares, rebuilt on torch's "meta" device (no memory), match the safetensors header. The
# bounds are far above any model this package trains (the shipped one: 4.8 M parameters, 80x60 input)
# and far below what would exhaust a robot's memory.

MAX_SIDECAR_BYTES = 16 << 20
MAX_HEADER_BYTES = 100 << 20  # safetensors' own limit on its JSON header
MAX_CHECKPOINT_BYTES = 4 << 30  # weights plus Adam moments of the largest model allowed below
MAX_MODEL_PARAMETERS = 200_000_000
MAX_CAMERAS = 1024
MAX_NATIVE_SIDE = 8192  # pixels: a 67-megapixel sensor
TRAINING_SIDE_RANGE = (8, 4096)  # pixels of the network's input
MAX_FRAME_GAP = 1000
MAX_FOCAL_PX = 1e6
MAX_POSE_ERROR_STD = {"translation_m": 100.0, "rotation_rad": math.pi}
#: ``model_config`` integer fields and their inclusive ranges; ``encoder_channels`` bounds each entry.
MODEL_CONFIG_RANGES = {
    "encoder_channels": (1, 2048), "latent_dim": (1, 4096), "scene_width": (1, 4096), "pose_width": (1, 4096),
    "hyper_width": (1, 4096), "hyper_depth": (1, 16), "hyper_rank": (1, 1024), "lfn_width": (1, 4096),
    "lfn_layers": (1, 32), "lfn_frequencies": (0, 32),
}
MAX_ENCODER_LAYERS = 16
#: Facts the odometry reads from a checkpoint (``PoseModel.from_checkpoint`` looks in the sidecar's top
#: level, its ``config`` and its ``metadata``), so each is validated wherever it appears.
SIZE_FACTS = ("training_resolution", "input_size", "image_size", "resolution")
_SAFETENSORS_DTYPES = {
    torch.float64: "F64", torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16",
    torch.int64: "I64", torch.int32: "I32", torch.int16: "I16", torch.int8: "I8", torch.uint8: "U8", torch.bool: "BOOL",
}


def _show(value: Any) -> str:
    """A hostile value, shown short."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


class _Fields:
    """Checks on one sidecar; each failure is a CheckpointError naming the file and the field."""

    def __init__(self, side: Path) -> None:
        self.side = side

    def fail(self, where: str, problem: str, value: Any) -> CheckpointError:
        return CheckpointError(f"{self.side}: {where} {problem}, got {_show(value)}")

    def integer(self, value: Any, where: str, low: int, high: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(where, "must be an integer", value)
        if not low <= value <= high:
            raise self.fail(where, f"must be between {low} and {high}", value)
        return value

    def number(self, value: Any, where: str, low: float = -math.inf, high: float = math.inf, above: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(where, "must be a number", value)
        if not math.isfinite(value):
            raise self.fail(where, "must be finite", value)
        if value < low or value > high or (above and value <= low):
            bound = f"above {low:g}" if above else f"at least {low:g}"
            raise self.fail(where, f"must be {bound} and at most {high:g}", value)
        return float(value)

    def mapping(self, value: Any, where: str, optional: bool = False) -> dict | None:
        if value is None and optional:
            return None
        if not isinstance(value, dict):
            raise self.fail(where, "must be a JSON object" + (" or null" if optional else ""), value)
        return value

    def sequence(self, value: Any, where: str, low: int, high: int) -> list:
        if not isinstance(value, list):
            raise self.fail(where, "must be a list", value)
        if not low <= len(value) <= high:
            raise self.fail(where, f"must hold {low} to {high} entries" if low != high else f"must hold {low} entries", value)
        return value

    def size(self, value: Any, where: str) -> None:
        """``[width, height]`` (or ``{"width", "height"}``) of the network input."""
        if isinstance(value, dict):
            value = [value.get("width"), value.get("height")]
            where += " (width, height)"
        for index, side in enumerate(self.sequence(value, where, 2, 2)):
            self.integer(side, f"{where}[{index}]", *TRAINING_SIDE_RANGE)

    def facts(self, facts: dict, where: str) -> None:
        """The keys the odometry reads, wherever they appear (see :data:`SIZE_FACTS`)."""
        for key in SIZE_FACTS:
            if facts.get(key) is not None:
                self.size(facts[key], f"{where}{key}")
        if facts.get("gap_range") is not None:
            low, high = self.sequence(facts["gap_range"], f"{where}gap_range", 2, 2)
            self.integer(low, f"{where}gap_range[0]", 1, MAX_FRAME_GAP)
            self.integer(high, f"{where}gap_range[1]", low, MAX_FRAME_GAP)
        if facts.get("max_gap") is not None:
            self.integer(facts["max_gap"], f"{where}max_gap", 1, MAX_FRAME_GAP)
        if facts.get("model_id") is not None and not (isinstance(facts["model_id"], str) and len(facts["model_id"]) <= 200):
            raise self.fail(f"{where}model_id", "must be a string of at most 200 characters", facts["model_id"])
        if "pose_error_std" in facts:
            std = self.mapping(facts["pose_error_std"], f"{where}pose_error_std", optional=True) or {}
            for key, high in MAX_POSE_ERROR_STD.items():
                if key in std:
                    self.number(std[key], f"{where}pose_error_std.{key}", 0.0, high, above=True)

    def model_config(self, config: Any) -> dict:
        config = self.mapping(config, "model_config")
        unknown = sorted(set(config) - set(DEFAULT_MODEL_CONFIG))
        if unknown:
            raise self.fail("model_config", f"has unknown keys {unknown[:5]}; known: {sorted(DEFAULT_MODEL_CONFIG)}", unknown)
        for key, (low, high) in MODEL_CONFIG_RANGES.items():
            if key not in config:
                continue
            if key == "encoder_channels":
                for index, channels in enumerate(self.sequence(config[key], f"model_config.{key}", 1, MAX_ENCODER_LAYERS)):
                    self.integer(channels, f"model_config.{key}[{index}]", low, high)
            else:
                self.integer(config[key], f"model_config.{key}", low, high)
        if "pose_scale" in config:
            self.number(config["pose_scale"], "model_config.pose_scale", 0.0, 1e6, above=True)
        return config

    def camera(self, fact: Any, index: int) -> None:
        where = f"cameras[{index}]"
        fact = self.mapping(fact, where)
        for key in ("width", "height"):
            self.integer(fact.get(key), f"{where}.{key}", 1, MAX_NATIVE_SIDE)
        for key in ("fx", "fy"):
            self.number(fact.get(key), f"{where}.{key}", 0.0, MAX_FOCAL_PX, above=True)
        for key in ("cx", "cy"):
            self.number(fact.get(key), f"{where}.{key}", -MAX_FOCAL_PX, MAX_FOCAL_PX)
        distortion = self.mapping(fact.get("distortion", {}), f"{where}.distortion")
        if distortion.get("type", "mlp") not in DISTORTION_TYPES.values():
            raise CheckpointError(f"{self.side}: {where}: unknown distortion type {_show(distortion.get('type'))}; "
                                  f"this software reads {sorted(DISTORTION_TYPES.values())}")
        for key, high in (("layers", 64), ("hidden", 1024)):
            if key in distortion:
                self.integer(distortion[key], f"{where}.distortion.{key}", 1, high)
        if "stage" in fact and fact["stage"] not in STAGES:
            raise self.fail(f"{where}.stage", f"must be one of {list(STAGES)}", fact["stage"])

    def training(self, training: Any) -> None:
        training = self.mapping(training, "training", optional=True)
        if training is None:
            return
        self.integer(training.get("step"), "training.step", 0, 10**12)
        self.integer(training.get("batches_drawn"), "training.batches_drawn", 0, 10**12)
        if training.get("stage") not in STAGES:
            raise self.fail("training.stage", f"must be one of {list(STAGES)}", training.get("stage"))
        for name, groups in self.mapping(training.get("optimisers"), "training.optimisers").items():
            for index, group in enumerate(self.sequence(groups, f"training.optimisers.{name}", 1, 64)):
                where = f"training.optimisers.{name}[{index}]"
                for key, value in self.mapping(group, where).items():
                    if isinstance(value, list):
                        for item_index, item in enumerate(value):
                            self.number(item, f"{where}.{key}[{item_index}]")
                    elif isinstance(value, (int, float)) and not isinstance(value, bool):
                        self.number(value, f"{where}.{key}", 0.0)
                    elif value is not None and not isinstance(value, (bool, str)):
                        raise self.fail(f"{where}.{key}", "must be a number, a list of numbers, a string or a boolean", value)


def validate_sidecar(sidecar: Any, side: Path, weights_name: str) -> None:
    """Check every field of a parsed sidecar for type, finiteness and range; CheckpointError otherwise.

    Only then may anything be built from it (:func:`_check_header` compares the declared shapes with
    the weights file before a tensor is allocated).
    """
    fields = _Fields(side)
    fields.mapping(sidecar, "the sidecar")
    version = sidecar.get("format_version")
    if isinstance(version, bool) or version != FORMAT_VERSION:
        raise CheckpointError(f"{side}: checkpoint format version {_show(version)}, this software reads {FORMAT_VERSION}")
    if sidecar.get("weights_file") != weights_name:
        raise CheckpointError(f"{side}: sidecar describes {_show(sidecar.get('weights_file'))}, not {weights_name!r}")
    digest = sidecar.get("weights_sha256")
    if not (isinstance(digest, str) and len(digest) == 64 and all(c in "0123456789abcdef" for c in digest)):
        raise fields.fail("weights_sha256", "must be 64 lowercase hex digits", digest)
    fields.model_config(sidecar.get("model_config") or {})
    for index, fact in enumerate(fields.sequence(sidecar.get("cameras"), "cameras", 0, MAX_CAMERAS)):
        fields.camera(fact, index)
    config = fields.mapping(sidecar.get("config"), "config", optional=True) or {}
    metadata = fields.mapping(sidecar.get("metadata", {}), "metadata", optional=True) or {}
    for facts, where in ((sidecar, ""), (config, "config."), (metadata, "metadata.")):
        fields.facts(facts, where)
    fields.training(sidecar.get("training"))


def _read_sidecar(side: Path) -> Any:
    try:
        size = side.stat().st_size
        if size > MAX_SIDECAR_BYTES:
            raise CheckpointError(f"{side}: sidecar is {size} bytes; a checkpoint sidecar is at most {MAX_SIDECAR_BYTES}")
        return json.loads(side.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as error:  # ValueError: bad JSON, or an integer of 4300+ digits
        raise CheckpointError(f"{side}: sidecar is not valid JSON ({' '.join(str(error).split())[:200]})") from None
    except RecursionError:
        raise CheckpointError(f"{side}: sidecar JSON is nested too deeply to be a checkpoint sidecar") from None


def _expected_tensors(sidecar: dict[str, Any], side: Path) -> dict[str, tuple[str, tuple[int, ...]]]:
    """``name -> (safetensors dtype, shape)`` of the model and cameras the sidecar describes, built on
    torch's meta device: shapes without memory."""
    with torch.device("meta"):
        try:
            model = NOCaL(model_config(sidecar.get("model_config") or {}))
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            raise CheckpointError(f"{side}: invalid model_config ({error})") from None
        parameters = sum(p.numel() for p in model.parameters())
        if parameters > MAX_MODEL_PARAMETERS:
            raise CheckpointError(f"{side}: model_config describes {parameters} parameters; at most {MAX_MODEL_PARAMETERS} are loaded")
        expected = {f"model.{k}": v for k, v in model.state_dict().items()}
        forms = {name: form for form, name in DISTORTION_TYPES.items()}
        for index, fact in enumerate(sidecar["cameras"]):
            form = forms[(fact.get("distortion") or {}).get("type", "mlp")]
            camera = CameraModel(int(fact["width"]), int(fact["height"]), distortion_form=form)
            expected.update({f"camera.{index}.{k}": v for k, v in camera.state_dict().items()})
    return {name: (_SAFETENSORS_DTYPES.get(t.dtype, str(t.dtype)), tuple(t.shape)) for name, t in expected.items()}


def _check_header(path: Path, side: Path, sidecar: dict[str, Any]) -> None:
    """Compare the tensors the sidecar describes with the safetensors header, before reading the data."""
    size = path.stat().st_size
    if size > MAX_CHECKPOINT_BYTES:
        raise CheckpointError(f"{path}: {size} bytes; checkpoints are at most {MAX_CHECKPOINT_BYTES} bytes")
    with open(path, "rb") as handle:
        prefix = handle.read(8)
        length = int.from_bytes(prefix, "little") if len(prefix) == 8 else -1
        if not 0 < length <= min(MAX_HEADER_BYTES, size - 8):
            raise CheckpointError(f"{path}: not a readable safetensors file (header length {length} in a {size}-byte file)")
        try:
            header = json.loads(handle.read(length).decode("utf-8"))
            declared = {name: (entry["dtype"], tuple(int(n) for n in entry["shape"]))
                        for name, entry in header.items() if name != "__metadata__"}
        except (UnicodeDecodeError, ValueError, RecursionError, KeyError, TypeError, AttributeError):
            raise CheckpointError(f"{path}: not a readable safetensors file (malformed header)") from None
    for name, (dtype, shape) in _expected_tensors(sidecar, side).items():
        if name not in declared:
            raise CheckpointError(f"{path}: tensor {name}, which the sidecar's model needs, is missing")
        if declared[name] != (dtype, shape):
            names = {code: str(torch_dtype) for torch_dtype, code in _SAFETENSORS_DTYPES.items()}
            raise CheckpointError(
                f"{path}: tensor {name} is declared {declared[name][1]} {names.get(declared[name][0], declared[name][0])}, "
                f"the sidecar's model needs {shape} {names.get(dtype, dtype)}")


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------


def _read_pair(path: Path, side: Path, name: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The sidecar and tensors of weights ``path`` with sidecar ``side``, for a checkpoint called ``name``."""
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file does not exist")
    if not side.is_file():
        raise CheckpointError(f"{path}: JSON sidecar {side.name} is missing")
    sidecar = _read_sidecar(side)
    validate_sidecar(sidecar, side, name)
    _check_header(path, side, sidecar)
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != sidecar.get("weights_sha256"):
        raise CheckpointError(f"{path}: weights do not match the sidecar's checksum (changed, truncated or replaced)")
    try:
        # safetensors parses a JSON header and raw arrays: a pickle or other file fails here, unexecuted.
        tensors = safetensors_load(data)
    except (SafetensorError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: not a readable safetensors file ({error})") from None
    for tensor_name, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path}: tensor {tensor_name} holds NaN or infinite values")
    return sidecar, tensors


def _read(path: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The sidecar and the tensors of ``path``, after every consistency check that needs no model.

    When the pair under the real names fails and a ``.previous`` pair exists (a save was interrupted
    between its two renames, see the module notes), that complete previous pair is loaded instead.
    """
    try:
        return _read_pair(path, sidecar_path(path), path.name)
    except CheckpointError as error:
        previous_weights, previous_side = previous_paths(path)
        if not (previous_weights.is_file() and previous_side.is_file()):
            raise
        try:
            result = _read_pair(previous_weights, previous_side, path.name)
        except CheckpointError:
            raise error from None
        log.warning("%s: loading the previous checkpoint, kept while a save that did not finish replaced it (%s)",
                    path, error)
        return result


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
        parameters = [p for group in optimiser.param_groups for p in group["params"]]
        for key, value in tensors.items():
            if key.startswith(prefix):
                index_text, _, field_name = key[len(prefix):].partition(".")
                if not index_text.isdigit() or int(index_text) >= len(parameters) or not field_name:
                    raise CheckpointError(f"{path}: optimiser tensor {key} names no parameter of {name!r}")
                index = int(index_text)
                # Adam's moments have their parameter's shape; a mismatch would only fail at the next step.
                if field_name != "step" and value.shape != parameters[index].shape:
                    raise CheckpointError(f"{path}: optimiser tensor {key} is {tuple(value.shape)}, "
                                          f"its parameter is {tuple(parameters[index].shape)}")
                state.setdefault(index, {})[field_name] = value.to(device) if field_name != "step" else value
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
