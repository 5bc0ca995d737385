"""Under the wall clock a fault that comes after a node asked the run to stop (a step of another rate group that was
running then raised) was hidden: the run's status stayed "stopped" with exit 0 though its faults listed one whose
action was to stop the run, while a node disabled (degrade) at that moment made it "degraded" (exit 3). Such a fault
is the run's result now."""

from __future__ import annotations

import sys
import time

from teletouch import Component, Kind, Params, Port, hookimpl
from teletouch.runtime import EXIT_FAULT, EXIT_OK, Runtime
from teletouch.testing import load_text, make_registry, run_yaml


class Stopper(Component):
    name = "s16-stopper"
    kind = Kind.CONTROLLER
    outputs = {"y": Port("float64", (), "")}

    def step(self, t, inputs):
        if t >= 0.3:
            self.ctx.request_stop("the routine is done")
        return {"y": t}


class Breaker(Component):
    name = "s16-breaker"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "")}
    outputs = {"z": Port("float64", (), "")}

    class Params(Params):
        at: float = 0.25

    def step(self, t, inputs):
        if t >= self.params.at:
            while self.ctx.now() < 0.4:   # (still in its step when the stopper asks the run to stop)
                time.sleep(0.005)
            raise RuntimeError("broke as the run stopped")
        return {"z": 0.0}


@hookimpl
def teletouch_components():
    return [Stopper, Breaker]


def _registry():
    return make_registry(sys.modules[__name__])


def _graph(policy: str, at: float) -> str:
    return f"""
clock: wall
nodes:
  - {{id: stopper, plugin: s16-stopper, rate: 100}}
  - {{id: breaker, plugin: s16-breaker, rate: 20, params: {{at: {at}}}, inputs: {{x: stopper.y}}, on_fault: {policy}}}
"""


def test_a_fault_as_the_run_stops_is_the_run_s_result():
    res, _ = run_yaml(_graph("stop", 0.25), _registry(), duration=5.0)
    assert [f.node for f in res.faults] == ["breaker"]
    assert (res.status, res.exit_code) == ("fault", EXIT_FAULT), res.message
    assert "node 'breaker' exception: RuntimeError: broke as the run stopped" in res.message
    assert "the routine is done" in res.message   # what had asked the run to stop


def test_a_stop_without_a_fault_is_still_ok():
    res, _ = run_yaml(_graph("stop", 5.0), _registry(), duration=5.0)
    assert (res.status, res.exit_code, res.faults) == ("stopped", EXIT_OK, []), res.message


def test_a_node_disabled_as_the_run_stops_is_still_degraded():
    res, _ = run_yaml(_graph("degrade", 0.25), _registry(), duration=5.0)
    assert (res.status, res.exit_code) == ("degraded", EXIT_FAULT), res.message


def test_a_progress_callback_that_fails_as_the_run_stops_is_named_as_such():
    # a second review found "node '' progress: ..." (the progress callback has no node)
    def progress(rt, t):
        rt.request_stop("the notebook's stop button")
        raise ValueError("the plot failed")

    text = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
"""
    rt = Runtime(load_text(text, _registry()), log=lambda m: None)
    res = rt.run(100.0, progress=progress, progress_interval=0.0)
    assert (res.status, res.exit_code) == ("fault", EXIT_FAULT), res.message
    assert res.message.startswith("progress: the progress callback raised ValueError: the plot failed"), res.message
    assert "(as the run stopped: the notebook's stop button)" in res.message
