"""Time-domain passivity observer/controller: pure functions, and a closed loop with an active environment."""

from __future__ import annotations

import math

import pytest

from teletouch import Sample
from teletouch.plugins.controllers.passivity import (
    PassivityState, commit, damping_for, observe, passivity_force, port_power,
)
from teletouch.plugins.controllers.position_force import PositionForce, PositionPosition
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
    p2p, comp = _loop(True, ke=300.0, spring_only=True, smoothing_time=0.0, max_force_rate=1e5,
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
    with Harness(PositionForce, {"deadband": 0.0, "smoothing_time": 0.0, "max_force_rate": 1e5, **params}) as h:
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
                                 "max_force_rate": 1e5}) as h:
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
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "max_force_rate": 1e5}) as h:
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
            if k == 299:
                assert h.comp.k_hat > 1000.0                     # learnt in the contact
        assert h.comp.k_hat == 0.0                               # and forgotten when it ended
    assert max(fs) > 1.0 and min(fs) == 0.0 and fs[-1] == 0.0


def test_two_port_observer_sees_an_ideal_coupling_as_lossless():
    # instantaneous coupling, force scale 2: the leader port takes in 2*F*dx, the follower port (seen through the
    # force scale) gives 2*F*dx to the environment: the two-port observer stays at ~0, the leader port alone grows
    def run(observer):
        with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "force_prediction": False,
                                     "smoothing_time": 0.0, "max_force_rate": 1e5, "force_scale": 2.0,
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
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "max_force_rate": 1e5,
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


def _finger_loop(cls, params, n=2000, deficit_at=100, deficit=-1.0):
    """The leader's finger (0.03 kg, sim-omega7's gripper + finger mass) held by a hand (300 N/m, 1 N*s/m) that
    closes to 8 mm; the controller renders on it at 1 kHz. A standing energy deficit is planted at ``deficit_at``.
    Returns the leader forces and the passivity damping output."""
    m, k_h, b_h = 0.03, 300.0, 1.0
    x, v, x_d = 0.02, 0.0, 0.008
    fs, ds = [], []
    with Harness(cls, params) as h:
        for k in range(n):
            t = k * 1e-3
            if k == deficit_at:
                h.comp.pas.energy = deficit
            vals = {"leader_opening": x, "leader_velocity": v, "follower_opening": x, "force": Sample(0.0, t)}
            out = h.step(t, **vals)
            f = out["gripper_force"]
            fs.append(f)
            ds.append(out["damping"])
            for _ in range(10):
                a = (f + k_h * (x_d - x) - b_h * v) / m
                v += a * 1e-4
                x += v * 1e-4
    return fs, ds


@pytest.mark.parametrize("cls,extra", [(PositionForce, {}), (PositionPosition, {"kp": 0.0, "kd": 10.0})])
def test_total_damping_on_the_leader_never_exceeds_max_damping(cls, extra):
    # constant damping + passivity damping (+ position-position's kd) together stay within max_damping, the most
    # the leader renders stably: the passivity cap is what the constant damping leaves. Before, 30 N*s/m of
    # leader_damping + 40 of passivity damping (70 in all) made the finger buzz at the rate limit (0.2 N p-p)
    p = {"leader_damping": 20.0 if extra else 30.0, "passivity_controller": "damping", "free_space_reset": None,
         **extra}
    fs, ds = _finger_loop(cls, p)
    constant = p["leader_damping"] + extra.get("kd", 0.0)
    assert max(ds) > 0.0 and constant + max(ds) <= 40.0 + 1e-9
    last = fs[-500:]
    assert max(last) - min(last) < 0.01


def test_a_leader_velocity_glitch_does_not_poison_the_observer():
    # one leader_velocity sample of 1000 m/s (a driver glitch; the opening did not move) put a 1.6 J deficit in the
    # observer, and the passivity controller then cut the contact force to 0 for as long as the contact lasted
    def run(glitch):
        fs = []
        with Harness(PositionForce, {"deadband": 0.0}) as h:
            for k in range(1500):
                t = k * 1e-3
                v = 0.01 * math.cos(4 * math.pi * t)
                x = 0.012 + 0.01 / (4 * math.pi) * math.sin(4 * math.pi * t)
                vals = {"leader_opening": x, "leader_velocity": 1000.0 if glitch and k == 500 else v,
                        "follower_opening": x}
                if k % 17 == 0:
                    vals["force"] = Sample(2.0, t)
                out = h.step(t, **vals)
                fs.append((out["gripper_force"], out["energy"]))
            return fs, h.comp
    clean, _ = run(False)
    fs, comp = run(True)
    assert min(f for f, e in fs[600:]) > 1.0 and min(e for f, e in fs) > -1e-3
    assert max(abs(a[0] - b[0]) for a, b in zip(clean, fs)) < 0.05
    assert comp.invalid_inputs == 1


