"""sim-pivot: the object is a uniform cylinder (its centre of mass at its middle) pinched somewhere along it, so the
centre of mass is at most half the length from the pinch axis; ``com_offset: 0.3`` with ``length: 0.12`` (or a
com_offset in cm read as m) is refused naming both."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.controllers.experiments import SimPivot


def test_a_centre_of_mass_beyond_the_object_is_refused_naming_both_fields_in_mm():
    # before: validated; the object's weight acted 300 mm from a 120 mm object's pinch axis
    with pytest.raises(ValidationError) as exc:
        SimPivot.Params(length=0.12, com_offset=0.3)
    text = str(exc.value)
    assert "com_offset (300 mm) is more than half the length (120 mm)" in text, text


def test_a_pinch_axis_off_the_end_of_the_object_is_refused():
    # a review found com_offset up to the whole length accepted: 100 mm of a 120 mm object puts the pinch axis 40 mm
    # beyond its end (the inertia m (L^2/12 + d^2) is the uniform cylinder's)
    with pytest.raises(ValidationError, match="expected com_offset <= length / 2"):
        SimPivot.Params(length=0.12, com_offset=0.10)


def test_a_centre_of_mass_at_most_half_the_length_away_still_validates():
    assert SimPivot.Params(length="12cm", com_offset="6cm").com_offset == pytest.approx(0.06)
    assert SimPivot.Params(length=0.05, com_offset=0.0).com_offset == 0.0
    p = SimPivot.Params()
    assert p.com_offset <= p.length / 2
