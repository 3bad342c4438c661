"""``nocal train``: pretrain or fine-tune NOCaL from a YAML config, on bags or rendered sequences.

Runs as one process, or under ``torchrun --nproc_per_node N`` with DistributedDataParallel (gloo on
CPU, nccl on GPU). Writes ``metrics.csv``, a resumable ``last.safetensors`` and the final
``model.safetensors`` (each with its JSON sidecar) into ``--out``. Ctrl-C stops at the next step and
leaves a resumable checkpoint (``--resume`` continues it exactly).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
from pathlib import Path
from typing import Any

import yaml

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
    parser.add_argument("--config", required=True, type=Path, help="training YAML (see config/*.yaml)")
    parser.add_argument("--bag", action="append", type=Path, default=[],
                        help="training bag (repeat for several cameras); without it the config's synthetic section is rendered")
    parser.add_argument("--init", help="pretrained model to fine-tune from (file, version or store directory)")
    parser.add_argument("--out", type=Path, help="output directory (default: runs/<config name>)")
    parser.add_argument("--resume", action="store_true", help="continue exactly from OUT/last.safetensors")
    parser.add_argument("--steps", type=int, help="override the config's number of steps")
    parser.add_argument("--bench", type=int, metavar="N",
                        help="time N optimisation steps (after 5 warm-up steps) and print the figures; trains nothing")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:1, ...")
    parser.add_argument("--image-topic", default="/camera/image_raw")
    parser.add_argument("--pose-topic", default="/arm/pose")


def load_config(path: Path) -> dict[str, Any]:
    """The YAML file as a dict; ConfigError naming the file when it is missing or malformed."""
    try:
        config = yaml.safe_load(Path(path).read_text())
    except OSError as error:
        raise ConfigError(f"{path}: cannot read config ({error.strerror})") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(error).split())})") from None
    if not isinstance(config, dict):
        raise ConfigError(f"{path}: config must be a mapping of training settings")
    return config


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
    import torch
    from tqdm import tqdm

    from nocal_ros.training import train, training_config

    if args.threads:
        torch.set_num_threads(args.threads)
    source = str(args.config)
    raw = load_config(args.config)
    if args.steps is not None:
        raw["steps"] = args.steps
    config = training_config(raw, source=source)
    out_dir = args.out or Path("runs") / args.config.stem
    distributed = _init_distributed(args.device)
    rank = int(os.environ.get("RANK", "0"))
    try:
        if args.bag:
            from nocal_ros.data.bags import read_sequence

            sequences = [read_sequence(bag, image_topic=args.image_topic, pose_topic=args.pose_topic) for bag in args.bag]
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
                for key in ("loss", "photometric", "translation", "rotation", "latent", "fx", "fy", "cx", "cy"):
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


def _tensorboard(out_dir: Path):
    """A TensorBoard writer when tensorboard is installed (optional), else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out_dir / "tensorboard"))
