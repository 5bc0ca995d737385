"""Component.results(): what a run achieved, asked once after it (the main job's summary said only how fast each node
ran: a newcomer never saw the contact force, the live view having drawn only once the gripper had let go)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from teletouch import Component, Kind, Port, hookimpl
from teletouch.graph import load_graph
from teletouch.runtime import Runtime
from teletouch.testing import make_registry, run_yaml

ROOT = Path(__file__).resolve().parents[1]

GRAPH = """
clock: sim
duration: 0.1
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 2.0}}
  - {id: peak, plugin: s17-peak, rate: 100, inputs: {x: src.value}, params: {}}
"""


class Peak(Component):
    """Keeps the largest input; its results() say it, or raise, or give values JSON cannot hold."""

    name = "s17-peak"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "N", "a force")}
    mode = "ok"

    def configure(self) -> None:
        self.peak = 0.0
        self.closed = False

    def step(self, t, inputs):
        self.peak = max(self.peak, float(inputs.value("x", 0.0)))

    def results(self):
        assert not self.closed, "results() asked after close()"
        if Peak.mode == "raise":
            raise RuntimeError("boom")
        if Peak.mode == "odd":
            return {"peak_force_n": np.float32(self.peak), "frames": np.int64(3), "where": object(), "ok": True}
        return {"peak_force_n": self.peak}

    def close(self) -> None:
        self.closed = True


@hookimpl
def teletouch_components():
    return [Peak]


@pytest.fixture
def registry():
    Peak.mode = "ok"
    yield make_registry(sys.modules[__name__])
    Peak.mode = "ok"


def test_a_node_s_results_are_in_its_stats_and_the_json_summary(registry):
    res, _ = run_yaml(GRAPH, registry)
    assert res.status == "ok", res.ending
    by = {n.id: n for n in res.nodes}
    assert by["peak"].results == {"peak_force_n": 2.0}
    assert by["src"].results == {}   # (says nothing: the default)
    doc = json.loads(json.dumps(res.as_dict()))
    assert [n["results"] for n in doc["nodes"] if n["id"] == "peak"] == [{"peak_force_n": 2.0}]


def test_results_that_raise_are_a_logged_shutdown_fault_and_the_run_stays_ok(registry):
    Peak.mode = "raise"
    res, _ = run_yaml(GRAPH, registry)
    assert res.status == "ok" and res.exit_code == 0, res.ending
    assert {n.id: n.results for n in res.nodes}["peak"] == {}
    [f] = [f for f in res.faults if f.node == "peak"]
    assert f.kind == "shutdown" and f.action == "logged" and "results() raised RuntimeError: boom" in f.message


def test_results_values_are_numbers_or_text_that_json_can_hold(registry):
    Peak.mode = "odd"
    res, _ = run_yaml(GRAPH, registry)
    got = {n.id: n.results for n in res.nodes}["peak"]
    assert type(got["peak_force_n"]) is float and got["peak_force_n"] == 2.0
    assert type(got["frames"]) is int and got["frames"] == 3
    assert got["ok"] is True and got["where"].startswith("<object object")
    json.dumps(res.as_dict())


def test_the_main_job_s_controller_says_the_contact_it_felt_and_how_closely_the_follower_followed():
    rt = Runtime(load_graph(str(ROOT / "examples" / "paper-sim.yaml")), log=lambda m: None)
    res = rt.run()
    assert res.status == "ok", res.ending
    r = {n.id: n.results for n in res.nodes}["controller"]
    # the simulated hand closes on the object and holds: about 1.2 N sensed for about 5 s (the graph's intent)
    assert 0.5 < r["peak_force_n"] < 3.0 and 0.5 < r["peak_feedback_n"] <= r["peak_force_n"] * 1.2
    assert 2.0 < r["contact_time_s"] < 8.0
    assert 0.0 < r["mean_position_error_m"] <= r["max_position_error_m"] < 2e-3
    assert all(math.isfinite(v) for v in r.values())


def test_teletouch_run_prints_the_results_below_the_summary_in_a_person_s_units(capsys):
    from teletouch.cli import main

    assert main(["run", str(ROOT / "examples" / "paper-sim.yaml"), "--duration", "4", "--json"]) == 0
    out, err = capsys.readouterr()
    tail = err[err.index("results:"):].splitlines()
    assert tail[1].split()[0] == "gripper" and "true_peak_force=" in tail[1] and tail[1].rstrip().endswith("N")
    ctl = tail[2].split()
    assert ctl[0] == "controller" and ctl[1].startswith("peak_force=") and ctl[1].endswith("N")
    assert any(w.startswith("mean_position_error=") and w.endswith("mm") for w in ctl)
    assert tail[3].startswith("teletouch: ok")
    doc = json.loads(out)
    ctl_json = [n["results"] for n in doc["nodes"] if n["id"] == "controller"][0]
    assert ctl_json["peak_force_n"] == pytest.approx(float(ctl[1][len("peak_force="):-1]), abs=0.006)


def test_a_quiet_run_prints_no_results(capsys):
    from teletouch.cli import main

    assert main(["run", str(ROOT / "examples" / "paper-sim.yaml"), "--duration", "0.5", "--quiet"]) == 0
    assert "results:" not in capsys.readouterr().err


def test_contact_time_counts_only_fresh_estimates():
    """A review found: the held estimate of a stale force kept counting as contact (0.5 s of 1 N, then stale until
    2 s: contact_time 1.999 s). Here stale until 1 s (fault_after_lost ends the run 0.5 s after the loss)."""
    from teletouch.plugins.controllers.position_force import PositionForce
    from teletouch.testing import Harness

    with Harness(PositionForce, {}) as h:
        t = 0.0
        while t < 1.0:
            force = {"force": 1.0} if t < 0.5 else {}
            h.step(t, leader_opening=0.02, follower_opening=0.02, **force)
            t = round(t + 0.001, 6)
        r = h.comp.results()
    assert r["peak_force_n"] == pytest.approx(1.0)
    assert 0.45 < r["contact_time_s"] < 0.65, r   # fresh for stale_after (0.1 s) after the last estimate at most


def test_position_position_says_no_sensed_force():
    """Its force is its PD coupling's: as peak_force it read 0.53 N while the object was squeezed with 5.3 N."""
    rt = Runtime(load_graph(str(ROOT / "examples" / "paper-sim.yaml"), sets=["controller.plugin=position-position"],
                            duration=3.0), log=lambda m: None)
    res = rt.run()
    r = {n.id: n.results for n in res.nodes}["controller"]
    assert "peak_force_n" not in r and "contact_time_s" not in r and r["peak_feedback_n"] > 0.0, r
    assert "mean_position_error_m" in r


NAN_PLUGIN = '''
import math
from teletouch import Component, Kind, hookimpl


class NanResults(Component):
    name = "nan-results"
    kind = Kind.ESTIMATOR

    def step(self, t, inputs):
        return None

    def results(self):
        return {"peak_force_n": math.nan, "ratio": math.inf, "frames": 3}


@hookimpl
def teletouch_components():
    return [NanResults]
'''


def test_teletouch_run_json_is_strict_json_when_a_plugin_s_results_are_not_finite(tmp_path, plugin_module, capsys):
    # before: json.dumps wrote NaN and Infinity, which no strict JSON reader (jq, JSON.parse) takes
    plugin_module("tt_nan_results", NAN_PLUGIN)
    graph = tmp_path / "g.yaml"
    graph.write_text("clock: sim\nduration: 0.05\nnodes:\n  - {id: est, plugin: nan-results, rate: 100}\n")
    from teletouch.cli import main

    assert main(["run", str(graph), "--quiet", "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()[-1]
    doc = json.loads(out, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    assert [n["results"] for n in doc["nodes"] if n["id"] == "est"] == [{"peak_force_n": None, "ratio": None,
                                                                          "frames": 3}]
