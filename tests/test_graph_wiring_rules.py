"""A component's own wiring rules (``Component.wiring_problems``), checked when a graph is validated: each problem
names the node and points at the line of the wire it is about."""

from __future__ import annotations

import types

import pytest

from teletouch import Kind, Port, hookimpl
from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph_text
from teletouch.mock import MockGain
from teletouch.testing import make_registry

SPLIT = """\
nodes:
  - id: ros
    plugin: ros2-subscribe
    rate: 100
    params: {topics: [force]}
  - id: gain
    plugin: mock-gain
    rate: 100
    inputs:
      x: ros.opening
"""


def test_a_bridge_output_read_by_the_graph_but_not_subscribed_is_refused_at_the_wire():
    with pytest.raises(GraphValidationError) as exc:
        load_graph_text(SPLIT, file="split.yaml", registry=make_registry("teletouch.plugins.bridges.ros2"))
    msg = str(exc.value)
    assert ("split.yaml:10: node 'ros': output 'opening' is wired, but its topic 'joint_states' is not in this "
            "node's topics [force]: add joint_states to topics, or read another output") in msg
    fixed = SPLIT.replace("topics: [force]", "topics: [force, joint_states]")
    spec = load_graph_text(fixed, file="split.yaml", registry=make_registry("teletouch.plugins.bridges.ros2"))
    assert [n.id for n in spec.nodes] == ["ros", "gain"]


class Picky(MockGain):
    name = "picky-gain"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "gain * x"), "z": Port("float64", (), "any", "reserved")}

    @classmethod
    def wiring_problems(cls, params, inputs, outputs):
        if "boom" in outputs:
            raise RuntimeError("the check itself broke")
        return {"z": "output 'z' is reserved"} if "z" in outputs else {}


@hookimpl
def teletouch_components():
    return [Picky]


PICKY = """\
nodes:
  - id: src
    plugin: mock-sensor
    rate: 100
  - id: p
    plugin: picky-gain
    rate: 100
    inputs: {x: src.value}
  - id: a
    plugin: mock-gain
    rate: 100
    inputs: {x: p.z}
  - id: b
    plugin: mock-gain
    rate: 100
    inputs: {x: p.z}
"""


def test_a_plugin_rule_points_at_the_first_wire_and_a_broken_check_does_not_hide_other_errors():
    reg = make_registry(types.SimpleNamespace(__name__="picky", teletouch_components=teletouch_components))
    with pytest.raises(GraphValidationError) as exc:
        load_graph_text(PICKY, file="g.yaml", registry=reg)
    assert "g.yaml:12: node 'p': output 'z' is reserved" in str(exc.value)
    load_graph_text(PICKY.replace("p.z", "p.y"), file="g.yaml", registry=reg)   # nothing else is refused
    # a check that raises is reported on the node, and the graph's other errors (an unknown output, a rate) still are
    broken = PICKY.replace("inputs: {x: p.z}\n  - id: b", "inputs: {x: p.boom}\n  - id: b")
    broken = broken[:broken.rindex("rate: 100")] + "rate: 1e9" + broken[broken.rindex("rate: 100") + 9:]
    with pytest.raises(GraphValidationError) as exc:
        load_graph_text(broken, file="g.yaml", registry=reg)
    msg = str(exc.value)
    assert "g.yaml:5: node 'p': the wiring check of picky-gain failed: RuntimeError: the check itself broke" in msg
    assert "g.yaml:15: node 'b': rate: at most 1000000 Hz" in msg and "has no output 'boom'" in msg
