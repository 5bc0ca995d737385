"""The runtime's fault paths, audited adversarially: errors of every kind in every lifecycle call, in steps, in the
run loop and in the caller's own callbacks. Each must end with every device safe, every component closed once in
order, and the first error as the run's result."""

from __future__ import annotations

import decimal
import math
import threading
import time

import numpy as np
import pytest

from teletouch import Component, Device, Kind, Port, Sample, hookimpl
from teletouch.runtime import EXIT_FAULT, EXIT_STARTUP, Runtime
from teletouch.testing import load_text, make_registry

EVENTS: list[tuple[str, str]] = []   # (node, call) in the order the runtime made them, for the lifecycle tests


class _Probe(Component):
    """An estimator that raises what it is told to, where it is told to."""
    name = "probe"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        fail_in: str = ""          # configure | activate | step | deactivate | close
        error: str = "runtime"     # runtime | exit | interrupt
        at: float = 0.05           # s, for step
        output: str = "ok"         # ok | list | decimal-stamp | bool-stamp | numpy-stamp

    def _maybe_fail(self, where: str) -> None:
        EVENTS.append((self.id, where))
        if self.params.fail_in == where:
            raise {"runtime": RuntimeError(f"{where} failed"), "exit": SystemExit(f"{where} exits"),
                   "interrupt": KeyboardInterrupt()}[self.params.error]

    def configure(self):
        self._maybe_fail("configure")

    def activate(self):
        self._maybe_fail("activate")

    def deactivate(self):
        self._maybe_fail("deactivate")

    def close(self):
        self._maybe_fail("close")

    def step(self, t, inputs):
        if t >= self.params.at:
            if self.params.fail_in == "step":
                self._maybe_fail("step")
            out = self.params.output
            if out == "list":
                return [1.0]
            if out == "decimal-stamp":
                return {"y": Sample(1.0, decimal.Decimal(str(t)))}
            if out == "bool-stamp":
                return {"y": Sample(1.0, True)}
            if out == "numpy-stamp":
                return {"y": Sample(1.0, np.float32(t))}
        return {"y": 1.0}


class _Dev(Device):
    """A device that logs its calls (with the thread that made them) and counts overlapping safe_state() calls."""
    name = "log-device"
    inputs = {"command": Port("float64", (), "any", required=False)}
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        safe_error: str = ""       # exit: safe_state() raises SystemExit | sigint: it gets a SIGINT (a 2nd Ctrl-C)
        safe_wait: bool = False    # safe_state() waits for self.release (set by the test)

    def configure(self):
        EVENTS.append((self.id, "configure"))
        self.log: list[tuple] = []
        self.safe = False
        self.active_calls = 0
        self.max_overlap = 0
        self.release = threading.Event()

    def activate(self):
        EVENTS.append((self.id, "activate"))

    def step(self, t, inputs):
        self.log.append(("step", t, self.safe, threading.get_ident()))
        return {"y": t}

    def safe_state(self):
        EVENTS.append((self.id, "safe_state"))
        self.active_calls += 1
        self.max_overlap = max(self.max_overlap, self.active_calls)
        try:
            self.log.append(("safe", threading.get_ident()))
            if self.params.safe_wait:
                self.release.wait(5.0)
            self.safe = True
            if self.params.safe_error == "exit":
                raise SystemExit("safe_state exits")
            if self.params.safe_error == "sigint":
                import os
                import signal

                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.01)
        finally:
            self.active_calls -= 1

    def deactivate(self):
        EVENTS.append((self.id, "deactivate"))

    def close(self):
        EVENTS.append((self.id, "close"))


class _Sleepy(Component):
    """Its step blocks once (a camera read that hangs), for ``block`` seconds from ``at``."""
    name = "sleepy"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        at: float = 0.05
        block: float = 2.5

    def configure(self):
        self.stepping = False
        self.blocked = False
        self.closed_during_step = None

    def step(self, t, inputs):
        if t >= self.params.at and not self.blocked:
            self.blocked = True
            self.stepping = True
            time.sleep(self.params.block)
            self.stepping = False
        return {"y": t}

    def close(self):
        self.closed_during_step = self.stepping


