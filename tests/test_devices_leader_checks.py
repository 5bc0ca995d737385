"""sim-omega7's simulated pinch force is checked for a unit typo as the other hand-force limits are, and the leaders'
``faults`` in status() is of the current activation, as every other figure of it (docs/leaders.md)."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from teletouch import ComponentFault
from teletouch.plugins.devices.sim_omega7 import SimOmega7
from teletouch.testing import Harness
from tests.test_leader_omega7 import harness

from fakes.dhd_standin import sdk_dir_fixture, standin_fixture

sdk_dir = sdk_dir_fixture("fdsdk-s15")
standin = standin_fixture()


def test_a_pinch_force_in_millinewtons_is_refused_naming_the_field_and_the_fix():
    # before: hand_max_force: 40000 (meant 40000 mN) was taken as 40 kN: the simulated hand overpowered any rendering
    with pytest.raises(ValidationError) as exc:
        SimOmega7.Params(hand_max_force=40000)
    msg = str(exc.value)
    assert "hand_max_force (40000 N) is beyond any person's pinch (200 N at most" in msg
    assert "mN in the N field?" in msg and "write '40000mN' (40 N)" in msg, msg


def test_a_strong_persons_pinch_is_still_a_valid_hand_max_force():
    assert SimOmega7.Params(hand_max_force="120 N").hand_max_force == 120.0      # an adult's key pinch
    assert SimOmega7.Params(hand_max_force="40000mN").hand_max_force == pytest.approx(40.0)


def _fault(h: Harness, t: float) -> None:
    with pytest.raises(ComponentFault, match="not finite"):
        h.step(t, gripper_force=math.nan)


def test_sim_omega7_faults_in_status_are_of_the_current_activation():
    # before: faults was set to 0 in configure only, so a second activation reported the first one's faults
    h = Harness(SimOmega7, {"intent": "hold"})
    h.comp.configure()
    h.comp.activate()
    h.step(0.0, gripper_force=1.0)
    _fault(h, 0.001)
    assert h.comp.status()["faults"] == 1
    h.comp.safe_state()
    h.comp.deactivate()
    h.comp.activate()
    assert h.comp.status()["faults"] == 0
    h.step(0.0, gripper_force=1.0)
    _fault(h, 0.001)
    assert h.comp.status()["faults"] == 1
    h.comp.close()


def test_omega7_reports_its_faults_of_the_current_activation(sdk_dir, standin):
    # before: omega7 counted its faults over the driver's lifetime and reported them nowhere (sim-omega7 has the key)
    h = harness(sdk_dir)
    h.comp.configure()
    try:
        h.comp.activate()
        h.step(0.0, gripper_force=1.0)
        assert h.comp.status()["faults"] == 0
        _fault(h, 0.001)
        assert h.comp.status()["faults"] == 1
        h.comp.safe_state()
        h.comp.deactivate()
        h.comp.activate()
        assert h.comp.status()["faults"] == 0
        h.comp.safe_state()
        h.comp.deactivate()
    finally:
        h.comp.close()
