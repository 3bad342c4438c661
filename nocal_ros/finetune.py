"""Field re-calibration: fine-tune a model on new rosbags and publish it to a model store.

A camera that was replaced, knocked or heated needs no calibration target: record a bag while an arm
moves the camera (its poses give a small labelled set) plus ordinary footage, and run this job. It is
the shared core of ``nocal train --init MODEL --bag ...`` and of the rclpy trainer node:

- ``run_finetune(config, progress, should_stop)`` does the work in the calling process: read the
  bags, load the initial model, call ``nocal_ros.training.train``, write the result as a new version
  of a ``ModelStore`` (so ``latest`` only ever moves to a complete model).
- ``FinetuneJob`` runs ``run_finetune`` in a separate worker process (``spawn`` context), so a crash,
  an out-of-memory kill or a stuck CUDA context cannot take a ROS node down with it. Progress comes
  back through a queue, cancellation goes in through an event, and a worker that ignores the cancel
  is terminated: the store's commit protocol makes killing it at any moment safe.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import multiprocessing as mp
import os
import queue as queue_module
import signal
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nocal_ros.errors import BagError, ConfigError, NocalError
from nocal_ros.model_store import MODEL_NAME, ModelStore, ModelVersion, resolve_model_path

log = logging.getLogger(__name__)

NOT_METRIC_WARNING = (
    "no arm poses found in {bags} (pose_source={source}, topic {topic}): fine-tuning on unlabelled "
    "images only; calibration is learnt but odometry scale is not metric"
)

ProgressCallback = Callable[[dict], None]


class FinetuneCancelled(NocalError):
    """The job was cancelled before it published a model; the previous model is untouched."""


@dataclass
class FinetuneConfig:
    """Everything a fine-tuning run needs; plain values so it crosses process boundaries and YAML.

    Attributes:
        bags: rosbag paths (rosbag2 directories, .mcap/.db3 files or ROS 1 bags).
        output: the model store directory the new version is published to.
        init: the model to start from: a checkpoint, a version directory or a store (its latest);
            empty means the store ``output`` if it has a model, else the shipped default.
        image_topic: sensor_msgs/Image or CompressedImage topic.
        pose_topic: geometry_msgs/PoseStamped arm pose topic (``pose_source`` "pose").
        pose_source: "auto" (PoseStamped topic if present, else TF, else none), "pose", "tf", "none".
        tf_parent, tf_child: the TF edge ``base -> tool`` when poses come from TF.
        T_tool_cam: hand-eye transform, 4x4 row-major (camera pose in the tool frame).
        tolerance_s: an image further than this from any arm pose is unlabelled.
        steps: training steps of the fine-tuning run.
        device: "auto", "cpu", "cuda", "cuda:1"...
        max_frames: read at most this many frames per bag (None: all).
        seed: random seed for pair sampling and initialisation.
        threads: torch CPU threads in the worker (0: torch's default).
        keep_versions: older versions beyond this many are pruned after publishing (0: keep all).
        camera_start: "reset" (f = width, centred principal point: a new, unknown camera) or "init"
            (the initial model's camera of the same size: a known camera that moved or heated).
        training_config: a training YAML (e.g. ``config/finetune.yaml``, the fine-tuning recipe);
            empty: the training defaults with a curriculum scaled to ``steps``.
        training: keys that override the training YAML (learning rates, batch size, stages...);
            ``steps`` and ``seed`` above always win.
    """

    bags: list[str]
    output: str
    init: str = ""
    image_topic: str = "/camera/image_raw"
    pose_topic: str = "/arm/pose"
    pose_source: str = "auto"
    tf_parent: str = "base"
    tf_child: str = "tool"
    T_tool_cam: list[float] = field(default_factory=lambda: np.eye(4).ravel().tolist())
    tolerance_s: float = 0.02
    steps: int = 2000
    device: str = "auto"
    max_frames: int | None = None
    seed: int = 0
    threads: int = 0
    keep_versions: int = 5
    camera_start: str = "reset"
    training_config: str = ""
    training: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.bags, (str, os.PathLike)):
            self.bags = [self.bags]
        self.bags = [str(b) for b in self.bags]
        self.output = str(self.output)
        self.init = str(self.init or "")
        if not self.bags:
            raise ConfigError("fine-tuning needs at least one bag")
        if not self.output:
            raise ConfigError("fine-tuning needs an output model store directory")
        if self.pose_source not in ("auto", "pose", "tf", "none"):
            raise ConfigError(f"pose_source must be auto, pose, tf or none, not {self.pose_source!r}")
        hand_eye = np.asarray(self.T_tool_cam, dtype=np.float64).reshape(-1)
        if hand_eye.size != 16 or not np.isfinite(hand_eye).all():
            raise ConfigError("T_tool_cam must be 16 finite numbers (a row-major 4x4 transform)")
        matrix = hand_eye.reshape(4, 4)
        rotation = matrix[:3, :3]
        if not np.allclose(matrix[3], [0, 0, 0, 1]) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
            raise ConfigError("T_tool_cam is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
        self.T_tool_cam = hand_eye.tolist()
        if int(self.steps) < 1:
            raise ConfigError(f"steps must be positive, not {self.steps}")
        if not (self.tolerance_s > 0 and math.isfinite(self.tolerance_s)):
            raise ConfigError(f"tolerance_s must be a positive number, not {self.tolerance_s}")
        if self.max_frames is not None and int(self.max_frames) <= 0:
            self.max_frames = None
        if int(self.keep_versions) < 0:
            raise ConfigError(f"keep_versions must be 0 (keep all) or more, not {self.keep_versions}")
        if int(self.threads) < 0:
            raise ConfigError(f"threads must be 0 (torch's default) or more, not {self.threads}")
        if self.camera_start not in ("reset", "init"):
            raise ConfigError(f"camera_start must be reset or init, not {self.camera_start!r}")
        if not isinstance(self.training, dict):
            raise ConfigError("training overrides must be a mapping")

    @property
    def hand_eye(self) -> np.ndarray:
        """``T_tool_cam`` as a 4x4 float64 array."""
        return np.asarray(self.T_tool_cam, dtype=np.float64).reshape(4, 4)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> FinetuneConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown fine-tuning settings: {', '.join(unknown)}")
        try:
            return cls(**values)
        except TypeError as error:
            raise ConfigError(f"fine-tuning settings: {error}") from error


@dataclass
class FinetuneResult:
    """A finished run: the published version and what happened on the way."""

    version: str
    model_path: str
    warnings: list[str]
    steps: int
    seconds: float
    final: dict

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def load_sequences(config: FinetuneConfig, warnings: list[str]) -> list:
    """Read every bag of ``config``; warn (into ``warnings`` and the log) when none has arm poses.

    Raises:
        BagError: a bag cannot be read or holds no images on ``config.image_topic``.
    """
    from nocal_ros.data.bags import read_sequence

    sequences = []
    for bag in config.bags:
        sequence = read_sequence(
            bag,
            image_topic=config.image_topic,
            pose_topic=config.pose_topic,
            pose_source=config.pose_source,
            tf_parent=config.tf_parent,
            tf_child=config.tf_child,
            T_tool_cam=config.hand_eye,
            tolerance_s=config.tolerance_s,
            max_frames=config.max_frames,
        )
        if len(sequence) < 2:
            raise BagError(f"{bag}: {len(sequence)} image(s) on {config.image_topic}; fine-tuning needs at least 2")
        sequences.append(sequence)
    sizes = {s.image_size for s in sequences}
    if len(sizes) > 1:
        raise BagError(f"{', '.join(config.bags)}: bags of one camera must share an image size, got {sorted(sizes)}")
    if not any(s.labelled.any() for s in sequences):
        message = NOT_METRIC_WARNING.format(bags=", ".join(config.bags), source=config.pose_source, topic=config.pose_topic)
        log.warning(message)
        warnings.append(message)
    return sequences


def _initial_model_path(config: FinetuneConfig) -> Path | None:
    """The checkpoint to start from (None: the shipped default)."""
    if config.init:
        return resolve_model_path(config.init)
    if ModelStore(config.output).latest() is None:
        return None
    return resolve_model_path(config.output)  # verified against its manifest, like any model loaded from a store


class _ProgressReporter:
    """Turns the training loop's callbacks into uniform progress records with an ETA."""

    def __init__(self, sink: ProgressCallback | None, total_steps: int) -> None:
        self.sink = sink
        self.total_steps = total_steps
        self.started = time.monotonic()
        self.last: dict = {}

    def __call__(self, info: Any = None, **kwargs: Any) -> None:
        record = dict(info) if isinstance(info, dict) else dict(getattr(info, "__dict__", {}) or {})
        record.update(kwargs)
        record = {k: _plain(v) for k, v in record.items()}
        record.setdefault("stage", "training")
        step = record.get("step")
        record["total_steps"] = int(record.pop("steps", None) or record.get("total_steps") or self.total_steps)
        record["elapsed_s"] = round(time.monotonic() - self.started, 3)  # whole job, bag reading included
        if record.get("eta_s") is None and isinstance(step, (int, float)) and step > 0:
            record["eta_s"] = record["elapsed_s"] / step * max(record["total_steps"] - step, 0)
        if isinstance(record.get("eta_s"), float):
            record["eta_s"] = round(record["eta_s"], 1)
        self.last = record
        if self.sink is not None:
            self.sink(record)


def _plain(value: Any) -> Any:
    """JSON-friendly scalars from tensors and numpy values."""
    if hasattr(value, "item") and getattr(value, "ndim", 0) == 0:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    return value


def run_finetune(
    config: FinetuneConfig,
    progress: ProgressCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> FinetuneResult:
    """Fine-tune from ``config.init`` on ``config.bags`` and publish a new version to ``config.output``.

    Args:
        config: what to train on and where to put the result.
        progress: called with dicts ``{stage, step, total_steps, loss, fx, fy, cx, cy, eta_s, ...}``.
        should_stop: polled between stages and by the training loop; True cancels the run.

    Returns:
        the published version and any warnings (e.g. scale not metric when no arm poses were found).

    Raises:
        FinetuneCancelled: ``should_stop`` turned true; nothing was published.
        BagError, CheckpointError, ConfigError: bad input, named in the message.
    """
    should_stop = should_stop or (lambda: False)
    started = time.monotonic()
    reporter = _ProgressReporter(progress, int(config.steps))
    warnings: list[str] = []

    def stop_if_asked(stage: str) -> None:
        if should_stop():
            reporter({"stage": "cancelled", "during": stage})
            raise FinetuneCancelled(f"fine-tuning into {config.output} cancelled during {stage}; previous model kept")

    reporter({"stage": "loading_bags", "step": 0})
    sequences = load_sequences(config, warnings)
    for message in warnings:
        reporter({"stage": "warning", "message": message})
    stop_if_asked("loading bags")

    # Imported after the bags are read, so bad input fails fast without loading torch models.
    from nocal_ros import checkpoint, training

    init_path = _initial_model_path(config)
    reporter({"stage": "loading_model", "step": 0, "init": str(init_path) if init_path else "shipped default"})
    initial = checkpoint.load_checkpoint(init_path, device="cpu")  # train() moves it
    stop_if_asked("loading the model")

    train_config = training_settings(config)
    cameras = _starting_cameras(config, initial, sequences)
    metadata = {
        "kind": "finetune",
        "bags": [str(Path(b).resolve()) for b in config.bags],
        "init": str(init_path) if init_path else "shipped default",
        "image_topic": config.image_topic,
        "pose_source": config.pose_source,
        "labelled_frames": int(sum(int(s.labelled.sum()) for s in sequences)),
        "frames": int(sum(len(s) for s in sequences)),
        "steps": int(train_config["steps"]),
        "metric_scale": not warnings,
        "warnings": warnings,
    }
    store = ModelStore(config.output)
    # Training writes straight into a staging directory of the store: model.safetensors, its sidecar
    # and metrics.csv become the version; a cancel or an exception discards the directory.
    with store.new_version(metadata) as staging:
        result = training.train(
            train_config, sequences, init=initial, progress=reporter, should_stop=should_stop,
            out_dir=staging, cameras=cameras, device=_device(config.device), metadata={"finetune": metadata},
        )
        if result.stopped or should_stop():
            stop_if_asked("training")
            raise FinetuneCancelled(f"fine-tuning into {config.output} stopped early; previous model kept")
        reporter({"stage": "saving", "step": result.step})
        for resumable in staging.glob("last.*"):  # optimiser state: large, and useless to the nodes
            resumable.unlink()
        if not (staging / MODEL_NAME).is_file():
            raise NocalError(f"{staging}: training returned without writing {MODEL_NAME}")
    version: ModelVersion = store.last_published
    if config.keep_versions > 0:
        store.prune(config.keep_versions)
    final = {k: v for k, v in reporter.last.items() if k not in ("stage", "message", "during")}
    reporter({"stage": "done", "step": result.step, "version": version.name, "model_path": str(version.model_path)})
    return FinetuneResult(
        version=version.name,
        model_path=str(version.model_path),
        warnings=warnings,
        steps=int(result.step),
        seconds=round(time.monotonic() - started, 3),
        final=final,
    )


def training_settings(config: FinetuneConfig) -> dict:
    """The training config of a run: the training YAML, then ``config.training``, then steps and seed.

    The curriculum is scaled to ``steps`` when neither source gives one, and when the YAML's was
    written for a different number of steps (so ``steps: 300`` on a 3000-step recipe still reaches
    the focal and distortion stages).
    """
    settings: dict = {}
    if config.training_config:
        from nocal_ros.config import load_config

        settings = load_config(Path(os.path.expanduser(config.training_config)))
    recipe_steps = int(settings.get("steps") or 0)
    for key, value in config.training.items():
        if isinstance(value, dict) and isinstance(settings.get(key), dict):
            settings[key] = {**settings[key], **value}
        else:
            settings[key] = value
    steps = int(config.steps)
    if "curriculum" not in config.training:
        curriculum = settings.get("curriculum")
        if not curriculum:
            settings["curriculum"] = finetune_curriculum(steps)
        elif recipe_steps and recipe_steps != steps:
            settings["curriculum"] = {k: max(1, round(int(v) * steps / recipe_steps)) for k, v in curriculum.items()}
    settings["steps"] = steps
    settings["seed"] = int(config.seed)
    return settings


def finetune_curriculum(steps: int) -> dict[str, int]:
    """Curriculum lengths for a run of ``steps``: the pretraining proportions (10 % fixed intrinsics,
    then 30 % focal only, then everything), so a short field run still reaches the distortion stage."""
    return {"fixed": max(1, round(0.1 * steps)), "focal": max(1, round(0.3 * steps))}


def _starting_cameras(config: FinetuneConfig, initial: Any, sequences: list) -> list | None:
    """``None`` (training's default: f = width, centred principal point, the paper's start for an unseen
    camera) unless ``camera_start`` is "init" and the initial model has a camera of the bags' size,
    which is the better start when re-calibrating a camera that was knocked or heated."""
    if config.camera_start != "init":
        return None
    width, height = sequences[0].image_size
    for camera in getattr(initial, "cameras", []) or []:
        if (int(camera.width), int(camera.height)) == (width, height):
            return [copy.deepcopy(camera) for _ in sequences]
    log.warning("camera_start=init: the initial model has no %dx%d camera; starting from f = width", width, height)
    return None


def _device(name: str) -> str:
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


# ---- worker process --------------------------------------------------------------------------

#: Exit status of a worker that stopped because its owner died (nobody is left to read it).
ORPHANED_EXIT_CODE = 75


def exit_when_parent_dies(interval_s: float = 0.5) -> threading.Thread:
    """Watch the process that started this one; when it is gone, end this process at once.

    A worker whose owner was SIGKILLed (or died of an out-of-memory kill) must not train on unattended
    and then publish, or prune the store, on nobody's behalf. ``daemon=True`` only covers an owner that
    exits normally. The owner's end of the spawn pipe (``multiprocessing.parent_process().sentinel``)
    reaches end of file when the owner dies, whatever killed it; polling ``getppid`` covers an owner
    whose pipe a forked grandchild still holds. ``prctl(PR_SET_PDEATHSIG)`` is not used: it fires when
    the starting *thread* exits, and a ROS node starts jobs from executor threads.

    The exit is immediate (``os._exit``): the model store's commit protocol makes a kill at any moment
    safe, so the previous ``latest`` stays, and the next writer removes the staging directory left here.
    """
    parent = mp.parent_process()
    sentinel = parent.sentinel if parent is not None else None
    parent_pid = os.getppid()

    def watch() -> None:
        from multiprocessing.connection import wait

        while True:
            if sentinel is not None:
                if wait([sentinel], timeout=interval_s):
                    break
            else:
                time.sleep(interval_s)
            if os.getppid() != parent_pid:
                break
        os._exit(ORPHANED_EXIT_CODE)

    thread = threading.Thread(target=watch, name="nocal-finetune-parent-watch", daemon=True)
    thread.start()
    return thread


def _worker_main(config_values: dict, messages: Any, cancel: Any, log_level: int) -> None:
    """Entry point of the worker process: run the job, report everything through ``messages``."""
    exit_when_parent_dies()
    # A terminal's Ctrl-C reaches the whole process group. The owner (CLI or node) answers it by
    # cancelling, so the worker stops between steps rather than dying mid-step of its own KeyboardInterrupt.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=log_level, format="[%(levelname)s] finetune worker: %(message)s")
    try:
        config = FinetuneConfig.from_dict(config_values)
        if config.threads > 0:
            import torch

            torch.set_num_threads(config.threads)
        result = run_finetune(
            config,
            progress=lambda record: messages.put({"type": "progress", **record}),
            should_stop=cancel.is_set,
        )
        messages.put({"type": "result", **result.to_dict()})
    except FinetuneCancelled as error:
        messages.put({"type": "cancelled", "message": str(error)})
    except NocalError as error:
        messages.put({"type": "error", "error_type": type(error).__name__, "message": str(error)})
    except BaseException as error:  # the caller must hear about anything, MemoryError included
        messages.put({
            "type": "error",
            "error_type": type(error).__name__,
            "message": f"{type(error).__name__}: {error}",
            "traceback": traceback.format_exc(),
        })


class FinetuneJob:
    """One fine-tuning run in a worker process, polled by its owner (a CLI loop or a ROS timer).

    States: ``idle`` -> ``running`` -> ``succeeded`` | ``failed`` | ``cancelled``.

    Args:
        config: the run's settings.
        worker: the function the worker process runs (tests substitute a module-level function
            with the same signature as ``_worker_main``; it must be importable for ``spawn``).
    """

    TERMINAL = ("succeeded", "failed", "cancelled")
    #: Seconds a worker has to exit after its result before it is terminated.
    exit_grace_s = 5.0

    def __init__(self, config: FinetuneConfig, worker: Callable = _worker_main) -> None:
        self.config = config
        self.worker = worker
        self.state = "idle"
        self.result: dict | None = None
        self.error: str | None = None
        self.warnings: list[str] = []
        self.last_progress: dict = {}
        self._context = mp.get_context("spawn")
        self._messages = None
        self._cancel = None
        self._process = None
        self._cancel_requested_at: float | None = None

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    @property
    def running(self) -> bool:
        return self.state == "running"

    def status(self) -> dict:
        """A JSON-ready summary for progress topics and diagnostics."""
        summary = {"state": self.state, "output": self.config.output, "bags": list(self.config.bags)}
        summary.update({k: v for k, v in self.last_progress.items() if k != "message"})
        summary["state"] = self.state
        if self.warnings:
            summary["warnings"] = list(self.warnings)
        if self.error:
            summary["error"] = self.error
        if self.result:
            summary["version"] = self.result["version"]
            summary["model_path"] = self.result["model_path"]
        return summary

    def start(self) -> None:
        """Start the worker process; a job runs once."""
        if self.state != "idle":
            raise RuntimeError(f"job already {self.state}")
        self._messages = self._context.Queue()
        self._cancel = self._context.Event()
        self._process = self._context.Process(
            target=self.worker,
            args=(self.config.to_dict(), self._messages, self._cancel, logging.getLogger().getEffectiveLevel()),
            name="nocal-finetune",
            daemon=True,  # dies with its parent instead of training on unattended
        )
        self._process.start()
        self.state = "running"

    def cancel(self) -> None:
        """Ask the worker to stop; ``poll`` terminates it if it has not stopped within ``grace_s``."""
        if self.state == "running" and self._cancel is not None:
            self._cancel.set()
            self._cancel_requested_at = time.monotonic()

    def poll(self, grace_s: float = 10.0) -> list[dict]:
        """Drain the worker's messages, update the state, and return the messages.

        Each message carries ``"state"``: the job's state once that message was handled, so a batch
        drained in one poll (the last progress, saving, done and the result together) keeps
        ``"running"`` on its progress records and only the result says ``"succeeded"``.
        """
        received = self._drain()
        if self.state != "running":
            return received
        process = self._process
        if self._cancel_requested_at is not None and process.is_alive():
            if time.monotonic() - self._cancel_requested_at > grace_s:
                log.warning("fine-tuning worker %s ignored the cancel for %.0f s; terminating it", process.pid, grace_s)
                self._stop_process()
                self.state = "cancelled"
                self.error = "cancelled (worker terminated)"
        elif not process.is_alive():
            process.join()
            received += self._drain()
            if self.state == "running":
                self.state = "failed"
                code = process.exitcode
                why = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                self.error = f"fine-tuning worker died without a result ({why}; killed or out of memory?); previous model kept"
        return received

    def wait(self, timeout: float | None = None, interval: float = 0.05, on_message: ProgressCallback | None = None) -> str:
        """Poll until the job ends or ``timeout`` passes; return the state."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.state == "running":
            for message in self.poll():
                if on_message is not None:
                    on_message(message)
            if self.state != "running" or (deadline is not None and time.monotonic() > deadline):
                break
            time.sleep(interval)
        return self.state

    def _drain(self) -> list[dict]:
        received = []
        if self._messages is None:
            return received
        while True:
            try:
                message = self._messages.get_nowait()
            except (queue_module.Empty, EOFError, OSError):
                break
            received.append(message)
            self._handle(message)
        return received

    def _handle(self, message: dict) -> None:
        kind = message.get("type")
        if kind == "progress":
            if message.get("stage") == "warning":
                self.warnings.append(message.get("message", ""))
            else:
                self.last_progress = {k: v for k, v in message.items() if k != "type"}
        elif kind == "result":
            self.result = {k: v for k, v in message.items() if k != "type"}
            self.state = "succeeded"
        elif kind == "cancelled":
            self.state = "cancelled"
            self.error = message.get("message")
        elif kind == "error":
            self.state = "failed"
            self.error = message.get("message")
            if message.get("traceback"):
                log.error("fine-tuning worker failed:\n%s", message["traceback"])
        message["state"] = self.state
        if self.state in self.TERMINAL and self._process is not None:
            # The result is sent: what is left is the worker's exit. A worker slow to exit (interpreter
            # teardown on a loaded machine) is stopped, so no caller finds a finished job's worker alive.
            self._process.join(timeout=self.exit_grace_s)
            if self._process.is_alive():
                log.warning("fine-tuning worker %s had not exited %.0f s after its result; terminating it",
                            self._process.pid, self.exit_grace_s)
                self._stop_process()

    def _stop_process(self) -> None:
        process = self._process
        if process is None or not process.is_alive():
            return
        process.terminate()
        process.join(timeout=1)  # a worker has nothing to tidy up: the store survives any kill
        if process.is_alive():
            process.kill()
            process.join(timeout=5)

    def close(self) -> None:
        """Stop the worker if it still runs (node shutdown) and release the queue."""
        if self.state == "running":
            self.cancel()
            self._stop_process()
            self._drain()
            if self.state == "running":
                self.state = "cancelled"
        if self._messages is not None:
            self._messages.close()
            self._messages.join_thread()
            self._messages = None
