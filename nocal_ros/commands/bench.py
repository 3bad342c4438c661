"""``nocal bench``: pose-head and estimator latency, the figures BENCHMARKS.md quotes.

For each device (CPU, and CUDA when present) it prints:

* the pose head alone at batch 1: milliseconds per pair, median and 90th percentile after warm-up;
* the pose head at batch 32: pairs per second;
* the estimator end to end per frame: decoding a ``sensor_msgs/Image`` at the native resolution,
  resizing to the training resolution, the pose head on (previous, current), pose integration and
  covariance, i.e. everything the odometry node does between receiving a message and publishing;
* the keyframe VO (``--vo``, on by default) on a rendered camera motion (or ``--bag``'s images): the
  tracking thread's cost per frame (frontend and PnP), the local mapping's per keyframe (the bundle
  adjustment alone, and with triangulation), the whole estimator per frame, and a replay at
  ``--rate`` Hz in real time with mapping in its worker, the way the node runs it: frames that arrive
  while one is being processed replace the waiting one and are counted as dropped. With a camera height
  (``--camera-height``; the rendered motion's own mean height with ``--camera-height auto``), also the
  live ground-plane fit per keyframe, which runs in the tracking thread.

On CUDA the estimator runs with CUDA graphs and pinned memory (as the node does), and in half
precision too, with the pose difference half precision makes against fp32 on the same frames.
Timings synchronise the device before reading the clock, so they are what a caller waits for.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from nocal_ros.commands import arguments as arg
from nocal_ros.errors import NocalError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default="", help="checkpoint or model store (default: the shipped model; "
                        "an untrained model of the default shape when none is shipped)")
    parser.add_argument("--untrained", action="store_true", help="time an untrained model of the default shape")
    parser.add_argument("--devices", default="auto", type=arg.device_list, help="comma list of cpu, cuda; auto = cpu and cuda when present")
    parser.add_argument("--native", default=(640, 480), type=arg.image_size, help="camera resolution fed to the estimator, WxH")
    parser.add_argument("--iterations", type=arg.positive_int, default=200, help="timed runs per figure")
    parser.add_argument("--warmup", type=arg.non_negative_int, default=20, help="untimed runs first")
    parser.add_argument("--threads", type=arg.thread_count, default=0, help="torch CPU threads (0: leave torch's default)")
    parser.add_argument("--layout", default="channels_last", choices=("channels_last", "contiguous"),
                        help="memory layout of the estimator's convolutions")
    parser.add_argument("--vo", default=True, action=argparse.BooleanOptionalAction,
                        help="time the keyframe VO on a camera motion (default: on)")
    parser.add_argument("--vo-frames", type=arg.positive_int, default=120,
                        help="frames of the VO runs (rendered at --native unless --bag)")
    parser.add_argument("--bag", default="", help="take the VO's frames from this bag's images instead of rendering")
    parser.add_argument("--rate", type=arg.positive_float, default=30.0, help="real-time replay rate (Hz) of the VO")
    parser.add_argument("--camera-height", default="", type=_camera_height,
                        help="the VO's camera height above the ground (m), for its ground-plane scale; 'auto': the "
                        "rendered motion's mean true height (default: none)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")


def _camera_height(text: str) -> str | float:
    return text if text in ("", "auto") else arg.positive_float(text)


def _pose_model(args: argparse.Namespace, device: torch.device):
    """The model to time, as a PoseModel, and a description of where it came from."""
    from nocal_ros.odometry import PoseModel

    if not args.untrained:
        try:
            return PoseModel.from_checkpoint(args.model or None, device), "checkpoint"
        except (ImportError, NocalError) as error:
            if args.model:
                raise
            reason = f"no shipped model ({error})"
    else:
        reason = "requested"
    from nocal_ros.model import NOCaL

    model = NOCaL().to(device).eval()
    return PoseModel(predict_pose=model.predict_pose, input_size=(80, 60), device=device,
                     model_id="untrained default shape", module=model), f"untrained ({reason})"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn, device: torch.device, iterations: int, warmup: int) -> np.ndarray:
    for _ in range(warmup):
        fn()
    _sync(device)
    times = np.empty(iterations)
    for index in range(iterations):
        start = time.perf_counter()
        fn()
        _sync(device)
        times[index] = time.perf_counter() - start
    return times * 1e3


def _stats(ms: np.ndarray) -> dict[str, float]:
    return {"median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)), "mean_ms": float(ms.mean()),
            "max_ms": float(ms.max()), "count": int(len(ms))}


def _frames(native: tuple[int, int], count: int, seed: int = 0) -> list[np.ndarray]:
    """Smooth random images (a real camera's frames are not white noise; resize cost does not care)."""
    import cv2

    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(count, native[1] // 8, native[0] // 8, 3), dtype=np.uint8)
    return [cv2.resize(image, native, interpolation=cv2.INTER_LINEAR) for image in small]


def _image_message(image: np.ndarray, stamp_ns: int) -> Any:
    height, width = image.shape[:2]
    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp, frame_id="camera_optical"), height=height, width=width,
        encoding="rgb8", is_bigendian=0, step=width * 3, data=image.tobytes(),
    )


