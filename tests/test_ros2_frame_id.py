"""ros2-subscribe reads header.frame_id: a WrenchStamped or Image of another frame (a wrist force/torque sensor's
wrench on the force topic, another camera's image) is refused, not taken as the fingertip's; JointState's frame is not
read. Real messages over rclpy, loopback only, a ROS_DOMAIN_ID of this module's own."""

from __future__ import annotations

import time

import numpy as np
import pytest
from rclpy.qos import QoSProfile

from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import Image, JointState

from teletouch import Inputs
from teletouch.recording import image_msg, ros_time

from fakes.ros2_peer import Peer, SubscribeNode, domain_fixture, own_domain

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(37)
ros_env = domain_fixture(DOMAIN)


class _Sub(SubscribeNode):
    def __init__(self, ns: str, **params):
        super().__init__(DOMAIN, ns, **params)

    def send(self, pub, msg) -> dict:
        """Publish one message, wait until the node has dealt with it, step once."""
        self.deliver(pub, msg)
        return {k: s.value for k, s in (self.comp.step(self.ctx.now(), Inputs({})) or {}).items()}


def _force(value: float, unix: float, frame: str) -> WrenchStamped:
    m = WrenchStamped()
    m.header.stamp, m.header.frame_id = ros_time(unix), frame
    m.wrench.force.z = value
    return m


def test_a_wrench_of_another_frame_is_refused_and_cannot_disorder_the_expected_one():
    sub = _Sub("/fr1")
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/fr1/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(1.0, now - 0.2, "digit")) == {"force": 1.0}
        # a wrist F/T sensor on the same topic, newer stamps: before, its 25 N went to the operator's hand
        assert sub.send(pub, _force(25.0, now - 0.1, "wrist_ft")) == {}
        assert sub.send(pub, _force(26.0, now - 0.05, "wrist_ft")) == {}
        assert sub.send(pub, _force(27.0, now - 0.04, "tool0")) == {}     # a third sender: counted, not logged
        st = sub.comp.status()
        assert st["wrong_frame"] == 3 and st["problems"] >= 3 and st["received"] == 1, st
        lines = [m for m in sub.logs if "frame_id" in m]
        assert len(lines) == 1 and "'wrist_ft', expected 'digit'" in lines[0], sub.logs   # logged once per topic
        # the refused messages' newer stamps did not become the port's last one: the next fingertip force is taken
        assert sub.send(pub, _force(1.5, now - 0.15, "digit")) == {"force": 1.5}
        assert sub.comp.status()["out_of_order"] == 0
    finally:
        sub.close()
        peer.close()


def test_frame_id_null_takes_any_frame_and_logs_the_first():
    sub = _Sub("/fr2", frame_id=None)
    peer = Peer("talker", DOMAIN)
    try:
        pub = peer.node.create_publisher(WrenchStamped, "/fr2/force", QoSProfile(depth=50))
        now = time.time()
        assert sub.send(pub, _force(1.0, now - 0.1, "tool0")) == {"force": 1.0}
        assert sub.send(pub, _force(2.0, now - 0.05, "other")) == {"force": 2.0}
        assert sub.comp.status()["wrong_frame"] == 0
        lines = [m for m in sub.logs if "frame_id" in m]
        assert len(lines) == 1 and "'tool0'" in lines[0] and "frame_id: null takes any frame" in lines[0], sub.logs
    finally:
        sub.close()
        peer.close()


def test_a_chosen_frame_id_is_the_one_taken_on_image_and_depth_topics_and_joint_states_are_not_checked():
    sub = _Sub("/fr3", frame_id="gel_cam", topics=["image", "depth", "joint_states"])
    peer = Peer("talker", DOMAIN)
    try:
        pubs = {k: peer.node.create_publisher(t, f"/fr3/{k}", QoSProfile(depth=50))
                for k, t in (("image", Image), ("depth", Image), ("joint_states", JointState))}
        now = time.time()
        img = np.zeros((4, 5, 3), np.uint8)
        assert sub.send(pubs["image"], image_msg(img, now - 0.2, "digit")) == {}
        got = sub.send(pubs["image"], image_msg(img, now - 0.1, "gel_cam"))
        assert list(got) == ["image"] and got["image"].shape == (4, 5, 3)
        d = np.full((4, 5), 1e-4, np.float32)
        assert sub.send(pubs["depth"], image_msg(d, now - 0.1, "camera_depth")) == {}
        assert list(sub.send(pubs["depth"], image_msg(d, now - 0.05, "gel_cam"))) == ["depth"]
        js = JointState(name=["gripper"], position=[0.03])
        js.header.stamp, js.header.frame_id = ros_time(now - 0.05), "base_link"
        assert sub.send(pubs["joint_states"], js) == {"opening": 0.03}
        st = sub.comp.status()
        assert st["wrong_frame"] == 2 and st["bad"] == 0, st
        assert sum("'digit', expected 'gel_cam'" in m for m in sub.logs) == 1, sub.logs
        assert sum("'camera_depth', expected 'gel_cam'" in m for m in sub.logs) == 1, sub.logs
    finally:
        sub.close()
        peer.close()
