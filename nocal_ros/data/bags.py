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
import logging
import os
import shutil
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nocal_ros.data.sequence import FrameSequence
from nocal_ros.errors import BagError, NocalError
from nocal_ros.geometry import (
    InvalidTransformError,
    interpolate_transform,
    invert_transform,
    matrix_to_quaternion,
    transform_from_translation_quaternion,
)

log = logging.getLogger(__name__)

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
    """``geometry_msgs/Pose`` -> 4x4; InvalidTransformError for a zero or non-finite quaternion."""
    q = pose.orientation
    p = pose.position
    return transform_from_translation_quaternion(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w]))


def transform_msg_to_matrix(transform: Any) -> np.ndarray:
    """``geometry_msgs/Transform`` -> 4x4 (bags and the nodes' TF lookups); InvalidTransformError for a
    zero or non-finite quaternion or translation."""
    q = transform.rotation
    t = transform.translation
    return transform_from_translation_quaternion(np.array([t.x, t.y, t.z]), np.array([q.x, q.y, q.z, q.w]))


def camera_info_to_calibration(msg: Any):
    """``sensor_msgs/CameraInfo`` (ROS 2 or ROS 1 field names) -> :class:`nocal_ros.lens.CameraCalibration`.

    CameraInfo has no camera name; the header's frame id stands in for it. R and P are kept.
    """
    from nocal_ros.lens import CameraCalibration

    def field(name: str, shape: tuple[int, ...]) -> np.ndarray:
        value = getattr(msg, name, None)
        value = getattr(msg, name.upper()) if value is None else value
        return np.asarray(value, dtype=np.float64).reshape(shape).copy()

    try:
        return CameraCalibration(
            width=int(msg.width),
            height=int(msg.height),
            K=field("k", (3, 3)),
            D=field("d", (-1,)),
            distortion_model=str(msg.distortion_model),
            camera_name=str(msg.header.frame_id) or "camera",
            R=field("r", (3, 3)),
            P=field("p", (3, 4)),
        )
    except ValueError as error:  # e.g. the all-zero K that uncalibrated camera drivers publish
        raise BagError(f"CameraInfo is not a usable calibration: {error}") from None


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
        self.bytes_written = 0  # serialized message bytes so far (the bag's size, less its small index)

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

    @property
    def types(self) -> Any:
        """Message classes of this bag's type store, for :meth:`write_message`."""
        return self._types

    def declare_topic(self, topic: str, msgtype: str) -> None:
        """Record a topic even if no message is written to it (as ``ros2 bag record`` does)."""
        self._connection(topic, msgtype)

    def write_message(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Write any message built from :attr:`types` (an escape hatch for types without a helper)."""
        self._write(topic, stamp_ns, msg)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        """A ``std_msgs/Header`` for this bag's ROS version."""
        return self._header(stamp_ns, frame_id)

    def _write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        connection = self._connection(topic, msg.__msgtype__)
        if self._ros1:
            data = self._typestore.serialize_ros1(msg, msg.__msgtype__)
        else:
            data = self._typestore.serialize_cdr(msg, msg.__msgtype__)
        self._writer.write(connection, int(stamp_ns), data)
        self.bytes_written += len(data)

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

        R and P are the calibration's (``rectification``, ``projection``) when it has them, else the
        identity and ``[K | 0]``: a monocular camera that is not rectified.
        """
        K = np.asarray(calibration.K, dtype=np.float64).reshape(3, 3)
        D = np.asarray(calibration.D, dtype=np.float64).reshape(-1)
        P = np.asarray(getattr(calibration, "projection", np.hstack((K, np.zeros((3, 1))))), dtype=np.float64)
        R = np.asarray(getattr(calibration, "rectification", np.eye(3)), dtype=np.float64)
        roi = self._types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        matrices = {"d": D, "k": K.reshape(-1), "r": R.reshape(-1), "p": P.reshape(-1)}
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


# --------------------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------------------


class PoseTrack:
    """Stamped poses of one frame pair, interpolated to query stamps without extrapolating.

    A query at a sample's stamp returns that sample. Between two samples the pose is interpolated
    (slerp rotation, linear translation) only when both lie within the tolerance of the query;
    otherwise, and before the first or after the last sample, there is no pose (None).
    """

    def __init__(self) -> None:
        self._samples: list[tuple[int, np.ndarray]] = []
        self._stamps: list[int] | None = None
        self._poses: list[np.ndarray] = []

    def add(self, stamp_ns: int, T: np.ndarray) -> None:
        self._samples.append((int(stamp_ns), T))
        self._stamps = None

    def __len__(self) -> int:
        return len(self._samples)

    def _sorted(self) -> None:
        if self._stamps is None:
            by_stamp: dict[int, np.ndarray] = {}
            for stamp, T in sorted(self._samples, key=lambda sample: sample[0]):
                by_stamp.setdefault(stamp, T)
            self._stamps = list(by_stamp)
            self._poses = list(by_stamp.values())

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """``(stamps_ns (N,) int64, poses (N, 4, 4))`` sorted by stamp, one per stamp."""
        self._sorted()
        return np.asarray(self._stamps, dtype=np.int64), np.asarray(self._poses, dtype=np.float64).reshape(-1, 4, 4)

    def at(self, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        self._sorted()
        stamps = self._stamps
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self._poses[i]
        if i == 0 or i == len(stamps):
            return None
        t0, t1 = stamps[i - 1], stamps[i]
        if stamp_ns - t0 > tolerance_ns or t1 - stamp_ns > tolerance_ns:
            return None
        return interpolate_transform(self._poses[i - 1], self._poses[i], (stamp_ns - t0) / (t1 - t0))


class TfBuffer:
    """TF edges from ``/tf`` (interpolated per edge) and ``/tf_static`` (constant), and chains between frames."""

    def __init__(self) -> None:
        self.dynamic: dict[tuple[str, str], PoseTrack] = {}
        self.static: dict[tuple[str, str], np.ndarray] = {}
        self._parent_of: dict[str, str] = {}
        self.invalid_samples = 0  # transforms with a zero or non-finite quaternion or translation: skipped

    def add(self, msg: Any, is_static: bool) -> None:
        for stamped in msg.transforms:
            parent = stamped.header.frame_id.lstrip("/")
            child = stamped.child_frame_id.lstrip("/")
            try:
                T = transform_msg_to_matrix(stamped.transform)
            except InvalidTransformError:
                self.invalid_samples += 1
                continue
            self._parent_of.setdefault(child, parent)
            if is_static:
                self.static[(parent, child)] = T
            else:
                self.dynamic.setdefault((parent, child), PoseTrack()).add(stamp_to_ns(stamped.header.stamp), T)

    def edges(self) -> list[str]:
        return sorted(f"{p}->{c}" for p, c in {**self.static, **dict.fromkeys(self.dynamic)})

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        while path[-1] in self._parent_of and self._parent_of[path[-1]] not in path:
            path.append(self._parent_of[path[-1]])
        return path

    def chain(self, parent: str, child: str) -> tuple[list[tuple[str, str]], list[tuple[str, str]]] | None:
        """Edges from a common ancestor down to ``parent`` and down to ``child``, or None if unconnected."""
        parent, child = parent.lstrip("/"), child.lstrip("/")  # ROS 1 frame ids may carry a leading slash
        up_child = self._path_to_root(child)
        up_parent = self._path_to_root(parent)
        common = next((frame for frame in up_child if frame in up_parent), None)
        if common is None:
            return None

        def edges_below(path: list[str]) -> list[tuple[str, str]]:
            down = path[: path.index(common) + 1][::-1]
            return list(zip(down[:-1], down[1:]))

        return edges_below(up_parent), edges_below(up_child)

    def _compose(self, edges: list[tuple[str, str]], stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        T = np.eye(4)
        for edge in edges:
            if edge in self.static:
                T = T @ self.static[edge]
                continue
            sample = self.dynamic[edge].at(stamp_ns, tolerance_ns)
            if sample is None:
                return None
            T = T @ sample
        return T

    def lookup(self, chain, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        """``T_parent_child`` at a stamp along a :meth:`chain`, or None where an edge has no pose."""
        to_parent, to_child = chain
        T_a_parent = self._compose(to_parent, stamp_ns, tolerance_ns)
        T_a_child = self._compose(to_child, stamp_ns, tolerance_ns)
        if T_a_parent is None or T_a_child is None:
            return None
        return invert_transform(T_a_parent) @ T_a_child


def _check_path(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag (file or directory does not exist)")
    return path


@contextlib.contextmanager
def _open_bag(path: Path) -> Iterator[Any]:
    """AnyReader over one bag; whatever rosbags (or sqlite, or the OS) raises becomes a BagError."""
    from rosbags.highlevel import AnyReader

    try:
        with AnyReader([path], default_typestore=_typestore()) as reader:
            yield reader
    except NocalError:
        raise
    except Exception as error:  # rosbags raises many kinds for corrupt and truncated files
        # One line: a YAML parser's message about a corrupt metadata.yaml spans several.
        detail = " ".join(f"{type(error).__name__}: {error}".split())
        raise BagError(f"{path}: cannot read the bag (corrupt, truncated or not a rosbag): {detail}") from error


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """``{topic: (message type, message count)}`` of a bag, read from its index (no messages decoded)."""
    path = _check_path(path)
    with _open_bag(path) as reader:
        return {name: (str(info.msgtype), int(info.msgcount)) for name, info in reader.topics.items()}


def camera_mounting(path: str | Path, parent: str, image_topic: str,
                    required: bool = True) -> tuple[np.ndarray | None, str]:
    """``(T_parent_cam, camera frame)``: the pose of the images' frame (the first image's frame id) in
    ``parent``, from the bag's ``/tf_static`` through intermediate frames (a robot's URDF, as
    robot_state_publisher latches it). Where the bag does not connect them: BagError, or ``None`` for
    the pose when not ``required``."""
    mountings = camera_mountings(path, [parent], image_topic)
    if mountings.poses[parent] is None and required:
        raise BagError(mountings.unconnected(parent))
    return mountings.poses[parent], mountings.camera_frame


@dataclass
class CameraMountings:
    """The images' frame, its pose ``T_parent_cam`` in each asked parent frame (None where the bag's
    ``/tf_static`` does not connect them), and that tree's edges."""

    path: Path
    camera_frame: str
    poses: dict[str, np.ndarray | None]
    edges: list[str]

    def unconnected(self, parent: str) -> str:
        """The one-line error for a parent frame the bag does not connect to the camera."""
        return (f"{self.path}: /tf_static does not connect {parent} to the images' frame {self.camera_frame!r} "
                f"(its edges: {', '.join(self.edges) or 'none'})")


