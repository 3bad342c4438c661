"""The dev set of replays: make its bags, replay them with a checkout, and compare two sets of replays.

    python scripts/compare/dev_replays.py bags DIR                       # the 23 bags (synth + import), once
    python scripts/compare/dev_replays.py replay DIR OUT [--checkout PATH] [--jobs 2] [--bags NAME ...]
    python scripts/compare/dev_replays.py compare OUT_A OUT_B [--bags NAME ...] [--from-pair 20]

The bags are those of docs/RESULTS.md's comparisons: the held-out camera at 160x120 and 640x480 and the
fisheye field bag (200 frames each), eight random cameras at 160x120 and eight at 640x480 (150 frames
each), VAMR's first 300 frames and all 736, KITTI's clip and its frames 20-50. The real recordings come
from ``../shared/data/real/`` and are left out, with a note, where it is missing.

``replay`` runs ``nocal odometry BAG --out OUT/NAME --threads 1 --arm-topic ''`` (the fisheye with
``--distortion-model equidistant``) for each bag, with ``--checkout`` first on ``PYTHONPATH`` (a git
worktree of another commit, say), ``--jobs`` at a time. A replay is deterministic on one machine but
chaotic: compare two checkouts by several draws, not one (docs/RESULTS.md, "The replays move by
themselves").

``compare`` prints, per bag and then as medians with how many bags went down / up: the published and
final focal error, the published rotation per pair (RMSE) over the whole bag and from pair
``--from-pair`` on (after the start-up through the guessed camera), the final rotation, the published
and final APE Sim(3), the mean rotation NEES, and the lost frames.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPOSITORY = Path(__file__).resolve().parents[2]
REAL = REPOSITORY.parent / "shared" / "data" / "real"
HELDOUT = REPOSITORY / "config" / "cameras" / "heldout_640x480.yaml"
FISHEYE = REPOSITORY / "config" / "cameras" / "fisheye_640x480.yaml"


def bag_commands() -> dict[str, list[str]]:
    """``{name: nocal arguments}`` of every rendered bag of the dev set."""
    test = ["--split", "test", "--threads", "1"]
    commands = {
        "heldout_160": ["synth", "--camera", str(HELDOUT), "--size", "160x120", "--frames", "200", "--seed", "31", *test],
        "heldout_640": ["synth", "--camera", str(HELDOUT), "--frames", "200", "--seed", "31", *test],
        "field_heldout": ["synth", "--camera", str(FISHEYE), "--size", "160x120", "--frames", "200", "--seed", "12", *test],
    }
    for size, seeds in (("160x120", range(201, 209)), ("640x480", range(301, 309))):
        for seed in seeds:
            name = f"r{size.split('x')[0]}_{seed}"
            commands[name] = ["synth", "--random-camera", "--seed", str(seed), "--size", size, "--frames", "150", *test]
    return commands


REAL_BAGS = ("vamr_300", "vamr_all", "kitti_clip", "kitti_20_50")
NAMES = tuple(bag_commands()) + REAL_BAGS


def make_bags(directory: Path) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for name, arguments in bag_commands().items():
        if not (directory / name).exists():
            _nocal([*arguments, "--out", str(directory / name)])
    if not REAL.is_dir():
        print(f"left out {', '.join(REAL_BAGS)}: {REAL} is missing")
        return
    if not (directory / "vamr_300").exists():
        _nocal(["import", "vamr", str(REAL / "vamr_ex1"), "--max-frames", "300", "--out", str(directory / "vamr_300")])
    if not (directory / "vamr_all").exists():
        _nocal(["import", "vamr", str(REAL / "vamr_ex1"), "--out", str(directory / "vamr_all")])
    if not (directory / "kitti_clip").exists():
        _nocal(["import", "kitti", str(REAL / "kitti_clip"), "--out", str(directory / "kitti_clip")])
    if not (directory / "kitti_20_50").exists():
        # Frames 20-50 as a KITTI folder of their own: the images linked, the poses and calibration copied.
        with tempfile.TemporaryDirectory() as folder:
            source = Path(folder)
            (source / "image_l").mkdir()
            for k in range(20, 51):
                os.symlink(REAL / "kitti_clip" / "image_l" / f"{k:06d}.png", source / "image_l" / f"{k - 20:06d}.png")
            poses = (REAL / "kitti_clip" / "poses.txt").read_text().splitlines()
            (source / "poses.txt").write_text("\n".join(poses[20:51]) + "\n")
            shutil.copy(REAL / "kitti_clip" / "calib.txt", source / "calib.txt")
            _nocal(["import", "kitti", str(source), "--out", str(directory / "kitti_20_50")])


def _nocal(arguments: list[str], env: dict[str, str] | None = None, log: Path | None = None) -> int:
    """``python -m nocal_ros.cli ARGUMENTS`` run from the log's folder: ``-m`` puts the working directory
    first on ``sys.path``, and from the repository's root its ``nocal_ros`` would shadow the checkout's."""
    command = [sys.executable, "-m", "nocal_ros.cli", *arguments]
    if log is None:
        return subprocess.run(command, env=env, check=True).returncode
    with open(log, "w") as stream:
        return subprocess.run(command, env=env, cwd=log.parent, stdout=stream, stderr=subprocess.STDOUT).returncode


def replay(bags: Path, out: Path, names: list[str], checkout: Path | None, jobs: int) -> int:
    bags, out = bags.resolve(), out.resolve()
    env = dict(os.environ)
    if checkout is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(checkout.resolve()), *filter(None, [env.get("PYTHONPATH")])])
    out.mkdir(parents=True, exist_ok=True)
    present = [name for name in names if (bags / name).exists()]
    for name in sorted(set(names) - set(present)):
        print(f"{name}: no bag in {bags}, left out")

    def one(name: str) -> tuple[str, int]:
        arguments = ["odometry", str(bags / name), "--out", str(out / name), "--threads", "1", "--arm-topic", "",
                     "--overwrite"]
        if name == "field_heldout":
            arguments += ["--distortion-model", "equidistant"]
        return name, _nocal(arguments, env, out / f"{name}.log")

    failed = 0
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        for name, code in pool.map(one, present):
            print(f"{name}: {'done' if code == 0 else f'failed (exit {code}, {out / name}.log)'}", flush=True)
            failed += code != 0
    return 1 if failed else 0


def replay_figures(result: Path, bag: Path, from_pair: int) -> dict[str, float] | None:
    """The figures ``compare`` prints of one replay, or None where it has no report."""
    from nocal_ros import evaluation
    from nocal_ros.data.bags import read_poses
    from nocal_ros.data.importers.common import read_tum_poses

    try:
        report = json.loads((result / "report.json").read_text())
    except (OSError, ValueError):
        return None
    stamps, estimate = read_tum_poses(result / "trajectory.tum")
    truth = read_poses(bag, "/ground_truth/pose", stamps)
    valid = np.isfinite(truth).all(axis=(1, 2))  # pairs across a frame without truth are left out
    rotation = np.asarray(evaluation.relative_pose_error(estimate[valid], truth[valid])["rotation_deg_per_pair"], dtype=float)
    later = rotation[from_pair:]
    final = report.get("final_trajectory", {})
    return {
        "focal %": report["calibration"]["focal_error_percent"],
        "final focal %": final.get("calibration", {}).get("focal_error_percent", np.nan),
        "rotation": report["rpe"]["rotation_deg"]["rmse"],
        f"rotation from {from_pair}": float(np.sqrt(np.mean(later**2))) if len(later) else np.nan,
        "final rotation": final.get("rpe", {}).get("rotation_deg", {}).get("rmse", np.nan),
        "APE": report.get("ape_sim3", {}).get("rmse", np.nan),
        "final APE": final.get("ape_sim3", {}).get("rmse", np.nan),
        "NEES": report.get("rotation_consistency", {}).get("mean_nees", np.nan),
        "lost": report["events"]["lost_frames"],
    }


def compare_table(figures_a: dict[str, dict[str, float]], figures_b: dict[str, dict[str, float]]) -> list[str]:
    """Markdown rows: per bag ``a -> b`` for every figure, then the medians and the bags lower / higher."""
    names = [name for name in figures_a if name in figures_b]
    keys = list(figures_a[names[0]]) if names else []
    rows = ["| bag | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for name in names:
        rows.append(f"| {name} | " + " | ".join(f"{figures_a[name][k]:.4g} -> {figures_b[name][k]:.4g}" for k in keys) + " |")
    medians, counts = [], []
    for key in keys:
        a = np.array([figures_a[name][key] for name in names], dtype=float)
        b = np.array([figures_b[name][key] for name in names], dtype=float)
        medians.append(f"{np.nanmedian(a):.4g} -> {np.nanmedian(b):.4g}")
        counts.append(f"{int(np.sum(b < a))} / {int(np.sum(b > a))}")
    rows.append("| median | " + " | ".join(medians) + " |")
    rows.append("| lower / higher | " + " | ".join(counts) + " |")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    make = commands.add_parser("bags", help="make the dev set's bags in DIR (those missing)")
    make.add_argument("directory", type=Path)
    run = commands.add_parser("replay", help="replay the bags of DIR into OUT")
    run.add_argument("directory", type=Path)
    run.add_argument("out", type=Path)
    run.add_argument("--checkout", type=Path, help="a checkout to run, put first on PYTHONPATH")
    run.add_argument("--jobs", type=int, default=2)
    run.add_argument("--bags", nargs="+", default=list(NAMES))
    compare = commands.add_parser("compare", help="compare two replays' OUT folders")
    compare.add_argument("a", type=Path)
    compare.add_argument("b", type=Path)
    compare.add_argument("--bags-from", type=Path, required=True, help="the bags' DIR (their ground truth)")
    compare.add_argument("--bags", nargs="+", default=list(NAMES))
    compare.add_argument("--from-pair", type=int, default=20)
    args = parser.parse_args(argv)

    if args.command == "bags":
        make_bags(args.directory)
        return 0
    if args.command == "replay":
        return replay(args.directory, args.out, args.bags, args.checkout, args.jobs)
    figures = []
    for folder in (args.a, args.b):
        found = {}
        for name in args.bags:
            value = replay_figures(folder / name, args.bags_from / name, args.from_pair)
            if value is not None:
                found[name] = value
        figures.append(found)
    missing = sorted(set(figures[0]) ^ set(figures[1]))
    if missing:
        print(f"in one of the two only, left out: {', '.join(missing)}")
    if not set(figures[0]) & set(figures[1]):
        print("no replay in both", file=sys.stderr)
        return 1
    print("\n".join(compare_table(*figures)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
