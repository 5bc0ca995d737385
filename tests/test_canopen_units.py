"""canopen-gripper (s17): profile velocity 0x6081 and velocity actual 0x606C in the drive's own velocity unit (SI unit
velocity 0x60A9 and position encoder resolution 0x608F, or the velocity_unit / counts_per_revolution params where the
drive has neither), and a drive found in FAULT at start-up, which is not reset unless reset_fault_at_start says so;
against the emulated CiA 402 drive on python-can's virtual bus."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import RPM, Cia402Drive  # noqa: E402
from fakes.followers import canopen_harness, channel_fixture  # noqa: E402
from fakes.realtime import configure_fails, drive_until  # noqa: E402

from teletouch.plugins.devices.canopen_gripper import CanopenGripper  # noqa: E402

pytestmark = pytest.mark.timeout(60)

channel = channel_fixture()
harness = canopen_harness

COUNTS_PER_M = 100000 / 0.08   # the default calibration: 100000 counts over 80 mm
MILLI_RPM = 0xFDB44700         # 0.001 rpm (10^-3, revolution 0xB4, minute 0x47)
TENTH_MILLI_RPM = 0xFCB44700   # 0.0001 rpm: Beckhoff's default velocity unit
MM_PER_S = 0xFD010300          # 0.001 m/s (metre 0x01, second 0x03): a linear axis unit the driver cannot map


def speed(drive, raw):
    """The speed (m/s) ``raw`` units of ``drive``'s velocity unit are with the default calibration."""
    return raw * drive.counts_per_unit / COUNTS_PER_M


def test_a_drive_in_rpm_is_given_max_speed_in_rpm_and_its_velocity_is_read_in_m_per_s(channel):
    """0x6081 was written in counts/s whatever the drive's unit: a drive in rpm (Maxon EPOS4's default) with 4096
    counts/rev ran ~68x max_speed (what the ``open`` safe state's jump runs at), and the velocity port showed rpm x
    m/count. 0x60A9 (0.001 rpm here) and 0x608F (4096 increments per revolution) say the unit."""
    with Cia402Drive(5, channel, position=0, velocity_unit=MILLI_RPM, counts_per_revolution=4096) as drive:
        h = harness(channel, max_speed=0.04)
        h.ctx.rate = 20.0   # the set-point runs ahead of the drive: it moves at its own limit (a loaded machine too)
        with h:
            # 0.04 m/s = 50000 counts/s = 732.421875 rpm: rounded down to 0.001 rpm
            assert drive.get(0x6081) == 732421
            assert speed(drive, drive.get(0x6081)) <= 0.04
            limit = speed(drive, 732421)
            trace: list = []
            drive_until(h, 0.0, lambda o: o["velocity"] == pytest.approx(-limit, rel=2e-3), trace=trace)
            assert all(s["velocity"] >= -0.04 * (1 + 1e-9) for s in trace), [s["velocity"] for s in trace]


def test_a_drive_without_0x608F_takes_counts_per_revolution(channel):
    """Beckhoff's 0.0001 rpm on a drive without position encoder resolution 0x608F: counts_per_revolution gives the
    counts per revolution; without it the start-up is refused naming both."""
    with Cia402Drive(5, channel, position=0, velocity_unit=TENTH_MILLI_RPM, counts_per_revolution=4096,
                     resolution_object=False) as drive:
        configure_fails(harness(channel, max_speed=0.04),
                        r"SI unit velocity 0x60A9 of CANopen node 5 .* is 0xFCB44700 \(0.0001 rpm\).* position "
                        r"encoder resolution 0x608F .*SDO abort.*counts_per_revolution")
        with harness(channel, max_speed=0.04, counts_per_revolution=4096):
            assert drive.get(0x6081) == math.floor(50000 * 60 / 4096 * 10000)   # 7324218 (0.0001 rpm)


