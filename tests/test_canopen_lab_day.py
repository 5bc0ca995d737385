"""canopen-gripper, what a lab set-up audit found: a CAN adapter lost mid-run (python-can's "Failed to transmit: No such
device" from the step's SYNC or RPDO1, or its receive thread stopped) faulted the node with python-can's bare error,
naming no drive, interface or channel; `interface: socketcann` passed validation, and every interface's start-up
failure got SocketCAN advice (pcan, kvaser); python-can's log lines ("Kvaser canlib is unavailable.") came on stderr
beside teletouch's own report.

The adapter is pulled at the bus boundary: the host's python-can bus (a VirtualBus; the emulated drive keeps its own,
powered) raises what python-can's socketcan raises for a vanished interface, CanOperationError with errno 19 (ENODEV),
from send and receive, until it is plugged in again."""

from __future__ import annotations

import contextlib
import errno
import logging
import sys
import threading
import time
from pathlib import Path

import can
import canopen
import pytest
from can.interfaces.virtual import VirtualBus
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.followers import canopen_harness as harness, channel_fixture, drive_fixture  # noqa: E402
from fakes.realtime import drive_until, step_until_raises, thread_exceptions, wait_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices.canopen_gripper import CanopenGripper  # noqa: E402
from teletouch.testing import Harness  # noqa: E402

pytestmark = pytest.mark.timeout(60)

channel = channel_fixture()
drive = drive_fixture(position=0)

ENODEV_SEND = "Failed to transmit: No such device"   # python-can's socketcan, an interface that vanished
ENODEV_RECV = "Error receiving: No such device"


class Unplug:
    """The host's CAN adapter, pulled and plugged in again: while pulled, ``send`` (``sends``) and receiving
    (``receives``) on the host's ``bus`` raise CanOperationError with errno 19, as python-can's socketcan does."""

    def __init__(self, bus: can.BusABC, sends: bool = True, receives: bool = True):
        self.bus, self.sends, self.receives = bus, sends, receives
        self.pulled = False
        self.failed: list[int] = []   # arbitration ids of the frames that did not go out
        self._send, self._recv = bus.send, bus._recv_internal
        bus.send, bus._recv_internal = self.send, self.recv

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.pulled and self.sends:
            self.failed.append(msg.arbitration_id)
            raise can.CanOperationError(ENODEV_SEND, errno.ENODEV)
        return self._send(msg, timeout)

    def recv(self, timeout: float | None):
        if self.pulled and self.receives:
            time.sleep(min(timeout or 0.01, 0.01))
            raise can.CanOperationError(ENODEV_RECV, errno.ENODEV)
        return self._recv(timeout)




def lost_adapter(exc: BaseException, channel: str, what: str) -> None:
    """``exc`` is the driver's HardwareError for an adapter lost while ``what``: it names the drive and the bus, says
    the adapter is gone and what to check, and comes from python-can's error."""
    assert isinstance(exc, HardwareError), repr(exc)
    msg = str(exc)
    assert f"CANopen node 5 on virtual:{channel}: {what}" in msg, msg
    assert "CAN adapter is gone (unplugged" in msg and "No such device" in msg and "replug the adapter" in msg, msg
    assert isinstance(exc.__cause__, can.CanOperationError) and exc.__cause__.error_code == errno.ENODEV


