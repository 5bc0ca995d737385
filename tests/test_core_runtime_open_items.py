"""Runtime items left open by the last audit: a device whose configure() failed part-way is made safe before it is
closed; start-up configures every node and reports every failure at once; outputs are checked against their
ports; a device sees one safe_state() per fault episode unless the first call failed or it was stepped since."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from teletouch import Component, Device, Kind, Port, Sample, hookimpl
from teletouch.runtime import EXIT_FAULT, EXIT_STARTUP, Runtime
from teletouch.testing import load_text, make_registry

EVENTS: list[tuple[str, str]] = []   # (node, call) in the order the runtime made them


class _HalfDevice(Device):
    """A device that opens its port and enables its torque in configure(), then may raise (a wrong baud rate)."""
    name = "half-device"
    inputs = {"command": Port("float64", (), "m", required=False)}
    outputs = {"y": Port("float64", (), "m")}

    class Params(Component.Params):
        fail: bool = False
        safe_error: bool = False    # safe_state() raises
        safe_hang: bool = False     # safe_state() blocks (until released by the test)
        step_error: bool = False    # step() raises
        interrupt: bool = False     # configure() is cut short by Ctrl-C
        exit_in: str = ""           # "configure" or "activate": that call calls sys.exit() (a plugin's bad habit)

    def configure(self):
        EVENTS.append((self.id, "configure"))
        self.torque = True          # half set up: the hardware is live
        self.safe_calls = 0
        self.release = threading.Event()
        if self.params.interrupt:
            raise KeyboardInterrupt
        if self.params.exit_in == "configure":
            raise SystemExit(f"{self.id}: giving up")
        if self.params.fail:
            raise OSError(f"{self.id}: no answer at 57600 baud")

    def activate(self):
        EVENTS.append((self.id, "activate"))
        if self.params.exit_in == "activate":
            raise SystemExit(3)

    def step(self, t, inputs):
        if self.params.step_error and t >= 0.05:
            raise RuntimeError("step failed")
        return {"y": 0.01}

    def safe_state(self):
        EVENTS.append((self.id, "safe_state"))
        self.safe_calls += 1
        if self.params.safe_hang:
            self.release.wait(10.0)
        if self.params.safe_error:
            raise RuntimeError("torque off refused")
        self.torque = False

    def deactivate(self):
        EVENTS.append((self.id, "deactivate"))

    def close(self):
        EVENTS.append((self.id, "close"))


class _Est(Component):
    """An estimator that may fail to configure (a model file that is missing)."""
    name = "half-est"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        fail: bool = False

    def configure(self):
        EVENTS.append((self.id, "configure"))
        if self.params.fail:
            raise FileNotFoundError(f"{self.id}: model.pt not found")

    def activate(self):
        EVENTS.append((self.id, "activate"))

    def step(self, t, inputs):
        return {"y": 1.0}

    def deactivate(self):
        EVENTS.append((self.id, "deactivate"))

    def close(self):
        EVENTS.append((self.id, "close"))


class _Out(Component):
    """Outputs ``value`` (by name) on a port of the declared dtype and shape, from ``at`` on; ``ok`` before."""
    name = "bad-out"
    kind = Kind.ESTIMATOR
    outputs = {"max_depth": Port("float64", (), "m"), "image": Port("uint8", (None, None, 3), ""),
               "centroid": Port("float64", (2,), "m"), "contact": Port("bool", (), ""),
               "status": Port("str", (), ""), "count": Port("int64", (), ""), "free": Port("any", None, "any")}

    class Params(Component.Params):
        port: str = "max_depth"
        value: str = "str"
        at: float = 0.05

    GOOD = {"max_depth": 0.001, "image": np.zeros((4, 3, 3), np.uint8), "centroid": np.zeros(2), "contact": False,
            "status": "ok", "count": 3, "free": "anything"}
    VALUES = {"str": "0.001", "bool": True, "np-bool": np.bool_(True), "none": None, "list2": [0.0, 0.0],
              "gray": np.zeros((240, 320), np.uint8), "float-image": np.zeros((240, 320, 3)),
              "float32-2": np.zeros(2, np.float32), "vec3": np.zeros(3), "int": 1, "float": 0.5,
              "np-float32": np.float32(0.5), "np-float64": np.float64(0.5), "np-int": np.int64(2), "nan": float("nan"),
              "0d": np.array(0.5), "image": np.zeros((240, 320, 3), np.uint8), "vec2": np.ones(2)}

    def step(self, t, inputs):
        out = dict(self.GOOD)
        if t >= self.params.at:
            out["max_depth"] = t   # the step's other outputs: none is stored when one is refused
            out[self.params.port] = self.VALUES[self.params.value]
        return out


class _Plugins:
    @hookimpl
    def teletouch_components(self):
        return [_HalfDevice, _Est, _Out]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugins())


def _runtime(text: str, reg) -> Runtime:
    return Runtime(load_text(text, reg), log=lambda m: None)


# ------------------------------------------------------------------- 1. a device whose configure() failed part-way
@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_a_device_that_fails_to_configure_is_made_safe_before_it_is_closed(reg, clock):
    EVENTS.clear()
    rt = _runtime(f"clock: {clock}\nnodes:\n  - {{id: g, plugin: half-device, rate: 100, params: {{fail: true}}}}\n",
                  reg)
    res = rt.run(0.2)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert res.message.startswith("node 'g' (half-device) failed to configure: OSError: g: no answer at 57600 baud")
    assert EVENTS == [("g", "configure"), ("g", "safe_state"), ("g", "close")]   # safe_state never came before
    assert rt.component("g").torque is False and rt.component("g").safe_calls == 1
    assert [(f.node, f.kind) for f in res.faults] == [("g", "startup")]


@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_a_safe_state_error_after_a_failed_configure_is_reported_beside_it_never_instead(reg, clock):
    EVENTS.clear()
    rt = _runtime(f"clock: {clock}\nnodes:\n  - {{id: g, plugin: half-device, rate: 100, "
                  f"params: {{fail: true, safe_error: true}}}}\n", reg)
    res = rt.run(0.2)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert res.message.startswith("node 'g' (half-device) failed to configure: OSError")
    assert [(f.node, f.kind) for f in res.faults] == [("g", "startup"), ("g", "shutdown")]
    assert res.faults[1].message.startswith("safe_state() raised RuntimeError: torque off refused")
    assert EVENTS == [("g", "configure"), ("g", "safe_state"), ("g", "close")]   # closed once, not made safe again


def test_a_safe_state_that_hangs_after_a_failed_configure_is_left_behind_and_start_up_ends(reg):
    EVENTS.clear()
    rt = _runtime("clock: wall\nfaults: {safe_timeout: 0.2}\nnodes:\n"
                  "  - {id: g, plugin: half-device, rate: 100, params: {fail: true, safe_hang: true}}\n"
                  "  - {id: e, plugin: half-est, rate: 10}\n", reg)
    try:
        res = rt.run(0.2)
    finally:
        rt.component("g").release.set()
    assert res.status == "startup-failed"
    kinds = [(f.node, f.kind) for f in res.faults]
    assert kinds == [("g", "startup"), ("g", "hung"), ("g", "shutdown")], kinds
    assert res.faults[2].message == "close() skipped: its safe_state() hung"
    assert ("g", "close") not in EVENTS and ("e", "close") in EVENTS and ("e", "configure") in EVENTS


def test_a_device_whose_configure_a_ctrl_c_cut_short_is_made_safe_before_it_is_closed(reg):
    EVENTS.clear()
    rt = _runtime("clock: sim\nnodes:\n  - {id: g, plugin: half-device, rate: 100, params: {interrupt: true}}\n"
                  "  - {id: e, plugin: half-est, rate: 10}\n", reg)
    res = rt.run(0.2)
    assert res.status == "interrupted"
    assert EVENTS == [("g", "configure"), ("g", "safe_state"), ("e", "close"), ("g", "close")]
    assert rt.component("g").torque is False


# ----------------------------------------------------------------- 2. every node configured, every failure at once
@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_start_up_configures_every_node_and_reports_every_failure_in_one_error(reg, clock):
    EVENTS.clear()
    text = f"""
