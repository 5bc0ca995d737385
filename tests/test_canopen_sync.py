"""canopen-gripper: a TPDO answers the driver's SYNC only after the answers to every earlier SYNC arrived, so a late
answer (to a SYNC whose step timed out, or to one of the state walk's SYNCs) is never taken for a newer SYNC's; against
the emulated CiA 402 drive on python-can's virtual bus, whose answers can come late or not at all, in order."""

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


def test_a_late_answer_is_not_taken_for_the_next_syncs(drive, channel):
    """A SYNC whose answer came after pdo_timeout (a failed read): that answer, arriving while the next read waited,
    was taken as the next SYNC's answer, a state from the SYNC before presented as fresh (here: 0.6 s old)."""
    with harness(channel) as h:
        drive.set_position(1000)
        assert counts_of(h, h.comp._hw_read()) == 1000
        # A: answered 0.6 s after its SYNC (P = 0.4 s: a failed read); B: answered 0.3 s after its own SYNC
        drive.answer_late(1.5 * P, 0.75 * P)
        assert h.comp._hw_read() is None and "no TPDO within 400 ms" in h.comp.last_error
        drive.set_position(2000)   # the fingers moved after A's SYNC: A's answer still says 1000
        t0 = time.monotonic()
        r = h.comp._hw_read()      # A's answer arrives 0.2 s into this read; B's answers this read
        assert r is not None and counts_of(h, r) == 2000
        assert r.mono > t0 + 0.5 * P   # stamped from its own SYNC, sent after A's answer came


def test_an_answer_that_never_comes_is_written_off_and_the_reads_go_on(drive, channel):
    with harness(channel) as h:
        drive.answer_late(None)   # this SYNC's answer is lost
        assert h.comp._hw_read() is None and "no TPDO within" in h.comp.last_error
        t0 = time.monotonic()
        assert h.comp._hw_read() is None   # waited pdo_timeout for the lost answer before sending a new SYNC
        assert time.monotonic() - t0 >= P
        assert "TPDOs answering earlier SYNCs (1 of TPDO1, 1 of TPDO2)" in h.comp.last_error
        assert "written off as lost" in h.comp.last_error
        drive.set_position(3000)
        r = h.comp._hw_read()
        assert r is not None and counts_of(h, r) == 3000


def test_answers_to_another_producers_sync_do_not_answer_the_drivers(drive, channel):
    """Frames beyond the SYNCs the driver sent (a SYNC producer elsewhere on the bus) are forgotten: a read still
    waits for a frame after its own SYNC, not for the count."""
    import canopen

    with harness(channel) as h:
        other = canopen.Network()
        other.connect(interface="virtual", channel=channel, receive_own_messages=False)
        try:
            before = dict(h.comp._arrivals)
            other.sync.transmit()
            assert wait_for(lambda: all(h.comp._arrivals[k] == before[k] + 1 for k in before))
        finally:
            other.disconnect()
        drive.set_position(4000)
        drive.answer_late(0.25 * P)   # the read's own answer comes a while after its SYNC
        r = h.comp._hw_read()
        assert r is not None and counts_of(h, r) == 4000


def test_answers_to_the_state_walks_syncs_are_not_taken_by_the_first_reads(drive, channel):
    """A drive answering 0.1 s after each SYNC: the SYNCs of the state walk (every 5 ms) still had answers on their
    way when it ended, and the first read (configure's, which sets the first set-point) took one of them."""
    drive.latency = 0.1
    h = harness(channel)
    readings = []
    real_open, real_read = h.comp._hw_open, h.comp._hw_read

    def opened():
        real_open()
        drive.set_position(3000)   # the fingers move as the start-up ends: every later SYNC's answer says so

    def read():
        r = real_read()
        readings.append(r)
        return r

    h.comp._hw_open, h.comp._hw_read = opened, read
    with h:
        assert len(readings) == 2   # configure's and activate's
        assert [counts_of(h, r) for r in readings] == [3000, 3000]
        assert h.comp.map.counts(h.comp._setpoint) == 3000
