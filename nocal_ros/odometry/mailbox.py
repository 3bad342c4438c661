"""Handing frames from a ROS executor to the odometry's worker thread, and replaying frames that way."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
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


@dataclass
class RateReplay:
    """What :func:`replay_at_rate` saw: items handled and dropped, each handled item's latency, and the
    worker thread's CPU time for each (its cost with the other threads' work left out: the machine's
    share of a live stream's budget that the handling itself takes)."""

    handled: int
    dropped: int
    latencies_ms: list[float]
    cpu_ms: list[float]


def replay_at_rate(items: Sequence[Any], rate_hz: float, handle: Callable[[int, Any], None]) -> RateReplay:
    """Offer ``items`` at ``rate_hz`` in real time to a worker thread the way the odometry node does.

    A one-slot :class:`FrameMailbox`: an item that arrives while the worker is busy replaces the waiting
    one and is counted as dropped. The worker calls ``handle(index, item)`` on the newest; the latency
    is from the item's arrival to the end of its handling. Returns when every item is handled or dropped.
    """
    mailbox = FrameMailbox(latest_only=True)
    latencies: list[float] = []
    cpu: list[float] = []
    handled = [0]

    def work() -> None:
        while True:
            entry = mailbox.get(timeout=0.5)
            if entry is None:
                return
            arrived, index, item = entry
            started = time.thread_time()
            handle(index, item)
            cpu.append((time.thread_time() - started) * 1e3)
            latencies.append((time.perf_counter() - arrived) * 1e3)
            handled[0] += 1

    worker = threading.Thread(target=work, name="replay_at_rate", daemon=True)
    worker.start()
    start = time.perf_counter()
    for index, item in enumerate(items):
        pause = start + index / rate_hz - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        mailbox.put((time.perf_counter(), index, item))
    mailbox.close()
    worker.join()
    return RateReplay(handled[0], mailbox.dropped, latencies, cpu)
