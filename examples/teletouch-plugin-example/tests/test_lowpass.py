"""Tests of the example plugin: `pip install .` then `pytest tests` in this folder."""

import math
from pathlib import Path

from teletouch.testing import Harness, make_registry, run_yaml

import teletouch_plugin_example as plugin

GRAPH_TEXT = (Path(__file__).parents[1] / "graph.yaml").read_text()   # the graph beside pyproject.toml


def test_one_time_constant_after_a_step_gives_63_percent():
    tau = 1.0 / (2.0 * math.pi * 10.0)
    with Harness(plugin.LowPass, {"cutoff": 10.0}) as h:
        assert h.step(0.0, x=0.0)["y"] == 0.0
        assert abs(h.step(tau, x=1.0)["y"] - (1.0 - math.exp(-1.0))) < 1e-9


def test_in_a_graph():
    ys = {}
    tap = lambda node, t, out: node == "filter" and ys.update({t: out["y"].value})   # noqa: E731
    result, rt = run_yaml(GRAPH_TEXT, make_registry(plugin), duration=1.0, taps=[tap])
    assert result.exit_code == 0
    assert ys[0.1] == 0.0                                              # before the 2 N step at 0.2 s
    assert abs(ys[0.5] - 2.0 * (1.0 - math.exp(-0.3 * 2.0 * math.pi * 2.0))) < 0.02   # cutoff: 2Hz
