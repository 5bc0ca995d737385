"""sim-gripper: servo limits, contact with rigid and compliant objects through the gel law, safe state, determinism."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from teletouch import Sample
from teletouch.testing import Harness, make_registry, run_yaml

from teletouch.plugins.devices import follower_contact as fc
from teletouch.plugins.devices.sim_gripper import SimGripper

MOD = "teletouch.plugins.devices.sim_gripper"


def run_to(h, cmd, t0, seconds, dt=1e-3, **extra):
    out = {}
    n = int(round(seconds / dt))
    for k in range(1, n + 1):
        out = h.step(t0 + k * dt, opening_command=cmd, **extra)
    return out, t0 + n * dt


def test_shape_setpoint():
    from teletouch.plugins.devices.follower_common import shape_setpoint

    assert shape_setpoint(0.05, 0.0, 0.0, 0.09, 0.1, 0.0) == 0.05  # no time, no motion
    assert shape_setpoint(0.05, 0.0, 0.0, 0.09, 0.1, 0.01) == pytest.approx(0.049)
    assert shape_setpoint(0.05, 0.5, 0.0, 0.09, 10.0, 1.0) == 0.09  # clamped to the range
    assert shape_setpoint(math.nan, 0.5, 0.0, 0.09, 0.1, 0.01) == 0.09


def test_free_motion_obeys_speed_limit_and_range():
    with Harness(SimGripper, {"object_width": None, "max_speed": 0.05, "max_opening": 0.09}) as h:
        o = h.step(0.0, opening_command=0.0)
        assert o["opening"] == pytest.approx(0.09)
        assert h.comp._setpoint == 0.09  # the first step does not jump the setpoint
        prev = 0.09
        for k in range(1, 400):
            o = h.step(k * 1e-3, opening_command=0.0)
            assert prev - o["opening"] <= 0.05 * 1e-3 + 1e-12
            assert o["velocity"] >= -0.05 - 1e-9
            prev = o["opening"]
        assert o["velocity"] == pytest.approx(-0.05, rel=1e-6)
        o, t = run_to(h, 0.0, 0.4, 2.5)
        assert o["opening"] == pytest.approx(0.0, abs=1e-6)  # min_opening
        assert o["contact"] is False and o["contact_force"] == 0.0 and o["effort"] == 0.0
        o, t = run_to(h, 0.5, t, 3.0)  # beyond max_opening: clamped
        assert o["opening"] == pytest.approx(0.09, abs=1e-6)


def test_rigid_object_gel_takes_all_penetration():
    p = {"object_width": 0.04, "object_stiffness": None, "max_effort": 10.0, "servo_stiffness": 4000.0}
    with Harness(SimGripper, p) as h:
        o, t = run_to(h, 0.036, 0.0, 2.0)
        gel = h.comp.gel
        pen = 0.04 - o["opening"]
        assert o["contact"] is True
        assert pen > 0
        assert o["indentation"] == pytest.approx(pen, rel=1e-9)  # one gel finger, rigid object
        assert o["contact_force"] == pytest.approx(gel(o["indentation"]), rel=1e-9)
        # the servo's force at equilibrium balances the contact force
        servo = min(10.0, 4000.0 * (o["opening"] - 0.036))
        assert o["contact_force"] == pytest.approx(servo, rel=1e-6)
        assert o["effort"] == o["contact_force"]
        assert abs(o["velocity"]) < 1e-9
        # squeezing harder saturates at the effort limit
        o, t = run_to(h, 0.0, t, 2.0)
        assert o["contact_force"] == pytest.approx(10.0, rel=1e-6)
        assert o["opening"] > 0.0  # the object stops the fingers
        # opening again releases the object completely
        o, t = run_to(h, 0.06, t, 2.0)
        assert o["contact"] is False and o["indentation"] == 0.0 and o["contact_force"] == 0.0


def test_compliant_object_in_series_with_gel():
    k = 2000.0
    with Harness(SimGripper, {"object_width": 0.04, "object_stiffness": k, "gel_fingers": 2}) as h:
        o, t = run_to(h, 0.03, 0.0, 2.0)
        d, f = o["indentation"], o["contact_force"]
        assert f == pytest.approx(h.comp.gel(d), rel=1e-9)
        assert 0.04 - o["opening"] == pytest.approx(2 * d + f / k, rel=1e-7)
    with Harness(SimGripper, {"object_width": 0.04, "object_stiffness": None, "gel_fingers": 2}) as h2:
        o2, _ = run_to(h2, 0.03, 0.0, 2.0)
    # a softer object gives way: the gel is pressed in less for the same command
    assert d < o2["indentation"]


def test_split_penetration_solver():
    from teletouch.plugins.sensors.gel import Indenter, gel_force

    ball = Indenter.sphere(0.005)
    gel = lambda d: gel_force(d, ball)  # noqa: E731
    for pen in (1e-5, 1e-4, 1e-3, 5e-3):
        d, f = fc.split_penetration(pen, gel, 1, 500.0)
        assert d + f / 500.0 == pytest.approx(pen, rel=1e-9)
        assert 0 < d < pen
    assert fc.split_penetration(-1e-3, gel) == (0.0, 0.0)
    x = fc.blocked_opening(0.04, 0.035, 3000.0, 5.0, gel, 1, None)
    f = gel(0.04 - x)
    assert f == pytest.approx(min(5.0, 3000.0 * (x - 0.035)), rel=1e-7)
    assert fc.blocked_opening(0.04, 0.05, 3000.0, 5.0, gel) == 0.04


def test_nan_command_holds_and_safe_state():
    with Harness(SimGripper, {"object_width": None}) as h:
        o, t = run_to(h, 0.05, 0.0, 2.0)
        assert o["opening"] == pytest.approx(0.05, abs=1e-6)
        o, t = run_to(h, math.nan, t, 0.5)
        assert o["opening"] == pytest.approx(0.05, abs=1e-6)
        h.comp.safe_state()  # hold: later commands are ignored
        o, t = run_to(h, 0.01, t, 0.5)
        assert o["opening"] == pytest.approx(0.05, abs=1e-6)
    with Harness(SimGripper, {"object_width": 0.04, "safe_mode": "open"}) as h:
        o, t = run_to(h, 0.03, 0.0, 2.0)
        assert o["contact"] is True
        h.comp.safe_state()
        o, t = run_to(h, 0.03, t, 2.0)
        assert o["opening"] == pytest.approx(0.09, abs=1e-6) and o["contact"] is False


def test_params_are_validated():
    with pytest.raises(ValidationError, match="min_opening"):
        SimGripper.Params(min_opening=0.05, max_opening=0.04)
    with pytest.raises(ValidationError, match="initial_opening"):
        SimGripper.Params(initial_opening=0.2)
    assert SimGripper.Params(object_width="35mm").object_width == pytest.approx(0.035)


def test_uses_sim_digit_gel_law(monkeypatch):
    """sim-gripper's contact force is sim-digit's gel_force of its indentation, with the configured indenter."""
    from teletouch.plugins.sensors import gel

    calls = []
    real = gel.gel_force

    def spy(d, indenter, *a, **kw):
        calls.append(indenter)
        return real(d, indenter, *a, **kw)

    monkeypatch.setattr(gel, "gel_force", spy)
    p = {"object_width": 0.04, "indenter": "probe", "indenter_radius": "5mm", "tip_radius": "10mm"}
    with Harness(SimGripper, p) as h:
        o, _ = run_to(h, 0.035, 0.0, 2.0)
    assert calls and all(c.kind == "probe" and c.radius == 0.005 and c.tip_radius == 0.010 for c in calls)
    assert o["contact_force"] == pytest.approx(real(o["indentation"], gel.Indenter.probe(0.005, 0.010)), rel=1e-9)
    # a stiffer gel is pressed in less by the same servo command
    with Harness(SimGripper, dict(p, modulus="2MPa")) as h:
        o2, _ = run_to(h, 0.035, 0.0, 2.0)
    assert o2["indentation"] < o["indentation"]


GRAPH = """
name: sim-follower
clock: sim
duration: 3
nodes:
  - id: cmd
    plugin: mock-sensor
    rate: 100
    params: {signal: sine, amplitude: 0.02, offset: 0.045, frequency: 0.5}
  - id: gripper
    plugin: sim-gripper
    rate: 1kHz
    params: {object_width: 35mm, object_stiffness: 3000}
    inputs: {opening_command: cmd.value}
