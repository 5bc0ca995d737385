"""Review of the bilateral controllers: bad samples are counted once per sample (not on every 1 kHz step while they
stay the latest), and a velocity is never derived across a gap in the samples (it met the returning hand as a
damping kick)."""

from __future__ import annotations

import math

import pytest

from teletouch import Sample
from teletouch.plugins.controllers.position_force import Differentiator, PositionForce, PositionPosition
from teletouch.testing import Harness

NO_FAULT = {"fault_after_lost": None}


# ------------------------------------------------------------------------------------------------ counters
def _steady_force(h, n=50):
    for k in range(n):
        h.step(k * 1e-3, leader_opening=0.02, follower_opening=0.02, force=Sample(1.0, k * 1e-3))


@pytest.mark.parametrize("stamp", [math.nan, 0.050])
def test_a_bad_force_sample_is_counted_once_however_long_it_stays_the_latest(stamp):
    # a NaN force with a NaN stamp was counted on every step (bad_force 50 after 50 ms, 500 by the fault): a NaN
    # stamp never equals itself, so the sample looked new at each step; one with a finite stamp was counted once
    with Harness(PositionForce, NO_FAULT) as h:
        _steady_force(h)
        h.step(0.050, leader_opening=0.02, force=Sample(math.nan, stamp))
        for k in range(51, 300):                  # (the force fades out over fade_time, 0.2 s)
            out = h.step(k * 1e-3, leader_opening=0.02)
        assert (h.comp.bad_force, h.comp.invalid_inputs) == (1, 1)
        assert h.comp.state == "bad-force" and out["gripper_force"] == 0.0
        h.step(0.300, leader_opening=0.02, force=Sample(math.inf, stamp + 0.25))     # a second bad sample counts
        h.step(0.301, leader_opening=0.02)
        assert (h.comp.bad_force, h.comp.invalid_inputs) == (2, 2)


def test_a_good_force_sample_with_a_nan_stamp_is_looked_at_once():
    # a finite force with a NaN stamp (stale) was taken again on every step: force_held set and the two-port
    # interval forgotten at 1 kHz; it is stale, not bad, and counted nowhere
    with Harness(PositionForce, NO_FAULT) as h:
        _steady_force(h)
        h.step(0.050, leader_opening=0.02, follower_opening=0.02, force=Sample(3.0, math.nan))
        assert h.comp.force_held == 3.0
        h.comp.force_held = -1.0                  # marks whether a later step takes the sample again
        for k in range(51, 100):
            h.step(k * 1e-3, leader_opening=0.02, follower_opening=0.02)
        assert h.comp.force_held == -1.0
        assert (h.comp.bad_force, h.comp.invalid_inputs, h.comp.state) == (0, 0, "stale-force")


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition])
@pytest.mark.parametrize("value", [math.nan, 1e30])
def test_a_bad_leader_opening_is_counted_once_while_it_stays_fresh(cls, value):
    # counted on every step for as long as it was fresh (leader_stale_after: 50 counts for one sample)
    with Harness(cls, NO_FAULT) as h:
        _steady_force(h)
        h.step(0.050, leader_opening=Sample(value, 0.050), follower_opening=0.02, force=Sample(1.0, 0.050))
        for k in range(51, 100):
            out = h.step(k * 1e-3, follower_opening=0.02, force=Sample(1.0, k * 1e-3))
        assert h.comp.invalid_inputs == 1
        assert out["opening_command"] == 0.02 and h.comp.x_l == 0.02       # the follower held meanwhile
        h.step(0.100, leader_opening=Sample(value, 0.100), follower_opening=0.02, force=Sample(1.0, 0.1))
        assert h.comp.invalid_inputs == 2


def test_a_bad_follower_opening_is_counted_once_while_it_stays_fresh():
    with Harness(PositionPosition, NO_FAULT) as h:
        _steady_force(h)
        h.step(0.050, leader_opening=0.02, follower_opening=Sample(math.nan, 0.050))
        for k in range(51, 100):
            h.step(k * 1e-3, leader_opening=0.02)
        assert h.comp.invalid_inputs == 1 and h.comp.state == "stale-follower"


def test_a_leader_velocity_glitch_is_counted_once_while_it_stays_fresh():
    with Harness(PositionForce, NO_FAULT) as h:
        _steady_force(h)
        h.step(0.050, leader_opening=0.02, leader_velocity=Sample(1000.0, 0.050), force=Sample(1.0, 0.050))
        for k in range(51, 100):
            h.step(k * 1e-3, leader_opening=0.02, force=Sample(1.0, k * 1e-3))
        assert h.comp.invalid_inputs == 1 and h.comp.v_l == 0.0


