"""An emulated Dynamixel servo (Protocol 2.0) on a pseudo-terminal, for testing the dynamixel-gripper driver.

The driver opens the pty's slave path with dynamixel-sdk's ``PortHandler`` exactly as it would open /dev/ttyUSB0;
this emulator sits on the master side, decodes the instruction packets byte by byte (header, CRC-16, byte
stuffing) and answers with status packets like the servo's firmware: PING, READ, WRITE, SYNC_READ, SYNC_WRITE,
REBOOT; CRC, access, range and instruction errors in the status packet's error byte; a hardware-error alert bit;
and it can be told to stop answering, to lose a given number of answers (``drop``), to corrupt its answers, or to
answer late; ``refuse_reads`` (address -> error byte) refuses, and ``drop_reads`` (addresses) loses, the answers to
READs that start at given addresses (one item of a poll refused or lost while the others are answered);
``refuse_writes`` (address -> error byte) refuses WRITEs that start at given addresses (not applied);
``ping_delay`` answers a PING that many seconds late (a busy servo: a resync PING that takes a while);
``unplug()`` pulls the USB adapter: the pty's master side closes, and the driver's port fails as a pulled adapter's
does (pyserial's SerialException on read, EIO from tcflush), as the lab audit did it.

Models (``MODELS``): an XM430-W350 (X-series table) and the ROBOTIS RH-P12-RN gripper with either firmware: the
RH-P12-RN(A) firmware (model number 35074, DYNAMIXEL-P-like table) and the old RH-P12-RN firmware (35073,
DYNAMIXEL-PRO-like table, whose Goal_Velocity is the profile's top speed), with the addresses of the ROBOTIS
e-Manual. The XM430-W350 has Drive_Mode (10, EEPROM; ``drive_mode`` sets it): bit 2 (Profile Configuration) makes the
profile time-based, Profile_Velocity then being the time of each move in ms (firmware V42 on); its other bits
(direction, torque on by goal update) are stored, not modelled. The RH-P12-RN tables have no time-based profile.
Min/Max_Position_Limit bound Goal_Position as on the servos (``Table.limited_modes``): the XM430's in position control
mode only (in current-based position mode it takes any goal within +-256 rev), the RH-P12-RN's (0..1150) in
current-based position mode too: a goal beyond them is refused, a SYNC_WRITE's silently.

Late answers: ``late_answers`` puts a short (1-byte) late status packet before SYNC_READ answers;
``delay_answers`` holds back whole SYNC_READ answers (taken when the request arrives, so they carry the servo's
state of that moment), either for ``answer_delay`` seconds (the servo is busy, requests queue) or, with
``answer_delay`` None, until the next instruction that is answered arrives, whose answer then follows it: what a
master sees when an answer comes after its timeout. ``on_delayed`` runs once a held-back answer's data is taken.

Timing: the emulator reads the baud rate the driver set on the pty (termios) and waits for the time the bytes would
take on a real wire (10 bits per byte, instruction and status) plus the servo's Return_Delay_Time, so a run at
57600 baud is as slow as the real bus.

The servo model: current-based position mode; the horn moves towards Goal_Position at ``speed`` ticks/s (the
servo's top speed), or at Profile_Velocity where that is set (non-zero; 0 means no limit, as on the servo; with a
time-based profile, at the speed that covers the move, from where the horn was when its Goal_Position arrived, in
Profile_Velocity ms); an object
(``block_at`` ticks, approached in the ``closing`` direction) stops it there, and the current rises to
``min(Goal_Current, current_gain * |goal - block_at|)``. ``trace`` records (monotonic, position in ticks) at every
physics update, so a test can measure the speed the horn actually moved at; ``poll()`` advances the physics without a
packet. ``instant`` (for benchmarks/follower_latency.py, which times the transport, not the motion): the horn is at
Goal_Position at the next physics update (the next packet), whatever Profile_Velocity and ``speed`` say; an object
still stops it. In hardware-error shutdown (``inject_hardware_error``) the torque is off and every status packet
carries the alert bit (0x80) in its error byte, as on the firmware.
"""

