"""Rosbag reading and writing without ROS: rosbag2 (mcap, sqlite3) and ROS 1 bags via ``rosbags``.

One decoder (:func:`decode_image`, :func:`decode_compressed_image`) serves bags and live nodes: it
reads any object with the ``sensor_msgs`` fields, so rosbags messages and rclpy messages alike.

Writing is atomic: a bag is written beside its destination and moved into place only when it is
complete, so an interrupted or failed write never leaves a half bag, and never replaces an existing
one unless asked to.

Reading turns a recording into a :class:`~nocal_ros.data.sequence.FrameSequence`: images decoded to
uint8 RGB, arm poses (``PoseStamped`` or TF, hand-eye applied) interpolated to image stamps, and the
ground truth and camera calibration when the bag has them. Every failure is a
:class:`~nocal_ros.errors.BagError` whose one-line message names the file and the problem.
"""

from __future__ import annotations

import bisect
import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nocal_ros.data.sequence import FrameSequence
from nocal_ros.errors import BagError, NocalError
from nocal_ros.geometry import (
    interpolate_transform,
    invert_transform,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
)

STORAGES = ("mcap", "sqlite3", "ros1")

# encoding -> (channels, bytes per channel); the decoder's whole vocabulary.
IMAGE_ENCODINGS: dict[str, tuple[int, int]] = {
    "rgb8": (3, 1),
    "bgr8": (3, 1),
    "rgba8": (4, 1),
    "bgra8": (4, 1),
    "mono8": (1, 1),
    "mono16": (1, 2),
}
COMPRESSED_FORMATS = ("jpeg", "png")

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED_TYPE = "geometry_msgs/msg/TransformStamped"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POSE_TYPES = (POSE_STAMPED_TYPE, POSE_COV_STAMPED_TYPE, TRANSFORM_STAMPED_TYPE)
TF_TOPICS = ("/tf", "/tf_static")

# The standard layout of a synthetic (or any nocal-written) sequence bag.
IMAGE_TOPIC = "/camera/image_raw"
ARM_POSE_TOPIC = "/arm/pose"
GT_POSE_TOPIC = "/ground_truth/pose"
CAMERA_INFO_TOPIC = "/ground_truth/camera_info"
CAMERA_FRAME = "camera_optical"
ARM_BASE_FRAME = "base"
WORLD_FRAME = "world"


def _typestore(ros1: bool = False):
    from rosbags.typesys import Stores, get_typestore

    if ros1:
        from rosbags.typesys import get_types_from_msg

        store = get_typestore(Stores.ROS1_NOETIC)
        # Noetic's store lacks tf2_msgs; its definition is one line.
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_TYPE))
        return store
    return get_typestore(Stores.ROS2_JAZZY)


# --------------------------------------------------------------------------------------------------
# decoding (bags and live nodes)
# --------------------------------------------------------------------------------------------------


