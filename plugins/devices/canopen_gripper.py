"""canopen-gripper: an electric gripper behind a CiA 402 drive on CANopen (canopen on python-can), profile position.

Start-up (all through the canopen library): connect the bus; check the node answers SDO and is a CiA 402 device
(0x1000), and read its statusword 0x6041 (one in FAULT is refused before anything is written to it, naming its error
code 0x603F, unless ``reset_fault_at_start``: then it is logged, and reset by the walk); NMT pre-operational; map the
PDOs (RPDO1: target position 0x607A + controlword 0x6040 + mode 0x6060, asynchronous; TPDO1: statusword 0x6041 +
position actual 0x6064 + mode display 0x6061, TPDO2: current actual 0x6078 + velocity actual 0x606C, both on SYNC);
producer heartbeat 0x1017; profile position mode (0x6060 = 1, then 0x6061 read until it shows it: a drive switches in
its own time; not within ``mode_timeout``, an error naming the requested and the displayed mode); profile velocity
0x6081 from ``max_speed`` (rounded down) in the drive's velocity unit; max current 0x6073 from ``max_effort``; target :=
actual; NMT operational; then the CiA 402 state machine to OPERATION ENABLED, one transition of canopen's BaseNode402
table at a time (with SYNCs every 5 ms from a thread of the driver), starting from the statusword of the drive's first
TPDO1 (a drive found enabled stays enabled); a FAULT seen at any step is refused as one found at start-up (canopen's own
walk resets it, transition 15, without a word).

The velocity unit (of 0x6081 and 0x606C) is the drive's own: its SI unit velocity 0x60A9 (bits 24-31 a power of ten,
16-23 the position unit, 8-15 the time unit: rpm is 0x00B44700), read at start-up; where the drive has none (SDO abort
0x06020000 or 0x06090011; any other abort is a start-up failure), the ``velocity_unit`` parameter, which is then
required (counts/s ran a drive in rpm ~68x max_speed at 4096 counts/rev). A unit in revolutions takes the 0x6064 counts
per revolution from ``counts_per_revolution``, else from the position encoder resolution 0x608F (increments / motor
revolutions). Other units (a linear m/s, whose relation to the fingers the driver cannot know) are refused, naming
0x60A9's value and what to set.

A new set-point goes out by CiA 402's handshake (RPDO1 with controlword bit 4 "new set-point" high, bit 5 "change set
immediately"; once the statusword's bit 12 acknowledges it, bit 4 low; once bit 12 is low again, the next: a new
set-point every other step at most, as a drive reads its controlword once per control cycle and bit 4 low then high back
to back is no edge to it); no acknowledge within ``read_timeout`` is a HardwareError. A set-point counts as sent only
once its frame went out (a failed transmit is retried by the next write), and the safe state always sends its hold
set-point at once (bit 4 low, SETPOINT_PULSE_GAP, high); a lock makes a step's command and send one unit, so a
safe_state() from another thread waits for it and its hold goes out last. No set-point goes out while the last
statusword is not OPERATION ENABLED: RPDO1's controlword would enable a drive in quick stop or switched on again (the
drive's own stop holds it). Max current 0x6073 is rounded down, so the current cap never exceeds ``max_effort``. Each
step then transmits SYNC and waits (``pdo_timeout``) for the TPDOs it triggers. TPDOs carry no SYNC number, so the
answers are counted: a frame answers this step's SYNC only after the answers to every earlier SYNC (a step that timed
out, the state walk's) arrived, which are waited for (up to ``pdo_timeout``) before the SYNC goes out, and written off
as lost, the step without a state, when they do not come; frames beyond the SYNCs sent (another SYNC producer) are
forgotten. Answers written off are remembered: one that comes after all arrives before the next SYNC's, so that read
waits (within its ``pdo_timeout``) for them too; not there, they are lost, and the frame received after its SYNC is its
answer. A drive in FAULT (statusword; reported with its EMCY), a lost heartbeat, a heartbeat saying the drive left NMT
OPERATIONAL, or missing TPDOs end in a HardwareError naming the cause; so does a python-can error that ends a step (its
SYNC or RPDO1 not sent: "Failed to transmit: No such device" from an unplugged adapter), a start-up request or a safe
state's send (logged), naming the drive, interface:channel, what failed and what to check (:func:`bus_failure_hint`).
An error in receiving (python-can's recv() raising in its receive thread, which goes on: :class:`ReceiveErrors`) that
frames follow is got over, logged by the next read and counted (status() ``receive_errors``); one that no frame follows
for ``read_timeout`` (or while the drive's heartbeat is missing that long, or a state is) ends the run the same way,
naming python-can's error, as does an SDO request at start-up left without an answer by such a failure; python-can's
receive thread ended all the same (a fault of the program, not of the bus: not started again, see
:meth:`CanopenGripper._receiver_ended`) is a HardwareError at the next read. Heartbeats and TPDOs are timed and counted
as they arrive, on the local monotonic clock: a received frame's timestamp is on whatever clock the python-can interface
uses (epoch on socketcan; monotonic, a device counter or none on others). Scaling (counts <-> opening, per-mille current
<-> newtons) is configuration; an EDS file is optional (without one, the standard CiA 301/402 objects above are
assumed). ``interface`` must be one python-can knows (checked with the params); one that does not open gets that
interface's advice (:func:`open_failure_hint`) and what python-can logged on the way (a vendor library it could not
load), which is then not printed.

The drive watches the host (host heartbeat): the driver watches the drive's heartbeat, and without this the drive kept
going, enabled and on its last set-point, when the host died, hung or lost its cable. With ``host_heartbeat_period`` > 0
(default 0.1 s, whole ms) the host produces a heartbeat, COB-ID 0x700 + ``host_node_id`` (default 127, the top of the
range, where masters often sit; not ``node_id``, nor an id another node already sends heartbeats with, listened for at
start-up: each gripper on a bus needs its own), one byte: NMT OPERATIONAL (5), through python-can's bus.send_periodic
(:class:`HostHeartbeat`). In the pre-operational phase the drive's consumer heartbeat time 0x1016 is read (sub 0, the
number of entries, then each entry) for the entry to use: one that already holds the host's node id, else a free one
(0); an entry of another producer (another master's) is never replaced, and none free is refused naming what each holds.
Then the producer starts, that entry is written (host node id in bits 16-23, ``host_heartbeat_timeout`` in ms in bits
0-15: default three periods, 0.3 s; at least two, so one late heartbeat stops nothing) and abort connection option code
0x6007 (``abort_connection_option``), then one heartbeat goes out at once (a CiA 301 consumer starts watching at the
first heartbeat after it is set; the periodic one may come a period later, on socketcan always). A drive without 0x1016
is refused naming ``host_heartbeat_period: 0`` (off: 0x1016 and 0x6007 are not touched), one without 0x6007 naming
``abort_connection_option: null`` (not written: the drive's own reaction). When the heartbeat stops for the consumer
time while the drive is NMT OPERATIONAL, the drive acts per 0x6007: 0 nothing, 1 FAULT (EMCY 0x8130), 2 disable voltage
(power stage off: the fingers hold only by their gearbox or brake), 3 quick stop, the default: the drive stops on its
quick-stop ramp and holds there (the project's safe state, "the follower holds position") in QUICK STOP ACTIVE where its
quick stop option code 0x605A is 5-8; with 0x605A 1-2 (CiA 402's default is 2) it then goes to SWITCH ON DISABLED, power
stage off: check 0x605A with the drive's tool; under its error behaviour 0x1029 (CiA 301's default) it also goes to NMT
PRE-OPERATIONAL. A drive that left OPERATION ENABLED, or NMT OPERATIONAL for PRE-OPERATIONAL or STOPPED, is reported
with that possible cause. The heartbeat runs as long as the driver holds the drive: through deactivate() (the drive
holds the safe state's set-point, still watched, and activate() works again; stopped there, it quick-stopped or faulted
one consumer time later), and stops in close(), after the safe state's set-point went out (the runtime and the Harness
call safe_state() before close(), and close() takes the set-point lock, so a send on another thread finishes first). An
orderly close() first turns the drive's watch off (the 0x1016 entry it wrote = 0): the drive goes on holding, powered
(left on, it quick-stopped after every run, power stage off under 0x605A 2); a drive that does not take that write is
logged and reacts one consumer time later, where it stands. With ``safe_mode: open``, close() first reads the state
until the drive reports the open set-point reached (statusword bits 12 and 10), at most the travel time at ``max_speed``
with a margin (OPEN_FINISH_MAX), the drive still watched. What the heartbeat proves: the process and its CAN interface
live, not that the control loop steps (a loop that hangs in a live process is the runtime watchdog's, which sends the
safe state). On socketcan python-can's periodic task is the kernel's broadcast manager (BCM): it goes on while the
process lives, also frozen, and ends when its BCM socket is closed (bus shutdown, or the process exits or is killed: the
kernel closes its files and removes the socket's tasks); a child made by a bare fork() would hold the socket too (the
runtime spawns its isolated nodes). Elsewhere it is a python-can thread, which ended at its first failed send; it is
given an ``on_error`` that has it go on sending through failed sends (a full transmit queue, a brief adapter error),
each run of them logged by the next read; where none has gone out for longer than the consumer time, the read is a
HardwareError naming the drive, the interface and python-can's error."""

from __future__ import annotations

import errno
import logging
import math
import threading
import time
from fractions import Fraction
from typing import Any

from pydantic import Field, field_validator, model_validator

from teletouch import HardwareError, hookimpl
from teletouch.units import Meters, Newtons, Seconds

from .follower_common import FollowerBase, FollowerParams, OpeningMap, Reading

PROFILE_POSITION = 1
#: unit codes (CiA 303-2, now CiA 890) in SI unit velocity 0x60A9: position unit in bits 16-23, time unit in 8-15
REVOLUTION, SECOND, MINUTE = 0xB4, 0x03, 0x47
POSITION_UNITS = {0x01: "m", 0x10: "rad", 0x41: "deg", REVOLUTION: "rev"}
TIME_UNITS = {SECOND: "s", MINUTE: "min"}
RPM = 0x00B44700
VELOCITY_UNITS = {"counts/s": ("counts", 1), "rev/s": ("rev", 1), "rpm": ("rev", 60)}   # param: (kind, seconds)
#: CiA 402 modes of operation (0x6060 / 0x6061), for messages; negative values are manufacturer-specific
MODE_NAMES = {0: "no mode", 1: "profile position", 3: "profile velocity", 4: "profile torque", 6: "homing",
              7: "interpolated position", 8: "cyclic synchronous position", 9: "cyclic synchronous velocity",
              10: "cyclic synchronous torque"}
MODE_POLL = 0.005  # s between two reads of the modes of operation display 0x6061 while the drive switches
WALK_SYNC_PERIOD = 0.005  # s between the SYNCs that drive the TPDOs (the statusword) while the state machine is walked
NMT_OPERATIONAL = 5  # the NMT state in a heartbeat (CiA 301)
#: abort connection option code 0x6007 (CiA 402): what the drive does when it loses the host (its heartbeat)
ABORT_OPTIONS = {0: "no action", 1: "fault", 2: "disable voltage", 3: "quick stop"}
HOST_TIMEOUT_PERIODS = 3   # host_heartbeat_timeout None: this many host heartbeat periods
HOST_ID_LISTEN = 2.5   # host heartbeat periods listened on the host's node id at start-up: another producer refused
HEARTBEAT_MS_MAX = 0xFFFF   # 0x1016's time (bits 0-15) and 0x1017 hold whole milliseconds, UNSIGNED16
#: close() with safe_mode open waits (the host heartbeat still going) for the drive to report the fingers open, at
#: most this long: the drive's quick stop on the lost host heartbeat would stop them part-way
OPEN_FINISH_MAX = 5.0
OPEN_FINISH_POLL = 0.01   # s between two state reads of that wait
CLOSE_LOCK_WAIT = 1.0   # s close() waits for a set-point being sent on another thread before the heartbeat stops
CW_ENABLE = 0x000F
CW_NEW_SETPOINT = 0x0010
CW_CHANGE_IMMEDIATELY = 0x0020
SW_SETPOINT_ACK = 0x1000   # statusword bit 12 in profile position mode: the drive took the new set-point
#: the pause between bit 4 low and bit 4 high of a set-point sent at once (the safe state's, which cannot wait over the
#: steps for the drive's acknowledge): longer than a CiA 402 drive's control cycle (62.5 us to 1 ms typically, 2 ms on
#: slow ones), which reads the controlword once a cycle: two frames within one cycle leave only the second seen
SETPOINT_PULSE_GAP = 0.004