clock: {clock}
nodes:
  - {{id: cam, plugin: half-est, rate: 10, params: {{fail: true}}}}
  - {{id: leader, plugin: half-device, rate: 100}}
  - {{id: est, plugin: half-est, rate: 10}}
  - {{id: gripper, plugin: half-device, rate: 100, params: {{fail: true}}}}
  - {{id: other, plugin: half-device, rate: 100}}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.2)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert res.message == (
        f"node 'cam' (half-est) failed to configure: {_line(res.error.failures[0][2])}; "
        f"node 'gripper' (half-device) failed to configure: {_line(res.error.failures[1][2])} "
        f"(2 nodes failed to configure; none was activated)")
    assert "FileNotFoundError: cam: model.pt not found" in res.message
    assert "OSError: gripper: no answer at 57600 baud" in res.message
    # one fault per failing node, each naming it
    assert [(f.node, f.kind) for f in res.faults] == [("cam", "startup"), ("gripper", "startup")]
    # ONE error; the first failure's exception is its cause
    from teletouch.runtime import StartupError

    err = res.error
    assert isinstance(err, StartupError) and str(err) == res.message
    assert [(n, p) for n, p, _ in err.failures] == [("cam", "half-est"), ("gripper", "half-device")]
    assert isinstance(err.__cause__, FileNotFoundError) and err.__cause__ is err.failures[0][2]
    # every node configured; a failed one made safe (a device) and closed at once; nothing activated; then every
    # configured device safe and all closed in reverse order, each once
    assert EVENTS == [("cam", "configure"), ("cam", "close"),
                      ("leader", "configure"), ("est", "configure"),
                      ("gripper", "configure"), ("gripper", "safe_state"), ("gripper", "close"),
                      ("other", "configure"),
                      ("leader", "safe_state"), ("other", "safe_state"),
                      ("other", "close"), ("est", "close"), ("leader", "close")]


