"""An emulated CiA 402 servo drive: a canopen LocalNode on python-can's virtual bus, for the canopen-gripper tests.

The drive speaks real CANopen frames on a virtual channel: an SDO server (LocalNode), NMT slave with heartbeat, PDOs
configured by the master through SDO (0x1400/0x1600 receive, 0x1800/0x1A00 transmit), TPDOs sent on SYNC
(transmission types 1-240), RPDOs applied on reception, EMCY on faults. Its firmware is the CiA 402 state machine
(controlword 0x6040 -> statusword 0x6041) and profile position mode (0x6060 = 1): a rising edge of controlword bit 4
("new set-point") latches target position 0x607A, acknowledged by statusword bit 12; the axis moves towards it at
profile velocity 0x6081, in the drive's velocity unit ``velocity_unit`` (CiA 402's SI unit velocity 0x60A9 encoding:
power of ten in bits 24-31, position unit in 16-23, time unit in 8-15; the default 0xFDB40300 is 0.001 rev/s, which
with the default ``counts_per_revolution`` of 1000 (position encoder resolution 0x608F) is one count per second; rpm is
0x00B44700); ``velocity_unit_object`` / ``resolution_object`` False: the drive has no 0x60A9 / 0x608F (an SDO upload
is aborted), its unit is its own. An object at ``block_at`` counts (approached in the ``closing`` direction) stops
it, and the current rises to ``min(max current 0x6073, current_gain * |target - block_at|)`` (per mille of the rated
current 0x6075). Entering OPERATION ENABLED holds the actual position (the position demand starts there, as on a
real drive): only a new set-point moves the axis. ``go_silent()`` makes the node vanish from the bus (no SDO, PDO or
heartbeat); ``inject_fault()`` sends an EMCY (unless ``emcy`` is False: a drive whose EMCY is off) and enters FAULT;
``fault_at`` (a state, an error code) faults the drive as its controlword takes it into that state, once; ``warn()``
sends an EMCY without a fault; ``aborts`` ({index: SDO abort code}) answers every upload of those objects with that
abort (0x08000022: "present device state"). ``mode_delay`` is how long the drive takes to
switch modes: the modes of operation display 0x6061 shows a mode written to 0x6060 that many seconds later (None:
never, a mode the drive does not enter). ``latency`` delays every SYNC's TPDOs, ``answer_late()`` those of the next
SYNCs (or loses them), each with the state sampled at its SYNC and never before an earlier answer; ``set_position()``
puts the axis somewhere (by hand). ``stamp`` (a clock, or None for the interface's own) stamps every frame the drive
sends, as the receiving interface would: python-can interfaces differ (socketcan: epoch kernel stamps; others
monotonic, device counters or none at all), so the driver must not trust the stamp's clock. ``instant`` (for
benchmarks/follower_latency.py, which times the transport, not the motion): the axis is at the latched set-point at
the next SYNC, whatever the profile velocity; an object still stops it. ``cycle`` is the drive's control cycle (s; 1 ms
by default, 0: every frame taken at once): as a real drive, it reads the controlword once a cycle, on a fixed grid of
the monotonic clock, so of the controlwords that arrive within one cycle (by RPDO or SDO) only the last is seen, at
that cycle's end: a "new set-point" pulse of bit 4 low then high sent back to back is no edge to it.

Heartbeat consumer (CiA 301 0x1016, CiA 402 0x6007): consumer heartbeat time 0x1016 has ``len(consumers)`` entries (sub
1 on; sub 0, read-only, their number), holding ``consumers`` at start (default one entry, 0); each entry (bits 16-23 a
producer's node id, bits 0-15 the time in ms; 0 in either: off, and it watches nothing) makes the drive listen for that
node's heartbeat (0x700 + id). As CiA 301 has it, a write that would give a node id a second entry with a time (both
non-zero) is refused, SDO abort 0x06040043 (general parameter incompatibility), the entry left as it was. Monitoring of
an entry starts with the first heartbeat received after its write (or the start), and when none came for longer than its
time while the drive is NMT OPERATIONAL, it acts once per abort connection option code 0x6007 (default 1, CiA 402's): 1
FAULT with EMCY 0x8130 (heartbeat/life guard error, error register 0x11); 2 disable voltage (SWITCH ON DISABLED); 3
quick stop (from OPERATION ENABLED: QUICK STOP ACTIVE, holding the position it stood at, where the emulator's stop is
instant; from READY TO SWITCH ON or SWITCHED ON: SWITCH ON DISABLED); 0 or a negative (manufacturer-specific) value:
nothing. Then per error behaviour 0x1029 sub 1 (communication error, ``error_behaviour``): 0 NMT PRE-OPERATIONAL (CiA
301's default: its heartbeat says so, and it sends and takes no PDOs), 1 no change of NMT state (the emulator's
default), 2 NMT STOPPED. Monitoring then waits for the next heartbeat. ``consumer_trips`` lists (monotonic time, option,
state before) per reaction, ``consumer_heartbeats`` the monotonic arrival times of the watched heartbeats;
``consumer_object`` / ``abort_option_object`` False: the drive has no 0x1016 / 0x6007 (an SDO write is aborted
0x06020000); 0x6007 refuses values 4-32767 (abort 0x06090030, value range exceeded).

:class:`FailingReceives` wraps the ``recv()`` of the driver's python-can bus (the host's side of the virtual bus, not
the drive's) so that it raises python-can's error in receiving, as an adapter's does, once or until told to stop.
"""

