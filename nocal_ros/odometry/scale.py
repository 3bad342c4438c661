"""Metric scale for monocular VO: from arm poses by a similarity fit, else from the pose head.

A monocular map is correct up to one scale factor ``s`` (metres per map unit). Two sources measure it:

* **Arm poses** (a bag topic, or TF base -> tool on a live robot): the camera positions the arm reports
  at keyframes, against the same keyframes' map positions. A similarity (Umeyama) fit gives ``s``; it
  needs three keyframes with arm poses that do not all sit at one point. It is refitted at every
  keyframe, as the map's keyframes move and more arm poses arrive.
* **The NOCaL pose head**: trained with arm poses, it predicts a metric translation for a frame pair.
  The estimator measures it once, on the pair that defines the map's unit (its first two keyframes),
  and keeps it: a scale that changes mid-stream makes the trajectory inconsistent with itself, and more
  pose head pairs did not make it more accurate (measured on five held-out bags: its error is a bias
  per camera and scene, x1.3-4.4 there; APE Sim(3) 4.6 cm mean when kept, 7.8 cm when refined).

Arm poses win whenever a fit is possible; ``source`` says which was used.

Live, the fit moves the map's scale but not its shape, which drifts between arm poses. At the end of a
replay (:meth:`~nocal_ros.odometry.estimator.OdometryEstimator.final_trajectory`) a map with arm poses at
three or more keyframes is moved into the arm's frame by this fit and solved whole with the arm's
positions as factors (``WindowProblem.positions``), so the drift between them goes too (measured on
heldout_640, arm poses on 10 % of frames: Sim(3) alignment scale 0.26 live, 0.995 after).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Fewest keyframes with arm poses for a similarity fit.
MIN_ARM_KEYFRAMES = 3


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``target ~ s R source + t`` (Umeyama 1991): ``(s, R (3, 3), t (3,))``.

    ``source``, ``target``: ``(N, 3)`` corresponding points, ``N >= 3`` not all on one point.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    mean_s, mean_t = source.mean(0), target.mean(0)
    a, b = source - mean_s, target - mean_t
    variance_s = (a**2).sum() / len(a)
    if variance_s <= 0:
        raise ValueError("umeyama: the source points all coincide")
    covariance = b.T @ a / len(a)
    U, d, Vt = np.linalg.svd(covariance)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / variance_s) if with_scale else 1.0
    t = mean_t - s * R @ mean_s
    return s, R, t


@dataclass
class ScaleEstimate:
    """Metres per map unit and where it came from (``"arm"``, ``"pose_head"`` or ``"none"``)."""

    scale: float = 1.0
    source: str = "none"
    samples: int = 0


def fit_arm_similarity(map_positions: np.ndarray, arm_positions: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
    """``(s, R, t)`` with ``arm ~ s R map + t``, fitted to the camera positions (``(N, 3)`` each); None
    until possible (fewer than :data:`MIN_ARM_KEYFRAMES`, all at one point, or no positive scale)."""
    map_positions = np.asarray(map_positions, dtype=np.float64).reshape(-1, 3)
    arm_positions = np.asarray(arm_positions, dtype=np.float64).reshape(-1, 3)
    if len(map_positions) < MIN_ARM_KEYFRAMES:
        return None
    if np.linalg.norm(map_positions - map_positions.mean(0), axis=1).max() <= 1e-9:
        return None
    s, R, t = umeyama(map_positions, arm_positions)
    if not np.isfinite(s) or s <= 0:
        return None
    return s, R, t


def fit_arm_scale(map_positions: np.ndarray, arm_positions: np.ndarray) -> ScaleEstimate | None:
    """Similarity fit of the arm's camera positions to the map's (``(N, 3)`` each); None until possible."""
    similarity = fit_arm_similarity(map_positions, arm_positions)
    if similarity is None:
        return None
    return ScaleEstimate(similarity[0], "arm", len(np.asarray(map_positions).reshape(-1, 3)))
