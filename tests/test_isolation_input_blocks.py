"""An isolated node's input block is never rewritten while a request that names it may still be waiting in the pipe.

After a step timed out (or was abandoned) the child may not have read the requests sent since: the next step wrote its
large input into the same shared-memory block, and a request still queued then read that later array (or half of
it) as its own. The proxy now writes into a fresh block while the child has not answered since, and removes the old
ones once it has."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from teletouch.component import Component, Context, Inputs, Kind, Port, Sample, _Slot
from teletouch.errors import ComponentFault
from teletouch.isolation import BLOCK_PREFIX, ProcessProxy

N = 8192   # float64: 64 kB, through shared memory


class Recorder(Component):
    """Records the first and last element of every ``x`` it gets (both the step's number when the array is whole);
    sleeps 1 s in the step whose ``x`` is 1; outputs what it has seen."""

    name = "s14-recorder"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (None,), "any", "")}
    outputs = {"seen": Port("float64", (None, 2), "any", "")}

    def configure(self):
        self.seen: list[tuple[float, float]] = []

    def step(self, t, inputs):
        x = inputs["x"].value
        self.seen.append((float(x[0]), float(x[-1])))
        if x[0] == 1.0:
            time.sleep(1.0)
        return {"seen": np.array(self.seen)}


def _blocks(proxy: ProcessProxy) -> list[str]:
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(proxy._prefix)) if os.path.isdir("/dev/shm") \
        else []


def test_a_request_queued_behind_a_timed_out_step_reads_its_own_input():
    ctx = Context(now=time.perf_counter, clock_kind="wall", rate=100.0)
    proxy = ProcessProxy(Recorder, Recorder.Params(), node_id="rec", ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                         step_timeout=0.2)
    slot = _Slot()
    inputs = Inputs({"x": slot})

    def step(k: int):
        slot.sample = Sample(np.full(N, float(k)), float(k))
        return proxy.step(float(k), inputs)

    try:
        proxy.configure()
        proxy.activate()
        with pytest.raises(ComponentFault, match="did not answer 'step'"):
            step(1)            # the child sleeps 1 s in it
        with pytest.raises(ComponentFault, match="did not answer 'step'"):
            step(2)            # sent; waits in the pipe behind step 1
        proxy._step_timeout = 20.0
        out = step(3)          # sent while step 2 still waits: before, its array went into step 2's block
        # every step saw its own array, whole (before: [1, 1], [3, 3], [3, 3])
        assert out["seen"].tolist() == [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]
        assert not proxy._lanes._retired          # the child answered: the blocks kept for step 2 are gone
        if os.path.isdir("/dev/shm"):
            assert len([n for n in _blocks(proxy) if n.startswith(proxy._prefix + "p")]) == 1, _blocks(proxy)
        assert step(4)["seen"].tolist()[-1] == [4.0, 4.0]
        assert len(proxy._lanes._own) == 1 and not proxy._lanes._retired
    finally:
        proxy.deactivate()
        proxy.close()
    assert proxy._proc.exitcode == 0
    assert not [n for n in os.listdir("/dev/shm") if n.startswith(proxy._prefix)] if os.path.isdir("/dev/shm") \
        else True
    assert proxy._prefix.startswith(BLOCK_PREFIX)
