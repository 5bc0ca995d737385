"""Component.warm() of an isolated node: the proxy asks its child to call the component's warm() 1 ms before each
step, as the runtime does inline, and waits for the answer (one call at a time, numbered, timed out and abandoned as a
step). A component without warm() (the base class's) and a device are never asked: no request crosses for them."""

from __future__ import annotations

import os
import threading
import time
from statistics import median
from types import SimpleNamespace

import numpy as np
import pytest

from helpers_depth import proxy_requests_fixture

from teletouch.component import Component, Context, Device, Inputs, Kind, Params, Port, Sample, _Slot
from teletouch.errors import ComponentFault
from teletouch.hookspecs import hookimpl
from teletouch.isolation import ProcessProxy, StepAbandoned
from teletouch.runtime import EXIT_FAULT, EXIT_OK, _Node
from teletouch.testing import make_registry, run_yaml

# --- test components (module level: the child imports them by name, as it does a plugin's) -------------------------


class Echo(Component):
    """Echoes its input ``x`` (a large array: it crosses through shared memory) and counts its steps; status() says
    what the child saw: steps, warm-ups, steps that a warm-up preceded and the median time from warm-up to step."""

    name = "s15-echo"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (None,), "any", "")}
    outputs = {"y": Port("float64", (None,), "any", ""), "steps": Port("float64", (), "", "")}

    class Params(Params):
        fail: bool = False        # warm() raises
        die: bool = False         # warm() ends the child process
        hang_s: float = 0.0       # warm() sleeps this long

    def configure(self):
        self.steps = 0
        self.warms = 0
        self.warmed_steps = 0
        self.gaps: list[float] = []
        self._warmed: float | None = None

    def step(self, t, inputs):
        now = time.perf_counter()
        self.steps += 1
        if self._warmed is not None:
            self.warmed_steps += 1
            self.gaps.append(now - self._warmed)
            self._warmed = None
        s = inputs["x"]
        return {"y": np.zeros(0) if s is None else s.value, "steps": float(self.steps)}

    def status(self):
        return {"steps": self.steps, "warms": self.warms, "warmed_steps": self.warmed_steps,
                "gap_median_s": median(self.gaps) if self.gaps else -1.0, "pid": os.getpid()}


class WarmEcho(Echo):
    name = "s15-warm-echo"

    def warm(self):
        self.warms += 1
        self._warmed = time.perf_counter()
        if self.params.fail:
            raise RuntimeError("cache rehearsal failed in the child")
        if self.params.die:
            os._exit(3)
        if self.params.hang_s:
            time.sleep(self.params.hang_s)


class Ramp(Component):
    """A 64 kB array filled with the step's time."""

    name = "s15-ramp"
    kind = Kind.SENSOR
    outputs = {"x": Port("float64", (None,), "any", "")}

    def step(self, t, inputs):
        return {"x": Sample(np.full(8192, t), t)}


class WarmDevice(Device):
    name = "s15-warm-device"
    outputs = {"y": Port("float64", (), "", "")}

    def warm(self):   # never called: a warm-up must not command hardware
        raise AssertionError("a device was warmed")

    def step(self, t, inputs):
        return {"y": t}

    def safe_state(self):
        pass


@hookimpl
def teletouch_components():
    return [Echo, WarmEcho, Ramp, WarmDevice]


@pytest.fixture(scope="module")
def reg():
    import sys

    return make_registry(sys.modules[__name__])


requests = proxy_requests_fixture()


GRAPH = """
clock: wall
faults: {max_overruns: 0, watchdog: 5}
nodes:
  - {id: src, plugin: s15-ramp, rate: 50}
  - {id: warmed, plugin: s15-warm-echo, rate: 50, inputs: {x: src.x}, isolate: process}
  - {id: plain, plugin: s15-echo, rate: 50, inputs: {x: src.x}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 500}
"""


