"""Review of the runtime core: one fault per failure (the first cause wins), a device made safe again after a step
that ran through its fault, the isolation warning from where the clock is known, and Params that refuse a boolean
for a number on assignment as at construction."""

from __future__ import annotations

import sys
import time

import pytest
from pydantic import Field, ValidationError

from teletouch.component import Params
from teletouch.graph import load_graph_text
from teletouch.hookspecs import hookimpl
from teletouch.mock import MockBurn, MockDevice
from teletouch.runtime import EXIT_FAULT, Runtime
from teletouch.testing import make_registry, run_yaml


class HangThenRaise(MockBurn):
    """A node whose step hangs once (``hang_for`` s at ``hang_at``) and then raises: a driver call that times out."""

    name = "review-hang-raise"

    def step(self, t, inputs):
        p = self.params
        if p.hang_at is not None and t >= p.hang_at and not getattr(self, "_hung", False):
            self._hung = True
            time.sleep(p.hang_for)
            raise TimeoutError("the call timed out")
        return {"y": inputs.value("x", 0.0), "pid": 0}


class LateWriteDevice(MockDevice):
    """A device whose step blocks once (``sleep_for`` s at ``sleep_at``) in a hardware read, then writes the command
    it computed before the read (``late_command``) to the hardware: what a driver does whose step began before the
    watchdog made it safe. ``raise_after``: the step raises after that write (a driver call that timed out)."""

    name = "review-late-write"

    class Params(MockDevice.Params):
        sleep_at: float = Field(0.3, description="s")
        sleep_for: float = Field(0.5, description="s")
        late_command: float = Field(5.0, description="the command written after the read")
        raise_after: bool = Field(False, description="raise after the late write")

    def step(self, t, inputs):
        p = self.params
        if t >= p.sleep_at and not getattr(self, "_slept", False):
            self._slept = True
            time.sleep(p.sleep_for)
            self.safe = False                  # the write in flight undoes what safe_state() did
            self.command = p.late_command
            if p.raise_after:
                raise TimeoutError("the read timed out")
        return super().step(t, inputs)


@hookimpl
def teletouch_components():
    return [HangThenRaise, LateWriteDevice]


def _reg():
    return make_registry(sys.modules[__name__])


# --- 1. an inline step that raises after the watchdog faulted its node: one fault, the first cause --------------------

INLINE_HANG_RAISE = """
clock: wall
faults: {watchdog: 0.1, on_fault: POLICY}
nodes:
  - {id: est, plugin: review-hang-raise, rate: 100, params: {burn: 0ms, hang_at: 0.3, hang_for: 0.5}}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
  - {id: tick, plugin: mock-sensor, rate: 50}
"""


def test_a_step_that_raises_after_the_watchdog_faulted_its_node_adds_no_second_fault_under_stop():
    res, rt = run_yaml(INLINE_HANG_RAISE.replace("POLICY", "stop"), _reg(), duration=2.0)
    assert res.exit_code == EXIT_FAULT
    assert res.message.startswith("node 'est' timeout: (review-hang-raise) step did not return within 0.1 s"), \
        res.message
    assert [(f.node, f.kind) for f in res.faults] == [("est", "timeout"), ("dev", "stall")], \
        [f.line() for f in res.faults]
    assert rt.component("dev").safe


def test_a_step_that_raises_after_the_watchdog_faulted_its_node_is_listed_once_under_degrade():
    res, rt = run_yaml(INLINE_HANG_RAISE.replace("POLICY", "degrade"), _reg(), duration=1.5)
    assert res.status == "degraded", res.message
    assert [(f.node, f.kind) for f in res.faults] == [("est", "timeout"), ("dev", "upstream")], \
        [f.line() for f in res.faults]
    assert res.message.count("'est'") == 1, res.message
    assert "TimeoutError" not in res.message
    assert rt.component("dev").safe


# --- a device faulted while its step ran is made safe again when that step returns ------------------------------------

LATE_WRITE = """
clock: wall
faults: {watchdog: 0.1, on_fault: degrade}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 1.0}}
  - {id: ctl, plugin: mock-gain, rate: 100, inputs: {x: src.value}}
  - {id: leader, plugin: review-late-write, rate: 100, params: {safe_value: 0.0, RAISE}, inputs: {command: ctl.y}}
"""


