"""What a plugin author needs from teletouch.testing and the mocks: the Harness refuses what the runtime refuses,
drives a device to its safe state, steps on a simulated clock and feeds stale or missing inputs; make_registry says
why a plugin did not load; run_yaml records every device's safe states."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
from pydantic import Field

from teletouch import Component, Device, Kind, Params, Port, Sample, hookimpl
from teletouch.errors import ComponentFault, PluginError
from teletouch.mock import MockSensor
from teletouch import testing
from teletouch.testing import Harness, make_registry, run_yaml


class LinearForce(Component):
    """force = stiffness * max_depth."""

    name = "acme-linear-force"
    kind = Kind.ESTIMATOR
    default_rate = 60.0
    inputs = {"max_depth": Port("float64", (), "m", "max depth")}
    outputs = {"force": Port("float64", (), "N", "force")}

    class Params(Params):
        stiffness: float = Field(2000.0, gt=0, description="spring constant", json_schema_extra={"unit": "N/m"})
        as_array: bool = Field(False, description="return a float32 array (the newcomer's mistake)")

    def step(self, t, inputs):
        s = inputs["max_depth"]
        if s is None:
            return {}
        f = self.params.stiffness * s.value
        return {"force": np.array([f], dtype=np.float32) if self.params.as_array else f}


class Gripper(Device):
    """Tracks opening_command; holds its opening in the safe state."""

    name = "acme-gripper"
    default_rate = 1000.0
    inputs = {"opening_command": Port("float64", (), "m", "command")}
    outputs = {"opening": Port("float64", (), "m", "opening")}

    class Params(Params):
        fail_at: float | None = Field(None, description="raise from this time on", json_schema_extra={"unit": "s"})

    def configure(self):
        self.opening = 0.02
        self.safe = False

    def step(self, t, inputs):
        if self.params.fail_at is not None and t >= self.params.fail_at:
            raise OSError("gripper unplugged")
        cmd = inputs.value("opening_command")
        if cmd is not None and not self.safe:
            self.opening = cmd
        return {"opening": self.opening}

    def safe_state(self):
        self.safe = True


def _module(name, *classes, decorate=True):
    mod = types.ModuleType(name)

    def teletouch_components():
        return list(classes)

    mod.teletouch_components = hookimpl(teletouch_components) if decorate else teletouch_components
    return mod


# --- the Harness refuses a class the registry would refuse -----------------------------------------------------

def test_harness_refuses_a_device_without_safe_state():
    class NoSafe(Device):
        name = "acme-nosafe"
        outputs = {"opening": Port("float64", (), "m")}

        def step(self, t, inputs):
            return {"opening": 0.0}

    with pytest.raises(PluginError, match=r"device .*NoSafe must define safe_state\(\)"):
        Harness(NoSafe)


def test_harness_refuses_a_port_in_millimetres():
    class InMm(Component):
        name = "acme-in-mm"
        inputs = {"max_depth": Port("float64", (), "mm")}

        def step(self, t, inputs):
            return None

    with pytest.raises(PluginError, match=r"InMm.inputs\['max_depth'\] unit 'mm' is not SI: declare 'm'"):
        Harness(InMm)


# --- outputs are checked as the runtime checks them ------------------------------------------------------------

def test_harness_output_of_the_wrong_dtype_raises_the_runtimes_message():
    expected = "output 'force': expected float64 scalar, got float32 array of shape (1,)"
    with Harness(LinearForce, {"as_array": True}) as h:
        with pytest.raises(ComponentFault) as exc:
            h.step(0.0, max_depth=0.001)
    assert str(exc.value) == expected
    graph = """
clock: sim
nodes:
  - {id: depth, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 0.001}}
  - {id: force, plugin: acme-linear-force, rate: 100, params: {as_array: true}, inputs: {max_depth: depth.value}}
