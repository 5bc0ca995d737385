"""pal-gripper: one commander per PAL controller. The same-controller check covered one process only: a second
teletouch process (or any ROS node) publishing JointTrajectory to the controller's command topic went unnoticed, and
the controller followed whichever sent last. Start-up now asks the ROS graph and refuses, naming the other node and
its namespace; while running, the same look once a second faults on a commander that appears later; and
allow_other_publishers: true runs anyway, naming the others in status() and the log (once each).

Real ROS 2 (rclpy, DDS on this host): a peer plays the robot (its joint_state_broadcaster and the controller's
subscription), other participants play the other commanders."""

from __future__ import annotations

import threading
import time

import pytest
import rclpy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

from fakes import realtime
from fakes.realtime import configure_fails
from fakes.ros2_peer import Peer, domain_fixture, own_domain

from teletouch import HardwareError
from teletouch.plugins.devices.pal_gripper import JOINTS, PalGripper
from teletouch.testing import Harness

DOMAIN = own_domain(1, base=20)   # this module's own ROS_DOMAIN_ID, different per test run
COMMAND = "/tiago/gripper_controller/joint_trajectory"

pytestmark = pytest.mark.timeout(90)


_localhost_ros = domain_fixture(DOMAIN, scope="function")


class Robot:
    """/joint_states every 10 ms and the controller's subscription to the command topic."""

    def __init__(self):
        self.peer = Peer("robot", DOMAIN)
        self.pub = self.peer.node.create_publisher(JointState, "/joint_states", 10)
        self.peer.listen(JointTrajectory, COMMAND, "commands")
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self):
        while not self._stop.is_set():
            msg = JointState()
            now = time.time()
            msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), int((now % 1) * 1e9)
            msg.name, msg.position = list(JOINTS), [0.02, 0.02]
            msg.velocity, msg.effort = [0.0, 0.0], [0.0, 0.0]
            self.pub.publish(msg)
            time.sleep(0.01)

    def close(self):
        self._stop.set()
        self._th.join(2)
        self.peer.close()


class Commander:
    """Another ROS 2 program with a publisher on ``topic`` (its own participant; DDS announces it without spinning)."""

    def __init__(self, name: str, namespace: str = "/", topic: str = COMMAND, mtype=JointTrajectory):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=DOMAIN)
        self.node = rclpy.create_node(name, namespace=namespace, context=self.ctx, start_parameter_services=False)
        self.pub = self.node.create_publisher(mtype, topic, 1)

    def close(self):
        self.node.destroy_node()
        self.ctx.try_shutdown()


@pytest.fixture
def robot():
    r = Robot()
    yield r
    r.close()


def harness(logs=None, **params) -> Harness:
    h = Harness(PalGripper, dict({"namespace": "tiago", "domain_id": DOMAIN, "connect_timeout": 8.0}, **params))
    h.ctx.clock_kind = "wall"
    if logs is not None:
        h.ctx._log = logs.append
    return h


def seen_by_graph(topic: str, n: int, gone: bool = False) -> bool:
    """Whether a fresh participant sees ``n`` publishers on ``topic`` (``gone``: fewer than ``n``) within the wait."""
    probe = Commander("probe", topic="/unused_probe_topic", mtype=String)
    try:
        count = probe.node.count_publishers
        return realtime.wait_for(lambda: (count(topic) < n) if gone else (count(topic) >= n))
    finally:
        probe.close()


def step(h, cmd=0.04):
    h.t = time.monotonic()
    return h.step(h.t, opening_command=cmd)


def test_another_process_with_the_same_node_name_is_refused_at_start(robot):
    """A second teletouch process with the same graph (the same node name, teletouch_pal_gripper) was accepted."""
    other = Commander("teletouch_pal_gripper")
    try:
        assert seen_by_graph(COMMAND, 1)
        configure_fails(harness(discovery_wait=5.0),   # an upper bound: the look ends when it finds the other
                        r"/tiago/gripper_controller/joint_trajectory \(ROS_DOMAIN_ID \d+\) has another "
                        r"JointTrajectory publisher: node /teletouch_pal_gripper: two commanders")
    finally:
        other.close()
    assert seen_by_graph(COMMAND, 1, gone=True)
    h = harness()
    with h:      # the other one gone: it starts
        step(h)
        assert h.comp.status()["other_publishers"] == []


def test_another_node_is_named_with_its_namespace(robot):
    other = Commander("teleop", namespace="/lab")
    try:
        assert seen_by_graph(COMMAND, 1)
        configure_fails(harness(discovery_wait=5.0), r"has another JointTrajectory publisher: node /lab/teleop: .*"
                                   r"allow_other_publishers: true")
    finally:
        other.close()


def test_a_publisher_of_another_type_is_not_a_commander(robot):
    """DDS does not connect a String publisher to the controller's JointTrajectory subscription."""
    other = Commander("noise", topic=COMMAND, mtype=String)
    try:
        assert seen_by_graph(COMMAND, 1)
        with harness(discovery_wait=1.0) as h:
            step(h)
            assert h.comp.status()["other_publishers"] == []
    finally:
        other.close()


def test_allowed_others_run_and_are_named_once(robot):
    other = Commander("teleop", namespace="/lab")
    logs: list[str] = []
    try:
        assert seen_by_graph(COMMAND, 1)
        with harness(logs, allow_other_publishers=True, discovery_wait=1.0) as h:
            def listed():   # at start-up, or by a run-time check: a new DDS participant may need ~3 s to see it
                step(h)
                time.sleep(0.01)
                return h.comp.status()["other_publishers"] == ["/lab/teleop"]

            assert realtime.wait_for(listed, 15.0), h.comp.status()
            t_end = time.monotonic() + 2.5       # spans two more run-time checks
            while time.monotonic() < t_end:
                step(h)
                time.sleep(0.01)
            assert h.comp.status()["other_publishers"] == ["/lab/teleop"]
            named = [m for m in logs if "/lab/teleop" in m]
            assert len(named) == 1 and "allow_other_publishers: true, running on" in named[0], logs
    finally:
        other.close()


def test_a_commander_that_appears_while_running_faults(robot):
    logs: list[str] = []
    h = harness(logs)
    with h:
        step(h)
        other = Commander("teleop", namespace="/lab")
        try:
            fault: list[str] = []

            def faulted():
                if not fault:
                    try:
                        step(h)
                    except HardwareError as exc:
                        fault.append(str(exc))
                    time.sleep(0.01)
                return bool(fault)

            assert realtime.wait_for(faulted, 15.0), h.comp.status()
            assert "node /lab/teleop, which appeared while running" in fault[0]
            assert h.comp.status()["other_publishers"] == ["/lab/teleop"]
            assert sum("/lab/teleop" in m for m in logs) == 1
        finally:
            other.close()