@pytest.mark.parametrize("raise_after", [False, True])
def test_a_device_that_its_own_step_commanded_after_the_watchdog_made_it_safe_is_made_safe_again_at_once(raise_after):
    """The leader's step blocks 0.5 s at t = 0.3 s: the watchdog makes it safe (zero force) at about 0.4 s; then the
    step goes on and writes its force. Its rate group goes on (ctl is healthy, degrade): before, nothing made the
    leader safe again until the end of the run (2 s), so the hand felt that force for the rest of the run (or, when
    the step then raised, only a second `exception` fault did)."""
    seen: list[tuple[float, float, bool]] = []
    holder: list[Runtime] = []

    def tap(node, t, out):
        if node == "src" and holder:
            dev = holder[0].component("leader")
            seen.append((t, dev.command, dev.safe))

    text = LATE_WRITE.replace("RAISE", f"raise_after: {str(raise_after).lower()}")
    spec = load_graph_text(text, "<test>", registry=_reg())
    rt = Runtime(spec, log=lambda m: None)
    holder.append(rt)
    rt.add_tap(tap)
    calls: list[float] = []
    original = rt.component("leader").safe_state

    def spy():
        calls.append(rt.now())
        original()

    rt.component("leader").safe_state = spy
    res = rt.run(2.0)
    assert [(f.node, f.kind) for f in res.faults] == [("leader", "stall")], [f.line() for f in res.faults]
    # made safe by the watchdog, and again right after the step that wrote the force returned (t ~ 0.8 s)
    assert len(calls) >= 2 and calls[0] < 0.6 and 0.75 < calls[1] < 1.2, calls
    # from shortly after the step returned to the end of the run, the leader holds its safe command
    late = [(t, cmd, safe) for t, cmd, safe in seen if 1.3 < t < 1.9]
    assert late and all(cmd == 0.0 and safe for _, cmd, safe in late), late[:3]


# --- 2. the isolation warning under the clock the Runtime runs ------------------------------------------------------

SHARED = """\
clock: sim
duration: 1
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: est, plugin: mock-burn, rate: 100, params: {burn: 0ms}, inputs: {x: src.value}, isolate: process}
  - {id: leader, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""


def test_a_runtime_on_the_wall_clock_warns_about_an_isolated_node_beside_a_device_of_a_sim_graph():
    spec = load_graph_text(SHARED, "lab.yaml", registry=make_registry())
    assert spec.warnings == []                       # loaded for the sim clock: the node would run inline
    lines: list[str] = []
    rt = Runtime(spec, clock="wall", log=lines.append)
    try:
        assert len(rt.warnings) == 1, rt.warnings
        assert rt.warnings[0].startswith("lab.yaml:5: node 'est' (isolate: process) shares its rate, 100 Hz, with "
                                         "device node 'leader': under the wall clock"), rt.warnings
        assert lines == [f"warning: {rt.warnings[0]}"], lines
    finally:
        for n in rt.nodes:     # never run: end the isolated node's process
            n.comp.close()
    # the same spec on its own clock: no warning
    lines.clear()
    assert Runtime(spec, log=lines.append).warnings == [] and lines == []


def test_a_runtime_on_the_sim_clock_has_no_warning_and_one_the_loader_gave_is_not_repeated():
    wall = SHARED.replace("clock: sim", "clock: wall")
    spec = load_graph_text(wall, "lab.yaml", registry=make_registry())
    assert len(spec.warnings) == 1
    lines: list[str] = []
    rt = Runtime(spec, clock="sim", log=lines.append)
    assert rt.warnings == [] and lines == []           # runs inline under the simulated clock
    rt = Runtime(spec, log=lines.append)
    try:
        assert rt.warnings == spec.warnings
        assert lines == []                               # the loader's caller (teletouch run) has printed it
    finally:
        for n in rt.nodes:
            n.comp.close()


# --- 3. Params refuse a boolean for a number on assignment too -------------------------------------------------------

class _P(Params):
    scale: float = 1.0
    count: int = 0
    flag: bool = False
    maybe: float | None = None


@pytest.mark.parametrize("field", ["scale", "count", "maybe"])
def test_assigning_a_boolean_to_a_number_field_is_refused_with_the_construction_message(field):
    with pytest.raises(ValidationError) as built:
        _P(**{field: True})
    p = _P(scale=2.0, count=3, maybe=0.5)
    with pytest.raises(ValidationError) as assigned:
        setattr(p, field, True)
    want = f"{field}: expected a number, got a boolean (YAML reads yes, no, on and off as true and false)"
    assert want in str(built.value) and want in str(assigned.value), (str(built.value), str(assigned.value))
    assert (p.scale, p.count, p.maybe) == (2.0, 3, 0.5)   # unchanged


def test_assignment_still_takes_booleans_for_bool_fields_and_numbers_for_numbers():
    p = _P()
    p.flag = True
    p.scale = 3
    p.count = 4
    p.maybe = None
    assert (p.flag, p.scale, p.count, p.maybe) == (True, 3.0, 4, None)
    with pytest.raises(ValidationError, match="scale"):
        p.scale = "fast"
    assert p.scale == 3.0


class _Q(Params):
    cutoff: float = Field(100.0, gt=0, json_schema_extra={"unit": "Hz"})


def test_assigning_a_quantity_with_units_is_converted_to_si_as_at_construction():
    assert _Q(cutoff="2kHz").cutoff == 2000.0
    q = _Q()
    q.cutoff = "3kHz"
    assert q.cutoff == 3000.0
    with pytest.raises(ValidationError) as built:
        _Q(cutoff="3mm")
    with pytest.raises(ValidationError) as assigned:
        q.cutoff = "3mm"
    first = str(built.value).splitlines()[1]
    assert first.startswith("  Value error, cutoff: ") and first.split(" [type=")[0] in str(assigned.value), \
        (str(built.value), str(assigned.value))
    assert q.cutoff == 3000.0
    with pytest.raises(ValidationError, match="greater than 0"):
        q.cutoff = "-1kHz"                                # the field's own rules still apply
    assert q.cutoff == 3000.0


# --- overruns: counted for the nodes the late cycles would have stepped, not for one disabled ------------------------

def test_a_node_disabled_by_a_fault_counts_no_overruns_for_the_late_cycles_of_its_rate_group_after_it():
    """`bad` faults at t = 0.05 s (degrade); `slow`, at its rate, makes every cycle of the group late (15 ms at
    100 Hz) until the end. `bad` is not stepped after its fault: the ticks its group misses after it are not its
    overruns (before, it showed as many as `slow`)."""
    text = """