"""
    result, _ = run_yaml(graph, make_registry(_module("acme_a", LinearForce)), duration=0.1)
    assert result.status == "fault" and expected in result.message   # the same words in a graph


def test_harness_refuses_an_unknown_output_and_a_non_mapping():
    class Sloppy(Component):
        name = "acme-sloppy"
        outputs = {"force": Port("float64", (), "N")}

        def step(self, t, inputs):
            return {"froce": 1.0} if t < 1 else 1.0

    with Harness(Sloppy) as h:
        with pytest.raises(ComponentFault, match=r"unknown output 'froce'; outputs: force"):
            h.step(0.0)
        with pytest.raises(ComponentFault, match=r"step\(\) returned float 1.0; expected a mapping"):
            h.step(1.0)


def test_harness_refuses_a_nan_stamp_and_keeps_a_given_stamp():
    class Stamped(Component):
        name = "acme-stamped"
        outputs = {"force": Port("float64", (), "N")}

        def step(self, t, inputs):
            return {"force": Sample(1.0, t - 0.01 if t < 1 else math.nan)}

    with Harness(Stamped) as h:
        assert h.step(0.5) == {"force": 1.0}
        assert h.samples["force"].stamp == pytest.approx(0.49)
        with pytest.raises(ComponentFault, match=r"stamped nan: a stamp must be a finite graph time"):
            h.step(1.0)


# --- inputs: missing, stale, misspelt -----------------------------------------------------------------------------

def test_harness_none_empties_an_input():
    seen = []

    class Reader(Component):
        name = "acme-reader"
        inputs = {"x": Port("float64", (), "N")}

        def step(self, t, inputs):
            seen.append(inputs["x"])
            return None

    with Harness(Reader) as h:
        h.step(0.0, x=1.0)
        h.step(0.1, x=None)       # nothing received: the runtime's slot holds None, not Sample(None)
    assert seen[0].value == 1.0 and seen[1] is None


def test_harness_stale_sample_keeps_its_stamp():
    with Harness(LinearForce) as h:
        h.step(1.0, max_depth=Sample(0.001, 0.5))
        assert h.inputs.age("max_depth", h.t) == pytest.approx(0.5)
        assert h.inputs.fresh("max_depth", h.t, 0.1) is None


def test_harness_misspelt_input_names_the_inputs():
    with Harness(LinearForce) as h:
        with pytest.raises(KeyError, match=r"has no input 'max_dpeth' \(did you mean 'max_depth'\?\); inputs: "
                                           r"max_depth"):
            h.step(0.0, max_dpeth=0.001)


# --- devices: safe state ----------------------------------------------------------------------------------------

def test_harness_makes_a_device_safe_at_the_end_and_counts_the_calls():
    with Harness(Gripper) as h:
        assert h.step(0.0, opening_command=0.01) == {"opening": 0.01}
        h.safe_state()
        assert h.safe_calls == 1
        assert h.step(0.001, opening_command=0.005) == {"opening": 0.01}   # holds in the safe state
    assert h.safe_calls == 2 and h.comp.safe


def test_harness_makes_a_device_safe_when_its_step_raises():
    with pytest.raises(OSError, match="gripper unplugged"):
        with Harness(Gripper, {"fail_at": 0.5}) as h:
            h.step(0.0, opening_command=0.01)
            h.step(0.5)
    assert h.safe_calls == 1 and h.comp.safe


def test_harness_safe_state_of_a_non_device_is_an_error():
    with Harness(LinearForce) as h:
        with pytest.raises(TypeError, match="not a device"):
            h.safe_state()


# --- a simulated clock ------------------------------------------------------------------------------------------

def test_harness_run_steps_at_the_rate_on_exact_ticks():
    with Harness(LinearForce, {"stiffness": "3 N/mm"}, rate=100.0) as h:
        assert h.ctx.rate == 100.0
        out = h.run(0.05, max_depth=lambda t: 0.001 * t)
        assert [t for t, _ in out] == [0.0, 0.01, 0.02, 0.03, 0.04, 0.05]
        assert out[-1][1]["force"] == pytest.approx(3000.0 * 0.001 * 0.05)
        more = h.run(0.07, max_depth=0.0)   # goes on from the next tick
        assert [t for t, _ in more] == [0.06, 0.07]


def test_harness_run_without_a_rate_says_how_to_give_one():
    class NoRate(Component):
        name = "acme-norate"

        def step(self, t, inputs):
            return None

    with Harness(NoRate) as h:
        with pytest.raises(ValueError, match=r"no default_rate: give Harness\(\.\.\., rate=HZ\)"):
            h.run(1.0)


# --- make_registry says why a plugin did not load ----------------------------------------------------------------

def test_make_registry_reports_a_forgotten_hookimpl():
    with pytest.raises(PluginError, match=r"plugin 'acme_nohook' failed to load: function 'teletouch_components' "
                                          r"is not decorated with @teletouch.hookimpl"):
        make_registry(_module("acme_nohook", LinearForce, decorate=False))


def test_make_registry_reports_a_rule_breaking_component_and_a_module_without_hooks():
    class Bad(Component):
        name = "acme-bad"
        outputs = {"force": Port("float64", (), "N")}

        class Params(Params):
            stiffness: float = Field(2.0, json_schema_extra={"unit": "N/mm"})

        def step(self, t, inputs):
            return None

    with pytest.raises(PluginError, match=r"acme_bad' failed to load: .*Bad.Params.stiffness unit 'N/mm' is not SI"):
        make_registry(_module("acme_bad", Bad))
    with pytest.raises(PluginError, match=r"plugin 'acme_empty' implements no teletouch hook"):
        make_registry(types.ModuleType("acme_empty"))


def test_make_registry_holds_a_good_plugin():
    reg = make_registry(_module("acme_good", LinearForce, Gripper))
    assert {"acme-linear-force", "acme-gripper", "mock-sensor"} <= set(reg.components)


# --- a graph test: safe states with their graph times ------------------------------------------------------------

GRAPH = """
clock: sim
nodes:
  - {id: cmd, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 10mm}}
  - {id: gripper, plugin: acme-gripper, rate: 1000, params: {fail_at: %s}, inputs: {opening_command: cmd.value}}
  - {id: other, plugin: mock-device, rate: 1000}
