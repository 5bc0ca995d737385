"""A run in a program without the command line's handlers (Python's own Ctrl-C handler): a Ctrl-C stops the run
until it is stopping, and is held from then on. A review of the first version (only the run's first Ctrl-C raised)
found it (a) left its handler installed for good when a Ctrl-C landed as Python's was given back (every later Ctrl-C
then only "held": the next run could not be stopped), and (b) held every Ctrl-C after a first one that did not stop
the run (swallowed by a component's close(), or used by a run inside the run)."""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest

from teletouch import Component, Kind, Port, hookimpl, runtime
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry

GRAPH = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
"""


@pytest.fixture(autouse=True)
def _python_handler():
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    sys.setprofile(None)
    signal.signal(signal.SIGINT, old)


def _ctrl_c():
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(1000):   # its handler runs at a bytecode boundary
        pass


def _runtime(text: str = GRAPH, *plugins) -> Runtime:
    return Runtime(load_text(text, make_registry(*plugins)), log=lambda m: None)


def _ctrl_c_as_python_s_handler_is_given_back():
    """A profile function sending a Ctrl-C as the run gives Python's handler back (at signal.signal's entry there)."""
    code = runtime._ctrl_c_until_stopping.__wrapped__.__code__
    sent = []

    def prof(frame, event, arg):
        if (event == "call" and frame.f_code is signal.signal.__code__ and frame.f_back.f_code is code
                and frame.f_locals.get("handler") is signal.default_int_handler and not sent):
            sent.append(True)
            os.kill(os.getpid(), signal.SIGINT)

    return prof, sent


def test_python_s_handler_is_back_after_a_ctrl_c_as_it_is_given_back_and_the_next_run_stops_for_one(capfd):
    prof, sent = _ctrl_c_as_python_s_handler_is_given_back()
    sys.setprofile(prof)
    try:
        res = _runtime().run(0.1)
    finally:
        sys.setprofile(None)
    assert sent and res.status == "ok"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    n = {"k": 0}

    def progress(rt, t):
        n["k"] += 1
        if n["k"] == 2:
            _ctrl_c()
            time.sleep(0.01)

    res = _runtime().run(200.0, progress=progress, progress_interval=0.0)
    assert res.status == "interrupted", (res.status, res.message, capfd.readouterr().err)


def test_a_ctrl_c_after_a_run_inside_the_run_used_the_first_still_stops_the_outer_run(capfd):
    n = {"k": 0}

    def progress(rt, t):
        n["k"] += 1
        if n["k"] == 1:   # a short run of its own (a check, a sub-graph), which a Ctrl-C stops
            res = _runtime().run(50.0, progress=lambda r, t: _ctrl_c(), progress_interval=0.0)
            assert res.status == "interrupted"
        elif n["k"] == 3:
            _ctrl_c()

    res = _runtime().run(300.0, progress=progress, progress_interval=0.0)
    assert res.status == "interrupted", (res.status, res.message, capfd.readouterr().err)


class _SlowConfigure(Component):
    name = "s16b-slow-configure"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}
    log: list[str] = []

    def configure(self):   # loading a model: the operator presses Ctrl-C again
        _ctrl_c()
        time.sleep(0.05)
        type(self).log.append("configured to the end")

    def step(self, t, inputs):
        return {"y": 0.0}


class _FailsAndCloses(Component):
    name = "s16b-fails"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    def configure(self):
        raise RuntimeError("no device")

    def close(self):   # the first Ctrl-C lands here: the start-up's close of a failed node swallows it
        _ctrl_c()

    def step(self, t, inputs):
        return {"y": 0.0}


class _P:
    @hookimpl
    def teletouch_components(self):
        return [_SlowConfigure, _FailsAndCloses]


def test_a_second_ctrl_c_during_start_up_stops_it_when_the_first_was_swallowed(capfd):
    text = """
clock: sim
nodes:
  - {id: a, plugin: s16b-fails, rate: 10}
  - {id: b, plugin: s16b-slow-configure, rate: 10}
"""
    _SlowConfigure.log.clear()
    res = _runtime(text, _P()).run(1.0)
    assert _SlowConfigure.log == [], "the second Ctrl-C did not stop b's configure: " + capfd.readouterr().err
    assert res.status == "interrupted", res.message


def test_a_second_ctrl_c_as_the_run_notes_the_first_is_held_and_the_devices_are_made_safe(capfd):
    """The first Ctrl-C stops the run (raised in its loop); a second one landing as run() notes it (its except clause,
    before the shutdown) came out of run() after the shutdown: the run's result was lost."""
    code = Runtime._fault_reason.__code__
    sent = []

    def prof(frame, event, arg):
        if event == "call" and frame.f_code is code and not sent:
            sent.append(True)
            signal.getsignal(signal.SIGINT)(signal.SIGINT, frame)   # its handler runs as _fault_reason is entered

    n = {"k": 0}

    def progress(rt, t):
        n["k"] += 1
        if n["k"] == 2:
            sys.setprofile(prof)
            _ctrl_c()

    rt = _runtime()
    escaped = None
    try:
        res = rt.run(200.0, progress=progress, progress_interval=0.0)
    except KeyboardInterrupt as exc:   # before: out of run(), after its shutdown
        escaped = exc
    finally:
        sys.setprofile(None)
    assert sent and escaped is None
    assert res.status == "interrupted", res.message
    assert "teletouch: Ctrl-C: already stopping safely, please wait" in capfd.readouterr().err