def bench_pose_head(pose_model, iterations: int, warmup: int) -> dict[str, Any]:
    device = pose_model.device
    width, height = pose_model.input_size
    generator = torch.Generator(device="cpu").manual_seed(0)
    results: dict[str, Any] = {}
    for batch in (1, 32):
        image_i = torch.rand((batch, 3, height, width), generator=generator).to(device)
        image_j = torch.rand((batch, 3, height, width), generator=generator).to(device)

        def step() -> None:
            with torch.inference_mode():
                pose_model.predict_pose(image_i, image_j)

        ms = _time(step, device, iterations if batch == 1 else max(10, iterations // 8), warmup)
        stats = _stats(ms)
        if batch == 1:
            results["batch1"] = stats
        else:
            results["batch32"] = {**stats, "pairs_per_s": float(32e3 / np.median(ms))}
    return results


def _rendered_frames(native: tuple[int, int], count: int) -> tuple[list[np.ndarray], float]:
    """A rendered camera motion (the demo's camera and room; the VO needs real motion to track) and its
    mean true height above the floor (m)."""
    from nocal_ros.commands.demo import DEMO_SEED, demo_camera
    from nocal_ros.data.synthetic import render_sequence

    sequence = render_sequence(demo_camera(*native), count, seed=DEMO_SEED, split="test")
    return list(sequence.images), float(sequence.ground_truth[:, 2, 3].mean())  # the floor is the world's z = 0


def bench_estimator(pose_model, native: tuple[int, int], iterations: int, warmup: int,
                    precision: str = "fp32", cuda_graphs: bool = True, channels_last: bool = True) -> tuple[dict[str, Any], np.ndarray]:
    """Per-frame latency of decode + the pose head path of ``OdometryEstimator.process``; also returns the poses."""
    from nocal_ros.data.bags import decode_image
    from nocal_ros.odometry import OdometryEstimator

    estimator = OdometryEstimator(pose_model, precision=precision, cuda_graphs=cuda_graphs,
                                  channels_last=channels_last, method="pose_head")
    frames = _frames(native, 16)
    messages = [_image_message(frame, 0) for frame in frames]
    period = 33_333_333
    state = {"k": 0}
    poses: list[np.ndarray] = []

    def step() -> None:
        k = state["k"]
        state["k"] = k + 1
        result = estimator.process(k * period, decode_image(messages[k % len(messages)]), encoding="rgb8")
        if result is not None:
            poses.append(result.T_prev_curr)

    ms = _time(step, pose_model.device, iterations, warmup)
    stats = _stats(ms)
    stats.update(precision=precision, cuda_graphs=bool(getattr(estimator._runner, "graphs", None)),
                 layout="channels_last" if channels_last else "contiguous",
                 keyframes=estimator.counters.keyframes, pairs=estimator.counters.pairs)
    return stats, np.asarray(poses)


def _vo_frames(native: tuple[int, int], count: int, bag: str, camera_height: str | float = "") -> tuple[list[np.ndarray], str, float | None]:
    """The VO's frames, what they are, and the camera height to run them with (None: no ground-plane scale)."""
    if not bag:
        images, true_height = _rendered_frames(native, count)
        height = true_height if camera_height == "auto" else (camera_height or None)
        return images, f"rendered demo camera at {native[0]}x{native[1]}", height
    if camera_height == "auto":
        raise NocalError("--camera-height auto needs the rendered motion; give the height of --bag's camera in metres")
    from nocal_ros.data.bags import read_sequence

    sequence = read_sequence(bag, pose_source="none", max_frames=count)
    images = list(sequence.images)
    return images, f"{bag} ({images[0].shape[1]}x{images[0].shape[0]})", camera_height or None


def _percentiles(values: list[float] | np.ndarray) -> dict[str, float] | None:
    """:func:`_stats` of ``values``, or None when there are none (no keyframe was mapped, say)."""
    values = np.asarray(values, dtype=np.float64)
    return _stats(values) if len(values) else None


def bench_vo(pose_model, frames: list[np.ndarray], warmup: int, rate_hz: float,
             camera_height: float | None = None) -> dict[str, Any]:
    """The keyframe VO's costs on ``frames`` (see the module notes); the first ``warmup`` frames'
    tracking times are left out (they hold the map's initialisation)."""
    from nocal_ros.data.bags import decode_image
    from nocal_ros.odometry import OdometryEstimator, replay_at_rate

    messages = [_image_message(frame, 0) for frame in frames]
    period_ns = int(round(1e9 / rate_hz))

    # In order, mapping inline: every frame and every keyframe timed, nothing dropped.
    estimator = OdometryEstimator(pose_model, method="vo", synchronous_mapping=True, camera_height=camera_height)
    per_frame: list[float] = []
    for k, message in enumerate(messages):
        start = time.perf_counter()
        estimator.process(k * period_ns, decode_image(message), encoding="rgb8")
        per_frame.append((time.perf_counter() - start) * 1e3)
    timings = estimator.timings()
    skip = min(warmup, max(len(frames) - 10, 0))
    result: dict[str, Any] = {
        "frames": len(frames),
        "tracking": _percentiles(timings["tracking"][skip:]),
        "bundle_adjustment": _percentiles(timings["bundle_adjustment"]),
        "mapping": _percentiles(timings["mapping"]),
        # The estimator's whole per-frame cost with mapping inline (decode, pose head ring, tracking,
        # the keyframes' mapping): what a replay with --synchronous mapping pays per frame on average.
        "estimator_inline_mean_ms": float(np.mean(per_frame)),
        "camera_height_m": camera_height,
        "ground_fit": _percentiles(timings["ground_fit"]),
        "ground_motion": _percentiles(timings["ground_motion"]),
        "keyframes": int(estimator.counters.keyframes),
        "tracking_states": dict(vars(estimator.counters)),
    }
    estimator.close()

    # In real time, mapping in its worker: frames arrive every 1/rate s; the worker takes the newest.
    estimator = OdometryEstimator(pose_model, method="vo", camera_height=camera_height)
    replay = replay_at_rate(messages, rate_hz, lambda k, message: estimator.process(
        k * period_ns, decode_image(message), encoding="rgb8"))
    estimator.wait_for_mapping(timeout=60.0)
    timings = estimator.timings()
    result["realtime"] = {
        "rate_hz": float(rate_hz), "frames_sent": len(messages), "frames_processed": replay.handled,
        "frames_dropped": int(replay.dropped), "latency": _percentiles(replay.latencies_ms),
        # The worker thread's own CPU per frame (tracking, the pose head's ring, decoding), which
        # the tracking figure above leaves partly out and the latency mixes with waiting.
        "worker_cpu": _percentiles(replay.cpu_ms),
        "bundle_adjustment": _percentiles(timings["bundle_adjustment"]),
        "keyframes": int(estimator.counters.keyframes),
        "keyframes_merged": estimator.keyframes_merged,
        "tracking_states": dict(vars(estimator.counters)),
    }
    estimator.close()
    return result


def _pose_difference(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    from nocal_ros.geometry import rotation_angle_deg

    n = min(len(a), len(b))
    translation = np.linalg.norm(a[:n, :3, 3] - b[:n, :3, 3], axis=1)
    rotation = [rotation_angle_deg(a[k, :3, :3].T @ b[k, :3, :3]) for k in range(n)]
    return {"max_translation_mm": float(translation.max() * 1e3), "max_rotation_deg": float(np.max(rotation))}


def run_bench(args: argparse.Namespace) -> dict[str, Any]:
    if args.threads:
        torch.set_num_threads(args.threads)
    native = tuple(args.native)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else []) if args.devices == "auto" else args.devices.split(",")
    report: dict[str, Any] = {
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        },
        "native": list(native),
        "iterations": args.iterations,
        "devices": {},
    }
    for name in devices:
        if name == "cuda" and not torch.cuda.is_available():
            raise NocalError("--devices cuda: CUDA is not available on this machine")
        device = torch.device(name)
        pose_model, source = _pose_model(args, device)
        entry: dict[str, Any] = {"model": pose_model.model_id, "model_source": source,
                                 "input": list(pose_model.input_size)}
        layout = args.layout == "channels_last"
        # The pose head alone first: the estimator converts the model's weights to its layout.
        entry["pose_head"] = bench_pose_head(pose_model, args.iterations, args.warmup)
        entry["estimator"], poses32 = bench_estimator(pose_model, native, args.iterations, args.warmup, channels_last=layout)
        if args.vo:
            frames, source, height = _vo_frames(native, args.vo_frames, args.bag, args.camera_height)
            entry["vo"] = bench_vo(pose_model, frames, min(args.warmup, 20), args.rate, height)
            entry["vo"]["source"] = source
        if device.type == "cuda":
            entry["estimator_eager"], _ = bench_estimator(pose_model, native, args.iterations, args.warmup,
                                                          cuda_graphs=False, channels_last=layout)
            entry["estimator_fp16"], poses16 = bench_estimator(pose_model, native, args.iterations, args.warmup,
                                                               precision="fp16", channels_last=layout)
            entry["estimator_fp16"]["difference_vs_fp32"] = _pose_difference(poses16, poses32)
        report["devices"][name] = entry
    return report


def format_bench(report: dict[str, Any]) -> str:
    machine = report["machine"]
    lines = [f"torch {machine['torch']}, {machine['torch_threads']} CPU threads, "
             f"GPU: {machine['cuda_device'] or 'none'}; native frames {report['native'][0]}x{report['native'][1]}, "
             f"{report['iterations']} timed runs"]
    for name, entry in report["devices"].items():
        head = entry["pose_head"]
        lines.append(f"[{name}] model: {entry['model']} ({entry['model_source']}), input {entry['input'][0]}x{entry['input'][1]}")
        lines.append(f"  pose head, batch 1:   median {head['batch1']['median_ms']:.3f} ms, p90 {head['batch1']['p90_ms']:.3f} ms per pair")
        lines.append(f"  pose head, batch 32:  {head['batch32']['pairs_per_s']:.0f} pairs/s "
                     f"({head['batch32']['median_ms']:.2f} ms per batch)")
        for key, label in (("estimator", "estimator (pose head alone)"),
                           ("estimator_eager", "estimator, no graphs"),
                           ("estimator_fp16", "estimator, fp16")):
            if key in entry:
                e = entry[key]
                extra = ""
                if "difference_vs_fp32" in e:
                    d = e["difference_vs_fp32"]
                    extra = f" (vs fp32: {d['max_translation_mm']:.3f} mm, {d['max_rotation_deg']:.4f} deg max)"
                what = "decode + resize + pose head + integration"
                lines.append(f"  {label + ':':<22}median {e['median_ms']:.3f} ms, p90 {e['p90_ms']:.3f} ms per frame "
                             f"({what}; {e['layout']}){extra}")
        if "vo" in entry:
            lines += _format_vo(entry["vo"])
    return "\n".join(lines)


def _format_vo(vo: dict[str, Any]) -> list[str]:
    def figure(stats: dict[str, float] | None, unit: str = "per frame") -> str:
        if not stats:
            return "none"
        return f"median {stats['median_ms']:.1f} ms, p90 {stats['p90_ms']:.1f} ms {unit} ({stats['count']})"

    states = vo["tracking_states"]
    realtime = vo["realtime"]
    lines = [
        f"  keyframe VO on {vo['frames']} frames of {vo['source']}: {vo['keyframes']} keyframes, "
        f"{states.get('maps', 0)} map(s), {states.get('lost_frames', 0)} lost frames",
        f"    tracking (frontend + PnP):           {figure(vo['tracking'])}",
        f"    bundle adjustment:                   {figure(vo['bundle_adjustment'], 'per keyframe')}",
        f"    local mapping (with triangulation):  {figure(vo['mapping'], 'per keyframe')}",
        f"    estimator, mapping inline:           mean {vo['estimator_inline_mean_ms']:.1f} ms per frame",
    ]
    if vo.get("camera_height_m"):
        lines.append(f"    ground-plane fit ({vo['camera_height_m']:.3f} m):     {figure(vo['ground_fit'], 'per keyframe')}")
        lines.append(f"    ground homography:                   {figure(vo['ground_motion'], 'per frame pair')}")
    lines += [
        f"    real time at {realtime['rate_hz']:g} Hz, mapping in its worker: {realtime['frames_processed']} of "
        f"{realtime['frames_sent']} frames processed, {realtime['frames_dropped']} dropped; latency "
        f"{figure(realtime['latency'])}; worker CPU {figure(realtime['worker_cpu'])}; "
        f"bundle adjustment {figure(realtime['bundle_adjustment'], 'per solve')}, "
        f"{realtime['keyframes_merged']} keyframes merged into a later solve",
    ]
    return lines


def run(args: argparse.Namespace) -> int:
    report = run_bench(args)
    print(json.dumps(report, indent=2) if args.json else format_bench(report))
    return 0