def test_an_isolated_node_is_warmed_in_its_child_before_each_step_and_one_without_warm_is_not_asked(reg, requests):
    outs: dict[str, list[tuple[float, dict]]] = {"warmed": [], "plain": []}
    res, rt = run_yaml(GRAPH, reg, duration=1.0, taps=[lambda n, t, o: n in outs and outs[n].append((t, o))])
    assert res.exit_code == EXIT_OK, res.message
    st = rt.component("warmed").status()
    assert st["pid"] != os.getpid() and st["steps"] >= 40, st
    # every step but the first (due at once, at t = 0) follows a warm-up of its own cycle, in the child; a heavily
    # loaded machine's slow cycle leaves a few out, by design (seen: 3 of 51 with 12 test processes on 16 cores)
    few = max(2, st["steps"] // 10)
    assert st["warms"] >= st["steps"] - few and st["warmed_steps"] >= st["steps"] - few, st
    # about WARM_LEAD (1 ms) before the step; far less than the 20 ms period (a loaded machine delays some)
    assert 0.3e-3 < st["gap_median_s"] < 6e-3, st
    ops = [op for nid, op in requests if nid == "warmed"]
    steps = [i for i, op in enumerate(ops) if op == "step"]
    assert sum(ops[i - 1] == "warm" for i in steps[1:]) >= len(steps) - few, ops
    assert ops.count("warm") == st["warms"]
    # the plugin without warm(): not one request more than its lifecycle and its steps
    plain = [op for nid, op in requests if nid == "plain"]
    assert "warm" not in plain and plain.count("step") >= 40, plain
    assert rt.component("plain").status()["warms"] == 0
    # configure, clock, activate, deactivate, results, close and the steps
    assert len(plain) == rt.component("plain")._seq == plain.count("step") + 6
    # the outputs are the step's own: its input echoed whole, steps counted once each (a warm-up is no step)
    for name, seen in outs.items():
        for k, (t, o) in enumerate(seen, 1):
            y = o["y"]
            assert y.shape == (8192,) and np.all(y == y[0]) and y[0] == pytest.approx(t, abs=0.02), (name, t, y[0])
            assert o["steps"] == k


def test_the_decision_to_warm_looks_at_the_isolated_class_and_never_at_a_device():
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=50.0)

    def node(cls):
        proxy = ProcessProxy(cls, cls.Params(), node_id="n", ctx=ctx, t0_perf=0.0, t0_mono=0.0, step_timeout=1.0)
        spec = SimpleNamespace(id="n", rate=50.0, cls=cls)
        n = _Node(spec, proxy, 0, "stop", {p: _Slot() for p in cls.inputs}, {p: _Slot() for p in cls.outputs})
        n.decide_warm()   # (the runtime decides once the node has configured)
        return n

    assert node(WarmEcho).warm is not None
    assert node(Echo).warm is None and node(WarmDevice).warm is None
    for cls in (Echo, WarmDevice):   # asked all the same: nothing is sent (no child was even started)
        proxy = ProcessProxy(cls, cls.Params(), node_id="n", ctx=ctx, t0_perf=0.0, t0_mono=0.0, step_timeout=1.0)
        proxy.warm()
        assert proxy._seq == 0


def test_an_exception_in_the_childs_warm_faults_the_node_naming_warm(reg):
    text = GRAPH.replace("s15-warm-echo, rate: 50,", "s15-warm-echo, rate: 50, params: {fail: true},")
    res, rt = run_yaml(text, reg, duration=2.0)
    assert res.exit_code == EXIT_FAULT, res.message
    (f,) = [f for f in res.faults if f.node == "warmed"]
    assert f.kind == "exception" and f.message.startswith(
        "warm(): ComponentFault: in isolated process: RuntimeError: cache rehearsal failed in the child"), f
    assert "test_isolation_warm.py:" in f.message, f   # its place in the child
    assert res.sim_time < 1.0 and rt.component("dev").safe_calls >= 1
    assert rt.component("warmed")._proc.exitcode == 0   # the child lived on and was closed


def test_a_child_that_dies_in_warm_is_reported_as_in_a_step(reg):
    text = GRAPH.replace("s15-warm-echo, rate: 50,", "s15-warm-echo, rate: 50, params: {die: true},")
    res, rt = run_yaml(text, reg, duration=5.0)
    assert res.exit_code == EXIT_FAULT and res.sim_time < 2.0, res.message
    assert "node 'warmed' exception: warm(): ComponentFault: isolated process died during 'warm': s15-warm-echo " \
           "(pid " in res.message and "exited with code 3" in res.message, res.message
    assert [f.kind for f in res.faults] == ["exception"]
    assert rt.component("dev").safe_calls >= 1