# ------------------------------------------------------------------------------------------------ the lost adapter
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")   # python-can's heartbeat task
def test_an_adapter_lost_mid_run_ends_the_step_naming_the_drive_and_the_bus(drive, channel):
    """The step's first frame, its SYNC, does not go out: a HardwareError naming node 5 on virtual:<channel> (python-can
    said only "Failed to transmit: No such device")."""
    with harness(channel) as h:
        drive_until(h, 0.05, lambda o: drive.latched == h.comp.map.counts(0.05) and h.comp.handshake_idle())
        adapter = Unplug(h.comp.network.bus, receives=False)
        adapter.pulled = True
        exc = step_until_raises(h, 0.05)
        lost_adapter(exc, channel, "sending SYNC failed")
        assert 0x80 in adapter.failed   # the SYNC
        adapter.pulled = False


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_set_point_on_a_lost_adapter_is_named_and_sent_again_once_it_is_back(drive, channel):
    """RPDO1's transmit fails: named as the SYNC's is; the set-point is not taken as sent, so the same target goes out
    at the next write once the adapter is back (a failed transmit is retried by the next write)."""
    with harness(channel) as h:
        drive_until(h, 0.06, lambda o: drive.latched == h.comp.map.counts(0.06) and h.comp.handshake_idle())
        adapter = Unplug(h.comp.network.bus, receives=False)
        adapter.pulled = True
        with pytest.raises(HardwareError) as ei:
            h.comp._hw_write(0.05)
        lost_adapter(ei.value, channel, f"sending set-point {h.comp.map.counts(0.05)} (RPDO1) failed")
        assert 0x205 in adapter.failed and drive.latched == h.comp.map.counts(0.06)
        adapter.pulled = False
        h.comp._hw_write(0.05)   # the same target again: sent this time
        assert wait_for(lambda: drive.latched == h.comp.map.counts(0.05))


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_the_safe_state_on_a_lost_adapter_logs_the_drive_and_the_bus(drive, channel):
    """safe_state() never raises: its log line names the drive and says the adapter is gone; back, the hold goes
    out."""
    with harness(channel) as h:
        drive_until(h, 0.06, lambda o: drive.latched == h.comp.map.counts(0.06) and h.comp.handshake_idle())
        logs: list[str] = []
        h.ctx._log = logs.append
        adapter = Unplug(h.comp.network.bus, receives=False)
        adapter.pulled = True
        h.comp.safe_state()
        said = [m for m in logs if m.startswith("safe_state could not command the gripper: ")]
        assert said and f"CANopen node 5 on virtual:{channel}: sending set-point" in said[0], logs
        assert "CAN adapter is gone (unplugged" in said[0], said
        adapter.pulled = False
        h.comp.safe_state()
        hold = h.comp.map.counts(h.comp._hold_at)
        assert wait_for(lambda: drive.latched == hold)


def test_an_error_in_receiving_is_named_without_a_thread_traceback(drive, channel):
    """Receiving fails for good: python-can's receive thread goes on trying (no traceback on stderr, "Exception in
    thread ..."), and once no frame has come for read_timeout a read names the error, not a lost drive (the heartbeats
    and TPDOs it no longer gets), and every read after it does (tests/test_canopen_receive_errors.py: one that frames
    follow is got over)."""
    with harness(channel) as h:
        drive_until(h, 0.05, lambda o: drive.latched == h.comp.map.counts(0.05) and h.comp.handshake_idle())
        adapter = Unplug(h.comp.network.bus, sends=False)
        with thread_exceptions() as ended:
            adapter.pulled = True
            exc = step_until_raises(h, 0.05)
            time.sleep(0.3)   # (the receive thread's next tries)
            lost_adapter(exc, channel, "receiving failed")
            assert ENODEV_RECV in str(exc) and "no heartbeat" not in str(exc) and "no valid state" not in str(exc)
            with pytest.raises(HardwareError, match="receiving failed"):   # and at every read after it
                h.comp._hw_read()
            adapter.pulled = False
        assert ended == []


def test_an_adapter_lost_during_the_start_up_is_named(drive, channel, monkeypatch):
    """An SDO request that cannot go out names what it was for, the drive and the bus (python-can's bare error came
    out of configure())."""
    drive_bus = drive.network.bus
    real = VirtualBus.send

    def send(self, msg, timeout=None):
        if self is not drive_bus and msg.arbitration_id == 0x605:
            raise can.CanOperationError(ENODEV_SEND, errno.ENODEV)
        return real(self, msg, timeout)

    monkeypatch.setattr(VirtualBus, "send", send)
    h = harness(channel)
    try:
        with pytest.raises(HardwareError) as ei:
            h.comp.configure()
    finally:
        h.comp.close()
    lost_adapter(ei.value, channel, "reading device type 0x1000 failed")


def test_what_to_check_after_a_lost_adapter_depends_on_the_cause_and_the_interface():
    from teletouch.plugins.devices.canopen_gripper import bus_failure_hint

    def socketcan(code: int, text: str) -> can.CanOperationError:
        try:   # as python-can's socketcan raises it: the errno passed on, the OSError its cause
            try:
                raise OSError(code, text)
            except OSError as os_error:
                raise can.CanOperationError(f"Failed to transmit: {text}", code) from os_error
        except can.CanOperationError as exc:
            return exc

    gone = bus_failure_hint(socketcan(errno.ENODEV, "No such device"), "socketcan", "can0", 500000)
    assert gone.startswith("the CAN adapter is gone (unplugged") and "No such device" in gone
    assert "`ip link show can0`" in gone and "sudo ip link set can0 up type can bitrate 500000" in gone
    assert "teletouch devices" in gone
    down = bus_failure_hint(socketcan(errno.ENETDOWN, "Network is down"), "socketcan", "can1", 1000000)
    assert down.startswith("the CAN interface went down") and "`ip link show can1`" in down
    full = bus_failure_hint(socketcan(errno.ENOBUFS, "No buffer space available"), "socketcan", "vcan0", 1000000)
    assert full.startswith("the transmit queue is full: no node acknowledges the frames")
    assert "sudo ip link set vcan0 up)" in full   # a vcan has no bit rate
    other = bus_failure_hint(can.CanOperationError("A PCAN error"), "pcan", "PCAN_USBBUS1", 1000000)
    assert other.startswith("the CAN adapter may have been unplugged or the interface went down (CanOperationError")
    assert "ip link" not in other and "replug the adapter" in other
    # an error code of another interface is its own, not an errno: pcan's 19 is not "no such device"
    assert not bus_failure_hint(can.CanOperationError("x", 19), "pcan", "PCAN_USBBUS1", 1).startswith("the CAN "
                                                                                                      "adapter is")