def _od_var(index: int, name: str, dtype: int, access: str, sub: int = 0) -> Any:
    from canopen.objectdictionary import ODVariable

    v = ODVariable(name, index, sub)
    v.data_type = dtype
    v.access_type = access
    return v


def standard_od(node_id: int) -> Any:
    """Object dictionary of the standard CiA 301/402 objects this driver uses (when no EDS file is given)."""
    import canopen
    from canopen import objectdictionary as o
    from canopen.objectdictionary import ODRecord

    od = canopen.ObjectDictionary()
    od.node_id = node_id
    for index, name, dtype, access in (
            (0x1000, "Device type", o.UNSIGNED32, "ro"), (0x1001, "Error register", o.UNSIGNED8, "ro"),
            (0x1017, "Producer heartbeat time", o.UNSIGNED16, "rw"), (0x603F, "Error code", o.UNSIGNED16, "ro"),
            (0x6040, "Controlword", o.UNSIGNED16, "rw"), (0x6041, "Statusword", o.UNSIGNED16, "ro"),
            (0x6060, "Modes of operation", o.INTEGER8, "rw"),
            (0x6061, "Modes of operation display", o.INTEGER8, "ro"),
            (0x6064, "Position actual value", o.INTEGER32, "ro"),
            (0x606C, "Velocity actual value", o.INTEGER32, "ro"), (0x6073, "Max current", o.UNSIGNED16, "rw"),
            (0x6075, "Motor rated current", o.UNSIGNED32, "rw"),
            (0x6077, "Torque actual value", o.INTEGER16, "ro"),
            (0x6078, "Current actual value", o.INTEGER16, "ro"), (0x607A, "Target position", o.INTEGER32, "rw"),
            (0x6081, "Profile velocity", o.UNSIGNED32, "rw"), (0x6502, "Supported drive modes", o.UNSIGNED32, "ro")):
        od.add_object(_od_var(index, name, dtype, access))
    for n in range(4):
        for com, mapping, kind in ((0x1400, 0x1600, "RPDO"), (0x1800, 0x1A00, "TPDO")):
            rec = ODRecord(f"{kind}{n + 1} communication parameter", com + n)
            for sub, name, dtype in ((0, "Highest sub-index supported", o.UNSIGNED8), (1, "COB-ID", o.UNSIGNED32),
                                     (2, "Transmission type", o.UNSIGNED8), (3, "Inhibit time", o.UNSIGNED16),
                                     (5, "Event timer", o.UNSIGNED16)):
                rec.add_member(_od_var(com + n, name, dtype, "ro" if sub == 0 else "rw", sub))
            od.add_object(rec)
            mp = ODRecord(f"{kind}{n + 1} mapping parameter", mapping + n)
            mp.add_member(_od_var(mapping + n, "Number of mapped objects", o.UNSIGNED8, "rw", 0))
            for sub in range(1, 9):
                mp.add_member(_od_var(mapping + n, f"Mapped object {sub}", o.UNSIGNED32, "rw", sub))
            od.add_object(mp)
    return od