def test_a_warm_up_times_out_and_is_abandoned_as_a_step_and_its_late_answer_is_dropped():
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=50.0)
    proxy = ProcessProxy(WarmEcho, WarmEcho.Params(hang_s=0.6), node_id="w", ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                         step_timeout=0.2)
    slot = _Slot()
    inputs = Inputs({"x": slot})
    try:
        proxy.configure()
        proxy.activate()
        slot.sample = Sample(np.full(8192, 1.0), 1.0)
        assert proxy.step(1.0, inputs)["steps"] == 1.0
        with pytest.raises(ComponentFault, match=r"did not answer 'warm' within 0.2 s"):
            proxy.warm()
        threading.Timer(0.1, proxy.abandon_step, ("the watchdog",)).start()
        t0 = time.monotonic()
        proxy._step_timeout = 5.0
        with pytest.raises(StepAbandoned, match=r"warm\(\) abandoned after 0\.\d+ s .*: the watchdog"):
            proxy.warm()
        assert time.monotonic() - t0 < 0.5   # at once, not after the child's 0.6 s nor the 5 s timeout
        slot.sample = Sample(np.full(8192, 2.0), 2.0)
        out = proxy.step(2.0, inputs)   # both warm-ups' late answers dropped: this step's own outputs
        assert out["steps"] == 2.0 and np.all(out["y"] == 2.0)
        assert proxy.status()["warms"] == 2
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0


def test_a_warm_up_that_hangs_is_cut_short_by_the_watchdog_as_a_step_is(reg):
    from teletouch.runtime import Runtime
    from teletouch.testing import load_text

    text = """
clock: wall
faults: {watchdog: 0.1}
nodes:
  - {id: src, plugin: s15-ramp, rate: 50}
  - {id: warmed, plugin: s15-warm-echo, rate: 50, params: {hang_s: 1.5}, inputs: {x: src.x}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 50}
"""
    logs: list[str] = []
    rt = Runtime(load_text(text, reg), log=logs.append)
    res = rt.run(5.0)
    assert res.exit_code == EXIT_FAULT and res.sim_time < 0.5, res.message
    assert [(f.node, f.kind) for f in res.faults] == [("warmed", "timeout"), ("dev", "stall")], res.faults
    assert "warm() did not return within 0.1 s" in res.faults[0].message, res.faults[0].message
    assert "waits for the warm() of node 'warmed'" in res.faults[1].message, res.faults[1].message
    # the wait for the warm-up was abandoned (not timed out after the step timeout, 1 s), and not faulted again
    assert not any("StepAbandoned" in f.message for f in res.faults)
    assert rt.component("dev").safe


def test_an_isolated_depth_node_rehearses_in_its_child_and_its_maps_equal_the_inline_ones(requests):
    """The real use: depth's warm() (its last new frame run again, the result thrown away) in the child, 1 ms before
    each step. Its depth maps are those the same estimator computes inline, step by step, without warm-ups."""
    from helpers_depth import ImageChainTap, isolated_depth_graph

    chain = ImageChainTap()
    reg = make_registry("teletouch.plugins.sensors.sim_digit", "teletouch.plugins.estimators.depth")
    # (25 Hz: a 40 ms period leaves the warm-up room beside the steps on a loaded machine; the budget is half of it)
    res, rt = run_yaml(isolated_depth_graph(25, "faults: {max_overruns: 0}"), reg, duration=2.0, taps=[chain])
    assert res.exit_code == EXIT_OK, res.message
    ops = [op for nid, op in requests if nid == "depth"]
    # (a warm-up is left out where the cycle would not leave it room: a loaded machine's slow cycle)
    assert ops.count("warm") >= ops.count("step") / 2 and ops.count("step") >= 40, ops
    assert chain.check_inline() >= 40 and max(float(o["max_depth"].value) for o in chain.outs) > 2e-4
