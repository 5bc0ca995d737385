"""`isolate: process`: a node runs in a child process under the wall clock, with the same ports, faults and clock."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
from pydantic import Field

from teletouch.component import Component, Kind, Params, Port, Sample
from teletouch.errors import GraphValidationError, ModelFileError
from teletouch.hookspecs import hookimpl
from teletouch.isolation import BLOCK_PREFIX, ProcessProxy
from teletouch.runtime import EXIT_FAULT, EXIT_INTERRUPTED, EXIT_OK, EXIT_STARTUP
from teletouch.testing import load_text, make_registry, run_yaml

# --- test components (module level: the child imports them by name, as it does a plugin's) -------------------------


class Crash(Component):
    """Dies in its step from ``at`` on: os._exit, a segfault, SIGKILL (what the out-of-memory killer sends)."""

    name = "iso-crash"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "")}

    class Params(Params):
        how: str = Field("exit", description="exit | segv | kill")
        at: float = Field(0.2, description="s")

    def step(self, t, inputs):
        if t >= self.params.at:
            if self.params.how == "exit":
                os._exit(3)
            if self.params.how == "segv":
                import ctypes

                ctypes.string_at(0)
            os.kill(os.getpid(), signal.SIGKILL)
        return {"y": t}


class Morph(Component):
    """Outputs an array whose size grows and whose dtype and shape change at every step (some small enough for the
    pipe), and echoes its input ``x`` with its stamp."""

    name = "iso-morph"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("any", None, "any", "", required=False)}
    outputs = {"a": Port("any", None, "any", ""), "n": Port("int64", (), "", ""), "echo": Port("any", None, "any", "")}

    def configure(self):
        self.n = 0

    @staticmethod
    def array(n: int) -> np.ndarray:
        dtype = np.dtype(["uint8", "float32", "float64", "complex64", "bool", "int16"][n % 6])
        count = (8000 if n % 5 == 4 else 20000 + 1500 * n) // dtype.itemsize   # every 5th: < 16 kB, the pipe
        rows = 1 + n % 7
        return (np.arange(rows * (count // rows)) % 251).astype(dtype).reshape(rows, -1)

    def step(self, t, inputs):
        out = {"a": self.array(self.n), "n": self.n}
        self.n += 1
        x = inputs["x"]
        if x is not None:
            out["echo"] = Sample(x.value, x.stamp)
        return out


class NanStamp(Component):
    name = "iso-nan-stamp"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "")}

    def step(self, t, inputs):
        return {"y": Sample(1.0, float("nan") if t >= 0.2 else t)}


class Unpicklable(Component):
    name = "iso-unpicklable"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("any", (), "any", ""), "ok": Port("float64", (), "any", "")}

    def step(self, t, inputs):
        import threading

        return {"ok": t, "y": threading.Lock() if t >= 0.2 else 0.0}


class LateBlock(Component):
    """Its step at ``at`` answers late (after the parent's 1 s step timeout) with its first large array; then it
    dies in deactivate(), so it never removes that block itself."""

    name = "iso-late-block"
    kind = Kind.ESTIMATOR
    outputs = {"a": Port("float64", (None,), "any", "")}

    class Params(Params):
        at: float = Field(0.1, description="s")

    def step(self, t, inputs):
        if t < self.params.at:
            return {"a": np.zeros(4)}
        time.sleep(1.5)
        return {"a": np.ones(100_000)}

    def deactivate(self):
        os._exit(1)


class SlowStart(Component):
    """Takes ``configure_s`` to configure (a model that loads); says so on stdout when it starts."""

    name = "iso-slow-start"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "")}

    class Params(Params):
        configure_s: float = Field(2.0, description="s")

    def configure(self):
        print("configuring", flush=True)
        time.sleep(self.params.configure_s)

    def step(self, t, inputs):
        return {"y": t}


class NeedsModel(Component):
    name = "iso-needs-model"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "")}

    class Params(Params):
        model: str = Field("x.model", description="model file")
        gain: float = Field(1.0, gt=0, description="gain")

    def configure(self):
        if not os.path.exists(self.params.model):
            raise ModelFileError(f"model: {self.params.model}: no such model file")

    def step(self, t, inputs):
        return {"y": t}


class Tally(Component):
    """Counts its steps; results() says how many and in which process (or raises, or holds a value that cannot be
    pickled)."""

    name = "iso-tally"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "any", "")}

    class Params(Params):
        results: str = Field("ok", description="ok | raise | unpicklable")

    def configure(self):
        self.n = 0

    def step(self, t, inputs):
        self.n += 1
        return {"y": t}

    def results(self):
        if self.params.results == "raise":
            raise RuntimeError("tally lost count")
        out = {"steps_counted": self.n, "pid": os.getpid()}
        if self.params.results == "unpicklable":
            out["lock"] = threading.Lock()
        return out


@hookimpl
def teletouch_components():
    return [Crash, Morph, NanStamp, Unpicklable, LateBlock, SlowStart, NeedsModel, Tally]

GRAPH = """
clock: wall
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: ramp, amplitude: 1.0}}
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 5ms}, inputs: {x: src.value}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 500, inputs: {command: est.y}}
"""


@pytest.fixture(scope="module")
def reg():
    return make_registry(sys.modules[__name__])


@pytest.fixture(scope="module")
def image_reg():
    """The mocks and the real image chain: sim-digit and depth."""
    return make_registry("teletouch.plugins.sensors.sim_digit", "teletouch.plugins.estimators.depth")


def test_isolated_node_runs_in_its_own_process_on_the_same_clock(reg):
    seen = []
    res, rt = run_yaml(GRAPH, reg, duration=1.0, taps=[lambda n, t, o: n == "est" and seen.append((t, o))])
    assert res.exit_code == EXIT_OK, res.message
    pids = {o["pid"] for _, o in seen}
    assert len(pids) == 1 and os.getpid() not in pids
    assert len(seen) >= 15
    # the echo of a ramp (value = t) shows both processes read the same graph clock. At a tick both rates share
    # (0.1 s, 0.2 s, ...) src's thread may write its sample after est's step took its time t and before est's
    # inputs were read (threads of two rates, no order between them): that echo is newer than t by the few
    # microseconds between the two (seen: 29 us), never by a period
    for t, o in seen[5:]:
        assert -0.001 <= t - o["y"] <= 0.05
    assert rt.latest("dev", "state").value == pytest.approx(seen[-1][1]["y"], abs=0.05)


def test_exception_in_child_is_a_fault_with_its_origin(reg):
    res, rt = run_yaml(GRAPH.replace("burn: 5ms}", "burn: 5ms, fail_at: 0.3}"), reg, duration=2.0)
    assert res.exit_code == EXIT_FAULT
    assert "in isolated process: ValueError: mock-burn failure" in res.message and "mock.py:" in res.message
    assert rt.component("dev").safe_calls >= 1


def test_request_stop_from_child(reg):
    res, _ = run_yaml(GRAPH.replace("burn: 5ms}", "burn: 5ms, stop_at: 0.2}"), reg, duration=5.0)
    assert res.status == "stopped" and "mock-burn stop" in res.message


def test_child_that_dies_is_a_fault(reg):
    text = GRAPH.replace("plugin: mock-burn, rate: 30, params: {burn: 5ms}",
                         "plugin: mock-burn, rate: 30, params: {burn: 5ms}")
    from teletouch.runtime import Runtime

    rt = Runtime(load_text(text, reg), log=lambda m: None)
    proxy = rt.component("est")
    killed = []

    def kill_after_some(node, t, out):
        if node == "dev" and t > 0.3 and not killed:
            proxy._proc.kill()
            killed.append(t)

    rt.add_tap(kill_after_some)
    res = rt.run(3.0)
    assert res.exit_code == EXIT_FAULT and "isolated process died" in res.message


def test_sim_clock_runs_isolated_nodes_inline(reg):
    seen = []
    res, _ = run_yaml(GRAPH.replace("clock: wall", "clock: sim"), reg, duration=0.5,
                      taps=[lambda n, t, o: n == "est" and seen.append(o["pid"])])
    assert res.exit_code == EXIT_OK and set(seen) == {os.getpid()}


def test_devices_cannot_be_isolated(reg):
    with pytest.raises(GraphValidationError, match="isolate: process is for sensors"):
        load_text(GRAPH.replace("inputs: {command: est.y}}", "inputs: {command: est.y}, isolate: process}"), reg)
    with pytest.raises(GraphValidationError, match="isolate: expected 'none' or 'process'"):
        load_text(GRAPH.replace("isolate: process", "isolate: thread"), reg)


# --- large arrays cross through shared memory ---------------------------------------------------------------------

def _shm_blocks(*prefixes: str) -> set[str]:
    """The shared-memory blocks in /dev/shm whose names start with one of ``prefixes``. Only ever this test's own:
    every process on the machine shares /dev/shm (another test run, another user of isolated nodes), so a test that
    compared all of them before and after failed whenever someone else made or removed a block meanwhile."""
    assert prefixes and all(prefixes), "name the blocks to look at: all of /dev/shm is not this test's"
    return {n for n in os.listdir("/dev/shm") if n.startswith(prefixes)} if os.path.isdir("/dev/shm") else set()


def _blocks_of(rt) -> set[str]:
    """The blocks left by ``rt``'s isolated nodes: each names all of its blocks, its own and its child's, with a
    random prefix of its own (teletouch_<8 hex>_), so nothing else on the machine has one."""
    prefixes = [n.comp._prefix for n in rt.nodes if isinstance(n.comp, ProcessProxy)]
    assert prefixes and all(p.startswith(BLOCK_PREFIX) and len(p) > len(BLOCK_PREFIX) + 1 for p in prefixes), prefixes
    return _shm_blocks(*prefixes)


def test_array_lanes_round_trip_large_arrays_through_shared_memory():
    import numpy as np

    from teletouch.isolation import SHARED_MIN_BYTES, ArrayLanes, SharedRef

    a, b = ArrayLanes(), ArrayLanes()
    small = np.arange(10.0)
    assert a.pack("x", small) is small and a.pack("f", 1.5) == 1.5           # small values take the pipe
    assert a.pack("o", np.array([None] * 5000, dtype=object)).dtype == object  # so do object arrays
    img = np.random.default_rng(0).integers(0, 255, (320, 240, 3), dtype=np.uint8)
    ref = a.pack("image", img)
    assert isinstance(ref, SharedRef) and ref.shape == (320, 240, 3) and img.nbytes >= SHARED_MIN_BYTES
    got = b.unpack(ref)
    assert got.dtype == np.uint8 and np.array_equal(got, img)
    first = got[0, 0, 0]
    img[0, 0] = 7 if first != 7 else 8
    assert b.unpack(a.pack("image", img))[0, 0, 0] == img[0, 0, 0]  # the same block, rewritten
    assert got[0, 0, 0] == first                                     # the receiver kept its own copy
    # a larger array on the same port remakes the block; a non-contiguous one is copied as it reads
    big = np.asfortranarray(np.random.default_rng(1).random((400, 300)))
    ref2 = a.pack("image", big)
    assert ref2.name != ref.name and np.array_equal(b.unpack(ref2), big)
    names = {ref.name, ref2.name}
    a.close()
    assert not (names & _shm_blocks("psm_"))     # the maker unlinks its blocks
    b.close(unlink_peer=True)                    # (and the reader may unlink what it read: already gone, no error)


def test_no_shared_memory_is_a_clear_fault(monkeypatch):
    import numpy as np

    from teletouch import isolation
    from teletouch.errors import ComponentFault

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(isolation.shared_memory, "SharedMemory", full)
    with pytest.raises(ComponentFault, match=r"cannot make a 230400 B shared-memory block .*No space left.*--shm-size"):
        isolation.ArrayLanes().pack("image", np.zeros((320, 240, 3), np.uint8))


def test_isolated_depth_estimator_gets_images_and_returns_depth_maps_exactly(image_reg):
    """The real image chain, split over two processes: sim-digit's frames go to an isolated `depth` through shared
    memory and its depth maps come back; they equal the maps the same estimator computes inline."""
    from helpers_depth import ImageChainTap, isolated_depth_graph
    from teletouch.runtime import Runtime

    chain = ImageChainTap()
    shared: list = []

    def tap(node, t, out):
        chain(node, t, out)
        if node == "depth":
            lanes = rt.component("depth")._lanes
            shared.append((len(lanes._own), len(lanes._peer)))   # the image went out, the maps came back shared

    rt = Runtime(load_text(isolated_depth_graph(30), image_reg), log=lambda m: None)
    rt.add_tap(tap)
    res = rt.run(1.0)
    assert res.exit_code == EXIT_OK, res.message
    assert rt.component("depth")._proc.exitcode == 0 and not _blocks_of(rt)   # no block left behind
    assert chain.check_inline(skip=3) >= 10 and max(float(o["max_depth"].value) for o in chain.outs) > 2e-4
    assert shared[-1] == (1, 2)   # image out; depth and contact mask back (max depth, area, centroid: the pipe)


def test_blocks_of_a_child_that_died_are_removed(image_reg):
    from teletouch.runtime import Runtime

    text = """