from __future__ import annotations

import contextlib
import os
import select
import struct
import termios
import threading
import time
import tty
from dataclasses import dataclass
from typing import Callable, Iterator

# --- Protocol 2.0 constants (ROBOTIS e-Manual) ------------------------------------------------------------------
HEADER = b"\xff\xff\xfd\x00"
INST_PING, INST_READ, INST_WRITE, INST_REBOOT = 0x01, 0x02, 0x03, 0x08
INST_STATUS, INST_SYNC_READ, INST_SYNC_WRITE = 0x55, 0x82, 0x83
BROADCAST = 0xFE
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = range(1, 8)
ALERT = 0x80
# Hardware_Error_Status bits
HW_INPUT_VOLTAGE, HW_OVERHEATING, HW_ENCODER, HW_ELECTRICAL_SHOCK, HW_OVERLOAD = 0x01, 0x04, 0x08, 0x10, 0x20

BAUDS = {getattr(termios, f"B{b}"): b for b in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000,
                                                 921600, 1000000, 1152000, 2000000, 2500000, 3000000, 3500000,
                                                 4000000) if hasattr(termios, f"B{b}")}


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


_CRC = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16 (polynomial 0x8005, initial 0, not reflected) of Protocol 2.0."""
    c = 0
    for b in data:
        c = ((c << 8) ^ _CRC[((c >> 8) ^ b) & 0xFF]) & 0xFFFF
    return c


def stuff(body: bytes) -> bytes:
    """Insert 0xFD after every FF FF FD in the instruction/parameter field (the header's FF FF FD is before it)."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3:-1] == b"\xff\xff":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if body[i] == 0xFD and len(out) >= 3 and out[-3:-1] == b"\xff\xff" and i + 1 < len(body) \
                and body[i + 1] == 0xFD:
            i += 1  # drop the stuffed byte
        i += 1
    return bytes(out)


def packet(dxl_id: int, inst: int, params: bytes) -> bytes:
    body = stuff(bytes([inst]) + params)
    head = HEADER + bytes([dxl_id]) + struct.pack("<H", len(body) + 2)
    msg = head + body
    return msg + struct.pack("<H", crc16(msg))


@dataclass(frozen=True)
class Table:
    """Addresses (address, size) of the items the emulator models; ``eeprom_end``: first RAM address."""

    model_number: int
    firmware: int
    eeprom_end: int
    return_delay: tuple[int, int]
    operating_mode: tuple[int, int]
    current_limit: tuple[int, int]
    max_position: tuple[int, int]
    min_position: tuple[int, int]
    torque_enable: tuple[int, int]
    hardware_error: tuple[int, int] | None
    goal_current: tuple[int, int]
    goal_position: tuple[int, int]
    present_current: tuple[int, int]
    present_velocity: tuple[int, int]
    present_position: tuple[int, int]
    current_limit_default: int
    max_position_default: int
    min_position_default: int
    velocity_unit_rpm: float
    size: int = 1024
    profile_velocity: tuple[int, int] | None = None  # unit velocity_unit_rpm, 0 = unlimited
    velocity_limit: tuple[int, int] | None = None  # where set: Profile_Velocity above it is refused (limit error)
    velocity_limit_default: int = 0
    drive_mode: tuple[int, int] | None = None  # where set: bit 2 (TIME_BASED_PROFILE) makes Profile_Velocity a time
    #: the operating modes whose Goal_Position the position limits bound (X-series: position control only; in
    #: current-based position mode the goal may be anywhere in +-256 rev, e-Manual)
    limited_modes: tuple[int, ...] = (3, 5)


#: Drive_Mode bit 2, Profile Configuration: 0 velocity-based, 1 time-based (Profile_Velocity in ms per move)
TIME_BASED_PROFILE = 0x04

XM430_W350 = Table(1020, 48, 64, (9, 1), (11, 1), (38, 2), (48, 4), (52, 4), (64, 1), (70, 1), (102, 2), (116, 4),
                   (126, 2), (128, 4), (132, 4), 1193, 4095, 0, 0.229, profile_velocity=(112, 4),
                   drive_mode=(10, 1), limited_modes=(3,))
# ROBOTIS RH-P12-RN(A) firmware (e-Manual platform/rh_p12_rna): RAM from 512; Current_Limit 1984 mA, Velocity_Limit
# 2970 x 0.01 rev/min, position limits 0 .. 1150
RH_P12_RN_A = Table(35074, 1, 512, (9, 1), (11, 1), (38, 2), (48, 4), (52, 4), (512, 1), (518, 1), (550, 2),
                    (564, 4), (574, 2), (576, 4), (580, 4), 1984, 1150, 0, 0.01, profile_velocity=(560, 4),
                    velocity_limit=(44, 4), velocity_limit_default=2970)
# the old RH-P12-RN firmware (e-Manual platform/rh_p12_rn): RAM from 562; Current_Limit 820 x ~4.02 mA,
# Velocity_Limit 100 x 0.114 rev/min; Goal_Velocity (600) caps the profile's speed in current-based position mode
RH_P12_RN = Table(35073, 1, 562, (9, 1), (11, 1), (30, 2), (36, 4), (40, 4), (562, 1), (892, 1), (604, 2), (596, 4),
                  (621, 2), (615, 4), (611, 4), 820, 1150, 0, 0.114, profile_velocity=(600, 4),
                  velocity_limit=(32, 4), velocity_limit_default=100)

MODELS = {"xm430-w350": XM430_W350, "rh-p12-rn-a": RH_P12_RN_A, "rh-p12-rn": RH_P12_RN}

#: The USB adapter's latency timer (ms) the tests give dynamixel-sdk (``slow_adapter``): its packet timeout is twice
#: this plus the bytes' time. The SDK assumes an FTDI's 16 ms (a packet timeout of about 34 ms), which a servo meets
#: with room to spare; this emulator answers from a Python thread of the test process, which a loaded 2-core machine
#: (and the driver's own polling loop, in the same process) can keep off the CPU for longer than that: every request
#: of a start-up then failed now and then ('no status packet'). An FTDI's latency timer is a setting of the adapter
#: (1-255 ms), so this is a slower adapter, not another protocol.
ADAPTER_LATENCY_MS = 60


@contextlib.contextmanager
def slow_adapter(latency_ms: float = ADAPTER_LATENCY_MS) -> Iterator[float]:
    """dynamixel-sdk with a USB adapter whose latency timer is ``latency_ms``; yields the packet timeout (s) of a
    short status packet, for tests whose answers must come after it.

    Also, while it waits for an answer, the SDK's own ``PortHandler.readPort`` waits up to 1 ms for the port to
    become readable (a select() that releases the GIL) before it reads, instead of spinning: the SDK polls the port
    in a busy loop that holds the GIL, and the emulator, a thread of the same process, got it only between two polls.
    This is for tests that use dynamixel-sdk directly: the dynamixel-gripper driver's port is a subclass with its own
    waiting read (dynamixel_gripper.port_handler_class), which this patch does not reach, so the driver's tests run
    the driver's code. The bytes read and the packet timeout are the SDK's own."""
    from dynamixel_sdk import port_handler

    read = port_handler.PortHandler.readPort

    def read_when_ready(self, length):
        try:
            select.select([self.ser.fileno()], [], [], 0.001)
        except (OSError, ValueError, AttributeError):   # closed or not a real port: the SDK's read says so
            pass
        return read(self, length)

    old = port_handler.LATENCY_TIMER
    port_handler.LATENCY_TIMER = latency_ms
    port_handler.PortHandler.readPort = read_when_ready
    try:
        yield (2.0 * latency_ms + 2.0) / 1000.0
    finally:
        port_handler.LATENCY_TIMER = old
        port_handler.PortHandler.readPort = read


class DynamixelEmulator:
    """One or more servos on one emulated bus; ``port`` is the path to give PortHandler."""

    def __init__(self, dxl_id: int = 15, model: str = "xm430-w350", *, position: int = 2048,
                 speed: float = 3000.0, block_at: int | None = None, closing: int = 1, current_gain: float = 2.0,
                 wire_timing: bool = True, return_delay: int = 0, instant: bool = False, drive_mode: int = 0):
        self.table = MODELS[model]
        self.id = dxl_id
        self.mem = bytearray(self.table.size)
        t = self.table
        self._put(("m", 0, 2), t.model_number)
        self.mem[6] = t.firmware
        self.mem[7] = dxl_id
        self._put(t.return_delay, return_delay)
        self._put(t.operating_mode, 3)
        if t.drive_mode is not None:
            self._put(t.drive_mode, drive_mode)
        elif drive_mode:
            raise ValueError(f"model {model!r} has no Drive_Mode in the emulator's table")
        self._put(t.current_limit, t.current_limit_default)
        self._put(t.max_position, t.max_position_default)
        self._put(t.min_position, t.min_position_default)
        if t.velocity_limit is not None:
            self._put(t.velocity_limit, t.velocity_limit_default)
        self._put(t.goal_position, position)
        self._put(t.present_position, position)
        self.pos = float(position)
        self._goal_seen = position   # the last Goal_Position the physics saw, and the move it started (ticks)
        self._move_ticks = 0.0
        self.speed = speed
        self.block_at = block_at
        self.closing = closing
        self.current_gain = current_gain
        self.wire_timing = wire_timing
        self.instant = instant       # at the goal at the next update, no profile speed (benchmarks only)
        # fault injection
        self.silent = False          # stop answering (cable pulled, servo dead)
        self.drop_answers = 0        # lose this many answers (noise on the bus) ...
        self.drop_after = 0          # ... after letting this many more through first
        self.dropped: list[bytes] = []   # the status packets lost so far
        self.corrupt_crc = False     # answer with a wrong CRC
        self.status_error = 0        # error byte added to every status packet
        self.write_error = 0         # error byte answered to every WRITE (the write is not applied)
        self.late_answers = 0        # answer this many SYNC_READs with a late 1-byte status first (as after a timeout)
        self.delay_answers = 0       # hold back this many SYNC_READ answers (full length, the state when asked) ...
        self.answer_delay: float | None = None  # ... for this long (s), or None: until the next answered request
        self.on_delayed: Callable[[], None] | None = None  # called (lock held) once a held-back answer is taken
        self.delayed: list[tuple[float, bytes]] = []  # (monotonic, data) of every held-back answer
        self._held: tuple[int, int, bytes] | None = None
        self.refuse_reads: dict[int, int] = {}  # READ start address -> error byte answered instead of the data
        self.drop_reads: set[int] = set()        # READ start addresses whose answers are lost (kept in ``dropped``)
        self.refuse_writes: dict[int, int] = {}  # WRITE start address -> error byte answered (the write not applied)
        self.ping_delay = 0.0        # answer a PING this long (s) after it arrived (busy: the requests after it queue)
        # observation
        self.rx_packets: list[tuple[float, int, int, bytes]] = []  # (monotonic, id, instruction, params)
        self.trace: list[tuple[float, float]] = []  # (monotonic, position in ticks) at every physics update
        self.raw_rx = bytearray()
        self.raw_tx = bytearray()
        self.crc_errors = 0
        self._lock = threading.Lock()
        self._last = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)

    # --- control table helpers -------------------------------------------------------------------------------
    def _put(self, item, value: int) -> None:
        addr, size = item[-2], item[-1]
        struct.pack_into({1: "<B", 2: "<H", 4: "<I"}[size], self.mem, addr, int(value) & ((1 << (8 * size)) - 1))

    def get(self, item) -> int:
        addr, size = item[-2], item[-1]
        return struct.unpack_from({1: "<B", 2: "<h", 4: "<i"}[size], self.mem, addr)[0]

    def inject_hardware_error(self, bits: int = HW_OVERLOAD, alert: bool = True) -> None:
        """What the firmware does on overload etc.: set Hardware_Error_Status, torque off, alert bit in statuses
        (``alert`` False: the register and the torque only, so that a test sees what the register alone shows)."""
        with self._lock:
            if self.table.hardware_error is not None:
                self._put(self.table.hardware_error, bits)
            self._put(self.table.torque_enable, 0)
            self._alert = alert

    _alert = False

    def poll(self) -> None:
        """Advance the physics now (the servo moves between packets too; tests sample ``trace``)."""
        with self._lock:
            self._update()

    def time_based(self) -> bool:
        """Whether Drive_Mode selects the time-based profile (Profile_Velocity: the time of each move in ms)."""
        t = self.table
        return t.drive_mode is not None and bool(self.get(t.drive_mode) & TIME_BASED_PROFILE)

    def max_speed_ticks(self) -> float:
        """Ticks/s the horn may move at: Profile_Velocity where set (non-zero), else the servo's top speed. With a
        time-based profile Profile_Velocity is the move's time (ms): the speed that covers the move in that time."""
        t = self.table
        if t.profile_velocity is not None:
            raw = self.get(t.profile_velocity)
            raw = abs(raw)  # the old RH-P12-RN firmware's Goal_Velocity may be negative
            if raw > 0 and self.time_based():
                return min(self.speed, self._move_ticks / (raw / 1000.0))
            if raw > 0:
                return min(self.speed, raw * t.velocity_unit_rpm / 60.0 * 4096.0)
        return self.speed

    # --- life cycle ------------------------------------------------------------------------------------------
    def start(self) -> "DynamixelEmulator":
        self._thread = threading.Thread(target=self._serve, name="dxl-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._closed:   # closed already: the fds' numbers may belong to someone else by now
            return
        self._closed = True
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    _closed = False

    def unplug(self) -> None:
        """The USB adapter pulled mid-run: the servo goes away with the pty's master side, so the driver's open port
        reads "device reports readiness to read but returned no data" / EIO, and its tcflush fails with EIO. The
        fds are closed once (``stop()`` after this closes nothing)."""
        self.stop()

    def __enter__(self) -> "DynamixelEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def baudrate(self) -> int:
        try:
            speed = termios.tcgetattr(self.master)[5]
        except termios.error:
            return 57600
        return BAUDS.get(speed, 57600)

    # --- physics ---------------------------------------------------------------------------------------------
    def _update(self) -> None:
        now = time.monotonic()
        dt = now - self._last
        self._last = now
        t = self.table
        torque = self.get(t.torque_enable) == 1
        goal = self.get(t.goal_position)
        if goal != self._goal_seen:   # a new move: a time-based profile spreads it over Profile_Velocity ms
            self._goal_seen, self._move_ticks = goal, abs(goal - self.pos)
        current = 0.0
        if torque:
            err = goal - self.pos
            v = self.max_speed_ticks()
            new = float(goal) if self.instant else self.pos + max(-v * dt, min(v * dt, err))
            if self.block_at is not None:
                c = self.closing
                if (new - self.block_at) * c > 0:  # would move into the object
                    new = float(self.block_at) if (self.pos - self.block_at) * c <= 0 else self.pos
                if (new - self.block_at) * c >= 0 and (goal - self.block_at) * c > 0:
                    squeeze = self.current_gain * abs(goal - self.block_at)
                    current = c * min(self.get(t.goal_current), squeeze)
            vel_ticks = (new - self.pos) / dt if dt > 0 else 0.0
            self.pos = new
        else:
            vel_ticks = 0.0
        rpm = vel_ticks / 4096.0 * 60.0
        self._put(t.present_velocity, int(round(rpm / t.velocity_unit_rpm)))
        self._put(t.present_position, int(round(self.pos)))
        self._put(t.present_current, int(round(current)))
        self.trace.append((now, self.pos))

    # --- protocol --------------------------------------------------------------------------------------------
    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self.master], [], [], 0.05)
            except (OSError, ValueError):
                return
            if not r:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            self.raw_rx += data
            buf += data
            while True:
                i = buf.find(HEADER)
                if i < 0:
                    del buf[:max(0, len(buf) - 3)]
                    break
                del buf[:i]
                if len(buf) < 7:
                    break
                length = struct.unpack_from("<H", buf, 5)[0]
                total = 7 + length
                if len(buf) < total:
                    break
                pkt = bytes(buf[:total])
                del buf[:total]
                self._handle(pkt)

    def _handle(self, pkt: bytes) -> None:
        dxl_id = pkt[4]
        body = unstuff(pkt[7:-2])
        if crc16(pkt[:-2]) != struct.unpack_from("<H", pkt, len(pkt) - 2)[0]:
            self.crc_errors += 1
            if dxl_id == self.id:
                self._reply(len(pkt), ERR_CRC, b"")
            return
        inst, params = body[0], body[1:]
        if dxl_id not in (self.id, BROADCAST):
            return
        with self._lock:
            self.rx_packets.append((time.monotonic(), dxl_id, inst, params))
            self._update()
            answered = inst in (INST_PING, INST_READ, INST_REBOOT) or (inst == INST_WRITE and dxl_id == self.id) \
                or (inst == INST_SYNC_READ and self.id in params[4:])
            if answered and self._held is not None:  # the held-back answer goes out now, late, before this one's
                held, self._held = self._held, None
                self._reply(*held)
            if inst == INST_PING:
                if self.ping_delay > 0:
                    time.sleep(self.ping_delay)
                self._reply(len(pkt), 0, struct.pack("<HB", self.table.model_number, self.table.firmware))
            elif inst == INST_READ:
                if len(params) != 4:
                    return self._reply(len(pkt), ERR_DATA_LENGTH, b"")
                addr, n = struct.unpack("<HH", params)
                if addr + n > self.table.size:
                    return self._reply(len(pkt), ERR_ACCESS, b"")
                if addr in self.refuse_reads:  # refused (e.g. an item this firmware does not give out)
                    return self._reply(len(pkt), self.refuse_reads[addr], b"")
                if addr in self.drop_reads:  # this one answer lost on the bus, every time
                    self.dropped.append(packet(self.id, INST_STATUS, bytes([0]) + bytes(self.mem[addr:addr + n])))
                    return
                self._reply(len(pkt), 0, bytes(self.mem[addr:addr + n]))
            elif inst == INST_WRITE:
                if len(params) < 3:
                    return self._reply(len(pkt), ERR_DATA_LENGTH, b"")
                addr = struct.unpack_from("<H", params)[0]
                err = self.write_error or self.refuse_writes.get(addr) or self._write(addr, params[2:])
                if dxl_id == self.id:
                    self._reply(len(pkt), err, b"")
            elif inst == INST_SYNC_WRITE:
                addr, n = struct.unpack_from("<HH", params)
                rec = params[4:]
                for k in range(0, len(rec) - n, n + 1):
                    if rec[k] == self.id:
                        self._write(addr, rec[k + 1:k + 1 + n])
            elif inst == INST_SYNC_READ:
                addr, n = struct.unpack_from("<HH", params)
                if self.id in params[4:]:
                    if self.late_answers > 0:
                        self.late_answers -= 1
                        a = (self.table.hardware_error or self.table.torque_enable)[0]
                        self._reply(0, 0, bytes(self.mem[a:a + 1]))  # a late answer to an earlier 1-byte READ
                    data = bytes(self.mem[addr:addr + n])
                    if self.delay_answers > 0:
                        self.delay_answers -= 1
                        self.delayed.append((time.monotonic(), data))
                        if self.on_delayed is not None:
                            self.on_delayed()
                        if self.answer_delay is None:
                            self._held = (len(pkt), 0, data)
                            return
                        time.sleep(self.answer_delay)  # busy: the requests that follow queue up
                    self._reply(len(pkt), 0, data)
            elif inst == INST_REBOOT:
                self._reply(len(pkt), 0, b"")
                if self.table.hardware_error is not None:
                    self._put(self.table.hardware_error, 0)
                self._put(self.table.torque_enable, 0)
                self._alert = False
            elif dxl_id == self.id:
                self._reply(len(pkt), ERR_INSTRUCTION, b"")

    def _write(self, addr: int, data: bytes) -> int:
        t = self.table
        if addr + len(data) > t.size:
            return ERR_ACCESS
        ro = [t.present_current, t.present_velocity, t.present_position] + \
             ([t.hardware_error] if t.hardware_error else [])
        for a, s in ro:
            if addr < a + s and a < addr + len(data):
                return ERR_ACCESS
        if addr < t.eeprom_end and self.get(t.torque_enable) == 1:
            return ERR_ACCESS  # EEPROM is locked while the torque is on
        backup = bytes(self.mem[addr:addr + len(data)])
        self.mem[addr:addr + len(data)] = data
        if self.get(t.goal_current) > self.get(t.current_limit) or self.get(t.goal_current) < 0:
            self.mem[addr:addr + len(data)] = backup
            return ERR_DATA_LIMIT
        g = self.get(t.goal_position)
        if self.get(t.operating_mode) in t.limited_modes \
                and not (self.get(t.min_position) <= g <= self.get(t.max_position)):
            self.mem[addr:addr + len(data)] = backup
            return ERR_DATA_LIMIT
        if t.profile_velocity is not None and t.velocity_limit is not None \
                and abs(self.get(t.profile_velocity)) > self.get(t.velocity_limit):
            self.mem[addr:addr + len(data)] = backup
            return ERR_DATA_LIMIT
        if self._alert and self.get(t.torque_enable) == 1:
            self._put(t.torque_enable, 0)  # cannot enable torque while in hardware error
            return ERR_RESULT_FAIL
        return 0

    def drop(self, n: int = 1, after: int = 0) -> None:
        """Lose the ``n`` answers that follow the next ``after`` ones (a packet lost to noise, or a servo busy
        writing its EEPROM): each is not sent, and is recorded in ``dropped``."""
        with self._lock:
            self.drop_answers, self.drop_after = n, after

    def _reply(self, rx_len: int, err: int, params: bytes) -> None:
        if self.silent:
            return
        if self.drop_answers > 0:
            if self.drop_after > 0:
                self.drop_after -= 1
            else:
                self.drop_answers -= 1
                self.dropped.append(packet(self.id, INST_STATUS, bytes([err | self.status_error]) + params))
                return
        err |= self.status_error
        if self._alert:
            err |= ALERT
        out = bytearray(packet(self.id, INST_STATUS, bytes([err]) + params))
        if self.corrupt_crc:
            out[-1] ^= 0x5A
        if self.wire_timing:
            baud = self.baudrate()
            delay = (rx_len + len(out)) * 10.0 / baud + 2e-6 * self.get(self.table.return_delay)
            if delay < 0.002:   # (a few bytes at 1 Mbaud: waited without giving the GIL to the driver's busy loop)
                t_end = time.perf_counter() + delay
                while time.perf_counter() < t_end:
                    pass
            else:
                time.sleep(delay)
        self.raw_tx += out
        try:
            os.write(self.master, bytes(out))
        except OSError:
            pass