# ------------------------------------------------------------------------------------------------ gaps
def test_the_differentiator_restarts_after_a_gap_longer_than_its_limit():
    d = Differentiator(50.0, max_gap=0.05)
    for k in range(100):
        d.update(k * 1e-3, 0.02)
    # the opening moved 20 mm during a 200 ms gap and stands still now: no velocity of 0.1 m/s (the gap's average)
    assert d.update(0.300, 0.04) == 0.0
    assert d.update(0.301, 0.04) == 0.0
    for k in range(302, 400):                    # a motion after the gap is tracked as before
        v = d.update(k * 1e-3, 0.04 + 0.01 * (k - 301) * 1e-3)
    assert v == pytest.approx(0.01, rel=1e-3)


def test_the_differentiator_bridges_a_missed_sample():
    # a gap within the limit (one or a few missed samples) is differentiated across: its average is the motion
    d = Differentiator(50.0, max_gap=0.05)
    for k in list(range(100)) + list(range(120, 200)):
        v = d.update(k * 1e-3, 0.01 * k * 1e-3)
        if k == 120:
            assert v == pytest.approx(0.01, rel=1e-3)
    assert v == pytest.approx(0.01, rel=1e-3)


def _leader_gap(cls, params, resume):
    """Steady at 20 mm, the leader lost for 200 ms (stale), back at ``resume(t)``; the outputs after the gap."""
    with Harness(cls, dict(NO_FAULT, **params)) as h:
        for k in range(100):
            h.step(k * 1e-3, leader_opening=0.02, follower_opening=0.02, force=Sample(1.0, k * 1e-3))
        for k in range(100, 300):
            h.step(k * 1e-3, follower_opening=0.02, force=Sample(1.0, k * 1e-3))
        outs = [h.step(k * 1e-3, leader_opening=resume(k * 1e-3), follower_opening=0.02,
                       force=Sample(1.0, k * 1e-3)) for k in range(300, 400)]
        return outs, h.comp


def test_a_hand_at_rest_after_a_leader_gap_gets_no_damping_kick():
    # the hand opened 20 mm while the leader was lost and rests now: the velocity across the gap (0.1 m/s) was
    # damped, a pull of up to 0.57 N (leader_damping 10 N*s/m) on a hand that does not move, in free space
    p = {"leader_damping": 10.0, "deadband": 2.0}         # the 1 N estimate is below the deadband: free space
    outs, comp = _leader_gap(PositionForce, p, lambda t: 0.04)
    assert max(abs(o["gripper_force"]) for o in outs) == 0.0 and comp.v_l == 0.0


def test_a_hand_at_rest_after_a_leader_gap_books_no_energy():
    # in contact, the phantom opening velocity booked a deficit in the passivity observer (-f * v) that the hand
    # at rest never put there; the damping and the cut then took it out of the contact force later
    outs, comp = _leader_gap(PositionForce, {"deadband": 0.0}, lambda t: 0.04)
    assert [o["energy"] for o in outs] == [0.0] * len(outs)
    assert [o["damping"] for o in outs] == [0.0] * len(outs)
    assert outs[-1]["gripper_force"] == pytest.approx(1.0)


def test_a_hand_moving_after_a_leader_gap_is_damped_at_its_own_velocity():
    p = {"leader_damping": 10.0, "deadband": 2.0, "passivity": False}
    outs, comp = _leader_gap(PositionForce, p, lambda t: 0.04 + 0.01 * (t - 0.3))
    assert comp.v_l == pytest.approx(0.01, rel=1e-3)
    assert outs[-1]["gripper_force"] == pytest.approx(-0.1, rel=1e-3)
    assert min(o["gripper_force"] for o in outs) >= -0.1 - 1e-9     # never more than the damping of the motion


def test_a_follower_gap_gives_position_position_no_damping_kick():
    # the follower moved 20 mm while its opening was lost and rests now: kd x the gap's average velocity kicked
    p = {"kp": 0.0, "kd": 10.0, "passivity": False}
    with Harness(PositionPosition, dict(NO_FAULT, **p)) as h:
        for k in range(100):
            h.step(k * 1e-3, leader_opening=0.02, follower_opening=0.02)
        for k in range(100, 300):
            h.step(k * 1e-3, leader_opening=0.02)
        outs = [h.step(k * 1e-3, leader_opening=0.02, follower_opening=0.04) for k in range(300, 400)]
    assert max(abs(o["gripper_force"]) for o in outs) == 0.0
