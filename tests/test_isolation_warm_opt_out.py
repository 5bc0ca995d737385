"""A per-node opt-out of warm-ups for an isolated node: a class with a warm() whose parameters turn it off
(``Component.wants_warm_up``; the depth node's ``warm: false``) makes no warm-up round trip to its child, where before
the proxy asked the child 1 ms before every step and waited for a warm() that returned at once. With warm-ups on,
the child is asked as before. Counted by the requests the proxy sends and the child's warm() calls, never by time."""

from __future__ import annotations

import sys

import pytest

from helpers_depth import proxy_requests_fixture

from teletouch.component import Component, Device, Kind, Params, Port, has_warm_up
from teletouch.hookspecs import hookimpl
from teletouch.runtime import EXIT_OK
from teletouch.testing import Harness, make_registry, run_yaml


# --- a plugin of our own (module level: the child imports it by name, as it does a plugin's) --------------------------
class Knob(Component):
    """Echoes ``x``; its warm() (counted, whatever its parameter says) is wanted only with ``warm: true``."""

    name = "s16-iso-knob"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "any", "")}
    outputs = {"y": Port("float64", (), "any", "")}

    class Params(Params):
        warm: bool = True

    @classmethod
    def wants_warm_up(cls, params):
        return params.warm

    def configure(self):
        self.steps = 0
        self.warm_calls = 0

    def warm(self):
        self.warm_calls += 1

    def step(self, t, inputs):
        self.steps += 1
        s = inputs["x"]
        return {"y": 0.0 if s is None else s.value}

    def status(self):
        return {"steps": self.steps, "warm_calls": self.warm_calls}


class Plain(Component):
    name = "s16-iso-plain"
    outputs = {"y": Port("float64", (), "any", "")}

    def step(self, t, inputs):
        return {"y": t}


class KnobDevice(Device):
    name = "s16-iso-knob-device"
    outputs = {"y": Port("float64", (), "", "")}

    class Params(Params):
        warm: bool = True

    def warm(self):   # never called: a warm-up must not command hardware
        raise AssertionError("a device was warmed")

    def step(self, t, inputs):
        return {"y": t}

    def safe_state(self):
        pass


@hookimpl
def teletouch_components():
    return [Knob, Plain, KnobDevice]


@pytest.fixture(scope="module")
def reg():
    return make_registry(sys.modules[__name__])


requests = proxy_requests_fixture()


def _graph(warm: str) -> str:
    return f"""
clock: wall
nodes:
  - {{id: src, plugin: mock-sensor, rate: 50}}
  - {{id: knob, plugin: s16-iso-knob, rate: 50, params: {{warm: {warm}}}, inputs: {{x: src.value}}, isolate: process}}
"""


def test_the_decision_to_warm_may_look_at_the_nodes_parameters():
    assert has_warm_up(Knob) and has_warm_up(Knob, Knob.Params())
    assert not has_warm_up(Knob, Knob.Params(warm=False))
    assert not has_warm_up(Plain) and not has_warm_up(Plain, Plain.Params())   # no warm() of its own
    assert not has_warm_up(KnobDevice, KnobDevice.Params())                       # never a device
    assert Component.wants_warm_up(Params()) is True                             # the default: as the class says


@pytest.mark.parametrize("warm", ["true", "false"])
def test_an_isolated_node_whose_parameters_turn_warm_ups_off_makes_no_warm_up_round_trip(reg, requests, warm):
    res, rt = run_yaml(_graph(warm), reg, duration=1.0)
    assert res.exit_code == EXIT_OK, res.message
    st = rt.component("knob").status()
    ops = [op for nid, op in requests if nid == "knob"]
    assert st["steps"] >= 20 and ops.count("step") == st["steps"], (st, ops)
    assert ops.count("warm") == st["warm_calls"]   # each request is one warm() in the child
    if warm == "true":
        assert st["warm_calls"] >= st["steps"] / 2, st   # (a loaded machine's slow cycle leaves a few out)
    else:
        assert st["warm_calls"] == 0, st
        # not one request more than its lifecycle and its steps: configure, clock, activate, deactivate, results
        # (the run's results, asked of the child), close
        assert len(ops) == rt.component("knob")._seq == st["steps"] + 6, ops
        assert ops[-3:] == ["deactivate", "results", "close"], ops


def test_an_isolated_depth_node_with_warm_false_sends_no_warm_up(requests):
    from helpers_depth import isolated_depth_graph

    from teletouch.plugins.estimators.depth import DepthEstimator

    assert has_warm_up(DepthEstimator, DepthEstimator.Params(warm=True))
    assert not has_warm_up(DepthEstimator, DepthEstimator.Params(warm=False))
    reg = make_registry("teletouch.plugins.sensors.sim_digit", "teletouch.plugins.estimators.depth")
    text = isolated_depth_graph(25).replace("isolate: process}", "isolate: process, params: {warm: false}}")
    assert "warm: false" in text
    res, rt = run_yaml(text, reg, duration=1.5)
    assert res.exit_code == EXIT_OK, res.message
    ops = [op for nid, op in requests if nid == "depth"]
    assert ops.count("step") >= 20 and "warm" not in ops, ops


@pytest.mark.parametrize("warm", ["true", "false"])
def test_an_inline_node_whose_parameters_turn_warm_ups_off_is_not_warmed(reg, warm):
    """Inline the runtime asks the same question with the node's parameters: with warm-ups off its warm() is never
    called (before, it was called before every step, and the warm-up budget counted it)."""
    res, rt = run_yaml(_graph(warm).replace(", isolate: process", ""), reg, duration=1.0)
    assert res.exit_code == EXIT_OK, res.message
    st = rt.component("knob").status()
    assert st["steps"] >= 20, st
    if warm == "true":
        assert st["warm_calls"] >= st["steps"] / 2, st
    else:
        assert st["warm_calls"] == 0, st


def test_the_harness_refuses_a_warm_up_the_parameters_turn_off():
    # a review found Harness.warm() calling warm() where the runtime never would (it refused only a device's)
    with Harness(Knob, {"warm": True}) as h:
        h.warm()
        assert h.comp.warm_calls == 1
    with Harness(Knob, {"warm": False}) as h:
        with pytest.raises(TypeError, match="wants_warm_up says no for these parameters"):
            h.warm()
        assert h.comp.warm_calls == 0


class BadWish(Knob):
    name = "s16-iso-bad-wish"

    @classmethod
    def wants_warm_up(cls, params):
        raise RuntimeError("no idea")


def test_a_wants_warm_up_that_raises_inline_fails_the_nodes_configure_naming_it():
    # a review found it raised out of Runtime() (when each node was built): "a component could not be created",
    # without the node, and the components already built were never closed; isolated, it was a configure failure
    class _P:
        @hookimpl
        def teletouch_components(self):
            return [BadWish]

    text = _graph("true").replace("s16-iso-knob", "s16-iso-bad-wish").replace(", isolate: process", "")
    res, _ = run_yaml(text, make_registry(_P()), duration=0.5)
    assert res.status == "startup-failed", res.message
    assert "node 'knob' (s16-iso-bad-wish) failed to configure" in res.message and "no idea" in res.message
