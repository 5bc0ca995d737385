"""Bilateral teleoperation controllers for a gripper: position-force (the paper's), position-position, no-feedback.

All three have the ports of docs/ports.md (Controller):

- in  ``leader_opening`` (m), optional ``leader_velocity`` (m/s), optional ``follower_opening`` (m), ``force`` (N,
  sensed, e.g. poly-force at 30-60 Hz);
- out ``opening_command`` (m, to the follower), ``gripper_force`` (N, to the leader, positive pushes the operator's
  fingers apart), ``energy`` (J, passivity observer), and ``damping`` (N*s/m, what the passivity controller added).

Every input is taken in stamp order: a sample stamped before the newest fresh one already taken (out of order) is
ignored, so an older measurement never replaces a newer one. A sample is fresh while it is at most its input's
``stale_after`` (``leader_stale_after``) old and at most ``max_clock_skew`` (50 ms, never more than that stale_after)
ahead of the graph clock: a stamp further ahead is a clock fault (clocks that disagree), not a fresh sample: it is not
used, counted (``future_stamps``, ``invalid_inputs``) and named in the fault of a loss that lasts. An opening
(leader or follower) that is not finite or beyond 1 m either way (``MAX_PLAUSIBLE_OPENING``: no gripper opens wider)
is invalid input, like NaN: counted, never differentiated into a velocity. A bad sample is counted once, not on
every step while it stays the latest. No velocity is differentiated across a gap of more than ``leader_stale_after``
between two openings (a loss): the estimate restarts at zero.

The control law of ``position-force`` (each step, at 1 kHz as the leader; see 4 for a lower rate):

1. follower:  ``x_fd = clip(scale * x_l + offset, opening_min, opening_max)``; a missing, stale or non-finite leader
   opening holds the last command (the follower keeps its position); a jump of the leader is passed on (every
   follower driver limits its speed to its ``max_speed``); while the force estimate is lost (stale or not finite,
   see 2; not while waiting for the first one) the command holds (``hold_on_lost_force``): the operator, who no
   longer feels the object, cannot make the follower squeeze it; when a fresh estimate returns the command moves
   from the held value to the mapped opening at no more than ``resume_speed``, never a jump;
2. force: every new force sample ``f_s`` is shaped, ``f = min(k_f * deadband(f_s), max_force)`` (positive: it
   pushes the operator's fingers apart), and the
   output ramps linearly from its present value to ``f`` over ``smoothing_time`` (a first-order hold: the hand never
   sees the camera-rate staircase). In contact (``force_prediction``, on by default) a local contact model bridges
   the estimate's latency: ``+ k_f * K * (x_cmd(capture) - x_cmd(now))``, with ``K = -dF/dx_cmd`` learnt from
   successive estimates and the follower commands at their capture times (never past zero, never beyond
   ``max_force``; blended in and out over ``smoothing_time``; forgotten when the contact ends); without it the
   rendered force is a delayed spring, an active element that makes stiff contacts oscillate. A force older than
   ``stale_after`` or non-finite fades linearly to zero over ``fade_time``, and meanwhile never raises the force
   (a lost leader that comes back during the fade does not bring the stale force back);
3. passivity (on by default): the time-domain passivity observer over the leader and follower ports (two-port:
   the follower's opening at each estimate's capture time); when the observed energy
   would go negative, damping ``-alpha * v_l`` (``alpha`` at most what the constant damping leaves of
   ``max_damping``, Omega.7: 40 N*s/m) and a cut of the
   feedback force towards zero for what the damping cannot dissipate; never a reversal of the contact force, nothing
   in free space (see passivity.py); when a lost leader comes back the observer starts afresh (energy and damping
   zero);
4. safety: the total leader force is rate-limited (``max_force_rate``; a lost leader fades it out over
   ``fade_time``, within that limit), clipped to ``+-max_force``; a non-finite desired force is taken as 0 (reached
   within the rate limit, not in one step): nothing but a finite force within limits ever leaves the controller.
   The leader holds each command, so one step's change reaches the hand at once: below 1 kHz one step changes the
   force by at most ``max_force_rate`` x 1 ms (``LEADER_PERIOD``), so the force follows more slowly (logged at
   configure), never in steps of ``max_force_rate`` x the period; a fade (the leader or the estimate lost) eases
   towards 0 at the rate limit alone, so it still ends within ``fade_time``;
5. a loss that lasts is a fault: a leader opening (once received) or, for position-force, a force estimate lost
   continuously for longer than ``fault_after_lost`` (0.5 s; at least ``fade_time``, so the force has faded out)
   makes step() raise ComponentFault naming what was lost and for how long (and the input: the runtime adds which
   node and port feed it); the runtime then drives the devices to their safe states (zero leader force, the follower
   holds). Invalid (not finite) estimates are counted (``invalid_forces`` in status() and results(); the first is
   logged); since each good estimate ends a loss, a good one that comes when at least ``max_invalid_force_share`` of
   the last ``INVALID_FORCE_WINDOW`` estimates were invalid, in at least ``MIN_INVALID_FORCE_DIPS`` separate runs (a
   single burst is a loss, fault_after_lost's), is a ComponentFault too.

``position-position`` replaces step 2 by a PD on the position error,
``f = kp * (x_f' - x_l) + kd * (v_f' - v_l)`` (``x_f'`` the follower opening mapped back to the leader's scale), the
follower side being the follower's own position servo; a lost follower opening fades it out over ``fade_time``
(never raising it meanwhile).
``no-feedback`` sends no force at all.
The pure functions here are tested without the runtime; the components are thin wrappers around them.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from teletouch import Component, ComponentFault, Kind, Params, Port, Sample, hookimpl
from teletouch.errors import value_text
from teletouch.units import (
    MAX_PLAUSIBLE_HAND_FORCE, MAX_PLAUSIBLE_OPENING, MAX_PLAUSIBLE_SPEED, Meters, NewtonSecondsPerMeter, Newtons,
    NewtonsPerMeter, Seconds, millimetres_in_metres, plausible_depth, plausible_hand_force, plausible_opening,
    plausible_quantity, plausible_speed,
)

from .passivity import (
    FollowerPort, PassivityState, adapt_gain, commit, observe, opposite_signs, passivity_force, reduce_force_to,
    same_sign,
)

__all__ = [
    "millimetres_in_metres", "map_opening", "unmap_opening", "deadband", "shape_force", "saturate", "rate_limit",
    "finite_or", "opening_or_nan", "no_rise", "ForceHold", "Differentiator", "PositionForce", "PositionPosition",
    "NoFeedback",
]

OMEGA7_MAX_GRIPPER_FORCE = 8.0     # N (CHAI3D's device table)
OMEGA7_MAX_DAMPING = 40.0          # N*s/m
#: a glitch filter on the leader's opening speed wider than this passes anything (a quick pinch: well below 1 m/s):
#: a larger max_leader_velocity is mm/s typed in the m/s field (2000 meant 2000 mm/s)
MAX_LEADER_VELOCITY_LIMIT = 100.0  # m/s
#: no tactile sensor reads grip forces so large that a deadband this wide leaves any to render (the packaged
#: calibration: 8.6 N at most): a wider deadband is mN typed in the N field (20 meant 20 mN)
MAX_PLAUSIBLE_DEADBAND = 10.0      # N
#: the period of a 1 kHz haptic leader (the Omega.7's loop): a leader holds each force command until the next one, so
#: what one controller step changes reaches the hand at once, within one leader period; below 1 kHz one step changes
#: the force by at most max_force_rate x this (see _Bilateral._reset)
LEADER_PERIOD = 1e-3               # s
#: no rate limit of the leader force is set higher than this (the default: 200 N/s): a haptic device's whole +-50 N
#: swing (MAX_PLAUSIBLE_HAND_FORCE; the Omega.7's gripper: +-8 N) in one 1 ms leader period, beyond which the limit
#: limits nothing (as the press routine's max_force_rate); a higher one is mN/s typed in the N/s field
MAX_PLAUSIBLE_FORCE_RATE = 2 * MAX_PLAUSIBLE_HAND_FORCE / LEADER_PERIOD   # N/s: 100 kN/s
#: the longest fade_time: a lost source's force stays on the hand while it fades (as stale_after's 1 s)
MAX_FADE_TIME = 1.0                # s
#: the longest smoothing_time: a few frames of the slowest estimator (the default: one frame at 60 Hz); every change of
#: the estimate, a release too, reaches the hand this late
MAX_SMOOTHING_TIME = 0.25          # s
#: the longest fault_after_lost: a loss longer than this is a fault, not a hiccup (a sensor's reconnect); the follower
#: holds and the operator feels nothing meanwhile
MAX_FAULT_AFTER_LOST = 10.0        # s
#: how many of the latest force estimates position-force's max_invalid_force_share looks at (1 s at 60 Hz)
INVALID_FORCE_WINDOW = 60
#: the separate runs of invalid estimates in that window the share fault needs: a single burst is a loss that ended
MIN_INVALID_FORCE_DIPS = 5


# ------------------------------------------------------------------------------------------------ pure functions
def map_opening(x_leader: float, scale: float, offset: float, lo: float, hi: float) -> float:
    """Follower opening command (m) for a leader opening (m): ``clip(scale * x + offset, lo, hi)``."""
    x = scale * x_leader + offset
    return lo if x < lo else hi if x > hi else x


def unmap_opening(x_follower: float, scale: float, offset: float) -> float:
    """The follower opening expressed on the leader's scale (inverse of :func:`map_opening` without limits)."""
    return (x_follower - offset) / scale


