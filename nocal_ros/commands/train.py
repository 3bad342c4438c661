"""``nocal train``: pretrain NOCaL from a YAML config, or fine-tune a model on bags (``--init``).

Pretraining (no ``--init``) trains on bags or on the config's rendered ``synthetic`` section, as one
process or under ``torchrun --nproc_per_node N`` with DistributedDataParallel (gloo on CPU, nccl on
GPU). It writes ``metrics.csv``, a resumable ``last.safetensors`` and the final ``model.safetensors``
(each with its JSON sidecar) into ``--out``. Ctrl-C stops at the next step and leaves a resumable
checkpoint (``--resume`` continues it exactly). An ``--out`` that already holds a run is refused unless
``--resume`` continues it or ``--overwrite`` deletes it first.

Fine-tuning (``--init MODEL --bag BAG ...``) is field re-calibration: exactly the job the trainer node
runs (``nocal_ros.finetune.FinetuneJob``, in a worker process). ``--out`` is then a model store: the
result becomes its next version and ``latest`` moves to it only once that version is complete.
Ctrl-C cancels and keeps the previous model.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import signal
from pathlib import Path
from typing import Any

from nocal_ros.commands import arguments as arg
from nocal_ros.config import load_config
from nocal_ros.errors import ConfigError

log = logging.getLogger(__name__)

SYNTHETIC_DEFAULTS = {
    "sequences": 4,  # one random camera and room per sequence
    "frames": 60,
    "width": 160,  # native image size of the rendered cameras
    "height": 120,
    "labelled_fraction": 0.1,
    "seed": 0,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path,
                        help="training YAML (see config/*.yaml); required to pretrain; with --init the fine-tuning "
                             "recipe, e.g. config/finetune.yaml (default: training defaults, curriculum scaled to --steps)")
    parser.add_argument("--bag", action="append", type=Path, default=[],
                        help="training bag (repeat for several); without it pretraining renders the config's synthetic section")
    parser.add_argument("--init", metavar="MODEL", nargs="?", const="",
                        help="fine-tune MODEL (file, version or store directory; --init alone: the store's latest, "
                             "else the shipped model) on --bag into the model store --out, as the trainer node does")
    parser.add_argument("--out", type=Path,
                        help="output directory (default: runs/<config name>); with --init the model store to publish to")
    parser.add_argument("--resume", action="store_true", help="continue pretraining exactly from OUT/last.safetensors")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the training run already in --out (its model, last checkpoint, metrics and "
                             "TensorBoard logs are deleted first); without it or --resume such an --out is refused")
    parser.add_argument("--steps", type=arg.positive_int, help="override the config's number of steps")
    parser.add_argument("--seed", type=arg.non_negative_int, help="override the config's seed")
    parser.add_argument("--bench", type=arg.positive_int, metavar="N",
                        help="time N optimisation steps (after 5 warm-up steps) and print the figures; trains nothing")
    parser.add_argument("--threads", type=arg.thread_count, help="torch CPU threads (default or 0: torch's choice)")
    parser.add_argument("--device", default="auto", type=arg.device_name, help="auto, cpu, cuda, cuda:1, ...")
    bags = parser.add_argument_group("bags")
    bags.add_argument("--image-topic", default="/camera/image_raw")
    bags.add_argument("--pose-topic", default="/arm/pose", help="arm poses (PoseStamped) for --pose-source pose")
    bags.add_argument("--pose-source", default="auto", choices=("auto", "pose", "tf", "none"),
                      help="auto: the pose topic if present, else TF, else none (unlabelled: scale not metric)")
    bags.add_argument("--tf-parent", default="base", help="TF edge parent -> child for --pose-source tf")
    bags.add_argument("--tf-child", default="tool")
    bags.add_argument("--hand-eye", type=arg.finite_float, nargs=16, metavar="T", help="T_tool_cam, row-major 4x4 (default identity)")
    bags.add_argument("--tolerance", type=arg.positive_float, default=0.02, help="seconds between an image and its arm pose")
    bags.add_argument("--max-frames", type=arg.positive_int, help="read at most this many frames per bag")
    finetune = parser.add_argument_group("fine-tuning (--init)")
    finetune.add_argument("--camera-start", default="reset", choices=("reset", "init"),
                          help="reset: f = width, centred principal point (a new camera); init: the model's camera of the same size")
    finetune.add_argument("--keep", type=arg.non_negative_int, default=5, help="versions kept in the store (0: all)")


def synthetic_sequences(section: dict[str, Any] | None, source: str) -> list:
    """Render the config's synthetic training set: one random camera and room per sequence."""
    import numpy as np

    from nocal_ros.data.synthetic import random_calibration, render_sequence

    settings = dict(SYNTHETIC_DEFAULTS)
    unknown = set(section or {}) - set(settings)
    if unknown:
        raise ConfigError(f"{source}: unknown synthetic keys {sorted(unknown)}; known: {sorted(settings)}")
    settings.update(section or {})
    rng = np.random.default_rng(settings["seed"])
    sequences = []
    for index in range(int(settings["sequences"])):
        calibration = random_calibration(rng, int(settings["width"]), int(settings["height"]))
        sequences.append(render_sequence(calibration, int(settings["frames"]), seed=int(settings["seed"]) * 1000 + index,
                                         labelled_fraction=float(settings["labelled_fraction"])))
    return sequences


