"""Review of the omega7 leader and its libdhd binding, against the C stand-in of libdhd (tests/fakes/dhd_standin.c,
built and loaded as tests/test_leader_omega7.py does): the ctypes path that runs against the hardware is under test."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from teletouch.plugins.devices import dhd
from tests.test_leader_omega7 import harness

from fakes.dhd_standin import sdk_dir_fixture, standin_fixture

sdk_dir = sdk_dir_fixture("fdsdk-review")
standin = standin_fixture()   # its firmware's clock frozen (moved only by standin.advance_clock)


# ------------------------------------------------------------------------------ forces that cannot be switched off
def test_deactivate_keeps_the_firmware_watchdog_when_forces_cannot_be_switched_off(sdk_dir, standin):
    """dhdEnableForce(0) failed at deactivate (and the zero-force write too: the step's 3 N stayed on the hand, no
    brakes): deactivate switched the firmware watchdog off anyway, removing the last protection that takes the force
    off the hand once the host stops sending, and said nothing (only safe_errors counted it)."""
    h = harness(sdk_dir, brakes_on_stop=False)
    h.comp.configure()
    h.comp.activate()
    h.step(0.0, gripper_force=3.0)
    assert standin.forces()[0][3] == pytest.approx(3.0)
    standin.set_write_fails(1)
    standin.set_force_off_fails(1)
    with pytest.raises(dhd.DhdError) as ei:
        h.comp.deactivate()
    msg = str(ei.value)
    assert "dhdEnableForce(0) failed" in msg and "forces may still be on" in msg, msg
    assert "firmware watchdog (20 ms) is left on" in msg, msg
    assert standin.get_watchdog() == 160   # still on
    assert standin.flags()["force_enabled"] and standin.forces()[0][3] == pytest.approx(3.0)
    standin.advance_clock(0.0201)   # no force command for longer than the watchdog: the device cuts the force
    assert standin.forces()[0] == [0.0] * 4 and not standin.flags()["force_enabled"]
    assert standin.get_force_off_cause() == dhd.DHD_FORCEOFF_WATCHDOG
    standin.set_write_fails(0)
    standin.set_force_off_fails(0)
    h.comp.close()   # forces can be switched off now: then the watchdog goes off too
    assert standin.get_watchdog() == 0 and not standin.flags()["open"]


def test_close_keeps_the_firmware_watchdog_when_forces_cannot_be_switched_off(sdk_dir, standin):
    """close() without deactivate (e.g. after a failed start-up): dhdEnableForce(0) failing was ignored (``pass``)
    and the watchdog switched off before dhdClose."""
    h = harness(sdk_dir, brakes_on_stop=False)
    h.comp.configure()
    h.comp.activate()
    h.step(0.0, gripper_force=3.0)
    standin.set_force_off_fails(1)
    with pytest.raises(dhd.DhdError, match=r"close: dhdEnableForce\(0\) failed.*forces may still be on"):
        h.comp.close()
    assert standin.get_watchdog() == 160 and not standin.flags()["open"]   # closed all the same
    assert h.comp.dhd is None
    h.comp.close()   # a second close has nothing left to do


def test_forces_that_cannot_be_switched_off_without_the_watchdog_are_reported(sdk_dir, standin):
    with harness(sdk_dir, firmware_watchdog=0) as h:
        h.step(0.0, gripper_force=1.0)
        standin.set_force_off_fails(1)
        try:
            with pytest.raises(dhd.DhdError, match=r"forces may still be on; no firmware watchdog is set "
                                                   r"\(firmware_watchdog: 0\)"):
                h.comp.deactivate()
        finally:
            standin.set_force_off_fails(0)
        h.comp.activate()   # (the harness deactivates again at the end)


# ------------------------------------------------------------------------------ figures of a new activation
def test_a_new_activation_reads_the_com_freq_again_and_forgets_a_lost_device(sdk_dir, standin):
    """_next_freq and lost were kept across activations: after a re-activation (graph time from 0 again) the SDK's
    communication rate was not read until graph time passed the previous activation's last reading, and status()
    still said the device was lost although it answered again."""
    standin.set_com_freq(3.9)
    h = harness(sdk_dir)
    h.comp.configure()
    try:
        h.comp.activate()
        h.step(5.0)
        assert h.comp.status()["com_freq_hz"] == pytest.approx(3900.0)
        standin.unplug()
        with pytest.raises(dhd.DeviceLostError):
            h.step(5.001)
        assert h.comp.status()["lost"]
        standin.replug()
        h.comp.safe_state()
        h.comp.deactivate()
        standin.set_com_freq(2.0)
        h.comp.activate()
        st = h.comp.status()
        assert st["lost"] == "" and math.isnan(st["com_freq_hz"]), st   # nothing measured in this activation yet
        h.step(0.0)
        assert h.comp.status()["com_freq_hz"] == pytest.approx(2000.0)
        h.comp.safe_state()
        h.comp.deactivate()
    finally:
        h.comp.close()


# ------------------------------------------------------------------------------ the translational force limit
@pytest.mark.parametrize("command", [(0.0, 0.0, 1e200), (-1e200, 0.0, 0.0), (1e308, 1e308, 1e308),
                                     (1e155, -1e155, 0.0)])
def test_a_huge_finite_force_is_scaled_to_max_force_not_zeroed(sdk_dir, standin, command):
    """The guard's norm (np.linalg.norm: the sum of squares) overflowed to inf for a finite command above ~1e154 N,
    so the command was scaled by max_force / inf = 0: zero force (and a RuntimeWarning in the haptic loop), not the
    command scaled to norm max_force as docs/leaders.md says."""
    c = np.array(command)
    with harness(sdk_dir, max_force=4.0) as h:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            h.step(0.0, force=c)
        sent = np.array(standin.forces()[1][:3])
        assert np.linalg.norm(sent) == pytest.approx(4.0), sent
        np.testing.assert_allclose(sent, 4.0 * (c / np.abs(c).max()) / np.linalg.norm(c / np.abs(c).max()))
        assert h.comp.status()["clamped"] == 1
        assert not caught, [str(w.message) for w in caught]   # no overflow warning either


# ------------------------------------------------------------------------------ brakes released before forces
def test_activate_releases_the_brakes_before_it_enables_forces(sdk_dir, standin):
    """dhdSetBrakes(DHD_OFF) puts the device in IDLE mode, no current to the motors (Force Dimension's API): activate
    called it after dhdEnableForce(DHD_ON), so on the real device every force write did nothing. The stand-in models
    the modes now (it did not, and the order went unseen)."""
    h = harness(sdk_dir, brakes_on_stop=True)
    h.comp.configure()
    assert standin.flags()["brakes"] and not standin.flags()["force_enabled"]
    h.comp.activate()
    assert standin.flags()["force_enabled"] and not standin.flags()["brakes"]   # FORCE mode
    assert h.comp.dhd.force_status() == (True, 0)
    h.step(0.0, gripper_force=2.0, force=np.array([0.0, 0.0, 1.5]))
    applied, commanded = standin.forces()
    assert applied[2] == pytest.approx(1.5) and applied[3] == pytest.approx(2.0), (applied, commanded)
    h.comp.deactivate()
    assert standin.flags()["brakes"] and not standin.flags()["force_enabled"] and standin.forces()[0] == [0.0] * 4
    h.comp.close()


def test_forces_that_do_not_come_on_at_activate_are_said(sdk_dir, standin):
    """The device can keep its forces off (its force button, a safety feature): the operator then feels nothing, and
    nothing said so unless a step came late."""
    standin.set_force_on_refused(2)   # the velocity threshold
    h = harness(sdk_dir)
    logs: list[str] = []
    h.ctx._log = logs.append
    h.comp.configure()
    h.comp.activate()
    assert any("forces did not come on" in m and "the velocity threshold" in m for m in logs), logs
    h.comp.deactivate()
    h.comp.close()


# ------------------------------------------------------------------------------ a safe state that fails
def test_a_safe_state_whose_forces_stay_on_raises_and_status_keeps_the_force(sdk_dir, standin):
    """The zero-force write and dhdEnableForce(0) both failed (the device answers, not lost): safe_state() only
    counted it in safe_errors, said nothing, and status() reported 0 N while 3 N stayed on the hand (without a
    firmware watchdog, for the rest of the run)."""
    h = harness(sdk_dir, brakes_on_stop=False, firmware_watchdog=0)
    logs: list[str] = []
    h.ctx._log = logs.append
    h.comp.configure()
    h.comp.activate()
    h.step(0.0, gripper_force=3.0)
    standin.set_write_fails(1)
    standin.set_force_off_fails(1)
    try:
        with pytest.raises(dhd.DhdError, match=r"safe_state: the zero-force write did not go through and "
                                               r"dhdEnableForce\(0\) failed .*the forces may still be on; no firmware "
                                               r"watchdog is set"):
            h.comp.safe_state()
        assert standin.forces()[0][3] == pytest.approx(3.0)   # still on
        st = h.comp.status()
        assert st["gripper_force_n"] == pytest.approx(3.0) and st["safe_errors"] >= 1   # before: 0 N
        assert any("forces may still be on" in m for m in logs), logs
    finally:
        standin.set_write_fails(0)
        standin.set_force_off_fails(0)
    h.comp.safe_state()   # the device takes it again: safe, nothing raised
    assert standin.forces()[0] == [0.0] * 4 and h.comp.status()["gripper_force_n"] == 0.0
    h.comp.deactivate()
    h.comp.close()


def test_a_safe_state_of_a_device_that_is_gone_does_not_raise(sdk_dir, standin):
    h = harness(sdk_dir)
    h.comp.configure()
    h.comp.activate()
    h.step(0.0, gripper_force=2.0)
    standin.unplug()
    h.comp.safe_state()   # nothing can be set on it; its firmware takes the forces off a USB disconnection
    assert h.comp.status()["safe_errors"] >= 1
    standin.replug()
    h.comp.close()
