"""omega7's status: ``lost`` is a device that stopped answering (the SDK's communication error or timeout:
DeviceLostError), not any failure of a step; another failure (an SDK error of a device that still answers, a bug in
the driver) is reported as what it is, still faults the node, and the device is made safe at once. Every figure of
status() is of the current activation. Against the C stand-in of libdhd, as tests/test_leader_omega7.py."""

from __future__ import annotations

import re

import pytest

from teletouch import Sample
from teletouch.plugins.devices import dhd
from tests.test_leader_omega7 import harness

from fakes.dhd_standin import sdk_dir_fixture, standin_fixture

sdk_dir = sdk_dir_fixture("fdsdk-s14")
standin = standin_fixture()


def _write_fails(h, standin):
    standin.set_write_fails(1)   # dhdSetForceAndGripperForce answers -1, DHD_ERROR: the device still answers
    return dhd.DhdError, r"dhdSetForceAndGripperForce failed: error \(error 1\)"


def _driver_bug(h, standin):
    def broken() -> float:
        raise ZeroDivisionError("float division by zero")
    h.comp.dhd.gripper_gap = broken   # a bug in the driver's own Python, on a device that answers
    return ZeroDivisionError, r"ZeroDivisionError: float division by zero"


@pytest.mark.parametrize("fail", [_write_fails, _driver_bug], ids=["sdk-error", "driver-bug"])
def test_a_failure_that_is_not_a_lost_device_is_reported_as_what_it_is_and_made_safe(sdk_dir, standin, fail):
    """Any exception of a step was recorded as lost ("device lost"), and the step left the device as it was: with
    brakes_on_stop the 3 N of the step before stayed on the hand, brakes off, until the runtime's safe_state()."""
    with harness(sdk_dir) as h:
        h.step(0.0, gripper_force=3.0)
        assert standin.forces()[0][3] == pytest.approx(3.0)
        exc_type, text = fail(h, standin)
        with pytest.raises(exc_type):
            h.step(0.001, gripper_force=3.0)
        st = h.comp.status()
        assert st["lost"] == "", st
        assert pytest.approx(0.0) == st["gripper_force_n"]
        assert re.search(text, st["error"]), st["error"]
        # made safe by the step itself, before the fault reaches the runtime: no force on the hand, brakes on
        assert standin.forces()[0] == [0.0] * 4 and standin.flags()["brakes"]
        standin.set_write_fails(0)


def test_a_lost_device_is_still_lost_and_no_error(sdk_dir, standin):
    with harness(sdk_dir) as h:
        h.step(0.0, gripper_force=1.0)
        standin.unplug()
        with pytest.raises(dhd.DeviceLostError):
            h.step(0.001, gripper_force=1.0)
        st = h.comp.status()
        assert "stopped answering" in st["lost"] and st["error"] == "", st
        standin.replug()


def test_every_status_figure_is_of_the_current_activation(sdk_dir, standin):
    """lost and com_freq_hz started afresh at each activation, while the counters (timeguards, saturated, clamped,
    stale_commands, faded_in, watchdog_trips) ran on over the driver's lifetime: a second activation reported the
    first one's."""
    standin.set_timeguard_every(5)       # the 5th write (after activate's zero force) is skipped
    h = harness(sdk_dir, max_gripper_force=2.0)
    h.comp.configure()
    try:
        h.comp.activate()
        h.step(0.0, gripper_force=5.0)                                   # clamped
        h.step(0.001, gripper_force=5.0)                                 # clamped
        h.step(0.5, gripper_force=Sample(1.0, 0.001))                    # the command went stale
        h.step(0.501, gripper_force=1.0)                                 # fresh again: faded in; time guard
        h.comp.dhd.set_max_gripper_force(0.5)
        h.step(0.7, gripper_force=1.0)                                   # the SDK saturates it
        st = h.comp.status()
        assert st["clamped"] and st["stale_commands"] and st["faded_in"] and st["timeguards"] and st["saturated"]
        h.comp.safe_state()
        h.comp.deactivate()
        h.comp.activate()
        st = h.comp.status()
        counts = {k: st[k] for k in ("clamped", "stale_commands", "faded_in", "timeguards", "saturated",
                                     "watchdog_trips")}
        assert counts == dict.fromkeys(counts, 0), counts
        assert st["lost"] == "" and st["error"] == ""
        h.comp.safe_state()
        h.comp.deactivate()
    finally:
        h.comp.close()