def _init_distributed(device: str) -> bool:
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return False
    import torch
    import torch.distributed as dist

    backend = "nccl" if (device != "cpu" and torch.cuda.is_available()) else "gloo"
    if backend == "nccl":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
    dist.init_process_group(backend=backend)
    return True


def run(args: argparse.Namespace) -> int:
    if args.init is not None:
        return run_finetune_job(args)
    import torch
    from tqdm import tqdm

    from nocal_ros.losses import TERM_NAMES
    from nocal_ros.training import train, training_config

    if args.config is None:
        raise ConfigError("pretraining needs --config (a training YAML, e.g. config/pretrain.yaml); "
                          "to fine-tune a model on bags, pass --init MODEL --bag BAG --out STORE")
    if args.threads:
        torch.set_num_threads(args.threads)
    source = str(args.config)
    raw = load_config(args.config)
    if args.steps is not None:
        raw["steps"] = args.steps
    if args.seed is not None:
        raw["seed"] = args.seed
    config = training_config(raw, source=source)
    out_dir = args.out or Path("runs") / args.config.stem
    rank = int(os.environ.get("RANK", "0"))
    if not args.bench:
        prepare_run_dir(out_dir, resume=args.resume, overwrite=args.overwrite, remove=rank == 0)
    distributed = _init_distributed(args.device)
    try:
        if args.bag:
            from nocal_ros.data.bags import read_sequence

            sequences = [read_sequence(bag, **bag_options(args)) for bag in args.bag]
        else:
            sequences = synthetic_sequences(config["synthetic"], source)
        if args.bench:
            from nocal_ros.training import benchmark_steps

            figures = benchmark_steps(config, sequences, steps=args.bench, device=args.device)
            print("training step: " + ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}"
                                                for k, v in figures.items()))
            return 0
        if rank == 0:
            log.info("training on %d sequences (%s) -> %s", len(sequences),
                     ", ".join(f"{s.name} {s.image_size[0]}x{s.image_size[1]}, {int(s.labelled.sum())}/{len(s)} labelled"
                               for s in sequences), out_dir)

        stop_requested = []
        previous_handler = signal.signal(signal.SIGINT, lambda *_: stop_requested.append(True))
        bar = tqdm(total=config["steps"], disable=rank != 0, unit="step", dynamic_ncols=True)
        writer = _tensorboard(out_dir) if rank == 0 else None

        def progress(record: dict[str, Any]) -> None:
            bar.n = record["step"]
            bar.set_postfix_str(f"{record['stage']} loss {record['loss']:.4f} fx {record['fx']:.1f} fy {record['fy']:.1f} "
                                f"cx {record['cx']:.1f} cy {record['cy']:.1f}")
            if writer is not None:
                for key in ("loss", *TERM_NAMES[1:], "fx", "fy", "cx", "cy"):
                    writer.add_scalar(key, record[key], record["step"])

        try:
            result = train(config, sequences, init=args.init, progress=progress, should_stop=lambda: bool(stop_requested),
                           out_dir=out_dir, resume=args.resume, device=args.device, metadata={"config_file": source})
        finally:
            signal.signal(signal.SIGINT, previous_handler)
            bar.close()
            if writer is not None:
                writer.close()
        if rank == 0:
            if result.stopped:
                print(f"stopped at step {result.step}; resume with --resume --out {out_dir}")
            else:
                fx, fy, cx, cy = (float(v.detach()) for v in result.cameras[0].intrinsics())
                print(f"model: {result.checkpoint}  (step {result.step}, camera 0: fx {fx:.2f} fy {fy:.2f} cx {cx:.2f} cy {cy:.2f})")
        return 130 if result.stopped else 0
    finally:
        if distributed:
            torch.distributed.destroy_process_group()


