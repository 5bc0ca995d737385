"""dynamixel-gripper: a state reading is stamped from the read that produced it, not from before the PING that
resynchronised the bus first (emulated servo on a pseudo-terminal)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import INST_PING, INST_SYNC_READ  # noqa: E402
from fakes.followers import dynamixel_fixture, dynamixel_harness, packet_timeout_fixture  # noqa: E402

pytestmark = pytest.mark.timeout(60)

#: how late the servo answers the resync PING (s): well inside the SDK's packet timeout with the slow adapter (~122
#: ms), and far longer than a state read at 1 Mbaud (~1 ms)
PING_DELAY = 0.05


packet_timeout = packet_timeout_fixture()   # the emulator's slower adapter for a loaded machine
emu = dynamixel_fixture(15, position=1024)


def harness(emu, **params):
    return dynamixel_harness(emu, error_check_period=30.0, **params)


def test_a_reading_after_a_resync_ping_is_stamped_from_its_own_read(emu):
    """After a lost answer the next state read is preceded by a PING; the reading's stamp (the midpoint of the read)
    started before that PING, so a PING answered 50 ms late made the sample ~25 ms older than the read that produced
    it."""
    with harness(emu) as h:
        assert h.comp._hw_read() is not None
        emu.drop(1)                       # the next state answer is lost: the bus is out of step
        assert h.comp._hw_read() is None and h.comp._desync
        emu.ping_delay = PING_DELAY
        n = len(emu.rx_packets)
        r = h.comp._hw_read()             # PING (answered late), then the state read
        after = time.monotonic()
        assert r is not None and h.comp.resyncs == 1
        sent = [(p[0], p[2]) for p in emu.rx_packets[n:]]
        assert [inst for _, inst in sent] == [INST_PING, INST_SYNC_READ]
        ping_arrived = sent[0][0]
        # the read went out only after the PING's answer (PING_DELAY after the PING arrived), so the whole read, and
        # its midpoint, lies after that
        assert ping_arrived + PING_DELAY <= r.mono <= after
