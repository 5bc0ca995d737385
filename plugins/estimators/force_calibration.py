"""Automated force calibration: a haptic device presses a probe into the gel in fixed steps (the paper's II-B).

Components:

- ``press-routine`` (controller): commands the leader's translational ``force`` with a PID position loop along the
  press axis (PD on the two other axes) and runs a state machine::

      wait -> approach (descend slowly until the depth estimator sees contact) -> backoff
           -> [ step (ramp to the next displacement) -> hold (settle) -> record ] x loading + unloading
           -> retract -> next cycle ... -> done (write samples, request the end of the run)
      any fault (limit, stale/NaN input, timeout, the abort button) -> abort-retract -> aborted (fault)
      a node feeding it disabled by a fault (Context.disabled_upstream) -> aborted at once, zero force (fault); in
      the last retract, every sample recorded -> done at once

  At each step it records the displacement, the device force (the force it applies along the press axis, averaged
  over the record window once settled: the device has no force sensor, at rest its command balances the gel), the
  mean max depth of the camera frames captured in the window, the phase (loading/unloading) and the cycle.
- ``sim-press-rig`` (device, simulation only): the physical coupling between the leader's handle and the simulated
  gel. From the handle position it computes the probe's indentation (for ``sim-digit``'s ``indentation`` input),
  its position over the sensor (``sim-digit``'s ``position``) and the gel's reaction on the handle (for
  ``sim-omega7``'s ``external_force``) with the same gel model as ``sim-digit``
  (:func:`teletouch.plugins.sensors.gel.gel_force`).

Command line (added to ``teletouch calibrate``)::

    teletouch calibrate force --graph examples/calibrate-force-sim.yaml -o sim.force.json
    teletouch calibrate force --csv pairs.csv -o sensor.force.json

Both write the calibration file, a Fig.-3-style PNG and (for a graph) the samples as CSV.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import deque
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import ComponentFault, Component, Device, Kind, Params, Port, hookimpl
from teletouch.argtypes import bare_metres_hint
from teletouch.paths import output_problem
from teletouch.runtime import feeders
from teletouch.reproducible import source_date_epoch
from teletouch.units import (
    MAX_PLAUSIBLE_DEPTH_LIMIT, MAX_PLAUSIBLE_HAND_FORCE, Meters, MetersPerSecond, NewtonSecondsPerMeter, Newtons,
    NewtonsPerMeter, Pascals, Seconds, plausible_depth, plausible_quantity, plausible_travel,
)

from .poly_force import (
    DEFAULT_MIN_R2, MAX_DEGREE, MAX_DEPTH_M, MAX_POSITION_DEGREE, PHASES, CalibrationError, ForceCalibration,
    PairsFileError, read_pairs_csv, write_pairs_csv,
)

__all__ = ["PressRoutine", "SimPressRig", "fit_samples", "run_press_calibration"]


def _u(unit: str) -> dict[str, str]:
    return {"unit": unit}


AXES = {"x": 0, "y": 1, "z": 2}

#: no approach, backoff or tracking error of the probe is longer than this (more than the Omega.7's workspace is
#: across, 0.15 m): a longer one in a metre field is millimetres typed there (``backoff: 0.5`` meant 0.5 mm)
MAX_PROBE_TRAVEL = 0.2   # m
#: no probe is driven towards a gel faster than this (the routine's defaults: 1 and 4 mm/s): a faster approach or move
#: speed in the m/s field is mm/s typed there
MAX_PROBE_SPEED = 0.2    # m/s
#: no rate limit of the press force is set higher than this (the default: 500 N/s): a haptic device's whole +-50 N
#: swing (:data:`~teletouch.units.MAX_PLAUSIBLE_HAND_FORCE`; the Omega.7: +-12 N) in one 1 ms period of the routine at
#: its 1 kHz default, beyond which the limit limits nothing; a higher one is mN/s typed in the N/s field
MAX_PLAUSIBLE_FORCE_RATE = 2 * MAX_PLAUSIBLE_HAND_FORCE / 1e-3   # N/s: 100 kN/s


# ================================================================================================ the press routine
class PressRoutine(Component):
    """Force calibration: presses a probe held by the leader into the gel in fixed steps and records (depth, force)."""

    name = "press-routine"
    kind = Kind.CONTROLLER
    default_rate = 1000.0
    guards_upstream = True   # a node feeding it disabled: the routine aborts at once, zero force (a fault)
    inputs = {
        "position": Port("float64", (3,), "m", "leader end-effector position", required=True),
        "max_depth": Port("float64", (), "m", "max depth from the depth estimator", required=True),
        "abort": Port("bool", (), "", "abort when true (e.g. the leader's button)", required=False),
        "reference_depth": Port("float64", (), "m", "ground-truth max depth to record beside (simulation)",
                                required=False),
        "reference_force": Port("float64", (), "N", "ground-truth force to record beside (simulation)",
                                required=False),
        "centroid": Port("float64", (2,), "m", "contact centroid from the depth estimator, recorded for a "
                         "calibration with position terms (--position-degree)", required=False),
    }
    outputs = {
        "force": Port("float64", (3,), "N", "translational force command to the leader"),
        "target": Port("float64", (3,), "m", "position the loop tracks"),
        "state": Port("str", (), "", "state of the routine"),
        "progress": Port("float64", (), "", "fraction of the routine done (0..1)"),
    }

    class Params(Params):
        axis: Literal["x", "y", "z"] = Field("z", description="press axis of the leader")
        direction: Literal[-1, 1] = Field(-1, description="sign of the press along the axis (-1: towards -axis)")
        cycles: int = Field(3, ge=1, le=100, description="press cycles (each loads and unloads)")
        positions: list[tuple[Meters, Meters]] = Field(default_factory=list, description="press points (m) "
                                                       "across the sensor, as offsets from the start position on "
                                                       "the two other axes in x, y, z order; cycle k presses at "
                                                       "positions[k % n], each with its own touch search; empty: "
                                                       "all cycles at the start position")
        step: Meters = Field(1e-4, gt=0, description="displacement step", json_schema_extra=_u("m"))
        max_displacement: Meters = Field(2e-3, gt=0, description="deepest displacement beyond the touch point",
                                         json_schema_extra=_u("m"))
        approach_speed: MetersPerSecond = Field(1e-3, gt=0, description="speed while searching for the gel",
                                                json_schema_extra=_u("m/s"))
        max_approach: Meters = Field(0.03, gt=0, description="give up if no contact after this travel",
                                     json_schema_extra=_u("m"))
        approach_max_force: Newtons = Field(1.0, gt=0, description="abort the approach if it needs more than this "
                                            "along the press axis for 0.1 s: the probe meets resistance the depth "
                                            "estimator does not see (a gel that reads too shallow, a dead "
                                            "estimator, something in the way)", json_schema_extra=_u("N"))
        move_speed: MetersPerSecond = Field(4e-3, gt=0, description="speed between steps and when retracting",
                                            json_schema_extra=_u("m/s"))
        backoff: Meters = Field(5e-4, ge=0, description="retreat above the touch point before the steps (the "
                                "device's force offset is measured there, off the gel; more than touch_depth)",
                                json_schema_extra=_u("m"))
        touch_depth: Meters = Field(3e-5, gt=0, description="max depth that counts as touching",
                                    json_schema_extra=_u("m"))
        touch_frames: int = Field(2, ge=1, le=30, description="consecutive depth frames at or above touch_depth "
                                  "that make a touch (noise rejection)")
        settle_time: Seconds = Field(0.4, ge=0, description="hold before recording", json_schema_extra=_u("s"))
        record_time: Seconds = Field(0.25, gt=0, description="averaging window at each step",
                                     json_schema_extra=_u("s"))
        settle_tolerance: Meters = Field(2e-5, gt=0, description="position error allowed when recording",
                                         json_schema_extra=_u("m"))
        hold_timeout: Seconds = Field(3.0, gt=0, description="abort if a step does not settle within this",
                                      json_schema_extra=_u("s"))
        kp: NewtonsPerMeter = Field(2000.0, gt=0, description="position gain", json_schema_extra=_u("N/m"))
        kd: NewtonSecondsPerMeter = Field(40.0, ge=0, description="velocity gain", json_schema_extra=_u("N*s/m"))
        ki: float = Field(2.0e4, ge=0, description="integral gain on the press axis", json_schema_extra=_u("N/(m*s)"))
        max_force: Newtons = Field(10.0, gt=0, description="abort if the press needs more than this",
                                   json_schema_extra=_u("N"))
        max_force_rate: float = Field(500.0, gt=0, description="largest change of each force component per second "
                                      "(a step to zero force is always allowed)", json_schema_extra=_u("N/s"))
        max_depth_limit: Meters = Field(3e-3, gt=0, description="abort if the gel is pressed deeper than this",
                                        json_schema_extra=_u("m"))
        max_tracking_error: Meters = Field(2e-3, gt=0, description="abort if the probe is this far from its "
                                           "target", json_schema_extra=_u("m"))
        max_overtravel: Meters = Field(3e-4, gt=0, description="abort if the probe gets more than this deeper than "
                                       "the deepest planned point (touch + max_displacement)",
                                       json_schema_extra=_u("m"))
        input_timeout: Seconds = Field(0.5, gt=0, description="abort if the max depth is older than this",
                                       json_schema_extra=_u("s"))
        position_timeout: Seconds = Field(0.05, gt=0, description="zero force at once if the leader position is "
                                          "older than this (the force loop runs on it)", json_schema_extra=_u("s"))
        start_timeout: Seconds = Field(10.0, gt=0, description="fault if no position and depth arrive within "
                                       "this after the start", json_schema_extra=_u("s"))
        samples_csv: str | None = Field(None, description="write the samples here when done (optional)")

        # a bare number is SI: millimetres, mm/s or mN typed in these fields are refused, naming the field (the
        # routine drives a real device into a gel: max_depth_limit: 3 was 3 m and never aborted a press)
        @field_validator("touch_depth", "settle_tolerance", "max_overtravel", "step")
        @classmethod
        def _into_the_gel(cls, v: float, info: Any) -> float:
            return plausible_depth(info.field_name, v)   # 0.03 meant 0.03 mm: no gel is 30 mm thick

        @field_validator("max_depth_limit", "max_displacement")
        @classmethod
        def _depth_limit(cls, v: float, info: Any) -> float:
            return plausible_depth(info.field_name, v, MAX_PLAUSIBLE_DEPTH_LIMIT)   # beyond the gel on a test rig

        @field_validator("max_tracking_error", "backoff", "max_approach")
        @classmethod
        def _travel(cls, v: float, info: Any) -> float:
            return plausible_travel(info.field_name, v, MAX_PROBE_TRAVEL)

        @field_validator("approach_speed", "move_speed")
        @classmethod
        def _speed(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PROBE_SPEED, "m/s",
                                      "faster than a probe is driven towards a gel")

        @field_validator("approach_max_force", "max_force")
        @classmethod
        def _force(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_HAND_FORCE, "N",   # the leader renders it
                                      "beyond what a haptic device renders", "; the Omega.7: 12 N in translation")

        @field_validator("max_force_rate")
        @classmethod
        def _force_rate(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_FORCE_RATE, "N/s",   # 500000 meant mN/s
                                      "faster than a press's force needs to change",
                                      f": a haptic device's whole +-{MAX_PLAUSIBLE_HAND_FORCE:g} N in 1 ms")

    SATURATION_TIME = 0.1  # s of a saturated press (or of resistance on the approach) before aborting
    MAX_OFFSET = 0.025  # m: a press point farther than this from the start is off any DIGIT's gel (mm given as m?)

    STATES = ("wait", "move", "approach", "backoff", "tare", "step", "hold", "record", "retract", "done",
              "abort-retract", "aborted")
    PRESSING = ("backoff", "tare", "step", "hold", "record", "retract")  # states in which the touch point is known

    # ------------------------------------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        p = self.params
        self.samples: list[dict[str, Any]] = []
        self.reset()  # first: a routine that fails to configure still reports its state and (no) samples
        if p.step > p.max_displacement:
            raise ValueError(f"step ({p.step * 1e3:.3f} mm) is larger than max_displacement "
                             f"({p.max_displacement * 1e3:.3f} mm)")
        if p.hold_timeout <= p.settle_time:
            raise ValueError(f"hold_timeout ({p.hold_timeout:g} s) must be longer than settle_time "
                             f"({p.settle_time:g} s): every step would time out")
        if p.touch_depth >= p.max_depth_limit:
            raise ValueError(f"touch_depth ({p.touch_depth * 1e3:.3f} mm) must be below max_depth_limit "
                             f"({p.max_depth_limit * 1e3:.3f} mm)")
        if p.backoff <= p.touch_depth:
            raise ValueError(f"backoff ({p.backoff * 1e3:.3f} mm) must be more than touch_depth "
                             f"({p.touch_depth * 1e3:.3f} mm): the probe is at least that far into the gel when the "
                             f"touch is seen, and the tare is measured off the gel (the run would abort there)")
        if p.approach_max_force >= p.max_force:
            raise ValueError(f"approach_max_force ({p.approach_max_force:g} N) must be below max_force "
                             f"({p.max_force:g} N)")
        for i, (ox, oy) in enumerate(p.positions):
            if math.hypot(ox, oy) > self.MAX_OFFSET:
                raise ValueError(f"positions[{i}]: ({ox * 1e3:g}, {oy * 1e3:g}) mm is more than "
                                 f"{self.MAX_OFFSET * 1e3:g} mm from the start, off the sensor's gel (offsets are "
                                 f"in m: write 2mm or 0.002, not 2)")
        if p.samples_csv:
            problem = output_problem(p.samples_csv)
            if problem:
                raise ValueError(f"samples_csv: cannot write {p.samples_csv!r}: {problem}")
        self.u = np.zeros(3)
        self.u[AXES[p.axis]] = float(p.direction)
        lateral = [i for i in range(3) if i != AXES[p.axis]]
        self.offsets = []
        for ox, oy in p.positions:
            o = np.zeros(3)
            o[lateral[0]], o[lateral[1]] = ox, oy
            self.offsets.append(o)
        self.plan = self._plan()

    def _plan(self) -> list[tuple[float, str]]:
        """(displacement, phase) of each step of a cycle."""
        p = self.params
        n = int(math.floor(p.max_displacement / p.step + 1e-9))
        load = [k * p.step for k in range(0, n + 1)]
        return [(d, "loading") for d in load] + [(d, "unloading") for d in reversed(load[:-1])]

    def reset(self) -> None:
        self.state = "wait"
        self.cycle = 0
        self.index = 0
        self.t_state = 0.0
        self.home: np.ndarray | None = None  # start position
        self.origin: np.ndarray | None = None  # start of this cycle (home moved to the cycle's press point)
        self.touch: float | None = None  # press coordinate of the touch point
        self.target = None  # target position (3,)
        self.goal = None  # where the ramp ends
        self.integral = 0.0
        self.last_t: float | None = None
        self.pos: np.ndarray | None = None
        self.vel = np.zeros(3)
        self.cmd = np.zeros(3)
        self.abort_reason: str | None = None
        self.window: dict[str, list] = {}
        self.last_depth_stamp: float | None = None
        self.pos_stamp: float | None = None
        self.resist_since: float | None = None
        self.events: list[tuple[float, str]] = []
        self.done_points = 0
        self.saturated_since: float | None = None
        self.touch_count = 0
        self.t_start: float | None = None
        self.tare = 0.0
        # the last second's steps: whether max_force_rate held the force command back (an abort names it when so)
        self.rate_held: deque[bool] = deque(maxlen=max(10, round(float(self.ctx.rate or self.default_rate))))
        self.arrived: float | None = None
        self._samples_written = False

    def activate(self) -> None:
        self.samples = []   # a new run: the last run's samples are not this one's (counts, cycles, samples_csv)
        self.reset()

    # ------------------------------------------------------------------------------------------------ helpers
    @property
    def total_points(self) -> int:
        return len(self._plan()) * self.params.cycles  # from the params: known before configure (progress bar)

    def _s(self, pos: np.ndarray) -> float:
        """Press coordinate: how far pos is along the press direction."""
        return float(pos @ self.u)

    def _at(self, s: float) -> np.ndarray:
        """This cycle's start point moved to press coordinate s."""
        assert self.origin is not None
        return self.origin + (s - self._s(self.origin)) * self.u

    def _go(self, t: float, state: str) -> None:
        self.events.append((t, state))
        self.state = state
        self.t_state = t

    def _abort(self, t: float, reason: str) -> None:
        if self.state in ("abort-retract", "aborted"):
            return
        held, steps = sum(self.rate_held), len(self.rate_held)
        if steps >= 10 and held > 0.5 * steps:
            # the symptom (a step that does not settle, a probe still in the gel at the backoff point) names another
            # setting; the force command lagging its controller's most of the last second is the cause
            reason += (f" (max_force_rate, {self.params.max_force_rate:g} N/s, held the force back in {held} of the "
                       f"last {steps} steps: the probe cannot follow its targets; raise it)")
        self.abort_reason = reason
        self.ctx.log(f"aborting: {reason}; retracting")
        # straight back out along the press axis to the start height (never sideways while pressing), from where the
        # probe is: not from the target, which may lie deeper (a blocked probe) or off to the side; the integral
        # (the force that held the probe against the gel) is dropped, and the retract never pushes (see _control)
        if self.home is not None and self.pos is not None and self.target is not None:
            self.target = self.pos.copy()
            self.goal = self.target + (min(self._s(self.home), self._s(self.pos)) - self._s(self.pos)) * self.u
            self.integral = min(self.integral, 0.0)
        else:
            self.goal = None
        self._go(t, "abort-retract" if self.goal is not None else "aborted")

    def _feeders_lost(self, t: float) -> bool:
        """Whether a node feeding the routine (through the graph's wiring, directly or not) has been disabled by a fault
        (Context.disabled_upstream): a filter in between may go on publishing its last value with fresh stamps, so
        the routine's freshness checks cannot tell, and its samples would be stale. Then the routine ends at once,
        with zero force (no retract: the lost node may be on the position's path): aborted (the abort path writes
        ``samples_csv`` marked partial and faults the node), or done in the last retract, where every sample was
        recorded before the fault was known. Checked at each step and again before a sample is stored (a fault in
        another rate group may land while this step runs). Not once the routine is done or aborted."""
        if self.state in ("done", "aborted"):
            return False
        lost = self.ctx.disabled_upstream()
        if not lost:
            return False
        names = ", ".join(f"'{n}'" for n in lost)
        what = (f"node {names}, which feeds the press routine, was" if len(lost) == 1 else
                f"nodes {names}, which feed the press routine, were")
        reason = f"{what} disabled by a fault: its samples would be stale"
        if self.state == "retract" and self.cycle + 1 >= self.params.cycles:
            self.ctx.log(f"{reason}; every sample was recorded before: the last retract is cut short (zero force)")
            self._finish(t)
            return True
        self.abort_reason = self.abort_reason or reason   # (an abort under way keeps its first reason)
        self.ctx.log(f"aborting: {reason}; zero force at once")
        self._go(t, "aborted")
        return True

    def _ramp(self, dt: float, speed: float) -> bool:
        """Move the target towards the goal at ``speed``; True once it is there."""
        if self.target is None or self.goal is None:
            return True
        delta = self.goal - self.target
        dist = float(np.linalg.norm(delta))
        stepd = speed * dt
        if dist <= stepd or dist == 0.0:
            self.target = self.goal.copy()
            return True
        self.target = self.target + delta * (stepd / dist)
        return False

    # ------------------------------------------------------------------------------------------------ stepping
    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        p = self.params
        dt = 0.0 if self.last_t is None else max(0.0, t - self.last_t)
        self.last_t = t
        ps = inputs["position"]
        pos = None
        if ps is not None and ps.is_fresh(t, p.position_timeout):  # neither old nor stamped ahead of the clock
            try:
                v = np.asarray(ps.value, dtype=float).reshape(-1)
            except (TypeError, ValueError):
                v = np.full(3, np.nan)
            if v.shape == (3,) and np.all(np.isfinite(v)):
                pos = v
        if pos is not None and self.pos_stamp is not None and not ps.stamp > self.pos_stamp:
            pos = self.pos  # a repeated or out-of-order sample: the newest position known (itself still fresh)
        elif pos is not None:
            # --- velocity estimate, from the samples' own stamps (a leader slower than this loop, or a late sample,
            # would otherwise give velocity spikes)
            if self.pos is not None and self.pos_stamp is not None:
                dtp = ps.stamp - self.pos_stamp
                raw = (pos - self.pos) / dtp
                a = dtp / (dtp + 0.002)  # 2 ms filter on the differentiated position
                self.vel = self.vel + a * (raw - self.vel)
            self.pos = pos
            self.pos_stamp = ps.stamp
        ds = inputs["max_depth"]
        depth = None
        if ds is not None and ds.is_fresh(t, p.input_timeout):
            try:
                depth = float(ds.value)
            except (TypeError, ValueError, OverflowError):   # (OverflowError: an int beyond any float)
                depth = math.nan
        # a new frame only if newer than the last one (a repeated or late, out-of-order frame is not), and only a
        # fresh one: a NaN stamp or one far ahead of the clock, taken as the newest, locked out every frame after it
        new_depth = depth is not None and (self.last_depth_stamp is None or ds.stamp > self.last_depth_stamp)
        if new_depth:
            self.last_depth_stamp = ds.stamp

        # --- faults ---------------------------------------------------------------------------------------
        self._feeders_lost(t)
        if self.state not in ("wait", "done", "aborted"):
            if pos is None:
                # cannot steer without a position: no retract possible, zero force at once
                self.abort_reason = self.abort_reason or "leader position lost (stale, missing or NaN)"
                self._go(t, "aborted")
            elif self.state != "abort-retract":
                if depth is None:
                    ahead = ds is not None and ds.stamp > t
                    self._abort(t, f"max depth stamped {ds.stamp - t:.3f} s ahead of the clock (a clock fault)"
                                if ahead else f"no max depth for more than {p.input_timeout:g} s")
                elif not math.isfinite(depth):
                    self._abort(t, f"max depth is {depth}")
                elif depth > p.max_depth_limit:
                    self._abort(t, f"max depth {depth * 1e3:.3f} mm beyond the limit "
                                   f"{p.max_depth_limit * 1e3:.3f} mm")
                elif bool(inputs.value("abort", False)):
                    self._abort(t, "abort input (button) pressed")
                elif (self.touch is not None and self.state in self.PRESSING
                      and self._s(pos) - self.touch > p.max_displacement + p.max_overtravel):
                    self._abort(t, f"probe {(self._s(pos) - self.touch) * 1e3:.3f} mm past the touch point, deeper "
                                   f"than max_displacement {p.max_displacement * 1e3:.3f} mm + max_overtravel "
                                   f"{p.max_overtravel * 1e3:.3f} mm")
                elif self.target is not None and float(np.linalg.norm(self.target - pos)) > p.max_tracking_error:
                    self._abort(t, f"probe {np.linalg.norm(self.target - pos) * 1e3:.2f} mm from its target")

        st = self.state
        if st == "wait":
            if self.t_start is None:
                self.t_start = t
            if (pos is None or depth is None or not math.isfinite(depth)) and t - self.t_start > p.start_timeout:
                missing = " and ".join(n for n, v in (("position", pos), ("max depth", depth)) if v is None)
                if missing:
                    self.abort_reason = f"no {missing} within {p.start_timeout:g} s of the start: check the wiring"
                else:
                    self.abort_reason = (f"max depth still {depth} {p.start_timeout:g} s after the start: check the "
                                         f"depth estimator")
                self._go(t, "aborted")
            elif pos is not None and depth is not None and math.isfinite(depth) and depth >= p.touch_depth:
                self.abort_reason = (f"the gel is already pressed ({depth * 1e3:.3f} mm) at the start: lift the "
                                     f"probe off the sensor")
                self._go(t, "aborted")
            elif pos is not None and depth is not None and math.isfinite(depth):
                self.home = pos.copy()
                self.target = pos.copy()
                self.ctx.log(f"start at {np.round(pos * 1e3, 3).tolist()} mm")
                self._move_to_cycle(t)
        elif st == "move":
            if self._ramp(dt, p.move_speed):
                self._approach(t)
        elif st == "approach":
            # resistance the depth estimator does not see: stop here rather than push on until max_force
            if float(self.cmd @ self.u) > p.approach_max_force:
                if self.resist_since is None:
                    self.resist_since = t
            else:
                self.resist_since = None
            arrived = self._ramp(dt, p.approach_speed)
            if new_depth:
                self.touch_count = self.touch_count + 1 if depth >= p.touch_depth else 0
            if self.touch_count >= p.touch_frames:
                self.touch = self._s(pos)
                self.ctx.log(f"touch at {self.touch * 1e3:.3f} mm along the press axis (depth "
                             f"{depth * 1e3:.3f} mm)")
                self._begin_cycle(t)
            elif self.resist_since is not None and t - self.resist_since >= self.SATURATION_TIME:
                self._abort(t, f"the approach needs {float(self.cmd @ self.u):.2f} N, more than approach_max_force "
                               f"{p.approach_max_force:g} N, while the max depth reads {depth * 1e3:.3f} mm (below "
                               f"touch_depth): does the depth estimator see the gel?")
            elif arrived:
                self._abort(t, f"no contact after {p.max_approach * 1e3:.1f} mm of approach: is the sensor "
                               f"under the probe?")
        elif st == "backoff":
            if self._ramp(dt, p.move_speed):
                if self.arrived is None:
                    self.arrived = t
                if t - self.arrived >= p.settle_time:
                    self.window = {"force": []}
                    self._go(t, "tare")
        elif st == "tare":
            # off the gel: the force the loop needs to hold still here (gravity-compensation error, friction) is
            # the device's offset, subtracted from this cycle's samples
            if depth >= p.touch_depth:
                self._abort(t, f"the probe still touches the gel ({depth * 1e3:.3f} mm) at the backoff point: "
                               f"increase backoff")
            else:
                self.window["force"].append(float(self.cmd @ self.u))
                if t - self.t_state >= p.record_time:
                    self.tare = float(np.mean(self.window["force"]))
                    self._next_point(t)
        elif st == "step":
            if self._ramp(dt, p.move_speed):
                self._go(t, "hold")
        elif st == "hold":
            settled = abs(self._s(self.target) - self._s(pos)) <= p.settle_tolerance
            if t - self.t_state >= p.settle_time and settled:
                self.window = {"force": [], "depth": [], "pos": [], "ref_depth": [], "ref_force": [],
                               "depth_stamps": [], "centroid": []}
                self._go(t, "record")
            elif t - self.t_state > p.hold_timeout:
                self._abort(t, f"step did not settle within {p.hold_timeout:g} s (error "
                               f"{abs(self._s(self.target) - self._s(pos)) * 1e6:.1f} um)")
        elif st == "record":
            w = self.window
            w["force"].append(float(self.cmd @ self.u))
            w["pos"].append(self._s(pos))
            if new_depth and ds.stamp >= self.t_state:
                w["depth"].append(depth)
                w["depth_stamps"].append(ds.stamp)
                c = inputs.value("centroid")
                if c is not None and np.all(np.isfinite(c)):
                    w["centroid"].append(np.asarray(c, dtype=float).reshape(2))
            rd = inputs.value("reference_depth")
            rf = inputs.value("reference_force")
            if rd is not None:
                w["ref_depth"].append(float(rd))
            if rf is not None:
                w["ref_force"].append(float(rf))
            if t - self.t_state >= p.record_time and w["depth"] and not self._feeders_lost(t):
                self._store(t)
                self._next_point(t)
        elif st == "retract":
            if self._ramp(dt, p.move_speed):
                self.cycle += 1
                if self.cycle >= p.cycles:
                    self._finish(t)
                elif self.offsets:
                    self._move_to_cycle(t)
                else:
                    self._begin_cycle(t)
        elif st == "abort-retract":
            if self._ramp(dt, p.move_speed) and (pos is None or
                                                 float(np.linalg.norm(self.goal - pos)) < 5 * p.settle_tolerance
                                                 or t - self.t_state > 5.0):
                self._go(t, "aborted")

        # --- control ----------------------------------------------------------------------------------------
        if self.state in ("wait", "done", "aborted") or pos is None or self.target is None:
            self.cmd = np.zeros(3)
        else:
            self.cmd = self._control(dt, pos)
        out = {"force": self.cmd.copy(), "state": self.state, "progress": self.progress}
        if self.target is not None:
            out["target"] = self.target.copy()
        if self.state == "aborted":
            self.cmd = np.zeros(3)
            out["force"] = np.zeros(3)
            self._write_samples(partial=True)
            raise ComponentFault(f"press routine aborted: {self.abort_reason}", self.id)
        return out

    def _control(self, dt: float, pos: np.ndarray) -> np.ndarray:
        p = self.params
        # a late step counts at most 2 periods of the node's rate (as position-force's _max_dt): the whole gap let the
        # rate limit and the integrator step the force at once (50 ms late: 3.02 N in one step, against 0.5 N on time)
        dt = min(dt, 2.0 / float(self.ctx.rate or self.default_rate))
        err = self.target - pos
        f = p.kp * err - p.kd * self.vel
        e_s = float(err @ self.u)
        f_s = float(f @ self.u)
        # integral on the press axis only, with anti-windup (frozen while saturated)
        candidate = self.integral + p.ki * e_s * dt
        if abs(f_s + candidate) <= p.max_force:
            self.integral = candidate
        f = f + self.integral * self.u
        n = float(np.linalg.norm(f))
        press = float(f @ self.u)
        t = self.last_t or 0.0
        if press > p.max_force and self.state != "abort-retract":
            if self.saturated_since is None:
                self.saturated_since = t
            elif t - self.saturated_since >= self.SATURATION_TIME:
                self._abort(t, f"the press needs {press:.2f} N, more than max_force {p.max_force:g} N")
        else:
            self.saturated_since = None
        if self.state == "abort-retract":
            press = float(f @ self.u)
            if press > 0:
                f = f - press * self.u  # an abort only ever pulls the probe out
            n = float(np.linalg.norm(f))
        if n > p.max_force:
            f = f * (p.max_force / n)
        # rate limit: each component moves at most max_force_rate * dt from the last command, except towards zero
        r = p.max_force_rate * dt
        out = np.clip(f, np.minimum(self.cmd - r, 0.0), np.maximum(self.cmd + r, 0.0))
        self.rate_held.append(not np.array_equal(out, f))
        return out

    def _move_to_cycle(self, t: float) -> None:
        """Go (at the start height) over this cycle's press point, then search for the gel there."""
        assert self.home is not None
        off = self.offsets[self.cycle % len(self.offsets)] if self.offsets else np.zeros(3)
        self.origin = self.home + off
        self.goal = self.origin.copy()
        self.touch = None
        self.touch_count = 0
        self.resist_since = None
        if self.offsets:
            self.ctx.log(f"cycle {self.cycle + 1}: press point {np.round(self.origin * 1e3, 3).tolist()} mm")
        self._go(t, "move")

    def _approach(self, t: float) -> None:
        self.goal = self._at(self._s(self.origin) + self.params.max_approach)
        self._go(t, "approach")

    def _begin_cycle(self, t: float) -> None:
        p = self.params
        assert self.touch is not None
        self.index = 0
        self.goal = self._at(self.touch - p.backoff)
        self.arrived = None
        self.ctx.log(f"cycle {self.cycle + 1}/{p.cycles}")
        self._go(t, "backoff")

    def _next_point(self, t: float) -> None:
        if self.index >= len(self.plan):
            self.goal = self.origin.copy()
            self._go(t, "retract")
            return
        disp, _ = self.plan[self.index]
        self.goal = self._at(self.touch + disp)
        self._go(t, "step")

    def _store(self, t: float) -> None:
        w = self.window
        disp, phase = self.plan[self.index]
        xy = np.mean(w["centroid"], axis=0) if w["centroid"] else (None, None)
        rec = {
            "depth_m": float(np.mean(w["depth"])),
            "force_n": float(np.mean(w["force"])) - self.tare,
            "tare_n": self.tare,
            "phase": phase,
            "cycle": self.cycle,
            "displacement_m": float(np.mean(w["pos"]) - self.touch),
            "press_point_m": [float(v) for i, v in enumerate(self.origin - self.home) if i != AXES[self.params.axis]],
            "gt_max_depth_m": float(np.mean(w["ref_depth"])) if w["ref_depth"] else None,
            "gt_force_n": float(np.mean(w["ref_force"])) if w["ref_force"] else None,
            "x_m": None if xy[0] is None else float(xy[0]),
            "y_m": None if xy[1] is None else float(xy[1]),
            "target_displacement_m": disp,
            "depth_std_m": float(np.std(w["depth"])),
            "force_std_n": float(np.std(w["force"])),
            "frames": len(w["depth"]),
            "time_s": t,
        }
        self.samples.append(rec)
        self.index += 1
        self.done_points += 1

    def partial_reason(self) -> str | None:
        """Why the samples are incomplete (for the CSV's ``# partial:`` line), or None once the routine is done."""
        if self.state == "done":
            return None
        why = f": {self.abort_reason}" if self.abort_reason else ""
        return (f"press routine {self.state}{why}; {len(self.samples)} of {self.total_points} planned steps "
                f"recorded")

    def _write_samples(self, partial: bool = False) -> None:
        """samples_csv, once: at the end, or marked partial at an abort (the samples so far, for a look)."""
        if not self.params.samples_csv or self._samples_written:
            return
        self._samples_written = True
        try:
            write_pairs_csv(self.params.samples_csv, self.samples, partial=self.partial_reason() if partial else None)
        except OSError as exc:
            if not partial:
                raise
            self.ctx.log(f"could not write the partial samples to {self.params.samples_csv}: {exc}")

    def _finish(self, t: float) -> None:
        self._go(t, "done")
        self.cmd = np.zeros(3)
        self._write_samples()
        self.ctx.request_stop(f"press routine done: {len(self.samples)} samples in {self.params.cycles} cycle(s)")

    @property
    def progress(self) -> float:
        if self.state == "done":
            return 1.0
        return min(1.0, self.done_points / max(1, self.total_points))

    def status(self) -> dict[str, Any]:
        if not hasattr(self, "state"):
            return {}
        return {"state": self.state, "cycle": self.cycle + 1, "samples": len(self.samples),
                "force_n": float(self.cmd @ self.u) if hasattr(self, "u") else 0.0}


