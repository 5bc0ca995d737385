"""Grip force limits in millinewtons typed in the newton field: every follower's ``max_effort`` (16000 was taken as
16 kN, and a driver set its current cap for it) is refused, naming the field and the unit meant."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.devices.canopen_gripper import CanopenGripper
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper
from teletouch.plugins.devices.follower_common import MAX_PLAUSIBLE_GRIP_FORCE, plausible_grip_force
from teletouch.plugins.devices.pal_gripper import PalGripper
from teletouch.plugins.devices.sim_gripper import SimGripper
from teletouch.units import plausible_quantity, plausible_travel

FOLLOWERS = [PalGripper, DynamixelGripper, CanopenGripper, SimGripper]


@pytest.mark.parametrize("cls", FOLLOWERS, ids=lambda c: c.name)
def test_a_grip_force_limit_in_millinewtons_is_refused(cls):
    # before: max_effort 1000 x its default (16000 N on the PAL gripper) validated silently
    default = cls.Params().max_effort
    with pytest.raises(ValidationError) as exc:
        cls.Params(max_effort=default * 1000)
    text = str(exc.value)
    assert f"max_effort ({default * 1000:g} N) is beyond what a parallel gripper squeezes (1000 N at most" in text
    assert f"mN in the N field? a bare number is N: for {default * 1000:g} mN write '{default * 1000:g}mN'" in text


@pytest.mark.parametrize("cls", FOLLOWERS, ids=lambda c: c.name)
def test_grip_force_limits_of_real_grippers_still_validate(cls):
    # an RH-P12-RN squeezes 170 N (tests/test_follower_dynamixel.py sets 400 N); "16000mN" is the 16 N meant
    for value in (0.5, 16.0, 400.0, MAX_PLAUSIBLE_GRIP_FORCE):
        assert cls.Params(max_effort=value).max_effort == value
    assert cls.Params(max_effort="16000mN").max_effort == pytest.approx(16.0)


def test_the_shared_checks_name_the_field_the_limit_and_the_unit_meant():
    assert plausible_grip_force("max_effort", 20.0) == 20.0
    with pytest.raises(ValueError, match=r"^grip \(1001 N\) is beyond what a parallel gripper squeezes"):
        plausible_grip_force("grip", 1001.0)
    assert plausible_travel("workspace_radius", -0.5) == -0.5
    with pytest.raises(ValueError, match=r"^r \(75 m\) is beyond a haptic leader's workspace \(1 m at most; the "
                                         r"Omega.7's: 0.075 m in radius\): millimetres in the metre field\? .*"
                                         r"for 75 mm write 0.075 or \"75mm\""):
        plausible_travel("r", 75.0)
    with pytest.raises(ValueError, match=r"^v \(3 m/s\) is too fast \(0.5 m/s at most\): mm/s in the m/s field\? .*"
                                         r"'3mm/s' \(0.003 m/s\)"):
        plausible_quantity("v", 3.0, 0.5, "m/s", "too fast")
