"""`isolate: process` items left open by the audit: an input the child cannot unpickle, unchanged inputs re-sent."""

from __future__ import annotations

import sys
import time
import types

import numpy as np
import pytest

from teletouch.component import Component, Context, Inputs, Kind, Port, Sample, _Slot
from teletouch.errors import ComponentFault
from teletouch.hookspecs import hookimpl
from teletouch.isolation import ProcessProxy
from teletouch.runtime import EXIT_FAULT
from teletouch.testing import make_registry, run_yaml

# --- test components (module level: the child imports them by name) ------------------------------------------------

_PARENT_ONLY = "teletouch_parent_only_values"   # a module that exists in the test process only


def _parent_only_value(k: int) -> object:
    """An object whose class the isolated process cannot import (its module exists in this process only)."""
    mod = sys.modules.get(_PARENT_ONLY)
    if mod is None:
        mod = types.ModuleType(_PARENT_ONLY)
        blob = type("Blob", (), {"__module__": _PARENT_ONLY})
        mod.Blob = blob
        sys.modules[_PARENT_ONLY] = mod
    obj = mod.Blob()
    obj.k = k
    return obj


class ParentOnly(Component):
    """Outputs a float until ``at``, then a value of a class only this process can import."""

    name = "iso-parent-only"
    kind = Kind.SENSOR
    outputs = {"y": Port("any", (), "any", "")}

    def step(self, t, inputs):
        return {"y": _parent_only_value(int(t * 1000)) if t >= 0.2 else t}


class Held(Component):
    """Says, for each input, whether its sample is the very object of its last step, and echoes value and stamp."""

    name = "iso-held"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("any", (), "any", "", required=False),
              "img": Port("uint8", (None, None, 3), "", "", required=False)}
    outputs = {"same_x": Port("bool", (), "", ""), "same_img": Port("bool", (), "", ""),
               "x": Port("any", (), "any", ""), "x_stamp": Port("float64", (), "s", ""),
               "img_sum": Port("float64", (), "", "")}

    def configure(self):
        self.prev = {"x": None, "img": None}

    def step(self, t, inputs):
        out = {}
        for name in ("x", "img"):
            s = inputs[name]
            out[f"same_{name}"] = s is not None and s is self.prev[name]
            self.prev[name] = s
        x = inputs["x"]
        if x is not None:
            if isinstance(x.value, str) and x.value == "boom":
                raise RuntimeError("iso-held failure")
            out["x"], out["x_stamp"] = x.value, x.stamp
        if inputs["img"] is not None:
            out["img_sum"] = float(np.asarray(inputs["img"].value, dtype=float).sum())
        return out


@hookimpl
def teletouch_components():
    return [ParentOnly, Held]


@pytest.fixture(scope="module")
def reg():
    return make_registry(sys.modules[__name__])


# --- an input the child cannot unpickle ----------------------------------------------------------------------------

def test_an_input_the_child_cannot_unpickle_is_a_fault_naming_plugin_and_input_and_the_child_lives(reg):
    """Before, the child died on the request (exit code 1, a traceback on stderr), and the fault only said the
    process died."""
    text = """
clock: wall
nodes:
  - {id: src, plugin: iso-parent-only, rate: 30}
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 0ms}, inputs: {x: src.y}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""
    res, rt = run_yaml(text, reg, duration=3.0)
    assert res.exit_code == EXIT_FAULT
    assert [f.kind for f in res.faults] == ["exception"], [f.line() for f in res.faults]
    msg = res.faults[0].message
    assert res.faults[0].node == "est"
    assert "input 'x' of mock-burn cannot be received in the isolated process: ModuleNotFoundError: No module " \
           f"named '{_PARENT_ONLY}'" in msg, msg
    assert "died" not in msg
    assert rt.component("dev").safe
    assert rt.component("est")._proc.exitcode == 0   # deactivated and closed normally: it survived the request


def _proxy(cls: type[Component]) -> tuple[ProcessProxy, dict[str, _Slot], Inputs]:
    ctx = Context(now=lambda: time.perf_counter(), clock_kind="wall", rate=100.0)
    proxy = ProcessProxy(cls, cls.Params(), node_id="n", ctx=ctx, t0_perf=0.0, t0_mono=0.0, step_timeout=20.0)
    slots = {n: _Slot() for n in cls.inputs}
    return proxy, slots, Inputs(slots)


def test_after_an_input_the_child_could_not_unpickle_the_next_step_goes_on_with_all_inputs():
    proxy, slots, inputs = _proxy(Held)
    try:
        proxy.configure()
        proxy.activate()
        img = Sample(np.ones((120, 160, 3), np.uint8), 0.5)   # shared memory
        slots["img"].sample = img
        slots["x"].sample = Sample(1.5, 0.5)
        out = proxy.step(0.5, inputs)
        assert out["x"] == 1.5 and out["img_sum"] == 120 * 160 * 3
        slots["x"].sample = Sample(_parent_only_value(7), 0.6)
        with pytest.raises(ComponentFault, match=r"input 'x' of iso-held cannot be received in the isolated "
                                                 r"process: ModuleNotFoundError"):
            proxy.step(0.6, inputs)
        assert proxy._proc.is_alive()
        slots["x"].sample = Sample(2.5, 0.7)
        out = proxy.step(0.7, inputs)
        assert out["x"] == 2.5 and out["x_stamp"] == 0.7 and out["img_sum"] == 120 * 160 * 3
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0


# --- unchanged inputs are not sent again ---------------------------------------------------------------------------

def test_an_unchanged_input_is_not_sent_again_and_the_child_sees_the_same_sample():
    proxy, slots, inputs = _proxy(Held)
    packed: list[str] = []
    pack = proxy._lanes.pack
    proxy._lanes.pack = lambda key, value: (packed.append(key), pack(key, value))[1]
    try:
        proxy.configure()
        proxy.activate()
        image = np.arange(240 * 320 * 3, dtype=np.uint32).astype(np.uint8).reshape(240, 320, 3)
        slots["img"].sample = Sample(image, 1.0)
        slots["x"].sample = Sample(0.25, 1.0)
        outs = [proxy.step(1.0 + 0.001 * k, inputs) for k in range(10)]
        assert sorted(packed) == ["img", "x"]                 # sent once each (before: 10 times each)
        assert [o["same_img"] for o in outs] == [False] + [True] * 9   # as inline: the very same sample
        assert [o["same_x"] for o in outs] == [False] + [True] * 9
        assert all(o["img_sum"] == float(image.sum()) and o["x"] == 0.25 for o in outs)
        # a new sample is sent, even with the same value and stamp (another object: another measurement)
        slots["x"].sample = Sample(0.25, 1.0)
        out = proxy.step(1.1, inputs)
        assert packed[2:] == ["x"] and out["same_x"] is False and out["same_img"] is True
        slots["x"].sample = Sample(0.75, 1.2)
        out = proxy.step(1.2, inputs)
        assert out["x"] == 0.75 and out["x_stamp"] == 1.2
        # a failed step (the child's component raised): everything is sent again at the next step
        slots["x"].sample = Sample("boom", 1.3)
        with pytest.raises(ComponentFault, match="iso-held failure"):
            proxy.step(1.3, inputs)
        n = len(packed)
        slots["x"].sample = Sample(1.25, 1.4)
        out = proxy.step(1.4, inputs)
        assert sorted(packed[n:]) == ["img", "x"] and out["x"] == 1.25 and out["img_sum"] == float(image.sum())
    finally:
        proxy.deactivate()
        proxy.close()