# ================================================================================================ the simulated rig
class SimPressRig(Device):
    """Simulated press rig: the probe on the leader's handle meets the simulated gel (indentation and reaction)."""

    name = "sim-press-rig"
    kind = Kind.DEVICE
    default_rate = 1000.0
    inputs = {"position": Port("float64", (3,), "m", "leader end-effector position (the probe's tip)",
                               required=True)}
    outputs = {
        "indentation": Port("float64", (), "m", "probe indentation into the gel (to sim-digit)"),
        "indenter_position": Port("float64", (2,), "m", "probe axis relative to the image centre (to sim-digit)"),
        "force": Port("float64", (3,), "N", "the gel's reaction on the handle (to the leader's external_force)"),
        "contact_force": Port("float64", (), "N", "ground truth: normal force between probe and gel"),
    }

    class Params(Params):
        surface: Meters = Field(-0.005, description="handle z at which the probe's tip touches the gel",
                                json_schema_extra=_u("m"))
        sensor_center: tuple[Meters, Meters] = Field((0.0, 0.0), description="handle (x, y) over the image centre "
                                                     "(m); handle x is image x (columns), handle y image y (rows)")
        # the gel and the probe: keep these equal to sim-digit's parameters of the same names
        indenter: Literal["probe", "sphere", "flat"] = Field("probe", description="probe shape (as sim-digit)")
        indenter_radius: Meters = Field(0.005, gt=0, description="probe radius", json_schema_extra=_u("m"))
        tip_radius: Meters = Field(0.010, gt=0, description="radius of the probe's curved tip",
                                   json_schema_extra=_u("m"))
        modulus: Pascals | None = Field(None, gt=0, description="gel Young's modulus (None: the gel model's "
                                        "default, as sim-digit)", json_schema_extra=_u("Pa"))
        poisson: float | None = Field(None, ge=0, le=0.5, description="gel Poisson ratio (None: default)")
        gel_thickness: Meters | None = Field(None, gt=0, description="gel layer thickness for the thin-layer "
                                             "correction (None: half space, as sim-digit's default)",
                                             json_schema_extra=_u("m"))
        damping: NewtonSecondsPerMeter = Field(5.0, ge=0, description="gel damping while in contact (never "
                                               "pulls)", json_schema_extra=_u("N*s/m"))
        probe_weight: Newtons = Field(0.0, ge=0, description="weight of the probe the device does not compensate "
                                      "(pulls the handle down; the routine's tare removes it)",
                                      json_schema_extra=_u("N"))

        @model_validator(mode="after")
        def _plausible_gel(self) -> "SimPressRig.Params":
            from teletouch.plugins.sensors.gel import check_gel_params   # numpy only

            check_gel_params(self)   # millimetres in metre fields, kPa/MPa as Pa: as sim-digit refuses them
            return self

    def configure(self) -> None:
        from teletouch.plugins.sensors.gel import Indenter, gel_force  # the same gel model as sim-digit

        p = self.params
        self._gel_force = gel_force
        if p.indenter == "probe":
            self.indenter = Indenter.probe(p.indenter_radius, p.tip_radius)
        elif p.indenter == "sphere":
            self.indenter = Indenter.sphere(p.indenter_radius)
        else:
            self.indenter = Indenter.flat(p.indenter_radius)
        self.last: tuple[float, float] | None = None
        self.d = 0.0
        self.f = 0.0
        self.safe = False

    def activate(self) -> None:
        self.safe = False
        self.last = None

    def gel(self, indentation: float) -> float:
        p = self.params
        return self._gel_force(indentation, self.indenter, p.modulus, p.poisson, p.gel_thickness)

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        s = inputs["position"]
        if s is None:
            return None
        pos = np.asarray(s.value, dtype=float).reshape(3)
        if not np.all(np.isfinite(pos)):
            raise ComponentFault(f"leader position {pos.tolist()} is not finite", self.id)
        p = self.params
        d = max(0.0, p.surface - float(pos[2]))
        rate = 0.0
        if self.last is not None and t > self.last[0]:
            rate = (d - self.last[1]) / (t - self.last[0])
        self.last = (t, d)
        f = self.gel(d) if d > 0 else 0.0
        if d > 0:
            f = max(0.0, f + p.damping * rate)
        self.d, self.f = d, f
        xy = np.array([pos[0] - p.sensor_center[0], pos[1] - p.sensor_center[1]])
        return {"indentation": d, "indenter_position": xy, "force": np.array([0.0, 0.0, f - p.probe_weight]),
                "contact_force": f}

    def safe_state(self) -> None:
        self.safe = True  # the gel is passive: nothing to drive

    def status(self) -> dict[str, Any]:
        return {"indentation_m": getattr(self, "d", 0.0), "gel_force_n": getattr(self, "f", 0.0)}


