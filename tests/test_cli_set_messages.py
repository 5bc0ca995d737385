"""A --set inside a parameter that the parameter's value before it cannot take says what to write. The simulated
Omega.7's intent is a name ('hold', its default) or a mapping with ``type``: ``--set leader.intent.opening=10mm`` on a
named intent made the intent ``{opening: 10mm}`` alone, and the user read "intent needs 'type' (one of ...), got None"
without learning that the type goes with it (``--set leader.intent.type=hold``); ``--set leader.intent.type=hold`` on
a close-and-hold intent kept its other fields and listed six "Extra inputs are not permitted" without saying that the
whole intent is given in one --set."""

from __future__ import annotations

from pathlib import Path

import pytest

from teletouch.cli import main

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = str(REPO / "examples" / "paper-sim.yaml")

DEFAULT_INTENT = """
clock: sim
duration: 1
nodes:
  - {id: leader, plugin: sim-omega7, rate: 1000}
"""


def _validate(capsys, graph: str, *sets: str) -> tuple[int, str]:
    code = main(["validate", graph, *[a for s in sets for a in ("--set", s)]])
    return code, capsys.readouterr().err


@pytest.fixture
def default_intent(tmp_path) -> str:
    path = tmp_path / "leader.yaml"
    path.write_text(DEFAULT_INTENT)
    return str(path)


def test_a_field_of_the_default_intent_says_the_type_goes_with_it(capsys, default_intent):
    code, err = _validate(capsys, default_intent, "leader.intent.opening=10mm")
    assert code == 1
    line = err.splitlines()[1].strip()
    assert line.startswith("--set leader.intent.opening=10mm: node 'leader': "), err   # still led by the --set
    assert "intent needs 'type'" in line, err
    assert "not given in the file: its default 'hold' is not a mapping" in line, err
    assert line.endswith("give its type with it: --set leader.intent.type=hold"), err
    assert _validate(capsys, default_intent, "leader.intent.type=hold", "leader.intent.opening=10mm")[0] == 0


def test_a_field_after_a_named_intent_says_the_type_goes_with_it(capsys):
    code, err = _validate(capsys, PAPER_SIM, "leader.intent=hold", "leader.intent.opening=10mm")
    assert code == 1
    line = err.splitlines()[1].strip()
    assert line.startswith("--set leader.intent.opening=10mm: "), err
    assert "intent was 'hold', not a mapping, so the --set made it {opening: 10mm} alone" in line, err
    assert line.endswith("give its type with it: --set leader.intent.type=hold"), err
    assert _validate(capsys, PAPER_SIM, "leader.intent=hold", "leader.intent.type=hold",
                     "leader.intent.opening=10mm")[0] == 0


@pytest.mark.parametrize("sets, whole", [(["leader.intent.type=hold"], "leader.intent={type: hold}"),
                                         (["leader.intent.type=hold", "leader.intent.opening=10mm"],
                                          "leader.intent={type: hold, opening: 10mm}")])
def test_another_type_for_a_mapped_intent_says_to_give_the_whole_intent(capsys, sets, whole):
    code, err = _validate(capsys, PAPER_SIM, *sets)
    assert code == 1
    line = err.splitlines()[1].strip()
    assert line.startswith(" and ".join(f"--set {s}" for s in sets) + ": "), err
    assert ("the --set changes only what it names in intent, the others stay (start_opening, target_opening, speed, "
            "start_time, hold_time, release)") in line, err
    assert line.endswith(f"give the whole value: --set '{whole}'"), err
    assert _validate(capsys, PAPER_SIM, whole)[0] == 0   # what it says works


@pytest.mark.parametrize("item", ["leader.intent.target_opening=abc", "leader.intent.opening=10mm"])
def test_a_refused_value_inside_the_intent_gets_no_hint(capsys, item):
    # nothing to add: the value is wrong (or not a field of close-and-hold), whatever the rest of the intent is
    code, err = _validate(capsys, PAPER_SIM, item)
    assert code == 1
    line = err.splitlines()[1].strip()
    assert line.startswith(f"--set {item}: node 'leader': param '{item.split('=')[0][7:]}' = "), err
    assert "give " not in line and "not a mapping" not in line, err


def test_a_field_inside_a_number_says_the_number_is_not_a_mapping(capsys):
    code, err = _validate(capsys, PAPER_SIM, "leader.max_force.x=3")
    assert code == 1
    line = err.splitlines()[1].strip()
    assert line.startswith("--set leader.max_force.x=3: "), err
    assert "max_force is not given in the file: its default 12.0 is not a mapping, so the --set made it {x: 3} alone"\
        in line, err


def test_a_refused_type_on_the_default_intent_gets_no_hint(capsys, default_intent):
    code, err = _validate(capsys, default_intent, "leader.intent.type=bogus")
    assert code == 1
    line = err.splitlines()[1].strip()
    assert line.startswith("--set leader.intent.type=bogus: ") and "unknown intent type 'bogus'" in line, err
    assert "not a mapping" not in line and "give " not in line, err