from __future__ import annotations

import collections
import errno
import math
import struct
import threading
import time
from fractions import Fraction
from typing import Callable, Sequence

import can
import canopen
from canopen import objectdictionary as od_mod
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

U8, U16, U32 = od_mod.UNSIGNED8, od_mod.UNSIGNED16, od_mod.UNSIGNED32
I8, I16, I32 = od_mod.INTEGER8, od_mod.INTEGER16, od_mod.INTEGER32

STATUS = {"NOT READY TO SWITCH ON": 0x0000, "SWITCH ON DISABLED": 0x0040, "READY TO SWITCH ON": 0x0021,
          "SWITCHED ON": 0x0023, "OPERATION ENABLED": 0x0027, "QUICK STOP ACTIVE": 0x0007, "FAULT": 0x0008}
DEVICE_TYPE_402 = 0x00020192  # CiA 402, servo drive
VELOCITY_UNIT = 0xFDB40300  # 0.001 rev/s (10^-3, revolution 0xB4, second 0x03): one count/s at 1000 counts/rev
RPM = 0x00B44700  # revolutions (0xB4) per minute (0x47)
REVOLUTION, SECOND, MINUTE = 0xB4, 0x03, 0x47  # CiA 303-2 / CiA 890 unit codes in 0x60A8/0x60A9


def _var(name, index, sub, dtype, access="rw", default=0):
    v = ODVariable(name, index, sub)
    v.data_type = dtype
    v.access_type = access
    v.default = default
    return v