# ================================================================================================ fitting + CLI
#: a force in contact more negative than this (N) is refused as a missing tare: a gel pressed in pushes back (the
#: packaged calibration's smallest force is +0.038 N) and a smaller offset is within a fit's residual (RMSE
#: 0.014-0.058 N in simulation)
NEGATIVE_FORCE_TOLERANCE_N = 0.05


def fit_samples(samples: list[dict[str, Any]], degree: int = 3, *, min_depth: float = 3e-5, use: str = "all",
                zero_intercept: bool = False, sensor_model_id: str = "", depth_source: str = "",
                source: str = "", position_degree: int = 0, min_r2: float | None = DEFAULT_MIN_R2,
                where: str = "", min_depth_option: str | None = None) -> ForceCalibration:
    """Fit a calibration from recorded samples, leaving out those without contact (depth < min_depth). With
    ``position_degree`` > 0 every kept sample needs its contact centroid (x_m, y_m). A sample in contact with a force
    below -:data:`NEGATIVE_FORCE_TOLERANCE_N` (a missing tare) and a fit with R^2 below ``min_r2`` are refused.
    ``where``: the samples' file, named with each sample's ``line`` in the errors. ``min_depth_option``: the
    ``--min-depth`` text as typed (the command line), named where no sample is that deep."""
    # a NaN depth is kept (and refused by the fit, naming the sample), not counted as a sample without contact
    keep = [s for s in samples if not s["depth_m"] < min_depth]
    if not keep:
        notes = []
        hint = ""
        if min_depth_option is not None:   # what was typed, as read: a bare 0.005 (meant mm) is 5 mm
            notes.append(f"--min-depth {min_depth_option}, read as {min_depth:g} m")
            hint = bare_metres_hint(min_depth_option).removeprefix("; ") if min_depth > 0 else ""
        deepest = max((s["depth_m"] for s in samples if math.isfinite(s["depth_m"])), default=None)
        if deepest is not None:
            notes.append(f"the deepest is {deepest * 1e3:.3f} mm")
        raise CalibrationError(f"no sample with a max depth of at least {min_depth * 1e3:.3f} mm"
                               f"{' (' + '; '.join(notes) + ')' if notes else ''}: "
                               f"{hint or 'did the probe touch the gel?'}")
    problem = _sample_problem(samples, min_depth, position_degree, where) or _negative_force_problem(
        samples, keep, min_depth, where)
    if problem:
        raise CalibrationError(problem)
    extra = {"excluded_no_contact": len(samples) - len(keep), "min_depth_m": min_depth}
    positions = None
    if position_degree:
        missing = [i for i, s in enumerate(keep) if s.get("x_m") is None or s.get("y_m") is None]
        if missing:
            s = keep[missing[0]]   # the first one, named as the other refusals name it: the file's line, or the sample
            if where and s.get("line"):
                at = f"{where}:{s['line']}: column '{'x_m' if s.get('x_m') is None else 'y_m'}' is empty: "
            else:
                i = next(k for k, x in enumerate(samples) if x is s)
                at = f"{where + ': ' if where else ''}sample {i} has no contact centroid: "
            raise CalibrationError(f"{at}position_degree {position_degree} needs the contact centroid of every sample; "
                                   f"{len(missing)} of {len(keep)} have none (wire depth.centroid into the "
                                   f"press-routine's 'centroid' input, or give x_m, y_m columns in the CSV)")
        positions = [(float(s["x_m"]), float(s["y_m"])) for s in keep]
    try:
        return ForceCalibration.fit([s["depth_m"] for s in keep], [s["force_n"] for s in keep], degree,
                                    phases=[s.get("phase") or "" for s in keep],
                                    cycles=[int(s.get("cycle") or 0) for s in keep], use=use,
                                    zero_intercept=zero_intercept, sensor_model_id=sensor_model_id,
                                    depth_source=depth_source, source=source, extra=extra, positions=positions,
                                    position_degree=position_degree, min_r2=min_r2)
    except CalibrationError as exc:   # the fit's refusals of the data as a whole name the file too
        if not where:
            raise
        raise CalibrationError(f"{where}: {exc}") from None


