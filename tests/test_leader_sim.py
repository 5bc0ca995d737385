"""sim-omega7 and the simulated operator: physics, safety, intents."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from teletouch import ComponentFault
from teletouch.plugins.devices import operator as op
from teletouch.plugins.devices.sim_omega7 import SimOmega7
from teletouch.testing import Harness, make_registry, run_yaml


def settle(h: Harness, seconds: float = 3.0, dt: float = 1e-3, **inputs):
    out = None
    t0 = h.t
    for i in range(1, int(round(seconds / dt)) + 1):
        out = h.step(t0 + i * dt, **inputs)
    return out


@pytest.mark.parametrize("k,force", [(300.0, 1.0), (300.0, 2.5), (300.0, -1.5), (800.0, 4.0), (150.0, 0.5)])
def test_rendered_force_pushes_the_hand_back_to_intent_plus_f_over_k(k, force):
    params = {"intent": {"type": "hold", "opening": "10mm"}, "hand_stiffness": k}
    with Harness(SimOmega7, params) as h:
        h.step(0.0)
        out = settle(h, 3.0, gripper_force=force)
        expected = 0.010 + force / k
        band = h.comp.params.gripper_coulomb / k  # static friction holds anywhere in this band
        assert out["gripper_opening"] == pytest.approx(expected, abs=band + 2e-5)
        assert abs(out["gripper_velocity"]) < 1e-4
        # the hand pushes against the rendered force with (about) the same magnitude
        assert out["hand_force"] == pytest.approx(-force, abs=h.comp.params.gripper_coulomb + 1e-3)


def test_no_force_means_the_hand_sits_at_its_intent():
    with Harness(SimOmega7, {"intent": {"type": "hold", "opening": 0.012}, "initial_opening": 0.02}) as h:
        out = settle(h, 2.0)
        assert out["gripper_opening"] == pytest.approx(0.012, abs=0.05 / 300 + 2e-5)


def test_gripper_force_is_clamped_to_the_configured_limit():
    params = {"intent": {"type": "hold", "opening": 0.005}, "hand_stiffness": 1000.0, "max_gripper_force": 3.0}
    with Harness(SimOmega7, params) as h:
        out = settle(h, 3.0, gripper_force=100.0)
        assert h.comp.g_applied == 3.0
        assert out["gripper_opening"] == pytest.approx(0.005 + 3.0 / 1000.0, abs=0.05 / 1000 + 2e-5)
        assert h.comp.status()["clamped"] > 0
        settle(h, 0.1, gripper_force=-100.0)
        assert h.comp.g_applied == -3.0


def test_limits_above_the_device_are_refused():
    with pytest.raises(ValidationError, match="max_gripper_force"):
        SimOmega7.Params(max_gripper_force=9.0)
    with pytest.raises(ValidationError, match="max_force"):
        SimOmega7.Params(max_force="13 N")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_gripper_force_gives_zero_force_and_a_fault(bad):
    with Harness(SimOmega7, {"intent": "hold"}) as h:
        settle(h, 0.1, gripper_force=2.0)
        assert h.comp.g_applied == 2.0
        with pytest.raises(ComponentFault, match="not finite"):
            h.step(h.t + 1e-3, gripper_force=bad)
        assert h.comp.g_applied == 0.0 and h.comp.safe
        # latched safe until re-activated: a good command afterwards is not applied
        h.step(h.t + 1e-3, gripper_force=1.0)
        assert h.comp.g_applied == 0.0


def test_non_finite_translational_force_faults_and_zeroes_everything():
    with Harness(SimOmega7, {"intent": "none"}) as h:
        settle(h, 0.05, force=np.array([1.0, 0.0, 0.0]), gripper_force=1.0)
        assert h.comp.g_applied == 1.0
        with pytest.raises(ComponentFault, match="not finite"):
            h.step(h.t + 1e-3, force=np.array([0.0, math.nan, 0.0]))
        assert h.comp.g_applied == 0.0 and not h.comp.f_applied.any()


def test_translational_force_is_clamped_by_norm():
    with Harness(SimOmega7, {"intent": "none", "max_force": 5.0}) as h:
        h.step(1e-3, force=np.array([30.0, 40.0, 0.0]))
        np.testing.assert_allclose(h.comp.f_applied, [3.0, 4.0, 0.0])


def test_stale_command_gives_zero_force_without_fault():
    from teletouch import Sample

    with Harness(SimOmega7, {"intent": "hold", "command_timeout": "50ms"}) as h:
        h.step(0.0, gripper_force=Sample(2.0, 0.0))
        h.step(0.01)
        assert h.comp.g_applied == 2.0
        h.step(0.2)
        assert h.comp.g_applied == 0.0
        assert h.comp.status()["stale_commands"] >= 1


def test_force_only_while_active_and_safe_state_zeroes():
    h = Harness(SimOmega7, {"intent": "hold"})
    h.comp.configure()
    # not active yet: the command is ignored
    h.step(0.0, gripper_force=2.0)
    assert h.comp.g_applied == 0.0
    h.comp.activate()
    h.step(0.001, gripper_force=2.0)
    assert h.comp.g_applied == 2.0
    h.comp.safe_state()
    assert h.comp.g_applied == 0.0
    h.comp.deactivate()
    h.comp.close()
    h.comp.safe_state()  # again, after close: must not raise


def test_close_and_hold_follows_the_script_and_holds_the_target():
    intent = {"type": "close-and-hold", "start_opening": "20mm", "target_opening": "5mm", "speed": "10mm/s",
              "start_time": 0.2, "hold_time": 1.0, "release": True}
    with Harness(SimOmega7, {"intent": intent}) as h:
        trace = [(0.0, h.step(0.0))]
        for i in range(1, 4601):
            trace.append((i * 1e-3, h.step(i * 1e-3)))
    at = dict((round(t, 3), o) for t, o in trace)
    assert at[0.1]["gripper_opening"] == pytest.approx(0.020, abs=2e-4)
    assert at[0.95]["gripper_velocity"] == pytest.approx(-0.010, rel=0.1)  # closing at the scripted speed
    assert at[1.8]["gripper_opening"] == pytest.approx(0.005, abs=3e-4)  # 0.2 s + 1.5 s of closing, then hold
    assert at[2.6]["gripper_opening"] == pytest.approx(0.005, abs=3e-4)
    assert at[4.6]["gripper_opening"] == pytest.approx(0.020, abs=3e-4)  # released back open by 4.2 s
    # the phase helper says where the script is
    ci = op.make_intent(intent)
    assert [ci.phase(t) for t in (0.1, 1.0, 2.0, 3.0, 4.5)] == ["wait", "closing", "hold", "release", "done"]


def test_closing_onto_an_object_stops_at_the_object_and_squeezes_with_k_times_overlap():
    """A rigid object 10 mm wide, rendered as a stiff wall by a test-side controller: the hand, intending 5 mm,
    squeezes with about K_hand * 5 mm, which is what a force-feedback controller must render."""
    k_hand = 300.0
    intent = {"type": "close-and-hold", "start_opening": 0.02, "target_opening": 0.005, "speed": 0.01,
              "start_time": 0.0, "hold_time": 5.0}
    with Harness(SimOmega7, {"intent": intent, "hand_stiffness": k_hand, "max_gripper_force": 8.0}) as h:
        out = h.step(0.0)
        for i in range(1, 4001):
            x = out["gripper_opening"]
            v = out["gripper_velocity"]
            wall = max(0.0, 3000.0 * (0.010 - x) - 20.0 * v * (x < 0.010))
            out = h.step(i * 1e-3, gripper_force=wall)
        applied = h.comp.g_applied
    k_wall = 3000.0
    x_eq = (k_wall * 0.010 + k_hand * 0.005) / (k_wall + k_hand)  # two springs in series meet here
    assert out["gripper_opening"] == pytest.approx(x_eq, abs=0.05 / k_hand + 2e-5)
    assert applied == pytest.approx(k_wall * (0.010 - x_eq), abs=0.06)
    assert applied == pytest.approx(k_hand * 0.005, rel=0.15)  # ~ K_hand * (object - intent) for a stiff object


def test_hand_off_the_device_means_only_rendered_force_moves_it():
    with Harness(SimOmega7, {"intent": "none", "initial_opening": 0.01}) as h:
        out = settle(h, 0.5)
        assert out["gripper_opening"] == pytest.approx(0.01)  # nothing pushes it
        assert math.isnan(out["intended_opening"]) and out["hand_force"] == 0.0
        out = settle(h, 1.0, gripper_force=0.5)
        assert out["gripper_opening"] == pytest.approx(h.comp.params.max_opening)  # end stop
        out = settle(h, 1.0, gripper_force=-0.5)
        assert out["gripper_opening"] == 0.0


def test_handle_is_pushed_by_an_external_spring_like_a_press_rig():
    """The calibration routine commands force down, a rig (spring) pushes back through external_force."""
    k_rig = 2000.0
    with Harness(SimOmega7, {"intent": "none"}) as h:
        out = h.step(0.0)
        cmd = np.array([0.0, 0.0, -4.0])
        for i in range(1, 3001):
            z = out["position"][2]
            ext = np.array([0.0, 0.0, -k_rig * min(z, 0.0)])  # the surface is at z = 0, pushes up when pressed
            out = h.step(i * 1e-3, force=cmd, external_force=ext)
        assert out["position"][2] == pytest.approx(-4.0 / k_rig, rel=0.02)
        assert abs(out["position"][0]) < 1e-12


def test_handle_stays_in_the_workspace():
    with Harness(SimOmega7, {"intent": "none", "max_force": 12.0}) as h:
        out = settle(h, 1.0, force=np.array([12.0, 0.0, 0.0]))
        assert np.linalg.norm(out["position"]) == pytest.approx(0.075)


def test_arm_impedance_holds_the_handle_when_the_operator_holds_it():
    with Harness(SimOmega7, {"intent": "hold", "arm_stiffness": 400.0}) as h:
        out = settle(h, 3.0, force=np.array([0.0, 2.0, 0.0]))
        assert out["position"][1] == pytest.approx(2.0 / 400.0, rel=0.02)


def test_button_intervals():
    with Harness(SimOmega7, {"intent": "none", "button_intervals": [[0.1, 0.2]]}) as h:
        assert h.step(0.05)["button"] is False
        assert h.step(0.15)["button"] is True
        assert h.step(0.25)["button"] is False


def test_trajectory_intent_interpolates_and_validates():
    ti = op.make_intent({"type": "trajectory", "waypoints": [[0, "20mm"], [1, "10mm"], ["2s", 0.01]]})
    st = op.OperatorState()
    assert ti.desired(0.5, st) == pytest.approx((0.015, -0.01))
    assert ti.desired(1.5, st) == pytest.approx((0.010, 0.0))
    assert ti.desired(9.0, st) == pytest.approx((0.010, 0.0))
    with pytest.raises(ValueError, match="times must increase"):
        op.validate_intent({"type": "trajectory", "waypoints": [[1, 0.01], [0.5, 0.02]]})
    with pytest.raises(ValidationError, match="intent 'hold' has no field 'openning'"):
        SimOmega7.Params(intent={"type": "hold", "openning": 0.01})
    with pytest.raises(ValidationError, match="unknown intent type 'wave'"):
        SimOmega7.Params(intent="wave")


class SqueezeWhenButton:
    """A test intent defined outside the plugin: closes to 4 mm once the perceived force exceeds 1 N."""

    name = "test-squeeze"

    class Params(op.IntentParams):
        threshold: float = 1.0

    def __init__(self, params):
        self.params = params
        self.triggered = False

    def desired(self, t, state):
        if state.gripper_force > self.params.threshold:
            self.triggered = True
        return (0.004 if self.triggered else 0.015), 0.0


def test_intents_can_be_added_from_other_modules():
    op.register_intent(SqueezeWhenButton)
    assert "test-squeeze" in op.intent_names()
    with pytest.raises(ValueError, match="already taken"):
        op.register_intent(type("Other", (), {"name": "test-squeeze", "desired": lambda s, t, st: None}))
    for spec in ({"type": "test-squeeze", "threshold": 0.5}, {"type": f"{__name__}:SqueezeWhenButton"}):
        with Harness(SimOmega7, {"intent": spec}) as h:
            out = settle(h, 1.0)
            assert out["gripper_opening"] == pytest.approx(0.015, abs=3e-4)
            out = settle(h, 0.01, gripper_force=2.0)
            out = settle(h, 2.0, gripper_force=0.0)
            assert out["gripper_opening"] == pytest.approx(0.004, abs=3e-4)
    with pytest.raises(ValueError, match="cannot import module"):
        op.validate_intent({"type": "no_such_module_xyz:Intent"})


def test_intent_opening_input_overrides_the_script():
    with Harness(SimOmega7, {"intent": {"type": "hold", "opening": 0.02}}) as h:
        out = settle(h, 1.0, intent_opening=0.008)
        assert out["gripper_opening"] == pytest.approx(0.008, abs=3e-4)
        assert out["intended_opening"] == 0.008


GRAPH = """
name: sim-leader
clock: sim
duration: 2
nodes:
  - id: force
    plugin: mock-sensor
    rate: 1000
    params: {signal: constant, amplitude: 1.5, nan_at: NAN_AT}
  - id: leader
    plugin: sim-omega7
    rate: 1kHz
    params:
      intent: {type: hold, opening: 12mm}
      hand_stiffness: 500 N/m
    inputs: {gripper_force: force.value}