@pytest.mark.timeout(120)
def test_the_cli_fault_of_a_lost_adapter_names_the_drive(drive, channel, tmp_path, monkeypatch, capsys):
    """The audit's run (`teletouch run`, the adapter pulled once the drive is enabled): the fault line was
    "exception: CanOperationError: Failed to transmit: [Errno 19] No such device", naming no node or channel."""
    from teletouch.cli import main

    drive_bus = drive.network.bus
    pulled = threading.Event()
    send, recv = VirtualBus.send, VirtualBus._recv_internal

    def bad_send(self, msg, timeout=None):
        if pulled.is_set() and self is not drive_bus:
            raise can.CanOperationError(ENODEV_SEND, errno.ENODEV)
        return send(self, msg, timeout)

    def bad_recv(self, timeout):
        if pulled.is_set() and self is not drive_bus:
            time.sleep(min(timeout or 0.01, 0.01))
            raise can.CanOperationError(ENODEV_RECV, errno.ENODEV)
        return recv(self, timeout)

    monkeypatch.setattr(VirtualBus, "send", bad_send)
    monkeypatch.setattr(VirtualBus, "_recv_internal", bad_recv)

    def pull():
        if wait_for(lambda: drive.state == "OPERATION ENABLED"):
            time.sleep(0.5)
            pulled.set()

    puller = threading.Thread(target=pull, daemon=True)
    puller.start()
    graph = tmp_path / "teleop_can.yaml"
    graph.write_text(TELEOP_CAN)
    code = main(["run", str(graph), "--quiet", "--set", f"gripper.channel={channel}"])
    puller.join()
    err = capsys.readouterr().err
    assert pulled.is_set() and code == 3, err
    fault = [line for line in err.splitlines() if line.startswith("teletouch: fault:")]
    assert fault and f"HardwareError: CANopen node 5 on virtual:{channel}: " in fault[0], err
    assert "CAN adapter is gone (unplugged" in fault[0] and "No such device" in fault[0], err
    assert "exception: CanOperationError" not in err


TELEOP_CAN = """\
name: teleop-can
clock: wall
duration: 10
nodes:
  - id: leader
    plugin: sim-omega7
    rate: 1kHz
    params:
      intent: {type: close-and-hold, start_opening: 40mm, target_opening: 20mm, speed: 20mm/s, start_time: 0.2s,
               hold_time: 30s}
    inputs: {gripper_force: {from: controller.gripper_force, max_age: 0.05}}
  - id: gripper
    plugin: canopen-gripper
    rate: 100
    params: {interface: virtual, channel: CHAN, node_id: 5}
    inputs: {opening_command: {from: controller.opening_command, max_age: 0.05}}
  - id: fsense
    plugin: mock-sensor
    rate: 100
    params: {signal: constant, offset: 2N}
  - id: controller
    plugin: position-force
    rate: 1kHz
    inputs:
      leader_opening: {from: leader.gripper_opening, max_age: 0.05}
      leader_velocity: leader.gripper_velocity
      follower_opening: {from: gripper.opening, max_age: 0.05}
      force: fsense.value
"""


# ------------------------------------------------------------------------------------------------ the interface
def test_an_interface_python_can_does_not_know_is_refused_naming_the_closest():
    with pytest.raises(ValidationError, match=r"interface 'socketcann' is not an interface python-can .* knows "
                                              r"\(did you mean 'socketcan'"):
        CanopenGripper.Params(interface="socketcann")
    with pytest.raises(ValidationError, match=r"\(did you mean 'socketcan'\?\)"):
        CanopenGripper.Params(interface="SocketCAN")   # python-can's names are lower case
    with pytest.raises(ValidationError, match=r"interface 'usb-can' is not .*: give socketcan .*virtual .*pcan"):
        CanopenGripper.Params(interface="usb-can")
    for name in can.interfaces.VALID_INTERFACES:   # every one python-can (and its installed plugins) knows
        assert CanopenGripper.Params(interface=name).interface == name


