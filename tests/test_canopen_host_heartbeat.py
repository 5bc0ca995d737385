"""canopen-gripper's host heartbeat: the drive watches the host (consumer heartbeat time 0x1016, abort connection option
code 0x6007) and stops when the host dies or hangs; the emulated drive (tests/fakes/canopen_drive.py) consumes the
heartbeat as a CiA 402 drive does."""

from __future__ import annotations

import re
import struct
import sys
import time
from pathlib import Path

import can
import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes.followers import canopen_harness, channel_fixture, drive_fixture  # noqa: E402
from fakes.realtime import WAIT, configure_fails, drive_until, wait_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices.canopen_gripper import CanopenGripper  # noqa: E402

pytestmark = pytest.mark.timeout(120)

channel = channel_fixture()
drive = drive_fixture(position=0)
harness = canopen_harness

HOST = 127   # host_node_id's default
#: how late the emulated drive's reaction may come after its consumer time on a loaded 2-core machine (a bound for a
#: failure; the reaction is never early, checked to 10 ms)
LATE = 0.25


class BusLog:
    """Every frame on the virtual ``channel`` (another node's view), stamped on arrival (monotonic)."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[tuple[float, int, bytes]] = []
        self.notifier = can.Notifier(self.bus, [self._on])

    def _on(self, msg: can.Message) -> None:
        self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def of(self, cob_id: int) -> list[tuple[float, bytes]]:
        return [(t, d) for t, i, d in list(self.frames) if i == cob_id]

    def sync(self) -> None:
        self.bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


@pytest.fixture
def buslog(channel):
    log = BusLog(channel)
    yield log
    log.close()


def hang(h) -> None:
    """The host hangs or dies: its heartbeat stops (the periodic task, not the driver's close()) and nothing steps."""
    h.comp._host_hb.stop()


class FailingSends:
    """The host's python-can ``bus`` raises python-can's error for a full transmit queue at the next ``n`` sends of
    the host heartbeat (None: at every one); ``failed`` lists when (monotonic)."""

    def __init__(self, bus: can.BusABC, n: int | None = 1):
        self.real, self.left, self.failed = bus.send, n, []
        bus.send = self.send

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == 0x700 + HOST and (self.left is None or self.left > 0):
            if self.left is not None:
                self.left -= 1
            self.failed.append(time.monotonic())
            raise can.CanOperationError("Transmit buffer full")
        return self.real(msg, timeout)


# --- the heartbeat and the objects ---------------------------------------------------------------------------------
def test_heartbeat_frames_at_the_period_with_the_nmt_state(drive, channel, buslog):
    with harness(channel, host_heartbeat_period=0.05):
        time.sleep(1.0)
        frames = buslog.of(0x700 + HOST)
    assert len(frames) >= 10
    assert {d for _, d in frames} == {b"\x05"}   # one byte: the host's NMT state, OPERATIONAL
    first, last = frames[0][0], frames[-1][0]
    assert (last - first) / (len(frames) - 1) == pytest.approx(0.05, rel=0.15)   # the mean period
    assert drive.consumer_heartbeats   # the drive received them (its consumer subscribed to 0x77F)


def test_another_host_node_id(drive, channel, buslog):
    with harness(channel, host_node_id=100, host_heartbeat_period="20 ms"):
        assert wait_for(lambda: len(buslog.of(0x764)) >= 3)
        assert drive.get(0x1016, 1) == 100 << 16 | 60   # None: three periods
    assert not buslog.of(0x700 + HOST)


def test_drive_objects_hold_the_written_values(drive, channel):
    with harness(channel):   # the defaults: 100 ms, consumer time three periods, quick stop
        assert drive.get(0x1016, 1) == HOST << 16 | 300
        assert drive.get(0x6007) == 3
    with harness(channel, host_node_id=42, host_heartbeat_period=0.05, host_heartbeat_timeout=0.25,
                 abort_connection_option=2):
        assert drive.get(0x1016, 1) == 42 << 16 | 250
        assert drive.get(0x6007) == 2
    drive.node.data_store[0x6007][0] = struct.pack("<h", -3)   # set with the drive's tool (manufacturer-specific)
    with harness(channel, abort_connection_option=None):   # not written: the drive's own
        assert drive.get(0x6007) == -3
        assert drive.get(0x1016, 1) == HOST << 16 | 300


def test_off_writes_nothing_and_sends_nothing(drive, channel, buslog):
    with harness(channel, host_heartbeat_period=0, node_id=5, host_node_id=5):   # off: host_node_id unchecked
        time.sleep(0.3)
        assert drive.get(0x1016, 1) == 0 and drive.get(0x6007) == 1   # the drive's defaults, untouched
        assert not [i for _, i, _ in buslog.frames if 0x701 <= i <= 0x77F and i != 0x705]


# --- the host dies or hangs ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("option, state", [(3, "QUICK STOP ACTIVE"), (2, "SWITCH ON DISABLED"), (1, "FAULT"),
                                           (0, "OPERATION ENABLED")])
