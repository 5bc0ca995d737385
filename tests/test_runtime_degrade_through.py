"""Under `degrade`, a device commanded through nodes that pass a dead node's last value on (a filter, a gain: fresh
stamps on a stale value) is made safe and disabled with the node that died, up to a node that guards its devices
itself (Component.guards_upstream: position-force fades the force, holds the follower). Before, only a device wired
straight from the dead node was: an adversarial audit kept a dead node's 0.55 N on a leader to the end of the run,
through one mock-gain."""

import pytest

from teletouch import Component, Kind, Port, hookimpl
from teletouch.runtime import EXIT_FAULT
from teletouch.testing import Harness, make_registry, run_yaml


class Guard(Component):
    """Passes x on while its feeder lives; a component that brings its devices to a safe end itself."""

    name = "test-guard"
    kind = Kind.CONTROLLER
    guards_upstream = True
    inputs = {"x": Port("float64", (), "any", "input")}
    outputs = {"y": Port("float64", (), "any", "output")}
    default_rate = 100.0

    def step(self, t, inputs):
        x = inputs.value("x")
        return None if x is None or self.ctx.disabled_upstream() else {"y": 0.0}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [Guard]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugin())


GRAPH = """
clock: sim
faults: {on_fault: degrade}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 2.0, fail_at: 0.3}}
  - {id: g1, plugin: mock-gain, rate: 100, params: {gain: 1}, inputs: {x: src.value}}
  - {id: g2, plugin: mock-gain, rate: 100, params: {gain: 1}, inputs: {x: g1.y}}
  - {id: dev, plugin: mock-device, rate: 1000, inputs: {command: g2.y}}
  - {id: ok, plugin: mock-sensor, rate: 100, params: {signal: constant}}
  - {id: dev2, plugin: mock-device, rate: 1000, inputs: {command: ok.value}}
"""


def test_a_device_two_filters_below_a_dead_node_is_made_safe_at_its_fault(reg):
    res, rt = run_yaml(GRAPH, reg, duration=1.0)
    assert res.status == "degraded" and res.exit_code == EXIT_FAULT
    faults = {f.node: f for f in res.faults}
    assert faults["dev"].kind == "upstream" and faults["dev"].time == pytest.approx(0.3)
    assert faults["dev"].message == ("input 'command' comes from node 'g2', fed by node 'src', which was disabled by "
                                     "a fault")
    stats = {n.id: n for n in res.nodes}
    assert stats["dev"].faulted and stats["dev"].steps < 400
    assert rt.component("dev").safe and rt.component("dev").safe_calls == 1
    # the filters themselves are not disabled (nothing they do is unsafe), an unrelated device goes on
    assert not stats["g1"].faulted and not stats["g2"].faulted
    assert not stats["dev2"].faulted and stats["dev2"].steps == 1001


def test_a_node_that_guards_its_devices_stops_the_spread(reg):
    text = GRAPH.replace("plugin: mock-gain, rate: 100, params: {gain: 1}, inputs: {x: g1.y}",
                         "plugin: test-guard, rate: 100, inputs: {x: g1.y}")
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.status == "degraded"
    assert [f.node for f in res.faults] == ["src"]
    stats = {n.id: n for n in res.nodes}
    assert not stats["dev"].faulted and stats["dev"].steps == 1001


def test_the_built_in_controllers_guard_their_devices():
    from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
    from teletouch.plugins.estimators.force_calibration import PressRoutine
    from teletouch.mock import MockGain

    assert all(c.guards_upstream for c in (PositionForce, NoFeedback, PressRoutine))
    # position-position renders a force from the follower's opening and does not ask ctx.disabled_upstream()
    assert not PositionPosition.guards_upstream and not MockGain.guards_upstream


def test_position_force_fades_the_force_when_a_node_feeding_it_is_disabled():
    """A controller that guards its devices must: a restamping filter between a dead estimator and the controller keeps
    its stamps fresh, so the loss shows only in ctx.disabled_upstream(); the force on the hand fades out within
    fade_time as for a stale estimate, and a lasting loss faults after fault_after_lost."""
    from teletouch import ComponentFault, Sample
    from teletouch.plugins.controllers.position_force import PositionForce

    p = {"passivity": False, "deadband": 0.0, "smoothing_time": 0.0, "fade_time": 0.1, "fault_after_lost": 0.5,
         "force_prediction": False}
    f = {}
    with Harness(PositionForce, p) as h:
        with pytest.raises(ComponentFault, match=r"node 'depth' feeding it disabled by a fault"):
            for k in range(2000):
                t = k * 1e-3
                if t >= 0.5:
                    h.disabled_upstream = ["depth"]
                out = h.step(t, leader_opening=Sample(0.03, t), force=Sample(1.0, t))   # fresh stamps throughout
                f[round(t, 3)] = out["gripper_force"]
                assert h.comp.status()["state"] == ("upstream-lost" if t >= 0.5 else "ok")
    assert f[0.499] == pytest.approx(-1.0, abs=1e-6) or f[0.499] == pytest.approx(1.0, abs=1e-6)
    assert abs(f[0.55]) < abs(f[0.499]) and f[0.6] == 0.0 and f[0.9] == 0.0
    assert 0.99 <= max(f) < 1.01   # the last step before the fault: fault_after_lost (0.5 s) after the loss
