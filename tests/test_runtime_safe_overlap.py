"""A device's safe state when a step of it, or of a node at its rate, is still in flight (wall clock).

The leader here is written as docs/writing-a-plugin.md writes a device: step() reads its `safe` flag, then a transfer
lands the force on the hardware (`hw_force`); every write is logged with the graph time and who made it. A step in
flight while safe_state() runs may land its force after it: the runtime must make the device safe again when that step
returns, whoever began the safe call and whether or not it still runs then.
"""

from __future__ import annotations

import threading
import time

import pytest
from pydantic import Field

from teletouch import Device, Params, Port, hookimpl
from teletouch.runtime import EXIT_FAULT, Runtime
from teletouch.testing import load_text, make_registry


class SlowLeader(Device):
    name = "t-slow-leader"
    outputs = {"opening": Port("float64", (), "")}

    class Params(Params):
        force: float = Field(2.0, description="N commanded each step")
        slow_at: float | None = Field(None, description="s: from here, one step's transfer takes slow_for")
        slow_for: float = Field(0.0, description="s")
        safe_io: float = Field(0.0, description="s safe_state() waits after its zero-force write (an acknowledge)")

    def configure(self):
        self.safe = False
        self.hw_force = 0.0
        self.writes: list[tuple[float, str, float]] = []
        self._slowed = False
        self._lk = threading.Lock()

    def activate(self):
        self.safe = False

    def _hw(self, who, f):
        with self._lk:
            self.hw_force = f
            self.writes.append((self.ctx.now(), who, f))

    def step(self, t, inputs):
        f = 0.0 if self.safe else self.params.force
        p = self.params
        if p.slow_at is not None and t >= p.slow_at and not self._slowed:
            self._slowed = True
            time.sleep(p.slow_for)   # a USB transfer that stalls; the force lands when it completes
        self._hw("step", f)
        return {"opening": 0.01}

    def safe_state(self):
        self.safe = True
        if hasattr(self, "hw_force"):
            self._hw("safe_state", 0.0)
            if self.params.safe_io:
                time.sleep(self.params.safe_io)


class LockedFollower(Device):
    """A driver whose step hangs in a bus transfer holding the lock its safe_state() needs."""
    name = "t-locked-follower"
    outputs = {"opening": Port("float64", (), "")}

    class Params(Params):
        hang_at: float = Field(0.3, description="s")
        hang_for: float = Field(2.0, description="s")

    def configure(self):
        self.lock = threading.Lock()
        self._hung = False

    def step(self, t, inputs):
        with self.lock:
            if t >= self.params.hang_at and not self._hung:
                self._hung = True
                time.sleep(self.params.hang_for)
        return {"opening": 0.02}

    def safe_state(self):
        if hasattr(self, "lock"):
            with self.lock:
                pass


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [SlowLeader, LockedFollower]


def _runtime(text: str) -> Runtime:
    return Runtime(load_text(text, make_registry(_Plugin())), log=lambda m: None)


def _after_last_safe(writes):
    last = max(i for i, w in enumerate(writes) if w[1] == "safe_state")
    return [w for w in writes[last + 1:] if w[2] != 0.0]


def test_a_step_that_returns_while_the_watchdogs_safe_call_still_runs_is_made_safe_again():
    # the transfer stalls 0.25 s from t=0.3; the watchdog (0.1 s) makes the leader safe at ~0.4 s, and its
    # safe_state() waits 0.3 s for an acknowledge: the stalled step lands 2 N at ~0.55 s, inside that call. It was
    # only waited for, and the leader (disabled under degrade) pushed 2 N on the hand to the end of the run.
    rt = _runtime("""
clock: wall
faults: {on_fault: degrade, max_overruns: 0, watchdog: 0.1}
nodes:
  - {id: leader, plugin: t-slow-leader, rate: 100, params: {slow_at: 0.3, slow_for: 0.25, safe_io: 0.3}}
  - {id: other, plugin: mock-sensor, rate: 100}
""")
    seen: list[float] = []

    def watch():   # the force on the hand at t = 1.0 s, before the run's own end makes it safe
        while not hasattr(rt.component("leader"), "writes"):   # (configured: the run's clock has started)
            time.sleep(0.005)
        while rt.now() < 1.0:
            time.sleep(0.005)
        seen.append(rt.component("leader").hw_force)

    threading.Thread(target=watch, daemon=True).start()
    res = rt.run(1.3)
    lead = rt.component("leader")
    assert [f.kind for f in res.faults] == ["stall"], res.faults
    late = [w for w in lead.writes if w[1] == "step" and w[2] != 0.0 and w[0] > 0.4]
    assert late, lead.writes   # the stalled step did land its force after the watchdog's call
    assert seen == [0.0], (seen, lead.writes)
    zeroed = [w for w in lead.writes if w[1] == "safe_state" and w[0] >= late[-1][0]]
    assert zeroed and zeroed[0][0] < 0.9, lead.writes   # made safe again once the first call had returned


