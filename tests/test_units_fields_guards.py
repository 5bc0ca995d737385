"""Guards and thresholds a unit typo switched off: ros2-subscribe's ``max_opening``/``max_depth`` (a guard against
millimetres that itself took millimetres as metres), the controllers' speed and motion thresholds and deadband, the
leaders' workspace and position scale, and the depth node's ``contact_depth`` in the shared words of
teletouch.units."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.bridges.ros2 import Ros2Subscribe
from teletouch.plugins.controllers.position_force import PositionForce, PositionPosition
from teletouch.plugins.devices.hid_leader import HidLeader
from teletouch.plugins.devices.sim_omega7 import SimOmega7
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.units import too_deep


def _refused(params_cls, field, value) -> str:
    with pytest.raises(ValidationError) as exc:
        params_cls(**{field: value})
    return str(exc.value)


@pytest.mark.parametrize("field, value, beyond", [
    ("max_opening", 1000.0, "beyond any gripper's opening (1 m at most)"),
    ("max_depth", 50.0, "deeper than a gel is pressed, even on a test rig (0.1 m at most)"),
])
def test_a_ros2_guard_against_millimetres_typed_in_millimetres_is_refused(field, value, beyond):
    # before: max_depth: 50 (meant 50 mm) let depth maps in mm through as metres, the very thing it guards against
    text = _refused(Ros2Subscribe.Params, field, value)
    assert f"{field} ({value:g} m) is {beyond}" in text and "millimetres in the metre field?" in text, text
    p = Ros2Subscribe.Params(max_opening="90mm", max_depth="10mm")
    assert (p.max_opening, p.max_depth) == pytest.approx((0.09, 0.01))


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition], ids=lambda c: c.name)
@pytest.mark.parametrize("field, value, unit, limit", [
    ("reduction_min_velocity", 3.0, "m/s", "(2 m/s at most)"),
    ("max_leader_velocity", 2000.0, "m/s", "(100 m/s at most"),
])
def test_a_controller_speed_threshold_in_mm_per_s_is_refused(cls, field, value, unit, limit):
    # before: reduction_min_velocity: 3 (3 m/s) never cut a force; max_leader_velocity: 2000 passed every glitch
    text = _refused(cls.Params, field, value)
    assert f"{field} ({value:g} {unit}) is " in text and limit in text and "mm/s in the m/s field?" in text, text
    assert getattr(cls.Params(**{field: f"{value:g}mm/s"}), field) == pytest.approx(value / 1e3)


def test_the_controllers_speed_thresholds_in_use_still_validate():
    # tests/test_safety_fuzz_controllers.py draws max_leader_velocity 50 m/s (a glitch filter left wide open)
    p = PositionForce.Params(max_leader_velocity=50.0, reduction_min_velocity=1.0)
    assert (p.max_leader_velocity, p.reduction_min_velocity) == (50.0, 1.0)


@pytest.mark.parametrize("field, value, unit, beyond", [
    ("deadband", 20.0, "N", "wider than the grip forces a tactile sensor reads"),
    ("prediction_min_motion", 0.02, "m", "more than a DIGIT's gel is thick"),
])
def test_a_position_force_threshold_in_the_smaller_unit_is_refused(field, value, unit, beyond):
    # before: deadband: 20 (meant 20 mN) rendered nothing below 20 N; prediction_min_motion: 0.02 (meant mm) never
    # learnt a stiffness
    text = _refused(PositionForce.Params, field, value)
    assert f"{field} ({value:g} {unit}) is {beyond}" in text, text
    p = PositionForce.Params(deadband=0.5, prediction_min_motion="0.02mm")
    assert (p.deadband, p.prediction_min_motion) == pytest.approx((0.5, 2e-5))


@pytest.mark.parametrize("cls, field, value", [(SimOmega7, "workspace_radius", 75.0),
                                               (HidLeader, "position_scale", 10.0)])
def test_a_leader_length_in_millimetres_is_refused(cls, field, value):
    # before: workspace_radius: 75 (75 m) let the simulated handle wander off; position_scale: 10 (meant 10 mm per
    # full deflection) output positions of metres
    text = _refused(cls.Params, field, value)
    assert f"{field} ({value:g} m) is beyond a haptic leader's workspace (1 m at most" in text, text
    assert f"for {value:g} mm write {value / 1e3:g} or \"{value:g}mm\"" in text, text
    assert getattr(cls.Params(**{field: f"{value:g}mm"}), field) == pytest.approx(value / 1e3)


def test_contact_depth_is_refused_in_the_shared_words():
    # before: its own copy of the text of teletouch.units.too_deep, worded apart from every other depth field's
    with pytest.raises(ValidationError) as exc:
        DepthEstimator.Params(contact_depth=0.03)
    assert too_deep("contact_depth", 0.03) in str(exc.value)
    assert DepthEstimator.Params(contact_depth=5e-3).contact_depth == 5e-3
