"""Two safety defects found by a review.

1. The press routine's force rate limit (``max_force_rate * dt``) and its integrator counted the whole gap since the
   last step: a step 50 ms late with 1 mm of tracking error sent 3.02 N at once, against 0.5 N on time. The gap is
   now capped at 2 periods of the node's rate, as position-force's ``_max_dt`` caps it.
2. A float64 port takes any Python int, and ``float(10**400)`` raises OverflowError, which the guards of the leader
   force commands (ForceGuard), of the controllers' inputs (``finite_or``/``opening_or_nan``) and of the simulated
   leader's intent did not catch: the node raised a bare OverflowError instead of reading the value as malformed (the
   omega7's guard sits outside its try block: no ``invalid`` count, no ``error``). Now such a number is malformed /
   not finite, as NaN is."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teletouch import ComponentFault, Sample
from teletouch.component import Inputs, _Slot
from teletouch.plugins.controllers.position_force import PositionForce, finite_or, opening_or_nan
from teletouch.plugins.devices.omega7 import ForceGuard
from teletouch.plugins.devices.sim_omega7 import SimOmega7
from teletouch.plugins.estimators.force_calibration import PressRoutine
from teletouch.testing import Harness
from tests.test_leader_omega7 import harness as omega7_harness

from fakes.dhd_standin import sdk_dir_fixture, standin_fixture

sdk_dir = sdk_dir_fixture("fdsdk-s17")
standin = standin_fixture()

HUGE = 10**400   # a Python int: a float64 port takes it, float() overflows


# ------------------------------------------------------------------------ 1. press routine: a late step is capped
def _holding(rate: float, **params) -> Harness:
    """A configured press routine holding 1 mm above its target (on the press axis), at rest, last stepped at 1 s."""
    h = Harness(PressRoutine, {"max_force_rate": 500.0, "max_force": 10.0, **params}, rate=rate)
    h.__enter__()
    r = h.comp
    r.state = "hold"
    r.target = np.array([0.0, 0.0, -1e-3])
    r.cmd = np.zeros(3)
    r.last_t = 1.0
    r.pos = np.zeros(3)
    r.vel = np.zeros(3)
    return h


@pytest.mark.parametrize("rate", [1000.0, 500.0])
def test_press_force_rate_limit_counts_at_most_two_periods_of_a_late_step(rate):
    h = _holding(rate)
    try:
        on_time = h.comp._control(1.0 / rate, np.zeros(3))
        h.comp.cmd = np.zeros(3)
        late = h.comp._control(0.050, np.zeros(3))   # a step 50 ms late
    finally:
        h.__exit__(None, None, None)
    assert on_time[2] == pytest.approx(-500.0 / rate)
    assert late[2] == pytest.approx(-500.0 * 2.0 / rate)   # 2 periods, not 50 ms: 1.0 N at 1 kHz (was 3.02 N)


def test_press_integrator_counts_at_most_two_periods_of_a_late_step():
    h = _holding(1000.0, ki=200.0)
    try:
        h.comp._control(0.050, np.zeros(3))
        integral = h.comp.integral
    finally:
        h.__exit__(None, None, None)
    # err along the press axis (-z): 1 mm; the integral grows by ki * e * dt with dt capped at 2 ms
    assert integral == pytest.approx(200.0 * 1e-3 * 0.002)


def test_press_routine_late_step_through_step_is_capped():
    """The same through step(): graph time jumps 50 ms between two steps of a held press."""
    h = _holding(1000.0)
    try:
        r = h.comp
        r.home = np.zeros(3)
        r.touch = 0.0
        r.t_state = 1.0
        r.last_depth_stamp = None
        r.pos_stamp = 0.999
        out = h.step(1.050, position=Sample(np.zeros(3), 1.050), max_depth=Sample(0.0005, 1.050))
    finally:
        h.__exit__(None, None, None)
    assert np.max(np.abs(out["force"])) <= 500.0 * 0.002 + 1e-12


# ------------------------------------------------------------------------ 2. an int too large for a float
def _inputs(**values) -> Inputs:
    slots = {"gripper_force": _Slot(), "force": _Slot()}
    for name, v in values.items():
        slots[name].sample = Sample(v, 0.0)
    return Inputs(slots)


@pytest.mark.parametrize("value", [HUGE, -HUGE], ids=["huge", "minus-huge"])
def test_force_guard_reads_an_overflowing_gripper_force_as_malformed(value):
    g = ForceGuard(8.0, 12.0, 0.1)
    grip, f, problem = g.apply(0.0, _inputs(gripper_force=value))
    assert grip == 0.0 and not np.any(f)
    assert problem is not None and "gripper_force" in problem and "not finite" in problem, problem
    assert g.invalid == 1


def test_force_guard_reads_an_overflowing_force_component_as_malformed():
    g = ForceGuard(8.0, 12.0, 0.1)
    grip, f, problem = g.apply(0.0, _inputs(force=[0.0, HUGE, 0.0]))
    assert grip == 0.0 and not np.any(f)
    assert problem is not None and problem.startswith("force command") and "not finite" in problem, problem
    assert g.invalid == 1


def test_omega7_faults_with_its_error_on_an_overflowing_gripper_force(sdk_dir, standin):
    h = omega7_harness(sdk_dir)
    with h:
        h.step(0.0, gripper_force=3.0)
        assert standin.forces()[0][3] == pytest.approx(3.0)
        with pytest.raises(ComponentFault, match="gripper_force command .*not finite"):
            h.step(0.001, gripper_force=HUGE)
        assert h.comp.guard.invalid == 1
        assert "gripper_force" in h.comp.error
        assert standin.forces()[0] == [0.0] * 4   # made safe: no force on the hand


def test_sim_omega7_faults_on_an_overflowing_gripper_force():
    with Harness(SimOmega7) as h:
        h.step(0.0, gripper_force=3.0)
        with pytest.raises(ComponentFault, match="gripper_force command .*not finite"):
            h.step(0.001, gripper_force=HUGE)
        assert h.comp.guard.invalid == 1 and h.comp.g_applied == 0.0


def test_sim_omega7_faults_on_an_overflowing_intent_opening():
    with Harness(SimOmega7) as h:
        with pytest.raises(ComponentFault, match="intent_opening .*not finite"):
            h.step(0.0, intent_opening=HUGE)
        assert h.comp.faults == 1 and h.comp.safe


def test_sim_omega7_faults_on_an_intent_answer_that_overflows():
    class Huge:
        def desired(self, t, state):
            return (HUGE, 0.0)

    with Harness(SimOmega7) as h:
        h.comp.intent = Huge()
        with pytest.raises(ComponentFault, match="expected"):
            h.step(0.0)
        assert h.comp.faults == 1 and h.comp.safe


@pytest.mark.parametrize("value", [HUGE, -HUGE], ids=["huge", "minus-huge"])
def test_conversion_helpers_read_an_overflowing_int_as_not_finite(value):
    assert finite_or(value, 0.25) == 0.25
    assert math.isnan(finite_or(value, math.nan))
    assert math.isnan(opening_or_nan(value))


def test_position_force_takes_an_overflowing_leader_opening_as_invalid():
    p = {"deadband": 0.0, "passivity": False}
    with Harness(PositionForce, p) as h:
        h.step(0.0, leader_opening=0.02, force=1.0)
        out = h.step(0.001, leader_opening=HUGE, force=1.0)
        assert h.comp.invalid_inputs == 1 and not h.comp.leader_ok
        assert math.isfinite(out["gripper_force"])


def test_position_force_takes_an_overflowing_force_estimate_as_bad():
    """As a NaN estimate: bad-force, counted, the force fades out (never a step)."""
    p = {"deadband": 0.0, "passivity": False, "smoothing_time": 0.0}
    with Harness(PositionForce, p) as h:
        h.step(0.0, leader_opening=0.02, force=1.0)
        out = h.step(0.001, leader_opening=0.02, force=HUGE)
        assert h.comp.state == "bad-force" and h.comp.bad_force == 1 and h.comp.force_held == 0.0
        assert math.isfinite(out["gripper_force"])


@pytest.mark.parametrize("value", [HUGE, 10**5000, -10**5000], ids=["huge", "beyond-repr", "minus-beyond-repr"])
def test_follower_holds_on_an_overflowing_opening_command(value):
    """A bad command: held, counted, logged once. An int of more than 4300 digits made the log's repr() raise
    ValueError (Python's limit on int-to-text conversion) instead."""
    from teletouch.plugins.devices.sim_gripper import SimGripper

    logs = []
    with Harness(SimGripper, {"object_width": None}) as h:
        h.ctx.log = logs.append
        h.step(0.001, opening_command=0.03)
        h.step(0.002, opening_command=value)
        status = h.comp.status()
    assert status["bad_commands"] == 1 and status["holding"] == "bad command"
    said = [m for m in logs if m.startswith("opening_command")]
    assert len(said) == 1 and "is not an opening" in said[0] and len(said[0]) < 400, said


def test_position_force_says_an_opening_beyond_any_float_by_its_size():
    """Printing a 5000-digit int raises ValueError (Python's limit on int text): the step crashed instead."""
    with Harness(PositionForce, {}) as h:
        h.step(0.0, leader_opening=0.02, force=1.0)
        out = h.step(0.001, leader_opening=10 ** 5000, force=1.0)
        assert not h.comp.leader_ok and "an integer of about 1e5000" in h.comp.leader_problem
        assert math.isfinite(out["gripper_force"])


def test_press_routine_reads_a_depth_beyond_any_float_as_not_a_number():
    with Harness(PressRoutine, {}) as h:
        h.step(0.0, position=np.zeros(3), max_depth=10 ** 400)   # (raised OverflowError)
        assert h.comp.state == "wait"
