"""The baselines (position-position, no-feedback) have position-force's protections; every mode under inputs that
arrive at different rates, repeat, arrive out of order or jump."""

from __future__ import annotations

import math

import pytest

from teletouch import Sample
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
from teletouch.testing import Harness

ALL = [PositionForce, PositionPosition, NoFeedback]
BASELINES = [PositionPosition, NoFeedback]


def _inputs(cls, t, x_l=0.02, x_f=None, **extra):
    """Inputs every mode can take: the leader, the follower (position-position needs it) and a force."""
    vals = {"leader_opening": x_l, "follower_opening": x_l if x_f is None else x_f, "force": Sample(0.0, t)}
    vals.update(extra)
    return vals


@pytest.mark.parametrize("cls", BASELINES)
def test_nothing_before_the_first_leader_reading(cls):
    with Harness(cls) as h:
        outs = [h.step(k * 1e-3, follower_opening=0.012, force=Sample(3.0, k * 1e-3)) for k in range(20)]
        assert h.comp.state == "waiting"
    assert all("opening_command" not in o and o["gripper_force"] == 0.0 and o["energy"] == 0.0 for o in outs)


@pytest.mark.parametrize("cls", BASELINES)
def test_follower_command_is_clamped(cls):
    with Harness(cls, {"opening_min": 0.005, "opening_max": 0.06, "scale": 2.0}) as h:
        assert h.step(0.0, **_inputs(cls, 0.0, x_l=0.001))["opening_command"] == 0.005
        assert h.step(0.001, **_inputs(cls, 0.001, x_l=0.05))["opening_command"] == 0.06
        assert h.step(0.002, **_inputs(cls, 0.002, x_l=1e300))["opening_command"] == 0.06
        assert h.step(0.003, **_inputs(cls, 0.003, x_l=0.02))["opening_command"] == pytest.approx(0.04)


@pytest.mark.parametrize("cls", BASELINES)
@pytest.mark.parametrize("loss", ["nan", "stale"])
def test_lost_leader_holds_the_command_and_fades_the_force(cls, loss):
    # no-feedback renders only the constant leader damping here (20 N*s/m at -0.1 m/s), position-position its
    # coupling (400 N/m x 5 mm): 2 N each
    p = {"fade_time": 0.1, "passivity": False}
    p.update({"kp": 400.0, "kd": 0.0} if cls is PositionPosition else {"leader_damping": 20.0})
    with Harness(cls, p) as h:
        for k in range(100):
            t = k * 1e-3
            x = 0.015 - 1e-4 * k
            out = h.step(t, leader_opening=x, follower_opening=x + 0.005, leader_velocity=-0.1)
        cmd, f0 = out["opening_command"], out["gripper_force"]
        assert f0 == pytest.approx(2.0)
        outs, ok = [], []
        for k in range(1, 200):
            t = 0.099 + k * 1e-3
            lead = math.nan if loss == "nan" else Sample(x, 0.099)
            outs.append(h.step(t, leader_opening=lead, follower_opening=x + 0.005))
            ok.append(h.comp.leader_ok)
        assert h.comp.state == "stale-leader"
    lost = ok.index(False)
    assert lost == (0 if loss == "nan" else pytest.approx(50, abs=1))   # a stale one after leader_stale_after
    assert all(o["gripper_force"] == pytest.approx(2.0) for o in outs[:lost])
    outs = outs[lost:]
    assert all(o["opening_command"] == cmd for o in outs)      # the follower holds its last command
    f = [o["gripper_force"] for o in outs]
    assert f[-1] == 0.0 and all(abs(b) <= abs(a) + 1e-12 for a, b in zip(f, f[1:]))
    assert max(abs(b - a) for a, b in zip([f0] + f, f)) <= 2.0 / 0.1 * 1e-3 + 1e-9   # faded over fade_time


def test_position_position_force_is_limited_and_rate_limited():
    with Harness(PositionPosition, {"kp": 1e4, "max_force": 3.0, "max_force_rate": 100.0, "passivity": False}) as h:
        f = [h.step(k * 1e-3, leader_opening=0.010, follower_opening=0.020)["gripper_force"] for k in range(100)]
        f += [h.step(0.1 + k * 1e-3, leader_opening=0.030, follower_opening=0.020)["gripper_force"]
              for k in range(100)]
    assert max(f) == 3.0 and min(f) == -3.0
    assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 100.0 * 2e-3 + 1e-12


