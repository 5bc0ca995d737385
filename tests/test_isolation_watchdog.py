"""A node whose step hangs in a rate group that holds devices (wall clock): the watchdog names that node, makes the
devices safe, and cuts the wait for an isolated node's step short, so its rate group is free again at once.

Before, the watchdog's fault named the first device of the group (`stall`), the isolated node's own fault came last
(its step timeout, 1 s, later), and the group's thread stayed blocked for that whole second."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest
from pydantic import Field

from teletouch.component import Context, Inputs, _Slot
from teletouch.errors import ComponentFault
from teletouch.hookspecs import hookimpl
from teletouch.isolation import ProcessProxy
from teletouch.mock import MockBurn, MockDevice
from teletouch.runtime import EXIT_FAULT
from teletouch.testing import make_registry, run_yaml, safe_states

# est (isolated) hangs 1.5 s at t = 0.5 s: longer than its own step timeout (1 s at 100 Hz), in the rate group of
# both devices; the leader renders est's output, the follower holds
ISOLATED_HANG = """
clock: wall
faults: {watchdog: 0.1}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 2.0}}
  - {id: est, plugin: mock-burn, rate: 100, params: {burn: 0ms, hang_at: 0.5, hang_for: 1.5}, inputs: {x: src.value},
     isolate: process}
  - {id: leader, plugin: mock-device, rate: 100, params: {safe_value: 0.0}, inputs: {command: est.y}}
  - {id: follower, plugin: mock-device, rate: 100, params: {initial: 0.02}}
"""


def _times(seen: list[tuple[str, float]], node: str) -> list[float]:
    return [t for n, t in seen if n == node]


def test_an_isolated_step_that_hangs_among_devices_is_its_own_fault_and_the_devices_are_made_safe():
    seen: list[tuple[str, float]] = []
    res, rt = run_yaml(ISOLATED_HANG, make_registry(), duration=3.0, taps=[lambda n, t, o: seen.append((n, t))])
    assert res.exit_code == EXIT_FAULT
    # the run's reason is the node that hung: its id, its plugin, what it did not do and the limit
    assert res.message.startswith("node 'est' timeout: (mock-burn, isolated process) step did not return within "
                                  "0.1 s (faults.watchdog"), res.message
    first = res.faults[0]
    assert (first.node, first.kind, first.action) == ("est", "timeout", "stop"), [f.line() for f in res.faults]
    assert "the devices at its rate ('leader', 'follower') are not stepped while it runs" in first.message
    # each device: safe, with a fault that says why it was not stepped; nothing else (no second fault of est when
    # its 1 s step timeout would have run out)
    assert sorted((f.node, f.kind) for f in res.faults[1:]) == [("follower", "stall"), ("leader", "stall")]
    for f in res.faults[1:]:
        assert "its rate group waits for the step of node 'est' (mock-burn, isolated process), past the " \
               "watchdog's 0.1 s: made safe" in f.message, f.message
    leader, follower = rt.component("leader"), rt.component("follower")
    assert leader.safe and leader.command == 0.0            # zero force on the hand
    assert follower.safe and follower.command == 0.02       # holds where it was
    # made safe by the watchdog, within its bound of the leader's last step (not at the end of est's 1 s timeout)
    last_leader = max(_times(seen, "leader"))
    assert 0.45 <= last_leader < 0.52, last_leader
    assert safe_states(rt)["leader"][0] - last_leader < 0.35, (safe_states(rt)["leader"], last_leader)
    # the group waited for est about as long as the watchdog allows, not the 1 s of its step timeout
    est = next(n for n in res.nodes if n.id == "est")
    assert est.max_step_s < 0.6, est.max_step_s
    assert rt.component("est")._proc.exitcode == 0          # deactivated and closed normally after its long step


DEGRADE = """
clock: wall
faults: {watchdog: 0.1, on_fault: degrade}
nodes:
  - {id: est, plugin: mock-burn, rate: 100, params: {burn: 0ms, hang_at: 0.5, hang_for: 1.5}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
  - {id: other, plugin: mock-device, rate: 100}
  - {id: tick, plugin: mock-sensor, rate: 100, params: {signal: ramp}}
"""


def test_under_degrade_the_rate_group_goes_on_at_once_with_the_node_that_hung_and_its_devices_disabled():
    seen: list[tuple[str, float]] = []
    res, rt = run_yaml(DEGRADE, make_registry(), duration=2.5, taps=[lambda n, t, o: seen.append((n, t))])
    assert res.status == "degraded", (res.message, [f.line() for f in res.faults])
    got = [(f.node, f.kind) for f in res.faults]
    assert got == [("est", "timeout"), ("dev", "upstream"), ("other", "stall")], [f.line() for f in res.faults]
    assert "step did not return within 0.1 s" in res.faults[0].message
    assert "waits for the step of node 'est'" in res.faults[2].message
    assert rt.component("dev").safe and rt.component("other").safe
    # the rest of the group (tick) is stepped again right after the watchdog's fault: before, it waited 1 s for
    # est's step timeout
    when = res.faults[0].time
    tick = _times(seen, "tick")
    assert any(when < t < when + 0.4 for t in tick), (when, [t for t in tick if t > when][:5])
    # est, disabled, never produced an output after its hang began
    assert max(_times(seen, "est")) < 0.5 + 0.02


INLINE_HANG = """
clock: wall
faults: {watchdog: 0.1}
nodes:
  - {id: est, plugin: mock-burn, rate: 100, params: {burn: 0ms, hang_at: 0.3, hang_for: 0.6}}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""


def test_an_inline_node_that_hangs_among_devices_is_named_by_the_watchdog():
    res, rt = run_yaml(INLINE_HANG, make_registry(), duration=2.0)
    assert res.message.startswith("node 'est' timeout: (mock-burn) step did not return within 0.1 s"), res.message
    assert [(f.node, f.kind) for f in res.faults] == [("est", "timeout"), ("dev", "stall")]
    assert "waits for the step of node 'est' (mock-burn)" in res.faults[1].message
    assert rt.component("dev").safe


class SleepyDevice(MockDevice):
    """A mock device whose step hangs once, for ``sleep_for`` s at ``sleep_at`` (a driver stuck in a hardware call)."""

    name = "s11-sleepy-device"

    class Params(MockDevice.Params):
        sleep_at: float = Field(0.3, description="s")
        sleep_for: float = Field(0.5, description="s")

    def step(self, t, inputs):
        if t >= self.params.sleep_at and not getattr(self, "_slept", False):
            self._slept = True
            time.sleep(self.params.sleep_for)
        return super().step(t, inputs)


@hookimpl
def teletouch_components():
    return [SleepyDevice]


def test_a_device_whose_own_step_hangs_is_a_stall_and_the_other_device_at_its_rate_names_it():
    """The blame goes to the node whose step the group waits in: a device that hangs is its own (`stall`, as when it
    is alone at its rate), and the other device's stall says which node it waited for."""
    text = """
clock: wall
faults: {watchdog: 0.1}
nodes:
  - {id: follower, plugin: mock-device, rate: 100}
  - {id: leader, plugin: s11-sleepy-device, rate: 100}
"""
    res, rt = run_yaml(text, make_registry(sys.modules[__name__]), duration=1.5)
    assert res.message.startswith("node 'leader' stall: not stepped for"), res.message
    assert [(f.node, f.kind) for f in res.faults] == [("leader", "stall"), ("follower", "stall")]
    assert "waits for the step of" not in res.faults[0].message
    assert "its rate group waits for the step of node 'leader' (s11-sleepy-device)" in res.faults[1].message
    assert rt.component("follower").safe and rt.component("leader").safe


# --- the proxy: abandon_step ------------------------------------------------------------------------------------------

def _hanging_proxy(hang_for: float) -> tuple[ProcessProxy, Inputs]:
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=100.0)
    params = MockBurn.Params(burn=0.0, hang_at=0.0, hang_for=hang_for)
    proxy = ProcessProxy(MockBurn, params, node_id="est", ctx=ctx, t0_perf=0.0, t0_mono=0.0, step_timeout=20.0)
    return proxy, Inputs({n: _Slot() for n in MockBurn.inputs})