def test_a_drive_that_scales_its_positions_needs_counts_per_revolution(channel):
    """A drive with a gear ratio 0x6091 or feed constant 0x6092 other than 1:1 gives 0x6064 in its own position units:
    0x608F's encoder increments per motor revolution are then not 0x6064 counts, and the profile velocity (and the
    velocity read) was off by that factor. Refused, naming the scaling; counts_per_revolution settles it; 1:1 is no
    scaling."""
    with Cia402Drive(5, channel, position=0, velocity_unit=MILLI_RPM, counts_per_revolution=4096,
                     scaling={0x6091: (3, 1), 0x6092: (1, 1)}) as drive:
        configure_fails(harness(channel, max_speed=0.04),
                        r"0x60A9 .* in revolutions: CANopen node 5 .* scales its positions \(gear ratio 0x6091 3:1\), "
                        r"so the position encoder resolution 0x608F \(4096 increments per 1 motor revolutions\) is "
                        r"not the 0x6064 counts per revolution; give counts_per_revolution")
        assert drive.get(0x6081) == 100000   # nothing written
        with harness(channel, max_speed=0.04, counts_per_revolution=4096):
            assert drive.get(0x6081) == 732421
    with Cia402Drive(5, channel, position=0, velocity_unit=MILLI_RPM, counts_per_revolution=4096,
                     scaling={0x6091: (1, 1), 0x6092: (7, 7)}) as drive:
        with harness(channel, max_speed=0.04):
            assert drive.get(0x6081) == 732421


def test_a_profile_acceleration_of_zero_is_refused(channel):
    """Profile acceleration 0x6083 (and deceleration 0x6084) are the drive's own: one of 0 moves nothing on many
    drives, and the start-up went on without a word."""
    with Cia402Drive(5, channel, position=0) as drive:
        drive._put(0x6083, 0)
        configure_fails(harness(channel), r"CANopen node 5 .* has a profile acceleration 0x6083 of 0: the set-points "
                                          r"would not move the fingers")
        drive._put(0x6083, 5000)
        with harness(channel):
            pass


def test_a_velocity_unit_the_driver_cannot_convert_is_refused_naming_0x60A9_and_what_to_set(channel):
    with Cia402Drive(5, channel, position=0, velocity_unit=MM_PER_S) as drive:
        configure_fails(harness(channel),
                        r"SI unit velocity 0x60A9 of CANopen node 5 .* is 0xFD010300 \(0.001 m/s\).*revolutions "
                        r"per minute or second.*0x00B44700 \(rpm\)")
        assert drive.get(0x6081) == 100000   # nothing written in a unit the driver does not know


def test_a_drive_without_0x60A9_needs_velocity_unit(channel):
    """Where the drive has no 0x60A9 the unit is not guessed (counts/s ran an rpm drive ~68x max_speed, rpm would
    run a counts/s drive ~68x slower and misread its velocity): velocity_unit is required."""
    with Cia402Drive(5, channel, position=0, velocity_unit=RPM, velocity_unit_object=False,
                     counts_per_revolution=4096) as drive:
        configure_fails(harness(channel), r"CANopen node 5 .* has no SI unit velocity 0x60A9 \(SDO abort.*\): .*"
                                          r"give velocity_unit")
        with harness(channel, max_speed=0.04, velocity_unit="rpm"):
            assert drive.get(0x6081) == 732   # 732.42 rpm, rounded down
    with Cia402Drive(5, channel, position=0, velocity_unit_object=False) as drive:   # one count/s
        with harness(channel, max_speed=0.04, velocity_unit="counts/s"):
            assert drive.get(0x6081) == 50000


def test_velocity_unit_that_disagrees_with_the_drives_0x60A9_is_refused(channel):
    with Cia402Drive(5, channel, position=0, velocity_unit=RPM, counts_per_revolution=4096) as drive:
        configure_fails(harness(channel, velocity_unit="counts/s"),
                        r"velocity_unit 'counts/s' disagrees with the SI unit velocity 0x60A9 of CANopen node 5 .* "
                        r"0x00B44700 \(rpm\)")
        with harness(channel, max_speed=0.04, velocity_unit="1 rpm"):   # the same unit: fine
            assert drive.get(0x6081) == 732


