"""Faults of the ROS 2 bridge a lab meets when it splits the loop across machines: stamps from another clock (zero,
invalid, old, repeated), values that are not finite or not in SI, QoS and message types that do not match, names and
domain ids that ROS refuses, and the rclpy lifecycle. Real messages over rclpy, loopback only.

Every test uses its own namespace, and the module its own ROS_DOMAIN_ID, so that tests (and other people's test
runs on the same machine) do not see each other's messages.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
import types

import numpy as np
import pytest
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from builtin_interfaces.msg import Time
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64

from teletouch import Component, Context, GraphValidationError, Inputs, Kind, Sample, hookimpl
from teletouch.component import _Slot
from teletouch.plugins.bridges.ros2 import Ros2Publish
from teletouch.recording import image_msg, ros_time
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry

from fakes.ros2_peer import Peer as _Peer
from fakes.ros2_peer import SubscribeNode, domain_fixture, own_domain, wait_until

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(3)
ros_env = domain_fixture(DOMAIN)


class Peer(_Peer):
    """A peer on this module's domain."""

    def __init__(self, name: str):
        super().__init__(name, DOMAIN)


_wait = wait_until


class Sub(SubscribeNode):
    """A ros2-subscribe node on this module's domain, collecting what it outputs."""

    def __init__(self, ns: str, **params):
        super().__init__(DOMAIN, ns, **params)
        self.out: list[tuple[float, str, Sample]] = []   # (step time, port, sample)

    def collect(self):
        t = self.ctx.now()
        for k, s in (self.comp.step(t, Inputs({})) or {}).items():
            self.out.append((t, k, s))

    def values(self, port):
        return [s.value for _, k, s in self.out if k == port]

    def matched(self, pub) -> bool:
        """Whether DDS has matched ``pub`` and this node's subscription to its topic, both ends (DDS matches them
        one at a time: a message sent before the subscription's end has matched may never arrive)."""
        subs = [s for s in self.comp._subs if s.topic_name == pub.topic_name]
        return pub.get_subscription_count() >= 1 and bool(subs) and subs[0].get_publisher_count() >= 1

    def send(self, pub, msg) -> dict:
        """Publish one message (once both ends are matched), wait until it has been handled, step once: what that
        step outputs."""
        assert _wait(lambda: self.matched(pub)), f"{pub.topic_name}: publisher and subscription never matched"
        h = self.handled()
        pub.publish(msg)
        assert _wait(lambda: self.handled() > h), f"message not handled: {self.comp.status()}"
        n = len(self.out)
        self.collect()
        return {k: s.value for _, k, s in self.out[n:]}


def _force(value, stamp, axis="z"):
    m = WrenchStamped()
    m.header.stamp, m.header.frame_id = stamp, "digit"   # (ros2-subscribe's default frame_id)
    setattr(m.wrench.force, axis, value)
    return m


def _connect(pub, sub, make):
    """Wait for discovery (both ends of the topic matched), check that ``make()`` comes through, then forget it.
    Nothing is published before both ends have matched, so no message of the discovery is still on its way when a
    test starts counting (a fixed quiet time after a burst of messages is no proof on a loaded machine)."""
    assert sub.send(pub, make()), "the first message after discovery did not come out"
    sub.out.clear()


# ---------------------------------------------------------------------------------------------- stamps and staleness
def test_unusable_stamps_are_refused_and_old_ones_keep_their_age():
    sub = Sub("/f1")
    peer = Peer("talker")
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/f1/force", QoSProfile(depth=50))
        # 10 s old: the 5 s old message below must be newer than the last one taken (an older one is dropped)
        _connect(pub, sub, lambda: _force(1.0, ros_time(time.time() - 10.0)))
        st = dict(sub.comp.status())
        # none of these comes out: before, a zero stamp came out as a sample stamped 56 years ago (it fails every
        # max_age on a wire, a fault of the consumer, and nothing said why)
        assert sub.send(pub, _force(2.0, Time(sec=0, nanosec=0))) == {}                     # the sender never stamps
        assert sub.send(pub, _force(3.0, Time(sec=int(time.time()), nanosec=4_000_000_000))) == {}  # nanosec > 1e9
        assert sub.send(pub, _force(4.0, Time(sec=-5, nanosec=0))) == {}                     # before 1970
        s = sub.comp.status()
        assert s["unstamped"] == st["unstamped"] + 1 and s["bad"] == st["bad"] + 2
        assert any("header.stamp is zero" in m and "stamps: arrival" in m for m in sub.logs), sub.logs
        assert any("nanosec" in m for m in sub.logs), sub.logs

        # a publisher whose clock is 5 s behind: the sample keeps its (stale) age, and the reason is reported
        assert sub.send(pub, _force(5.0, ros_time(time.time() - 5.0))) == {"force": 5.0}
        t, _, sample = sub.out[-1]
        assert t - sample.stamp == pytest.approx(5.0, abs=0.5) and not sample.is_fresh(t, 0.1)
        s = sub.comp.status()
        assert s["late"] == st["late"] + 1 and s["lag_s"] == pytest.approx(5.0, abs=0.5)
        assert any("behind" in m for m in sub.logs), sub.logs
    finally:
        sub.close()
        peer.close()