def test_lost_host_stops_the_drive_per_0x6007(drive, channel, buslog, option, state):
    """The ``open`` safe state sets the fingers moving (75000 counts at 50000 counts/s: 1.5 s), then the host hangs:
    within the consumer time the drive reacts per 0x6007 and stands where it was then (quick stop, disable voltage,
    fault); with 0 (no action) it goes on to the set-point on its own, as every drive did before."""
    timeout = 0.2
    with harness(channel, safe_mode="open", max_speed=0.04, host_heartbeat_period=0.05,
                 host_heartbeat_timeout=timeout, abort_connection_option=option) as h:
        drive_until(h, 0.02, lambda o: drive.latched == 75000 and h.comp.handshake_idle())
        h.comp.safe_state()   # the open set-point (0 counts) goes out at once
        assert wait_for(lambda: drive.latched == 0)
        hang(h)
        stopped = time.monotonic()
        assert wait_for(lambda: drive.consumer_trips, timeout=timeout + WAIT)
        at, seen_option, before = drive.consumer_trips[0]
        last = drive.consumer_heartbeats[-1]
        assert last <= stopped + 0.01
        assert timeout - 0.01 <= at - last <= timeout + LATE   # not early, and within the consumer time
        assert (seen_option, before) == (option, "OPERATION ENABLED")
        assert drive.state == state
        pos = drive.pos
        if option == 0:   # no action: the drive finishes the move
            assert wait_for(lambda: (buslog.sync(), drive.pos)[1] == 0)
            return
        assert 1000 < pos < 75000 - 1000   # it had moved, and stopped part-way
        for _ in range(20):   # the drive's control goes on (SYNCs from another master): it stands still
            buslog.sync()
            time.sleep(0.01)
        assert drive.pos == pos and drive.state == state
        assert drive.get(0x6041) & 0x6F == {"QUICK STOP ACTIVE": 0x07, "SWITCH ON DISABLED": 0x40,
                                            "FAULT": 0x08}[state] & 0x6F
        emcys = [d for _, d in buslog.of(0x85)]
        if option == 1:
            assert drive.get(0x603F) == 0x8130
            assert emcys and struct.unpack_from("<H", emcys[-1])[0] == 0x8130   # heartbeat/life guard error
            assert wait_for(lambda: any(e.code == 0x8130 for e in h.comp.emcys))
            with pytest.raises(HardwareError, match=r"is in FAULT .*error code 0x8130"):
                h.step(time.monotonic(), opening_command=0.02)
        else:
            assert not emcys and drive.get(0x603F) == 0
            with pytest.raises(HardwareError, match=r"left OPERATION ENABLED .*host_heartbeat_timeout 0.2 s"):
                h.step(time.monotonic(), opening_command=0.02)


def test_the_drive_watches_the_host_from_the_start(drive, channel):
    """A host that dies right after the start-up is caught: a CiA 301 consumer starts watching at the first heartbeat
    after 0x1016 was written, and the driver sends one then (the periodic one came a period later: a second here)."""
    with harness(channel, host_heartbeat_period=1.0, host_heartbeat_timeout=2.0) as h:
        hang(h)
        assert drive.consumer_heartbeats   # (one, or two where the start-up took over a second)
        assert wait_for(lambda: drive.state == "QUICK STOP ACTIVE", timeout=2.0 + WAIT)
        assert 2.0 - 0.01 <= drive.consumer_trips[0][0] - drive.consumer_heartbeats[-1] <= 2.0 + LATE


