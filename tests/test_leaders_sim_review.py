"""Review of hid-leader, sim-omega7 (and its simulated operator) and sim-gripper: the opening a SpaceMouse in position
mode reports before its first report, an unplugged device named in the fault, millimetres typed in the leaders'
metre fields, and re-activation (a graph's clock that starts afresh) of the simulated leader and follower.

hid-leader runs against the hidapi fake of tests/test_leader_hid.py (hidapi's enumerate/device interface, reports as
lists of ints); the simulated devices need no hardware."""

from __future__ import annotations

import math
import struct
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

import test_leader_hid as hid_fakes  # noqa: E402  (its hidapi fake)

from teletouch import HardwareError, Sample  # noqa: E402
from teletouch.plugins.devices import hid_leader as hl  # noqa: E402
from teletouch.plugins.devices import operator as op  # noqa: E402
from teletouch.plugins.devices.sim_gripper import SimGripper  # noqa: E402
from teletouch.plugins.devices.sim_omega7 import SimOmega7  # noqa: E402
from teletouch.testing import Harness  # noqa: E402


# ------------------------------------------------------------------------------------------------ hid-leader
fake_hid = hid_fakes.fake_hid     # the fixture: hidapi's enumerate/device replaced by the fake
info = hid_fakes.info


def test_spacemouse_in_position_mode_starts_half_open_not_fully_open(fake_hid):
    """A SpaceMouse is silent at rest, and a cap at rest maps to half open in position mode; before its first report
    the opening was max_opening (fully open, the rate mode's start), and the first report of a cap barely touched
    stepped the opening (and the follower's command) by half the range."""
    fake_hid.devices.append(info(0x256F, 0xC635))
    with Harness(hl.HidLeader, {"mode": "position", "min_opening": "2mm", "max_opening": "22mm"}) as h:
        out = h.step(0.0)                                   # no report yet: the cap is at rest
        assert out["gripper_opening"] == pytest.approx(0.012)
        assert out["gripper_velocity"] == 0.0
        fake_hid.reports.append(bytes.fromhex("01 0000 0000") + struct.pack("<h", 20))   # inside the dead band
        out = h.step(0.004)
        assert out["gripper_opening"] == pytest.approx(0.012)   # no jump at the first report


def test_rate_mode_still_starts_fully_open(fake_hid):
    fake_hid.devices.append(info(0x256F, 0xC635))
    with Harness(hl.HidLeader, {"min_opening": "2mm", "max_opening": "22mm"}) as h:
        assert h.step(0.0)["gripper_opening"] == pytest.approx(0.022)


@pytest.mark.parametrize("dev,params,report", [
    (info(0x1234, 0x5678, b"3-1:1.0", name=""), {"device": "generic", "vendor_id": 0x1234, "trigger_offset": 1},
     bytes([0, 0x80])),
    (info(0x054C, 0x0CE6, b"3-1:1.0"), {}, bytes.fromhex("01 80 80 80 80 00 ff 12 28 02 00") + bytes(53)),
])
def test_unplugging_names_the_device_its_ids_and_path(fake_hid, dev, params, report):
    """The fault said '<name> stopped answering': for a pad without a product string that was 'HID stopped
    answering', naming no device at all (and never the ids or the path, which every other error gives)."""
    fake_hid.devices.append(dev)
    with Harness(hl.HidLeader, params) as h:
        fake_hid.reports.append(report)
        h.step(0.0)
        fake_hid.unplugged = True
        with pytest.raises(HardwareError) as ei:
            h.step(0.004)
    msg = str(ei.value)
    assert "stopped answering (read error)" in msg and "check the USB cable" in msg
    assert f"HID device {dev['vendor_id']:04x}:{dev['product_id']:04x} at 3-1:1.0 was unplugged" in msg


@pytest.mark.parametrize("field", ["min_opening", "max_opening"])
def test_hid_leader_refuses_millimetres_in_its_metre_fields(field):
    """``max_opening: 22`` (meant mm) was taken as 22 m: the leader's opening, the follower's command, went to
    metres."""
    params = {"min_opening": 0.0, "max_opening": 30.0} if field == "max_opening" else {"min_opening": 2.0,
                                                                                         "max_opening": 30.0}
    with pytest.raises(ValidationError, match=rf"{field} \({params[field]:g} m\) is beyond any gripper's opening.*"
                                              rf"millimetres in the metre field\?"):
        hl.HidLeader.Params(**params)
    assert hl.HidLeader.Params(min_opening="2mm", max_opening="30mm").max_opening == pytest.approx(0.03)


# ------------------------------------------------------------------------------------------------ sim-omega7
def test_sim_omega7_refuses_millimetres_in_its_opening_fields():
    with pytest.raises(ValidationError, match=r"max_opening \(25 m\) is beyond any gripper's opening.*write 0.025"):
        SimOmega7.Params(max_opening=25)
    assert SimOmega7.Params(max_opening="25mm").max_opening == pytest.approx(0.025)


@pytest.mark.parametrize("intent,field", [
    ({"type": "hold", "opening": 15}, "opening"),
    ({"type": "close-and-hold", "start_opening": 20}, "start_opening"),
    ({"type": "close-and-hold", "target_opening": 5}, "target_opening"),
    ({"type": "trajectory", "waypoints": [[0, 0.01], [1, 12]]}, "waypoints"),
])
def test_intent_openings_refuse_millimetres(intent, field):
    """``intent: {type: hold, opening: 15}`` held 15 m: the hand pushed the gripper into its end stop with its full
    pinch force (40 N) for the whole run."""
    with pytest.raises(ValidationError, match=rf"intent\.{field}: .*beyond any gripper's opening.*millimetres"):
        SimOmega7.Params(intent=intent)