def _sample_problem(samples: list[dict[str, Any]], min_depth: float, position_degree: int,
                    where: str) -> str | None:
    """Why a sample in contact cannot be fitted (a non-finite value, an unknown phase), named by its line in the file
    or its index in ``samples`` (the fit, given the samples in contact only, would count those), or None."""
    for i, s in enumerate(samples):
        if s["depth_m"] < min_depth:
            continue   # no contact: left out
        at = f"{where}:{s['line']}" if where and s.get("line") else f"{where + ': ' if where else ''}sample {i}"
        if not (math.isfinite(s["depth_m"]) and math.isfinite(s["force_n"])):
            return f"{at}: depth {float(s['depth_m'])!r} m, force {float(s['force_n'])!r} N is not finite"
        if (s.get("phase") or "") not in PHASES:
            return f"{at}: phase must be 'loading', 'unloading' or empty, got {s['phase']!r}"
        xy = (s.get("x_m"), s.get("y_m"))
        if position_degree and None not in xy and not all(math.isfinite(float(v)) for v in xy):
            return f"{at}: contact centroid {[float(v) for v in xy]} m is not finite"
    return None


def _negative_force_problem(samples: list[dict[str, Any]], keep: list[dict[str, Any]], min_depth: float,
                            where: str) -> str | None:
    """Why the forces in contact look untared (the first one below -NEGATIVE_FORCE_TOLERANCE_N), or None."""
    tol = NEGATIVE_FORCE_TOLERANCE_N
    low = [s for s in keep if s["force_n"] < -tol]   # a NaN force is left to the fit (it names the sample)
    if not low:
        return None
    s = low[0]
    i = next(k for k, x in enumerate(samples) if x is s)
    if where and s.get("line"):
        at = f"{where}:{s['line']}: column '{s.get('column') or 'force_n'}'"
    else:
        at = (f"{where + ': ' if where else ''}sample {i}"
              + (f" (cycle {s.get('cycle', 0)}, {s['phase']})" if s.get("phase") else ""))
    free = [x["force_n"] for x in samples if x["depth_m"] < min_depth and math.isfinite(x["force_n"])]
    offset = (f"; the {len(free)} samples without contact read a median of {float(np.median(free)):.3f} N, the likely "
              f"offset" if free else "")
    return (f"{at}: force {s['force_n']:.4g} N at a max depth of {s['depth_m'] * 1e3:.3f} mm, below zero by more than "
            f"the {tol:g} N tolerance ({len(low)} of {len(keep)} samples in contact are): a gel pressed in pushes "
            f"back, so the forces were probably recorded without a tare (the force measured off the gel not "
            f"subtracted){offset}; fitting them would leave a 0 N band at small depths. Re-tare the force measurement "
            f"(off the gel) and record again, or add the offset to every force of the file")


