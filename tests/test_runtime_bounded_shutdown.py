"""A node's deactivate(), results() or close() that hangs at the end of a run (wall clock) is left behind after
Runtime.LIFECYCLE_TIMEOUT, reported, and the other nodes are still closed: a hung deactivate() held the run, and every
close() after it, until it returned (signals are held during the shutdown: only a kill ended it)."""

from __future__ import annotations

import threading
import time

import pytest

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry

RELEASE = threading.Event()   # set at the end of each test: the hung calls return


class Stuck(Component):
    name = "t-stuck"
    kind = Kind.ESTIMATOR
    outputs = {"value": Port("float64", (), "")}
    stuck_in = ""   # set per test: "deactivate", "results" or "close"

    def step(self, t, inputs):
        return {"value": 1.0}

    def _maybe_hang(self, name):
        if Stuck.stuck_in == name:
            RELEASE.wait(30)

    def deactivate(self):
        self._maybe_hang("deactivate")

    def results(self):
        self._maybe_hang("results")
        return {"steps": 1}

    def close(self):
        self._maybe_hang("close")


class Holder(Device):
    name = "t-holder"
    outputs = {"value": Port("float64", (), "")}
    closed: list[str] = []

    def step(self, t, inputs):
        return {"value": 0.0}

    def safe_state(self):
        pass

    def close(self):
        Holder.closed.append(self.id)


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [Stuck, Holder]


@pytest.fixture(autouse=True)
def _release(monkeypatch):
    monkeypatch.setattr(Runtime, "LIFECYCLE_TIMEOUT", 0.5, raising=False)
    RELEASE.clear()
    Holder.closed = []
    yield
    RELEASE.set()


@pytest.mark.parametrize("where", ["deactivate", "results", "close"])
def test_a_hung_shutdown_call_is_left_behind_and_the_others_still_close(where):
    Stuck.stuck_in = where
    spec = load_text("""
clock: wall
nodes:
  - {id: holder, plugin: t-holder, rate: 100}
  - {id: stuck, plugin: t-stuck, rate: 100}
""", make_registry(_Plugin()))
    t0 = time.monotonic()
    res = Runtime(spec, log=lambda m: None).run(0.2)
    took = time.monotonic() - t0
    assert took < 5.0, took   # not the 30 s the call hangs
    hung = [f for f in res.faults if f.node == "stuck" and f.kind == "shutdown"]
    assert len(hung) == 1 and hung[0].message.startswith(f"{where}() did not return within 0.5 s: left behind"), \
        res.faults
    if where == "deactivate":
        assert "its results() and close() are skipped" in hung[0].message
    assert Holder.closed == ["holder"]   # the other node is closed all the same
    assert res.status == "ok" and res.exit_code == 0, res.message   # (the devices were safe: only logged)
