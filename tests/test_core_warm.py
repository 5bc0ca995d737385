"""Component.warm(): under the wall clock the runtime calls a node's warm() WARM_LEAD (1 ms) before each of its
steps, in its rate group's thread, so that a slow estimator's step finds its data in the CPU's caches; never under the
simulated clock, for a device or in a fast group (period under 5 x WARM_LEAD); an exception in it faults the node as
one in its step does. The depth node's warm() rehearses its last new frame without changing any output. (An isolated
node's warm-up: tests/test_isolation_warm.py.)"""

from __future__ import annotations

import time

import numpy as np
import pytest

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.sensors.sim_digit import DigitSimulator
from teletouch.runtime import EXIT_FAULT, EXIT_OK, Runtime
from teletouch.testing import Harness, make_registry, run_yaml

EVENTS: dict[str, list[tuple[str, float]]] = {}


class _Warmed(Component):
    """Records when its warm() and its step() begin (perf_counter)."""
    name = "warmed"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        fail: bool = False

    def configure(self):
        EVENTS[self.id] = []

    def warm(self):
        EVENTS[self.id].append(("warm", time.perf_counter()))
        if self.params.fail:
            raise RuntimeError("cache rehearsal failed")

    def step(self, t, inputs):
        EVENTS[self.id].append(("step", time.perf_counter()))
        return {"y": t}


class _WarmedDevice(Device):
    name = "warmed-device"
    outputs = {"y": Port("float64", (), "")}

    def configure(self):
        EVENTS[self.id] = []

    def warm(self):   # must never be called: a warm-up must not command hardware
        EVENTS[self.id].append(("warm", time.perf_counter()))

    def step(self, t, inputs):
        EVENTS[self.id].append(("step", time.perf_counter()))
        return {"y": t}

    def safe_state(self):
        pass


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Warmed, _WarmedDevice]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugin())


def _kinds(node: str) -> list[str]:
    return [k for k, _ in EVENTS[node]]


def test_wall_clock_warms_a_slow_node_shortly_before_each_step(reg):
    text = """
clock: wall
faults: {max_overruns: 0, watchdog: 5}
nodes:
  - {id: est, plugin: warmed, rate: 50}
  - {id: dev, plugin: mock-device, rate: 500}
"""
    res, _ = run_yaml(text, reg, duration=0.6)
    assert res.exit_code == EXIT_OK, res.message
    ev = EVENTS["est"]
    kinds = _kinds("est")
    assert kinds.count("step") >= 20, kinds
    # every step but the first (due at once, at t = 0) follows a warm-up of its own cycle
    assert all(kinds[i - 1] == "warm" for i, k in enumerate(kinds) if k == "step" and i > 1), kinds
    assert kinds.count("warm") >= kinds.count("step") - 2
    gaps = [b[1] - a[1] for a, b in zip(ev, ev[1:]) if a[0] == "warm" and b[0] == "step"]
    # about WARM_LEAD before the step; far less than the 20 ms period (the median: a loaded machine delays some)
    assert Runtime.WARM_LEAD * 0.5 < float(np.median(gaps)) < Runtime.WARM_LEAD + 0.005, gaps


def test_no_warm_up_under_the_sim_clock_for_a_device_or_in_a_fast_group(reg):
    sim = """
clock: sim
nodes:
  - {id: est, plugin: warmed, rate: 50}
"""
    res, _ = run_yaml(sim, reg, duration=0.5)
    assert res.exit_code == EXIT_OK, res.message
    assert _kinds("est").count("step") >= 20 and "warm" not in _kinds("est")
    wall = """
clock: wall
faults: {max_overruns: 0, watchdog: 5}
nodes:
  - {id: fast, plugin: warmed, rate: 1000}
  - {id: arm, plugin: warmed-device, rate: 50}
"""
    res, _ = run_yaml(wall, reg, duration=0.4)
    assert res.exit_code == EXIT_OK, res.message
    assert _kinds("fast").count("step") >= 100 and "warm" not in _kinds("fast")   # 1 ms period: no time for it
    assert _kinds("arm").count("step") >= 10 and "warm" not in _kinds("arm")


def test_an_exception_in_warm_faults_the_node_naming_warm(reg):
    text = """
clock: wall
faults: {watchdog: 5}
nodes:
  - {id: est, plugin: warmed, rate: 50, params: {fail: true}}
  - {id: dev, plugin: mock-device, rate: 500}
"""
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.exit_code == EXIT_FAULT, res.message
    (f,) = [f for f in res.faults if f.node == "est"]
    assert f.kind == "exception" and "warm(): RuntimeError: cache rehearsal failed" in f.message, f
    assert rt.component("dev").safe_calls >= 1
    assert _kinds("est").count("step") <= 1   # faulted at its first warm-up (after the step due at t = 0)


def _frames() -> list[np.ndarray]:
    sim = DigitSimulator("qvga", noise=2.0, seed=5)
    out = []
    for k, depth in enumerate((0.0, 0.4e-3, 0.8e-3, 0.8e-3, 1.1e-3, 0.0)):
        out.append(sim.render(depth, (0.5e-3 * k, -0.3e-3 * k))[0])
    return out


