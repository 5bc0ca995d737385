"""sim-omega7's ``hand_position`` (where the simulated operator holds the handle) must lie in the handle's
workspace, as ``initial_position`` must: ``hand_position: [0, 0, 50]`` meant 50 mm and pulled the handle towards a
point 50 m away (it sat pinned on the workspace's wall the whole run)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.devices.sim_omega7 import SimOmega7


def test_a_hand_position_in_millimetres_is_refused_naming_the_field_and_the_unit_meant():
    # before: validated; the arm's spring (300 N/m) pulled the handle with 15 kN against the workspace's wall
    with pytest.raises(ValidationError) as exc:
        SimOmega7.Params(hand_position=(0.0, 0.0, 50.0))
    text = str(exc.value)
    assert "hand_position [0.0, 0.0, 50.0] m is 50000 mm from the centre, outside workspace_radius (75 mm)" in text, \
        text
    assert ('millimetres in the metre field? a bare number is metres: write [0, 0, 0.05] or ["0mm", "0mm", "50mm"]'
            in text), text


def test_a_hand_position_just_outside_the_workspace_is_refused_without_a_unit_hint():
    with pytest.raises(ValidationError) as exc:
        SimOmega7.Params(hand_position=(0.0, 0.08, 0.0))
    text = str(exc.value)
    assert "hand_position [0.0, 0.08, 0.0] m is 80 mm from the centre, outside workspace_radius (75 mm)" in text, text
    assert "millimetres" not in text, text


def test_an_initial_position_in_millimetres_gets_the_same_hint():
    with pytest.raises(ValidationError) as exc:
        SimOmega7.Params(initial_position=(30.0, 0.0, 0.0))
    text = str(exc.value)
    assert "initial_position [30.0, 0.0, 0.0] m is 30000 mm from the centre, outside workspace_radius" in text, text
    assert '"30mm"' in text, text


def test_hand_positions_inside_the_workspace_still_validate():
    assert SimOmega7.Params().hand_position == (0.0, 0.0, 0.0)
    p = SimOmega7.Params(hand_position=("50mm", 0.0, "-2cm"))
    assert p.hand_position == pytest.approx((0.05, 0.0, -0.02))
    # on the wall of a larger workspace
    p = SimOmega7.Params(workspace_radius="0.2m", hand_position=(0.0, 0.0, 0.2))
    assert p.hand_position == pytest.approx((0.0, 0.0, 0.2))