def _sensor_model_id(spec: Any) -> tuple[str, str]:
    """(sensor model id, depth source) guessed from the graph: the depth node's model (its default where the graph
    does not set it), else the sensor node."""
    sensor = ""
    for n in spec.nodes:
        if n.plugin in ("sim-digit", "digit", "replay"):
            prm = n.params or {}
            sensor = n.plugin + (f":{prm['serial']}" if prm.get("serial") else "")
    depth = ""
    for n in spec.nodes:
        if n.plugin == "press-routine":
            w = n.inputs.get("max_depth")
            if w is not None:
                src = spec.node(w.node)
                depth = f"{w.node}.{w.source_port} ({src.plugin})"
                model = (src.params or {}).get("model")
                fields = getattr(getattr(src.cls, "Params", None), "model_fields", {})
                if not model and "model" in fields:   # the depth node's default model
                    model = fields["model"].default
                if model:
                    return Path(str(model)).name, depth
    return sensor, depth


def run_press_calibration(graph: str, *, sets: list[str] | None = None, clock: str | None = None,
                          duration: float | None = None, progress: bool = True,
                          registry: Any = None) -> tuple[Any, PressRoutine, Any]:
    """Run a press-routine graph; returns (run result, the routine component, the graph spec)."""
    from teletouch.graph import load_graph
    from teletouch.runtime import Runtime

    spec = load_graph(graph, sets=sets or [], clock=clock, duration=duration, registry=registry)
    ids = [n.id for n in spec.nodes if n.cls is not None and issubclass(n.cls, PressRoutine)]
    if len(ids) != 1:
        raise CalibrationError(f"{graph}: the graph needs exactly one press-routine node, found {len(ids)}")
    if spec.clock == "sim" and spec.duration is None:
        spec.duration = 3600.0
    rt = Runtime(spec)
    bar = None
    cb = None
    if progress:
        comp = rt.component(ids[0])
        if sys.stderr.isatty():
            from tqdm import tqdm

            bar = tqdm(total=comp.total_points, desc="press calibration", unit="step", file=sys.stderr)
        seen = [0]

        def cb(runtime: Any, t: float) -> None:
            n = len(comp.samples)
            if bar is not None:
                bar.n = n
                bar.set_postfix_str(f"t={t:.1f}s {comp.state}, cycle {comp.cycle + 1}/{comp.params.cycles}")
                bar.refresh()
                return
            for s in comp.samples[seen[0]:n]:  # not a terminal: one line per recorded step
                print(f"[{100 * comp.progress:5.1f}%] t={t:7.1f}s cycle {s['cycle'] + 1} {s['phase']:<9} "
                      f"displacement {s['displacement_m'] * 1e3:6.3f} mm  depth {s['depth_m'] * 1e3:6.3f} mm  "
                      f"force {s['force_n']:6.3f} N", file=sys.stderr, flush=True)
            seen[0] = n

    try:
        result = rt.run(spec.duration, progress=cb, progress_interval=0.5)
    finally:
        if cb is not None:
            cb(rt, rt.now())
        if bar is not None:
            bar.close()
    return result, rt.component(ids[0]), spec


