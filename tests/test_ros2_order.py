"""The subscriber's stamps never go back in time: a message older than the last one taken for a port (a second
publisher on the topic with older stamps, messages out of order) is dropped and counted, not output, with either
``stamps`` mode; a repeat stays a repeat. Real messages over rclpy, loopback only, a ROS_DOMAIN_ID of this module's
own."""

from __future__ import annotations

import time

import pytest
from rclpy.qos import QoSProfile

from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import JointState

from teletouch import Inputs, Sample
from teletouch.recording import ros_time

from fakes.ros2_peer import Peer, SubscribeNode, domain_fixture, own_domain

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(29)
ros_env = domain_fixture(DOMAIN)


class _Sub(SubscribeNode):
    """A ros2-subscribe node on this module's domain, keeping what it outputs."""

    def __init__(self, ns: str, **params):
        super().__init__(DOMAIN, ns, **params)
        self.out: list[tuple[str, Sample]] = []

    def step(self) -> dict[str, Sample]:
        out = self.comp.step(self.ctx.now(), Inputs({})) or {}
        self.out += list(out.items())
        return out

    def send(self, pub, msg) -> dict[str, float]:
        self.deliver(pub, msg)
        return {k: s.value for k, s in self.step().items()}

    def stamps(self, port: str) -> list[float]:
        return [s.stamp for k, s in self.out if k == port]


def _force(value: float, unix: float) -> WrenchStamped:
    m = WrenchStamped()
    m.header.stamp, m.header.frame_id = ros_time(unix), "digit"   # (ros2-subscribe's default frame_id)
    m.wrench.force.z = value
    return m


@pytest.mark.parametrize("stamps", ["message", "arrival"])
def test_an_older_message_is_dropped_and_counted_not_output(stamps):
    ns = f"/s14o_{stamps}"
    sub = _Sub(ns, stamps=stamps)
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, f"{ns}/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(1.0, now)) == {"force": 1.0}
        # a second writer (or a late message) with an older stamp: before, it came out, and with stamps: message
        # the port's stamp went back 0.5 s; with stamps: arrival the old value came out as the newest sample
        assert sub.send(pub, _force(9.0, now - 0.5)) == {}
        assert sub.send(pub, _force(9.0, now - 0.2)) == {}
        st = sub.comp.status()
        assert st["out_of_order"] == 2 and st["duplicates"] == 0 and st["problems"] >= 2, st
        older = [m for m in sub.logs if "older than the last" in m]
        assert len(older) == 1 and "force" in older[0] and "0.500 s" in older[0], sub.logs
        # a newer one comes out again, and the repeat of it is a repeat, not an older message
        newer = _force(2.0, now + 0.01)
        assert sub.send(pub, newer) == {"force": 2.0}
        assert sub.send(pub, newer) == {}
        st = sub.comp.status()
        assert st["duplicates"] == 1 and st["out_of_order"] == 2, st
        s = sub.stamps("force")
        assert len(s) == 2 and s[1] >= s[0], s
    finally:
        sub.close()
        peer.close()


def test_an_older_message_in_the_same_step_does_not_replace_the_newer_one():
    sub = _Sub("/s14o_between")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/s14o_between/force", QoSProfile(depth=50))
        now = time.time()
        sub.deliver(pub, _force(1.0, now))
        sub.deliver(pub, _force(9.0, now - 0.3))   # arrives before the next step: before, it replaced the newer one
        out = sub.step()
        assert {k: s.value for k, s in out.items()} == {"force": 1.0}
        assert sub.comp.status()["out_of_order"] == 1
    finally:
        sub.close()
        peer.close()


def test_older_is_per_port_in_a_joint_state():
    # opening's last stamp is newer than velocity's: a message with both at a stamp between them keeps velocity
    # (newer for it) and drops opening (older for it)
    sub = _Sub("/s14o_js", topics=["joint_states"])
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(JointState, "/s14o_js/joint_states", QoSProfile(depth=50))
        now = time.time()

        def js(stamp, **fields):
            m = JointState()
            m.header.stamp = ros_time(stamp)
            m.name = ["gripper"]
            for k, v in fields.items():
                setattr(m, k, [v])
            return m

        assert sub.send(pub, js(now - 0.2, velocity=0.1)) == {"velocity": 0.1}
        assert sub.send(pub, js(now, position=0.03)) == {"opening": 0.03}
        assert sub.send(pub, js(now - 0.1, position=0.09, velocity=0.2)) == {"velocity": 0.2}
        assert sub.comp.status()["out_of_order"] == 1
        assert sub.send(pub, js(now - 0.05, position=0.08)) == {}
        assert sub.comp.status()["out_of_order"] == 2
    finally:
        sub.close()
        peer.close()


def test_a_clamped_stamp_never_goes_back_before_the_last_one_taken():
    # a sender whose clock is ahead: the first stamp is within max_clock_skew (kept, 1.9 s in the future), the next
    # beyond it (clamped to the arrival time, which is before the first one's stamp): before, the port went back
    # 1.9 s; the newer measurement must still come out, not be dropped
    sub = _Sub("/s14o_clamp", max_clock_skew=2.0)
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/s14o_clamp/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(1.0, now + 1.9)) == {"force": 1.0}
        assert sub.send(pub, _force(2.0, now + 5.0)) == {"force": 2.0}
        s = sub.stamps("force")
        assert len(s) == 2 and s[1] > s[0], s
        st = sub.comp.status()
        assert st["skewed"] == 1 and st["out_of_order"] == 0, st
    finally:
        sub.close()
        peer.close()


def test_a_single_stamp_in_the_future_does_not_silence_the_port():
    # a stamp clamped as too far in the future is not the reference for the next ones' order: a sender's one wrong
    # stamp (5 s ahead) must not drop its right ones for 5 s
    sub = _Sub("/s14o_glitch")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/s14o_glitch/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(1.0, now)) == {"force": 1.0}
        glitch = _force(2.0, now + 5.0)
        assert sub.send(pub, glitch) == {"force": 2.0}
        assert sub.send(pub, glitch) == {}                        # its repeat is still a repeat
        assert sub.send(pub, _force(3.0, now + 0.01)) == {"force": 3.0}
        assert sub.send(pub, _force(9.0, now + 0.005)) == {}      # older than the last right one
        st = sub.comp.status()
        assert st["skewed"] == 1 and st["duplicates"] == 1 and st["out_of_order"] == 1, st
        s = sub.stamps("force")
        assert len(s) == 3 and s[0] < s[1] < s[2], s
    finally:
        sub.close()
        peer.close()
