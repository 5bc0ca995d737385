"""press-routine drives a real Omega.7 into a gel: a length, speed or force in the unit below the SI one typed as a
bare number (``max_depth_limit: 3`` was 3 m and switched the depth abort off) is refused, naming the field and the
unit meant."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.plugins.estimators.force_calibration import PressRoutine

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

#: each checked field, 1000 x its default (as a newcomer's sweep typed them), and what the message says it is beyond
TYPOS = [
    ("max_depth_limit", 3.0, "m", "deeper than a gel is pressed"),
    ("touch_depth", 0.03, "m", "more than a DIGIT's gel is thick"),
    ("settle_tolerance", 0.02, "m", "more than a DIGIT's gel is thick"),
    ("max_overtravel", 0.3, "m", "more than a DIGIT's gel is thick"),
    ("step", 0.1, "m", "more than a DIGIT's gel is thick"),
    ("max_displacement", 2.0, "m", "deeper than a gel is pressed"),
    ("max_tracking_error", 2.0, "m", "beyond a haptic leader's workspace"),
    ("backoff", 0.5, "m", "beyond a haptic leader's workspace"),
    ("max_approach", 30.0, "m", "beyond a haptic leader's workspace"),
    ("approach_speed", 1.0, "m/s", "faster than a probe is driven towards a gel"),
    ("move_speed", 4.0, "m/s", "faster than a probe is driven towards a gel"),
    ("approach_max_force", 1000.0, "N", "beyond what a haptic device renders"),
    ("max_force", 10000.0, "N", "beyond what a haptic device renders"),
]


@pytest.mark.parametrize("field, value, unit, beyond", TYPOS, ids=[t[0] for t in TYPOS])
def test_a_unit_typo_in_a_press_field_is_refused(field, value, unit, beyond):
    # before: each validated; max_depth_limit: 3 (3 m) never aborted a press however deep it went
    with pytest.raises(ValidationError) as exc:
        PressRoutine.Params(**{field: value})
    text = str(exc.value)
    assert f"{field} ({value:g} {unit}) is {beyond}" in text, text
    small = {"m": "millimetres in the metre field?", "m/s": "mm/s in the m/s field?", "N": "mN in the N field?"}
    assert small[unit] in text, text


def test_the_values_in_use_still_validate():
    # the examples' and the tests' values (tests/test_force_calibration.py, tests/test_force_runtime_audit.py)
    p = PressRoutine.Params(step="0.25mm", max_displacement="2mm", approach_speed="2mm/s", move_speed="5mm/s",
                            max_approach="25mm", touch_depth="2.9mm", backoff="3mm", max_force=10.0,
                            approach_max_force=1.0, max_depth_limit="3mm", max_tracking_error="2mm")
    assert (p.step, p.max_approach, p.backoff, p.max_force) == pytest.approx((2.5e-4, 0.025, 3e-3, 10.0))
    # a thicker gel on a test rig: a depth limit and a displacement beyond the DIGIT's 4-5 mm
    p = PressRoutine.Params(max_depth_limit="9mm", max_displacement="8mm", max_overtravel="1mm", backoff="20mm")
    assert (p.max_depth_limit, p.max_displacement) == pytest.approx((9e-3, 8e-3))


def test_the_depth_abort_switched_off_by_a_typo_is_refused_when_the_graph_is_validated():
    with pytest.raises(GraphValidationError) as exc:
        load_graph(EXAMPLES / "calibrate-force-sim.yaml", sets=["routine.max_depth_limit=3"])
    (line,) = [str(e) for e in exc.value.errors]
    assert "param 'max_depth_limit'" in line and "for 3 mm write 0.003 or \"3mm\"" in line, line


def test_the_press_force_message_names_the_omega7_translation_force_not_its_grip():
    # before: "(50 N at most; the Omega.7's grip: 8 N)": the press pushes with the device's translation (12 N)
    with pytest.raises(ValueError) as exc:
        PressRoutine.Params(max_force=8000)
    assert "the Omega.7: 12 N in translation" in str(exc.value) and "grip" not in str(exc.value), str(exc.value)