def test_teletouch_validate_names_the_interface_field(tmp_path, capsys):
    from teletouch.cli import main

    graph = tmp_path / "teleop_can.yaml"
    graph.write_text(TELEOP_CAN)
    assert main(["validate", str(graph), "--set", "gripper.interface=socketcann"]) == 1
    err = capsys.readouterr().err
    assert "node 'gripper': param 'interface' = 'socketcann'" in err and "did you mean 'socketcan'" in err, err
    assert main(["validate", str(graph)]) == 0


@contextlib.contextmanager
def unconfigured_logging():
    """As in a program that configured no logging (the CLI): the root logger without handlers (pytest's taken off
    for the block), logging's last-resort handler (which prints WARNING and above to stderr) replaced by a list of
    what it would print."""
    root, printed = logging.getLogger(), []

    class LastResort(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            printed.append(f"{record.name}: {record.getMessage()}")

    saved = root.handlers[:], logging.lastResort
    root.handlers[:] = []
    logging.lastResort = LastResort(logging.WARNING)
    try:
        yield printed
    finally:
        root.handlers[:] = saved[0]
        logging.lastResort = saved[1]


def _open_error(monkeypatch, interface: str, channel: str, raised: BaseException, logged: str = "") -> str:
    """The start-up error of ``interface:channel`` when python-can logs ``logged`` (at WARNING, as at a backend's
    import) and raises ``raised``; nothing of python-can's is printed."""
    def connect(self, *args, **kwargs):
        if logged:
            logging.getLogger(f"can.{interface}").warning(logged)
        raise raised

    monkeypatch.setattr(canopen.Network, "connect", connect)
    h = Harness(CanopenGripper, {"interface": interface, "channel": channel})
    with unconfigured_logging() as printed:
        try:
            with pytest.raises(HardwareError) as ei:
                h.comp.configure()
        finally:
            h.comp.close()
    assert printed == [] and logging.getLogger("can").handlers == []
    return str(ei.value)


def test_the_start_up_hint_depends_on_the_interface(monkeypatch):
    """Every interface got SocketCAN's "sudo ip link set ... up type can bitrate ..."; an adapter's interface needs its
    vendor library, and python-can's log line that says so (kvaser raises a NameError or "channel must be an
    integer" without it) is in the error instead of on stderr."""
    pcan = _open_error(monkeypatch, "pcan", "PCAN_USBBUS1", OSError("pcanbasic library not found."),
                       "uptime library not available, timestamps are relative to boot time and not to Epoch UTC")
    assert "cannot open CAN interface pcan:PCAN_USBBUS1 (OSError: pcanbasic library not found." in pcan
    assert "python-can's pcan interface needs PEAK-System's PCAN-Basic library" in pcan and "ip link" not in pcan
    kvaser = _open_error(monkeypatch, "kvaser", "0", NameError("name 'canGetNumberOfChannels' is not defined"),
                         "Kvaser canlib is unavailable.")
    assert "(NameError: name 'canGetNumberOfChannels' is not defined; python-can logged: Kvaser canlib is " \
           "unavailable.)" in kvaser
    assert "Kvaser's CANlib" in kvaser and "ip link" not in kvaser
    virtual = _open_error(monkeypatch, "virtual", "x", ValueError("odd"))
    assert "virtual interface needs nothing installed or set up" in virtual and "ip link" not in virtual
    socketcan = _open_error(monkeypatch, "socketcan", "vcan9", can.CanInitializationError("refused"))
    assert "check the adapter and that the interface is up (sudo ip link set vcan9 up)" in socketcan


def test_no_sdo_answer_names_the_drive_and_aborts_the_transfer(channel):
    """A wrong node id: the driver's own "no SDO answer from CANopen node 5", and canopen's client aborts the transfer
    on the bus (abort code 0x05040000, SDO protocol timed out). canopen also logs that abort at ERROR ("Transfer
    aborted by client"), which is left as the library's: a program that configured logging gets it."""
    bus = can.Bus(interface="virtual", channel=channel)
    frames: list[can.Message] = []
    notifier = can.Notifier(bus, [frames.append])
    try:
        h = harness(channel, sdo_timeout=0.1)
        try:
            with pytest.raises(HardwareError, match=r"no SDO answer from CANopen node 5 on virtual:"):
                h.comp.configure()
        finally:
            h.comp.close()
        assert wait_for(lambda: any(m.arbitration_id == 0x605 and bytes(m.data) == bytes.fromhex("8000000000000405")
                                    for m in frames))
    finally:
        notifier.stop()
        bus.shutdown()
