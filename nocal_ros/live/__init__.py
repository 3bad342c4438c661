"""What the live ROS nodes decide, without ROS: the rclpy nodes in ``nocal_ros.ros`` are thin shells over these.

* ``calibration_url.py``: camera_info_manager's calibration URLs (``file://``, ``package://``, ``${NAME}``,
  ``${ROS_HOME}``) and loading / saving the calibration YAML they point at;
* ``arm_poses.py``: the hand-eye transform, and image stamps waiting for their TF arm pose;
* ``health.py``: the odometry node's diagnostics (rate, delay and age against the image stamps, levels);
* ``recorder.py``: the trainer node's live recording of images and arm poses into a bounded rosbag2;
* ``trainer.py``: the trainer node's progress records and diagnostics summary.

Nothing here imports rclpy, so all of it is tested on every CI run.
"""
