"""A unit-typo message never suggests a value that is refused in turn: where the number is still too large in the
smaller unit (contact_threshold: 30 is neither 30 m nor 30 mm: 30 um is its default), it suggests the next smaller
unit where that fits, else no value at all."""

from __future__ import annotations

import re

import pytest

from teletouch.units import (
    MAX_PLAUSIBLE_GEL_DEPTH, parse_quantity, plausible_quantity, too_deep, too_large_an_area,
)


def test_a_depth_too_deep_even_in_millimetres_suggests_micrometres():
    # before: "for 30 mm write 0.03 or "30mm"", and 0.03 m is refused in turn
    why = too_deep("contact_threshold", 30.0)
    assert "for 30 mm write" not in why, why
    assert 'for 30 um write 3e-05 or "30um"' in why, why
    assert parse_quantity("30um", "m") <= MAX_PLAUSIBLE_GEL_DEPTH
    assert 'for 3 mm write 0.003 or "3mm"' in too_deep("touch_depth", 3.0)   # (fits in mm: as before)


def test_an_area_too_large_even_in_square_millimetres_suggests_no_value():
    why = too_large_an_area("min_contact_area", 600.0)   # 600 mm^2 > the sensing area too
    assert "write '600mm^2'" not in why and "a bare number is m^2" in why, why
    assert "for 4 mm^2 write '4mm^2'" in too_large_an_area("min_contact_area", 4.0)


def test_every_suggested_value_is_accepted():
    for v in (0.5, 3.0, 30.0, 400.0, 6000.0, 3e7):
        for why, si in ((too_deep("d", v), r"write (\S+) or"), (too_large_an_area("a", v), r"\((\S+) m\^2\)$")):
            m = re.search(si, why)
            if m:
                assert abs(float(m.group(1))) <= max(MAX_PLAUSIBLE_GEL_DEPTH, 5e-4), why
            else:
                assert "write" not in why, why


def test_plausible_quantity_names_a_unit_it_has_no_check_for():
    # before: a raw KeyError, which pydantic does not turn into a validation error
    with pytest.raises(ValueError, match=r"plausible_quantity: unit 'Pa': expected one of m, m/s, N"):
        plausible_quantity("stiffness", 1e9, 1e6, "Pa", "too stiff")
