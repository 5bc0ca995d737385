"""The multi-rate runtime: determinism, ordering, feedback, faults, safe states, lifecycle."""

from __future__ import annotations

import math
import re
import threading
import time

import pytest

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph_text
from teletouch.runtime import EXIT_FAULT, EXIT_INTERRUPTED, EXIT_OK, EXIT_STARTUP
from teletouch.testing import Harness, make_registry, run_yaml

CHAIN = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: ramp, amplitude: 1.0}}
  - {id: gain, plugin: mock-gain, rate: 100, params: {gain: 2}, inputs: {x: src.value}}
  - {id: dev, plugin: mock-device, rate: 1000, inputs: {command: gain.y}}
"""


class Recorder:
    def __init__(self):
        self.rows = []

    def __call__(self, node, t, out):
        self.rows.append((node, round(t, 9), {k: (v.value if hasattr(v, "stamp") else v) for k, v in out.items()}))


@pytest.fixture(scope="module")
def reg():
    return make_registry()


def test_multirate_counts_and_order(reg):
    rec = Recorder()
    res, rt = run_yaml(CHAIN, reg, duration=1.0, taps=[rec])
    assert res.status == "ok" and res.exit_code == EXIT_OK
    steps = {n.id: n.steps for n in res.nodes}
    assert steps == {"src": 101, "gain": 101, "dev": 1001}
    # producers step before consumers at the same tick: gain at t sees src at t
    gain_rows = [r for r in rec.rows if r[0] == "gain"]
    for _, t, out in gain_rows:
        assert out["y"] == pytest.approx(2.0 * t)
    # the fast device holds the latest (zero-order hold) value between slow samples
    dev = [r for r in rec.rows if r[0] == "dev"]
    at = {t: out["state"] for _, t, out in dev}
    assert at[0.015] == pytest.approx(2.0 * 0.01)
    assert res.sim_time == pytest.approx(1.0)


def test_sim_clock_is_deterministic(reg):
    a, b = Recorder(), Recorder()
    run_yaml(CHAIN, reg, duration=0.5, taps=[a])
    run_yaml(CHAIN, reg, duration=0.5, taps=[b])
    assert a.rows == b.rows and len(a.rows) > 500


def test_feedback_loop_reads_previous_sample():
    class Acc(Component):
        """x[k] = x[k-1] + 1 read through its own feedback wire."""
        name = "acc"
        kind = Kind.CONTROLLER
        inputs = {"prev": Port("float64", (), "", required=False)}
        outputs = {"x": Port("float64", (), "")}

        def step(self, t, inputs):
            return {"x": inputs.value("prev", 0.0) + 1.0}

    class P:
        @hookimpl
        def teletouch_components(self):
            return [Acc]

    reg = make_registry(P())
    res, rt = run_yaml("clock: sim\nnodes:\n  - {id: a, plugin: acc, rate: 10, inputs: {prev: a.x}}\n", reg,
                       duration=1.0)
    assert res.exit_code == 0
    assert rt.latest("a", "x").value == 11.0


def test_exception_stops_graph_and_devices_go_safe(reg):
    text = CHAIN.replace("amplitude: 1.0}", "amplitude: 1.0, fail_at: 0.3}")
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.status == "fault" and res.exit_code == EXIT_FAULT
    assert "node 'src' exception: RuntimeError: mock-sensor failure" in res.message
    assert "safe state" in res.message
    dev = rt.component("dev")
    assert dev.safe_calls >= 1 and dev.safe
    assert dev.lifecycle == ["configure", "activate", "deactivate", "close"]
    assert res.sim_time == pytest.approx(0.3)


def test_degrade_keeps_running(reg):
    text = CHAIN.replace("amplitude: 1.0}", "amplitude: 1.0, fail_at: 0.3}, on_fault: degrade") + """\
  - {id: other, plugin: mock-device, rate: 1000}
