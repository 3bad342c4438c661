"""Live recording for the trainer node: camera images and arm poses into one bounded rosbag2.

The trainer node fine-tunes from bags. With :class:`LiveRecorder` it records one itself: the images
(``sensor_msgs/Image`` or ``CompressedImage``, written as they arrived, bytes untouched) and the arm's
poses, as ``geometry_msgs/PoseStamped`` on the pose topic or as ``/tf`` edges ``base -> tool``, in the
layout :func:`nocal_ros.data.bags.read_sequence` reads. Writing goes through
:class:`~nocal_ros.data.bags.BagWriter`, so the bag appears at its path only once it is complete.

A recording is bounded twice, and stops itself at whichever comes first:

* ``max_bytes``: the serialized messages never exceed it (a message that would is not written; the
  file adds the mcap index, a few kB);
* ``max_duration_s``: clock time since the start (the node's clock: ``/clock`` under sim time).

Frames that cannot be read back (an unsupported encoding, a size that changes mid-recording) are
counted and skipped, so the recording stays usable for fine-tuning.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nocal_ros.data.bags import (
    BagWriter,
    COMPRESSED_IMAGE_TYPE,
    IMAGE_TYPE,
    _as_uint8,
    decode_compressed_image,
    decode_image,
    stamp_to_ns,
)
from nocal_ros.errors import BagError, NocalError

# Upper bounds of the CDR overhead of one message beyond its strings and pixel bytes (header stamp,
# lengths, alignment): used to keep a recording strictly under max_bytes.
_IMAGE_OVERHEAD = 64
_POSE_OVERHEAD = 160


@dataclass(frozen=True)
class RecordingLimits:
    """When a recording stops by itself."""

    max_bytes: int = 2_000_000_000
    max_duration_s: float = 120.0

    def __post_init__(self) -> None:
        if int(self.max_bytes) <= 0 or not float(self.max_duration_s) > 0:
            raise NocalError(f"recording limits must be positive, got {self.max_bytes} bytes and {self.max_duration_s} s")


@dataclass
class RecordingSummary:
    """A finished recording: where it is, what it holds, and why it ended."""

    path: str | None  # None when nothing was recorded (no image arrived): no bag is left behind
    frames: int
    arm_poses: int
    bytes: int
    duration_s: float
    stopped_by: str  # "request", "max_bytes" or "max_duration"
    rejected: int = 0
    problems: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class LiveRecorder:
    """Writes images and arm poses into ``path`` until :meth:`stop` or a limit.

    Thread-safe: image, pose and timer callbacks may call it from different threads.

    Args:
        path: the bag to write (a rosbag2 directory for ``mcap`` or ``sqlite3``); must not exist.
        image_topic: topic the images are recorded on (the trainer's ``image_topic``).
        pose_topic: topic PoseStamped arm poses are recorded on.
        tf_parent, tf_child: the TF edge arm poses from TF are recorded as.
        limits: when to stop by itself.
        start_ns: clock time of the start, for ``max_duration_s``.
        storage: ``mcap`` or ``sqlite3``.
    """

    def __init__(self, path: str | Path, image_topic: str, pose_topic: str, limits: RecordingLimits,
                 start_ns: int, *, tf_parent: str = "base", tf_child: str = "tool", storage: str = "mcap") -> None:
        self.path = Path(path)
        self.image_topic, self.pose_topic = image_topic, pose_topic
        self.tf_parent, self.tf_child = tf_parent, tf_child
        self.limits = limits
        self.start_ns = int(start_ns)
        self._lock = threading.Lock()
        self._writer = BagWriter(self.path, storage)
        self._writer.open()
        self._frames = 0
        self._arm_poses = 0
        self._rejected = 0
        self._problems: list[str] = []
        self._image_shape: tuple[int, int] | None = None
        self._last_ns = self.start_ns
        self.summary: RecordingSummary | None = None

    @property
    def active(self) -> bool:
        return self.summary is None

    @property
    def frames(self) -> int:
        return self._frames

    @property
    def arm_poses(self) -> int:
        return self._arm_poses

    @property
    def bytes_written(self) -> int:
        return self._writer.bytes_written

    # -- messages ----------------------------------------------------------------------------------

    def add_image(self, msg: Any, now_ns: int) -> bool:
        """Record a ``sensor_msgs/Image`` or ``CompressedImage`` (any object with their fields) as it
        arrived; False when it was not recorded (stopped, a limit reached, or a frame that cannot be read)."""
        compressed = hasattr(msg, "format")
        try:  # the fine-tuning job must be able to read every frame back
            shape = (decode_compressed_image(msg) if compressed else decode_image(msg)).shape[:2]
        except BagError as error:
            self._reject(f"{self.image_topic}: {error}")
            return False
        data = _as_uint8(msg.data)
        strings = len(str(msg.header.frame_id)) + len(str(msg.format if compressed else msg.encoding))
        with self._lock:
            if not self._admit(now_ns, data.size + strings + _IMAGE_OVERHEAD):
                return False
            if self._image_shape is not None and shape != self._image_shape:
                self._reject_locked(f"{self.image_topic}: image size changed from {self._image_shape[1]}x"
                                    f"{self._image_shape[0]} to {shape[1]}x{shape[0]}; frame not recorded")
                return False
            self._image_shape = shape
            stamp = stamp_to_ns(msg.header.stamp)
            header = self._writer.header(stamp, str(msg.header.frame_id))
            types = self._writer.types
            if compressed:
                record = types[COMPRESSED_IMAGE_TYPE](header=header, format=str(msg.format), data=data)
            else:
                record = types[IMAGE_TYPE](header=header, height=int(msg.height), width=int(msg.width),
                                           encoding=str(msg.encoding), is_bigendian=int(msg.is_bigendian),
                                           step=int(msg.step), data=data)
            self._writer.write_message(self.image_topic, stamp, record)
            self._frames += 1
            return True

    def add_pose(self, stamp_ns: int, frame_id: str, T_base_tool: np.ndarray, now_ns: int) -> bool:
        """Record the tool's pose in the arm's base frame as PoseStamped on the pose topic."""
        with self._lock:
            if not self._admit(now_ns, len(frame_id) + _POSE_OVERHEAD):
                return False
            self._writer.write_pose(self.pose_topic, stamp_ns, frame_id, T_base_tool)
            self._arm_poses += 1
            return True

    def add_tf(self, stamp_ns: int, T_base_tool: np.ndarray, now_ns: int) -> bool:
        """Record the tool's pose as the ``/tf`` edge ``tf_parent -> tf_child`` at ``stamp_ns``."""
        with self._lock:
            if not self._admit(now_ns, len(self.tf_parent) + len(self.tf_child) + _POSE_OVERHEAD):
                return False
            self._writer.write_tf("/tf", stamp_ns, [(self.tf_parent, self.tf_child, T_base_tool)])
            self._arm_poses += 1
            return True

    def check(self, now_ns: int) -> RecordingSummary | None:
        """Stop if the duration limit has passed (called by a timer, so a silent camera still stops)."""
        with self._lock:
            if self.summary is None and self._over_time(now_ns):
                self._finish("max_duration")
            return self.summary

    def stop(self, now_ns: int | None = None) -> RecordingSummary:
        """Finish the recording (or return how it already finished); the bag is then complete at ``path``."""
        with self._lock:
            if self.summary is None:
                if now_ns is not None:
                    self._last_ns = max(self._last_ns, int(now_ns))
                self._finish("request")
            return self.summary

    # -- internals (hold the lock) -----------------------------------------------------------------

    def _over_time(self, now_ns: int) -> bool:
        self._last_ns = max(self._last_ns, int(now_ns))
        return (int(now_ns) - self.start_ns) * 1e-9 >= self.limits.max_duration_s

    def _admit(self, now_ns: int, size: int) -> bool:
        """Whether a message of ``size`` bytes may be written now; finishes the recording at a limit."""
        if self.summary is not None:
            return False
        if self._over_time(now_ns):
            self._finish("max_duration")
            return False
        if self._writer.bytes_written + size > self.limits.max_bytes:
            self._finish("max_bytes")
            return False
        return True

    def _reject(self, problem: str) -> None:
        with self._lock:
            self._reject_locked(problem)

    def _reject_locked(self, problem: str) -> None:
        self._rejected += 1
        if len(self._problems) < 5:
            self._problems.append(problem)

    def _finish(self, stopped_by: str) -> None:
        path: str | None = str(self.path)
        if self._frames == 0:
            self._writer.abort()  # a bag without images would only fail the fine-tune later
            path = None
        else:
            self._writer.close()
        self.summary = RecordingSummary(
            path=path, frames=self._frames, arm_poses=self._arm_poses, bytes=self._writer.bytes_written,
            duration_s=round((self._last_ns - self.start_ns) * 1e-9, 3), stopped_by=stopped_by,
            rejected=self._rejected, problems=list(self._problems),
        )
