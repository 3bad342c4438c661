"""COLMAP's self-calibrating SfM on the frames of a bag, scored exactly as ``nocal odometry`` is.

    python scripts/compare/colmap.py BAG --out DIR [--max-frames N] [--camera-model OPENCV]
        [--matcher exhaustive|sequential] [--refine-principal-point] [--max-image-size PX] [--threads 1]

pycolmap (an optional extra: ``pip install -r requirements-compare.txt``) extracts SIFT features,
matches them and runs incremental mapping with one shared camera that starts from COLMAP's own prior
(focal 1.2 x the larger image side, centred principal point, no distortion: no calibration is given)
and whose focal length and distortion are refined by bundle adjustment (the principal point too with
``--refine-principal-point``). The camera is converted to a ROS CameraCalibration by
``nocal_ros.colmap_camera`` and the poses of the registered frames are scored against the bag's
``/ground_truth/pose`` and ``/ground_truth/camera_info`` by ``nocal_ros.evaluation``, as
``nocal odometry`` does.

A monocular reconstruction has no metric scale: its positions are multiplied by the scale of the
Sim(3) alignment to the truth before RPE and APE SE(3) are computed (``evo_rpe --correct_scale``);
``nocal odometry``'s figures are metric. Frames COLMAP did not register are counted and listed; the
trajectory metrics use the registered frames of the largest reconstruction, and "RPE per pair" is
then over consecutive registered frames.

Writes to DIR: ``report.json`` (the layout of ``nocal odometry``'s, plus a ``colmap`` section),
``calibration.yaml``, ``trajectory.tum`` (registered frames, camera poses in the first registered
frame, scale-corrected) and ``sparse/`` (the COLMAP model). ``--keep-workspace`` keeps the frames and
the feature database in ``DIR/workspace``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PYCOLMAP_VERSION = "4.2.1"
INSTALL_HINT = f"pip install pycolmap=={PYCOLMAP_VERSION} (or: pip install -r requirements-compare.txt)"
OUTPUT_NAMES = ("report.json", "calibration.yaml", "trajectory.tum", "sparse")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", type=Path, help="input bag (rosbag2 directory or file, or ROS 1 .bag)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--image-topic", default="/camera/image_raw")
    parser.add_argument("--gt-topic", default="/ground_truth/pose", help="true camera poses (camera in world)")
    parser.add_argument("--camera-info-topic", default="/ground_truth/camera_info", help="true calibration")
    parser.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
    parser.add_argument("--camera-model", default="OPENCV",
                        help="COLMAP camera model: OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL, RADIAL, FULL_OPENCV, ... (default OPENCV)")
    parser.add_argument("--matcher", default="exhaustive", choices=("exhaustive", "sequential"))
    parser.add_argument("--overlap", type=int, default=10, help="sequential matcher: neighbours matched per frame")
    parser.add_argument("--prior-focal-factor", type=float, default=None, metavar="F",
                        help="start from f = F x the larger image side and let COLMAP treat it as a focal prior "
                             "(COLMAP 4.2 marks fisheye pairs without one as degenerate; 1.2 is COLMAP's own default guess)")
    parser.add_argument("--refine-principal-point", action="store_true", help="refine cx, cy too (COLMAP's default: fixed at the centre)")
    parser.add_argument("--max-image-size", type=int, default=-1, help="SIFT on frames downscaled to this longer side (-1: native)")
    parser.add_argument("--max-features", type=int, default=8192, help="SIFT features per frame (COLMAP's default 8192)")
    parser.add_argument("--threads", type=int, default=1, help="COLMAP threads (default 1, as nocal odometry --threads 1)")
    parser.add_argument("--max-mapping-seconds", type=int, default=-1,
                        help="stop COLMAP's incremental mapping after this long and keep what it has (-1: no limit)")
    parser.add_argument("--seed", type=int, default=0, help="COLMAP's RANSAC and mapper seed")
    parser.add_argument("--keep-workspace", action="store_true", help="keep frames and database in DIR/workspace")
    parser.add_argument("--overwrite", action="store_true", help="replace outputs already in --out")
    parser.add_argument("--verbose", action="store_true", help="COLMAP's own progress log (glog INFO) on stderr")
    return parser.parse_args(argv)


def import_pycolmap():
    """pycolmap, or one line saying how to install it."""
    from nocal_ros.evaluation import MissingDependencyError

    try:
        import pycolmap
    except ImportError as error:
        raise MissingDependencyError(f"this comparison needs pycolmap, which is not installed ({error}); {INSTALL_HINT}") from None
    if pycolmap.__version__ != PYCOLMAP_VERSION:
        print(f"warning: pycolmap {pycolmap.__version__}, figures in docs/RESULTS.md are from {PYCOLMAP_VERSION}", file=sys.stderr)
    return pycolmap


def write_frames(bag: Path, topic: str, max_frames: int | None, image_dir: Path) -> tuple[list[str], np.ndarray, tuple[int, int]]:
    """The bag's frames as PNG files in ``image_dir``: names, stamps and the native size."""
    import cv2

    from nocal_ros.data.bags import iter_images

    image_dir.mkdir(parents=True, exist_ok=True)
    names, stamps, size = [], [], None
    for index, (stamp_ns, _, image) in enumerate(iter_images(bag, topic)):
        if max_frames is not None and index >= max_frames:
            break
        size = (image.shape[1], image.shape[0])
        name = f"frame_{index:06d}.png"
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        names.append(name)
        stamps.append(stamp_ns)
    return names, np.asarray(stamps, dtype=np.int64), size


