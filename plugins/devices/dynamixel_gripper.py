"""dynamixel-gripper: a Dynamixel servo gripper (Protocol 2.0, dynamixel-sdk) in current-based position mode.

The servo runs in current-based position mode (Operating_Mode 5): it goes to Goal_Position but never pushes with
more than Goal_Current, which is how the grip force is capped (``max_effort`` / ``newtons_per_amp``). Each step
reads Present_Current, Present_Velocity and Present_Position with one GroupSyncRead and sends Goal_Position with a
GroupSyncWrite. The status packet of that read is checked for the alert bit (0x80, set by the firmware while the
servo is in hardware-error shutdown), and Torque_Enable (with Hardware_Error_Status where the table has it) is polled
every ``error_check_period``: the torque dropping to 0 (a shutdown, or a servo reset by a brown-out) is a fault.

The servo's own speed limit: Profile_Velocity is set from ``max_speed`` at start-up (rounded down), so a setpoint
jump (the ``open`` safe state) is not run at the servo's full speed. A table without Profile_Velocity relies on the
driver's setpoint shaping only.

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
    profile_velocity: Item | None = Field((112, 4), description="Profile_Velocity (same unit as velocity_unit_rpm, "
                                          "0 = unlimited); None: the servo has no speed limit the driver can set")
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
    # ROBOTIS RH-P12-RN gripper: its own table; position 0 (open) .. 740 (closed). No Hardware_Error_Status and no
    # Profile_Velocity in this preset: a shutdown is detected by the alert bit and by polling Torque_Enable, and the
    # speed is limited only by the driver's setpoint shaping (a setpoint jump, e.g. safe_mode "open", runs at the
    # servo's own speed). Give "profile_velocity" in control_table once checked against your firmware's e-Manual.
    "rh-p12-rn": {"model_number": 35073, "torque_enable": (512, 1), "hardware_error_status": None,
                  "profile_velocity": None,
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
        error_check_period: Seconds = Field(0.1, gt=0, description="poll Torque_Enable and Hardware_Error_Status "
                                            "this often",
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
        # rounded down: the grip cap is at or below max_effort (ceil gave e.g. 186 units = 5.003 N for 5 N)
        want = int(math.floor(p.max_effort / p.newtons_per_amp / t.current_unit))
        if want < 1:  # 0 would not move at all, 1 unit would exceed max_effort
            raise HardwareError(f"max_effort {p.max_effort} N is below one Goal_Current unit of {self._where()} "
                                f"({t.current_unit * p.newtons_per_amp:.4f} N with newtons_per_amp "
                                f"{p.newtons_per_amp})")
        self.goal_current = min(want, limit)
        if want > limit:
            self.ctx.log(f"max_effort {p.max_effort} N needs Goal_Current {want} > Current_Limit {limit}; "
                         f"capped at {limit * t.current_unit * p.newtons_per_amp:.2f} N")
        self._write(t.goal_current, self.goal_current, "Goal_Current")
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
        self.comm_failures = 0
        self.last_comm_error = ""

    def _profile_velocity(self) -> int | None:
        """Profile_Velocity (raw) for ``max_speed``: rounded down so the servo's limit is at or below it."""
        p, t = self.params, self.table
        if t.profile_velocity is None:
            return None
        ticks_per_s = p.max_speed / abs(self.map.scale)
        # floor, with a hair of margin so that float error never rounds a just-above value back to the limit
        raw = int(math.floor(ticks_per_s / t.ticks_per_rev * 60.0 / t.velocity_unit_rpm * (1 - 1e-12)))
        if raw < 1:  # 0 would mean "no limit" to the servo
            slowest = t.velocity_unit_rpm / 60.0 * t.ticks_per_rev * abs(self.map.scale)
            raise HardwareError(f"max_speed {p.max_speed} m/s is below the slowest Profile_Velocity of "
                                f"{self._where()} ({slowest:.5f} m/s with this calibration)")
        return raw

    def _poll_shutdown(self) -> None:
        """Every error_check_period: Torque_Enable (0 while active: shutdown or reset) and Hardware_Error_Status."""
        p, t, sdk = self.params, self.table, self._sdk
        items = [t.torque_enable] + ([t.hardware_error_status] if t.hardware_error_status is not None else [])
        start = min(a for a, _ in items)
        length = max(a + s for a, s in items) - start
        spans = list(items) if length > 16 else [(start, length)]  # far apart: one read each
        mem: dict[int, int] = {}
        for addr, n in spans:
            data, result, error = self.ph.readTxRx(self.port, p.dxl_id, addr, n)
            if result != sdk.COMM_SUCCESS or len(data) != n:
                return  # a lost answer is the state read's business (read_timeout)
            if error & 0x80:
                self._alert("hardware-error alert (0x80) in the status packet")
            mem.update({addr + i: b for i, b in enumerate(data)})

        def value(item: Item) -> int:
            return int.from_bytes(bytes(mem[item[0] + i] for i in range(item[1])), "little")

        if t.hardware_error_status is not None and value(t.hardware_error_status):
            self._alert(f"Hardware_Error_Status {hw_error_text(value(t.hardware_error_status))}")
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
        p, t, sdk = self.params, self.table, self._sdk
        now = time.monotonic()
        if now - self._last_check >= p.error_check_period:
            self._last_check = now
            self._poll_shutdown()
        # GroupSyncRead.txRxPacket() drops the status packet's error byte (its rxPacket discards it): send the
        # SYNC_READ with the group, then take the answer with readRx, which returns the error byte too
        t0 = time.monotonic()
        result = self.gsr.txPacket()
        data: list[int] = []
        error = 0
        if result == sdk.COMM_SUCCESS:
            data, result, error = self.ph.readRx(self.port, p.dxl_id, self._rd_len)
        t1 = time.monotonic()
        if result != sdk.COMM_SUCCESS:
            self.comm_failures += 1
            self.last_comm_error = self.ph.getTxRxResult(result)
            return None
        if error & 0x80:
            self._alert("hardware-error alert (0x80) in the status packet of the state read")
        if len(data) != self._rd_len:
            # a late status packet of an earlier, timed-out request was taken as this one's answer
            self.comm_failures += 1
            self.last_comm_error = f"stale or short status packet ({len(data)} of {self._rd_len} bytes)"
            self.port.clearPort()
            return None
        if error:
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