class _FakeSlow(Component):
    """Its step takes ``took`` seconds of the fake clock the overrun test drives the rate group with."""
    name = "fake-slow"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}
    clock: list[float] = [0.0]

    class Params(Component.Params):
        took: float = 0.015

    def step(self, t, inputs):
        self.clock[0] += self.params.took
        return {"y": t}


class _Plugins:
    @hookimpl
    def teletouch_components(self):
        return [_Probe, _Dev, _Sleepy, _FakeSlow]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugins())


def _runtime(text: str, reg, **kw) -> Runtime:
    return Runtime(load_text(text, reg), log=lambda m: None, **kw)


def _events(ids: set[str] | None = None) -> list[tuple[str, str]]:
    return [e for e in EVENTS if ids is None or e[0] in ids]


# --------------------------------------------------------------------------------------- lifecycle order, run once
def test_a_runtime_runs_once(reg):
    rt = _runtime("clock: sim\nnodes:\n  - {id: d, plugin: log-device, rate: 100}\n", reg)
    assert rt.run(0.3).status == "ok"
    # a second run re-configured the closed components and "ran" one step of 0.3 s, reported ok
    with pytest.raises(RuntimeError, match="has already run and its components are closed; build a new Runtime"):
        rt.run(0.3)


@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_an_activate_failure_takes_the_active_nodes_safe_and_closes_all_once_in_reverse_order(reg, clock):
    EVENTS.clear()
    text = f"""
clock: {clock}
nodes:
  - {{id: d1, plugin: log-device, rate: 100}}
  - {{id: p2, plugin: probe, rate: 100}}
  - {{id: p3, plugin: probe, rate: 100, params: {{fail_in: activate}}}}
  - {{id: d4, plugin: log-device, rate: 100}}
"""
    res = _runtime(text, reg).run(0.3)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert res.message.startswith("node 'p3' (probe) failed to activate: RuntimeError: activate failed")
    assert _events() == [("d1", "configure"), ("p2", "configure"), ("p3", "configure"), ("d4", "configure"),
                         ("d1", "activate"), ("p2", "activate"), ("p3", "activate"),
                         ("d1", "safe_state"), ("d4", "safe_state"),
                         ("p2", "deactivate"), ("d1", "deactivate"),
                         ("d4", "close"), ("p3", "close"), ("p2", "close"), ("d1", "close")]


# --------------------------------------------------------------------------------------------- errors in steps
def test_sim_a_device_disabled_by_an_upstream_fault_is_not_stepped_after_its_safe_state(reg):
    text = """
clock: sim
faults: {on_fault: degrade}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {fail_at: 0.1}}
  - {id: d, plugin: log-device, rate: 1000, inputs: {command: src.value}}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.3)
    assert res.status == "degraded"
    log = rt.component("d").log
    first_safe = next(i for i, e in enumerate(log) if e[0] == "safe")
    # it was stepped once more (t = 0.1 s) after its safe state: a real driver would have sent that step's command
    assert [e for e in log[first_safe:] if e[0] == "step"] == []
    assert {n.id: n.steps for n in res.nodes}["d"] == 100


@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_system_exit_from_a_step_is_a_fault_of_its_node(reg, clock):
    # sim: the SystemExit went through run() (no result); wall: it ended the rate group's thread in silence and the
    # run was "ok" with that node no longer stepped
    text = f"""
clock: {clock}
nodes:
  - {{id: p, plugin: probe, rate: 100, params: {{fail_in: step, error: exit}}}}
  - {{id: d, plugin: log-device, rate: 50}}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.6)
    assert res.status == "fault" and res.exit_code == EXIT_FAULT
    assert "node 'p' exception: SystemExit: step exits" in res.message
    assert rt.component("d").safe


def test_a_step_that_returns_no_mapping_is_a_fault_that_says_what_was_expected(reg):
    res = _runtime("clock: sim\nnodes:\n  - {id: p, plugin: probe, rate: 100, params: {output: list}}\n",
                   reg).run(0.2)
    assert res.status == "fault"
    assert "step() returned list [1.0]; expected a mapping of output name to value (outputs: y) or None" \
           in res.message