def test_a_device_step_still_in_flight_at_the_end_is_a_fault_and_made_safe_when_it_returns():
    # the transfer stalls 2.6 s from t=0.15 and the run ends at 0.2 s: the shutdown's safe_state() ran while the step
    # hung; the step then landed 2 N with nothing to take it off, and the run said ok, exit 0
    rt = _runtime("""
clock: wall
faults: {max_overruns: 0}
nodes:
  - {id: leader, plugin: t-slow-leader, rate: 100, params: {slow_at: 0.15, slow_for: 2.6}}
""")
    res = rt.run(0.2)
    lead = rt.component("leader")
    assert res.status == "fault" and res.exit_code == EXIT_FAULT, res.message
    assert "node 'leader', which may not be in it" in res.message and "step() was still running" in res.message
    assert "made safe again if that step returns" in res.message
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and not any(w[1] == "step" and w[0] > 2.0 for w in lead.writes):
        time.sleep(0.02)
    time.sleep(0.1)
    assert any(w[1] == "step" and w[2] != 0.0 and w[0] > 2.0 for w in lead.writes), lead.writes
    assert _after_last_safe(lead.writes) == [] and lead.hw_force == 0.0, lead.writes


def test_a_hung_safe_state_does_not_hold_up_the_other_devices_at_its_rate():
    # follower and leader share the 100 Hz thread; the follower's step hangs at 0.3 s holding its lock, so its
    # safe_state() hangs too (safe_timeout 0.5 s): the leader was made safe only after that wait, 0.6 s after its last
    # step, where the watchdog promises 0.1 s
    rt = _runtime("""
clock: wall
faults: {max_overruns: 0, watchdog: 0.1, safe_timeout: 0.5}
nodes:
  - {id: follower, plugin: t-locked-follower, rate: 100, params: {hang_at: 0.3, hang_for: 1.5}}
  - {id: leader, plugin: t-slow-leader, rate: 100}
""")
    res = rt.run(1.0)
    lead = rt.component("leader")
    kinds = {(f.node, f.kind) for f in res.faults}
    assert {("follower", "stall"), ("leader", "stall"), ("follower", "hung")} <= kinds, res.faults
    last_step = [w for w in lead.writes if w[1] == "step"][-1]
    safe = [w for w in lead.writes if w[1] == "safe_state"][0]
    assert safe[0] - last_step[0] < 0.3, (last_step, safe)


@pytest.mark.parametrize("isolated", [False, True], ids=["inline", "isolated"])
def test_a_stop_while_a_node_at_the_devices_rate_hangs_makes_the_device_safe_at_once(isolated):
    # an estimator at the leader's rate hangs from 0.25 s; the run stops at 0.3 s, before the watchdog (0.1 s) fires:
    # the watchdog ended with the stop and the leader kept its 2 N until its thread's joins gave up (1-2 s). Made
    # safe once the step passed the watchdog's limit (0.35 s), as the watchdog would have
    iso = ", isolate: process" if isolated else ""
    rt = _runtime(f"""
clock: wall
faults: {{max_overruns: 0, watchdog: 0.1}}
nodes:
  - {{id: est, plugin: mock-burn, rate: 100, params: {{burn: 0ms, hang_at: 0.25, hang_for: 3.0}}{iso}}}
  - {{id: leader, plugin: t-slow-leader, rate: 100}}
""")
    rt.run(0.3)
    lead = rt.component("leader")
    safe = [w for w in lead.writes if w[1] == "safe_state"]
    assert safe and 0.34 < safe[0][0] < 0.5, lead.writes
    assert _after_last_safe(lead.writes) == [], lead.writes
