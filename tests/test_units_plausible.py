"""Unit mistakes in speeds and forces: as an opening in millimetres typed in a metre field is refused, so is a speed a
gripper or a hand never reaches (mm/s typed in the m/s field) and a force limit on a person's hand beyond what a
haptic device renders (mN typed in the N field, or a typo)."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.units import (
    MAX_PLAUSIBLE_HAND_FORCE, MAX_PLAUSIBLE_SPEED, plausible_hand_force, plausible_speed, too_fast,
    too_strong_for_a_hand,
)

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"


def test_the_shared_checks_pass_what_hardware_does_and_say_which_unit_was_meant():
    assert too_fast("max_speed", MAX_PLAUSIBLE_SPEED) is None and too_fast("speed", -0.08) is None
    assert plausible_speed("max_speed", 0.1) == 0.1
    why = too_fast("max_speed", 100)
    assert why.startswith("max_speed (100 m/s) is faster than any gripper closes or a hand pinches (2 m/s at most)")
    assert "mm/s in the m/s field? a bare number is m/s: for 100 mm/s write '100mm/s' (0.1 m/s)" in why
    with pytest.raises(ValueError, match=r"speed \(5 m/s\)"):
        plausible_speed("speed", 5.0)
    assert too_strong_for_a_hand("max_force", MAX_PLAUSIBLE_HAND_FORCE) is None
    assert plausible_hand_force("max_force", 8.0) == 8.0
    why = too_strong_for_a_hand("max_force", 8000)
    assert why.startswith("max_force (8000 N) is beyond what a haptic device renders on a hand (50 N at most")
    assert "mN in the N field? a bare number is N: for 8000 mN write '8000mN' (8 N)" in why
    with pytest.raises(ValueError, match=r"max_force \(51 N\)"):
        plausible_hand_force("max_force", 51.0)


@pytest.mark.parametrize("graph, item, field", [
    ("paper-sim.yaml", "leader.intent.speed=5", "intent.speed"),
    ("paper-sim.yaml", "gripper.max_speed=80", "max_speed"),
    ("paper.yaml", "gripper.max_speed=100", "max_speed"),
    ("paper.yaml", "controller.resume_speed=20", "resume_speed"),
])
def test_a_speed_in_mm_per_s_typed_as_m_per_s_is_refused(graph, item, field):
    # before: --set leader.intent.speed=5 (5 m/s) and gripper.max_speed=100 on paper.yaml validated
    with pytest.raises(GraphValidationError) as exc:
        load_graph(EXAMPLES / graph, sets=[item])
    (line,) = [str(e) for e in exc.value.errors]
    assert line.startswith(f"--set {item}: "), line
    assert f"param '{field}'" in line and "mm/s in the m/s field?" in line, line


@pytest.mark.parametrize("item", ["controller.max_force=8000", "controller.max_force=51N"])
def test_a_force_limit_on_the_hand_beyond_any_haptic_device_is_refused(item):
    # before: --set controller.max_force=8000 validated and ran (the Omega.7 saturates, other leaders may not)
    with pytest.raises(GraphValidationError) as exc:
        load_graph(EXAMPLES / "paper-sim.yaml", sets=[item])
    (line,) = [str(e) for e in exc.value.errors]
    assert line.startswith(f"--set {item}: node 'controller': param 'max_force' = "), line
    assert "beyond what a haptic device renders on a hand (50 N at most" in line


@pytest.mark.parametrize("plugin, module", [
    ("sim-gripper", "teletouch.plugins.devices.sim_gripper:SimGripper"),
    ("pal-gripper", "teletouch.plugins.devices.pal_gripper:PalGripper"),
    ("dynamixel-gripper", "teletouch.plugins.devices.dynamixel_gripper:DynamixelGripper"),
    ("canopen-gripper", "teletouch.plugins.devices.canopen_gripper:CanopenGripper"),
    ("hid-leader", "teletouch.plugins.devices.hid_leader:HidLeader"),
])
def test_every_follower_and_the_hid_leader_refuse_an_absurd_max_speed(plugin, module):
    import importlib

    mod, _, name = module.partition(":")
    cls = getattr(importlib.import_module(mod), name)
    with pytest.raises(ValidationError, match=r"max_speed \(3 m/s\) is faster than any gripper"):
        cls.Params(max_speed=3)
    assert cls.Params(max_speed="80mm/s").max_speed == pytest.approx(0.08)
    assert cls.Params(max_speed=MAX_PLAUSIBLE_SPEED).max_speed == MAX_PLAUSIBLE_SPEED


def test_the_position_position_controller_limits_the_hand_force_too():
    from teletouch.plugins.controllers.position_force import PositionForce, PositionPosition

    for cls in (PositionForce, PositionPosition):
        with pytest.raises(ValidationError, match=r"max_force \(80 N\) is beyond what a haptic device renders"):
            cls.Params(max_force=80)


@pytest.mark.parametrize("graph", sorted(p.name for p in EXAMPLES.glob("*.yaml")))
def test_the_examples_and_defaults_still_validate(graph):
    # calibrate-force.yaml names the reader's own depth model (my-digit.model): the packaged one stands in for it
    sets = ["depth.model=sim-digit-qvga"] if graph == "calibrate-force.yaml" else []
    assert load_graph(EXAMPLES / graph, sets=sets).nodes


def test_the_hint_is_conditional_on_a_bare_number():
    # before: "2000mm" (typed with its unit, refused as 2 m) was told to "write 0.002 or "2mm"", as if it were a typo
    from teletouch.units import millimetres_in_metres

    why = millimetres_in_metres("max_opening", 2.0)
    assert "a bare number is metres: for 2 mm write 0.002" in why, why
    assert "a bare number is m/s: for 3 mm/s" in too_fast("max_speed", 3.0)
    assert "a bare number is N: for 60 mN" in too_strong_for_a_hand("max_force", 60.0)
