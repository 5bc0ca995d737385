"""A node learns that a node feeding it was disabled by a fault: ``Context.disabled_upstream()``, and the press routine
aborts on it.

When a fault disabled a node (degrade or stop), only the devices wired straight to it were made safe; a node further
down saw only its own inputs, and a node in between (a filter) went on publishing its last value with fresh stamps.
The press routine then recorded (depth, force) samples on a frozen depth: `teletouch run` ended with its
``samples_csv`` unmarked, and under `teletouch calibrate force` too the leader went on pressing on stale data to the
end. Now each node's Context lists the nodes feeding it (through the wiring, directly or through other nodes) that a
fault has disabled, and the routine aborts as soon as one is: zero force at once, ``samples_csv`` marked partial, the
node faults naming the lost node.

The press graphs are test_force_calibration's fast one (1 cycle, 13 samples at t = 3.4 ... 10.8 s, done at 11.8 s)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_force_calibration import graph  # noqa: E402
from test_force_calibrate_faults import _graph  # noqa: E402

from teletouch import Component, Kind, Port, hookimpl  # noqa: E402
from teletouch.cli import main  # noqa: E402
from teletouch.component import Context  # noqa: E402
from teletouch.plugins.estimators.poly_force import read_pairs_csv  # noqa: E402
from teletouch.runtime import Runtime  # noqa: E402
from teletouch.testing import Harness, load_text, make_registry, run_yaml, safe_states  # noqa: E402


class FeederWatch(Component):
    """Says which of the nodes feeding it a fault has disabled, and in which process it runs."""

    name = "s17-feeder-watch"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "any", "anything", required=False)}
    outputs = {"lost": Port("str", (), "", "Context.disabled_upstream(), joined by ','"),
               "pid": Port("int64", (), "", "process id that ran the step")}
    default_rate = 100.0

    def step(self, t, inputs):
        return {"lost": ",".join(self.ctx.disabled_upstream()), "pid": os.getpid()}


@hookimpl
def teletouch_components():
    return [FeederWatch]


def _reg():
    return make_registry(sys.modules[__name__], "teletouch.plugins.devices.sim_omega7",
                         "teletouch.plugins.estimators.force_calibration")


def _watched(text: str, duration: float) -> tuple[list[tuple[float, str, int]], object]:
    seen: list[tuple[float, str, int]] = []
    result, _ = run_yaml(text, _reg(), duration=duration,
                         taps=[lambda n, t, o: n == "watch" and seen.append((t, o["lost"], o["pid"]))])
    return seen, result


# ------------------------------------------------------------------------------------------- Context.disabled_upstream
CHAIN = """
clock: {clock}
nodes:
  - {{id: src, plugin: mock-sensor, rate: 100, on_fault: degrade, params: {{signal: constant, fail_at: {fail}}}}}
  - {{id: mid, plugin: mock-gain, rate: 100, inputs: {{x: src.value}}}}
  - {{id: watch, plugin: s17-feeder-watch, rate: {rate}, inputs: {{x: mid.y}}{isolate}}}
  - {{id: other, plugin: mock-sensor, rate: 100, on_fault: degrade, params: {{signal: constant, fail_at: 0.2}}}}
  - {{id: side, plugin: mock-gain, rate: 100, inputs: {{x: other.value}}}}
"""


def test_a_node_two_hops_upstream_disabled_by_a_fault_is_listed_an_unrelated_one_is_not():
    seen, result = _watched(CHAIN.format(clock="sim", fail=0.5, rate=100, isolate=""), 1.0)
    assert result.status == "degraded", result.message   # other at 0.2 s, src at 0.5 s
    assert [f.node for f in result.faults] == ["other", "src"]
    assert len(seen) == 101
    # 'mid' goes on publishing src's last value with fresh stamps; the watcher learns of src's fault at once (src steps
    # before it at 0.5 s), and never of other's, which does not feed it
    assert {lost for t, lost, _ in seen if t < 0.5} == {""}, seen[:60]
    assert {lost for t, lost, _ in seen if t >= 0.5} == {"src"}, seen[45:]


def test_outside_a_graph_no_node_is_disabled_upstream():
    assert Context().disabled_upstream() == []


def test_the_harness_gives_the_disabled_upstream_a_test_sets():
    with Harness(FeederWatch) as h:
        assert h.step(0.0)["lost"] == ""
        h.disabled_upstream = ["depth", "filter"]
        assert h.step(0.01)["lost"] == "depth,filter"
        assert h.ctx.disabled_upstream() == ["depth", "filter"]


def test_an_isolated_node_learns_it_in_its_process():
    seen, result = _watched(CHAIN.format(clock="wall", fail=0.3, rate=20, isolate=", isolate: process"), 1.0)
    assert result.status == "degraded", result.message
    assert seen and {pid for _, _, pid in seen} != {os.getpid()}   # it ran in its own process
    assert {lost for t, lost, _ in seen if t < 0.25} == {""}, seen
    late = [lost for t, lost, _ in seen if t > 0.4]
    assert late and set(late) == {"src"}, seen


# ------------------------------------------------------------------------------------------- the press routine
LOST = "node 'lost', which feeds the press routine, was disabled by a fault: its samples would be stale"


def _press(tmp_path: Path, fail_at: float) -> tuple[str, Path]:
    """The press graph whose max depth comes from the rig through 'lost' (faults at ``fail_at``, degrade) and 'hold',
    which goes on publishing lost's last value with fresh stamps."""
    csv = tmp_path / "own.csv"
    g = graph(routine={"samples_csv": str(csv)}).replace("max_depth: rig.indentation", "max_depth: hold.y") + f"""
  - id: lost
    plugin: mock-burn
    rate: 1000
    on_fault: degrade
    params: {{burn: 0, fail_at: {fail_at}}}
    inputs: {{x: rig.indentation}}
  - id: hold
    plugin: mock-gain
    rate: 1000
    inputs: {{x: lost.y}}
"""
    assert "max_depth: hold.y" in g
    path = tmp_path / "press.yaml"
    path.write_text(g)
    return str(path), csv