"""


def test_graph_is_deterministic_and_reaches_contact():
    reg = make_registry(MOD)
    traces = []
    for _ in range(2):
        rows = []
        res, rt = run_yaml(GRAPH, reg, taps=[lambda n, t, o, rows=rows: rows.append(
            (t, o["opening"].value, o["contact_force"].value)) if n == "gripper" else None])
        assert res.status == "ok", res.summary()
        traces.append(rows)
    assert traces[0] == traces[1]
    assert max(r[2] for r in traces[0]) > 0.5  # the sine closes to 25 mm < 35 mm object
    assert min(r[1] for r in traces[0]) > 0.025


SIM_DIGIT_GRAPH = """
name: squeeze-sim-digit
clock: sim
duration: 1.5
nodes:
  - id: cmd
    plugin: mock-sensor
    rate: 100
    params: {signal: constant, amplitude: 0.0375}
  - id: gripper
    plugin: sim-gripper
    rate: 1kHz
    params: {object_width: 40mm, object_stiffness: 5000, indenter: probe, indenter_radius: 5mm, tip_radius: 10mm}
    inputs: {opening_command: cmd.value}
  - id: digit
    plugin: sim-digit
    rate: 30
    params: {indenter: probe, indenter_radius: 5mm, tip_radius: 10mm}
    inputs: {indentation: gripper.indentation}