"""
    res, rt = run_yaml(text.replace("inputs: {command: gain.y}", "inputs: {command: gain.y}, on_fault: degrade"),
                       reg, duration=1.0)
    # ran to the end, and says that it did so with nodes disabled (a non-zero exit for scripts)
    assert res.status == "degraded" and res.exit_code == EXIT_FAULT
    assert "nodes disabled by faults: 'src' (exception at t=0.300 s)" in res.message
    stats = {n.id: n for n in res.nodes}
    # dev is fed through gain, which would pass src's last value on with fresh stamps: made safe and disabled too
    assert stats["src"].faulted and stats["dev"].faulted and not stats["other"].faulted
    assert stats["other"].steps == 1001 and stats["dev"].steps < 400
    assert res.faults[0].action == "degrade"
    dev = next(f for f in res.faults if f.node == "dev")
    assert dev.kind == "upstream" and dev.message == ("input 'command' comes from node 'gain', fed by node 'src', "
                                                      "which was disabled by a fault")
    assert rt.component("dev").safe


def test_degrade_disables_the_devices_the_faulted_node_commands(reg):
    # the node that commands the device dies under `degrade`: the device must not keep its last command
    text = """
clock: sim
faults: {on_fault: degrade}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {fail_at: 0.3}}
  - {id: other, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: mock-device, rate: 1000, inputs: {command: src.value}}
  - {id: dev2, plugin: mock-device, rate: 1000, inputs: {command: other.value}}
"""
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.status == "degraded"
    by_node = {f.node: f for f in res.faults}
    assert by_node["src"].kind == "exception"
    assert by_node["dev"].kind == "upstream" and "input 'command' comes from node 'src'" in by_node["dev"].message
    assert by_node["dev"].time == pytest.approx(0.3)
    dev = rt.component("dev")
    stats = {n.id: n for n in res.nodes}
    assert dev.safe and stats["dev"].faulted and stats["dev"].steps < 400
    # dev: made safe at the fault, not again at the end of the run (not stepped since); dev2 only at the end
    assert dev.safe_calls == 1 and rt.component("dev2").safe_calls == 1
    assert not stats["dev2"].faulted and stats["dev2"].steps == 1001
    # the device's own policy decides what its fault does: `stop` (the default) ends the run
    res, rt = run_yaml(text.replace("faults: {on_fault: degrade}", "").replace(
        "params: {fail_at: 0.3}}", "params: {fail_at: 0.3}, on_fault: degrade}"), reg, duration=1.0)
    assert res.status == "fault" and "node 'dev' upstream" in res.message and res.sim_time == pytest.approx(0.3)
    assert rt.component("dev").safe and rt.component("dev2").safe


def test_device_fault_drives_it_safe(reg):
    text = CHAIN.replace("inputs: {command: gain.y}", "inputs: {command: gain.y}, params: {fail_at: 0.5}")
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.exit_code == EXIT_FAULT and "node 'dev'" in res.message
    assert rt.component("dev").safe_calls >= 1


def test_stale_input_faults(reg):
    # the source stops producing at 0.2 s; the device's 50 ms staleness limit trips after the grace time
    text = """
clock: sim
faults: {startup_grace: 0.1}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {silent_at: 0.2}}
  - {id: dev, plugin: mock-device, rate: 1000, inputs: {command: {from: src.value, max_age: 0.05}}}
"""
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.exit_code == EXIT_FAULT
    stale = [f for f in res.faults if f.kind == "stale"]
    assert stale and stale[0].node == "dev" and "limit 0.05 s" in stale[0].message
    assert 0.24 <= stale[0].time <= 0.26
    assert rt.component("dev").safe_calls >= 1


def test_never_received_input_is_stale(reg):
    text = """