def test_position_position_stale_follower_fades_the_coupling_over_fade_time():
    # the coupling force's source is the follower opening: lost, the force fades out over fade_time like a lost
    # estimate in position-force (it used to drop at max_force_rate, 2 N in 10 ms; with a high rate limit at once)
    p = {"kp": 400.0, "kd": 0.0, "passivity": False, "fade_time": 0.2}
    for loss in (math.nan, None):
        with Harness(PositionPosition, p) as h:
            for k in range(100):
                out = h.step(k * 1e-3, leader_opening=0.010, follower_opening=0.015)
            f0 = out["gripper_force"]
            assert f0 == pytest.approx(2.0)
            f = []
            for k in range(1, 300):
                t = 0.099 + k * 1e-3
                fol = Sample(0.015, 0.099) if loss is None else loss
                f.append(h.step(t, leader_opening=0.010, follower_opening=fol)["gripper_force"])
            assert h.comp.state == "stale-follower"
        if loss is None:                                  # still fresh for leader_stale_after (50 ms)
            assert f[48] == pytest.approx(2.0)
            f = f[50:]
        assert f[99] == pytest.approx(1.0, abs=0.02)      # half-way after 100 ms
        assert f[205:] == [0.0] * len(f[205:])
        assert max(abs(b - a) for a, b in zip([f0] + f, f)) <= 2.0 / 0.2 * 1e-3 + 1e-9
        # the follower back: the coupling returns, rate-limited
        with Harness(PositionPosition, dict(p, max_force_rate=200.0)) as h:
            for k in range(100):
                h.step(k * 1e-3, leader_opening=0.010, follower_opening=0.015)
            for k in range(1, 100):
                h.step(0.099 + k * 1e-3, leader_opening=0.010, follower_opening=math.nan)
            g = [h.step(0.2 + k * 1e-3, leader_opening=0.010, follower_opening=0.015)["gripper_force"]
                 for k in range(100)]
        assert max(abs(b - a) for a, b in zip(g, g[1:])) <= 0.2 + 1e-9 and g[-1] == pytest.approx(2.0)


@pytest.mark.parametrize("cls", ALL)
def test_reactivation_starts_afresh(cls):
    p = {"kp": 400.0} if cls is PositionPosition else {"leader_damping": 20.0} if cls is NoFeedback else {}
    with Harness(cls, p) as h:
        for k in range(300):
            t = k * 1e-3
            h.step(t, **_inputs(cls, t, x_l=0.015 - 1e-5 * k, x_f=0.02, leader_velocity=-0.1,
                                force=Sample(3.0, t)))
        assert abs(h.comp.out_force) > 0.5
        h.comp.pas.energy = -0.5
        h.comp.deactivate()
        h.comp.activate()
        assert h.comp.pas.energy == 0.0 and h.comp.out_force == 0.0 and h.comp.command is None
        assert h.comp.state == "waiting"
        out = h.step(1.0, **_inputs(cls, 1.0, x_l=0.015, x_f=0.02, leader_velocity=-0.1, force=Sample(3.0, 1.0)))
        assert out["gripper_force"] == 0.0 and out["energy"] == 0.0     # no jump to the old force
        out2 = h.step(1.001, **_inputs(cls, 1.001, x_l=0.015, x_f=0.02, leader_velocity=-0.1,
                                       force=Sample(3.0, 1.001)))
        assert abs(out2["gripper_force"]) <= 0.2 + 1e-12
        assert out["opening_command"] == pytest.approx(0.015)


@pytest.mark.parametrize("cls", ALL)
def test_an_older_leader_sample_after_a_newer_one_is_ignored(cls):
    # a leader sample stamped before the newest one taken (out of order) must not move the follower back
    p = {"kp": 400.0, "kd": 0.0, "passivity": False} if cls is PositionPosition else {"passivity": False}
    with Harness(cls, p) as h:
        for k in range(100):
            t = k * 1e-3
            h.step(t, **_inputs(cls, t, x_l=0.02, x_f=0.02))
        out = h.step(0.1, **_inputs(cls, 0.1, x_l=Sample(0.03, 0.1), x_f=0.03))
        assert out["opening_command"] == pytest.approx(0.03)
        outs = [h.step(0.1 + k * 1e-3, **_inputs(cls, 0.1 + k * 1e-3, x_l=Sample(0.02, 0.09), x_f=0.03))
                for k in range(1, 40)]
        assert all(o["opening_command"] == pytest.approx(0.03) for o in outs)
        assert h.comp.x_l == 0.03
        if cls is PositionPosition:                       # the coupling uses the newest leader opening too
            assert all(abs(o["gripper_force"]) < 1e-9 for o in outs)
        # the newest sample ages: the leader goes stale on time, and later samples are taken again
        out = h.step(0.16, **_inputs(cls, 0.16, x_l=Sample(0.02, 0.09), x_f=0.03))
        assert not h.comp.leader_ok
        out = h.step(0.161, **_inputs(cls, 0.161, x_l=0.025, x_f=0.025))
        assert h.comp.leader_ok and out["opening_command"] == pytest.approx(0.025)