def deadband(f: float, width: float) -> float:
    """Continuous deadband on a normal force: 0 below ``width``, ``f - width`` above (no step at the edge).
    A negative sensed normal force is not physical and is taken as 0."""
    return f - width if f > width else 0.0


def saturate(f: float, limit: float) -> float:
    """Clip to ``[-limit, limit]``."""
    return -limit if f < -limit else limit if f > limit else f


def shape_force(f_sensed: float, gain: float, sign: int, width: float, limit: float) -> float:
    """Leader force (N) for a sensed force (N): sign * min(gain * deadband(f), limit); non-finite gives 0."""
    if not math.isfinite(f_sensed):
        return 0.0
    return sign * min(gain * deadband(f_sensed, width), limit)


def rate_limit(previous: float, target: float, max_rate: float, dt: float, max_step: float = math.inf) -> float:
    """Move from ``previous`` towards ``target`` by at most ``max_rate * dt``, and at most ``max_step``."""
    step = min(max_rate * dt, max_step)
    d = target - previous
    if d > step:
        return previous + step
    if d < -step:
        return previous - step
    return target


@dataclass
class RunFigures:
    """What a bilateral controller's run achieved, summed step by step (:meth:`_Bilateral.results`)."""

    peak_force: float = 0.0        # N, the sensed force
    peak_feedback: float = 0.0     # N, |the force rendered to the leader|
    contact_time: float = 0.0      # s with a sensed force above zero
    error_sum: float = 0.0         # m x steps, |follower - its target|
    error_max: float = 0.0
    error_steps: int = 0
    sensed_steps: int = 0          # steps with a fresh sensed force

    def add(self, dt: float, sensed: float, feedback: float, target: float, follower: float) -> None:
        """One step: ``dt`` (s) since the last, the sensed force and the feedback force (N), the follower's target
        and its opening (m; NaN where one is not known)."""
        if math.isfinite(sensed):
            self.sensed_steps += 1
            self.peak_force = max(self.peak_force, sensed)
            if sensed > 0.0:
                self.contact_time += dt
        if math.isfinite(feedback):
            self.peak_feedback = max(self.peak_feedback, abs(feedback))
        e = abs(follower - target)
        if math.isfinite(e):
            self.error_sum += e
            self.error_max = max(self.error_max, e)
            self.error_steps += 1

    def results(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.sensed_steps:
            out["peak_force_n"] = self.peak_force
        out["peak_feedback_n"] = self.peak_feedback
        if self.sensed_steps:
            out["contact_time_s"] = self.contact_time
        if self.error_steps:
            out["mean_position_error_m"] = self.error_sum / self.error_steps
            out["max_position_error_m"] = self.error_max
        return out


def finite_or(x: Any, default: float) -> float:
    """``float(x)`` if it is a finite number, else ``default`` (also for an int too large for a float: a float64 port
    takes any int, and ``float(10**400)`` raises OverflowError)."""
    try:
        v = float(x)
    except (TypeError, ValueError, OverflowError):
        return default
    return v if math.isfinite(v) else default


def opening_or_nan(x: Any) -> float:
    """``float(x)`` if it is a plausible gripper opening (finite, at most MAX_PLAUSIBLE_OPENING = 1 m either way),
    else NaN: an opening of 1e30 m is no measurement, and differentiated it gave a velocity that the damping and
    the passivity observer took as real (position-position's coupling overflowed to NaN)."""
    v = finite_or(x, math.nan)
    return v if abs(v) <= MAX_PLAUSIBLE_OPENING else math.nan


def no_rise(f: float, last: float) -> float:
    """``f`` limited so that it moves ``last`` only towards zero: never a larger magnitude, never across zero.
    Applied to a feedback force whose source is stale (fading): stale data never pushes the hand harder."""
    if last >= 0.0:
        return 0.0 if f < 0.0 else min(f, last)
    return 0.0 if f > 0.0 else max(f, last)


class ForceHold:
    """Hold + smooth a slow force estimate for a fast loop: linear ramps from the present value to each new target.

    ``set(t, target, duration)`` starts a ramp; ``value(t)`` reads it. A ramp restarts from wherever the output is,
    so the output is continuous whatever arrives (never a jump in the operator's hand).
    """

    __slots__ = ("v0", "v1", "t0", "duration")

    def __init__(self, value: float = 0.0):
        self.v0 = self.v1 = value
        self.t0 = 0.0
        self.duration = 0.0

    def value(self, t: float) -> float:
        if self.duration <= 0.0 or t >= self.t0 + self.duration:
            return self.v1
        if t <= self.t0:
            return self.v0
        return self.v0 + (self.v1 - self.v0) * (t - self.t0) / self.duration

    def set(self, t: float, target: float, duration: float) -> None:
        self.v0 = self.value(t)
        self.v1 = target
        self.t0 = t
        self.duration = duration

    @property
    def target(self) -> float:
        return self.v1


class Differentiator:
    """d/dt of a sampled signal with a first-order low-pass (cutoff ``hz``); robust to repeated or missing samples.

    Two samples more than ``max_gap`` s apart have a loss between them (the signal was stale): no velocity is
    derived across it, the estimate restarts from the new sample at zero velocity, as at the first one (the gap's
    average velocity met a hand at rest as a damping kick and an energy deficit it never caused). A shorter gap, a
    missed sample or a few, is differentiated across (its average is the motion)."""

    __slots__ = ("tau", "max_gap", "x", "t", "v")

    def __init__(self, hz: float, max_gap: float = math.inf):
        self.tau = 1.0 / (2.0 * math.pi * hz)
        self.max_gap = max_gap
        self.x: float | None = None
        self.t: float | None = None
        self.v = 0.0

    def update(self, t: float, x: float) -> float:
        if not (math.isfinite(t) and math.isfinite(x)):
            return self.v                      # a bad sample is skipped, never taken into the state
        if self.x is None or self.t is None:
            self.x, self.t = x, t
            return self.v
        dt = t - self.t
        if dt <= 0.0:
            return self.v
        if dt > self.max_gap:                  # a loss in between: restart here (no velocity across the gap)
            self.x, self.t, self.v = x, t, 0.0
            return self.v
        raw = (x - self.x) / dt
        a = dt / (self.tau + dt)
        v = self.v + a * (raw - self.v)
        self.v = v if math.isfinite(v) else 0.0
        self.x, self.t = x, t
        return self.v

    def reset(self) -> None:
        self.x = self.t = None
        self.v = 0.0


# ------------------------------------------------------------------------------------------------ components
_IN = {
    "leader_opening": Port("float64", (), "m", "leader gripper opening", required=True),
    "leader_velocity": Port("float64", (), "m/s", "leader gripper velocity (differentiated if not wired)",
                            required=False),
    "follower_opening": Port("float64", (), "m", "follower opening (the status, the two-port passivity "
                             "observer, and position-position)", required=False),
    "force": Port("float64", (), "N", "sensed grip force (camera rate)", required=True),
}
_OUT = {
    "opening_command": Port("float64", (), "m", "follower opening command"),
    "gripper_force": Port("float64", (), "N", "leader gripper force; positive pushes the fingers apart"),
    "energy": Port("float64", (), "J", "passivity observer: energy the operator put into the teleoperator"),
    "damping": Port("float64", (), "N*s/m", "damping injected by the passivity controller"),
}


class _CommonParams(Params):
    scale: float = Field(1.0, gt=0, description="follower opening per leader opening (position scale)")
    offset: Meters = Field(0.0, description="added to the scaled leader opening", json_schema_extra={"unit": "m"})
    opening_min: Meters = Field(0.0, ge=0, description="smallest follower command", json_schema_extra={"unit": "m"})
    opening_max: Meters = Field(0.09, gt=0, description="largest follower command (PAL gripper: 0.09 m)",
                                json_schema_extra={"unit": "m"})
    max_force: Newtons = Field(OMEGA7_MAX_GRIPPER_FORCE, gt=0,
                               description="limit of the leader force (Omega.7 gripper: 8 N)",
                               json_schema_extra={"unit": "N"})
    max_force_rate: float = Field(200.0, gt=0, description="rate limit of the leader force (at most 100000 N/s, a "
                                  "haptic device's whole +-50 N in 1 ms: a higher one limits nothing, mN/s typed in "
                                  "the N/s field); below 1 kHz one step changes the force by at most this x 1 ms "
                                  "(a leader period)", json_schema_extra={"unit": "N/s"})
    leader_stale_after: Seconds = Field(0.05, gt=0, le=1.0, description="a leader opening older than this holds the "
                                        "follower and fades the force (at most 1 s: the force of a dead leader "
                                        "stayed on the hand that long; 100 meant as ms was 100 s)",
                                        json_schema_extra={"unit": "s"})
    fade_time: Seconds = Field(0.2, gt=0, le=MAX_FADE_TIME, description="time to fade the force to zero when its "
                               "source is lost (at most 1 s, as stale_after: the lost source's force stays on the "
                               "hand while it fades; 200 meant as ms was 200 s)", json_schema_extra={"unit": "s"})
    max_clock_skew: Seconds = Field(0.05, ge=0, description="an input stamped further ahead of the graph clock "
                                    "(never more than its stale_after) is a clock fault, not a fresh sample: not "
                                    "used, counted; as the ROS 2 subscriber's and poly-force's max_clock_skew",
                                    json_schema_extra={"unit": "s"})
    fault_after_lost: Seconds | None = Field(0.5, gt=0, le=MAX_FAULT_AFTER_LOST,
                                             description="a leader opening (stale or not finite) or, for "
                                             "position-force, a force estimate (stale or not finite) lost for "
                                             "longer than this is a fault: step() raises and the runtime drives the "
                                             "devices to their safe states (null: never, the force still fades out "
                                             "over fade_time; at least fade_time, so the force has faded out by "
                                             "then; at most 10 s: the follower holds and the operator feels nothing "
                                             "meanwhile, 500 meant as ms was 500 s)",
                                             json_schema_extra={"unit": "s"})
    passivity: bool = Field(True, description="time-domain passivity controller on the leader port (the observer "
                            "always runs and feeds the energy output)")
    passivity_controller: Literal["force", "damping"] = Field(
        "force", description="force: damping -alpha*v (alpha <= max_damping) and a cut of the feedback force towards "
        "zero for what the damping leaves, never a reversal, nothing in free space; damping: the classic TDPA "
        "(damping alone; it drags the hand in free space and pulls opening fingers)")
    passivity_observer: Literal["two-port", "leader-port"] = Field(
        "two-port", description="two-port: leader port + follower port (the sensed force and the follower "
        "opening at its capture time), so the environment's stored energy is not the teleoperator's; "
        "leader-port: the leader port only (the environment inside the observed one-port)")
    passivity_no_reversal: bool = Field(True, description="passivity_controller force: the damping never turns "
                                        "the feedback force round (no pull where the contact pushes)")
    max_damping: NewtonSecondsPerMeter = Field(OMEGA7_MAX_DAMPING, ge=0,
                                               description="the most damping the leader renders stably (Omega.7: "
                                               "40 N*s/m): the constant damping (leader_damping, and "
                                               "position-position's kd) and the passivity damping together",
                                               json_schema_extra={"unit": "N*s/m"})
    energy_leak_time: Seconds | None = Field(1.0, gt=0, description="time constant of the decay of stored "
                                             "(positive) observed energy; null: no leak",
                                             json_schema_extra={"unit": "s"})
    velocity_cutoff: float = Field(50.0, gt=0, description="low-pass of differentiated velocities",
                                   json_schema_extra={"unit": "Hz"})
    max_leader_velocity: float = Field(2.0, gt=0, description="a leader_velocity sample faster than this is taken "
                                       "as invalid (counted; the differentiated opening is used instead): one "
                                       "glitch would otherwise fill the passivity observer with a deficit that no "
                                       "contact pays back", json_schema_extra={"unit": "m/s"})
    leader_damping: NewtonSecondsPerMeter = Field(0.0, ge=0, description="constant damping rendered on the leader "
                                                  "(passive; helps the slow force loop)",
                                                  json_schema_extra={"unit": "N*s/m"})
    free_space_reset: Seconds | None = Field(0.2, gt=0, description="while no force is exchanged an energy "
                                             "deficit is forgiven with this time constant (null: never)",
                                             json_schema_extra={"unit": "s"})
    passivity_force_reduction: bool = Field(False, description="passivity_controller damping: when max_damping is "
                                            "not enough, also cut the rendered force towards zero within the step "
                                            "(the force controller always does)")
    passivity_gain_adaptation: bool = Field(False, description="while the passivity controller has to cut the "
                                            "force (or a deficit beyond gain_adaptation_margin remains), lower the "
                                            "scale of the rendered force smoothly (gain_drop_rate, down to gain_min) "
                                            "and restore it afterwards (gain_recover_time)")
    gain_drop_rate: float = Field(5.0, gt=0, description="passivity_gain_adaptation: drop of the force scale per "
                                  "second while the controller has to cut", json_schema_extra={"unit": "1/s"})
    gain_recover_time: Seconds = Field(0.5, gt=0, description="passivity_gain_adaptation: time constant of the "
                                       "recovery in free space", json_schema_extra={"unit": "s"})
    gain_recover_time_contact: Seconds | None = Field(None, gt=0, description="passivity_gain_adaptation: time "
                                                      "constant of the recovery while in contact (null: the scale "
                                                      "recovers only in free space)", json_schema_extra={"unit": "s"})
    gain_adaptation_power: float = Field(1e-3, ge=0, description="passivity_gain_adaptation: the force scale is "
                                         "lowered while the force cut takes out more than this power on average",
                                         json_schema_extra={"unit": "W"})
    passivity_cut_time: Seconds = Field(0.1, gt=0, description="averaging time of the power taken out by the cut",
                                        json_schema_extra={"unit": "s"})
    gain_min: float = Field(0.1, gt=0, le=1, description="passivity_gain_adaptation: floor of the force scale")
    reduction_margin: float = Field(0.0, ge=0, description="energy deficit left to the damping before the force "
                                    "is cut", json_schema_extra={"unit": "J"})
    reduction_time: Seconds = Field(0.01, ge=0, description="the force cut pays a deficit over this time rather "
                                    "than within one step (0: the exact one-step cut, which clicks)",
                                    json_schema_extra={"unit": "s"})
    reduction_min_velocity: float = Field(3e-3, gt=0, description="the force is cut only while the leader moves "
                                          "faster than this (slower, the energy that leaks is tiny; cutting a "
                                          "standing deficit on every tremor would make the force chatter)",
                                          json_schema_extra={"unit": "m/s"})
    gain_adaptation_margin: float = Field(2e-3, ge=0, description="energy deficit beyond which the force scale is "
                                          "lowered", json_schema_extra={"unit": "J"})
    damping_smoothing: Seconds = Field(0.005, ge=0, description="time constant of the passivity damping's rise "
                                       "(0: the exact one-step TDPA value)", json_schema_extra={"unit": "s"})
    damping_release: Seconds = Field(0.05, ge=0, description="time constant of the passivity damping's decay "
                                     "(no step in the hand when the deficit is paid; dissipates a little more)",
                                     json_schema_extra={"unit": "s"})

    @field_validator("max_force")
    @classmethod
    def _hand_force(cls, v: float, info: Any) -> float:
        return plausible_hand_force(info.field_name, v)   # a force on a person's hand: 8000 meant 8000 mN

    @field_validator("max_force_rate")
    @classmethod
    def _force_rate(cls, v: float, info: Any) -> float:
        return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_FORCE_RATE, "N/s",   # 200000 meant mN/s
                                  "faster than a force on a hand needs to change",
                                  f": a haptic device's whole +-{MAX_PLAUSIBLE_HAND_FORCE:g} N in 1 ms")

    @field_validator("reduction_min_velocity", "max_leader_velocity")
    @classmethod
    def _speeds(cls, v: float, info: Any) -> float:
        # 3 meant 3 mm/s (no force was ever cut); a glitch filter is wider than a hand's speed, yet not 2000 m/s
        limit = MAX_LEADER_VELOCITY_LIMIT if info.field_name == "max_leader_velocity" else MAX_PLAUSIBLE_SPEED
        return plausible_speed(info.field_name, v, limit)

    @model_validator(mode="after")
    def _check(self) -> "_CommonParams":
        for name in ("opening_min", "opening_max", "offset"):
            plausible_opening(name, getattr(self, name))
        if self.opening_min >= self.opening_max:
            raise ValueError(f"opening_min ({self.opening_min} m) must be below opening_max ({self.opening_max} m)")
        if self.fault_after_lost is not None and self.fault_after_lost < self.fade_time:
            raise ValueError(f"fault_after_lost ({self.fault_after_lost} s) must be at least fade_time "
                             f"({self.fade_time} s): the force on the hand fades out before the run stops (or "
                             f"null: never a fault)")
        constant = self.constant_damping()
        if constant > self.max_damping:
            names = " + ".join(n for n in self._constant_damping_fields() if getattr(self, n))
            raise ValueError(f"{names} ({constant} N*s/m) must not exceed max_damping ({self.max_damping} N*s/m), "
                             f"the most damping the leader renders stably (raise max_damping only for a leader "
                             f"that renders more)")
        return self

    def _constant_damping_fields(self) -> tuple[str, ...]:
        return ("leader_damping",)

    def constant_damping(self) -> float:
        """The damping (N*s/m) always rendered on the leader; the passivity damping may add what is left of
        max_damping."""
        return sum(getattr(self, n) for n in self._constant_damping_fields())


