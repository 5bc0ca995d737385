"""`isolate: process`: a node runs in a child process under the wall clock, with the same ports, faults and clock."""

from __future__ import annotations

import os

import pytest

from teletouch.errors import GraphValidationError
from teletouch.runtime import EXIT_FAULT, EXIT_OK
from teletouch.testing import load_text, make_registry, run_yaml

GRAPH = """
clock: wall
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: ramp, amplitude: 1.0}}
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 5ms}, inputs: {x: src.value}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 500, inputs: {command: est.y}}
"""


@pytest.fixture(scope="module")
def reg():
    return make_registry()


def test_isolated_node_runs_in_its_own_process_on_the_same_clock(reg):
    seen = []
    res, rt = run_yaml(GRAPH, reg, duration=1.0, taps=[lambda n, t, o: n == "est" and seen.append((t, o))])
    assert res.exit_code == EXIT_OK, res.message
    pids = {o["pid"] for _, o in seen}
    assert len(pids) == 1 and os.getpid() not in pids
    assert len(seen) >= 15
    # the echo of a ramp (value = t) shows both processes read the same graph clock
    for t, o in seen[5:]:
        assert 0.0 <= t - o["y"] <= 0.05
    assert rt.latest("dev", "state").value == pytest.approx(seen[-1][1]["y"], abs=0.05)


def test_exception_in_child_is_a_fault_with_its_origin(reg):
    res, rt = run_yaml(GRAPH.replace("burn: 5ms}", "burn: 5ms, fail_at: 0.3}"), reg, duration=2.0)
    assert res.exit_code == EXIT_FAULT
    assert "in isolated process: ValueError: mock-burn failure" in res.message and "mock.py:" in res.message
    assert rt.component("dev").safe_calls >= 1


def test_request_stop_from_child(reg):
    res, _ = run_yaml(GRAPH.replace("burn: 5ms}", "burn: 5ms, stop_at: 0.2}"), reg, duration=5.0)
    assert res.status == "stopped" and "mock-burn stop" in res.message


def test_child_that_dies_is_a_fault(reg):
    text = GRAPH.replace("plugin: mock-burn, rate: 30, params: {burn: 5ms}",
                         "plugin: mock-burn, rate: 30, params: {burn: 5ms}")
    from teletouch.runtime import Runtime

    rt = Runtime(load_text(text, reg), log=lambda m: None)
    proxy = rt.component("est")
    killed = []

    def kill_after_some(node, t, out):
        if node == "dev" and t > 0.3 and not killed:
            proxy._proc.kill()
            killed.append(t)

    rt.add_tap(kill_after_some)
    res = rt.run(3.0)
    assert res.exit_code == EXIT_FAULT and "isolated process died" in res.message


def test_sim_clock_runs_isolated_nodes_inline(reg):
    seen = []
    res, _ = run_yaml(GRAPH.replace("clock: wall", "clock: sim"), reg, duration=0.5,
                      taps=[lambda n, t, o: n == "est" and seen.append(o["pid"])])
    assert res.exit_code == EXIT_OK and set(seen) == {os.getpid()}


def test_devices_cannot_be_isolated(reg):
    with pytest.raises(GraphValidationError, match="isolate: process is for sensors"):
        load_text(GRAPH.replace("inputs: {command: est.y}}", "inputs: {command: est.y}, isolate: process}"), reg)
    with pytest.raises(GraphValidationError, match="isolate: expected 'none' or 'process'"):
        load_text(GRAPH.replace("isolate: process", "isolate: thread"), reg)