"""


def test_sim_digit_sees_what_the_fingers_squeeze():
    """sim-gripper's indentation drives sim-digit; both give the same force for it (one gel model)."""
    reg = make_registry(MOD, "teletouch.plugins.sensors.sim_digit")
    res, rt = run_yaml(SIM_DIGIT_GRAPH, reg)
    assert res.status == "ok", res.summary()
    d = rt.latest("gripper", "indentation").value
    f = rt.latest("gripper", "contact_force").value
    assert d > 0.5e-3 and f > 0.5
    assert rt.latest("digit", "gt_force").value == pytest.approx(f, rel=1e-9)
    assert rt.latest("digit", "gt_max_depth").value == pytest.approx(d, rel=0.05)


# ------------------------------------------------------------------------------------------------ audit
def test_object_that_cannot_be_between_or_touched_by_the_fingers_is_refused():
    # wider than the fingers open: the first step reported 40 N (1466 N for 0.2 m) with max_effort 16 N, and the
    # next pushed the fingers open to 0.19 m at 104 m/s
    with pytest.raises(ValidationError, match=r"object_width \(100 mm\) is wider than max_opening \(90 mm\)"):
        SimGripper.Params(object_width=0.1)
    SimGripper.Params(object_width=0.09)
    # zero width or no wider than min_opening: the fingers never touch it (a run without contact)
    for w, lo in ((0.0, 0.0), (0.002, 0.002), (0.001, 0.002)):
        with pytest.raises(ValidationError, match="object_width"):
            SimGripper.Params(object_width=w, min_opening=lo)


def test_starting_inside_the_object_never_exceeds_max_effort():
    p = {"object_width": 0.04, "initial_opening": 0.03, "max_effort": 16.0}
    with Harness(SimGripper, p) as h:
        o = h.step(0.0)
        assert o["contact"] is True
        assert o["contact_force"] <= 16.0 + 1e-9                       # was 40 N: 10 mm squeezed into the gel
        assert 0.03 < o["opening"] < 0.04                               # where the servo's force balances the gel's
        o, t = run_to(h, 0.03, 0.0, 0.2)
        assert o["contact_force"] == pytest.approx(16.0, rel=1e-6) and abs(o["velocity"]) < 1e-9


@pytest.mark.parametrize("beyond", [1e-6, 5e-3])
def test_opening_beyond_the_object_releases_it_at_least_as_fast_as_opening_to_it(beyond):
    """A target outside the object left the fingers inside it (moving out at the servo's pace, still squeezing);
    a target just inside pushed them out to where the servo balances the gel. Commanding wider squeezed harder."""
    w = 0.015
    p = {"object_width": w, "initial_opening": 0.02, "indenter": "probe", "indenter_radius": 0.005}
    forces = {}
    for target in (w - 1e-5, w + beyond):
        with Harness(SimGripper, p) as h:
            o, t = run_to(h, 0.0148, 0.0, 1.0)
            assert o["contact_force"] > 0.1
            o, t = run_to(h, target, t, 0.004)                          # the setpoint gets past the surface
            forces[target] = o["contact_force"]
    assert forces[w + beyond] == 0.0                                    # was 0.02 N
    assert forces[w + beyond] <= forces[w - 1e-5]