def test_the_heartbeat_goes_on_through_a_failed_send(drive, channel, buslog):
    """python-can's thread-based periodic task ended at its first failed send (a full transmit queue) and a read
    started it again; now it goes on sending by itself (the same task), and the failure is logged once."""
    with harness(channel, host_heartbeat_period=0.05) as h:
        logs = []
        h.ctx._log = logs.append
        task = h.comp._host_hb
        failing = FailingSends(h.comp.network.bus)
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            h.step(time.monotonic(), opening_command=0.07)
            time.sleep(0.005)
        assert failing.failed and h.comp._host_hb is task
        said = [m for m in logs if "host heartbeat" in m]
        assert len(said) == 1 and re.search(r"sending the host heartbeat to CANopen node 5 on virtual:\S+ failed "
                                            r"\(CanOperationError: Transmit buffer full\): it goes on", said[0]), said
        assert [t for t, _ in buslog.of(0x700 + HOST) if t > failing.failed[0] + 0.2]   # it goes on
        assert not drive.consumer_trips and drive.state == "OPERATION ENABLED"


def test_a_failed_send_while_inactive_does_not_trip_the_drive(drive, channel, buslog):
    """Deactivated, nothing reads (the reads restarted the task that a failed send ended): a failed send then stopped
    the heartbeat for good, the drive quick-stopped one consumer time later, and activate() found it out of OPERATION
    ENABLED. The heartbeat now goes on through the failed send: the drive holds, watched, and activates again."""
    with harness(channel, host_heartbeat_period=0.05, host_heartbeat_timeout=0.15) as h:
        drive_until(h, 0.06, lambda o: drive.latched == 25000 and h.comp.handshake_idle())
        h.comp.safe_state()
        h.comp.deactivate()
        failing = FailingSends(h.comp.network.bus)
        assert wait_for(lambda: failing.failed)
        time.sleep(0.6)   # four consumer times
        assert [t for t, _ in buslog.of(0x700 + HOST) if t > failing.failed[0]]
        assert not drive.consumer_trips and drive.state == "OPERATION ENABLED"
        h.comp.activate()
        drive_until(h, 0.04, lambda o: drive.latched == 50000)
        assert drive.latched == 50000


def test_a_heartbeat_that_cannot_be_sent_is_reported(drive, channel, buslog):
    """A heartbeat whose sends all fail (an adapter that takes no frames) is not hidden by the retries: once none has
    gone out for longer than the drive's consumer time, the step's read is a HardwareError naming the drive, the
    interface, python-can's error and what to check (before, each read started python-can's task again, which ended
    at its next send, and nothing was said). With 0x6007 = 0 the drive does not react: the heartbeat is the one
    sign."""
    with harness(channel, host_heartbeat_period=0.05, host_heartbeat_timeout=0.15, abort_connection_option=0) as h:
        drive_until(h, 0.06, lambda o: drive.latched == 25000)
        failing = FailingSends(h.comp.network.bus, n=None)
        with pytest.raises(HardwareError, match=r"CANopen node 5 on virtual:\S+: sending the host heartbeat \(COB-ID "
                                                r"0x77F; none went out for 0\.\d+ s, longer than "
                                                r"host_heartbeat_timeout 0.15 s: the drive acts per "
                                                r"abort_connection_option 0, no action\) failed: .*"
                                                r"\(CanOperationError: Transmit buffer full\); replug"):
            drive_until(h, 0.06, lambda o: False, timeout=WAIT)
        raised = time.monotonic()
        last = [t for t, _ in buslog.of(0x700 + HOST) if t < failing.failed[0]][-1]
        assert 0.15 - 0.01 <= raised - last <= 0.15 + LATE   # when the drive would act, not before
        assert drive.state == "OPERATION ENABLED"