clock: sim
faults: {startup_grace: 0.1}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {silent_at: 0.0}}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: {from: src.value, max_age: 0.05}}}
"""
    res, _ = run_yaml(text, reg, duration=1.0)
    assert res.exit_code == EXIT_FAULT and "nothing received" in res.message


def test_request_stop_ends_normally(reg):
    res, _ = run_yaml(CHAIN.replace("amplitude: 1.0}", "amplitude: 1.0, stop_at: 0.25}"), reg, duration=5.0)
    assert res.status == "stopped" and res.exit_code == EXIT_OK and "stop at t=0.250" in res.message


class _Boom(Component):
    name = "boom"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        mode: str = "configure"

    def configure(self):
        if self.params.mode == "configure":
            raise OSError("camera busy")

    def step(self, t, inputs):
        if self.params.mode == "interrupt" and t >= 0.1:
            raise KeyboardInterrupt
        if self.params.mode == "badout":
            return {"nope": 1.0}
        return {"y": 1.0}


class _BoomPlugin:
    @hookimpl
    def teletouch_components(self):
        return [_Boom]


def test_startup_failure_closes_everything():
    reg = make_registry(_BoomPlugin())
    text = CHAIN + "  - {id: b, plugin: boom, rate: 10}\n"
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert "node 'b' (boom) failed to configure: OSError: camera busy" in res.message
    assert [(f.node, f.kind) for f in res.faults] == [("b", "startup")]   # the summary names the node ('' before)
    assert rt.component("dev").lifecycle[-1] == "close"


def test_ctrl_c_drives_devices_safe():
    reg = make_registry(_BoomPlugin())
    text = CHAIN + "  - {id: b, plugin: boom, rate: 100, params: {mode: interrupt}}\n"
    res, rt = run_yaml(text, reg, duration=1.0)
    assert res.status == "interrupted" and res.exit_code == EXIT_INTERRUPTED
    assert rt.component("dev").safe_calls >= 1
    assert rt.component("dev").lifecycle[-2:] == ["deactivate", "close"]


def test_unknown_output_is_a_clear_fault():
    reg = make_registry(_BoomPlugin())
    res, _ = run_yaml("clock: sim\nnodes:\n  - {id: b, plugin: boom, rate: 10, params: {mode: badout}}\n", reg,
                      duration=1.0)
    assert res.exit_code == EXIT_FAULT and "unknown output 'nope'" in res.message


def test_sim_clock_requires_duration(reg):
    with pytest.raises(ValueError, match="needs a duration"):
        run_yaml(CHAIN, reg, duration=None)


class _Slow(Component):
    """Sleeps (releases the GIL like a camera read or a torch op) for a configurable time."""
    name = "slow"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        sleep: float = 0.03

    def step(self, t, inputs):
        time.sleep(self.params.sleep)
        return {"y": t}


class _SlowPlugin:
    @hookimpl
    def teletouch_components(self):
        return [_Slow]


def test_wall_clock_slow_node_does_not_delay_fast_node():
    reg = make_registry(_SlowPlugin())
    text = """
clock: wall
faults: {max_overruns: 0}
nodes:
  - {id: slow, plugin: slow, rate: 20, params: {sleep: 0.04}}
  - {id: dev, plugin: mock-device, rate: 500}
"""
    times: list[float] = []
    res, _ = run_yaml(text, reg, duration=1.0, taps=[lambda n, t, o: times.append(t) if n == "dev" else None])
    assert res.exit_code == EXIT_OK, res.message
    nodes = {n.id: n for n in res.nodes}
    # in one thread each 40 ms sleep would stop the 500 Hz node for 40 ms: a gap in its steps at every slow step.
    # Counted as gaps, not as steps in the second (a loaded machine takes steps from both threads alike); a gap of
    # 30 ms that the load makes now and then is far from one at every slow step
    gaps = [b - a for a, b in zip(times, times[1:]) if b - a > 0.030]
    assert nodes["slow"].steps >= 10 and len(times) > 100, (nodes["slow"], len(times))
    assert len(gaps) < nodes["slow"].steps / 3, (len(gaps), nodes["slow"].steps, gaps)


def test_wall_clock_repeated_overruns_fault():
    reg = make_registry(_SlowPlugin())
    text = """
clock: wall
faults: {max_overruns: 3}
nodes:
  - {id: slow, plugin: slow, rate: 100, params: {sleep: 0.03}}
  - {id: dev, plugin: mock-device, rate: 200}
