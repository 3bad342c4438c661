"""rclpy messages <-> numpy for the nodes. Needs the ROS 2 message packages (rclpy installs them).

Image decoding is not here: :func:`nocal_ros.data.bags.decode_image` reads any object with the
``sensor_msgs/Image`` fields, so bags and live nodes share one decoder.
"""

from __future__ import annotations

import array
import sys
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseStamped, Quaternion, Transform, TransformStamped, Vector3
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import CameraInfo, PointCloud2, PointField, RegionOfInterest
from std_msgs.msg import Header

from nocal_ros.data.bags import decode_compressed_image, decode_image, stamp_to_ns, transform_msg_to_matrix
from nocal_ros.geometry import matrix_to_quaternion

__all__ = [
    "camera_info_message",
    "decode_compressed_image",
    "decode_image",
    "diagnostic_status",
    "matrix_to_pose",
    "matrix_to_transform",
    "ns_to_stamp",
    "odometry_message",
    "path_message",
    "point_cloud_message",
    "stamp_to_ns",
    "transform_msg_to_matrix",
    "transform_stamped",
]


def ns_to_stamp(stamp_ns: int) -> Time:
    """Nanoseconds -> ``builtin_interfaces/Time``."""
    seconds, nanoseconds = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=seconds, nanosec=nanoseconds)


def _quaternion(T: np.ndarray) -> Quaternion:
    x, y, z, w = matrix_to_quaternion(T[:3, :3])
    return Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def matrix_to_pose(T: np.ndarray) -> Pose:
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation = _quaternion(T)
    return pose


def matrix_to_transform(T: np.ndarray) -> Transform:
    x, y, z = (float(v) for v in T[:3, 3])
    return Transform(translation=Vector3(x=x, y=y, z=z), rotation=_quaternion(T))


def transform_stamped(T: np.ndarray, stamp: Time, parent: str, child: str) -> TransformStamped:
    """``T_parent_child`` as a TF edge ``parent -> child``."""
    return TransformStamped(header=Header(stamp=stamp, frame_id=parent), child_frame_id=child, transform=matrix_to_transform(T))


def odometry_message(result: Any, stamp: Time, odom_frame: str, base_frame: str) -> Odometry:
    """``nav_msgs/Odometry`` from an :class:`~nocal_ros.odometry.OdometryResult` (pose in ``odom_frame``,
    twist in ``base_frame``, row-major 6x6 covariances)."""
    msg = Odometry(header=Header(stamp=stamp, frame_id=odom_frame), child_frame_id=base_frame)
    msg.pose.pose = matrix_to_pose(result.T_odom_base)
    msg.pose.covariance = [float(v) for v in np.asarray(result.pose_covariance).reshape(36)]
    twist = np.asarray(result.twist, dtype=np.float64)
    msg.twist.twist.linear = Vector3(x=float(twist[0]), y=float(twist[1]), z=float(twist[2]))
    msg.twist.twist.angular = Vector3(x=float(twist[3]), y=float(twist[4]), z=float(twist[5]))
    msg.twist.covariance = [float(v) for v in np.asarray(result.twist_covariance).reshape(36)]
    return msg


def path_message(stamps_ns: np.ndarray, poses: np.ndarray, header: Header) -> Path:
    """``nav_msgs/Path`` of poses ``(N, 4, 4)`` in ``header.frame_id``, each stamped with its own stamp."""
    return Path(header=header, poses=[
        PoseStamped(header=Header(stamp=ns_to_stamp(stamp), frame_id=header.frame_id), pose=matrix_to_pose(T))
        for stamp, T in zip(np.asarray(stamps_ns).tolist(), np.asarray(poses).reshape(-1, 4, 4))
    ])


def point_cloud_message(points: np.ndarray, header: Header) -> PointCloud2:
    """``sensor_msgs/PointCloud2`` of points ``(N, 3)`` in ``header.frame_id``: one row of x, y, z float32."""
    xyz = np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
    fields = [PointField(name=name, offset=4 * k, datatype=PointField.FLOAT32, count=1) for k, name in enumerate("xyz")]
    return PointCloud2(header=header, height=1, width=len(xyz), fields=fields, is_bigendian=sys.byteorder == "big",
                       point_step=12, row_step=12 * len(xyz), data=array.array("B", xyz.tobytes()),
                       is_dense=bool(np.isfinite(xyz).all()))


def camera_info_message(calibration: Any, header: Header) -> CameraInfo:
    """``sensor_msgs/CameraInfo`` of a :class:`~nocal_ros.lens.CameraCalibration`, full size, with its R and
    P (the identity and ``[K | 0]`` for a monocular camera that is not rectified)."""
    K = np.asarray(calibration.K, dtype=np.float64).reshape(3, 3)
    P = np.asarray(calibration.projection, dtype=np.float64).reshape(3, 4)
    return CameraInfo(
        header=header,
        height=int(calibration.height),
        width=int(calibration.width),
        distortion_model=str(calibration.distortion_model),
        d=[float(v) for v in np.asarray(calibration.D).reshape(-1)],
        k=[float(v) for v in K.reshape(-1)],
        r=[float(v) for v in np.asarray(calibration.rectification, dtype=np.float64).reshape(-1)],
        p=[float(v) for v in P.reshape(-1)],
        binning_x=0,
        binning_y=0,
        roi=RegionOfInterest(),
    )


def diagnostic_status(name: str, hardware_id: str, level: int, message: str, values: dict[str, Any]) -> DiagnosticStatus:
    """A ``DiagnosticStatus`` with ``values`` as key/value strings (floats with 3 decimals)."""
    def text(value: Any) -> str:
        return f"{value:.3f}" if isinstance(value, float) else str(value)

    return DiagnosticStatus(
        level=bytes([level]) if isinstance(level, int) else level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=str(k), value=text(v)) for k, v in values.items()],
    )