def _line(exc: BaseException) -> str:
    from teletouch.errors import exception_line

    return exception_line(exc)


def test_a_single_start_up_failure_reads_as_before_and_is_the_error(reg):
    res = _runtime("clock: sim\nnodes:\n  - {id: cam, plugin: half-est, rate: 10, params: {fail: true}}\n"
                   "  - {id: d, plugin: half-device, rate: 10}\n", reg).run(0.1)
    assert res.message.startswith("node 'cam' (half-est) failed to configure: FileNotFoundError: cam: model.pt")
    assert "nodes failed" not in res.message
    from teletouch.runtime import StartupError

    assert isinstance(res.error, StartupError) and len(res.error.failures) == 1
    assert res.error.__cause__ is res.error.failures[0][2]


def test_a_run_that_started_has_no_start_up_error(reg):
    res = _runtime("clock: sim\nnodes:\n  - {id: d, plugin: half-device, rate: 10}\n", reg).run(0.1)
    assert res.status == "ok" and res.error is None


# ------------------------------------------------------------------------------ 3. outputs checked against ports
@pytest.mark.parametrize("port, value, says", [
    ("max_depth", "str", "expected float64 scalar, got str"),
    ("max_depth", "bool", "expected float64 scalar, got bool"),
    ("max_depth", "np-bool", "expected float64 scalar, got numpy bool scalar"),
    ("max_depth", "none", "expected float64 scalar, got None"),
    ("max_depth", "vec3", "expected float64 scalar, got float64 array of shape (3,)"),
    ("image", "gray", "expected uint8 array of shape (*, *, 3), got uint8 array of shape (240, 320)"),
    ("image", "float-image", "expected uint8 array of shape (*, *, 3), got float64 array of shape (240, 320, 3)"),
    ("centroid", "list2", "expected float64 array of shape (2,), got list"),
    ("centroid", "vec3", "expected float64 array of shape (2,), got float64 array of shape (3,)"),
    ("centroid", "float32-2", "expected float64 array of shape (2,), got float32 array of shape (2,)"),
    ("contact", "int", "expected bool scalar, got int"),
    ("status", "float", "expected str scalar, got float"),
    ("count", "float", "expected int64 scalar, got float"),
    ("count", "bool", "expected int64 scalar, got bool"),
])
@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_an_output_that_does_not_fit_its_port_is_a_fault_of_its_node_naming_port_expected_and_got(
        reg, clock, port, value, says):
    text = f"""
clock: {clock}
nodes:
  - {{id: depth, plugin: bad-out, rate: 100, params: {{port: {port}, value: {value}}}}}
  - {{id: d, plugin: half-device, rate: 100, inputs: {{command: depth.max_depth}}}}
"""
    rt = _runtime(text, reg)
    res = rt.run(0.3)
    assert res.status == "fault" and res.exit_code == EXIT_FAULT
    assert res.faults[0].node == "depth" and res.faults[0].kind == "exception"
    assert f"node 'depth' exception: ComponentFault: output '{port}': {says}" in res.message, res.message
    # the place to look is the plugin's step(), not the runtime that found it (it said 'runtime.py:432')
    assert (f"got {says.rsplit('got ', 1)[1]} (returned by _Out.step (test_core_runtime_open_items.py:"
            f"{_Out.step.__code__.co_firstlineno}));") in res.message, res.message
    assert res.faults[0].time == pytest.approx(0.05, abs=0.03)
    # none of that step's outputs was stored: max_depth still holds the last good step's value
    assert rt.latest("depth", "max_depth").value == 0.001
    assert rt.component("d").torque is False