"""
    res, rt = run_yaml(text, reg, duration=2.0)
    assert res.exit_code == EXIT_FAULT
    assert any(f.kind == "overrun" and f.node == "slow" for f in res.faults)
    assert rt.component("dev").safe_calls >= 1
    assert res.sim_time < 1.0


def test_harness_steps_a_component_by_hand():
    from teletouch.mock import MockDevice

    with Harness(MockDevice, {"tau": 0.0}) as h:
        assert h.step(0.0, command=0.5)["state"] == 0.5
        h.comp.safe_state()
        assert h.step(0.001, command=0.9)["command_applied"] == 0.5


def test_nan_passes_through_mocks_untouched(reg):
    # the runtime does not hide NaN: consumers (controllers) must guard; this documents the contract
    res, rt = run_yaml(CHAIN.replace("amplitude: 1.0}", "amplitude: 1.0, nan_at: 0.2}"), reg, duration=0.5)
    assert res.exit_code == 0 and math.isnan(rt.latest("gain", "y").value)


def test_thread_priority_rules():
    from teletouch.runtime import thread_priority

    assert thread_priority(50, 1000, [None, None]) == 50
    assert thread_priority(50, 60, [None]) == 0
    assert thread_priority(50, 60, [None, 40]) == 40
    assert thread_priority(0, 1000, [30]) == 30
    assert thread_priority(50, 1000, [0]) == 0  # a node may opt out


def test_node_priority_validated(reg):
    from teletouch.errors import GraphValidationError
    from teletouch.testing import load_text

    spec = load_text(CHAIN.replace("rate: 1000,", "rate: 1000, priority: 40,"), reg)
    assert spec.node("dev").priority == 40
    with pytest.raises(GraphValidationError, match="priority: expected an integer 0-99"):
        load_text(CHAIN.replace("rate: 1000,", "rate: 1000, priority: 120,"), reg)


# ------------------------------------------------------------------------------------------------ fault paths
class _Stamper(Component):
    """Returns its value as a Sample with a given stamp (a plugin with a clock bug)."""
    name = "stamper"
    kind = Kind.SENSOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        stamp: str = "nan"

    def step(self, t, inputs):
        from teletouch import Sample

        return {"y": Sample(1.0, {"nan": math.nan, "inf": math.inf, "text": "soon"}[self.params.stamp])}


class _Hang(Device):
    """A device whose step hangs for ``hang_for`` seconds once, at ``hang_at``."""
    name = "hang-device"
    kind = Kind.DEVICE

    class Params(Component.Params):
        hang_at: float = 0.2
        hang_for: float = 0.6
        locked: bool = False   # the hang holds the driver's lock, which safe_state() and deactivate() take too

    outputs = {"y": Port("float64", (), "")}

    def configure(self):
        self.hung_at = self.safe_at = None
        self.lock = threading.Lock()
        self.calls: list[str] = []

    def step(self, t, inputs):
        if t >= self.params.hang_at and self.hung_at is None:
            self.hung_at = time.perf_counter()
            if self.params.locked:
                with self.lock:
                    time.sleep(self.params.hang_for)
            else:
                time.sleep(self.params.hang_for)
        return {"y": t}

    def safe_state(self):
        with self.lock:
            if self.safe_at is None:
                self.safe_at = time.perf_counter()

    def deactivate(self):
        with self.lock:
            self.calls.append("deactivate")


class _FaultPlugins:
    @hookimpl
    def teletouch_components(self):
        return [_Stamper, _Hang]


@pytest.mark.parametrize("stamp", ["nan", "inf", "text"])
def test_a_non_finite_output_stamp_is_a_fault_naming_the_port(stamp):
    text = f"""
clock: sim
nodes:
  - {{id: s, plugin: stamper, rate: 100, params: {{stamp: {stamp}}}}}
  - {{id: dev, plugin: mock-device, rate: 100, inputs: {{command: s.y}}}}
"""
    res, rt = run_yaml(text, make_registry(_FaultPlugins()), duration=0.1)
    assert res.status == "fault" and "node 's' exception" in res.message
    assert "output 'y' stamped" in res.message and "finite graph time" in res.message
    assert rt.component("dev").safe


def test_max_age_counts_a_stamp_from_the_future_as_stale():
    text = """
