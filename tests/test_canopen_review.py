"""canopen-gripper review: the frames' timestamps on other clocks (heartbeat and TPDO arrival), a drive resting away
from its open end at start-up, and the drive leaving NMT OPERATIONAL; against the emulated CiA 402 drive on python-can's
virtual bus."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes.followers import canopen_harness, channel_fixture  # noqa: E402
from fakes.realtime import WAIT, drive_until  # noqa: E402
from fakes.realtime import drive as drive_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402

pytestmark = pytest.mark.timeout(60)

_T0 = time.monotonic()
#: Clocks python-can interfaces stamp received frames with (msg.timestamp): socketcan and the virtual bus give epoch
#: time; others a monotonic or perf_counter clock, a device's own counter from its power-on, a stamp far from the
#: host's epoch time (a device clock set elsewhere), or nothing at all (a constant).
CLOCKS = {
    "monotonic": time.monotonic,
    "perf_counter": time.perf_counter,
    "device counter": lambda: time.monotonic() - _T0,
    "epoch an hour ahead": lambda: time.time() + 3600.0,
    "constant": lambda: 0.0,
}


channel = channel_fixture()
harness = canopen_harness


@pytest.mark.parametrize("clock", list(CLOCKS), ids=list(CLOCKS))
def test_a_live_drive_is_not_lost_whatever_clock_stamps_its_frames(channel, clock):
    """The heartbeat's age was msg.timestamp compared with time.time(): a drive whose frames come stamped on another
    clock (monotonic, a device counter) was declared lost after read_timeout ("no heartbeat") while it worked; and a
    TPDO counted as received only when its stamp changed (one without stamps never did: no valid state)."""
    with Cia402Drive(5, channel, position=0, stamp=CLOCKS[clock]) as drive:
        with harness(channel, heartbeat_period=0.05, read_timeout=0.3) as h:
            drive_for(h, 0.07, 1.0)  # over three read_timeouts of heartbeats
            assert "heartbeat" not in getattr(h.comp, "last_error", "")
            assert drive.node.nmt.state == "OPERATIONAL"
            o = drive_until(h, 0.07, lambda o: o["opening"] == pytest.approx(0.07, abs=1e-4))
            assert o["opening"] == pytest.approx(0.07, abs=1e-4)  # it follows: the TPDOs are taken as they come


@pytest.mark.parametrize("clock", ["monotonic", "epoch an hour ahead", "constant"])
def test_a_stopped_heartbeat_is_seen_whatever_clock_stamps_it(channel, clock):
    """The drive's heartbeat stops (its producer switched off) while its PDOs go on: a HardwareError naming the
    missing heartbeat after read_timeout, whatever clock its frames were stamped with (stamped an hour ahead, the
    heartbeat looked fresh for an hour)."""
    with Cia402Drive(5, channel, position=0, stamp=CLOCKS[clock]) as drive:
        with harness(channel, heartbeat_period=0.05, read_timeout=0.3) as h:
            drive_for(h, 0.07, 0.2)
            drive.node.nmt.stop_heartbeat()
            t0 = time.monotonic()
            with pytest.raises(HardwareError, match=r"CANopen node 5 .*no heartbeat for .* s; the drive is gone"):
                drive_for(h, 0.07, WAIT)  # a failure bound
            assert 0.3 - 0.06 <= time.monotonic() - t0 < 0.3 + WAIT / 2


def test_a_gripper_resting_part_closed_holds_where_it_is_at_start_up(channel):
    """A drive resting away from counts 0 (the fingers part closed on an object) holds there when the driver enables
    it and until a command moves it; then it moves from there at max_speed. (The emulator's position demand started
    at 0 whatever its position, so enabling walked it to 0 counts, the open end: every test started the drive there,
    where a driver that latched 0 counts at start-up, opening the gripper and dropping the object, passed.)"""
    start = 60000
    with Cia402Drive(5, channel, position=start) as drive:
        with harness(channel, max_speed=0.02) as h:
            resting = h.comp.map.opening(start)
            assert h.comp._setpoint == pytest.approx(resting, abs=1e-9)
            t_end = time.monotonic() + 0.3
            while time.monotonic() < t_end:   # no command: the driver holds the measured opening
                h.t = time.monotonic()
                o = h.step(h.t, opening_command=None)
                assert o["opening"] == pytest.approx(resting, abs=1e-9), o
                time.sleep(0.005)
            assert drive.latched == start and round(drive.pos) == start
            target = resting + 0.01
            trace: list = []
            o = drive_until(h, target, lambda o: drive.latched == h.comp.map.counts(target)
                            and o["opening"] == pytest.approx(target, abs=1e-4), trace=trace)
            assert o["opening"] == pytest.approx(target, abs=1e-4) and drive.latched == h.comp.map.counts(target)
            openings = [s["opening"] for s in trace]
            assert min(openings) >= resting - 1e-9   # it opened from where it rested, never went past


def test_a_drive_leaving_nmt_operational_is_named(channel):
    """A drive sent to NMT PRE-OPERATIONAL (another master, or a reset: it boots into it) stops its PDOs: the
    HardwareError names its NMT state, without waiting read_timeout for TPDOs that cannot come."""
    with Cia402Drive(5, channel, position=0) as drive:
        with harness(channel, heartbeat_period=0.02, read_timeout=2.0) as h:
            drive_for(h, 0.07, 0.1)
            drive.node.nmt.state = "PRE-OPERATIONAL"
            t0 = time.monotonic()
            with pytest.raises(HardwareError, match=r"CANopen node 5 .*left NMT OPERATIONAL \(heartbeat: "
                                                    r"PRE-OPERATIONAL\)"):
                drive_for(h, 0.07, WAIT)  # a failure bound
            assert time.monotonic() - t0 < 1.5  # not after read_timeout (2 s)


class RecordingDrive(Cia402Drive):
    """The CiA 402 drive, recording each state its controlword took it to (with the controlword)."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.states: list[tuple[str, int]] = []

    def _controlword(self, cw: int) -> None:
        with self._lock:
            before = self.state
            super()._controlword(cw)
            if self.state != before:
                self.states.append((self.state, cw))


