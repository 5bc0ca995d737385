"""A fault of an isolated node (``isolate: process``) keeps what a fault of an inline node carries across the process
boundary: its type and message, its place in the plugin (``where``) and the input it is about (``input_port``), so
that the runtime still adds which node and port feed that input (test_faults_upstream.py, inline)."""

from __future__ import annotations

import sys
import time

import pytest

from teletouch.component import Component, Context, Inputs, Kind, Params, Port, _Slot
from teletouch.errors import ComponentFault, HardwareError
from teletouch.hookspecs import hookimpl
from teletouch.isolation import ProcessProxy
from teletouch.runtime import EXIT_FAULT
from teletouch.testing import make_registry, run_yaml

HERE = "test_isolation_faults.py:"


# --- a plugin of our own (module level: the child imports it by name, as it does a plugin's) --------------------------
class Lossy(Component):
    """Raises from its third step on: a ComponentFault about input ``port`` (params), a plain one without a port
    (``port: ''``), or a HardwareError about ``port`` (``hardware: true``)."""

    name = "s16-iso-lossy"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "any", "a signal"), "y": Port("float64", (), "any", "", required=False)}
    outputs = {"z": Port("float64", (), "any", "")}

    class Params(Params):
        port: str = "x"
        hardware: bool = False

    def configure(self):
        self.steps = 0

    def step(self, t, inputs):
        self.steps += 1
        if self.steps >= 3:
            if self.params.hardware:
                raise HardwareError("cable pulled", input_port=self.params.port)
            if self.params.port:
                raise ComponentFault(f"lost {self.params.port}", input_port=self.params.port)
            raise ComponentFault("it broke")
        return {"z": 0.0}


@hookimpl
def teletouch_components():
    return [Lossy]


def _graph(params: str) -> str:
    return f"""
clock: wall
nodes:
  - {{id: src, plugin: mock-sensor, rate: 50}}
  - {{id: lossy, plugin: s16-iso-lossy, rate: 50, params: {{{params}}}, inputs: {{x: src.value}}, isolate: process}}
"""


@pytest.fixture(scope="module")
def reg():
    return make_registry(sys.modules[__name__])


@pytest.mark.parametrize("params, said", [
    ("port: x", "ComponentFault: in isolated process: ComponentFault: lost x; input 'x' is fed by node 'src' port "
                "'value' ("),
    ("port: y", "ComponentFault: in isolated process: ComponentFault: lost y; input 'y' is not wired in the graph ("),
    ("port: ''", "ComponentFault: in isolated process: ComponentFault: it broke ("),
    ("hardware: true", "ComponentFault: in isolated process: HardwareError: cable pulled; input 'x' is fed by node "
                       "'src' port 'value' ("),
])
def test_an_isolated_nodes_fault_names_the_node_that_feeds_its_input(reg, params, said):
    res, rt = run_yaml(_graph(params), reg, duration=3.0)
    assert res.exit_code == EXIT_FAULT and res.sim_time < 2.0, res.message
    (f,) = res.faults
    assert f.node == "lossy" and f.kind == "exception", f
    # what the runtime adds comes before the place of the raise, which is the plugin's line in the child (not the
    # proxy's in the parent)
    assert f.message.startswith(said), f.message
    assert f.message.endswith(")") and f.message.rsplit("(", 1)[1].startswith(HERE), f.message
    assert "isolation.py" not in f.message, f.message
    assert ("fed by" in res.message) == ("'src'" in said), res.message
    assert rt.component("lossy")._proc.exitcode == 0   # the child lived on and was closed


def test_the_proxy_raises_a_component_fault_with_the_childs_input_port_and_place():
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=50.0)
    proxy = ProcessProxy(Lossy, Lossy.Params(port="x"), node_id="n", ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                         step_timeout=5.0)
    inputs = Inputs({"x": _Slot(), "y": _Slot()})
    try:
        proxy.configure()
        proxy.activate()
        for k in range(2):
            assert proxy.step(k * 0.02, inputs) == {"z": 0.0}
        with pytest.raises(ComponentFault) as caught:
            proxy.step(0.04, inputs)
    finally:
        proxy.deactivate()
        proxy.close()
    exc = caught.value
    assert type(exc) is ComponentFault and str(exc) == "in isolated process: ComponentFault: lost x"
    assert exc.input_port == "x"
    assert exc.where.startswith(HERE) and exc.where[len(HERE):].isdigit(), exc.where