def test_a_repeated_message_is_not_output_again_with_a_fresh_stamp():
    # stamps: arrival (clocks not synchronised): a sender that repeats its last message (its estimator died, it
    # re-sends what it has) must not keep the force fresh on this side
    sub = Sub("/f2", stamps="arrival")
    peer = Peer("talker")
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/f2/force", QoSProfile(depth=50))
        _connect(pub, sub, lambda: _force(1.0, ros_time(time.time() - 10.0)))   # older than the one below
        last = _force(2.0, ros_time(time.time() - 1.0))
        assert sub.send(pub, last) == {"force": 2.0}
        for _ in range(5):
            assert sub.send(pub, last) == {}        # before: a new sample each time, stamped on arrival
        assert sub.comp.status()["duplicates"] == 5
    finally:
        sub.close()
        peer.close()


class _SlowStart(Component):
    """Takes a while to configure, like a device driver that connects or a model that loads."""

    name = "slow-start"
    kind = Kind.ESTIMATOR
    inputs: dict = {}
    outputs: dict = {}

    def configure(self):
        time.sleep(1.0)

    def step(self, t, inputs):
        return None


def test_samples_received_during_start_up_are_not_stamped_in_the_future():
    # the wall clock's graph time starts when every node has started; a message that arrived while a slow node
    # was starting must keep its age on the graph clock that runs, not come out stamped in the future (it was
    # then "fresh" a whole start-up time later, after its publisher had died)
    reg = make_registry("teletouch.plugins.bridges.ros2",
                        types.SimpleNamespace(__name__="slowplug", teletouch_components=hookimpl(lambda: [_SlowStart])))
    spec = load_text(f"""
clock: wall
faults: {{max_overruns: 0}}
nodes:
  - {{id: sub, plugin: ros2-subscribe, rate: 200, params: {{domain_id: {DOMAIN}, namespace: /f3}}}}
  - {{id: slow, plugin: slow-start, rate: 10}}
""", reg)
    peer = Peer("talker")
    stop = threading.Event()
    pub = peer.node.create_publisher(WrenchStamped, "/f3/force", QoSProfile(depth=5))

    def talk():
        while not stop.is_set():
            pub.publish(_force(1.0, ros_time(time.time())))
            time.sleep(0.1)

    th = threading.Thread(target=talk, daemon=True)
    th.start()
    try:
        rt = Runtime(spec, log=lambda m: None)
        outs: list[tuple[float, float]] = []
        rt.add_tap(lambda n, t, o: outs.append((t, o["force"].stamp)) if n == "sub" and "force" in o else None)
        result = rt.run(1.0)
    finally:
        stop.set()
        th.join(2)
        peer.close()
    assert result.status == "ok", result.message
    assert outs, "nothing received"
    ahead = max(s - t for t, s in outs)
    assert ahead < 0.05, outs[:3]


