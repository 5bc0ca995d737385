"""What the four follower grippers share: ports, limits, command shaping, velocity estimate and the safe state.

A follower driver subclasses :class:`FollowerBase` and implements four hardware hooks::

    _hw_open()                 connect, check the hardware answers as expected (raise HardwareError otherwise)
    _hw_read() -> Reading      measured opening (m), velocity (m/s or None), effort (N or NaN), measurement time
    _hw_write(opening)         send one opening setpoint (m), already clamped and rate limited
    _hw_close()                release everything (must not raise)

Everything else (limits, NaN commands, the speed limit, safe state, velocity by finite differences where the hardware
does not report it, watchdog on reads) lives here once.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import Field, model_validator

from teletouch import Device, HardwareError, Kind, Params, Port, Sample
from teletouch.units import Meters, MetersPerSecond, Newtons, Seconds

__all__ = ["FollowerParams", "FollowerBase", "Reading", "OpeningMap", "FOLLOWER_INPUTS", "FOLLOWER_OUTPUTS",
           "clamp", "shape_setpoint"]

FOLLOWER_INPUTS = {
    "opening_command": Port("float64", (), "m", "desired distance between the fingers", required=True),
}
FOLLOWER_OUTPUTS = {
    "opening": Port("float64", (), "m", "measured distance between the fingers"),
    "velocity": Port("float64", (), "m/s", "d(opening)/dt, positive opening"),
    "effort": Port("float64", (), "N", "grip force where the hardware reports it, NaN where it does not"),
}


def clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def shape_setpoint(previous: float, command: float, lo: float, hi: float, max_speed: float, dt: float) -> float:
    """Clamp ``command`` to [lo, hi] and move from ``previous`` towards it by at most ``max_speed * dt``."""
    target = clamp(command, lo, hi)
    if not math.isfinite(previous):
        return target
    step = max_speed * max(dt, 0.0)  # no time elapsed (first step): no motion
    return clamp(target, previous - step, previous + step)


@dataclass(frozen=True)
class OpeningMap:
    """Linear map between the actuator's position counts and the opening: two calibration points."""

    counts_open: float
    opening_open: float
    counts_closed: float
    opening_closed: float

    def __post_init__(self) -> None:
        if self.counts_open == self.counts_closed or self.opening_open == self.opening_closed:
            raise ValueError("the open and closed calibration points must differ in counts and in opening")

    @property
    def scale(self) -> float:
        """Metres of opening per count (negative when the counts grow while closing)."""
        return (self.opening_closed - self.opening_open) / (self.counts_closed - self.counts_open)

    def counts(self, opening: float) -> int:
        return int(round(self.counts_open + (opening - self.opening_open) / self.scale))

    def opening(self, counts: float) -> float:
        return self.opening_open + (counts - self.counts_open) * self.scale


class FollowerParams(Params):
    """Limits and safe state common to every follower (each driver overrides the defaults with its hardware's)."""

    min_opening: Meters = Field(0.0, ge=0, description="smallest opening commanded", json_schema_extra={"unit": "m"})
    max_opening: Meters = Field(0.09, gt=0, description="largest opening commanded", json_schema_extra={"unit": "m"})
    max_speed: MetersPerSecond = Field(0.05, gt=0, description="opening speed limit of the setpoint",
                                       json_schema_extra={"unit": "m/s"})
    max_effort: Newtons = Field(16.0, gt=0, description="grip force limit", json_schema_extra={"unit": "N"})
    safe_mode: Literal["hold", "open"] = Field("hold", description="safe state: hold the current opening, or open "
                                                                   "to max_opening")
    read_timeout: Seconds = Field(0.5, gt=0, description="fault when no valid state arrives for this long",
                                  json_schema_extra={"unit": "s"})

    @model_validator(mode="after")
    def _range(self) -> "FollowerParams":
        if self.min_opening >= self.max_opening:
            raise ValueError(f"min_opening ({self.min_opening} m) must be below max_opening ({self.max_opening} m)")
        return self


@dataclass
class Reading:
    opening: float
    velocity: float | None = None
    effort: float = math.nan
    mono: float | None = None  # time.monotonic() of the measurement (None: now)


