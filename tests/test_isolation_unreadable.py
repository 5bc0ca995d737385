"""A reply to a request the child could not read is the answer to that request, never to a later call's.

The child cannot say the number of a request it could not unpickle: its reply carries ``_UNREADABLE``. Before, the
parent took such a reply as the answer to whatever call was waiting. After a step had timed out with its request
still unread in the pipe, the next call got that step's "cannot be unpickled" fault instead of its own outputs (and
its own reply, coming next, was dropped as a late one). The child answers every request once, in order: the parent
now counts the requests it has sent and not had answered, and an unreadable reply answers the oldest of them."""

from __future__ import annotations

import sys
import time
import types

import numpy as np
import pytest

from teletouch.component import Component, Context, Inputs, Kind, Port, Sample, _Slot
from teletouch.errors import ComponentFault
from teletouch.isolation import ProcessProxy

_PARENT_ONLY = "teletouch_s15_parent_only"   # a module that exists in the test process only


def _unreadable(x: float) -> np.ndarray:
    """A small numeric array (it crosses as a plain value) whose dtype carries metadata of a class the child cannot
    import: the whole request cannot be unpickled there, so its reply cannot carry the request's number."""
    mod = sys.modules.get(_PARENT_ONLY)
    if mod is None:
        mod = types.ModuleType(_PARENT_ONLY)
        mod.Tag = type("Tag", (), {"__module__": _PARENT_ONLY})
        sys.modules[_PARENT_ONLY] = mod
    return np.full(2, x, dtype=np.dtype(np.float64, metadata={"tag": mod.Tag()}))


_CHILD_ONLY = "teletouch_s15_child_only"   # a module that the component makes in the isolated process only


def _child_only_value() -> object:
    mod = sys.modules.get(_CHILD_ONLY)
    if mod is None:
        mod = types.ModuleType(_CHILD_ONLY)
        mod.Blob = type("Blob", (), {"__module__": _CHILD_ONLY})
        sys.modules[_CHILD_ONLY] = mod
    return mod.Blob()


class Sleepy(Component):
    """Echoes ``x[0]``; sleeps 1 s in the step whose ``x[0]`` is 1."""

    name = "s15-sleepy"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (None,), "any", "")}
    outputs = {"y": Port("float64", (), "any", "")}

    def step(self, t, inputs):
        x = float(inputs["x"].value[0])
        if x == 1.0:
            time.sleep(1.0)
        return {"y": x}


def _proxy() -> tuple[ProcessProxy, _Slot, Inputs]:
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=100.0)
    proxy = ProcessProxy(Sleepy, Sleepy.Params(), node_id="s", ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                         step_timeout=0.2)
    slot = _Slot()
    return proxy, slot, Inputs({"x": slot})


def test_the_unreadable_reply_of_a_timed_out_step_is_not_taken_as_a_later_steps_answer():
    proxy, slot, inputs = _proxy()

    def step(k: int, value: object) -> dict:
        slot.sample = Sample(value, float(k))
        return proxy.step(float(k), inputs)

    try:
        proxy.configure()
        proxy.activate()
        with pytest.raises(ComponentFault, match="did not answer 'step'"):
            step(1, np.full(2, 1.0))             # the child sleeps 1 s in it
        with pytest.raises(ComponentFault, match="did not answer 'step'"):
            step(2, _unreadable(2.0))            # waits unread in the pipe behind step 1
        proxy._step_timeout = 20.0
        # the child answers step 1 (dropped), then step 2 with an unreadable reply, then step 3: step 3's answer is
        # its own output (before: step 2's "cannot be unpickled" fault)
        assert step(3, np.full(2, 3.0)) == {"y": 3.0}
        assert not proxy._stuck
        assert step(4, np.full(2, 4.0)) == {"y": 4.0}
        # an unreadable request of the call in progress is still that call's fault, and the child lives on
        with pytest.raises(ComponentFault, match="a request from the parent cannot be unpickled in the isolated "
                                                 f"process: ModuleNotFoundError: No module named '{_PARENT_ONLY}'"):
            step(5, _unreadable(5.0))
        assert step(6, np.full(2, 6.0)) == {"y": 6.0}
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0


class Undecodable(Component):
    """Echoes ``x[0]``; in the step whose ``x[0]`` is 1 it sleeps 1 s and outputs a value of a class that only the
    isolated process can import (the parent cannot unpickle that reply)."""

    name = "s15-undecodable"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (None,), "any", "")}
    outputs = {"y": Port("any", (), "any", "")}

    def step(self, t, inputs):
        x = float(inputs["x"].value[0])
        if x == 1.0:
            time.sleep(1.0)
            return {"y": _child_only_value()}
        return {"y": x}


def test_a_reply_of_a_timed_out_step_that_cannot_be_unpickled_here_is_not_a_later_steps_fault():
    """The same for a reply the parent cannot unpickle (its number unknown): before, the step in progress raised
    "a reply ... cannot be unpickled here" for the earlier step's reply, and its own outputs were dropped."""
    logs: list[str] = []
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=100.0, log=logs.append)
    proxy = ProcessProxy(Undecodable, Undecodable.Params(), node_id="u", ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                         step_timeout=0.2)
    slot = _Slot()
    inputs = Inputs({"x": slot})

    def step(k: int) -> dict:
        slot.sample = Sample(np.full(2, float(k)), float(k))
        return proxy.step(float(k), inputs)

    try:
        proxy.configure()
        proxy.activate()
        with pytest.raises(ComponentFault, match="did not answer 'step'"):
            step(1)
        proxy._step_timeout = 20.0
        assert step(2) == {"y": 2.0}
        assert any("cannot be unpickled here" in line and _CHILD_ONLY in line for line in logs), logs
        assert step(3) == {"y": 3.0}
        # the reply of the call in progress cannot be unpickled: still that call's fault
        with pytest.raises(ComponentFault, match=r"a reply of the isolated process \(s15-undecodable\) to 'step' "
                                                 r"cannot be unpickled here: ModuleNotFoundError"):
            step(1)
        assert step(4) == {"y": 4.0}
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0
