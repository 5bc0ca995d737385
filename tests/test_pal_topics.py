"""pal-gripper refuses topic names ROS 2 would refuse as too long (247 characters once expanded) when its params are
validated, naming the param, instead of when the node makes its publisher or subscription at start-up."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.devices.pal_gripper import PalGripper
from teletouch.plugins.ros_names import MAX_TOPIC_LENGTH


def test_a_command_topic_too_long_is_refused_naming_the_param_and_the_limit():
    suffix = len("/gripper_controller/joint_trajectory")
    ok = "/" + "a" * (MAX_TOPIC_LENGTH - suffix - 1)   # the command topic exactly 247 characters long
    assert len(f"{ok}/gripper_controller/joint_trajectory") == MAX_TOPIC_LENGTH
    PalGripper.Params(namespace=ok, joint_states_topic="/joint_states")
    with pytest.raises(ValidationError) as err:
        PalGripper.Params(namespace=ok + "b", joint_states_topic="/joint_states")
    msg = str(err.value)
    assert "controller:" in msg and "248 characters" in msg and f"at most {MAX_TOPIC_LENGTH}" in msg, msg


def test_a_relative_state_topic_is_measured_under_the_namespace():
    ns = "/" + "n" * 200
    with pytest.raises(ValidationError) as err:
        PalGripper.Params(namespace=ns, controller="g", joint_states_topic="s" * 47)   # 201 + 1 + 47 = 249
    msg = str(err.value)
    assert "joint_states_topic:" in msg and "249 characters" in msg and "controller:" not in msg, msg
    PalGripper.Params(namespace=ns, controller="g", joint_states_topic="/" + "s" * 47)   # absolute: 48 characters