def drive_od(node_id: int, velocity_unit: int | None = VELOCITY_UNIT,
             resolution: tuple[int, int] | None = (1000, 1),
             scaling: dict[int, tuple[int, int]] | None = None, consumer: bool = True,
             abort_option: bool = True, consumers: Sequence[int] = (0,),
             error_behaviour: int = 1) -> canopen.ObjectDictionary:
    """The drive's object dictionary (communication profile, 4 RPDOs/TPDOs, CiA 402 objects it implements), with SI
    unit velocity 0x60A9 = ``velocity_unit`` and position encoder resolution 0x608F = ``resolution`` (increments,
    motor revolutions) unless None (the drive has no such object); ``scaling``: the position scaling objects the
    drive has ({0x6091: (motor revs, shaft revs)} gear ratio, {0x6092: (feed, shaft revs)} feed constant);
    ``consumer`` / ``abort_option``: it has consumer heartbeat time 0x1016 (entries sub 1 up holding ``consumers``)
    / abort connection option code 0x6007 (1, fault: CiA 402's default); error behaviour 0x1029 sub 1 (communication
    error) is ``error_behaviour``."""
    od = canopen.ObjectDictionary()
    od.node_id = node_id
    od.add_object(_var("Device type", 0x1000, 0, U32, "ro", DEVICE_TYPE_402))
    od.add_object(_var("Error register", 0x1001, 0, U8, "ro", 0))
    if consumer:
        arr = ODArray("Consumer heartbeat time", 0x1016)
        arr.add_member(_var("Highest sub-index supported", 0x1016, 0, U8, "ro", len(consumers)))
        for sub, value in enumerate(consumers, 1):
            arr.add_member(_var(f"Consumer heartbeat time {sub}", 0x1016, sub, U32, "rw", value))
        od.add_object(arr)
    arr = ODArray("Error behaviour", 0x1029)
    arr.add_member(_var("Highest sub-index supported", 0x1029, 0, U8, "ro", 1))
    arr.add_member(_var("Communication error", 0x1029, 1, U8, "rw", error_behaviour))
    od.add_object(arr)
    if abort_option:
        od.add_object(_var("Abort connection option code", 0x6007, 0, I16, "rw", 1))
    od.add_object(_var("Producer heartbeat time", 0x1017, 0, U16, "rw", 0))
    ident = ODRecord("Identity object", 0x1018)
    ident.add_member(_var("Number of entries", 0x1018, 0, U8, "ro", 2))
    ident.add_member(_var("Vendor-ID", 0x1018, 1, U32, "ro", 0x00000ABC))
    ident.add_member(_var("Product code", 0x1018, 2, U32, "ro", 0x00000402))
    od.add_object(ident)
    for n in range(4):
        for com, mapping, base, kind in ((0x1400, 0x1600, 0x200, "RPDO"), (0x1800, 0x1A00, 0x180, "TPDO")):
            rec = ODRecord(f"{kind}{n + 1} communication parameter", com + n)
            rec.add_member(_var("Highest sub-index supported", com + n, 0, U8, "ro", 5))
            rec.add_member(_var("COB-ID", com + n, 1, U32, "rw", 0x80000000 | (base + 0x100 * n + node_id)))
            rec.add_member(_var("Transmission type", com + n, 2, U8, "rw", 255))
            rec.add_member(_var("Inhibit time", com + n, 3, U16, "rw", 0))
            rec.add_member(_var("Event timer", com + n, 5, U16, "rw", 0))
            od.add_object(rec)
            mp = ODRecord(f"{kind}{n + 1} mapping parameter", mapping + n)
            mp.add_member(_var("Number of mapped objects", mapping + n, 0, U8, "rw", 0))
            for s in range(1, 9):
                mp.add_member(_var(f"Mapped object {s}", mapping + n, s, U32, "rw", 0))
            od.add_object(mp)
    for index, name, dtype, access, default in (
            (0x603F, "Error code", U16, "ro", 0),
            (0x6040, "Controlword", U16, "rw", 0),
            (0x6041, "Statusword", U16, "ro", STATUS["SWITCH ON DISABLED"]),
            (0x6060, "Modes of operation", I8, "rw", 0),
            (0x6061, "Modes of operation display", I8, "ro", 0),
            (0x6064, "Position actual value", I32, "ro", 0),
            (0x606C, "Velocity actual value", I32, "ro", 0),
            (0x6073, "Max current", U16, "rw", 1000),
            (0x6075, "Motor rated current", U32, "rw", 2000),
            (0x6077, "Torque actual value", I16, "ro", 0),
            (0x6078, "Current actual value", I16, "ro", 0),
            (0x607A, "Target position", I32, "rw", 0),
            (0x6081, "Profile velocity", U32, "rw", 100000),
            (0x6083, "Profile acceleration", U32, "rw", 1000000),
            (0x6502, "Supported drive modes", U32, "ro", 0x0000000D)):
        od.add_object(_var(name, index, 0, dtype, access, default))
    if velocity_unit is not None:
        od.add_object(_var("SI unit velocity", 0x60A9, 0, U32, "rw", velocity_unit))
    if resolution is not None:
        rec = ODRecord("Position encoder resolution", 0x608F)
        rec.add_member(_var("Highest sub-index supported", 0x608F, 0, U8, "ro", 2))
        rec.add_member(_var("Encoder increments", 0x608F, 1, U32, "rw", resolution[0]))
        rec.add_member(_var("Motor revolutions", 0x608F, 2, U32, "rw", resolution[1]))
        od.add_object(rec)
    for index, (a, b) in (scaling or {}).items():
        rec = ODRecord({0x6091: "Gear ratio", 0x6092: "Feed constant"}[index], index)
        rec.add_member(_var("Highest sub-index supported", index, 0, U8, "ro", 2))
        rec.add_member(_var("Numerator", index, 1, U32, "rw", a))
        rec.add_member(_var("Denominator", index, 2, U32, "rw", b))
        od.add_object(rec)
    return od


def counts_per_unit(velocity_unit: int, counts_per_revolution: int) -> float:
    """Counts per second in one ``velocity_unit`` (0x60A9 encoding): revolutions are ``counts_per_revolution``; any
    other position unit is taken as counts (what the emulator moves in)."""
    exponent = struct.unpack("<b", bytes([velocity_unit >> 24 & 0xFF]))[0]
    per = counts_per_revolution if velocity_unit >> 16 & 0xFF == REVOLUTION else 1
    return float(Fraction(10) ** exponent * per / (60 if velocity_unit >> 8 & 0xFF == MINUTE else 1))


