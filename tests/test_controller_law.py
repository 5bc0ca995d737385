"""Control law of the teleoperation controllers: pure functions and the component's force path (no runtime)."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from teletouch import Sample
from teletouch.plugins.controllers.position_force import (
    Differentiator, ForceHold, NoFeedback, PositionForce, PositionPosition, deadband, finite_or, map_opening,
    rate_limit, saturate, shape_force, unmap_opening,
)
from teletouch.testing import Harness


def test_mapping_scale_offset_limits():
    assert map_opening(0.01, 2.0, 0.005, 0.0, 0.09) == pytest.approx(0.025)
    assert map_opening(0.06, 2.0, 0.0, 0.0, 0.09) == 0.09          # upper limit
    assert map_opening(-0.01, 1.0, 0.0, 0.002, 0.09) == 0.002      # lower limit
    assert unmap_opening(map_opening(0.012, 1.5, 0.003, 0.0, 0.09), 1.5, 0.003) == pytest.approx(0.012)


def test_deadband_is_continuous_and_rejects_negative():
    assert deadband(0.01, 0.02) == 0.0
    assert deadband(0.02, 0.02) == 0.0
    assert deadband(0.02 + 1e-9, 0.02) == pytest.approx(1e-9)     # no step at the edge
    assert deadband(1.0, 0.02) == pytest.approx(0.98)
    assert deadband(-3.0, 0.02) == 0.0


def test_shape_force_gain_sign_saturation_nan():
    assert shape_force(2.0, 1.5, 1, 0.0, 8.0) == pytest.approx(3.0)
    assert shape_force(2.0, 1.5, -1, 0.0, 8.0) == pytest.approx(-3.0)
    assert shape_force(20.0, 1.0, 1, 0.0, 8.0) == 8.0
    assert shape_force(math.nan, 1.0, 1, 0.0, 8.0) == 0.0
    assert shape_force(math.inf, 1.0, 1, 0.0, 8.0) == 0.0
    assert saturate(-9.0, 8.0) == -8.0 and saturate(3.0, 8.0) == 3.0


def test_rate_limit_and_finite_or():
    assert rate_limit(0.0, 5.0, 200.0, 1e-3) == pytest.approx(0.2)
    assert rate_limit(1.0, -5.0, 200.0, 1e-3) == pytest.approx(0.8)
    assert rate_limit(1.0, 1.1, 200.0, 1e-3) == pytest.approx(1.1)
    assert finite_or("x", 3.0) == 3.0 and finite_or(math.nan, 1.0) == 1.0 and finite_or(2, 0.0) == 2.0


def test_force_hold_ramps_from_wherever_it_is():
    h = ForceHold(0.0)
    h.set(0.0, 1.0, 0.02)
    assert h.value(0.01) == pytest.approx(0.5)
    assert h.value(0.02) == pytest.approx(1.0)
    h.set(0.01, 0.0, 0.02)                      # interrupted half-way: restarts from 0.5, no jump
    assert h.value(0.01) == pytest.approx(0.5)
    assert h.value(0.02) == pytest.approx(0.25)
    assert h.value(1.0) == 0.0


def test_differentiator_tracks_a_ramp():
    d = Differentiator(50.0)
    v = 0.0
    for k in range(200):
        v = d.update(k * 1e-3, 0.02 - 0.01 * k * 1e-3)
    assert v == pytest.approx(-0.01, rel=1e-3)
    assert d.update(0.199, 0.0) == v             # a repeated/old sample changes nothing


def _run_pf(params, n, force_at, leader=lambda t: 0.02, rate=1000.0):
    """Step a position-force controller; force_at(k, t) -> Sample or None."""
    outs = []
    with Harness(PositionForce, params) as h:
        for k in range(n):
            t = k / rate
            vals = {"leader_opening": leader(t)}
            s = force_at(k, t)
            if s is not None:
                vals["force"] = s
            outs.append(h.step(t, **vals))
        return outs, h.comp


def test_position_force_follows_leader_and_renders_scaled_force():
    params = {"scale": 1.0, "offset": 0.001, "force_scale": 2.0, "deadband": 0.0, "passivity": False}
    outs, comp = _run_pf(params, 300, lambda k, t: Sample(1.5, t) if k % 17 == 0 else None,
                         leader=lambda t: 0.02 - 0.01 * t)
    assert outs[-1]["opening_command"] == pytest.approx(0.02 - 0.01 * 0.299 + 0.001)
    assert outs[-1]["gripper_force"] == pytest.approx(3.0)      # k_f * f_s, positive pushes fingers apart
    assert comp.status()["leader_m"] == pytest.approx(0.02 - 0.01 * 0.299, abs=1e-9)


def test_camera_rate_estimate_is_smoothed_never_a_jump():
    # a 60 Hz staircase 0 -> 4 N in one frame: the hand sees a ramp limited by smoothing and the rate limit
    params = {"deadband": 0.0, "passivity": False, "max_force_rate": 1000.0, "smoothing_time": 1 / 60}
    outs, comp = _run_pf(params, 200, lambda k, t: Sample(0.0 if t < 0.05 else 4.0, t) if k % 17 == 0 else None)
    f = [o["gripper_force"] for o in outs]
    steps = [abs(b - a) for a, b in zip(f, f[1:])]
    assert max(steps) <= 4.0 / (1000 / 60) + 1e-9                 # <= 0.24 N per 1 ms step
    assert f[-1] == pytest.approx(4.0)
    # documented latency: the ramp reaches the new value smoothing_time after it arrives
    k_new = next(k for k in range(200) if k % 17 == 0 and k / 1000 >= 0.05)
    k_full = next(k for k, v in enumerate(f) if v >= 4.0 - 1e-9)
    assert (k_full - k_new) / 1000 == pytest.approx(1 / 60, abs=1.5e-3)


def test_position_position_baseline_pd_on_error():
    with Harness(PositionPosition, {"kp": 500.0, "kd": 0.0, "passivity": False, "max_force_rate": 1e5}) as h:
        for k in range(50):
            out = h.step(k * 1e-3, leader_opening=0.010, follower_opening=0.012)
    assert out["opening_command"] == pytest.approx(0.010)
    assert out["gripper_force"] == pytest.approx(500.0 * 0.002)   # follower blocked wider: pushes the hand open
    with Harness(PositionPosition, {"kp": 500.0, "kd": 0.0, "passivity": False, "max_force_rate": 1e5}) as h:
        out = h.step(0.0, leader_opening=0.010)                     # no follower reading: no force
        out = h.step(0.001, leader_opening=0.010)
    assert out["gripper_force"] == 0.0


def test_no_feedback_baseline_sends_no_force():
    with Harness(NoFeedback) as h:
        for k in range(50):
            out = h.step(k * 1e-3, leader_opening=0.015, force=5.0, leader_velocity=-0.01)
    assert out["gripper_force"] == 0.0 and out["opening_command"] == pytest.approx(0.015)
    assert h.comp.status()["force_n"] == 5.0


def test_params_are_validated():
    with pytest.raises(ValidationError, match=r"opening_min \(0.05 m\) must be below opening_max \(0.01 m\)"):
        PositionForce.Params(opening_min=0.05, opening_max=0.01)
    assert PositionForce.Params(deadband="50mN").deadband == pytest.approx(0.05)
    with pytest.raises(ValidationError, match=r"force_sign\s+Input should be 1"):
        PositionForce.Params(force_sign=2)


def test_constant_leader_damping_option():
    p = {"leader_damping": 5.0, "passivity": False, "deadband": 0.0, "max_force_rate": 1e5}
    with Harness(PositionForce, p) as h:
        for k in range(20):
            out = h.step(k * 1e-3, leader_opening=0.02 + 0.01 * k * 1e-3, leader_velocity=0.01)
    assert out["gripper_force"] == pytest.approx(-0.05)            # opposes the motion


def test_a_sign_that_pulls_the_fingers_closed_is_refused():
    # gripper_force is positive when it pushes the operator's fingers apart (docs/ports.md), and every leader driver
    # keeps to that: force_sign -1 rendered a sensed grip as a pull closing the fingers into the object (-2 N here)
    with pytest.raises(ValidationError, match=r"force_sign[\s\S]*pull"):
        PositionForce.Params(force_sign=-1)
    assert PositionForce.Params(force_sign=1).force_sign == 1
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "smoothing_time": 0.0}) as h:
        for k in range(50):
            out = h.step(k * 1e-3, leader_opening=0.02, force=Sample(2.0, k * 1e-3))
    assert out["gripper_force"] == pytest.approx(2.0)                # pushes the fingers apart


@pytest.mark.parametrize("cls,params,names", [
    (PositionForce, {"leader_damping": 50.0}, ("leader_damping", "max_damping")),
    (NoFeedback, {"leader_damping": 10.0, "max_damping": 5.0}, ("leader_damping", "max_damping")),
    (PositionPosition, {"kd": 30.0, "leader_damping": 15.0}, ("kd", "leader_damping", "max_damping")),
])
def test_constant_damping_beyond_what_the_leader_renders_is_refused(cls, params, names):
    # max_damping is the most damping the leader renders stably (Omega.7: 40 N*s/m); the constant damping must fit
    # in it (the passivity damping gets what is left)
    with pytest.raises(ValidationError) as e:
        cls.Params(**params)
    assert all(n in str(e.value) for n in names), str(e.value)
    cls.Params(**dict(params, max_damping=60.0))