def camera_mountings(path: str | Path, parents: Sequence[str], image_topic: str) -> CameraMountings:
    """:func:`camera_mounting` for several parent frames from one read of the bag's first image and
    ``/tf_static``."""
    path = _check_path(path)
    tf = TfBuffer()
    with _open_bag(path) as reader:
        image_connections = _image_connections(reader, path, image_topic)
        camera_frame = None
        for connection, _, raw in reader.messages(connections=image_connections):
            camera_frame = reader.deserialize(raw, connection.msgtype).header.frame_id.lstrip("/")
            break
        if camera_frame is None:
            raise BagError(f"{path}: no usable frames: topic {image_topic} has no messages")
        static = [c for c in reader.connections if c.topic == "/tf_static" and c.msgtype == TF_TYPE]
        for connection, _, raw in reader.messages(connections=static):
            tf.add(reader.deserialize(raw, connection.msgtype), is_static=True)
    poses = {}
    for parent in parents:
        chain = tf.chain(parent, camera_frame)
        poses[parent] = None if chain is None else tf.lookup(chain, 0, 0)
    return CameraMountings(path, camera_frame, poses, list(tf.edges()))


def _topic_list(reader: Any) -> str:
    return ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(reader.topics.items())) or "none"


def _image_connections(reader: Any, path: Path, image_topic: str) -> list:
    info = reader.topics.get(image_topic)
    if info is None:
        raise BagError(f"{path}: no image topic {image_topic!r}; topics in the bag: {_topic_list(reader)}")
    if info.msgtype not in (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE):
        raise BagError(f"{path}: topic {image_topic} holds {info.msgtype}, not sensor_msgs/Image or CompressedImage")
    return [c for c in reader.connections if c.topic == image_topic]