def lost_since(since: float | None, lost: bool, t: float, limit: float, what: str, problem: str, fix: str,
               port: str | None = None) -> float | None:
    """When a loss of ``what`` began (None: not lost now), given when it began so far (``since``); ComponentFault
    once it has lasted longer than ``limit`` s, naming what, for how long, why (``problem``) and what to check; it
    is about input ``port`` (the runtime adds which node feeds it)."""
    if not lost:
        return None
    if since is None:
        return t
    if t - since > limit:
        raise ComponentFault(f"{what} lost for {t - since:.3f} s (since t={since:.3f} s; {problem}), longer than "
                             f"fault_after_lost {limit:g} s: {fix}", input_port=port)
    return since


class _Bilateral(Component):
    """Shared follower mapping, leader-force safety chain and passivity; subclasses give the force law."""

    kind = Kind.CONTROLLER
    default_rate = 1000.0
    #: a lost force estimate, or a node feeding it disabled by a fault, fades the force on the hand (position-force;
    #: no-feedback renders none) and the follower holds a stale leader: under degrade the runtime leaves the devices
    #: it commands to it (position-position sets it False)
    guards_upstream = True
    inputs = dict(_IN)
    outputs = dict(_OUT)
    Params = _CommonParams

    # -- lifecycle
    def configure(self) -> None:
        self._reset()
        rate = self._rate()
        if 1.0 / rate > LEADER_PERIOD * (1.0 + 1e-9):
            p = self.params
            step = p.max_force_rate * LEADER_PERIOD
            self.ctx.log(f"{self.name} at {rate:g} Hz, below 1 kHz: the leader holds each force command "
                         f"{1e3 / rate:g} ms, so one step changes the force by at most max_force_rate x 1 ms "
                         f"({step:g} N, not {p.max_force_rate / rate:g} N): the force follows at most "
                         f"{step * rate:g} N/s (a fade still ends within fade_time); run it at 1 kHz")

    def _rate(self) -> float:
        """The node's step rate (Hz)."""
        return float(self.ctx.rate or self.default_rate or 1000.0)

    def activate(self) -> None:
        self._reset()

    def _reset(self) -> None:
        p = self.params
        self.t_last: float | None = None
        self.command: float | None = None       # last follower command (m)
        self.x_l = math.nan
        self.v_l = 0.0
        self.x_f = math.nan
        self.out_force = 0.0                     # last leader force sent (N)
        self.pas = PassivityState()
        self.damping = 0.0                       # the damping output of the last step (N*s/m)
        # openings more than leader_stale_after apart have a loss between them: no velocity across it
        self.vel_l = Differentiator(p.velocity_cutoff, p.leader_stale_after)
        self.vel_f = Differentiator(p.velocity_cutoff, p.leader_stale_after)
        self.leader_ok = False
        self.state = "waiting"                   # waiting | ok | stale-force | bad-force | stale-leader
        self.invalid_inputs = 0
        self.future_stamps = 0                   # samples stamped more than max_clock_skew ahead (see _fresh)
        self.force_held = 0.0
        self.fading = False
        self.leader_fade_rate: float | None = None
        self.gain = 1.0                          # passivity: scale of the rendered force (adapt_gain)
        self.fport = FollowerPort()              # two-port observer: follower openings by time
        self.cut_power = 0.0                     # average power taken out by the force cut (W)
        self.cmd_hist = FollowerPort()           # follower commands by time (force prediction)
        self._record_commands = bool(getattr(p, "force_prediction", False))
        self._two_port = p.passivity_observer == "two-port"
        rate = self._rate()
        self._max_dt = 2.0 / rate               # longest step the force rate limit counts (see step)
        # the largest change of the force in one step: the leader holds each command, so the hand gets a step's change
        # at once, within one leader period (max_force_rate x 50 ms at 20 Hz would step 0 -> 7.98 N within 1 ms);
        # below 1 kHz at most max_force_rate x one 1 kHz leader period; from 1 kHz up, the two periods _max_dt counts
        self._max_step = math.inf if 1.0 / rate <= LEADER_PERIOD * (1.0 + 1e-9) else p.max_force_rate * LEADER_PERIOD
        self._taken: dict[str, Sample] = {}     # the newest fresh sample taken per input (see _ordered)
        self._ahead: dict[str, Sample] = {}     # the last sample refused as stamped ahead, per input (see _usable)
        self._looked: dict[str, Sample] = {}    # the sample looked at last per input (see _first_look)
        # passivity damping cap: what the constant damping leaves of what the leader renders stably
        self._damping_cap = max(0.0, p.max_damping - p.constant_damping())
        self.leader_lost_since: float | None = None     # the leader opening lost (after it was once ok) since
        self.force_lost_since: float | None = None      # position-force: the force estimate lost since
        self.leader_problem = ""                        # why the leader opening is not ok (for the fault)
        self.force_problem = ""                         # why the force estimate is lost (for the fault)
        self.figures = RunFigures()                     # what the run achieved (results())
        self._target = math.nan                         # the follower's target at the last step (m)

    # -- helpers
    def _ordered(self, name: str, s: Sample | None, t: float, max_age: float) -> Sample | None:
        """The sample of input ``name`` to use: ``s``, unless it is stamped before the newest fresh sample already
        taken (it arrived out of order), then that one, so that an older measurement never replaces a newer one.
        Only usable samples are taken (:meth:`_usable`), so a sample stamped in the future (or NaN) cannot lock out
        the ones after it, also once the clock has caught up with its stamp."""
        last = self._taken.get(name)
        if s is None:
            return last
        if last is not None and s.stamp < last.stamp:
            return last
        if self._usable(name, s, t, max_age):
            self._taken[name] = s
        return s

    def _usable(self, name: str, s: Sample, t: float, max_age: float) -> bool:
        """Whether sample ``s`` of input ``name`` may be used at ``t``: fresh (:meth:`_fresh`), and not refused
        before as stamped ahead. A sample refused as ahead of the clock stays refused when the clock catches up
        with its stamp (it stays the latest input for several steps): taken then, it would be used late and its
        stamp would lock out the good samples after it as out of order (an estimate 55 ms ahead faded the force
        for 64 ms)."""
        if self._refused_ahead(name, s):
            return False
        if self._fresh(s, t, max_age):
            return True
        if s.stamp > t:   # (not for a NaN stamp: it is refused as such on every look)
            self._ahead[name] = s
        return False

    def _refused_ahead(self, name: str, s: Sample) -> bool:
        """Whether ``s`` (or a copy of it: the same stamp) is the sample of input ``name`` refused as stamped ahead."""
        a = self._ahead.get(name)
        return a is not None and (a is s or a.stamp == s.stamp)

    def _fresh(self, s: Sample, t: float, max_age: float) -> bool:
        """Whether ``s`` may be used at ``t``: at most ``max_age`` old and at most ``max_clock_skew`` (never more
        than ``max_age``) ahead of the graph clock; False for a NaN stamp. (Sample.is_fresh took up to ``max_age``
        ahead: a force stamped 80 ms in the future was fresh for 180 ms, and the tolerance grew with stale_after.)"""
        return -min(self.params.max_clock_skew, max_age) <= t - s.stamp <= max_age

    def _not_fresh(self, name: str, s: Sample, t: float, max_age: float, limit: str, first: bool | None = None
                   ) -> str:
        """Why ``s``, not fresh at ``t``, is not (for the fault of a loss that lasts); a stamp ahead of the clock is
        counted once per sample (``future_stamps``, ``invalid_inputs``). ``limit``: the name of ``max_age``;
        ``first``: whether ``s`` is looked at for the first time (None: asked here, see :meth:`_first_look`)."""
        ahead = s.stamp - t
        if math.isnan(ahead):
            return f"stamp {s.stamp!r}"
        refused = self._refused_ahead(name, s)
        if ahead <= 0.0 and not refused:
            return f"stale (older than {limit} {max_age:g} s)"
        if self._first_look(name, s) if first is None else first:
            self.future_stamps += 1
            self.invalid_inputs += 1
        if ahead <= 0.0:   # refused when it came, and still the latest
            return (f"stamped more than max_clock_skew {min(self.params.max_clock_skew, max_age):g} s ahead of the "
                    f"graph clock when it came: the clocks disagree; synchronise them (chrony, PTP), or stamp on "
                    f"arrival (stamps: arrival on a ROS 2 subscriber)")
        return (f"stamped {ahead:.3f} s ahead of the graph clock, more than max_clock_skew "
                f"{min(self.params.max_clock_skew, max_age):g} s: the clocks disagree; synchronise them (chrony, "
                f"PTP), or stamp on arrival (stamps: arrival on a ROS 2 subscriber)")

    def _first_look(self, name: str, s: Sample) -> bool:
        """Whether ``s`` is looked at for the first time on input ``name``: not the sample of the last look (it
        stays the latest for many steps) nor a copy of it (the same stamp). A bad sample is counted on its first
        look only, once per sample (a bad opening was counted on every step while it was fresh, and a NaN stamp,
        never equal to itself, made every step a first look: the counters grew at 1 kHz)."""
        last = self._looked.get(name)
        if last is not None and (s is last or s.stamp == last.stamp):
            return False
        self._looked[name] = s
        return True

    def _leader(self, t: float, inputs: Any) -> bool:
        p = self.params
        s = self._ordered("leader_opening", inputs["leader_opening"], t, p.leader_stale_after)
        if s is None or not self._usable("leader_opening", s, t, p.leader_stale_after):
            self.leader_problem = ("nothing received" if s is None else
                                   self._not_fresh("leader_opening", s, t, p.leader_stale_after, "leader_stale_after"))
            return False
        x = opening_or_nan(s.value)
        if not math.isfinite(x):
            if self._first_look("leader_opening", s):
                self.invalid_inputs += 1
            self.leader_problem = f"invalid ({value_text(s.value)} m: not a finite opening within 1 m)"
            return False
        self.x_l = x
        v_raw = self._ordered("leader_velocity", inputs.get("leader_velocity"), t, p.leader_stale_after)
        v = math.nan
        if v_raw is not None and not self._usable("leader_velocity", v_raw, t, p.leader_stale_after):
            self._not_fresh("leader_velocity", v_raw, t, p.leader_stale_after, "leader_stale_after")   # (counted)
        elif v_raw is not None:
            v = finite_or(v_raw.value, math.nan)
            if not abs(v) <= p.max_leader_velocity:          # NaN, inf, or a glitch the opening never made
                if self._first_look("leader_velocity", v_raw):
                    self.invalid_inputs += 1
                v = math.nan
        vd = self.vel_l.update(s.stamp, x)
        self.v_l = v if math.isfinite(v) else vd
        return True

    def _follower(self, t: float, inputs: Any) -> bool:
        max_age = self.params.leader_stale_after
        s = self._ordered("follower_opening", inputs.get("follower_opening"), t, max_age)
        if s is None:
            return False
        if not self._usable("follower_opening", s, t, max_age):
            self._not_fresh("follower_opening", s, t, max_age, "leader_stale_after")     # (a future stamp counted)
            return False
        x = opening_or_nan(s.value)
        if not math.isfinite(x):
            if self._first_look("follower_opening", s):
                self.invalid_inputs += 1
            return False
        self.x_f = x
        self.vel_f.update(s.stamp, x)
        if self._two_port:
            self.fport.record(s.stamp, x)
        return True

    def _restart_observer(self) -> None:
        """The leader is back (or there for the first time): the passivity observer starts afresh, energy and
        damping at zero, as at activation. What it held is about a hand that was cut off: the leader port was not
        booked while the leader was lost (the follower port's estimates were), so its energy no longer describes
        this coupling, and its damping (up to max_damping) would have met the returning hand at once. The damping
        then rises over damping_smoothing as for any deficit, and the force comes back within max_force_rate.
        The totals (dissipated, active_steps, follower_energy) are kept."""
        self.pas.energy = 0.0
        self.pas.alpha = 0.0
        self.cut_power = 0.0
        self.fport.forget()                      # no two-port interval across the gap

    def feedback(self, t: float, inputs: Any, follower_ok: bool) -> float:
        """The desired leader force before passivity and limits (N)."""
        return 0.0

    def _follow(self, target: float, dt: float) -> float:
        """The follower command for the leader's mapped opening ``target`` (m): here the target itself."""
        return target

    def force_lost(self) -> bool:
        """The force estimate is lost (stale or not finite; not the start-up wait for a first one)."""
        return False

    def _watch_losses(self, t: float) -> None:
        """Raise ComponentFault when the leader opening or the force estimate has been lost continuously for
        longer than ``fault_after_lost``: a loss that lasts is a fault, not silence. The runtime then drives the
        devices to their safe states (zero leader force; the follower holds). The leader counts once it was ok."""
        limit = self.params.fault_after_lost
        self.leader_lost_since = lost_since(self.leader_lost_since, not (self.leader_ok or self.command is None), t,
                                            limit, "leader opening", self.leader_problem,
                                            "check the leader and its wire", "leader_opening")
        self.force_lost_since = lost_since(self.force_lost_since, self.force_lost(), t, limit, "force estimate",
                                           self.force_problem, "check the sensor and its estimators", "force")

    # -- the step
    def step(self, t: float, inputs: Any) -> dict[str, float]:
        p = self.params
        dt = 0.0 if self.t_last is None else max(0.0, t - self.t_last)
        self.t_last = t
        was_ok = self.leader_ok
        self.leader_ok = self._leader(t, inputs)
        if self.leader_ok and not was_ok:
            self._restart_observer()
        follower_ok = self._follower(t, inputs)
        if self.leader_ok:
            cmd = map_opening(self.x_l, p.scale, p.offset, p.opening_min, p.opening_max)
            self._target = cmd
            if math.isfinite(cmd):               # (finite params and opening: always; else the last one holds)
                self.command = cmd if self.command is None else self._follow(cmd, dt)
            if self._record_commands:
                self.cmd_hist.record(t, self.command)
        f_fb = self.feedback(t, inputs, follower_ok)
        if p.fault_after_lost is not None:
            self._watch_losses(t)
        v = self.v_l if self.leader_ok else 0.0
        if not self.leader_ok:
            f_fb = 0.0
            if self.state != "waiting":
                self.state = "stale-leader"
        free = f_fb == 0.0                       # no force exchanged: free space
        if p.leader_damping > 0.0 and self.leader_ok:
            f_fb -= p.leader_damping * v
        alpha = 0.0
        cut = False                              # the passivity controller had to cut the force this step
        stopped = False                          # ... or stopped it at zero (passivity_no_reversal)
        if p.passivity and p.passivity_gain_adaptation:
            f_fb *= self.gain
        f_des = f_fb
        if self.leader_ok and free and self.pas.energy < 0.0 and p.free_space_reset and dt > 0:
            self.pas.energy *= math.exp(-dt / p.free_space_reset)
        if p.passivity and self.leader_ok:
            # capped damping, raised and released smoothly; then a cut of what is still missing
            f_des, alpha = passivity_force(self.pas, f_fb, v, dt, self._damping_cap, p.energy_leak_time,
                                           reduce_force=False)
            f_capped = f_des                       # with the capped damping at once (what the cut may count on)
            if p.passivity_controller == "force" and p.passivity_no_reversal and opposite_signs(f_capped, f_fb):
                f_capped = 0.0                     # it stops the force at zero: the cut never counts on a pull
            if dt <= 0.0:                          # a repeated time is no step: the damping stays (it dropped
                alpha = self.pas.alpha             # to 0 with damping_release 0, then rose: a surge of the force)
            elif p.damping_smoothing > 0.0 and alpha > self.pas.alpha:
                alpha = self.pas.alpha + (alpha - self.pas.alpha) * min(1.0, dt / p.damping_smoothing)
            elif p.damping_release > 0.0 and alpha < self.pas.alpha:
                alpha = self.pas.alpha + (alpha - self.pas.alpha) * min(1.0, dt / p.damping_release)
                if alpha < 1e-3 * self._damping_cap:
                    alpha = 0.0
            f_des = f_fb - alpha * v
            if p.passivity_controller == "force":
                if free:
                    # nothing in free space: no drag, no pull once contact is over; and no damping kept raised for
                    # the next contact (it met that contact at once, up to max_damping, not over damping_smoothing,
                    # and the damping output showed what was not applied)
                    f_des, alpha = f_fb, 0.0
                elif p.passivity_no_reversal and opposite_signs(f_des, f_fb):   # (a product may underflow)
                    f_des = 0.0                    # the damping may take the feedback force away, not reverse it
                    stopped = True
            if ((p.passivity_force_reduction or p.passivity_controller == "force") and dt > 0
                    and same_sign(f_des, v) and abs(v) >= p.reduction_min_velocity):
                # cut only what even the capped damping would leave: a deficit that the damping's smooth rise
                # merely delays is paid by the damping a few steps later (no one-step click in the hand)
                e_after = observe(self.pas.energy, min(f_des, f_capped) if v > 0 else max(f_des, f_capped), v, dt,
                                  p.energy_leak_time)
                f_cut = reduce_force_to(f_des, e_after, v, dt, p.reduction_margin, p.reduction_min_velocity,
                                        p.reduction_time)
                cut = f_cut != f_des
                # the power the cut takes out, averaged (passivity_cut_time): how hard the controller is working
                self.cut_power += (abs((f_des - f_cut) * v) - self.cut_power) * min(1.0, dt / p.passivity_cut_time)
                f_des = f_cut
        # safety chain: rate limit (a lost leader fades the force to zero within fade_time), saturation, finiteness;
        # a non-finite desired force is a fault of the law: the output goes to zero within the rate limit (it
        # dropped from max_force to 0 in one step)
        if not math.isfinite(f_des):
            f_des = 0.0
        if self.leader_ok:
            self.leader_fade_rate = None
            max_rate = p.max_force_rate
        else:
            if self.leader_fade_rate is None:
                self.leader_fade_rate = max(abs(self.out_force) / p.fade_time, 1e-6)
            max_rate = min(self.leader_fade_rate, p.max_force_rate)     # a short fade_time never beats the limit
        # the rate limit's step is at most two nominal periods long: after a stalled or late step the force still
        # moves by no more than max_force_rate x 2 periods (not by the rate x the whole gap); below 1 kHz one step
        # moves it by at most max_force_rate x 1 ms (_max_step: the leader holds the command, the hand gets a step)
        # (a fade, the leader or the estimate lost, is not held to that cap: it eases towards 0 at the rate limit,
        # within fade_time, as at 1 kHz; in normal operation the cap holds both ways, an uneven limit in the loop
        # with the hand made a limit cycle that kept the force far below the sensed one)
        fading = not self.leader_ok or self.force_lost()
        easing = fading and f_des * self.out_force >= 0 and abs(f_des) <= abs(self.out_force)   # to 0, not across
        f = rate_limit(self.out_force, f_des, max_rate, min(dt, self._max_dt), math.inf if easing else self._max_step)
        f = saturate(f, p.max_force)
        if not math.isfinite(f):
            f = 0.0
        if self.leader_ok:                       # the observer always runs; it acts only with passivity on
            commit(self.pas, f, f_fb, v, dt, alpha, p.energy_leak_time)
            if p.passivity and p.passivity_gain_adaptation and dt > 0:
                short = self.cut_power > p.gain_adaptation_power or self.pas.energy < -p.gain_adaptation_margin
                if short or free:
                    self.gain = adapt_gain(self.gain, short, dt, p.gain_drop_rate, p.gain_recover_time, p.gain_min)
                elif p.gain_recover_time_contact is not None:
                    self.gain = adapt_gain(self.gain, False, dt, p.gain_drop_rate, p.gain_recover_time_contact,
                                           p.gain_min)
            if not math.isfinite(self.pas.energy):
                self.pas = PassivityState()
        self.out_force = f
        if (cut or stopped) and v != 0.0:
            # the equivalent damping of damping + cut, for the output; stopped at zero, the damping the hand got (the
            # whole feedback force), not the larger one that would have pulled
            alpha = (f_fb - f_des) / v
        if not math.isfinite(alpha):
            alpha = 0.0
        self.damping = alpha
        self.figures.add(dt, self._sensed(), f, self._target if self.leader_ok and follower_ok else math.nan, self.x_f)
        out: dict[str, float] = {"gripper_force": f, "energy": self.pas.energy, "damping": alpha}
        if self.command is not None:
            out["opening_command"] = self.command
        return out

    def status(self) -> dict[str, Any]:
        """SI, the unit in each key (docs/writing-a-plugin.md); the live view shows the first six."""
        return {
            "force_n": self.force_held,
            "leader_m": self.x_l if math.isfinite(self.x_l) else None,
            "follower_m": self.x_f if math.isfinite(self.x_f) else None,
            "feedback_n": self.out_force,
            "energy_j": self.pas.energy,
            "state": self.state,
            "damping_n_s_per_m": self.damping,
        }

    def _sensed(self) -> float:
        """The sensed force (N) this step took fresh, for the results; NaN where it took none (a stale estimate, or a
        law without one: position-position's force is its coupling's)."""
        return math.nan

    def results(self) -> dict[str, Any]:
        """What the run achieved: the peak sensed force and the peak force rendered to the hand, how long the sensor
        felt a contact (steps with a fresh estimate above zero), and how far the follower was from the opening the
        leader asked for (x_fd = x_l mapped, at steps where both openings were known; in contact, how far the leader
        went into the object). A law that takes no sensed force (position-position) says no peak force nor contact
        time."""
        return self.figures.results()


