"""pal-gripper on lab day: a wrong ``namespace`` or ``controller`` failed start-up with "no controller subscribes to
/gripper_controller/joint_trajectory ...; check the robot is up, the namespace and controller name" and nothing of what
the ROS graph did hold. The error names the JointTrajectory subscriptions it sees now, each with the
namespace/controller params that select it and the JointState topic the driver would then read; a wrong
joint_states_topic is answered with the topics that do have a JointState publisher. Real ROS 2 (rclpy, DDS on
loopback), an own ROS_DOMAIN_ID."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.pal_gripper_node import PalGripperNode  # noqa: E402
from fakes.realtime import configure_error, configure_fails  # noqa: E402
from fakes.ros2_peer import Peer, domain_fixture, own_domain  # noqa: E402

from teletouch.plugins.devices.pal_gripper import PalGripper  # noqa: E402
from teletouch.testing import Harness  # noqa: E402

DOMAIN = own_domain(61, base=20)   # this module's own ROS_DOMAIN_ID, different per test run

pytestmark = pytest.mark.timeout(90)

_localhost_ros = domain_fixture(DOMAIN, scope="function")


def harness(**params):
    # connect_timeout: how long a failing start-up looks (a passing one ends once connected); long enough for DDS to
    # discover the robot on a loaded 2-core machine, which is what the candidates are read from
    h = Harness(PalGripper, dict({"domain_id": DOMAIN, "connect_timeout": 3.0}, **params))
    h.ctx.clock_kind = "wall"
    return h


def start_error(**params) -> str:
    return configure_error(harness(**params))


@pytest.fixture
def robot():
    r = PalGripperNode("/tiago", domain_id=DOMAIN).start()
    yield r
    r.stop()


def suggested(msg: str, topic: str) -> dict[str, str]:
    """The params the error suggests for ``topic``: ``namespace``, ``controller``."""
    m = re.search(re.escape(topic) + r" \(namespace: (\S*), controller: (\w+);", msg)
    assert m, msg
    ns = "" if m.group(1) == '""' else m.group(1)
    return {"namespace": ns, "controller": m.group(2)}


def test_a_wrong_namespace_names_the_controller_there_and_the_params_that_select_it(robot):
    msg = start_error()   # namespace "" (the default): the robot is under /tiago
    assert "no controller subscribes to /gripper_controller/joint_trajectory" in msg, msg
    assert ("/tiago/gripper_controller/joint_trajectory (namespace: /tiago, controller: gripper_controller; "
            "JointState on /joint_states)") in msg, msg
    # and what it suggests does start
    with harness(**suggested(msg, "/tiago/gripper_controller/joint_trajectory"), connect_timeout=10.0) as h:
        assert h.comp.command_topic == "/tiago/gripper_controller/joint_trajectory"


def test_a_wrong_controller_names_the_controller_of_the_namespace(robot):
    msg = start_error(namespace="tiago", controller="gripper_ctrl")
    assert "no controller subscribes to /tiago/gripper_ctrl/joint_trajectory" in msg, msg
    assert "(namespace: /tiago, controller: gripper_controller; JointState on /joint_states)" in msg, msg


class TwoRobots:
    """Two arms' controllers on one graph: /left with a gripper controller and its own JointState topic, /right with
    an arm controller only; plus a JointTrajectory subscription the driver cannot command (no <controller>/
    joint_trajectory form)."""

    def __init__(self):
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.peer = Peer("lab_robots", DOMAIN)
        node = self.peer.node
        self.subs = [node.create_subscription(JointTrajectory, t, lambda m: None, 10)
                     for t in ("/right/arm_controller/joint_trajectory", "/left/gripper_controller/joint_trajectory",
                               "/trajectory_in")]
        self.pub = node.create_publisher(JointState, "/left/joint_states", 10)

    def close(self):
        self.peer.close()


def test_every_controller_seen_is_listed_gripper_first_with_the_state_topic_it_would_need():
    robots = TwoRobots()
    try:
        msg = start_error(namespace="robot")
    finally:
        robots.close()
    left = msg.index("/left/gripper_controller/joint_trajectory (namespace: /left, controller: gripper_controller; "
                     "nothing publishes JointState on /joint_states: set joint_states_topic to one of "
                     "/left/joint_states)")
    right = msg.index("/right/arm_controller/joint_trajectory (namespace: /right, controller: arm_controller;")
    assert left < right, msg   # a gripper's controller first
    assert "/trajectory_in (not <namespace>/<controller>/joint_trajectory: this driver cannot command it)" in msg, msg


def test_nothing_on_the_graph_says_so_and_what_to_check():
    t0 = time.monotonic()
    configure_fails(harness(connect_timeout=0.3), r"no controller subscribes to /gripper_controller/joint_trajectory "
                    r"after 0\.3 s \(ROS_DOMAIN_ID \d+\); no JointTrajectory subscription on the ROS graph \d+\.\d s "
                    r"after joining it, so no controller to suggest: check the robot is up, on this ROS_DOMAIN_ID "
                    r".*ROS_LOCALHOST_ONLY")
    assert time.monotonic() - t0 < 5.0   # looked a moment longer for discovery (GRAPH_WAIT), no more


def test_a_wrong_state_topic_names_the_topics_with_a_joint_state_publisher(robot):
    msg = start_error(namespace="tiago", joint_states_topic="joint_states")   # relative: /tiago/joint_states
    assert "/tiago/joint_states: no message for" in msg, msg
    assert "JointState is published on /joint_states (set joint_states_topic to the one with the finger joints)" in msg
