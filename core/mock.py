"""Mock components that ship with the core, for tests of graphs and of third-party plugins.

- ``mock-sensor``: a known signal (constant, step, ramp, sine), optionally failing, turning NaN or going quiet at a
  given time; ``amplitude: 0.5mm`` is converted to SI like any quantity.
- ``mock-gain``: an estimator that multiplies its input by a gain (for wiring and rate tests).
- ``mock-device``: mirrors its command into its state with a first-order lag, like ros2_control's GenericSystem;
  counts calls to ``safe_state`` so tests can check that the runtime drove it there.
- ``mock-burn``: burns CPU in pure Python (holding the GIL) per step, like a heavy estimator.
- ``noop``: does nothing (scheduler benchmarks).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BeforeValidator, Field

from .component import Component, Device, Kind, Params, Port
from .hookspecs import hookimpl
from .units import Seconds, parse_quantity

# a quantity in any unit, converted to SI ("0.5mm" -> 0.0005, "2N" -> 2.0): the mocks' ports have unit "any", so
# they feed an input in m as well as one in N, and a test writes the value as a person reads it
AnySI = Annotated[float, BeforeValidator(lambda v: parse_quantity(v) if isinstance(v, str) else v)]


class MockSensor(Component):
    """A known signal: value(t) for tests."""

    name = "mock-sensor"
    kind = Kind.SENSOR
    outputs = {"value": Port("float64", (), "any", "the signal")}
    default_rate = 100.0

    class Params(Params):
        signal: Literal["constant", "step", "ramp", "sine"] = Field("sine", description="waveform")
        amplitude: AnySI = Field(1.0, description="amplitude in the SI unit of the consumer; a quantity with a unit "
                                 "is converted to SI ('0.5mm' -> 0.0005)")
        offset: AnySI = Field(0.0, description="offset added to the waveform (SI; '20mm' -> 0.02)")
        frequency: float = Field(1.0, gt=0, description="sine frequency", json_schema_extra={"unit": "Hz"})
        step_time: Seconds = Field(0.5, description="time of the step", json_schema_extra={"unit": "s"})
        fail_at: Seconds | None = Field(None, description="raise RuntimeError from this time on",
                                        json_schema_extra={"unit": "s"})
        nan_at: Seconds | None = Field(None, description="output NaN from this time on",
                                       json_schema_extra={"unit": "s"})
        stop_at: Seconds | None = Field(None, description="request a normal stop at this time",
                                        json_schema_extra={"unit": "s"})
        silent_at: Seconds | None = Field(None, description="output nothing from this time on (a source that goes "
                                          "quiet without an error)", json_schema_extra={"unit": "s"})

    def value_at(self, t: float) -> float:
        p = self.params
        if p.signal == "constant":
            v = p.amplitude
        elif p.signal == "step":
            v = p.amplitude if t >= p.step_time else 0.0
        elif p.signal == "ramp":
            v = p.amplitude * t
        else:
            v = p.amplitude * math.sin(2 * math.pi * p.frequency * t)
        return v + p.offset

    def step(self, t, inputs):
        p = self.params
        if p.fail_at is not None and t >= p.fail_at:
            raise RuntimeError(f"mock-sensor failure at t={t:.3f}")
        if p.stop_at is not None and t >= p.stop_at:
            self.ctx.request_stop(f"mock-sensor stop at t={t:.3f}")
        if p.silent_at is not None and t >= p.silent_at:
            return {}
        if p.nan_at is not None and t >= p.nan_at:
            return {"value": math.nan}
        return {"value": self.value_at(t)}


class MockGain(Component):
    """y = gain * x."""

    name = "mock-gain"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "any", "input")}
    outputs = {"y": Port("float64", (), "any", "gain * x")}
    default_rate = 100.0

    class Params(Params):
        gain: float = Field(1.0, description="gain")

    def step(self, t, inputs):
        s = inputs["x"]
        if s is None:
            return None
        return {"y": self.params.gain * s.value}


class MockDevice(Device):
    """Mirrors command into state with a first-order lag (time constant tau; 0 = instant)."""

    name = "mock-device"
    inputs = {"command": Port("float64", (), "any", "commanded value", required=False)}
    outputs = {"state": Port("float64", (), "any", "measured value"),
               "command_applied": Port("float64", (), "any", "the command as applied (after safe state)")}
    default_rate = 1000.0

    class Params(Params):
        tau: Seconds = Field(0.0, ge=0, description="first-order lag time constant", json_schema_extra={"unit": "s"})
        initial: float = Field(0.0, description="initial state")
        safe_value: float | None = Field(None, description="command applied in the safe state (None: hold state)")
        fail_at: Seconds | None = Field(None, description="raise from this time on", json_schema_extra={"unit": "s"})

    def configure(self):
        self.state = self.params.initial
        self.command = self.state
        self.safe = False
        self.safe_calls = 0
        self.safe_at: float | None = None     # time.perf_counter() of the first safe_state() call
        self.last_t = None
        self.lifecycle: list[str] = ["configure"]

    def activate(self):
        self.safe = False
        self.lifecycle.append("activate")

    def step(self, t, inputs):
        p = self.params
        if p.fail_at is not None and t >= p.fail_at:
            raise RuntimeError(f"mock-device failure at t={t:.3f}")
        cmd = inputs.value("command")
        if cmd is not None and not self.safe:
            self.command = float(cmd)
        dt = 0.0 if self.last_t is None else t - self.last_t
        self.last_t = t
        if p.tau <= 0:
            self.state = self.command
        else:
            self.state += (self.command - self.state) * (1.0 - math.exp(-dt / p.tau))
        return {"state": self.state, "command_applied": self.command}

    def safe_state(self):
        import time

        self.safe_calls += 1
        if self.safe_at is None:
            self.safe_at = time.perf_counter()
        self.safe = True
        self.command = self.params.safe_value if self.params.safe_value is not None else self.state

    def deactivate(self):
        self.lifecycle.append("deactivate")

    def close(self):
        if hasattr(self, "lifecycle"):
            self.lifecycle.append("close")


class MockBurn(Component):
    """Burns CPU in pure Python (holding the GIL) each step, like a heavy estimator; echoes its input."""

    name = "mock-burn"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "any", "passed through", required=False)}
    outputs = {"y": Port("float64", (), "any", "the input (0 before any)"),
               "pid": Port("int64", (), "", "process id that ran the step")}
    default_rate = 60.0

    class Params(Params):
        burn: Seconds = Field(0.008, ge=0, description="CPU time to burn per step", json_schema_extra={"unit": "s"})
        fail_at: Seconds | None = Field(None, description="raise from this time on", json_schema_extra={"unit": "s"})
        stop_at: Seconds | None = Field(None, description="request a normal stop at this time",
                                        json_schema_extra={"unit": "s"})
        hang_at: Seconds | None = Field(None, description="once, at this time, sleep hang_for inside the step (a "
                                        "step that hangs)", json_schema_extra={"unit": "s"})
        hang_for: Seconds = Field(1.5, ge=0, description="how long the hang lasts", json_schema_extra={"unit": "s"})
        deactivate_error: bool = Field(False, description="deactivate() raises (to test how shutdown reports it)")

    def deactivate(self):
        if self.params.deactivate_error:
            raise RuntimeError("mock-burn deactivate failure")

    def step(self, t, inputs):
        import os
        import time

        p = self.params
        if p.fail_at is not None and t >= p.fail_at:
            raise ValueError(f"mock-burn failure at t={t:.3f}")
        if p.hang_at is not None and t >= p.hang_at and not getattr(self, "_hung", False):
            self._hung = True
            time.sleep(p.hang_for)
        if p.stop_at is not None and t >= p.stop_at:
            self.ctx.request_stop(f"mock-burn stop at t={t:.3f}")
        end = time.perf_counter() + p.burn
        n = 0
        while time.perf_counter() < end:
            n += sum(range(200))
        return {"y": inputs.value("x", 0.0), "pid": os.getpid()}


class Noop(Component):
    """Does nothing (scheduler benchmarks)."""

    name = "noop"
    kind = Kind.ESTIMATOR
    default_rate = 1000.0

    def step(self, t, inputs):
        return None


@hookimpl
def teletouch_components():
    return [MockSensor, MockGain, MockDevice, MockBurn, Noop]