class PositionForce(_Bilateral):
    """Position-force teleoperation: the follower tracks the leader, the leader renders the sensed force."""

    name = "position-force"

    class Params(_CommonParams):
        force_scale: float = Field(1.0, ge=0, description="k_f: leader force per sensed force")
        force_sign: Literal[1] = Field(1, description="always +1: a sensed grip force pushes the operator's "
                                       "fingers apart (docs/ports.md); -1, which pulled them closed into the object, "
                                       "is refused")
        deadband: Newtons = Field(0.02, ge=0, description="sensed forces below this are not rendered "
                                  "(continuous: the width is subtracted)", json_schema_extra={"unit": "N"})
        smoothing_time: Seconds = Field(1.0 / 60.0, ge=0, le=MAX_SMOOTHING_TIME, description="each new estimate "
                                        "is reached by a linear ramp of this length (latency: this to the full "
                                        "value, half on average; at most 0.25 s, a few frames of a slow estimator: "
                                        "a release reaches the hand this late, 17 meant as ms was 17 s)",
                                        json_schema_extra={"unit": "s"})
        stale_after: Seconds = Field(0.1, gt=0, le=1.0, description="a force estimate older than this fades to zero "
                                     "(at most 1 s: a dead sensor's last force stayed on the hand that long; 100 "
                                     "meant as ms was 100 s)", json_schema_extra={"unit": "s"})
        first_force_timeout: Seconds | None = Field(5.0, gt=0, le=60.0, description="no force estimate at all "
                                                    "this long after the leader's first usable opening is a fault "
                                                    "(a sensor that never started, a ROS 2 domain or topic that "
                                                    "does not match: the follower went on without feedback for the "
                                                    "whole run, which ended ok; null: wait for ever)",
                                                    json_schema_extra={"unit": "s"})
        max_invalid_force_share: float | None = Field(0.5, gt=0, le=1, description="when a good estimate comes "
                                                      "and at least this share of the last "
                                                      f"{INVALID_FORCE_WINDOW} received (1 s at 60 Hz) were invalid "
                                                      f"(not finite), in at least {MIN_INVALID_FORCE_DIPS} separate "
                                                      "runs (one burst is a loss), it is a fault: an estimator failing "
                                                      "on every "
                                                      "other frame makes no loss that lasts (each good estimate "
                                                      "ends it) while the force dips at every bad one (a lasting "
                                                      "loss is fault_after_lost's; null: never; counted in "
                                                      "invalid_forces either way)")
        force_prediction: bool = Field(True, description="in contact, bridge the estimate's latency with a local "
                                       "contact model: add k_f * K * (x_cmd(capture) - x_cmd(now)), K the "
                                       "stiffness learnt from successive estimates (never past zero)")
        prediction_max_stiffness: NewtonsPerMeter = Field(2e4, ge=0, description="cap of the learnt contact "
                                                          "stiffness K", json_schema_extra={"unit": "N/m"})
        prediction_max_change: Newtons = Field(1.0, ge=0, description="largest predicted change of the sensed "
                                               "force (a misjudged stiffness cannot push the hand far)",
                                               json_schema_extra={"unit": "N"})
        prediction_min_motion: Meters = Field(2e-5, ge=0, description="K is learnt only from estimates this far "
                                              "apart in follower command", json_schema_extra={"unit": "m"})
        prediction_rate: float = Field(0.3, gt=0, le=1, description="weight of each new stiffness measurement")
        hold_on_lost_force: bool = Field(True, description="while the force estimate is lost (stale or not "
                                         "finite; not while waiting for the first one) the follower command holds "
                                         "its value: the operator, who no longer feels the object, cannot make "
                                         "the follower squeeze it")
        resume_speed: float = Field(0.02, gt=0, description="when a fresh estimate returns after a hold, the "
                                    "follower command moves from the held value to the leader's mapped opening "
                                    "at no more than this speed (never a jump)", json_schema_extra={"unit": "m/s"})

        @field_validator("resume_speed")
        @classmethod
        def _speed(cls, v: float, info: Any) -> float:
            return plausible_speed(info.field_name, v)

        @field_validator("deadband")
        @classmethod
        def _deadband(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_DEADBAND, "N",
                                      "wider than the grip forces a tactile sensor reads",
                                      "; nothing below it is rendered")

        @field_validator("prediction_min_motion")
        @classmethod
        def _min_motion(cls, v: float, info: Any) -> float:
            return plausible_depth(info.field_name, v)   # 0.02 meant 0.02 mm: in contact, K would never be learnt

        @field_validator("force_sign", mode="before")
        @classmethod
        def _no_pull(cls, v: Any) -> Any:
            if v == -1:
                raise ValueError("force_sign -1 would pull the operator's fingers closed, into the object, with the "
                                 "sensed grip force: every leader takes gripper_force positive when it pushes the "
                                 "fingers apart (docs/ports.md); a leader wired the other way is fixed in its driver")
            return v

    def _reset(self) -> None:
        super()._reset()
        self.hold = ForceHold(0.0)
        self.xref = ForceHold(0.0)              # follower command at the capture of the estimate, ramped likewise
        self.k_hat = 0.0                        # learnt contact stiffness (N/m, sensed force per follower metre)
        self.k_from = 0.0                       # the stiffness used when k_hat last changed (see _stiffness) ...
        self.k_t0 = 0.0                         # ... and when
        self.pred_prev: tuple[float, float] | None = None
        self.pred_on = False
        self.pred_active = False                # the predicted term was being added (see _predicted)
        self.pred_term = 0.0                    # the term added in the last step (N, after the clip)
        self.pred_from = 0.0                    # the term when the prediction last started or stopped
        self.pred_t0 = 0.0                      # ... and when
        self.latencies: list[float] = []        # controller time of first use - force stamp, per new fresh estimate
        self.bad_force = 0                      # invalid (not finite) estimates: invalid_forces in status, results
        self.bad_since: float | None = None     # when the first one came (logged once)
        self.recent_bad: deque[bool] = deque(maxlen=INVALID_FORCE_WINDOW)   # the latest estimates: each invalid?
        self.resuming = False                   # the follower command was held: it slews back (resume_speed)
        self.force_state = "waiting"            # the estimate's state, kept while step() shows stale-leader
        self.first_wait_since: float | None = None   # the leader's first usable step while no estimate has come

    def feedback(self, t: float, inputs: Any, follower_ok: bool) -> float:
        p = self.params
        # step() shows stale-leader while the leader is lost; the estimate's own state returns with the leader (it
        # stayed stale-leader, and the prediction off, until the next estimate came)
        if self.state == "stale-leader":
            self.state = self.force_state
        lost = self.ctx.disabled_upstream()
        if lost:   # a node feeding it was disabled by a fault: a filter in between may keep the stamps fresh
            if not self.fading:
                self.force_problem = (f"node{'s' if len(lost) > 1 else ''} {', '.join(repr(n) for n in lost)} "
                                      f"feeding it disabled by a fault")
            self.state = "upstream-lost"
            self._fade(t)
        else:
            s = self._ordered("force", inputs["force"], t, p.stale_after)     # an older estimate never replaces a newer
            if s is not None and self._first_look("force", s):     # once per sample (a NaN stamp too)
                f_s = finite_or(s.value, math.nan)
                self._count_invalid(t, s, not math.isfinite(f_s))
                if math.isfinite(f_s):
                    self.force_held = f_s
                    if self._usable("force", s, t, p.stale_after):   # (False for a NaN stamp: no latency to count)
                        if len(self.latencies) < 100_000:
                            self.latencies.append(t - s.stamp)
                        f_l = shape_force(f_s, p.force_scale, p.force_sign, p.deadband, p.max_force)
                        self.hold.set(t, f_l, p.smoothing_time)
                        self.fading = False
                        self.state = "ok"
                        if p.force_prediction:
                            self._learn(t, s.stamp, f_s)
                        if p.passivity_observer == "two-port":
                            e_f = self.fport.sample(s.stamp, f_l, p.scale)
                            self.pas.energy += e_f
                            self.pas.follower_energy += e_f
                    else:
                        self.fport.forget()
                        self._not_fresh("force", s, t, p.stale_after, "stale_after", True)   # (a future stamp counted)
                else:
                    self.fport.forget()
                    self.force_held = 0.0
                    self.state = "bad-force"
                    self._fade(t)
            if s is None:
                self.state = "waiting" if self.state == "waiting" else self.state
                self._first_force_wait(t)
            elif not self._usable("force", s, t, p.stale_after) and self.state != "bad-force":
                if not self.fading:                       # why, for the fault of a loss that lasts
                    self.force_problem = self._not_fresh("force", s, t, p.stale_after, "stale_after", False)
                self.state = "stale-force"
                self._fade(t)
        self.force_state = self.state
        f = self._predicted(t, self.hold.value(t))
        # a stale or bad estimate fades: it never raises the force (when a lost leader came back during the fade,
        # the force rose again towards the stale estimate)
        return no_rise(f, self.out_force) if self.fading else f

    def _count_invalid(self, t: float, s: Sample, bad: bool) -> None:
        """Book a new estimate ``s`` as invalid (``bad``: not finite) or not. The first invalid one is logged. A good
        one ends a loss (fault_after_lost never sees an estimator that fails on every other frame): when the last
        INVALID_FORCE_WINDOW estimates have a share of at least ``max_invalid_force_share`` invalid ones, it is a
        ComponentFault instead (a loss that lasts is fault_after_lost's, as it was without good estimates)."""
        self.recent_bad.append(bad)
        if bad:
            self.bad_force += 1
            self.invalid_inputs += 1
            if self.bad_since is None:
                self.bad_since = t
                self.ctx.log(f"force estimate {value_text(s.value)} N (not finite) at t={t:.3f} s: the force fades "
                             f"out (fade_time), as for a lost estimate; invalid estimates are counted "
                             f"(invalid_forces in the status and the results), not logged again")
            return
        share = self.params.max_invalid_force_share
        if share is None or len(self.recent_bad) < INVALID_FORCE_WINDOW:
            return
        n = sum(self.recent_bad)
        if n < share * INVALID_FORCE_WINDOW:
            return
        recent = list(self.recent_bad)
        dips = sum(1 for i, b in enumerate(recent) if b and (i == 0 or not recent[i - 1]))
        if dips >= MIN_INVALID_FORCE_DIPS:   # (one burst, however long, is a loss: fault_after_lost's)
            raise ComponentFault(f"{n} of the last {INVALID_FORCE_WINDOW} force estimates were not finite, in {dips} "
                                 f"separate runs ({self.bad_force} since t={self.bad_since:.3f} s), at least "
                                 f"max_invalid_force_share {share:g}: the estimator is failing (the force on the "
                                 f"hand dipped at every one); check the sensor and its estimators",
                                 input_port="force")

    def _predicted(self, t: float, f: float) -> float:
        """``f`` plus the contact prediction, within ``[0, max_force]``. When the prediction starts or stops (a
        contact begins or ends, the estimate goes stale or comes back) the term is blended from what was added
        to its new value over ``smoothing_time``, as the hold ramps the estimate: never a step in the hand (it
        was dropped at once, a jump of up to prediction_max_change x force_scale)."""
        p = self.params
        active = self.pred_on and self.state == "ok" and self.command is not None and f != 0.0
        target = 0.0
        if active:
            d = self._stiffness(t) * (self.xref.value(t) - self.command)   # sensed force change since the capture
            lim = p.prediction_max_change
            d = lim if d > lim else -lim if d < -lim else d
            target = p.force_scale * d
        if active != self.pred_active:
            self.pred_active = active
            self.pred_from, self.pred_t0 = self.pred_term, t
        term = target
        # blended over smoothing_time; while the estimate fades, within fade_time (as the estimate's force): the term
        # must not outlast the fade
        ts = min(p.smoothing_time, p.fade_time) if self.fading else p.smoothing_time
        if ts > 0.0 and t - self.pred_t0 < ts:
            w = max(0.0, (t - self.pred_t0) / ts)
            term = self.pred_from + (target - self.pred_from) * w
        if term == 0.0:
            self.pred_term = 0.0
            return f
        total = min(max(0.0, f + term), p.max_force)
        self.pred_term = total - f
        return total

    def _stiffness(self, t: float) -> float:
        """The stiffness the prediction uses: ``k_hat``, reached by a linear ramp of ``smoothing_time`` from the
        value used when it last changed, as the capture point ramps (a new K at once stepped the term, and the
        force in the hand, by up to prediction_max_change x force_scale when the first K of a contact was learnt)."""
        ts = self.params.smoothing_time
        if ts > 0.0 and t - self.k_t0 < ts:
            return self.k_from + (self.k_hat - self.k_from) * max(0.0, (t - self.k_t0) / ts)
        return self.k_hat

    def _learn(self, t: float, stamp: float, f_s: float) -> None:
        """Contact model for the prediction: the stiffness K = -dF/dx_cmd from successive estimates."""
        p = self.params
        x_s = self.cmd_hist.opening_at(stamp)
        if x_s is None or not f_s > p.deadband:
            self.pred_prev = None
            self.pred_on = False
            if not f_s > p.deadband:
                self.k_hat = self.k_from = 0.0      # the contact is over: the next one is learnt afresh
            return
        prev = self.pred_prev
        if prev is not None and abs(x_s - prev[1]) > p.prediction_min_motion:
            k = -(f_s - prev[0]) / (x_s - prev[1])
            k = min(max(k, 0.0), p.prediction_max_stiffness)
            self.k_from, self.k_t0 = self._stiffness(t), t
            self.k_hat += p.prediction_rate * (k - self.k_hat)
            self.pred_prev = (f_s, x_s)
        elif prev is None:
            self.pred_prev = (f_s, x_s)
        if self.pred_on:
            self.xref.set(t, x_s, p.smoothing_time)
        else:
            self.xref = ForceHold(x_s)
            self.pred_on = True

    def status(self) -> dict[str, Any]:
        d = super().status()
        d["contact_stiffness_n_per_m"] = getattr(self, "k_hat", 0.0)     # learnt by the prediction
        d["invalid_forces"] = getattr(self, "bad_force", 0)              # estimates not finite
        return d

    def results(self) -> dict[str, Any]:
        """As :meth:`_Bilateral.results`, and ``invalid_forces``: how many estimates were not finite."""
        return {**super().results(), "invalid_forces": self.bad_force}

    def _sensed(self) -> float:
        return self.force_held if self.force_state == "ok" else math.nan   # (stale, bad: fading, not sensed)

    def _first_force_wait(self, t: float) -> None:
        """No force sample yet (state "waiting": any sample, a stale or bad one too, ends it): once the leader gives
        openings (the follower follows them), a wait longer than ``first_force_timeout`` is a ComponentFault about the
        force input (the runtime names the node feeding it)."""
        limit = self.params.first_force_timeout
        if self.state != "waiting" or limit is None or self.command is None:
            return
        if self.first_wait_since is None:
            self.first_wait_since = t
        elif t - self.first_wait_since > limit:
            raise ComponentFault(f"no force estimate received in {t - self.first_wait_since:.3f} s since the leader's "
                                 f"first opening (t={self.first_wait_since:.3f} s), longer than first_force_timeout "
                                 f"{limit:g} s: the follower would be teleoperated without force feedback; check the "
                                 f"sensor, its estimators and the force wire (a ROS 2 bridge: its domain, topic and "
                                 f"QoS)",
                                 input_port="force")

    def _fade(self, t: float) -> None:
        if not self.fading:
            self.fading = True
            if self.state == "bad-force":             # (a stale one: its force_problem is set by feedback())
                self.force_problem = "not finite"
            self.hold.set(t, 0.0, self.params.fade_time)

    def force_lost(self) -> bool:
        """Stale or not finite since the last fresh estimate (``fading``; set by feedback()): never while waiting
        for the first estimate at start-up."""
        return self.fading

    def _follow(self, target: float, dt: float) -> float:
        """While the force estimate is lost (as of the last feedback(): a step later than the loss is noticed) the
        command holds; afterwards it slews to ``target`` at ``resume_speed``, then follows again."""
        p = self.params
        if self.fading and p.hold_on_lost_force:
            self.resuming = True
            return self.command                  # type: ignore[return-value]  (not None: see step)
        if self.resuming:
            x = rate_limit(self.command, target, p.resume_speed, min(dt, self._max_dt))   # type: ignore[arg-type]
            self.resuming = x != target
            return x
        return target


