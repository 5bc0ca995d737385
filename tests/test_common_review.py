"""Review of follower_common (the followers' base), the test Harness and process isolation: each test failed on the
code before its fix.

- follower_common: a re-activation that could not read the state took the set-point (and the safe state's hold)
  from the reading of before the node was inactive, and sent it: the fingers, moved meanwhile, were driven back.
- Harness.run stepped on ticks of a rounded period (7 Hz: 1.000000001 s, so run(1.0) missed the runtime's step at
  1 s) and took any rate, also those a graph refuses (a rate above 1 GHz made run() loop for ever).
- isolation: a status() that raises (or returns what cannot be pickled) faulted an isolated node at every step,
  while inline the live view just shows nothing for it.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.followers import dynamixel, goal_positions  # noqa: E402
from fakes.realtime import drive, wait_for  # noqa: E402

from teletouch import Component, Kind, Port, hookimpl  # noqa: E402
from teletouch.mock import MockSensor  # noqa: E402
from teletouch.testing import Harness, make_registry, run_yaml  # noqa: E402
from teletouch.plugins.devices.follower_common import FollowerBase, Reading  # noqa: E402


# ------------------------------------------------------------------------------------ follower_common: re-activation
class BenchFollower(FollowerBase):
    """A follower on a bench: its fingers are at ``pos``; a read returns None while ``lost`` (an answer lost on the
    bus); every set-point sent is recorded in ``sent``."""

    name = "bench-follower"

    def _hw_open(self) -> None:
        self.pos = 0.07
        self.lost = False
        self.sent: list[float] = []

    def _hw_read(self) -> Reading | None:
        return None if self.lost else Reading(self.pos)

    def _hw_write(self, opening: float) -> None:
        self.sent.append(opening)


def _moved_while_inactive(h, to=0.02):
    """Deactivate, move the fingers to ``to`` (someone else), lose the state and activate again."""
    h.comp.deactivate()
    h.comp.pos = to
    h.comp.lost = True
    h.comp.activate()
    h.comp.sent.clear()


def test_reactivation_without_a_reading_sends_nothing_until_the_state_comes_back():
    with Harness(BenchFollower, {"max_speed": 0.05}, rate=200.0) as h:
        for k in range(1, 5):
            h.step(k * 0.005, opening_command=0.07)
        _moved_while_inactive(h)
        for k in range(1, 6):   # the state is still lost (within read_timeout): nothing known, nothing sent
            h.step(10.0 + k * 0.005, opening_command=None)
            assert h.samples == {}   # the opening of before the inactive time is not reported as now's
        assert h.comp.sent == []
        h.comp.lost = False
        out = h.step(10.030, opening_command=None)
        assert out["opening"] == pytest.approx(0.02)
        assert h.comp.sent == [pytest.approx(0.02)]   # holds where the fingers are, not 70 mm
        h.step(10.035, opening_command=0.07)           # a command: walked from there at max_speed
        assert h.comp.sent[-1] == pytest.approx(0.02 + 0.05 * 0.005)


def test_reactivation_without_a_reading_a_fresh_command_does_not_jump():
    with Harness(BenchFollower, {"max_speed": 0.05}, rate=200.0) as h:
        h.step(0.005, opening_command=0.07)
        _moved_while_inactive(h)
        h.step(10.005, opening_command=0.03)
        assert h.comp.sent == []
        h.comp.lost = False
        h.step(10.010, opening_command=0.03)
        assert h.comp.sent and all(abs(s - 0.02) <= 0.05 * 0.010 + 1e-12 for s in h.comp.sent)


def test_hold_safe_state_after_a_reactivation_without_a_reading_does_not_send_the_old_opening():
    with Harness(BenchFollower, {"max_speed": 0.05}, rate=200.0) as h:
        h.step(0.005, opening_command=0.07)
        _moved_while_inactive(h)
        h.safe_state()
        assert h.comp.sent == []   # where the fingers are is not known: the hardware keeps what it does
        h.comp.lost = False
        h.step(10.005, opening_command=0.03)   # a step after the safe state (wall clock: one in flight) holds
        assert h.comp.sent == [pytest.approx(0.02)]


def test_open_safe_state_after_a_reactivation_without_a_reading_still_opens():
    with Harness(BenchFollower, {"max_speed": 0.05, "safe_mode": "open", "max_opening": 0.08}, rate=200.0) as h:
        h.step(0.005, opening_command=0.07)
        _moved_while_inactive(h)
        h.safe_state()
        assert h.comp.sent == [pytest.approx(0.08)]


def test_dynamixel_reactivation_with_lost_answers_does_not_drive_back():
    """Another program moved the servo while the node was inactive; the answers to the state reads of the
    re-activation and of the next steps are lost (the goals, which need none, still reach the servo)."""
    with dynamixel(read_timeout=2.0) as (emu, h):
        t_on, trace = time.monotonic(), []
        drive(h, 0.07, 0.3, trace=trace)
        old = h.comp.map.counts(0.07)
        h.comp.deactivate()
        assert wait_for(lambda: len(goal_positions(emu, t_on)) >= len(trace))
        with emu._lock:
            emu._put(emu.table.goal_position, 1400)

        def moved():
            with emu._lock:
                emu._update()
            return abs(emu.get(emu.table.present_position) - 1400) <= 2

        assert wait_for(moved, timeout=3.0)
        emu.silent = True
        t0 = time.monotonic()
        h.comp.activate()
        for _ in range(5):
            h.step(time.monotonic() - t0, opening_command=None)
        time.sleep(0.05)
        assert not any(abs(g - old) <= 3 for g in goal_positions(emu, t0))   # not sent back towards 0.07 m
        with emu._lock:
            emu._update()
            assert abs(emu.get(emu.table.present_position) - 1400) <= 2
        emu.silent = False
        drive(h, None, 0.1)
        gp = goal_positions(emu, t0)
    assert gp and all(abs(g - 1400) <= 3 for g in gp)


# ------------------------------------------------------------------------------------------------ Harness: the clock
def _runtime_ticks(rate: float, duration: float) -> list[int]:
    ts: list[float] = []
    text = f"nodes:\n  - {{id: s, plugin: mock-sensor, rate: {rate!r}, params: {{signal: constant}}}}\n"
    result, _ = run_yaml(text, make_registry(), duration=duration, clock="sim",
                         taps=[lambda node, t, out: ts.append(t)])
    assert result.exit_code == 0
    return [round(t * 1e9) for t in ts]


@pytest.mark.parametrize("rate", [7.0, 300.0, 1000.0])
def test_harness_run_steps_on_the_runtimes_ticks(rate):
    want = _runtime_ticks(rate, 1.0)
    with Harness(MockSensor, {"signal": "constant"}, rate=rate) as h:
        got = [round(t * 1e9) for t, _ in h.run(0.5)]
        got += [round(t * 1e9) for t, _ in h.run(1.0)]   # goes on from the next tick
    assert got == want


@pytest.mark.parametrize("rate", [0.0, -5.0, math.nan, math.inf, 2e6, 3e9, True, "fast"])
def test_harness_refuses_a_rate_a_graph_refuses(rate):
    with pytest.raises(ValueError, match="rate"):
        Harness(MockSensor, rate=rate)


def test_harness_takes_a_rate_with_its_unit_as_a_graph_does():
    with Harness(MockSensor, {"signal": "constant"}, rate="1kHz") as h:
        assert h.rate == 1000.0 and h.ctx.rate == 1000.0
        assert [round(t * 1e9) for t, _ in h.run(0.002)] == [0, 1000000, 2000000]


# ------------------------------------------------------------------------------------------- isolation: status()
class BadStatus(Component):
    """Its status() raises (``how: raise``) or holds a value that cannot be pickled (``how: lock``)."""

    name = "review-bad-status"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "")}

    class Params(Component.Params):
        how: str = "raise"

    def step(self, t, inputs):
        return {"y": t}

    def status(self):
        if self.params.how == "raise":
            raise RuntimeError("status is broken")
        return {"lock": threading.Lock()}


class GoodStatus(BadStatus):
    name = "review-good-status"

    def status(self):
        return {"steps": 1}


@hookimpl
def teletouch_components():
    return [BadStatus, GoodStatus]


@pytest.mark.parametrize("how", ["raise", "lock"])
def test_an_isolated_node_whose_status_fails_runs_as_it_does_inline(how):
    ys: list[float] = []
    text = f"""
clock: wall
nodes:
  - {{id: est, plugin: review-bad-status, rate: 50, isolate: process, params: {{how: {how}}}}}
"""
    result, rt = run_yaml(text, make_registry(sys.modules[__name__]), duration=0.5,
                          taps=[lambda node, t, out: ys.append(out["y"])])
    assert result.exit_code == 0, result.message
    assert len(ys) >= 5
    assert rt.component("est").status() == {}


def test_an_isolated_nodes_status_still_reaches_the_parent():
    text = """
clock: wall
nodes:
  - {id: est, plugin: review-good-status, rate: 50, isolate: process}
"""
    result, rt = run_yaml(text, make_registry(sys.modules[__name__]), duration=0.3)
    assert result.exit_code == 0, result.message
    assert rt.component("est").status() == {"steps": 1}
