"""canopen-gripper against an emulated CiA 402 drive (canopen LocalNode) on python-can's virtual bus."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes.followers import canopen_harness, channel_fixture, drive_fixture  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from fakes.realtime import WAIT, configure_fails, drive_until, wait_for  # noqa: E402
from fakes.realtime import drive as drive_for  # noqa: E402  ('drive' is the CiA 402 drive fixture here)
from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.canopen_gripper import CW_NEW_SETPOINT, CanopenGripper  # noqa: E402

pytestmark = pytest.mark.timeout(60)


channel = channel_fixture()
drive = drive_fixture(position=0, block_at=60000)
harness = canopen_harness


# The drive moves in real time and the set-point moves at max_speed over at most two nominal periods per step: on a
# loaded machine the steps come late and the gripper gets somewhere later than the nominal time. A test that needs it
# somewhere steps until it is there (drive_until; its timeout only bounds a failure), never for a fixed time.
BLOCK = 60000  # counts: the object the fixture's drive closes on


def at(opening):
    """drive_until's condition: the measured opening is ``opening`` (m)."""
    return lambda o: o["opening"] == pytest.approx(opening, abs=1e-4)


def handshake_done(drive, h, counts):
    """drive_until's condition: the drive latched ``counts`` and the set-point handshake is over (bit 4 low again, and
    the statusword's acknowledge low, so the drive has read that last frame): no frame is on its way, and the next
    write sends the next set-point."""
    return lambda o: drive.latched == counts and h.comp.handshake_idle()


def latched(drive, counts):
    """drive_until's condition: the drive latched the set-point ``counts`` (the steps that sent it have finished)."""
    return lambda o: drive.latched == counts


def squeezing(drive, h, effort=None):
    """drive_until's condition: the drive latched the closed set-point (0 m) and stands at the object, pressing (with
    ``effort`` N if given)."""
    return lambda o: (drive.latched == 100000 and o["effort"] > 0
                      and o["opening"] == pytest.approx(h.comp.map.opening(BLOCK), abs=1e-9)
                      and (effort is None or o["effort"] == pytest.approx(effort, rel=1e-6)))


def test_start_up_sequence(drive, channel):
    with harness(channel, max_effort=10.0, newtons_per_amp=20.0, max_speed=0.04) as h:
        assert drive.state == "OPERATION ENABLED"
        assert drive.node.nmt.state == "OPERATIONAL"
        assert drive.get(0x6061) == 1  # profile position
        # PDO mapping written by the master through SDO: TPDO1 statusword + position, RPDO1 target + controlword
        assert drive.get(0x1A00, 1) >> 16 == 0x6041 and drive.get(0x1A00, 2) >> 16 == 0x6064
        assert drive.get(0x1600, 1) >> 16 == 0x607A and drive.get(0x1600, 2) >> 16 == 0x6040
        assert drive.get(0x1A00, 3) >> 16 == 0x6061 and drive.get(0x1600, 3) >> 16 == 0x6060
        assert drive.get(0x1800, 2) == 1  # TPDO on every SYNC
        assert drive.get(0x1017) == 100  # heartbeat 100 ms
        assert drive.get(0x6081) == round(0.04 / (0.08 / 100000))  # profile velocity, counts/s
        assert drive.get(0x6073) == 250  # 10 N / 20 N/A = 0.5 A = 250 per mille of 2 A (exact: not rounded)
        assert wait_for(lambda: h.comp.node.nmt.timestamp is not None)  # heartbeats arrive