def _resize_size(resize: Sequence[int] | None) -> tuple[int, int] | None:
    if resize is None:
        return None
    width, height = (int(v) for v in resize)
    if width <= 0 or height <= 0:
        raise BagError(f"resize must be a positive (width, height), got {tuple(resize)}")
    return width, height


class _FrameChecker:
    """Decodes one image topic's messages, resizes them, and refuses a size change mid-bag."""

    def __init__(self, path: Path, topic: str, resize: tuple[int, int] | None, network: bool = False) -> None:
        self.path, self.topic, self.resize, self.network = path, topic, resize, network
        self.native_size: tuple[int, int] | None = None
        self.count = 0

    def __call__(self, msg: Any, msgtype: str, stamp_ns: int) -> np.ndarray:
        try:
            rgb = decode_any_image(msg, msgtype)
        except BagError as error:
            raise BagError(f"{self.path}: {self.topic} message {self.count} (stamp {stamp_ns} ns): {error}") from None
        size = (rgb.shape[1], rgb.shape[0])
        if self.native_size is None:
            self.native_size = size
        elif size != self.native_size:
            raise BagError(
                f"{self.path}: image size changes mid-bag on {self.topic}: message {self.count} (stamp {stamp_ns} ns) "
                f"is {size[0]}x{size[1]}, earlier images are {self.native_size[0]}x{self.native_size[1]}"
            )
        self.count += 1
        if self.resize is not None and size != self.resize:
            if self.network:  # what the network is fed (nocal_ros.network_input)
                from nocal_ros.network_input import network_input

                rgb = network_input(rgb, self.resize)[0]
            else:
                rgb = cv2.resize(rgb, self.resize, interpolation=cv2.INTER_AREA)
        return rgb