#: how the command's errors and warnings start, as `teletouch calibrate depth: error:` (before, `teletouch: error:`)
PREFIX = "teletouch calibrate force"


def _cmd_calibrate_force(args: argparse.Namespace) -> int:
    """`teletouch calibrate force`: its refusals (a fit refused, a graph without a press routine, an output that could
    not be written) under the command's own prefix; a graph's validation report as `teletouch run` gives it."""
    from teletouch.errors import GraphValidationError, TeletouchError
    from teletouch.runtime import EXIT_INVALID

    try:
        return _calibrate_force(args)
    except GraphValidationError:
        raise
    except TeletouchError as exc:
        print(f"{PREFIX}: error: {exc}", file=sys.stderr)
        return EXIT_INVALID
    except BrokenPipeError:
        raise
    except OSError as exc:   # a calibration or plot that could not be written after all (a full disk)
        names = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        print(f"{PREFIX}: error: {exc.strerror or exc}{': ' + names if names else ''}", file=sys.stderr)
        return EXIT_INVALID


def _calibrate_force(args: argparse.Namespace) -> int:
    from teletouch.units import parse_quantity

    def usage(msg: str) -> int:
        print(f"{PREFIX}: error: {msg}", file=sys.stderr)
        return 2

    try:
        min_depth = parse_quantity(args.min_depth, "m")
        if not min_depth >= 0:
            raise ValueError(f"expected a depth of at least 0, got {args.min_depth!r}")
    except ValueError as exc:
        return usage(f"--min-depth: {exc}")
    if min_depth >= MAX_DEPTH_M:   # no gel is pressed that deep: every sample would be no contact, after the press run
        return usage(f"--min-depth {args.min_depth} (read as {min_depth:g} m): samples shallower than "
                     f"{min_depth * 1e3:g} mm would all be left out as no contact (no gel is pressed "
                     f"{MAX_DEPTH_M * 1e3:g} mm deep or more; the default is 0.03mm){bare_metres_hint(args.min_depth)}")
    min_r2 = args.min_r2
    if not 0.0 <= min_r2 < 1.0:   # argparse gave a float (NaN fails this too)
        return usage(f"--min-r2: expected an R^2 from 0 (no limit) to below 1, got {min_r2!r}")
    # the fit's own limits, checked before a press run that a refused degree would waste
    if not 1 <= args.degree <= MAX_DEGREE:
        return usage(f"--degree: expected an integer from 1 to {MAX_DEGREE}, got {args.degree}")
    if not 0 <= args.position_degree <= MAX_POSITION_DEGREE:
        return usage(f"--position-degree: expected an integer from 0 (none) to {MAX_POSITION_DEGREE}, got "
                     f"{args.position_degree}")
    try:
        source_date_epoch()   # a malformed SOURCE_DATE_EPOCH is refused before the press run, not at the write
    except ValueError as exc:
        return usage(str(exc))
    duration = None
    ended = None   # the result of a press run that did not end ok after its routine had finished
    if args.csv:
        graph_only = [opt for opt, given in (("--duration", args.duration is not None), ("--set", args.sets),
                                             ("--clock", args.clock is not None),
                                             ("--samples", args.samples is not None)) if given]
        if graph_only:
            return usage(f"{', '.join(graph_only)}: only with --graph (a press run); --csv fits the pairs of the "
                         f"file as they are")
    elif args.allow_partial:
        return usage("--allow-partial: only with --csv (a press run that does not finish writes no calibration)")
    elif args.duration is not None:
        try:
            duration = parse_quantity(args.duration, "s")
            if not duration > 0:
                raise ValueError(f"expected a positive duration, got {args.duration!r}")
        except ValueError as exc:
            return usage(f"--duration: {exc}")
    # the outputs are checked before the fit and the press run, which are lost if they cannot be written after
    out = Path(args.output)
    plot = Path(args.plot) if args.plot else out.with_name(_stem(out) + ".png")
    samples_path = Path(args.samples) if args.samples else out.with_name(_stem(out) + ".samples.csv")
    # the raw strings where given: Path drops a trailing separator ("-o models/" would write a file named models)
    outputs = [("-o", out, args.output), ("--plot", plot, args.plot or plot)]
    if not args.csv:
        outputs.append(("--samples", samples_path, args.samples or samples_path))
    for opt, path, given in outputs:
        problem = output_problem(given)
        if problem:
            return usage(f"{opt}: cannot write {str(path)!r}: {problem}")
    # two outputs on one path overwrote each other (the PNG over the calibration, exit 0); a plot in a format
    # matplotlib cannot write failed after the fit (a traceback) or after the whole press run
    seen: dict[Path, str] = {}
    for opt, path, _ in outputs:
        first = seen.setdefault(path.expanduser().resolve(), opt)
        if first != opt:
            return usage(f"{opt}: {str(path)!r} is also {first}'s file: give each output a path of its own")
    if plot.suffix.lower() not in PLOT_SUFFIXES:
        return usage(f"--plot: {str(plot)!r}: expected an image file ({', '.join(PLOT_SUFFIXES)}), not "
                     f"{plot.suffix or 'a name without a suffix'}")
    if args.csv:
        try:
            data = read_pairs_csv(args.csv)
        except PairsFileError as exc:   # missing, a folder, unreadable: the path given is wrong (as calibrate depth)
            return usage(f"--csv: {exc}")
        partial = data.get("partial")
        if partial and not args.allow_partial:
            raise CalibrationError(f"{args.csv}: partial samples ({partial}): {_partial_harm(partial)}; rerun the "
                                   f"calibration, or pass --allow-partial to fit them anyway")
        if partial:
            print(f"{PREFIX}: warning: {args.csv}: fitting partial samples ({partial}) as --allow-partial asks",
                  file=sys.stderr)
        samples = [{"depth_m": float(d), "force_n": float(f), "line": data["line"][i],
                    "column": data["force_column"],
                    "phase": (data["phase"][i] if data["phase"] else ""),
                    "cycle": (data["cycle"][i] if data["cycle"] else 0),
                    "x_m": (data["x_m"][i] if data["x_m"] is not None else None),
                    "y_m": (data["y_m"][i] if data["y_m"] is not None else None)}
                   for i, (d, f) in enumerate(zip(data["depth_m"], data["force_n"]))]
        cal = fit_samples(samples, args.degree, min_depth=min_depth, use=args.use,
                          position_degree=args.position_degree,
                          zero_intercept=args.zero_intercept,
                          sensor_model_id=args.sensor_model_id or data.get("sensor_model_id") or "",
                          depth_source="csv", source=f"csv:{Path(args.csv).name}", min_r2=min_r2, where=args.csv,
                          min_depth_option=args.min_depth)
        if partial:
            cal.extra["partial"] = partial   # recorded in the calibration file
    else:
        result, routine, spec = run_press_calibration(args.graph, sets=args.sets, clock=args.clock,
                                                      duration=duration, progress=not args.quiet)
        spoiled = _spoiled_samples(result, routine, spec) if routine.state == "done" else None
        model_id, depth_src = _sensor_model_id(spec)
        if routine.samples:
            partial = routine.partial_reason() or spoiled
            write_pairs_csv(samples_path, routine.samples, partial=partial,
                            sensor_model_id=args.sensor_model_id or model_id)
            print(f"wrote {len(routine.samples)} samples to {samples_path}"
                  + (f" (marked partial: {'a fault may have spoiled them' if spoiled else 'the run did not finish'})"
                     if partial else ""), file=sys.stderr)
        if spoiled:
            _mark_own_samples(routine, spoiled)
        if routine.state != "done":
            why = routine.abort_reason or result.message
            run = why if result.status == "interrupted" else f"run {result.status}: {why}"   # (says it already)
            print(f"teletouch: press routine did not finish (routine state {routine.state!r}, {run}); no calibration "
                  f"written", file=sys.stderr)
            return result.exit_code or 3
        for f in result.faults:   # each, as `teletouch run`'s summary lists them (the fit below may still refuse)
            print(f"teletouch: fault: {f.line()} -> {f.action}", file=sys.stderr)
        if spoiled:
            print(f"teletouch: {result.ending}; {spoiled}; no calibration written", file=sys.stderr)
            return result.exit_code or 3
        if result.exit_code:   # interrupted (held as the run stopped), degraded, fault: the calibration is complete,
            ended = result     # still written, and the command exits as `teletouch run` does for that run
        try:
            cal = fit_samples(routine.samples, args.degree, min_depth=min_depth, use=args.use,
                              position_degree=args.position_degree,
                              zero_intercept=args.zero_intercept, sensor_model_id=args.sensor_model_id or model_id,
                              depth_source=depth_src, source=f"press-routine:{Path(args.graph).name}",
                              min_r2=min_r2, min_depth_option=args.min_depth)
        except CalibrationError as exc:
            if ended is None:
                raise
            # the fit refused the samples of a run a signal (or a fault) ended: the run's exit code, as below, not the
            # fit's (a Ctrl-C said 130 only when the fit succeeded); the samples file is written for --csv
            print(f"{PREFIX}: error: {exc}", file=sys.stderr)
            print(f"teletouch: {ended.ending}; the press routine had finished but its samples gave no calibration: "
                  f"none written", file=sys.stderr)
            return ended.exit_code
    cal.save(out)
    cal.save_plot(plot)
    print(cal.summary())
    print(f"wrote {out} and {plot}")
    if ended is not None:   # the run's exit code, as `teletouch run` gives it (3; a signal: 130, 143 for SIGTERM)
        faulted = any(f.action != "logged" for f in ended.faults)
        print(f"teletouch: {ended.ending}; the press routine had finished"
              f"{' and no fault reached its samples' if faulted else ''}: its calibration is written", file=sys.stderr)
        return ended.exit_code
    return 0