def test_velocity_unit_and_counts_per_revolution_are_validated():
    for good in ("rpm", "0.001 rpm", "1e-4 rpm", "rev/s", "counts/s", "0.1 counts/s"):
        assert CanopenGripper.Params(velocity_unit=good).velocity_unit == good
    for bad in ("mm/s", "rpm/s", "-1 rpm", "0 rpm", "fast"):
        with pytest.raises(ValidationError, match=r"velocity_unit '.*' is not a velocity unit the driver converts"):
            CanopenGripper.Params(velocity_unit=bad)
    with pytest.raises(ValidationError, match="counts_per_revolution"):
        CanopenGripper.Params(counts_per_revolution=0)


def test_a_drive_found_in_fault_is_not_reset_unless_reset_fault_at_start(channel):
    """A drive found in FAULT was reset and enabled (transition 15) with only a log line: the operator never saw
    the fault. Refused by default, naming the error code 0x603F and how to clear it; reset_fault_at_start: true
    lets the state walk reset it."""
    with Cia402Drive(5, channel, position=0) as drive:
        drive.inject_fault(0x2310)
        configure_fails(harness(channel), r"CANopen node 5 .* is in FAULT \(statusword 0x[0-9A-F]{4}, error code "
                                          r"0x2310, .*\): not reset.*reset_fault_at_start: true")
        assert drive.state == "FAULT" and drive.get(0x603F) == 0x2310   # left as found
        with harness(channel, reset_fault_at_start=True):
            assert drive.state == "OPERATION ENABLED" and drive.get(0x603F) == 0


def test_an_abort_other_than_no_such_object_is_a_fault_not_an_absent_0x60A9(channel):
    """A review found every SDO abort read as "the drive has no 0x60A9": a drive in rpm answering "present device
    state" (0x08000022) started with an old config's velocity_unit counts/s, 68x max_speed."""
    from canopen.sdo.exceptions import SdoAbortedError

    with Cia402Drive(5, channel, position=0, velocity_unit=MILLI_RPM, counts_per_revolution=4096) as drive:
        def refuse(index, subindex, od):
            if index == 0x60A9:
                raise SdoAbortedError(0x08000022)

        drive.node.add_read_callback(refuse)
        configure_fails(harness(channel, velocity_unit="counts/s"), r"reading SI unit velocity 0x60A9.*refused it")
        assert drive.get(0x6081) != 50000   # (what counts/s would have written: 68x max_speed in rpm)


@pytest.mark.parametrize("text", ["1e400 rpm", "1e-400 rpm", "1e12 counts/s"])
def test_a_velocity_unit_factor_no_drive_has_is_refused(text):
    with pytest.raises(ValidationError, match="outside 1e-9..1e9"):
        CanopenGripper.Params(velocity_unit=text)


def test_a_fault_during_the_enable_walk_is_not_reset_without_you(channel):
    """A review found canopen's own state walk resetting a fault that came as the drive was being enabled (a following
    error on enabling): the start-up went on, no line said it."""
    class FaultOnEnable(Cia402Drive):
        faulted = False

        def _controlword(self, cw):
            super()._controlword(cw)
            if self.state == "OPERATION ENABLED" and not self.faulted:   # (before a statusword says enabled)
                self.faulted = True
                self.inject_fault(0x8611)

    with FaultOnEnable(5, channel, position=0) as drive:
        configure_fails(harness(channel), r"went into FAULT during the start-up \(the state walk to OPERATION "
                                          r"ENABLED at SWITCHED ON\) \(.*error code 0x8611, last EMCY Code 0x8611")
        assert drive.faulted and drive.state == "FAULT", drive.state   # left in FAULT, not reset
    with FaultOnEnable(5, channel, position=0) as drive:
        h = harness(channel, reset_fault_at_start=True)
        try:
            h.comp.configure()   # allowed: reset by the walk, as a fault found at start-up is
            assert drive.state == "OPERATION ENABLED"
        finally:
            h.comp.close()


@pytest.mark.parametrize("code, absent", [(0x06020000, True), (0x06090011, True), (0x08000022, False),
                                          (0x06010000, False)])