def _header_stamp(msg: Any, bag_stamp_ns: int) -> int:
    """The sensor stamp of a message; its bag receive time where the header stamp was left at zero."""
    stamp = stamp_to_ns(msg.header.stamp)
    return stamp if stamp > 0 else int(bag_stamp_ns)


def _pose_from_msg(msg: Any, msgtype: str) -> np.ndarray:
    if msgtype == POSE_STAMPED_TYPE:
        return pose_msg_to_matrix(msg.pose)
    if msgtype == POSE_COV_STAMPED_TYPE:
        return pose_msg_to_matrix(msg.pose.pose)
    return transform_msg_to_matrix(msg.transform)


def _add_pose(track: PoseTrack, msg: Any, msgtype: str, bag_stamp_ns: int) -> bool:
    """Add a pose message's sample to ``track``; False (nothing added) when it is no pose.

    A zero or non-finite quaternion (an unset orientation, a driver glitch) is skipped rather than
    refusing the bag: interpolation then bridges it from the samples around it, within the tolerance.
    """
    try:
        track.add(_header_stamp(msg, bag_stamp_ns), _pose_from_msg(msg, msgtype))
    except InvalidTransformError:
        return False
    return True


def _warn_invalid_poses(path: Path, count: int) -> None:
    if count:
        log.warning("%s: skipped %d pose sample(s) with a zero or non-finite quaternion or position", path, count)