@pytest.mark.parametrize("output, says", [("decimal-stamp", "stamped Decimal('0.05')"), ("bool-stamp", "stamped True")])
def test_a_stamp_that_is_not_a_real_number_of_seconds_is_a_fault_of_its_producer(reg, output, says):
    # a Decimal stamp was stored; the consumer's staleness check then raised TypeError out of run()
    text = f"""
clock: sim
faults: {{startup_grace: 0}}
nodes:
  - {{id: p, plugin: probe, rate: 100, params: {{output: {output}}}}}
  - {{id: d, plugin: log-device, rate: 100, inputs: {{command: {{from: p.y, max_age: 0.05}}}}}}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.2)
    assert res.status == "fault" and "node 'p' exception" in res.message
    assert f"output 'y' {says}: a stamp must be a finite graph time in seconds" in res.message
    assert rt.component("d").safe


def test_a_numpy_stamp_is_kept_as_a_float(reg):
    rt = _runtime("clock: sim\nnodes:\n  - {id: p, plugin: probe, rate: 100, params: {output: numpy-stamp}}\n",
                  reg)
    assert rt.run(0.2).status == "ok"
    s = rt.latest("p", "y")
    assert type(s.stamp) is float and s.stamp == pytest.approx(0.2)


# ----------------------------------------------------------------------------------------- errors at shutdown
@pytest.mark.parametrize("where, error", [("deactivate", "exit"), ("close", "exit"), ("deactivate", "interrupt"),
                                          ("close", "interrupt")])
def test_an_error_of_any_kind_at_shutdown_is_reported_and_the_others_are_still_closed(reg, where, error):
    # a SystemExit or KeyboardInterrupt from one component's deactivate()/close() went through run() and left the
    # components after it in the shutdown order open (and the device before it never deactivated)
    EVENTS.clear()
    text = f"""
clock: sim
nodes:
  - {{id: d1, plugin: log-device, rate: 100}}
  - {{id: p, plugin: probe, rate: 100, params: {{fail_in: {where}, error: {error}}}}}
  - {{id: d2, plugin: log-device, rate: 100}}
"""
    res = _runtime(text, reg).run(0.2)
    assert res.status == "ok"
    assert [e for e in _events({"d1", "d2"}) if e[1] in ("deactivate", "close")] == [
        ("d2", "deactivate"), ("d1", "deactivate"), ("d2", "close"), ("d1", "close")]
    shutdown = [f for f in res.faults if f.kind == "shutdown"]
    kind = "SystemExit" if error == "exit" else "KeyboardInterrupt"
    assert len(shutdown) == 1 and shutdown[0].node == "p" and shutdown[0].message.startswith(f"{where}() raised "
                                                                                             f"{kind}")


def test_a_safe_state_that_raises_system_exit_is_reported_under_the_wall_clock(reg):
    # the helper thread caught Exception only: SystemExit ended it in silence and the call counted as done
    rt = _runtime("clock: wall\nnodes:\n  - {id: d, plugin: log-device, rate: 100, params: {safe_error: exit}}\n",
                  reg)
    res = rt.run(0.2)
    raised = [f for f in res.faults if f.kind == "shutdown" and f.node == "d"]
    assert raised and raised[0].message.startswith("safe_state() raised SystemExit: safe_state exits")


# ------------------------------------------------------------------------------------------- safe-state calls
def test_sim_clock_safe_state_runs_inline_in_the_thread_that_steps(reg):
    rt = _runtime("clock: sim\nnodes:\n  - {id: d, plugin: log-device, rate: 100}\n", reg)
    rt.run(0.1)
    log = rt.component("d").log
    threads = {e[3] for e in log if e[0] == "step"} | {e[1] for e in log if e[0] == "safe"}
    assert threads == {threading.get_ident()}


def test_safe_state_calls_for_one_device_never_overlap(reg):
    # two callers at once (a rate group leaving its loop and the shutdown; or a call whose wait a Ctrl-C cut short
    # and the shutdown's): the second used to start a second safe_state() beside the first
    rt = _runtime("clock: wall\nfaults: {safe_timeout: 5}\nnodes:\n"
                  "  - {id: d, plugin: log-device, rate: 100, params: {safe_wait: true}}\n", reg)
    node = rt.nodes[0]
    dev = rt.component("d")
    dev.configure()
    callers = [threading.Thread(target=rt._safe, args=(node,)) for _ in range(2)]
    for th in callers:
        th.start()
    while not any(e[0] == "safe" for e in dev.log):   # the first call is inside safe_state()
        time.sleep(0.001)
    for _ in range(20):                                # let the second caller arrive
        time.sleep(0.005)
    dev.release.set()
    for th in callers:
        th.join(10.0)
    assert dev.max_overlap == 1
    assert not node.hung and not [f for f in rt.faults if f.kind == "hung"]


# ------------------------------------------------------------------------------------- overruns in a rate group
@pytest.mark.parametrize("policy", ["stop", "degrade"])
def test_an_overrun_fault_goes_to_the_slow_member_of_a_rate_group_not_to_its_neighbours(reg, policy):
    # a fake clock drives the group's loop (deterministic): the 15 ms step of `slow` makes every 10 ms cycle late.
    # The fault went to every member, the healthy device first: `stop` named the device, `degrade` disabled it too
    text = f"""
