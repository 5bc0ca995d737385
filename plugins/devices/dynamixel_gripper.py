"""dynamixel-gripper: a Dynamixel servo gripper (Protocol 2.0, dynamixel-sdk) in current-based position mode.

The servo runs in current-based position mode (Operating_Mode 5): it goes to Goal_Position but never pushes with
more than Goal_Current, which is how the grip force is capped (``max_effort`` / ``newtons_per_amp``). Each step
reads Present_Current, Present_Velocity and Present_Position with one GroupSyncRead and sends Goal_Position with a
GroupSyncWrite. Hardware_Error_Status is polled every ``error_check_period``.

The opening maps linearly to ticks (``ticks_open`` <-> ``opening_at_ticks_open``, ``ticks_closed`` <->
``opening_at_ticks_closed``). Control tables are data: ``model`` picks a preset from :data:`CONTROL_TABLES`
(X-series such as the OpenManipulator-X's XM430-W350, or ROBOTIS RH-P12-RN) and ``control_table`` overrides it, so
a servo with another table needs configuration, not code.
"""

from __future__ import annotations

import math
import time
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from teletouch import HardwareError, hookimpl
from teletouch.units import Meters, Newtons, Seconds

from .follower_common import FollowerBase, FollowerParams, OpeningMap, Reading

Item = tuple[int, int]  # (address, size in bytes)


class ControlTable(BaseModel):
    """Addresses (address, bytes) of the items the driver uses, and the units of the servo's raw values."""

    model_config = ConfigDict(extra="forbid")
    model_number: int | None = Field(None, description="expected model number from PING (None: any)")
    operating_mode: Item = (11, 1)
    current_limit: Item = (38, 2)
    torque_enable: Item = (64, 1)
    hardware_error_status: Item | None = (70, 1)
    goal_current: Item = (102, 2)
    goal_position: Item = (116, 4)
    present_current: Item = (126, 2)
    present_velocity: Item = (128, 4)
    present_position: Item = (132, 4)
    current_unit: float = Field(2.69e-3, gt=0, description="A per raw current unit")
    velocity_unit_rpm: float = Field(0.229, gt=0, description="rev/min per raw velocity unit")
    ticks_per_rev: int = Field(4096, gt=0, description="position ticks per revolution")


#: Control tables of known models (ROBOTIS e-Manual; verify against your servo's firmware).
CONTROL_TABLES: dict[str, dict[str, Any]] = {
    # X-series (XM430-W350: OpenManipulator-X gripper, ID 15)
    "xm430-w350": {"model_number": 1020},
    "x-series": {},
    # ROBOTIS RH-P12-RN gripper: its own table; position 0 (open) .. 740 (closed)
    "rh-p12-rn": {"model_number": 35073, "torque_enable": (512, 1), "hardware_error_status": None,
                  "goal_current": (550, 2), "goal_position": (564, 4), "present_current": (574, 2),
                  "present_velocity": (576, 4), "present_position": (580, 4), "current_unit": 4.02e-3,
                  "velocity_unit_rpm": 0.01},
}

BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 2000000,
             2500000, 3000000, 3500000, 4000000)
HW_ERROR_BITS = {0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder", 0x10: "electrical shock",
                 0x20: "overload"}
