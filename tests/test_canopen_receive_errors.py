"""canopen-gripper, errors in receiving: python-can's receive thread (its Notifier) calls the bus's ``recv()``, which
raises now and then on real adapters (a brief adapter error, an interface bouncing); the driver's listener handles the
error, so the thread goes on receiving. One such error that frames follow (the drive's heartbeat and TPDOs arriving
again) is got over: logged, counted in status() (``receive_errors``), and the run goes on. One that goes on (no frame
for read_timeout, or the drive's heartbeat missing as long) ends the run in a HardwareError naming the drive, the
interface and python-can's error; python-can's receive thread ended is named at once.

The failure is injected at the driver's bus (tests/fakes/canopen_drive.py, FailingReceives): its ``recv()`` raises
python-can's CanOperationError as socketcan's does for an interface that went down (errno 100)."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import can
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import RECV_DOWN, FailingReceives  # noqa: E402
from fakes.followers import canopen_harness as harness, channel_fixture, drive_fixture  # noqa: E402
from fakes.realtime import drive as step_for, drive_until, step_until_raises, thread_exceptions, wait_for  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices import canopen_gripper  # noqa: E402

pytestmark = pytest.mark.timeout(60)

channel = channel_fixture()
drive = drive_fixture(position=0)

GOT_OVER = r"receiving on CANopen node 5 on virtual:\S+ failed \(CanOperationError: Error receiving: Network is down"


def logging_to(h) -> list[str]:
    said: list[str] = []
    h.ctx._log = said.append
    return said


def got_over(said: list[str]) -> list[str]:
    return [m for m in said if re.match(GOT_OVER, m)]


def at(h, counts: int, drive) -> None:
    """Step ``h`` until the drive has taken the set-point of ``counts`` and the handshake is over."""
    opening = h.comp.map.opening(counts)
    drive_until(h, opening, lambda o: drive.latched == counts and h.comp.handshake_idle())
    assert drive.latched == counts




# ------------------------------------------------------------------------------------------- errors that frames end
def test_one_failed_receive_is_got_over_logged_and_counted(drive, channel):
    """recv() raises once, then the frames flow: the run goes on (steps well past read_timeout, a new set-point taken
    after each error), each error logged once naming the drive, the bus and python-can's error, and counted. The
    Notifier kept the error and canopen raised it from every later send, so the next step ended the run."""
    with harness(channel) as h:
        said = logging_to(h)
        at(h, 25000, drive)
        failing = FailingReceives(h.comp.network.bus)
        for n, counts in ((1, 50000), (2, 30000)):
            failing.fail(1)
            assert wait_for(lambda: len(failing.failed) == n)
            step_for(h, h.comp.map.opening(25000 if n == 1 else 50000), 3 * h.comp.params.read_timeout)
            at(h, counts, drive)
            assert len(got_over(said)) == n, said
            assert h.comp.status()["receive_errors"] == n
        assert "frames arrived again" in got_over(said)[0] and "(1 failed receives so far)" in got_over(said)[0]
        assert h.comp.node.sdo[0x6041].raw & 0x6F == 0x27   # an SDO exchange too (canopen's sends no longer raise)


def test_a_run_of_failed_receives_shorter_than_read_timeout_is_got_over(drive, channel):
    """recv() fails over and over for 0.25 s (of read_timeout 1 s), python-can's thread retrying (RECEIVE_RETRY
    apart after the first), then works: the run goes on; the run of errors is one log line, each error counted."""
    with harness(channel, read_timeout=1.0) as h:
        said = logging_to(h)
        at(h, 25000, drive)
        failing = FailingReceives(h.comp.network.bus)
        failing.fail(None)
        t0 = time.monotonic()
        while time.monotonic() < t0 + 0.25:
            h.step(time.monotonic(), opening_command=h.comp.map.opening(25000))
            time.sleep(0.005)
        failing.fail(0)
        failed_for = time.monotonic() - t0
        step_for(h, h.comp.map.opening(25000), 1.0)
        at(h, 40000, drive)
        lines = got_over(said)
        assert len(lines) == 1 and re.search(r", \d+ times in a row\); frames arrived again", lines[0]), said
        assert h.comp.status()["receive_errors"] == len(failing.failed) >= 2
        # not a spin: after the first error python-can's thread waits RECEIVE_RETRY before each try
        assert len(failing.failed) <= failed_for / canopen_gripper.RECEIVE_RETRY + 3


def test_a_failed_receive_during_the_start_up_is_got_over(drive, channel, monkeypatch):
    """The driver's bus fails its first recv(), as the start-up begins: the start-up's SDO requests went out with
    canopen raising the kept error; now the start-up goes on and says what it got over."""
    real = can.Bus
    installed: list[FailingReceives] = []

    def bus(*args, **kwargs):
        b = real(*args, **kwargs)
        installed.append(FailingReceives(b))
        installed[-1].fail(1)
        return b

    monkeypatch.setattr(can, "Bus", bus)
    h = harness(channel)
    said = logging_to(h)
    with h:
        monkeypatch.setattr(can, "Bus", real)
        assert len(installed) == 1 and len(installed[0].failed) == 1
        assert h.comp.status()["receive_errors"] == 1 and len(got_over(said)) == 1, said
        at(h, 25000, drive)


def test_error_frames_do_not_end_a_failure():
    """Only a frame that carries data says the bus receives again, not an error frame (a burst of them is what a
    disturbed bus gives)."""

    class Notifier:
        exception: BaseException | None = None
        stopped = False

    rx, notifier = canopen_gripper.ReceiveErrors(), Notifier()
    rx.attach(notifier)
    exc = can.CanOperationError(RECV_DOWN)
    notifier.exception = exc   # (python-can keeps it, then calls the listeners' on_error)
    rx.on_error(exc)
    assert notifier.exception is None   # taken from the Notifier: canopen's sends do not raise it
    rx(can.Message(is_error_frame=True))
    assert rx.failing() is not None and rx.take() == []
    rx(can.Message(arbitration_id=0x705, data=b"\x05", is_extended_id=False))
    assert rx.failing() is None
    (first, back, n, last), = rx.take()
    assert n == 1 and last is exc and back >= first and rx.count == 1


# ------------------------------------------------------------------------------------------ failures that go on
@pytest.mark.parametrize("heartbeat_period", [0.1, 0])
def test_a_receive_failure_that_goes_on_ends_the_run_after_read_timeout(drive, channel, heartbeat_period):
    """recv() fails from now on: not at the next step (a failure frames may still end), but once no frame came for
    read_timeout (with the drive's heartbeat watch, or without it): a HardwareError naming the drive, the bus, what
    to check and python-can's error, from it; not taken for a lost drive ("no heartbeat") or a bare "no valid state"
    (without the heartbeat the TPDOs are what is missing). Every read after it says so too."""
    with harness(channel, heartbeat_period=heartbeat_period) as h:
        at(h, 25000, drive)
        failing = FailingReceives(h.comp.network.bus)
        failing.fail(None)   # (at python-can's next recv(): stepping, so that frames come and the one under way ends)
        drive_until(h, h.comp.map.opening(25000), lambda o: failing.failed)
        exc = step_until_raises(h, h.comp.map.opening(25000))
        waited = time.monotonic() - failing.failed[0]
        msg = str(exc)
        assert isinstance(exc, HardwareError) and re.match(r"CANopen node 5 on virtual:\S+: receiving", msg), msg
        assert "failed: the CAN interface went down" in msg and f"(CanOperationError: {RECV_DOWN}" in msg, msg
        assert "no heartbeat" not in msg and not msg.startswith("canopen-gripper: no valid state"), msg
        assert isinstance(exc.__cause__, can.CanOperationError)
        # no frame for read_timeout: the last (a heartbeat, a step's TPDOs) came up to a heartbeat period or a step
        # before the first error
        assert waited >= h.comp.params.read_timeout - 0.15, (waited, msg)
        with pytest.raises(HardwareError, match="receiving.* failed: the CAN interface went down"):
            h.comp._hw_read()
        failing.fail(0)


def test_a_receive_failure_through_the_start_up_names_python_cans_error(drive, channel, monkeypatch):
    """The driver's bus receives nothing from the start: the first SDO request gets no answer, and the error names
    python-can's error in receiving, not only a missing SDO answer (check power, wiring...)."""
    real = can.Bus

    def bus(*args, **kwargs):
        b = real(*args, **kwargs)
        FailingReceives(b).fail(None)
        return b

    monkeypatch.setattr(can, "Bus", bus)
    h = harness(channel)
    try:
        with pytest.raises(HardwareError) as ei:
            h.comp.configure()
    finally:
        monkeypatch.setattr(can, "Bus", real)
        h.comp.close()
    msg = str(ei.value)
    assert re.match(r"CANopen node 5 on virtual:\S+: receiving \(no SDO answer to reading device type 0x1000; \d+ "
                    r"failed receives in [\d.]+ s, no frame since\) failed: the CAN interface went down", msg), msg
    assert isinstance(ei.value.__cause__, can.CanOperationError)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_an_ended_receive_thread_is_named_at_once(drive, channel):
    """python-can's receive thread ends where a listener's on_error raises (here one of the test's, after the
    driver's): nothing is received any more, for good. The next read says so, naming the error, instead of waiting
    read_timeout for a drive that seems lost."""

    class Raises:
        def __call__(self, msg):
            return None

        def on_error(self, exc):
            raise RuntimeError("a listener that fails")

    with harness(channel) as h:
        at(h, 25000, drive)
        h.comp.network.notifier.add_listener(Raises())
        failing = FailingReceives(h.comp.network.bus)
        with thread_exceptions() as ended:
            failing.fail(1)
            assert wait_for(lambda: ended)
            assert "a listener that fails" in ended[0]
            t0 = time.monotonic()
            exc = step_until_raises(h, h.comp.map.opening(25000))
        assert time.monotonic() - t0 < h.comp.params.read_timeout
        assert isinstance(exc, HardwareError)
        assert re.match(r"CANopen node 5 on virtual:\S+: python-can's receive thread for virtual:\S+ has ended after "
                        rf"CanOperationError: {RECV_DOWN}.*close the driver and start it again", str(exc)), str(exc)


def test_a_send_in_the_gap_before_the_listener_takes_the_error_does_not_raise_it(drive, channel):
    """python-can sets the Notifier's exception just before the driver's listener takes it; canopen checks that
    exception after every send, so a step's SYNC or SDO request in that gap raised the receive error as its own
    ("sending SYNC failed"). Held in the gap here: the steps and an SDO exchange go on."""
    with harness(channel) as h:
        at(h, 25000, drive)
        h.comp.network.notifier.exception = can.CanOperationError("Error receiving: Network is down", 100)
        try:
            step_for(h, h.comp.map.opening(25000), 0.2)
            at(h, 40000, drive)
            assert h.comp.node.sdo[0x6041].raw & 0x6F == 0x27
        finally:
            h.comp.network.notifier.exception = None
