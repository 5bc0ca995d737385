"""press-routine's ``max_force_rate`` (N/s) keeps a position glitch from hammering the handle: a rate so high that
it limits nothing (``500000``: 500 N/s typed in mN/s, 500 N per millisecond) is refused, naming the field."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.plugins.estimators.force_calibration import PressRoutine

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_a_force_rate_in_millinewtons_per_second_is_refused_with_the_value_meant():
    # before: validated; each force component could jump 500 N in one 1 ms step (the limit limited nothing)
    with pytest.raises(ValidationError) as exc:
        PressRoutine.Params(max_force_rate=500000.0)
    text = str(exc.value)
    assert ("max_force_rate (500000 N/s) is faster than a press's force needs to change (100000 N/s at most: a "
            "haptic device's whole +-50 N in 1 ms)") in text, text
    assert "mN/s in the N/s field? a bare number is N/s: for 500000 mN/s write 500" in text, text


def test_a_force_rate_too_high_in_either_unit_gets_no_suggestion():
    with pytest.raises(ValidationError) as exc:
        PressRoutine.Params(max_force_rate=1e9)
    text = str(exc.value)
    assert "max_force_rate (1e+09 N/s) is faster" in text and "a bare number is N/s" in text, text
    assert "write" not in text, text


def test_the_typo_is_refused_when_the_graph_is_validated():
    with pytest.raises(GraphValidationError) as exc:
        load_graph(EXAMPLES / "calibrate-force-sim.yaml", sets=["routine.max_force_rate=500000"])
    (line,) = [str(e) for e in exc.value.errors]
    assert "param 'max_force_rate'" in line and "for 500000 mN/s write 500" in line, line


@pytest.mark.parametrize("rate", [500.0, 1.0, 5000.0, 24000.0, 100000.0])
def test_the_rates_a_user_may_mean_still_validate(rate):
    # the default, a slow and careful press, and the Omega.7's whole +-12 N swing within 1 ms
    assert PressRoutine.Params(max_force_rate=rate).max_force_rate == rate
    assert PressRoutine.Params().max_force_rate == 500.0
