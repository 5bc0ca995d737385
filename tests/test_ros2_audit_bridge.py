"""ROS 2 bridge, outside audit: one camera frame's messages carry identical header stamps (an exact-time synchroniser
pairs them), a looped bag with ``stamps: arrival`` is heard again on its next pass (``restart_after``), forces outside
the port's plausible range are refused as a NaN is, and ``lag_s`` of a stamp clamped as in the future is the raw
stamp's (as docs/ros2.md says). Real messages over rclpy, loopback only, a ROS_DOMAIN_ID of this module's own."""

from __future__ import annotations

import time
import types

import numpy as np
import pytest
from rclpy.qos import QoSProfile

from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import Image

from teletouch import Context, Inputs, Sample
from teletouch.component import _Slot
from teletouch.plugins.bridges import ros2 as ros2_module
from teletouch.plugins.bridges.ros2 import Ros2Publish, Ros2Subscribe
from teletouch.recording import ros_time

from fakes.ros2_peer import Peer, SubscribeNode, domain_fixture, own_domain, wait_until

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(53)
ros_env = domain_fixture(DOMAIN)


class _Sub(SubscribeNode):
    """A ros2-subscribe node on this module's domain, keeping what it outputs."""

    def __init__(self, ns: str, **params):
        super().__init__(DOMAIN, ns, **params)
        self.out: list[tuple[str, Sample]] = []

    def send(self, pub, msg) -> dict[str, float]:
        self.deliver(pub, msg)
        out = self.comp.step(self.ctx.now(), Inputs({})) or {}
        self.out += list(out.items())
        return {k: s.value for k, s in out.items()}


def _force(value: float, unix: float, frame: str = "digit") -> WrenchStamped:
    m = WrenchStamped()
    m.header.stamp, m.header.frame_id = ros_time(unix), frame
    m.wrench.force.z = value
    return m


# ------------------------------------------------------------------------------------- one frame, one header.stamp
class _SlewingTime:
    """The ``time`` module, with a system clock that NTP slews: each ``time()`` reads 1 us further ahead than the one
    before (the Unix to graph offset then changes between two conversions of one graph stamp, as it does, by less,
    between any two readings of a real clock)."""

    def __init__(self):
        self.extra = 0.0

    def time(self) -> float:
        self.extra += 1e-6
        return time.time() + self.extra

    def __getattr__(self, name):
        return getattr(time, name)


@pytest.mark.parametrize("clock", ["steady", "slewing"])
def test_one_frames_messages_carry_identical_stamps(monkeypatch, clock):
    """Audit: the force and the image of one camera frame carried header stamps up to 768 ns apart (only about half
    bit-identical): each message converted the graph stamp to ROS time with a fresh reading of the Unix to graph
    offset, in float seconds (238 ns apart near 1.7e9 s). A ROS user syncing on equal stamps (message_filters
    ExactTime) missed the pairs."""
    if clock == "slewing":
        monkeypatch.setattr(ros2_module, "time", _SlewingTime())
    ns = f"/a3_{clock}"
    ctx = Context(clock_kind="wall")
    pub = Ros2Publish({"domain_id": DOMAIN, "namespace": ns}, node_id="pub", ctx=ctx)
    slots = {n: _Slot() for n in pub.inputs}
    inputs = Inputs(slots)
    peer = Peer("sync_listener", DOMAIN)
    try:
        subs = {k: peer.listen(mtype, f"{ns}/{k}", k, QoSProfile(depth=100))
                for k, mtype in (("force", WrenchStamped), ("image", Image), ("depth", Image))}
        pub.configure()
        pub.activate()
        assert wait_until(lambda: all(pub._pubs[k].get_subscription_count() >= 1 and subs[k].get_publisher_count() >= 1
                                      for k in subs)), "publishers and listener never matched"
        img = np.zeros((16, 12, 3), np.uint8)
        depth = np.zeros((16, 12), np.float32)
        frames = 20
        for k in range(frames):
            stamp = ctx.now() - 0.005   # the frame's capture time
            # as a pipeline publishes them: the image first, the depth a step later, the force after the estimator
            for port, value in (("image", img), ("depth", depth), ("force", 0.1 * k)):
                slots[port].sample = Sample(value, stamp)
                pub.step(ctx.now(), inputs)
                time.sleep(0.002)
        assert wait_until(lambda: all(len(peer.got[k]) >= frames for k in subs)), \
            {k: len(v) for k, v in peer.got.items()}

        def stamps(key):
            return [(m.header.stamp.sec, m.header.stamp.nanosec) for m in peer.got[key]]

        force, image, depth_ = stamps("force"), stamps("image"), stamps("depth")
        assert len(set(force)) == frames   # one stamp per frame
        # the exact-equality check of an ExactTime synchroniser: every frame's three messages pair up
        assert force == image == depth_, [(f, i, d) for f, i, d in zip(force, image, depth_) if not f == i == d]
    finally:
        pub.deactivate()
        pub.close()
        peer.close()


