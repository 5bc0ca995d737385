"""position-force when the force estimate or the leader is lost: the follower command holds while the estimate is
lost (not while waiting for the first one), slews back at resume_speed when it returns, and a loss that lasts longer
than fault_after_lost is a fault (ComponentFault naming what was lost and for how long)."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from teletouch import ComponentFault, Sample
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce
from teletouch.testing import Harness

DT = 1e-3
BASE = {"deadband": 0.0, "passivity": False, "stale_after": 0.1, "fade_time": 0.2}


def closing(t: float) -> float:
    """The operator closes the hand at 5 mm/s from 20 mm."""
    return 0.02 - 0.005 * t


def warm_up(h: Harness, until: float = 0.3) -> float:
    """Leader closing, a fresh estimate of 2 N every step up to ``until``; returns the last step's time."""
    k = 0
    while k * DT <= until + 1e-12:
        t = k * DT
        h.step(t, leader_opening=closing(t), force=Sample(2.0, t))
        k += 1
    return (k - 1) * DT


def test_follower_holds_while_the_estimate_is_stale():
    with Harness(PositionForce, dict(BASE, fault_after_lost=None)) as h:
        t0 = warm_up(h)
        outs = [(t0 + k * DT, h.step(t0 + k * DT, leader_opening=closing(t0 + k * DT)))
                for k in range(1, 700)]
        assert h.comp.state == "stale-force"
    # the estimate (last at t0) is stale after stale_after: from one step later the command stays where it was
    held = [(t, o["opening_command"]) for t, o in outs if t > t0 + 0.1 + 2 * DT]
    x_hold = held[0][1]
    assert all(x == x_hold for _t, x in held), "the follower kept following the leader with no force estimate"
    assert x_hold == pytest.approx(closing(t0 + 0.1), abs=2e-5)
    assert closing(held[-1][0]) < x_hold - 2e-3        # the hand closed 2+ mm meanwhile
    assert outs[-1][1]["gripper_force"] == 0.0          # and the force faded out


def test_follower_holds_on_a_nan_estimate():
    with Harness(PositionForce, dict(BASE, fault_after_lost=None)) as h:
        t0 = warm_up(h)
        outs = [h.step(t0 + k * DT, leader_opening=closing(t0 + k * DT), force=Sample(math.nan, t0 + k * DT))
                for k in range(1, 300)]
        assert h.comp.state == "bad-force"
    xs = [o["opening_command"] for o in outs[2:]]
    assert max(xs) - min(xs) == 0.0 and xs[0] == pytest.approx(closing(t0), abs=3e-5)


def test_command_slews_back_at_resume_speed_when_the_estimate_returns():
    speed = 0.02
    with Harness(PositionForce, dict(BASE, fault_after_lost=None, resume_speed=speed)) as h:
        t0 = warm_up(h)
        t = t0
        for k in range(1, 400):                                  # lost for 0.4 s: held
            t = t0 + k * DT
            x_hold = h.step(t, leader_opening=closing(t))["opening_command"]
        # the hand opened to 30 mm meanwhile; the estimate returns
        xs = [x_hold]
        for k in range(1, 800):
            tk = t + k * DT
            xs.append(h.step(tk, leader_opening=0.03, force=Sample(0.0, tk))["opening_command"])
    steps = [b - a for a, b in zip(xs, xs[1:])]
    assert max(abs(s) for s in steps) <= speed * DT + 1e-12, "the command jumped when the estimate returned"
    assert xs[2] > x_hold                                        # it moves (no hold once the estimate is back)
    assert xs[-1] == 0.03                                        # and reaches the leader's mapped opening
    n = next(i for i, x in enumerate(xs) if x == 0.03)
    assert n * DT == pytest.approx((0.03 - x_hold) / speed, abs=3 * DT)
    # once there it follows the leader directly again
    assert h.comp.resuming is False


def test_waiting_for_the_first_estimate_does_not_hold():
    # start-up: no estimate yet is no loss: the follower follows (the experiments' figures) and no fault
    with Harness(PositionForce, dict(BASE, hold_on_lost_force=True, fault_after_lost=0.5)) as h:
        outs = [h.step(k * DT, leader_opening=closing(k * DT)) for k in range(0, 800)]
        assert h.comp.state == "waiting"
    assert [o["opening_command"] for o in outs] == [closing(k * DT) for k in range(0, 800)]