class Cia402Drive:
    """The emulated drive. ``channel`` names the virtual CAN bus shared with the driver under test."""

    def __init__(self, node_id: int = 5, channel: str = "teletouch-vcan", *, position: int = 0,
                 block_at: int | None = None, closing: int = 1, current_gain: float = 0.5,
                 device_type: int = DEVICE_TYPE_402, stamp: Callable[[], float] | None = None,
                 mode_delay: float | None = 0.0, latency: float = 0.0, instant: bool = False,
                 velocity_unit: int = VELOCITY_UNIT, velocity_unit_object: bool = True,
                 counts_per_revolution: int = 1000, resolution_object: bool = True, emcy: bool = True,
                 fault_at: tuple[str, int] | None = None, aborts: dict[int, int] | None = None,
                 cycle: float = 0.001, scaling: dict[int, tuple[int, int]] | None = None,
                 consumer_object: bool = True, abort_option_object: bool = True, consumers: Sequence[int] = (0,),
                 error_behaviour: int = 1):
        self.node_id = node_id
        self.channel = channel
        self.od = drive_od(node_id, velocity_unit if velocity_unit_object else None,
                           (counts_per_revolution, 1) if resolution_object else None, scaling,
                           consumer_object, abort_option_object, consumers, error_behaviour)
        self.counts_per_unit = counts_per_unit(velocity_unit, counts_per_revolution)  # counts/s per velocity unit
        self.od[0x1000].default = device_type
        self.pos = float(position)
        self.vel = 0.0
        self.block_at = block_at
        self.closing = closing
        self.current_gain = current_gain
        self.state = "SWITCH ON DISABLED"
        self.emcy = emcy
        self.fault_at = fault_at   # (state, error code): fault on entering that state, once
        self.aborts = dict(aborts or {})
        self.silent = False
        self.syncs = 0
        self.stamp = stamp
        self.mode_delay = mode_delay
        self.latency = latency   # s from a SYNC to its TPDOs (answer_late overrides it for the next SYNCs)
        self.instant = instant   # at the set-point at the next SYNC, no profile velocity (benchmarks only)
        self.latched = int(round(self.pos))  # the position demand: where the axis is, until a new set-point
        self.rpdo_frames = 0
        self._cw = 0
        self.cycle = cycle
        self._pending: tuple[int, int] | None = None   # (cycle number, controlword) not yet read by the firmware
        self._batch = False
        self._pdo_dirty = True
        self._hooked: set[int] = set()
        self._lock = threading.RLock()
        self._last = None
        self._late: collections.deque[float | None] = collections.deque()  # answer_late's delays, one per SYNC
        self._outbox: collections.deque[tuple[float, list[tuple[int, bytes]]]] = collections.deque()
        self._out_cv = threading.Condition()
        self._last_due = 0.0
        self._sender: threading.Thread | None = None
        self._closed = False
        # heartbeat consumer (0x1016 / 0x6007): per entry on (sub-index), (producer node id, time s); the monotonic
        # time of the last heartbeat received from it since the entry was written (None: monitoring not started, or
        # a reaction came)
        self._consumers: dict[int, tuple[int, float]] = {}
        self._consumer_seen: dict[int, float | None] = {}
        self._consumer_subscribed: set[int] = set()   # node ids whose heartbeat COB-ID is subscribed
        self._consumer_cv = threading.Condition()
        self._watcher: threading.Thread | None = None
        self.consumer_heartbeats: list[float] = []
        self.consumer_trips: list[tuple[float, int, str]] = []
        self.network = canopen.Network()
        self.node = canopen.LocalNode(node_id, self.od)

    # --- life cycle ------------------------------------------------------------------------------------------
    def start(self) -> "Cia402Drive":
        if self.stamp is None:
            self.network.connect(interface="virtual", channel=self.channel, receive_own_messages=False)
        else:  # the virtual bus passes a sent frame's stamp on (preserve_timestamps): stamp each on our clock
            self.network.connect(interface="virtual", channel=self.channel, receive_own_messages=False,
                                 preserve_timestamps=True)
            bus, send = self.network.bus, self.network.bus.send

            def stamped_send(msg, timeout=None):
                msg.timestamp = self.stamp()
                return send(msg, timeout)

            bus.send = stamped_send  # also what the heartbeat's periodic task sends through
        self.network.add_node(self.node)
        n = self.node
        n.data_store.setdefault(0x6064, {})[0] = struct.pack("<i", int(self.pos))
        n.data_store.setdefault(0x607A, {})[0] = struct.pack("<i", int(self.pos))
        n.add_write_callback(self._on_write)
        n.add_read_callback(self._on_read)
        self.network.subscribe(0x80, self._on_sync)
        self.network.subscribe(0, self._on_nmt)  # after the NmtSlave's own handler
        if 0x1016 in self.od:   # entries set before (another master's, with the drive's tool)
            for sub in range(1, self.get(0x1016) + 1):
                self._configure_consumer(sub, self.get(0x1016, sub))
        # boot-up message, then PRE-OPERATIONAL (as a drive does after power-on)
        self.network.send_message(0x700 + self.node_id, [0])
        n.nmt.state = "PRE-OPERATIONAL"
        self._status()
        return self

    def stop(self) -> None:
        try:
            self.node.nmt.stop_heartbeat()
        except Exception:
            pass
        with self._out_cv:
            self._closed = True
            self._out_cv.notify_all()
        with self._consumer_cv:
            self._consumer_cv.notify_all()
        if self._sender is not None:
            self._sender.join(2.0)
        if self._watcher is not None:
            self._watcher.join(2.0)
        self.network.disconnect()

    def __enter__(self) -> "Cia402Drive":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- fault injection -------------------------------------------------------------------------------------
    def go_silent(self) -> None:
        """The node vanishes (power loss, cable): no SDO answers, no PDOs, no heartbeat."""
        self.silent = True
        self.node.nmt.stop_heartbeat()
        self.network.unsubscribe(self.node.sdo.rx_cobid)

    def answer_late(self, *delays: float | None) -> None:
        """The TPDOs answering the next ``len(delays)`` SYNCs go out that many seconds after their SYNC (None: never,
        an answer lost), each with the state sampled at its SYNC, and never before an earlier answer (the drive keeps
        their order, as a CAN bus does); the drive takes its other frames meanwhile."""
        with self._lock:
            self._late.extend(delays)

    def set_position(self, counts: int) -> None:
        """The axis is put at ``counts`` (by hand, with the drive enabled) and holds there: position demand and actual
        position both ``counts`` from the next SYNC on."""
        with self._lock:
            self.pos = float(counts)
            self.latched = int(counts)

    def inject_fault(self, code: int = 0x2310, register: int = 0x02) -> None:
        """A drive fault (default 0x2310: continuous over-current): EMCY (if ``emcy``), FAULT state, 0x603F set."""
        with self._lock:
            self.state = "FAULT"
            self.node.data_store.setdefault(0x603F, {})[0] = struct.pack("<H", code)
            self.node.data_store.setdefault(0x1001, {})[0] = bytes([register])
            self._status()
        if self.emcy:
            self.node.emcy.send(code, register)

    def warn(self, code: int = 0x4210, register: int = 0x08) -> None:
        """An EMCY without a fault (default 0x4210: temperature warning): the drive stays in its state."""
        self.node.emcy.send(code, register)

    # --- helpers ---------------------------------------------------------------------------------------------
    def get(self, index: int, sub: int = 0) -> int:
        obj = self.od[index]
        if not isinstance(obj, ODVariable):   # (a record's or an array's sub 0 too)
            obj = obj[sub]
        return obj.decode_raw(self.node.get_data(index, sub))

    def _put(self, index: int, value: int) -> None:
        self.node.data_store.setdefault(index, {})[0] = self.od[index].encode_raw(int(value))

    def _status(self, ack: bool | None = None) -> None:
        sw = STATUS[self.state] | 0x0200 | (0x0010 if self.state not in ("SWITCH ON DISABLED", "FAULT") else 0)
        old = self.get(0x6041)
        if ack is None:
            sw |= old & 0x1000
        elif ack:
            sw |= 0x1000
        target = self.get(0x607A)
        if abs(self.pos - target) < 1.0 or (self.block_at is not None and
                                            (target - self.block_at) * self.closing > 0 and
                                            abs(self.pos - self.block_at) < 1.0):
            sw |= 0x0400  # target reached (or blocked against the object)
        self._put(0x6041, sw)

    # --- firmware --------------------------------------------------------------------------------------------
    def _on_read(self, index, subindex, od):
        if index in self.aborts:
            from canopen.sdo.exceptions import SdoAbortedError

            raise SdoAbortedError(self.aborts[index])
        return None

    def _on_write(self, index, subindex, od, data):
        if index == 0x6007:
            (option,) = struct.unpack("<h", data)
            if option > 3:   # 4-32767 are reserved (negative ones are the manufacturer's)
                from canopen.sdo.exceptions import SdoAbortedError

                raise SdoAbortedError(0x06090030)
        elif index == 0x1016 and subindex >= 1:
            self._configure_consumer(subindex, struct.unpack("<I", data)[0])
        elif 0x1400 <= index <= 0x1BFF:
            self._pdo_dirty = True
        elif index == 0x6060:
            (mode,) = struct.unpack("<b", data)
            self._switch_mode(mode)
        elif index == 0x6040 and not self._batch:
            self._receive_controlword(struct.unpack("<H", data)[0])

    # --- heartbeat consumer (CiA 301 0x1016) and abort connection option (CiA 402 0x6007) --------------------------
    def _configure_consumer(self, sub: int, value: int) -> None:
        """0x1016 sub ``sub`` written: watch node ``value >> 16 & 0xFF``'s heartbeat for ``value & 0xFFFF`` ms (either
        0: off). Refused (SDO abort 0x06040043) where another entry watches that node with a time. Monitoring of the
        entry (re)starts with the first heartbeat received after the write."""
        node, ms = value >> 16 & 0xFF, value & 0xFFFF
        with self._consumer_cv:
            if node and ms and any(n == node for s, (n, _) in self._consumers.items() if s != sub):
                from canopen.sdo.exceptions import SdoAbortedError

                raise SdoAbortedError(0x06040043)   # general parameter incompatibility (CiA 301)
            self._consumers.pop(sub, None)
            self._consumer_seen.pop(sub, None)
            if node and ms:
                self._consumers[sub] = (node, ms / 1000.0)
                self._consumer_seen[sub] = None
                if node not in self._consumer_subscribed:
                    self.network.subscribe(0x700 + node, self._on_consumer_heartbeat)
                    self._consumer_subscribed.add(node)
                if self._watcher is None:
                    self._watcher = threading.Thread(target=self._watch_consumer, name="cia402-hb-consumer",
                                                     daemon=True)
                    self._watcher.start()
            self._consumer_cv.notify_all()

    def _on_consumer_heartbeat(self, can_id, data, timestamp) -> None:
        with self._consumer_cv:
            subs = [sub for sub, (node, _) in self._consumers.items() if can_id == 0x700 + node]
            if not subs:
                return
            now = time.monotonic()
            for sub in subs:
                self._consumer_seen[sub] = now
            self.consumer_heartbeats.append(now)
            self._consumer_cv.notify_all()

    def _watch_consumer(self) -> None:
        """The drive's consumer: when an entry's heartbeat is missing for longer than its time, the reaction of
        0x6007 (and 0x1029), once (monitoring of the entry waits for the next heartbeat)."""
        while True:
            with self._consumer_cv:
                while True:
                    if self._closed:
                        return
                    due = [(seen + self._consumers[sub][1], sub) for sub, seen in self._consumer_seen.items()
                           if seen is not None]
                    if not due:
                        self._consumer_cv.wait()
                        continue
                    at, sub = min(due)
                    left = at - time.monotonic()
                    if left > 0:
                        self._consumer_cv.wait(left)
                        continue
                    self._consumer_seen[sub] = None   # the event comes once; the next heartbeat starts monitoring
                    break
            if not self.silent and self.node.nmt.state == "OPERATIONAL":
                self._abort_connection()

    def _abort_connection(self) -> None:
        """The heartbeat the drive consumes is lost: abort connection option code 0x6007 says what it does (CiA 402's
        default, 1, where the drive has no 0x6007), then error behaviour 0x1029 sub 1 its NMT state."""
        option = self.get(0x6007) if 0x6007 in self.od else 1
        with self._lock:
            before = self.state
            self.consumer_trips.append((time.monotonic(), option, before))
            if before == "OPERATION ENABLED":
                self._physics()   # the motion up to now, then the reaction (the emulator's quick stop is instant)
            if option == 1:
                if before != "FAULT":
                    self.inject_fault(0x8130, 0x11)   # heartbeat/life guard error; generic + communication error
            elif option == 2 and before in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED",
                                            "QUICK STOP ACTIVE"):
                self.state = "SWITCH ON DISABLED"
            elif option == 3 and before == "OPERATION ENABLED":
                self.state = "QUICK STOP ACTIVE"
                self.latched = int(round(self.pos))   # holds where it stopped
            elif option == 3 and before in ("READY TO SWITCH ON", "SWITCHED ON"):
                self.state = "SWITCH ON DISABLED"
            if option != 1:
                self._status()
        nmt = {0: "PRE-OPERATIONAL", 2: "STOPPED"}.get(self.get(0x1029, 1))
        if nmt is not None:   # (the heartbeat it produces says so from its next frame)
            self.node.nmt.state = nmt

    def _switch_mode(self, mode: int) -> None:
        """Modes of operation 0x6060 written: the display 0x6061 follows after ``mode_delay`` s (None: never)."""
        if self.mode_delay is None:
            return
        if self.mode_delay <= 0 or self.get(0x6061) == mode:
            self._put(0x6061, mode)
            return
        timer = threading.Timer(self.mode_delay, self._put, (0x6061, mode))
        timer.daemon = True
        timer.start()

    def _receive_controlword(self, cw: int) -> None:
        """A controlword came (RPDO or SDO): read by the firmware at the end of its control cycle (``cycle``), where a
        later one of the same cycle replaces it; one of an earlier cycle still waiting is read first (its cycle has
        ended: the timer that reads it may come late)."""
        with self._lock:
            if self.cycle <= 0:
                self._controlword(cw)
                return
            now = time.monotonic()
            slot = math.floor(now / self.cycle)
            self._read_pending(slot)
            self._pending = (slot, cw)
        timer = threading.Timer(max(0.0, (slot + 1) * self.cycle - now), self._cycle_end, (slot,))
        timer.daemon = True
        timer.start()

    def _read_pending(self, slot: int | None) -> None:
        """The firmware reads the controlword waiting from a cycle before ``slot`` (None: whatever its cycle)."""
        if self._pending is not None and (slot is None or self._pending[0] < slot):
            cw, self._pending = self._pending[1], None
            self._controlword(cw)

    def _cycle_end(self, slot: int) -> None:
        with self._lock:
            if self._pending is not None and self._pending[0] == slot:
                self._read_pending(None)

    def _controlword(self, cw: int) -> None:
        """The firmware reads controlword ``cw`` (once per control cycle, see _receive_controlword)."""
        with self._lock:
            prev, self._cw = self._cw, cw
            s = self.state
            if s == "FAULT":
                if cw & 0x80 and not prev & 0x80:
                    self.state = "SWITCH ON DISABLED"
                    self._put(0x603F, 0)
                    self._put(0x1001, 0)
                    self.node.emcy.reset()
            elif cw & 0x82 == 0x00:
                self.state = "SWITCH ON DISABLED"
            elif cw & 0x86 == 0x02:
                self.state = "QUICK STOP ACTIVE" if s == "OPERATION ENABLED" else "SWITCH ON DISABLED"
            elif cw & 0x87 == 0x06:
                if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                    self.state = "READY TO SWITCH ON"
            elif cw & 0x8F == 0x07:
                if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                    self.state = "SWITCHED ON"
            elif cw & 0x8F == 0x0F:
                if s in ("SWITCHED ON", "QUICK STOP ACTIVE"):
                    self.state = "OPERATION ENABLED"
                    self.latched = int(round(self.pos))  # enabled: holds where it is until a new set-point
            if self.fault_at is not None and self.state == self.fault_at[0] != s:
                code, self.fault_at = self.fault_at[1], None
                self.inject_fault(code)   # (before any statusword shows the state: as the drive enters it)
                return
            ack = None
            if self.state == "OPERATION ENABLED" and self.get(0x6061) == 1:
                if cw & 0x10 and not prev & 0x10:
                    # the axis moved towards the old set-point until now; the new one's motion starts now, not at the
                    # last SYNC (the physics runs at each SYNC: a step's first period counted from before it came).
                    # (instant: at the goal at the next SYNC anyway; a physics step here would leave the next one a
                    # dt of microseconds, and the jump's velocity would not fit 0x606C)
                    if not self.instant:
                        self._physics()
                    self.latched = self.get(0x607A)
                    ack = True
                elif not cw & 0x10:
                    ack = False
            self._status(ack)

    def _apply_rpdo(self, pdo_map) -> None:
        if self.silent or self.node.nmt.state not in ("OPERATIONAL",):
            return
        self.rpdo_frames += 1
        with self._lock:
            self._batch = True
            cw = None
            try:
                for var in pdo_map:
                    data = var.get_data()
                    self.node.set_data(var.index, var.subindex, data)
                    if var.index == 0x6040:
                        cw = struct.unpack("<H", data)[0]
            finally:
                self._batch = False
            if cw is not None:
                self._receive_controlword(cw)

    def _reload_pdos(self) -> None:
        for m in list(self.node.rpdo.map.values()):
            if m.enabled and m.cob_id is not None:
                try:
                    self.network.unsubscribe(m.cob_id, m.on_message)
                except (KeyError, ValueError):
                    pass
        self.node.tpdo.read()
        self.node.rpdo.read()
        for no, m in self.node.rpdo.map.items():
            if no not in self._hooked:
                m.add_callback(self._apply_rpdo)
                self._hooked.add(no)
        self._pdo_dirty = False

    def _physics(self) -> None:
        now = time.monotonic()
        dt = 0.0 if self._last is None else now - self._last
        self._last = now
        old = self.pos
        current = 0.0
        if self.state == "OPERATION ENABLED":
            target = float(self.latched)
            v = self.get(0x6081) * self.counts_per_unit   # counts/s
            new = target if self.instant else old + max(-v * dt, min(v * dt, target - old))
            if self.block_at is not None:
                c = self.closing
                if (new - self.block_at) * c > 0:
                    new = float(self.block_at) if (old - self.block_at) * c <= 0 else old
                if (new - self.block_at) * c >= 0 and (target - self.block_at) * c > 0:
                    current = c * min(self.get(0x6073), self.current_gain * abs(target - self.block_at))
            self.pos = new
        self.vel = (self.pos - old) / dt if dt > 0 else 0.0
        self._put(0x6064, int(round(self.pos)))
        self._put(0x606C, int(round(self.vel / self.counts_per_unit)))
        self._put(0x6078, int(round(current)))
        self._put(0x6077, int(round(current)))
        self._status()

    def _on_nmt(self, can_id, data, timestamp) -> None:
        if not self.silent and self.node.nmt.state == "OPERATIONAL" and self._pdo_dirty:
            with self._lock:
                self._reload_pdos()

    def _on_sync(self, can_id, data, timestamp) -> None:
        if self.silent or self.node.nmt.state != "OPERATIONAL":
            return
        self.syncs += 1
        with self._lock:
            if self.cycle > 0:
                self._read_pending(math.floor(time.monotonic() / self.cycle))
            if self._pdo_dirty:
                self._reload_pdos()
            self._physics()
            frames = []
            for m in self.node.tpdo.map.values():
                if m.enabled and m.trans_type is not None and 1 <= m.trans_type <= 240:
                    for var in m:
                        var.set_data(self.node.get_data(var.index, var.subindex))
                    frames.append((m.cob_id, bytes(m.data)))
            delay = self._late.popleft() if self._late else self.latency
        if delay is not None:   # None: this SYNC's answer is lost
            self._answer(frames, delay)

    def _answer(self, frames: list[tuple[int, bytes]], delay: float) -> None:
        """Send a SYNC's TPDOs ``delay`` s from now, after every answer still waiting (their order kept)."""
        with self._out_cv:
            if delay <= 0 and not self._outbox:
                for cob_id, data in frames:
                    self.network.send_message(cob_id, data)
                return
            self._last_due = max(time.monotonic() + delay, self._last_due)
            self._outbox.append((self._last_due, frames))
            if self._sender is None:
                self._sender = threading.Thread(target=self._send_late, name="cia402-late-tpdos", daemon=True)
                self._sender.start()
            self._out_cv.notify_all()

    def _send_late(self) -> None:
        with self._out_cv:
            while not self._closed:
                if not self._outbox:
                    self._out_cv.wait()
                    continue
                due, frames = self._outbox[0]
                left = due - time.monotonic()
                if left > 0:
                    self._out_cv.wait(left)
                    continue
                self._outbox.popleft()
                if not self.silent:
                    for cob_id, data in frames:
                        self.network.send_message(cob_id, data)


