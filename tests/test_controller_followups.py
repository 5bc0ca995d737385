"""Follow-ups of the controller audit: millimetres in metre fields, NaN-stamped estimates in the latency figures,
the passivity observer when the leader comes back."""

from __future__ import annotations

import math

import pytest
import yaml
from pydantic import ValidationError

from teletouch import Sample
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
from teletouch.testing import Harness

ALL = [PositionForce, PositionPosition, NoFeedback]


@pytest.mark.parametrize("cls", ALL)
@pytest.mark.parametrize("field,value,hint", [("opening_max", 90, "0.09"), ("opening_min", 5, "0.005"),
                                              ("offset", -20, "-0.02")])
def test_millimetres_typed_in_a_metre_field_are_refused(cls, field, value, hint):
    # `opening_max: 90` (mm meant) was taken as 90 m: the controller's limit was none (only the follower
    # driver's own clamp held)
    with pytest.raises(ValidationError, match=rf"{field} \({value:g} m\) is beyond any gripper's opening \(1 m at "
                                              rf"most\): millimetres in the metre field\? a bare number is metres: "
                                              rf"for {value:g} mm write {hint} or \"{value:g}mm\""):
        cls.Params(**{field: value})
    # the plausible values and the mm spelling are accepted
    assert cls.Params(opening_max="90mm").opening_max == pytest.approx(0.09)
    assert cls.Params(opening_min=0.005, opening_max=1.0, offset=-0.02).offset == -0.02


def test_millimetres_in_a_metre_field_are_named_when_the_graph_is_validated():
    from teletouch.errors import GraphValidationError
    from teletouch.graph import load_graph_text

    doc = {"name": "mm", "clock": "sim", "duration": 1, "nodes": [
        {"id": "controller", "plugin": "position-force", "params": {"opening_max": 90},
         "inputs": {"leader_opening": "controller.opening_command", "force": "controller.gripper_force"}}]}
    with pytest.raises(GraphValidationError, match=r"node 'controller'.*opening_max \(90 m\).*millimetres in the"):
        load_graph_text(yaml.safe_dump(doc, sort_keys=False), "<mm>")


def test_a_nan_stamped_estimate_adds_no_latency():
    # a force sample stamped NaN (a broken clock upstream) put NaN into the latency list on every step it stayed the
    # latest sample, so the latency statistics became NaN
    p = {"deadband": 0.0, "stale_after": 0.1}
    with Harness(PositionForce, p) as h:
        for k in range(100):
            t = k * 1e-3
            vals = {"leader_opening": 0.02}
            if k % 17 == 0:
                vals["force"] = Sample(1.0, t - 0.002)
            h.step(t, **vals)
        n = len(h.comp.latencies)
        assert n == 6 and all(lat == pytest.approx(0.002) for lat in h.comp.latencies)
        for k in range(100, 200):
            h.step(k * 1e-3, leader_opening=0.02, force=Sample(1.0, math.nan))
        assert len(h.comp.latencies) == n and all(math.isfinite(lat) for lat in h.comp.latencies)
        assert h.comp.state == "stale-force"
        h.step(0.2, leader_opening=0.02, force=Sample(1.0, 0.199))        # a good one again: counted
        assert h.comp.latencies[-1] == pytest.approx(0.001) and len(h.comp.latencies) == n + 1


def _leader_loss(cls, params, deficit=-1.0, lost=(500, 800), n=1000):
    """The leader closes at 10 mm/s against a 2 N contact; a deficit planted at step 400 brings the passivity
    damping up; the leader is lost over ``lost`` (its last sample goes stale) and comes back, still closing.
    Returns the outputs per step and the component."""
    outs = []
    with Harness(cls, params) as h:
        for k in range(n):
            t = k * 1e-3
            if k == 400:
                h.comp.pas.energy = deficit
            x = 0.02 - 0.01 * t
            vals = {"force": Sample(2.0, t), "follower_opening": Sample(x, t)}
            if not lost[0] <= k < lost[1]:
                vals.update(leader_opening=Sample(x, t), leader_velocity=Sample(-0.01, t))
            outs.append(h.step(t, **vals))
        return outs, h.comp


@pytest.mark.parametrize("cls,params,two_port", [
    (PositionForce, {"deadband": 0.0}, True),
    (PositionForce, {"deadband": 0.0, "passivity_controller": "damping", "free_space_reset": None}, True),
    (PositionForce, {"deadband": 0.0, "passivity_observer": "leader-port"}, False),
    (PositionPosition, {"kp": 0.0, "kd": 0.0, "free_space_reset": None}, False),
])
def test_the_returning_leader_does_not_get_the_old_damping(cls, params, two_port):
    # the passivity damping, and the 1 J deficit behind it, carried over a loss of the leader: the returning hand
    # got the full 40 N*s/m at once and for good (the deficit, 250 s of it at 10 mm/s; position-position with no
    # coupling at all rendered 0.4 N of damping). The observer now starts afresh when the leader comes back.
    outs, comp = _leader_loss(cls, params)
    assert max(o["damping"] for o in outs[400:500]) >= 39.0             # the deficit brought the damping up
    assert all(o["damping"] == 0.0 for o in outs[560:800])               # none while the leader is lost
    back = outs[800:]
    assert back[0]["damping"] == 0.0 and back[1]["damping"] == 0.0      # was 40 at the first step back
    assert min(o["energy"] for o in back) > -1e-3                       # was -1 J
    assert back[-1]["energy"] >= 0.0 and back[-1]["damping"] < 10.0      # was 40
    d = [o["damping"] for o in back]
    if two_port:
        # the force comes back within max_force_rate while the follower port books the whole sensed force: a new,
        # small deficit (< 0.1 mJ), met by damping that rises over damping_smoothing from zero, no step
        assert max(b - a for a, b in zip(d, d[1:])) <= 0.2 * 40.0 + 1e-9
    else:
        assert max(d) == 0.0                                              # closing against the contact: energy in


def test_a_deficit_after_the_return_is_met_by_damping_that_rises_smoothly():
    # the observer starts afresh on the return; a new deficit is met as any other: the damping rises over
    # damping_smoothing (5 ms), never a step to the cap
    p = {"deadband": 0.0, "passivity_controller": "damping", "free_space_reset": None}
    outs = []
    with Harness(PositionForce, p) as h:
        for k in range(1000):
            t = k * 1e-3
            x = 0.02 - 0.01 * t
            vals = {"force": Sample(2.0, t)}
            if not 500 <= k < 800:
                vals.update(leader_opening=Sample(x, t), leader_velocity=Sample(-0.01, t))
            if k == 850:
                h.comp.pas.energy = -1.0
            outs.append(h.step(t, **vals))
    d = [o["damping"] for o in outs[850:900]]
    assert d[0] < 0.25 * 40.0 and max(d) == pytest.approx(40.0, rel=1e-3)
    assert max(b - a for a, b in zip(d, d[1:])) <= 0.2 * 40.0 + 1e-9