clock: wall
faults: {max_overruns: 0}
nodes:
  - {id: bad, plugin: mock-sensor, rate: 100, params: {fail_at: 0.05}, on_fault: degrade}
  - {id: slow, plugin: mock-burn, rate: 100, params: {burn: 15ms}}
"""
    res, _ = run_yaml(text, make_registry(), duration=0.8)
    assert [(f.node, f.kind) for f in res.faults] == [("bad", "exception")], [f.line() for f in res.faults]
    stats = {n.id: n for n in res.nodes}
    assert stats["slow"].overruns >= 15, stats["slow"]
    assert stats["bad"].overruns <= 6, (stats["bad"].overruns, stats["slow"].overruns)


# --- Ctrl-C: a second one while the rate groups are joined leaves the interpreter as it was ---------------------------

def test_a_second_ctrl_c_while_the_threads_are_joined_restores_the_gil_switch_interval():
    """Wall clock: the first Ctrl-C ends the run; while the runtime waits for a rate group whose step hangs (1 s at
    most), a second one arrives. Before, it cut that wait short before the interpreter's switch interval, shortened
    for the run (2% of the fastest period: 20 us here), was put back: the process went on switching threads every
    20 us after the run."""
    import _thread
    import threading

    text = """
clock: wall
faults: {watchdog: 0}
nodes:
  - {id: est, plugin: mock-burn, rate: 50, params: {burn: 0ms, hang_at: 0.2, hang_for: 1.5}}
  - {id: dev, plugin: mock-device, rate: 1000}
"""
    spec = load_graph_text(text, "<test>", registry=make_registry())
    rt = Runtime(spec, log=lambda m: None)
    before = sys.getswitchinterval()

    def progress(runtime, t):
        if t > 0.4:   # est hangs in its step: the first Ctrl-C now, the second 0.2 s later (during the join)
            threading.Timer(0.2, _thread.interrupt_main).start()
            raise KeyboardInterrupt

    try:
        res = rt.run(3.0, progress=progress, progress_interval=0.05)
    finally:
        now = sys.getswitchinterval()
        sys.setswitchinterval(before)
    assert res.status == "interrupted", res.message
    assert now == before, (now, before)
    assert rt.component("dev").safe


def test_a_ctrl_c_while_the_rate_group_threads_are_started_restores_the_gil_switch_interval(monkeypatch):
    """A Ctrl-C that arrives while the threads are being started (here: as the second one starts) ends the run as
    interrupted with the devices safe; before, the switch interval, shortened just before, stayed shortened."""
    import threading

    text = """
clock: wall
nodes:
  - {id: fast, plugin: mock-device, rate: 1000}
  - {id: slow, plugin: mock-device, rate: 100}
"""
    spec = load_graph_text(text, "<test>", registry=make_registry())
    rt = Runtime(spec, log=lambda m: None)
    started: list[str] = []
    real_start = threading.Thread.start

    def start(self):
        if self.name.startswith("teletouch-") and self.name.endswith("Hz"):
            started.append(self.name)
            if len(started) == 2:
                raise KeyboardInterrupt
        real_start(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    before = sys.getswitchinterval()
    try:
        res = rt.run(1.0)
    finally:
        now = sys.getswitchinterval()
        sys.setswitchinterval(before)
    assert started == ["teletouch-1000Hz", "teletouch-100Hz"]
    assert res.status == "interrupted", res.message
    assert now == before, (now, before)
    assert rt.component("fast").safe and rt.component("slow").safe