"""


def test_sim_leader_in_a_graph_and_nan_from_upstream_stops_it_safely():
    reg = make_registry("teletouch.plugins.devices.sim_omega7")
    text = GRAPH.replace("NAN_AT", "null")
    # mock-sensor's port has unit "any", so it wires into gripper_force (N)
    result, rt = run_yaml(text, reg)
    assert result.status == "ok", result.summary()
    leader = rt.component("leader")
    assert leader.x == pytest.approx(0.012 + 1.5 / 500, abs=0.05 / 500 + 2e-5)
    result, rt = run_yaml(GRAPH.replace("NAN_AT", "1.0"), reg)
    assert result.status == "fault"
    assert any(f.node == "leader" and "not finite" in f.message for f in result.faults)
    assert rt.component("leader").g_applied == 0.0 and rt.component("leader").safe


class CloseWhenTilted:
    """A reactive intent (like a pivoting operator): close to 3 mm while the perceived angle exceeds 0.3 rad."""

    name = "test-close-when-tilted"

    def desired(self, t, state):
        return (0.003 if state.extra.get("cue", 0.0) > 0.3 else 0.018), 0.0


def test_intent_cue_input_reaches_the_intent():
    with Harness(SimOmega7, {"intent": {"type": f"{__name__}:CloseWhenTilted"}}) as h:
        out = settle(h, 1.0, intent_cue=0.1)
        assert out["gripper_opening"] == pytest.approx(0.018, abs=3e-4)
        out = settle(h, 1.0, intent_cue=0.5)
        assert out["gripper_opening"] == pytest.approx(0.003, abs=3e-4)
        assert h.comp.state.extra["cue"] == 0.5


@pytest.mark.parametrize("port,value", [("external_force", np.array([0.0, math.nan, 0.0])),
                                        ("intent_opening", math.inf)])
def test_non_finite_environment_inputs_fault_too(port, value):
    with Harness(SimOmega7, {"intent": "hold"}) as h:
        settle(h, 0.05, gripper_force=1.0)
        with pytest.raises(ComponentFault, match="not finite"):
            h.step(h.t + 1e-3, **{port: value})
        assert h.comp.g_applied == 0.0 and h.comp.safe


def test_bad_intent_in_a_graph_names_the_file_line_and_field():
    from teletouch.errors import GraphValidationError
    from teletouch.testing import load_text

    reg = make_registry("teletouch.plugins.devices.sim_omega7")
    text = GRAPH.replace("intent: {type: hold, opening: 12mm}", "intent: {type: close-and-hold, speed: -1}")
    with pytest.raises(GraphValidationError) as ei:
        load_text(text.replace("NAN_AT", "null"), reg)
    msg = str(ei.value)
    assert "<test>:" in msg and "intent.speed" in msg and "greater than 0" in msg


# ------------------------------------------------------------------------------------------------ audit
@pytest.mark.parametrize("params", [
    {"hand_stiffness": 1e7}, {"hand_stiffness": 1e8},                  # a stiff pinch
    {"hand_damping": 300.0}, {"hand_damping": 1e4},                    # a heavily damped one
    {"gripper_mass": 1e-5, "hand_mass": 0.0},                          # a very light gripper
], ids=lambda p: ",".join(f"{k}={v:g}" for k, v in p.items()))
def test_stiff_damped_or_light_parameters_stay_stable(params):
    """The explicit substep went unstable past h*c/m or h^2*k/m of ~1: the hand force chattered at +-40 N and the
    gripper ran at 0.2-70 m/s where the hand held still. Now the stiff terms are implicit: it settles."""
    p = {"intent": {"type": "hold", "opening": 0.010}, "initial_opening": 0.020, **params}
    with Harness(SimOmega7, p) as h:
        outs = [h.step(i * 1e-3) for i in range(2001)]
    assert all(math.isfinite(o["gripper_opening"]) for o in outs)
    for o in outs[-500:]:                                              # the last 0.5 s: no chatter, no running off
        assert 0.010 - 0.05 / 300 - 2e-5 <= o["gripper_opening"] <= 0.020
        assert abs(o["gripper_velocity"]) < 5e-3 and abs(o["hand_force"]) < 1.0
    if "hand_damping" in params:                                       # overdamped: straight to the intent
        xs = [o["gripper_opening"] for o in outs]
        assert all(a >= b - 1e-12 for a, b in zip(xs, xs[1:]))


def test_a_light_gripper_without_a_hand_is_pushed_open_by_a_rendered_force():
    with Harness(SimOmega7, {"intent": "none", "gripper_mass": 1e-5, "initial_opening": 0.01}) as h:
        out = settle(h, 1.0, gripper_force=0.5)
        assert out["gripper_opening"] == pytest.approx(h.comp.params.max_opening)  # was 0: the wrong end stop


@pytest.mark.parametrize("params,expected", [
    ({"intent": "none", "handle_damping": 1e4}, 1.0 * 2.0 / 1e4),           # drifts at F / b for 2 s
    ({"intent": "hold", "arm_stiffness": 1e8}, 1.0 / 1e8),                  # held by the arm's spring
    ({"intent": "hold", "arm_damping": 1e4, "arm_stiffness": 300.0}, None),  # slowly towards F / k
])
def test_stiff_or_heavily_damped_handle_stays_stable(params, expected):
    with Harness(SimOmega7, params) as h:
        out = h.step(0.0, force=np.array([1.0, 0.0, 0.0]))
        for i in range(1, 2001):
            out = h.step(i * 1e-3, force=np.array([1.0, 0.0, 0.0]))
            assert np.linalg.norm(out["position"]) < 0.01             # it went to the workspace's edge (75 mm)
    x = out["position"][0]
    if expected is not None:
        assert x == pytest.approx(expected, rel=0.02)
    else:
        assert 0.0 < x < 1.0 / 300.0


class NanAfter:
    """An intent that goes wrong after 0.1 s (a reactive intent fed a NaN cue, say)."""

    name = "test-nan-after"

    def desired(self, t, state):
        return (math.nan if t > 0.1 else 0.012), 0.0


class NotAPair:
    name = "test-not-a-pair"

    def desired(self, t, state):
        return 0.012


def test_an_intent_that_returns_nan_faults_instead_of_poisoning_the_state():
    with Harness(SimOmega7, {"intent": {"type": f"{__name__}:NanAfter"}}) as h:
        settle(h, 0.1, gripper_force=1.0)
        x = h.comp.x
        with pytest.raises(ComponentFault, match="test_leader_sim:NanAfter' returned opening nan"):
            h.step(h.t + 1e-3, gripper_force=1.0)
        assert h.comp.x == x and math.isfinite(h.comp.v)                # the opening was NaN for good before
        assert h.comp.g_applied == 0.0 and h.comp.safe
    with Harness(SimOmega7, {"intent": {"type": f"{__name__}:NotAPair"}, "initial_opening": 0.01}) as h:
        with pytest.raises(ComponentFault, match=r"returned 0.012: expected \(opening m, velocity m/s\) or None"):
            h.step(0.001)                                                # was a TypeError from the integrator
    with pytest.raises(ComponentFault, match="returned 0.012"):      # the start opening comes from the intent too
        Harness(SimOmega7, {"intent": {"type": f"{__name__}:NotAPair"}}).comp.configure()


def test_huge_intent_openings_do_not_make_the_state_nan():
    from teletouch import Sample

    with Harness(SimOmega7, {"intent": "hold"}) as h:
        h.step(0.0, intent_opening=Sample(1.7e308, 0.0))
        h.step(0.001, intent_opening=Sample(1e308, 0.001))              # velocity -inf, spring force +inf: NaN
        out = settle(h, 1.0, intent_opening=0.01)
        assert math.isfinite(out["gripper_opening"]) and math.isfinite(out["hand_force"])
        assert out["gripper_opening"] == pytest.approx(0.01, abs=3e-4)
        with pytest.raises(ComponentFault, match="intent_opening is 'wide' \\(not a number\\)"):
            h.step(h.t + 1e-3, intent_opening="wide")                    # was a bare ValueError, no safe state
        assert h.comp.safe and h.comp.g_applied == 0.0


@pytest.mark.parametrize("intent,field", [({"type": "hold", "opening": math.inf}, "intent.opening"),
                                          ({"type": "close-and-hold", "speed": math.inf}, "intent.speed"),
                                          ({"type": "close-and-hold", "hold_time": math.inf}, "intent.hold_time")])
def test_intent_parameters_must_be_finite(intent, field):
    with pytest.raises(ValidationError, match=f"{field}: Input should be a finite number"):
        SimOmega7.Params(intent=intent)


def test_start_outside_the_device_is_refused():
    with pytest.raises(ValidationError, match=r"initial_opening \(50 mm\) is beyond max_opening \(25 mm"):
        SimOmega7.Params(initial_opening="50mm")
    SimOmega7.Params(initial_opening="25mm")
    with pytest.raises(ValidationError, match="initial_position .* outside workspace_radius"):
        SimOmega7.Params(initial_position=(0.1, 0.0, 0.0))


def test_lifecycle_like_the_real_driver():
    """Zero force while inactive and after safe_state() (latched); deactivate/activate renders commands again."""
    h = Harness(SimOmega7, {"intent": {"type": "hold", "opening": 0.01}})
    c = h.comp
    c.configure()
    c.activate()
    settle(h, 0.05, gripper_force=2.0)
    assert c.g_applied == 2.0
    c.deactivate()
    assert c.g_applied == 0.0
    h.step(h.t + 1e-3, gripper_force=2.0)
    assert c.g_applied == 0.0
    c.activate()
    h.step(h.t + 1e-3, gripper_force=2.0)
    assert c.g_applied == 2.0
    c.safe_state()
    settle(h, 0.01, gripper_force=2.0)
    assert c.g_applied == 0.0
    c.deactivate()
    c.activate()
    out = settle(h, 0.5, gripper_force=2.0)
    assert c.g_applied == 2.0 and math.isfinite(out["gripper_opening"])
