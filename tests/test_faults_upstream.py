"""A fault about a lost input names where that input comes from. The controller raises ComponentFault("force
estimate lost ...") and cannot know the graph; the runtime, which knows the wires, adds which node and port feed the
input the fault is about (``ComponentFault(..., input_port="force")``). A plain ComponentFault(message), as third-party
plugins raise it, is reported as before."""

from __future__ import annotations

import pickle
import sys

import pytest

from teletouch import Component, ComponentFault, Kind, Params, Port, Sample, hookimpl
from teletouch.plugins.controllers.position_force import PositionForce
from teletouch.testing import Harness, make_registry, run_yaml

PLUGIN = "teletouch.plugins.controllers.position_force"

LOST_FORCE = """
clock: sim
duration: 1.2
nodes:
  - {id: hand, plugin: mock-sensor, rate: 1kHz, params: {signal: constant, amplitude: 0.02}}
  - {id: poly-est, plugin: mock-sensor, rate: 60, params: {signal: constant, amplitude: 2.0, silent_at: 0.5}}
  - id: ctl
    plugin: position-force
    rate: 1kHz
    params: {fade_time: 0.2}
    inputs: {leader_opening: hand.value, force: poly-est.value}
  - {id: leader, plugin: mock-device, rate: 1kHz, inputs: {command: ctl.gripper_force}}
"""


def test_a_lost_force_estimate_names_the_node_and_port_that_feed_it():
    res, rt = run_yaml(LOST_FORCE, make_registry(PLUGIN))
    assert (res.status, res.exit_code) == ("fault", 3), res.summary()
    fed = "input 'force' is fed by node 'poly-est' port 'value'"
    assert "force estimate lost for" in res.message and fed in res.message, res.message
    assert res.faults[0].node == "ctl" and fed in res.faults[0].message, res.faults
    assert fed in res.summary() and fed in str(res.as_dict()["faults"]), res.summary()
    # the wire is said before the location of the raise, which stays the plugin's line
    assert res.faults[0].message.endswith(")") and "position_force.py:" in res.faults[0].message.rsplit("(", 1)[1]
    assert rt.latest("leader", "command_applied").value == 0.0      # the devices were made safe as before


def test_a_lost_leader_names_the_node_that_feeds_it():
    text = LOST_FORCE.replace("amplitude: 0.02}", "amplitude: 0.02, nan_at: 0.3}").replace(", silent_at: 0.5", "")
    res, _ = run_yaml(text, make_registry(PLUGIN))
    assert res.status == "fault", res.summary()
    assert "leader opening lost for" in res.message, res.message
    assert "input 'leader_opening' is fed by node 'hand' port 'value'" in res.message, res.message


def test_the_controller_says_which_input_it_lost():
    with Harness(PositionForce, {"passivity": False, "fault_after_lost": 0.5}) as h:
        h.step(0.0, leader_opening=0.02, force=Sample(1.0, 0.0))
        with pytest.raises(ComponentFault, match="force estimate lost") as caught:
            for k in range(1, 800):
                h.step(k * 1e-3, leader_opening=0.02)
    assert caught.value.input_port == "force"


# --- a plugin of our own ------------------------------------------------------------------------------------------
class Picky(Component):
    """Raises at 0.1 s: a plain ComponentFault, or one about input ``port`` (params)."""

    name = "s16-picky"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "N", "a force"), "y": Port("float64", (), "N", "another", required=False)}
    outputs = {"z": Port("float64", (), "N", "their sum")}
    default_rate = 100.0

    class Params(Params):
        port: str = ""

    def step(self, t, inputs):
        if t >= 0.1:
            if self.params.port:
                raise ComponentFault(f"lost {self.params.port}", input_port=self.params.port)
            raise ComponentFault("it broke")
        return {"z": 0.0}


@hookimpl
def teletouch_components():
    return [Picky]


def _picky(port: str) -> str:
    return f"""
clock: sim
duration: 0.3
nodes:
  - {{id: src, plugin: mock-sensor, rate: 100}}
  - {{id: p, plugin: s16-picky, rate: 100, params: {{port: '{port}'}}, inputs: {{x: src.value}}}}
"""


@pytest.mark.parametrize("port, tail", [
    ("", "ComponentFault: it broke ("),
    ("x", "ComponentFault: lost x; input 'x' is fed by node 'src' port 'value' ("),
    ("y", "ComponentFault: lost y; input 'y' is not wired in the graph ("),
    ("w", "ComponentFault: lost w; the fault names input 'w', which s16-picky does not have (inputs: x, y) ("),
])
def test_what_is_said_of_the_input_a_fault_names(port, tail):
    res, _ = run_yaml(_picky(port), make_registry(sys.modules[__name__]))
    assert res.status == "fault", res.summary()
    assert res.faults[0].message.startswith(tail), res.faults[0].message
    assert ("fed by" in res.message) == (port == "x"), res.message


def test_component_fault_keeps_its_old_signature():
    plain = ComponentFault("boom", "n1")
    assert str(plain) == "node 'n1': boom" and plain.node == "n1" and plain.input_port is None
    about = ComponentFault("lost", input_port="force")
    assert str(about) == "lost" and about.input_port == "force"
    back = pickle.loads(pickle.dumps(about))   # (an isolated node's process sends its errors pickled)
    assert str(back) == "lost" and back.input_port == "force"