CURRENT_BASED_POSITION = 5


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
        ticks_open: int = Field(1024, description="Goal_Position (ticks) at the open end")
        ticks_closed: int = Field(2048, description="Goal_Position (ticks) with the fingers closed")
        opening_at_ticks_open: Meters = Field(0.075, ge=0, description="opening at ticks_open",
                                              json_schema_extra={"unit": "m"})
        opening_at_ticks_closed: Meters = Field(0.0, ge=0, description="opening at ticks_closed",
                                                json_schema_extra={"unit": "m"})
        newtons_per_amp: float = Field(10.0, gt=0, description="grip force per ampere of motor current "
                                       "(calibrate for your gripper)", json_schema_extra={"unit": "N/A"})
        error_check_period: Seconds = Field(0.1, gt=0, description="poll Hardware_Error_Status this often",
                                            json_schema_extra={"unit": "s"})
        serial_poll: Seconds = Field(0.0005, gt=0, le=0.01, description="serial read blocking granularity",
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
            if self.ticks_open == self.ticks_closed:
                raise ValueError("ticks_open and ticks_closed must differ")
            OpeningMap(self.ticks_open, self.opening_at_ticks_open, self.ticks_closed, self.opening_at_ticks_closed)
            self.table()  # validates control_table
            return self

        def table(self) -> ControlTable:
            items = dict(CONTROL_TABLES[self.model])
            items.update(self.control_table or {})
            return ControlTable(**items)

    # mapping ---------------------------------------------------------------------------------------------------
    @property
    def map(self) -> OpeningMap:
        p = self.params
        return OpeningMap(p.ticks_open, p.opening_at_ticks_open, p.ticks_closed, p.opening_at_ticks_closed)

    def ticks_for(self, opening: float) -> int:
        return self.map.counts(opening)

    def opening_for(self, ticks: float) -> float:
        return self.map.opening(ticks)

    # hardware --------------------------------------------------------------------------------------------------
    def _where(self) -> str:
        p = self.params
        return f"Dynamixel ID {p.dxl_id} on {p.port} at {p.baudrate} baud"

    def _check(self, what: str, result: int, error: int) -> None:
        if result != self._sdk.COMM_SUCCESS:
            raise HardwareError(f"{what}: no valid answer from {self._where()} ({self.ph.getTxRxResult(result)}); "
                                f"check power, cable, ID and baud rate")
        if error & 0x80:
            raise HardwareError(f"{what}: {self._where()} reports a hardware error ({self._hw_error()}); "
                                f"power-cycle or reboot the servo")
        if error:
            raise HardwareError(f"{what}: {self._where()} refused it ({self.ph.getRxPacketError(error)})")

    def _hw_error(self) -> str:
        item = self.table.hardware_error_status
        if item is None:
            return "details not in this control table"
        value, result, _ = self.ph.read1ByteTxRx(self.port, self.params.dxl_id, item[0])
        return hw_error_text(value) if result == self._sdk.COMM_SUCCESS else "status unreadable"

    def _write(self, item: Item, value: int, what: str) -> None:
        addr, size = item
        fn = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx, 4: self.ph.write4ByteTxRx}[size]
        result, error = fn(self.port, self.params.dxl_id, addr, value & ((1 << (8 * size)) - 1))
        self._check(f"writing {what}", result, error)

    def _read(self, item: Item, what: str) -> int:
        addr, size = item
        fn = {1: self.ph.read1ByteTxRx, 2: self.ph.read2ByteTxRx, 4: self.ph.read4ByteTxRx}[size]
        value, result, error = fn(self.port, self.params.dxl_id, addr)
        self._check(f"reading {what}", result, error)
        return _signed(value, size)

    def _hw_open(self) -> None:
        import dynamixel_sdk as sdk

        p = self.params
        self._sdk = sdk
        self.table = p.table()
        self.port = sdk.PortHandler(p.port)
        self.ph = sdk.PacketHandler(2.0)
        self.port.baudrate = p.baudrate
        try:
            ok = self.port.openPort() and self.port.setBaudRate(p.baudrate)
        except Exception as exc:
            raise HardwareError(f"cannot open {p.port} ({exc}); check the USB adapter is plugged in and that you "
                                f"may use it (group dialout)") from exc
        if not ok:
            raise HardwareError(f"cannot set {p.baudrate} baud on {p.port}")
        self._port_open = True
        # pyserial blocks for at most serial_poll per read instead of spinning (the SDK polls with timeout 0)
        self.port.ser.timeout = p.serial_poll
        model, result, error = self.ph.ping(self.port, p.dxl_id)
        self._check("ping", result, error)
        t = self.table
        if t.model_number is not None and model != t.model_number:
            raise HardwareError(f"{self._where()} answered with model number {model}, expected {t.model_number} "
                                f"({p.model}); check the ID and the 'model' parameter")
        self._write(t.torque_enable, 0, "Torque_Enable=0")
        self._write(t.operating_mode, CURRENT_BASED_POSITION, "Operating_Mode=5 (current-based position)")
        limit = self._read(t.current_limit, "Current_Limit")
        want = int(math.ceil(p.max_effort / p.newtons_per_amp / t.current_unit))
        self.goal_current = min(want, limit)
        if want > limit:
            self.ctx.log(f"max_effort {p.max_effort} N needs Goal_Current {want} > Current_Limit {limit}; "
                         f"capped at {limit * t.current_unit * p.newtons_per_amp:.2f} N")
        self._write(t.goal_current, self.goal_current, "Goal_Current")
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
        self.comm_failures = 0
        self.last_comm_error = ""

    def _hw_read(self) -> Reading | None:
        p, t, sdk = self.params, self.table, self._sdk
        now = time.monotonic()
        if t.hardware_error_status is not None and now - self._last_check >= p.error_check_period:
            self._last_check = now
            bits, result, error = self.ph.read1ByteTxRx(self.port, p.dxl_id, t.hardware_error_status[0])
            if result == sdk.COMM_SUCCESS and (bits or error & 0x80):
                raise HardwareError(f"{self._where()} reports a hardware error ({hw_error_text(bits)}); torque is "
                                    f"off. Remove the cause, then reboot or power-cycle the servo")
        t0 = time.monotonic()
        result = self.gsr.txRxPacket()
        t1 = time.monotonic()
        if result != sdk.COMM_SUCCESS or not self.gsr.isAvailable(p.dxl_id, self._rd_start, self._rd_len):
            self.comm_failures += 1
            self.last_comm_error = self.ph.getTxRxResult(result)
            return None
        if len(self.gsr.data_dict.get(p.dxl_id) or ()) != self._rd_len:
            # a late status packet of an earlier, timed-out request was taken as this one's answer
            self.comm_failures += 1
            self.last_comm_error = f"stale or short status packet ({len(self.gsr.data_dict.get(p.dxl_id) or ())} " \
                                   f"of {self._rd_len} bytes)"
            self.port.clearPort()
            return None

        def get(item: Item) -> int:
            return _signed(self.gsr.getData(p.dxl_id, item[0], item[1]), item[1])

        ticks = get(t.present_position)
        vel_ticks = get(t.present_velocity) * t.velocity_unit_rpm / 60.0 * t.ticks_per_rev
        amps = get(t.present_current) * t.current_unit
        return Reading(self.opening_for(ticks), vel_ticks * self.map.scale, abs(amps) * p.newtons_per_amp,
                       0.5 * (t0 + t1))

    def read_state(self, t: float) -> Reading:
        try:
            return super().read_state(t)
        except HardwareError as exc:
            raise HardwareError(f"{exc}: {self._where()}, {self.comm_failures} failed reads, last: "
                                f"{self.last_comm_error}") from None

    def _hw_write(self, opening: float) -> None:
        ticks = self.ticks_for(opening)
        data = list(int(ticks & 0xFFFFFFFF).to_bytes(4, "little"))
        p = self.params
        if not self.gsw.changeParam(p.dxl_id, data):
            self.gsw.addParam(p.dxl_id, data)
        result = self.gsw.txPacket()
        if result != self._sdk.COMM_SUCCESS:
            raise HardwareError(f"sending Goal_Position to {self._where()}: {self.ph.getTxRxResult(result)}")

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
        d.update(comm_failures=getattr(self, "comm_failures", 0))
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


def serial_ports() -> list[dict[str, Any]]:
    """USB serial ports (pyserial's list), with the Dynamixel adapters named, for `teletouch devices`."""
    from serial.tools import list_ports

    found = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        if p.vid is None:
            continue  # not a USB adapter (built-in UARTs)
        name = KNOWN_ADAPTERS.get((p.vid, p.pid))
        found.append({"kind": "serial", "id": p.serial_number or p.device, "path": p.device,
                      "details": {"usb": f"{p.vid:04x}:{p.pid:04x}", "description": name or p.description or "",
                                  "plugin": "dynamixel-gripper", "params": {"port": p.device}}})
    return found


@hookimpl
def teletouch_discover_devices():
    return serial_ports()
