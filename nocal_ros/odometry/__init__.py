"""Monocular visual odometry through the learnt camera (no ROS here).

The odometry node, ``nocal odometry`` and ``nocal demo`` all feed frames to
:class:`~nocal_ros.odometry.estimator.OdometryEstimator`. Files, by thread of work:

* ``estimator.py``: the entry point: frames in, poses, twist and covariances out; scale and anchoring;
* ``tracking.py``: the tracking thread's state machine (initialising, ok, lost) and keyframe choice;
* ``frontend.py``: persistent corner tracks and PnP on rays through the online camera;
* ``initializer.py``: the first two keyframes and landmarks from two views;
* ``map.py``: keyframes, landmarks, triangulation;
* ``local_mapping.py``: the mapping thread: triangulation and windowed bundle adjustment;
* ``bundle_adjustment.py``: the solver, over keyframes, landmarks and the camera;
* ``calibration.py``: the online camera and the information it carries from window to window;
* ``scale.py``: metric scale from arm poses or the pose head;
* ``pose_head.py``: the NOCaL pose head and its runner;
* ``covariance.py``: pose covariance propagation;
* ``mailbox.py``: handing frames from a ROS executor to the worker thread.
"""

from __future__ import annotations

import importlib
from typing import Any

# Names are loaded on first use (PEP 562): the bundle adjustment's worker process imports
# ``nocal_ros.odometry.bundle_adjustment`` alone, and importing the estimator here would load torch
# there too (1.8 s of the first keyframe's solve, measured).
_EXPORTS = {
    "UNKNOWN_VARIANCE": "covariance", "adjoint": "covariance", "propagate_covariance": "covariance",
    "FrameError": "estimator", "FrameSizeError": "estimator", "OdometryCounters": "estimator",
    "OdometryEstimator": "estimator", "OdometryResult": "estimator", "fit_calibration": "estimator",
    "FrameMailbox": "mailbox", "RateReplay": "mailbox", "replay_at_rate": "mailbox",
    "DEFAULT_MAX_GAP": "pose_head", "DEFAULT_POSE_ERROR_STD": "pose_head", "PoseModel": "pose_head",
    "PoseRunner": "pose_head", "resolve_device": "pose_head",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