def test_a_drive_found_enabled_is_not_switched_off_at_start_up(channel):
    """A drive left in OPERATION ENABLED (closing keeps it holding, as every follower does) stays enabled when the
    driver starts again: canopen's state walk began from its default statusword 0 (none received yet), so its first
    controlword was "disable voltage": the power stage went off and a gripper holding an object let go."""
    with RecordingDrive(5, channel, position=0) as drive:
        with harness(channel) as h:
            goal = h.comp.map.counts(0.06)   # at rest at the goal: a drive still moving goes on when SYNCs come back
            drive_until(h, 0.06, lambda o: drive.latched == goal and abs(drive.pos - goal) < 1.0)
        assert drive.state == "OPERATION ENABLED"
        held = round(drive.pos)
        drive.states.clear()
        with harness(channel) as h:
            assert drive.state == "OPERATION ENABLED"
            assert drive.states == []   # never left OPERATION ENABLED
            o = h.step(time.monotonic(), opening_command=None)
            assert o["opening"] == pytest.approx(h.comp.map.opening(held), abs=1e-9)


def test_a_fault_found_at_start_up_is_reported_before_it_is_reset(channel):
    """A drive found in FAULT at start-up is reset by the state walk (fault reset, controlword bit 7) when
    reset_fault_at_start says so (by default it is refused: tests/test_canopen_units.py): its error code 0x603F
    is logged first (it was erased without a word)."""
    with RecordingDrive(5, channel, position=0) as drive:
        drive.inject_fault(0x2310)
        h = harness(channel, reset_fault_at_start=True)
        logs: list[str] = []
        h.ctx._log = logs.append
        with h:
            assert drive.state == "OPERATION ENABLED" and drive.get(0x603F) == 0
            assert [s for s, _ in drive.states][:1] == ["SWITCH ON DISABLED"]   # the fault reset
        assert any(re.search(r"CANopen node 5 .* was in FAULT \(statusword 0x[0-9A-F]{4}, error code 0x2310, .*\): "
                             r"resetting it", m) for m in logs), logs