#: what python-can's socketcan raises from recv() on an interface that went down (errno 100, ENETDOWN)
RECV_DOWN = "Error receiving: Network is down"


class FailingReceives:
    """A thin wrapper of ``bus.recv()`` (the driver's python-can bus, ``h.comp.network.bus``, which python-can's
    Notifier calls in its receive thread): ``fail(n)`` has the next ``n`` calls raise (None: every call until
    ``fail(0)``) python-can's error in receiving, CanOperationError ``text`` with error code ``code`` (default: an
    interface that went down, as python-can's socketcan raises it), a new one each time; a call that fails while
    failing goes on returns after up to 10 ms, as a dead socket's would. Other calls are the bus's own: the frames
    flow again. ``failed`` lists when each failed (monotonic); ``uninstall()`` puts the bus's own ``recv`` back."""

    def __init__(self, bus: can.BusABC, text: str = RECV_DOWN, code: int = errno.ENETDOWN):
        self.bus, self.text, self.code = bus, text, code
        self.failed: list[float] = []
        self._left: int | None = 0
        self._lock = threading.Lock()
        self._recv = bus.recv
        bus.recv = self.recv

    def fail(self, n: int | None = 1) -> None:
        with self._lock:
            self._left = n

    def recv(self, timeout: float | None = None) -> can.Message | None:
        with self._lock:
            fails = self._left is None or self._left > 0
            if fails:
                if self._left is not None:
                    self._left -= 1
                self.failed.append(time.monotonic())
            persistent = self._left is None
        if fails:
            if persistent:
                time.sleep(min(timeout if timeout is not None else 0.01, 0.01))
            raise can.CanOperationError(self.text, self.code)
        return self._recv(timeout)

    def uninstall(self) -> None:
        self.bus.recv = self._recv