clock: sim
faults: {startup_grace: 0.0}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: {from: src.value, max_age: 0.05}}}
"""
    from teletouch import Sample

    class Ahead(Component):
        name = "ahead"
        kind = Kind.SENSOR
        outputs = {"value": Port("float64", (), "")}

        def step(self, t, inputs):
            return {"value": Sample(1.0, t + 3600.0)}

    class P:
        @hookimpl
        def teletouch_components(self):
            return [Ahead]

    res, rt = run_yaml(text.replace("mock-sensor", "ahead"), make_registry(P()), duration=0.5)
    assert res.status == "fault" and "node 'dev' stale" in res.message and "ahead of the graph clock" in res.message
    assert res.sim_time == 0.0


def test_watchdog_makes_a_hung_device_safe_while_it_hangs():
    # wall clock: the device's step hangs 1.5 s at t = 0.2 s; the watchdog (0.1 s) makes it safe long before the
    # step returns, and the run stops with a `stall` fault. (The hang is long, and no overrun faults, so that a loaded
    # 2-core machine, which makes the watchdog's own thread late, cannot make it look as if the hang ended first.)
    text = """
clock: wall
faults: {max_overruns: 0WATCHDOG}
nodes:
  - {id: dev, plugin: hang-device, rate: 100, params: {hang_at: 0.2, hang_for: 1.5}}
"""
    res, rt = run_yaml(text.replace("WATCHDOG", ""), make_registry(_FaultPlugins()), duration=3.0)
    dev = rt.component("dev")
    assert res.status == "fault" and "node 'dev' stall" in res.message and "watchdog 0.1 s" in res.message
    assert dev.safe_at is not None and 0.09 <= dev.safe_at - dev.hung_at <= 1.0
    # the watchdog is a graph setting (0: off): without it the hang goes unnoticed until the step returns
    res, rt = run_yaml(text.replace("WATCHDOG", ", watchdog: 0"), make_registry(_FaultPlugins()), duration=2.0)
    dev = rt.component("dev")
    assert res.status == "ok" and dev.safe_at - dev.hung_at >= 1.49


def test_a_device_whose_safe_state_hangs_does_not_block_the_others_or_the_end_of_the_run():
    # the leader's step hangs inside a "hardware call" holding its driver's lock for 4 s; its safe_state() waits for
    # that lock. The watchdog must still make the other device safe at once, and the run must end (after
    # faults.safe_timeout), leaving the hung node behind, instead of blocking on its safe_state() for 4 s
    # (no overrun faults: on a loaded machine late steps must not end the run before the hang)
    text = """
clock: wall
faults: {safe_timeout: 0.3, max_overruns: 0}
nodes:
  - {id: leader, plugin: hang-device, rate: 100, params: {hang_at: 0.2, hang_for: 8.0, locked: true}}
  - {id: follower, plugin: mock-device, rate: 200}