def test_the_depth_nodes_warm_up_rehearses_the_last_frame_without_changing_any_output():
    frames = _frames()
    with Harness(DepthEstimator, {}) as cold, Harness(DepthEstimator, {}) as warm:
        calls = [0]
        warm.comp.warm()   # before any frame: nothing to rehearse
        for k, frame in enumerate(frames):
            t = 0.1 * (k + 1)
            a = cold.step(t, image=frame)
            b = warm.step(t, image=frame)   # (after the warm-up of the frame before: the same outputs)
            for port in a:
                np.testing.assert_array_equal(np.asarray(a[port]), np.asarray(b[port]), err_msg=port)
            offset = warm.comp.pipe._offset.copy()
            warm.comp.pipe = _Counting(warm.comp.pipe, calls)
            warm.comp.warm()
            warm.comp.pipe = warm.comp.pipe.inner
            np.testing.assert_array_equal(warm.comp.pipe._offset, offset)   # the rehearsal's state put back
        assert calls[0] == len(frames)   # one rehearsal of the last frame per warm-up


class _Counting:
    """The depth pipeline, its rehearsals counted (what warm() runs)."""

    def __init__(self, inner, calls):
        self.inner = inner
        self.calls = calls

    def rehearse(self, frame):
        self.calls[0] += 1
        return self.inner.rehearse(frame)

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __setattr__(self, name, value):
        if name in ("inner", "calls"):
            object.__setattr__(self, name, value)
        else:
            setattr(self.inner, name, value)


def test_warm_false_rehearses_nothing():
    frame = _frames()[2]
    with Harness(DepthEstimator, {"warm": False}) as h:
        h.step(0.1, image=frame)
        calls = [0]
        h.comp.pipe = _Counting(h.comp.pipe, calls)
        h.comp.warm()
        assert calls[0] == 0


class _Costly(Component):
    """Its step and its warm-up each sleep ``step_s`` / ``warm_s`` (a warm-up that hangs: a long ``warm_s``; a slow
    first one only, a page fault or a loaded machine's pause: ``first_warm_s``)."""
    name = "costly"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        step_s: float = 0.0
        warm_s: float = 0.0
        first_warm_s: float | None = None

    def configure(self):
        self.warms = 0

    def warm(self):
        self.warms += 1
        first = self.params.first_warm_s
        time.sleep(first if self.warms == 1 and first is not None else self.params.warm_s)

    def step(self, t, inputs):
        time.sleep(self.params.step_s)
        return {"y": t}


class _CostlyPlugin:
    @hookimpl
    def teletouch_components(self):
        return [_Costly]


def test_a_warm_up_that_would_not_fit_the_period_beside_the_steps_is_left_out():
    # before: an 11 ms warm-up before an 11 ms step at 50 Hz (20 ms) overran every period, and the overrun fault
    # blamed the step, which fits alone
    reg = make_registry(_CostlyPlugin())
    text = """
clock: wall
faults: {max_overruns: 3, watchdog: 5}
nodes:
  - {id: est, plugin: costly, rate: 50, params: {step_s: 0.011, warm_s: 0.011}}
"""
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.exit_code == EXIT_OK, res.message
    assert rt.component("est").warms <= 2   # tried before its cost was known, then left out


def test_a_warm_up_that_hangs_is_named_as_the_warm_up_with_its_own_start():
    # before: "step did not return within 0.2 s (... it began at t=<the previous step's start>)"
    reg = make_registry(_CostlyPlugin())
    text = """
clock: wall
faults: {watchdog: 0.2}
nodes:
  - {id: est, plugin: costly, rate: 50, params: {warm_s: 1.0}}
  - {id: arm, plugin: mock-device, rate: 50}
"""
    res, _ = run_yaml(text, reg, duration=2.0)
    assert res.exit_code == EXIT_FAULT, res.message
    (f,) = [f for f in res.faults if f.node == "est"]
    assert f.kind == "timeout" and "(costly) warm() did not return within 0.2 s" in f.message, f.message
    began = float(f.message.split("it began at t=")[1].split(" s")[0])
    assert 0.015 < began < 0.05, f.message   # the warm-up 1 ms before the second step (t = 20 ms), not t = 0
    (d,) = [f for f in res.faults if f.node == "arm"]
    assert "waits for the warm() of node 'est'" in d.message, d.message


def test_one_slow_warm_up_does_not_turn_the_warm_up_off_for_the_rest_of_the_run():
    # before: the budget read the latest warm-up's time, which a skipped warm-up never renews: one 12 ms warm-up
    # at 50 Hz left the node cold for the whole run (1 warm-up in 100 steps)
    reg = make_registry(_CostlyPlugin())
    text = """
clock: wall
faults: {max_overruns: 0, watchdog: 5}
nodes:
  - {id: est, plugin: costly, rate: 50, params: {step_s: 0.001, warm_s: 0.0005, first_warm_s: 0.012}}
"""
    res, rt = run_yaml(text, reg, duration=2.0)
    assert res.exit_code == EXIT_OK, res.message
    assert rt.component("est").warms >= 40, rt.component("est").warms   # ~100 steps: warmed again a second later
