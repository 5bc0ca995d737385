"""pal-gripper: with the controller's subscription gone for controller_timeout, "/joint_states goes on" (the controller
crashed) only where the states still come, not where the last one arrived just after the subscription was seen gone
(DDS delivers a queued message late on a loaded machine): the robot as a whole went away. Before, a state that
arrived 10 ms after the controller was seen gone read as states going on (seen in CI under load)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.pal_gripper_node import PalGripperNode  # noqa: E402
from fakes.ros2_peer import domain_fixture, own_domain  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.pal_gripper import PalGripper  # noqa: E402

DOMAIN = own_domain(7, base=20)
_localhost_ros = domain_fixture(DOMAIN, scope="function")


def _check(h, gone: float, state_age: float) -> str:
    """The controller check's fault with the controller seen gone ``gone`` s ago and the last state ``state_age`` s
    old."""
    comp = h.comp
    now = time.monotonic()
    comp.pub.get_subscription_count = lambda: 0   # (the instance attribute: the controller is gone)
    comp._no_controller_since = now - gone
    opening, vel, eff, _ = comp._state
    comp._state = (opening, vel, eff, now - state_age)
    with pytest.raises(HardwareError) as exc:
        comp._check_controller(now)
    return str(exc.value)


@pytest.mark.parametrize("gone, state_age, robot_gone", [
    (0.31, 0.30, True),    # the last state came 10 ms after the subscription was seen gone: all went away
    (0.31, 0.40, True),    # the states stopped first
    (0.31, 0.02, False),   # states still come at the robot's rate: the controller alone went away
    (0.31, 0.10, False),   # (a few states missed: they still come)
])
def test_states_go_on_only_while_they_still_come(gone, state_age, robot_gone):
    robot = PalGripperNode("/tiago", domain_id=DOMAIN).start()
    h = Harness(PalGripper, {"namespace": "tiago", "domain_id": DOMAIN, "connect_timeout": 10.0,
                             "controller_timeout": 0.3})
    h.ctx.clock_kind = "wall"
    try:
        with h:
            assert h.comp._state is not None or _wait_state(h)
            msg = _check(h, gone, state_age)
            assert ("the robot or the network is gone" in msg) is robot_gone, msg
            assert ("goes on: the controller was unloaded or crashed" in msg) is not robot_gone, msg
    finally:
        robot.stop()


def _wait_state(h) -> bool:
    t_end = time.monotonic() + 10.0
    while time.monotonic() < t_end and h.comp._state is None:
        time.sleep(0.01)
    return h.comp._state is not None