class LatchOnForce:
    """A reactive intent with state: closes to 4 mm once the rendered force exceeded 1 N, until reset()."""

    name = "review-latch"
    resets = 0

    def __init__(self, params=None):
        self.latched = False

    def reset(self):
        self.latched = False
        LatchOnForce.resets += 1

    def desired(self, t, state):
        if state.gripper_force > 1.0:
            self.latched = True
        return (0.004 if self.latched else 0.015), 0.0


def _settle(h, t0, seconds, **inputs):
    out = None
    for i in range(1, int(round(seconds / 1e-3)) + 1):
        out = h.step(t0 + i * 1e-3, **inputs)
    return out


def test_reactivation_starts_the_operator_afresh():
    """The intent's optional reset() (operator.py) was never called: an intent that had reacted in one activation
    (a latch, a counter) went on reacting in the next; the last cue perceived was still perceived."""
    h = Harness(SimOmega7, {"intent": {"type": f"{__name__}:LatchOnForce"}})
    c = h.comp
    c.configure()
    c.activate()
    resets = LatchOnForce.resets
    _settle(h, 0.0, 0.2, gripper_force=2.0)
    out = _settle(h, 0.2, 1.0, gripper_force=0.0)
    assert out["intended_opening"] == 0.004                         # latched
    c.safe_state()
    c.deactivate()
    c.activate()                                                    # a new run: the graph's clock starts afresh
    assert LatchOnForce.resets == resets + 1
    out = _settle(h, 0.0, 1.0, gripper_force=0.0)
    assert out["intended_opening"] == 0.015
    assert out["gripper_opening"] == pytest.approx(0.015, abs=3e-4)
    c.close()


def test_reactivation_forgets_the_cue_and_the_intent_opening_rate():
    """After a re-activation whose clock started afresh, the rate of intent_opening from the previous run (a jump
    there: -10 m/s) was taken as the operator's intended rate: the hand pulled the gripper with 30 N more at
    the first step; and the previous run's intent_cue was still in state.extra."""
    h = Harness(SimOmega7, {"intent": "hold"})
    c = h.comp
    c.configure()
    c.activate()
    _settle(h, 0.0, 0.5, intent_opening=0.02, intent_cue=0.5)
    out = h.step(0.501, intent_opening=0.01)                        # a jump in the last step of the run
    c.safe_state()
    c.deactivate()
    c.activate()
    x, v = out["gripper_opening"], out["gripper_velocity"]
    out = h.step(0.0, intent_opening=Sample(0.01, 0.0), intent_cue=None)    # a new run: no cue received yet
    k, b = c.params.hand_stiffness, c.params.hand_damping
    assert out["hand_force"] == pytest.approx(k * (0.01 - x) - b * v, abs=1e-9)     # no intended rate yet
    assert "cue" not in c.state.extra and "cue_stamp" not in c.state.extra
    out = _settle(h, 0.0, 1.0, intent_opening=0.01)
    assert out["gripper_opening"] == pytest.approx(0.01, abs=3e-4)
    c.close()


# ------------------------------------------------------------------------------------------------ sim-gripper
def test_sim_gripper_moves_after_a_reactivation_whose_clock_starts_afresh():
    """The servo's integration time was kept across activate(): in a new run whose clock starts at 0 again the
    fingers stood still (every step looked like no time had passed) until the clock passed the old run's end."""
    h = Harness(SimGripper, {"object_width": None})
    c = h.comp
    c.configure()
    c.activate()
    out = _settle(h, 0.0, 1.0, opening_command=0.03)
    x_end = out["opening"]
    c.safe_state()
    c.deactivate()
    c.activate()
    h.step(0.0, opening_command=0.08)
    out = _settle(h, 0.0, 0.3, opening_command=0.08)
    assert out["opening"] == pytest.approx(min(0.08, x_end + 0.05 * 0.3), abs=2e-3)   # at max_speed
    assert out["velocity"] > 0.0
    assert h.samples["opening"].stamp == pytest.approx(0.3)
    c.close()


def test_sim_gripper_reactivation_with_a_running_clock_holds_the_grip():
    """Re-activation on a clock that goes on (the safe state's hold, then commands again): the grip stays where it
    was held, and the first step after activate() reports no motion."""
    params = {"object_width": 0.015, "initial_opening": 0.02}
    h = Harness(SimGripper, params)
    c = h.comp
    c.configure()
    c.activate()
    out = _settle(h, 0.0, 2.0, opening_command=0.0146)
    f0 = out["contact_force"]
    c.safe_state()
    c.deactivate()
    c.activate()
    out = h.step(5.0, opening_command=0.0146)
    assert out["velocity"] == 0.0 and out["contact_force"] == pytest.approx(f0, rel=1e-9)
    out = _settle(h, 5.0, 0.5, opening_command=0.0146)
    assert out["contact_force"] == pytest.approx(f0, rel=1e-6) and math.isfinite(out["opening"])
    c.close()


def test_intent_reset_is_optional():
    """An intent without reset() still re-activates (the hook is optional, as operator.py says)."""
    h = Harness(SimOmega7, {"intent": {"type": "hold", "opening": 0.01}})
    assert not hasattr(op.make_intent("hold"), "reset")
    h.comp.configure()
    h.comp.activate()
    h.comp.deactivate()
    h.comp.activate()
    assert _settle(h, 0.0, 0.5)["intended_opening"] == 0.01
    h.comp.close()
