"""A review of the runtime's safe-state and shutdown changes reproduced these; each test failed on the code it was
written against (wall clock):
- a stop inside a healthy slow device step called safe_state() from the main thread beside that step (0.1 s after the
  stop, whatever the step's own period), and again after it;
- a stale input's fault asked the source device's status() in the consumer's rate-group thread: a status() that
  blocks (a lock its hung reader holds) held that thread, and the leader at its rate, for seconds;
- a results() left behind was followed by a close() beside it;
- a status() that raised SystemExit ended the run's thread instead of being ignored."""

from __future__ import annotations

import threading
import time

import pytest

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry

RELEASE = threading.Event()


class SlowServo(Device):
    """A healthy 5 Hz device whose every step takes 0.15 s (its watchdog limit: 3 periods, 0.6 s)."""
    name = "t-slow-servo"
    outputs = {"o": Port("float64", (), "")}

    def configure(self):
        self.in_step = False
        self.calls: list[str] = []

    def step(self, t, inputs):
        self.in_step = True
        time.sleep(0.15)
        self.in_step = False
        return {"o": 0.0}

    def safe_state(self):
        if hasattr(self, "calls"):
            self.calls.append("during step" if self.in_step else "after step")


class StallingGripper(Device):
    """Publishes until t = 0.3 s; then a reader thread holds its state lock inside a read for 3 s, and status()
    takes that lock."""
    name = "t-stalling-gripper"
    outputs = {"value": Port("float64", (), "")}

    def configure(self):
        self.lock = threading.Lock()
        self.stalled = False

    def _reader(self):
        with self.lock:
            RELEASE.wait(3.0)

    def step(self, t, inputs):
        if t >= 0.3:
            if not self.stalled:
                self.stalled = True
                threading.Thread(target=self._reader, daemon=True).start()
            return None
        return {"value": 1.0}

    def safe_state(self):
        pass

    def status(self):
        with self.lock:
            return {"problem": "no valid state" if self.stalled else None}


class ExitingGripper(StallingGripper):
    name = "t-exiting-gripper"

    def _reader(self):
        pass

    def status(self):
        raise SystemExit(0)


class Leader(Device):
    name = "t-leader"
    inputs = {"force": Port("float64", (), "", required=False)}
    outputs = {"pos": Port("float64", (), "")}

    def configure(self):
        self.safe_at: list[float] = []
        self.pushing = False

    def step(self, t, inputs):
        self.pushing = True
        return {"pos": 0.0}

    def safe_state(self):
        if hasattr(self, "safe_at") and self.pushing:
            self.pushing = False
            self.safe_at.append(self.ctx.now())


class SlowResults(Component):
    name = "t-slow-results"
    kind = Kind.ESTIMATOR
    outputs = {"v": Port("float64", (), "")}

    def configure(self):
        self.log: list[str] = []
        self.busy = False

    def step(self, t, inputs):
        return {"v": 1.0}

    def results(self):
        self.busy = True
        RELEASE.wait(3.0)
        self.busy = False
        return {}

    def close(self):
        self.log.append("close while results() runs" if self.busy else "close")


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [SlowServo, StallingGripper, ExitingGripper, Leader, SlowResults]


@pytest.fixture(autouse=True)
def _release():
    RELEASE.clear()
    yield
    RELEASE.set()


def _runtime(text: str) -> Runtime:
    return Runtime(load_text(text, make_registry(_Plugin())), log=lambda m: None)


def test_a_stop_inside_a_healthy_slow_step_waits_for_it():
    rt = _runtime("""
clock: wall
faults: {max_overruns: 0}
nodes:
  - {id: servo, plugin: t-slow-servo, rate: 5}
""")
    res = rt.run(0.41)   # ends inside the step begun at 0.4 s
    assert res.status == "ok" and res.exit_code == 0, res.message
    assert rt.component("servo").calls == ["after step"]


@pytest.mark.parametrize("gripper", ["t-stalling-gripper", "t-exiting-gripper"])
def test_a_source_status_that_blocks_or_exits_does_not_hold_the_stale_fault(gripper):
    rt = _runtime(f"""
clock: wall
faults: {{on_fault: stop, max_overruns: 0, watchdog: 0, startup_grace: 0.1}}
nodes:
  - {{id: gripper, plugin: {gripper}, rate: 100}}
  - id: controller
    plugin: mock-gain
    rate: 500
    inputs: {{x: {{from: gripper.value, max_age: 0.05}}}}
  - {{id: leader, plugin: t-leader, rate: 500, inputs: {{force: controller.y}}}}
""")
    t0 = time.monotonic()
    res = rt.run(2.0)
    assert time.monotonic() - t0 < 1.5
    f = res.faults[0]
    assert (f.node, f.kind) == ("controller", "stale") and res.exit_code == 3, res.faults
    assert "reports" not in f.message, f.message   # nothing to quote: its status() blocked (or raised)
    assert rt.component("leader").safe_at and rt.component("leader").safe_at[0] < 0.6, rt.component("leader").safe_at


def test_a_results_left_behind_gets_no_close_beside_it(monkeypatch):
    monkeypatch.setattr(Runtime, "LIFECYCLE_TIMEOUT", 0.5)
    rt = _runtime("""
clock: wall
nodes:
  - {id: log, plugin: t-slow-results, rate: 100}
""")
    res = rt.run(0.2)
    f = [f for f in res.faults if f.node == "log"]
    assert len(f) == 1 and f[0].message.endswith("results() did not return within 0.5 s: left behind; its close() "
                                                 "is skipped"), res.faults
    assert rt.component("log").log == []