def test_hold_can_be_switched_off():
    with Harness(PositionForce, dict(BASE, fault_after_lost=None, hold_on_lost_force=False)) as h:
        t0 = warm_up(h)
        t = t0 + 0.4
        out = h.step(t, leader_opening=closing(t))
        assert h.comp.state == "stale-force" and out["opening_command"] == closing(t)


def test_lost_estimate_is_a_fault_after_fault_after_lost():
    with Harness(PositionForce, dict(BASE, fault_after_lost=0.5)) as h:
        t0 = warm_up(h)
        last = None
        with pytest.raises(ComponentFault, match=r"force estimate lost for 0\.50\d s .*stale.*fault_after_lost 0\.5"):
            for k in range(1, 2000):
                t = t0 + k * DT
                last = (t, h.step(t, leader_opening=closing(t)))
        t_last, out = last
        # lost (noticed) at t0 + stale_after; the fault ~0.5 s later, the force faded out by then
        assert t_last == pytest.approx(t0 + 0.1 + 0.5, abs=3 * DT)
        assert out["gripper_force"] == 0.0


def test_lost_leader_is_a_fault_after_fault_after_lost():
    with Harness(PositionForce, dict(BASE, fault_after_lost=0.5, leader_stale_after=0.05)) as h:
        t0 = warm_up(h)
        with pytest.raises(ComponentFault, match=r"leader opening lost for 0\.50\d s .*invalid.*nan"):
            for k in range(1, 2000):
                t = t0 + k * DT
                h.step(t, leader_opening=math.nan, force=Sample(2.0, t))
        assert t == pytest.approx(t0 + 0.5 + DT, abs=2 * DT)


def test_no_feedback_faults_on_a_lost_leader_too_but_not_on_a_missing_force():
    with Harness(NoFeedback, {"fault_after_lost": 0.5}) as h:
        for k in range(0, 1500):                 # no force at all: not a loss for no-feedback
            h.step(k * DT, leader_opening=0.02)
        t0 = 1.5
        with pytest.raises(ComponentFault, match="leader opening lost"):
            for k in range(1, 1000):
                h.step(t0 + k * DT, leader_opening=Sample(0.02, t0))
        assert h.comp.leader_lost_since is not None


def test_a_short_loss_is_no_fault():
    with Harness(PositionForce, dict(BASE, fault_after_lost=0.5)) as h:
        t0 = warm_up(h)
        t = t0
        for cycle in range(4):                   # lost 0.4 s (noticed 0.3 s), back for 0.1 s, four times
            for k in range(1, 400):
                t += DT
                h.step(t, leader_opening=closing(t))
            for k in range(1, 100):
                t += DT
                h.step(t, leader_opening=closing(t), force=Sample(2.0, t))
        assert h.comp.state == "ok" and h.comp.force_lost_since is None


def test_fault_after_lost_shorter_than_the_fade_is_refused():
    with pytest.raises(ValidationError, match="fault_after_lost .* must be at least fade_time"):
        PositionForce.Params(fault_after_lost=0.1, fade_time=0.2)


def test_a_force_estimate_that_never_comes_is_a_fault_after_first_force_timeout():
    """A sensor that never started (a ROS 2 domain or topic that does not match on the split setup): the controller
    stayed "waiting" for the first estimate for the whole run, the follower teleoperated without feedback (9.3 N on
    the object, 0 N rendered), and the run ended ok, exit 0. Only a loss after a first estimate was a fault."""
    with Harness(PositionForce, dict(BASE, first_force_timeout=0.5)) as h:
        with pytest.raises(ComponentFault, match=r"no force estimate received in 0\.50\d s since the leader's first "
                                                 r"opening \(t=0\.100 s\), longer than first_force_timeout 0\.5 s") \
                as info:
            for k in range(2000):
                t = k * DT
                h.step(t, leader_opening=closing(t) if t >= 0.1 else None)   # the leader from 0.1 s on
        assert info.value.input_port == "force"
        assert 0.6 < k * DT < 0.61
    # an estimate before the timeout: no fault (a loss after it is fault_after_lost's); null: waits for ever
    with Harness(PositionForce, dict(BASE, first_force_timeout=0.5, fault_after_lost=None)) as h:
        for k in range(2000):
            t = k * DT
            h.step(t, leader_opening=closing(t), force=Sample(1.0, t) if k == 400 else None)
    with Harness(PositionForce, dict(BASE, first_force_timeout=None)) as h:
        for k in range(2000):
            h.step(k * DT, leader_opening=closing(k * DT))
        assert h.comp.state == "waiting"
    with pytest.raises(ValidationError, match="first_force_timeout"):
        PositionForce.Params(first_force_timeout=120)