def test_a_heartbeat_that_cannot_be_sent_while_inactive_is_named_at_activate(drive, channel):
    """The same while the node is inactive: the drive quick-stops (0x6007 = 3), and activate() names the heartbeat
    that could not be sent, the cause, rather than only the drive that left OPERATION ENABLED."""
    with harness(channel, host_heartbeat_period=0.05, host_heartbeat_timeout=0.15) as h:
        drive_until(h, 0.06, lambda o: drive.latched == 25000 and h.comp.handshake_idle())
        h.comp.safe_state()
        h.comp.deactivate()
        FailingSends(h.comp.network.bus, n=None)
        assert wait_for(lambda: drive.consumer_trips)
        with pytest.raises(HardwareError, match=r"CANopen node 5 on virtual:\S+: sending the host heartbeat .*none "
                                                r"went out .*longer than host_heartbeat_timeout 0.15 s: the drive "
                                                r"acts per abort_connection_option 3, quick stop"):
            h.comp.activate()


def test_a_drive_sent_to_pre_operational_by_a_lost_heartbeat_names_it(channel, buslog):
    """Under CiA 301's default error behaviour 0x1029 (0), a consumer heartbeat timeout also takes the drive to NMT
    PRE-OPERATIONAL (its heartbeat says so): the error names the missed host heartbeat next to the other causes."""
    with Cia402Drive(5, channel, position=0, error_behaviour=0) as d:
        with harness(channel, host_heartbeat_period=0.05, host_heartbeat_timeout=0.2) as h:
            drive_until(h, 0.06, lambda o: d.latched == 25000)
            hang(h)
            assert wait_for(lambda: d.consumer_trips and d.node.nmt.state == "PRE-OPERATIONAL")
            tripped = d.consumer_trips[0][0]
            assert wait_for(lambda: [f for t, f in buslog.of(0x705) if t > tripped and f == b"\x7f"])
            with pytest.raises(HardwareError, match=r"CANopen node 5 on virtual:\S+ left NMT OPERATIONAL \(heartbeat: "
                                                    r"PRE-OPERATIONAL\): it sends and takes no PDOs; likely it missed "
                                                    r"the host's heartbeat .*0x1029.*host_heartbeat_timeout 0.2 s "
                                                    r"\(sent every host_heartbeat_period 0.05 s\), with this process "
                                                    r"stalled or its CAN interface busy or lost; or the drive was "
                                                    r"reset \(power, watchdog\), or another master changed its NMT "
                                                    r"state$"):
                h.step(time.monotonic(), opening_command=0.06)


def test_without_the_host_heartbeat_pre_operational_names_the_other_causes(channel):
    with Cia402Drive(5, channel, position=0) as d:
        with harness(channel, host_heartbeat_period=0, heartbeat_period=0.02) as h:
            drive_until(h, 0.06, lambda o: d.latched == 25000)
            d.node.nmt.state = "PRE-OPERATIONAL"
            with pytest.raises(HardwareError, match=r"left NMT OPERATIONAL \(heartbeat: PRE-OPERATIONAL\): it sends "
                                                    r"and takes no PDOs; the drive was reset \(power, watchdog\) or "
                                                    r"another master changed its NMT state$"):
                drive_until(h, 0.06, lambda o: False, timeout=WAIT)


# --- orderly stops -------------------------------------------------------------------------------------------------
def test_deactivate_keeps_the_heartbeat(drive, channel):
    """An orderly deactivate does not stop the heartbeat: the driver still holds the drive, which holds the safe
    state's set-point, supervised; it faults nothing (even with 0x6007 = 1, fault) and activates again."""
    with harness(channel, host_heartbeat_period=0.05, host_heartbeat_timeout=0.15, abort_connection_option=1) as h:
        drive_until(h, 0.06, lambda o: drive.latched == 25000 and h.comp.handshake_idle())
        h.comp.safe_state()
        h.comp.deactivate()
        n = len(drive.consumer_heartbeats)
        time.sleep(0.6)   # four consumer times
        assert len(drive.consumer_heartbeats) >= n + 6
        assert not drive.consumer_trips
        assert drive.state == "OPERATION ENABLED" and drive.get(0x603F) == 0
        h.comp.activate()
        drive_until(h, 0.04, lambda o: drive.latched == 50000)
        assert drive.latched == 50000