def test_only_the_no_such_object_aborts_mean_a_drive_without_0x608F(channel, code, absent):
    """0x608F is read as 0x60A9 is: an abort other than "object / sub-index does not exist" (the drive's state, an
    unsupported access) is a start-up failure naming the object and the abort, not a drive without the object."""
    with Cia402Drive(5, channel, position=0, velocity_unit=RPM, aborts={0x608F: code}) as drive:
        if absent:
            configure_fails(harness(channel), r"CANopen node 5 .* has no position encoder resolution 0x608F \(SDO "
                                              rf"abort: Code 0x{code:08X}.*give counts_per_revolution")
        else:
            configure_fails(harness(channel), r"reading position encoder resolution 0x608F: CANopen node 5 .* "
                                              rf"refused it \(SDO abort: Code 0x{code:08X}, \w+")
        assert drive.get(0x6081) == 100000   # nothing written


def test_a_fault_on_the_way_to_operation_enabled_is_refused_without_an_emcy(channel):
    """A review found canopen's state walk resetting (transition 15) a fault that came on the way: the start-up's
    check of the EMCYs saw it only where the drive sends one (its EMCY may be off). The statusword tells it, at every
    step of the walk; the drive is left in FAULT, its error code unerased."""
    with Cia402Drive(5, channel, position=0, emcy=False, fault_at=("SWITCHED ON", 0x8611)) as drive:
        configure_fails(harness(channel), r"CANopen node 5 .* went into FAULT during the start-up \(the state walk "
                                          r"to OPERATION ENABLED at READY TO SWITCH ON\) \(statusword 0x[0-9A-F]{4}, "
                                          r"error code 0x8611, no EMCY received\): not reset without you.*"
                                          r"reset_fault_at_start: true")
        assert drive.state == "FAULT" and drive.get(0x603F) == 0x8611   # not reset


def test_a_fault_on_the_way_is_logged_before_reset_fault_at_start_resets_it(channel):
    with Cia402Drive(5, channel, position=0, emcy=False, fault_at=("SWITCHED ON", 0x8611)) as drive:
        h = harness(channel, reset_fault_at_start=True)
        logs: list[str] = []
        h.ctx._log = logs.append
        with h:
            assert drive.state == "OPERATION ENABLED" and drive.get(0x603F) == 0
        assert [m for m in logs if "went into FAULT" in m and "error code 0x8611" in m and "resetting it" in m], logs


def test_an_emcy_warning_on_the_way_to_operation_enabled_is_no_fault(channel):
    """An EMCY is no FAULT: a drive that reports a warning (here a temperature warning, 0x4210) by EMCY as it is
    enabled, and stays enabled, starts (the EMCY check refused it, switching it off)."""
    class WarnOnEnable(Cia402Drive):
        def _controlword(self, cw):
            was = self.state
            super()._controlword(cw)
            if self.state == "SWITCHED ON" != was:
                self.warn(0x4210)

    with WarnOnEnable(5, channel, position=0) as drive:
        h = harness(channel)
        with h:
            assert drive.state == "OPERATION ENABLED"
            assert [e.code for e in h.comp.emcys] == [0x4210]


def test_a_drive_in_fault_is_refused_before_anything_is_written_to_it(channel):
    """The FAULT refusal came after the start-up's writes (PDO mapping, heartbeat 0x1017, mode 0x6060, profile
    velocity 0x6081, max current 0x6073, NMT OPERATIONAL): the statusword 0x6041 is read by SDO first."""
    with Cia402Drive(5, channel, position=0) as drive:
        drive.inject_fault(0x2310)
        configure_fails(harness(channel), r"CANopen node 5 .* is in FAULT \(statusword 0x[0-9A-F]{4}, error code "
                                          r"0x2310, .*\): not reset")
        assert drive.node.nmt.state == "PRE-OPERATIONAL"
        assert (drive.get(0x1017), drive.get(0x6060), drive.get(0x6081), drive.get(0x6073)) == (0, 0, 100000, 1000)
        assert (drive.node.get_data(0x1A00, 0), drive.node.get_data(0x1600, 0)) == (b"\x00", b"\x00")   # unmapped
        assert drive.state == "FAULT" and drive.get(0x603F) == 0x2310