def test_closes_on_object_with_capped_current(drive, channel):
    with harness(channel, max_effort=10.0, newtons_per_amp=20.0) as h:
        o = drive_until(h, 0.06, at(0.06))
        assert o["opening"] == pytest.approx(0.06, abs=1e-4)
        assert o["effort"] == pytest.approx(0.0, abs=1e-9)
        o = drive_until(h, 0.0, squeezing(drive, h, effort=0.250 * 2.0 * 20.0))
        assert o["opening"] == pytest.approx(h.comp.map.opening(60000), abs=1e-6)  # blocked by the object
        assert o["effort"] == pytest.approx(0.250 * 2.0 * 20.0, rel=1e-6)  # max current 250 per mille of 2 A
        assert drive.latched == 100000  # the final set-point (0 m) was latched by the set-point handshake
        assert drive.get(0x6041) & 0x1000  # set-point acknowledged
        h.comp.safe_state()  # hold: target := actual position
        assert wait_for(lambda: drive.latched == 60000)
        drive_for(h, 0.08, 0.1)
        assert drive.latched == 60000  # commands are ignored after the safe state


def test_max_current_rounds_down(drive, channel):
    """The current cap never exceeds max_effort, not even by rounding: 0x6073 is rounded down (it was rounded up:
    167 per mille = 10.02 N here)."""
    with harness(channel, max_effort=10.0, newtons_per_amp=30.0) as h:
        # 10 N / 30 N/A = 0.3333 A = 166.67 per mille of 2 A -> 166 (9.96 N)
        assert drive.get(0x6073) == 166 == h.comp.max_current
        assert 166 / 1000 * 2.0 * 30.0 <= 10.0
        # squeeze the object at 60000 counts: the drive limits the current
        o = drive_until(h, 0.0, squeezing(drive, h, effort=0.166 * 2.0 * 30.0))
        assert o["effort"] <= 10.0
        assert o["effort"] == pytest.approx(0.166 * 2.0 * 30.0, rel=1e-6)
    with harness(channel, max_effort=0.3, newtons_per_amp=0.5) as h:  # exactly 300 per mille: no binary loss
        assert drive.get(0x6073) == 300
    # below one per mille of the rated current no cap at or below max_effort exists: refused, not rounded up
    configure_fails(harness(channel, max_effort=0.01, newtons_per_amp=20.0),
                    r"max_effort 0.01 N is below the smallest current limit .* 0.04 N")


class _FlakyRpdo:
    """Makes the next ``n`` RPDO1 frames of node 5 fail as socketcan does when its tx queue is full."""

    def __init__(self, bus, cob_id=0x205):
        self.bus, self.cob_id, self.n, self.failed = bus, cob_id, 0, 0
        self.real = bus.send
        bus.send = self.send

    def send(self, msg, timeout=None):
        import can

        if self.n > 0 and msg.arbitration_id == self.cob_id:
            self.n -= 1
            self.failed += 1
            raise can.CanOperationError("Failed to transmit: [Errno 105] No buffer space available")
        return self.real(msg, timeout)


def test_failed_setpoint_is_sent_again(drive, channel):
    """A set-point whose frame failed to go out is not taken as sent: the next write with the same target sends it
    (it was skipped forever: the target was recorded before the transmit)."""
    with harness(channel) as h:
        drive_until(h, 0.06, handshake_done(drive, h, h.comp.map.counts(0.06)))
        flaky = _FlakyRpdo(h.comp.network.bus)
        flaky.n = 1
        with pytest.raises(Exception, match="No buffer space"):
            h.comp._hw_write(0.05)
        assert flaky.failed == 1 and drive.latched == h.comp.map.counts(0.06)
        h.comp._hw_write(0.05)  # the same target again: sent this time
        assert wait_for(lambda: drive.latched == h.comp.map.counts(0.05))


def test_safe_state_hold_sent_after_failed_transmit(drive, channel):
    """The safe state always sends its hold set-point: a hold whose frames failed is sent by the next safe_state()
    (it was never sent again, and the drive kept squeezing towards the old set-point)."""
    with harness(channel) as h:
        drive_until(h, 0.06, at(0.06))
        o = drive_until(h, 0.0, squeezing(drive, h))  # closing on the object at 60000 counts; latched set-point 0 m
        assert drive.latched == 100000 and o["effort"] > 0
        logs = []
        h.ctx._log = logs.append
        flaky = _FlakyRpdo(h.comp.network.bus)
        flaky.n = 1  # the hold's set-point handshake fails (its first frame)
        h.comp.safe_state()  # logs the failure, never raises
        assert flaky.failed == 1 and drive.latched == 100000
        assert any("safe_state could not command" in m for m in logs)
        h.comp.safe_state()  # the bus works again: the hold goes out
        assert wait_for(lambda: drive.latched == 60000)
        drive_for(h, 0.07, 0.1)  # later commands are ignored
        assert drive.latched == 60000


