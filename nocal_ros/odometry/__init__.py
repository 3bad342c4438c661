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

from nocal_ros.odometry.covariance import UNKNOWN_VARIANCE, adjoint, propagate_covariance
from nocal_ros.odometry.estimator import (
    FrameError,
    FrameSizeError,
    OdometryCounters,
    OdometryEstimator,
    OdometryResult,
    fit_calibration,
)
from nocal_ros.odometry.mailbox import FrameMailbox
from nocal_ros.odometry.pose_head import DEFAULT_MAX_GAP, DEFAULT_POSE_ERROR_STD, PoseModel, PoseRunner, resolve_device

__all__ = [
    "DEFAULT_MAX_GAP",
    "DEFAULT_POSE_ERROR_STD",
    "FrameError",
    "FrameMailbox",
    "FrameSizeError",
    "OdometryCounters",
    "OdometryEstimator",
    "OdometryResult",
    "PoseModel",
    "PoseRunner",
    "UNKNOWN_VARIANCE",
    "adjoint",
    "fit_calibration",
    "propagate_covariance",
    "resolve_device",
]
