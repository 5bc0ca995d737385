"""dynamixel-gripper: a Dynamixel servo gripper (Protocol 2.0, dynamixel-sdk) in current-based position mode.

The servo runs in current-based position mode (Operating_Mode 5): it goes to Goal_Position but never pushes with
more than Goal_Current, which is how the grip force is capped (``max_effort`` / ``newtons_per_amp``). Each step
reads Present_Current, Present_Velocity and Present_Position with one SYNC_READ and sends Goal_Position with a
GroupSyncWrite. The status packet of that read is checked for the alert bit (0x80, set by the firmware while the
servo is in hardware-error shutdown), and Torque_Enable (with Hardware_Error_Status where the table has it) is polled
every ``error_check_period``: the torque dropping to 0 (a shutdown, or a servo reset by a brown-out) is a fault. Where
the two are read apart (far apart in the table), each is judged when its own read was answered.

One thing on the bus at a time: a lock makes every request with its answer, and a step's goal worked out and sent,
one unit, so a safe_state() from another thread (the watchdog) waits for the one in progress (dynamixel-sdk refused
its write while a read waited for its answer: "Port is in use") and its hold goes out last. The ``hold`` safe state
sends the measured opening, or with the state stale (no valid state for ``read_timeout``) the last set-point sent:
the goals went on reaching the servo while its answers were lost, and the stale opening would move the fingers back.

The servo's own speed limit: Profile_Velocity is set from ``max_speed`` at start-up (rounded down, and capped at
Velocity_Limit where the table names it), so a setpoint jump (the ``open`` safe state) is not run at the servo's full
speed. A table without Profile_Velocity relies on the driver's setpoint shaping only. Drive_Mode's bit 2 (Profile
Configuration: X-series from firmware V42, DYNAMIXEL-P) makes the profile time-based, Profile_Velocity then being the
time of each move in ms (the 43 for 0.05 m/s asked for a 75 mm jump in 43 ms: the servo's full speed): a servo found
time-based is set velocity-based before Profile_Velocity is written, as Operating_Mode is set (an EEPROM item, with the
torque off), the other bits (direction, torque on by goal update) kept, with a log line.

Answers: Protocol 2.0 status packets carry no sequence number, so a status packet that arrives after its request
timed out (a late answer) looks like the answer to the next request. Every answer is checked (the servo's ID, and the
number of data bytes the request asked for; other packets are dropped and counted in ``stale_answers``), and after a
request without a valid answer the next one is preceded by a PING whose answer is waited for: the servo answers in
order, so whatever arrives before that PING's answer is a late answer to an earlier request and is dropped. A late
answer of the right length can therefore never be taken for a newer request's. A reading is stamped from the read
that produced it (the midpoint of its request going out and its answer), never from before that PING.

Waiting for answers: dynamixel-sdk polls the port in a Python loop (pyserial timeout 0) until the status packet's
bytes or its packet timeout; the driver's port (:func:`port_handler_class`) waits in select() for the port to become
readable (which releases the GIL: the runtime's 1 kHz controller thread runs meanwhile) for at most the time left
until the SDK's packet timeout (and ``serial_poll``), then reads what is there. The SDK's framing, checks and
timeouts stay its own: a lost answer still times out after the SDK's packet timeout, with a handful of reads instead
of thousands.

Start-up: every request of the start-up (the PING, each read and write, the first state read) is tried up to
:data:`STARTUP_TRIES` times when its answer is lost or corrupt (the port's input cleared, and the bus resynchronised
by a PING, before the next try): a bus loses a packet now and then (noise, a servo busy writing its EEPROM), which
must not fail the start-up; a servo that does not answer at all still fails it, naming the port, ID and baud rate.
The writes are of absolute values, so repeating one whose answer was lost changes nothing. A refusal (an error in the
status packet) is not retried. At run time a lost answer is not retried: the step goes on with the last reading, and
no valid state for ``read_timeout`` is a fault.

Goal_Position goes out in a SYNC_WRITE, which the servo never answers (no status packet, so no lost or corrupt answer
and no error byte: a goal lost on the bus is replaced by the next step's, and the servo's hardware errors show in the
state read's alert bit and the shutdown poll, a fault at once, never retried). What can fail is the port (pyserial
raising: a USB glitch) or the SDK's send (a short write, the port busy). A failed goal write is not retried within
the step: the next step's goal, one period later, is the retry, with the newer set-point (an immediate retry would
lengthen a step whose bus is in trouble, and delay the state read after it). The set-point goes back to the last goal
that went out, which the servo still has: the speed limit counts from it, and a hold while the reads are stale holds
it. Goal writes failing for longer than ``read_timeout`` are a fault naming the servo, port and baud rate, how long
and how many writes failed, and the last error (``write_failures`` in the status counts them). The safe state's hold
is tried up to :data:`HOLD_TRIES` times at once, ``serial_poll`` apart (no step may follow to send it).

The port itself failing (the USB adapter pulled, or a glitch): pyserial raises from within dynamixel-sdk's calls
(SerialException, termios.error from its tcflush), which left the SDK's busy flag set, so that every later request,
the safe state's hold among them, was refused ("Port is in use!"). Every transaction turns what the port raises
into a HardwareError naming the servo (ID, model), port and baud rate and the likely cause (unplugged: replug, then
restart; `teletouch devices`), chained from pyserial's error, with the busy flag cleared. In a state read it is a
failed read (held within ``read_timeout``, then a fault saying so); in a Goal_Position write a failed write (the
same: held within ``read_timeout``, see above).

The opening maps linearly to ticks (``ticks_open`` <-> ``opening_at_ticks_open``, ``ticks_closed`` <->
``opening_at_ticks_closed``); ticks left unset are the preset's (:data:`PRESET_TICKS`: X-series 1024/2048,
RH-P12-RN 0/740). Control tables are data: ``model`` picks a preset from :data:`CONTROL_TABLES` (X-series such as the
OpenManipulator-X's XM430-W350; ROBOTIS RH-P12-RN with either firmware) and ``control_table`` overrides it, so a
servo with another table needs configuration, not code. At start-up the model number the servo answers the PING with
must be the preset's (a firmware mismatch names the preset that fits), and where the table names Min/Max_Position_Limit
the ticks must lie within them (the servo drops a goal beyond: the gripper would silently not follow).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import math
import os
import select
import stat
import termios
import threading
import time
from typing import Any, Callable

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from teletouch import HardwareError, hookimpl
from teletouch.plugins.sensors import discovery  # the device-node checks shared with `teletouch devices`
from teletouch.units import Meters, Newtons, Seconds

from .follower_common import FollowerBase, FollowerParams, OpeningMap, Reading

Item = tuple[int, int]  # (address, size in bytes)


class ControlTable(BaseModel):
    """Addresses (address, bytes) of the items the driver uses, and the units of the servo's raw values."""

    model_config = ConfigDict(extra="forbid")
    model_number: int | None = Field(None, description="expected model number from PING (None: any)")
    operating_mode: Item = (11, 1)
    drive_mode: Item | None = Field((10, 1), description="Drive_Mode, whose bit 2 (Profile Configuration) set makes "
                                    "Profile_Velocity the time of each move (ms): cleared at start-up; None: the "
                                    "servo has no time-based profile (not read)")
    current_limit: Item = (38, 2)
    torque_enable: Item = (64, 1)
    hardware_error_status: Item | None = (70, 1)
    velocity_limit: Item | None = Field(None, description="Velocity_Limit, where the firmware refuses a larger "
                                        "Profile_Velocity: Profile_Velocity is capped at it; None: not checked")
    profile_velocity: Item | None = Field((112, 4), description="Profile_Velocity (same unit as velocity_unit_rpm, "
                                          "0 = unlimited); None: the servo has no speed limit the driver can set")
    goal_current: Item = (102, 2)
    goal_position: Item = (116, 4)
    min_position_limit: Item | None = Field(None, description="Min_Position_Limit, where the servo drops a "
                                            "Goal_Position below it in current-based position mode: read at start-up, "
                                            "ticks_open/ticks_closed outside the limits refused; None: not checked")
    max_position_limit: Item | None = Field(None, description="Max_Position_Limit (as min_position_limit)")
    present_current: Item = (126, 2)
    present_velocity: Item = (128, 4)
    present_position: Item = (132, 4)
    current_unit: float = Field(2.69e-3, gt=0, description="A per raw current unit")
    velocity_unit_rpm: float = Field(0.229, gt=0, description="rev/min per raw velocity unit")
    ticks_per_rev: int = Field(4096, gt=0, description="position ticks per revolution")


