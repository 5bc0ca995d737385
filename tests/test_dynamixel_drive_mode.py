"""dynamixel-gripper: Drive_Mode's Profile Configuration (bit 2). A servo left with a time-based profile reads
Profile_Velocity as the time of each move in ms, so the driver's speed limit (43 for 0.05 m/s) asked for a 43 ms move:
the `open` safe state's 75 mm jump (a quarter turn: ~350 rev/min) ran at the servo's full speed. Start-up sets it
velocity-based (an EEPROM item, written with the torque off, as Operating_Mode is), keeping the other bits (emulated
servo on a pseudo-terminal)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import ERR_DATA_RANGE, INST_READ, INST_WRITE, DynamixelEmulator  # noqa: E402
from fakes.followers import dynamixel_harness, packet_timeout_fixture  # noqa: E402
from fakes.realtime import configure_fails, wait_for  # noqa: E402

from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper  # noqa: E402

pytestmark = pytest.mark.timeout(60)

packet_timeout = packet_timeout_fixture()   # the emulator's slower adapter for a loaded machine
harness = dynamixel_harness                 # at 1 Mbaud
DRIVE_MODE = 10                             # X-series Drive_Mode address (EEPROM)
M_PER_TICK = 0.075 / 1024                   # the default calibration: 75 mm over 1024 ticks


def _requests(emu, inst: int, addr: int) -> list:
    return [p for p in emu.rx_packets if p[2] == inst and int.from_bytes(p[3][:2], "little") == addr]


def _max_speed(emu, n0: int, seconds: float) -> float:
    """The fastest the emulated horn moved (m/s of opening) between position-trace entries since entry ``n0``, after
    letting it move for ``seconds``."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        emu.poll()
        time.sleep(0.01)
    tr = emu.trace[n0:]
    return max(abs(b[1] - a[1]) / (b[0] - a[0]) * M_PER_TICK for a, b in zip(tr, tr[1:]) if b[0] > a[0])


def test_emulator_runs_a_time_based_move_in_profile_velocity_ms():
    # the fake itself: with bit 2 set, Profile_Velocity 500 makes a 400-tick move take 0.5 s (800 ticks/s), and the
    # same value velocity-based is 500 x 0.229 rev/min = 7816 ticks/s, capped at the servo's top speed
    with DynamixelEmulator(15, position=1024, drive_mode=0x04, wire_timing=False) as emu:
        t = emu.table
        emu._put(t.profile_velocity, 500)
        emu._put(t.torque_enable, 1)
        emu.poll()
        emu._put(t.goal_position, 1424)
        emu.poll()
        assert emu.max_speed_ticks() == pytest.approx(800.0)
        emu._put(t.drive_mode, 0)
        assert emu.max_speed_ticks() == emu.speed == 3000.0


def test_time_based_profile_is_set_velocity_based_keeping_the_other_bits():
    # bit 0 (reverse), bit 2 (time-based) and bit 3 (torque on by goal update) set; the servo found with its torque on,
    # so its EEPROM is locked until the driver's Torque_Enable=0
    logs = []
    with DynamixelEmulator(15, position=2048, drive_mode=0x0D) as emu:
        emu._put(emu.table.torque_enable, 1)
        h = harness(emu, max_speed=0.05)
        h.ctx._log = logs.append
        with h:
            assert emu.get(emu.table.drive_mode) == 0x09   # velocity-based, direction and bit 3 as they were
            assert emu.get(emu.table.profile_velocity) == 43   # now 43 x 0.229 rev/min, not 43 ms
            assert emu.get(emu.table.torque_enable) == 1
        assert len(_requests(emu, INST_WRITE, DRIVE_MODE)) == 1
    assert any("Drive_Mode (address 10) was 13" in m and "time-based" in m and "set to 9" in m for m in logs), logs


def test_open_jump_of_a_servo_found_time_based_runs_at_max_speed():
    # closed (2048), safe_mode open: the jump to 1024 ticks (75 mm) goes out in one packet; time-based, the servo was
    # asked to run it in 43 ms, so it ran at its top speed (3000 ticks/s here: 0.22 m/s)
    with DynamixelEmulator(15, position=2048, drive_mode=0x04) as emu:
        with harness(emu, safe_mode="open", max_speed=0.05) as h:
            h.comp.safe_state()
            assert wait_for(lambda: emu.get(emu.table.goal_position) == 1024)
            speed = _max_speed(emu, len(emu.trace), 0.4)
            assert 0.045 < speed <= 0.05


def test_velocity_based_servo_is_read_not_rewritten(emu_velocity_based):
    emu = emu_velocity_based
    with harness(emu):
        assert emu.get(emu.table.drive_mode) == 0x01
    assert len(_requests(emu, INST_READ, DRIVE_MODE)) == 1
    assert not _requests(emu, INST_WRITE, DRIVE_MODE)   # the EEPROM is not rewritten at every start


@pytest.fixture
def emu_velocity_based():
    emu = DynamixelEmulator(15, position=1024, drive_mode=0x01).start()   # reverse mode, velocity-based
    yield emu
    emu.stop()


def test_refused_drive_mode_write_names_address_value_and_torque_stays_off():
    with DynamixelEmulator(15, position=1024, drive_mode=0x04) as emu:
        emu.refuse_writes[DRIVE_MODE] = ERR_DATA_RANGE
        configure_fails(harness(emu), r"writing Drive_Mode \(address 10\) = 0, velocity-based profile \(read 4: "
                                      r"time-based\): Dynamixel ID 15 .*refused it .*set Drive_Mode to 0 \(bit 2 "
                                      r"cleared\) with the Dynamixel Wizard")
        assert emu.get(emu.table.torque_enable) == 0   # never switched on
        assert not [p for p in emu.rx_packets if p[2] == INST_WRITE and p[3][:2] == bytes([112, 0])]


@pytest.mark.parametrize("model", ["rh-p12-rn-a", "rh-p12-rn"])
def test_rh_p12_rn_presets_have_no_drive_mode_to_read(model):
    # the e-Manual's RH-P12-RN(A) table has no time-based profile (Drive_Mode 10, where listed, is direction only),
    # and the old firmware's none at all: nothing read at address 10
    params = {"dxl_id": 1, "ticks_open": 0, "ticks_closed": 740, "opening_at_ticks_open": 0.106,
              "opening_at_ticks_closed": 0.0, "max_opening": 0.106, "model": model}
    assert DynamixelGripper.Params(**params).table().drive_mode is None
    with DynamixelEmulator(1, model, position=0) as emu:
        with harness(emu, **params):
            pass
        assert not _requests(emu, INST_READ, DRIVE_MODE) and not _requests(emu, INST_WRITE, DRIVE_MODE)


def test_control_table_without_drive_mode_is_accepted_and_left_alone():
    with pytest.raises(ValidationError, match="drive_mode"):
        DynamixelGripper.Params(control_table={"drive_mode": [10]})
    with DynamixelEmulator(15, position=1024, drive_mode=0x04) as emu:
        with harness(emu, control_table={"drive_mode": None}):
            assert emu.get(emu.table.drive_mode) == 0x04   # the user's table says there is none: not touched
        assert not _requests(emu, INST_READ, DRIVE_MODE)