@pytest.mark.parametrize("bad", ["nan", "stale", "unwired"])
def test_bad_leader_velocity_falls_back_to_the_differentiated_opening(bad):
    def run(kind):
        with Harness(PositionForce, {"deadband": 0.0, "passivity_observer": "leader-port"}) as h:
            for k in range(400):
                t = k * 1e-3
                vals = {"leader_opening": 0.02 - 0.01 * t, "force": Sample(2.0, t)}
                if kind == "nan":
                    vals["leader_velocity"] = math.nan
                elif kind == "stale":
                    vals["leader_velocity"] = Sample(0.5, -1.0)
                out = h.step(t, **vals)
            return out, h.comp.v_l
    (out, v), (ref, v_ref) = run(bad), run("unwired")
    assert v == pytest.approx(-0.01, rel=1e-3) and v == v_ref
    assert out["energy"] == ref["energy"] and out["energy"] > 0      # closing against the force: energy in


def test_damping_and_cut_stay_within_the_force_and_rate_limits():
    # a large deficit while the fingers open fast against a large force: what leaves is still limited
    for controller in ("force", "damping"):
        p = {"deadband": 0.0, "max_force": 3.0, "max_force_rate": 100.0, "passivity_controller": controller,
             "smoothing_time": 0.0}
        with Harness(PositionForce, p) as h:
            f = []
            for k in range(300):
                t = k * 1e-3
                if k == 100:
                    h.comp.pas.energy = -10.0
                v = 0.3 if k < 200 else -0.3
                f.append(h.step(t, leader_opening=0.02 + 1e-4 * (k % 100), leader_velocity=v,
                                force=Sample(50.0, t))["gripper_force"])
        assert max(abs(x) for x in f) <= 3.0
        assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 100.0 * 2e-3 + 1e-12


def test_the_stiffness_of_a_previous_contact_is_not_used_on_the_next():
    # a stiff contact (20 kN/m), released, then a soft one (500 N/m): the prediction used the stiff contact's K at
    # the soft one's onset and rendered ~1 N (3.7 N at k_f = 4) where the contact gave 0.1 N, for ~130 ms
    def true_force(t, x):
        return max(0.0, (2e4 if t < 0.5 else 500.0) * (0.015 - x))

    def opening(t):
        if t < 0.3:
            return 0.0155 - 0.001 * t / 0.3
        if t < 0.5:
            return 0.0145 + (t - 0.3) * 0.01
        return 0.0165 - 0.005 * (t - 0.5)

    for k_f in (1.0, 4.0):
        rows = []
        with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "force_scale": k_f}) as h:
            pending = None
            for k in range(1500):
                t = k * 1e-3
                x = opening(t)
                vals = {"leader_opening": x}
                if k % 17 == 0:
                    if pending is not None:
                        vals["force"] = Sample(*pending)
                    pending = (true_force(t, x), t)
                rows.append((t, h.step(t, **vals)["gripper_force"], k_f * true_force(t, x)))
                if k == 290:
                    assert h.comp.k_hat > 1e4                              # learnt on the stiff contact
            assert h.comp.k_hat == pytest.approx(500.0, rel=0.1)           # and then on the soft one
        assert max(f - g for t, f, g in rows if t > 0.5) < 0.05 * k_f
        assert max(abs(f - g) for t, f, g in rows if t > 1.2) < 0.02 * k_f  # the prediction works again


@pytest.mark.parametrize("case", ["release", "stale"])
def test_the_prediction_never_steps_the_force_when_it_stops(case):
    # the predicted term was dropped in one step when the prediction stopped: on release (opening at 50 mm/s out of
    # the contact) the force jumped up by ~1 N after the contact was gone, when the estimate of zero arrived;
    # closing when the estimates stopped (stale), it dropped by the predicted 0.25 N in one step
    with Harness(PositionForce, {"deadband": 0.0, "passivity": False, "max_force_rate": 1e5}) as h:
        pending, fs = None, []
        for k in range(600):
            t = k * 1e-3
            if case == "release":
                x = 0.0155 - 0.005 * t if t < 0.3 else 0.014 + 0.05 * (t - 0.3)
            else:
                x = 0.0155 - 0.005 * t
            vals = {"leader_opening": x}
            if k % 17 == 0 and (case == "release" or t < 0.3):
                if pending is not None:
                    vals["force"] = Sample(*pending)
                pending = (max(0.0, 2000.0 * (0.015 - x)), t)
            fs.append(h.step(t, **vals)["gripper_force"])
            if k == 299:
                assert h.comp.k_hat > 1000.0 and fs[-1] > 1.5        # the prediction was at work
    steps = [b - a for a, b in zip(fs[300:], fs[301:])]
    if case == "release":
        assert max(steps) < 0.05 and fs[-1] == 0.0               # no bump up once out of the contact
    else:
        # the predicted 1 N (the cap) is blended out over smoothing_time (~0.06 N a step) while the estimate fades
        assert max(abs(s) for s in steps) < 0.08 and fs[-1] == 0.0


