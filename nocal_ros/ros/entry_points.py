"""The ROS executables (``odometry_node``, ``trainer_node``): setup.py's console scripts call these.

Each imports its node only when called. Why: a process started by spawning (local mapping's solver, the
trainer's fine-tuning job) first runs the parent's main script again, every top-level import with it,
and an executable's script is ``from <module> import <function>``. With the node's module there (rclpy,
torch and the message packages), the odometry node's solver process answered its first bundle
adjustment 3.7 s after it was started instead of 0.9 s (VAMR replayed at 30 Hz through the estimator,
torch and the estimator imported by the main script, rclpy not even among them; two runs each), and
the map's first keyframes waited for it.
"""

from __future__ import annotations


def odometry_node(args: list[str] | None = None) -> int:
    """``ros2 run nocal_ros odometry_node``: :func:`nocal_ros.ros.odometry_node.main`."""
    from nocal_ros.ros.odometry_node import main

    return main(args)


def trainer_node(args: list[str] | None = None) -> int:
    """``ros2 run nocal_ros trainer_node``: :func:`nocal_ros.ros.trainer_node.main`."""
    from nocal_ros.ros.trainer_node import main

    return main(args)
