"""Safety of the teleoperation controllers: stale force fades, NaN never leaves, saturation, rate limit, faults."""

from __future__ import annotations

import math
import random

import pytest
from pydantic import ValidationError

from teletouch import Sample
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
from teletouch.testing import Harness, make_registry, run_yaml

PLUGIN = "teletouch.plugins.controllers.position_force"


def test_stale_force_fades_to_zero_smoothly():
    p = {"deadband": 0.0, "passivity": False, "stale_after": 0.1, "fade_time": 0.2, "fault_after_lost": None}
    f = []
    with Harness(PositionForce, p) as h:
        for k in range(800):
            t = k * 1e-3
            vals = {"leader_opening": 0.02}
            if k % 17 == 0 and t < 0.2:           # the estimator stops at 0.2 s
                vals["force"] = Sample(3.0, t)
            f.append(h.step(t, **vals)["gripper_force"])
        assert h.comp.state == "stale-force"
    assert f[180] == pytest.approx(3.0)
    last = max(k for k in range(0, 200, 17))
    k_stale = int((last / 1000 + 0.1) * 1000)
    assert f[k_stale - 1] == pytest.approx(3.0)                     # held while fresh enough
    assert f[k_stale + 100] == pytest.approx(1.5, abs=0.05)         # half-way through the fade
    assert all(v == 0.0 for v in f[k_stale + 205:])                 # zero after fade_time
    fade = f[k_stale - 1:]
    assert max(abs(b - a) for a, b in zip(fade, fade[1:])) <= 3.0 / 200 + 1e-9   # no jump


def test_nan_force_never_leaves_and_fades():
    # the core's mock sensor turns NaN at 0.5 s; the controller's outputs stay finite and the force fades out; the
    # estimate lost for longer than fault_after_lost (0.5 s) is a fault: the run stops at ~1.0 s
    text = """
name: nan-force
clock: sim
duration: 1.2
nodes:
  - {id: hand, plugin: mock-sensor, rate: 1kHz, params: {signal: constant, amplitude: 0.02}}
  - {id: est, plugin: mock-sensor, rate: 60, params: {signal: constant, amplitude: 2.0, nan_at: 0.5}}
  - id: ctl
    plugin: position-force
    rate: 1kHz
    params: {fade_time: 0.2}
    inputs: {leader_opening: hand.value, force: est.value}
  - {id: leader, plugin: mock-device, rate: 1kHz, inputs: {command: ctl.gripper_force}}
"""
    rec = []
    res, rt = run_yaml(text, make_registry(PLUGIN), taps=[lambda n, t, o: rec.append((t, dict(o))) if n == "ctl"
                                                          else None])
    assert (res.status, res.exit_code) == ("fault", 3), res.summary()
    assert "force estimate lost for 0.50" in res.message and "not finite" in res.message, res.message
    assert res.faults[0].node == "ctl" and 1.0 <= res.faults[0].time <= 1.02, res.faults
    for t, o in rec:
        for k, v in o.items():
            assert math.isfinite(v), (t, k, v)
    f = {round(t, 3): o["gripper_force"] for t, o in rec}
    assert f[0.49] == pytest.approx(1.98)
    assert f[0.8] == 0.0 and max(f) <= 1.02          # faded out by 0.8 s; the run stopped at ~1.0 s
    assert rt.component("ctl").bad_force > 0
    assert rt.latest("leader", "command_applied").value == 0.0


def test_nan_or_stale_leader_holds_follower_and_fades_force():
    p = {"deadband": 0.0, "passivity": False, "fade_time": 0.1, "leader_stale_after": 0.05}
    with Harness(PositionForce, p) as h:
        for k in range(100):
            out = h.step(k * 1e-3, leader_opening=0.015 - 1e-5 * k, force=2.0)
        cmd = out["opening_command"]
        f0 = out["gripper_force"]
        assert f0 == pytest.approx(2.0, abs=0.01)   # a sample every step: the ramps act as a low-pass
        outs = [h.step(0.1 + k * 1e-3, leader_opening=math.nan, force=2.0) for k in range(1, 200)]
    assert all(o["opening_command"] == cmd for o in outs)          # follower holds its last command
    f = [o["gripper_force"] for o in outs]
    assert f[-1] == 0.0 and all(b <= a + 1e-12 for a, b in zip(f, f[1:]))
    assert h.comp.state == "stale-leader"
    # a leader that never arrived: no follower command at all, no force
    with Harness(PositionForce) as h:
        out = h.step(0.0, force=3.0)
        out = h.step(0.001, force=3.0)
    assert "opening_command" not in out and out["gripper_force"] == 0.0


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition, NoFeedback])
def test_outputs_always_finite_and_within_limits_under_garbage(cls):
    rng = random.Random(1)
    bad = [math.nan, math.inf, -math.inf, 1e300, -1e300, "x", None]
    with Harness(cls, {"max_force": 5.0, "max_force_rate": 1e5, "smoothing_time": 0.0}
                 if cls is PositionForce else {"max_force": 5.0, "max_force_rate": 1e5}) as h:
        for k in range(3000):
            def pick(scale):
                return rng.choice(bad) if rng.random() < 0.2 else rng.uniform(-scale, scale)
            vals = {"leader_opening": pick(0.05), "leader_velocity": pick(5.0), "follower_opening": pick(0.05),
                    "force": pick(100.0)}
            vals = {k2: v for k2, v in vals.items() if v is not None}
            out = h.step(k * 1e-3, **vals)
            for name, v in out.items():
                assert isinstance(v, float) and math.isfinite(v), (k, name, v)
            assert abs(out["gripper_force"]) <= 5.0
            if "opening_command" in out:
                assert 0.0 <= out["opening_command"] <= 0.09