#: Control tables of known models (ROBOTIS e-Manual; verify against your servo's firmware).
CONTROL_TABLES: dict[str, dict[str, Any]] = {
    # X-series (XM430-W350: OpenManipulator-X gripper, ID 15). Its Min/Max_Position_Limit (52/48, EEPROM) bound
    # Goal_Position in position control mode only: in current-based position mode (5, the driver's) the e-Manual gives
    # Goal_Position -1,048,575 .. 1,048,575 (256 rev) and says the limits are not used, so they are not read here
    "xm430-w350": {"model_number": 1020},
    "x-series": {},
    # ROBOTIS RH-P12-RN gripper, "RH-P12-RN(A)" firmware (model number 35074; the table of DYNAMIXEL-P / PRO(A)):
    # e-Manual platform/rh_p12_rna. Position 0 (open) .. 740 (closed) within the 0..1150 position limits; current
    # in 1 mA, velocity in 0.01 rev/min; Profile_Velocity (0 = none) at most Velocity_Limit. No time-based profile:
    # its Drive_Mode (10), where the e-Manual lists it, is the direction only (0 ~ 1), so it is not read.
    "rh-p12-rn-a": {"model_number": 35074, "operating_mode": (11, 1), "drive_mode": None, "current_limit": (38, 2),
                    "velocity_limit": (44, 4), "torque_enable": (512, 1), "hardware_error_status": (518, 1),
                    "goal_current": (550, 2), "profile_velocity": (560, 4), "goal_position": (564, 4),
                    "present_current": (574, 2), "present_velocity": (576, 4), "present_position": (580, 4),
                    "max_position_limit": (48, 4), "min_position_limit": (52, 4),
                    "current_unit": 1e-3, "velocity_unit_rpm": 0.01},
    # the same gripper with its old "RH-P12-RN" firmware (model number 35073; a DYNAMIXEL-PRO-like table): e-Manual
    # platform/rh_p12_rn. Current in about 4.02 mA, velocity in 0.114 rev/min; its Goal_Velocity (600) is the
    # profile's top speed in current-based position mode (0 = none), so it takes the place of Profile_Velocity.
    # ROBOTIS recommends flashing the RH-P12-RN(A) firmware (DYNAMIXEL Wizard 2.0 / R+ Manager 2.0, Firmware
    # Recovery) and using "rh-p12-rn-a". No Drive_Mode in this table. Max/Min_Position_Limit at 36/40 (0..1150).
    "rh-p12-rn": {"model_number": 35073, "operating_mode": (11, 1), "drive_mode": None, "current_limit": (30, 2),
                  "velocity_limit": (32, 4), "torque_enable": (562, 1), "hardware_error_status": (892, 1),
                  "goal_position": (596, 4), "profile_velocity": (600, 4), "goal_current": (604, 2),
                  "present_position": (611, 4), "present_velocity": (615, 4), "present_current": (621, 2),
                  "max_position_limit": (36, 4), "min_position_limit": (40, 4),
                  "current_unit": 4.02e-3, "velocity_unit_rpm": 0.114},
}

#: each preset's default (ticks_open, ticks_closed): the X-series values are the OpenManipulator-X gripper's; the
#: RH-P12-RN runs from 0 (open) to 740 (closed) (with either firmware), and drops a Goal_Position beyond its 0..1150
#: position limits, so the X-series' 1024/2048 never tracked on it
PRESET_TICKS: dict[str, tuple[int, int]] = {
    "xm430-w350": (1024, 2048),
    "x-series": (1024, 2048),
    "rh-p12-rn-a": (0, 740),
    "rh-p12-rn": (0, 740),
}

#: What a model number answered to PING is (for messages), and the preset for it.
MODEL_NAMES: dict[int, tuple[str, str]] = {
    1020: ("XM430-W350", "xm430-w350"),
    35073: ("RH-P12-RN with its old RH-P12-RN firmware", "rh-p12-rn"),
    35074: ("RH-P12-RN with the RH-P12-RN(A) firmware", "rh-p12-rn-a"),
}


def model_text(number: int) -> str:
    name = MODEL_NAMES.get(number)
    return f"{number} ({name[0]}: model {name[1]!r})" if name else f"{number}"


def preset_ticks(model: str) -> tuple[int, int]:
    """(ticks_open, ticks_closed) a preset gives when the params leave them unset (X-series' for a model without)."""
    return PRESET_TICKS.get(model, PRESET_TICKS["x-series"])


def firmware_hint(found: int, model: str) -> str:
    """What to do when the servo answered ``found`` but ``model`` was configured."""
    name = MODEL_NAMES.get(found)
    if found == 35073 and model == "rh-p12-rn-a":
        o, c = preset_ticks("rh-p12-rn")
        return (f"set model: rh-p12-rn (the old firmware's table; the same ticks: ticks_open {o} (open) and "
                f"ticks_closed {c} (closed) unless set), or flash the RH-P12-RN(A) firmware as ROBOTIS recommends "
                f"(DYNAMIXEL Wizard 2.0 or R+ Manager 2.0, Firmware Recovery) and keep rh-p12-rn-a")
    if name:
        o, c = preset_ticks(name[1])
        same = preset_ticks(model) == (o, c)
        ticks = (f"; its ticks: ticks_open {o} (open) and ticks_closed {c} (closed) unless set"
                 + ("" if same else f", not {model}'s {'/'.join(map(str, preset_ticks(model)))}: check any ticks "
                    f"set for {model}"))
        return f"set model: {name[1]}{ticks}; or check the ID"
    return "check the ID and the 'model' parameter"


BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 2000000,
             2500000, 3000000, 3500000, 4000000)
HW_ERROR_BITS = {0x01: "input voltage", 0x02: "motor hall sensor", 0x04: "overheating", 0x08: "motor encoder",
                 0x10: "electrical shock", 0x20: "overload"}