def test_failed_hold_is_retried_by_the_next_step(drive, channel):
    with harness(channel) as h:
        drive_until(h, 0.06, at(0.06))
        drive_until(h, 0.0, squeezing(drive, h))
        flaky = _FlakyRpdo(h.comp.network.bus)
        flaky.n = 1
        h.comp.safe_state()
        assert flaky.failed == 1 and drive.latched == 100000
        # the runtime keeps stepping: each write retries the hold until it went out
        drive_until(h, 0.0, latched(drive, 60000))
        assert wait_for(lambda: drive.latched == 60000)


def test_safe_state_waits_for_a_send_in_progress(drive, channel):
    """safe_state() from another thread does not interleave with a step's command and send: it waits for them,
    then sends the hold last (so the step's set-point cannot replace the hold)."""
    import threading

    with harness(channel) as h:
        drive_until(h, 0.06, handshake_done(drive, h, h.comp.map.counts(0.06)))
        frames = []
        real = h.comp.rp1.transmit
        in_send, release = threading.Event(), threading.Event()

        def slow_transmit():
            frames.append((threading.current_thread().name, h.comp.rp1[0x607A].raw,
                           h.comp.rp1[0x6040].raw & CW_NEW_SETPOINT))
            if threading.current_thread().name == "stepper" and not release.is_set():
                in_send.set()
                release.wait(10.0)
            real()

        h.comp.rp1.transmit = slow_transmit
        h.t = time.monotonic()
        h.set(opening_command=0.05)
        stepper = threading.Thread(target=h.comp.step, args=(h.t, h.inputs), name="stepper")
        stepper.start()
        assert in_send.wait(10.0)
        safe = threading.Thread(target=h.comp.safe_state, name="safe")
        safe.start()
        time.sleep(0.1)
        assert [f[0] for f in frames] == ["stepper"]  # safe_state waits for the step's handshake
        release.set()
        stepper.join(10.0)
        safe.join(10.0)
        assert not stepper.is_alive() and not safe.is_alive()
        assert [f[0] for f in frames] == ["stepper", "safe", "safe"]
        stepped, hold = frames[0][1], frames[1][1]
        assert stepped > h.comp.map.counts(0.06)  # the step moved towards 0.05 m: its set-point raised (bit 4 high)
        assert hold == h.comp.map.counts(h.comp._setpoint) and frames[2][1] == hold
        # the hold at once, after the step's: bit 4 low, a pause longer than the drive's cycle, high
        assert [f[2] for f in frames] == [CW_NEW_SETPOINT, 0, CW_NEW_SETPOINT]
        assert wait_for(lambda: drive.latched == hold)
        drive_for(h, 0.05, 0.1)
        assert drive.latched == hold  # the hold stays


def test_setpoint_speed_limited(drive, channel):
    """The drive moves at profile velocity 0x6081 = max_speed, never faster, and the velocity port says so in m/s
    (closing: negative). The velocity of a step is the drive's own (its last SYNC period); it is max_speed whenever the
    set-point sent before is at least that period's travel ahead, which happens within a few steps (it was the last
    step's velocity, read after 0.5 s: lower on a loaded machine, where the drive catches up with a set-point whose
    steps come late)."""
    h = harness(channel, max_speed=0.02)
    h.ctx.rate = 20.0  # the set-point counts steps up to 0.1 s late at full max_speed (a loaded machine's steps)
    with h:
        trace: list = []
        t0 = time.monotonic()
        o = drive_until(h, 0.0, lambda o: o["velocity"] == pytest.approx(-0.02, rel=1e-3), trace=trace)   # a bound
        dt = time.monotonic() - t0
        assert o["opening"] > 0.08 - 0.02 * dt - 1e-3
        velocities = [s["velocity"] for s in trace]
        assert min(velocities) == pytest.approx(-0.02, rel=1e-3), velocities  # moving at max_speed
        assert all(v >= -0.02 * (1 + 1e-9) for v in velocities), velocities  # never faster


