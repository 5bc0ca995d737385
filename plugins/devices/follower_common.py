"""What the four follower grippers share: ports, limits, command shaping, velocity estimate and the safe state.

A follower driver subclasses :class:`FollowerBase` and implements four hardware hooks::

    _hw_open()                 connect, check the hardware answers as expected (raise HardwareError otherwise)
    _hw_read() -> Reading      measured opening (m), velocity (m/s or None), effort (N or NaN), measurement time
    _hw_write(opening)         send one opening setpoint (m), already clamped and rate limited
    _hw_close()                release everything (must not raise)

Everything else (limits, NaN and stale commands, the speed limit, safe state, velocity by finite differences where the
hardware does not report it, watchdog on reads) lives here once.

Holding: whenever there is no usable command (none yet, stale, NaN) and in the ``hold`` safe state, the setpoint goes
to the measured opening (taken once, when the hold starts). The setpoint itself starts at the measured opening, at
configure and at every activate (when activate cannot read the state: at the first reading after it, and nothing is
sent before), and only ever moves at ``max_speed`` (over at most two nominal periods per step), so a gripper resting
outside [min_opening, max_opening] is walked into the range rather than jumped there.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import time
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from teletouch import Device, HardwareError, Kind, Params, Port, Sample
from teletouch.errors import value_text
from teletouch.units import (
    MAX_PLAUSIBLE_OPENING, Meters, MetersPerSecond, Newtons, Seconds, plausible_opening, plausible_quantity,
    plausible_speed,
)

__all__ = ["FollowerParams", "FollowerBase", "Reading", "OpeningMap", "FOLLOWER_INPUTS", "FOLLOWER_OUTPUTS",
           "clamp", "command_value", "shape_setpoint", "MAX_PLAUSIBLE_GRIP_FORCE", "plausible_grip_force"]

#: no parallel gripper of the followers' class squeezes harder than this (the PAL gripper: 16 N, an XM430 servo: a
#: few N, a ROBOTIS RH-P12-RN: 170 N, the strongest electric parallel grippers: a few hundred N): a larger grip force
#: limit in the newton field is millinewtons typed there (``max_effort: 16000`` was taken as 16 kN)
MAX_PLAUSIBLE_GRIP_FORCE = 1000.0   # N

def plausible_grip_force(name: str, value: float, limit: float = MAX_PLAUSIBLE_GRIP_FORCE) -> float:
    """``value`` if it is a plausible grip force limit (N) of a parallel gripper, else a ValueError: mN in the N
    field."""
    return plausible_quantity(name, value, limit, "N", "beyond what a parallel gripper squeezes",
                              "; the PAL gripper: 16 N")


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


def command_value(value: Any) -> float | None:
    """``value`` as an opening command (m): a real number (not a bool, a string or a sequence), finite and at most
    :data:`MAX_PLAUSIBLE_OPENING` either way; None for anything else (``float()`` took ``True`` as 1 m, ``"0.03"``
    as 30 mm and 1e30 m as a full opening)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        dtype = getattr(value, "dtype", None)  # a numpy scalar or 0-d array of a numeric type
        if dtype is None or getattr(dtype, "kind", "") not in "fiu" or getattr(value, "shape", None) != ():
            return None
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        return None
    return v if math.isfinite(v) and abs(v) <= MAX_PLAUSIBLE_OPENING else None


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

    def check_limits(self, params: "FollowerParams", open_field: str, closed_field: str) -> None:
        """Refuse ``min_opening``/``max_opening`` outside the two calibration points: a command there would be
        extrapolated past the points to counts the fingers may not reach (driving into the mechanical end). A
        calibration opening beyond any gripper's (millimetres typed in the metre field) is refused, naming the field:
        ``75`` was taken as 75 m and the limits lay within it."""
        for field, value in ((open_field, self.opening_open), (closed_field, self.opening_closed)):
            plausible_opening(field, value)
        lo, hi = sorted((self.opening_open, self.opening_closed))
        for name, value in (("min_opening", params.min_opening), ("max_opening", params.max_opening)):
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise ValueError(
                    f"{name} ({value * 1e3:g} mm) is outside the calibrated range {lo * 1e3:g}-{hi * 1e3:g} mm "
                    f"({open_field}, {closed_field}); commands there would be extrapolated past the calibration "
                    f"points: set {name} within the range or recalibrate")

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
    command_timeout: Seconds = Field(0.2, gt=0, le=2.0, description="an opening_command older than this (or stamped "
                                     "more than this ahead, or with a NaN stamp) is stale: the gripper holds its "
                                     "measured opening", json_schema_extra={"unit": "s"})

    @field_validator("max_speed")
    @classmethod
    def _speed(cls, v: float, info: Any) -> float:
        return plausible_speed(info.field_name, v)   # 100 meant 100 mm/s: no gripper closes at 100 m/s

    @field_validator("max_effort")
    @classmethod
    def _effort(cls, v: float, info: Any) -> float:
        return plausible_grip_force(info.field_name, v)   # 16000 meant 16000 mN: no such gripper squeezes 16 kN

    @model_validator(mode="after")
    def _range(self) -> "FollowerParams":
        for name in ("min_opening", "max_opening"):
            plausible_opening(name, getattr(self, name))
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
    #: while the reads fail, hold the last set-point sent rather than the stale reading (see _measured)
    hold_setpoint_while_stale = True
    _read_failed = False   # the last step's read gave no state (set by configure, activate and each step's read)
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
        self._read_failed = False
        self._last_t: float | None = None
        self._last_reading: Reading | None = None
        self._last_good = time.monotonic()
        self._prev: tuple[float, float] | None = None  # (graph time, opening) for finite differences
        self._bad_commands = 0
        self._stale_commands = 0
        self._command_stamp = -math.inf  # stamp of the newest command used: an older one is out of order
        self._holding: str | None = None  # why the setpoint holds (None: following the command)
        self._resync = False  # take the setpoint from the next reading (activate() could not read the state)
        self._hold_at = math.nan  # the measured opening the setpoint holds (walked into the range at max_speed)
        rate = getattr(self.ctx, "rate", None) or self.default_rate
        self._max_dt = 2.0 / float(rate)  # longest step the speed limit counts: a late step does not jump
        self._ready = False
        self._opened = True  # close() releases whatever _hw_open() got before it failed
        self._hw_open()
        first = self._hw_read()
        if first is None or not math.isfinite(first.opening):
            raise HardwareError(f"{self.name}: no valid state from the gripper after connecting; check power, "
                                f"cabling and configuration")
        self._last_reading = first
        self._setpoint = first.opening  # not clamped: the speed limit walks it into the range (no jump)
        self._ready = True

    def activate(self) -> None:
        """Start from where the gripper is now: it may have been moved while the node was inactive."""
        self._safe = False
        self._last_t = None
        self._holding = None
        self._prev = None
        self._command_stamp = -math.inf  # the graph's clock may start afresh
        self._read_failed = False
        r = self._hw_read()
        self._last_good = time.monotonic()
        if r is not None and math.isfinite(r.opening):
            self._last_reading = r
            self._setpoint = r.opening
            self._resync = False
        else:  # no state right now: the first step with a reading takes the setpoint from it
            # the reading and the set-point of before are not where the fingers are now (moved while inactive):
            # nothing is sent, held or reported from them (see command_target and safe_state)
            self._last_reading = None
            self._setpoint = math.nan
            self._resync = True

    def close(self) -> None:
        if getattr(self, "_opened", False):
            self._opened = False
            self._hw_close()

    # step ------------------------------------------------------------------------------------------------------
    def _measured(self) -> float:
        """The last measured opening; NaN when there is none since activate() (and no set-point either). While the
        reads fail (``read_timeout`` not yet passed), the last set-point sent instead: the set-points, which need no
        answer, may still reach the hardware, which has taken the fingers towards them since the last reading; a hold
        of that stale reading moved them back, by up to read_timeout x max_speed (``hold_setpoint_while_stale``
        False: the last reading all the same; pal-gripper has its own rule, see its safe_target)."""
        r = self._last_reading
        if self.hold_setpoint_while_stale and self._read_failed and math.isfinite(self._setpoint):
            return self._setpoint
        return r.opening if r is not None and math.isfinite(r.opening) else self._setpoint

    def _start_hold(self, why: str) -> bool:
        """Hold the measured opening (taken when the hold starts) until a usable command arrives again; whether
        ``why`` is a new reason to hold."""
        if self._holding is None:
            self._hold_at = self._measured()
        new = self._holding != why
        self._holding = why
        return new

    def command_target(self, t: float, inputs: Any) -> float:
        """The setpoint for this step: the command (clamped, rate limited) or the hold / safe target; NaN (nothing to
        send) while no state has been read since activate()."""
        p = self.params
        # the speed limit counts at most two nominal periods: after a late step the setpoint does not jump
        dt = 0.0 if self._last_t is None else min(t - self._last_t, self._max_dt)
        self._last_t = t
        if self._resync or not math.isfinite(self._setpoint):
            self._setpoint = self._measured()
            if not math.isfinite(self._setpoint):   # where the fingers are is not known yet: nothing to start from
                return self._setpoint
            self._resync = False
        if self._safe:
            target = self._hold_at
        else:
            target = self._command(t, inputs)
            if target is None:
                target = self._hold_at
            else:
                self._holding = None
        if math.isfinite(target):
            self._setpoint = shape_setpoint(self._setpoint, target, p.min_opening, p.max_opening, p.max_speed, dt)
        return self._setpoint

    def _command(self, t: float, inputs: Any) -> float | None:
        """The opening command if it is usable now (fresh and finite); None after starting a hold otherwise."""
        p = self.params
        s = inputs.get("opening_command")
        if s is None:
            self._start_hold("no command yet")
            return None
        if not s.is_fresh(t, p.command_timeout):
            self._stale_commands += 1
            if self._start_hold("stale command"):
                self.ctx.log(f"opening_command stamped {s.stamp} at t={t} (command_timeout {p.command_timeout} s) "
                             f"is stale; holding the measured opening {self._hold_at * 1e3:.2f} mm")
            return None
        cmd = command_value(s.value)
        if cmd is None:
            self._bad_commands += 1
            self._start_hold("bad command")
            if self._bad_commands == 1:
                self.ctx.log(f"opening_command {value_text(s.value)} is not an opening (expected a finite number of "
                             f"metres, at most {MAX_PLAUSIBLE_OPENING:g} m either way); holding the measured opening "
                             f"{self._hold_at * 1e3:.2f} mm")
            return None
        if s.stamp < self._command_stamp:
            self._stale_commands += 1
            if self._start_hold("out-of-order command"):
                self.ctx.log(f"opening_command stamped {s.stamp} is older than the one used before (stamped "
                             f"{self._command_stamp}); holding the measured opening {self._hold_at * 1e3:.2f} mm")
            return None
        self._command_stamp = s.stamp
        return cmd

    def read_state(self, t: float) -> Reading | None:
        """This step's reading; the last one when this read failed (None: none since activate()); raises after
        ``read_timeout`` without a valid one."""
        r = self._hw_read()
        now = time.monotonic()
        self._read_failed = r is None or not math.isfinite(r.opening)
        if self._read_failed:
            if now - self._last_good > self.params.read_timeout:
                raise HardwareError(f"{self.name}: no valid state for {now - self._last_good:.3f} s "
                                    f"(read_timeout {self.params.read_timeout} s); check the connection")
            return self._last_reading
        self._last_good = now
        self._last_reading = r
        return r

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        r = self.read_state(t)
        with self._command_guard():
            target = self.command_target(t, inputs)
            if math.isfinite(target):   # NaN: no state since activate(), nothing to send
                self._hw_write(target)
        return None if r is None else self.outputs_from(r, t)

    def _command_guard(self) -> Any:
        """Held while a step works out and sends its set-point: a driver whose safe_state() may come from another
        thread returns its lock here, so that the hold is never overtaken by a step's send (default: nothing)."""
        return contextlib.nullcontext()

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
        """``open``: max_opening; ``hold``: the measured opening, not clamped (later steps walk a gripper resting
        outside the range into it at max_speed instead of jumping); NaN when nothing was measured since activate()
        (the opening of before is not where the fingers are now: nothing is sent)."""
        p = self.params
        if p.safe_mode == "open":
            return p.max_opening
        return self._measured()

    def _forget_sent(self) -> None:
        """Before the safe state's hold: a driver that skips re-sending an unchanged set-point forgets what it sent,
        so the hold always goes out (default: nothing to forget)."""

    def safe_state(self) -> None:
        if not getattr(self, "_ready", False):
            return
        # under the driver's command lock (see _command_guard): a step's command and send in progress on another
        # thread finishes first, and the hold goes out last
        with self._command_guard():
            self._forget_sent()
            self._send_hold()

    def _send_hold(self) -> None:
        try:
            self._safe = True
            self._hold_at = self.safe_target()
            if math.isfinite(self._hold_at):
                self._setpoint = self._hold_at
            if math.isfinite(self._setpoint):
                self._hw_write(self._setpoint)
            else:   # no state since activate(): where to hold is not known; the hardware keeps what it does
                self.ctx.log("safe_state: no state read since activation, so no opening to hold: nothing sent")
        except Exception as exc:  # never raise from the safe state; the hardware's own limits take over
            try:
                self.ctx.log(f"safe_state could not command the gripper: {exc}")
            except Exception:
                pass

    def status(self) -> dict[str, Any]:
        r = getattr(self, "_last_reading", None)
        d = {"opening_m": None if r is None else r.opening, "setpoint_m": getattr(self, "_setpoint", None),
             "effort_n": None if r is None else r.effort, "safe": getattr(self, "_safe", False),
             "holding": getattr(self, "_holding", None), "stale_commands": getattr(self, "_stale_commands", 0),
             "bad_commands": getattr(self, "_bad_commands", 0)}
        if self._read_failed:   # quoted by the fault of a node whose input from this one goes stale first
            age = time.monotonic() - getattr(self, "_last_good", time.monotonic())
            why = self._read_problem()
            d["problem"] = (f"no valid state for {age:.3f} s (read_timeout {self.params.read_timeout:g} s)"
                            + (f": {why}" if why else ""))
        return d

    def _read_problem(self) -> str:
        """What the driver knows of why its reads fail (where it talks, how many failed, the last error), for the
        ``problem`` of :meth:`status` and the fault after ``read_timeout``; '' when it knows nothing more."""
        return ""
