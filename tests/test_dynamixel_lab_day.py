"""dynamixel-gripper on a lab day (found by a lab-setup audit against the emulator): the USB adapter pulled mid-run
(or a transient serial error), an RH-P12-RN with the X-series' default ticks, a ping that finds nobody, and a port
that is not a serial port.

The pull is emulated as the audit did it: the emulated servo goes away with the pty's master side
(``DynamixelEmulator.unplug``), so the driver's real pyserial port fails as a pulled adapter's does. A transient
error is pyserial raising once from the port's read or write (what a USB glitch gives), the port staying usable
(tests/test_dynamixel_write_errors.py has more of the write's)."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest
import serial
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import INST_SYNC_WRITE, DynamixelEmulator  # noqa: E402
from fakes.followers import dynamixel_fixture, dynamixel_harness, packet_timeout_fixture  # noqa: E402
from fakes.realtime import WAIT, drive, drive_until, wait_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices import dynamixel_gripper as dg  # noqa: E402
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper  # noqa: E402
from teletouch.testing import Harness, load_text, make_registry  # noqa: E402

pytestmark = pytest.mark.timeout(90)

packet_timeout = packet_timeout_fixture()   # the emulator's slower adapter for a loaded machine
emu = dynamixel_fixture(15, position=1024)
harness = dynamixel_harness   # at 1 Mbaud


def chain(exc: BaseException) -> list[BaseException]:
    out = []
    while exc is not None and exc not in out:
        out.append(exc)
        exc = exc.__cause__ or exc.__context__
    return out


def logged(h) -> list[str]:
    lines: list[str] = []
    h.ctx.log = lines.append
    return lines


def names_the_lost_port(msg: str, emu) -> None:
    for words in ("Dynamixel ID 15 (XM430-W350)", emu.port, "1000000 baud", "unplugged", "replug",
                  "restart", "teletouch devices"):
        assert words in msg, (words, msg)


class FlakyPort:
    """The driver's pyserial port, whose read or write raises as pyserial does on a USB glitch (``times`` times after
    ``after`` calls that work, then it works again: the adapter stayed plugged in)."""

    def __init__(self, ser, method: str, times: int, exc: Exception, after: int = 0):
        self.ser, self.method, self.left, self.exc, self.raised, self.after = ser, method, times, exc, 0, after
        self.real = getattr(ser, method)

    def __call__(self, *args):
        if self.after > 0:
            self.after -= 1
        elif self.left > 0:
            self.left -= 1
            self.raised += 1
            raise self.exc
        return self.real(*args)

    def __enter__(self) -> "FlakyPort":
        setattr(self.ser, self.method, self)
        return self

    def __exit__(self, *exc) -> None:
        setattr(self.ser, self.method, self.real)


NO_DATA = serial.SerialException("device reports readiness to read but returned no data (device disconnected or "
                                 "multiple access on port?)")


# --- 1. the port itself failing ----------------------------------------------------------------------------------
def test_adapter_pulled_mid_run_is_a_hardware_error_naming_servo_port_and_baud(emu):
    with harness(emu, read_timeout=0.3) as h:
        lines = logged(h)
        drive(h, 0.05, 0.1)
        emu.unplug()
        with pytest.raises(HardwareError) as ei:
            drive(h, 0.05, WAIT)   # a failure bound
        names_the_lost_port(str(ei.value), emu)
        # chained from what pyserial (or termios under it) raised
        assert any(isinstance(e, dg.PORT_ERRORS) for e in chain(ei.value)[1:]), chain(ei.value)
        assert h.comp.port.is_using is False   # the SDK's busy flag, left set by the exception, is cleared
        sent = h.comp.gsw.txPacket
        calls = []
        h.comp.gsw.txPacket = lambda: calls.append(1) or sent()
        h.safe_state()
    assert calls, "the safe state's hold write was not attempted"
    failures = [m for m in lines if "safe_state could not command" in m]
    assert failures and all("in use" not in m for m in failures), lines
    assert "sending Goal_Position" in failures[0] and "serial port failed" in failures[0], failures
    assert "unplugged" in failures[0]


def test_a_transient_read_error_is_a_failed_read_that_holds_and_the_port_recovers(emu):
    """A serial exception in one state read: a failed read (the step goes on with the last reading, as for a lost
    answer), not a fault; the next reads work (before, the SDK's busy flag stayed set and every later request
    failed "Port is in use")."""
    with harness(emu, read_timeout=5.0) as h:
        first = drive(h, 0.05, 0.1)
        with FlakyPort(h.comp.port.ser, "read", 1, NO_DATA) as flaky:
            out = h.step(h.t + 0.005, opening_command=0.05)
        assert flaky.raised == 1
        assert out["opening"] == pytest.approx(first["opening"], abs=2e-3)   # the last reading, held
        assert h.comp.comm_failures == 1 and "serial port failed" in h.comp.last_comm_error
        assert h.comp.port.is_using is False
        resyncs = h.comp.resyncs
        out = drive_until(h, 0.04, lambda o: o["opening"] == pytest.approx(0.04, abs=1e-3))
        assert out["opening"] == pytest.approx(0.04, abs=1e-3)   # tracking again
        assert h.comp.comm_failures == 1 and h.comp.resyncs == resyncs + 1 and h.comp.port_failure is None


def test_a_transient_write_error_is_a_failed_write_that_holds_and_the_hold_still_goes_out(emu):
    """A serial exception in the Goal_Position write: a failed write (held within read_timeout, as a failed read is;
    before, a fault at once), and the safe state's hold goes out on the port, which is not left "in use"."""
    with harness(emu, error_check_period=30.0) as h:   # (no poll: the step's writes are its read's, then its goal)
        lines = logged(h)
        drive(h, 0.05, 0.1)
        with FlakyPort(h.comp.port.ser, "write", 1, serial.SerialException("write failed: [Errno 5] I/O error"),
                       after=1) as flaky:
            h.step(h.t + 0.005, opening_command=0.05)
        assert flaky.raised == 1 and h.comp.write_failures == 1
        assert h.comp.last_write_error.startswith("sending Goal_Position: the serial port failed")
        names_the_lost_port(h.comp.last_write_error, emu)
        assert h.comp.port.is_using is False
        since = time.monotonic()
        h.safe_state()
        assert not [m for m in lines if "could not command" in m], lines
        # the hold reached the servo
        assert wait_for(lambda: any(p[2] == INST_SYNC_WRITE and p[0] >= since for p in emu.rx_packets))


