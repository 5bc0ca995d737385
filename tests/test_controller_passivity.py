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


def _opening_with_deficit(params, force, n=60, v=0.02):
    """Leader opening at ``v`` with a standing energy deficit, the estimate at ``force``; returns the forces."""
    out = []
    with Harness(PositionForce, {"deadband": 0.0, "smoothing_time": 0.0, "max_force_rate": 1e6, **params}) as h:
        h.step(0.0, leader_opening=0.015, leader_velocity=v, force=Sample(force, 0.0))
        h.comp.pas.energy = -0.05                       # e.g. left over by the release of a contact
        for k in range(1, n):
            t = k * 1e-3
            out.append(h.step(t, leader_opening=0.015 + v * t, leader_velocity=v, force=Sample(force, t))
                       ["gripper_force"])
    return out


def test_no_drag_and_no_pull_in_free_space():
    # after the contact: no force exchanged, a deficit left; the default controller sends exactly nothing
    assert all(f == 0.0 for f in _opening_with_deficit({}, 0.0))
    # the classic damping controller drags the opening fingers (a pull: negative force), capped at 40 N*s/m
    f = _opening_with_deficit({"passivity_controller": "damping"}, 0.0)
    assert min(f) == pytest.approx(-40.0 * 0.02, rel=0.05)


def test_passivity_never_turns_the_contact_force_round():
    # a small contact force while the fingers open fast with a large deficit: the force is taken away, not reversed
    f = _opening_with_deficit({}, 0.1, v=0.05)
    assert all(0.0 <= x <= 0.1 + 1e-12 for x in f) and f[-1] == 0.0
    f = _opening_with_deficit({"passivity_controller": "damping"}, 0.1, v=0.05)
    assert min(f) < -1.0


def _spring_contact(prediction: bool, k_env=2000.0, w=0.015, v=-0.005, n=400):
    """Leader closing at constant speed on a spring; the estimate is captured at 60 Hz and arrives one frame
    later, stamped with its capture time (as the DIGIT chain does). Returns (time, rendered, true force) lists
    and the controller."""
    frame = 17
    rows = []
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "force_prediction": prediction,
                                 "max_force_rate": 1e6}) as h:
        pending = None
        for k in range(n):
            t = k * 1e-3
            x = 0.0155 + v * t
            vals = {"leader_opening": x, "leader_velocity": v, "follower_opening": x}
            if k % frame == 0:
                if pending is not None:
                    vals["force"] = Sample(*pending)
                pending = (max(0.0, k_env * (w - x)), t)        # captured now, delivered one frame later
            f = h.step(t, **vals)["gripper_force"]
            rows.append((t, f, max(0.0, k_env * (w - x))))
        return rows, h.comp


def test_prediction_learns_the_contact_and_removes_the_latency():
    rows, comp = _spring_contact(True)
    assert comp.k_hat == pytest.approx(2000.0, rel=0.05)          # the learnt contact stiffness
    late = [abs(f - g) for t, f, g in rows if t > 0.25]
    assert max(late) < 0.05                                       # renders the present force, not a late one
    rows0, _ = _spring_contact(False)
    late0 = [abs(f - g) for t, f, g in rows0 if t > 0.25]
    assert min(late0) > 0.1                                       # without: 2000 N/m * 5 mm/s * >10 ms behind


def test_prediction_never_pulls_when_the_fingers_leave_the_contact():
    # closing into the spring, then opening fast out of it: the predicted force goes to zero, never below
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "max_force_rate": 1e6}) as h:
        pending, fs = None, []
        for k in range(600):
            t = k * 1e-3
            x = 0.0155 - 0.005 * t if t < 0.3 else 0.014 + 0.05 * (t - 0.3)
            vals = {"leader_opening": x}
            if k % 17 == 0:
                if pending is not None:
                    vals["force"] = Sample(*pending)
                pending = (max(0.0, 2000.0 * (0.015 - x)), t)
            fs.append(h.step(t, **vals)["gripper_force"])
        assert h.comp.k_hat > 1000.0
    assert max(fs) > 1.0 and min(fs) == 0.0 and fs[-1] == 0.0


