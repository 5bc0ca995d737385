"""The ROS 2 bridge's graph <-> Unix time mapping is not shifted by a preemption between its two clock reads."""

from __future__ import annotations

import time

import pytest

from teletouch.plugins.bridges.ros2 import _Clock


class _JumpyCtx:
    """A wall-clock context (graph time = perf_counter - origin) whose thread stalls ``stall`` seconds just before
    the reads numbered in ``at``, as if it were preempted there."""

    clock_kind = "wall"

    def __init__(self, stall: float = 0.0, at: tuple[int, ...] = ()):
        self.t0 = time.perf_counter()
        self.reads = 0
        self.stall, self.at = stall, at

    def now(self) -> float:
        self.reads += 1
        if self.reads in self.at:
            time.sleep(self.stall)
        return time.perf_counter() - self.t0


def _true_offset(ctx: _JumpyCtx) -> float:
    best = (float("inf"), 0.0)
    for _ in range(20):
        a = time.perf_counter() - ctx.t0
        u = time.time()
        b = time.perf_counter() - ctx.t0
        best = min(best, (b - a, u - 0.5 * (a + b)))
    return best[1]


@pytest.mark.parametrize("at, reads", [((2,), 4), ((2, 4), 6)])
def test_a_preemption_between_the_reads_does_not_shift_the_mapping(at, reads):
    """A 20 ms stall between the Unix read and the graph read after it puts a plain ``time.time() - now()`` 20 ms
    off (10 ms referred to the pair's middle); the bracketed read sees the wide pair, reads again and keeps the
    tight one: within 1 ms."""
    ctx = _JumpyCtx()
    clock = _Clock(ctx)                  # the construction's own read, no stall
    ctx.reads, ctx.stall, ctx.at = 0, 0.020, at
    got = clock.offset_now()
    assert ctx.reads == reads            # the wide pairs were read again, the first tight one ended it
    assert abs(got - _true_offset(ctx)) < 1e-3


def test_a_tight_first_pair_is_not_read_again():
    ctx = _JumpyCtx()
    clock = _Clock(ctx)
    ctx.reads = 0
    clock.offset_now()
    assert ctx.reads == 2


def test_the_mapping_round_trips_and_a_sim_clock_keeps_its_offset():
    ctx = _JumpyCtx()
    clock = _Clock(ctx)
    g = 12.5
    assert abs(clock.to_graph(clock.to_ros(g)) - g) < 1e-3
    assert abs(clock.to_ros(g) - (g + _true_offset(ctx))) < 1e-3

    class SimCtx:
        clock_kind = "sim"
        t = 3.0

        def now(self):
            return self.t

    sim = SimCtx()
    c = _Clock(sim)
    off = c.offset_now()
    sim.t = 7.0
    time.sleep(0.01)
    assert c.offset_now() == off         # fixed when the node activates on a simulated clock