def test_the_press_routine_aborts_when_the_node_feeding_its_depth_is_disabled(tmp_path):
    path, csv = _press(tmp_path, 6.0)
    result, rt = run_yaml(Path(path).read_text(), _reg())
    r = rt.component("routine")
    # before: the routine recorded the frozen depth to the end (13 samples) and the run ended "degraded"
    assert r.state == "aborted" and r.abort_reason == LOST, (r.state, r.abort_reason)
    t_abort = r.events[-1][0]
    assert r.events[-1][1] == "aborted" and 6.0 <= t_abort <= 6.002, r.events[-3:]
    assert result.status == "fault" and result.message.startswith("node 'routine' exception: ComponentFault: node "
                                                                  f"'routine': press routine aborted: {LOST} ("), \
        result.message
    assert [f.node for f in result.faults] == ["lost", "routine"]
    assert r.samples and all(s["time_s"] < 6.0 for s in r.samples)   # none recorded on the frozen depth
    rows = read_pairs_csv(csv)
    assert rows["partial"] == f"press routine aborted: {LOST}; {len(r.samples)} of 13 planned steps recorded"
    # the leader: safe (zero force) at once
    leader = rt.component("leader")
    assert safe_states(rt)["leader"][0] <= t_abort + 0.002
    assert leader.safe and not leader.f_applied.any() and leader.status()["force_norm_n"] == 0.0


def test_teletouch_run_of_a_press_graph_whose_depth_feeder_is_lost_exits_3_with_its_samples_marked(tmp_path, capsys):
    path, csv = _press(tmp_path, 6.0)
    capsys.readouterr()
    rc = main(["run", path, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 3, err[-3000:]   # before: 3 as well ("degraded"), with samples_csv unmarked
    assert LOST in err, err[-3000:]
    partial = read_pairs_csv(csv)["partial"]
    assert partial is not None and partial.startswith(f"press routine aborted: {LOST}; "), partial


def test_calibrate_force_stops_pressing_when_a_node_it_reads_is_disabled(tmp_path, capsys):
    out = tmp_path / "x.force.json"
    capsys.readouterr()
    rc = main(["calibrate", "force", "--graph", _graph(tmp_path, 6.0, read=True), "-o", str(out), "--quiet"])
    err = capsys.readouterr().err
    spare = "node 'spare', which feeds the press routine, was disabled by a fault: its samples would be stale"
    assert rc == 3 and not out.exists(), err[-3000:]
    # before: the routine pressed on to the end and only the command found the fault afterwards
    assert f"press routine did not finish (routine state 'aborted', run fault: {spare}); no calibration written" \
        in err, err[-3000:]
    rows = read_pairs_csv(tmp_path / "x.samples.csv")
    assert rows["partial"] == f"press routine aborted: {spare}; 5 of 13 planned steps recorded", rows["partial"]
    assert len(rows["depth_m"]) == 5


def test_a_fault_upstream_in_the_last_retract_ends_the_routine_done_at_once(tmp_path):
    # every sample is in (the last at 10.8 s): the run is complete; the retract on what may be stale data is cut short
    result, rt = run_yaml(Path(_graph(tmp_path, 11.0, read=True)).read_text(), _reg())
    r = rt.component("routine")
    assert r.state == "done" and len(r.samples) == 13, (r.state, r.abort_reason)
    assert 11.0 <= r.events[-1][0] <= 11.002, r.events[-3:]   # before: done at 11.8 s, retracting on
    assert result.status == "degraded" and "press routine done: 13 samples in 1 cycle(s)" in result.message
    assert rt.component("leader").safe and safe_states(rt)["leader"][0] <= 11.002


def test_no_sample_is_stored_once_a_feeder_is_known_lost(tmp_path):
    """A fault that lands while the routine's step runs (another rate group under the wall clock): the check at the top
    of the step saw none, the one before the sample is stored does. Here the Context says so only on its second call in
    a step from t = 6 s on."""
    rt = Runtime(load_text(graph(), _reg()), log=lambda m: None)
    r = rt.component("routine")
    calls: dict[float, int] = {}

    def late_fault() -> list[str]:
        t = rt.now()
        calls[t] = calls.get(t, 0) + 1
        return ["ghost"] if t >= 6.0 and calls[t] >= 2 else []

    r.ctx.disabled_upstream = late_fault
    result = rt.run(60.0)
    assert r.state == "aborted", (r.state, len(r.samples))   # before: done, 13 samples
    assert r.abort_reason == "node 'ghost', which feeds the press routine, was disabled by a fault: its samples " \
                             "would be stale"
    assert r.samples and all(s["time_s"] < 6.0 for s in r.samples)
    assert 6.0 <= r.events[-1][0] < 6.5 and result.status == "fault"
