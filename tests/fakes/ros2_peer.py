"""Another ROS 2 program for the bridge tests: a participant of its own (its own rclpy Context and DDS participant,
never the global one), with an executor spinning in a thread."""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any, Callable, Iterator

import pytest
import rclpy
from rclpy.context import Context as RosContext
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile


class Peer:
    def __init__(self, name: str, domain_id: int):
        self.ctx = RosContext()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node(name, namespace="/peer", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.got: dict[str, list] = {}
        self._stop = threading.Event()
        self.th = threading.Thread(target=self._spin, daemon=True)
        self.th.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.02)

    def listen(self, mtype: Any, topic: str, key: str, qos: QoSProfile | None = None, timed: bool = False) -> Any:
        """Collect the messages of ``topic`` in ``got[key]``: the messages, or (arrival Unix time, message) pairs with
        ``timed``. Returns the subscription (``get_publisher_count()`` says whether it has matched a publisher yet)."""
        self.got[key] = []
        got = self.got[key]
        cb = (lambda m: got.append((time.time(), m))) if timed else got.append
        return self.node.create_subscription(mtype, topic, cb, qos or QoSProfile(depth=50))

    def close(self) -> None:
        self._stop.set()
        self.th.join(2)
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


@contextlib.contextmanager
def localhost_domain(domain_id: int) -> Iterator[None]:
    """ROS_DOMAIN_ID set to a test module's own domain, discovery kept on this host (other people's tests run ROS 2
    on the same machine)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ROS_DOMAIN_ID", str(domain_id))
        mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        mp.setenv("ROS_LOCALHOST_ONLY", "1")
        yield


def wait_until(cond: Callable[[], bool], timeout: float = 15.0, every: Callable[[], Any] | None = None) -> bool:
    """Poll ``cond`` (calling ``every`` before each poll) until it holds or ``timeout`` s pass; whether it held."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if every is not None:
            every()
        if cond():
            return True
        time.sleep(0.02)
    return False