def reconstruct(pycolmap, args: argparse.Namespace, workspace: Path, image_dir: Path, names: list[str],
                size: tuple[int, int]) -> tuple[dict, dict[str, float]]:
    """Features, matches and incremental mapping; the reconstructions by index and each stage's seconds."""
    database = workspace / "database.db"
    database.unlink(missing_ok=True)
    timing: dict[str, float] = {}
    device = pycolmap.Device.cpu
    clock = _Clock(timing)

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = args.camera_model
    if args.prior_focal_factor is not None:
        # Given camera parameters make COLMAP's focal a prior; the rest is its usual uncalibrated start.
        start = pycolmap.Camera.create_from_model_name(1, args.camera_model, args.prior_focal_factor * max(size), *size)
        reader.camera_params = ",".join(repr(float(v)) for v in start.params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = args.threads
    extraction.max_image_size = args.max_image_size
    extraction.sift.max_num_features = args.max_features
    with clock("features"):
        pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=device)

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = args.threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = args.seed
    with clock("matching"):
        if args.matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification, device=device)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = args.overlap
            pairing.num_threads = args.threads
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                      verification_options=verification, device=device)

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = args.threads
    mapping.random_seed = args.seed
    mapping.ba_refine_focal_length = True
    mapping.ba_refine_extra_params = True
    mapping.ba_refine_principal_point = bool(args.refine_principal_point)
    mapping.max_runtime_seconds = int(args.max_mapping_seconds)
    sparse = workspace / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    with clock("mapping"):
        reconstructions = pycolmap.incremental_mapping(database, image_dir, sparse, options=mapping)
    return reconstructions, timing


class _Clock:
    """Wall and CPU seconds of a stage: on a shared machine the CPU time is the figure that repeats."""

    def __init__(self, timing: dict[str, float]) -> None:
        self.timing = timing

    @contextlib.contextmanager
    def __call__(self, stage: str):
        wall, cpu = time.perf_counter(), time.process_time()
        yield
        self.timing[stage] = time.perf_counter() - wall
        self.timing[stage + "_cpu"] = time.process_time() - cpu


def registered_poses(reconstruction, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into ``names``) of the registered frames, sorted, and their ``T_w_cam`` ``(R, 4, 4)``."""
    from nocal_ros.geometry import invert_transform

    index_of = {name: i for i, name in enumerate(names)}
    rows = []
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        T_cam_w = np.eye(4)
        T_cam_w[:3] = image.cam_from_world().matrix()
        rows.append((index_of[image.name], invert_transform(T_cam_w)))
    rows.sort(key=lambda row: row[0])
    return np.array([i for i, _ in rows], dtype=np.int64), np.array([T for _, T in rows]).reshape(-1, 4, 4)


def evaluate(estimate: np.ndarray, stamps_ns: np.ndarray, truth_poses: np.ndarray, truth_calibration, calibration) -> dict:
    """``nocal odometry``'s metrics of a scale-free trajectory: RPE and APE SE(3) after scaling the
    positions by the Sim(3) alignment's scale, APE Sim(3), and the camera errors."""
    from nocal_ros import evaluation
    from nocal_ros.geometry import invert_transform

    report: dict = {}
    valid = np.isfinite(truth_poses).all(axis=(1, 2))
    estimate, truth, stamps = estimate[valid], truth_poses[valid], stamps_ns[valid]
    report["evaluated_poses"] = int(len(stamps))
    if len(stamps) >= 3:
        # Both in the first evaluated camera frame, as nocal odometry's report.
        estimate = invert_transform(estimate[0]) @ estimate
        truth = invert_transform(truth[0]) @ truth
        scale = evaluation.absolute_pose_error(estimate, truth, correct_scale=True)["scale"]
        estimate = estimate.copy()
        estimate[:, :3, 3] *= scale
        report["scale_correction"] = float(scale)
        report.update(evaluation.summary(evaluation.trajectory_errors(stamps, estimate, truth)))
        report["_trajectory"] = estimate
    if truth_calibration is not None:
        report["calibration"] = evaluation.calibration_errors(calibration, truth_calibration)
        report["calibration"]["distortion_model"] = calibration.distortion_model
    return report