CURRENT_BASED_POSITION = 5
#: Drive_Mode bit 2, Profile Configuration: 0 velocity-based (Profile_Velocity a speed), 1 time-based (a time, ms)
TIME_BASED_PROFILE = 0x04
# Protocol 2.0 status packet: FF FF FD 00 | ID | LEN_L LEN_H | 0x55 | ERR | data | CRC_L CRC_H (LEN counts from 0x55)
_PKT_ID, _PKT_LEN, _PKT_INST, _PKT_ERR, _PKT_DATA = 4, 5, 7, 8, 9
_INST_PING = 0x01
#: tries of each start-up request whose answer is lost or corrupt (not of a refused one)
STARTUP_TRIES = 3
#: tries of the safe state's hold (Goal_Position) when the port fails, ``serial_poll`` apart
HOLD_TRIES = 3
#: how far past the SDK's packet timeout a wait for the port may end (s): the SDK's own check then sees the timeout
#: at once instead of polling the last microseconds
_TIMEOUT_MARGIN = 5e-5
#: what a transaction raises when the port itself fails (the USB adapter pulled, or a glitch): pyserial's
#: SerialException, an OSError ("read failed: [Errno 5] Input/output error", "device reports readiness to read but
#: returned no data"), and termios.error, which is not one (tcflush, as the SDK clears the input before each request)
PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)


def port_failed(exc: BaseException) -> bool:
    """Whether ``exc`` is the driver's HardwareError for the serial port failing in a transaction (its ``port_failed``
    set, chained from what the port raised), not the servo's own fault or answer."""
    return isinstance(exc, HardwareError) and getattr(exc, "port_failed", False)


@functools.lru_cache(maxsize=None)
def port_handler_class() -> type:
    """dynamixel-sdk's ``PortHandler`` whose ``readPort`` waits for the port to become readable in select() (the GIL
    released) instead of returning empty at once, for at most the time left until the packet timeout the SDK set
    (``setPacketTimeout``) and at most ``max_wait`` (s); then it reads what is there, as the SDK does. rxPacket's
    framing, checks and timeout are the SDK's: the wait ends when bytes arrive or just after the SDK's timeout, so
    what the SDK returns, and when, is unchanged (within ``_TIMEOUT_MARGIN``)."""
    from dynamixel_sdk import PortHandler

    class WaitingPortHandler(PortHandler):
        max_wait = 0.01

        def readPort(self, length):  # noqa: N802 (the SDK's name)
            if length > 0:
                left = (self.packet_timeout - self.getTimeSinceStart()) / 1000.0  # the SDK counts in ms
                if left > 0:
                    try:
                        select.select([self.ser.fileno()], [], [], min(left + _TIMEOUT_MARGIN, self.max_wait))
                    except (OSError, ValueError, AttributeError):  # closed or not a real port: the read says so
                        pass
            return self.ser.read(length)   # pyserial timeout 0 (as the SDK opens it): what is there

    return WaitingPortHandler


def hw_error_text(bits: int) -> str:
    names = [n for b, n in HW_ERROR_BITS.items() if bits & b]
    return ", ".join(names) if names else f"0x{bits:02x}"


