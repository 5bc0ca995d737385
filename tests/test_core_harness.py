"""Harness.run steps at the very times (to the last bit) that a graph's simulated clock gives the same node: the
runtime turned its integer-nanosecond ticks into seconds as t_ns * 1e-9, the Harness as t_ns / 1e9, and the two
differed in the last bit at ticks such as 0.03 s at 100 Hz (a component that compares t with a threshold then stepped
differently in its test and in a graph). Both now use teletouch.runtime.graph_time."""

from __future__ import annotations

import pytest

from teletouch.mock import MockSensor
from teletouch.testing import Harness, make_registry, run_yaml


def _runtime_times(rate: float, duration: float) -> list[float]:
    text = f"""
clock: sim
nodes:
  - {{id: s, plugin: mock-sensor, rate: {rate!r}, params: {{signal: constant}}}}
"""
    ts: list[float] = []
    result, _ = run_yaml(text, make_registry(), duration=duration, taps=[lambda node, t, out: ts.append(t)])
    assert result.exit_code == 0, result.message
    return ts


@pytest.mark.parametrize("rate", [7.0, 100.0, 1000.0])
def test_harness_run_steps_at_the_runtimes_times_to_the_last_bit(rate):
    want = _runtime_times(rate, 0.5)
    with Harness(MockSensor, {"signal": "constant"}, rate=rate) as h:
        got = [t for t, _ in h.run(0.2)]
        got += [t for t, _ in h.run(0.5)]   # goes on from the next tick
        assert h.t == want[-1] and h.ctx.now() == want[-1]
    assert len(got) == len(want) and got == want, [(g, w) for g, w in zip(got, want) if g != w][:3]
