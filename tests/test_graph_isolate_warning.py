"""Validation warns (does not fail) when a node with `isolate: process` shares its rate with a device node under the
wall clock: the nodes of one rate run in one thread, so each isolated step holds up the device's steps until the
child process answers (docs/graphs.md: give an isolated node a rate of its own). `teletouch validate` prints the
warning and exits 0; `teletouch run` prints it before it starts."""

from __future__ import annotations

import pytest

import teletouch.registry as registry
from teletouch.cli import main
from teletouch.graph import load_graph, load_graph_text
from teletouch.testing import make_registry

SHARED = """\
clock: wall
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: est, plugin: mock-burn, rate: 100, params: {burn: 0ms}, inputs: {x: src.value},
     isolate: process}
  - {id: leader, plugin: mock-device, rate: 100, inputs: {command: est.y}}
  - {id: follower, plugin: mock-device, rate: 100}
  - {id: slow, plugin: mock-device, rate: 50}
"""


def test_an_isolated_node_at_the_rate_of_devices_is_a_warning_naming_file_line_nodes_and_rate():
    spec = load_graph_text(SHARED, "lab.yaml", registry=make_registry())
    assert len(spec.warnings) == 1, spec.warnings
    w = spec.warnings[0]
    assert w.startswith("lab.yaml:4: node 'est' (isolate: process) shares its rate, 100 Hz, with device nodes "
                        "'leader', 'follower': "), w
    assert "'slow'" not in w and "'src'" not in w     # another rate; not a device
    assert "under the wall clock" in w
    assert w.endswith("give node 'est' a rate of its own, one no device uses (e.g. rate: 99)"), w


@pytest.mark.parametrize("change", [
    ("est", "rate: 100, params", "rate: 99, params"),                 # a rate of its own
    ("no device", "rate: 100, inputs: {command", "rate: 50, inputs: {command"),
    ("not isolated", "\n     isolate: process", ""),
    ("sim clock", "clock: wall", "clock: sim"),                        # isolation does not apply: runs inline
])
def test_no_warning_when_no_device_shares_the_isolated_nodes_rate(change):
    _, old, new = change
    text = SHARED.replace(old, new)
    if change[0] == "no device":
        text = text.replace("{id: follower, plugin: mock-device, rate: 100}", "{id: follower, plugin: mock-device, "
                                                                              "rate: 50}")
    assert text != SHARED
    spec = load_graph_text(text, "lab.yaml", registry=make_registry())
    assert spec.warnings == []


def test_the_clock_given_on_the_command_line_decides():
    sim = SHARED.replace("clock: wall", "clock: sim")
    assert load_graph_text(sim, "lab.yaml", registry=make_registry(), clock="wall").warnings
    assert not load_graph_text(SHARED, "lab.yaml", registry=make_registry(), clock="sim").warnings


def test_one_warning_per_isolated_node_and_a_device_named_only_at_its_own_rate():
    text = SHARED + "  - {id: est2, plugin: mock-burn, rate: 50, params: {burn: 0ms}, isolate: process}\n"
    spec = load_graph_text(text, "lab.yaml", registry=make_registry())
    assert [w.split(": node ")[1].split(" (")[0] for w in spec.warnings] == ["'est'", "'est2'"], spec.warnings
    assert "shares its rate, 50 Hz, with device node 'slow': " in spec.warnings[1]
    assert "(e.g. rate: 49)" in spec.warnings[1]


def test_validate_prints_the_warning_and_exits_0(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(registry, "_default", None)   # the CLI's registry loaded afresh (with the mock plugin)
    graph = tmp_path / "lab.yaml"
    graph.write_text(SHARED)
    assert main(["validate", str(graph)]) == 0
    out, err = capsys.readouterr()
    assert f"teletouch: warning: {graph}:4: node 'est' (isolate: process) shares its rate, 100 Hz, with device " \
           f"nodes 'leader', 'follower'" in err, err
    assert f"{graph}: OK (5 nodes" in out and out.rstrip().endswith("clock wall; 1 warning)"), out
    # the same graph with a rate of its own for est: no warning
    graph.write_text(SHARED.replace("rate: 100, params", "rate: 99, params"))
    assert main(["validate", str(graph)]) == 0
    out, err = capsys.readouterr()
    assert "warning" not in err and "warning" not in out, (out, err)
    assert load_graph(graph).warnings == []


def test_run_prints_the_warning_before_it_starts(tmp_path, capsys, monkeypatch):
    """`teletouch run` says it on stderr first, then runs as before (here a run that src stops at t = 0)."""
    monkeypatch.setattr(registry, "_default", None)
    graph = tmp_path / "lab.yaml"
    graph.write_text(SHARED.replace("{id: src, plugin: mock-sensor, rate: 100}",
                                    "{id: src, plugin: mock-sensor, rate: 100, params: {stop_at: 0}}"))
    assert main(["run", str(graph), "--quiet", "--duration", "1"]) == 0
    _, err = capsys.readouterr()
    first = err.splitlines()[0]
    assert first.startswith(f"teletouch: warning: {graph}:4: node 'est' (isolate: process) shares its rate"), err