def _as_uint8(data: Any) -> np.ndarray:
    """A flat uint8 view of a message's ``data`` (numpy array, bytes, array.array or list)."""
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8) if data.dtype.itemsize == 1 else data.astype(np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def decode_image(msg: Any) -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` to ``(H, W, 3)`` uint8 RGB.

    Respects ``step`` (row padding) and ``is_bigendian``; ``mono16`` is scaled to 8 bits
    (``round(v / 257)``, so 8-bit values stored as ``v * 257`` come back exactly).

    Raises:
        BagError: unsupported encoding, or ``data`` whose length is not ``height * step``.
    """
    encoding = str(msg.encoding)
    if encoding not in IMAGE_ENCODINGS:
        raise BagError(
            f"unsupported image encoding {encoding!r}; supported: {', '.join(IMAGE_ENCODINGS)} "
            f"(and CompressedImage {'/'.join(COMPRESSED_FORMATS)})"
        )
    channels, depth = IMAGE_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = _as_uint8(msg.data)
    row_bytes = width * channels * depth
    if height <= 0 or width <= 0:
        raise BagError(f"{encoding} image has an empty size {width}x{height}")
    if step < row_bytes:
        raise BagError(f"{encoding} image {width}x{height}: step {step} is less than a row ({row_bytes} bytes)")
    if data.size != height * step:
        raise BagError(
            f"{encoding} image {width}x{height}: data has {data.size} bytes, expected height*step = {height * step}"
        )
    rows = data.reshape(height, step)[:, :row_bytes]
    if depth == 2:
        values = rows.copy().view(">u2" if msg.is_bigendian else "<u2").astype(np.uint32)
        gray = ((values + 128) // 257).astype(np.uint8)
        return np.repeat(gray[:, :, None], 3, axis=2)
    pixels = rows.reshape(height, width, channels)
    if encoding == "rgb8":
        return np.ascontiguousarray(pixels)
    if encoding == "bgr8":
        return np.ascontiguousarray(pixels[:, :, ::-1])
    if encoding == "rgba8":
        return np.ascontiguousarray(pixels[:, :, :3])
    if encoding == "bgra8":
        return np.ascontiguousarray(pixels[:, :, 2::-1])
    return np.repeat(pixels, 3, axis=2)  # mono8


def decode_compressed_image(msg: Any) -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (jpeg or png) to ``(H, W, 3)`` uint8 RGB.

    ``format`` is either bare (``"jpeg"``) or image_transport's ``"rgb8; jpeg compressed bgr8"``;
    image_transport always compresses colour as bgr8, which is what OpenCV decodes to.
    """
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt.replace(" ", "") or not any(f in fmt for f in ("jpeg", "jpg", "png")):
        raise BagError(f"unsupported compressed image format {msg.format!r}; supported: {', '.join(COMPRESSED_FORMATS)}")
    buffer = _as_uint8(msg.data)
    image = cv2.imdecode(buffer, cv2.IMREAD_COLOR) if buffer.size else None
    if image is None:
        raise BagError(f"compressed image ({msg.format!r}, {buffer.size} bytes) could not be decoded")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def decode_any_image(msg: Any, msgtype: str) -> np.ndarray:
    """Decode an Image or CompressedImage message by its type name."""
    if msgtype == COMPRESSED_IMAGE_TYPE:
        return decode_compressed_image(msg)
    return decode_image(msg)


# --------------------------------------------------------------------------------------------------
# message <-> numpy
# --------------------------------------------------------------------------------------------------


def stamp_to_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def pose_msg_to_matrix(pose: Any) -> np.ndarray:
    """``geometry_msgs/Pose`` -> 4x4."""
    q = pose.orientation
    p = pose.position
    return make_transform(quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([p.x, p.y, p.z]))


def transform_msg_to_matrix(transform: Any) -> np.ndarray:
    """``geometry_msgs/Transform`` -> 4x4."""
    q = transform.rotation
    t = transform.translation
    return make_transform(quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([t.x, t.y, t.z]))


def camera_info_to_calibration(msg: Any):
    """``sensor_msgs/CameraInfo`` (ROS 2 or ROS 1 field names) -> :class:`nocal_ros.lens.CameraCalibration`."""
    from nocal_ros.lens import CameraCalibration

    k = getattr(msg, "k", None)
    d = getattr(msg, "d", None)
    k = np.asarray(msg.K if k is None else k, dtype=np.float64).reshape(3, 3)
    d = np.asarray(msg.D if d is None else d, dtype=np.float64).reshape(-1)
    return CameraCalibration(
        width=int(msg.width),
        height=int(msg.height),
        K=k.copy(),
        D=d.copy(),
        distortion_model=str(msg.distortion_model),
    )


# --------------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------------


class BagWriter:
    """Write a rosbag2 (``mcap`` or ``sqlite3``) or ROS 1 (``ros1``, path ending in ``.bag``) bag.

    Use as a context manager. The bag appears at ``path`` only when the block exits cleanly; on an
    exception nothing is left behind and an existing bag at ``path`` is untouched. An existing
    ``path`` is an error unless ``overwrite=True``.

    Stamps are nanoseconds; each message's header stamp and its bag receive time are both the stamp.
    """

    def __init__(self, path: str | Path, storage: str = "mcap", *, overwrite: bool = False) -> None:
        if storage not in STORAGES:
            raise BagError(f"{path}: unknown bag storage {storage!r}; choose one of {', '.join(STORAGES)}")
        self.path = Path(path)
        self.storage = storage
        self.overwrite = overwrite
        self._ros1 = storage == "ros1"
        if self._ros1 and self.path.suffix != ".bag":
            raise BagError(f"{self.path}: a ROS 1 bag's name must end in .bag")
        self._typestore = _typestore(self._ros1)
        self._types = self._typestore.types
        self._writer = None
        self._staging: Path | None = None
        self._connections: dict[str, Any] = {}
        self._seq = 0

    # context management --------------------------------------------------------------------------

    def __enter__(self) -> "BagWriter":
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def open(self) -> None:
        if self.path.exists() and not self.overwrite:
            raise BagError(f"{self.path}: already exists; refusing to overwrite it")
        if not self.path.parent.is_dir():
            raise BagError(f"{self.path}: parent directory {self.path.parent} does not exist")
        # Stage inside a hidden sibling directory so the final move is a rename on one file system.
        self._staging = self.path.parent / f".{self.path.name}.partial-{uuid.uuid4().hex[:8]}"
        self._staging.mkdir()
        target = self._staging / self.path.name
        if self._ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self._writer = Writer1(target)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
            self._writer = Writer(target, version=9, storage_plugin=plugin)
        self._writer.open()

    def close(self) -> None:
        """Finish the bag and move it into place."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        try:
            writer.close()
            staged = self._staging / self.path.name
            if self.path.exists():  # overwrite=True: swap only now that the new bag is complete
                old = self._staging / f"{self.path.name}.old"
                os.replace(self.path, old)
            os.replace(staged, self.path)
        finally:
            shutil.rmtree(self._staging, ignore_errors=True)

    def abort(self) -> None:
        """Discard everything written; leave ``path`` as it was."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        with contextlib.suppress(Exception):
            writer.close()
        shutil.rmtree(self._staging, ignore_errors=True)

    # messages ------------------------------------------------------------------------------------

    def _connection(self, topic: str, msgtype: str):
        connection = self._connections.get(topic)
        if connection is None:
            if self._writer is None:
                raise BagError(f"{self.path}: writer is not open (use it as a context manager)")
            connection = self._writer.add_connection(topic, msgtype, typestore=self._typestore)
            self._connections[topic] = connection
        elif connection.msgtype != msgtype:
            raise BagError(f"{self.path}: topic {topic} holds {connection.msgtype}, cannot also write {msgtype}")
        return connection

    def _write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        connection = self._connection(topic, msg.__msgtype__)
        if self._ros1:
            data = self._typestore.serialize_ros1(msg, msg.__msgtype__)
        else:
            data = self._typestore.serialize_cdr(msg, msg.__msgtype__)
        self._writer.write(connection, int(stamp_ns), data)

    def _header(self, stamp_ns: int, frame_id: str):
        stamp_ns = int(stamp_ns)
        if stamp_ns < 0:
            raise BagError(f"{self.path}: negative stamp {stamp_ns}")
        stamp = self._types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        if self._ros1:
            self._seq += 1
            return self._types["std_msgs/msg/Header"](seq=self._seq, stamp=stamp, frame_id=frame_id)
        return self._types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _pose(self, T: np.ndarray):
        T = np.asarray(T, dtype=np.float64)
        q = matrix_to_quaternion(T[:3, :3])
        point = self._types["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3])
        quat = self._types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
        return self._types["geometry_msgs/msg/Pose"](position=point, orientation=quat)

    def write_image(self, topic: str, stamp_ns: int, frame_id: str, image: np.ndarray, encoding: str = "rgb8") -> None:
        """Write ``(H, W, 3)`` uint8 RGB (or ``(H, W)`` for mono) as a ``sensor_msgs/Image``.

        ``encoding`` is the wire encoding: ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8`` or
        ``mono16`` (mono from an RGB image takes its luma; mono16 stores ``v * 257``).
        """
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise BagError(f"{self.path}: write_image wants uint8 (H, W, 3) RGB, got {image.dtype} {image.shape}")
        rgb = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
        if encoding == "rgb8":
            pixels = rgb
        elif encoding == "bgr8":
            pixels = rgb[:, :, ::-1]
        elif encoding in ("rgba8", "bgra8"):
            colour = rgb if encoding == "rgba8" else rgb[:, :, ::-1]
            pixels = np.concatenate((colour, np.full(rgb.shape[:2] + (1,), 255, np.uint8)), axis=2)
        elif encoding in ("mono8", "mono16"):
            gray = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
            pixels = gray if encoding == "mono8" else (gray.astype("<u2") * 257).view(np.uint8)
        else:
            raise BagError(f"{self.path}: cannot write image encoding {encoding!r}; supported: {', '.join(IMAGE_ENCODINGS)}")
        pixels = np.ascontiguousarray(pixels)
        height, width = image.shape[:2]
        msg = self._types[IMAGE_TYPE](
            header=self._header(stamp_ns, frame_id),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=pixels.size // height,
            data=pixels.reshape(-1),
        )
        self._write(topic, stamp_ns, msg)

    def write_compressed_image(
        self, topic: str, stamp_ns: int, frame_id: str, image: np.ndarray, fmt: str = "jpeg", quality: int = 95
    ) -> None:
        """Write ``(H, W, 3)`` uint8 RGB as a ``sensor_msgs/CompressedImage`` (jpeg or png)."""
        if fmt not in COMPRESSED_FORMATS:
            raise BagError(f"{self.path}: cannot compress as {fmt!r}; supported: {', '.join(COMPRESSED_FORMATS)}")
        bgr = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else []
        ok, buffer = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", bgr, params)
        if not ok:
            raise BagError(f"{self.path}: OpenCV could not encode a {fmt} image of shape {image.shape}")
        msg = self._types[COMPRESSED_IMAGE_TYPE](
            header=self._header(stamp_ns, frame_id),
            format=f"rgb8; {fmt} compressed bgr8",  # image_transport's convention
            data=buffer.reshape(-1).astype(np.uint8),
        )
        self._write(topic, stamp_ns, msg)

    def write_pose(self, topic: str, stamp_ns: int, frame_id: str, T: np.ndarray) -> None:
        """Write a 4x4 pose of something in ``frame_id`` as a ``geometry_msgs/PoseStamped``."""
        msg = self._types[POSE_STAMPED_TYPE](header=self._header(stamp_ns, frame_id), pose=self._pose(T))
        self._write(topic, stamp_ns, msg)

    def write_camera_info(self, topic: str, stamp_ns: int, frame_id: str, calibration: Any) -> None:
        """Write a calibration (``width, height, K, D, distortion_model``) as ``sensor_msgs/CameraInfo``.

        R is the identity and P = [K | 0]: a monocular camera that is not rectified.
        """
        K = np.asarray(calibration.K, dtype=np.float64).reshape(3, 3)
        D = np.asarray(calibration.D, dtype=np.float64).reshape(-1)
        P = np.hstack((K, np.zeros((3, 1))))
        roi = self._types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        matrices = {"d": D, "k": K.reshape(-1), "r": np.eye(3).reshape(-1), "p": P.reshape(-1)}
        if self._ros1:
            matrices = {name.upper(): value for name, value in matrices.items()}
        msg = self._types[CAMERA_INFO_TYPE](
            header=self._header(stamp_ns, frame_id),
            height=int(calibration.height),
            width=int(calibration.width),
            distortion_model=str(calibration.distortion_model),
            binning_x=0,
            binning_y=0,
            roi=roi,
            **matrices,
        )
        self._write(topic, stamp_ns, msg)

    def write_odometry(
        self,
        topic: str,
        stamp_ns: int,
        frame_id: str,
        child_frame_id: str,
        T: np.ndarray,
        twist: Sequence[float] = (0, 0, 0, 0, 0, 0),
        pose_cov: Sequence[float] | None = None,
        twist_cov: Sequence[float] | None = None,
    ) -> None:
        """Write ``nav_msgs/Odometry``: pose ``T`` of ``child_frame_id`` in ``frame_id``, twist (vx vy vz wx wy wz)
        in ``child_frame_id``, row-major 6x6 covariances (zeros when not given)."""
        t = self._types
        twist = np.asarray(twist, dtype=np.float64).reshape(6)
        pose_cov = np.zeros(36) if pose_cov is None else np.asarray(pose_cov, dtype=np.float64).reshape(36)
        twist_cov = np.zeros(36) if twist_cov is None else np.asarray(twist_cov, dtype=np.float64).reshape(36)
        twist_msg = t["geometry_msgs/msg/Twist"](
            linear=t["geometry_msgs/msg/Vector3"](x=twist[0], y=twist[1], z=twist[2]),
            angular=t["geometry_msgs/msg/Vector3"](x=twist[3], y=twist[4], z=twist[5]),
        )
        msg = t[ODOMETRY_TYPE](
            header=self._header(stamp_ns, frame_id),
            child_frame_id=child_frame_id,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(T), covariance=pose_cov),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist_msg, covariance=twist_cov),
        )
        self._write(topic, stamp_ns, msg)

    def write_tf(self, topic: str, stamp_ns: int, transforms: Sequence[tuple[str, str, np.ndarray]]) -> None:
        """Write ``tf2_msgs/TFMessage`` with ``(parent, child, T_parent_child)`` edges (``/tf`` or ``/tf_static``)."""
        t = self._types
        stamped = []
        for parent, child, T in transforms:
            T = np.asarray(T, dtype=np.float64)
            q = matrix_to_quaternion(T[:3, :3])
            stamped.append(
                t[TRANSFORM_STAMPED_TYPE](
                    header=self._header(stamp_ns, parent),
                    child_frame_id=child,
                    transform=t["geometry_msgs/msg/Transform"](
                        translation=t["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                        rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                    ),
                )
            )
        self._write(topic, stamp_ns, t[TF_TYPE](transforms=stamped))


def write_sequence(sequence: FrameSequence, path: str | Path, storage: str = "mcap", *, overwrite: bool = False) -> Path:
    """Write a sequence in the standard layout; :func:`read_sequence` reads it back exactly.

    ``/camera/image_raw`` (Image rgb8, frame ``camera_optical``), ``/arm/pose`` (PoseStamped of the
    camera in ``base``, labelled frames only), ``/ground_truth/pose`` (PoseStamped in ``world``,
    every frame) and ``/ground_truth/camera_info`` (true K, D, model; with every frame).
    """
    path = Path(path)
    labelled = sequence.labelled
    with BagWriter(path, storage, overwrite=overwrite) as writer:
        for index, stamp in enumerate(np.asarray(sequence.stamps_ns, dtype=np.int64)):
            stamp = int(stamp)
            writer.write_image(IMAGE_TOPIC, stamp, CAMERA_FRAME, sequence.images[index])
            if labelled[index]:
                writer.write_pose(ARM_POSE_TOPIC, stamp, ARM_BASE_FRAME, sequence.arm_poses[index])
            if sequence.ground_truth is not None and np.isfinite(sequence.ground_truth[index]).all():
                writer.write_pose(GT_POSE_TOPIC, stamp, WORLD_FRAME, sequence.ground_truth[index])
            if sequence.calibration is not None:
                writer.write_camera_info(CAMERA_INFO_TOPIC, stamp, CAMERA_FRAME, sequence.calibration)
    return path
