"""ROS 2 bridge items left open by the audit: publishers made before the first sample (it was lost during DDS
discovery), and ports wired to a topic the node does not carry. Real DDS over loopback, a domain of this module's
own."""

from __future__ import annotations

import pytest
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import Image, JointState

from teletouch import ComponentFault, Context, Inputs, Sample
from teletouch.component import _Slot
from teletouch.plugins.bridges.ros2 import Ros2Publish, Ros2Subscribe

from fakes.ros2_peer import Peer, domain_fixture, own_domain, wait_until

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(5)
ros_env = domain_fixture(DOMAIN)


def _publisher(ns: str, **params) -> tuple[Ros2Publish, Context, dict[str, _Slot], Inputs]:
    ctx = Context(clock_kind="wall")
    pub = Ros2Publish(dict({"domain_id": DOMAIN, "namespace": ns}, **params), node_id="pub", ctx=ctx)
    slots = {n: _Slot() for n in pub.inputs}
    return pub, ctx, slots, Inputs(slots)


def test_the_first_sample_is_published_to_a_subscriber_that_was_there_before_it():
    """Before, the publisher of a topic was made at its first sample and that sample went out before DDS had
    matched it with the subscriber (volatile: lost); the topic did not exist until then."""
    pub, ctx, slots, inputs = _publisher("/o1")
    peer = Peer("listener", DOMAIN)
    try:
        subs = [peer.listen(WrenchStamped, "/o1/force", "force"), peer.listen(JointState, "/o1/joint_states", "joints")]
        pub.configure()
        # the graph starts (other nodes configure, a model loads): discovery happens meanwhile, before any sample
        assert wait_until(lambda: peer.node.count_publishers("/o1/force") == 1
                          and peer.node.count_publishers("/o1/joint_states") == 1), "topics not advertised"
        assert wait_until(lambda: all(p.get_subscription_count() == 1 for k, p in pub._pubs.items()
                                      if k in ("force", "joint_states"))), "not matched"
        # DDS matches the two ends one at a time: the subscriber's end too, so that it was there before the sample
        assert wait_until(lambda: all(s.get_publisher_count() == 1 for s in subs)), "the subscriber never matched"
        pub.activate()
        assert pub.published == 0 and peer.got["force"] == []
        now = ctx.now()
        slots["force"].sample = Sample(1.5, now)
        slots["opening"].sample = Sample(0.03, now)
        pub.step(now, inputs)                           # the very first sample, sent once
        assert wait_until(lambda: peer.got["force"] and peer.got["joints"]), "first sample lost"   # a failure bound
        assert [m.wrench.force.z for m in peer.got["force"]] == [1.5]
        assert [list(m.position) for m in peer.got["joints"]] == [[0.03]]
    finally:
        pub.deactivate()
        pub.close()
        peer.close()


def test_only_the_listed_topics_are_advertised_and_a_wired_input_of_another_is_a_fault():
    pub, ctx, slots, inputs = _publisher("/o2", topics=["force"])
    peer = Peer("watcher", DOMAIN)
    try:
        pub.configure()
        assert wait_until(lambda: peer.node.count_publishers("/o2/force") == 1)
        assert peer.node.count_publishers("/o2/image") == 0 and set(pub._pubs) == {"force"}
        now = ctx.now()
        slots["force"].sample = Sample(1.0, now)
        pub.step(now, inputs)
        assert pub.published == 1
        slots["velocity"].sample = Sample(0.01, now)   # wired, but joint_states is not advertised
        with pytest.raises(ComponentFault) as err:
            pub.step(ctx.now(), inputs)
        assert str(err.value) == ("input 'velocity' is wired, but its topic 'joint_states' is not in this node's "
                                  "topics [force]: add joint_states to topics (its samples cannot be published)")
    finally:
        pub.close()
        peer.close()


def test_wiring_problems_name_each_port_whose_topic_the_node_does_not_carry():
    """For the graph's validation (the core calls ``wiring_problems`` with the wired ports): before, an output of
    ros2-subscribe read by the graph but not subscribed (topics) was never detected, and never carried a sample."""
    sub = Ros2Subscribe.Params(topics=["force"])
    problems = Ros2Subscribe.wiring_problems(sub, set(), {"force", "opening", "effort", "image"})
    assert problems == {
        "effort": "output 'effort' is wired, but its topic 'joint_states' is not in this node's topics [force]: add "
                  "joint_states to topics, or read another output",
        "image": "output 'image' is wired, but its topic 'image' is not in this node's topics [force]: add image to "
                 "topics, or read another output",
        "opening": "output 'opening' is wired, but its topic 'joint_states' is not in this node's topics [force]: "
                   "add joint_states to topics, or read another output"}
    assert Ros2Subscribe.wiring_problems(Ros2Subscribe.Params(topics=["force", "joint_states", "image"]), set(),
                                         {"force", "opening", "effort", "image"}) == {}
    assert Ros2Subscribe.wiring_problems(sub, set(), set()) == {}
    pub = Ros2Publish.Params(topics=["force", "image"])
    assert Ros2Publish.wiring_problems(pub, {"force", "image", "depth"}, set()) == {
        "depth": "input 'depth' is wired, but its topic 'depth' is not in this node's topics [force, image]: add "
                 "depth to topics"}
    assert Ros2Publish.wiring_problems(Ros2Publish.Params(), set(Ros2Publish.inputs), set()) == {}


def test_each_listed_topic_is_advertised_at_configure_with_its_standard_type():
    """Both image topics carry sensor_msgs/Image; a topic not listed is not advertised."""
    pub, ctx, slots, inputs = _publisher("/o3", topics=["image", "depth"])
    peer = Peer("typer", DOMAIN)
    try:
        peer.listen(Image, "/o3/image", "image")
        pub.configure()
        assert wait_until(lambda: [i.topic_type for i in peer.node.get_publishers_info_by_topic("/o3/image")]
                          == ["sensor_msgs/msg/Image"])
        assert [i.topic_type for i in peer.node.get_publishers_info_by_topic("/o3/depth")] == \
            ["sensor_msgs/msg/Image"]
        assert peer.node.count_publishers("/o3/force") == 0
    finally:
        pub.close()
        peer.close()