def test_profile_velocity_rounds_down(drive, channel):
    """The drive's own speed limit (what the ``open`` safe state's jump runs at) never exceeds max_speed: 0x6081 is
    rounded down (it was rounded to nearest: 62502 counts/s = 0.0500002 m/s here, and a limit below 1 count/s was
    raised to 1 count/s)."""
    with harness(channel, counts_closed=100003, max_speed=0.05) as h:
        # 0.05 m/s / (0.08 m / 100003 counts) = 62501.875 counts/s
        assert drive.get(0x6081) == 62501 == h.comp.profile_velocity
        assert drive.get(0x6081) * abs(h.comp.map.scale) <= 0.05
    with harness(channel, max_speed=0.04):   # exactly 50000 counts/s: not lost to binary rounding
        assert drive.get(0x6081) == 50000
    configure_fails(harness(channel, counts_closed=100, max_speed=0.0005),
                    r"max_speed 0.0005 m/s is below the slowest profile velocity 0x6081 .* 0.0008 m/s")


def test_safe_state_does_not_enable_a_stopped_drive(drive, channel):
    """A drive that left OPERATION ENABLED (its quick stop: an e-stop input, another master) is not enabled again by
    the safe state: RPDO1's controlword (enable operation) took it back to OPERATION ENABLED, and the ``open`` safe
    state's set-point then drove the fingers open."""
    with harness(channel, safe_mode="open") as h:
        drive_until(h, 0.06, handshake_done(drive, h, h.comp.map.counts(0.06)))
        logs = []
        h.ctx._log = logs.append
        drive._controlword(0x0002)   # quick stop (the drive's own input)
        assert drive.state == "QUICK STOP ACTIVE"
        with pytest.raises(HardwareError, match=r"left OPERATION ENABLED \(statusword 0x"):
            drive_for(h, 0.06, WAIT)   # a failure bound: raises at the next state
        frames = drive.rpdo_frames
        h.comp.safe_state()   # logs, never raises
        time.sleep(0.1)
        assert drive.state == "QUICK STOP ACTIVE" and drive.rpdo_frames == frames
        assert drive.latched == h.comp.map.counts(0.06)   # not the open set-point (0 counts)
        assert any("not in OPERATION ENABLED" in m for m in logs)


def test_heartbeat_period_must_fit_0x1017():
    # 0x1017 holds whole milliseconds (UNSIGNED16): 0.0004 s was written as 0 (heartbeat off, then faulted as a lost
    # drive after read_timeout), 70 s failed at start-up with "Value does not fit in specified type"
    for value in (0.0004, 70.0):
        with pytest.raises(ValidationError, match=r"heartbeat_period .* 0x1017"):
            CanopenGripper.Params(heartbeat_period=value)
    assert CanopenGripper.Params(heartbeat_period=0).heartbeat_period == 0
    assert CanopenGripper.Params(heartbeat_period=65.535).heartbeat_period == 65.535


def test_safe_state_open(drive, channel):
    with harness(channel, safe_mode="open") as h:
        drive_for(h, 0.07, 0.3)
        h.comp.safe_state()
        assert wait_for(lambda: drive.latched == 0)


def test_no_node_on_bus(channel):
    t0 = time.monotonic()
    configure_fails(harness(channel, sdo_timeout=0.2), r"no SDO answer from CANopen node 5 .*node id")
    assert time.monotonic() - t0 < 2.0


def test_bad_interface():
    with pytest.raises(ValidationError, match=r"interface 'no-such-interface' is not an interface python-can"):
        Harness(CanopenGripper, {"interface": "no-such-interface", "channel": "x"})
    configure_fails(Harness(CanopenGripper, {"interface": "serial", "channel": "/nonexistent/ttyCAN"}),
                    "cannot open CAN interface serial:/nonexistent/ttyCAN")


