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


def drive(h, cmd, seconds, period=0.005, trace=None):
    """Step a driver Harness in real time with a constant opening command; the last outputs (all of them appended
    to ``trace`` if given)."""
    t_end = time.monotonic() + seconds
    out = {}
    while time.monotonic() < t_end:
        h.t = time.monotonic()
        out = h.step(h.t, opening_command=cmd)
        if trace is not None:
            trace.append(out)
        time.sleep(period)
    return out
