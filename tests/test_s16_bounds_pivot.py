"""sim-pivot: the centre of mass lies on the object, so its offset from the pinch axis is at most the object's
length; ``com_offset: 0.3`` with ``length: 0.12`` (or a com_offset in cm read as m) is refused naming both."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.controllers.experiments import SimPivot


def test_a_centre_of_mass_beyond_the_object_is_refused_naming_both_fields_in_mm():
    # before: validated; the object's weight acted 300 mm from a 120 mm object's pinch axis
    with pytest.raises(ValidationError) as exc:
        SimPivot.Params(length=0.12, com_offset=0.3)
    text = str(exc.value)
    assert "com_offset (300 mm) is longer than length (120 mm)" in text, text


def test_a_centre_of_mass_at_most_the_length_away_still_validates():
    assert SimPivot.Params(length="12cm", com_offset="12cm").com_offset == pytest.approx(0.12)
    assert SimPivot.Params(length=0.05, com_offset=0.0).com_offset == 0.0
    p = SimPivot.Params()
    assert p.com_offset <= p.length
