"""What a tap gets, as docs/recording.md shows it: ``tap(node, t, outputs)`` with ``outputs`` the mapping the step
returned, as it returned it: a bare value (stamped ``t``) or a ``Sample`` (``.value``, ``.stamp``) where the step gave
its own stamp. The doc's example is run here on a real graph, so that it cannot drift from the code."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from teletouch import Component, Kind, Port, Sample, hookimpl
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry, run_yaml

DOC = Path(__file__).resolve().parents[1] / "docs" / "recording.md"

GRAPH = """
clock: sim
duration: 0.1
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 2.0}}
  - {id: cam, plugin: s16-stamped, rate: 50}
"""


class Stamped(Component):
    """Returns its value with its own stamp, 10 ms before the step (a camera's capture time)."""

    name = "s16-stamped"
    kind = Kind.SENSOR
    outputs = {"frame": Port("float64", (), "", "a measurement")}
    default_rate = 50.0

    def step(self, t, inputs):
        return {"frame": Sample(3.0, t - 0.01)}


@hookimpl
def teletouch_components():
    return [Stamped]


def _registry():
    return make_registry(sys.modules[__name__])


def test_a_tap_gets_what_the_step_returned_a_sample_where_it_gave_its_own_stamp():
    got = []
    res, _ = run_yaml(GRAPH, _registry(), taps=[lambda node, t, out: got.append((node, t, dict(out)))])
    assert res.status == "ok", res.summary()
    cam = [(t, out["frame"]) for node, t, out in got if node == "cam"]
    src = [(t, out["value"]) for node, t, out in got if node == "src"]
    assert cam and src
    assert all(isinstance(s, Sample) and s.value == 3.0 and s.stamp == pytest.approx(t - 0.01) for t, s in cam), cam
    assert all(type(v) is float and v == 2.0 for _, v in src), src


def _doc_example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    taps = [b for b in blocks if "add_tap" in b]
    assert len(taps) == 1, f"{DOC}: expected one python example with add_tap, found {len(taps)}"
    return taps[0]


def test_the_documented_tap_example_runs_on_a_real_graph():
    rt = Runtime(load_text(GRAPH, _registry()), log=lambda m: None)
    scope = {"runtime": rt}
    exec(compile(_doc_example(), str(DOC), "exec"), scope)
    assert rt.run().status == "ok"
    signals = scope["signals"]
    assert set(signals) == {"src.value", "cam.frame"}, signals
    # stamps and values, as the example takes them apart: a Sample's own stamp, a bare value's step time
    assert signals["cam.frame"][:3] == [(pytest.approx(t - 0.01), 3.0) for t in (0.0, 0.02, 0.04)]
    assert signals["src.value"][:3] == [(pytest.approx(t), 2.0) for t in (0.0, 0.01, 0.02)]
