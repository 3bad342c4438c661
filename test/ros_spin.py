"""Running rclpy nodes for the ROS tests: spin in a thread, wait on conditions, stop in rclpy's order.

Imported by ``test_ros_*.py`` after their ``importorskip("rclpy")``: this module needs rclpy.

Teardown order (issue 12: "cannot use Destroyable because destruction was requested" in about one
run in six, from destroying nodes while the spinner was still inside a callback): stop the spinning
loop and join its thread first, so no callback runs any more; then shut the executor down, destroy
the nodes, and then shut the context down (the fixture's last step). The executor is single-threaded so that "the thread has
joined" means "no callback is in flight" on every rclpy version; the nodes under test do their heavy
work in their own threads or processes, so one executor thread serves them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from rclpy.executors import SingleThreadedExecutor


def wait_for(condition: Callable[[], bool], timeout: float = 10.0, interval: float = 0.02) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` passes; the sleep is the polling interval only."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(interval)
    return bool(condition())


class Spinner:
    """Spins ``nodes`` of ``context`` in a background thread until :meth:`shutdown`."""

    def __init__(self, context, *nodes) -> None:
        self.context = context
        self.nodes = list(nodes)
        self.executor = SingleThreadedExecutor(context=context)
        for node in self.nodes:
            self.executor.add_node(node)
        self.errors: list[BaseException] = []  # raised by callbacks; shutdown() fails the test with them
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="test_spinner", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception as error:  # noqa: BLE001 - a callback raised: keep serving, report at the end
                self.errors.append(error)

    def shutdown(self) -> None:
        """Join the spinner, then shut the executor down and destroy the nodes (the context is the caller's)."""
        self._stop.set()
        self._thread.join(timeout=30.0)
        assert not self._thread.is_alive(), "the spinner did not stop"
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        assert not self.errors, f"callbacks raised: {self.errors!r}"


def call(node, srv_type, name: str, request=None, timeout: float = 30.0):
    """Call service ``name`` from ``node`` (spun by a :class:`Spinner`) and return the response."""
    client = node.create_client(srv_type, name)
    try:
        assert client.wait_for_service(timeout_sec=timeout), f"{name} not available"
        future = client.call_async(request if request is not None else srv_type.Request())
        assert wait_for(future.done, timeout), f"{name} did not answer"
        return future.result()
    finally:
        node.destroy_client(client)