#: What a pretraining run writes into --out (``training.train``), and the pair a save may keep aside.
RUN_OUTPUTS = ("model.safetensors", "model.json", "last.safetensors", "last.json", "metrics.csv", "tensorboard")


def prepare_run_dir(out_dir: Path, resume: bool, overwrite: bool, remove: bool = True) -> None:
    """Refuse to train into a directory that holds a run unless asked to ``resume`` it or ``overwrite`` it.

    ``overwrite`` deletes the earlier run's outputs before training starts (``remove``: on rank 0 only),
    so a failed new run never leaves the old model beside new metrics.
    """
    from nocal_ros.checkpoint import previous_paths

    if resume and overwrite:
        raise ConfigError("give --resume (continue the run in --out) or --overwrite (replace it), not both")
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"{out_dir}: exists and is not a directory")
    names = list(RUN_OUTPUTS)
    for checkpoint_name in ("model.safetensors", "last.safetensors"):
        names += [p.name for p in previous_paths(out_dir / checkpoint_name)]
    existing = [name for name in names if (out_dir / name).exists()]
    if not existing or resume:
        return
    if not overwrite:
        raise ConfigError(f"{out_dir}: already holds a training run ({', '.join(existing)}); "
                          "pass --resume to continue it or --overwrite to replace it")
    if remove:
        for name in existing:
            target = out_dir / name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            else:
                target.unlink()
        log.info("--overwrite: removed the earlier run's %s from %s", ", ".join(existing), out_dir)


def bag_options(args: argparse.Namespace) -> dict[str, Any]:
    """``read_sequence`` keyword arguments from the command line's bag options."""
    import numpy as np

    return dict(
        image_topic=args.image_topic, pose_topic=args.pose_topic, pose_source=args.pose_source,
        tf_parent=args.tf_parent, tf_child=args.tf_child, tolerance_s=args.tolerance, max_frames=args.max_frames,
        T_tool_cam=None if args.hand_eye is None else np.asarray(args.hand_eye, dtype=np.float64).reshape(4, 4),
    )


def finetune_config(args: argparse.Namespace):
    """The trainer node's ``FinetuneConfig`` from ``nocal train --init`` arguments.

    ``--steps`` and ``--seed`` default to the recipe's (``--config``), as in pretraining; the job
    itself lets them win over the recipe and rescales its curriculum to them.
    """
    from nocal_ros.finetune import FinetuneConfig
    from nocal_ros.model_store import resolve_model_path

    if args.resume:
        raise ConfigError("--resume continues pretraining; a fine-tuning run (--init) is not resumable: "
                          "a cancelled run kept the previous model, so start it again")
    if args.overwrite:
        raise ConfigError("--overwrite replaces a pretraining run; fine-tuning (--init) adds a version to the "
                          "model store --out and never replaces one (--keep prunes old versions)")
    if args.bench:
        raise ConfigError("--bench times pretraining steps; leave out --init")
    if not args.bag:
        raise ConfigError("fine-tuning (--init) needs at least one --bag")
    if args.out is None:
        raise ConfigError("fine-tuning (--init) publishes into a model store: pass --out STORE "
                          "(the odometry node's model_path, e.g. ~/.ros/nocal_ros/models)")
    if args.init:
        resolve_model_path(args.init)  # a wrong path fails here, before a worker process starts
    recipe = load_config(args.config) if args.config else {}
    values: dict[str, Any] = dict(
        bags=[str(bag) for bag in args.bag], output=str(args.out), init=args.init,
        training_config=str(args.config or ""), image_topic=args.image_topic, pose_topic=args.pose_topic,
        pose_source=args.pose_source, tf_parent=args.tf_parent, tf_child=args.tf_child, tolerance_s=args.tolerance,
        max_frames=args.max_frames, threads=args.threads or 0, keep_versions=args.keep,
        camera_start=args.camera_start, device=args.device,
    )
    for key in ("steps", "seed"):
        value = getattr(args, key) if getattr(args, key) is not None else recipe.get(key)
        if value is not None:
            values[key] = int(value)
    if args.hand_eye is not None:
        values["T_tool_cam"] = list(args.hand_eye)
    return FinetuneConfig(**values)