#: the file types the calibration's plot is written in (matplotlib's raster and vector formats a person opens)
PLOT_SUFFIXES = (".png", ".svg", ".pdf", ".jpg", ".jpeg")


#: how :func:`_spoiled_samples`'s reason ends (so `--csv` tells a stale-sample file from an unfinished run's)
STALE_SAMPLES = "they may hold stale values"


def _spoiled_samples(result: Any, routine: PressRoutine, spec: Any) -> str | None:
    """Why samples of a finished press run may be stale, or None. A node that feeds the routine (directly or through
    other nodes) and was disabled by a fault (stop or degrade) publishes nothing more, and a filter in between steps
    on with fresh stamps on a stale value. The routine aborts on such a fault itself
    (:meth:`PressRoutine._feeders_lost`, at each step and before each sample), but not on one it cannot have seen when
    it stored a sample: a fault in another rate group at that instant (the wall clock), or of a node behind a feedback
    edge that steps after it at the same tick; the fault's time is its step's start, so a sample stored from then on
    may hold stale values. This check after the run is the second guard. A fault logged at the shutdown, after the
    samples, or of a node the routine does not read cannot reach them."""
    feeding = set(feeders(spec).get(routine.id, ()))
    hits = [(f, sum(1 for s in routine.samples if s["time_s"] >= f.time)) for f in result.faults
            if f.action != "logged" and f.node in feeding]
    hits = [(f, n) for f, n in hits if n]
    if not hits:
        return None
    f, n = min(hits, key=lambda hit: hit[0].time)
    return (f"node '{f.node}' ({f.kind} at t={f.time:.3f} s) feeds the press routine and was disabled before {n} of "
            f"its {len(routine.samples)} samples were recorded: {STALE_SAMPLES}")