def test_not_a_402_device(channel):
    with Cia402Drive(5, channel, device_type=0x00000191):
        configure_fails(harness(channel), r"not a CiA 402 drive: device type 0x00000191")


def test_fault_with_emcy(drive, channel):
    with harness(channel) as h:
        drive_for(h, 0.05, 0.2)
        drive.inject_fault(0x2310)
        with pytest.raises(HardwareError, match=r"FAULT .*error code 0x2310.*EMCY Code 0x2310, Current"):
            drive_for(h, 0.05, WAIT)   # a failure bound: raises at the next state


def test_mode_change_is_a_fault(drive, channel):
    with harness(channel) as h:
        drive_for(h, 0.05, 0.1)
        drive.node.set_data(0x6060, 0, bytes([3]))  # someone switches the drive to profile velocity
        with pytest.raises(HardwareError, match=r"left profile position mode \(0x6061 = 3\)"):
            drive_for(h, 0.05, WAIT)   # a failure bound: raises at the next state


def test_node_goes_silent(drive, channel):
    # read_timeout 1 s: the emulated drive's TPDOs (a thread of this process) late by more than pdo_timeout for a
    # while on a loaded machine must not end the run before the drive goes silent
    with harness(channel, read_timeout=1.0, pdo_timeout=0.02) as h:
        drive_for(h, 0.05, 0.2)
        drive.go_silent()
        t0 = time.monotonic()
        with pytest.raises(HardwareError, match=r"no valid state|no heartbeat"):
            drive_for(h, 0.05, WAIT)
        # after read_timeout (counted from the last good state, up to a step before t0), and not a whole wait later
        assert 1.0 - 0.1 <= time.monotonic() - t0 < 1.0 + WAIT / 2


def test_with_eds_file(drive, channel, tmp_path):
    import canopen

    eds = tmp_path / "drive.eds"
    canopen.export_od(drive.od, str(eds))
    with harness(channel, eds=str(eds)) as h:
        o = drive_until(h, 0.075, at(0.075))
        assert o["opening"] == pytest.approx(0.075, abs=1e-4)
    configure_fails(harness(channel, eds=str(tmp_path / "missing.eds")), "cannot use the object dictionary")


def test_params_validation():
    with pytest.raises(ValidationError, match="calibration points must differ"):
        CanopenGripper.Params(counts_open=5, counts_closed=5)
    with pytest.raises(ValidationError, match="node_id"):
        CanopenGripper.Params(node_id=200)
    # a calibration opening in millimetres (80 m) is refused naming the field (the limits lay within 0-80 m)
    with pytest.raises(ValidationError, match=r"opening_at_counts_open \(80 m\) is beyond any gripper's opening"):
        CanopenGripper.Params(opening_at_counts_open=80)


def test_opening_limits_must_lie_within_the_calibration():
    # a gripper calibrated to open 50 mm, with the default max_opening of 80 mm: commands above 50 mm would be
    # extrapolated to counts past the open end
    with pytest.raises(ValidationError, match=r"max_opening \(80 mm\) is outside the calibrated range 0-50 mm "
                                              r"\(opening_at_counts_open, opening_at_counts_closed\)"):
        CanopenGripper.Params(opening_at_counts_open=0.05)
    with pytest.raises(ValidationError, match=r"min_opening \(5 mm\) is outside the calibrated range 10-80 mm"):
        CanopenGripper.Params(opening_at_counts_closed=0.01, min_opening=0.005)
    p = CanopenGripper.Params(opening_at_counts_open=0.05, max_opening=0.05, opening_at_counts_closed=0.01,
                              min_opening=0.01)
    assert (p.min_opening, p.max_opening) == (0.01, 0.05)


