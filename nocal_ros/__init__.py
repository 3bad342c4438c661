"""nocal_ros: visual odometry and camera calibration from an uncalibrated camera (NOCaL)."""

__version__ = "0.1.0"
