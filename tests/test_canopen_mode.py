"""canopen-gripper: profile position mode is entered when the drive's modes of operation display 0x6061 shows it,
however long the drive takes to switch (CiA 402: the display follows the request, not at once), within
``mode_timeout``; against the emulated CiA 402 drive on python-can's virtual bus."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes.followers import canopen_harness, channel_fixture  # noqa: E402
from fakes.realtime import configure_fails  # noqa: E402

from teletouch.plugins.devices.canopen_gripper import CanopenGripper  # noqa: E402

pytestmark = pytest.mark.timeout(60)


channel = channel_fixture()
harness = canopen_harness


def test_a_drive_that_switches_mode_after_a_while_is_waited_for(channel):
    """0x6061 was read once, right after 0x6060 was written: a drive that takes 0.2 s to switch (the display still
    0, no mode) failed the start-up with "did not enter profile position mode"."""
    with Cia402Drive(5, channel, position=0, mode_delay=0.2) as drive:
        t0 = time.monotonic()
        with harness(channel, mode_timeout=1.0) as h:
            assert time.monotonic() - t0 >= 0.2
            assert drive.get(0x6061) == 1 and drive.state == "OPERATION ENABLED"
            assert h.comp._hw_read() is not None   # TPDO1's mode display says profile position too


def test_a_drive_that_never_shows_the_mode_fails_after_mode_timeout_naming_both_modes(channel):
    with Cia402Drive(5, channel, position=0, mode_delay=None) as drive:
        t0 = time.monotonic()
        configure_fails(harness(channel, mode_timeout=0.3),
                        r"CANopen node 5 on virtual:tt-\w+ did not switch to the requested mode 1 \(profile "
                        r"position\) within mode_timeout 0.3 s: modes of operation display 0x6061 still shows 0 "
                        r"\(no mode\)")
        elapsed = time.monotonic() - t0
        assert 0.3 <= elapsed < 0.3 + 2.0   # the bound, and not much more
        assert drive.get(0x6060) == 1 and drive.get(0x6061) == 0 and drive.state == "SWITCH ON DISABLED"


def test_mode_timeout_must_be_positive():
    with pytest.raises(ValidationError, match="mode_timeout"):
        CanopenGripper.Params(mode_timeout=0)