# ---------------------------------------------------------------------------------------------- values and units
def test_non_finite_values_never_come_out():
    sub = Sub("/f4", topics=["force", "depth", "joint_states", "value"])
    peer = Peer("talker")
    try:
        pubs = {k: peer.node.create_publisher(t, f"/f4/{k}", QoSProfile(depth=50)) for k, t in
                (("force", WrenchStamped), ("depth", Image), ("joint_states", JointState), ("value", Float64))}
        _connect(pubs["force"], sub, lambda: _force(1.0, ros_time(time.time())))
        bad = sub.comp.bad
        assert sub.send(pubs["force"], _force(math.nan, ros_time(time.time()))) == {}
        assert sub.send(pubs["force"], _force(-math.inf, ros_time(time.time()))) == {}
        d = np.full((4, 5), 1e-3, np.float32)
        d[1, 2] = np.nan
        assert sub.send(pubs["depth"], image_msg(d, time.time(), "digit")) == {}
        js = JointState(name=["gripper"], position=[0.03], velocity=[math.nan], effort=[])
        js.header.stamp = ros_time(time.time())
        assert sub.send(pubs["joint_states"], js) == {"opening": 0.03}     # the NaN field is left out
        assert sub.send(pubs["value"], Float64(data=math.inf)) == {}
        assert sub.comp.bad == bad + 5
        assert any("not finite" in m for m in sub.logs), sub.logs
        for _, port, s in sub.out:
            assert np.all(np.isfinite(s.value)), (port, s)
    finally:
        sub.close()
        peer.close()


def test_millimetres_and_malformed_messages_are_refused():
    sub = Sub("/f5", topics=["force", "image", "depth", "joint_states"])
    peer = Peer("talker")
    try:
        pubs = {k: peer.node.create_publisher(t, f"/f5/{k}", QoSProfile(depth=50)) for k, t in
                (("force", WrenchStamped), ("image", Image), ("depth", Image), ("joint_states", JointState))}
        _connect(pubs["force"], sub, lambda: _force(1.0, ros_time(time.time())))
        bad = sub.comp.bad
        now = time.time()
        js = JointState(name=["gripper"], position=[42.0], velocity=[5.0])   # mm and mm/s in the m, m/s fields
        js.header.stamp = ros_time(now)
        assert sub.send(pubs["joint_states"], js) == {}
        js2 = JointState(name=["a", "gripper"], position=[0.01])              # 1 position for 2 names
        js2.header.stamp = ros_time(now + 1e-3)
        assert sub.send(pubs["joint_states"], js2) == {}
        # 1.5 mm written as 1.5 m
        assert sub.send(pubs["depth"], image_msg(np.full((4, 5), 1.5, np.float32), now, "digit")) == {}
        empty = image_msg(np.zeros((4, 5, 3), np.uint8), now, "digit")
        empty.height, empty.width, empty.step, empty.data = 0, 0, 0, b""
        assert sub.send(pubs["image"], empty) == {}
        short = image_msg(np.zeros((4, 5, 3), np.uint8), now + 1e-3, "digit")
        short.step = 5                                                        # 5 bytes a row for 5 bgr8 pixels
        assert sub.send(pubs["image"], short) == {}
        good = JointState(name=["gripper"], position=[0.042])
        good.header.stamp = ros_time(time.time())
        assert sub.send(pubs["joint_states"], good) == {"opening": 0.042}
        assert sub.comp.bad == bad + 5
        text = "\n".join(sub.logs)
        assert "max_opening" in text and "millimetres" in text and "max_depth" in text, text
        assert "empty" in text and "step" in text, text
    finally:
        sub.close()
        peer.close()


def test_a_force_on_another_axis_is_reported():
    sub = Sub("/f6")
    peer = Peer("talker")
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/f6/force", QoSProfile(depth=50))
        _connect(pub, sub, lambda: _force(1.0, ros_time(time.time())))
        pub.publish(_force(2.0, ros_time(time.time()), axis="x"))   # the sender's force_axis is x, ours z
        assert _wait(lambda: sub.comp.status()["off_axis"] == 1, every=sub.collect)
        assert any("force_axis" in m and "x" in m for m in sub.logs), sub.logs
    finally:
        sub.close()
        peer.close()