def test_saturation_and_rate_limit_of_the_leader_force():
    p = {"deadband": 0.0, "passivity": False, "max_force": 3.0, "max_force_rate": 100.0, "smoothing_time": 0.0}
    with Harness(PositionForce, p) as h:
        f = [h.step(k * 1e-3, leader_opening=0.02, force=Sample(50.0, k * 1e-3))["gripper_force"]
             for k in range(100)]
    assert max(f) == 3.0                                            # saturated at max_force
    assert max(b - a for a, b in zip(f, f[1:])) <= 0.1 + 1e-12      # 100 N/s * 1 ms
    assert f[30] == pytest.approx(3.0) and f[10] == pytest.approx(1.0)   # first step has dt = 0


@pytest.mark.parametrize("fail_in", ["est", "ctl-input"])
def test_devices_reach_safe_states_on_fault(fail_in):
    # a fault anywhere stops the graph; the leader ends with zero force, the follower holds its position
    est = ("{signal: constant, amplitude: 2.0, fail_at: 0.4}" if fail_in == "est"
           else "{signal: constant, amplitude: 2.0}")
    hand = "{signal: ramp, amplitude: -0.01, offset: 0.02}" if fail_in == "est" else \
        "{signal: ramp, amplitude: -0.01, offset: 0.02, fail_at: 0.4}"
    text = f"""
name: fault
clock: sim
duration: 1.0
nodes:
  - {{id: hand, plugin: mock-sensor, rate: 1kHz, params: {hand}}}
  - {{id: est, plugin: mock-sensor, rate: 60, params: {est}}}
  - id: ctl
    plugin: position-force
    rate: 1kHz
    inputs: {{leader_opening: hand.value, force: est.value}}
  - {{id: leader, plugin: mock-device, rate: 1kHz, params: {{safe_value: 0.0}}, inputs: {{command: ctl.gripper_force}}}}
  - {{id: follower, plugin: mock-device, rate: 1kHz, params: {{tau: 0.01}}, inputs: {{command: ctl.opening_command}}}}
"""
    res, rt = run_yaml(text, make_registry(PLUGIN))
    assert res.status == "fault" and res.exit_code == 3
    leader, follower = rt.component("leader"), rt.component("follower")
    assert leader.safe_calls >= 1 and leader.command == 0.0
    assert follower.safe_calls >= 1 and follower.command == pytest.approx(follower.state)
    assert leader.lifecycle[-2:] == ["deactivate", "close"]


@pytest.mark.parametrize("stamp", [3600.0, math.nan], ids=["future", "nan"])
def test_badly_stamped_force_or_leader_is_stale_not_fresh_forever(stamp):
    # a last sample stamped an hour ahead, or NaN, must not be rendered forever: it counts as stale
    p = {"deadband": 0.0, "passivity": False, "stale_after": 0.1, "fade_time": 0.2, "fault_after_lost": None}
    with Harness(PositionForce, p) as h:
        for k in range(100):
            h.step(k * 1e-3, leader_opening=0.02, force=Sample(3.0, k * 1e-3))
        h.step(0.1, leader_opening=0.02, force=Sample(3.0, stamp))
        f = [h.step(0.1 + k * 1e-3, leader_opening=0.02)["gripper_force"] for k in range(1, 1000)]
        assert h.comp.state == "stale-force" and f[-1] == 0.0
        assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 3.0 / 200 + 1e-9     # faded, no jump
    with Harness(PositionForce, p) as h:
        for k in range(100):
            h.step(k * 1e-3, leader_opening=0.02, force=Sample(3.0, k * 1e-3))
        h.step(0.1, leader_opening=Sample(0.02, stamp), force=Sample(3.0, 0.1))
        out = [h.step(0.1 + k * 1e-3, force=Sample(3.0, 0.1 + k * 1e-3)) for k in range(1, 1000)]
        assert not h.comp.leader_ok and h.comp.state == "stale-leader" and out[-1]["gripper_force"] == 0.0


