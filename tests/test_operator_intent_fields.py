"""An unknown field of an intent ("--set leader.intent.opening=10mm" on a 'close-and-hold' intent) was refused with
pydantic's "intent.opening: Extra inputs are not permitted", without the fields that intent type takes: the message
names them now, with their units where they have one."""

from __future__ import annotations

from pathlib import Path

import pytest

from teletouch.cli import main
from teletouch.plugins.devices.operator import validate_intent

REPO = Path(__file__).resolve().parents[1]
CLOSE_AND_HOLD = ("start_opening (m), target_opening (m), speed (m/s), start_time (s), hold_time (s), release")
MEAN = "(did you mean 'start_opening' or 'target_opening'?)"


@pytest.mark.parametrize("spec, says", [
    ({"type": "close-and-hold", "opening": 0.01},
     f"intent 'close-and-hold' has no field 'opening' {MEAN}; its fields: {CLOSE_AND_HOLD}"),
    ({"type": "close-and-hold", "opening": 0.01, "force": 2},
     f"intent 'close-and-hold' has no fields 'opening' {MEAN}, 'force'; its fields: {CLOSE_AND_HOLD}"),
    ({"type": "hold", "target_opening": "5mm"},
     "intent 'hold' has no field 'target_opening' (did you mean 'opening'?); its fields: opening (m)"),
    ({"type": "trajectory", "waypoints": [[0, 0.01]], "speed": 1},
     "intent 'trajectory' has no field 'speed'; its fields: waypoints"),
    ({"type": "none", "opening": 0.01}, "intent 'none' has no field 'opening'; it takes no fields"),
])
def test_an_unknown_intent_field_names_the_fields_of_that_intent(spec, says):
    with pytest.raises(ValueError) as exc:
        validate_intent(spec)
    assert str(exc.value) == says


def test_an_unknown_field_beside_a_bad_value_says_both():
    with pytest.raises(ValueError) as exc:
        validate_intent({"type": "close-and-hold", "speed": -1, "opening": 0.01})
    assert str(exc.value) == (f"intent 'close-and-hold' has no field 'opening' {MEAN}; its fields: {CLOSE_AND_HOLD}; "
                              f"intent.speed: Input should be greater than 0")


def test_a_set_of_an_unknown_intent_field_is_led_by_the_set_and_names_the_fields(capsys):
    assert main(["validate", str(REPO / "examples" / "paper-sim.yaml"), "--set", "leader.intent.opening=10mm"]) == 1
    err = capsys.readouterr().err
    line = next(x.strip() for x in err.splitlines() if "opening" in x)
    assert line.startswith("--set leader.intent.opening=10mm: node 'leader': "), err
    assert line.endswith(f"intent 'close-and-hold' has no field 'opening' {MEAN}; its fields: {CLOSE_AND_HOLD}"), err
    assert "Extra inputs" not in err


def test_a_misspelt_intent_field_gets_a_did_you_mean():
    # before: the fields were listed, but the likely one was not named (a misspelt parameter gets "did you mean")
    with pytest.raises(ValueError, match=r"has no field 'target_openning' \(did you mean 'target_opening'( or "
                                         r"'start_opening')?\?\); its fields: "):
        validate_intent({"type": "close-and-hold", "target_openning": 0.01})


@pytest.mark.parametrize("source, says", [
    ("def desired(:\n", "module 'tt_bad_intent' failed to load ("),
    ("raise RuntimeError('no config')\n", "module 'tt_bad_intent' failed to load: RuntimeError: no config"),
])
def test_an_intent_module_that_fails_to_load_is_a_clear_error(site, source, says):
    # before: a SyntaxError (or any error but ImportError) in a user's intent module came out as itself, a traceback
    (site / "tt_bad_intent.py").write_text(source)
    with pytest.raises(ValueError) as err:
        validate_intent({"type": "tt_bad_intent:MyIntent"})
    assert str(err.value).startswith("intent type 'tt_bad_intent:MyIntent': ") and says in str(err.value), err.value
    if "def desired" in source:
        assert "tt_bad_intent.py:1): SyntaxError" in str(err.value)
