"""Markdown table rows from ``report.json`` files of ``nocal odometry`` and ``scripts/compare/colmap.py``.

    python scripts/compare/table.py [--no-motion BAG [--max-frames N]] [LABEL=]REPORT.json[#final] ...

One row per report: method, focal error %, ``dr``, RPE per pair (RMSE, m / deg), APE after Sim(3)
alignment (RMSE, m), wall time (and the process's CPU time, which repeats on a shared machine), and frames with a pose of frames in the bag. The label defaults to the
report's method (COLMAP and its settings; for ``nocal odometry`` whether two-view geometry was used).
``REPORT.json#final`` gives the row of a ``nocal odometry`` replay's final trajectory (``trajectory_final.tum``:
every frame posed again in the final map and camera) instead of what it published; its time is the
final solves' own.

``--no-motion BAG`` adds the row of an estimate that never moves, from the bag's ``/ground_truth/pose``
at its image stamps: its RPE is the true motion per pair itself (``evaluation.relative_pose_error``
of identity poses). A constant trajectory maps to one point under any alignment, so Umeyama's fit is
degenerate; its APE is the closed form instead: the RMS distance of the true positions from their
centroid, the best single point.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HEADER = ("| method | focal err | dr | RPE per pair m / deg | APE Sim(3) m | time (wall) | frames |\n"
          "|---|---|---|---|---|---|---|")


def default_label(report: dict) -> str:
    if report.get("method") == "colmap":
        return report.get("model", "COLMAP")
    if report.get("method") == "vo":
        scale = report.get("scale_source", {})
        return "nocal odometry (keyframe VO" + (", arm-pose scale)" if scale.get("arm") else ")")
    # reports from before the keyframe VO (no "method" key) and --method pose_head
    events = report.get("events", {})
    path = "two-view" if events.get("two_view_pairs", 0) > 0 else "pose head alone"
    return f"nocal odometry ({path})"


def final_report(report: dict, path: str) -> dict:
    """A ``nocal odometry`` report with its final trajectory's figures in place of the published ones."""
    from nocal_ros.errors import NocalError

    final = report.get("final_trajectory")
    if not final or "rpe" not in final:
        raise NocalError(f"{path}: no final trajectory in this report (nocal odometry writes one at the end of a replay)")
    keys = ("calibration", "rpe", "ape_sim3", "seconds", "poses")
    return {**{k: v for k, v in report.items() if k not in keys + ("cpu_seconds", "evaluated_poses")},
            **{k: final[k] for k in keys if k in final}}


def report_row(label: str, report: dict) -> str:
    calibration = report.get("calibration")
    focal = f"{calibration['focal_error_percent']:.2f} %" if calibration else "-"
    dr = f"{calibration['dr']:.4f}" if calibration else "-"
    rpe = report.get("rpe")
    rpe_text = f"{rpe['translation_m']['rmse']:.4f} / {rpe['rotation_deg']['rmse']:.3f}" if rpe else "-"
    ape = report.get("ape_sim3")
    ape_text = f"{ape['translation_m']['rmse']:.4f}" if ape else "-"
    if "scale_correction" in report:
        rpe_text += f" (scale x{report['scale_correction']:.3g})"
    elif ape:
        ape_text += f" (scale {ape['scale']:.3g})"
    seconds = report.get("seconds")
    frames = report.get("bag_frames")
    cpu = report.get("cpu_seconds")
    time_text = "-" if seconds is None else f"{seconds:.1f} s" + ("" if cpu is None else f" ({cpu:.1f} s CPU)")
    posed = report.get("evaluated_poses", report.get("poses"))
    return f"| {label} | {focal} | {dr} | {rpe_text} | {ape_text} | {time_text} | {posed}/{frames} |"


def no_motion(bag: Path, gt_topic: str, image_topic: str, max_frames: int | None) -> dict:
    """The metrics of reporting the identity for every frame, against the bag's true poses."""
    from nocal_ros import evaluation
    from nocal_ros.data.bags import iter_images, read_poses

    stamps = []
    for index, (stamp_ns, _, _) in enumerate(iter_images(bag, image_topic)):
        if max_frames is not None and index >= max_frames:
            break
        stamps.append(stamp_ns)
    truth = read_poses(bag, gt_topic, np.asarray(stamps, dtype=np.int64))
    truth = truth[np.isfinite(truth).all(axis=(1, 2))]
    rpe = evaluation.relative_pose_error(np.broadcast_to(np.eye(4), truth.shape), truth, delta=1)
    positions = truth[:, :3, 3]
    spread = float(np.sqrt(np.mean(np.sum((positions - positions.mean(0)) ** 2, axis=1))))
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return {"rpe": rpe, "ape_rmse": spread, "poses": len(truth), "frames": len(stamps), "mean_step_m": float(steps.mean())}


def no_motion_row(result: dict) -> str:
    rpe = result["rpe"]
    return (f"| no motion (identity poses; mean step {100 * result['mean_step_m']:.2f} cm) | | | "
            f"{rpe['translation_m']['rmse']:.4f} / {rpe['rotation_deg']['rmse']:.3f} | {result['ape_rmse']:.4f} | | "
            f"{result['poses']}/{result['frames']} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="*", help="report.json files, optionally LABEL=PATH")
    parser.add_argument("--no-motion", type=Path, default=None, metavar="BAG", help="add the no-motion row from this bag's ground truth")
    parser.add_argument("--max-frames", type=int, default=None, help="with --no-motion: the first N frames, as the runs used")
    parser.add_argument("--gt-topic", default="/ground_truth/pose")
    parser.add_argument("--image-topic", default="/camera/image_raw")
    args = parser.parse_args(argv)
    from nocal_ros.errors import NocalError

    rows = [HEADER]
    try:
        for item in args.reports:
            label, _, path = item.rpartition("=") if "=" in item else ("", "", item)
            path, final = (path[: -len("#final")], True) if path.endswith("#final") else (path, False)
            try:
                report = json.loads(Path(path).read_text(encoding="utf-8"))
            except (OSError, ValueError) as error:
                raise NocalError(f"{path}: cannot read a report ({error})") from None
            if final:
                report = final_report(report, path)
            rows.append(report_row(label or default_label(report) + (", final" if final else ""), report))
        if args.no_motion is not None:
            rows.append(no_motion_row(no_motion(args.no_motion, args.gt_topic, args.image_topic, args.max_frames)))
    except NocalError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
