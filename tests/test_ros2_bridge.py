"""ros2-publish / ros2-subscribe against independent rclpy peers over real DDS (loopback only)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from rclpy.qos import QoSProfile

from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64

from teletouch import Context, GraphValidationError, Inputs, Sample
from teletouch.component import _Slot
from teletouch.plugins.bridges.ros2 import Ros2Publish, Ros2Subscribe
from teletouch.recording import image_msg, ros_time
from teletouch.testing import load_text, make_registry

from fakes.ros2_peer import Peer as _Peer
from fakes.ros2_peer import domain_fixture, own_domain, wait_until

pytestmark = pytest.mark.timeout(120)

# a domain of our own: other engineers run ROS 2 tests on this machine at the same time
DOMAIN = own_domain(1)
ros_env = domain_fixture(DOMAIN)


class Peer(_Peer):
    """A peer on this module's domain."""

    def __init__(self, name: str):
        super().__init__(name, DOMAIN)

    def listen(self, mtype, topic, key, qos=None):
        super().listen(mtype, topic, key, qos, timed=True)


_wait = wait_until


def _offset(ctx) -> float:
    """time.time() - ctx.now() from the tightest of 20 bracketed reads: the test's own reading must not be the one
    a preemption between two reads shifts by milliseconds."""
    best = (float("inf"), 0.0)
    for _ in range(20):
        a = ctx.now()
        u = time.time()
        b = ctx.now()
        best = min(best, (b - a, u - 0.5 * (a + b)))
    return best[1]


def test_publish_standard_messages_with_preserved_stamps():
    ctx = Context(clock_kind="wall")
    pub = Ros2Publish({"domain_id": DOMAIN, "namespace": "/t1", "frame_id": "gel", "joint_name": "finger"},
                      node_id="pub", ctx=ctx)
    slots = {n: _Slot() for n in pub.inputs}
    inputs = Inputs(slots)
    peer = Peer("listener")
    try:
        peer.listen(WrenchStamped, "/t1/force", "force")
        peer.listen(Image, "/t1/image", "image")
        peer.listen(Image, "/t1/depth", "depth")
        peer.listen(JointState, "/t1/joint_states", "joints")
        peer.listen(Float64, "/t1/value", "value")
        pub.configure()
        pub.activate()
        assert not rclpy.ok()  # the global default context is never initialised by the bridge
        img = np.random.default_rng(1).integers(0, 255, (32, 24, 3), dtype=np.uint8)
        depth = np.linspace(0, 1e-3, 32 * 24, dtype=np.float32).reshape(32, 24)
        sent: list[tuple[float, float]] = []

        def publish_once():
            now = ctx.now()
            stamp = now - 0.010  # measured 10 ms ago
            slots["force"].sample = Sample(1.25, stamp)
            slots["image"].sample = Sample(img, stamp)
            slots["depth"].sample = Sample(depth, stamp)
            slots["opening"].sample = Sample(0.042, stamp)
            slots["velocity"].sample = Sample(-0.01, stamp)
            slots["value"].sample = Sample(7.5, stamp)
            pub.step(now, inputs)
            sent.append((stamp, _offset(ctx)))

        assert _wait(lambda: all(peer.got[k] for k in peer.got), every=publish_once), \
            {k: len(v) for k, v in peer.got.items()}
        n = len(sent)
        pub.step(ctx.now(), inputs)  # nothing new: nothing published
        assert pub.published == 5 * n
        _, m = peer.got["force"][-1]
        assert m.wrench.force.z == 1.25 and m.wrench.force.x == 0 and m.header.frame_id == "gel"
        stamp_s = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
        # header.stamp = the sample's graph stamp on ROS (Unix) time, within clock-mapping jitter
        assert any(abs(stamp_s - (s + off)) < 1e-3 for s, off in sent)
        _, im = peer.got["image"][-1]
        assert im.encoding == "bgr8" and (im.height, im.width, im.step) == (32, 24, 72)
        assert np.array_equal(np.frombuffer(im.data, np.uint8).reshape(32, 24, 3), img)
        _, dm = peer.got["depth"][-1]
        assert dm.encoding == "32FC1" and np.array_equal(np.frombuffer(dm.data, np.float32).reshape(32, 24), depth)
        _, js = peer.got["joints"][-1]
        assert list(js.name) == ["finger"] and list(js.position) == [0.042] and list(js.velocity) == [-0.01]
        assert list(js.effort) == []  # not wired: left empty, as JointState allows
        assert peer.got["value"][-1][1].data == 7.5
    finally:
        pub.deactivate()
        pub.close()
        peer.close()


