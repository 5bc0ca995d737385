"""The pivoting experiment's object and operator: a length or a speed in millimetres (per second) typed as a bare
number in a metre (m/s) field is refused, naming the field and the unit meant."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.controllers.experiments import PivotOperator, SimPivot

TYPOS = [
    (PivotOperator, "start_opening", 22.0, "m", "beyond any gripper's opening"),
    (PivotOperator, "squeeze", 2.5, "m", "wider than a hand's pinch opens"),
    (PivotOperator, "regrip_step", 1.0, "m", "wider than a hand's pinch opens"),
    (PivotOperator, "tremor", 0.05, "m", "more than a hand trembles or drifts"),
    (PivotOperator, "hand_drift", 0.4, "m", "more than a hand trembles or drifts"),
    (PivotOperator, "hand_speed", 20.0, "m/s", "faster than any gripper closes or a hand pinches"),
    (PivotOperator, "loosen_rate_position", 0.6 * 1000, "m/s", "faster than any gripper closes or a hand pinches"),
    (SimPivot, "length", 120.0, "m", "longer than an object pivoted between two fingertips"),
    (SimPivot, "com_offset", 30.0, "m", "longer than an object pivoted between two fingertips"),
    (SimPivot, "friction_radius", 2.5, "m", "larger than a contact patch on a DIGIT"),
]


@pytest.mark.parametrize("cls, field, value, unit, beyond", TYPOS, ids=[t[1] for t in TYPOS])
def test_a_unit_typo_in_a_pivot_field_is_refused(cls, field, value, unit, beyond):
    # before: each validated (the 1000 x default of a newcomer's sweep), e.g. tremor: 0.05 (meant 0.05 mm) shook
    # the simulated hand by 5 cm
    with pytest.raises(ValidationError) as exc:
        cls.Params(**{field: value})
    text = str(exc.value)
    assert f"{field} ({value:g} {unit}) is {beyond}" in text, text
    assert ("millimetres in the metre field?" if unit == "m" else "mm/s in the m/s field?") in text, text


def test_the_pivot_values_in_use_and_their_units_still_validate():
    op = PivotOperator.Params(start_opening="22mm", squeeze="2.5mm", regrip_step="1mm", tremor="0.05mm",
                              hand_drift="0.4mm", hand_speed="20mm/s", loosen_rate_position="0.6mm/s")
    assert (op.start_opening, op.hand_speed, op.loosen_rate_position) == pytest.approx((0.022, 0.02, 6e-4))
    obj = SimPivot.Params(length="12cm", com_offset="3cm", friction_radius="2.5mm")
    assert (obj.length, obj.com_offset, obj.friction_radius) == pytest.approx((0.12, 0.03, 2.5e-3))
    assert PivotOperator.Params().hand_speed == 0.02 and SimPivot.Params().length == 0.12