def run(args: argparse.Namespace) -> dict:
    from nocal_ros.colmap_camera import SUPPORTED_MODELS, calibration_from_pycolmap
    from nocal_ros.commands.odometry import write_tum
    from nocal_ros.data.bags import bag_topics, read_camera_info, read_poses
    from nocal_ros.errors import BagError, NocalError

    pycolmap = import_pycolmap()
    args.camera_model = args.camera_model.upper()
    if args.camera_model not in SUPPORTED_MODELS:
        raise NocalError(f"--camera-model {args.camera_model}: no ROS equivalent to score it; use one of {', '.join(SUPPORTED_MODELS)}")
    if not args.bag.exists():
        raise BagError(f"{args.bag}: no such bag (file or directory does not exist)")
    existing = [name for name in OUTPUT_NAMES if (args.out / name).exists()]
    if existing and not args.overwrite:
        raise NocalError(f"{args.out}: already holds {', '.join(existing)}; pass --overwrite to replace them")
    args.out.mkdir(parents=True, exist_ok=True)

    if not args.verbose:
        pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING)
    start, start_cpu = time.perf_counter(), time.process_time()
    workspace = args.out / "workspace" if args.keep_workspace else Path(tempfile.mkdtemp(prefix="colmap_", dir=args.out))
    try:
        image_dir = workspace / "images"
        if image_dir.exists():
            shutil.rmtree(image_dir)
        names, stamps_ns, native_size = write_frames(args.bag, args.image_topic, args.max_frames, image_dir)
        timing = {"frames": time.perf_counter() - start, "frames_cpu": time.process_time() - start_cpu}
        print(f"{len(names)} frames {native_size[0]}x{native_size[1]} from {args.bag}; COLMAP {pycolmap.__version__}, "
              f"{args.camera_model}, {args.matcher} matching, principal point {'refined' if args.refine_principal_point else 'fixed'}, "
              f"{args.threads} thread(s)", flush=True)
        reconstructions, stages = reconstruct(pycolmap, args, workspace, image_dir, names, native_size)
        timing.update(stages)
        seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
        if not reconstructions:
            hint = "; COLMAP's fisheye models need a focal prior (--prior-focal-factor)" if "FISHEYE" in args.camera_model and args.prior_focal_factor is None else ""
            raise NocalError(f"{args.bag}: COLMAP registered no frames ({len(names)} frames; {args.camera_model}, {args.matcher}){hint}")
        sizes = {key: rec.num_reg_images() for key, rec in reconstructions.items()}
        best = max(sizes, key=lambda key: sizes[key])
        reconstruction = reconstructions[best]
        sparse_out = args.out / "sparse"
        if sparse_out.exists():
            shutil.rmtree(sparse_out)
        sparse_out.mkdir()
        reconstruction.write(sparse_out)
    finally:
        if not args.keep_workspace:
            shutil.rmtree(workspace, ignore_errors=True)

    indices, T_w_cam = registered_poses(reconstruction, names)
    camera = next(iter(reconstruction.cameras.values()))
    calibration = calibration_from_pycolmap(camera, native_size, camera_name=f"colmap_{args.camera_model.lower()}")
    calibration.save(args.out / "calibration.yaml")
    unregistered = sorted(set(range(len(names))) - set(indices.tolist()))

    topics = bag_topics(args.bag)
    truth_poses = read_poses(args.bag, args.gt_topic, stamps_ns[indices]) if args.gt_topic in topics else np.full((len(indices), 4, 4), np.nan)
    truth_calibration = read_camera_info(args.bag, args.camera_info_topic) if args.camera_info_topic in topics else None
    report = {
        "method": "colmap",
        "model": f"COLMAP {pycolmap.__version__} {args.camera_model} {args.matcher}"
                 f" pp {'refined' if args.refine_principal_point else 'fixed'}"
                 + ("" if args.prior_focal_factor is None else f" focal prior {args.prior_focal_factor:g}x"),
        "bag_frames": len(names),
        "poses": int(len(indices)),
        "events": {"frames": len(names), "registered": int(len(indices)), "unregistered": len(unregistered),
                   "reconstructions": len(reconstructions)},
        "seconds": float(seconds),
        "cpu_seconds": float(cpu_seconds),
        "ms_per_frame": float(1e3 * seconds / max(len(names), 1)),
    }
    evaluated = evaluate(T_w_cam, stamps_ns[indices], truth_poses, truth_calibration, calibration)
    trajectory = evaluated.pop("_trajectory", None)
    report.update(evaluated)
    report["colmap"] = {
        "version": pycolmap.__version__,
        "settings": {"camera_model": args.camera_model, "matcher": args.matcher, "overlap": args.overlap if args.matcher == "sequential" else None,
                     "refine_principal_point": bool(args.refine_principal_point), "refine_focal_length": True,
                     "refine_extra_params": True, "max_image_size": args.max_image_size, "max_features": args.max_features,
                     "threads": args.threads, "seed": args.seed, "max_mapping_seconds": args.max_mapping_seconds, "prior": "COLMAP default (focal 1.2 x max(width, height), centred, no distortion)" if args.prior_focal_factor is None
                     else f"focal {args.prior_focal_factor} x max(width, height) as a focal prior, centred, no distortion"},
        "timing_s": {k: float(v) for k, v in timing.items()},
        "camera": {"model": camera.model.name, "params": [float(v) for v in camera.params], "width": camera.width, "height": camera.height},
        "unregistered_frames": unregistered,
        "reconstruction_sizes": sorted(sizes.values(), reverse=True),
        "points3D": int(reconstruction.num_points3D()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "note": "trajectory metrics over the registered frames of the largest reconstruction; positions scaled by the "
                "Sim(3) alignment's scale (scale_correction) before RPE and APE SE(3): monocular SfM has no metric scale",
    }
    if trajectory is not None:
        valid = np.isfinite(truth_poses).all(axis=(1, 2))
        write_tum(args.out / "trajectory.tum", stamps_ns[indices][valid], trajectory)
    temporary = args.out / ".report.json.tmp"
    temporary.write_text(json.dumps(report, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(temporary, args.out / "report.json")
    return report


def summary(report: dict) -> str:
    from nocal_ros.evaluation import format_report

    colmap = report["colmap"]
    t = colmap["timing_s"]
    timing = ", ".join(f"{k} {t[k]:.1f} s" for k in t if not k.endswith("_cpu"))
    lines = [
        f"{report['model']}: registered {report['poses']} of {report['bag_frames']} frames "
        f"({report['events']['unregistered']} unregistered; reconstructions {colmap['reconstruction_sizes']}) "
        f"in {report['seconds']:.1f} s wall, {report['cpu_seconds']:.1f} s CPU ({timing})",
        f"camera {colmap['camera']['model']} {np.round(colmap['camera']['params'], 5).tolist()}; "
        f"{colmap['points3D']} points, reprojection error {colmap['mean_reprojection_error_px']:.3f} px",
    ]
    if colmap["unregistered_frames"]:
        lines.append(f"unregistered frames: {colmap['unregistered_frames']}")
    if "scale_correction" in report:
        lines.append(f"trajectory metrics over the {report['evaluated_poses']} registered frames with a true pose; RPE per pair "
                     f"between consecutive registered frames; positions scaled by {report['scale_correction']:.5g} "
                     "(Sim(3) alignment: monocular SfM has no metric scale)")
    body = {k: v for k, v in report.items() if k not in ("colmap", "model", "method")}
    lines.append(format_report(body))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from nocal_ros.errors import NocalError

    args = parse_args(argv)
    try:
        report = run(args)
    except NocalError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(summary(report))
    print(f"outputs in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