clock: wall
nodes:
  - {id: digit, plugin: sim-digit, rate: 30, params: {indentation: 0.0005}}
  - {id: depth, plugin: depth, rate: 30, inputs: {image: digit.image}, isolate: process}
"""
    rt = Runtime(load_text(text, image_reg), log=lambda m: None)
    proxy = rt.component("depth")
    seen: list = []

    def kill_when_shared(node, t, out):
        if node == "depth" and not seen and len(proxy._lanes._peer) == 2:
            seen.append({b.name for b in proxy._lanes._peer.values()} & _blocks_of(rt))   # the child's blocks exist
            proxy._proc.kill()

    rt.add_tap(kill_when_shared)
    res = rt.run(3.0)
    assert res.exit_code == EXIT_FAULT and "isolated process died" in res.message
    assert len(seen[0]) == 2 and not _blocks_of(rt)


def test_isolated_node_runs_at_its_priority(reg):
    """`priority:` on an isolated node applies to its process (it would have applied to its thread inline)."""
    if not hasattr(os, "sched_getscheduler"):  # pragma: no cover - Linux has it
        pytest.fail("needs Linux scheduling calls")
    logs: list[str] = []
    from teletouch.runtime import Runtime

    text = GRAPH.replace("isolate: process}", "isolate: process, priority: 7}")
    rt = Runtime(load_text(text, reg), log=logs.append)
    policies = []

    def tap(node, t, out):
        if node == "est" and not policies:
            pid = out["pid"]
            policies.append((os.sched_getscheduler(pid), os.sched_getparam(pid).sched_priority))

    rt.add_tap(tap)
    res = rt.run(0.5)
    assert res.exit_code == EXIT_OK, res.message
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))   # may this user use SCHED_FIFO at all?
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        allowed = True
    except PermissionError:
        allowed = False
    if allowed:
        assert policies[0] == (os.SCHED_FIFO, 7)
    else:
        assert policies[0][0] == os.SCHED_OTHER
        assert any("priority 7: cannot use SCHED_FIFO in the isolated process" in m for m in logs)
    # without a priority the child runs with normal scheduling
    policies.clear()
    res, _ = run_yaml(GRAPH, reg, duration=0.3, taps=[tap])
    assert policies[0] == (os.SCHED_OTHER, 0)


def test_a_step_that_times_out_does_not_shift_the_replies_of_later_calls():
    # the isolated step hangs past its timeout (1 s): a fault; then deactivate() raises in the child. That error must
    # be reported as deactivate's (the late step reply is read and dropped first), not as close()'s
    text = """