# --- the set-point handshake (controlword bit 4 / statusword bit 12) -----------------------------------------------
class _Frames:
    """Records each RPDO1 the driver sends: (target counts, bit 4, the last statusword's acknowledge bit 12)."""

    def __init__(self, comp):
        self.comp, self.sent = comp, []
        real = comp.rp1.transmit

        def transmit():
            self.sent.append((comp.rp1[0x607A].raw, bool(comp.rp1[0x6040].raw & CW_NEW_SETPOINT),
                              bool(comp.tp1[0x6041].raw & 0x1000)))
            real()

        comp.rp1.transmit = transmit


def test_each_set_point_waits_for_the_drive_to_acknowledge_the_one_before(drive, channel):
    """The drive reads its controlword once per control cycle (1 ms here): bit 4 low then high back to back, as the
    driver sent them, was no edge to it and the set-point was never taken (the fingers did not move). Now each
    set-point goes out with bit 4 high while the acknowledge is low, bit 4 goes low once the acknowledge is high."""
    with harness(channel) as h:
        frames = _Frames(h.comp)
        goal = h.comp.map.counts(0.04)
        done = handshake_done(drive, h, goal)
        drive_until(h, 0.04, lambda o: done(o) and abs(drive.pos - goal) < 1.0)   # (the axis moves in its own time)
        assert drive.latched == goal
        sent = frames.sent
        assert len(sent) >= 6
        for (target, high, ack), (target2, high2, _) in zip(sent, sent[1:]):
            if high:   # raised while the acknowledge was low; lowered next (same target) once it was high
                assert not ack and not high2 and target2 == target
            else:
                assert high2 and ack is True or not high2
        highs = [t for t, high, _ in sent if high]
        assert highs == sorted(highs) and len(set(highs)) == len(highs)   # each set-point raised once, closing
        assert h.comp.status()["setpoint_m"] == pytest.approx(0.04)


def test_a_set_point_the_drive_never_acknowledges_is_a_fault(channel):
    """A drive that does not take the set-point (bit 12 stays low: not in profile position after all, a drive that
    wants another handshake) is a HardwareError after read_timeout, naming the set-point and the statusword."""
    class Deaf(Cia402Drive):
        def _controlword(self, cw):
            super()._controlword(cw & ~CW_NEW_SETPOINT)   # bit 4 never seen: no set-point taken, no acknowledge

    with Deaf(5, channel, position=0) as d:
        with harness(channel, read_timeout=0.3) as h:
            with pytest.raises(HardwareError, match=r"CANopen node 5 .*did not take set-point \d+ \(statusword bit 12 "
                                                    r"set-point acknowledge\) within read_timeout \(0\.3\d* s; "
                                                    r"statusword 0x"):
                drive_for(h, 0.04, WAIT)   # a failure bound
            assert d.latched == 0


def test_back_to_back_pulses_are_no_edge_to_the_emulated_drive(drive, channel):
    """The emulator's control cycle, which the tests above rely on: frames within one cycle leave only the last seen;
    frames a cycle apart are each seen."""
    with harness(channel) as h:
        drive_until(h, 0.06, handshake_done(drive, h, h.comp.map.counts(0.06)))
        c = h.comp
        goal = c.map.counts(0.05)
        with c._io_lock:
            c._send_setpoint(c._target, new=True)   # bit 4 high left on, as the old pulse left it
            time.sleep(0.004)
            taken = 0
            for i in range(20):   # low then high back to back (the old pulse), a new target each time: bit 4 was high
                c._send_setpoint(goal + i, new=False)
                c._send_setpoint(goal + i, new=True)
                taken += wait_for(lambda: drive.latched == goal + i, 0.01)
            assert taken <= 15   # (taken only where the two frames straddle the end of a cycle: ~4 of 20 here; 20 with
            #  a drive that takes every frame at once)
            goal += 100
            c._send_setpoint(goal, new=False)
            time.sleep(0.004)
            c._send_setpoint(goal, new=True)   # a cycle apart: taken
            assert wait_for(lambda: drive.latched == goal)
            c._raised, c._waiting_since = goal, time.monotonic()