def test_reads_failing_in_the_port_past_read_timeout_fault_chained_from_the_serial_error(emu):
    """The reads fail in the port (the writes still go out): within read_timeout the gripper holds, past it a fault
    that says the port failed, chained from pyserial's exception."""
    with harness(emu, read_timeout=0.3) as h:
        first = drive(h, 0.05, 0.1)
        with FlakyPort(h.comp.port.ser, "read", 10 ** 9, NO_DATA):
            t0 = time.monotonic()
            out = h.step(h.t + 0.005, opening_command=0.05)   # within read_timeout: the last reading, no fault
            assert out["opening"] == first["opening"]
            with pytest.raises(HardwareError) as ei:
                drive(h, 0.05, WAIT)
            assert time.monotonic() - t0 >= 0.25   # (read_timeout counts from the last good read, before t0)
        msg = str(ei.value)
        assert "no valid state" in msg and "read_timeout 0.3 s" in msg
        names_the_lost_port(msg, emu)
        assert ei.value.__cause__ is NO_DATA


def test_the_audit_run_ends_in_a_fault_naming_the_servo_and_the_hold_is_about_the_lost_port():
    """/tmp/audit_lab/dxl_unplug.sh in a test: a graph runs the gripper, the adapter is pulled after 0.5 s."""
    from teletouch.runtime import Runtime

    reg = make_registry("teletouch.plugins.devices.dynamixel_gripper")
    e = DynamixelEmulator(15, position=1024).start()
    try:
        text = f"""
name: dxl-unplug
clock: wall
duration: 10
faults: {{max_overruns: 0, watchdog: 0.5}}
nodes:
  - id: cmd
    plugin: mock-sensor
    rate: 100
    params: {{signal: sine, amplitude: 0.01, offset: 0.05, frequency: 0.5}}
  - id: gripper
    plugin: dynamixel-gripper
    rate: 100
    params: {{port: '{e.port}', baudrate: 1000000}}
    inputs: {{opening_command: {{from: cmd.value, max_age: 0.1}}}}
"""
        lines: list[str] = []
        rt = Runtime(load_text(text, reg), log=lines.append)
        pulled = threading.Event()

        def pull(node, t, out):
            if node == "gripper" and t >= 0.5 and not pulled.is_set():
                pulled.set()
                threading.Thread(target=e.unplug, daemon=True).start()

        rt.add_tap(pull)
        res = rt.run()
    finally:
        e.stop()
    assert pulled.is_set(), res.summary()
    assert res.status == "fault" and res.exit_code == 3, res.summary()
    # a HardwareError of the driver (pyserial's SerialException escaped unwrapped, naming no servo)
    assert "node 'gripper' exception: HardwareError: " in res.message, res.message
    names_the_lost_port(res.message, e)
    holds = [m for m in lines if "safe_state could not command" in m]
    assert all("in use" not in m for m in holds), holds
    assert all("serial port failed" in m for m in holds), holds