class FollowerBase(Device):
    """Base of the follower drivers (not registered itself)."""

    kind = Kind.DEVICE
    default_rate = 200.0
    inputs = dict(FOLLOWER_INPUTS)
    outputs = dict(FOLLOWER_OUTPUTS)
    Params = FollowerParams

    # hardware hooks --------------------------------------------------------------------------------------------
    def _hw_open(self) -> None:
        raise NotImplementedError

    def _hw_read(self) -> Reading | None:
        raise NotImplementedError

    def _hw_write(self, opening: float) -> None:
        raise NotImplementedError

    def _hw_close(self) -> None:
        pass

    # lifecycle -------------------------------------------------------------------------------------------------
    def configure(self) -> None:
        self._safe = False
        self._setpoint = math.nan
        self._last_t: float | None = None
        self._last_reading: Reading | None = None
        self._last_good = time.monotonic()
        self._prev: tuple[float, float] | None = None  # (graph time, opening) for finite differences
        self._bad_commands = 0
        self._ready = False
        self._opened = True  # close() releases whatever _hw_open() got before it failed
        self._hw_open()
        first = self._hw_read()
        if first is None or not math.isfinite(first.opening):
            raise HardwareError(f"{self.name}: no valid state from the gripper after connecting; check power, "
                                f"cabling and configuration")
        self._last_reading = first
        self._setpoint = clamp(first.opening, self.params.min_opening, self.params.max_opening)
        self._ready = True

    def activate(self) -> None:
        self._safe = False
        self._last_good = time.monotonic()
        self._last_t = None

    def close(self) -> None:
        if getattr(self, "_opened", False):
            self._opened = False
            self._hw_close()

    # step ------------------------------------------------------------------------------------------------------
    def command_target(self, t: float, inputs: Any) -> float:
        """The setpoint for this step: the command (clamped, rate limited) or the safe target."""
        p = self.params
        dt = 0.0 if self._last_t is None else t - self._last_t
        self._last_t = t
        if self._safe:
            return self._setpoint
        cmd = inputs.value("opening_command")
        if cmd is None:
            return self._setpoint
        cmd = float(cmd)
        if not math.isfinite(cmd):
            self._bad_commands += 1
            if self._bad_commands == 1:
                self.ctx.log(f"non-finite opening_command ({cmd}); holding {self._setpoint * 1e3:.2f} mm")
            return self._setpoint
        self._setpoint = shape_setpoint(self._setpoint, cmd, p.min_opening, p.max_opening, p.max_speed, dt)
        return self._setpoint

    def read_state(self, t: float) -> Reading:
        r = self._hw_read()
        now = time.monotonic()
        if r is None or not math.isfinite(r.opening):
            if now - self._last_good > self.params.read_timeout:
                raise HardwareError(f"{self.name}: no valid state for {now - self._last_good:.3f} s "
                                    f"(read_timeout {self.params.read_timeout} s); check the connection")
            return self._last_reading  # type: ignore[return-value]
        self._last_good = now
        self._last_reading = r
        return r

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        r = self.read_state(t)
        self._hw_write(self.command_target(t, inputs))
        return self.outputs_from(r, t)

    def outputs_from(self, r: Reading, t: float) -> dict[str, Any]:
        stamp = t if r.mono is None or self.ctx.clock_kind == "sim" else self.ctx.from_monotonic(r.mono)
        vel = r.velocity
        if vel is None:
            if self._prev is not None and stamp > self._prev[0]:
                vel = (r.opening - self._prev[1]) / (stamp - self._prev[0])
            else:
                vel = 0.0 if self._prev is None else self._prev_vel
        if self._prev is None or stamp > self._prev[0]:
            self._prev = (stamp, r.opening)
            self._prev_vel = vel
        return {"opening": Sample(float(r.opening), stamp), "velocity": Sample(float(vel), stamp),
                "effort": Sample(float(r.effort), stamp)}

    # safe state ------------------------------------------------------------------------------------------------
    def safe_target(self) -> float:
        p = self.params
        if p.safe_mode == "open":
            return p.max_opening
        r = self._last_reading
        if r is not None and math.isfinite(r.opening):
            return clamp(r.opening, p.min_opening, p.max_opening)
        return self._setpoint

    def safe_state(self) -> None:
        if not getattr(self, "_ready", False):
            return
        try:
            self._safe = True
            self._setpoint = self.safe_target()
            self._hw_write(self._setpoint)
        except Exception as exc:  # never raise from the safe state; the hardware's own limits take over
            try:
                self.ctx.log(f"safe_state could not command the gripper: {exc}")
            except Exception:
                pass

    def status(self) -> dict[str, Any]:
        r = getattr(self, "_last_reading", None)
        return {"opening": None if r is None else r.opening, "setpoint": getattr(self, "_setpoint", None),
                "effort": None if r is None else r.effort, "safe": getattr(self, "_safe", False)}
