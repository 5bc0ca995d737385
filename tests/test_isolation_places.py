"""The error replies of an isolated node's child that carried no place (the component class that cannot be imported
there, a request it cannot unpickle) made a fault whose place was the proxy's own line in the parent
("isolation.py:NNN": nothing to look at). Now they name what to look at: the plugin's line that raised as its module
was imported in the child (a dependency missing there), else the class the child could not import; for an unreadable
request, the input values sent to the plugin."""

from __future__ import annotations

import sys
import time
import types

import numpy as np
import pytest

from teletouch.component import Component, Context, Inputs, Kind, Port, Sample, _Slot
from teletouch.errors import ComponentFault, exception_line
from teletouch.isolation import ProcessProxy

_PARENT_ONLY = "teletouch_s16b_parent_only"   # a module that exists in the test process only


def _parent_only() -> types.ModuleType:
    mod = sys.modules.get(_PARENT_ONLY)
    if mod is None:
        mod = types.ModuleType(_PARENT_ONLY)
        mod.Tag = type("Tag", (), {"__module__": _PARENT_ONLY})
        sys.modules[_PARENT_ONLY] = mod
    return mod


class Echo(Component):
    """Echoes ``x[0]``."""

    name = "s16b-echo"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (None,), "any", "")}
    outputs = {"y": Port("float64", (), "any", "")}

    def step(self, t, inputs):
        return {"y": float(inputs["x"].value[0])}


def _proxy(cls: type[Component]) -> ProcessProxy:
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=100.0)
    return ProcessProxy(cls, cls.Params(), node_id="n", ctx=ctx, t0_perf=0.0, t0_mono=0.0, step_timeout=20.0)


def _configure_fault(cls: type[Component]) -> str:
    proxy = _proxy(cls)
    try:
        with pytest.raises(ComponentFault) as caught:
            proxy.configure()
    finally:
        proxy.close()
    return exception_line(caught.value)


def test_a_component_class_the_child_cannot_import_names_the_class_not_the_proxy():
    mod = _parent_only()
    ghost = type("Ghost", (Echo,), {"__module__": _PARENT_ONLY, "__qualname__": "Ghost", "name": "s16b-ghost"})
    mod.Ghost = ghost
    line = _configure_fault(ghost)
    assert line.startswith(f"ComponentFault: in isolated process: cannot import the component class: "
                           f"ModuleNotFoundError: No module named '{_PARENT_ONLY}'"), line
    assert "isolation.py:" not in line, line   # before: (isolation.py:NNN), the proxy's line in the parent
    assert line.endswith(f" (class Ghost of module {_PARENT_ONLY})"), line


def test_a_plugin_module_that_fails_to_import_in_the_child_names_its_own_line(tmp_path, monkeypatch):
    (tmp_path / "s16b_child_fails.py").write_text(
        "import multiprocessing\n"
        "from teletouch.component import Component\n"
        "if multiprocessing.parent_process() is not None:   # in the isolated process only\n"
        "    import teletouch_s16b_not_installed\n"
        "class Fails(Component):\n"
        "    name = 's16b-fails'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    from s16b_child_fails import Fails

    line = _configure_fault(Fails)
    assert "No module named 'teletouch_s16b_not_installed'" in line, line
    assert "isolation.py:" not in line, line
    assert line.endswith(" (s16b_child_fails.py:4)"), line   # the plugin's import that failed there


def test_a_request_the_child_cannot_unpickle_names_the_input_values_sent_to_the_plugin():
    mod = _parent_only()
    proxy = _proxy(Echo)
    slot = _Slot()
    inputs = Inputs({"x": slot})
    try:
        proxy.configure()
        proxy.activate()
        slot.sample = Sample(np.full(2, 1.0), 0.0)
        assert proxy.step(0.0, inputs) == {"y": 1.0}
        slot.sample = Sample(np.full(2, 2.0, dtype=np.dtype(np.float64, metadata={"tag": mod.Tag()})), 0.01)
        with pytest.raises(ComponentFault) as caught:
            proxy.step(0.01, inputs)
        slot.sample = Sample(np.full(2, 3.0), 0.02)
        assert proxy.step(0.02, inputs) == {"y": 3.0}   # the child lives on
    finally:
        proxy.deactivate()
        proxy.close()
    line = exception_line(caught.value)
    assert "s16b-echo: a request from the parent cannot be unpickled in the isolated process: ModuleNotFoundError: " \
           f"No module named '{_PARENT_ONLY}'" in line, line
    assert "isolation.py:" not in line, line   # before: (isolation.py:NNN)
    assert line.endswith(" (the input values sent to s16b-echo)"), line