# ---------------------------------------------------------------------------------------------- the publisher side
def test_publisher_sends_each_measurement_once_and_only_finite_values():
    ctx = Context(clock_kind="wall", log=lambda m: logs.append(m))
    logs: list[str] = []
    pub = Ros2Publish({"domain_id": DOMAIN, "namespace": "/f7", "depth": 20}, node_id="pub", ctx=ctx)
    slots = {n: _Slot() for n in pub.inputs}
    inputs = Inputs(slots)
    peer = Peer("listener")
    try:
        peer.listen(WrenchStamped, "/f7/force", "force")
        peer.listen(JointState, "/f7/joint_states", "joints")
        pub.configure()
        pub.activate()

        def refresh(name, value, stamp):
            # `isolate: process` hands a node a new Sample object for the same measurement at every step
            slots[name].sample = Sample(value, stamp)

        def discover():
            now = ctx.now()
            refresh("force", 1.0, now)
            refresh("opening", 0.04, now)
            refresh("velocity", 0.0, now)
            pub.step(now, inputs)

        assert _wait(lambda: peer.got["force"] and peer.got["joints"], every=discover)
        # discovery: the publishers now exist and are matched. One last measurement marks the end of it: each topic
        # delivers in order (reliable), so once the marker has arrived no message of the discovery is still on its
        # way (a fixed wait was no proof on a loaded machine); from here on count what goes out
        marker = ctx.now()
        refresh("force", 1.5, marker)
        refresh("opening", 0.039, marker)
        refresh("velocity", 0.0, marker)
        pub.step(marker, inputs)
        assert _wait(lambda: peer.got["force"][-1].wrench.force.z == 1.5 and peer.got["joints"][-1].position[0]
                     == 0.039), "the marker never arrived"
        peer.got["force"].clear()
        peer.got["joints"].clear()
        n0 = pub.published
        s1 = ctx.now()
        for _ in range(30):                 # the same measurement, stepped 30 times
            refresh("force", 2.0, s1)
            pub.step(ctx.now(), inputs)
            time.sleep(0.002)
        refresh("force", math.nan, ctx.now())   # a NaN estimate: not on the wire
        pub.step(ctx.now(), inputs)
        # the velocity's source stops (its last sample stays), the opening goes on: the velocity must not be
        # re-sent with the opening's newer stamps
        for i in range(5):
            refresh("opening", 0.04 + i * 1e-3, ctx.now())
            pub.step(ctx.now(), inputs)
            time.sleep(0.002)
        refresh("force", 3.0, ctx.now())
        pub.step(ctx.now(), inputs)
        assert _wait(lambda: any(m.wrench.force.z == 3.0 for m in peer.got["force"]) and len(peer.got["joints"]) >= 5)
        time.sleep(0.2)
        assert [m.wrench.force.z for m in peer.got["force"]] == [2.0, 3.0]
        assert pub.published - n0 == 2 + 5 and pub.status()["bad"] == 1
        assert any("not finite" in m for m in logs), logs
        assert [list(m.velocity) for m in peer.got["joints"]] == [[]] * 5
        assert [m.position[0] for m in peer.got["joints"]] == pytest.approx([0.04 + i * 1e-3 for i in range(5)])
    finally:
        pub.deactivate()
        pub.close()
        peer.close()


# ---------------------------------------------------------------------------------------------- QoS and types
def test_a_late_subscriber_never_gets_a_latched_old_force(tmp_path):
    reg = make_registry("teletouch.plugins.bridges.ros2")
    with pytest.raises(GraphValidationError) as ei:
        load_text("""
clock: wall
nodes:
  - {id: sub, plugin: ros2-subscribe, params: {durability: transient_local, stamps: arrival}}
""", reg)
    text = str(ei.value)
    assert "<test>:4" in text and "durability" in text and "latched" in text, text

    # a transient_local publisher keeps its last force for late joiners; the (volatile) subscriber joins later
    peer = Peer("talker")
    try:
        qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub = peer.node.create_publisher(WrenchStamped, "/f8/force", qos)
        pub.publish(_force(5.0, ros_time(time.time())))
        time.sleep(0.3)
        sub = Sub("/f8", stamps="arrival")
        try:
            assert _wait(lambda: sub.matched(pub))   # both ends: what the publisher sends from now on arrives
            time.sleep(0.5)
            sub.collect()
            assert sub.out == []
            pub.publish(_force(6.0, ros_time(time.time())))           # a new one does arrive
            assert _wait(lambda: 6.0 in sub.values("force"), every=sub.collect)
            assert 5.0 not in sub.values("force")
        finally:
            sub.close()
    finally:
        peer.close()