@pytest.mark.parametrize("cls", ALL)
def test_a_future_stamp_does_not_lock_out_the_samples_after_it(cls):
    with Harness(cls, {"passivity": False}) as h:
        for k in range(50):
            h.step(k * 1e-3, **_inputs(cls, k * 1e-3, x_l=0.02))
        out = h.step(0.05, **_inputs(cls, 0.05, x_l=Sample(0.05, 3600.0)))
        assert not h.comp.leader_ok and out["opening_command"] == pytest.approx(0.02)
        out = h.step(0.051, **_inputs(cls, 0.051, x_l=0.021))
        assert h.comp.leader_ok and out["opening_command"] == pytest.approx(0.021)


def test_position_position_ignores_an_older_follower_sample():
    with Harness(PositionPosition, {"kp": 400.0, "kd": 0.0, "passivity": False, "max_force_rate": 1e5}) as h:
        for k in range(50):
            out = h.step(k * 1e-3, leader_opening=0.010, follower_opening=0.015)
        assert out["gripper_force"] == pytest.approx(2.0)
        out = h.step(0.05, leader_opening=0.010, follower_opening=Sample(0.010, 0.04))   # older, out of order
        assert out["gripper_force"] == pytest.approx(2.0)


@pytest.mark.parametrize("cls", ALL)
def test_leader_and_estimate_at_their_own_rates_with_repeats(cls):
    # 1 kHz controller, leader at 500 Hz (each sample seen twice), estimate at 60 Hz: no step in the force
    # beyond the rate limit, the command follows every new leader sample
    p = {"kp": 400.0, "passivity": False} if cls is PositionPosition else {"deadband": 0.0} \
        if cls is PositionForce else {}
    with Harness(cls, p) as h:
        f, cmds = [], []
        for k in range(400):
            t = k * 1e-3
            tl = (k // 2) * 2e-3
            x = 0.02 - 0.01 * tl
            vals = {"leader_opening": Sample(x, tl), "follower_opening": Sample(x + 5e-4, tl)}
            if k % 17 == 0:
                vals["force"] = Sample(0.0 if t < 0.1 else 2.0, t)
            out = h.step(t, **vals)
            f.append(out["gripper_force"])
            cmds.append((x, out["opening_command"]))
    assert all(c == pytest.approx(x) for x, c in cmds)
    assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 0.2 + 1e-9
    if cls is PositionForce:
        assert f[-1] == pytest.approx(2.0, abs=0.05)
    elif cls is PositionPosition:
        assert f[-1] == pytest.approx(400.0 * 5e-4, abs=0.05)


@pytest.mark.parametrize("cls", ALL)
def test_a_leader_jump_is_passed_to_the_follower_and_the_force_stays_rate_limited(cls):
    # a 20 mm jump of the leader opening in one sample: the command jumps with it (every follower driver moves at
    # most max_speed: docs/followers.md), the leader force moves no faster than max_force_rate
    p = {"passivity": True, "leader_damping": 10.0}
    if cls is PositionPosition:
        p["kp"] = 400.0
    with Harness(cls, p) as h:
        f, cmds = [], []
        for k in range(200):
            t = k * 1e-3
            x = 0.01 if k < 100 else 0.03
            out = h.step(t, **_inputs(cls, t, x_l=x, x_f=0.01 if k < 110 else 0.03, force=Sample(1.0, t)))
            f.append(out["gripper_force"])
            cmds.append(out["opening_command"])
            assert all(math.isfinite(v) for v in out.values())
    assert cmds[99] == pytest.approx(0.01) and cmds[100] == pytest.approx(0.03)
    assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 200.0 * 2e-3 + 1e-9
    assert max(abs(v) for v in f) <= 8.0