def read_pose_messages(path: str | Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Every pose on ``topic`` (PoseStamped, PoseWithCovarianceStamped or TransformStamped) as
    ``(stamps_ns (N,) int64, poses (N, 4, 4))`` in the bag's order, header stamps. Samples that are no
    pose (a zero or non-finite quaternion or position) are skipped, with a warning that counts them.

    Reads that one topic only, without decoding images.
    """
    path = _check_path(path)
    track = PoseTrack()
    with _open_bag(path) as reader:
        info = reader.topics.get(topic)
        if info is None:
            raise BagError(f"{path}: no pose topic {topic!r}; topics in the bag: {_topic_list(reader)}")
        if info.msgtype not in POSE_TYPES:
            raise BagError(f"{path}: topic {topic} holds {info.msgtype}, not one of {', '.join(POSE_TYPES)}")
        connections = [c for c in reader.connections if c.topic == topic]
        invalid = 0
        for connection, bag_stamp, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            invalid += not _add_pose(track, msg, connection.msgtype, bag_stamp)
    _warn_invalid_poses(path, invalid)
    return track.samples()


def read_poses(
    path: str | Path, topic: str, stamps_ns: Sequence[int] | np.ndarray, tolerance_s: float = 0.02
) -> np.ndarray:
    """Poses on ``topic`` at the given stamps, ``(N, 4, 4)``, NaN where no sample is within tolerance
    (see :class:`PoseTrack`). Reads that one topic only: for ground truth beside :func:`iter_images`.
    """
    track = PoseTrack()
    for stamp, T in zip(*read_pose_messages(path, topic)):
        track.add(int(stamp), T)
    tolerance_ns = int(round(tolerance_s * 1e9))
    poses = np.full((len(stamps_ns), 4, 4), np.nan)
    for row, stamp in enumerate(np.asarray(stamps_ns, dtype=np.int64).tolist()):
        T = track.at(stamp, tolerance_ns)
        if T is not None:
            poses[row] = T
    return poses


def read_camera_info(path: str | Path, topic: str = CAMERA_INFO_TOPIC):
    """The first ``sensor_msgs/CameraInfo`` on ``topic`` as a :class:`nocal_ros.lens.CameraCalibration`.

    Reads that one topic only, so a long bag's images are neither read nor decoded.

    Raises:
        BagError: the topic is missing, holds another type, is empty, or its message is not a
            usable calibration (e.g. the all-zero K of an uncalibrated driver); the message names the bag.
    """
    path = _check_path(path)
    with _open_bag(path) as reader:
        info = reader.topics.get(topic)
        if info is None:
            raise BagError(f"{path}: no camera info topic {topic!r}; topics in the bag: {_topic_list(reader)}")
        if info.msgtype != CAMERA_INFO_TYPE:
            raise BagError(f"{path}: topic {topic} holds {info.msgtype}, not {CAMERA_INFO_TYPE}")
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            try:
                return camera_info_to_calibration(msg)
            except BagError as error:
                raise BagError(f"{path}: {topic}: {error}") from None
    raise BagError(f"{path}: topic {topic} has no messages")


def iter_images(
    path: str | Path, image_topic: str = IMAGE_TOPIC, resize: Sequence[int] | None = None
) -> Iterator[tuple[int, str, np.ndarray]]:
    """Stream ``(stamp_ns, frame_id, rgb uint8 (H, W, 3))`` from a bag's image topic in recording order.

    Memory stays at one image whatever the bag's length (offline odometry replays long bags).
    """
    path = _check_path(path)
    size = _resize_size(resize)
    with _open_bag(path) as reader:
        connections = _image_connections(reader, path, image_topic)
        decode = _FrameChecker(path, image_topic, size)
        for connection, bag_stamp, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            stamp = _header_stamp(msg, bag_stamp)
            yield stamp, str(msg.header.frame_id), decode(msg, connection.msgtype, stamp)
        if decode.count == 0:
            raise BagError(f"{path}: topic {image_topic} has no messages; no frames to read")


def read_sequence(
    path: str | Path,
    image_topic: str = IMAGE_TOPIC,
    pose_topic: str | None = ARM_POSE_TOPIC,
    pose_source: str = "auto",
    tf_parent: str = "base",
    tf_child: str = "tool",
    T_tool_cam: np.ndarray | None = None,
    tolerance_s: float = 0.02,
    gt_topic: str | None = GT_POSE_TOPIC,
    camera_info_topic: str | None = CAMERA_INFO_TOPIC,
    resize: Sequence[int] | None = None,
    max_frames: int | None = None,
    network_size: Sequence[int] | None = None,
) -> FrameSequence:
    """Read a bag (rosbag2 mcap/sqlite3 directory or file, or ROS 1 ``.bag``) into a FrameSequence.

    Args:
        image_topic: ``sensor_msgs/Image`` or ``CompressedImage`` topic.
        pose_topic: arm poses ``T_base_tool`` (PoseStamped, PoseWithCovarianceStamped or TransformStamped).
        pose_source: ``"pose"`` (``pose_topic``), ``"tf"`` (``tf_parent -> tf_child`` from ``/tf`` and
            ``/tf_static``, through intermediate frames if needed), ``"none"``, or ``"auto"``: the pose
            topic if the bag has it, else TF if it connects the two frames, else none.
        T_tool_cam: static hand-eye transform; arm poses become ``T_base_cam = T_base_tool @ T_tool_cam``.
        tolerance_s: an image gets a pose only from samples within this time of its stamp (see
            :class:`PoseTrack`); other images are unlabelled (NaN).
        gt_topic, camera_info_topic: ground-truth camera poses and calibration, read when present.
        resize: ``(width, height)`` to resize images to (``cv2.INTER_AREA``); the calibration is
            scaled to match and ``extras["native_size"]`` keeps the recorded size.
        max_frames: keep only the first images.
        network_size: ``(width, height)`` of a network's input: frames are mapped onto it as training
            and the odometry map them (:func:`nocal_ros.network_input.network_input`); the calibration
            stays at native resolution. Not with ``resize``.

    Stamps are the images' header stamps, sorted; frames with a repeated stamp are dropped.
    """
    path = _check_path(path)
    if resize is not None and network_size is not None:
        raise BagError(f"{path}: give resize or network_size, not both")
    size = _resize_size(resize if network_size is None else network_size)
    if pose_source not in ("auto", "pose", "tf", "none"):
        raise BagError(f"{path}: pose_source must be auto, pose, tf or none, not {pose_source!r}")
    T_tool_cam = np.eye(4) if T_tool_cam is None else np.asarray(T_tool_cam, dtype=np.float64)
    if T_tool_cam.shape != (4, 4) or not np.isfinite(T_tool_cam).all():
        raise BagError(f"{path}: T_tool_cam must be a finite 4x4 transform")
    tolerance_ns = int(round(tolerance_s * 1e9))
    limit = None if max_frames is None else int(max_frames)

    images: list[np.ndarray] = []
    stamps: list[int] = []
    arm = PoseTrack()
    ground_truth = PoseTrack()
    tf = TfBuffer()
    camera_info = None
    invalid_poses = 0
    with _open_bag(path) as reader:
        topics = reader.topics
        _image_connections(reader, path, image_topic)  # a missing or wrong image topic: one clear error first
        if pose_source == "pose" and pose_topic not in topics:
            raise BagError(f"{path}: no arm pose topic {pose_topic!r}; topics in the bag: {_topic_list(reader)}")
        use_pose_topic = pose_source in ("pose", "auto") and pose_topic in topics
        if use_pose_topic and topics[pose_topic].msgtype not in POSE_TYPES:
            raise BagError(f"{path}: arm pose topic {pose_topic} holds {topics[pose_topic].msgtype}, not one of {', '.join(POSE_TYPES)}")
        use_tf = (pose_source == "tf") or (pose_source == "auto" and not use_pose_topic)
        wanted = {image_topic}
        if use_pose_topic:
            wanted.add(pose_topic)
        if use_tf:
            wanted.update(topic for topic in TF_TOPICS if topic in topics and topics[topic].msgtype == TF_TYPE)
        if gt_topic in topics and topics[gt_topic].msgtype in POSE_TYPES:
            wanted.add(gt_topic)
        if camera_info_topic in topics and topics[camera_info_topic].msgtype == CAMERA_INFO_TYPE:
            wanted.add(camera_info_topic)
        connections = [c for c in reader.connections if c.topic in wanted]
        decode = _FrameChecker(path, image_topic, size, network=network_size is not None)
        seen_images = 0
        for connection, bag_stamp, raw in reader.messages(connections=connections):
            topic, msgtype = connection.topic, connection.msgtype
            if topic == image_topic:
                seen_images += 1
                if limit is not None and seen_images > limit:
                    continue  # keep going only for poses that bracket the last kept image
                msg = reader.deserialize(raw, msgtype)
                stamp = _header_stamp(msg, bag_stamp)
                images.append(decode(msg, msgtype, stamp))
                stamps.append(stamp)
            elif topic == camera_info_topic:
                if camera_info is None:
                    camera_info = reader.deserialize(raw, msgtype)
            elif topic in TF_TOPICS and use_tf:
                tf.add(reader.deserialize(raw, msgtype), is_static=topic == "/tf_static")
            else:
                msg = reader.deserialize(raw, msgtype)
                track = arm if (use_pose_topic and topic == pose_topic) else ground_truth
                invalid_poses += not _add_pose(track, msg, msgtype, bag_stamp)
        if not images:
            raise BagError(f"{path}: no usable frames: topic {image_topic} has no messages")

    tf_chain = tf.chain(tf_parent, tf_child) if use_tf else None
    if pose_source == "tf" and tf_chain is None:
        raise BagError(
            f"{path}: TF does not connect {tf_parent!r} to {tf_child!r}; TF edges in the bag: {', '.join(tf.edges()) or 'none'}"
        )

    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    stamps_sorted = np.asarray(stamps, dtype=np.int64)[order]
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = np.diff(stamps_sorted) > 0
    order, stamps_sorted = order[keep], stamps_sorted[keep]

    arm_poses = np.full((len(order), 4, 4), np.nan)
    gt_poses = np.full((len(order), 4, 4), np.nan) if len(ground_truth) else None
    for row, stamp in enumerate(stamps_sorted.tolist()):
        if use_pose_topic:
            T_base_tool = arm.at(stamp, tolerance_ns)
        elif tf_chain is not None:
            T_base_tool = tf.lookup(tf_chain, stamp, tolerance_ns)
        else:
            T_base_tool = None
        if T_base_tool is not None:
            arm_poses[row] = T_base_tool @ T_tool_cam
        if gt_poses is not None:
            T_w_cam = ground_truth.at(stamp, tolerance_ns)
            if T_w_cam is not None:
                gt_poses[row] = T_w_cam

    calibration = None
    native_size = decode.native_size
    invalid_poses += tf.invalid_samples
    _warn_invalid_poses(path, invalid_poses)
    extras = {"native_size": native_size, "dropped_repeated_stamps": int((~keep).sum()),
              "invalid_pose_samples": int(invalid_poses)}
    if network_size is not None:
        extras["network_size"] = size
    if camera_info is not None:
        try:
            calibration = camera_info_to_calibration(camera_info)
        except BagError as error:  # an unknown camera is what nocal is for, not a reason to refuse the bag
            extras["camera_info_problem"] = f"{camera_info_topic}: {error}"
        if calibration is not None and size is not None and size != native_size and network_size is None:
            calibration = calibration.scaled(*size)
    if use_pose_topic:
        extras["pose_source"] = f"topic {pose_topic}"
    elif tf_chain is not None:
        extras["pose_source"] = f"tf {tf_parent}->{tf_child}"
    else:
        extras["pose_source"] = "none"
    return FrameSequence(
        images=np.stack([images[i] for i in order]),
        stamps_ns=stamps_sorted,
        arm_poses=arm_poses,
        ground_truth=gt_poses,
        calibration=calibration,
        name=str(path),
        extras=extras,
    )
