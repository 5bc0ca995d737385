"""dynamixel-gripper: a lost status packet at start-up is retried (STARTUP_TRIES), and the driver's port waits for
answers in select() instead of dynamixel-sdk's polling loop (emulated servo on a pseudo-terminal)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import ERR_ACCESS, INST_PING, INST_SYNC_READ, INST_SYNC_WRITE, INST_WRITE  # noqa: E402
from fakes.followers import dynamixel_fixture, dynamixel_harness, packet_timeout_fixture  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices import dynamixel_gripper as dg  # noqa: E402

pytestmark = pytest.mark.timeout(60)

#: the answers of an XM430-W350's start-up: PING, Torque_Enable=0, Operating_Mode, Current_Limit, Goal_Current,
#: Drive_Mode (read; written only where time-based), Profile_Velocity, Present_Position, Goal_Position,
#: Torque_Enable=1, then the first SYNC_READ of the state
STARTUP_ANSWERS = 11
#: the tries of a start-up request (docs/followers.md; dynamixel_gripper.STARTUP_TRIES)
STARTUP_TRIES = 3


packet_timeout = packet_timeout_fixture()   # the emulator's slower adapter for a loaded machine
emu = dynamixel_fixture(15, position=1024)
harness = dynamixel_harness


def instructions(emu, inst):
    return [p for p in emu.rx_packets if p[2] == inst]


def test_start_up_has_the_answers_counted_here(emu):
    """The parametrised test below loses each of these in turn."""
    assert dg.STARTUP_TRIES == STARTUP_TRIES
    with harness(emu) as h:
        assert h.comp.startup_retries == 0
    answered = [p[2] for p in emu.rx_packets if p[2] != INST_SYNC_WRITE]   # (SYNC_WRITE is not answered)
    R = 0x02
    assert answered[:STARTUP_ANSWERS] == [INST_PING, INST_WRITE, INST_WRITE, R, INST_WRITE, R, INST_WRITE, R,
                                          INST_WRITE, INST_WRITE, INST_SYNC_READ]


@pytest.mark.parametrize("after", range(STARTUP_ANSWERS))
def test_one_lost_answer_at_start_up_is_retried(emu, after):
    emu.drop(1, after=after)
    with harness(emu, max_effort=5.0) as h:
        assert len(emu.dropped) == 1          # the answer was lost ...
        assert h.comp.startup_retries == 1    # ... and its request tried again
        assert emu.get(emu.table.operating_mode) == 5
        assert emu.get(emu.table.torque_enable) == 1
        assert emu.get(emu.table.goal_current) == 185
        assert h.comp.status()["startup_retries"] == 1
        out = h.step(0.0, opening_command=h.comp.opening_for(1024))
        assert out["opening"] == pytest.approx(h.comp.opening_for(1024), abs=1e-4)


def test_two_lost_answers_in_a_row_are_still_survived(emu):
    emu.drop(STARTUP_TRIES - 1, after=3)   # the Current_Limit read and its first retry's resync PING
    with harness(emu) as h:
        assert len(emu.dropped) == STARTUP_TRIES - 1
        assert h.comp.startup_retries == STARTUP_TRIES - 1
        assert emu.get(emu.table.torque_enable) == 1


def test_a_servo_that_never_answers_fails_after_the_tries_naming_port_id_baud(emu):
    emu.silent = True
    with pytest.raises(HardwareError) as ei:
        harness(emu).__enter__()
    msg = str(ei.value)
    assert "ping" in msg and "ID 15" in msg and emu.port in msg and "1000000 baud" in msg
    assert f"{STARTUP_TRIES} tries" in msg and "check power, cable, ID and baud rate" in msg
    assert len(instructions(emu, INST_PING)) == STARTUP_TRIES   # tried, and no more


def test_as_many_lost_answers_as_tries_fail_the_start_up(emu):
    emu.drop(STARTUP_TRIES, after=3)   # the Current_Limit read, then each retry's PING
    with pytest.raises(HardwareError, match=rf"reading Current_Limit: no valid answer from Dynamixel ID 15 on "
                                            rf".* at 1000000 baud .*{STARTUP_TRIES} tries"):
        harness(emu).__enter__()
    assert emu.get(emu.table.torque_enable) == 0   # never switched on


def test_lost_first_state_read_is_retried_and_its_failure_is_named(emu):
    emu.drop(STARTUP_TRIES, after=STARTUP_ANSWERS - 1)   # the SYNC_READ, then each retry's PING
    with pytest.raises(HardwareError, match=rf"reading the state \(SYNC_READ\): no valid answer from Dynamixel ID "
                                            rf"15 .*{STARTUP_TRIES} tries"):
        harness(emu).__enter__()
    assert len(instructions(emu, INST_SYNC_READ)) == 1   # the retries' PINGs were lost: no SYNC_READ repeated


def test_a_refused_write_is_not_retried(emu):
    emu.write_error = ERR_ACCESS
    with pytest.raises(HardwareError, match="refused"):
        harness(emu).__enter__()
    assert len(instructions(emu, INST_WRITE)) == 1
    assert not emu.dropped


def test_a_lost_answer_at_run_time_is_not_retried(emu):
    with harness(emu, read_timeout=5.0) as h:
        first = h.step(0.0, opening_command=h.comp.opening_for(1024))
        n = len(instructions(emu, INST_SYNC_READ))
        emu.drop(1)
        out = h.step(0.01, opening_command=h.comp.opening_for(1024))   # the last reading, as before
        assert out["opening"] == first["opening"]
        assert h.comp.comm_failures == 1 and h.comp.startup_retries == 0
        assert len(instructions(emu, INST_SYNC_READ)) == n + 1   # one request, not repeated within the step


# --- the waiting read ---------------------------------------------------------------------------------------------
def test_the_driver_port_is_the_waiting_subclass_not_the_test_patch(emu, monkeypatch):
    import dynamixel_sdk as sdk

    base_calls = []
    base = sdk.PortHandler.readPort   # (slow_adapter's patch, for tests that use the SDK directly)
    monkeypatch.setattr(sdk.PortHandler, "readPort", lambda self, n: base_calls.append(n) or base(self, n))
    with harness(emu) as h:
        cls = type(h.comp.port)
        assert cls is dg.port_handler_class() and issubclass(cls, sdk.PortHandler)
        assert cls.readPort is not sdk.PortHandler.readPort
        assert h.comp.port.max_wait == h.comp.params.serial_poll
        h.step(0.0, opening_command=h.comp.opening_for(1024))
    assert base_calls == []   # every read went through the driver's own readPort


def test_a_timed_out_transaction_waits_instead_of_spinning(emu, monkeypatch, packet_timeout):
    import dynamixel_sdk as sdk

    with harness(emu, read_timeout=5.0) as h:
        cls = type(h.comp.port)
        calls = []
        own = cls.readPort
        monkeypatch.setattr(cls, "readPort", lambda self, n: calls.append(n) or own(self, n))
        emu.silent = True
        assert h.comp._hw_read() is None                    # one request, its answer never comes
        assert h.comp.last_comm_error == h.comp.ph.getTxRxResult(sdk.COMM_RX_TIMEOUT)
        # the SDK's busy loop reads thousands of times per packet timeout, a 0.5 ms poll hundreds; this waits until
        # the timeout in slices of serial_poll (10 ms by default)
        assert h.comp.params.serial_poll == 0.01
        assert 1 <= len(calls) <= 3 + packet_timeout / 0.01
        assert len(instructions(emu, INST_SYNC_READ)) >= 1


class _Ser:
    def __init__(self, data=b""):
        self.data = data

    def fileno(self):
        return 99

    def read(self, n):
        out, self.data = self.data[:n], self.data[n:]
        return out


def test_wait_is_bounded_by_the_sdk_packet_timeout_and_max_wait(monkeypatch):
    waits = []
    monkeypatch.setattr(dg.select, "select", lambda r, w, x, t: waits.append(t) or (r, [], []))
    port = dg.port_handler_class()("/dev/null-test")
    port.ser = _Ser(b"\x01\x02\x03")
    port.max_wait = 0.01
    port.setPacketTimeoutMillis(4.0)          # 4 ms left: the wait ends at the SDK's timeout (and a hair)
    assert port.readPort(2) == b"\x01\x02"
    assert 0 < waits[-1] <= 0.004 + dg._TIMEOUT_MARGIN
    port.setPacketTimeoutMillis(500.0)        # far away: at most max_wait, then the SDK checks its timeout
    assert port.readPort(5) == b"\x03"
    assert waits[-1] == pytest.approx(0.01)
    n = len(waits)
    port.packet_timeout = 0                   # timed out (the SDK sets 0): no wait, the read of what is there
    assert port.readPort(4) == b""
    port.setPacketTimeoutMillis(500.0)
    assert port.readPort(0) == b""            # nothing asked for: no wait
    assert len(waits) == n