@pytest.mark.parametrize("port, value", [
    ("max_depth", "float"), ("max_depth", "int"), ("max_depth", "np-float32"), ("max_depth", "np-float64"),
    ("max_depth", "np-int"), ("max_depth", "nan"), ("max_depth", "0d"), ("image", "image"), ("centroid", "vec2"),
    ("contact", "np-bool"), ("count", "np-int"), ("free", "none"), ("free", "list2"), ("free", "gray"),
])
def test_outputs_that_fit_their_ports_pass_as_they_are(reg, port, value):
    rt = _runtime(f"clock: sim\nnodes:\n  - {{id: depth, plugin: bad-out, rate: 100, "
                  f"params: {{port: {port}, value: {value}}}}}\n", reg)
    res = rt.run(0.2)
    assert res.status == "ok", res.message
    got = rt.latest("depth", port).value
    assert got is _Out.VALUES[value]   # not converted


def test_a_sample_output_is_checked_by_its_value():
    from teletouch.component import value_checker

    check = value_checker(Port("float64", (), "m"))
    assert check(Sample(1.0, 0.0).value) is None and check(Sample("x", 0.0).value) == "str"
    assert value_checker(Port("any", (3,), "any")) is None   # dtype any: nothing is checked
    free = value_checker(Port("float32", None, "m"))
    assert free(np.zeros((2, 3, 4), np.float32)) is None and free(1.5) is None
    assert free(np.zeros(2)) == "float64 array of shape (2,)"


# ---------------------------------------------------------------------- 5. one safe_state() per fault episode
@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_a_device_whose_step_faults_gets_one_safe_state(reg, clock):
    # wall clock: the fault, the rate group leaving its loop and the shutdown each called it (3 calls)
    rt = _runtime(f"clock: {clock}\nnodes:\n  - {{id: g, plugin: half-device, rate: 100, "
                  f"params: {{step_error: true}}}}\n  - {{id: e, plugin: half-est, rate: 100}}\n", reg)
    res = rt.run(0.5)
    assert res.status == "fault" and "node 'g' exception: RuntimeError: step failed" in res.message
    assert rt.component("g").safe_calls == 1 and rt.component("g").torque is False


