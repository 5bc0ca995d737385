"""dynamixel-gripper review: the shutdown poll with one of its reads refused or lost, safe_state() from another thread
racing a step, and the fault messages (driver against the emulated Protocol 2.0 servo on a pseudo-terminal)."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import ERR_ACCESS, HW_OVERLOAD, DynamixelEmulator  # noqa: E402
from fakes.followers import dynamixel_harness, packet_timeout_fixture  # noqa: E402
from fakes.realtime import drive, drive_until, wait_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402

pytestmark = pytest.mark.timeout(60)

# the RH-P12-RN with its old firmware: Torque_Enable (562) and Hardware_Error_Status (892) lie far apart, so the
# shutdown poll reads them with one READ each
RH_P12_OLD = {"model": "rh-p12-rn", "dxl_id": 1, "ticks_open": 0, "ticks_closed": 740, "opening_at_ticks_open": 0.106,
              "opening_at_ticks_closed": 0.0, "max_opening": 0.106, "newtons_per_amp": 100.0, "max_effort": 30.0,
              "max_speed": 0.1}
TORQUE_ENABLE, HW_ERROR_STATUS = 562, 892
#: a bound for a failure only: the poll runs every 0.05 s, a missed check never raises
WITHIN = 2.0


packet_timeout = packet_timeout_fixture()
harness = dynamixel_harness   # at 1 Mbaud


def near(x, abs):
    return lambda o: o["opening"] == pytest.approx(x, abs=abs)


def goal_writes(emu, since):
    """Goal_Position (ticks) of every SYNC_WRITE the servo received after packet ``since``, in order."""
    return [int.from_bytes(p[5:9], "little", signed=True) for (_t, _i, inst, p) in emu.rx_packets[since:]
            if inst == 0x83]


def settled(h, emu):
    """The number of packets the servo has received once it has the last goal sent (the emulator runs behind)."""
    assert wait_for(lambda: emu.get(emu.table.goal_position) == h.comp.ticks_for(h.comp._setpoint))
    time.sleep(0.05)  # (the same goal sent again may still be on its way)
    return len(emu.rx_packets)


# --- 1. the shutdown poll evaluates whatever of its reads arrived --------------------------------------------------

@pytest.mark.parametrize("lose", ["refused", "lost"])
def test_torque_drop_is_seen_when_only_the_error_status_read_fails(lose):
    # Torque_Enable was read (0: the servo was reset by a power dip), Hardware_Error_Status was refused or its answer
    # lost: the poll returned before looking at Torque_Enable, at every poll, and the drop was never a fault
    with DynamixelEmulator(1, "rh-p12-rn", position=0) as emu:
        with harness(emu, **dict(RH_P12_OLD, error_check_period=0.05)) as h:
            drive(h, 0.06, 0.1)
            if lose == "refused":
                emu.refuse_reads[HW_ERROR_STATUS] = ERR_ACCESS
            else:
                emu.drop_reads.add(HW_ERROR_STATUS)
            with emu._lock:
                emu._put(emu.table.torque_enable, 0)
            with pytest.raises(HardwareError, match=r"Dynamixel ID 1 .*Torque_Enable dropped to 0"):
                drive(h, 0.06, WITHIN)
            assert any(p[2] == 0x02 and int.from_bytes(p[3][:2], "little") == HW_ERROR_STATUS
                       for p in emu.rx_packets)  # the error status was asked for (and refused or lost)


def test_hardware_error_status_is_seen_when_only_the_torque_read_is_lost():
    # the firmware's shutdown without the alert bit in the status packets: Hardware_Error_Status names it; the
    # Torque_Enable answer before it was lost, and the poll gave up on both
    with DynamixelEmulator(1, "rh-p12-rn", position=0) as emu:
        with harness(emu, **dict(RH_P12_OLD, error_check_period=0.05)) as h:
            drive(h, 0.06, 0.1)
            emu.drop_reads.add(TORQUE_ENABLE)
            emu.inject_hardware_error(HW_OVERLOAD, alert=False)
            with pytest.raises(HardwareError, match=r"Dynamixel ID 1 .*Hardware_Error_Status overload"):
                drive(h, 0.06, WITHIN)


def test_nothing_read_by_the_poll_is_no_fault():
    # both answers refused: the poll has nothing to judge (the state reads go on), no fault is made up
    with DynamixelEmulator(1, "rh-p12-rn", position=0) as emu:
        with harness(emu, **dict(RH_P12_OLD, error_check_period=0.02)) as h:
            drive(h, 0.06, 0.1)
            emu.refuse_reads.update({TORQUE_ENABLE: ERR_ACCESS, HW_ERROR_STATUS: ERR_ACCESS})
            n0 = len(emu.rx_packets)
            o = drive(h, 0.06, 0.3)
            polled = [p for p in emu.rx_packets[n0:] if p[2] == 0x02]
            assert len(polled) >= 4  # the poll ran (and was refused) several times
            assert o["opening"] == pytest.approx(h.comp.opening_for(emu.get(emu.table.present_position)), abs=1e-3)


# --- 2. safe_state() from another thread and a step in progress ----------------------------------------------------

def test_safe_state_waits_for_a_step_between_computing_and_sending_its_goal():
    # a step has worked out its goal (towards 30 mm) and is about to send it when the watchdog's thread calls
    # safe_state() (open: 75 mm). Without a lock the hold went out at once and the step's goal after it: the servo
    # was left at the step's goal, not the safe state
    with DynamixelEmulator(15, position=1024) as emu:
        with harness(emu, safe_mode="open") as h:
            drive_until(h, 0.06, near(0.06, 1e-3))
            gsw = h.comp.gsw   # dynamixel-sdk's GroupSyncWrite: the step pauses where it hands over its goal
            real = gsw.changeParam
            in_send, release = threading.Event(), threading.Event()

            def slow_change(dxl_id, data):
                if threading.current_thread().name == "stepper" and not release.is_set():
                    in_send.set()
                    release.wait(10.0)
                return real(dxl_id, data)

            gsw.changeParam = slow_change
            h.t = time.monotonic()
            h.set(opening_command=0.03)
            n0 = settled(h, emu)
            stepper = threading.Thread(target=h.comp.step, args=(h.t, h.inputs), name="stepper")
            stepper.start()
            try:
                assert in_send.wait(10.0)
                safe = threading.Thread(target=h.comp.safe_state, name="safe")
                safe.start()
                time.sleep(0.1)
                assert goal_writes(emu, n0) == []  # the hold waits for the step's send
            finally:
                release.set()
            stepper.join(10.0)
            safe.join(10.0)
            assert not stepper.is_alive() and not safe.is_alive()
            hold = h.comp.ticks_for(0.075)
            assert wait_for(lambda: len(goal_writes(emu, n0)) == 2)
            stepped, last = goal_writes(emu, n0)
            assert 1024 < stepped < 2048 and stepped != hold   # the step's goal (moving towards 30 mm) went first
            assert last == hold
            assert wait_for(lambda: emu.get(emu.table.goal_position) == hold)
            drive(h, 0.03, 0.1)
            assert emu.get(emu.table.goal_position) == hold  # the hold stays


def test_safe_state_during_a_step_read_is_not_refused_as_port_busy():
    # safe_state() while a step waits for its state read's answer: dynamixel-sdk refused the hold's write (the port
    # in use: COMM_PORT_BUSY) and the safe state logged that it could not command the gripper
    with DynamixelEmulator(15, position=1024) as emu:
        with harness(emu, safe_mode="open", error_check_period=30.0) as h:
            drive_until(h, 0.05, near(0.05, 1e-3))
            logs: list[str] = []
            h.ctx._log = logs.append
            asked = threading.Event()
            emu.on_delayed, emu.answer_delay, emu.delay_answers = asked.set, 0.05, 1  # answered within the timeout
            h.t = time.monotonic()
            h.set(opening_command=0.05)
            n0 = settled(h, emu)
            stepper = threading.Thread(target=h.comp.step, args=(h.t, h.inputs), name="stepper")
            stepper.start()
            assert asked.wait(10.0)   # the step's SYNC_READ is at the servo, its answer not yet back
            h.comp.safe_state()
            stepper.join(10.0)
            assert not stepper.is_alive()
            assert not [m for m in logs if "could not command" in m], logs
            hold = h.comp.ticks_for(0.075)
            assert wait_for(lambda: hold in goal_writes(emu, n0))
            assert wait_for(lambda: emu.get(emu.table.goal_position) == hold)
            assert h.comp.comm_failures == 0   # the step's read got its answer


# --- 3. fault messages ---------------------------------------------------------------------------------------------

def test_a_torque_drop_is_not_reported_as_failed_reads():
    # read_state() appended ", N failed reads, last: <empty>" to every HardwareError of the state read, also to the
    # shutdown poll's faults, where no read had failed
    with DynamixelEmulator(15, position=1024) as emu:
        with harness(emu, error_check_period=0.05) as h:
            drive(h, 0.06, 0.1)
            with emu._lock:
                emu._put(emu.table.torque_enable, 0)
            with pytest.raises(HardwareError, match="Torque_Enable dropped to 0") as info:
                drive(h, 0.06, WITHIN)
            assert "failed reads" not in str(info.value) and str(info.value).endswith("then restart")


def test_a_read_timeout_still_names_the_failed_reads():
    with DynamixelEmulator(15, position=1024) as emu:
        with harness(emu, read_timeout=0.3, error_check_period=30.0) as h:
            drive(h, 0.06, 0.1)
            emu.silent = True
            with pytest.raises(HardwareError, match=r"no valid state.*Dynamixel ID 15 .*\d+ failed reads, last: "
                                                    r"\[TxRxResult\]"):
                drive(h, 0.06, WITHIN * 2)
            emu.silent = False


# --- 4. the hold with the state stale -------------------------------------------------------------------------------

def test_hold_after_a_read_timeout_keeps_the_last_goal_instead_of_the_stale_opening():
    # the servo's answers are lost (its receive line, noise) while its goals still arrive: the steps went on moving
    # the set-point at max_speed and the servo followed it, for read_timeout; the fault's hold then sent the stale
    # measured opening, and the servo moved back by up to read_timeout x max_speed. (Each step here waits out the
    # slow adapter's 0.12 s packet timeout and moves the set-point by two periods, 1 mm: ~12 mm in 1.5 s)
    with DynamixelEmulator(15, position=1024) as emu:
        with harness(emu, read_timeout=1.5, error_check_period=30.0) as h:
            drive_until(h, 0.04, near(0.04, 5e-4))
            stale = h.comp._last_reading.opening
            emu.silent = True   # no answers; SYNC_WRITEs (unanswered anyway) are still applied
            with pytest.raises(HardwareError, match="no valid state"):
                drive(h, 0.07, WITHIN * 2)
            sent = h.comp._setpoint
            assert sent - stale > 0.005   # the set-point (and the servo) went on for read_timeout
            assert wait_for(lambda: emu.get(emu.table.goal_position) == h.comp.ticks_for(sent))
            h.comp.safe_state()   # what the runtime does after the fault
            time.sleep(0.05)
            assert emu.get(emu.table.goal_position) == h.comp.ticks_for(sent)
            assert h.comp._setpoint == sent
            emu.silent = False


def test_hold_during_a_shorter_read_loss_keeps_the_last_goal_too():
    # the same loss, shorter than read_timeout (no fault of the gripper's own yet) when another node's fault makes the
    # runtime call safe_state(): the override above took the last goal only after read_timeout, so this hold sent the
    # stale measured opening and the servo moved back (5.6 mm in an audit's run)
    with DynamixelEmulator(15, position=1024) as emu:
        with harness(emu, read_timeout=5.0, error_check_period=30.0) as h:
            drive_until(h, 0.04, near(0.04, 5e-4))
            stale = h.comp._last_reading.opening
            emu.silent = True
            drive(h, 0.07, 0.8)   # well under read_timeout
            sent = h.comp._setpoint
            assert sent - stale > 0.002
            assert wait_for(lambda: emu.get(emu.table.goal_position) == h.comp.ticks_for(sent))
            h.comp.safe_state()
            time.sleep(0.05)
            assert emu.get(emu.table.goal_position) == h.comp.ticks_for(sent)   # before: the stale opening's ticks
            emu.silent = False