def test_subscribe_maps_stamps_to_the_graph_clock_and_converts_messages():
    ctx = Context(clock_kind="wall")
    sub = Ros2Subscribe({"domain_id": DOMAIN, "namespace": "/t2", "reliability": "best_effort",
                         "topics": ["force", "image", "depth", "joint_states", "value"], "joint_name": "gripper"},
                        node_id="sub", ctx=ctx)
    sub.configure()
    sub.activate()
    peer = Peer("talker")
    qos = QoSProfile(depth=10)
    try:
        pubs = {k: peer.node.create_publisher(t, f"/t2/{k}", qos) for k, t in
                (("force", WrenchStamped), ("image", Image), ("depth", Image), ("joint_states", JointState),
                 ("value", Float64))}
        got: dict[str, list[Sample]] = {}

        def collect():
            for k, s in (sub.step(ctx.now(), Inputs({})) or {}).items():
                got.setdefault(k, []).append(s)

        def send_force(age, value):
            m = WrenchStamped()
            m.header.stamp, m.header.frame_id = ros_time(time.time() - age), "digit"   # (frame_id's default)
            m.wrench.force.z = value
            pubs["force"].publish(m)

        # discovery: keep sending until the first one arrives; then every topic's two ends (DDS matches them one at
        # a time, and a message sent before the subscription's end has matched may never arrive: the messages
        # below are sent once each)
        assert _wait(lambda: "force" in got, every=lambda: (send_force(0.2, 1.0), collect()))
        ours = {s.topic_name: s for s in sub._subs}
        assert _wait(lambda: all(p.get_subscription_count() >= 1 and ours[p.topic_name].get_publisher_count() >= 1
                                 for p in pubs.values())), "not matched"
        # (the force topic delivers in order: once a marker has come out, nothing of the discovery is on its way)
        send_force(0.0, 2.0)
        assert _wait(lambda: got["force"][-1].value == 2.0, every=collect)
        got.clear()
        time.sleep(0.25)   # the next stamp (0.2 s old) must be newer than the marker's: an older one is dropped
        before = ctx.now()
        send_force(0.2, 3.0)
        after = ctx.now()
        assert _wait(lambda: "force" in got, every=collect)
        s = got["force"][-1]
        assert s.value == 3.0
        # the age survives the bridge: stamped 0.2 s before it was sent, whenever it arrived and was stepped out (a
        # bound on the time of sending, not on the delivery, which a loaded machine delays)
        assert before - 0.2 - 0.05 <= s.stamp <= after - 0.2 + 0.05, (before, s.stamp, after)
        skewed = sub.skewed
        before = ctx.now()
        send_force(-5.0, 4.0)  # 5 s in the future: a clock problem, clamped to the arrival time
        assert _wait(lambda: got["force"][-1].value == 4.0, every=collect)
        assert sub.skewed == skewed + 1 and before <= got["force"][-1].stamp <= ctx.now()

        rgb = np.zeros((4, 5, 3), np.uint8)
        rgb[..., 0] = 200  # red in RGB order
        m = image_msg(rgb, time.time(), "digit")
        m.encoding = "rgb8"
        pubs["image"].publish(m)
        mm = np.full((4, 5), 3, np.uint16)  # 16UC1: millimetres by ROS convention
        pubs["depth"].publish(image_msg(mm, time.time(), "digit"))
        js = JointState()
        js.header.stamp = ros_time(time.time())
        js.name, js.position, js.velocity, js.effort = ["other", "gripper"], [0.5, 0.03], [0.0, 0.01], [1.0, 2.5]
        pubs["joint_states"].publish(js)
        pubs["value"].publish(Float64(data=9.0))
        assert _wait(lambda: all(k in got for k in ("image", "depth", "opening", "value")), every=collect), got
        img = got["image"][-1].value
        assert img.shape == (4, 5, 3) and img[0, 0].tolist() == [0, 0, 200]  # BGR
        d = got["depth"][-1].value
        assert d.dtype == np.float32 and np.allclose(d, 0.003)
        assert got["opening"][-1].value == 0.03 and got["velocity"][-1].value == 0.01
        assert got["effort"][-1].value == 2.5

        bad = sub.bad
        m = image_msg(np.zeros((4, 5), np.uint16), time.time(), "digit")  # not a colour image on the image topic
        pubs["image"].publish(m)
        other = JointState(name=["other"], position=[0.7])
        pubs["joint_states"].publish(other)
        # then a marker on the same topic (a velocity only): the topic delivers in order, so once the marker has
        # come out the other joint's state has been dealt with (waited for, not a fixed time)
        marker = JointState(name=["gripper"], velocity=[0.02])
        marker.header.stamp = ros_time(time.time())
        pubs["joint_states"].publish(marker)
        assert _wait(lambda: sub.bad == bad + 1)
        assert _wait(lambda: got["velocity"][-1].value == 0.02, every=collect)
        assert got["opening"][-1].value == 0.03  # another joint's state is not ours
        assert sub.status()["received"] >= 6
    finally:
        sub.deactivate()
        sub.close()
        peer.close()


def test_bridge_params_and_clock_are_validated():
    reg = make_registry("teletouch.plugins.bridges.ros2")
    with pytest.raises(GraphValidationError) as ei:
        load_text("""
clock: wall
nodes:
  - {id: sub, plugin: ros2-subscribe, params: {reliability: sometimes, topics: [force, torque]}}
""", reg)
    text = str(ei.value)
    assert "<test>:4" in text and "reliability" in text and "topics" in text
    with pytest.raises(GraphValidationError, match="cannot run on the simulated clock"):
        load_text("""
clock: sim
nodes:
  - {id: sub, plugin: ros2-subscribe}
""", reg)
    # a publisher may run on the simulated clock (stamps = Unix time of graph time 0 + graph time)
    load_text("""
clock: sim
nodes:
  - {id: src, plugin: mock-sensor}
  - {id: pub, plugin: ros2-publish, inputs: {value: src.value}}
""", reg)
