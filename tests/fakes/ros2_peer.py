"""Another ROS 2 program for the bridge tests: a participant of its own (its own rclpy Context and DDS participant,
never the global one), with an executor spinning in a thread."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from typing import Any, Callable, Iterator

import pytest
import rclpy
from rclpy.context import Context as RosContext
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile

from teletouch import Context
from teletouch.plugins.bridges.ros2 import Ros2Subscribe


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


class SubscribeNode:
    """A ros2-subscribe node (node id "sub", ``namespace`` ``ns``, on ``domain_id``) configured and activated, stepped
    by hand on a wall clock: its Context in ``ctx``, its log lines in ``logs``. The tests' subclasses step it and keep
    what it outputs in the form their assertions read."""

    def __init__(self, domain_id: int, ns: str, **params: Any):
        self.logs: list[str] = []
        self.ctx = Context(clock_kind="wall", log=self.logs.append)
        self.comp = Ros2Subscribe(dict({"domain_id": domain_id, "namespace": ns}, **params), node_id="sub",
                                  ctx=self.ctx)
        self.comp.configure()
        self.comp.activate()

    def deliver(self, pub: Any, msg: Any) -> None:
        """Publish one message on ``pub`` (once both ends are matched) and wait until the node has dealt with it (taken
        or refused); no step."""
        subs = [s for s in self.comp._subs if s.topic_name == pub.topic_name]
        assert wait_until(lambda: pub.get_subscription_count() >= 1 and subs[0].get_publisher_count() >= 1), \
            f"{pub.topic_name}: never matched"
        h = self.handled()
        pub.publish(msg)
        assert wait_until(lambda: self.handled() > h), f"message not handled: {self.comp.status()}"

    def handled(self) -> int:
        """Messages the subscription callbacks have dealt with, taken or refused."""
        st = self.comp.status()
        counted = ("received", "bad", "unstamped", "duplicates", "out_of_order", "wrong_frame")
        return sum(st.get(k, 0) for k in counted)

    def close(self) -> None:
        self.comp.deactivate()
        self.comp.close()


@contextlib.contextmanager
def localhost_domain(domain_id: int) -> Iterator[None]:
    """ROS_DOMAIN_ID set to a test module's own domain, discovery kept on this host (other people's tests run ROS 2
    on the same machine)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ROS_DOMAIN_ID", str(domain_id))
        mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        mp.setenv("ROS_LOCALHOST_ONLY", "1")
        yield


def own_domain(salt: int, base: int = 120) -> int:
    """A ROS_DOMAIN_ID of a test module's own: ``base`` plus 0-89 from this process's id and the module's ``salt``
    (each module of a ``base`` passes a salt of its own), so that the modules of one run, and other people's test
    runs on the same machine, do not meet. The bridge tests use base 120, the PAL gripper's 20."""
    return base + (os.getpid() * 7 + salt) % 90


def domain_fixture(domain_id: int, scope: str = "module"):
    """An autouse fixture that runs the module's tests (``scope="module"``) or each of them (``"function"``) in
    localhost_domain(domain_id); bind it to a name in the test module: ``ros_env = domain_fixture(DOMAIN)``."""
    @pytest.fixture(scope=scope, autouse=True)
    def ros_env() -> Iterator[None]:
        with localhost_domain(domain_id):
            yield
    return ros_env


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