def test_an_orderly_close_turns_the_drives_watch_off_and_it_keeps_holding(drive, channel, buslog):
    """close() turns the drive's consumer heartbeat time off (0x1016 sub 1 = 0) before the heartbeat stops, after the
    safe state's hold went out: the drive keeps holding, powered, in OPERATION ENABLED (its quick stop after every
    run ended, under CiA 402's default 0x605A 2, in SWITCH ON DISABLED: a gripper holding an object let go)."""
    with harness(channel) as h:
        drive_until(h, 0.05, lambda o: drive.latched == 37500 and h.comp.handshake_idle()
                    and o["opening"] == pytest.approx(0.05, abs=1e-6))
        hold = round(drive.pos)
    assert h.comp.host_watch_released
    rpdos = buslog.of(0x205)
    assert struct.unpack_from("<i", rpdos[-1][1])[0] == hold == 37500   # the last RPDO1 was the hold
    assert drive.get(0x1016, 1) == 0
    time.sleep(0.3 + LATE)   # one consumer time and more after the last heartbeat
    assert not drive.consumer_trips
    assert drive.state == "OPERATION ENABLED" and round(drive.pos) == hold


def test_a_close_whose_release_fails_sends_the_hold_before_the_heartbeat_ends(drive, channel, buslog):
    """A drive that does not take the release: close() stops the heartbeat after the safe state's hold set-point
    went out (and says so in the log); the drive then quick-stops (0x6007 = 3, the default) one consumer time later,
    where it holds: no fault, no EMCY."""
    from canopen.sdo.exceptions import SdoAbortedError

    with harness(channel) as h:
        lines: list[str] = []
        h.ctx.log = lines.append
        drive_until(h, 0.05, lambda o: drive.latched == 37500 and h.comp.handshake_idle()
                    and o["opening"] == pytest.approx(0.05, abs=1e-6))
        hold = round(drive.pos)
        download = h.comp.node.sdo.download

        def refuse(index, sub, data, *args, **kwargs):
            if index == 0x1016:
                raise SdoAbortedError(0x08000020)   # data cannot be transferred or stored
            return download(index, sub, data, *args, **kwargs)

        h.comp.node.sdo.download = refuse
    closed = time.monotonic()
    assert any("could not be turned off at close" in m and "abort_connection_option 3" in m for m in lines), lines
    rpdos = buslog.of(0x205)
    beats = buslog.of(0x700 + HOST)
    assert rpdos and beats and beats[-1][0] <= closed
    assert struct.unpack_from("<i", rpdos[-1][1])[0] == hold == 37500   # the last RPDO1 was the hold
    # ... and went out while the heartbeat still ran: it stopped after, before its next frame (a period later)
    assert rpdos[-1][0] < beats[-1][0] + 0.1
    assert wait_for(lambda: drive.consumer_trips)
    at = drive.consumer_trips[0][0]
    assert 0.3 - 0.01 <= at - drive.consumer_heartbeats[-1] <= 0.3 + LATE
    assert drive.state == "QUICK STOP ACTIVE" and round(drive.pos) == hold
    assert drive.get(0x603F) == 0 and not buslog.of(0x85)


def test_close_with_safe_mode_open_waits_for_the_fingers(drive, channel):
    """safe_mode ``open``: close() waits, the drive still watched, until it reports the open set-point reached
    (75000 counts at 50000 counts/s: 1.5 s, five consumer times), then turns the watch off: the drive holds there."""
    with harness(channel, safe_mode="open", max_speed=0.04) as h:
        drive_until(h, 0.02, lambda o: drive.latched == 75000 and h.comp.handshake_idle())
    assert drive.pos == pytest.approx(0, abs=1)
    time.sleep(0.3 + LATE)
    assert not drive.consumer_trips and drive.state == "OPERATION ENABLED" and drive.pos == pytest.approx(0, abs=1)


def test_a_host_node_id_another_node_produces_is_refused(drive, channel):
    """Two grippers on one bus with the default host_node_id: each drive took the other driver's heartbeat for its
    host's, so a drive whose process died kept going (the review: drive 5 still enabled after five consumer times,
    fed by drive 6's host). The second driver finds the id in use at start-up and is refused, naming host_node_id."""
    other = Cia402Drive(6, channel, position=0).start()
    try:
        with harness(channel) as h5:
            drive_until(h5, 0.05, lambda o: drive.latched == 37500)
            h6 = canopen_harness(channel, node_id=6)
            configure_fails(h6, r"another node sends heartbeats as node 127 \(COB-ID 0x77F\).*own host_node_id")
            with canopen_harness(channel, node_id=6, host_node_id=126) as h6:   # its own id: taken
                drive_until(h6, 0.05, lambda o: other.latched == 37500)
                assert other.get(0x1016, 1) == 126 << 16 | 300
    finally:
        other.stop()


