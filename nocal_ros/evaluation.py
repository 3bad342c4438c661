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
from nocal_ros.geometry import invert_transform, relative_transform, rotation_angle_deg

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


def undistorted_grid(camera: "CameraModel | CameraCalibration", width: int, height: int) -> np.ndarray:
    """Undistorted normalised points ``(H * W, 2)`` of every pixel of a ``width x height`` image.

    For a learnt camera of another native size the pixels are mapped with the pixel-centre rule.
    NaN where a parametric lens maps nothing to the pixel.
    """
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
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


def radial_shift(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> dict[str, float]:
    """Statistics of the per-pixel shift ``|(x, y)_est - (x, y)_true|`` over the truth's native grid."""
    true_xy = undistorted_grid(truth, truth.width, truth.height)
    est_xy = undistorted_grid(estimate, truth.width, truth.height)
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


def camera_errors(estimate: "CameraModel | CameraCalibration", truth: "CameraCalibration") -> dict[str, Any]:
    """All camera metrics in one JSON-serialisable dict."""
    return {
        "focal": focal_error(estimate, truth),
        "principal_point": principal_point_error(estimate, truth),
        "radial_shift": radial_shift(estimate, truth),
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
    """Chain relative poses ``T_ci_ci+1`` ``(M, 4, 4)`` into a trajectory ``T_w_ci`` ``(M + 1, 4, 4)``."""
    relative = _check_poses(relative, "relative poses")
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


def absolute_pose_error(estimate: np.ndarray, truth: np.ndarray, correct_scale: bool = False) -> dict[str, Any]:
    """APE after Umeyama alignment of the estimate to the truth (``correct_scale``: similarity, else SE(3))."""
    metrics, trajectory = _evo()
    estimate = _check_poses(estimate, "estimated poses")
    truth = _check_poses(truth, "true poses")
    if len(estimate) != len(truth):
        raise ValueError(f"trajectories differ in length: {len(estimate)} estimated, {len(truth)} true poses")
    if len(truth) < 3:
        raise ValueError(f"alignment needs at least 3 poses, got {len(truth)}")
    reference = trajectory.PosePath3D(poses_se3=list(truth))
    estimated = trajectory.PosePath3D(poses_se3=list(estimate))
    rotation, translation, scale = estimated.align(reference, correct_scale=correct_scale)
    result: dict[str, Any] = {
        "correct_scale": bool(correct_scale),
        "scale": float(scale),
        "alignment": [[float(x) for x in row] for row in np.vstack((np.column_stack((rotation, translation)), [0, 0, 0, 1]))],
    }
    for key, relation in (("translation_m", metrics.PoseRelation.translation_part), ("rotation_deg", metrics.PoseRelation.rotation_angle_deg)):
        metric = metrics.APE(relation)
        metric.process_data((reference, estimated))
        result[key] = _statistics(metric.error)
        result[key + "_per_pose"] = [float(e) for e in metric.error]
    return result


def odometry_errors(estimate: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """RPE (delta 1, metric) plus APE with SE(3) and Sim(3) alignment for one trajectory."""
    return {
        "rpe": relative_pose_error(estimate, truth, delta=1),
        "ape_se3": absolute_pose_error(estimate, truth, correct_scale=False),
        "ape_sim3": absolute_pose_error(estimate, truth, correct_scale=True),
    }


# --------------------------------------------------------------------------------------------------
# report: table and plot
# --------------------------------------------------------------------------------------------------


def _without_series(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_series(v) for k, v in value.items() if not (k.endswith("_per_pair") or k.endswith("_per_pose"))}
    return value


def format_report(report: dict[str, Any]) -> str:
    """A plain-text table of a report made of :func:`camera_errors` / :func:`odometry_errors` parts."""
    lines: list[str] = []
    camera = report.get("camera")
    if camera:
        focal, principal, shift = camera["focal"], camera["principal_point"], camera["radial_shift"]
        lines += [
            "camera                      estimate        truth        error",
            f"  fx (px)               {focal['fx_est']:>12.2f} {focal['fx_true']:>12.2f} {focal['fx_px']:>9.2f} ({focal['fx_percent']:.2f} %)",
            f"  fy (px)               {focal['fy_est']:>12.2f} {focal['fy_true']:>12.2f} {focal['fy_px']:>9.2f} ({focal['fy_percent']:.2f} %)",
            f"  cx (px)               {principal['cx_est']:>12.2f} {principal['cx_true']:>12.2f} {principal['cx_px']:>9.2f}",
            f"  cy (px)               {principal['cy_est']:>12.2f} {principal['cy_true']:>12.2f} {principal['cy_px']:>9.2f}",
            f"  mean radial shift dr  {shift['mean']:>12.5f} (normalised units; about {shift['mean_px']:.2f} px; max {shift['max']:.5f})",
        ]
    odometry = report.get("odometry")
    if odometry:
        lines.append("odometry                         mean        std       rmse        max      count")
        rows = [("rpe", "RPE"), ("ape_se3", "APE SE(3)"), ("ape_sim3", "APE Sim(3)")]
        for key, label in rows:
            if key not in odometry:
                continue
            for unit_key, unit in (("translation_m", "m"), ("rotation_deg", "deg")):
                s = odometry[key][unit_key]
                lines.append(
                    f"  {label + ' ' + unit:<24} {s['mean']:>10.4f} {s['std']:>10.4f} {s['rmse']:>10.4f} {s['max']:>10.4f} {s['count']:>10d}"
                )
            if key == "ape_sim3":
                lines.append(f"  {'Sim(3) scale':<24} {odometry[key]['scale']:>10.4f}")
    for key, value in report.items():
        if key not in ("camera", "odometry") and not isinstance(value, (dict, list)):
            lines.append(f"{key}: {value}")
    return "\n".join(lines)


def print_report(report: dict[str, Any]) -> None:
    """Print :func:`format_report`'s table."""
    print(format_report(report))


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """The report without per-pair series (for compact JSON)."""
    return _without_series(report)


def plot_trajectory(
    estimate: np.ndarray,
    truth: np.ndarray,
    path: str | Path,
    stamps_s: Sequence[float] | None = None,
    title: str = "",
) -> Path:
    """PNG with the top view of estimate and truth, and the per-pair RPE over time.

    The top view shows the plane of the truth's two largest position extents (world frames differ
    in which axis is up). Uses matplotlib's Agg backend: no display needed.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    estimate = _check_poses(estimate, "estimated poses")
    truth = _check_poses(truth, "true poses")
    if len(estimate) != len(truth):
        raise ValueError(f"trajectories differ in length: {len(estimate)} estimated, {len(truth)} true poses")
    errors = [relative_transform(truth[i], truth[i + 1]) for i in range(len(truth) - 1)]
    predicted = [relative_transform(estimate[i], estimate[i + 1]) for i in range(len(estimate) - 1)]
    pair_errors = [invert_transform(q) @ p for q, p in zip(errors, predicted)]
    translation_error = np.array([np.linalg.norm(e[:3, 3]) for e in pair_errors])
    rotation_error = np.array([rotation_angle_deg(e[:3, :3]) for e in pair_errors])
    time = np.arange(1, len(truth)) if stamps_s is None else np.asarray(stamps_s, dtype=np.float64)[1:]

    extent = truth[:, :3, 3].max(0) - truth[:, :3, 3].min(0)
    a, b = sorted(np.argsort(extent)[-2:])
    axis_names = "xyz"
    figure, (top, error_axis) = plt.subplots(1, 2, figsize=(11, 4.5))
    top.plot(truth[:, a, 3], truth[:, b, 3], "k-", label="truth")
    top.plot(estimate[:, a, 3], estimate[:, b, 3], "r-", label="estimate")
    top.plot(truth[0, a, 3], truth[0, b, 3], "ko")
    top.set_xlabel(f"{axis_names[a]} (m)")
    top.set_ylabel(f"{axis_names[b]} (m)")
    top.set_aspect("equal", adjustable="datalim")
    top.legend()
    top.set_title("top view")
    error_axis.plot(time, translation_error, "b-")
    error_axis.set_xlabel("frame" if stamps_s is None else "time (s)")
    error_axis.set_ylabel("RPE translation (m)", color="b")
    rotation_axis = error_axis.twinx()
    rotation_axis.plot(time, rotation_error, "g-")
    rotation_axis.set_ylabel("RPE rotation (deg)", color="g")
    error_axis.set_title("per-pair error")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path
