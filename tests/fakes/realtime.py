"""Helpers shared by the follower-driver tests that talk to emulated hardware in real time."""

from __future__ import annotations

import time

import pytest

from teletouch import HardwareError


def configure_fails(h, match):
    try:
        with pytest.raises(HardwareError, match=match):
            h.comp.configure()
    finally:
        h.comp.close()


def wait_for(cond, timeout=1.0):
    t_end = time.monotonic() + timeout
    while not cond() and time.monotonic() < t_end:
        time.sleep(0.002)
    return cond()