class DynamixelGripper(FollowerBase):
    """Dynamixel servo gripper over Protocol 2.0 (current-based position mode, Goal_Current caps the grip)."""

    name = "dynamixel-gripper"
    default_rate = 100.0
    requires_wall_clock = True  # the servo moves in real time; speed limits use the graph's time steps

    class Params(FollowerParams):
        port: str = Field("/dev/ttyUSB0", description="serial device of the U2D2/USB adapter")
        baudrate: int = Field(57600, description="bus baud rate (the servo's Baud_Rate)")
        dxl_id: int = Field(15, ge=0, le=252, description="servo ID")
        model: str = Field("xm430-w350", description=f"control table preset: {', '.join(CONTROL_TABLES)}")
        control_table: dict[str, Any] | None = Field(None, description="items overriding the preset's table")
        ticks_open: int | None = Field(None, description="Goal_Position (ticks) at the open end; None: the "
                                       "preset's (X-series 1024, RH-P12-RN 0)")
        ticks_closed: int | None = Field(None, description="Goal_Position (ticks) with the fingers closed; None: "
                                         "the preset's (X-series 2048, RH-P12-RN 740)")
        opening_at_ticks_open: Meters = Field(0.075, ge=0, description="opening at ticks_open",
                                              json_schema_extra={"unit": "m"})
        opening_at_ticks_closed: Meters = Field(0.0, ge=0, description="opening at ticks_closed",
                                                json_schema_extra={"unit": "m"})
        newtons_per_amp: float = Field(10.0, gt=0, description="grip force per ampere of motor current "
                                       "(calibrate for your gripper)", json_schema_extra={"unit": "N/A"})
        error_check_period: Seconds = Field(0.1, gt=0, description="poll Torque_Enable and Hardware_Error_Status "
                                            "this often",
                                            json_schema_extra={"unit": "s"})
        serial_poll: Seconds = Field(0.01, gt=0, le=0.01, description="longest single wait (select, GIL "
                                     "released) for the port to become readable before the SDK checks its packet "
                                     "timeout again; a wait also ends at that timeout",
                                     json_schema_extra={"unit": "s"})
        max_opening: Meters = Field(0.075, gt=0, description="largest opening commanded",
                                    json_schema_extra={"unit": "m"})
        max_effort: Newtons = Field(10.0, gt=0, description="grip force limit (sets Goal_Current)",
                                  json_schema_extra={"unit": "N"})

        @field_validator("baudrate")
        @classmethod
        def _baud(cls, v: int) -> int:
            if v not in BAUDRATES:
                raise ValueError(f"baudrate {v} is not one dynamixel-sdk supports: {BAUDRATES}")
            return v

        @field_validator("model")
        @classmethod
        def _model(cls, v: str) -> str:
            if v not in CONTROL_TABLES:
                raise ValueError(f"unknown model {v!r}; known: {', '.join(CONTROL_TABLES)} "
                                 f"(or give control_table)")
            return v

        @model_validator(mode="after")
        def _table(self) -> "DynamixelGripper.Params":
            ticks_open, ticks_closed = self.ticks()
            if ticks_open == ticks_closed:
                unset = [n for n in ("ticks_open", "ticks_closed") if getattr(self, n) is None]
                src = f"; {' and '.join(unset)}: model {self.model}'s default" if unset else ""
                raise ValueError(f"ticks_open and ticks_closed must differ (both {ticks_open}{src})")
            OpeningMap(ticks_open, self.opening_at_ticks_open, ticks_closed,
                       self.opening_at_ticks_closed).check_limits(self, "opening_at_ticks_open",
                                                                  "opening_at_ticks_closed")
            table = self.table()  # validates control_table
            preset = CONTROL_TABLES[self.model].get("model_number")
            if preset is not None and table.model_number != preset and table.model_number in MODEL_NAMES:
                # e.g. an RH-P12-RN(A) number on the old firmware's table: the addresses would be the wrong ones
                other = MODEL_NAMES[table.model_number][1]
                raise ValueError(f"control_table.model_number {table.model_number} belongs to model {other!r}, "
                                 f"whose control table differs from {self.model!r}'s (model number {preset}); "
                                 f"set model: {other} instead")
            return self

        def table(self) -> ControlTable:
            items = dict(CONTROL_TABLES[self.model])
            items.update(self.control_table or {})
            return ControlTable(**items)

        def ticks(self) -> tuple[int, int]:
            """(ticks_open, ticks_closed): as set, or the preset's (:data:`PRESET_TICKS`) where left unset."""
            o, c = preset_ticks(self.model)
            return (o if self.ticks_open is None else self.ticks_open,
                    c if self.ticks_closed is None else self.ticks_closed)

    # mapping ---------------------------------------------------------------------------------------------------
    @property
    def map(self) -> OpeningMap:
        p = self.params
        ticks_open, ticks_closed = p.ticks()
        return OpeningMap(ticks_open, p.opening_at_ticks_open, ticks_closed, p.opening_at_ticks_closed)

    def ticks_for(self, opening: float) -> int:
        return self.map.counts(opening)

    def opening_for(self, ticks: float) -> float:
        return self.map.opening(ticks)

    # hardware --------------------------------------------------------------------------------------------------
    def _where(self) -> str:
        p = self.params
        return f"Dynamixel ID {p.dxl_id} on {p.port} at {p.baudrate} baud"

    def _servo(self) -> str:
        """The servo with its model: the one its PING answered with, else the configured preset."""
        p = self.params
        found = getattr(self, "model_found", None)
        if found is None:
            model = f"model {p.model}"
        else:
            model = MODEL_NAMES[found][0] if found in MODEL_NAMES else f"model number {found}"
        return f"Dynamixel ID {p.dxl_id} ({model}) on {p.port} at {p.baudrate} baud"

    def _check(self, what: str, result: int, error: int, hint: str = "") -> None:
        if result != self._sdk.COMM_SUCCESS:
            raise HardwareError(f"{what}: no valid answer from {self._where()} ({self.ph.getTxRxResult(result)}, "
                                f"{STARTUP_TRIES} tries); check power, cable, ID and baud rate{hint}")
        if error & 0x80:
            raise HardwareError(f"{what}: {self._where()} reports a hardware error ({self._hw_error()}); "
                                f"power-cycle or reboot the servo")
        if error:
            raise HardwareError(f"{what}: {self._where()} refused it ({self.ph.getRxPacketError(error)})")

    def _ping_hint(self) -> str:
        """After a PING without a valid answer: what was tried, and the set-ups servos usually come in."""
        p = self.params
        defaults = {"dxl_id": "ID 15", "baudrate": "57600 baud"}
        unset = [n for n in defaults if n not in p.model_fields_set]
        left = (f" ({' and '.join(unset)} not set in the graph: the default{'s' if len(unset) > 1 else ''}, "
                f"{' at '.join(defaults[n] for n in unset)})") if unset else ""
        return (f". Tried ID {p.dxl_id} at {p.baudrate} baud{left}. Common set-ups: a new X-series servo (and an "
                f"RH-P12-RN as shipped) answers as ID 1 at 57600 baud (dxl_id: 1, baudrate: 57600); an "
                f"OpenManipulator-X gripper as ID 15 at 1000000 baud (dxl_id: 15, baudrate: 1000000); the DYNAMIXEL "
                f"Wizard's scan finds any. `teletouch devices` lists the serial adapters (is {p.port} the right "
                f"port?)")

    # the port itself failing (the adapter pulled): a HardwareError naming the servo, the busy flag cleared
    def _port_failed(self, exc: BaseException, what: str) -> HardwareError:
        kind = "termios.error" if isinstance(exc, termios.error) else type(exc).__name__
        failure = HardwareError(f"{what}: the serial port failed talking to {self._servo()} ({kind}: {exc}): the "
                                f"USB adapter (U2D2, OpenCR) may have been unplugged or lost power; replug it, then "
                                f"restart (`teletouch devices` lists the serial adapters: a replugged adapter may get "
                                f"another port name)")
        failure.port_failed = True   # (see port_failed())
        return failure

    @contextlib.contextmanager
    def _port_guard(self, what: str) -> Any:
        """Turn what the port raises (:data:`PORT_ERRORS`) into a HardwareError (:func:`port_failed`; chained from
        it), with dynamixel-sdk's busy flag cleared: the SDK sets ``is_using`` when a request goes out and clears it
        only on the paths that return, so an exception left it set and every later request, the safe state's hold
        among them, was refused ("Port is in use!"), after a transient error as much as after a pulled adapter."""
        try:
            yield
        except PORT_ERRORS as exc:
            port = getattr(self, "port", None)
            if port is not None:
                port.is_using = False
            self._desync = True   # what went out, and whether an answer is still on its way, is unknown
            raise self._port_failed(exc, what) from exc

    # requests and their answers: every answer is checked, a lost one makes the next request resynchronise first
    def _transact(self, n: int, send: Callable[..., int], *args: Any,
                  what: str = "a request") -> tuple[list[int], int, int]:
        """Send a request (``send(*args)``, which sets the SDK's packet timeout) and take its answer: ``n`` data
        bytes. After a lost answer the bus is resynchronised by a PING first (see :meth:`_resync_bus`). Under the
        I/O lock: a safe_state() from another thread waits for the answer instead of finding the port in use. The
        port failing raises a HardwareError (:func:`port_failed`; ``what``: the request, for its message)."""
        with self._io_lock, self._port_guard(what):
            if self._desync:
                result = self._resync_bus()
                if result != self._sdk.COMM_SUCCESS:
                    return [], result, 0
            return self._request(n, send, *args)

    def _request(self, n: int, send: Callable[..., int], *args: Any) -> tuple[list[int], int, int]:
        self._sent_at = time.monotonic()   # when this request went out (after any resync PING): a reading's stamp
        result = send(*args)
        if result != self._sdk.COMM_SUCCESS:
            self._desync = True  # what went out is unknown: an answer may still come
            return [], result, 0
        return self._answer(n)

    def _answer(self, n: int) -> tuple[list[int], int, int]:
        """The status packet answering the request just sent: from this servo's ID, with ``n`` data bytes (or none,
        with an error other than the alert bit: a refused request). Any other status packet is a late answer to an
        earlier request (or another servo's): dropped, and the wait goes on until the request's packet timeout."""
        sdk, p = self._sdk, self.params
        while True:
            pkt, result = self.ph.rxPacket(self.port, False)
            if result != sdk.COMM_SUCCESS:
                self._desync = True  # the answer may still arrive, late
                return [], result, 0
            count = (pkt[_PKT_LEN] | pkt[_PKT_LEN + 1] << 8) - 4  # LEN = instruction + error + data + CRC
            error = pkt[_PKT_ERR]
            if pkt[_PKT_ID] == p.dxl_id and (count == n or (count == 0 and error & 0x7F)):
                return list(pkt[_PKT_DATA:_PKT_DATA + count]), result, error
            self.stale_answers += 1
            self.last_stale = f"{count}-byte status packet from ID {pkt[_PKT_ID]} while waiting for {n} bytes"

    def _send_ping(self) -> int:
        pkt = [0] * 10
        pkt[_PKT_ID], pkt[_PKT_LEN], pkt[_PKT_INST] = self.params.dxl_id, 3, _INST_PING
        result = self.ph.txPacket(self.port, pkt)
        if result == self._sdk.COMM_SUCCESS:
            self.port.setPacketTimeout(14)  # the status packet of a PING: 11 bytes + 3 data bytes
        return result

    def _send_write(self, addr: int, size: int, value: int) -> int:
        data = list(int(value & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
        result = self.ph.writeTxOnly(self.port, self.params.dxl_id, addr, size, data)
        if result == self._sdk.COMM_SUCCESS:
            self.port.setPacketTimeout(11)  # the status packet of a WRITE: no data
        return result

    def _resync_bus(self) -> int:
        """After a request without a valid answer: PING, and take nothing before the PING's answer. The servo
        answers in order, so a late answer to an earlier request arrives before it and is dropped there; only then is
        another request sent (a full-length late answer is never taken for a newer request's)."""
        _data, result, _error = self._request(3, self._send_ping)
        if result == self._sdk.COMM_SUCCESS:
            self._desync = False
            self.resyncs += 1
        return result

    def _hw_error(self) -> str:
        item = self.table.hardware_error_status
        if item is None:
            return "details not in this control table"
        try:
            data, result, _ = self._transact(1, self.ph.readTx, self.port, self.params.dxl_id, item[0], 1,
                                             what="reading Hardware_Error_Status")
        except HardwareError as exc:
            if not port_failed(exc):
                raise
            return "status unreadable: the serial port failed"
        return hw_error_text(data[0]) if result == self._sdk.COMM_SUCCESS and data else "status unreadable"

    def _startup(self, n: int, send: Callable[..., int], *args: Any, what: str) -> tuple[list[int], int, int]:
        """A start-up request (:meth:`_transact`), tried up to STARTUP_TRIES times while its answer is lost or
        corrupt: the port's input cleared before each new try, whose PING (the bus is out of step after a lost answer)
        drops whatever late answer still comes. A refusal or an alert is the answer: not retried; nor is the port
        failing (:func:`port_failed`)."""
        for attempt in range(STARTUP_TRIES):
            if attempt:
                self.startup_retries += 1
                with self._io_lock, self._port_guard(what):
                    self.port.clearPort()
            data, result, error = self._transact(n, send, *args, what=what)
            if result == self._sdk.COMM_SUCCESS:
                break
        return data, result, error

    def _write(self, item: Item, value: int, what: str) -> None:
        addr, size = item
        _data, result, error = self._startup(0, self._send_write, addr, size, value, what=f"writing {what}")
        self._check(f"writing {what}", result, error)

    def _read(self, item: Item, what: str) -> int:
        addr, size = item
        data, result, error = self._startup(size, self.ph.readTx, self.port, self.params.dxl_id, addr, size,
                                            what=f"reading {what}")
        self._check(f"reading {what}", result, error)
        return _signed(int.from_bytes(bytes(data), "little"), size)

    def _check_position_limits(self) -> None:
        """Where the table names Min/Max_Position_Limit: ticks_open and ticks_closed within them. The servo drops a
        Goal_Position outside (no status packet to a SYNC_WRITE), so the gripper would silently not follow: the
        X-series' 1024/2048 on an RH-P12-RN (0 open .. 740 closed, limits 0..1150) ended a run "ok"."""
        p, t = self.params, self.table
        if t.min_position_limit is None or t.max_position_limit is None:
            return
        lo = self._read(t.min_position_limit, "Min_Position_Limit")
        hi = self._read(t.max_position_limit, "Max_Position_Limit")
        self.position_limits = (lo, hi)
        ticks = dict(zip(("ticks_open", "ticks_closed"), p.ticks()))
        bad = {n: v for n, v in ticks.items() if not lo <= v <= hi}
        if bad:
            given = ", ".join(f"{n} {v}" + ("" if getattr(p, n) is not None else f" (model {p.model}'s default)")
                              for n, v in bad.items())
            o, c = preset_ticks(p.model)
            raise HardwareError(
                f"{given} outside the position limits of {self._servo()}: Min_Position_Limit {lo} (address "
                f"{t.min_position_limit[0]}) .. Max_Position_Limit {hi} (address {t.max_position_limit[0]}); the "
                f"servo drops a Goal_Position beyond them and the gripper would not follow. Set ticks_open and "
                f"ticks_closed within {lo}..{hi} (model {p.model}: ticks_open {o} (open), ticks_closed {c} "
                f"(closed) by default), or widen the limits in the servo's EEPROM with the DYNAMIXEL Wizard")

    def _hw_open(self) -> None:
        import dynamixel_sdk as sdk

        p = self.params
        self._sdk = sdk
        # one transaction on the bus at a time, and a step's goal worked out and sent as one unit (step vs.
        # safe_state() from another thread: dynamixel-sdk refuses a second request while one waits for its answer)
        self._io_lock = threading.RLock()
        self.table = p.table()
        self._desync = False
        self._sent_at = 0.0   # monotonic time the last request went out
        self.stale_answers = 0
        self.last_stale = ""
        self.resyncs = 0
        self.comm_failures = 0
        self.last_comm_error = ""
        self.startup_retries = 0
        self.write_failures = 0   # Goal_Position writes that failed (each try of the safe state's hold counted)
        self.last_write_error = ""
        self.sent_opening = math.nan   # the opening of the last Goal_Position that went out
        self._forget_write_failures()
        self.model_found: int | None = None   # the model number the PING answered with
        self.position_limits: tuple[int, int] | None = None   # (Min, Max_Position_Limit) where the table has them
        self.port_failure: HardwareError | None = None   # the port failing in the last state read (None: it did not)
        self._started = False   # until the first valid state read: requests are retried (STARTUP_TRIES)
        self.port = port_handler_class()(p.port)
        self.port.max_wait = p.serial_poll
        self.ph = sdk.PacketHandler(2.0)
        self.port.baudrate = p.baudrate
        try:
            ok = self.port.openPort() and self.port.setBaudRate(p.baudrate)
        except Exception as exc:
            raise HardwareError(f"cannot open {p.port} ({exc}); {port_open_hint(p.port, exc)}") from exc
        if not ok:
            raise HardwareError(f"cannot set {p.baudrate} baud on {p.port}")
        self._port_open = True
        try:   # one program per servo bus: the lock pyserial's exclusive=True takes (the SDK opens without it)
            fcntl.flock(self.port.ser.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            self._hw_close()   # closed before anything is written: a safe_state() after this failure sends nothing
            raise HardwareError(f"{p.port} is in use: another process holds it (another teletouch, or a tool that "
                                f"opens it with pyserial's exclusive=True); two programs writing one servo bus fight "
                                f"over the gripper: stop the other one ({exc.strerror})") from exc
        data, result, error = self._startup(3, self._send_ping, what="ping")
        self._check("ping", result, error, hint=self._ping_hint())
        model = data[0] | data[1] << 8
        t = self.table
        if t.model_number is not None and model != t.model_number:
            raise HardwareError(f"{self._where()} answered with model number {model_text(model)}, expected "
                                f"{model_text(t.model_number)} for model {p.model!r}: the control tables differ; "
                                f"{firmware_hint(model, p.model)}")
        self.model_found = model
        self._check_position_limits()   # before anything is written
        self._write(t.torque_enable, 0, "Torque_Enable=0")
        self._write(t.operating_mode, CURRENT_BASED_POSITION, "Operating_Mode=5 (current-based position)")
        limit = self._read(t.current_limit, "Current_Limit")
        # rounded down: the grip cap is at or below max_effort (ceil gave e.g. 186 units = 5.003 N for 5 N)
        want = int(math.floor(p.max_effort / p.newtons_per_amp / t.current_unit))
        if want < 1:  # 0 would not move at all, 1 unit would exceed max_effort
            raise HardwareError(f"max_effort {p.max_effort} N is below one Goal_Current unit of {self._where()} "
                                f"({t.current_unit * p.newtons_per_amp:.4f} N with newtons_per_amp "
                                f"{p.newtons_per_amp})")
        if limit < 1:   # Goal_Current is capped by it: 0 leaves the servo no torque, the gripper could not grip
            raise HardwareError(f"Current_Limit of {self._where()} is {limit}: Goal_Current (the grip force cap) "
                                f"would be 0 and the gripper cannot grip at all; set Current_Limit (address "
                                f"{t.current_limit[0]}) in the servo's EEPROM with the Dynamixel Wizard, to at least "
                                f"{want} for max_effort {p.max_effort} N")
        self.goal_current = min(want, limit)
        if want > limit:
            self.ctx.log(f"max_effort {p.max_effort} N needs Goal_Current {want} > Current_Limit {limit}; "
                         f"capped at {limit * t.current_unit * p.newtons_per_amp:.2f} N")
        self._write(t.goal_current, self.goal_current, "Goal_Current")
        self._velocity_based_profile()
        self.profile_velocity = self._profile_velocity()
        if self.profile_velocity is not None:
            self._write(t.profile_velocity, self.profile_velocity, "Profile_Velocity")
        present = self._read(t.present_position, "Present_Position")
        self._write(t.goal_position, present, "Goal_Position")
        self._write(t.torque_enable, 1, "Torque_Enable=1")
        # one sync read covering current, velocity and position
        items = (t.present_current, t.present_velocity, t.present_position)
        self._rd_start = min(a for a, _ in items)
        self._rd_len = max(a + s for a, s in items) - self._rd_start
        self.gsr = sdk.GroupSyncRead(self.port, self.ph, self._rd_start, self._rd_len)
        if not self.gsr.addParam(p.dxl_id):
            raise HardwareError(f"GroupSyncRead refused ID {p.dxl_id}")
        self.gsw = sdk.GroupSyncWrite(self.port, self.ph, t.goal_position[0], 4)
        self._last_check = time.monotonic()

    def _velocity_based_profile(self) -> None:
        """Drive_Mode with its time-based profile bit cleared, before Profile_Velocity is written: time-based, the
        servo reads Profile_Velocity as the time of each move (ms), whatever its length, so no speed limit at all.
        The driver sets it as it sets Operating_Mode (the mode its Profile_Velocity needs; an EEPROM item, written
        with the torque off, still off here), and only when set (EEPROM writes wear it); the other bits are kept."""
        t = self.table
        if t.drive_mode is None or t.profile_velocity is None:
            return
        addr, size = t.drive_mode
        mode = self._read(t.drive_mode, "Drive_Mode") & ((1 << 8 * size) - 1)
        if not mode & TIME_BASED_PROFILE:
            return
        new = mode & ~TIME_BASED_PROFILE
        try:
            self._write(t.drive_mode, new, f"Drive_Mode (address {addr}) = {new}, velocity-based profile (read "
                                          f"{mode}: time-based)")
        except HardwareError as exc:
            raise HardwareError(f"{exc}; without it the servo's speed limit would not hold: set Drive_Mode to {new} "
                                f"(bit 2 cleared) with the Dynamixel Wizard") from None
        self.ctx.log(f"{self._where()}: Drive_Mode (address {addr}) was {mode}, a time-based profile (Profile_Velocity "
                     f"the time of each move in ms); set to {new}, velocity-based, so that the servo moves at most at "
                     f"max_speed; its other bits kept")

    def _profile_velocity(self) -> int | None:
        """Profile_Velocity (raw) for ``max_speed``: rounded down so the servo's limit is at or below it, and capped
        at Velocity_Limit where the table names it (the firmware refuses a larger value)."""
        p, t = self.params, self.table
        if t.profile_velocity is None:
            return None
        ticks_per_s = p.max_speed / abs(self.map.scale)
        # floor, with a hair of margin so that float error never rounds a just-above value back to the limit
        raw = int(math.floor(ticks_per_s / t.ticks_per_rev * 60.0 / t.velocity_unit_rpm * (1 - 1e-12)))
        unit = t.velocity_unit_rpm / 60.0 * t.ticks_per_rev * abs(self.map.scale)  # m/s of opening per unit
        if raw < 1:  # 0 would mean "no limit" to the servo
            raise HardwareError(f"max_speed {p.max_speed} m/s is below the slowest Profile_Velocity of "
                                f"{self._where()} ({unit:.5f} m/s with this calibration)")
        if t.velocity_limit is not None:
            vmax = self._read(t.velocity_limit, "Velocity_Limit")
            if vmax < 1:
                raise HardwareError(f"Velocity_Limit of {self._where()} is {vmax}: no Profile_Velocity can be set "
                                    f"(0 would mean no speed limit); set Velocity_Limit (address "
                                    f"{t.velocity_limit[0]}) to at least {raw}")
            if raw > vmax:
                self.ctx.log(f"max_speed {p.max_speed} m/s needs Profile_Velocity {raw} > Velocity_Limit {vmax}; "
                             f"the servo's own limit is capped at {vmax * unit:.4f} m/s")
                raw = vmax
        return raw

    def _poll_shutdown(self) -> None:
        """Every error_check_period: Torque_Enable (0 while active: shutdown or reset) and Hardware_Error_Status,
        each judged when its read was answered: where the two are read apart (far apart in the table), one read
        refused or lost does not keep the other's value from being judged. A lost answer is otherwise the state
        read's business (read_timeout); what was not read is read again at the next poll."""
        p, t, sdk = self.params, self.table, self._sdk
        items = [t.torque_enable] + ([t.hardware_error_status] if t.hardware_error_status is not None else [])
        start = min(a for a, _ in items)
        length = max(a + s for a, s in items) - start
        spans = list(items) if length > 16 else [(start, length)]  # far apart: one read each
        mem: dict[int, int] = {}
        for addr, n in spans:
            data, result, error = self._transact(n, self.ph.readTx, self.port, p.dxl_id, addr, n,
                                                 what="polling Torque_Enable and Hardware_Error_Status")
            if result != sdk.COMM_SUCCESS:
                continue  # lost: the other span may still have been read
            if error & 0x80:
                self._alert("hardware-error alert (0x80) in the status packet")
            if len(data) == n:  # (not a refusal)
                mem.update({addr + i: b for i, b in enumerate(data)})

        def value(item: Item | None) -> int | None:
            if item is None or any(item[0] + i not in mem for i in range(item[1])):
                return None
            return int.from_bytes(bytes(mem[item[0] + i] for i in range(item[1])), "little")

        hw_error = value(t.hardware_error_status)
        if hw_error:
            self._alert(f"Hardware_Error_Status {hw_error_text(hw_error)}")
        if value(t.torque_enable) == 0:
            raise HardwareError(f"{self._where()}: Torque_Enable dropped to 0 while active (hardware-error shutdown "
                                f"or the servo was reset, e.g. by a power dip); the gripper no longer holds. Check "
                                f"the supply and the servo, then restart")

    def _alert(self, what: str) -> None:
        detail = self._hw_error() if self.table.hardware_error_status is not None else \
            "no Hardware_Error_Status in this control table"
        raise HardwareError(f"{self._where()} reports a hardware error: {what} ({detail}); torque is off. Remove "
                            f"the cause, then reboot or power-cycle the servo")

    def _hw_read(self) -> Reading | None:
        """The state; None when this read failed (no valid answer, or the port failed: the base class holds, and
        faults after ``read_timeout`` without a valid state). At start-up the port failing raises at once."""
        if not self._started:
            return self._read_state()
        try:
            reading = self._read_state()
        except HardwareError as exc:
            if not port_failed(exc):
                raise
            self.comm_failures += 1
            self.last_comm_error = str(exc)
            self.port_failure = exc   # the fault after read_timeout is chained from its cause
            return None
        if reading is not None:
            self.port_failure = None
        return reading

    def _read_state(self) -> Reading | None:
        p, t, sdk = self.params, self.table, self._sdk
        now = time.monotonic()
        if now - self._last_check >= p.error_check_period:
            self._last_check = now
            self._poll_shutdown()
        # the SYNC_READ goes out with the group; its answer is taken (and checked) here, with its error byte
        # (GroupSyncRead.txRxPacket() would drop it). The sample is stamped from that read alone: from when it went
        # out (after the PING that resynchronises the bus after a lost answer) to its answer
        what = "reading the state (SYNC_READ)"
        data, result, error = self._transact(self._rd_len, self.gsr.txPacket, what=what)
        t1 = time.monotonic()
        if not self._started:   # the first state read is part of the start-up: retried, and its failure says so
            for _ in range(STARTUP_TRIES - 1):
                if result == sdk.COMM_SUCCESS:
                    break
                self.startup_retries += 1
                with self._io_lock, self._port_guard(what):
                    self.port.clearPort()
                data, result, error = self._transact(self._rd_len, self.gsr.txPacket, what=what)
                t1 = time.monotonic()
            self._check("reading the state (SYNC_READ)", result, error & 0x80)
            self._started = True
        if result != sdk.COMM_SUCCESS:
            self.comm_failures += 1
            self.last_comm_error = self.ph.getTxRxResult(result)
            return None
        if error & 0x80:
            self._alert("hardware-error alert (0x80) in the status packet of the state read")
        if error or len(data) != self._rd_len:
            self.comm_failures += 1
            self.last_comm_error = f"status packet error: {self.ph.getRxPacketError(error)}"
            return None

        def get(item: Item) -> int:
            off = item[0] - self._rd_start
            return _signed(int.from_bytes(bytes(data[off:off + item[1]]), "little"), item[1])

        ticks = get(t.present_position)
        vel_ticks = get(t.present_velocity) * t.velocity_unit_rpm / 60.0 * t.ticks_per_rev
        amps = get(t.present_current) * t.current_unit
        return Reading(self.opening_for(ticks), vel_ticks * self.map.scale, abs(amps) * p.newtons_per_amp,
                       0.5 * (self._sent_at + t1))

    def read_state(self, t: float) -> Reading:
        try:
            return super().read_state(t)
        except HardwareError as exc:
            if "no valid state" not in str(exc):  # the servo's own faults (shutdown poll, alert) name it already
                raise
            lost = getattr(self, "port_failure", None)
            if lost is not None:   # the last read failed in the port itself: chained from pyserial's error
                raise HardwareError(f"{exc}; {self.comm_failures} failed reads, the last: {lost}") \
                    from (lost.__cause__ or lost)
            raise HardwareError(f"{exc}: {self._read_problem()}") from None

    def _read_problem(self) -> str:
        return f"{self._where()}, {self.comm_failures} failed reads, last: {self.last_comm_error}"

    def _command_guard(self) -> Any:
        # the step's goal and its send are one unit against a safe_state() from elsewhere (the state read takes the
        # lock per transaction, so the hold waits at most for one answer)
        return self._io_lock

    def activate(self) -> None:
        self._forget_write_failures()
        self.sent_opening = math.nan   # what the servo was sent before may not be where the fingers are now
        super().activate()

    def _forget_write_failures(self) -> None:
        self._write_failing_since: float | None = None   # monotonic time of the first of the failed writes in a row
        self._write_fail_run = 0

    def _send_hold(self) -> None:
        self._hold_write = True   # the hold's write is tried again at once (no later step may send it)
        try:
            super()._send_hold()
        finally:
            self._hold_write = False

    def _hw_write(self, opening: float) -> None:
        """Goal_Position in a SYNC_WRITE, which the servo does not answer: what can fail is the port (pyserial
        raising: a USB glitch, or the adapter pulled) or the SDK's send (a short write, the port busy). A failed write
        is not retried within the step (its goal goes out with the next step's, one period later, the newer
        set-point: an immediate retry would lengthen a step whose bus is in trouble, and the state read after it);
        writes failing for longer than ``read_timeout`` are a fault. The safe state's hold is tried up to
        :data:`HOLD_TRIES` times at once (no step may follow it). After a failed write the set-point goes back to the
        last goal sent: the servo still has that one, the speed limit counts from it, and a hold while the reads are
        stale holds it (not a set-point that never reached the servo)."""
        p = self.params
        tries = HOLD_TRIES if getattr(self, "_hold_write", False) else 1
        with self._io_lock:   # (held already by a step's command guard and the safe state: an RLock)
            for attempt in range(tries):
                if attempt:
                    time.sleep(p.serial_poll)   # a glitch of the port may last a little
                failure = self._send_goal(opening)
                if failure is None:
                    self.sent_opening = opening
                    self._forget_write_failures()
                    return
                self.write_failures += 1
                self._write_fail_run += 1
                self.last_write_error = str(failure)
                if self._write_failing_since is None:
                    self._write_failing_since = time.monotonic()
            failing = time.monotonic() - self._write_failing_since
            if math.isfinite(getattr(self, "sent_opening", math.nan)):
                self._setpoint = self.sent_opening   # what the servo has (see above)
            cause = failure.__cause__   # the port's own error; None for the SDK's send failing
            if tries > 1:
                raise HardwareError(f"{failure} ({tries} tries)") from cause
            if failing > p.read_timeout:
                raise HardwareError(
                    f"sending Goal_Position to {self._servo()} failed for {failing:.3f} s ({self._write_fail_run} "
                    f"failed writes in a row; read_timeout {p.read_timeout:g} s): the servo keeps its last goal and "
                    f"the gripper no longer follows; the last: {failure}") from cause

    def _send_goal(self, opening: float) -> HardwareError | None:
        """One SYNC_WRITE of Goal_Position: None when it went out, else what failed (not raised). The bus is
        resynchronised before the next request (what went out, if anything, is unknown)."""
        ticks = self.ticks_for(opening)
        data = list(int(ticks & 0xFFFFFFFF).to_bytes(4, "little"))
        p = self.params
        try:
            with self._io_lock, self._port_guard("sending Goal_Position"):
                if not self.gsw.changeParam(p.dxl_id, data):
                    self.gsw.addParam(p.dxl_id, data)
                result = self.gsw.txPacket()
        except HardwareError as exc:
            if not port_failed(exc):
                raise
            return exc
        if result != self._sdk.COMM_SUCCESS:
            self._desync = True
            return HardwareError(f"sending Goal_Position to {self._where()}: {self.ph.getTxRxResult(result)}")
        return None

    def _hw_close(self) -> None:
        if getattr(self, "_port_open", False):
            # the torque stays on: the servo keeps holding its last Goal_Position (the safe state)
            self._port_open = False
            try:
                self.port.closePort()
            except Exception:
                pass

    def status(self) -> dict[str, Any]:
        d = super().status()
        d.update(comm_failures=getattr(self, "comm_failures", 0), stale_answers=getattr(self, "stale_answers", 0),
                 resyncs=getattr(self, "resyncs", 0), startup_retries=getattr(self, "startup_retries", 0),
                 write_failures=getattr(self, "write_failures", 0))
        return d


def _signed(value: int, size: int) -> int:
    bits = 8 * size
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


@hookimpl
def teletouch_components():
    return [DynamixelGripper]


#: USB ids of serial adapters used with Dynamixel servos (vendor, product) -> name
KNOWN_ADAPTERS = {(0x0403, 0x6014): "ROBOTIS U2D2 (FTDI FT232H)", (0x0483, 0x5740): "ROBOTIS OpenCR",
                  (0x2F5D, 0x2202): "ROBOTIS OpenRB-150"}


def _owner_group(path: str) -> str:
    """The group that owns ``path`` (dialout on Debian/Ubuntu, uucp on Arch), "dialout" when it cannot be told."""
    try:
        import grp

        return grp.getgrgid(os.stat(path).st_gid).gr_name
    except (ImportError, KeyError, OSError):
        return "dialout"


def permission_hint(path: str, vid: int = 0x0403, pid: int = 0x6014) -> str:
    """What gives this user access to a serial port: the group that owns it (dialout on Debian/Ubuntu), or a udev
    rule for the adapter's USB ids (default: the U2D2's)."""
    rule = (f"a udev rule (/etc/udev/rules.d/70-dynamixel.rules: KERNEL==\"tty[A-Z]*[0-9]*\", ATTRS{{idVendor}}==\""
            f"{vid:04x}\", ATTRS{{idProduct}}==\"{pid:04x}\", MODE=\"0666\", then sudo udevadm control --reload-rules "
            f"&& sudo udevadm trigger)")
    group = _owner_group(path)
    if group == "root":
        return f"give access with {rule}"
    return f"join the {group} group (sudo usermod -aG {group} $USER, then log out and in again), or use {rule}"


def _errnos(exc: BaseException | None) -> list[int]:
    """The errnos in ``exc`` and the exceptions it was raised from or during: pyserial's SerialException for a port
    that does not take a serial port's settings has none of its own, the termios.error it was raised during has
    ENOTTY ("Could not configure port: (25, 'Inappropriate ioctl for device')")."""
    found, seen = [], set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        err = getattr(exc, "errno", None)
        if err is None and isinstance(exc, termios.error) and exc.args and isinstance(exc.args[0], int):
            err = exc.args[0]
        if isinstance(err, int) and err:
            found.append(err)
        exc = exc.__cause__ or exc.__context__
    return found


def _node_kind(port: str) -> str:
    """What ``port`` is when it is not a terminal: "a regular file", "a character device that is not a terminal"."""
    try:
        mode = os.stat(port).st_mode
    except OSError:
        return "not a terminal"
    if stat.S_ISREG(mode):
        return "a regular file"
    if stat.S_ISCHR(mode):
        return "a character device that is not a terminal"
    return "not a terminal"


def port_open_hint(port: str, exc: BaseException) -> str:
    """What to do when ``port`` cannot be opened, from the errno of pyserial's own open (O_RDWR | O_NOCTTY |
    O_NONBLOCK; the port is not opened again: that would pulse DTR once more) through the meanings shared with
    `teletouch devices` (discovery.check_node): missing, permission (the group or udev rule; EPERM: a container's
    device rule), busy, gone; not a serial port (ENOTTY from configuring it: /dev/null, a file); without an errno,
    the checks that need no open."""
    err = getattr(exc, "errno", None)
    if err == errno.ENOENT or not os.path.lexists(port):
        return (f"{port} does not exist: plug in the USB adapter (U2D2, OpenCR) and check the port name; `teletouch "
                f"devices` lists the serial adapters, with the port param of each")
    if errno.ENOTTY in _errnos(exc):
        return (f"{port} is not a serial port ({_node_kind(port)}: ENOTTY, it takes no baud rate): set port to the "
                f"USB adapter's (U2D2, OpenCR), e.g. /dev/ttyUSB0 or /dev/ttyACM0; `teletouch devices` lists the "
                f"serial adapters, with the port param of each")
    if isinstance(err, int) and err:
        acc = discovery.NodeAccess(port, err, detail="open()")
    else:
        acc = discovery.check_node(port, open_node=False, sysfs_root=os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys"))
    if acc.errno is not None:
        problem = acc.problem(permission_hint(port))
        if acc.cause == "other":
            problem += ("; check that no other program (DYNAMIXEL Wizard, another teletouch) holds it; `teletouch "
                        "devices` lists the serial adapters")
        return problem
    return ("check that no other program (DYNAMIXEL Wizard, another teletouch) holds it; `teletouch devices` lists "
            "the serial adapters")


#: what the serial rows of `teletouch devices` checked (the ports are not opened: see discovery.check_node)
SERIAL_CHECK = ("not opened (opening a serial port pulses DTR, which resets Arduino-like boards): access(2), the "
                "mount and the device behind the node were checked")


def serial_ports() -> list[dict[str, Any]]:
    """USB serial ports (pyserial's list), with the Dynamixel adapters named, for `teletouch devices`: the
    dynamixel-gripper params that select each, whether this user may open it (``readable``, from
    discovery.check_node without opening the port: ``checked`` says so) and, when not, the ``problem`` saying why and
    how to get access."""
    from serial.tools import list_ports

    found = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        if p.vid is None:
            continue  # not a USB adapter (built-in UARTs)
        name = KNOWN_ADAPTERS.get((p.vid, p.pid))
        acc = discovery.check_node(p.device, open_node=False,
                                   sysfs_root=os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys"))
        readable = acc.readable
        details: dict[str, Any] = {"usb": f"{p.vid:04x}:{p.pid:04x}", "description": name or p.description or "",
                                   "readable": readable, "plugin": "dynamixel-gripper",
                                   "params": {"port": p.device}}
        if readable is not None:
            details["checked"] = SERIAL_CHECK
        if readable is False:
            details["access"] = acc.why()
            details["problem"] = acc.problem(permission_hint(p.device, p.vid, p.pid))
        found.append({"kind": "serial", "id": p.serial_number or p.device, "path": p.device, "details": details})
    return found


@hookimpl
def teletouch_discover_devices():
    return serial_ports()
