"""Under the wall clock the runtime shortens the interpreter's GIL switch interval to Runtime.SWITCH_FRACTION of the
fastest rate's period (20 us at 1 kHz; at least 5 us), and puts the old value back when the run ends; the
simulated clock leaves it alone."""

from __future__ import annotations

import sys

import pytest

from teletouch.component import Component, Kind
from teletouch.hookspecs import hookimpl
from teletouch.runtime import Runtime
from teletouch.testing import make_registry, run_yaml


class SwitchSpy(Component):
    """Records the interpreter's switch interval in every step."""

    name = "s13-switch-spy"
    kind = Kind.SENSOR
    inputs: dict = {}
    outputs: dict = {}
    default_rate = 100.0

    def configure(self):
        self.seen: list[float] = []

    def step(self, t, inputs):
        self.seen.append(sys.getswitchinterval())
        return None


@hookimpl
def teletouch_components():
    return [SwitchSpy]


@pytest.fixture
def registry():
    return make_registry(sys.modules[__name__])


@pytest.fixture(autouse=True)
def keep_switch_interval():
    old = sys.getswitchinterval()
    sys.setswitchinterval(0.005)
    yield
    sys.setswitchinterval(old)


def _spy(rt):
    return rt.component("spy")


@pytest.mark.parametrize("fast, expected", [(1000.0, 2e-5), (100.0, 2e-4), (10000.0, 5e-6)])
def test_wall_clock_sets_the_interval_from_the_fastest_rate_and_restores_it(registry, fast, expected):
    text = f"""
clock: wall
faults: {{max_overruns: 0}}   # a loaded machine's late ticks are counted, not a fault
nodes:
  - {{id: spy, plugin: s13-switch-spy, rate: 20}}
  - {{id: fast, plugin: s13-switch-spy, rate: {fast:g}}}
"""
    _, rt = run_yaml(text, registry, duration=0.3)
    seen = _spy(rt).seen + rt.component("fast").seen
    assert seen and all(v == pytest.approx(expected, rel=1e-6) for v in seen)
    assert sys.getswitchinterval() == pytest.approx(0.005)


def test_a_shorter_interval_set_by_the_program_is_kept(registry):
    sys.setswitchinterval(1e-5)
    _, rt = run_yaml("clock: wall\nfaults: {max_overruns: 0}\nnodes:\n  - {id: spy, plugin: s13-switch-spy, "
                     "rate: 1000}\n", registry, duration=0.2)
    assert _spy(rt).seen and max(_spy(rt).seen) == pytest.approx(1e-5)
    assert sys.getswitchinterval() == pytest.approx(1e-5)


def test_the_simulated_clock_leaves_the_interval_alone(registry):
    _, rt = run_yaml("clock: sim\nnodes:\n  - {id: spy, plugin: s13-switch-spy, rate: 1000}\n", registry,
                     duration=0.05)
    assert _spy(rt).seen and all(v == pytest.approx(0.005) for v in _spy(rt).seen)


def test_the_fraction_is_two_percent_of_the_period():
    assert Runtime.SWITCH_FRACTION == pytest.approx(0.02)