def test_incompatible_qos_and_message_types_are_reported():
    sub = Sub("/f9", topics=["force", "value"])   # reliable (the default)
    peer = Peer("talker")
    other = Peer("other")
    try:
        be = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)   # e.g. a driver's sensor-data QoS
        be_pub = peer.node.create_publisher(WrenchStamped, "/f9/force", be)
        wrong = other.node.create_publisher(WrenchStamped, "/f9/value", QoSProfile(depth=5))  # a wrench on a Float64
        assert _wait(lambda: sub.comp.status()["incompatible_qos"] >= 1 and sub.comp.status()["wrong_type"] >= 1,
                     every=lambda: (be_pub.publish(_force(1.0, ros_time(time.time()))),
                                    wrong.publish(_force(1.0, ros_time(time.time()))), sub.collect())), \
            (sub.comp.status(), sub.logs)
        assert sub.out == []
        text = "\n".join(sub.logs)
        assert "RELIABILITY" in text and "best_effort" in text, text
        assert "geometry_msgs/msg/WrenchStamped" in text and "std_msgs/msg/Float64" in text and "/f9/value" in text
    finally:
        sub.close()
        peer.close()
        other.close()


# ---------------------------------------------------------------------------------------------- parameters
def test_bad_names_and_topics_are_refused_at_validation_naming_the_field():
    reg = make_registry("teletouch.plugins.bridges.ros2")
    with pytest.raises(GraphValidationError) as ei:
        load_text("""
clock: wall
nodes:
  - id: sub
    plugin: ros2-subscribe
    params:
      force_topic: my force
      namespace: /tele-touch
      node_name: 9lives
      topics: []
  - {id: pub, plugin: ros2-publish, params: {value_topic: /teletouch/force}}
  - {id: pub2, plugin: ros2-publish, params: {image_topic: "cam/"}}
""", reg)
    text = str(ei.value)
    for field, line in (("force_topic", 7), ("namespace", 8), ("node_name", 9), ("topics", 10)):
        assert f"<test>:{line}" in text and field in text, (field, text)
    assert "<test>:11" in text and "'value_topic'" in text and "is also force_topic's topic" in text, text
    assert "<test>:12" in text and "image_topic" in text, text
    assert "topic name" in text and "namespace" in text


@pytest.mark.parametrize("value", ["500", "abc"])
def test_a_bad_ros_domain_id_is_a_clear_start_up_error(value):
    # rcl reads ROS_DOMAIN_ID; 500 made Fast DDS end the whole process (exit 1, no message, no safe state)
    code = """
import sys
from teletouch import Context
from teletouch.plugins.bridges.ros2 import Ros2Subscribe
sub = Ros2Subscribe({}, node_id="sub", ctx=Context(clock_kind="wall"))
try:
    sub.configure()
except Exception as exc:
    print("ERROR", type(exc).__name__, exc)
finally:
    sub.close()
print("STILL RUNNING")
"""
    env = dict(os.environ, ROS_DOMAIN_ID=value)
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "STILL RUNNING" in p.stdout, (p.returncode, p.stdout, p.stderr[-2000:])
    assert "ERROR ComponentFault" in p.stdout and "ROS_DOMAIN_ID" in p.stdout and "232" in p.stdout, p.stdout


# ---------------------------------------------------------------------------------------------- lifecycle
def test_two_bridges_in_one_process_and_a_second_run():
    from rclpy.signals import get_current_signal_handlers_options

    reg = make_registry("teletouch.plugins.bridges.ros2")
    text = f"""
clock: wall
faults: {{max_overruns: 0}}
nodes:
  - {{id: src, plugin: mock-sensor, rate: 60, params: {{signal: constant, amplitude: 2.0}}}}
  - {{id: pub, plugin: ros2-publish, rate: 120, params: {{domain_id: {DOMAIN}, namespace: /f10}},
     inputs: {{force: src.value}}}}
  - {{id: sub, plugin: ros2-subscribe, rate: 200, params: {{domain_id: {DOMAIN}, namespace: /f10}}}}
"""
    before = {th.ident for th in threading.enumerate()}
    handlers = get_current_signal_handlers_options()
    for _ in range(2):
        rt = Runtime(load_text(text, reg), log=lambda m: None)
        got: list[float] = []
        rt.add_tap(lambda n, t, o: got.append(o["force"].value) if n == "sub" and "force" in o else None)
        result = rt.run(3.0)
        assert result.status == "ok", result.message
        assert got and set(got) == {2.0}
        assert not rclpy.ok()  # the global default context is left alone
        assert get_current_signal_handlers_options() == handlers   # rclpy's SIGINT/SIGTERM handlers not touched
        left = [th.name for th in threading.enumerate() if th.ident not in before]
        assert left == [], left
