"""sim-gripper: commands after a hold in contact pick the servo up from the effort it held (no grip dip)."""

from __future__ import annotations

import pytest

from teletouch import Sample
from teletouch.testing import Harness

from teletouch.plugins.devices.sim_gripper import SimGripper

PROBE = {"object_width": 0.015, "initial_opening": 0.02, "indenter": "probe", "indenter_radius": 0.005}
#: the documented margin (docs/followers.md, sim-gripper): after a hold the grip never dips below the held force by
#: more than this fraction when the command asks for the same squeeze
MARGIN = 1e-3


def run(h, cmd, t0, seconds, dt=1e-3):
    forces, out = [], {}
    n = int(round(seconds / dt))
    for k in range(1, n + 1):
        out = h.step(t0 + k * dt, opening_command=cmd)
        forces.append(out["contact_force"])
    return out, t0 + n * dt, forces


def hold(h, how, cmd, t):
    """Lose the commands for 0.5 s in one of the two ways that hold the fingers; resume as the runtime would."""
    if how == "safe-state":
        h.comp.safe_state()
        _, t, _ = run(h, cmd, t, 0.5)
        h.comp.activate()
        return t
    _, t, _ = run(h, Sample(cmd, t - 1.0), t, 0.5)                    # stale: the base holds
    return t


@pytest.mark.parametrize("how", ["safe-state", "stale"])
@pytest.mark.parametrize("command", [0.0146, 0.0])      # a light squeeze on the probe; one at max_effort (16 N)
def test_resuming_the_same_squeeze_after_a_hold_does_not_dip_the_grip(how, command):
    """Before: the held offset was dropped at once and the set-point walked back at max_speed: 0.39 -> 0.27 N for
    9 ms (probe), 16 -> 6.8 N for 79 ms (max_effort) after a safe-state hold; 0.33 N / 6.9 N after a stale one."""
    with Harness(SimGripper, PROBE) as h:
        o, t, _ = run(h, command, 0.0, 2.0)
        f0 = o["contact_force"]
        assert o["contact"] and f0 > 0.3
        t = hold(h, how, command, t)
        _, t, forces = run(h, command, t, 0.5)
        assert min(forces) >= f0 * (1.0 - MARGIN), (min(forces), f0)
        assert forces[-1] == pytest.approx(f0, rel=1e-9)


@pytest.mark.parametrize("how", ["safe-state", "stale"])
def test_after_a_hold_a_lighter_squeeze_and_an_opening_are_still_followed(how):
    """The held effort is bled off (at max_speed): it never keeps the grip harder than the new command asks."""
    with Harness(SimGripper, PROBE) as h:
        o, t, _ = run(h, 0.0, 0.0, 2.0)
        assert o["contact_force"] == pytest.approx(16.0)
        t = hold(h, how, 0.0, t)
        # a lighter squeeze: the force it gives when commanded from the start
        with Harness(SimGripper, PROBE) as ref:
            light = run(ref, 0.0146, 0.0, 2.0)[0]["contact_force"]
        o, t, forces = run(h, 0.0146, t, 0.5)
        assert o["contact_force"] == pytest.approx(light, rel=1e-9)
        assert all(b <= a + 1e-12 for a, b in zip(forces, forces[1:]))  # released monotonically, no overshoot
        o, t, _ = run(h, 0.02, t, 0.5)
        assert o["contact_force"] == 0.0 and o["opening"] == pytest.approx(0.02, abs=1e-9)


def test_the_open_safe_state_keeps_no_effort_of_an_earlier_hold():
    """Before: after a stale-command hold the open safe state still counted as a hold and kept its offset (the
    effort when it began over servo_stiffness): the fingers stopped at 86 mm instead of max_opening (90 mm)."""
    with Harness(SimGripper, dict(PROBE, safe_mode="open")) as h:
        o, t, _ = run(h, 0.0, 0.0, 2.0)
        _, t, _ = run(h, Sample(0.0, t - 1.0), t, 0.2)                 # a stale hold at max_effort first
        h.comp.safe_state()
        o, t, _ = run(h, 0.0, t, 2.5)
        assert o["contact_force"] == 0.0 and o["opening"] == pytest.approx(0.09, abs=1e-9)