def run_finetune_job(args: argparse.Namespace) -> int:
    """Fine-tune in a worker process and publish to the store ``--out``; Ctrl-C cancels the job."""
    import time

    from nocal_ros.errors import NocalError
    from nocal_ros.finetune import FinetuneJob

    config = finetune_config(args)
    job = FinetuneJob(config)
    # A terminal's Ctrl-C goes to the whole process group; only this process should react, by cancelling.
    # The worker ignores SIGINT itself once running; inheriting "ignore" covers its start-up as well.
    # Here Ctrl-C only sets a flag: a KeyboardInterrupt raised at an arbitrary point could land inside a
    # read of the worker's message pipe and leave it half-read, so the cancel could never be heard.
    interrupted: list[bool] = []
    previous_handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        job.start()
        signal.signal(signal.SIGINT, lambda *_: interrupted.append(True))
        display = _JobProgress(int(config.steps))
        started = time.monotonic()
        try:
            cancelling = False
            while job.state == "running":
                job.wait(timeout=0.2, interval=0.2, on_message=display)
                if interrupted and not cancelling:
                    display.write("cancelling; the previous model stays in place")
                    job.cancel()  # job.poll terminates a worker that does not stop within its grace period
                    cancelling = True
        finally:
            job.close()
            display.close()
    finally:
        signal.signal(signal.SIGINT, previous_handler)
    if job.state == "succeeded":
        result = job.result
        final = display.last_training
        camera = " ".join(f"{k} {final[k]:.2f}" for k in ("fx", "fy", "cx", "cy") if isinstance(final.get(k), float))
        print(f"published {result['version']} of {config.output} (latest): {result['model_path']}  "
              f"({result['steps']} steps in {time.monotonic() - started:.1f} s{', camera 0: ' + camera if camera else ''})",
              flush=True)
        for warning in result.get("warnings") or []:
            print(f"warning: {warning}", flush=True)
        return 0
    if job.state == "cancelled":
        print(f"cancelled: {job.error}", flush=True)
        return 130
    # The worker's error already names the file and the problem; the CLI prints it as one line.
    raise NocalError(job.error or "fine-tuning failed; previous model kept")


class _JobProgress:
    """The worker's progress records as a step bar, one line per stage, and logged warnings."""

    def __init__(self, total_steps: int) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total_steps, unit="step", dynamic_ncols=True)
        self.stage: str | None = None
        self.last_training: dict = {}  # the latest record with a loss and the camera's intrinsics

    def __call__(self, message: dict) -> None:
        if message.get("type") != "progress":
            return
        stage = message.get("stage")
        if stage == "warning":
            log.warning(message.get("message", ""))
            return
        if message.get("loss") is not None:
            self.last_training = message
            self.bar.n = int(message.get("step") or 0)
            camera = " ".join(f"{k} {message[k]:.1f}" for k in ("fx", "fy", "cx", "cy") if isinstance(message.get(k), float))
            self.bar.set_postfix_str(f"{stage} loss {message['loss']:.4f} {camera}")
        elif stage != self.stage and stage not in ("done", "cancelled"):  # the final line says those
            detail = f" {message['init']}" if message.get("init") else ""
            self.write(f"{str(stage).replace('_', ' ')}{detail}")
        self.stage = stage

    def write(self, line: str) -> None:
        self.bar.write(line)

    def close(self) -> None:
        self.bar.close()


def _tensorboard(out_dir: Path):
    """A TensorBoard writer when tensorboard is installed (optional), else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out_dir / "tensorboard"))