@pytest.mark.parametrize("k_env,v", [(20000.0, -0.005), (2000.0, -0.02)])
def test_a_newly_learnt_stiffness_never_steps_the_force(k_env, v):
    # the learnt K was used at once: when the first K of a contact was learnt (and at every large change of it) the
    # predicted term stepped by K's change x the command's motion since the capture, 0.97 N in one step at 20 kN/m
    # (0.41 N at 2 kN/m, 20 mm/s) where the true force moves 0.1 N (0.04 N) a step; K now ramps as the capture
    # point does, over smoothing_time
    rows, comp = _spring_contact(True, k_env=k_env, v=v)
    assert comp.k_hat > 0.5 * k_env                                 # the prediction was at work
    steps = [abs(b[1] - a[1]) for a, b in zip(rows, rows[1:])]
    assert max(steps) < 2.0 * k_env * abs(v) * 1e-3                 # at most twice the true force's change a step


def test_no_damping_is_kept_raised_in_free_space_for_the_next_contact():
    # a deficit left by a released contact, the fingers closing in free space onto a new object: the force
    # controller applies nothing in free space, yet its damping went up to 40 N*s/m there (shown on the damping
    # output) and met the new contact at once, 2 N at 50 mm/s in one step; it now rises over damping_smoothing
    v = -0.05
    with Harness(PositionForce, {"deadband": 0.0, "force_prediction": False, "max_force_rate": 1e5}) as h:
        h.step(0.0, leader_opening=0.05, leader_velocity=v, force=Sample(0.0, 0.0))
        h.comp.pas.energy = -0.01
        outs = []
        for k in range(1, 80):
            t = k * 1e-3
            outs.append(h.step(t, leader_opening=0.05 + v * t, leader_velocity=v,
                               force=Sample(0.0 if k < 40 else 0.5, t)))
    free = outs[:39]
    assert all(o["gripper_force"] == 0.0 and o["damping"] == 0.0 for o in free)    # was 40 N*s/m shown
    assert free[-1]["energy"] < -0.005                                  # the deficit is still there
    first = next(i for i, o in enumerate(outs) if o["gripper_force"] > 0.0)
    d = [o["damping"] for o in outs[first - 1:]]
    assert d[1] <= 0.2 * 40.0 + 1e-9 and max(b - a for a, b in zip(d, d[1:])) <= 0.2 * 40.0 + 1e-9
    assert max(d) > 35.0                                                # the deficit still brings it up
    assert outs[first]["gripper_force"] < 0.5 + 0.2 * 40.0 * abs(v)     # was 2.03 N


def test_a_repeated_time_keeps_the_passivity_damping():
    # a step at the same time as the previous one (dt = 0) dropped the damping to 0 with damping_release 0, and it
    # rose again over damping_smoothing: the force surged 1.2 -> 1.6 N while the deficit was still being paid
    p = {"deadband": 0.0, "smoothing_time": 0.0, "force_prediction": False, "damping_release": 0.0,
         "reduction_min_velocity": 1.0}
    v = 0.02
    with Harness(PositionForce, p) as h:
        outs = []
        for k in range(120):
            t = k * 1e-3
            if k == 60:
                h.comp.pas.energy = -0.05
            vals = {"leader_opening": 0.015 + v * t, "leader_velocity": v, "force": Sample(2.0, t)}
            outs.append(h.step(t, **vals))
            if k == 80:
                outs.append(h.step(t, **vals))                      # the same time again
    assert outs[80]["damping"] == pytest.approx(40.0)
    assert all(o["damping"] == pytest.approx(40.0) for o in outs[80:])
    assert max(o["gripper_force"] for o in outs[80:]) == pytest.approx(2.0 - 40.0 * v)