class PositionPosition(_Bilateral):
    """Position-position baseline: a PD on the leader-follower position error is rendered to the operator."""

    name = "position-position"
    #: its force comes from the follower's opening, which a filter between may keep fresh after a fault upstream of
    #: it: under degrade the runtime makes its devices safe then
    guards_upstream = False
    inputs = dict(_IN, follower_opening=Port("float64", (), "m", "follower opening", required=True),
                  force=Port("float64", (), "N", "sensed force (not used by this law)", required=False))

    class Params(_CommonParams):
        kp: NewtonsPerMeter = Field(400.0, ge=0, description="stiffness of the position coupling on the leader",
                                    json_schema_extra={"unit": "N/m"})
        kd: NewtonSecondsPerMeter = Field(2.0, ge=0, description="damping of the position coupling on the leader",
                                          json_schema_extra={"unit": "N*s/m"})
        passivity_controller: Literal["force", "damping"] = Field(
            "damping", description="the coupling force is not a contact force (it changes sign): the classic "
            "damping TDPA by default")
        passivity_observer: Literal["two-port", "leader-port"] = Field(
            "leader-port", description="no sensed force here: the leader port only")

        def _constant_damping_fields(self) -> tuple[str, ...]:
            return ("kd", "leader_damping")          # kd damps the leader's own velocity too

    def _reset(self) -> None:
        super()._reset()
        self.coupling = ForceHold(0.0)           # the coupling force; faded out over fade_time without a follower
        self.coupling_fading = False

    def feedback(self, t: float, inputs: Any, follower_ok: bool) -> float:
        p = self.params
        if not self.leader_ok:                   # the step fades the force out; no stale coupling comes back
            self.coupling.set(t, 0.0, 0.0)
            self.coupling_fading = False
            self.force_held = 0.0
            return 0.0
        if not follower_ok:                      # the coupling's source is lost: fade out over fade_time
            self.state = "stale-follower"
            if not self.coupling_fading:
                self.coupling_fading = True
                self.coupling.set(t, 0.0, p.fade_time)
            self.force_held = 0.0
            return no_rise(self.coupling.value(t), self.out_force)       # the stale coupling never pushes harder
        self.state = "ok"
        self.coupling_fading = False
        x_fb = unmap_opening(self.x_f, p.scale, p.offset)
        v_fb = self.vel_f.v / p.scale
        f = p.kp * (x_fb - self.x_l) + p.kd * (v_fb - self.v_l)
        self.force_held = f
        f = saturate(f, p.max_force) if math.isfinite(f) else 0.0
        self.coupling.set(t, f, 0.0)
        return f


#: how old a no-feedback controller's force input may be to count as sensed in its results (s; position-force's
#: default stale_after)
NO_FEEDBACK_STALE_AFTER = 0.1


class NoFeedback(_Bilateral):
    """No force feedback: the follower tracks the leader, the operator feels nothing."""

    name = "no-feedback"
    inputs = dict(_IN, force=Port("float64", (), "N", "sensed force (shown in the status only)", required=False))

    def _reset(self) -> None:
        super()._reset()
        self.fresh_force = False

    def feedback(self, t: float, inputs: Any, follower_ok: bool) -> float:
        s = inputs["force"]
        f = finite_or(inputs.value("force"), 0.0)
        self.force_held = f
        # sensed (for the results) while the estimate is as fresh as position-force's default stale_after
        self.fresh_force = s is not None and self._fresh(s, t, NO_FEEDBACK_STALE_AFTER)
        if self.leader_ok:
            self.state = "ok"
        return 0.0

    def _sensed(self) -> float:
        return self.force_held if self.fresh_force else math.nan


@hookimpl
def teletouch_components():
    return [PositionForce, PositionPosition, NoFeedback]
