"""Millimetres typed in metre fields: poly-force's depths and contact area (``contact_threshold: 30`` ran with no force
at all, status no-contact the whole run) and sim-gripper's openings and widths are refused with the hint the other
length fields give; a unit a plugin declares that teletouch cannot convert is named as such."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import Field, ValidationError

from teletouch import Params
from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.plugins.devices.sim_gripper import SimGripper
from teletouch.plugins.estimators.poly_force import PolyForce
from teletouch.units import parse_quantity

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = REPO / "examples" / "paper-sim.yaml"


def _error(item: str) -> str:
    with pytest.raises(GraphValidationError) as exc:
        load_graph(PAPER_SIM, sets=[item])
    (line,) = [str(e) for e in exc.value.errors]
    assert line.startswith(f"--set {item}: "), line
    return line


# ------------------------------------------------------------------------------------------------ the shared checks
def test_the_shared_depth_and_area_checks_name_the_field_the_value_the_bound_and_the_fix():
    from teletouch.units import (
        MAX_PLAUSIBLE_CONTACT_AREA, MAX_PLAUSIBLE_GEL_DEPTH, plausible_contact_area, plausible_depth, too_deep,
        too_large_an_area,
    )

    assert too_deep("contact_threshold", MAX_PLAUSIBLE_GEL_DEPTH) is None and too_deep("band", -1e-3) is None
    assert plausible_depth("contact_threshold", 3e-5) == 3e-5
    why = too_deep("contact_threshold", 30.0)
    assert why.startswith("contact_threshold (30 m) is more than a DIGIT's gel is thick (0.005 m at most"), why
    assert "micrometres in the metre field? a bare number is metres: for 30 um write 3e-05 or \"30um\"" in why, why
    with pytest.raises(ValueError, match=r"negative_tolerance \(0\.1 m\)"):
        plausible_depth("negative_tolerance", 0.1)
    assert too_large_an_area("min_contact_area", MAX_PLAUSIBLE_CONTACT_AREA) is None
    assert plausible_contact_area("min_contact_area", 1e-6) == 1e-6
    why = too_large_an_area("min_contact_area", 4.0)
    assert why.startswith("min_contact_area (4 m^2) is larger than a DIGIT's sensing area (0.0005 m^2 at most"), why
    assert "mm^2 in the m^2 field? a bare number is m^2: for 4 mm^2 write '4mm^2' (4e-06 m^2)" in why, why


# ------------------------------------------------------------------------------------------------ 1. poly-force
@pytest.mark.parametrize("item, field, fix", [
    ("force.contact_threshold=30", "contact_threshold", "for 30 um write 3e-05 or \"30um\""),
    ("force.contact_threshold=0.03", "contact_threshold", "for 0.03 mm write 3e-05 or \"0.03mm\""),
    ("force.negative_tolerance=0.1", "negative_tolerance", "for 0.1 mm write 0.0001 or \"0.1mm\""),
    ("force.centroid_band=0.02", "centroid_band", "for 0.02 mm write 2e-05 or \"0.02mm\""),
    ("force.depth_limit=5", "depth_limit", "for 5 mm write 0.005 or \"5mm\""),
    ("force.min_contact_area=4", "min_contact_area", "for 4 mm^2 write '4mm^2' (4e-06 m^2)"),
])
def test_poly_force_refuses_millimetres_in_its_depth_and_area_fields(item, field, fix):
    # before: each validated OK; `teletouch run` with contact_threshold=30 gave 0 N, no-contact, the whole run
    line = _error(item)
    assert f"node 'force': param '{field}'" in line and fix in line, line
    assert "field? a bare number is" in line, line


def test_poly_force_keeps_its_defaults_the_packaged_calibration_and_plausible_values():
    p = PolyForce.Params()
    assert (p.calibration, p.contact_threshold, p.depth_limit) == ("sim-digit-qvga", 3e-5, 5e-3)
    p = PolyForce.Params(contact_threshold="5mm", negative_tolerance="5mm", centroid_band="1mm",
                         min_contact_area="500mm^2")
    assert p.contact_threshold == pytest.approx(5e-3) and p.min_contact_area == pytest.approx(5e-4)
    # a depth_limit beyond the gel (a test rig, or a calibration deeper than 5 mm) stays possible
    assert PolyForce.Params(depth_limit=0.05).depth_limit == 0.05
    assert load_graph(PAPER_SIM, sets=["force.contact_threshold=0.05mm", "force.min_contact_area=1mm^2"]).nodes
    with pytest.raises(ValidationError, match=r"depth_limit \(0\.2 m\) is deeper than"):
        PolyForce.Params(depth_limit=0.2)


# ------------------------------------------------------------------------------------------------ 2. sim-gripper
@pytest.mark.parametrize("item, field, fix", [
    ("gripper.initial_opening=20", "initial_opening", "for 20 mm write 0.02 or \"20mm\""),
    ("gripper.object_width=15", "object_width", "for 15 mm write 0.015 or \"15mm\""),
    ("gripper.object_core_width=10", "object_core_width", "for 10 mm write 0.01 or \"10mm\""),
])
def test_sim_gripper_gives_the_millimetre_hint_for_its_openings_and_widths(item, field, fix):
    # before: "initial_opening 20.0 m is outside [0.0, 0.09] m", "object_width (15000 mm) is wider than max_opening"
    line = _error(item)
    assert f"{field} (" in line and "millimetres in the metre field?" in line and fix in line, line


def test_sim_gripper_keeps_its_range_checks_for_real_out_of_range_values():
    with pytest.raises(ValidationError, match=r"initial_opening 0\.5 m is outside \[0\.0, 0\.09\] m"):
        SimGripper.Params(initial_opening=0.5)
    with pytest.raises(ValidationError, match=r"object_width \(500 mm\) is wider than max_opening"):
        SimGripper.Params(object_width=0.5)
    assert SimGripper.Params(initial_opening="20mm", object_width="15mm").object_width == pytest.approx(0.015)


# ------------------------------------------------------------------------------------------------ 3. unknown units
class _Stiff(Params):
    k: float = Field(1e6, gt=0, description="volumetric stiffness", json_schema_extra={"unit": "N/m^3"})


def test_a_unit_teletouch_cannot_convert_asks_for_a_plain_number_in_si():
    # before: "unknown unit 'N/m^3' in '2e6 N/m^3'; expected a quantity in N/m^3 (a plain number)"
    with pytest.raises(ValidationError) as exc:
        _Stiff(k="2e6 N/m^3")
    msg = str(exc.value)
    assert "(a plain number)" not in msg, msg
    assert "N/m^3 is not a unit teletouch converts" in msg and "write a plain number, in N/m^3" in msg, msg
    assert "(SI)" not in msg, msg   # (the field's own unit need not be SI: it is the plugin's)
    assert "teletouch converts m, N, s," in msg, msg
    assert _Stiff(k="2e6").k == 2e6 and _Stiff(k=3e6).k == 3e6   # such a field still takes numbers
    # a unit teletouch knows, for a quantity in a unit it does not: not a unit mistake it could convert either
    with pytest.raises(ValueError, match=r"N/m\^3 is not a unit teletouch converts"):
        parse_quantity("2 N/mm", "N/m^3")
    # the known units' message is unchanged
    with pytest.raises(ValueError, match=r"expected a quantity in m \(m, cm, mm, um, µm\)$"):
        parse_quantity("5 parsec", "m")
