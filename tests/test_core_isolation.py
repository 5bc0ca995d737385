"""`isolate: process`: a node runs in a child process under the wall clock, with the same ports, faults and clock."""

from __future__ import annotations

import os

import pytest

from teletouch.errors import GraphValidationError
from teletouch.runtime import EXIT_FAULT, EXIT_OK
from teletouch.testing import load_text, make_registry, run_yaml

GRAPH = """
clock: wall
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: ramp, amplitude: 1.0}}
  - {id: est, plugin: mock-burn, rate: 30, params: {burn: 5ms}, inputs: {x: src.value}, isolate: process}
  - {id: dev, plugin: mock-device, rate: 500, inputs: {command: est.y}}
"""


@pytest.fixture(scope="module")
def reg():
    return make_registry()


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
    # the echo of a ramp (value = t) shows both processes read the same graph clock
    for t, o in seen[5:]:
        assert 0.0 <= t - o["y"] <= 0.05
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

def _shm_blocks() -> set[str]:
    return {n for n in os.listdir("/dev/shm") if n.startswith("psm_")} if os.path.isdir("/dev/shm") else set()


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
    assert not (names & _shm_blocks())           # the maker unlinks its blocks
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
    import numpy as np

    from teletouch.component import Sample
    from teletouch.plugins.estimators.depth import DepthEstimator
    from teletouch.testing import Harness

    text = """
clock: wall
nodes:
  - {id: press, plugin: mock-sensor, rate: 30, params: {signal: sine, amplitude: 0.0004, offset: 0.0006, frequency: 2}}
  - {id: digit, plugin: sim-digit, rate: 30, inputs: {indentation: press.value}}
  - {id: depth, plugin: depth, rate: 30, inputs: {image: digit.image}, isolate: process}
"""
    before = _shm_blocks()
    images: dict[float, np.ndarray] = {}
    outs: list[dict] = []

    def tap(node, t, out):
        if node == "digit":
            v = out["image"]
            images[v.stamp if isinstance(v, Sample) else t] = v.value if isinstance(v, Sample) else v
        elif node == "depth":
            outs.append(out)
            lanes = rt_ref[0].component("depth")._lanes
            shared.append((len(lanes._own), len(lanes._peer)))   # the image went out, the maps came back shared

    rt_ref: list = []
    shared: list = []
    from teletouch.runtime import Runtime

    rt = Runtime(load_text(text, image_reg), log=lambda m: None)
    rt_ref.append(rt)
    rt.add_tap(tap)
    res = rt.run(1.0)
    assert res.exit_code == EXIT_OK, res.message
    assert rt.component("depth")._proc.exitcode == 0 and _shm_blocks() <= before   # no block left behind
    checked = 0
    with Harness(DepthEstimator, {}) as h:
        for o in outs[3:]:
            d = o["depth"]
            img = images.get(d.stamp)
            if img is None:
                continue
            h.set(image=Sample(img, d.stamp))
            ref = h.comp.step(d.stamp, h.inputs)
            assert d.value.dtype == np.float32 and d.value.shape == (320, 240)
            assert np.array_equal(d.value, ref["depth"].value)
            assert np.array_equal(o["contact_mask"].value, ref["contact_mask"].value)
            checked += 1
    assert checked >= 10 and max(float(o["max_depth"].value) for o in outs) > 2e-4
    assert shared[-1] == (1, 2)   # image out; depth and contact mask back (max depth, area, centroid: the pipe)


def test_blocks_of_a_child_that_died_are_removed(image_reg):
    from teletouch.runtime import Runtime

    text = """
clock: wall
nodes:
  - {id: digit, plugin: sim-digit, rate: 30, params: {indentation: 0.0005}}
  - {id: depth, plugin: depth, rate: 30, inputs: {image: digit.image}, isolate: process}
"""
    before = _shm_blocks()
    rt = Runtime(load_text(text, image_reg), log=lambda m: None)
    proxy = rt.component("depth")
    seen: list = []

    def kill_when_shared(node, t, out):
        if node == "depth" and not seen and len(proxy._lanes._peer) == 2:
            seen.append(set(proxy._lanes._peer) & _shm_blocks())   # the child's blocks exist
            proxy._proc.kill()

    rt.add_tap(kill_when_shared)
    res = rt.run(3.0)
    assert res.exit_code == EXIT_FAULT and "isolated process died" in res.message
    assert len(seen[0]) == 2 and not (seen[0] & _shm_blocks()) and _shm_blocks() <= before


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
