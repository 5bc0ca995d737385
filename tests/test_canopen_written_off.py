"""canopen-gripper: an answer written off as lost (its SYNC's TPDOs did not come within two pdo_timeouts) that comes
after all, during the next read, is not taken for that read's answer; against the emulated CiA 402 drive on
python-can's virtual bus, whose answers can come late or not at all, in order.

Before, the write-off set the count back to the frames received, so the first frame after the next SYNC answered it:
a drive that stalled (answers held back, then sent in order) had its oldest answer, a state from before the write-off,
taken for the new SYNC's and stamped as fresh. The written-off answers are now remembered: they come before the new
SYNC's (in order), so the read waits (within its pdo_timeout) for all of them; when they do not come they are taken as
lost, and the frame that came after the SYNC is its answer."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.followers import SYNC_PDO_TIMEOUT as P, channel_fixture, counts_of, drive_fixture  # noqa: E402
from fakes.followers import sync_harness as harness  # noqa: E402
from fakes.realtime import wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(60)

channel = channel_fixture()
drive = drive_fixture(position=0)


def write_off(h, drive, *delays):
    """A read whose SYNC is answered ``delays[0]`` s late (later than 2 P: written off by the read after it), the
    next SYNCs as ``delays[1:]`` say; returns once that answer was written off."""
    drive.answer_late(*delays)
    assert h.comp._hw_read() is None and "no TPDO within 400 ms" in h.comp.last_error
    assert h.comp._hw_read() is None and "written off as lost" in h.comp.last_error


def test_a_written_off_answer_that_comes_during_the_next_read_is_not_taken_for_its_answer(drive, channel):
    """The drive stalls: A's answer comes 2.5 P after its SYNC (0.2 s into the next read), the next SYNC's (B) 0.1 s
    after it. Before, A's answer (1000 counts) was taken for B's."""
    with harness(channel) as h:
        drive.set_position(1000)
        assert counts_of(h, h.comp._hw_read()) == 1000
        write_off(h, drive, 2.5 * P, 0.75 * P)
        drive.set_position(2000)   # after A's SYNC: A's answer still says 1000
        t0 = time.monotonic()
        r = h.comp._hw_read()      # B's SYNC; A's answer comes 0.2 s into this read, B's 0.1 s after that
        assert r is not None and counts_of(h, r) == 2000
        assert r.mono > t0 + 0.5 * 0.25 * P   # from its SYNC to its own answer, after A's came
        drive.set_position(2500)
        assert counts_of(h, h.comp._hw_read()) == 2500   # the count is right afterwards


def test_a_written_off_answer_that_comes_just_before_the_next_sync_goes_out_is_not_taken_for_its_answer(drive,
                                                                                                        channel):
    """The edge: A's answer arrives after the next read counted what was owed and before its SYNC went out."""
    with harness(channel) as h:
        drive.set_position(1000)
        assert counts_of(h, h.comp._hw_read()) == 1000
        write_off(h, drive, 2.2 * P, 0.25 * P)   # A comes 0.08 s after the write-off; B 0.1 s after its SYNC
        drive.set_position(2000)
        sync = h.comp.network.sync
        real = sync.transmit
        arrivals = h.comp._arrivals
        seen = []

        def transmit(*args, **kwargs):   # the SYNC goes out just after A's answer arrived
            before = sum(arrivals.values())
            seen.append(wait_for(lambda: sum(arrivals.values()) > before, timeout=1.0))
            sync.transmit = real
            return real(*args, **kwargs)

        sync.transmit = transmit
        r = h.comp._hw_read()
        assert seen == [True]      # A's answer did arrive between the count and the SYNC
        assert r is not None and counts_of(h, r) == 2000


def test_after_a_write_off_of_an_answer_that_never_comes_the_next_read_has_its_own_state_and_stamp(drive, channel):
    """The written-off answer is lost for good: the next read waits out its pdo_timeout for it, then takes the frame
    that came after its SYNC, stamped from that SYNC to that frame (not to the end of the wait)."""
    with harness(channel) as h:
        write_off(h, drive, None)
        drive.set_position(3000)
        t0 = time.monotonic()
        r = h.comp._hw_read()
        assert r is not None and counts_of(h, r) == 3000
        assert t0 <= r.mono < t0 + 0.25 * P
        t0 = time.monotonic()
        assert counts_of(h, h.comp._hw_read()) == 3000
        assert time.monotonic() - t0 < 0.5 * P   # the count is right again: no wait for anything written off