class CanopenGripper(FollowerBase):
    """Gripper on a CiA 402 CANopen drive (profile position mode), via canopen and python-can."""

    name = "canopen-gripper"
    default_rate = 200.0
    #: a set-point goes out over several writes, each after a read (CiA 402's handshake, see _handshake): a caller
    #: that writes once and then only reads (benchmarks/follower_latency.py's round trip) writes again after each read
    setpoint_handshake = True
    requires_wall_clock = True  # the drive moves in real time; speed limits use the graph's time steps

    class Params(FollowerParams):
        interface: str = Field("socketcan", description="python-can interface (socketcan, pcan, kvaser, virtual..)")
        channel: str = Field("can0", description="python-can channel")
        bitrate: int = Field(1000000, gt=0, description="CAN bit rate", json_schema_extra={"unit": "bit/s"})
        node_id: int = Field(1, ge=1, le=127, description="CANopen node id of the drive")
        eds: str | None = Field(None, description="EDS/DCF file of the drive (None: standard CiA 402 objects)")
        counts_open: int = Field(0, description="position (0x6064 counts) with the fingers open")
        counts_closed: int = Field(100000, description="position (counts) with the fingers closed")
        opening_at_counts_open: Meters = Field(0.08, ge=0, json_schema_extra={"unit": "m"},
                                               description="opening at counts_open")
        opening_at_counts_closed: Meters = Field(0.0, ge=0, json_schema_extra={"unit": "m"},
                                                 description="opening at counts_closed")
        newtons_per_amp: float = Field(20.0, gt=0, description="grip force per ampere of motor current "
                                       "(calibrate for your gripper)", json_schema_extra={"unit": "N/A"})
        max_opening: Meters = Field(0.08, gt=0, description="largest opening commanded",
                                    json_schema_extra={"unit": "m"})
        max_effort: Newtons = Field(20.0, gt=0, description="grip force limit (sets max current 0x6073)",
                                    json_schema_extra={"unit": "N"})
        sdo_timeout: Seconds = Field(0.3, gt=0, description="SDO response timeout", json_schema_extra={"unit": "s"})
        pdo_timeout: Seconds = Field(0.05, gt=0, description="wait this long for the TPDOs after each SYNC",
                                     json_schema_extra={"unit": "s"})
        mode_timeout: Seconds = Field(0.5, gt=0, description="wait this long for the modes of operation display "
                                      "0x6061 to show profile position after 0x6060 was written",
                                      json_schema_extra={"unit": "s"})
        heartbeat_period: Seconds = Field(0.1, ge=0, description="drive heartbeat period (0: off); three missed "
                                          "heartbeats are a fault", json_schema_extra={"unit": "s"})
        host_heartbeat_period: Seconds = Field(0.1, ge=0, description="period of the heartbeat the host (this "
                                               "driver) produces for the drive's consumer heartbeat time 0x1016, "
                                               "so that the drive notices a dead or unplugged host and acts per "
                                               "abort_connection_option; whole milliseconds; 0: off (0x1016 and "
                                               "0x6007 are left as they are, and the drive keeps going without a "
                                               "host)", json_schema_extra={"unit": "s"})
        host_heartbeat_timeout: Seconds | None = Field(None, gt=0, description="the drive's consumer heartbeat time "
                                                       "(its 0x1016 entry): no host heartbeat for this long and it "
                                                       "acts per abort_connection_option; whole milliseconds up to "
                                                       "65.535 s, at least twice host_heartbeat_period; None: three "
                                                       "periods", json_schema_extra={"unit": "s"})
        host_node_id: int = Field(127, ge=1, le=127, description="node id the host's heartbeat carries (COB-ID "
                                  "0x700 + id): one no node on the bus has, not node_id")
        abort_connection_option: int | None = Field(3, description="abort connection option code 0x6007, what the "
                                                    "drive does when the host's heartbeat stops: 0 no action, 1 "
                                                    "fault, 2 disable voltage, 3 quick stop (stops and holds; what "
                                                    "follows is the drive's quick stop option code 0x605A); None: "
                                                    "not written, the drive's own")
        velocity_unit: str | None = Field(None, description="the drive's velocity unit (of profile velocity 0x6081 "
                                          "and velocity actual 0x606C) where it has no SI unit velocity 0x60A9: "
                                          "'rpm', 'rev/s' or 'counts/s' (0x6064 counts per second), with a factor "
                                          "if it has one ('0.001 rpm'); None: 0x60A9's, and a drive without it is "
                                          "refused. Given where the drive has 0x60A9, the two must agree")
        counts_per_revolution: float | None = Field(None, gt=0, description="position counts (0x6064) per "
                                                    "revolution, for a velocity unit in revolutions (rpm); None: the "
                                                    "position encoder resolution 0x608F (increments / motor "
                                                    "revolutions)")
        reset_fault_at_start: bool = Field(False, description="reset a drive found in FAULT at start-up (fault "
                                           "reset, controlword bit 7) instead of refusing to start")

        @field_validator("interface")
        @classmethod
        def _interface_known(cls, v: str) -> str:
            # python-can's own list (its interfaces and those of installed plugins): a typo ('socketcann') passed
            # validation and failed at start-up with SocketCAN advice
            check_interface(v)
            return v

        @field_validator("velocity_unit")
        @classmethod
        def _velocity_unit_known(cls, v: str | None) -> str | None:
            if v is not None:
                parse_velocity_unit(v)
            return v

        @field_validator("heartbeat_period")
        @classmethod
        def _heartbeat(cls, v: float) -> float:
            # 0x1017 holds whole milliseconds (UNSIGNED16): 0.0004 s was written as 0 (heartbeat off, then faulted as
            # a lost drive), 70 s failed with a bare "Value does not fit in specified type"
            if v != 0:
                _whole_ms("heartbeat_period", v, "the drive's producer heartbeat time 0x1017 (whole ms, 1-65535)",
                          "0 (off) or 0.001-65.535 s", HEARTBEAT_MS_MAX)
            return v

        @field_validator("host_heartbeat_period")
        @classmethod
        def _host_period(cls, v: float) -> float:
            if v != 0:
                _whole_ms("host_heartbeat_period", v, "the host's heartbeat period, in CANopen's whole milliseconds",
                          "0 (off) or 0.001-32.767 s, e.g. 0.1", HEARTBEAT_MS_MAX // 2)
            return v

        @field_validator("host_heartbeat_timeout")
        @classmethod
        def _host_timeout(cls, v: float | None) -> float | None:
            if v is not None:
                _whole_ms("host_heartbeat_timeout", v, "the drive's consumer heartbeat time 0x1016 (whole ms, "
                          "1-65535)", "None (three host heartbeat periods) or 0.002-65.535 s, e.g. 0.3",
                          HEARTBEAT_MS_MAX)
            return v

        @field_validator("abort_connection_option")
        @classmethod
        def _abort_option(cls, v: int | None) -> int | None:
            if v is not None and v not in ABORT_OPTIONS:
                raise ValueError(f"abort_connection_option {v} is no CiA 402 abort connection option code 0x6007 "
                                 f"the driver writes: give 0 (no action), 1 (fault), 2 (disable voltage), 3 (quick "
                                 f"stop) or null (not written: for a manufacturer-specific reaction, a negative "
                                 f"value, set it with the drive's tool)")
            return v

        @model_validator(mode="after")
        def _host_heartbeat(self) -> "CanopenGripper.Params":
            if self.host_heartbeat_period == 0:
                return self
            if self.host_node_id == self.node_id:
                raise ValueError(f"host_node_id {self.host_node_id} is the drive's node_id: the host's heartbeat "
                                 f"(COB-ID 0x{0x700 + self.host_node_id:03X}) would be taken for the drive's; give "
                                 f"host_node_id a node id no node on the bus has (1-127)")
            timeout = self.host_timeout
            if timeout > HEARTBEAT_MS_MAX / 1000:
                raise ValueError(f"host_heartbeat_timeout None is {HOST_TIMEOUT_PERIODS} x host_heartbeat_period "
                                 f"= {timeout:g} s, beyond the drive's consumer heartbeat time 0x1016 (at most "
                                 f"65.535 s): give host_heartbeat_timeout, or a shorter host_heartbeat_period")
            if round(timeout * 1000) < 2 * round(self.host_heartbeat_period * 1000):
                raise ValueError(f"host_heartbeat_timeout {timeout:g} s is less than twice host_heartbeat_period "
                                 f"{self.host_heartbeat_period:g} s: the drive would stop at one late heartbeat "
                                 f"(CiA 301 needs it above the period); give at least "
                                 f"{2 * self.host_heartbeat_period:g} s, or leave it None "
                                 f"({HOST_TIMEOUT_PERIODS} periods)")
            return self

        @property
        def host_timeout(self) -> float:
            """The consumer heartbeat time written to the drive's 0x1016 entry for the host (s)."""
            if self.host_heartbeat_timeout is not None:
                return self.host_heartbeat_timeout
            return HOST_TIMEOUT_PERIODS * self.host_heartbeat_period

        @model_validator(mode="after")
        def _map(self) -> "CanopenGripper.Params":
            OpeningMap(self.counts_open, self.opening_at_counts_open, self.counts_closed,
                       self.opening_at_counts_closed).check_limits(self, "opening_at_counts_open",
                                                                   "opening_at_counts_closed")
            return self

    # ------------------------------------------------------------------------------------------------------------
    @property
    def map(self) -> OpeningMap:
        p = self.params
        return OpeningMap(p.counts_open, p.opening_at_counts_open, p.counts_closed, p.opening_at_counts_closed)

    def _where(self) -> str:
        p = self.params
        return f"CANopen node {p.node_id} on {p.interface}:{p.channel}"

    def _sdo(self, what: str, fn: Any) -> Any:
        from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

        try:
            return fn()
        except SdoAbortedError as exc:
            raise HardwareError(f"{what}: {self._where()} refused it (SDO abort: {exc})") from exc
        except SdoCommunicationError as exc:
            lost = self._receive_failure(f"no SDO answer to {what}")
            if lost is not None:
                raise lost from lost.__cause__
            raise HardwareError(f"{what}: no SDO answer from {self._where()} ({exc}); check power, wiring, "
                                f"termination, bit rate and node id") from exc
        except self._bus_errors as exc:   # the request itself did not go out
            raise self._bus_lost(what, exc) from exc

    def _bus_lost(self, what: str, exc: BaseException) -> HardwareError:
        """A python-can error that ended ``what`` on the bus (can.CanError, OSError: "Failed to transmit: No such
        device" from an adapter that was unplugged), as a HardwareError naming the drive, its interface and channel,
        what failed, python-can's words and what to check (:func:`bus_failure_hint`); raised ``from`` it."""
        p = self.params
        hint = bus_failure_hint(exc, p.interface, p.channel, p.bitrate)
        return HardwareError(f"{self._where()}: {what} failed: {hint}")

    def _hw_open(self) -> None:
        import can
        import canopen

        p = self.params
        self._io_lock = threading.RLock()  # one set-point handshake at a time (step vs. safe_state)
        self._target: int | None = None  # counts of the last set-point the drive took (acknowledged, bit 4 low again)
        self._raised: int | None = None  # counts of the set-point sent with bit 4 high, not yet acknowledged
        self._waiting_since = 0.0   # (monotonic) since when the handshake waits for the drive's acknowledge
        self._resend = False   # the next write sends its set-point even when the drive has it (the safe state's)
        self._sent_at = -math.inf   # (monotonic) when the last RPDO1 went out
        #: what python-can raises when a frame cannot go out or come in (an unplugged adapter: CanOperationError
        #: "Failed to transmit: No such device"; OSError from a serial one)
        self._bus_errors = (can.CanError, OSError)
        if p.interface == "socketcan":
            info = can_interface_info(p.channel)
            if info is not None and info["up"] is False:   # it would open, and every frame fail with "Network is down"
                cmd = up_command(p.channel, info["virtual"], p.bitrate)
                raise HardwareError(f"CAN interface {p.channel} is down: bring it up with {cmd}"
                                    + ("" if info["virtual"] else " (the drive's bit rate: the bitrate param)"))
        # (in the Network's listeners before connect() starts python-can's receive thread: an error at its first
        # recv() ended it, with no listener to handle it yet)
        self._rx = ReceiveErrors()
        self.network = receiving_network(self._rx)
        self.network.listeners.append(self._rx)
        logged = LogLines("can")   # python-can's words on the way (a vendor library it could not load)
        try:
            with logged:
                self.network.connect(interface=p.interface, channel=p.channel, bitrate=p.bitrate)
        except Exception as exc:   # (a backend without its vendor library raises anything: kvaser a NameError)
            said = f"{type(exc).__name__}: {exc}" + (f"; python-can logged: {'; '.join(logged.lines)}"
                                                     if logged.lines else "")
            raise HardwareError(f"cannot open CAN interface {p.interface}:{p.channel} ({said}); "
                                f"{open_failure_hint(exc, p.interface, p.channel, p.bitrate)}") from exc
        self._rx.attach(self.network.notifier)
        try:
            od = p.eds if p.eds else standard_od(p.node_id)
            node = canopen.BaseNode402(p.node_id, od)
        except Exception as exc:  # a broken EDS file
            raise HardwareError(f"cannot use the object dictionary {p.eds!r}: {exc}") from exc
        self.network.add_node(node)
        self.node = node
        node.sdo.RESPONSE_TIMEOUT = p.sdo_timeout
        node.sdo.MAX_RETRIES = 1  # one attempt (0 would retry forever in canopen 2.4)
        try:
            self._start_drive()
        except self._bus_errors as exc:   # (an SDO request's is named by _sdo: an NMT command, a PDO, a SYNC)
            raise self._bus_lost("the start-up", exc) from exc

    def _start_drive(self) -> None:
        """The start-up after the bus is open (see the module's docstring)."""
        p, node = self.params, self.node
        self.emcys: list[Any] = []
        self._host_hb: Any = None   # the host's heartbeat producer (canopen's PeriodicMessageTask), while it runs
        node.emcy.add_callback(self.emcys.append)
        self._hb_seen = time.monotonic()
        self._nmt_state: int | None = None  # the NMT state in the drive's last heartbeat
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        dev = self._sdo("reading device type 0x1000", lambda: node.sdo[0x1000].raw)
        if dev & 0xFFFF != 402:
            raise HardwareError(f"{self._where()} is not a CiA 402 drive: device type 0x{dev:08X} (profile "
                                f"{dev & 0xFFFF}); check the node id")
        # a drive in FAULT is refused before anything is written to it (PDO mapping, heartbeat, mode, NMT): as found
        sw = self._sdo("reading statusword 0x6041", lambda: node.sdo[0x6041].raw)
        found_in_fault = self._fault(sw, "is in FAULT", "was in FAULT")
        self.counts_per_unit = self._velocity_unit()   # counts/s in one unit of 0x6081 and 0x606C
        self._mps_per_unit = float(self.counts_per_unit) * self.map.scale
        node.nmt.state = "PRE-OPERATIONAL"
        self._map_pdos()
        if p.heartbeat_period > 0:
            self._sdo("writing heartbeat 0x1017", lambda: setattr(node.sdo[0x1017], "raw",
                                                                   int(round(p.heartbeat_period * 1000))))
        if p.host_heartbeat_period > 0:
            self._watch_host()
        self._enter_mode(PROFILE_POSITION)
        self.profile_velocity = self._profile_velocity()
        self._check_profile_acceleration()
        self._sdo("writing profile velocity 0x6081", lambda: setattr(node.sdo[0x6081], "raw", self.profile_velocity))
        self.rated_ma = self._sdo("reading rated current 0x6075", lambda: node.sdo[0x6075].raw)
        if not self.rated_ma:
            raise HardwareError(f"{self._where()} reports a rated current (0x6075) of 0 mA")
        self.max_current = self._max_current_permille(self.rated_ma)
        self._sdo("writing max current 0x6073", lambda: setattr(node.sdo[0x6073], "raw", self.max_current))
        actual = self._sdo("reading position 0x6064", lambda: node.sdo[0x6064].raw)
        self._cw = CW_ENABLE | CW_CHANGE_IMMEDIATELY
        self._send_setpoint(actual, new=False)
        self._target, self._waiting_since = actual, time.monotonic()
        node.nmt.state = "OPERATIONAL"
        node.setup_402_state_machine(read_pdos=False)
        # SYNC drives the TPDOs that carry the statusword while the state machine is walked: sent (and counted, so the
        # first state read waits out their answers still on their way) by a thread of ours
        walked = threading.Event()
        syncs = threading.Thread(target=self._walk_syncs, args=(walked,), daemon=True,
                                 name=f"canopen-sync-node{p.node_id}")
        syncs.start()
        try:
            self._walk_to_enabled(found_in_fault)
        except (RuntimeError, ValueError) as exc:
            lost = self._receive_failure("the state walk to OPERATION ENABLED")
            if lost is not None:
                raise lost from lost.__cause__
            raise HardwareError(f"{self._where()} did not reach OPERATION ENABLED ({exc}; statusword "
                                f"0x{node.statusword:04X}, {self._emcy_text()})") from exc
        finally:
            walked.set()
            syncs.join()
        self._hb_seen = time.monotonic()
        self._nmt_state = None  # heartbeats from here on (the ones before said PRE-OPERATIONAL)
        self._check_receiving()   # (errors in receiving the start-up got over: logged)

    def _fault(self, sw: int, what: str, logged: str) -> bool:
        """Whether statusword ``sw`` is FAULT (or its reaction): then refused, a HardwareError "<the drive> <what>"
        naming the error code 0x603F and the last EMCY, unless ``reset_fault_at_start``: then logged ("<the drive>
        <logged>", to be reset)."""
        if sw & 0x4F not in (0x08, 0x0F):
            return False
        found = f"(statusword 0x{sw:04X}, error code {self._fault_code()}, {self._emcy_text()})"
        if not self.params.reset_fault_at_start:
            raise HardwareError(f"{self._where()} {what} {found}: not reset without you, the cause may still be there "
                                f"(over-current, a following error, a blocked gripper). Find and clear it, reset the "
                                f"fault (the drive's own tool, or power-cycle it), then start again; or set "
                                f"reset_fault_at_start: true to have the start-up reset it")
        self.ctx.log(f"{self._where()} {logged} {found}: resetting it (controlword bit 7, reset_fault_at_start)")
        return True

    def _watch_host(self) -> None:
        """Have the drive watch the host (pre-operational, with the other SDO writes): the host's heartbeat producer
        (:class:`HostHeartbeat`: python-can's periodic task, the kernel's broadcast manager on socketcan) first, for a
        drive that watches from the moment its consumer is set; then the drive's consumer heartbeat time 0x1016 (the
        entry :meth:`_consumer_entry` chose: host node id, time in ms) and abort connection option code 0x6007; then
        one heartbeat at once: a CiA 301 consumer starts watching at the first heartbeat after it was set, and the
        periodic one may come a period later (socketcan's first frame comes after a period), after the start-up, so
        that a host that died right after it went unwatched. A drive without either object is refused, naming the
        param that does without. First the host's node id is listened on (HOST_ID_LISTEN periods): a drive takes any
        heartbeat with that id for its host's, so another host producing it (a second gripper's driver, another
        teletouch on the bus) would keep this drive watched "alive" after this process died; that is refused, naming
        host_node_id."""
        p = self.params
        self._host_id_free()
        sub = self._consumer_entry()
        self._start_host_heartbeat()
        self._host_sub = sub   # the entry close() turns off again
        timeout_ms = int(round(p.host_timeout * 1000))
        self._write_object(0x1016, sub, (p.host_node_id << 16 | timeout_ms).to_bytes(4, "little"),
                           f"writing consumer heartbeat time 0x1016 sub {sub} = "
                           f"0x{p.host_node_id << 16 | timeout_ms:08X} (host node {p.host_node_id}, "
                           f"host_heartbeat_timeout {timeout_ms} ms)", consumer_missing(sub))
        if p.abort_connection_option is not None:
            option = p.abort_connection_option
            self._write_object(0x6007, 0, option.to_bytes(2, "little", signed=True),
                               f"writing abort connection option code 0x6007 = {option} "
                               f"({ABORT_OPTIONS[option]}, abort_connection_option)",
                               "no abort connection option code 0x6007: what it does when the host's heartbeat "
                               "stops is its own (its manual; often a fault). Set abort_connection_option: null to "
                               "leave that as it is, or host_heartbeat_period: 0 to turn the host heartbeat off")
        try:
            self.network.send_message(0x700 + p.host_node_id, bytes([NMT_OPERATIONAL]))
        except Exception as exc:   # (can.CanError, OSError: a full transmit queue; the periodic one still comes)
            self.ctx.log(f"the first host heartbeat to {self._where()} could not be sent ({exc}): the drive watches "
                         f"the host from the periodic one, a period later")

    def _consumer_entry(self) -> int:
        """The sub-index of consumer heartbeat time 0x1016 that watches the host: 0x1016 sub 0 (the number of
        entries) is read, then each entry (bits 16-23 a producer's node id, bits 0-15 its time in ms). The entry that
        already holds ``host_node_id`` (one with a time first: CiA 301 refuses a second entry for the same node with a
        time, SDO abort 0x06040043), else the first free one (0); an entry of another producer (another master's) is
        never replaced: none free is refused, naming what each entry holds and what to do. A drive without 0x1016 (or
        without entries) is refused naming ``host_heartbeat_period: 0``."""
        p = self.params
        count, why = self._read_u32(0x1016, 0, "reading consumer heartbeat time 0x1016 sub 0 (number of entries)")
        if count is None or count == 0:
            why = f"SDO abort: {why}" if count is None else "0x1016 sub 0, its number of entries, is 0"
            raise HardwareError(f"{self._where()} has {consumer_missing(1)} ({why})")
        entries: dict[int, int] = {}
        for sub in range(1, min(count, 0x7F) + 1):
            value, _ = self._read_u32(0x1016, sub, f"reading consumer heartbeat time 0x1016 sub {sub}")
            if value is not None:   # (a sub-index the drive does not have: skipped)
                entries[sub] = value
        host = [sub for sub, value in entries.items() if value >> 16 & 0xFF == p.host_node_id]
        if host:
            return next((sub for sub in host if entries[sub] & 0xFFFF), host[0])
        free = [sub for sub, value in entries.items() if value == 0]
        if free:
            return free[0]
        held = "; ".join(f"sub {sub} {consumer_text(value)}" for sub, value in entries.items()) or "none readable"
        raise HardwareError(
            f"{self._where()} has no free entry in its consumer heartbeat time 0x1016 for the host's heartbeat (node "
            f"{p.host_node_id}); its {count} entries: {held}. An entry with a node id is another producer the drive "
            f"watches (another master, set with the drive's tool), which the driver does not replace: free one (set "
            f"it to 0 with the drive's tool, or from the master that set it), or, where one is this host's, give "
            f"host_node_id its node id; host_heartbeat_period: 0 runs the drive without watching this host")

    def _host_id_free(self) -> None:
        p = self.params
        cob = 0x700 + p.host_node_id
        seen: list[float] = []

        def heard(can_id: int, data: bytes, timestamp: float) -> None:
            seen.append(time.monotonic())

        self.network.subscribe(cob, heard)
        try:
            time.sleep(HOST_ID_LISTEN * p.host_heartbeat_period)
        finally:
            self.network.unsubscribe(cob, heard)
        if seen:
            raise HardwareError(
                f"another node sends heartbeats as node {p.host_node_id} (COB-ID 0x{cob:03X}) on "
                f"{p.interface}:{p.channel} (another gripper's driver, or another program): {self._where()} would take "
                f"them for this host's, and keep going if this process died. Give each canopen-gripper on a bus its "
                f"own host_node_id (1-127, no node's id), or host_heartbeat_period: 0")

    def _start_host_heartbeat(self) -> None:
        p = self.params
        try:
            self._host_hb = HostHeartbeat(self.network.bus, 0x700 + p.host_node_id, p.host_heartbeat_period)
        except Exception as exc:   # (a BCM socket refused, a bus that has no periodic sending)
            raise HardwareError(f"cannot start the host heartbeat on {p.interface}:{p.channel} ({exc}); set "
                                f"host_heartbeat_period: 0 to run without it") from exc
        self._hb_runs_seen = 0   # runs of failed heartbeat sends already logged

    def _stop_host_heartbeat(self) -> None:
        task, self._host_hb = getattr(self, "_host_hb", None), None
        if task is not None:
            try:
                task.stop()
            except Exception:
                pass

    def _check_host_heartbeat(self) -> None:
        """Failed sends of the host heartbeat (:class:`HostHeartbeat`, which goes on sending through them): each run
        of them is logged once; where none has gone out for longer than the drive's consumer time
        ``host_heartbeat_timeout`` (the drive has missed the host, and acts per abort_connection_option), a
        HardwareError naming the drive, the interface, python-can's error and what to check (:meth:`_bus_lost`)."""
        hb = self._host_hb
        if hb is None:
            return
        silent, runs, error = hb.failures()
        if error is None:
            return
        p = self.params
        if silent > p.host_timeout:
            option = p.abort_connection_option
            raise self._bus_lost(f"sending the host heartbeat (COB-ID 0x{0x700 + p.host_node_id:03X}; none went out "
                                 f"for {silent:.3f} s, longer than host_heartbeat_timeout {p.host_timeout:g} s: the "
                                 f"drive acts per abort_connection_option {option}, "
                                 f"{ABORT_OPTIONS.get(option, 'its own')})", error) from error
        if runs > self._hb_runs_seen:
            self._hb_runs_seen = runs
            self.ctx.log(f"sending the host heartbeat to {self._where()} failed ({type(error).__name__}: {error}): "
                         f"it goes on sending; the drive acts if none goes out for host_heartbeat_timeout "
                         f"{p.host_timeout:g} s")

    def _write_object(self, index: int, sub: int, data: bytes, what: str, missing: str) -> None:
        """An SDO download (an EDS file need not list the object); a drive without the object (abort 0x06020000 or
        0x06090011) is refused saying it has ``missing``; any other abort names ``what`` (:meth:`_sdo`)."""
        from canopen.sdo.exceptions import SdoAbortedError

        def download() -> str:
            try:
                self.node.sdo.download(index, sub, data)
            except SdoAbortedError as exc:
                if getattr(exc, "code", None) not in NO_SUCH_OBJECT:
                    raise
                return str(exc)
            return ""

        why = self._sdo(what, download)
        if why:
            raise HardwareError(f"{self._where()} has {missing} (SDO abort: {why})")

    def _walk_to_enabled(self, fault_seen: bool) -> None:
        """The CiA 402 state machine to OPERATION ENABLED, one transition of canopen's table at a time, from the
        drive's own statusword (from canopen's default 0, none received yet, the first controlword was "disable
        voltage", switching off a drive found enabled). canopen's own walk (``node.state = ...``) resets a FAULT on
        its way (transition 15) without a word: here each FAULT is refused, or logged first (:meth:`_fault`);
        ``fault_seen``: the drive was found in FAULT, and that was logged. A transition not shown within canopen's
        single-step timeout is commanded again, until its final timeout (a RuntimeError, as canopen's)."""
        from canopen.profiles.p402 import State402

        node, target = self.node, "OPERATION ENABLED"
        node.check_statusword()
        deadline = time.monotonic() + node.TIMEOUT_SWITCH_STATE_FINAL
        at = "its start"   # the walk's last state that was no fault (for the message)
        while (state := node.state) != target:
            if state in ("FAULT", "FAULT REACTION ACTIVE"):
                if not fault_seen:   # a new one: a fault that came during the start-up
                    came = f"went into FAULT during the start-up (the state walk to {target} at {at})"
                    fault_seen = self._fault(node.statusword, came, came)
            else:
                fault_seen, at = False, state
            step = target if (state, target) in State402.TRANSITIONTABLE else State402.next_state_indirect(state)
            if (state, step) not in State402.TRANSITIONTABLE:
                raise ValueError(f"no transition from {state} towards {target}")
            node.controlword = State402.TRANSITIONTABLE[(state, step)]
            until = time.monotonic() + node.TIMEOUT_SWITCH_STATE_SINGLE
            while node.state == state and time.monotonic() < until:
                node.check_statusword()
            if node.state == state and time.monotonic() > deadline:
                raise RuntimeError("Timeout when trying to change state")

    def _enter_mode(self, mode: int) -> None:
        """Write modes of operation 0x6060, then read the display 0x6061 (every MODE_POLL) until it shows ``mode``:
        a CiA 402 drive switches in its own time, and the display follows the request when it has (read once, at
        once, a drive still switching was refused). Not within ``mode_timeout``: a HardwareError naming both."""
        node, p = self.node, self.params
        self._sdo("writing mode 0x6060", lambda: setattr(node.sdo[0x6060], "raw", mode))
        deadline = time.monotonic() + p.mode_timeout
        while True:
            shown = self._sdo("reading mode display 0x6061", lambda: node.sdo[0x6061].raw)
            if shown == mode:
                return
            if time.monotonic() >= deadline:
                raise HardwareError(f"{self._where()} did not switch to the requested mode {mode_text(mode)} within "
                                    f"mode_timeout {p.mode_timeout:g} s: modes of operation display 0x6061 still "
                                    f"shows {mode_text(shown)} (check that supported drive modes 0x6502 has it; a "
                                    f"drive that switches slowly needs a longer mode_timeout)")
            time.sleep(MODE_POLL)

    def _profile_velocity(self) -> int:
        """Profile velocity 0x6081 (in the drive's velocity unit) for ``max_speed``, rounded down in exact arithmetic:
        the drive's own speed limit (what a set-point jump, the ``open`` safe state, runs at) never exceeds max_speed
        (rounded to nearest it did, a limit below one unit became one, and counts/s written to a drive in rpm ran
        it ~68x max_speed at 4096 counts/rev)."""
        p = self.params
        span = abs(Fraction(repr(p.opening_at_counts_open)) - Fraction(repr(p.opening_at_counts_closed)))
        exact = Fraction(repr(p.max_speed)) * abs(p.counts_closed - p.counts_open) / span / self.counts_per_unit
        raw = min(math.floor(exact), 0xFFFFFFFF)
        if raw < 1:
            unit = float(self.counts_per_unit * span / abs(p.counts_closed - p.counts_open))
            raise HardwareError(f"max_speed {p.max_speed} m/s is below the slowest profile velocity 0x6081 of "
                                f"{self._where()} (1 x {self.velocity_unit} = {unit:.4g} m/s with this calibration); "
                                f"raise max_speed")
        return raw

    def _velocity_unit(self) -> Fraction:
        """Counts per second in one unit of the drive's velocity (profile velocity 0x6081, velocity actual 0x606C):
        from its SI unit velocity 0x60A9, or ``velocity_unit`` where it has none (:meth:`_read_u32`); a unit in
        revolutions times the counts per revolution. Refused: a unit the driver cannot convert, none known, a
        ``velocity_unit`` that disagrees with 0x60A9."""
        p = self.params
        code, why = self._read_u32(0x60A9, 0, "reading SI unit velocity 0x60A9")
        if code is None:
            if p.velocity_unit is None:
                raise HardwareError(f"{self._where()} has no SI unit velocity 0x60A9 (SDO abort: {why}): the unit of "
                                    f"its profile velocity 0x6081 and velocity actual 0x606C is unknown, and a wrong "
                                    f"guess runs the gripper at a multiple of max_speed; give velocity_unit from the "
                                    f"drive's manual ('rpm', '0.001 rpm', 'counts/s', ...)")
            kind, per_second = parse_velocity_unit(p.velocity_unit)
            self.velocity_unit = p.velocity_unit
            source = f"velocity_unit '{p.velocity_unit}'"
        else:
            self.velocity_unit = velocity_unit_text(code)
            source = f"SI unit velocity 0x60A9 of {self._where()} is 0x{code:08X} ({self.velocity_unit})"
            unit = si_velocity_unit(code)
            if unit is None:
                raise HardwareError(f"{source}: the driver converts only revolutions per minute or second (with a "
                                    f"power of ten) to the fingers' m/s; set 0x60A9 to 0x{RPM:08X} (rpm) or "
                                    f"0xFDB44700 (0.001 rpm) with the drive's configuration tool")
            if p.velocity_unit is not None and parse_velocity_unit(p.velocity_unit) != unit:
                raise HardwareError(f"velocity_unit '{p.velocity_unit}' disagrees with the SI unit velocity 0x60A9 "
                                    f"of {self._where()}, 0x{code:08X} ({self.velocity_unit}): leave velocity_unit "
                                    f"out (the drive's own is used) or correct it")
            kind, per_second = unit
        return per_second if kind == "counts" else per_second * self._counts_per_revolution(source)

    def _counts_per_revolution(self, source: str) -> Fraction:
        """0x6064 counts per revolution: ``counts_per_revolution``, else the position encoder resolution 0x608F
        (increments / motor revolutions)."""
        p = self.params
        if p.counts_per_revolution is not None:
            return Fraction(repr(p.counts_per_revolution))
        increments, why = self._read_u32(0x608F, 1, "reading position encoder resolution 0x608F")
        revolutions, why = (None, why) if increments is None else \
            self._read_u32(0x608F, 2, "reading position encoder resolution 0x608F")
        if increments is None or revolutions is None:
            raise HardwareError(f"{source}, in revolutions: converting it needs the position counts (0x6064) per "
                                f"revolution, and {self._where()} has no position encoder resolution 0x608F (SDO "
                                f"abort: {why}); give counts_per_revolution")
        if not increments or not revolutions:
            raise HardwareError(f"{self._where()} reports a position encoder resolution 0x608F of {increments} "
                                f"increments per {revolutions} motor revolutions; give counts_per_revolution")
        scaling = self._position_scaling()
        if scaling:   # 0x6064 is then in the drive's position units, not encoder increments
            raise HardwareError(f"{source}, in revolutions: {self._where()} scales its positions ({scaling}), so the "
                                f"position encoder resolution 0x608F ({increments} increments per {revolutions} motor "
                                f"revolutions) is not the 0x6064 counts per revolution; give counts_per_revolution "
                                f"(0x6064 counts per revolution of the velocity unit, from the drive's manual)")
        return Fraction(increments, revolutions)

    def _position_scaling(self) -> str:
        """The drive's position scaling where it has one ("" where it has none, or 1:1): gear ratio 0x6091 (motor
        revolutions : shaft revolutions) and feed constant 0x6092 (feed : shaft revolutions). A drive without the
        objects (SDO abort: no such object) scales nothing."""
        found = []
        for index, name in ((0x6091, "gear ratio 0x6091"), (0x6092, "feed constant 0x6092")):
            a, _ = self._read_u32(index, 1, f"reading {name}")
            b, _ = (None, "") if a is None else self._read_u32(index, 2, f"reading {name}")
            if a is not None and b is not None and a != b:
                found.append(f"{name} {a}:{b}")
        return ", ".join(found)

    def _check_profile_acceleration(self) -> None:
        """Profile acceleration 0x6083 and deceleration 0x6084 are the drive's own (set with its tool): one of 0
        moves nothing (or stops nothing) on many drives, and was left unseen. Objects the drive does not have are
        its own business."""
        for index, name in ((0x6083, "profile acceleration 0x6083"), (0x6084, "profile deceleration 0x6084")):
            value, _ = self._read_u32(index, 0, f"reading {name}")
            if value == 0:
                raise HardwareError(f"{self._where()} has a {name} of 0: the set-points would not move the fingers "
                                    f"(or not stop them); set it with the drive's configuration tool (in its "
                                    f"acceleration unit, e.g. velocity units per second)")

    def _read_u32(self, index: int, sub: int, what: str) -> tuple[int | None, str]:
        """An UNSIGNED32 object read by SDO upload (an EDS file need not list it): (value, ""), or (None, the abort)
        where the drive has no such object (abort 0x06020000 or 0x06090011); any other abort (the drive's state, a
        refused access) and no answer at all are a HardwareError: taken for "no such object", a drive that has one
        was driven in a unit it does not use."""
        from canopen.sdo.exceptions import SdoAbortedError

        def upload() -> tuple[bytes | None, str]:
            try:
                return self.node.sdo.upload(index, sub), ""
            except SdoAbortedError as exc:
                if getattr(exc, "code", None) not in NO_SUCH_OBJECT:
                    raise   # (_sdo names it)
                return None, str(exc)

        data, why = self._sdo(what, upload)
        return (None, why) if data is None else (int.from_bytes(data[:4], "little"), "")

    def _max_current_permille(self, rated_ma: int) -> int:
        """Max current 0x6073 (per mille of the rated current) for ``max_effort``, rounded down: the cap the drive
        applies never exceeds max_effort. Computed in exact decimal arithmetic (the parameters as written), so a
        value that is exactly representable (10 N at 20 N/A of 2 A: 250) is not lost to binary rounding."""
        p = self.params
        exact = Fraction(repr(p.max_effort)) * 1_000_000 / (Fraction(repr(p.newtons_per_amp)) * rated_ma)
        permille = min(math.floor(exact), 0xFFFF)
        if permille < 1:
            least = Fraction(rated_ma, 1_000_000) * Fraction(repr(p.newtons_per_amp))
            raise HardwareError(f"max_effort {p.max_effort} N is below the smallest current limit {self._where()} "
                                f"accepts (0x6073 = 1 per mille of the rated {rated_ma} mA = {float(least):.4g} N "
                                f"at newtons_per_amp {p.newtons_per_amp}); raise max_effort")
        return permille

    def _map_pdos(self) -> None:
        n = self.node

        def configure() -> None:
            n.tpdo.read()
            n.rpdo.read()
            for m in list(n.tpdo.map.values()) + list(n.rpdo.map.values()):
                m.clear()
                m.enabled = False
            t1, t2, r1 = n.tpdo[1], n.tpdo[2], n.rpdo[1]
            t1.add_variable(0x6041)
            t1.add_variable(0x6064)
            t1.add_variable(0x6061)
            t2.add_variable(0x6078)
            t2.add_variable(0x606C)
            r1.add_variable(0x607A)  # the target first: the drive latches it on the controlword's edge
            r1.add_variable(0x6040)
            r1.add_variable(0x6060)
            for m, tt in ((t1, 1), (t2, 1), (r1, 255)):
                m.trans_type = tt
                m.enabled = True
            n.tpdo.save()
            n.rpdo.save()

        self._sdo("mapping PDOs", configure)
        self.tp1, self.tp2, self.rp1 = n.tpdo[1], n.tpdo[2], n.rpdo[1]
        self._arrivals = {id(self.tp1): 0, id(self.tp2): 0}   # frames received, per TPDO
        self._owed = {id(self.tp1): 0, id(self.tp2): 0}       # the count that answers every SYNC sent so far
        self._late = {id(self.tp1): 0, id(self.tp2): 0}       # answers written off that may still come
        self._arrived_at = {id(self.tp1): -math.inf, id(self.tp2): -math.inf}   # monotonic time of the last frame
        for m in (self.tp1, self.tp2):
            m.add_callback(self._on_tpdo)

    def _on_heartbeat(self, state: int) -> None:
        # the age of a heartbeat is measured on the local monotonic clock from when it arrived (called as the frame
        # is received): msg.timestamp's clock depends on the python-can interface (epoch on socketcan, monotonic,
        # a device counter or nothing on others), so comparing it with time.time() lost live drives and kept dead
        # ones alive
        self._hb_seen = time.monotonic()
        self._nmt_state = state

    def _on_tpdo(self, pdo: Any) -> None:
        # counted and timed on arrival (under pdo.receive_condition): msg.timestamp need not change from frame to
        # frame, and its clock is the interface's
        self._arrived_at[id(pdo)] = time.monotonic()
        self._arrivals[id(pdo)] += 1

    def _send_setpoint(self, counts: int, new: bool) -> None:
        """RPDO1: target ``counts`` with controlword bit 4 ("new set-point") high (``new``) or low."""
        r = self.rp1
        r[0x6060].raw = PROFILE_POSITION
        r[0x607A].raw = int(counts)
        r[0x6040].raw = (self._cw | CW_NEW_SETPOINT) if new else (self._cw & ~CW_NEW_SETPOINT)
        r.transmit()
        self._sent_at = time.monotonic()

    def _handshake(self, sw: int, counts: int) -> None:
        """CiA 402's set-point handshake in profile position mode, over the steps: a new set-point goes out with bit 4
        high; once the statusword's set-point acknowledge (bit 12) shows the drive took it, bit 4 goes low (same
        target); once the acknowledge is low again, the next set-point may go: one every other step at most. (Bit 4
        low then high back to back, as before, reached the drive within one of its control cycles: no edge to it, and
        the set-point was never taken.) No acknowledge within ``read_timeout`` is a HardwareError."""
        now = time.monotonic()
        if self._raised is not None:   # bit 4 high: waiting for the drive to take the set-point
            if sw & SW_SETPOINT_ACK:
                self._send_setpoint(self._raised, new=False)
                self._target, self._raised, self._waiting_since = self._raised, None, now
            else:
                self._check_ack_wait(now, sw, f"take set-point {self._raised} (statusword bit 12 set-point "
                                              f"acknowledge)")
            return
        if sw & SW_SETPOINT_ACK:   # bit 4 low has not been answered yet: the acknowledge still high
            self._check_ack_wait(now, sw, "drop its set-point acknowledge (statusword bit 12) after bit 4 went low")
            return
        if self._resend or counts != self._target:
            self._send_setpoint(counts, new=True)
            self._raised, self._waiting_since, self._resend = counts, now, False

    def handshake_idle(self) -> bool:
        """Whether the set-point handshake is over: bit 4 low again and the last statusword's acknowledge low (the
        drive has read that frame): the next write with another target sends it at once."""
        return self._raised is None and not self.tp1[0x6041].raw & SW_SETPOINT_ACK

    def _check_ack_wait(self, now: float, sw: int, what: str) -> None:
        waited = now - self._waiting_since
        if waited > self.params.read_timeout:
            raise HardwareError(f"{self._where()} did not {what} within read_timeout ({waited:.3f} s; statusword "
                                f"0x{sw:04X}, {self._emcy_text()})")

    def _send_at_once(self, counts: int) -> None:
        """The safe state's set-point, which cannot wait for the handshake over the steps: where bit 4 is high (or
        its acknowledge still is), bit 4 low with the target, a pause longer than the drive's control cycle
        (SETPOINT_PULSE_GAP), then high; the next steps finish the handshake. Each frame goes out a pause after the
        one before, so that the drive reads every one (a step's set-point raised just before is taken, not lost)."""
        time.sleep(max(0.0, self._sent_at + SETPOINT_PULSE_GAP - time.monotonic()))
        if self._raised is not None or self.tp1[0x6041].raw & SW_SETPOINT_ACK:
            self._raised = None
            self._send_setpoint(counts, new=False)
            time.sleep(SETPOINT_PULSE_GAP)
        self._send_setpoint(counts, new=True)
        self._raised, self._waiting_since, self._resend = counts, time.monotonic(), False

    def _emcy_text(self) -> str:
        if not self.emcys:
            return "no EMCY received"
        e = self.emcys[-1]
        return f"last EMCY {e}"

    def _sync(self) -> None:
        """Transmit SYNC: TPDO1 and TPDO2 (transmission type 1) each owe one more answer."""
        self.network.sync.transmit()
        for key in self._owed:
            self._owed[key] += 1

    def _walk_syncs(self, walked: threading.Event) -> None:
        while not walked.wait(WALK_SYNC_PERIOD):
            try:
                self._sync()
            except Exception:   # (a full transmit queue: the next one is tried; the walk times out if none goes out)
                pass

    def _still_owed(self) -> str:
        """The answers to earlier SYNCs that have not arrived ("" when none), after forgetting extra frames (an
        answer written off that came after all, a SYNC of another producer on the bus): a frame answers a SYNC only
        after every earlier SYNC's answer."""
        owed = []
        for pdo in (self.tp1, self.tp2):
            key = id(pdo)
            got = self._arrivals[key]
            if got > self._owed[key]:
                self._late[key] = max(0, self._late[key] - (got - self._owed[key]))
                self._owed[key] = got
            elif got < self._owed[key]:
                owed.append(f"{self._owed[key] - got} of TPDO{1 if pdo is self.tp1 else 2}")
        return ", ".join(owed)

    def _answered(self, deadline: float, since: float = -math.inf) -> bool:
        """Whether every SYNC sent so far has its TPDO1 and TPDO2, the last of them received after ``since`` (the
        last SYNC's time), waiting until ``deadline``. Answers written off may still come, before any later SYNC's
        (in order): waited for too, and taken as lost after all at ``deadline`` (then the frame that came after
        ``since`` is the last SYNC's answer)."""
        for pdo in (self.tp1, self.tp2):
            key = id(pdo)
            with pdo.receive_condition:
                while self._arrivals[key] < self._owed[key] + self._late[key] or self._arrived_at[key] < since:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    pdo.receive_condition.wait(left)
                if self._arrivals[key] < self._owed[key] or self._arrived_at[key] < since:
                    return False
        for key in self._late:
            self._late[key] = 0   # come, or lost
        return True

    def _hw_read(self) -> Reading | None:
        p = self.params
        # errors in receiving (python-can's receive thread, see ReceiveErrors) first, before the heartbeats and TPDOs
        # not received are taken for a lost drive: one that frames followed is logged; one that goes on for the
        # driver's bounds (read_timeout since its first error, or the drive's heartbeat watch) ends the run
        failing = self._check_receiving()
        if failing is not None:
            first, _, exc = failing
            now = time.monotonic()
            if now - first > p.read_timeout or (p.heartbeat_period > 0 and now - self._hb_seen > p.read_timeout):
                raise self._bus_lost("receiving", exc) from exc
        # the host heartbeat first: where it could not be sent for the drive's consumer time, that is the cause of
        # what the drive did then (quick stop, NMT PRE-OPERATIONAL)
        self._check_host_heartbeat()
        if p.heartbeat_period > 0:
            self._check_heartbeat()
        # TPDOs carry no SYNC number: each SYNC's answer is counted. The answers to earlier SYNCs (a step that timed
        # out, the state walk's) arrive first, in order: waited for before this step's SYNC, so that none of them is
        # taken for its answer; not there within pdo_timeout, they are written off as lost and the step has no state
        owed = self._still_owed()
        if owed and not self._answered(time.monotonic() + p.pdo_timeout):
            for key in self._owed:   # remembered: they may still come, before the next SYNC's answer
                self._late[key] += max(0, self._owed[key] - self._arrivals[key])
                self._owed[key] = self._arrivals[key]
            self.last_error = (f"the TPDOs answering earlier SYNCs ({owed}) did not come within another "
                               f"{p.pdo_timeout * 1e3:.0f} ms: written off as lost")
            return None
        t0 = time.monotonic()
        try:
            self._sync()
        except self._bus_errors as exc:
            raise self._bus_lost("sending SYNC", exc) from exc
        ok = self._answered(t0 + p.pdo_timeout, since=t0)
        t1 = max(self._arrived_at.values())   # the reading is whole (not the end of a wait for written-off answers)
        if not ok:
            self.last_error = f"no TPDO within {p.pdo_timeout * 1e3:.0f} ms of SYNC"
            return None
        sw = self.tp1[0x6041].raw
        if sw & 0x4F == 0x08 or sw & 0x4F == 0x0F:
            code = self._fault_code()
            raise HardwareError(f"{self._where()} is in FAULT (statusword 0x{sw:04X}, error code {code}, "
                                f"{self._emcy_text()}); clear the cause, then reset the drive")
        if sw & 0x6F != 0x27:
            raise HardwareError(f"{self._where()} left OPERATION ENABLED (statusword 0x{sw:04X}, "
                                f"{self._emcy_text()}){self._host_loss_hint()}")
        mode = self.tp1[0x6061].raw
        if mode != PROFILE_POSITION:
            raise HardwareError(f"{self._where()} left profile position mode (0x6061 = {mode})")
        counts = self.tp1[0x6064].raw
        amps = self.tp2[0x6078].raw / 1000.0 * self.rated_ma / 1000.0
        vel = self.tp2[0x606C].raw * self._mps_per_unit   # the drive's velocity unit -> counts/s -> m/s
        return Reading(self.map.opening(counts), vel, abs(amps) * p.newtons_per_amp, 0.5 * (t0 + t1))

    def _check_receiving(self) -> tuple[float, int, BaseException] | None:
        """Errors in receiving (:class:`ReceiveErrors`): each run of them that frames ended is logged (the frames flow
        again: going on); python-can's receive thread ended is a HardwareError (:meth:`_receiver_ended`); the failure
        frames have not ended yet (its first error's time, failed receives, the last error), or None."""
        rx = self._rx
        for first, back, n, exc in rx.take():
            times = "" if n == 1 else f", {n} times in a row"
            self.ctx.log(f"receiving on {self._where()} failed ({type(exc).__name__}: {exc}{times}); frames arrived "
                         f"again {back - first:.3f} s after the first error: going on ({rx.count} failed receives "
                         f"so far)")
        ended = self._receiver_ended()
        if ended is not None:
            raise ended from ended.__cause__
        return rx.failing()

    def _receiver_ended(self) -> HardwareError | None:
        """python-can's receive thread ended while the bus is open (:meth:`ReceiveErrors.stopped`): nothing is
        received any more, for good. A HardwareError (from the last error in receiving where there was one) that has
        the driver started again, not a new thread: with ReceiveErrors handling every error, python-can ends the
        thread only where another listener's on_error raises or something other than an Exception is raised in it
        (the program's fault, which a new thread would meet again), and a new thread is a new Notifier in place of
        canopen's (``Notifier.add_bus`` refuses a bus a running Notifier holds); None while it runs."""
        rx = getattr(self, "_rx", None)
        if rx is None or not rx.stopped():
            return None
        p, failing = self.params, rx.failing()
        said = "" if failing is None else f" after {type(failing[2]).__name__}: {failing[2]}"
        err = HardwareError(f"{self._where()}: python-can's receive thread for {p.interface}:{p.channel} has "
                            f"ended{said}; nothing is received any more (no state, heartbeat or SDO answer): close "
                            f"the driver and start it again")
        err.__cause__ = None if failing is None else failing[2]
        return err

    def _receive_failure(self, what: str) -> HardwareError | None:
        """For a wait that ended without an answer (``what``): python-can's receive thread ended, or the error in
        receiving that no frame has followed, as :meth:`_bus_lost` names it (chained from it: ``__cause__``); None
        when neither."""
        ended = self._receiver_ended()
        if ended is not None:
            return ended
        rx = getattr(self, "_rx", None)
        failing = None if rx is None else rx.failing()
        if failing is None:
            return None
        first, n, exc = failing
        err = self._bus_lost(f"receiving ({what}; {n} failed receives in {time.monotonic() - first:.3f} s, no "
                             f"frame since)", exc)
        err.__cause__ = exc
        return err

    def _host_loss_hint(self) -> str:
        """For a drive that left OPERATION ENABLED: that it may be its reaction to a missed host heartbeat."""
        p = self.params
        if p.host_heartbeat_period == 0 or p.abort_connection_option not in (None, 2, 3):
            return ""
        return (f"; a quick stop or disable voltage is also what it does when it misses the host's heartbeat for "
                f"host_heartbeat_timeout {p.host_timeout:g} s (abort connection option code 0x6007): was this "
                f"process or its CAN interface stalled?")

    def _check_heartbeat(self) -> None:
        """The drive's heartbeat: none for more than three periods is noted, for more than read_timeout a fault; one
        saying the drive left NMT OPERATIONAL (reset, or another master) is a fault at once: its PDOs stopped."""
        p = self.params
        age = time.monotonic() - self._hb_seen
        if age > 3 * p.heartbeat_period:
            self.last_error = f"no heartbeat for {age:.3f} s"
            if age > p.read_timeout:
                raise HardwareError(f"{self._where()}: {self.last_error}; the drive is gone (power, cable)")
        state = self._nmt_state
        if state is not None and state != NMT_OPERATIONAL:
            from canopen.nmt import NMT_STATES   # (the state's name, on this error path only: the check runs each step)

            causes = "the drive was reset (power, watchdog) or another master changed its NMT state"
            if p.host_heartbeat_period > 0 and state in NMT_HOST_LOSS_STATES:
                causes = (f"likely it missed the host's heartbeat (a drive leaves OPERATIONAL when its consumer "
                          f"heartbeat time 0x1016 runs out, per its error behaviour 0x1029: PRE-OPERATIONAL by CiA "
                          f"301's default): none reached it for host_heartbeat_timeout {p.host_timeout:g} s (sent "
                          f"every host_heartbeat_period {p.host_heartbeat_period:g} s), with this process stalled or "
                          f"its CAN interface busy or lost; or the drive was reset (power, watchdog), or another "
                          f"master changed its NMT state")
            raise HardwareError(f"{self._where()} left NMT OPERATIONAL (heartbeat: {NMT_STATES.get(state, state)}): "
                                f"it sends and takes no PDOs; {causes}")

    def _fault_code(self) -> str:
        try:
            return f"0x{self.node.sdo[0x603F].raw:04X}"
        except Exception:
            return "unreadable"

    def read_state(self, t: float) -> Reading:
        try:
            return super().read_state(t)
        except HardwareError as exc:
            if "no valid state" in str(exc):
                lost = self._receive_failure("no valid state")   # (python-can's error says why)
                if lost is not None:
                    raise lost from lost.__cause__
                raise HardwareError(f"{exc}: {self._read_problem()}") from None
            raise

    def _read_problem(self) -> str:
        rx = getattr(self, "_rx", None)
        failing = None if rx is None else rx.failing()
        receiving = "" if failing is None else (f"; receiving has failed for {time.monotonic() - failing[0]:.3f} s "
                                                f"({type(failing[2]).__name__}: {failing[2]})")
        return f"{self._where()}, last problem: {getattr(self, 'last_error', '?')}{receiving}"

    def activate(self) -> None:
        super().activate()
        self._waiting_since = time.monotonic()   # a wait for the drive's acknowledge counts from now

    def _command_guard(self) -> Any:
        # the step's set-point and its send are one unit against a safe_state() from elsewhere (the state read, which
        # waits up to pdo_timeout for the TPDOs, stays outside)
        return self._io_lock

    def _hw_write(self, opening: float) -> None:
        with self._io_lock:
            sw = self.tp1[0x6041].raw   # the last statusword received
            if sw & 0x6F != 0x27:   # RPDO1's controlword (enable operation) would enable the drive again
                raise HardwareError(f"{self._where()} is not in OPERATION ENABLED (statusword 0x{sw:04X}): no "
                                    f"set-point sent, it would enable the drive again (quick stop, disabled or fault)")
            counts = self.map.counts(opening)
            try:
                if self._safe and (self._resend or counts not in (self._raised, self._target)):
                    self._send_at_once(counts)   # the safe state's hold (or open) goes out now
                else:
                    self._handshake(sw, counts)
            except self._bus_errors as exc:   # (not taken as sent: the next write sends it again)
                raise self._bus_lost(f"sending set-point {counts} (RPDO1)", exc) from exc

    def _forget_sent(self) -> None:
        self._resend = True  # always (re)send the hold set-point, whatever was sent before

    def _hw_close(self) -> None:
        net = getattr(self, "network", None)
        if net is None:
            return
        # an orderly end: the drive's watch of the host is turned off first (its 0x1016 entry = 0), so that it keeps
        # holding the safe state's set-point, powered, as it did before it watched the host (its reaction, a quick
        # stop, ends in SWITCH ON DISABLED, power stage off, under CiA 402's default 0x605A: a gripper holding an
        # object let go 0.3 s after every run); only a host that dies or hangs without close() trips it. Where that
        # write fails, the heartbeat stops last, after the safe state's set-point went out (the runtime and the
        # Harness call safe_state() before close(); a send on another thread holds the lock): the drive's reaction
        # then comes after the hold (and, safe_mode open, after the fingers opened: waited for first), never before
        if getattr(self, "_host_hb", None) is not None:
            try:   # (safe_mode open: the fingers opened while the drive is still watched)
                self._finish_open()
            except Exception:   # (close() must not raise; the heartbeat stops all the same)
                pass
            self._release_host_watch()
            lock = getattr(self, "_io_lock", None)
            got = lock is not None and lock.acquire(timeout=CLOSE_LOCK_WAIT)
            try:
                self._stop_host_heartbeat()
            finally:
                if got:
                    lock.release()
        self.network = None
        try:
            net.sync.stop()
        except Exception:
            pass
        if getattr(net.notifier, "exception", None) is not None:   # (a read reported it; canopen's disconnect()
            net.notifier.exception = None                           # would log it at ERROR, and raise it)
        try:
            net.disconnect()
        except Exception:
            pass

    def _release_host_watch(self) -> bool:
        """Turn the drive's consumer heartbeat time 0x1016 entry that watched the host (``_host_sub``) off (0) at an
        orderly close, before the host's heartbeat stops; whether it was taken. A drive that does not take it is said
        in the log: it will act per abort_connection_option once the heartbeat has stopped for
        host_heartbeat_timeout."""
        node, sub = getattr(self, "node", None), getattr(self, "_host_sub", None)
        if node is None or sub is None:
            return False
        try:
            node.sdo.download(0x1016, sub, bytes(4))
            self.host_watch_released = True
            return True
        except Exception as exc:   # (a drive gone, an SDO abort: the drive's reaction comes, after the hold)
            p = self.params
            self.ctx.log(f"{self._where()}: its watch of the host (0x1016 sub {sub}) could not be turned off at close "
                         f"({exc}): with the heartbeat stopped, it acts per abort_connection_option "
                         f"{p.abort_connection_option} ({ABORT_OPTIONS.get(p.abort_connection_option, 'its own')}) "
                         f"in {p.host_timeout:g} s")
            return False

    def _finish_open(self) -> None:
        """safe_mode ``open``: the safe state sent max_opening, and the drive stops (quick stop) once the host
        heartbeat ends: the state is read (SYNC) until the drive has the set-point (statusword bit 12) and reports the
        target reached (bit 10), for the travel time at max_speed with a margin (at most OPEN_FINISH_MAX); a drive
        not in OPERATION ENABLED, or without a state for read_timeout (gone), ends the wait. ``hold`` sends the
        measured opening: nothing to wait for."""
        p = self.params
        counts = self.map.counts(p.max_opening)
        if p.safe_mode != "open" or not getattr(self, "_safe", False) or counts not in (self._raised, self._target):
            return
        r = getattr(self, "_last_reading", None)
        travel = p.max_opening - p.min_opening if r is None else abs(p.max_opening - r.opening)
        start = good = time.monotonic()
        deadline = start + min(1.5 * travel / p.max_speed + 0.25, OPEN_FINISH_MAX)
        while (now := time.monotonic()) < deadline and now - good < p.read_timeout:
            try:
                r = self._hw_read()
            except Exception:   # (left OPERATION ENABLED, a fault, a lost drive: nothing to wait for)
                return
            if r is not None:
                if self.tp1[0x6041].raw & 0x1400 == 0x1400:
                    return
                good = time.monotonic()
            time.sleep(OPEN_FINISH_POLL)

    def status(self) -> dict[str, Any]:
        d = super().status()
        d["emcy"] = len(getattr(self, "emcys", []))
        rx = getattr(self, "_rx", None)
        d["receive_errors"] = 0 if rx is None else rx.count   # failed receives (python-can's recv() raised)
        return d



#: SDO abort codes that say the object is not there: object does not exist in the OD, sub-index does not exist
NO_SUCH_OBJECT = (0x06020000, 0x06090011)
#: NMT states (in a heartbeat) a drive goes to when its consumer heartbeat time runs out, per its error behaviour
#: 0x1029 sub 1 (communication error): PRE-OPERATIONAL (127, CiA 301's default) or STOPPED (4)
NMT_HOST_LOSS_STATES = (127, 4)


def consumer_missing(sub: int) -> str:
    """What a drive without consumer heartbeat time 0x1016 (sub ``sub``) lacks, for the start-up's error."""
    return (f"no consumer heartbeat time 0x1016 sub {sub}: it cannot watch the host's heartbeat, and would keep going "
            f"(enabled, on its last set-point) if this computer died or hung. Set host_heartbeat_period: 0 to run it "
            f"without that watch")


def consumer_text(value: int) -> str:
    """An entry of consumer heartbeat time 0x1016 in words ("watches node 3 (500 ms)"); one without a node id or a
    time is off."""
    node, ms = value >> 16 & 0xFF, value & 0xFFFF
    if node and ms:
        return f"watches node {node} ({ms} ms)"
    return f"= 0x{value:08X} (" + (f"node {node}, time 0: off" if node else "no node id: off") + ")"


def _whole_ms(name: str, seconds: float, what: str, expected: str, most: int) -> None:
    """A ValueError naming ``name`` unless ``seconds`` is a whole number of milliseconds in 1..``most``."""
    ms = seconds * 1000
    if not 1 <= round(ms) <= most or abs(ms - round(ms)) > 1e-6:
        raise ValueError(f"{name} {seconds:g} s does not fit {what}: give {expected}")

#: the factor a ``velocity_unit`` may have (beyond: a typo; 1e400 overflowed at start-up, 1e-400 read every velocity 0)
VELOCITY_FACTOR_RANGE = (Fraction(1, 10 ** 9), Fraction(10 ** 9))


def parse_velocity_unit(text: str) -> tuple[str, Fraction]:
    """A ``velocity_unit`` param ('0.001 rpm', 'counts/s'): ("counts" or "rev", the factor per second)."""
    import re

    m = re.fullmatch(r"\s*(?:(\S+?)\s*)?(counts/s|rev/s|rpm)\s*", text)
    factor = None
    if m:
        try:
            factor = Fraction(m.group(1) or "1")
        except (ValueError, ZeroDivisionError, OverflowError):   # "x", "1/0", "inf"
            factor = None
    if factor is not None and factor > 0 and not VELOCITY_FACTOR_RANGE[0] <= factor <= VELOCITY_FACTOR_RANGE[1]:
        raise ValueError(f"velocity_unit {text!r}: the factor {m.group(1)} is outside 1e-9..1e9, which no drive's "
                         f"velocity unit has (a typo?)")
    if not m or factor is None or factor <= 0:
        raise ValueError(f"velocity_unit {text!r} is not a velocity unit the driver converts: give 'rpm', 'rev/s' or "
                         f"'counts/s' (position counts 0x6064 per second), with a positive factor if the drive's unit "
                         f"has one ('0.001 rpm', '0.1 counts/s')")
    kind, seconds = VELOCITY_UNITS[m.group(2)]
    return kind, factor / seconds


def _power_of_ten(exponent: int) -> str:
    return str(10 ** exponent) if exponent >= 0 else "0." + "0" * (-exponent - 1) + "1"


def _exponent(code: int) -> int:
    """The power of ten in bits 24-31 of an SI unit object (signed)."""
    return int.from_bytes(bytes([code >> 24 & 0xFF]), "little", signed=True)


def velocity_unit_text(code: int) -> str:
    """SI unit velocity 0x60A9 in words: 0xFDB44700 -> "0.001 rpm", 0xFD010300 -> "0.001 m/s"."""
    position, time_ = code >> 16 & 0xFF, code >> 8 & 0xFF
    if (position, time_) == (REVOLUTION, MINUTE):
        unit = "rpm"
    else:
        unit = (f"{POSITION_UNITS.get(position, f'unit 0x{position:02X}')}/"
                f"{TIME_UNITS.get(time_, f'unit 0x{time_:02X}')}")
    return f"{_power_of_ten(_exponent(code))} {unit}" if _exponent(code) else unit


def si_velocity_unit(code: int) -> tuple[str, Fraction] | None:
    """SI unit velocity 0x60A9 as ("rev", the factor per second) for revolutions per second or minute with a power of
    ten; None for any other unit (a linear or angular one the driver cannot relate to the counts)."""
    seconds = {SECOND: 1, MINUTE: 60}.get(code >> 8 & 0xFF)
    if code >> 16 & 0xFF != REVOLUTION or seconds is None:
        return None
    return "rev", Fraction(10) ** _exponent(code) / seconds


def mode_text(mode: int) -> str:
    """A CiA 402 mode of operation with its name: "1 (profile position)"."""
    name = MODE_NAMES.get(mode, "manufacturer-specific" if mode < 0 else "reserved")
    return f"{mode} ({name})"


@hookimpl
def teletouch_components():
    return [CanopenGripper]


IFF_UP = 0x1   # the administrative "up" bit of a network interface's flags (sysfs ``flags``, linux/if.h)
SOCKETCAN_MISSING = ("no SocketCAN in this kernel (or container): load it with 'sudo modprobe can can_raw' (on the "
                     "host: a container cannot load kernel modules, and needs the interface in its network, e.g. "
                     "docker run --network host)")


def up_command(name: str, virtual: bool, bitrate: int = 1000000) -> str:
    """The command that brings a CAN interface up: a virtual one (vcan, slcan: no ``device`` in sysfs) has no bit rate
    to set."""
    if virtual:
        return f"sudo ip link set {name} up"
    return f"sudo ip link set {name} up type can bitrate {bitrate}"


#: what python-can's interface for an adapter needs installed besides python-can, and a channel as it names one
ADAPTER_NEEDS = {
    "pcan": ("PEAK-System's PCAN-Basic library (libpcanbasic) and the adapter's driver", "PCAN_USBBUS1"),
    "kvaser": ("Kvaser's CANlib (on Linux: Kvaser's linuxcan driver package)", "0"),
    "vector": ("Vector's XL Driver Library (vxlapi)", "0"),
    "ixxat": ("IXXAT's VCI driver", "0"),
    "neovi": ("the python-ics package", None),
    "gs_usb": ("the gs_usb package", None),
    "canalystii": ("the canalystii package", None),
    "slcan": ("pyserial", "/dev/ttyACM0, its serial port"),
    "serial": ("pyserial", "/dev/ttyUSB0, its serial port"),
}


def check_interface(name: str) -> None:
    """A ValueError unless ``name`` is an interface the installed python-can knows (its own and those of installed
    python-can plugins, ``can.interfaces.VALID_INTERFACES``), naming the closest ones."""
    import difflib

    import can
    from can.interfaces import VALID_INTERFACES

    if name in VALID_INTERFACES:
        return
    key = str(name).strip().lower()
    near = [key] if key in VALID_INTERFACES else difflib.get_close_matches(key, sorted(VALID_INTERFACES), 2, 0.6)
    hint = f" (did you mean {' or '.join(repr(n) for n in near)}?)" if near else ""
    others = ", ".join(sorted(VALID_INTERFACES - {"socketcan", "virtual"}))
    raise ValueError(f"interface {name!r} is not an interface python-can {can.__version__} knows{hint}: give "
                     f"socketcan (a Linux CAN network interface, the channel as `teletouch devices` lists it: can0), "
                     f"virtual (python-can's bus within this process, no adapter) or an adapter's own: {others}")


def open_failure_hint(exc: BaseException, interface: str, channel: str, bitrate: int) -> str:
    """What to do when python-can cannot open ``interface:channel``, from the interface and the error it raised:
    socketcan's from the kernel's errno (no SocketCAN, no such interface, else the command that brings it up); virtual
    needs nothing set up; an adapter's interface needs its vendor library or driver (:data:`ADAPTER_NEEDS`)."""
    if interface == "socketcan":
        code = getattr(exc, "errno", None) or getattr(exc.__cause__, "errno", None)
        if code == errno.EAFNOSUPPORT or "Address family not supported" in str(exc):
            return SOCKETCAN_MISSING
        if code == errno.ENODEV or "No such device" in str(exc):
            return (f"there is no network interface {channel}: plug in the CAN adapter (for a test without one: "
                    f"sudo modprobe vcan && sudo ip link add dev {channel} type vcan); `teletouch devices` lists "
                    f"the CAN interfaces")
        cmd = up_command(channel, channel.startswith("vcan"), bitrate)
        return (f"check the adapter and that the interface is up ({cmd}); `teletouch devices` lists the CAN "
                f"interfaces")
    if interface == "virtual":
        return ("python-can's virtual interface needs nothing installed or set up (no adapter, driver or bit rate; "
                "the channel is any name the nodes of this process share): the error above is python-can's own")
    needs, example = ADAPTER_NEEDS.get(interface, (f"the adapter maker's library or driver that python-can's "
                                                   f"{interface} interface loads (python-can's documentation of "
                                                   f"the interface names it)", None))
    channel_hint = f", with channel as that interface names the adapter (e.g. {example})" if example else ""
    return (f"python-can's {interface} interface needs {needs} installed and the adapter plugged in{channel_hint}; "
            f"python-can's words above say which is missing (`teletouch devices` lists SocketCAN interfaces only)")


def _errno_of(exc: BaseException, interface: str) -> int | None:
    """The OS error number behind a python-can error: an OSError's, its cause's, or (python-can's socketcan passes
    it on so) a CanError's ``error_code`` on socketcan (and the virtual bus, where tests emulate socketcan's)."""
    for e in (exc, exc.__cause__):
        code = getattr(e, "errno", None)
        if isinstance(code, int):
            return code
    code = getattr(exc, "error_code", None)
    return code if isinstance(code, int) and interface in ("socketcan", "virtual") else None


def bus_failure_hint(exc: BaseException, interface: str, channel: str, bitrate: int) -> str:
    """Why a frame could not go out or come in on an open bus (a CAN adapter unplugged mid-run: python-can's
    "Failed to transmit: No such device"), python-can's words, and what to check: ``ip link show`` on socketcan;
    replug; `teletouch devices`."""
    code, text = _errno_of(exc, interface), str(exc)
    if code in (errno.ENODEV, errno.ENXIO) or "No such device" in text:
        why = "the CAN adapter is gone (unplugged, or its USB connection reset)"
    elif code == errno.ENETDOWN or "Network is down" in text or "appears to be down" in text:
        why = ("the CAN interface went down (set down, or its controller went bus-off and was not restarted), or "
               "the adapter was unplugged")
    elif code == errno.ENOBUFS or "buffer" in text.lower():
        why = ("the transmit queue is full: no node acknowledges the frames (the drive unpowered or disconnected, a "
               "loose cable, no termination, a wrong bit rate), the controller is bus-off, or the adapter was "
               "unplugged")
    else:
        why = "the CAN adapter may have been unplugged or the interface went down"
    if interface == "socketcan":
        check = (f"check `ip link show {channel}` (\"does not exist\": replug the adapter; state DOWN: "
                 f"{up_command(channel, channel.startswith('vcan'), bitrate)}) and `teletouch devices`")
    else:
        check = ("replug the adapter and check that its driver sees it (`teletouch devices` lists SocketCAN "
                 "interfaces only)")
    return f"{why} ({type(exc).__name__}: {exc}); {check}"


class LogLines(logging.Handler):
    """In a ``with`` block, the messages of logger ``name``'s WARNING and ERROR records (and its children's), for an
    error message: python-can logs why a backend cannot work ("Kvaser canlib is unavailable.") when it imports it,
    and raises something else ("channel must be an integer", a NameError). While attached, logging's last-resort
    handler (which prints such records to stderr where nothing configured logging) leaves them alone: they are said
    in the error, or concern no one when nothing failed ("uptime library not available" at every pcan start).
    Handlers a program configured still get them."""

    def __init__(self, name: str):
        super().__init__(logging.WARNING)
        self.logger = logging.getLogger(name)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.lines.append(record.getMessage())
        except Exception:   # (a record whose message cannot be formatted: nothing to say)
            pass

    def __enter__(self) -> "LogLines":
        self.logger.addHandler(self)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.logger.removeHandler(self)


RECEIVE_RETRY = 0.1   # s python-can's receive thread waits after a second error in a row before it receives again


class ReceiveErrors:
    """A listener of the Notifier of canopen's Network (python-can's receive thread) that judges errors in receiving
    (python-can's ``recv()`` raising: a brief adapter error, an unplugged adapter's "Error receiving: No such device").
    Its ``on_error`` handles them, so python-can's thread goes on receiving (one that no listener handles ends the
    thread, its traceback on stderr). The error is taken from the Notifier (``exception``), where canopen's
    ``Network.check()`` would raise it from every later send (an SDO request, the SYNC, RPDO1) as if receiving had
    stopped, and kept here: failed receives in a row without a frame between them are a run, which the next frame (not
    an error frame) received ends: the bus works again. After the first error of a run the thread receives again at
    once, after each further one it waits ``RECEIVE_RETRY`` (until close(): a few tries a second, not a spin on a dead
    socket). The driver's reads take the runs that ended (:meth:`take`) to log them, and end the run on a receive
    failure that goes on (:meth:`failing`) within its bounds; ``count`` is the number of failed receives. ``thread``
    is python-can's receive thread (seen at its first frame or error), for :meth:`stopped`. It is one of the
    Network's ``listeners`` before ``connect()``, which starts the thread, and is given the Notifier after
    (:meth:`attach`)."""

    def __init__(self) -> None:
        self._notifier: Any = None
        self._last: BaseException | None = None   # the last error handled
        self._lock = threading.Lock()
        self.thread: threading.Thread | None = None
        self.count = 0
        #: the run no frame has ended yet: (monotonic time of its first error, its failed receives, the last error)
        self._failing: tuple[float, int, BaseException] | None = None
        #: runs that frames ended, not yet taken: (first error, first frame after the run, failed receives, last error)
        self._ended: list[tuple[float, float, int, BaseException]] = []

    def __call__(self, msg: Any) -> None:
        if self.thread is None:
            self.thread = threading.current_thread()
        if self._failing is not None and not msg.is_error_frame:
            with self._lock:
                if self._failing is not None:
                    first, n, exc = self._failing
                    self._ended.append((first, time.monotonic(), n, exc))
                    self._failing = None

    def attach(self, notifier: Any) -> None:
        """The Notifier connect() made (its thread started before it was known: an error it met is taken now)."""
        with self._lock:
            self._notifier, last = notifier, self._last
        if last is not None and notifier.exception is last:
            notifier.exception = None

    def on_error(self, exc: Exception) -> None:
        self.thread = threading.current_thread()
        with self._lock:
            self.count += 1
            self._last = exc
            again = self._failing is not None
            self._failing = (self._failing[0] if again else time.monotonic(),
                             self._failing[1] + 1 if again else 1, exc)
            notifier = self._notifier
        if notifier is not None and notifier.exception is exc:   # (set by python-can just before it called this)
            notifier.exception = None
        if again:
            time.sleep(RECEIVE_RETRY)

    def failing(self) -> tuple[float, int, BaseException] | None:
        """The receive failure no frame has ended yet: (monotonic time of its first error, failed receives, the last
        error), or None."""
        return self._failing

    def take(self) -> list[tuple[float, float, int, BaseException]]:
        """The runs of failed receives that frames ended since the last call: (first error, first frame after it,
        failed receives, last error) each."""
        with self._lock:
            ended, self._ended = self._ended, []
        return ended

    def stopped(self) -> bool:
        """Whether python-can's receive thread has ended while the Notifier runs (another listener's ``on_error``
        raised, or something other than an Exception did): nothing is received any more."""
        t, notifier = self.thread, self._notifier
        return t is not None and not t.is_alive() and notifier is not None and not notifier.stopped


def receiving_network(receive_errors: ReceiveErrors) -> Any:
    """A canopen Network whose ``check()`` (called after every send: an SDO request, the SYNC, RPDO1) leaves errors in
    receiving to the driver's :class:`ReceiveErrors` while python-can's receive thread lives: python-can sets the
    Notifier's ``exception`` just before that listener's ``on_error`` takes it, and a send in between raised the
    receive error as its own ("sending SYNC failed"; the safe state's hold not sent). A thread that has ended is
    canopen's check as before. (A subclass made here: canopen is imported only where a drive is opened.)"""
    import canopen

    class ReceivingNetwork(canopen.Network):
        def check(self) -> None:
            if receive_errors.thread is not None and not receive_errors.stopped():
                return   # (the driver's reads judge a receive failure that lasts: ReceiveErrors.failing)
            super().check()

    return ReceivingNetwork()


class HostHeartbeat:
    """The host's heartbeat producer: one frame (COB-ID ``cob_id``, NMT OPERATIONAL) every ``period`` through
    python-can's own periodic sending (``bus.send_periodic``): the kernel's broadcast manager on socketcan, an
    adapter's scheduler where python-can uses one, else python-can's thread, a ThreadBasedCyclicSendTask. That thread
    ends for good at its first failed send (a full transmit queue, a brief adapter error) unless it has an ``on_error``
    that says go on, which ``bus.send_periodic`` does not give it: the task is made unstarted, given one (and a
    ``modifier_callback``, which python-can calls before each send, to tell a send that went out from one that
    failed), then started. Failed sends are counted (python-can logs each); :meth:`failures` says for how long no
    heartbeat has gone out. ``stop()`` ends it (its ``on_error`` then says stop)."""

    def __init__(self, bus: Any, cob_id: int, period: float):
        import can
        from can.broadcastmanager import ThreadBasedCyclicSendTask

        self._lock = threading.Lock()
        self._stopped = False
        self._attempt: float | None = None   # (monotonic) when the latest send began
        self._attempt_failed = False   # ... and whether it failed
        self._failing = False   # whether the latest send that ended failed
        self.sent_at = time.monotonic()   # when the latest send known to have gone out began (at first: now)
        self.runs = 0   # runs of failed sends (one or more in a row)
        self.count = 0   # failed sends
        self.error: BaseException | None = None   # the last one's
        msg = can.Message(arbitration_id=cob_id, data=bytes([NMT_OPERATIONAL]), is_extended_id=False)
        self.task = bus.send_periodic(msg, period, autostart=False)
        #: python-can's thread (not the kernel's or an adapter's own sending, which no failed send ends)
        self.threaded = isinstance(self.task, ThreadBasedCyclicSendTask)
        if self.threaded:
            self.task.on_error = self._failed
            self.task.modifier_callback = self._sending
        try:
            self.task.start()
        except BaseException:
            self.stop()
            raise

    def _sending(self, msg: Any) -> None:
        """Before each send (python-can's thread): the send before went out unless it failed."""
        with self._lock:
            if self._attempt is not None and not self._attempt_failed:
                self.sent_at, self._failing = self._attempt, False
            self._attempt, self._attempt_failed = time.monotonic(), False

    def _failed(self, exc: Exception) -> bool:
        """A send failed (python-can's thread, after logging it): counted; whether to go on (until stop())."""
        with self._lock:
            if not self._failing:
                self.runs += 1
            self._attempt_failed = self._failing = True
            self.count += 1
            self.error = exc
            return not self._stopped

    def failures(self) -> tuple[float, int, BaseException | None]:
        """(for how long no heartbeat has gone out where the latest send that ended failed, else 0; the runs of
        failed sends so far; the last failed send's error or None). A send under way counts as going out: the
        silence is then the one up to its start."""
        with self._lock:
            if not self._failing:
                silent = 0.0
            elif self._attempt_failed or self._attempt is None:
                silent = time.monotonic() - self.sent_at
            else:
                silent = self._attempt - self.sent_at
            return silent, self.runs, self.error

    def stop(self) -> None:
        with self._lock:
            self._stopped = True
        self.task.stop()


def _read(path: str) -> str:
    try:
        with open(path) as fh:
            return fh.read().strip()
    except OSError:
        return ""


def can_interface_info(name: str, sysfs_root: str | None = None) -> dict[str, Any] | None:
    """A SocketCAN interface from sysfs: ``up`` (IFF_UP in ``flags``; from ``operstate`` when flags cannot be read;
    None: unknown), ``state`` (operstate: "unknown" on an up vcan, so not the up/down answer), ``virtual`` (no
    ``device`` link: vcan, slcan). None when ``name`` is no CAN interface there."""
    import os

    d = os.path.join(sysfs_root or os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys"), "class", "net", name)
    if _read(os.path.join(d, "type")) != "280":  # ARPHRD_CAN
        return None
    state = _read(os.path.join(d, "operstate")) or "unknown"
    try:
        up: bool | None = bool(int(_read(os.path.join(d, "flags")), 16) & IFF_UP)
    except ValueError:
        up = {"up": True, "down": False}.get(state)
    return {"up": up, "state": state, "virtual": not os.path.exists(os.path.join(d, "device"))}


def socketcan_available() -> str:
    """"" when this kernel (in this network namespace) can open SocketCAN sockets, else why not and what to do."""
    import socket

    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return "this Python has no socket.AF_CAN (SocketCAN needs Linux)"
    try:
        socket.socket(family, socket.SOCK_RAW, getattr(socket, "CAN_RAW", 1)).close()
    except OSError as exc:
        if exc.errno == 97:
            return f"socket(AF_CAN) failed ({exc}): {SOCKETCAN_MISSING}"
        return f"a SocketCAN socket cannot be opened ({exc})"
    return ""


def can_interfaces(sysfs_root: str | None = None, probe: Any = socketcan_available) -> list[dict[str, Any]]:
    """SocketCAN network interfaces (type 280 in sysfs), for `teletouch devices`: with the canopen-gripper params
    that select each, ``up``, and a ``problem`` when it cannot be used as it is (down: the command that brings it up;
    no SocketCAN in the kernel: the modules to load). ``probe`` says whether SocketCAN sockets can be opened here
    ("" when they can)."""
    import os

    root = os.path.join(sysfs_root or os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys"), "class", "net")
    found = []
    try:
        names = sorted(os.listdir(root))
    except OSError:
        return []
    missing: str | None = None
    for name in names:
        info = can_interface_info(name, sysfs_root)
        if info is None:
            continue
        details: dict[str, Any] = {"state": info["state"], "up": info["up"], "virtual": info["virtual"],
                                   "plugin": "canopen-gripper", "params": {"interface": "socketcan", "channel": name}}
        if missing is None:
            missing = probe()
        problems = [missing] if missing else []
        if info["up"] is False:
            problems.append(f"the interface is down: {up_command(name, info['virtual'])}"
                            + ("" if info["virtual"] else " (with the drive's bit rate: canopen-gripper's bitrate)"))
        if problems:
            details["problem"] = "; ".join(problems)
        found.append({"kind": "can", "id": name, "path": name, "details": details})
    return found


@hookimpl
def teletouch_discover_devices():
    return can_interfaces()
