"""dynamixel-gripper: a failed Goal_Position write is held like a failed read (the next step's goal is the retry, a
fault only after ``read_timeout`` of failing writes), the safe state's hold is tried again at once and holds the goal
the servo has, a hardware error is still a fault at once, and the start-up's port clearing runs under the I/O lock.

Goal_Position goes out in a SYNC_WRITE, which the servo never answers (Protocol 2.0: no status packet, so no answer to
lose or corrupt): what fails is the port or the SDK's send. The faults are injected into the driver's real pyserial
port (as a USB glitch makes pyserial raise), only while a Goal_Position write is on its way; everything else speaks
Protocol 2.0 with the emulated servo on a pseudo-terminal."""

from __future__ import annotations

import errno
import re
import sys
import termios
import time
from pathlib import Path

import pytest
import serial

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import HW_OVERLOAD, INST_SYNC_WRITE  # noqa: E402
from fakes.followers import dynamixel_fixture, dynamixel_harness, goal_positions, packet_timeout_fixture  # noqa: E402
from fakes.realtime import WAIT, drive, drive_until, wait_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices import dynamixel_gripper as dg  # noqa: E402

pytestmark = pytest.mark.timeout(90)

packet_timeout = packet_timeout_fixture()   # the emulator's slower adapter for a loaded machine
emu = dynamixel_fixture(15, position=1024)

#: how the port fails in a Goal_Position write: (pyserial method, what it raises; None: it writes nothing, returns 0)
FAULTS = {
    "write raises": ("write", serial.SerialException("write failed: [Errno 5] Input/output error")),
    "tcflush raises": ("reset_input_buffer", termios.error(errno.EIO, "Input/output error")),
    "short write": ("write", None),   # the SDK's COMM_TX_FAIL ("Failed transmit instruction packet!")
}
#: the answers of an XM430-W350's start-up (tests/test_dynamixel_startup.py): the 11th is the first state read's
STARTUP_ANSWERS = 11


def harness(emu, **params):
    # no shutdown poll in the way: a step's requests are its state read, then its goal
    return dynamixel_harness(emu, **dict(dict(error_check_period=30.0), **params))


def near(x, abs=1e-3):
    return lambda o: o["opening"] == pytest.approx(x, abs=abs)


def logged(h) -> list[str]:
    lines: list[str] = []
    h.ctx.log = lines.append
    return lines


def goal(emu) -> int:
    return emu.get(emu.table.goal_position)


class GoalWriteFault:
    """The driver's pyserial port fails (``FAULTS[fault]``) in the next ``times`` Goal_Position writes (None: all of
    them), and only there: the state reads, and the writes after, work."""

    def __init__(self, comp, fault: str, times: int | None = 1):
        self.comp, self.left, self.failed = comp, times, 0
        self.method, self.exc = FAULTS[fault]

    def _broken(self, *args):
        if self.exc is None:
            return 0
        raise self.exc

    def __enter__(self) -> "GoalWriteFault":
        gsw, ser, real_tx = self.comp.gsw, self.comp.port.ser, self.comp.gsw.txPacket

        def tx():
            if self.left is not None and self.left <= 0:
                return real_tx()
            if self.left is not None:
                self.left -= 1
            self.failed += 1
            setattr(ser, self.method, self._broken)
            try:
                return real_tx()
            finally:
                delattr(ser, self.method)   # pyserial's own method again

        gsw.txPacket = tx
        return self

    def __exit__(self, *exc) -> None:
        del self.comp.gsw.txPacket


class FailingReads:
    """Every read of the driver's pyserial port raises as on a USB glitch (the state reads fail in the port)."""

    def __init__(self, ser):
        self.ser = ser

    def _broken(self, *args):
        raise serial.SerialException("device reports readiness to read but returned no data")

    def __enter__(self) -> "FailingReads":
        self.ser.read = self._broken
        return self

    def __exit__(self, *exc) -> None:
        del self.ser.read


