"""Graph errors a newcomer met: an error inside a nested parameter given by --set names the --set (the file's line only
where the bad value came from the file), and a malformed wire is reported once, without the "not wired" it leads to."""

from __future__ import annotations

from pathlib import Path

import pytest

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = REPO / "examples" / "paper-sim.yaml"


def _errors(path, sets=()) -> list[str]:
    with pytest.raises(GraphValidationError) as exc:
        load_graph(path, sets=sets)
    return [str(e) for e in exc.value.errors]


# --- 2. a nested --set's error names the --set -----------------------------------------------------------------------
@pytest.mark.parametrize("item, value, why", [
    ("leader.intent.type=close-and-hodl", "'close-and-hodl'", "unknown intent type 'close-and-hodl'"),
    ("leader.intent.start_opening=20", "20", "start_opening (20 m) is beyond any gripper's opening"),
    ("leader.params.intent.start_opening=20", "20", "start_opening (20 m) is beyond any gripper's opening"),
    ("leader.intent.sped=5mm/s", "'5mm/s'", "intent 'close-and-hold' has no field 'sped'"),
])
def test_an_error_in_a_nested_param_given_by_set_names_the_set(item, value, why):
    # before: "examples/paper-sim.yaml:20: node 'leader': param 'intent' = {'type': ..., 'release': True}: ..."
    (line,) = _errors(PAPER_SIM, [item])
    path = item.split("=")[0].split(".", 1)[1].removeprefix("params.")
    assert line.startswith(f"--set {item}: node 'leader': param '{path}' = {value}: "), line
    assert why in line and "paper-sim.yaml" not in line and "'hold_time'" not in line, line   # (not the whole intent)
    assert "Value error, " not in line


def test_the_bad_one_of_several_sets_in_one_param_is_named(tmp_path):
    sets = ["leader.intent.speed=4mm/s", "leader.intent.target_opening=8", "leader.intent.hold_time=2s"]
    (line,) = _errors(PAPER_SIM, sets)
    assert line.startswith("--set leader.intent.target_opening=8: node 'leader': param 'intent.target_opening' = 8: ")


def test_an_error_the_file_made_stays_at_its_line_beside_a_set_in_the_same_param(tmp_path):
    graph = tmp_path / "g.yaml"
    graph.write_text(PAPER_SIM.read_text().replace("type: close-and-hold", "type: close-and-hodl"))
    (line,) = _errors(graph, ["leader.intent.speed=4mm/s"])
    assert line.startswith(f"{graph}:20: node 'leader': param 'intent' = "), line
    assert "unknown intent type 'close-and-hodl'" in line and "--set" not in line


def test_a_nested_set_that_replaces_a_name_is_laid_on_the_set(tmp_path):
    # the file names the intent ('hold'); a --set inside it starts a mapping without 'type': the --set's doing
    graph = tmp_path / "g.yaml"
    graph.write_text("clock: sim\nnodes:\n  - {id: leader, plugin: sim-omega7, rate: 1kHz, params: {intent: hold}}\n")
    (line,) = _errors(graph, ["leader.intent.opening=10mm"])
    assert line.startswith("--set leader.intent.opening=10mm: node 'leader': param 'intent.opening' = '10mm': "), line


def test_other_set_errors_are_led_by_the_set():
    (line,) = _errors(PAPER_SIM, ["griper.max_speed=0.01"])
    assert line == "--set griper.max_speed=0.01: no node 'griper' (did you mean 'gripper'?)"


# --- 4. a malformed wire: the root cause only ------------------------------------------------------------------------
@pytest.mark.parametrize("wire", ["force", "{from: force}", "{from: force.force, max_ag: 0.1}", "force.force.x"])
def test_a_malformed_wire_is_reported_once_not_also_as_an_unwired_input(tmp_path, wire):
    # before: a second error blamed the included file: "paper-sim.yaml:41: ... required input 'force' ... not wired"
    graph = tmp_path / "over.yaml"
    graph.write_text(f"include: {PAPER_SIM}\nnodes:\n  - id: controller\n    inputs: {{force: {wire}}}\n")
    (line,) = _errors(graph)
    assert line.startswith(f"{graph}:4: node 'controller': input 'force': "), line
    assert "not wired" not in line


def test_an_unwired_required_input_is_still_reported(tmp_path):
    graph = tmp_path / "over.yaml"
    graph.write_text(f"include: {PAPER_SIM}\nnodes:\n  - id: controller\n    inputs: {{force: null}}\n")
    (line,) = _errors(graph)
    assert "required input 'force' (float64[scalar] N) of position-force is not wired" in line