# --- 0x1016's entries ------------------------------------------------------------------------------------------------
OTHER = 3 << 16 | 500   # another master's entry: node 3, 500 ms


def test_another_masters_entry_is_kept(channel):
    """0x1016 sub 1 watches another master: the driver takes the free sub 2 (it replaced sub 1), the drive watches
    the host there, and close() clears sub 2 only."""
    with Cia402Drive(5, channel, position=0, consumers=(OTHER, 0)) as d:
        with harness(channel) as h:
            assert (d.get(0x1016, 1), d.get(0x1016, 2)) == (OTHER, HOST << 16 | 300)
        assert (d.get(0x1016, 1), d.get(0x1016, 2)) == (OTHER, 0)
        with harness(channel, host_heartbeat_timeout=0.2) as h:
            hang(h)
            assert wait_for(lambda: d.state == "QUICK STOP ACTIVE")   # watched through sub 2
            assert d.get(0x1016, 1) == OTHER


def test_an_entry_holding_the_host_id_is_used(channel):
    """An entry for the host's node id already there (a run whose close could not clear it, set with the drive's
    tool): the driver writes that one (sub 1 for the same node, with a time, the drive refused: SDO abort
    0x06040043), and close() clears it."""
    with Cia402Drive(5, channel, position=0, consumers=(0, HOST << 16 | 1000, 0)) as d:
        with harness(channel):
            assert [d.get(0x1016, sub) for sub in (1, 2, 3)] == [0, HOST << 16 | 300, 0]
        assert [d.get(0x1016, sub) for sub in (1, 2, 3)] == [0, 0, 0]


def test_no_free_entry_is_refused_naming_the_entries(channel, buslog):
    with Cia402Drive(5, channel, position=0, consumers=(OTHER, 4 << 16)) as d:
        configure_fails(harness(channel), r"CANopen node 5 on virtual:\S+ has no free entry in its consumer heartbeat "
                                          r"time 0x1016 for the host's heartbeat \(node 127\); its 2 entries: sub 1 "
                                          r"watches node 3 \(500 ms\); sub 2 = 0x00040000 \(node 4, time 0: off\)\. "
                                          r".*free one .*host_node_id .*host_heartbeat_period: 0")
        assert (d.get(0x1016, 1), d.get(0x1016, 2)) == (OTHER, 4 << 16)
        assert not buslog.of(0x700 + HOST)   # no heartbeat started


def test_the_emulated_drive_refuses_a_second_entry_for_a_node(channel):
    """CiA 301: two entries of 0x1016 for one node id, both with a time, are refused (SDO abort 0x06040043)."""
    import canopen
    from canopen.sdo.exceptions import SdoAbortedError

    with Cia402Drive(5, channel, consumers=(OTHER, 0, 0)) as d:
        net = canopen.Network()
        net.connect(interface="virtual", channel=channel)
        try:
            sdo = net.add_node(5, canopen.ObjectDictionary()).sdo
            with pytest.raises(SdoAbortedError) as ei:
                sdo.download(0x1016, 2, struct.pack("<I", 3 << 16 | 300))
            assert ei.value.code == 0x06040043 and d.get(0x1016, 2) == 0
            sdo.download(0x1016, 2, struct.pack("<I", 3 << 16))   # no time: off, taken
            sdo.download(0x1016, 3, struct.pack("<I", 4 << 16 | 300))
            assert [d.get(0x1016, sub) for sub in (1, 2, 3)] == [OTHER, 3 << 16, 4 << 16 | 300]
            assert sdo.upload(0x1016, 0) == b"\x03"
        finally:
            net.disconnect()


