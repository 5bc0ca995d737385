"""The controllers' inputs stamped in the future: a sample stamped more than ``max_clock_skew`` (50 ms, the ROS 2
subscriber's and poly-force's figure; never more than the input's own stale_after) ahead of the graph clock is a clock
fault, not a fresh sample: not used, counted, and named as such in the fault of a loss that lasts. A sample stamped
ahead by less (threads of the wall clock, clocks of a split graph that agree within it) is taken as before."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch import ComponentFault, Sample
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
from teletouch.testing import Harness

P = {"deadband": 0.0, "passivity": False, "force_prediction": False, "smoothing_time": 0.0, "max_force_rate": 1e5}


def _steady(h, n: int = 100, f: float = 1.0) -> None:
    for k in range(n):
        h.step(k * 1e-3, leader_opening=0.02, force=Sample(f, k * 1e-3))


@pytest.mark.parametrize("stale_after, ahead", [(0.1, 0.08), (1.0, 0.5)])
def test_a_force_stamped_ahead_beyond_max_clock_skew_is_not_rendered(stale_after, ahead):
    """A force stamped 80 ms ahead (within stale_after, 100 ms) was fresh: rendered at once, and kept fresh for
    180 ms; with stale_after 1 s one stamped 0.5 s ahead was taken too (the tolerance grew with stale_after)."""
    with Harness(PositionForce, {**P, "stale_after": stale_after, "fault_after_lost": None}) as h:
        _steady(h)
        f = [h.step(0.1, leader_opening=0.02, force=Sample(3.0, 0.1 + ahead))["gripper_force"]]
        f += [h.step(0.1 + k * 1e-3, leader_opening=0.02)["gripper_force"] for k in range(1, 20)]
        assert max(f) <= 1.0 + 1e-9, f              # never the 3 N of the clock fault
        assert h.comp.state == "stale-force" and h.comp.force_lost()
        assert (h.comp.future_stamps, h.comp.invalid_inputs, h.comp.bad_force) == (1, 1, 0)   # counted once


@pytest.mark.parametrize("ahead", [0.0005, 0.004, 0.049])
def test_a_force_stamped_ahead_within_max_clock_skew_is_taken(ahead):
    with Harness(PositionForce, {**P, "fault_after_lost": None}) as h:
        _steady(h)
        out = h.step(0.1, leader_opening=0.02, force=Sample(3.0, 0.1 + ahead))
        assert out["gripper_force"] == pytest.approx(3.0) and h.comp.state == "ok"
        assert h.comp.future_stamps == 0


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition, NoFeedback])
def test_a_leader_opening_stamped_ahead_beyond_max_clock_skew_is_not_taken(cls):
    p = {"passivity": False, "max_clock_skew": 0.01, "fault_after_lost": None}
    with Harness(cls, p) as h:
        for k in range(50):
            h.step(k * 1e-3, leader_opening=0.02, follower_opening=0.02, force=Sample(0.0, k * 1e-3))
        out = h.step(0.05, leader_opening=Sample(0.03, 0.08), follower_opening=0.02, force=Sample(0.0, 0.05))
        assert not h.comp.leader_ok and out["opening_command"] == pytest.approx(0.02)
        assert "ahead of the graph clock" in h.comp.leader_problem and h.comp.future_stamps == 1
        out = h.step(0.051, leader_opening=Sample(0.025, 0.051), follower_opening=0.02, force=Sample(0.0, 0.051))
        assert h.comp.leader_ok and out["opening_command"] == pytest.approx(0.025)


def test_a_lasting_clock_fault_is_named_in_the_fault():
    """The fault said "stale: older than stale_after 0.1 s" of a force stamped ahead of the clock: the one thing it
    was not; the cause (clocks that disagree) and what to do are named now."""
    with Harness(PositionForce, P) as h:
        _steady(h)
        with pytest.raises(ComponentFault) as ei:
            for k in range(100, 1000):
                t = k * 1e-3
                h.step(t, leader_opening=0.02, force=Sample(1.0, t + 0.07))
        msg = str(ei.value)
        assert "force estimate lost" in msg and "0.070 s ahead of the graph clock" in msg, msg
        assert "max_clock_skew" in msg and "synchronise" in msg and "older than" not in msg, msg


def test_max_clock_skew_is_a_parameter_of_every_controller_and_not_negative():
    for cls in (PositionForce, PositionPosition, NoFeedback):
        assert cls.Params(max_clock_skew="20ms").max_clock_skew == pytest.approx(0.02)
        assert cls.Params().max_clock_skew == pytest.approx(0.05)
        with pytest.raises(ValidationError, match="max_clock_skew"):
            cls.Params(max_clock_skew=-0.01)


@pytest.mark.parametrize("ahead", [0.055, 0.066])
def test_a_sample_refused_as_ahead_never_locks_out_the_good_ones_after_it(ahead):
    """An estimate at 62.5 Hz stamped just beyond max_clock_skew stays the latest input until the next one comes;
    when the clock caught up with its stamp meanwhile it was taken as the newest fresh sample, and the good estimates
    after it (stamped earlier) were ignored as out of order: the force faded until the clock passed its stamp."""
    with Harness(PositionForce, {**P, "fault_after_lost": None}) as h:
        latest, out = None, []
        for k in range(400):
            t = k * 1e-3
            if k % 16 == 0:
                latest = Sample(1.0, t + ahead if k == 192 else t)
            r = h.step(t, leader_opening=0.02, force=latest)
            out.append((t, r["gripper_force"], h.comp.state))
        assert h.comp.future_stamps == 1
        after = [(t, f, st) for t, f, st in out if t >= 0.208]   # from the first good estimate after it
        assert all(st == "ok" and f == pytest.approx(1.0) for t, f, st in after), after[:5]
        assert max(f for _, f, _ in out) <= 1.0 + 1e-9   # the refused one is never rendered