clock: wall
faults: {{max_overruns: 3, on_fault: {policy}}}
nodes:
  - {{id: dev, plugin: log-device, rate: 100}}
  - {{id: slow, plugin: fake-slow, rate: 100}}
"""
    rt = _runtime(text, reg)
    assert rt._startup() is None
    clock = _FakeSlow.clock
    clock[0] = 0.0
    stop = rt._stop_evt

    def perf() -> float:
        clock[0] += 1e-6
        if clock[0] > 0.5:
            stop.set()
        return clock[0]

    def sleep(s: float) -> None:
        clock[0] += s

    members = list(rt.nodes)
    for n in members:
        n.starts = [0.0] * rt.JITTER_RING
    try:
        rt._wall_steps(members, 0.01, 2e-4, perf, sleep, 0.0, stop, 3, rt.JITTER_RING)
    finally:
        rt._shutdown()
    overruns = [f for f in rt.faults if f.kind == "overrun"]
    assert [f.node for f in overruns] == ["slow"]
    assert "missed its 10.000 ms period 4 times in a row (its last step took 15.00" in overruns[0].message
    assert "the longest of the 2 nodes at this rate" in overruns[0].message
    by_id = {n.id: n for n in rt.nodes}
    assert not by_id["dev"].faulted and by_id["slow"].faulted
    if policy == "stop":
        assert rt._stop_reason[2].startswith("node 'slow' overrun")
    else:   # the device went on stepping to the end of the (fake) run
        assert by_id["dev"].steps > 20


# -------------------------------------------------------------------------- a step still running at the end
def test_a_step_still_running_when_the_run_ends_is_not_closed_under(reg):
    # wall clock: `sleepy`'s step blocks 2.5 s; the run ends at 0.2 s. The join gives up after 1 s; close() was then
    # called while the step still ran in its thread (a model or camera released under a running step)
    EVENTS.clear()
    text = """
clock: wall
nodes:
  - {id: s, plugin: sleepy, rate: 50, params: {at: 0.05, block: 2.5}}
  - {id: d, plugin: log-device, rate: 100}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.2)
    sleepy = rt.component("s")
    assert sleepy.closed_during_step is None      # not closed at all: left behind, and said so
    skipped = [f for f in res.faults if f.node == "s" and f.kind == "shutdown"]
    assert skipped and "deactivate() and close() skipped: its step() was still running" in skipped[0].message
    assert rt.component("d").safe and ("d", "close") in EVENTS