def _mark_own_samples(routine: PressRoutine, spoiled: str) -> None:
    """The routine's own ``samples_csv``, which it wrote unmarked as it finished (a fault upstream that it could not
    see at its step: see :func:`_spoiled_samples`), written again marked partial with why its samples may be stale, as
    the command's are."""
    own = routine.params.samples_csv
    if not own or not routine._samples_written:
        return
    try:
        write_pairs_csv(own, routine.samples, partial=spoiled)
    except OSError as exc:
        print(f"{PREFIX}: warning: {own}: could not mark the routine's samples_csv partial ({exc}): its samples may "
              f"hold stale values", file=sys.stderr)
        return
    print(f"marked the routine's samples_csv {own} partial too (a fault may have spoiled its samples)", file=sys.stderr)


def _partial_harm(partial: str) -> str:
    """What a fit of samples marked partial with ``partial`` (a ``# partial:`` line's reason) would get wrong."""
    if partial.endswith(STALE_SAMPLES):   # a finished run's samples that a fault upstream may have spoiled
        return "a fit of them may not be the sensor's force curve"
    return ("a run that did not finish may lack the deeper steps, the unloading or the other press points, so the fit "
            "would not cover the range it claims")


def _stem(p: Path) -> str:
    name = p.name
    for suf in (".force.json", ".json"):
        if name.endswith(suf):
            return name[: -len(suf)]
    return p.stem


@hookimpl
def teletouch_components():
    return [PressRoutine, SimPressRig]


@hookimpl
def teletouch_add_commands(calibrate: Any) -> None:
    from teletouch.graph import set_argument   # a malformed --set is a usage error, as for `teletouch run`

    p = calibrate.add_parser("force", help="force calibration: run a press routine graph, or fit a CSV of "
                                           "(depth, force) pairs",
                             description="Fit max depth (m) -> force (N) with a least-squares polynomial. "
                                         "Either run a graph with a press-routine node (the leader presses a "
                                         "probe into the gel in steps) or fit an existing CSV.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--graph", help="graph with a press-routine node (e.g. examples/calibrate-force-sim.yaml)")
    src.add_argument("--csv", help="CSV with a header: one depth column (depth_m or depth_mm), one force column "
                                   "(force_n), optional phase, cycle, x_m, y_m (contact centroid); see docs/force.md")
    p.add_argument("-o", "--output", default="force-calibration.force.json", help="calibration file to write")
    p.add_argument("--plot", default=None, help="PNG to write (default: beside the output)")
    p.add_argument("--samples", default=None, help="CSV of the recorded samples (default: beside the output)")
    p.add_argument("--degree", type=int, default=3, help="polynomial degree (default 3)")
    p.add_argument("--use", choices=("all", "loading", "unloading"), default="all",
                   help="which samples make the fit (the other phase still gives the hysteresis gap)")
    p.add_argument("--zero-intercept", action="store_true", help="force F(0) = 0")
    p.add_argument("--position-degree", type=int, default=0, metavar="P",
                   help="also fit how the curve varies with the contact centroid (2-D polynomial of degree P over "
                        "the area the presses cover; needs presses across the sensor and the centroid: the "
                        "routine's 'centroid' input or x_m, y_m CSV columns). Default 0: the paper's single curve")
    p.add_argument("--allow-partial", action="store_true", help="with --csv: fit samples marked partial (a press "
                   "run that did not finish, or whose samples a fault may have spoiled) instead of refusing them; the "
                   "file records it (extra.partial)")
    p.add_argument("--min-depth", default="0.03mm", metavar="DEPTH",
                   help="samples with a max depth below this are no contact (left out); a depth with its unit, e.g. "
                        "0.03mm (a bare number is metres; default %(default)s)")
    p.add_argument("--min-r2", type=float, default=DEFAULT_MIN_R2, metavar="R2",
                   help=f"refuse (and write nothing for) a fit whose R^2 is below this (default {DEFAULT_MIN_R2:g}; "
                        f"0: no limit)")
    p.add_argument("--sensor-model-id", default=None, help="recorded in the file (default: the depth model)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="NODE.FIELD=VALUE", type=set_argument,
                   help="override a graph parameter (repeatable)")
    p.add_argument("--clock", choices=("sim", "wall"), default=None, help="override the graph's clock")
    p.add_argument("--duration", default=None, help="longest run (s); default: the graph's, or 1 h simulated")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_calibrate_force)