def test_two_port_observer_sees_an_ideal_coupling_as_lossless():
    # instantaneous coupling, force scale 2: the leader port takes in 2*F*dx, the follower port (seen through the
    # force scale) gives 2*F*dx to the environment: the two-port observer stays at ~0, the leader port alone grows
    def run(observer):
        with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "force_prediction": False,
                                     "smoothing_time": 0.0, "max_force_rate": 1e6, "force_scale": 2.0,
                                     "energy_leak_time": None, "passivity_observer": observer}) as h:
            for k in range(300):
                t = k * 1e-3
                x = 0.0155 - 0.005 * t
                out = h.step(t, leader_opening=x, leader_velocity=-0.005, follower_opening=x,
                             force=Sample(max(0.0, 2000.0 * (0.015 - x)), t))
            return out["energy"], h.comp.pas.follower_energy
    e_leader, _ = run("leader-port")
    e_two, e_follower = run("two-port")
    assert e_leader > 1e-4                                    # ~ 2 * 1/2 * 2000 N/m * (1 mm)^2 = 2 mJ
    assert e_follower == pytest.approx(-e_leader, rel=0.02)
    assert abs(e_two) < 0.02 * e_leader


@pytest.mark.parametrize("mode,oscillates", [
    ({}, False),                                                               # the default
    ({"force_prediction": False, "passivity_controller": "damping",
      "passivity_observer": "leader-port"}, True),                              # the previous default
    ({"passivity": False}, True),                                              # the prediction alone
])
def test_stiff_contact_at_high_force_scale_in_the_simulated_loop(mode, oscillates):
    # the stability sweep's hardest corner (k_f = 4, 1 MPa gel): sim-omega7 + sim-gripper + sim-force-sensor
    import numpy as np

    from teletouch.plugins.controllers.experiments import Recorder, build_runtime, sim_graph

    intent = {"type": "close-and-hold", "start_opening": 0.02, "target_opening": 0.010, "speed": 0.005,
              "start_time": 0.5, "hold_time": 100.0, "release": False}
    doc = sim_graph("position-force", "ideal", duration=4.0, intent=intent,
                    controller_params={"force_scale": 4.0, **mode}, gripper_params={"modulus": 1.0e6})
    rt = build_runtime(doc)
    rec = Recorder(["gripper.contact_force", "controller.gripper_force"])
    rt.add_tap(rec)
    assert rt.run().status == "ok"
    t, f = rec.series("gripper.contact_force")
    p2p = float(np.ptp(f[t >= 2.5]))
    assert (p2p > 0.2) == oscillates, p2p
    _, fr = rec.series("controller.gripper_force")
    assert np.all(np.isfinite(fr)) and np.abs(fr).max() <= 8.0
    if not oscillates:
        assert fr.min() >= 0.0 and f[t >= 2.5].mean() == pytest.approx(1.4 / 4, rel=0.3)   # full force scale


def test_force_cut_can_spread_the_payment_of_a_deficit():
    from teletouch.plugins.controllers.passivity import reduce_force_to

    assert reduce_force_to(2.0, -1e-5, 0.01, 1e-3) == pytest.approx(1.0)                  # within one step
    assert reduce_force_to(2.0, -1e-5, 0.01, 1e-3, pay_time=0.01) == pytest.approx(1.9)   # over 10 ms
    assert reduce_force_to(2.0, -1e-5, 0.002, 1e-3, v_min=0.003) == 2.0                  # too slow to matter


def test_a_misjudged_contact_stiffness_cannot_push_the_hand_far():
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "max_force_rate": 1e6,
                                 "prediction_max_change": 0.5}) as h:
        pending = None
        for k in range(200):                       # learn on a closing contact
            t = k * 1e-3
            vals = {"leader_opening": 0.0155 - 0.005 * t}
            if k % 17 == 0:
                if pending is not None:
                    vals["force"] = Sample(*pending)
                pending = (max(0.0, 2000.0 * (0.015 - vals["leader_opening"])), t)
            f0 = h.step(t, **vals)["gripper_force"]
        h.comp.k_hat = 1e6                         # a wildly wrong stiffness
        f1 = h.step(0.2, leader_opening=0.0155 - 0.005 * 0.2 - 0.002)["gripper_force"]
    assert f0 > 0.5 and f1 - f0 <= 0.5 + 0.05
