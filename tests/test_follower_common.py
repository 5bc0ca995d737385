"""follower_common (the base of the four follower drivers): no setpoint jump at start-up, at re-activation, after a
late step or into the range from outside it; stale commands hold the measured opening.

The shared logic is exercised through sim-gripper (deterministic, stepped by hand) and, where what goes on the wire
matters, through dynamixel-gripper against its emulated servo (tests/fakes/dynamixel_emulator.py).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.followers import dynamixel, goal_positions  # noqa: E402
from fakes.realtime import drive, drive_until, wait_for  # noqa: E402

from teletouch import Sample  # noqa: E402
from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper  # noqa: E402
from teletouch.plugins.devices.follower_common import FollowerParams  # noqa: E402
from teletouch.plugins.devices.sim_gripper import SimGripper  # noqa: E402

FREE = {"object_width": None, "max_speed": 0.05}
DT = 1e-3  # sim-gripper's default rate: 1 kHz


class RestingAt(SimGripper):
    """sim-gripper whose fingers rest at ``REST`` when it is switched on (sim-gripper's own initial_opening must lie
    in the range; real hardware need not)."""

    REST = 0.08

    def _hw_open(self) -> None:
        super()._hw_open()
        self.x = self.target = self.REST


def steps(h, t0, n, cmd, dt=DT):
    """n steps of dt from t0 with a fresh command; the setpoints and the last outputs."""
    sp, out = [], {}
    for k in range(1, n + 1):
        out = h.step(t0 + k * dt, opening_command=cmd)
        sp.append(h.comp._setpoint)
    return sp, out, t0 + n * dt


def assert_speed_limited(setpoints, first, vmax, dt):
    prev = first
    for s in setpoints:
        assert abs(s - prev) <= vmax * dt + 1e-12, (prev, s)
        prev = s


# ---------------------------------------------------------------------------------------------- 1. start-up
def test_startup_outside_the_range_walks_in_at_max_speed():
    with Harness(RestingAt, dict(FREE, max_opening=0.06)) as h:
        assert h.comp._setpoint == pytest.approx(0.08)  # the measured opening, not clamped to 0.06
        o = h.step(0.0, opening_command=0.06)
        assert h.comp._setpoint == pytest.approx(0.08) and o["opening"] == pytest.approx(0.08)  # no jump
        sp, o, t = steps(h, 0.0, 600, 0.06)
        assert_speed_limited(sp, 0.08, 0.05, DT)
        assert sp[99] == pytest.approx(0.08 - 0.05 * 0.1)  # walking in at max_speed
        assert sp[-1] == pytest.approx(0.06)  # inside the range after (0.08 - 0.06) / 0.05 = 0.4 s
        assert o["opening"] == pytest.approx(0.06, abs=1e-4)


def test_hold_outside_the_range_walks_in_at_max_speed():
    # no command yet: the hold target is the measured opening (outside the range), walked in at max_speed
    with Harness(RestingAt, dict(FREE, max_opening=0.06)) as h:
        sp = []
        for k in range(300):
            h.step(k * DT)
            sp.append(h.comp._setpoint)
        assert_speed_limited(sp, 0.08, 0.05, DT)
        assert sp[0] == pytest.approx(0.08) and sp[-1] == pytest.approx(0.08 - 0.05 * 0.299)
        assert h.comp.status()["holding"] == "no command yet"
    # the hold safe state: sends the measured opening (no jump), later steps walk it into the range
    with Harness(RestingAt, dict(FREE, max_opening=0.06)) as h:
        h.comp.safe_state()
        assert h.comp._setpoint == pytest.approx(0.08) and h.comp.target == pytest.approx(0.08)
        sp, o, t = steps(h, 0.0, 600, 0.0)  # commands are ignored in the safe state
        assert_speed_limited(sp, 0.08, 0.05, DT)
        assert sp[-1] == pytest.approx(0.06)


def test_startup_outside_the_range_dynamixel_first_packet_is_the_present_position():
    """The audit's case: the servo rests fully open (0.075 m), max_opening 0.04: the first Goal_Position is the
    present position and the goal then moves at most max_speed over two nominal periods per packet."""
    with dynamixel(max_opening=0.04, max_speed=0.05) as (emu, h):
        t0 = time.monotonic()
        # until it has walked in 5 mm in more than 10 packets (not a fixed time: late steps on a loaded machine)
        o = drive_until(h, 0.04, lambda o: o["opening"] < 0.075 - 0.005 and len(goal_positions(emu, t0)) > 10,
                        period=0.01)
        m = h.comp.map
        gp = goal_positions(emu, t0)
    assert len(gp) > 10
    assert abs(gp[0] - 1024) <= 1  # no jump to the clamped 0.04 m (1502 ticks)
    step_max = 0.05 * 2.0 / DynamixelGripper.default_rate  # two nominal periods at max_speed
    for a, b in zip(gp, gp[1:]):
        assert abs(m.opening(b) - m.opening(a)) <= step_max + abs(m.scale) + 1e-12
    assert o["opening"] < 0.075 - 0.005  # and it does walk in


# ------------------------------------------------------------------------------------------- 2. re-activation
def test_reactivation_starts_from_the_measured_opening():
    with Harness(SimGripper, FREE) as h:
        sp, o, t = steps(h, 0.0, 2000, 0.05)
        assert o["opening"] == pytest.approx(0.05, abs=1e-6)
        h.comp.deactivate()
        h.comp.x = h.comp.target = 0.02  # moved by someone else while inactive
        h.comp.activate()
        assert h.comp._setpoint == pytest.approx(0.02)
        assert h.comp.status()["opening_m"] == pytest.approx(0.02)  # the last reading is refreshed
        # the operator's command matches where the gripper is now: nothing moves
        sp, o, t = steps(h, t + 1.0, 200, 0.02)
        assert all(s == pytest.approx(0.02) for s in sp)
        assert o["opening"] == pytest.approx(0.02, abs=1e-9)
        assert abs(o["velocity"]) < 1e-9


def test_reactivation_after_safe_state_also_starts_from_the_measured_opening():
    with Harness(SimGripper, dict(FREE, safe_mode="open")) as h:
        steps(h, 0.0, 1000, 0.05)
        h.comp.safe_state()
        h.comp.deactivate()
        h.comp.x = h.comp.target = 0.03
        h.comp.activate()
        assert h.comp._safe is False and h.comp._setpoint == pytest.approx(0.03)
        o = h.step(2.0, opening_command=0.03)
        assert h.comp._setpoint == pytest.approx(0.03) and o["opening"] == pytest.approx(0.03)


def test_reactivation_dynamixel_does_not_drive_back():
    with dynamixel() as (emu, h):
        m = h.comp.map
        t_on, steps = time.monotonic(), []
        drive(h, 0.07, 0.5, trace=steps)
        h.comp.deactivate()
        # each step's Goal_Position goes out in a SYNC_WRITE, which the servo does not answer: wait until the emulator
        # took them all (on a loaded machine the last one landed after the other program's command below, and the
        # servo never moved to 1400)
        assert wait_for(lambda: len(goal_positions(emu, t_on)) >= len(steps))
        with emu._lock:   # (a packet is recorded before it is applied, both under this lock)
            emu._put(emu.table.goal_position, 1400)  # another program moves the servo while the node is inactive

        def moved():
            with emu._lock:
                emu._update()
            return abs(emu.get(emu.table.present_position) - 1400) <= 2

        assert wait_for(moved, timeout=3.0)
        present = emu.get(emu.table.present_position)
        h.comp.activate()
        assert h.comp._setpoint == pytest.approx(m.opening(present), abs=3 * abs(m.scale))
        t0 = time.monotonic()
        drive(h, m.opening(present), 0.05)
        gp = goal_positions(emu, t0)
    assert gp and all(abs(g - present) <= 3 for g in gp)  # not back towards 0.07 m (1092 ticks)


# -------------------------------------------------------------------------------------------- 3. stale commands
def test_command_timeout_param():
    assert FollowerParams().command_timeout == 0.2
    assert SimGripper.Params(command_timeout="50ms").command_timeout == pytest.approx(0.05)
    for bad in (0.0, -0.1, 2.5):
        with pytest.raises(ValidationError, match="command_timeout"):
            FollowerParams(command_timeout=bad)


@pytest.mark.parametrize("field, value", [("max_opening", 90.0), ("min_opening", 5.0)])
def test_millimetres_typed_in_an_opening_limit_are_refused(field, value):
    """``max_opening: 90`` meant 90 mm; taken as 90 m, the open safe state drove the fingers to their end stop."""
    other = {"max_opening": 100.0} if field == "min_opening" else {}
    with pytest.raises(ValidationError, match=rf"{field} \({value:g} m\) is beyond any gripper's opening .*"
                                              rf"millimetres in the metre field\? a bare number is metres: for "
                                              rf"{value:g} mm write {value / 1e3:g}"):
        FollowerParams(**{field: value, **other})
    assert FollowerParams(max_opening="90mm").max_opening == pytest.approx(0.09)


@pytest.mark.parametrize("field, value", [("opening_at_ticks_open", 75.0), ("opening_at_ticks_closed", 5.0)])
def test_millimetres_typed_in_a_calibration_opening_are_refused(field, value):
    """``opening_at_ticks_open: 75`` meant 75 mm; taken as 75 m, the limits (0-75 mm) lay within the calibration and it
    was accepted: the open gripper read 75 m and every command mapped to ticks near the closed end."""
    with pytest.raises(ValidationError, match=rf"{field} \({value:g} m\) is beyond any gripper's opening .*"
                                              rf"write {value / 1e3:g}"):
        DynamixelGripper.Params(**{field: value})
    assert DynamixelGripper.Params(opening_at_ticks_open="75mm").opening_at_ticks_open == pytest.approx(0.075)


@pytest.mark.parametrize("stamp", ["old", "future", "nan"])
def test_stale_command_holds_the_measured_opening(stamp):
    with Harness(SimGripper, FREE) as h:  # command_timeout 0.2 s (the default)
        sp, o, t = steps(h, 0.0, 2000, 0.05)
        assert o["opening"] == pytest.approx(0.05, abs=1e-6)
        for k in range(1, 1001):
            tk = t + k * DT
            s = {"old": tk - 0.5, "future": tk + 0.5, "nan": math.nan}[stamp]
            o = h.step(tk, opening_command=Sample(0.01, s))
        assert o["opening"] == pytest.approx(0.05, abs=1e-6)  # not followed to 0.01
        st = h.comp.status()
        assert st["stale_commands"] == 1000 and st["holding"] == "stale command" and st["safe"] is False
        # a fresh command is followed again (at max_speed)
        sp, o, t = steps(h, t + 1.0, 1000, 0.01)
        assert_speed_limited(sp, 0.05, 0.05, DT)
        assert o["opening"] == pytest.approx(0.01, abs=1e-3)
        assert h.comp.status()["holding"] is None


def test_command_ageing_past_the_timeout_holds():
    with Harness(SimGripper, dict(FREE, max_speed=0.025)) as h:
        h.step(0.0, opening_command=0.03)  # one command, never refreshed (the source died)
        outs = [h.step(k * DT) for k in range(1, 2001)]
        # it was followed while fresh (0.2 s at 0.025 m/s: 5 mm of setpoint), then the gripper held where it was
        assert h.comp.status()["stale_commands"] == 2000 - 200 and h.comp.status()["holding"] == "stale command"
        x = outs[-1]["opening"]
        assert 0.09 - 0.005 - 1e-6 <= x < 0.09 - 0.003
        assert outs[999]["opening"] == pytest.approx(x, abs=1e-9)  # at rest for the last second


def test_stale_command_holds_in_contact_without_squeezing_further():
    with Harness(SimGripper, {"object_width": 0.04}) as h:
        sp, o, t = steps(h, 0.0, 2000, 0.045)
        for k in range(1, 1001):
            o = h.step(t + k * DT, opening_command=Sample(0.0, t - 10.0))  # an old "close fully"
        assert o["contact"] is False and o["opening"] == pytest.approx(0.045, abs=1e-6)


def test_nan_command_holds_the_measured_opening():
    with Harness(SimGripper, {"object_width": 0.04}) as h:
        sp, o, t = steps(h, 0.0, 2000, 0.035)
        assert o["contact"] is True
        x = o["opening"]
        for k in range(1, 501):
            o = h.step(t + k * DT, opening_command=math.nan)
        assert h.comp._setpoint == pytest.approx(x, abs=1e-6)  # the measured opening, not the squeezing setpoint
        assert h.comp.status()["bad_commands"] == 500 and h.comp.status()["holding"] == "bad command"


# ------------------------------------------------------------------------------------------------ 4. late step
def test_late_step_moves_the_setpoint_by_at_most_two_periods():
    with Harness(SimGripper, FREE) as h:  # 1 kHz (Harness: ctx.rate = default_rate)
        sp, o, t = steps(h, 0.0, 100, 0.09)
        before = h.comp._setpoint
        h.step(t + 0.4, opening_command=0.0)  # a step 0.4 s late
        assert before - h.comp._setpoint == pytest.approx(0.05 * 2e-3)  # not 0.05 * 0.4 = 20 mm
    h = Harness(SimGripper, FREE)
    h.ctx.rate = 100.0  # the graph's rate for the node is what counts
    with h:
        h.step(0.0, opening_command=0.09)
        h.step(0.5, opening_command=0.0)
        assert 0.09 - h.comp._setpoint == pytest.approx(0.05 * 0.02)
    h = Harness(SimGripper, FREE)
    h.ctx.rate = None  # outside a graph: the class's default_rate
    with h:
        h.step(0.0, opening_command=0.09)
        h.step(0.5, opening_command=0.0)
        assert 0.09 - h.comp._setpoint == pytest.approx(0.05 * 2.0 / SimGripper.default_rate)


def test_late_step_dynamixel_sends_no_jump():
    """The audit's case: a step 0.4 s late sent a goal 20 mm away in one packet."""
    with dynamixel() as (emu, h):
        m = h.comp.map
        drive(h, 0.075, 0.2)
        time.sleep(0.4)
        t0 = time.monotonic()
        h.t = t0
        h.step(t0, opening_command=0.0)
        assert wait_for(lambda: len(goal_positions(emu, t0)) > 0)
        gp = goal_positions(emu, t0)
    assert 0.075 - m.opening(gp[-1]) <= 0.05 * 0.02 + abs(m.scale)
