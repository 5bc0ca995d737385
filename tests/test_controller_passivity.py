"""Time-domain passivity observer/controller: pure functions, and a closed loop with an active environment."""

from __future__ import annotations

import pytest

from teletouch import Sample
from teletouch.plugins.controllers.passivity import (
    PassivityState, commit, damping_for, observe, passivity_force, port_power,
)
from teletouch.plugins.controllers.position_force import PositionForce
from teletouch.testing import Harness


def test_observer_sign_convention_and_leak():
    # closing (v < 0) against a resisting force (f > 0): the operator puts energy in
    assert port_power(2.0, -0.01) == pytest.approx(0.02)
    assert observe(0.0, 2.0, -0.01, 1e-3) == pytest.approx(2e-5)
    assert observe(0.0, 2.0, 0.01, 1e-3) == pytest.approx(-2e-5)        # pushing the fingers open: energy out
    assert observe(1.0, 0.0, 0.0, 0.1, leak_time=0.1) == pytest.approx(1 / 2.718281828, rel=1e-6)
    assert observe(-1.0, 0.0, 0.0, 0.1, leak_time=0.1) == -1.0            # a deficit never leaks away


def test_damping_dissipates_the_deficit_and_is_capped():
    assert damping_for(1e-3, 0.1, 1e-3, 40.0) == 0.0
    a = damping_for(-1e-6, 0.05, 1e-3, 40.0)
    assert a == pytest.approx(1e-6 / (0.05 ** 2 * 1e-3))
    assert damping_for(-1.0, 0.05, 1e-3, 40.0) == 40.0                    # capped at the device's damping
    assert damping_for(-1.0, 0.0, 1e-3, 40.0) == 0.0                      # nothing to do without motion
    st = PassivityState(energy=-1e-6)
    f, alpha = passivity_force(st, 1.0, 0.05, 1e-3, 40.0)
    assert f == pytest.approx(1.0 - alpha * 0.05) and alpha > 0
    commit(st, f, 1.0, 0.05, 1e-3, alpha)
    assert st.energy == pytest.approx(0.0, abs=1e-12)                     # exactly restored to passive
    assert st.dissipated == pytest.approx(alpha * 0.05 ** 2 * 1e-3)


def test_force_reduction_never_reverses_the_force():
    # a deficit far beyond what 40 N*s/m can dissipate while the device pushes the fingers open (energy out)
    st = PassivityState(energy=-1.0)
    f, alpha = passivity_force(st, 2.0, 0.01, 1e-3, 40.0)
    assert f == 0.0 and alpha == pytest.approx(200.0)           # reduced to zero, not past it
    f, alpha = passivity_force(st, 2.0, 0.01, 1e-3, 40.0, reduce_force=False)
    assert f == pytest.approx(2.0 - 40.0 * 0.01) and alpha == 40.0
    # closing against the force (energy in): only the capped damping, the force is not reduced
    f, alpha = passivity_force(st, 2.0, -0.01, 1e-3, 40.0)
    assert f == pytest.approx(2.0 + 40.0 * 0.01) and alpha == 40.0


def _loop(passivity: bool, ke: float, delay: float = 0.04, duration: float = 3.0, spring_only: bool = False,
          **params):
    """The controller component in a loop with a leader (finger mass, a loosely held hand) and an active
    environment: a spring whose force reaches the controller at 60 Hz, ``delay`` late (a slow estimator).
    Returns the peak-to-peak leader force over the last second, and the controller."""
    m, k_h, b_h = 0.03, 300.0, 1.0
    x, v = 0.02, 0.0
    w, x_d = 0.015, 0.008
    hist: list[tuple[float, float]] = []
    forces = []
    with Harness(PositionForce, {"passivity": passivity, "deadband": 0.0, **params}) as h:
        n = int(duration * 1000)
        for k in range(n):
            t = k * 1e-3
            hist.append((t, max(0.0, ke * (w - x))))
            vals = {"leader_opening": x, "leader_velocity": v}
            if spring_only:
                vals["force"] = Sample(hist[-1][1], t)
            elif k % 17 == 0:
                td = t - delay
                fd = next((fv for ts, fv in reversed(hist) if ts <= td), 0.0)
                vals["force"] = Sample(fd, t)
            f = h.step(t, **vals)["gripper_force"]
            assert abs(f) <= 8.0
            for _ in range(10):
                a = (f + k_h * (x_d - x) - b_h * v) / m
                v += a * 1e-4
                x += v * 1e-4
            forces.append(f)
        last = forces[-1000:]
        return max(last) - min(last), h.comp


def test_active_environment_is_kept_stable_by_the_passivity_controller():
    p2p_off, _ = _loop(False, ke=1000.0)
    p2p_on, comp = _loop(True, ke=1000.0)
    assert p2p_off > 2.0                     # the delayed estimate makes the loop oscillate (limit cycle)
    assert p2p_on < 0.2                      # passivity control removes it
    assert comp.pas.dissipated > 0 and comp.pas.active_steps > 0


def test_passive_environment_gets_no_damping():
    # an instantaneous spring, no smoothing: passive, so the controller stays transparent (pure TDPA: the leak of
    # stored energy, a deliberate trade of transparency for robustness, is off here)
    p2p, comp = _loop(True, ke=300.0, spring_only=True, smoothing_time=0.0, max_force_rate=1e6,
                      energy_leak_time=None)
    assert p2p < 0.05
    assert comp.pas.dissipated < 1e-4
    assert comp.pas.energy >= -1e-9


def test_gain_adaptation_drops_smoothly_and_recovers():
    from teletouch.plugins.controllers.passivity import adapt_gain

    g = 1.0
    for _ in range(100):                              # 0.1 s of persistent deficit at 2/s
        g = adapt_gain(g, True, 1e-3)
    assert g == pytest.approx(0.8)
    for _ in range(1000):
        g = adapt_gain(g, True, 1e-3)
    assert g == 0.1                                   # floor
    for _ in range(3000):                             # 3 time constants without deficit
        g = adapt_gain(g, False, 1e-3)
    assert g == pytest.approx(1 - 0.9 * 2.718281828 ** -3, abs=2e-3)


def test_observer_runs_without_the_controller():
    # passivity off: the energy output still observes the port, and no damping is added
    with Harness(PositionForce, {"passivity": False, "deadband": 0.0, "smoothing_time": 0.0}) as h:
        for k in range(100):
            out = h.step(k * 1e-3, leader_opening=0.02 + 1e-5 * k, leader_velocity=0.01, force=Sample(2.0, k * 1e-3))
    assert out["energy"] < 0 and out["damping"] == 0.0      # pushing the fingers open: energy flows out
    assert out["gripper_force"] == pytest.approx(2.0)
