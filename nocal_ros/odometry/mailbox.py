"""Handing frames from a ROS executor to the odometry's worker thread."""

from __future__ import annotations

import threading
from collections import deque
from typing import Any


class FrameMailbox:
    """Hands frames from the executor to the worker. ``latest_only``: one slot, a new frame replaces
    the waiting one (counted in ``dropped``); otherwise a FIFO of ``capacity`` that drops the oldest."""

    def __init__(self, latest_only: bool = True, capacity: int = 1) -> None:
        self._items: deque = deque(maxlen=1 if latest_only else max(1, capacity))
        self._condition = threading.Condition()
        self.dropped = 0
        self.received = 0
        self._closed = False

    def put(self, item: Any) -> None:
        with self._condition:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append(item)
            self.received += 1
            self._condition.notify()

    def get(self, timeout: float | None = None) -> Any | None:
        with self._condition:
            if not self._items and not self._closed:
                self._condition.wait(timeout)
            return self._items.popleft() if self._items else None

    def clear(self) -> None:
        with self._condition:
            self._items.clear()

    def close(self) -> None:
        with self._condition:
            self._closed = True
            self._condition.notify_all()