# --- drives without the objects ------------------------------------------------------------------------------------
def test_drive_without_0x1016(channel, buslog):
    with Cia402Drive(5, channel, consumer_object=False) as d:
        configure_fails(harness(channel), r"CANopen node 5 on virtual:\S+ has no consumer heartbeat time 0x1016 sub 1"
                                          r".*host_heartbeat_period: 0 .*SDO abort")
        t = time.monotonic()
        time.sleep(0.3)
        assert not [f for f in buslog.of(0x700 + HOST) if f[0] > t]   # the failed start-up stopped the heartbeat
        with harness(channel, host_heartbeat_period=0):
            assert d.state == "OPERATION ENABLED"


def test_drive_without_0x6007(channel):
    with Cia402Drive(5, channel, abort_option_object=False) as d:
        configure_fails(harness(channel), r"has no abort connection option code 0x6007: .*abort_connection_option: "
                                          r"null .*host_heartbeat_period: 0")
        with harness(channel, abort_connection_option=None, host_heartbeat_timeout=0.2) as h:
            assert d.get(0x1016, 1) == HOST << 16 | 200
            hang(h)
            # the drive's own reaction (here CiA 402's default, a fault)
            assert wait_for(lambda: d.state == "FAULT")
            with pytest.raises(HardwareError, match=r"is in FAULT .*0x8130"):
                h.step(time.monotonic(), opening_command=0.07)


# --- params --------------------------------------------------------------------------------------------------------
def test_defaults():
    p = CanopenGripper.Params()
    assert (p.host_heartbeat_period, p.host_heartbeat_timeout, p.host_timeout) == (0.1, None, pytest.approx(0.3))
    assert (p.host_node_id, p.abort_connection_option) == (127, 3)
    assert CanopenGripper.Params(host_heartbeat_period="50ms").host_timeout == pytest.approx(0.15)


@pytest.mark.parametrize("params, match", [
    ({"host_heartbeat_period": 0.0005}, r"host_heartbeat_period 0.0005 s does not fit .*whole milliseconds"),
    ({"host_heartbeat_period": 0.0505}, r"host_heartbeat_period 0.0505 s does not fit"),
    ({"host_heartbeat_period": 40}, r"host_heartbeat_period 40 s does not fit .*0.001-32.767 s"),
    ({"host_heartbeat_period": -1}, r"host_heartbeat_period\n.*greater than or equal to 0"),
    ({"host_heartbeat_timeout": 0.15}, r"host_heartbeat_timeout 0.15 s is less than twice host_heartbeat_period "
                                       r"0.1 s.*at least 0.2 s"),
    ({"host_heartbeat_timeout": 0.2505}, r"host_heartbeat_timeout 0.2505 s does not fit .*0x1016"),
    ({"host_heartbeat_timeout": 70}, r"host_heartbeat_timeout 70 s does not fit .*0x1016"),
    ({"host_heartbeat_period": 30}, r"host_heartbeat_timeout None is 3 x host_heartbeat_period = 90 s"),
    ({"host_node_id": 5, "node_id": 5}, r"host_node_id 5 is the drive's node_id"),
    ({"host_node_id": 128}, r"host_node_id\n.*less than or equal to 127"),
    ({"host_node_id": 0}, r"host_node_id\n.*greater than or equal to 1"),
    ({"abort_connection_option": 4}, r"abort_connection_option 4 is no CiA 402 abort connection option code 0x6007"
                                     r".*3 \(quick stop\) or null"),
    ({"abort_connection_option": -1}, r"abort_connection_option -1 is no CiA 402"),
])
def test_bad_params_are_refused(params, match):
    with pytest.raises(ValidationError, match=match):
        CanopenGripper.Params(**params)


def test_good_params_are_taken():
    p = CanopenGripper.Params(host_heartbeat_period=0.02, host_heartbeat_timeout=0.04, host_node_id=1, node_id=2,
                              abort_connection_option=0)
    assert (p.host_timeout, p.host_node_id, p.abort_connection_option) == (0.04, 1, 0)
    assert CanopenGripper.Params(host_heartbeat_period=32.767, host_heartbeat_timeout=65.535).host_timeout == 65.535
    assert CanopenGripper.Params(host_heartbeat_period=0, host_heartbeat_timeout=0.5).host_heartbeat_period == 0