# --- 2. each preset's own ticks, and the servo's position limits -------------------------------------------------
RH = {"dxl_id": 1, "newtons_per_amp": 100.0, "max_effort": 30.0}


def test_each_preset_has_its_own_default_ticks():
    assert DynamixelGripper.Params().ticks() == (1024, 2048)
    assert DynamixelGripper.Params(model="x-series").ticks() == (1024, 2048)
    assert DynamixelGripper.Params(model="rh-p12-rn-a").ticks() == (0, 740)
    assert DynamixelGripper.Params(model="rh-p12-rn").ticks() == (0, 740)
    assert DynamixelGripper.Params(model="rh-p12-rn", ticks_closed=700).ticks() == (0, 700)   # one set, one not
    assert DynamixelGripper.Params().ticks_open is None   # None: the preset's
    with pytest.raises(ValidationError, match="ticks_open and ticks_closed must differ.*rh-p12-rn-a's default"):
        DynamixelGripper.Params(model="rh-p12-rn-a", ticks_closed=0)


@pytest.mark.parametrize("model", ["rh-p12-rn-a", "rh-p12-rn"])
def test_rh_p12_rn_with_the_default_ticks_tracks(model):
    """The audit: model rh-p12-rn with the default ticks (X-series 1024/2048) commanded goals beyond the gripper's
    0..1150 position limits, which the servo dropped, and the run ended ok. Now the preset's 0/740 apply."""
    with DynamixelEmulator(1, model, position=0) as e:   # open
        with harness(e, model=model, **RH) as h:
            want = round((0.03 - 0.075) / (-0.075 / 740))   # 444 ticks
            out = drive_until(h, 0.03, lambda o: e.get(e.table.goal_position) == want
                              and o["opening"] == pytest.approx(0.03, abs=1e-3))
            assert e.get(e.table.goal_position) == want   # the goals reached the servo (not dropped)
            assert out["opening"] == pytest.approx(0.03, abs=1e-3)   # and the fingers followed
            assert h.comp.position_limits == (0, 1150)   # read at start-up


@pytest.mark.parametrize("model, limit_item", [("rh-p12-rn-a", "max_position"), ("rh-p12-rn", "max_position")])
def test_ticks_outside_the_position_limits_are_refused_before_anything_is_written(model, limit_item):
    with DynamixelEmulator(1, model, position=0) as e:
        with pytest.raises(HardwareError) as ei:
            harness(e, model=model, ticks_closed=2048, **RH).__enter__()
        msg = str(ei.value)
        for words in ("ticks_closed 2048", "Min_Position_Limit 0", "Max_Position_Limit 1150", "ticks_open",
                      f"model {model}: ticks_open 0 (open), ticks_closed 740 (closed) by default", "Dynamixel ID 1"):
            assert words in msg, (words, msg)
        assert "ticks_open 0 outside" not in msg   # only the one outside is named as such
        assert e.get(e.table.torque_enable) == 0 and e.get(e.table.operating_mode) == 3   # nothing written
        # a servo whose limits were narrowed in its EEPROM: the preset's own default is refused, and said to be one
        e.stop()
    with DynamixelEmulator(1, model, position=0) as e:
        with e._lock:
            e._put(getattr(e.table, limit_item), 700)
        with pytest.raises(HardwareError, match=rf"ticks_closed 740 \(model {model}'s default\) outside the "
                                                r"position limits .*Max_Position_Limit 700"):
            harness(e, model=model, **RH).__enter__()


