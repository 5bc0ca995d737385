"""pal-gripper's QoS: reliability and depth of its /joint_states subscription and its command publisher are
parameters (defaults as before: best-effort state, reliable commands, depth 1, volatile), and a robot endpoint whose
QoS cannot connect to the driver's is named, with the topic, the policy and both sides' values, in the start-up
error, in status() and in the log (before, start-up said only "no controller subscribes" / "no message").

A peer on real ROS 2 (its own DDS participant) plays the robot: a joint_state_broadcaster publishing
sensor_msgs/JointState and a joint_trajectory_controller subscription, each with the QoS a test chooses."""

from __future__ import annotations

import threading
import time

import pytest
from pydantic import ValidationError
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from fakes import realtime
from fakes.realtime import configure_fails
from fakes.ros2_peer import Peer, domain_fixture, own_domain

from teletouch.plugins.devices.pal_gripper import JOINTS, PalGripper
from teletouch.testing import Harness

DOMAIN = own_domain(6, base=20)   # this module's own ROS_DOMAIN_ID, different per test run
COMMAND = "/tiago/gripper_controller/joint_trajectory"
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

pytestmark = pytest.mark.timeout(60)


_localhost_ros = domain_fixture(DOMAIN, scope="function")


#: connect_timeout of the start-ups that must fail: what such a test waits, long enough for DDS to discover the robot
#: on a loaded 2-core machine (before that, the error cannot name the robot's incompatible endpoint)
FAILING_CONNECT = 5.0


def harness(logs: list[str] | None = None, **params) -> Harness:
    # connect_timeout: a failure bound (a start-up that connects ends once connected)
    h = Harness(PalGripper, dict({"namespace": "tiago", "domain_id": DOMAIN, "connect_timeout": 10.0}, **params))
    h.ctx.clock_kind = "wall"
    if logs is not None:
        h.ctx._log = logs.append
    return h


class Robot:
    """/joint_states published every 10 ms with ``state_qos``; the controller's subscription with ``command_qos``
    (None: no controller)."""

    def __init__(self, name: str, state_qos: QoSProfile, command_qos: QoSProfile | None):
        self.peer = Peer(name, DOMAIN)
        self.pub = self.peer.node.create_publisher(JointState, "/joint_states", state_qos)
        if command_qos is not None:
            self.peer.listen(JointTrajectory, COMMAND, "commands", qos=command_qos)
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = JointState()
            now = time.time()
            msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), int((now % 1) * 1e9)
            msg.name = list(JOINTS)
            msg.position, msg.velocity, msg.effort = [0.02, 0.02], [0.0, 0.0], [0.0, 0.0]
            self.pub.publish(msg)
            time.sleep(0.01)

    def close(self) -> None:
        self._stop.set()
        self._th.join(2.0)
        self.peer.close()


def test_a_reliable_state_subscription_against_a_best_effort_broadcaster_is_named_at_start_up():
    robot = Robot("be_robot", BEST_EFFORT, RELIABLE)
    try:
        configure_fails(harness(state_reliability="reliable", connect_timeout=FAILING_CONNECT),
                        r"/joint_states: no message .*; topic /joint_states: this subscription and a publisher"
                        r"( of node /peer/be_robot)? have incompatible QoS \(RELIABILITY: reliable here, best_effort "
                        r"there\): nothing flows between the two; set state_reliability: best_effort")
    finally:
        robot.close()


def test_a_best_effort_command_publisher_against_the_reliable_controller_is_named_at_start_up():
    robot = Robot("rel_robot", RELIABLE, RELIABLE)
    try:
        configure_fails(harness(command_reliability="best_effort", connect_timeout=FAILING_CONNECT),
                        rf"no controller subscribes to {COMMAND} after .*; topic {COMMAND}: this publisher and a "
                        rf"subscription( of node /peer/rel_robot)? have incompatible QoS \(RELIABILITY: best_effort "
                        rf"here, reliable there\): nothing flows between the two; the controller subscribes "
                        rf"reliable: set command_reliability: reliable")
    finally:
        robot.close()


def test_with_the_defaults_a_latched_controller_subscription_is_named_at_start_up():
    """The defaults unchanged (volatile commands): a controller subscribing transient_local never matches; start-up
    said only 'no controller subscribes'."""
    robot = Robot("latched_robot", RELIABLE, LATCHED)
    try:
        configure_fails(harness(connect_timeout=FAILING_CONNECT),
                        rf"no controller subscribes to {COMMAND} .*\(DURABILITY: volatile here, "
                        rf"transient_local there\)")
    finally:
        robot.close()


def test_an_incompatible_peer_while_running_is_in_status_and_the_log_once():
    robot = Robot("good_robot", RELIABLE, RELIABLE)
    logs: list[str] = []
    h = harness(logs, state_reliability="reliable", state_depth=5, command_depth=2)
    other = Peer("stray_tool", DOMAIN)
    try:
        h.__enter__()   # reliable state from a reliable broadcaster: connects
        assert h.comp.status()["incompatible_qos"] == 0 and h.comp.status()["qos_problems"] == []
        assert h.comp.pub.qos_profile.depth == 2
        stray = other.node.create_publisher(JointState, "/joint_states", BEST_EFFORT)   # e.g. a replay tool
        assert realtime.wait_for(lambda: h.comp.status()["incompatible_qos"] >= 1, realtime.WAIT), h.comp.status()
        expected = ("topic /joint_states: this subscription and a publisher of node /peer/stray_tool have "
                    "incompatible QoS (RELIABILITY: reliable here, best_effort there): nothing flows between the "
                    "two; set state_reliability: best_effort to hear a best-effort /joint_states publisher")
        # the peer's node is named once discovery has brought its name (status() describes it afresh)
        assert realtime.wait_for(lambda: h.comp.status()["qos_problems"] == [expected]), h.comp.status()
        logged = [line for line in logs if "(RELIABILITY: reliable here, best_effort there)" in line]
        assert len(logged) == 1 and logged[0].startswith("topic /joint_states: this subscription and a publisher"), \
            logs
        stray.destroy()
    finally:
        other.close()
        h.__exit__(None, None, None)
        robot.close()


def test_qos_params_are_checked_naming_the_field():
    p = PalGripper.Params()
    assert (p.state_reliability, p.state_depth, p.command_reliability, p.command_depth) == \
        ("best_effort", 1, "reliable", 1)
    for bad in ({"state_reliability": "reliabel"}, {"command_depth": 0}, {"command_durability": "transient_local"}):
        with pytest.raises(ValidationError) as err:
            PalGripper.Params(**bad)
        assert next(iter(bad)) in str(err.value)