def test_stamp_memory_is_bounded():
    ctx = Context(clock_kind="wall")
    pub = Ros2Publish({"domain_id": DOMAIN, "namespace": "/a3_mem", "topics": ["force"]}, node_id="pub", ctx=ctx)
    pub._clock = types.SimpleNamespace(to_ros=lambda t: t + 1.7e9)
    pub._stamps = {}
    first = pub._stamp_ns(0.5)
    for k in range(ros2_module.STAMP_MEMORY + 10):
        pub._stamp_ns(1.0 + k * 1e-3)
    assert len(pub._stamps) == ros2_module.STAMP_MEMORY and 0.5 not in pub._stamps
    assert first == 1_700_000_000_500_000_000


# --------------------------------------------------------------------------------------------- a looped bag
def test_a_looped_bag_is_heard_on_its_next_pass_with_restart_after():
    """Audit: ``ros2 bag play --loop`` into ``stamps: arrival``: the second pass starts with the recording's first
    stamp again, 3 s older than the last one taken, and was dropped as out of order (the controller went stale).
    With restart_after it is the sender starting again; an older stamp within restart_after is still dropped."""
    sub = _Sub("/a4", stamps="arrival", frame_id="force", restart_after=0.5)
    peer = Peer("bagplay", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/a4/force", QoSProfile(depth=50))
        t0 = time.time() - 3600.0   # the recording's stamps: an hour ago
        bag = [t0 + 0.1 * k for k in range(31)]   # 3 s
        for rnd in range(2):
            for k, t in enumerate(bag):
                assert sub.send(pub, _force(1.0 + k, t, "force")) == {"force": 1.0 + k}, (rnd, k, sub.comp.status())
        st = sub.comp.status()
        assert st["restarts"] == 1 and st["out_of_order"] == 0 and st["problems"] == 0, st
        assert any("restart_after" in m and "3.000 s older" in m for m in sub.logs), sub.logs
        stamps = [s.stamp for _, s in sub.out]
        assert all(b > a for a, b in zip(stamps, stamps[1:]))   # stamped on arrival: never back
        # a message out of order by less than restart_after is still an old message
        assert sub.send(pub, _force(99.0, bag[-1] - 0.2, "force")) == {}
        assert sub.comp.status()["out_of_order"] == 1 and sub.comp.status()["restarts"] == 1
    finally:
        sub.close()
        peer.close()


def test_without_restart_after_a_looped_bag_is_dropped_and_restart_after_needs_arrival_stamps():
    sub = _Sub("/a4b", stamps="arrival", frame_id="force")
    peer = Peer("bagplay", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/a4b/force", QoSProfile(depth=50))
        t0 = time.time() - 3600.0
        assert sub.send(pub, _force(1.0, t0 + 3.0, "force")) == {"force": 1.0}
        assert sub.send(pub, _force(2.0, t0, "force")) == {}   # the next pass: dropped, as documented
        assert sub.comp.status()["out_of_order"] == 1 and sub.comp.status()["restarts"] == 0
    finally:
        sub.close()
        peer.close()
    with pytest.raises(ValueError, match="restart_after: only with stamps: arrival"):
        Ros2Subscribe.Params(restart_after=0.5)
    assert Ros2Subscribe.Params(restart_after="500ms", stamps="arrival").restart_after == 0.5


# ------------------------------------------------------------------------------------------ implausible forces
def test_forces_outside_the_plausible_range_are_refused_like_a_nan():
    """Audit: 1e6 N, 1e300 N and -5 N were passed on (a controller's peak force of 1e300 N). docs/ports.md: a grip
    force is >= 0 N, 0 without contact; the project's force calibrations take 200 N as implausible for a tactile
    sensor. Refused, counted (bad) and logged once per kind, no sample: as a NaN is."""
    sub = _Sub("/a5")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/a5/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(2.0, now)) == {"force": 2.0}
        bad0 = sub.comp.status()["bad"]
        for k, v in enumerate((1e6, 1e300, 200.5, -5.0, -0.06, float("nan"))):
            assert sub.send(pub, _force(v, now + 0.001 * (k + 1))) == {}, v
        st = sub.comp.status()
        assert st["bad"] == bad0 + 6 and st["problems"] >= 6, st
        assert sum("larger than max_force" in m for m in sub.logs) == 1, sub.logs
        assert sum("below min_force" in m for m in sub.logs) == 1, sub.logs
        assert any("1e+06 N > 200 N" in m for m in sub.logs), sub.logs
        # the limits themselves, and noise around the sensor's zero (output as 0: a grip force is >= 0)
        assert sub.send(pub, _force(200.0, now + 0.1)) == {"force": 200.0}
        assert sub.send(pub, _force(-0.03, now + 0.2)) == {"force": 0.0}
        assert sub.send(pub, _force(0.5, now + 0.3)) == {"force": 0.5}
    finally:
        sub.close()
        peer.close()


def test_force_limits_are_params_with_a_unit():
    sub = _Sub("/a5b", max_force="300 N", min_force="-1 N")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/a5b/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(250.0, now)) == {"force": 250.0}
        assert sub.send(pub, _force(-0.5, now + 0.01)) == {"force": 0.0}
        assert sub.send(pub, _force(301.0, now + 0.02)) == {}
    finally:
        sub.close()
        peer.close()
    assert Ros2Subscribe.Params().max_force == 200.0 and Ros2Subscribe.Params().min_force == -0.05
    with pytest.raises(ValueError, match=r"max_force \(8000 N\).*mN in the N field"):
        Ros2Subscribe.Params(max_force=8000)   # millinewtons typed in the newton field: the guard would be off
    with pytest.raises(ValueError, match="min_force"):
        Ros2Subscribe.Params(min_force=0.5)


# --------------------------------------------------------------------------------------------------- lag_s
def test_lag_s_of_a_clamped_future_stamp_is_the_raw_stamps():
    """docs/ros2.md: lag_s is arrival minus the header.stamp as sent, also for a stamp clamped as in the future
    (negative: how far ahead the sender's clock is), while the sample itself is stamped on arrival."""
    sub = _Sub("/a2")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/a2/force", QoSProfile(depth=50))
        assert sub.send(pub, _force(0.5, time.time())) == {"force": 0.5}   # (discovery: matched from here on)
        assert sub.send(pub, _force(1.0, time.time() + 1.0)) == {"force": 1.0}
        st = sub.comp.status()
        assert st["skewed"] == 1 and st["lag_s"] == pytest.approx(-1.0, abs=0.1), st
        t, sample = sub.ctx.now(), sub.out[-1][1]
        assert 0.0 <= t - sample.stamp < 0.5   # the sample: clamped to its arrival
    finally:
        sub.close()
        peer.close()
