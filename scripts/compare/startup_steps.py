"""The published steps of a replay's start-up against the truth, grouped by how they were measured.

    python scripts/compare/startup_steps.py BAG [BAG ...] [--frames 40] [--camera-height M|auto]
                                            [--distortion-model plumb_bob|equidistant] [--steps]

Each bag's first ``--frames`` frames are replayed in-process as ``nocal odometry`` replays them
(synchronous mapping, the shipped model unless ``--model``). For every published step it records
whether the camera was still the prior guess when the frame was tracked (``calibration_status()``
before the frame: state ``prior``, not from a file), the step's motion and scale sources, and against
the bag's ``/ground_truth/pose``: the translation's direction error (deg), its length over the true
length, its error over the mean true step, and its translation NEES against the published covariance
(``evaluation.translation_consistency``'s error, in the true step's frame). The summary groups the
steps by (through the guess, scale source). docs/RESULTS.md ("Steps through the guessed camera") has
the figures over the dev replays; ``--camera-height auto`` takes each bag's mean true camera height.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def startup_steps(bag: Path, frames: int, camera_height: str | float | None = None,
                  distortion_model: str = "auto", model=None) -> list[dict]:
    """One record per published step of the bag's first ``frames`` frames (see the module notes)."""
    import torch

    from nocal_ros.data.bags import read_sequence
    from nocal_ros.evaluation import CHI2_3DOF_99
    from nocal_ros.geometry import invert_transform
    from nocal_ros.odometry import OdometryEstimator

    torch.set_num_threads(1)
    sequence = read_sequence(bag, pose_source="none", max_frames=frames)
    truth = sequence.ground_truth
    if truth is None or not np.isfinite(truth).all():
        raise SystemExit(f"{bag}: every frame needs a /ground_truth/pose")
    height = float(truth[:, 2, 3].mean()) if camera_height == "auto" else camera_height
    estimator = OdometryEstimator(model, "cpu", synchronous_mapping=True, camera_height=height,
                                  distortion_model=distortion_model)
    true_steps = [invert_transform(truth[k - 1]) @ truth[k] for k in range(1, len(truth))]
    mean_step = float(np.mean([np.linalg.norm(T[:3, 3]) for T in true_steps]))
    records, previous_stamp = [], None
    try:
        for k, (stamp, image) in enumerate(zip(sequence.stamps_ns, sequence.images)):
            status = estimator.calibration_status()
            guess = status["state"] == "prior" and status["source"] != "file"
            result = estimator.process(int(stamp), image)
            if k == 0 or result is None:
                previous_stamp = int(stamp)
                continue
            true_step, step = true_steps[k - 1], result.T_prev_curr
            dt = (int(stamp) - previous_stamp) * 1e-9
            previous_stamp = int(stamp)
            t_true, t_step = true_step[:3, 3], step[:3, 3]
            length = float(np.linalg.norm(t_step))
            cosine = float(t_true @ t_step) / max(float(np.linalg.norm(t_true)) * length, 1e-300)
            error = (invert_transform(true_step) @ step)[:3, 3]
            covariance = result.twist_covariance[:3, :3] * dt**2
            nees = float(error @ np.linalg.solve(covariance, error))
            records.append({
                "frame": k, "guess": guess, "motion": result.motion_source, "scale": result.scale_source,
                "direction_deg": float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))) if length > 0 else float("nan"),
                "length_ratio": length / max(float(np.linalg.norm(t_true)), 1e-300),
                "error_steps": float(np.linalg.norm(error)) / mean_step,
                "nees": nees, "within_99": nees < CHI2_3DOF_99,
            })
    finally:
        estimator.close()
    return records


def summary(records: list[dict]) -> list[dict]:
    """Per (through the guess, scale source): steps, RMS error over the mean step, median direction error
    and length ratio, and the share within the 99 % bound."""
    groups: dict[tuple[bool, str], list[dict]] = {}
    for record in records:
        groups.setdefault((record["guess"], record["scale"]), []).append(record)
    rows = []
    for (guess, scale), group in sorted(groups.items(), key=lambda item: (not item[0][0], item[0][1])):
        errors = np.array([r["error_steps"] for r in group])
        directions = np.array([r["direction_deg"] for r in group])
        rows.append({"guess": guess, "scale": scale, "steps": len(group),
                     "error_rms_steps": float(np.sqrt(np.mean(errors**2))),
                     "direction_median_deg": float(np.nanmedian(directions)) if np.isfinite(directions).any() else float("nan"),
                     "length_ratio_median": float(np.median([r["length_ratio"] for r in group])),
                     "within_99": float(np.mean([r["within_99"] for r in group]))})
    return rows


def _height(text: str) -> str | float:
    if text == "auto":
        return text
    value = float(text)
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"a positive height in metres or auto, not {text!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--frames", type=int, default=40, help="frames replayed from each bag's start")
    parser.add_argument("--camera-height", type=_height, default=None, help="metres, or auto: the bag's mean true height")
    parser.add_argument("--distortion-model", default="auto", choices=("auto", "plumb_bob", "equidistant"))
    parser.add_argument("--model", default=None, help="checkpoint or model store (default: the shipped model)")
    parser.add_argument("--steps", action="store_true", help="print every step, not only the summary")
    args = parser.parse_args(argv)
    everything = []
    for bag in args.bags:
        records = startup_steps(bag, args.frames, args.camera_height, args.distortion_model, args.model)
        everything += records
        print(f"{bag}: {len(records)} steps")
        if args.steps:
            for r in records:
                print(f"  {r['frame']:4d} {'guess' if r['guess'] else 'known':5s} {r['motion']:9s} {r['scale']:9s} "
                      f"direction {r['direction_deg']:6.1f} deg  length x{r['length_ratio']:5.2f}  "
                      f"error {r['error_steps']:5.2f} steps  NEES {r['nees']:8.2f}")
    print("camera  scale      steps  error RMS (steps)  direction median (deg)  length median  within 99 %")
    for row in summary(everything):
        print(f"{'guess' if row['guess'] else 'known':6s}  {row['scale']:9s} {row['steps']:6d} {row['error_rms_steps']:18.2f} "
              f"{row['direction_median_deg']:23.1f} {row['length_ratio_median']:14.2f} {100 * row['within_99']:11.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