clock: wall
nodes:
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 1ms, hang_at: 0.1, hang_for: 1.4, deactivate_error: true},
     isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""
    res, rt = run_yaml(text, make_registry(), duration=5.0)
    assert res.status == "fault" and "did not answer 'step'" in res.message
    shutdown = [f.message for f in res.faults if f.kind == "shutdown"]
    assert any(m.startswith("deactivate() raised") and "mock-burn deactivate failure" in m for m in shutdown), shutdown
    assert not any(m.startswith("close() raised") for m in shutdown), shutdown
    assert rt.component("dev").safe


# --- failure modes: a child that dies or hangs, values that cannot cross, signals, start-up errors ------------------

CRASH = """
clock: wall
nodes:
  - {id: est, plugin: iso-crash, rate: 30, params: {how: HOW}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""


@pytest.mark.parametrize("how, says", [
    ("exit", "exited with code 3"),
    ("segv", "was killed by signal 11 (SIGSEGV)"),
    ("kill", "was killed by signal 9 (SIGKILL; the out-of-memory killer sends it too)"),
])
def test_a_child_that_dies_is_a_fault_that_names_the_node_the_plugin_and_how(reg, how, says):
    t0 = time.monotonic()
    res, rt = run_yaml(CRASH.replace("HOW", how), reg, duration=10.0)
    assert time.monotonic() - t0 < 20.0                 # start-up included (generous: a loaded machine)
    assert res.exit_code == EXIT_FAULT and res.sim_time < 3.0        # noticed at once, not at the end of the run
    assert "node 'est' exception: ComponentFault: isolated process died during 'step': iso-crash (pid " in res.message
    assert says in res.message, res.message
    assert rt.component("dev").safe and rt.component("dev").safe_calls >= 1
    assert [f.kind for f in res.faults] == ["exception"]          # no second fault from its shutdown
    proc = rt.component("est")._proc
    assert proc.exitcode == {"exit": 3, "segv": -11, "kill": -9}[how]   # reaped: no zombie
    assert not _blocks_of(rt)


def test_a_step_that_hangs_for_good_is_a_fault_and_the_shutdown_kills_the_child_in_bounded_time(monkeypatch):
    """Before, deactivate waited 120 s and close 10 s more for the answer of the hung step (137 s in all here)."""
    from teletouch import isolation

    monkeypatch.setattr(isolation, "SHUTDOWN_TIMEOUT", 1.0, raising=False)
    text = """