@pytest.mark.parametrize("loss", ["safe-state", "stale", "nan"])
@pytest.mark.parametrize("command", [0.0146, 0.0])
def test_the_hold_keeps_the_fingers_and_the_grip_where_they_are(loss, command):
    """The P-only servo, commanded to the opening it measured, pushed with no force: in contact the object pushed the
    fingers open and the grip relaxed (0.39 -> 0.27 N and 0.07 mm wider on the probe; 16 -> 6.8 N, 1.7 mm wider, at
    max_effort), where the follower must hold its position. A real servo keeps its effort (integral action, or a
    gearbox the object cannot back-drive)."""
    p = {"object_width": 0.015, "initial_opening": 0.02, "indenter": "probe", "indenter_radius": 0.005}
    with Harness(SimGripper, p) as h:
        o, t = run_to(h, command, 0.0, 2.0)
        x0, f0 = o["opening"], o["contact_force"]
        assert o["contact"] and f0 > 0.3
        if loss == "safe-state":
            h.comp.safe_state()
            o, t = run_to(h, 0.02, t, 1.0)                             # later commands are ignored
        elif loss == "stale":
            o, t = run_to(h, Sample(0.02, t - 1.0), t, 1.0)
        else:
            o, t = run_to(h, math.nan, t, 1.0)
        assert o["opening"] == pytest.approx(x0, abs=1e-9)
        assert o["contact_force"] == pytest.approx(f0, rel=1e-6)
        assert o["velocity"] == pytest.approx(0.0, abs=1e-9)
        assert h.comp._setpoint == pytest.approx(x0, abs=1e-9)          # the hold commands the measured opening
        if loss != "safe-state":                                        # commands again: followed, nothing held
            o, t = run_to(h, 0.02, t, 1.0)
            assert o["opening"] == pytest.approx(0.02, abs=1e-6) and o["contact_force"] == 0.0
            o, t = run_to(h, command, t, 2.0)
            assert o["opening"] == pytest.approx(x0, abs=1e-9) and o["contact_force"] == pytest.approx(f0, rel=1e-6)


def test_the_hold_in_free_motion_stops_where_the_fingers_are_and_the_open_safe_state_opens_fully():
    with Harness(SimGripper, {"object_width": None}) as h:
        o, t = run_to(h, 0.03, 0.0, 0.2)                                # still moving at max_speed
        x0 = o["opening"]
        assert o["velocity"] < -0.01
        h.comp.safe_state()
        o, t = run_to(h, 0.03, t, 0.5)
        assert o["opening"] == pytest.approx(x0, abs=1e-9) and o["velocity"] == 0.0
    # safe_mode open from a squeeze at max_effort: all the way open (no effort of the squeeze kept)
    p = {"object_width": 0.015, "initial_opening": 0.02, "safe_mode": "open"}
    with Harness(SimGripper, p) as h:
        o, t = run_to(h, 0.0, 0.0, 2.0)
        assert o["contact_force"] == pytest.approx(16.0)
        h.comp.safe_state()
        o, t = run_to(h, 0.0, t, 3.0)
        assert o["opening"] == pytest.approx(0.09, abs=1e-9) and o["contact_force"] == 0.0


@pytest.mark.parametrize("cls", ["sim-gripper", "sim-press-rig"])
@pytest.mark.parametrize("field, value, match", [
    ("indenter_radius", 3.0, r"indenter_radius \(3 m\) is larger than 100 mm.*millimetres typed in a metre field\? "
                             r"write 0.003"),
    ("tip_radius", 10.0, r"tip_radius \(10 m\) is larger than 1000 mm"),
    ("gel_thickness", 4.5, r"gel_thickness \(4.5 m\) is larger than 100 mm"),
    ("modulus", 0.41, r"modulus 0.41 Pa is outside 1000-1e\+09 Pa.*kPa or MPa typed as Pa"),
])
def test_the_gel_parameters_shared_with_sim_digit_refuse_what_sim_digit_refuses(cls, field, value, match):
    """The same gel parameters as sim-digit's: indenter_radius 3 (meant mm) was a 3 m sphere here, accepted."""
    from teletouch.plugins.estimators.force_calibration import SimPressRig
    from teletouch.plugins.sensors.sim_digit import SimDigit

    params = (SimGripper if cls == "sim-gripper" else SimPressRig).Params
    with pytest.raises(ValidationError, match=match):
        params(**{field: value})
    with pytest.raises(ValidationError, match=match):   # one rule: sim-digit says the same
        SimDigit.Params(**{field: value})
    assert params(**{field: "3mm" if field != "modulus" else "0.41MPa"})