def test_force_rate_limit_holds_after_a_late_step():
    # one late step (the thread stalled 60 ms) moves the force by at most two periods' worth of the rate limit
    p = {"deadband": 0.0, "passivity": False, "max_force_rate": 200.0, "smoothing_time": 0.0,
         "force_prediction": False}
    with Harness(PositionForce, p) as h:
        assert h.comp.ctx.rate == 1000.0
        h.step(0.0, leader_opening=0.02, force=Sample(0.0, 0.0))
        f0 = h.step(0.001, leader_opening=0.02)["gripper_force"]
        f1 = h.step(0.061, leader_opening=0.02, force=Sample(6.0, 0.061))["gripper_force"]
        assert f1 - f0 == pytest.approx(200.0 * 0.002)


@pytest.mark.parametrize("override", [{"max_force": math.inf}, {"max_force_rate": math.inf},
                                      {"max_damping": math.inf}, {"stale_after": math.inf},
                                      {"fade_time": math.inf}, {"leader_stale_after": math.inf},
                                      {"offset": math.nan}, {"scale": math.inf}, {"reduction_min_velocity": 0.0},
                                      {"max_leader_velocity": 0.0}, {"max_leader_velocity": math.inf}],
                         ids=lambda d: next(iter(d)))
def test_params_that_would_switch_a_limit_off_are_refused(override):
    text = f"""
clock: sim
nodes:
  - {{id: hand, plugin: mock-sensor, rate: 1kHz, params: {{signal: constant, amplitude: 0.02}}}}
  - {{id: est, plugin: mock-sensor, rate: 60}}
  - id: ctl
    plugin: position-force
    rate: 1kHz
    params: {{{next(iter(override))}: {next(iter(override.values()))!r}}}
    inputs: {{leader_opening: hand.value, force: est.value}}
"""
    text = text.replace("inf", ".inf").replace("nan", ".nan")
    from teletouch.errors import GraphValidationError

    with pytest.raises(GraphValidationError) as e:
        run_yaml(text, make_registry(PLUGIN), duration=0.01)
    name = next(iter(override))
    assert "'ctl'" in str(e.value) and name in str(e.value)
    assert ("finite" in str(e.value)) or ("greater than" in str(e.value))


@pytest.mark.parametrize("name", ["stale_after", "leader_stale_after"])
def test_staleness_limits_cannot_keep_a_lost_force_for_long(name):
    """stale_after: 1e308 kept a dead sensor's last 5 N on the hand for good (4.98 N after 60 s, no fade, no fault),
    and `stale_after: 100` (meant as ms) was 100 s: at most 1 s now, as the leaders' command_timeout."""
    from teletouch.errors import GraphValidationError

    text = f"""
clock: sim
nodes:
  - {{id: hand, plugin: mock-sensor, rate: 1kHz, params: {{signal: constant, amplitude: 0.02}}}}
  - {{id: est, plugin: mock-sensor, rate: 60}}
  - {{id: ctl, plugin: position-force, rate: 1kHz, params: {{{name}: VALUE}},
     inputs: {{leader_opening: hand.value, force: est.value}}}}
"""
    for bad, shown in (("100", "100"), ("1.5", "1.5"), ("1e308", r"1e\+308")):
        with pytest.raises(GraphValidationError, match=rf"node 'ctl': param '{name}' = {shown}: Input should be less "
                                                       rf"than or equal to 1 s"):
            run_yaml(text.replace("VALUE", bad), make_registry(PLUGIN), duration=0.01)
    res, _ = run_yaml(text.replace("VALUE", "1.0"), make_registry(PLUGIN), duration=0.01)
    assert res.status == "ok"


@pytest.mark.parametrize("leader", ["sim-omega7", "omega7"])
def test_leader_command_timeout_cannot_be_switched_off(leader):
    from teletouch.plugins.devices.omega7 import Omega7
    from teletouch.plugins.devices.sim_omega7 import SimOmega7

    cls = {"omega7": Omega7, "sim-omega7": SimOmega7}[leader]
    for bad in (None, math.inf, 5.0):
        with pytest.raises(ValidationError, match="command_timeout"):
            cls.Params.model_validate({"command_timeout": bad})
    assert cls.Params.model_validate({"command_timeout": "50ms"}).command_timeout == pytest.approx(0.05)


