"""Bounds of the bilateral controllers that keep the force on the operator's hand finite, within limits and short-lived
whatever the params or the estimator do (a safety audit's findings, docs/teleoperation.md).

1. Below 1 kHz the rate limit allowed ``max_force_rate`` x the controller's period per step, and the leader holds
   each command: at 20 Hz the hand got 0 -> 7.98 N within one 1 ms leader step. One step changes the force by at
   most ``max_force_rate`` x 1 ms (a 1 kHz leader's period) at any rate; the lower rate is logged.
2. ``max_force_rate: 1e300`` switched the rate limit off: above 100000 N/s (as the press routine's) it is refused.
3. ``fade_time``, ``fault_after_lost`` and ``smoothing_time`` had no upper bound (``fade_time: 100`` kept a dead
   estimator's force on the hand for 100 s); and the contact prediction's term was blended out over smoothing_time
   even while the estimate faded, so it outlasted a shorter fade_time.
4. NaN on every other estimate never faulted nor said anything (each good one ends the loss): they are counted
   (``invalid_forces``), the first is logged, and a high share among the last 60 is a fault.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from pydantic import ValidationError

from teletouch import ComponentFault, Sample
from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.plugins.controllers import position_force
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
from teletouch.plugins.devices.sim_omega7 import SimOmega7
from teletouch.runtime import Runtime
from teletouch.testing import Harness

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "paper-sim.yaml"
RATE = 200.0             # N/s, the default max_force_rate
HAND_STEP = RATE * 1e-3  # N: what it allows over one 1 kHz leader period


def _logged(h: Harness) -> list[str]:
    """The messages the component of ``h`` logs (the harness drops them)."""
    logs: list[str] = []
    h.ctx._log = logs.append
    return logs


# ------------------------------------------------------------------------ 1. a controller below 1 kHz
def test_a_20_hz_controller_never_steps_the_force_in_the_operator_s_hand():
    """The controller at 20 Hz, the simulated Omega.7 at 1 kHz holding its latest command; an estimate of 8 N from
    0.3 s: the force the leader applies changes by at most max_force_rate x 1 ms per leader step (it went 0 ->
    7.98 N in one)."""
    ctl = Harness(PositionForce, {"passivity": False}, rate=20)
    logs = _logged(ctl)
    leader = Harness(SimOmega7, {"intent": "hold"})
    applied = [0.0]
    cmd = None
    with ctl, leader:
        for k in range(2000):
            t = k * 1e-3
            out = leader.step(t, **({"gripper_force": cmd} if cmd is not None else {}))
            applied.append(leader.comp.g_applied)
            if k % 50 == 0:
                f = ctl.step(t, leader_opening=Sample(out["gripper_opening"], t),
                             force=Sample(8.0 if t >= 0.3 else 0.0, t))["gripper_force"]
                cmd = Sample(f, t)
    steps = [abs(b - a) for a, b in zip(applied, applied[1:])]
    assert max(steps) <= HAND_STEP + 1e-9, max(steps)
    assert applied[-1] > 5.0                         # it gets there, 0.2 N per 50 ms step: 4 N/s
    (line,) = [m for m in logs if "below 1 kHz" in m]
    assert "20 Hz" in line and "max_force_rate x 1 ms (0.2 N, not 10 N)" in line and "4 N/s" in line, line


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition])
@pytest.mark.parametrize("rate", [20.0, 100.0, 500.0])
def test_below_1_khz_one_step_raises_the_force_by_at_most_max_force_rate_x_1_ms(cls, rate):
    p = {"passivity": False, "fade_time": 0.2}
    p.update({"kp": 400.0, "kd": 0.0} if cls is PositionPosition else {"deadband": 0.0, "smoothing_time": 0.0})
    period = 1.0 / rate
    f = []
    with Harness(cls, p, rate=rate) as h:
        for k in range(int(3.0 * rate)):
            t = k * period
            lost = 2.0 <= t < 2.5                    # the leader lost for 0.5 s: the fade too
            f.append(h.step(t, leader_opening=math.nan if lost else 0.010, follower_opening=0.020,
                            force=Sample(4.0, t))["gripper_force"])
    rises = [abs(b - a) for a, b in zip(f, f[1:]) if not (a * b >= 0 and abs(b) <= abs(a))]
    assert max(rises) == pytest.approx(HAND_STEP)    # (the force was rising: the cap is what bounds it)
    assert max(f) == pytest.approx(4.0, abs=0.02)
    # towards zero it moves at the rate limit alone: the leader's loss at 2.0 s fades it out within fade_time, as at
    # 1 kHz (capped, it took 4 N / (0.2 N x 20 Hz) = 1 s at 20 Hz)
    assert f[int(round((2.0 + 0.2) * rate)) + 1] == 0.0


def test_at_1_khz_nothing_is_logged_and_the_rate_limit_is_the_one_it_was():
    h = Harness(PositionForce, {"deadband": 0.0, "passivity": False, "smoothing_time": 0.0})
    logs = _logged(h)
    with h:
        h.step(0.0, leader_opening=0.02, force=Sample(0.0, 0.0))
        f0 = h.step(0.001, leader_opening=0.02, force=Sample(6.0, 0.001))["gripper_force"]
        f1 = h.step(0.002, leader_opening=0.02, force=Sample(6.0, 0.002))["gripper_force"]
        f2 = h.step(0.052, leader_opening=0.02, force=Sample(6.0, 0.052))["gripper_force"]   # a late step
    assert (f0, f1 - f0, f2 - f1) == pytest.approx((RATE * 1e-3, RATE * 1e-3, RATE * 2e-3))   # 2 periods
    assert not logs


# ------------------------------------------------------------------------ 2. max_force_rate
@pytest.mark.parametrize("cls", [PositionForce, PositionPosition, NoFeedback])
def test_a_force_rate_that_limits_nothing_is_refused(cls):
    with pytest.raises(ValidationError) as e:
        cls.Params(max_force_rate=1e300)
    text = str(e.value)
    assert ("max_force_rate (1e+300 N/s) is faster than a force on a hand needs to change (100000 N/s at most: a "
            "haptic device's whole +-50 N in 1 ms)") in text, text
    with pytest.raises(ValidationError, match=r"mN/s in the N/s field\? a bare number is N/s: for 200000 mN/s write "
                                              r"200\b"):
        cls.Params(max_force_rate=200000)
    assert cls.Params(max_force_rate=1e5).max_force_rate == 1e5
    assert cls.Params(max_force_rate=0.5).max_force_rate == 0.5


def test_the_force_rate_bound_is_the_press_routine_s():
    from teletouch.plugins.estimators.force_calibration import MAX_PLAUSIBLE_FORCE_RATE

    assert position_force.MAX_PLAUSIBLE_FORCE_RATE == MAX_PLAUSIBLE_FORCE_RATE == 1e5


def test_the_force_rate_is_refused_when_the_graph_is_validated():
    with pytest.raises(GraphValidationError) as e:
        load_graph(str(EXAMPLE), sets=["controller.max_force_rate=1e300"])
    (line,) = [str(x) for x in e.value.errors]
    assert "node 'controller': param 'max_force_rate'" in line and "100000 N/s at most" in line, line


# ------------------------------------------------------------------- 3. fade_time, fault_after_lost, smoothing_time
@pytest.mark.parametrize(("name", "bad", "limit"), [("fade_time", "100", "1 s"), ("fault_after_lost", "200", "10 s"),
                                                    ("smoothing_time", "17", "0.25 s")])
def test_times_that_keep_a_lost_force_on_the_hand_are_refused(name, bad, limit):
    with pytest.raises(GraphValidationError) as e:
        load_graph(str(EXAMPLE), sets=[f"controller.{name}={bad}"])
    (line,) = [str(x) for x in e.value.errors]
    assert f"node 'controller': param '{name}' = {bad}: Input should be less than or equal to {limit}" in line, line
    ok = [f"controller.{name}={limit.split()[0]}"] + (["controller.fault_after_lost=1"] if name == "fade_time" else [])
    load_graph(str(EXAMPLE), sets=ok)


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition, NoFeedback])
def test_the_bounds_are_shared_and_null_still_means_never(cls):
    for name, bad in (("fade_time", 1.01), ("fault_after_lost", 10.5)):
        with pytest.raises(ValidationError, match=name):
            cls.Params(**{name: bad})
    assert cls.Params(fault_after_lost=None, fade_time=1.0).fault_after_lost is None


def test_with_fault_after_lost_null_a_dead_estimator_s_force_is_gone_after_the_fade():
    p = {"deadband": 0.0, "passivity": False, "fault_after_lost": None, "fade_time": 1.0, "stale_after": 0.1}
    f = {}
    with Harness(PositionForce, p) as h:
        for k in range(8000):
            t = k * 1e-3
            est = {"force": Sample(3.0, t)} if k % 17 == 0 and t < 2.0 else {}
            f[k] = h.step(t, leader_opening=0.02, **est)["gripper_force"]
        last = max(k for k in range(2000) if k % 17 == 0) * 1e-3
    assert f[1999] == pytest.approx(3.0)
    gone = round((last + 0.1 + 1.0) * 1e3) + 2       # stale after 0.1 s, faded over 1 s
    assert all(f[k] == 0.0 for k in range(gone, 8000)), [(k, f[k]) for k in range(gone, 8000) if f[k]][:3]


def test_the_contact_prediction_fades_with_the_estimate_not_over_smoothing_time():
    """Closing on a stiff object, the prediction adds a term; the estimator stops: the term went out over
    smoothing_time (0.25 s) and kept ~0.2 N on the hand 0.2 s after the 50 ms fade had ended."""
    p = {"deadband": 0.0, "passivity": False, "smoothing_time": 0.25, "fade_time": 0.05, "fault_after_lost": None,
         "stale_after": 0.05}
    f = []
    last_stamp = None
    with Harness(PositionForce, p) as h:
        for k in range(1500):
            t = k * 1e-3
            kw = {"leader_opening": max(0.020 - 0.01 * t, 0.005)}       # closing at 10 mm/s
            tc = t - 0.035                                              # estimates at ~60 Hz, 35 ms late
            xc = h.comp.cmd_hist.opening_at(tc) if k % 17 == 0 and t < 0.8 and tc > 0 else None
            if xc is not None:
                kw["force"] = Sample(1000.0 * max(0.0, 0.015 - xc), tc)   # 1 N/mm beyond 15 mm
                last_stamp = tc
            f.append(h.step(t, **kw)["gripper_force"])
            if t == 0.79:
                assert h.comp.pred_term > 0.1       # the prediction was adding to the estimate
    gone = round((last_stamp + 0.05 + 0.05) * 1e3) + 2
    assert f[gone - 60] > 0.5 and all(v == 0.0 for v in f[gone:]), [(k, v) for k, v in enumerate(f) if v][-3:]


# ------------------------------------------------------------------------ 4. invalid estimates
def _alternating(h: Harness, seconds: float, start: float = 0.0):
    """Estimates at ~60 Hz from ``start``, NaN on every other one (1 N before ``start``)."""
    for k in range(int(seconds * 1000)):
        t = k * 1e-3
        est = {}
        if k % 17 == 0:
            est["force"] = Sample(math.nan if t >= start and (k // 17) % 2 else 1.0, t)
        yield t, h.step(t, leader_opening=0.02, **est)


def test_nan_on_every_other_estimate_is_counted_logged_once_and_a_fault():
    h = Harness(PositionForce)
    logs = _logged(h)
    with h:
        with pytest.raises(ComponentFault) as e:
            for t, out in _alternating(h, 5.0, start=1.0):
                assert math.isfinite(out["gripper_force"])
        st = h.comp.status()
    # 30 of the last 60 (1 s at 60 Hz) once the window holds only the alternating ones
    assert 1.9 < t < 2.1, t
    assert "30 of the last 60 force estimates were not finite" in str(e.value), e.value
    assert "max_invalid_force_share 0.5" in str(e.value) and e.value.input_port == "force"
    assert st["invalid_forces"] == 30
    (line,) = [m for m in logs if "not finite" in m]
    assert line.startswith("force estimate nan N (not finite) at t=1.0") and "invalid_forces" in line, line


def test_with_the_share_switched_off_they_are_counted_in_the_status_and_the_results():
    with Harness(PositionForce, {"max_invalid_force_share": None}) as h:
        outs = [out for _, out in _alternating(h, 4.0)]
        st, res = h.comp.status(), h.comp.results()
    assert st["invalid_forces"] == res["invalid_forces"] == len(range(0, 4000, 17)) // 2 == 118
    assert all(math.isfinite(o["gripper_force"]) and abs(o["gripper_force"]) <= 8.0 for o in outs)


def test_a_lasting_loss_is_still_fault_after_lost_s():
    """NaN from 0.5 s on and never a good one: the loss fault, not the share's (no good estimate ends it)."""
    with Harness(PositionForce) as h:
        with pytest.raises(ComponentFault, match="force estimate lost for 0.50"):
            for k in range(3000):
                t = k * 1e-3
                est = {"force": Sample(math.nan if t >= 0.5 else 1.0, t)} if k % 17 == 0 else {}
                h.step(t, leader_opening=0.02, **est)


def test_the_example_graph_has_no_invalid_estimate():
    res = Runtime(load_graph(str(EXAMPLE), duration=2.5), log=lambda m: None).run()
    assert res.status == "ok", res.message
    ctl = {n.id: n.results for n in res.nodes}["controller"]
    assert ctl["invalid_forces"] == 0 and ctl["peak_force_n"] > 0.5, ctl


def test_one_burst_of_invalid_estimates_is_a_loss_not_the_share_fault():
    """A force sensor at 1 kHz sending NaN for 30 ms, then good estimates: 30 of the last 60 were invalid, but in one
    run: a loss that ended (fault_after_lost's), not an estimator failing on every other frame (it faulted at once)."""
    with Harness(PositionForce) as h:
        for k in range(1000):
            t = k * 1e-3
            out = h.step(t, leader_opening=0.02, force=Sample(math.nan if 0.05 <= t < 0.08 else 1.0, t))
            assert math.isfinite(out["gripper_force"])
        assert h.comp.status()["invalid_forces"] == 30
