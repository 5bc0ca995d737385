"""The ROS 2 bridge's graph <-> Unix time mapping is not shifted by a preemption between its two clock reads."""

from __future__ import annotations

import time

import pytest

from teletouch.plugins.bridges.ros2 import _Clock

ORIGIN = 1_700_000_000.0     # Unix time of the fake graph clock's zero: the true offset, exactly


class _JumpyCtx:
    """A wall-clock context whose graph clock is Unix time - ORIGIN, read ``stall`` seconds late on the reads
    numbered in ``at`` (as if the thread had been preempted just before them: the value is later, no real sleep)."""

    clock_kind = "wall"

    def __init__(self, stall: float = 0.0, at: tuple[int, ...] = ()):
        self.reads = 0
        self.stall, self.at = stall, at

    def now(self) -> float:
        self.reads += 1
        return time.time() - ORIGIN + (self.stall if self.reads in self.at else 0.0)


@pytest.mark.parametrize("at", [(2,), (2, 4)])
def test_a_preemption_between_the_reads_does_not_shift_the_mapping(at):
    """A 20 ms stall between the Unix read and the graph read after it puts a plain ``time.time() - now()`` 20 ms
    off (10 ms referred to the pair's middle); the bracketed read sees the wide pair, reads again and keeps the
    tight one: within 1 ms of the true offset."""
    ctx = _JumpyCtx()
    clock = _Clock(ctx)                          # the construction's own read, no stall
    ctx.reads, ctx.stall, ctx.at = 0, 0.020, at
    got = clock.offset_now()
    assert ctx.reads >= 2 * (len(at) + 1)        # each wide pair was read again (a real preemption may add one)
    assert abs(got - ORIGIN) < 1e-3
    ctx.reads, ctx.at = 0, (2, 4, 6)             # all three pairs wide: the tightest of them, no more reads
    clock.offset_now()
    assert ctx.reads == 2 * _Clock.READS


def test_a_tight_first_pair_is_not_read_again():
    class Fixed:
        clock_kind = "wall"
        reads = 0

        def now(self):
            self.reads += 1
            return 5.0 + 1e-6 * self.reads      # two reads 1 us apart: tight

    ctx = Fixed()
    clock = _Clock(ctx)
    ctx.reads = 0
    clock.offset_now()
    assert ctx.reads == 2


def test_the_mapping_round_trips_and_a_sim_clock_keeps_its_offset():
    clock = _Clock(_JumpyCtx())
    g = 12.5
    assert abs(clock.to_graph(clock.to_ros(g)) - g) < 1e-3
    assert abs(clock.to_ros(g) - (g + ORIGIN)) < 1e-3

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
    assert c.offset_now() == off                 # fixed when the node activates on a simulated clock