"""


def test_safe_states_lists_the_graph_time_of_every_call():
    result, rt = run_yaml(GRAPH % "0.25", make_registry(_module("acme_g", Gripper)), duration=1.0)
    assert result.status == "fault" and "gripper unplugged" in result.message
    calls = testing.safe_states(rt)
    assert set(calls) == {"gripper", "other"}           # devices only
    assert calls["gripper"] == [pytest.approx(0.25)]    # once, at the fault
    assert len(calls["other"]) == 1
    assert rt.component("gripper").safe


def test_safe_states_at_the_normal_end():
    result, rt = run_yaml(GRAPH % "null", make_registry(_module("acme_g2", Gripper)), duration=0.5)
    assert result.status == "ok"
    assert testing.safe_states(rt)["gripper"] == [pytest.approx(0.5)]
    with pytest.raises(ValueError, match="only the runtimes that run_yaml"):
        testing.safe_states(object())


# --- mock-sensor takes quantities --------------------------------------------------------------------------------

def test_mock_sensor_amplitude_with_a_unit_is_si():
    p = MockSensor.Params(signal="constant", amplitude="0.5mm", offset="20mm")
    assert p.amplitude == pytest.approx(0.0005) and p.offset == pytest.approx(0.02)
    with pytest.raises(ValueError, match="unknown unit 'furlongs'"):
        MockSensor.Params(amplitude="5 furlongs")


@pytest.mark.parametrize("fail_in", ["configure", "activate"])
def test_harness_makes_safe_and_closes_a_device_whose_start_failed(fail_in):
    # before: an exception in configure()/activate() left the component open (the with body and __exit__ never
    # run), so a driver holding a port or a one-per-process registration broke the tests after it
    calls = []

    class Half(Device):
        name = "half-started"
        outputs = {"y": Port("float64", (), "m")}

        def configure(self):
            calls.append("configure")
            if fail_in == "configure":
                raise OSError("no answer")

        def activate(self):
            calls.append("activate")
            if fail_in == "activate":
                raise OSError("no answer")

        def step(self, t, inputs):
            return {"y": 0.0}

        def safe_state(self):
            calls.append("safe_state")

        def close(self):
            calls.append("close")

    with pytest.raises(OSError, match="no answer"):
        with Harness(Half):
            pass
    assert calls[-2:] == ["safe_state", "close"]
