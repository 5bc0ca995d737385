"""An inline node whose step runs past the watchdog's bound is faulted (`timeout`) while that step still runs (wall
clock). When the step finally returns, its outputs are dropped: nothing of a node is published after its fault.

Before, the late step's outputs were written anyway, so under `degrade` the nodes downstream (still running at their
own rates) received a sample from a node already reported disabled, and a recording tap saw it too."""

from __future__ import annotations

import sys

import pytest

from teletouch.component import Component, Kind, Port
from teletouch.hookspecs import hookimpl
from teletouch.runtime import EXIT_FAULT
from teletouch.testing import make_registry, run_yaml

HANG_AT = 0.3   # est's step that begins at t >= 0.3 s sleeps HANG_FOR s (inline: nothing can cut it short)


class Probe(Component):
    """Records every sample it reads on ``x``: (graph time of its step, the sample's stamp)."""

    name = "s13-probe"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "any", "the watched output")}
    default_rate = 100.0

    def configure(self):
        self.seen: list[tuple[float, float]] = []

    def step(self, t, inputs):
        s = inputs["x"]
        if s is not None:
            self.seen.append((t, s.stamp))
        return None


@hookimpl
def teletouch_components():
    return [Probe]


# est (inline) hangs 0.8 s at t = 0.3 s in the rate group of device `dev`: the watchdog faults est (timeout) at about
# 0.4 s, then `arm` (wired from est) as upstream and `dev` (its rate group waits) as stall. `probe` and `arm` run at
# another rate: probe goes on reading est.y for the whole run, past the end of est's late step (about 1.1 s).
GRAPH_DEGRADE = f"""
clock: wall
faults: {{watchdog: 0.1, on_fault: degrade}}
nodes:
  - {{id: est, plugin: mock-burn, rate: 50, params: {{burn: 0ms, hang_at: {HANG_AT}, hang_for: 0.8}}}}
  - {{id: dev, plugin: mock-device, rate: 50}}
  - {{id: probe, plugin: s13-probe, rate: 100, inputs: {{x: est.y}}}}
  - {{id: arm, plugin: mock-device, rate: 100, params: {{safe_value: 0.0}}, inputs: {{command: est.y}}}}
"""

# the same with each node's own `on_fault: degrade` (the graph's policy stays `stop`)
GRAPH_NODE_DEGRADE = f"""
clock: wall
faults: {{watchdog: 0.1}}
nodes:
  - {{id: est, plugin: mock-burn, rate: 50, params: {{burn: 0ms, hang_at: {HANG_AT}, hang_for: 0.8}},
     on_fault: degrade}}
  - {{id: dev, plugin: mock-device, rate: 50, on_fault: degrade}}
  - {{id: probe, plugin: s13-probe, rate: 100, inputs: {{x: est.y}}}}
  - {{id: arm, plugin: mock-device, rate: 100, params: {{safe_value: 0.0}}, inputs: {{command: est.y}},
     on_fault: degrade}}
"""


@pytest.mark.parametrize("text", [GRAPH_DEGRADE, GRAPH_NODE_DEGRADE], ids=["graph-degrade", "node-degrade"])
def test_under_degrade_the_late_step_of_a_node_the_watchdog_faulted_publishes_nothing(text):
    taps: list[tuple[str, float]] = []
    res, rt = run_yaml(text, make_registry(sys.modules[__name__]), duration=2.0,
                       taps=[lambda n, t, o: taps.append((n, t))])
    # the run's result and faults as before: est's timeout, then the devices that depend on it, made safe
    assert res.status == "degraded" and res.exit_code == EXIT_FAULT, (res.message, [f.line() for f in res.faults])
    assert [(f.node, f.kind, f.action) for f in res.faults] == [
        ("est", "timeout", "degrade"), ("arm", "upstream", "degrade"), ("dev", "stall", "degrade")], \
        [f.line() for f in res.faults]
    assert "(mock-burn) step did not return within 0.1 s" in res.faults[0].message
    assert "input 'command' comes from node 'est', which was disabled by a fault" in res.faults[1].message
    assert "waits for the step of node 'est' (mock-burn)" in res.faults[2].message
    arm, dev = rt.component("arm"), rt.component("dev")
    assert arm.safe and arm.command == 0.0 and arm.safe_calls >= 1    # zero command on the downstream device
    assert dev.safe and dev.safe_calls >= 1
    fault_t = res.faults[0].time
    assert HANG_AT < fault_t < HANG_AT + 0.5, fault_t
    stats = {n.id: n for n in res.nodes}
    assert stats["est"].faulted and stats["arm"].faulted and stats["dev"].faulted and not stats["probe"].faulted
    # the late step did return within the run (so its outputs had the chance to be written) and probe was stepped
    # after that: the checks below are not vacuous
    assert stats["est"].max_step_s > 0.6, stats["est"].max_step_s
    seen = rt.component("probe").seen
    assert any(t > HANG_AT + 0.8 + 0.2 for t, _ in seen), seen[-3:]
    # nothing of est after its fault: the last sample of est.y is from a step before the hang, probe never read a
    # sample stamped at or after the hang's start, and no tap (a recording) got est's late outputs
    latest = rt.latest("est", "y")
    assert latest is not None and latest.stamp < HANG_AT, latest.stamp
    late = [(t, stamp) for t, stamp in seen if stamp >= HANG_AT]
    assert not late, late[:3]
    assert max(t for n, t in taps if n == "est") < HANG_AT
    # probe went on reading the last sample from before the fault (it handles the stale input itself)
    assert {stamp for t, stamp in seen if t > fault_t} == {latest.stamp}


STOP = f"""
clock: wall
faults: {{watchdog: 0.1}}
nodes:
  - {{id: est, plugin: mock-burn, rate: 50, params: {{burn: 0ms, hang_at: {HANG_AT}, hang_for: 0.4}}}}
  - {{id: dev, plugin: mock-device, rate: 50, params: {{safe_value: 0.0}}}}
"""


def test_under_stop_the_late_step_of_the_node_that_stopped_the_run_is_not_recorded():
    """Under `stop` the run ends at est's timeout; its step returns during the shutdown (its thread is joined for up
    to 1 s): its outputs are dropped there too, a recording never shows them."""
    taps: list[tuple[str, float]] = []
    res, rt = run_yaml(STOP, make_registry(), duration=2.0, taps=[lambda n, t, o: taps.append((n, t))])
    assert res.exit_code == EXIT_FAULT
    assert res.message.startswith("node 'est' timeout: (mock-burn) step did not return within 0.1 s"), res.message
    assert [(f.node, f.kind) for f in res.faults] == [("est", "timeout"), ("dev", "stall")]
    assert rt.component("dev").safe and rt.component("dev").command == 0.0
    stats = {n.id: n for n in res.nodes}
    assert stats["est"].max_step_s > 0.3, stats["est"].max_step_s    # the late step returned before the end
    assert rt.latest("est", "y").stamp < HANG_AT
    assert max(t for n, t in taps if n == "est") < HANG_AT
