"""status() is SI, the unit in each key (``opening_m``, ``force_n``, ``step_s``; docs/writing-a-plugin.md); the live
view of `teletouch run` shows those numbers in a person's units. Before, the plugins mixed metres under bare keys
(``opening``), millimetres and millijoules under suffixed ones (``leader_mm``, ``energy_mJ``), degrees (``angle_deg``)
and the depth node's ``ms``; and sim-omega7's counters ran from configure while omega7's start again at each
activation."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from teletouch import Sample
from teletouch.plugins.controllers.experiments import PivotOperator, SimPivot, build_runtime, sim_graph
from teletouch.plugins.devices.sim_omega7 import SimOmega7
from teletouch.plugins.estimators.force_calibration import SimPressRig
from teletouch.testing import Harness

#: key endings of a unit that is not SI, or not in lower case, as the plugins had them
NOT_SI = re.compile(r"(_mm|_mm2|_mj|_deg|_ms|_us)$|^(ms|fps)$|[A-Z]")


@pytest.fixture(scope="module")
def sim_run():
    rt = build_runtime(sim_graph(sensor="image", duration=1.5))
    res = rt.run()
    assert res.status == "ok", res.message
    return {n.id: dict(n.comp.status()) for n in rt.nodes}


def test_every_node_of_the_simulated_setup_reports_si_under_keys_that_name_the_unit(sim_run):
    for node, st in sim_run.items():
        bad = [k for k in st if NOT_SI.search(k)]
        assert st and not bad, f"{node}: {bad} in {st}"
    leader, gripper, digit = sim_run["leader"], sim_run["gripper"], sim_run["digit"]
    depth, force, ctl = sim_run["depth"], sim_run["force"], sim_run["controller"]
    assert 0.0 < leader["gripper_opening_m"] < 0.025 and math.isfinite(leader["gripper_force_n"])
    assert 0.0 < gripper["opening_m"] < 0.025 and 0.0 < gripper["setpoint_m"] < 0.025
    assert gripper["indentation_m"] < 0.003 and gripper["contact_force_n"] >= 0.0
    assert 0.0 <= digit["true_max_depth_m"] < 0.003 and digit["true_force_n"] >= 0.0
    assert digit["true_indentation_m"] < 0.003   # the truth, named so beside the depth node's estimate
    assert 0.0 <= depth["max_depth_m"] < 0.003 and 0.0 <= depth["contact_area_m2"] < 1e-3
    assert 0.0 < depth["step_s"] < 1.0   # one frame's computation, in s (was "ms")
    assert force["force_n"] >= 0.0
    assert ctl["leader_m"] == pytest.approx(leader["gripper_opening_m"], abs=2e-3)
    assert ctl["follower_m"] == pytest.approx(gripper["opening_m"], abs=2e-3)
    assert abs(ctl["energy_j"]) < 1.0 and math.isfinite(ctl["damping_n_s_per_m"])
    assert ctl["contact_stiffness_n_per_m"] >= 0.0
    # the six the live view shows: the forces and openings, then the energy and the state
    assert list(ctl)[:6] == ["force_n", "leader_m", "follower_m", "feedback_n", "energy_j", "state"]


def test_sim_pivot_and_the_pivot_operator_report_angles_in_rad_and_forces_in_n():
    with Harness(SimPivot, {"lift_time": 0.0}) as h:
        hold = h.comp.holding_force(0.0)
        k = 0
        for force in [3.0] * 500 + [0.8 * hold] * 300:
            out = h.step(k * 1e-3, grip_force=force)
            k += 1
        assert out["angle"] > 0.01
        assert h.comp.status()["angle_rad"] == out["angle"]
    with Harness(PivotOperator, {"strategy": "force", "hold_force": 2.5}) as h:
        for k in range(300):
            h.step(k * 1e-2, angle=0.2, contact=True, felt_force=1.0, leader_opening=0.02)
        st = h.comp.status()
        assert st["seen_angle_rad"] == pytest.approx(h.comp.theta_p) and st["seen_angle_rad"] > 0.1
        h.comp.f_target = 2.34567                            # the grip force it aims at (force strategy)
        assert h.comp.status()["target_force_n"] == 2.34567


def test_the_press_rig_reports_the_indentation_in_m():
    with Harness(SimPressRig) as h:
        out = h.step(0.0, position=np.array([0.0, 0.0, -0.0058]))
        assert out["indentation"] == pytest.approx(0.0008)
        assert h.comp.status()["indentation_m"] == pytest.approx(0.0008)
        assert h.comp.status()["gel_force_n"] > 0.0


def test_sim_omega7_counts_each_activation_afresh_as_omega7():
    with Harness(SimOmega7, {"intent": "hold", "command_timeout": "50ms", "max_gripper_force": 3.0}) as h:
        h.step(0.0, gripper_force=Sample(100.0, 0.0))        # clamped
        h.step(0.01)
        h.step(0.2)                                          # stale
        h.step(0.21, gripper_force=Sample(1.0, 0.21))        # fresh again: faded in
        st = h.comp.status()
        assert st["clamped"] >= 1 and st["stale_commands"] >= 1 and st["faded_in"] == 1, st
        h.comp.deactivate()
        h.comp.activate()
        st = h.comp.status()
        assert (st["clamped"], st["stale_commands"], st["faded_in"]) == (0, 0, 0), st