def test_a_healthy_device_at_the_end_of_a_wall_clock_run_gets_one_safe_state(reg):
    # its rate group made it safe as it left its loop, then the shutdown did again
    rt = _runtime("clock: wall\nnodes:\n  - {id: g, plugin: half-device, rate: 100}\n", reg)
    res = rt.run(0.2)
    assert res.status == "ok" and rt.component("g").safe_calls == 1


@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_safe_state_is_called_again_after_a_failed_call(reg, clock):
    rt = _runtime(f"clock: {clock}\nnodes:\n  - {{id: g, plugin: half-device, rate: 100, "
                  f"params: {{step_error: true, safe_error: true}}}}\n", reg)
    res = rt.run(0.5)
    assert res.status == "fault"
    calls = rt.component("g").safe_calls
    assert calls >= 2, calls   # the fault's call failed: the next stop path tries again
    assert len([f for f in res.faults if f.kind == "shutdown" and "safe_state() raised" in f.message]) == calls


@pytest.mark.parametrize("clock", ["sim", "wall"])
def test_safe_state_is_called_again_for_a_device_stepped_after_it(reg, clock):
    rt = _runtime(f"clock: {clock}\nfaults: {{safe_timeout: 5}}\nnodes:\n"
                  f"  - {{id: g, plugin: half-device, rate: 100}}\n", reg)
    node = rt.nodes[0]
    dev = rt.component("g")
    dev.configure()
    rt._safe(node)
    rt._safe(node)
    assert dev.safe_calls == 1          # still safe: not called again
    node.acts += 1                      # a step began since (a step that hung through the call, then went on)
    rt._safe(node)
    assert dev.safe_calls == 2
    node.in_step = True                 # a step in flight while it is made safe (the watchdog's case)
    node.acts += 1
    rt._safe(node)
    node.in_step = False
    rt._safe(node)                      # that step may have commanded the device after the call: again
    assert dev.safe_calls == 4
    rt._safe(node)
    assert dev.safe_calls == 4


@pytest.mark.parametrize("where", ["configure", "activate"])
def test_a_sys_exit_at_start_up_is_the_nodes_failure_and_every_device_ends_safe(reg, where):
    # before: configure()/activate() caught Exception only, so a plugin's sys.exit() went through run() (after the
    # shutdown) and ended the whole process instead of a start-up failure naming the node
    EVENTS.clear()
    rt = _runtime(f"clock: sim\nnodes:\n  - {{id: a, plugin: half-device, rate: 100}}\n"
                  f"  - {{id: g, plugin: half-device, rate: 100, params: {{exit_in: {where}}}}}\n", reg)
    res = rt.run(0.1)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert res.message.startswith(f"node 'g' (half-device) failed to {where}: SystemExit")
    assert ("g", "safe_state") in EVENTS and ("a", "safe_state") in EVENTS
    assert EVENTS[-2:] == [("g", "close"), ("a", "close")] or (where == "configure" and EVENTS[-1] == ("a", "close"))


def test_a_run_that_faults_at_time_zero_shows_no_achieved_rate(reg):
    # before: 1 step in max(0, 1e-12) s gave an achieved rate of 1e12 Hz, run together with the rate in the table
    # ('1000.01000000000000.0') and in the JSON
    import json

    rt = _runtime("clock: sim\nnodes:\n  - {id: depth, plugin: bad-out, rate: 1000, params: {port: max_depth, "
                  "value: str, at: 0.0}}\n  - {id: d, plugin: half-device, rate: 1000}\n", reg)
    res = rt.run(0.5)
    assert res.status == "fault" and res.sim_time == 0.0
    stats = {n.id: n for n in res.nodes}
    assert stats["depth"].achieved_rate is None and stats["depth"].steps == 1
    row = next(line for line in res.summary().splitlines() if line.startswith("  depth "))
    assert row.split()[2:4] == ["1000.0", "-"], row
    json.dumps(res.as_dict(), allow_nan=False)
