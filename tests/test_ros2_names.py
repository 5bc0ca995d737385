"""Topic names longer than ROS 2 allows (247 characters once the namespace, and for a private name the node name,
is applied) are refused when the graph is validated, naming the param and the limit, not by rclpy when the node
starts. Real rclpy for the longest name allowed, loopback only, a ROS_DOMAIN_ID of this module's own."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch import ComponentFault, Context, GraphValidationError
from teletouch.plugins import ros_names
from teletouch.plugins.bridges import ros2
from teletouch.plugins.bridges.ros2 import Ros2Publish, Ros2Subscribe
from teletouch.testing import load_text, make_registry

from fakes.ros2_peer import domain_fixture, own_domain

pytestmark = pytest.mark.timeout(120)

DOMAIN = own_domain(31)
ros_env = domain_fixture(DOMAIN)


def _no_ros(monkeypatch) -> None:
    """Any ROS node made from here on fails the test."""
    def made(*args, **kwargs):
        raise AssertionError("a ROS node was made for a name that should have been refused before")
    monkeypatch.setattr(ros2, "_Ros", made)


def test_a_topic_too_long_is_refused_at_validation_naming_the_param_and_the_limit():
    reg = make_registry("teletouch.plugins.bridges.ros2")
    long = "a" * 237   # '/teletouch/' + 237 = 248
    with pytest.raises(GraphValidationError) as ei:
        load_text(f"""
clock: wall
nodes:
  - id: sub
    plugin: ros2-subscribe
    params:
      force_topic: {long}
  - id: pub
    plugin: ros2-publish
    params:
      namespace: /{"n" * 242}
      topics: [value]
""", reg)
    text = str(ei.value)
    assert "<test>:7" in text and "param 'force_topic'" in text and "248 characters" in text and "247" in text, text
    # a long namespace makes the relative topics too long: each is named, with the namespace as the remedy
    for field in ros2.TOPIC_FIELDS:
        assert f"node 'pub': param '{field}'" in text, (field, text)
    assert "shorten the topic or the namespace" in text, text


def test_the_longest_topic_allowed_is_accepted_by_rclpy():
    # '/teletouch/' + 236 = 247: accepted at validation and by rclpy (the expansion is the one rcl makes; rclpy
    # refuses 248: "topic length should not exceed '255U - 8U'")
    ctx = Context(clock_kind="wall")
    pub = Ros2Publish({"domain_id": DOMAIN, "force_topic": "a" * 236, "topics": ["force"]}, node_id="pub", ctx=ctx)
    try:
        pub.configure()
        assert len(pub._pubs["force"].topic_name) == 247
    finally:
        pub.close()
    with pytest.raises(ValidationError, match="force_topic.*248 characters.*247"):
        Ros2Publish.Params(force_topic="a" * 237)
    with pytest.raises(ValidationError, match="image_topic.*248 characters.*247"):
        Ros2Subscribe.Params(image_topic="/" + "b" * 247)
    assert ros_names.MAX_TOPIC_LENGTH == 247


def test_a_private_topic_is_checked_with_the_node_name():
    # '~/x' expands to NAMESPACE/NODE/x: with node_name set, at validation
    with pytest.raises(ValidationError, match="value_topic.*248 characters.*247"):
        Ros2Subscribe.Params(node_name="m" * 235, value_topic="~/x")   # '/teletouch/' + 235 + '/x' = 248
    Ros2Subscribe.Params(node_name="m" * 234, value_topic="~/x")


def test_a_private_topic_with_the_default_node_name_is_refused_at_configure_before_any_ros_node(monkeypatch):
    # the node name defaults to the graph node id, which the params do not know: checked when the node is
    # configured, before any ROS node is made (rclpy refused it only once the publisher was made)
    _no_ros(monkeypatch)
    for cls in (Ros2Publish, Ros2Subscribe):
        comp = cls({"domain_id": DOMAIN, "force_topic": "~/f", "topics": ["force"]}, node_id="x" * 235,
                   ctx=Context(clock_kind="wall"))
        with pytest.raises(ComponentFault, match="force_topic.*248 characters.*247"):
            comp.configure()
        comp.close()
