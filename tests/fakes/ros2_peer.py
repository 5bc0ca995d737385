"""Another ROS 2 program for the bridge tests: a participant of its own (its own rclpy Context and DDS participant,
never the global one), with an executor spinning in a thread."""

from __future__ import annotations

import threading
import time
from typing import Any

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

    def listen(self, mtype: Any, topic: str, key: str, qos: QoSProfile | None = None, timed: bool = False) -> None:
        """Collect the messages of ``topic`` in ``got[key]``: the messages, or (arrival Unix time, message) pairs with
        ``timed``."""
        self.got[key] = []
        got = self.got[key]
        cb = (lambda m: got.append((time.time(), m))) if timed else got.append
        self.node.create_subscription(mtype, topic, cb, qos or QoSProfile(depth=50))

    def close(self) -> None:
        self._stop.set()
        self.th.join(2)
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)
