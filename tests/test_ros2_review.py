"""Review of the ROS 2 bridge: JointState fields that are not finite or that come in separate messages, over real
rclpy messages between independent participants (loopback only, a ROS_DOMAIN_ID of this module's own)."""

from __future__ import annotations

import math
import time

import pytest
from rclpy.qos import QoSProfile

from sensor_msgs.msg import JointState

from teletouch import Context, Inputs, Sample
from teletouch.component import _Slot
from teletouch.plugins.bridges.ros2 import Ros2Publish, Ros2Subscribe
from teletouch.recording import ros_time

from fakes.ros2_peer import Peer, SubscribeNode, domain_fixture, own_domain, wait_until

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(13)
ros_env = domain_fixture(DOMAIN)


class _Sub(SubscribeNode):
    """A ros2-subscribe node on joint_states on this module's domain, collecting what it outputs."""

    def __init__(self, ns: str, **params):
        super().__init__(DOMAIN, ns, **dict({"topics": ["joint_states"]}, **params))
        self.out: list[dict[str, Sample]] = []

    def collect(self) -> dict[str, float]:
        got = self.comp.step(self.ctx.now(), Inputs({})) or {}
        self.out.append(got)
        return {k: s.value for k, s in got.items()}

    def handled(self) -> int:
        st = self.comp.status()
        return sum(st[k] for k in ("received", "bad", "unstamped", "duplicates"))

    def matched(self, topic: str, count_publisher) -> bool:
        sub = next(s for s in self.comp._subs if s.topic_name == topic)
        return count_publisher() >= 1 and sub.get_publisher_count() >= 1


def _joints(stamp: float, **fields) -> JointState:
    m = JointState(name=["gripper"], **fields)
    m.header.stamp = ros_time(stamp)
    return m


def test_an_infinite_opening_is_left_out_and_the_other_fields_go_on():
    """docs/ros2.md: 'a NaN or inf JointState field is left out, the message's other fields go on'. An inf
    position was taken for millimetres (inf > max_opening) and refused the whole message, velocity and effort
    with it, under a misleading 'millimetres' log line."""
    sub = _Sub("/rv1")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(JointState, "/rv1/joint_states", QoSProfile(depth=50))
        assert wait_until(lambda: sub.matched("/rv1/joint_states", pub.get_subscription_count))

        def send(msg) -> dict[str, float]:
            h = sub.handled()
            pub.publish(msg)
            assert wait_until(lambda: sub.handled() > h), sub.comp.status()
            return sub.collect()

        # the first message after discovery comes out (nothing of the discovery is on its way any more)
        assert send(_joints(time.time(), position=[0.02])) == {"opening": 0.02}
        bad = sub.comp.bad
        got = send(_joints(time.time(), position=[math.inf], velocity=[0.01], effort=[-3.0]))
        assert got == {"velocity": 0.01, "effort": -3.0}
        assert sub.comp.bad == bad + 1
        assert not any("millimetres" in m for m in sub.logs), sub.logs
        assert any("opening is not finite" in m for m in sub.logs), sub.logs
        # millimetres are still refused, the whole message
        assert send(_joints(time.time(), position=[42.0], velocity=[5.0])) == {}
        assert any("millimetres" in m for m in sub.logs), sub.logs
    finally:
        sub.close()
        peer.close()


def test_fields_of_one_measurement_sent_in_two_messages_all_come_out():
    """The publisher reads its inputs without a lock while the gripper driver's rate group writes them one port
    after the other: a step can see the new opening beside the old velocity, send the opening, and send the new
    velocity (same stamp: the same measurement) at its next step. The subscriber took the second message for a
    repeat of the first (same header.stamp on the topic) and dropped the velocity: a repeat is per field."""
    ctx = Context(clock_kind="wall")
    pub = Ros2Publish({"domain_id": DOMAIN, "namespace": "/rv2", "topics": ["joint_states"]}, node_id="pub",
                      ctx=ctx)
    slots = {n: _Slot() for n in pub.inputs}
    inputs = Inputs(slots)
    sub = _Sub("/rv2")
    try:
        pub.configure()
        pub.activate()
        assert wait_until(lambda: sub.matched("/rv2/joint_states",
                                              pub._pubs["joint_states"].get_subscription_count))

        def step(**fields) -> dict[str, float]:
            h = sub.handled()
            for k, s in fields.items():
                slots[k].sample = s
            n = pub.published
            pub.step(ctx.now(), inputs)
            assert pub.published == n + 1
            assert wait_until(lambda: sub.handled() > h), sub.comp.status()
            return sub.collect()

        t0 = ctx.now()
        assert step(opening=Sample(0.03, t0), velocity=Sample(0.0, t0)) == {"opening": 0.03, "velocity": 0.0}
        t1 = ctx.now()
        assert step(opening=Sample(0.031, t1)) == {"opening": 0.031}   # the velocity of t1 not written yet
        got = step(velocity=Sample(0.002, t1))                          # ... now it is: the same measurement
        assert got == {"velocity": 0.002}
        assert sub.out[-1]["velocity"].stamp == pytest.approx(sub.out[-2]["opening"].stamp, abs=1e-6)
        assert sub.comp.status()["duplicates"] == 0
        # a real repeat (the same message again) is still not output again
        h = sub.handled()
        m = _joints(time.time(), position=[0.032], velocity=[0.001])
        raw = pub._pubs["joint_states"]
        raw.publish(m)
        assert wait_until(lambda: sub.handled() > h)
        assert sub.collect() == {"opening": 0.032, "velocity": 0.001}
        h = sub.handled()
        raw.publish(m)
        assert wait_until(lambda: sub.handled() > h)
        assert sub.collect() == {}
        assert sub.comp.status()["duplicates"] == 1
    finally:
        pub.deactivate()
        pub.close()
        sub.close()


@pytest.mark.parametrize("cls", [Ros2Publish, Ros2Subscribe])
def test_without_the_ros2_message_packages_configure_names_the_extra(monkeypatch, cls):
    # before: a bare ModuleNotFoundError ("No module named 'geometry_msgs'") that named no extra to install
    import sys

    from teletouch import ComponentFault
    from teletouch.testing import Harness

    monkeypatch.setitem(sys.modules, "geometry_msgs.msg", None)   # what an environment without the extra gives
    with pytest.raises(ComponentFault, match=r"pip install 'teletouch\[ros2\]'"):
        with Harness(cls, {"topics": ["force"]}):
            pass
