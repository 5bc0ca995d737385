"""sim-gripper: a compliant object has a solid core (``object_core_width``): the fingers cannot squeeze it away."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from teletouch.plugins.devices import follower_contact as fc
from teletouch.plugins.devices.sim_gripper import SimGripper
from teletouch.plugins.sensors import gel
from teletouch.testing import Harness


def run_to(h, cmd, t0, seconds, dt=1e-3):
    out = {}
    n = int(round(seconds / dt))
    for k in range(1, n + 1):
        out = h.step(t0 + k * dt, opening_command=cmd)
    return out, t0 + n * dt


def squeeze(params, cmd=0.0, seconds=3.0):
    with Harness(SimGripper, params) as h:
        o, _ = run_to(h, cmd, 0.0, seconds)
        return o


def test_very_soft_object_stops_at_its_core_like_a_rigid_one():
    # 100 N/m: at 16 N the spring alone would be squeezed 160 mm, four times the object's 40 mm width
    soft = squeeze({"object_width": 0.04, "object_stiffness": 100.0})
    core = squeeze({"object_width": 0.02, "object_stiffness": None})  # the default core: half the object's width
    assert soft["contact_force"] == pytest.approx(16.0, rel=1e-6)      # max_effort, as on a rigid object
    assert soft["opening"] == pytest.approx(core["opening"], abs=1e-9)
    assert soft["indentation"] == pytest.approx(core["indentation"], abs=1e-9)
    assert soft["opening"] > 0.01     # not squeezed to nothing (0.9 mm before the core)


def test_starting_inside_a_soft_object_rests_on_its_core():
    with Harness(SimGripper, {"object_width": 0.04, "object_stiffness": 100.0, "initial_opening": 0.01}) as h:
        soft = h.step(0.0, opening_command=0.01)
    with Harness(SimGripper, {"object_width": 0.02, "object_stiffness": None, "initial_opening": 0.01}) as h:
        rigid = h.step(0.0, opening_command=0.01)
    assert soft["opening"] == pytest.approx(rigid["opening"], abs=1e-9)
    assert soft["contact_force"] == pytest.approx(rigid["contact_force"], rel=1e-9)
    assert soft["contact_force"] > 1.0


def test_core_width_param_and_force_rising_past_it():
    p = {"object_width": 0.04, "object_stiffness": 200.0, "object_core_width": 0.03}
    light = squeeze(p, cmd=0.035)   # 5 mm of squeeze: the spring carries it, the core is not reached
    assert 0.0 < light["contact_force"] < 200.0 * 0.01
    assert 0.04 - light["opening"] == pytest.approx(light["indentation"] + light["contact_force"] / 200.0, rel=1e-7)
    hard = squeeze(p)
    rigid = squeeze({"object_width": 0.03, "object_stiffness": None})
    assert hard["opening"] == pytest.approx(rigid["opening"], abs=1e-9)
    assert hard["contact_force"] == pytest.approx(16.0, rel=1e-6)


def test_solvers_with_a_compression_limit():
    law = gel.force_law(gel.Indenter.sphere(0.003))
    for g in (law, fc.TabulatedGel(law, 0.04)):
        for n in (1, 2):
            for pen in (1e-4, 2e-3, 5e-3, 2e-2):
                d, f = fc.split_penetration(pen, g, n, 300.0, 0.004)
                assert f == law(d)
                assert n * d + min(f / 300.0, 0.004) == pytest.approx(pen, abs=1e-12)
            # the servo saturates against the core: the rigid problem with an object of the core's width
            x = fc.blocked_opening(0.04, 0.0, 4000.0, 16.0, g, n, 300.0, 0.004)
            assert x == pytest.approx(fc.blocked_opening(0.036, 0.0, 4000.0, 16.0, g, n, None), abs=1e-12)
            # a light squeeze: the limit is not reached and nothing changes
            x = fc.blocked_opening(0.04, 0.039, 4000.0, 16.0, g, n, 3000.0, 0.004)
            assert x == fc.blocked_opening(0.04, 0.039, 4000.0, 16.0, g, n, 3000.0)


def test_core_width_is_checked():
    assert SimGripper.Params(object_width=0.02, object_core_width=0.01).object_core_width == 0.01
    assert SimGripper.Params(object_width=0.02, object_core_width=0.02).object_core_width == 0.02  # rigid
    with pytest.raises(ValidationError, match=r"object_core_width \(30 mm\) is wider than object_width \(20 mm\)"):
        SimGripper.Params(object_width=0.02, object_core_width=0.03)
    with pytest.raises(ValidationError, match="object_core_width .* without an object"):
        SimGripper.Params(object_width=None, object_core_width=0.01)
