"""Helpers shared by the follower-driver tests that talk to emulated hardware in real time."""

from __future__ import annotations

import contextlib
import re
import threading
import time

import pytest

from teletouch import HardwareError


def configure_error(h) -> str:
    """The HardwareError a driver's configure() raises, as text (the harness closed after it, as the runtime does)."""
    try:
        with pytest.raises(HardwareError) as ei:
            h.comp.configure()
    finally:
        h.comp.close()
    return str(ei.value)


def configure_fails(h, match):
    msg = configure_error(h)
    assert re.search(match, msg), (match, msg)


#: How long the waits below give a condition before they give up: a bound for a failure only (a passing test stops
#: waiting as soon as its condition holds), generous for a loaded 2-core CI machine.
WAIT = 10.0


def wait_for(cond, timeout=WAIT):
    """Whether ``cond()`` became true within ``timeout`` s (polled every 2 ms)."""
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


def drive_until(h, cmd, cond, timeout=WAIT, period=0.005, trace=None):
    """Step a driver Harness in real time with a constant opening command until ``cond(outputs)`` holds (checked after
    every step) or ``timeout`` s passed; the last outputs. For a test that needs the gripper somewhere: it waits for
    that, not for a fixed time (on a loaded machine the steps come late and the set-point, limited per step, lags)."""
    t_end = time.monotonic() + timeout
    while True:
        h.t = time.monotonic()
        out = h.step(h.t, opening_command=cmd)
        if trace is not None:
            trace.append(out)
        if cond(out) or time.monotonic() >= t_end:
            return out
        time.sleep(period)


@contextlib.contextmanager
def thread_exceptions():
    """The exceptions that end a thread in the block (what Python prints as "Exception in thread ...")."""
    ended: list[str] = []
    saved = threading.excepthook
    threading.excepthook = lambda args: ended.append(f"{args.thread.name}: {args.exc_value!r}")
    try:
        yield ended
    finally:
        threading.excepthook = saved


def step_until_raises(h, cmd: float, timeout: float = WAIT) -> BaseException:
    """Step ``h`` in real time with ``cmd`` until a step raises (its error); fails after ``timeout`` s without one."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            h.step(time.monotonic(), opening_command=cmd)
        except Exception as exc:
            return exc
        time.sleep(0.005)
    pytest.fail(f"no step raised within {timeout} s")