# ------------------------------------------------------------------------------ the caller's code, the loop itself
@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_a_progress_callback_that_raises_ends_the_run_as_a_fault_with_a_result(reg, clock):
    def progress(rt, t):
        raise BrokenPipeError("stderr closed")

    # (no overrun faults: on a loaded machine ten late 1 kHz steps in a row could end the run before the callback)
    text = f"clock: {clock}\nfaults: {{max_overruns: 0}}\nnodes:\n  - {{id: d, plugin: log-device, rate: 1000}}\n"
    rt = _runtime(text, reg)
    res = rt.run(2.0 if clock == "sim" else 0.5, progress=progress, progress_interval=0.0)
    assert res.status == "fault" and res.exit_code == EXIT_FAULT
    assert "the progress callback raised BrokenPipeError: stderr closed" in res.message
    assert res.faults[0].kind == "progress" and rt.component("d").safe


def test_an_error_in_the_loop_outside_a_step_stops_the_run_instead_of_ending_its_thread_in_silence(reg):
    text = """
clock: wall
faults: {startup_grace: 0}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: g, plugin: mock-gain, rate: 50, inputs: {x: {from: src.value, max_age: 0.1}}}
  - {id: d, plugin: log-device, rate: 100}
"""
    rt = _runtime(text, reg)

    def broken(node, t):
        raise AttributeError("the staleness check broke")

    rt._check_stale = broken
    res = rt.run(0.5)
    assert res.status == "fault" and res.exit_code == EXIT_FAULT
    assert "the thread of 'g' ended with AttributeError: the staleness check broke" in res.message
    assert rt.component("d").safe


def test_a_logger_that_fails_does_not_break_the_fault_handling(reg):
    def log(msg):
        raise BrokenPipeError("stderr closed")

    text = """
clock: sim
faults: {on_fault: degrade}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {fail_at: 0.1}}
  - {id: d, plugin: log-device, rate: 100}
"""
    res = Runtime(load_text(text, reg), log=log).run(0.3)
    assert res.status == "degraded" and "'src' (exception at t=0.100 s)" in res.message


def test_an_interrupt_after_a_fault_keeps_the_fault_as_the_result(reg):
    # the operator presses Ctrl-C while the faulted run shuts down: the result was "interrupted", hiding the fault
    EVENTS.clear()
    text = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {fail_at: 0.1}}
  - {id: k, plugin: log-device, rate: 100, params: {safe_error: sigint}}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.3)
    assert res.status == "fault" and res.exit_code == EXIT_FAULT
    assert res.message.startswith("node 'src' exception: RuntimeError: mock-sensor failure at t=0.100")
    assert res.message.endswith("; then interrupted (Ctrl-C); devices driven to their safe state"), res.message
    assert rt.component("k").safe and ("k", "close") in EVENTS


def test_nan_from_a_step_is_passed_on_as_it_is(reg):
    # the contract (docs/graphs.md): the runtime does not hide NaN; the consumer sees it and must guard
    rt = _runtime("clock: sim\nnodes:\n  - {id: s, plugin: mock-sensor, rate: 100, params: {nan_at: 0.1}}\n", reg)
    res = rt.run(0.2)
    assert res.status == "ok" and math.isnan(rt.latest("s", "value").value)


def test_a_constructor_that_raises_names_its_node():
    """A component's __init__ that raises was a bare exception out of Runtime(): which node of the graph?"""
    from teletouch.errors import ComponentFault
    from teletouch.mock import MockGain

    class Fragile(MockGain):
        name = "fragile-gain"

        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            raise ValueError("no such device file")

    @hookimpl
    def teletouch_components():
        return [Fragile]

    import types

    reg = make_registry(types.SimpleNamespace(__name__="fragile", teletouch_components=teletouch_components))
    spec = load_text("clock: sim\nduration: 0.1\nnodes:\n  - {id: src, plugin: mock-sensor, rate: 10}\n"
                     "  - {id: g, plugin: fragile-gain, rate: 10, inputs: {x: src.value}}\n", reg)
    with pytest.raises(ComponentFault, match=r"node 'g': fragile-gain could not be created: ValueError: no such "
                                             r"device file \(test_core_runtime_faults.py:\d+\)"):
        Runtime(spec)
