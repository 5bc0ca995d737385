"""Review of pal-gripper: the finger joint limits' units."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.devices.pal_gripper import PalGripper, parse_joint_state


class _JointState:
    """The fields of sensor_msgs/JointState that parse_joint_state reads."""

    def __init__(self, positions):
        self.name = ["gripper_left_finger_joint", "gripper_right_finger_joint"]
        self.position = list(positions)
        self.velocity = [0.0, 0.0]
        self.effort = [0.0, 0.0]


@pytest.mark.parametrize("field, params", [("finger_upper", {"finger_upper": 45}),
                                           ("finger_lower", {"finger_lower": 2, "finger_upper": 45})])
def test_finger_limits_in_millimetres_are_refused_naming_the_field(field, params):
    """finger_upper: 45 (the URDF's 45 mm typed in the metre field) was taken as 45 m: the joint range check then let
    /joint_states in millimetres (22.5 per finger) through as a 45 m opening, which is what the range check is there
    to refuse (finger_lower: 2 was reported as 'min_opening (0 m) is outside what the fingers reach, 4000-90000 mm')."""
    with pytest.raises(ValidationError, match=rf"{field} \(\d+ m\) is beyond any gripper's opening .*millimetres in "
                                              rf"the metre field"):
        PalGripper.Params(**params)


def test_the_joint_range_of_valid_limits_refuses_millimetres():
    """With limits in metres, finger positions in millimetres are refused (what finger_upper: 45 let through)."""
    p = PalGripper.Params(finger_upper="45mm")
    assert p.finger_upper == pytest.approx(0.045)
    assert parse_joint_state(_JointState([0.0225, 0.0225]), p.joint_names, p.finger_lower, p.finger_upper)[0] == (
        0.0225, 0.0225)
    with pytest.raises(Exception, match="outside 0-45 mm"):
        parse_joint_state(_JointState([22.5, 22.5]), p.joint_names, p.finger_lower, p.finger_upper)