def test_passivity_never_divides_by_an_underflowing_velocity():
    from teletouch.plugins.controllers.passivity import damping_for, reduce_force_to

    # |v| * dt underflows to 0: the whole force is cut (never past zero), no ZeroDivisionError
    assert reduce_force_to(2.0, -1e-3, 1e-320, 1e-3) == 0.0
    assert reduce_force_to(-2.0, -1e-3, -1e-320, 1e-3) == 0.0
    assert damping_for(-1e-3, 1e-3, 1e-320, 40.0) == 40.0
    # a subnormal leader velocity through the whole controller, with the deficit the auditor's run built up
    p = {"deadband": 0.0, "reduction_min_velocity": 1e-3}
    with Harness(PositionForce, p) as h:
        for k in range(3000):
            t = k * 1e-3
            out = h.step(t, leader_opening=0.02 - 2e-3 * min(t, 0.3), leader_velocity=-1e-309 if t > 0.3 else -2e-3,
                         force=Sample(2.0, t))
            assert all(math.isfinite(v) for v in out.values()), (t, out)


def test_differentiator_skips_bad_samples():
    from teletouch.plugins.controllers.position_force import Differentiator

    d = Differentiator(50.0)
    for k in range(50):
        d.update(k * 1e-3, 0.01 * k * 1e-3)
    v = d.update(math.inf, 0.5)
    assert v == pytest.approx(d.v) and math.isfinite(v)
    assert math.isfinite(d.update(0.050, math.nan)) and math.isfinite(d.update(0.051, 0.01 * 0.051))
    assert d.v == pytest.approx(0.01, rel=0.1)


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition])
def test_the_fade_of_a_lost_leader_obeys_the_rate_limit(cls):
    # a fade_time shorter than max_force / max_force_rate must not drop the force faster than the rate limit (it
    # dropped 4 N in one step: the fade replaced the rate limit instead of acting within it)
    p = {"passivity": False, "fade_time": 0.001, "max_force_rate": 200.0}
    p.update({"kp": 400.0, "kd": 0.0} if cls is PositionPosition else {"deadband": 0.0})
    with Harness(cls, p) as h:
        for k in range(100):
            out = h.step(k * 1e-3, leader_opening=0.010, follower_opening=0.020, force=Sample(4.0, k * 1e-3))
        f = [out["gripper_force"]]
        assert f[0] == pytest.approx(4.0, abs=0.02)
        f += [h.step(0.099 + k * 1e-3, leader_opening=math.nan, follower_opening=0.020,
                     force=Sample(4.0, 0.099 + k * 1e-3))["gripper_force"] for k in range(1, 100)]
    assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 200.0 * 1e-3 + 1e-9
    assert f[-1] == 0.0


def test_an_older_force_estimate_after_a_newer_one_is_ignored():
    # estimates out of order (an older capture delivered after a newer one): the hand must not be given the older
    # force again (it went back from 3 N to 1 N), nor the two-port observer an interval run backwards
    p = {"deadband": 0.0, "passivity": False, "force_prediction": False, "energy_leak_time": None}

    def run(out_of_order):
        with Harness(PositionForce, p) as h:
            f, e = [], []
            for k in range(300):
                t = k * 1e-3
                x = 0.015 - 0.005 * t
                vals = {"leader_opening": x, "follower_opening": x}
                if k % 17 == 0:
                    vals["force"] = Sample(10.0 * t, t)
                elif out_of_order and k % 17 == 8 and k > 100:
                    vals["force"] = Sample(10.0 * (t - 0.05), t - 0.05)       # an old capture, late
                out = h.step(t, **vals)
                f.append(out["gripper_force"])
                e.append(out["energy"])
            return f, e

    f0, e0 = run(False)
    f1, e1 = run(True)
    assert f1 == pytest.approx(f0, abs=1e-12)
    assert e1 == pytest.approx(e0, abs=1e-12)


def test_the_estimate_state_comes_back_with_the_leader():
    # the leader lost for 60 ms and back, the 60 Hz estimate fresh all along: the state stayed stale-leader (and the
    # contact prediction, which needs the state ok, off) until the next estimate arrived, up to a frame later
    with Harness(PositionForce, {"deadband": 0.0}) as h:
        for k in range(400):
            t = k * 1e-3
            vals = {"leader_opening": math.nan if 100 <= k < 160 else 0.02}
            if k % 17 == 0:
                vals["force"] = Sample(2.0, t)
            h.step(t, **vals)
            if k == 120:
                assert h.comp.state == "stale-leader"
            if k == 160:                                       # back; the next estimate comes at 170
                assert h.comp.leader_ok and h.comp.state == "ok"
        for k in range(400, 600):                              # a stale estimate while the leader is lost: stale-force
            t = k * 1e-3
            h.step(t, leader_opening=math.nan if k < 450 else 0.02)
        assert h.comp.state == "stale-force" and h.comp.force_lost()
