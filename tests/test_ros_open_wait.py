"""ros2-publish's optional wait at activate for matched subscribers (``wait_for_subscribers``, ``wait_timeout``):
the first samples of a run are no longer lost to DDS discovery where a graph asks for it, a subscriber that does
not come is a start-up error naming the topic and the counts, and incompatible QoS is named with both sides' values.
Real DDS over loopback, a domain of this module's own."""

from __future__ import annotations

import pytest
from geometry_msgs.msg import WrenchStamped
from pydantic import ValidationError
from rclpy.qos import DurabilityPolicy, QoSProfile

from teletouch import ComponentFault, Context, Inputs, Sample
from teletouch.component import _Slot
from teletouch.plugins.bridges.ros2 import Ros2Publish

from fakes.ros2_peer import Peer, domain_fixture, own_domain, wait_until

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(6)
ros_env = domain_fixture(DOMAIN)


def _publisher(ns: str, **params) -> tuple[Ros2Publish, Context, dict[str, _Slot], Inputs, list[str]]:
    logs: list[str] = []
    ctx = Context(clock_kind="wall", log=logs.append)
    pub = Ros2Publish(dict({"domain_id": DOMAIN, "namespace": ns, "topics": ["force"]}, **params), node_id="pub",
                      ctx=ctx)
    slots = {n: _Slot() for n in pub.inputs}
    return pub, ctx, slots, Inputs(slots), logs


def test_activate_waits_until_the_subscriber_is_matched_and_the_first_sample_reaches_it():
    pub, ctx, slots, inputs, _ = _publisher("/w1", wait_for_subscribers=1, wait_timeout=20.0)
    peer = Peer("first_listener", DOMAIN)
    try:
        pub.configure()
        peer.listen(WrenchStamped, "/w1/force", "force")   # appears while the graph starts: not matched yet
        pub.activate()
        # activate returned: DDS has matched the subscriber, so a sample sent now is delivered (volatile, reliable)
        assert pub._pubs["force"].get_subscription_count() >= 1
        now = ctx.now()
        slots["force"].sample = Sample(2.5, now)
        pub.step(now, inputs)
        assert wait_until(lambda: peer.got["force"], timeout=10.0), "the first sample was lost"
        assert [m.wrench.force.z for m in peer.got["force"]] == [2.5]
    finally:
        pub.close()
        peer.close()


def test_too_few_subscribers_is_a_start_up_error_naming_the_topic_and_the_counts():
    pub, ctx, *_ = _publisher("/w2", topics=["force", "value"], wait_for_subscribers={"force": 2},
                              wait_timeout=0.5)
    peer = Peer("lone_listener", DOMAIN)
    try:
        pub.configure()
        peer.listen(WrenchStamped, "/w2/force", "force")
        assert wait_until(lambda: pub._pubs["force"].get_subscription_count() == 1)
        with pytest.raises(ComponentFault) as err:
            pub.activate()
        msg = str(err.value)
        assert msg.startswith(f"wait_for_subscribers: not reached after 0.5 s (wait_timeout), ROS_DOMAIN_ID {DOMAIN}: "
                              f"/w2/force: 1 subscriber(s) matched, 2 expected;"), msg
        assert "/w2/value" not in msg            # not waited for (only force is named)
    finally:
        pub.close()
        peer.close()


def test_a_subscriber_with_incompatible_qos_is_named_with_both_values_in_the_error_and_the_log():
    pub, ctx, _, _, logs = _publisher("/w3", wait_for_subscribers=1, wait_timeout=0.5)   # volatile (default)
    peer = Peer("latched_listener", DOMAIN)
    try:
        pub.configure()
        peer.listen(WrenchStamped, "/w3/force", "force", qos=QoSProfile(depth=1,
                                                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert wait_until(lambda: pub.status()["incompatible_qos"] >= 1), pub.status()
        assert wait_until(lambda: "latched_listener" in "".join(pub._ros.qos_report.texts()))   # its name known
        with pytest.raises(ComponentFault) as err:
            pub.activate()
        msg = str(err.value)
        assert "/w3/force: 0 subscriber(s) matched, 1 expected (1 more subscription(s) on the topic that DDS did not " \
               "match: QoS or message type)" in msg, msg
        assert ("topic /w3/force: this publisher and a subscription of node /peer/latched_listener have incompatible "
                "QoS (DURABILITY: volatile here, transient_local there): nothing flows between the two") in msg, msg
        assert any("DURABILITY: volatile here, transient_local there" in line for line in logs), logs
    finally:
        pub.close()
        peer.close()


def test_no_wait_by_default_and_bad_counts_are_refused_naming_the_field():
    pub, *_ = _publisher("/w4")
    try:
        pub.configure()
        pub.activate()                           # nobody subscribes: the default (0) does not wait
        assert pub._pubs["force"].get_subscription_count() == 0
    finally:
        pub.close()
    assert Ros2Publish.Params().wait_for_subscribers == 0
    with pytest.raises(ValidationError) as err:
        Ros2Publish.Params(topics=["force"], wait_for_subscribers={"image": 1})
    assert "wait_for_subscribers: image not in topics [force]" in str(err.value)
    with pytest.raises(ValidationError) as err:
        Ros2Publish.Params(wait_for_subscribers=-1)
    assert "expected a count of subscribers >= 0" in str(err.value)
    with pytest.raises(ValidationError, match=r"wait_timeout\s+Input should be greater than 0"):
        Ros2Publish.Params(wait_timeout=0)
