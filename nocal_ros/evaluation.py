"""Metrics, report tables and plots: DESIGN.md's "Metrics" section, implemented exactly.

* Focal error: ``|f_est - f_true|`` in pixels at the native resolution, and as a percentage.
* Mean radial shift ``dr``: over every pixel of the native image grid, the distance between the learnt
  undistorted normalised point ``(x, y)`` and the true one (the true lens via ``nocal_ros.lens``, which
  matches ``cv2.undistortPoints``), averaged. Normalised image-plane units.
* Odometry: relative pose error per pair (translation in metres, rotation in degrees; mean, std, RMSE)
  with ``evo``; APE after Umeyama alignment with and without scale for whole trajectories.

``evo`` is GPLv3 and an optional extra: it is imported inside the functions that need it, so the nodes
and the rest of the core never load it. Its ``align()`` changes trajectories in place; every function
here works on copies and never modifies the caller's arrays.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from nocal_ros.errors import NocalError
from nocal_ros.geometry import nearest_rotation

if TYPE_CHECKING:
    from nocal_ros.camera import CameraModel
    from nocal_ros.lens import CameraCalibration

EVO_INSTALL_HINT = "pip install evo==1.38.1 (GPLv3; the optional evaluation extra in requirements.txt)"


class MissingDependencyError(NocalError):
    """An optional package needed by this job is not installed."""


def _evo():
    try:
        from evo.core import metrics, trajectory
    except ImportError as error:
        raise MissingDependencyError(f"pose errors are computed with evo, which is not installed ({error}); {EVO_INSTALL_HINT}") from None
    return metrics, trajectory


# --------------------------------------------------------------------------------------------------
# camera
# --------------------------------------------------------------------------------------------------


def _native_K(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> np.ndarray:
    """The estimate's K at the truth's image size (scaled with the pixel-centre rule when they differ)."""
    from nocal_ros.lens import scale_intrinsics

    K = estimate.K() if callable(getattr(estimate, "K", None)) else np.asarray(estimate.K, dtype=np.float64)
    if (estimate.width, estimate.height) != (truth.width, truth.height):
        K = scale_intrinsics(K, truth.width / estimate.width, truth.height / estimate.height)
    return K


def focal_error(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> dict[str, float]:
    """``|f_est - f_true|`` in native pixels and percent, for fx, fy and their mean."""
    K = _native_K(estimate, truth)
    fx_px, fy_px = abs(K[0, 0] - truth.fx), abs(K[1, 1] - truth.fy)
    return {
        "fx_est": float(K[0, 0]),
        "fy_est": float(K[1, 1]),
        "fx_true": truth.fx,
        "fy_true": truth.fy,
        "fx_px": float(fx_px),
        "fy_px": float(fy_px),
        "fx_percent": float(100.0 * fx_px / truth.fx),
        "fy_percent": float(100.0 * fy_px / truth.fy),
        "mean_px": float((fx_px + fy_px) / 2.0),
        "mean_percent": float(50.0 * (fx_px / truth.fx + fy_px / truth.fy)),
    }


def principal_point_error(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> dict[str, float]:
    """``|c_est - c_true|`` per axis and the Euclidean distance, in native pixels."""
    K = _native_K(estimate, truth)
    dx, dy = K[0, 2] - truth.cx, K[1, 2] - truth.cy
    return {
        "cx_est": float(K[0, 2]),
        "cy_est": float(K[1, 2]),
        "cx_true": truth.cx,
        "cy_true": truth.cy,
        "cx_px": float(abs(dx)),
        "cy_px": float(abs(dy)),
        "distance_px": float(math.hypot(dx, dy)),
    }


def undistorted_grid(camera: "CameraModel | CameraCalibration", width: int, height: int, step: int = 1) -> np.ndarray:
    """Undistorted normalised points ``(N, 2)`` of every ``step``-th pixel (each axis) of a ``width x height`` image.

    For a learnt camera of another native size the pixels are mapped with the pixel-centre rule.
    NaN where a parametric lens maps nothing to the pixel.
    """
    v, u = np.mgrid[0:height:step, 0:width:step].astype(np.float64)
    u, v = u.ravel(), v.ravel()
    if hasattr(camera, "float64_copy"):  # CameraModel
        import torch

        model = camera.float64_copy()
        u_native = (u + 0.5) * (camera.width / width) - 0.5
        v_native = (v + 0.5) * (camera.height / height) - 0.5
        with torch.no_grad():
            return model.undistorted_normalised(torch.from_numpy(u_native), torch.from_numpy(v_native)).numpy()
    calibration = camera if (camera.width, camera.height) == (width, height) else camera.scaled(width, height)
    return np.asarray(calibration.undistorted_normalised(np.stack((u, v), -1)), dtype=np.float64)


def radial_shift(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration", step: int = 1) -> dict[str, float]:
    """Statistics of the per-pixel shift ``|(x, y)_est - (x, y)_true|`` over the truth's native grid
    (every ``step``-th pixel on each axis; 1: every pixel, DESIGN.md's ``dr``)."""
    true_xy = undistorted_grid(truth, truth.width, truth.height, step)
    est_xy = undistorted_grid(estimate, truth.width, truth.height, step)
    shift = np.linalg.norm(est_xy - true_xy, axis=-1)
    valid = np.isfinite(shift)
    if not valid.any():
        raise ValueError("no pixel has a finite undistorted point in both cameras")
    shift = shift[valid]
    return {
        "mean": float(shift.mean()),
        "rms": float(np.sqrt(np.mean(shift**2))),
        "max": float(shift.max()),
        "mean_px": float(shift.mean() * (truth.fx + truth.fy) / 2.0),
        "valid_fraction": float(valid.mean()),
    }


def mean_radial_shift(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> float:
    """DESIGN.md's ``dr``: mean over native pixels of the undistorted-point distance (normalised units)."""
    return radial_shift(estimate, truth)["mean"]


def calibration_errors(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> dict[str, Any]:
    """All camera metrics as one flat JSON-serialisable dict (native pixels; ``dr`` in normalised units).

    Headline keys: ``focal_error_px`` / ``focal_error_percent`` (mean of fx and fy),
    ``principal_point_error_px`` (distance) and ``dr`` (mean radial shift).
    """
    focal = focal_error(estimate, truth)
    principal = principal_point_error(estimate, truth)
    shift = radial_shift(estimate, truth)
    return {
        "focal_error_px": focal["mean_px"],
        "focal_error_percent": focal["mean_percent"],
        "principal_point_error_px": principal["distance_px"],
        "dr": shift["mean"],
        "dr_rms": shift["rms"],
        "dr_max": shift["max"],
        "dr_px": shift["mean_px"],
        "dr_valid_fraction": shift["valid_fraction"],
        **{k: focal[k] for k in ("fx_est", "fy_est", "fx_true", "fy_true")},
        "fx_error_px": focal["fx_px"],
        "fy_error_px": focal["fy_px"],
        **{k: principal[k] for k in ("cx_est", "cy_est", "cx_true", "cy_true")},
        "cx_error_px": principal["cx_px"],
        "cy_error_px": principal["cy_px"],
    }


# --------------------------------------------------------------------------------------------------
# odometry
# --------------------------------------------------------------------------------------------------


def _check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    poses = np.array(poses, dtype=np.float64)  # a copy: evo's align works in place
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must be (N, 4, 4), got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError(f"{name} holds non-finite values")
    return poses


def _statistics(errors: np.ndarray) -> dict[str, float]:
    errors = np.asarray(errors, dtype=np.float64)
    return {
        "mean": float(errors.mean()),
        "std": float(errors.std()),
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "median": float(np.median(errors)),
        "max": float(errors.max()),
        "count": int(errors.size),
    }


def integrate_relative_poses(relative: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Chain relative poses ``T_ci_ci+1`` ``(M, 4, 4)`` into a trajectory ``T_w_ci`` ``(M + 1, 4, 4)``.

    Each relative rotation is first replaced by its nearest rotation matrix (SVD): the pose head's
    float32 rotations are orthonormal to ~1e-7 only, and chaining ~100 of them exceeded evo's 1e-6 SO(3)
    tolerance, so RPE/APE raised "not a valid SO(3) group element" on a 200-frame bag.
    """
    relative = _check_poses(relative, "relative poses")
    relative[:, :3, :3] = nearest_rotation(relative[:, :3, :3])
    trajectory = np.empty((len(relative) + 1, 4, 4))
    trajectory[0] = np.eye(4) if start is None else start
    for i, T in enumerate(relative):
        trajectory[i + 1] = trajectory[i] @ T
    return trajectory


def relative_pose_error(
    estimate: np.ndarray, truth: np.ndarray, delta: int = 1, correct_scale: bool = False
) -> dict[str, Any]:
    """RPE between trajectories ``T_w_c`` ``(N, 4, 4)`` over pairs ``(i, i + delta)``, with evo.

    Per pair ``E = inv(inv(Q_i) Q_j) inv(P_i) P_j``; translation ``|t(E)|`` in metres and rotation
    ``angle(E)`` in degrees. ``correct_scale`` first aligns a (monocular, scale-free) estimate to the
    truth with a similarity (Umeyama with scale), as ``evo_rpe --correct_scale`` does.
    """
    metrics, trajectory = _evo()
    estimate = _check_poses(estimate, "estimated poses")
    truth = _check_poses(truth, "true poses")
    if len(estimate) != len(truth):
        raise ValueError(f"trajectories differ in length: {len(estimate)} estimated, {len(truth)} true poses")
    if len(truth) <= delta:
        raise ValueError(f"need more than {delta} poses for pairs {delta} apart, got {len(truth)}")
    reference = trajectory.PosePath3D(poses_se3=list(truth))
    estimated = trajectory.PosePath3D(poses_se3=list(estimate))
    scale = 1.0
    if correct_scale:
        _, _, scale = estimated.align(reference, correct_scale=True)
    result: dict[str, Any] = {"delta": int(delta), "correct_scale": bool(correct_scale), "scale": float(scale)}
    for key, relation in (("translation_m", metrics.PoseRelation.translation_part), ("rotation_deg", metrics.PoseRelation.rotation_angle_deg)):
        metric = metrics.RPE(relation, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=False)
        metric.process_data((reference, estimated))
        result[key] = _statistics(metric.error)
        result[key + "_per_pair"] = [float(e) for e in metric.error]
    return result


def relative_pose_error_of_pairs(predicted: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """RPE of predicted relative poses ``T_ci_cj`` ``(M, 4, 4)`` for consecutive frames of ``truth`` ``(M + 1, 4, 4)``.

    Integrating the predictions from the first true pose gives a trajectory whose consecutive relative
    poses are exactly the predictions, so evo's delta-1 RPE is the per-pair error.
    """
    truth = _check_poses(truth, "true poses")
    if len(predicted) != len(truth) - 1:
        raise ValueError(f"{len(predicted)} predicted pairs for {len(truth)} true poses; expected {len(truth) - 1}")
    return relative_pose_error(integrate_relative_poses(predicted, start=truth[0]), truth, delta=1)


#: Chi-square, 3 degrees of freedom, 99 %: a consistent estimator's normalised rotation errors stay
#: below it on 99 % of pairs.
CHI2_3DOF_99 = 11.345


def rotation_consistency(estimate: np.ndarray, truth: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    """How well the reported rotation covariance of each step describes its error (NEES).

    For consecutive poses ``T_w_c`` ``(N, 4, 4)`` and each step's ``(3, 3)`` rotation covariance in the
    later camera's frame ``(N - 1, 3, 3)`` (right perturbation, rad^2), the error ``e = log(R_true^T R_est)``
    of the step's rotation is normalised, ``e^T C^-1 e``: 3 on average for a consistent estimator, more
    for an overconfident one. Steps whose covariance is not finite and positive definite are skipped.

    Returns ``{"pairs", "mean_nees", "median_nees", "within_99"}`` (the share below :data:`CHI2_3DOF_99`).
    """
    from nocal_ros.geometry import so3_log

    def rotation_error(step_est: np.ndarray, step_true: np.ndarray) -> np.ndarray:
        return so3_log(step_true[:3, :3].T @ step_est[:3, :3])

    return _step_consistency(estimate, truth, covariances, rotation_error)


def translation_consistency(estimate: np.ndarray, truth: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    """How well the reported translation covariance of each step describes its error (NEES), as
    :func:`rotation_consistency` does for the rotation.

    The error of a step ``T_ij`` is its translation in the true step's frame, ``R_true^T (t_est - t_true)``
    (the translation part of ``T_true^-1 T_est``, right perturbation, m); each covariance ``(3, 3)`` is
    in the later camera's frame (m^2). A step whose length is off by a scale error ``s`` has
    ``|e| = s |t|``, so a covariance that leaves out the scale's uncertainty is overconfident wherever the
    scale is guessed.
    """

    def translation_error(step_est: np.ndarray, step_true: np.ndarray) -> np.ndarray:
        return step_true[:3, :3].T @ (step_est[:3, 3] - step_true[:3, 3])

    return _step_consistency(estimate, truth, covariances, translation_error)


def _step_consistency(estimate: np.ndarray, truth: np.ndarray, covariances: np.ndarray, error: Any) -> dict[str, Any]:
    from nocal_ros.geometry import relative_transform

    estimate = _check_poses(estimate, "estimated poses")
    truth = _check_poses(truth, "true poses")
    covariances = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    if len(estimate) != len(truth) or len(covariances) != len(truth) - 1:
        raise ValueError(f"{len(estimate)} estimated and {len(truth)} true poses need {len(truth) - 1} step covariances, "
                         f"got {len(covariances)}")
    nees = []
    for k, C in enumerate(covariances):
        if not np.isfinite(C).all() or np.linalg.eigvalsh(0.5 * (C + C.T)).min() <= 0:
            continue
        e = error(relative_transform(estimate[k], estimate[k + 1]), relative_transform(truth[k], truth[k + 1]))
        nees.append(float(e @ np.linalg.solve(C, e)))
    if not nees:
        return {"pairs": 0}
    values = np.array(nees)
    return {"pairs": int(len(values)), "mean_nees": float(values.mean()), "median_nees": float(np.median(values)),
            "within_99": float(np.mean(values < CHI2_3DOF_99))}


def absolute_pose_error(estimate: np.ndarray, truth: np.ndarray, correct_scale: bool = False,
                        align: bool = True) -> dict[str, Any]:
    """APE after Umeyama alignment of the estimate to the truth (``correct_scale``: similarity, else SE(3)).

    ``align=False``: the poses as they are, already in one frame (odometry and truth both starting at the
    first pose): the error a consumer of the poses meets, with no fit to the truth.

    The alignment is undefined when the positions do not span a plane (a still camera, a straight line):
    Umeyama's cross-covariance then has rank below 2. The result says so, ``{"correct_scale",
    "undefined": reason}`` with no error statistics, rather than raising: the other errors still stand.
    """
    metrics, trajectory = _evo()
    from evo.core.geometry import GeometryException

    estimate = _check_poses(estimate, "estimated poses")
    truth = _check_poses(truth, "true poses")
    if len(estimate) != len(truth):
        raise ValueError(f"trajectories differ in length: {len(estimate)} estimated, {len(truth)} true poses")
    if len(truth) < 3:
        raise ValueError(f"alignment needs at least 3 poses, got {len(truth)}")
    reference = trajectory.PosePath3D(poses_se3=list(truth))
    estimated = trajectory.PosePath3D(poses_se3=list(estimate))
    result: dict[str, Any] = {"correct_scale": bool(correct_scale) and align, "aligned": bool(align)}
    if align:
        try:
            rotation, translation, scale = estimated.align(reference, correct_scale=correct_scale)
        except GeometryException as error:
            return {"correct_scale": bool(correct_scale), "aligned": True,
                    "undefined": f"alignment undefined: {error} (the positions do not span a plane: still or straight-line motion)"}
        result["scale"] = float(scale)
        result["alignment"] = [[float(x) for x in row] for row in np.vstack((np.column_stack((rotation, translation)), [0, 0, 0, 1]))]
    for key, relation in (("translation_m", metrics.PoseRelation.translation_part), ("rotation_deg", metrics.PoseRelation.rotation_angle_deg)):
        metric = metrics.APE(relation)
        metric.process_data((reference, estimated))
        result[key] = _statistics(metric.error)
        result[key + "_per_pose"] = [float(e) for e in metric.error]
    # APE is quoted as a position error: its translation statistics (metres) also sit at the top level.
    result.update(result["translation_m"])
    return result


def trajectory_errors(stamps_ns: np.ndarray | None, estimate: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """RPE per consecutive pair (metric, no alignment) plus APE with SE(3) and Sim(3) alignment.

    ``estimate`` and ``truth`` are camera poses ``(N, 4, 4)`` at the same ``stamps_ns`` (or None).
    """
    truth = _check_poses(truth, "true poses")
    positions = truth[:, :3, 3]
    result: dict[str, Any] = {
        "poses": int(len(truth)),
        "path_length_m": float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()),
    }
    if stamps_ns is not None and len(stamps_ns) == len(truth):
        result["duration_s"] = float((int(stamps_ns[-1]) - int(stamps_ns[0])) * 1e-9)
    result["rpe"] = relative_pose_error(estimate, truth, delta=1)
    if len(truth) >= 3:
        result["ape_se3"] = absolute_pose_error(estimate, truth, correct_scale=False)
        result["ape_sim3"] = absolute_pose_error(estimate, truth, correct_scale=True)
    return result


# --------------------------------------------------------------------------------------------------
# report: table and plot
# --------------------------------------------------------------------------------------------------


def _without_series(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_series(v) for k, v in value.items() if not (k.endswith("_per_pair") or k.endswith("_per_pose"))}
    return value


def format_report(report: dict[str, Any]) -> str:
    """A plain-text table of a report holding ``calibration`` (:func:`calibration_errors`) and/or the
    ``rpe`` / ``ape_se3`` / ``ape_sim3`` parts of :func:`trajectory_errors`, plus scalar facts."""
    lines: list[str] = []
    c = report.get("calibration")
    if c:
        lines += [
            "camera                     estimate        truth        error",
            f"  fx (px)              {c['fx_est']:>11.2f} {c['fx_true']:>12.2f} {c['fx_error_px']:>12.2f}",
            f"  fy (px)              {c['fy_est']:>11.2f} {c['fy_true']:>12.2f} {c['fy_error_px']:>12.2f}",
            f"  cx (px)              {c['cx_est']:>11.2f} {c['cx_true']:>12.2f} {c['cx_error_px']:>12.2f}",
            f"  cy (px)              {c['cy_est']:>11.2f} {c['cy_true']:>12.2f} {c['cy_error_px']:>12.2f}",
            f"  focal error          {c['focal_error_px']:>11.2f} px ({c['focal_error_percent']:.2f} %)",
            f"  mean radial shift dr {c['dr']:>11.5f} (normalised; about {c['dr_px']:.2f} px; max {c['dr_max']:.5f})",
        ]
        if "fit_residual_px" in c:
            lines.append(f"  {c.get('distortion_model', 'parametric')} fit residual {c['fit_residual_px']:.3f} px RMS")
    history = report.get("calibration_history")
    if history:
        # The start, the end and a few keyframes between: how the online camera converged.
        picks = sorted({round(i) for i in np.linspace(0, len(history) - 1, min(len(history), 6))})
        lines.append("  focal error over the replay: " + ", ".join(
            f"frame {history[i]['frame']} {history[i]['focal_error_percent']:.2f} %" for i in picks))
    rows = [(key, label) for key, label in (("rpe", "RPE"), ("ape_se3", "APE SE(3)"), ("ape_sim3", "APE Sim(3)"),
                                            ("ape_unaligned", "APE unaligned")) if report.get(key)]
    if rows:
        lines.append("odometry                        mean        std       rmse        max    count")
        for key, label in rows:
            if report[key].get("undefined"):
                lines.append(f"  {label:<22} {report[key]['undefined']}")
                continue
            for unit_key, unit in (("translation_m", "m"), ("rotation_deg", "deg")):
                st = report[key][unit_key]
                lines.append(
                    f"  {label + ' ' + unit:<22} {st['mean']:>10.4f} {st['std']:>10.4f} {st['rmse']:>10.4f} {st['max']:>10.4f} {st['count']:>8d}"
                )
        tracked = report.get("rpe_tracked")
        if tracked and "rotation_deg" in tracked:
            for unit_key, unit in (("translation_m", "m"), ("rotation_deg", "deg")):
                st = tracked[unit_key]
                lines.append(f"  {'RPE tracked ' + unit:<22} {st['mean']:>10.4f} {'':>10} {st['rmse']:>10.4f} {st['max']:>10.4f} "
                             f"{tracked['pairs']:>8d}  (pairs of tracked frames)")
        if report.get("ape_sim3") and "scale" in report["ape_sim3"]:
            lines.append(f"  Sim(3) alignment scale {report['ape_sim3']['scale']:>10.4f}")
        for part in ("rotation", "translation"):
            consistency = report.get(f"{part}_consistency")
            if consistency and consistency.get("pairs"):
                lines.append(f"  {part} NEES {consistency['mean_nees']:>10.2f} mean, {consistency['median_nees']:.2f} median "
                             f"(3 when the covariance is consistent); {100 * consistency['within_99']:.1f} % of "
                             f"{consistency['pairs']} steps within the 99 % bound")
    for key, label in (("tracking", "tracking"), ("scale_source", "scale from")):
        if isinstance(report.get(key), dict):
            lines.append(f"{label}: " + ", ".join(f"{k} {v}" for k, v in report[key].items()))
    facts = [f"{k}: {v}" for k, v in report.items() if not isinstance(v, (dict, list)) and v is not None]
    return "\n".join(facts + lines)


def print_report(report: dict[str, Any]) -> None:
    """Print :func:`format_report`'s table."""
    print(format_report(report))


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """The report without per-pair series (for compact JSON)."""
    return _without_series(report)


def plot_trajectory(
    path: str | Path,
    stamps_ns: Sequence[int] | np.ndarray | None,
    estimate: np.ndarray,
    truth: np.ndarray,
    title: str = "",
    calibration_history: list[dict[str, Any]] | None = None,
    others: dict[str, np.ndarray] | None = None,
) -> Path:
    """PNG: top view of the estimate (after Sim(3) alignment) and the truth; position error after that
    alignment and the per-pair RPE over time; with ``calibration_history`` (rows with ``stamp_ns``,
    ``focal_error_percent`` and ``dr``), a third panel with the online camera's errors over time.
    ``others``: more estimates of the same frames (label -> poses) in the truth's frame (both starting at the
    first pose), drawn as they are (dashed, no alignment) with their position errors over time, beside the
    estimate's own error without alignment (dotted): for a metric estimate whose history is not revised,
    such as nocal odometry's map frame, where a fit to the truth would hide an offset odom carries.

    The top view shows the plane of the truth's two largest position extents (world frames differ in
    which axis is up). Uses matplotlib's Agg backend: no display needed.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    estimate = _check_poses(estimate, "estimated poses")
    truth = _check_poses(truth, "true poses")
    if len(estimate) != len(truth) or len(truth) < 3:
        raise ValueError(f"need two trajectories of the same length >= 3, got {len(estimate)} and {len(truth)} poses")
    others = {label: _check_poses(poses, label) for label, poses in (others or {}).items()}
    if any(len(poses) != len(truth) for poses in others.values()):
        raise ValueError(f"every estimate needs the truth's {len(truth)} poses: "
                         + ", ".join(f"{label} has {len(poses)}" for label, poses in others.items()))
    ape = absolute_pose_error(estimate, truth, correct_scale=True)
    if ape.get("undefined"):  # a still or straight-line truth: show the estimate as it is, from the shared start
        aligned = estimate[:, :3, 3]
        estimate_label = "estimate (not aligned: alignment undefined)"
        position_error = np.linalg.norm(aligned - truth[:, :3, 3], axis=1)
    else:
        alignment = np.array(ape["alignment"])
        aligned = ape["scale"] * estimate[:, :3, 3] @ alignment[:3, :3].T + alignment[:3, 3]
        estimate_label = f"estimate (Sim(3) aligned, scale {ape['scale']:.3f})"
        position_error = np.asarray(ape["translation_m_per_pose"])
    rpe = relative_pose_error(estimate, truth)
    if stamps_ns is None:
        time, time_label = np.arange(len(truth), dtype=np.float64), "frame"
    else:
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        time, time_label = (stamps - stamps[0]) * 1e-9, "time (s)"

    extent = truth[:, :3, 3].max(0) - truth[:, :3, 3].min(0)
    a, b = sorted(np.argsort(extent)[-2:])
    panels = 3 if calibration_history and stamps_ns is not None else 2
    figure, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4.5))
    top, error_axis = axes[0], axes[1]
    top.plot(truth[:, a, 3], truth[:, b, 3], "k-", label="truth")
    top.plot(aligned[:, a], aligned[:, b], "r-", label=estimate_label)
    other_errors = []
    for (label, poses), colour in zip(others.items(), ("tab:orange", "tab:purple", "tab:brown")):
        top.plot(poses[:, a, 3], poses[:, b, 3], "--", color=colour, label=f"{label} (not aligned)")
        other_errors.append((label, colour, np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)))
    top.plot(truth[0, a, 3], truth[0, b, 3], "ko")
    top.set_xlabel(f"{'xyz'[a]} (m)")
    top.set_ylabel(f"{'xyz'[b]} (m)")
    top.set_aspect("equal", adjustable="datalim")
    top.legend(fontsize="small")
    top.set_title("top view")
    error_axis.plot(time, position_error, "b-",
                    label="position error, " + ("unaligned" if ape.get("undefined") else "Sim(3) aligned"))
    if other_errors:
        error_axis.plot(time, np.linalg.norm(estimate[:, :3, 3] - truth[:, :3, 3], axis=1), "r:",
                        label="position error, not aligned")
    for label, colour, errors in other_errors:
        error_axis.plot(time, errors, "--", color=colour, label=f"{label}: position error, not aligned")
    error_axis.plot(time[1:], rpe["translation_m_per_pair"], "c-", label="RPE translation per pair")
    error_axis.set_xlabel(time_label)
    error_axis.set_ylabel("error (m)")
    error_axis.legend(fontsize="small", loc="upper left")
    rotation_axis = error_axis.twinx()
    rotation_axis.plot(time[1:], rpe["rotation_deg_per_pair"], "g-", alpha=0.6)
    rotation_axis.set_ylabel("RPE rotation per pair (deg)", color="g")
    error_axis.set_title("error over time")
    if panels == 3:
        camera_axis = axes[2]
        camera_time = (np.array([row["stamp_ns"] for row in calibration_history], dtype=np.int64) - stamps[0]) * 1e-9
        camera_axis.step(camera_time, [row["focal_error_percent"] for row in calibration_history], "m-", where="post",
                         label="focal error")
        camera_axis.set_yscale("symlog", linthresh=0.1)  # zero error (a given camera) stays drawable
        camera_axis.set_xlabel(time_label)
        camera_axis.set_ylabel("focal error (%)", color="m")
        dr_axis = camera_axis.twinx()
        dr_axis.step(camera_time, [row["dr"] for row in calibration_history], "y-", where="post")
        dr_axis.set_ylabel("mean radial shift dr", color="y")
        camera_axis.set_title("online calibration")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    from nocal_ros.files import atomic_path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as temporary:  # a full disk leaves no half PNG
            figure.savefig(temporary, dpi=100, format="png")
    finally:
        plt.close(figure)
    return path