"""
    # (the follower at another rate: a thread of its own, which the hang does not stall)
    t0 = time.perf_counter()
    res, rt = run_yaml(text, make_registry(_FaultPlugins()), duration=20.0)
    took = time.perf_counter() - t0
    leader, follower = rt.component("leader"), rt.component("follower")
    assert res.status == "fault" and "node 'leader' stall" in res.message
    # not the 8 s hang (nor the 20 s duration): the hang is long so that a loaded machine's slow start-up and
    # shutdown leave the bound far from it
    assert took < 5.0, took
    assert follower.safe_at is not None and follower.safe_at - leader.hung_at < 1.5
    assert leader.safe_at is None                  # it could not be made safe: reported, left behind
    kinds = {(f.node, f.kind) for f in res.faults}
    assert ("leader", "hung") in kinds
    hung = next(f for f in res.faults if f.kind == "hung")
    assert "did not return within 0.3 s (faults.safe_timeout" in hung.message
    assert "deactivate" not in leader.calls and "deactivate" in follower.lifecycle


def test_safe_timeout_is_validated():
    for bad in ("0", "-1", "120", "soon"):
        with pytest.raises(GraphValidationError, match=r"faults.safe_timeout"):
            load_graph_text(f"faults: {{safe_timeout: {bad}}}\nnodes:\n  - {{id: d, plugin: mock-device}}\n",
                            "<t>")


def test_startup_grace_is_at_most_a_minute():
    """faults.startup_grace: 1e9 let a source that never sent anything go unseen for good (status ok, exit 0)."""
    for bad in ("61", "1e9", "61000ms"):
        with pytest.raises(GraphValidationError, match=r"faults.startup_grace: expected at most 60 s"):
            load_graph_text(f"faults: {{startup_grace: {bad}}}\nnodes:\n  - {{id: d, plugin: mock-device}}\n",
                            "<t>")
    spec = load_graph_text("faults: {startup_grace: 60}\nnodes:\n  - {id: d, plugin: mock-device}\n", "<t>")
    assert spec.faults.startup_grace == 60.0


def test_on_stop_a_device_is_made_safe_by_its_own_thread_not_after_the_slow_ones():
    # the 1 kHz source faults at 0.3 s while a 2 Hz node is inside a 0.6 s step: the device (1 kHz thread) must be
    # safe within a few periods, not after that step ends and the threads are joined
    # (no overrun faults: on a loaded machine the 1 kHz steps come late, which must not end the run first; a long
    # burn, so that the bound below, roomy for a late thread, is still far from the end of that step)
    text = """
clock: wall
faults: {max_overruns: 0}
nodes:
  - {id: src, plugin: mock-sensor, rate: 1kHz, params: {fail_at: 0.3}}
  - {id: dev, plugin: mock-device, rate: 1kHz, inputs: {command: src.value}}
  - {id: slow, plugin: mock-burn, rate: 2, params: {burn: 1.5}}
"""
    res, rt = run_yaml(text, make_registry(), duration=3.0)
    assert res.status == "fault" and "node 'src' exception" in res.message
    fault_at = rt._t0 + res.faults[0].time
    assert rt.component("dev").safe_at - fault_at < 0.5


def test_a_second_interrupt_during_shutdown_does_not_skip_safe_states():
    import os
    import signal

    class Kicker(Device):
        """A device whose safe_state() gets a SIGINT while it runs (the operator presses Ctrl-C again)."""
        name = "kicker"
        kind = Kind.DEVICE
        outputs = {"y": Port("float64", (), "")}

        def configure(self):
            self.calls = 0

        def step(self, t, inputs):
            return {"y": 0.0}

        def safe_state(self):
            self.calls += 1
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)

    class P:
        @hookimpl
        def teletouch_components(self):
            return [Kicker]

    text = """
clock: sim
nodes:
  - {id: k, plugin: kicker, rate: 100}
  - {id: dev, plugin: mock-device, rate: 100}
"""
    res, rt = run_yaml(text, make_registry(P()), duration=0.1)
    assert res.status == "interrupted" and res.exit_code == EXIT_INTERRUPTED
    assert rt.component("k").calls >= 1 and rt.component("dev").safe
    assert rt.component("dev").lifecycle[-2:] == ["deactivate", "close"]


def test_start_up_time_is_reported_apart_from_the_run():
    class Slow(Component):
        name = "slow-start"
        kind = Kind.ESTIMATOR

        def configure(self):
            time.sleep(1.0)

        def step(self, t, inputs):
            return None

    class P:
        @hookimpl
        def teletouch_components(self):
            return [Slow]

    res, _ = run_yaml("clock: wall\nnodes:\n  - {id: s, plugin: slow-start, rate: 100}\n", make_registry(P()),
                      duration=0.3)
    assert 1.0 <= res.startup_time < res.wall_time
    # real time is real time once running; the whole call (start-up included) is slower. (A loaded machine ends a
    # run late, which lowers the run's factor: bounded by what a start-up counted in would give, 0.3 / 1.3.)
    assert 0.5 < res.run_realtime_factor <= 1.0 + 1e-6 and res.realtime_factor < 0.3
    assert re.search(r"s start-up \((1\.0|0\.[5-9])x real time\)", res.summary()), res.summary()
    assert res.as_dict()["startup_time_s"] == res.startup_time
