"""``nocal finetune``: field re-calibration without ROS, the same job the trainer node runs.

Fine-tunes a model on bags (arm poses as labels where present) in a worker process and publishes
the result as a new version of a model store, moving its ``latest`` pointer only once the version is
complete. Ctrl-C cancels and keeps the previous model.
"""

from __future__ import annotations

import argparse
import logging
import time

from nocal_ros.errors import NocalError

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bag", action="append", required=True, help="bag to fine-tune on (repeat for several)")
    parser.add_argument("--store", required=True, help="model store directory; the new model becomes its latest")
    parser.add_argument("--init", default="", help="model to start from (file, version or store; default: the store's latest, else the shipped model)")
    parser.add_argument("--config", default="", help="training recipe YAML, e.g. config/finetune.yaml")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--image-topic", default="/camera/image_raw")
    parser.add_argument("--pose-topic", default="/arm/pose")
    parser.add_argument("--pose-source", default="auto", choices=("auto", "pose", "tf", "none"))
    parser.add_argument("--tf-parent", default="base")
    parser.add_argument("--tf-child", default="tool")
    parser.add_argument("--hand-eye", type=float, nargs=16, metavar="T", help="T_tool_cam, row-major 4x4 (default identity)")
    parser.add_argument("--tolerance", type=float, default=0.02, help="seconds between an image and its arm pose")
    parser.add_argument("--camera-start", default="reset", choices=("reset", "init"))
    parser.add_argument("--max-frames", type=int)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads in the worker")
    parser.add_argument("--keep", type=int, default=5, help="versions kept in the store (0: all)")
    parser.add_argument("--device", default="auto")


def run(args: argparse.Namespace) -> int:
    from nocal_ros.finetune import FinetuneConfig, FinetuneJob

    values = dict(
        bags=args.bag, output=args.store, init=args.init, training_config=args.config, steps=args.steps,
        image_topic=args.image_topic, pose_topic=args.pose_topic, pose_source=args.pose_source,
        tf_parent=args.tf_parent, tf_child=args.tf_child, tolerance_s=args.tolerance,
        camera_start=args.camera_start, max_frames=args.max_frames, seed=args.seed, threads=args.threads,
        keep_versions=args.keep, device=args.device,
    )
    if args.hand_eye:
        values["T_tool_cam"] = list(args.hand_eye)
    config = FinetuneConfig(**values)
    job = FinetuneJob(config)
    job.start()
    started = time.monotonic()
    try:
        job.wait(interval=0.2, on_message=_print_progress)
    except KeyboardInterrupt:
        print("cancelling; the previous model stays in place", flush=True)
        job.cancel()
        job.wait(timeout=30, interval=0.2, on_message=_print_progress)
    finally:
        job.close()
    if job.state == "succeeded":
        print(f"published {job.result['model_path']} in {time.monotonic() - started:.1f} s "
              f"({job.result['steps']} steps)", flush=True)
        return 0
    if job.state == "cancelled":
        print(f"cancelled: {job.error}", flush=True)
        return 130
    # The worker's error already names the file and the problem; the CLI prints it as one line.
    raise NocalError(job.error or "fine-tuning failed")


def _print_progress(message: dict) -> None:
    if message.get("type") != "progress":
        return
    if message.get("stage") == "warning":
        log.warning(message.get("message", ""))
    elif message.get("loss") is not None:
        print(f"step {message['step']}/{message['total_steps']} {message['stage']} loss {message['loss']:.4f} "
              f"fx {message['fx']:.1f} fy {message['fy']:.1f} cx {message['cx']:.1f} cy {message['cy']:.1f} "
              f"eta {message.get('eta_s') or 0:.0f} s", flush=True)
    else:
        print(message.get("stage"), flush=True)