# --- 1. one failed goal write: held, the next step's goal is the retry -------------------------------------------
@pytest.mark.parametrize("fault", list(FAULTS))
def test_one_failed_goal_write_is_not_a_fault_and_the_next_goal_reaches_the_servo(emu, fault):
    """Before, a failed Goal_Position write faulted the node at once, while a failed read is held within
    read_timeout."""
    with harness(emu) as h:
        drive_until(h, 0.05, near(0.05))
        had = h.comp.ticks_for(h.comp.sent_opening)
        assert wait_for(lambda: emu.rx_packets[-1][2] == INST_SYNC_WRITE)   # the last step's goal taken
        assert goal(emu) == had
        resyncs, n = h.comp.resyncs, len(emu.rx_packets)
        with GoalWriteFault(h.comp, fault) as f:
            out = h.step(h.t + 0.005, opening_command=0.04)   # no fault
        assert f.failed == 1
        assert out["opening"] == pytest.approx(0.05, abs=1e-3)   # the step's state read went on as usual
        assert h.comp.write_failures == 1 and h.comp.status()["write_failures"] == 1
        assert h.comp.last_write_error.startswith("sending Goal_Position")
        assert h.comp.port.is_using is False   # the SDK's busy flag, left set by an exception, cleared
        assert h.comp._setpoint == h.comp.sent_opening   # back to the goal the servo has: the speed limit counts
        time.sleep(0.05)
        assert not [p for p in emu.rx_packets[n:] if p[2] == INST_SYNC_WRITE] and goal(emu) == had   # none went out
        # the next steps' goals reach the servo: tracking again, the bus resynchronised once (what went out is unknown)
        out = drive_until(h, 0.04, lambda o: near(0.04)(o) and goal(emu) == h.comp.ticks_for(0.04))
        assert goal(emu) == h.comp.ticks_for(0.04) and out["opening"] == pytest.approx(0.04, abs=1e-3)
        assert h.comp.write_failures == 1 and h.comp.resyncs == resyncs + 1


# --- 2. goal writes failing for longer than read_timeout: a fault saying what, where and for how long -------------
@pytest.mark.parametrize("fault", ["write raises", "short write"])
def test_goal_writes_failing_past_read_timeout_fault_naming_servo_port_baud_and_how_long(emu, fault):
    with harness(emu, read_timeout=0.3) as h:
        drive(h, 0.05, 0.1)
        with GoalWriteFault(h.comp, fault, times=None) as f:
            t0 = time.monotonic()
            h.step(h.t + 0.005, opening_command=0.05)   # the first failed write: held
            with pytest.raises(HardwareError) as ei:
                drive(h, 0.05, WAIT)   # a failure bound
            assert time.monotonic() - t0 >= 0.3
        msg = str(ei.value)
        for words in ("sending Goal_Position to Dynamixel ID 15 (XM430-W350)", emu.port, "1000000 baud",
                      "read_timeout 0.3 s", f"{f.failed} failed writes in a row", "the gripper no longer follows"):
            assert words in msg, (words, msg)
        assert float(re.search(r"failed for (\d+\.\d+) s", msg)[1]) >= 0.3, msg   # (printed to the ms)
        assert "no valid state" not in msg   # the reads were answered all along: the writes' fault
        if fault == "write raises":
            assert "serial port failed" in msg and "unplugged" in msg and "replug" in msg, msg
            assert ei.value.__cause__ is FAULTS[fault][1]   # chained from pyserial's error
        else:
            assert "Failed transmit instruction packet" in msg, msg