def test_abandon_step_ends_the_wait_for_a_step_at_once_and_the_late_answer_is_dropped():
    from teletouch.isolation import StepAbandoned

    proxy, inputs = _hanging_proxy(1.2)
    try:
        proxy.configure()
        proxy.activate()
        timer = threading.Timer(0.2, proxy.abandon_step, args=("the devices wait",))
        timer.start()
        t0 = time.monotonic()
        with pytest.raises(StepAbandoned, match=r"step abandoned after .* s without an answer from the isolated "
                                                r"process: the devices wait") as err:
            proxy.step(0.0, inputs)
        took = time.monotonic() - t0
        timer.join()
        assert isinstance(err.value, ComponentFault) and err.value.abandoned
        assert took < 1.0, took                 # not the 1.2 s the child sleeps (nor its 20 s step timeout)
        assert proxy._proc.is_alive()
        # the next step gets its own answer (the abandoned step's comes first and is dropped), and no abandon is left
        out = proxy.step(2.0, inputs)
        assert out["y"] == 0.0 and out["pid"] == proxy._proc.pid
        assert proxy.step(2.01, inputs)["pid"] == proxy._proc.pid
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0
    assert proxy._wake is None                  # its wake-up pipe closed with it


def test_a_wake_up_left_over_from_a_step_that_had_ended_does_not_end_a_later_step():
    proxy, inputs = _hanging_proxy(0.0)
    try:
        proxy.configure()
        proxy.activate()
        proxy.step(0.0, inputs)
        proxy.abandon_step("late")              # no step in flight: the next one to wait is abandoned
        with pytest.raises(ComponentFault, match="late"):
            proxy.step(0.01, inputs)
        os.write(proxy._wake[1], b"!")          # a stray wake-up byte without a request: drained, the step goes on
        assert proxy.step(0.02, inputs)["pid"] == proxy._proc.pid
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0