def test_x_series_limits_are_not_read_in_current_based_position_mode():
    """An X-series servo ignores Min/Max_Position_Limit in current-based position mode (the e-Manual: goal
    -1,048,575 .. 1,048,575): ticks below 0 (outside its 0..4095 limits) are not refused, and track."""
    with DynamixelEmulator(15, position=200) as e:
        with harness(e, ticks_open=-500, ticks_closed=524) as h:
            assert h.comp.position_limits is None
            out = drive_until(h, 0.06, lambda o: o["opening"] == pytest.approx(0.06, abs=1e-3))
            assert out["opening"] == pytest.approx(0.06, abs=1e-3)
            assert e.get(e.table.goal_position) < 0


def test_firmware_hint_mentions_the_ticks():
    hint = dg.firmware_hint(35073, "rh-p12-rn-a")
    assert "set model: rh-p12-rn" in hint and "ticks_open 0 (open)" in hint and "ticks_closed 740" in hint
    hint = dg.firmware_hint(35074, "xm430-w350")
    assert "set model: rh-p12-rn-a" in hint and "ticks_open 0 (open) and ticks_closed 740 (closed)" in hint
    assert "not xm430-w350's 1024/2048" in hint
    hint = dg.firmware_hint(1020, "rh-p12-rn-a")
    assert "ticks_open 1024" in hint and "ticks_closed 2048" in hint


# --- 3. messages: a ping that finds nobody, a port that is not a serial port --------------------------------------
def test_ping_without_answer_says_what_was_tried_and_the_common_set_ups(emu):
    emu.silent = True
    h = Harness(DynamixelGripper, dict(port=emu.port))   # dxl_id and baudrate left at their defaults
    h.ctx.clock_kind = "wall"
    with pytest.raises(HardwareError) as ei:
        h.__enter__()
    msg = str(ei.value)
    for words in ("ping: no valid answer from Dynamixel ID 15", "check power, cable, ID and baud rate",
                  "Tried ID 15 at 57600 baud (dxl_id and baudrate not set in the graph: the defaults, ID 15 at "
                  "57600 baud)",
                  "ID 1 at 57600 baud", "OpenManipulator-X gripper as ID 15 at 1000000 baud", "teletouch devices"):
        assert words in msg, (words, msg)


def test_ping_without_answer_names_only_the_defaults_left(emu):
    emu.silent = True
    with pytest.raises(HardwareError) as ei:
        harness(emu, dxl_id=15).__enter__()   # both set: baudrate by the harness
    msg = str(ei.value)
    assert "Tried ID 15 at 1000000 baud." in msg and "the default" not in msg, msg
    assert "ID 1 at 57600 baud" in msg
    emu_ids = harness(emu)   # dxl_id left: that one named as the default
    with pytest.raises(HardwareError, match=r"Tried ID 15 at 1000000 baud \(dxl_id not set in the graph: the "
                                            r"default, ID 15\)\."):
        emu_ids.__enter__()


def test_dev_null_is_not_a_serial_port():
    h = Harness(DynamixelGripper, dict(port="/dev/null"))
    h.ctx.clock_kind = "wall"
    with pytest.raises(HardwareError) as ei:
        h.__enter__()
    msg = str(ei.value)
    assert "/dev/null is not a serial port" in msg and "ENOTTY" in msg and "teletouch devices" in msg, msg
    assert "no other program" not in msg, msg


def test_a_regular_file_is_not_a_serial_port(tmp_path):
    f = tmp_path / "ttyUSB0"
    f.write_bytes(b"")
    h = Harness(DynamixelGripper, dict(port=str(f)))
    h.ctx.clock_kind = "wall"
    with pytest.raises(HardwareError, match=r"is not a serial port \(a regular file"):
        h.__enter__()