clock: wall
nodes:
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 0ms, hang_at: 0.1, hang_for: 600}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""
    t0 = time.monotonic()
    res, rt = run_yaml(text, make_registry(), duration=30.0)
    assert time.monotonic() - t0 < 20.0
    assert res.status == "fault" and "isolated process did not answer 'step' within 1 s" in res.message
    assert res.faults[0].time < 1.0                                  # the time of the step that hung
    shutdown = [f.message for f in res.faults if f.kind == "shutdown"]
    assert len(shutdown) == 1 and shutdown[0].startswith(
        "deactivate() raised ComponentFault: isolated process did not answer 'deactivate' within 1 s"), shutdown
    assert rt.component("dev").safe
    assert rt.component("est")._proc.exitcode == -signal.SIGKILL     # killed (it ignores SIGTERM), and reaped
    assert not _blocks_of(rt)


def test_shutdown_while_a_step_is_still_running_waits_for_it_and_never_takes_its_reply():
    """The run ends (its duration) while the isolated node's thread waits for a 3 s step (4 Hz: its timeout is 5 s).
    The runtime joins threads for 1 s only, then deactivates from the main thread: before, both threads read the
    same pipe, the step got deactivate's answer and the run that ended normally was a fault ('not enough values to
    unpack')."""
    text = """
clock: wall
nodes:
  - {id: est, plugin: mock-burn, rate: 4, params: {burn: 0ms, hang_at: 0.2, hang_for: 3.0}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""
    steps: list[float] = []
    res, rt = run_yaml(text, make_registry(), duration=0.6, taps=[lambda n, t, o: n == "est" and steps.append(t)])
    assert res.status == "ok" and res.exit_code == EXIT_OK, (res.message, [f.line() for f in res.faults])
    assert res.faults == []
    assert any(0.2 <= t < 0.6 for t in steps), steps                 # the long step's own reply reached it
    assert rt.component("est")._proc.exitcode == 0                   # deactivated and closed normally


def test_a_block_of_a_child_that_died_before_naming_it_is_removed(reg):
    """The child answers a step after its timeout with a new large-array block (that late reply is dropped, so the
    parent never learns the block's name), then dies in deactivate(): its block is removed all the same."""
    text = """
clock: wall
nodes:
  - {id: est, plugin: iso-late-block, rate: 30, isolate: process}
"""
    res, rt = run_yaml(text, reg, duration=5.0)
    assert res.status == "fault" and "did not answer 'step'" in res.message
    assert any(f.kind == "shutdown" and "died during 'deactivate'" in f.message and "exited with code 1" in f.message
               for f in res.faults), [f.line() for f in res.faults]
    assert not _blocks_of(rt)


def test_arrays_that_change_size_shape_and_dtype_cross_both_ways_without_piling_up_blocks(reg):
    """An isolated node gets arrays that change every step from an inline node and returns such arrays. The reader
    keeps one mapping per port: before, every larger array left a mapping (and 2 file descriptors) behind on the
    reading side, until the process ran out of descriptors."""
    from teletouch.runtime import Runtime

    text = """
clock: wall
nodes:
  - {id: src, plugin: iso-morph, rate: 60}
  - {id: iso, plugin: iso-morph, rate: 60, inputs: {x: src.a}, isolate: process}
"""
    rt = Runtime(load_text(text, reg), log=lambda m: None)
    proxy = rt.component("iso")
    sent: dict[float, np.ndarray] = {}
    checked: list[int] = []
    echoed: list[int] = []
    mapped: list[int] = []

    def tap(node, t, out):
        if node == "src":
            sent[t] = out["a"]
            return
        n = out["n"]
        a = out["a"].value if isinstance(out["a"], Sample) else out["a"]
        ref = Morph.array(n)
        assert a.dtype == ref.dtype and a.shape == ref.shape and np.array_equal(a, ref)
        if "echo" in out and out["echo"].stamp in sent:
            x = sent[out["echo"].stamp]
            assert out["echo"].value.dtype == x.dtype and np.array_equal(out["echo"].value, x)
            echoed.append(n)
        checked.append(n)
        mapped.append(len(proxy._lanes._peer))

    rt.add_tap(tap)
    res = rt.run(1.0)
    assert res.exit_code == EXIT_OK, res.message
    assert len(checked) >= 10 and len(echoed) >= 5
    assert max(mapped) <= 2, mapped              # one block per port that comes back shared ("a", "echo")
    assert not _blocks_of(rt)


def test_array_lanes_keep_one_mapping_per_port_while_arrays_grow():
    from teletouch.isolation import ArrayLanes

    a, b = ArrayLanes(), ArrayLanes()
    fds = len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else None
    for n in range(200):
        v = np.full(2048 + 8 * n, float(n))
        got = b.unpack(a.pack("y", v), "y")
        assert got.shape == v.shape and got[-1] == n
    assert len(b._peer) == 1 and len(a._own) == 1
    if fds is not None:
        assert len(os.listdir("/proc/self/fd")) - fds <= 4                 # before: 2 per larger array (~400)
    a.close()
    b.close()


def test_a_full_dev_shm_is_a_clear_fault_not_a_sigbus(monkeypatch):
    """A block is a sparse file: made larger than what is left in /dev/shm, the first write to a missing page killed
    the writing process (the parent: no safe state) with SIGBUS. Its pages are now reserved when it is made. Where a
    private mount namespace can be made (root, or user namespaces), a real 1 MB /dev/shm is also tried."""
    import errno
    import shutil

    from teletouch import isolation
    from teletouch.errors import ComponentFault

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(isolation.os, "posix_fallocate", full, raising=False)
        prefix = f"teletouch_testfull{os.getpid()}_"   # this process's own: nobody else makes or removes them
        with pytest.raises(ComponentFault, match=r"cannot make a 800000 B shared-memory block .*No space left.*"
                                                 r"--shm-size"):
            isolation.ArrayLanes(prefix).pack("image", np.zeros(100_000))
        assert not _shm_blocks(prefix)                                   # the block that could not be had is gone
    code = textwrap.dedent("""
        import numpy as np
        from teletouch.errors import ComponentFault
        from teletouch.isolation import ArrayLanes
        try:
            ArrayLanes().pack("x", np.ones(4_000_000))
            print("packed")
        except ComponentFault as exc:
            print("fault:", exc)
    """)
    for cmd in (["unshare", "-rm"], ["unshare", "-m"]):
        if shutil.which(cmd[0]) is None:
            break
        probe = subprocess.run(cmd + ["true"], capture_output=True)
        if probe.returncode != 0:
            continue
        run = subprocess.run(cmd + ["sh", "-c", 'mount -t tmpfs -o size=1m tmpfs /dev/shm && exec "$0" -c "$1"',
                                    sys.executable, code], capture_output=True, text=True, timeout=60)
        if "mount" in run.stderr and run.returncode != 0 and "fault" not in run.stdout:
            continue   # no tmpfs mounts here
        assert run.returncode == 0, (run.returncode, run.stderr[-2000:])   # -7: SIGBUS
        assert "fault: isolated node: cannot make a 32000000 B shared-memory block" in run.stdout, run.stdout
        break


def test_a_value_that_cannot_be_pickled_is_a_fault_naming_its_port(reg):
    text = """
clock: wall
nodes:
  - {id: est, plugin: iso-unpicklable, rate: 30, isolate: process}
"""
    res, rt = run_yaml(text, reg, duration=3.0)
    assert res.exit_code == EXIT_FAULT
    assert "output 'y' cannot cross to the parent process: TypeError: cannot pickle '_thread.lock' object" \
        in res.message, res.message
    assert rt.component("est")._proc.exitcode == 0
    # the other way: an inline node's output that an isolated node reads
    text = """
clock: wall
nodes:
  - {id: src, plugin: iso-unpicklable, rate: 30}
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 0ms}, inputs: {x: src.y}, isolate: process}
"""
    res, rt = run_yaml(text, reg, duration=3.0)
    assert res.exit_code == EXIT_FAULT
    assert "node 'est' exception: ComponentFault: input 'x' cannot cross to the isolated process: TypeError: " \
           "cannot pickle '_thread.lock' object" in res.message, res.message
    assert rt.component("est")._proc.exitcode == 0                   # the pipe was not left half-written


def test_a_nan_stamp_from_the_child_is_a_fault_as_inline(reg):
    for isolate in ("none", "process"):
        text = f"""
clock: wall
nodes:
  - {{id: est, plugin: iso-nan-stamp, rate: 30, isolate: {isolate}}}
"""
        res, _ = run_yaml(text, reg, duration=3.0)
        assert res.exit_code == EXIT_FAULT
        assert "step() returned output 'y' stamped nan: a stamp must be a finite graph time" in res.message


def test_start_up_errors_in_the_child_are_reported_like_inline_ones(reg):
    base = """
clock: wall
nodes:
  - {id: est, plugin: iso-needs-model, rate: 30, params: {model: /nonexistent/m.model}, isolate: ISO}
"""
    for iso in ("none", "process"):
        res, _ = run_yaml(base.replace("ISO", iso), reg, duration=1.0)
        assert res.exit_code == EXIT_STARTUP
        assert res.message.startswith("node 'est' (iso-needs-model) failed to configure: ")
        assert "ModelFileError: model: /nonexistent/m.model: no such model file" in res.message
        assert [f.kind for f in res.faults] == ["startup"], [f.line() for f in res.faults]
        # bad parameters are refused when the graph is loaded, before any process starts
        with pytest.raises(GraphValidationError, match="gain"):
            load_text(base.replace("ISO", iso).replace("model: /nonexistent/m.model", "gain: -1"), reg)


def test_a_component_class_the_child_cannot_import_is_a_start_up_failure_with_its_reason(reg, tmp_path,
                                                                                         monkeypatch):
    """Before, the child died while unpickling its arguments and the parent reported 'isolated process died (exit
    code None) during configure: ConnectionResetError', and a second fault from close()."""
    import importlib
    import shutil

    mod = "iso_vanishing_plugin_" + os.urandom(4).hex()
    (tmp_path / f"{mod}.py").write_text(textwrap.dedent("""
        from teletouch.component import Component, Port
        from teletouch.hookspecs import hookimpl

        class Gone(Component):
            name = "iso-gone"
            outputs = {"y": Port("float64", (), "any", "")}

            def step(self, t, inputs):
                return {"y": t}

        @hookimpl
        def teletouch_components():
            return [Gone]
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    plugin = importlib.import_module(mod)
    (tmp_path / f"{mod}.py").unlink()            # importable here, not in a new process (a plugin removed meanwhile)
    shutil.rmtree(tmp_path / "__pycache__", ignore_errors=True)
    text = """
clock: wall
nodes:
  - {id: est, plugin: iso-gone, rate: 30, isolate: process}
"""
    res, rt = run_yaml(text, make_registry(plugin), duration=1.0)
    assert res.exit_code == EXIT_STARTUP
    assert res.message.startswith("node 'est' (iso-gone) failed to configure: ComponentFault: in isolated process: "
                                  f"cannot import the component class: ModuleNotFoundError: No module named '{mod}'")
    assert [f.kind for f in res.faults] == ["startup"], [f.line() for f in res.faults]
    assert rt.component("est")._proc.exitcode == 0


def test_a_local_component_class_is_a_start_up_failure_that_says_why(reg):
    class Local(Component):
        name = "iso-local"
        outputs = {"y": Port("float64", (), "any", "")}

        def step(self, t, inputs):
            return {"y": t}

    class Plugin:
        @hookimpl
        def teletouch_components(self):
            return [Local]

    text = """
clock: wall
nodes:
  - {id: est, plugin: iso-local, rate: 30, isolate: process}
"""
    res, _ = run_yaml(text, make_registry(Plugin(), mocks=False), duration=1.0)
    assert res.exit_code == EXIT_STARTUP
    assert "isolate: process needs a component class that a new process can import by name" in res.message
    # before: close() also raised "AssertionError: can only join a started process"
    assert [f.kind for f in res.faults] == ["startup"], [f.line() for f in res.faults]


_SCRIPT = """
import faulthandler, json, signal, sys
faulthandler.dump_traceback_later(45, exit=True)   # a run that hangs: every thread's stack on stderr, then exit
sys.path.insert(0, sys.argv[1])            # the tests: their components, importable by the child as well
import test_core_isolation
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry

def term(signum, frame):                   # as `teletouch run` does
    raise KeyboardInterrupt

signal.signal(signal.SIGTERM, term)
rt = Runtime(load_text(sys.argv[2], make_registry(test_core_isolation)),
             log=lambda m: print("log:", m, file=sys.stderr))
said = []

def tap(node, t, out):
    if node == "est" and not said:
        said.append(1)
        print("child", out["pid"], flush=True)

rt.add_tap(tap)
res = rt.run(30.0)
proc = rt.component("est")._proc
print(json.dumps({"status": res.status, "exit_code": res.exit_code, "faults": [f.line() for f in res.faults],
                  "child_exit": proc.exitcode, "safe": getattr(rt.component("dev"), "safe", None)}), flush=True)
"""

_RUNNING = """
clock: wall
nodes:
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 1ms, hang_at: HANG, hang_for: 300}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""
_STARTING = """
clock: wall
nodes:
  - {id: est, plugin: iso-slow-start, rate: 30, isolate: process}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: est.y}}
"""


def _start_script(graph: str, until: str) -> tuple[subprocess.Popen, int]:
    """Run ``graph`` in a new Python process (a session of its own) until it prints a line starting with ``until``
    ('child PID' from the isolated node's first step, or 'configuring' from iso-slow-start in the child)."""
    here = os.path.dirname(os.path.abspath(__file__))
    proc = subprocess.Popen([sys.executable, "-c", _SCRIPT, here, graph], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    line = proc.stdout.readline()
    if not line.startswith(until):
        proc.kill()
        raise AssertionError(f"the run did not start: {line!r} {proc.communicate()[1][-2000:]}")
    return proc, int(line.split()[1]) if line.startswith("child ") else 0


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"     # a zombie: dead, waiting for its reaper
    except FileNotFoundError:
        return True


@pytest.mark.parametrize("phase", ["running", "starting"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_to_the_process_group_shuts_down_cleanly(sig, phase):
    """Ctrl-C reaches every process of the terminal's group (systemd's stop sends SIGTERM to all processes of the
    service). Before, the child died of it at once (a KeyboardInterrupt traceback), its component was never
    deactivated or closed, and the parent reported faults for the dead child; hit while the child was still in
    configure() (loading a model), it answered configure with the KeyboardInterrupt and close() took that answer."""
    if phase == "running":
        proc, _ = _start_script(_RUNNING.replace("HANG", "1000"), "child ")
    else:
        proc, _ = _start_script(_STARTING, "configuring")
    try:
        time.sleep(0.3)
        os.killpg(proc.pid, sig)
        try:
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:   # (the script dumps its threads' stacks and exits after 45 s itself)
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            raise AssertionError(f"no exit 60 s after the signal; stdout: {out[-2000:]!r}; stderr: {err[-6000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    import json

    assert "Timeout (0:00:45)!" not in err, f"the run hung; its threads' stacks:\n{err[-8000:]}"
    res = json.loads(out.strip().splitlines()[-1])
    assert res["status"] == "interrupted" and res["exit_code"] == EXIT_INTERRUPTED, res
    assert res["faults"] == [], res["faults"]
    assert res["child_exit"] == 0                                     # closed through the pipe: a clean exit
    assert res["safe"] is (True if phase == "running" else None)     # (not configured yet: never started)
    assert "Traceback" not in err, err[-3000:]


def _interrupt_in_the_wait(rt, k: int, nth: int = 3) -> tuple[object, bool]:
    """Run ``rt`` (wall clock) in a thread that stands for the main one, where a Ctrl-C raises KeyboardInterrupt at
    whichever bytecode it is at: in the watchdog loop's ``nth`` wait for the stop (the main thread spends the run
    there), it is raised before the ``k``-th bytecode (counting those of the functions that the wait calls). Returns
    the run's result (or what it raised, or a text with its thread's stack when it hung), and whether the wait had
    returned before its ``k``-th bytecode (k past its end: nothing was raised; the run is then stopped)."""
    from teletouch.runtime import Runtime

    loop = Runtime._run_wall.__code__
    st = {"loop": None, "waits": 0, "top": None, "n": 0, "done": False, "fired": False}

    def local(frame, event, arg):
        if st["done"]:
            return None
        if event == "opcode":
            st["n"] += 1
            if st["n"] == k:
                st["done"] = st["fired"] = True
                raise KeyboardInterrupt
        elif event == "return" and frame is st["top"]:
            st["done"] = True   # the wait returned first: nothing more to test, the run is stopped
            rt.request_stop("k past the end of the wait")
        return local

    def tracer(frame, event, arg):
        if st["done"]:
            return None
        if frame.f_code is loop:
            st["loop"] = frame
        elif st["top"] is not None:   # called from the wait: its bytecodes count too
            frame.f_trace_opcodes = True
            return local
        elif frame.f_back is st["loop"] is not None and frame.f_code.co_name == "wait":
            st["waits"] += 1
            if st["waits"] == nth:
                st["top"] = frame
                frame.f_trace_opcodes = True
                return local
        return None

    out: list[object] = []

    def main():
        # Python 3.12 sends opcode events only where f_trace_opcodes was set on a frame before sys.settrace() (a
        # frame's f_trace_opcodes set in its call event is ignored: CPython issues 103615, 114480); elsewhere harmless
        sys._getframe().f_trace_opcodes = True
        sys.settrace(tracer)
        try:
            out.append(rt.run(20.0))
        except BaseException as exc:   # noqa: BLE001 - the test says what it was
            out.append(exc)
        finally:
            sys.settrace(None)

    th = threading.Thread(target=main, name="as-main", daemon=True)
    th.start()
    th.join(15.0)
    if th.is_alive():   # hung: its rate groups' threads are ended (the flag they read); this thread stays stuck
        import traceback

        stack = "".join(traceback.format_stack(sys._current_frames()[th.ident]))
        rt._stop_evt._flag = True
        return f"the run hung; its thread:\n{stack}", False
    assert st["top"] is not None, "the run never reached its watchdog loop"
    return out[0], not st["fired"]


@pytest.mark.parametrize("isolated", [False, True], ids=["inline", "isolated"])
def test_a_ctrl_c_at_any_bytecode_of_the_main_threads_wait_ends_the_run_cleanly(reg, isolated):
    """The main thread spends the run in the watchdog loop's wait for the stop; a Ctrl-C raises KeyboardInterrupt
    there at whichever bytecode it is at. That wait was threading.Event.wait(): interrupted right after its
    Condition's lock was taken (Condition.__enter__) or right before it was released (Condition.__exit__), it left
    that lock held, and the shutdown's first stop_evt.set() waited for it forever: the process never exited (about 1
    CI run in 9 of the Ctrl-C test above, never seen locally). Interrupted just before the lock was taken back
    (Condition._acquire_restore) it raised RuntimeError('release unlocked lock') out of run(). Here every bytecode
    of that wait is hit in turn, deterministically."""
    from teletouch.runtime import Runtime

    text = _RUNNING.replace("HANG", "1000")
    if not isolated:
        text = text.replace(", isolate: process", "")
    k = 1
    while True:
        rt = Runtime(load_text(text, reg), log=lambda m: None)
        res, past_the_end = _interrupt_in_the_wait(rt, k)
        assert not isinstance(res, (str, BaseException)), f"KeyboardInterrupt before bytecode {k} of the wait: {res}"
        if past_the_end:
            break
        assert (res.status, res.exit_code, res.faults) == ("interrupted", EXIT_INTERRUPTED, []), (k, res.summary())
        assert rt.component("dev").safe is True
        if isolated:
            assert rt.component("est")._proc.exitcode == 0   # closed through the pipe
        k += 1
    assert k > 3   # (the wait was traced)


def test_a_ctrl_c_while_the_rate_groups_threads_start_ends_the_run_cleanly(reg, monkeypatch):
    """Ctrl-C right at the start of the run, while the main thread starts the rate groups' threads: the thread of
    the second group (est, 30 Hz) is not started. The shutdown's join() of it raised RuntimeError ('cannot join
    thread before it is started') out of run(), in place of the interrupted result (seen 5 times in 600 runs of a
    SIGINT at a random moment under load)."""
    from teletouch.runtime import Runtime

    start = threading.Thread.start

    def interrupted_start(self):
        if self.name == "teletouch-30Hz":
            raise KeyboardInterrupt
        start(self)

    monkeypatch.setattr(threading.Thread, "start", interrupted_start)
    rt = Runtime(load_text(_RUNNING.replace("HANG", "1000"), reg), log=lambda m: None)
    res = rt.run(20.0)
    assert (res.status, res.exit_code, res.faults) == ("interrupted", EXIT_INTERRUPTED, []), res.summary()
    assert rt.component("dev").safe is True
    assert rt.component("est")._proc.exitcode == 0   # closed through the pipe


def test_a_child_does_not_outlive_its_parent():
    """The parent is killed (SIGKILL: no shutdown at all) while its isolated node hangs in a step: the child is
    killed too (Linux), instead of holding its camera or GPU until its step returns."""
    if not sys.platform.startswith("linux"):  # pragma: no cover - the project's machines are Linux
        pytest.fail("PR_SET_PDEATHSIG is Linux only")
    proc, child = _start_script(_RUNNING.replace("HANG", "0.1"), "child ")
    try:
        time.sleep(0.5)
        proc.kill()
        proc.wait(timeout=30)
        deadline = time.monotonic() + 10.0
        while not _gone(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(child)
    finally:
        if not _gone(child):
            os.kill(child, signal.SIGKILL)


def test_a_child_left_running_does_not_hang_the_interpreter_at_exit():
    """The child ignores SIGTERM, which multiprocessing sends its daemon children at exit before an unbounded join():
    one never closed (a proxy used by hand) is killed then instead."""
    code = textwrap.dedent("""
        from teletouch.component import Context
        from teletouch.isolation import ProcessProxy
        from teletouch.mock import MockBurn

        p = ProcessProxy(MockBurn, MockBurn.Params(), node_id="x", ctx=Context(), t0_perf=0.0, t0_mono=0.0,
                         step_timeout=1.0)
        p.configure()
        print("child", p._proc.pid, flush=True)
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr[-2000:]
    child = int(run.stdout.split()[1])
    deadline = time.monotonic() + 10.0
    while not _gone(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _gone(child)


TALLY = """
clock: wall
nodes:
  - {id: est, plugin: iso-tally, rate: 50, params: {results: HOW}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 200, inputs: {command: est.y}}
"""


def test_an_isolated_nodes_results_come_from_its_process(reg):
    """results() was not asked of an isolated node (its proxy in the runtime said nothing): `teletouch run` showed no
    results for it. Now the child is asked, after deactivate() and before close(), and its values are taken as an
    inline node's (one that is no number or text, here a lock that could not cross pickled, as its repr)."""
    for how in ("ok", "unpicklable"):
        res, rt = run_yaml(TALLY.replace("HOW", how), reg, duration=0.5)
        assert res.exit_code == EXIT_OK, res.message
        stats = {n.id: n for n in res.nodes}
        got = stats["est"].results
        assert got["pid"] != os.getpid()                           # asked of the child
        assert got["steps_counted"] == stats["est"].steps >= 20    # the child's count: every step the runtime made
        assert not [f for f in res.faults if f.kind == "shutdown"]
        if how == "unpicklable":
            assert got["lock"].startswith("<unlocked _thread.lock object"), got


def test_an_isolated_nodes_results_that_raise_are_a_logged_shutdown_fault(reg):
    res, rt = run_yaml(TALLY.replace("HOW", "raise"), reg, duration=0.3)
    assert res.exit_code == EXIT_OK, res.message               # the run's result stays
    stats = {n.id: n for n in res.nodes}
    assert stats["est"].results == {}
    shutdown = [f for f in res.faults if f.kind == "shutdown"]
    assert len(shutdown) == 1 and shutdown[0].action == "logged", shutdown
    assert shutdown[0].message.startswith("results() raised") and "RuntimeError: tally lost count" in \
        shutdown[0].message, shutdown[0].message
    assert not rt.component("est")._proc.is_alive()            # closed afterwards all the same