# --- 3. the safe state's hold: tried again at once, and the goal the servo has --------------------------------------
def test_the_hold_is_tried_again_when_the_port_fails_in_it(emu):
    """Before, one port failure in the hold's write left the servo without it (logged "could not command")."""
    with harness(emu) as h:
        lines = logged(h)
        drive_until(h, 0.05, near(0.05))
        assert wait_for(lambda: emu.rx_packets[-1][2] == INST_SYNC_WRITE)   # the last step's goal taken
        since = time.monotonic()
        with GoalWriteFault(h.comp, "write raises") as f:
            h.safe_state()
        assert not [m for m in lines if "could not command" in m], lines
        assert f.failed == 1 and h.comp.write_failures == 1
        hold = h.comp.ticks_for(h.comp._hold_at)
        assert wait_for(lambda: goal_positions(emu, since) == [hold]), (goal_positions(emu, since), hold)
        assert goal(emu) == hold   # the hold went out, once


def test_a_hold_that_cannot_be_sent_says_so_after_its_tries(emu):
    with harness(emu) as h:
        lines = logged(h)
        drive(h, 0.05, 0.05)
        with GoalWriteFault(h.comp, "write raises", times=None) as f:
            h.safe_state()
        assert f.failed == dg.HOLD_TRIES
        failures = [m for m in lines if "could not command" in m]
        assert len(failures) == 1 and "sending Goal_Position: the serial port failed" in failures[0], lines
        assert f"({dg.HOLD_TRIES} tries)" in failures[0]


def test_a_hold_after_failed_writes_and_reads_holds_the_goal_the_servo_has(emu):
    """Reads and goal writes failing (within read_timeout) while the command moves on: the servo still has the last
    goal that went out, and the hold is that goal, not a set-point that never reached it (which would move the
    fingers by up to read_timeout x max_speed)."""
    with harness(emu, read_timeout=5.0) as h:
        lines = logged(h)
        drive_until(h, 0.05, near(0.05))
        had = h.comp.ticks_for(h.comp.sent_opening)
        assert wait_for(lambda: goal(emu) == had)
        with FailingReads(h.comp.port.ser), GoalWriteFault(h.comp, "write raises", times=None) as f:
            drive(h, 0.03, 0.2)   # 0.2 s at 0.05 m/s: 10 mm the set-point would have moved
        assert f.failed > 1 and h.comp.comm_failures >= 1
        assert goal(emu) == had   # none of those goals reached the servo
        with FailingReads(h.comp.port.ser):
            since = time.monotonic()
            h.safe_state()   # the reads still fail: the state is stale
        assert not [m for m in lines if "could not command" in m], lines
        assert h.comp.ticks_for(h.comp._hold_at) == had
        assert wait_for(lambda: goal_positions(emu, since) == [had]) and goal(emu) == had


# --- 4. a hardware error is no failed write to hold: a fault at once -----------------------------------------------
def test_a_hardware_error_while_goal_writes_fail_is_a_fault_at_the_next_step(emu):
    """A SYNC_WRITE has no status packet: the servo's error shows in the state read's alert bit, a fault at once
    (not held within read_timeout like the failing writes)."""
    with harness(emu, read_timeout=5.0) as h:
        drive(h, 0.05, 0.1)
        with GoalWriteFault(h.comp, "write raises", times=None):
            h.step(h.t + 0.005, opening_command=0.05)   # a failed write: held
            emu.inject_hardware_error(HW_OVERLOAD)
            with pytest.raises(HardwareError, match=r"Dynamixel ID 15 .*reports a hardware error.*overload"):
                h.step(h.t + 0.01, opening_command=0.05)


# --- 5. the start-up's port clearing, under the I/O lock as every other use of the port ---------------------------
@pytest.mark.parametrize("after", [3, STARTUP_ANSWERS - 1], ids=["Current_Limit read", "first state read"])
def test_start_up_retries_clear_the_port_under_the_io_lock(emu, monkeypatch, after):
    h = harness(emu)
    owned: list[bool] = []
    cls = dg.port_handler_class()
    real = cls.clearPort

    def clear(port):
        owned.append(h.comp._io_lock._is_owned())
        return real(port)

    monkeypatch.setattr(cls, "clearPort", clear)
    emu.drop(1, after=after)
    with h:
        assert h.comp.startup_retries == 1
    assert owned and all(owned), owned
