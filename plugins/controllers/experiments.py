"""The paper's experiments in simulation: ``teletouch experiment contact|pivot``, and the simulated pieces they need.

Contact (paper Fig. 4)
    The simulated operator (sim-omega7, intent ``close-and-hold``) closes on a rigid object held by sim-gripper; the
    gel fingertip's indentation drives sim-digit, whose images go through the real estimators (depth, poly-force)
    to the controller. Run twice, with ``position-force`` and with ``no-feedback``. Metric: the mean of
    |leader opening (desired, the operator's hand) - follower opening (actual, blocked by the object)| while the
    fingers touch the object. Paper: 0.6 mm with feedback.

Pivot (paper's user study)
    A cylinder held between the fingers pivots under gravity when the grip is loosened (``sim-pivot``: torsional
    friction from the grip force, stick-slip). A simulated operator (``pivot-operator``: perception noise and delay,
    hand tremor) tries to bring it to a target angle, once feeling the grip force (visual + force: position-force)
    and once without (visual only: no-feedback), over seeded trials. Metrics: success rate and completion time per
    condition. Paper: 86.7 % vs 40 %, median 13.75 s vs 15.37 s.

Components added here: ``sim-force-sensor`` (a camera-rate stand-in for the DIGIT + estimator chain: samples a
ground-truth force at the frame rate with a frame of latency and noise, for many-trial experiments),
``sim-pivot`` and ``pivot-operator``.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from teletouch import Component, Kind, Params, Port, Sample, hookimpl
from teletouch.units import (
    Kilograms, Meters, Newtons, Radians, Seconds, plausible_opening, plausible_quantity, plausible_speed,
)

G = 9.81

#: no object pivoted between two fingertips is longer than this (the experiment's: 0.12 m): a longer length or centre
#: of mass offset in the metre field is millimetres typed there
MAX_PLAUSIBLE_OBJECT = 1.0       # m
#: no contact patch on a DIGIT's gel is wider than its sensing area (about 15-20 x 20-25 mm): a larger friction
#: radius is millimetres typed in the metre field
MAX_PLAUSIBLE_PATCH = 0.02       # m
#: a person's pinch opens no wider than this: a larger squeeze or regrip step in the metre field is millimetres
MAX_PLAUSIBLE_PINCH_SPAN = 0.2   # m
#: a hand's tremor and slow drift of its aperture stay well below this (a tremor: well below 1 mm): a larger one in
#: the metre field is millimetres typed there (tremor: 0.05 meant 0.05 mm)
MAX_PLAUSIBLE_TREMOR = 0.02      # m


def seeded_stream(seed: int, name: str) -> random.Random:
    """A random stream of its own for ``name``, derived from ``seed``: reproducible (a string seed is hashed with
    SHA-512, not Python's per-process hash) and independent of ``Random(seed)`` and of every other name's stream."""
    return random.Random(f"{name}/{seed}")

# ================================================================================================ sim components


class SimForceSensor(Component):
    """Camera-rate force sensor stand-in: a ground-truth force sampled per frame, delayed and noisy."""

    name = "sim-force-sensor"
    kind = Kind.SENSOR
    default_rate = 60.0
    inputs = {"force_true": Port("float64", (), "N", "ground-truth normal force (e.g. sim-gripper.contact_force)")}
    outputs = {"force": Port("float64", (), "N", "sensed force, stamped with its capture time")}

    class Params(Params):
        delay_frames: int = Field(1, ge=0, le=10, description="frames between capture and output "
                                  "(exposure, transfer, estimation)")
        noise: Newtons = Field(0.02, ge=0, description="standard deviation of the estimate's noise in contact",
                               json_schema_extra={"unit": "N"})
        gain: float = Field(1.0, gt=0, description="scale error of the estimate")
        seed: int = Field(0, description="noise seed")

    def configure(self) -> None:
        self.rng = random.Random(self.params.seed)
        self.buf: deque[tuple[float, float]] = deque(maxlen=self.params.delay_frames + 1)

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        f = inputs.value("force_true")
        if f is None:
            return None
        f = float(f)
        if f > 0.0 and math.isfinite(f):
            f = max(0.0, self.params.gain * f + self.rng.gauss(0.0, self.params.noise))
        self.buf.append((t, f))
        if len(self.buf) <= self.params.delay_frames:
            return None
        stamp, val = self.buf[0]
        return {"force": Sample(val, stamp)}


class SimPivot(Component):
    """A cylinder pinched off its centre of mass that pivots under gravity against the grip's friction.

    Gravity turns it about the pinch axis against the torsional friction of the contacts (static/kinetic, from the
    grip force); it drops when the grip cannot carry its weight. It rests on a support until the grip first holds it.
    """

    name = "sim-pivot"
    kind = Kind.SENSOR
    default_rate = 1000.0
    inputs = {"grip_force": Port("float64", (), "N", "normal force of the fingers on the object")}
    outputs = {
        "angle": Port("float64", (), "rad", "angle below the horizontal"),
        "angular_velocity": Port("float64", (), "rad/s", "d(angle)/dt"),
        "slipping": Port("bool", (), "", "the object turns in the grip"),
        "dropped": Port("bool", (), "", "the grip could not carry the weight: the object fell"),
    }

    class Params(Params):
        mass: Kilograms = Field(0.03, gt=0, description="object mass", json_schema_extra={"unit": "kg"})
        length: Meters = Field(0.12, gt=0, description="cylinder length", json_schema_extra={"unit": "m"})
        com_offset: Meters = Field(0.03, ge=0, description="pinch axis to centre of mass",
                                   json_schema_extra={"unit": "m"})
        friction_radius: Meters = Field(0.0025, gt=0, description="effective torsional friction radius of a "
                                        "contact patch (2/3 of its radius for uniform pressure)",
                                        json_schema_extra={"unit": "m"})
        contacts: int = Field(2, ge=1, le=2, description="finger contacts carrying friction")
        mu_static: float = Field(1.0, gt=0, description="static friction coefficient")
        mu_kinetic: float = Field(0.85, gt=0, description="kinetic friction coefficient")
        damping: float = Field(5e-3, ge=0, description="viscous damping about the pinch axis (the gel's "
                               "viscoelasticity)",
                               json_schema_extra={"unit": "N*m*s/rad"})
        initial_angle: Radians = Field(0.0, description="start angle", json_schema_extra={"unit": "rad"})
        max_angle: Radians = Field(math.pi / 2, description="hanging straight down", json_schema_extra={"unit": "rad"})
        lift_force: Newtons = Field(2.8, ge=0, description="grip force at which the operator has the object and "
                                    "its support goes away", json_schema_extra={"unit": "N"})
        lift_time: Seconds = Field(0.5, ge=0, description="how long the grip must reach lift_force first",
                                   json_schema_extra={"unit": "s"})
        drop_time: Seconds = Field(0.05, ge=0, description="the object falls out when the grip cannot carry its "
                                   "weight for this long", json_schema_extra={"unit": "s"})
        substep: Seconds = Field(2.5e-4, gt=0, description="largest integration step", json_schema_extra={"unit": "s"})

        @field_validator("length", "com_offset")
        @classmethod
        def _object(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_OBJECT, "m",
                                      "longer than an object pivoted between two fingertips")

        @field_validator("friction_radius")
        @classmethod
        def _patch(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_PATCH, "m", "larger than a contact patch on a "
                                      "DIGIT", "; its sensing area: about 15-20 x 20-25 mm")

        @model_validator(mode="after")
        def _friction(self) -> "SimPivot.Params":
            if self.mu_kinetic > self.mu_static:
                raise ValueError(f"mu_kinetic ({self.mu_kinetic:g}) is above mu_static ({self.mu_static:g}): "
                                 f"expected mu_kinetic <= mu_static (sliding friction is at most sticking friction)")
            if self.max_angle < self.initial_angle:
                raise ValueError(f"max_angle ({self.max_angle:g} rad) is below initial_angle "
                                 f"({self.initial_angle:g} rad): expected initial_angle <= max_angle (the object "
                                 f"turns down from initial_angle to max_angle)")
            return self

        @model_validator(mode="after")
        def _centre_of_mass_on_the_object(self) -> "SimPivot.Params":
            if self.com_offset > self.length / 2:   # a uniform cylinder: its centre of mass is at its middle
                raise ValueError(f"com_offset ({self.com_offset * 1e3:g} mm) is more than half the length "
                                 f"({self.length * 1e3:g} mm): expected com_offset <= length / 2 (the object is a "
                                 f"uniform cylinder, its centre of mass at its middle, and the pinch axis on the "
                                 f"object)")
            return self

    def configure(self) -> None:
        p = self.params
        self.weak_since: float | None = None
        self.firm_since: float | None = None
        self.inertia = p.mass * (p.length ** 2 / 12.0 + p.com_offset ** 2)
        self.theta = p.initial_angle
        self.omega = 0.0
        self.dropped = False
        self.slipping = False
        self.supported = True       # on its support until the grip first holds it
        self.t_last: float | None = None
        self.last_motion = 0.0

    def torque_gravity(self, theta: float) -> float:
        p = self.params
        return p.mass * G * p.com_offset * math.cos(theta)

    def holding_force(self, theta: float, kinetic: bool = False) -> float:
        """Grip force (N) that stops (kinetic) or holds (static) the object at ``theta``."""
        p = self.params
        mu = p.mu_kinetic if kinetic else p.mu_static
        return self.torque_gravity(theta) / (p.contacts * mu * p.friction_radius)

    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        p = self.params
        n = inputs.value("grip_force", 0.0)
        n = float(n) if n is not None and math.isfinite(float(n)) else 0.0
        n = max(n, 0.0)
        dt = 0.0 if self.t_last is None else max(0.0, t - self.t_last)
        self.t_last = t
        if self.supported:
            if n < p.lift_force:
                self.firm_since = None
            elif self.firm_since is None:
                self.firm_since = t
            elif t - self.firm_since >= p.lift_time:
                self.supported = False          # grasped firmly: the support goes away
        elif not self.dropped and p.contacts * p.mu_static * n < p.mass * G:
            if self.weak_since is None:
                self.weak_since = t
            if t - self.weak_since >= p.drop_time:
                self.dropped = True
        else:
            self.weak_since = None
        if dt > 0 and not self.dropped and not self.supported:
            k = max(1, int(math.ceil(dt / p.substep - 1e-9)))
            h = dt / k
            cap_s = p.contacts * p.mu_static * p.friction_radius * n
            cap_k = p.contacts * p.mu_kinetic * p.friction_radius * n
            for _ in range(k):
                tg = self.torque_gravity(self.theta)
                if self.omega == 0.0 and abs(tg) <= cap_s:
                    continue                        # stuck
                drive = tg - p.damping * self.omega
                w_new = self.omega + h * (drive - cap_k * math.copysign(1.0, self.omega if self.omega else drive)) \
                    / self.inertia
                if self.omega != 0.0 and w_new * self.omega <= 0.0:
                    w_new = 0.0                     # friction stops it; it does not reverse it
                self.omega = w_new
                self.theta += h * self.omega
                if self.theta >= p.max_angle:
                    self.theta, self.omega = p.max_angle, 0.0
        self.slipping = self.omega != 0.0
        if self.slipping:
            self.last_motion = t
        return {"angle": self.theta, "angular_velocity": self.omega, "slipping": self.slipping,
                "dropped": self.dropped}

    def status(self) -> dict[str, Any]:
        return {"angle_rad": getattr(self, "theta", 0.0), "slipping": getattr(self, "slipping", False),
                "dropped": getattr(self, "dropped", False)}


class PivotOperator(Component):
    """A simulated operator who pivots a held object to a target angle (drives sim-omega7's intent_opening).

    Sees the angle (delay, bias, noise), feels the grip force or not (strategy ``force`` or ``position``), moves the
    hand with tremor and drift.
    """

    name = "pivot-operator"
    kind = Kind.CONTROLLER
    default_rate = 100.0
    inputs = {
        "angle": Port("float64", (), "rad", "object angle (seen through the operator's eyes)"),
        "contact": Port("bool", (), "", "fingers touch the object (seen)", required=False),
        "felt_force": Port("float64", (), "N", "force rendered on the fingers (felt; force strategy)",
                           required=False),
        "leader_opening": Port("float64", (), "m", "leader opening (proprioception)", required=False),
    }
    outputs = {"intent_opening": Port("float64", (), "m", "where the operator wants the gripper")}

    class Params(Params):
        strategy: Literal["force", "position"] = Field("force", description="force: regulates the felt grip "
                                                       "force; position: only moves the hand (visual only)")
        target_angle: Radians = Field(math.radians(30), gt=0, le=math.pi / 2, description="angle to reach, below "
                                      "the horizontal (the object turns down from 0 to hanging, pi/2)",
                                      json_schema_extra={"unit": "rad"})
        tolerance: Radians = Field(math.radians(5), gt=0, description="success band around the target",
                                   json_schema_extra={"unit": "rad"})
        start_opening: Meters = Field(0.022, gt=0, description="hand opening at the start",
                                      json_schema_extra={"unit": "m"})
        hold_force: Newtons = Field(3.0, gt=0, description="firm grip force (force strategy)",
                                    json_schema_extra={"unit": "N"})
        squeeze: Meters = Field(0.0025, gt=0, description="closing beyond the seen contact (position strategy; "
                                "without a felt force people over-grip)", json_schema_extra={"unit": "m"})
        loosen_rate_force: float = Field(0.3, gt=0, description="grip force decrease while loosening",
                                         json_schema_extra={"unit": "N/s"})
        loosen_rate_position: float = Field(0.0006, gt=0, description="hand opening speed while loosening",
                                            json_schema_extra={"unit": "m/s"})
        regrip_step: Meters = Field(0.001, gt=0, description="hand closing to stop the object (position strategy)",
                                    json_schema_extra={"unit": "m"})
        hand_speed: float = Field(0.02, gt=0, description="fastest hand motion", json_schema_extra={"unit": "m/s"})
        force_gain: float = Field(0.01, gt=0, description="hand speed per newton of felt force error",
                                  json_schema_extra={"unit": "m/(N*s)"})
        visual_delay: Seconds = Field(0.25, ge=0, description="visual reaction delay", json_schema_extra={"unit": "s"})
        haptic_delay: Seconds = Field(0.1, ge=0, description="haptic reaction delay", json_schema_extra={"unit": "s"})
        angle_bias: Radians = Field(math.radians(2.5), ge=0, description="std of the per-trial misjudgement of "
                                    "the angle", json_schema_extra={"unit": "rad"})
        angle_noise: Radians = Field(math.radians(0.5), ge=0, description="std of the perception noise",
                                     json_schema_extra={"unit": "rad"})
        force_noise: float = Field(0.07, ge=0, description="relative std of the felt force (Weber fraction)")
        variability: float = Field(0.3, ge=0, le=0.9, description="relative std, per trial and per movement, of "
                                   "the operator's rates and step sizes")
        tremor: Meters = Field(5e-5, ge=0, description="RMS hand tremor", json_schema_extra={"unit": "m"})
        hand_drift: Meters = Field(4e-4, ge=0, description="RMS slow drift of the finger aperture the operator "
                                   "cannot sense without a force to push against", json_schema_extra={"unit": "m"})
        drift_time: Seconds = Field(1.5, gt=0, description="time constant of the drift",
                                    json_schema_extra={"unit": "s"})
        lead_time: Seconds = Field(0.3, ge=0, description="how far ahead the operator extrapolates the motion",
                                   json_schema_extra={"unit": "s"})
        settle_time: Seconds = Field(1.0, gt=0, description="still this long before judging the result",
                                     json_schema_extra={"unit": "s"})
        seed: int = Field(0, description="seed of this operator's noise (one trial)")
        stop_when_done: bool = Field(True, description="end the run when the operator is done")

        # a bare number is SI: millimetres (per second) typed in these fields are refused, naming the field
        @field_validator("start_opening")
        @classmethod
        def _opening(cls, v: float, info: Any) -> float:
            return plausible_opening(info.field_name, v)   # 22 meant 22 mm

        @field_validator("squeeze", "regrip_step")
        @classmethod
        def _pinch(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_PINCH_SPAN, "m",
                                      "wider than a hand's pinch opens")

        @field_validator("tremor", "hand_drift")
        @classmethod
        def _tremor(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_TREMOR, "m",
                                      "more than a hand trembles or drifts", "; a tremor: well below 1 mm")

        @field_validator("hand_speed", "loosen_rate_position")
        @classmethod
        def _speed(cls, v: float, info: Any) -> float:
            return plausible_speed(info.field_name, v)   # 20 meant 20 mm/s

    #: the operator's noise streams, each derived from ``seed`` and its name (:func:`seeded_stream`): what the
    #: operator sees and how the hand shakes do not depend on what it feels or does (the felt force's noise and a
    #: regrip's size come from streams of their own), and none repeats sim-force-sensor's numbers (``Random(seed)``)
    STREAMS = ("trial", "eyes", "hand", "touch", "moves")

    def configure(self) -> None:
        p = self.params
        self.rngs = {name: seeded_stream(p.seed, f"pivot-operator/{name}") for name in self.STREAMS}
        trial = self.rngs["trial"]
        self.bias = trial.gauss(0.0, p.angle_bias)
        var = p.variability
        self.k_loosen = max(0.2, 1.0 + var * trial.gauss(0.0, 1.0))     # this trial's loosening speed factor
        self.k_squeeze = max(0.3, 1.0 + var * trial.gauss(0.0, 1.0))
        self.angle_hist: deque[tuple[float, float]] = deque()
        self.seen: deque[tuple[float, float]] = deque()
        self.force_hist: deque[tuple[float, float]] = deque()
        self.contact_hist: deque[tuple[float, bool]] = deque()
        self.u = p.start_opening
        self.phase = "grasp"
        self.t_phase = 0.0
        self.f_target = 0.0
        self.noise = 0.0
        self.tremor = 0.0
        self.drift = 0.0
        self.theta_p = 0.0
        self.omega_p = 0.0
        self.theta_start = 0.0
        self.still_since: float | None = None
        self.contact_seen_at: float | None = None
        self.done_at: float | None = None
        self.result = ""
        self.regrip_from = 0.0
        self.regrip_size = p.regrip_step
        self.t_last: float | None = None

    @staticmethod
    def _delayed(hist: deque, t: float, delay: float, value: Any) -> Any:
        hist.append((t, value))
        while len(hist) > 1 and hist[1][0] <= t - delay:
            hist.popleft()
        return hist[0][1]

    def _set_phase(self, name: str, t: float) -> None:
        self.phase, self.t_phase = name, t

    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        p = self.params
        dt = 0.0 if self.t_last is None else t - self.t_last
        self.t_last = t
        # --- perception
        a = inputs.value("angle", 0.0)
        a_del = self._delayed(self.angle_hist, t, p.visual_delay, float(a))
        if dt > 0:
            decay = math.exp(-dt / 0.5)                 # perception error: an Ornstein-Uhlenbeck process, 0.5 s
            eyes, hand = self.rngs["eyes"], self.rngs["hand"]
            self.noise = self.noise * decay + p.angle_noise * math.sqrt(1.0 - decay * decay) * eyes.gauss(0, 1)
            self.tremor += min(1.0, dt / 0.02) * (hand.gauss(0.0, p.tremor * 3.0) - self.tremor)
            dec = math.exp(-dt / p.drift_time)
            self.drift = self.drift * dec + p.hand_drift * math.sqrt(1.0 - dec * dec) * hand.gauss(0.0, 1.0)
        self.theta_p = a_del + self.bias + self.noise
        self.seen.append((t, self.theta_p))
        while len(self.seen) > 1 and self.seen[0][0] < t - 0.5:
            self.seen.popleft()
        t_old, th_old = self.seen[0]
        self.omega_p = (self.theta_p - th_old) / (t - t_old) if t > t_old else 0.0   # seen motion over 0.5 s
        f_felt = 0.0
        if "felt_force" in inputs and inputs.get("felt_force") is not None:
            f_raw = float(inputs.value("felt_force", 0.0))
            f_del = self._delayed(self.force_hist, t, p.haptic_delay, f_raw)
            f_felt = f_del * (1.0 + p.force_noise * self.rngs["touch"].gauss(0.0, 1.0) * 0.3)
        contact = bool(self._delayed(self.contact_hist, t, p.visual_delay, bool(inputs.value("contact", False))))
        force_mode = p.strategy == "force"
        target, tol = p.target_angle, p.tolerance
        # --- the plan
        ph = self.phase
        if ph == "grasp":
            if force_mode:
                if f_felt < p.hold_force:
                    self.u -= min(p.hand_speed * 0.5, p.force_gain * (p.hold_force - f_felt) + 0.005) * dt
                else:
                    self.f_target = p.hold_force
                    self._set_phase("hold", t)
            else:
                if contact and self.contact_seen_at is None:
                    self.contact_seen_at = t
                    self.u_goal = self.u - p.squeeze * self.k_squeeze
                if self.contact_seen_at is None:
                    self.u -= 0.005 * dt
                else:
                    self.u = max(self.u_goal, self.u - p.hand_speed * 0.5 * dt)
                    if self.u <= self.u_goal:
                        self._set_phase("hold", t)
        elif ph == "hold":
            if t - self.t_phase > 1.0:
                self.theta_start = self.theta_p
                self._set_phase("loosen", t)
        elif ph == "loosen":
            if force_mode:
                self.f_target = max(0.0, self.f_target - p.loosen_rate_force * self.k_loosen * dt)
            else:
                self.u += p.loosen_rate_position * self.k_loosen * dt
            if self.theta_p - self.theta_start > math.radians(3.0) or self.omega_p > math.radians(5.0):
                self._set_phase("rotate", t)
        elif ph == "rotate":
            if self.theta_p + max(self.omega_p, 0.0) * p.lead_time >= target:
                self.regrip_from = self.u
                self.regrip_size = p.regrip_step * max(0.2, 1.0 + p.variability
                                                       * self.rngs["moves"].gauss(0.0, 1.0))
                if force_mode:
                    self.f_target = p.hold_force
                self._set_phase("regrip", t)
            elif abs(self.omega_p) < math.radians(3.0):
                if self.still_since is None:
                    self.still_since = t
                elif t - self.still_since > 0.5:
                    self.still_since = None
                    self.theta_start = self.theta_p
                    self._set_phase("loosen", t)
            else:
                self.still_since = None
        elif ph == "regrip":
            if not force_mode:
                self.u = max(self.regrip_from - self.regrip_size, self.u - p.hand_speed * dt)
            if abs(self.omega_p) < math.radians(3.0):
                if self.still_since is None:
                    self.still_since = t
                elif t - self.still_since >= p.settle_time:
                    self.still_since = None
                    if self.theta_p < target - tol:
                        self.theta_start = self.theta_p
                        self._set_phase("loosen", t)    # not there yet: loosen again
                    else:
                        self.done_at = t
                        self.result = "on-target" if abs(self.theta_p - target) <= tol else "overshoot"
                        self._set_phase("done", t)
                        if p.stop_when_done:
                            self.ctx.request_stop(f"operator done ({self.result}) at t={t:.2f} s")
            else:
                self.still_since = None
        # --- force regulation by the hand (only when the force is felt)
        if force_mode and self.phase in ("hold", "loosen", "rotate", "regrip", "done"):
            v = p.force_gain * (f_felt - self.f_target)
            v = max(-p.hand_speed, min(p.hand_speed, v))
            self.u += v * dt
        return {"intent_opening": self.u + self.tremor + self.drift}

    def status(self) -> dict[str, Any]:
        return {"phase": getattr(self, "phase", ""), "seen_angle_rad": getattr(self, "theta_p", 0.0),
                "target_force_n": getattr(self, "f_target", 0.0)}


@hookimpl
def teletouch_components():
    return [SimForceSensor, SimPivot, PivotOperator]


# ================================================================================================ graphs


#: the object's surface where it presses into the fingertip gel: the paper's probe (5 mm radius, curved tip), the
#: same in sim-gripper (force) and sim-digit (image), the shape the force calibration was made with
OBJECT_SURFACE = {"indenter": "probe", "indenter_radius": 0.005}

DEFAULT_INTENT = {"type": "close-and-hold", "start_opening": 0.02, "target_opening": 0.010, "speed": 0.005,
                  "start_time": 0.5, "hold_time": 3.0, "release": True}


#: max_age (s) of the 1 kHz wires between the devices and the controller in sim_graph (50 periods)
WIRE_MAX_AGE = 0.05
#: faults.startup_grace (s) of sim_graph: nothing to start up under the simulated clock (every node produces from
#: t=0), so the max_age checks start after 6 camera frames rather than after the default 1 s
SIM_STARTUP_GRACE = 0.1


def sim_graph(controller: str = "position-force", sensor: str = "image", *, duration: float = 10.0,
              intent: dict[str, Any] | None = None, object_width: float = 0.015, extra_nodes: list | None = None,
              controller_params: dict[str, Any] | None = None, leader_params: dict[str, Any] | None = None,
              gripper_params: dict[str, Any] | None = None, seed: int = 0, name: str = "paper-sim") -> dict:
    """The simulated twin of the paper's setup as a graph document (examples/paper-sim.yaml is this with the
    defaults). ``sensor``: ``image`` (sim-digit -> depth -> poly-force, the real estimators), ``gt`` (sim-digit's
    ground-truth max depth -> poly-force: no depth estimation) or ``ideal`` (sim-force-sensor: ground-truth force at
    the camera rate, one frame late, noisy). The 1 kHz wires between the devices and the controller have a
    ``max_age`` (WIRE_MAX_AGE, as examples/paper.yaml): a device or a controller whose data stops is a fault of the
    run (its consumers are stopped and the devices made safe), not silence; the 60 Hz force wire has none (the
    controller's stale_after and fault_after_lost handle a lost estimate); the checks start at SIM_STARTUP_GRACE."""
    intent = intent or dict(DEFAULT_INTENT)
    nodes: list[dict[str, Any]] = [
        {"id": "leader", "plugin": "sim-omega7", "rate": 1000,
         "params": {"intent": intent, **(leader_params or {})},
         "inputs": {"gripper_force": {"from": "controller.gripper_force", "max_age": WIRE_MAX_AGE}}},
        {"id": "gripper", "plugin": "sim-gripper", "rate": 1000,
         "params": {"object_width": object_width, "initial_opening": 0.02, **OBJECT_SURFACE,
                    **(gripper_params or {})},
         "inputs": {"opening_command": {"from": "controller.opening_command", "max_age": WIRE_MAX_AGE}}},
    ]
    if sensor == "image":
        nodes += [
            {"id": "digit", "plugin": "sim-digit", "rate": 60,
             "params": {"indenter": OBJECT_SURFACE["indenter"], "indenter_radius": OBJECT_SURFACE["indenter_radius"]},
             "inputs": {"indentation": "gripper.indentation"}},
            {"id": "depth", "plugin": "depth", "rate": 60, "inputs": {"image": "digit.image"}},
            {"id": "force", "plugin": "poly-force", "rate": 60,
             "inputs": {"max_depth": "depth.max_depth", "contact_area": "depth.contact_area",
                        "centroid": "depth.centroid"}},
        ]
    elif sensor == "gt":
        nodes += [
            {"id": "digit", "plugin": "sim-digit", "rate": 60,
             "params": {"indenter": OBJECT_SURFACE["indenter"], "indenter_radius": OBJECT_SURFACE["indenter_radius"]},
             "inputs": {"indentation": "gripper.indentation"}},
            {"id": "force", "plugin": "poly-force", "rate": 60,
             "inputs": {"max_depth": "digit.gt_max_depth", "centroid": "digit.gt_position"}},
        ]
    elif sensor == "ideal":
        nodes += [{"id": "force", "plugin": "sim-force-sensor", "rate": 60, "params": {"seed": seed},
                   "inputs": {"force_true": "gripper.contact_force"}}]
    else:
        raise ValueError(f"sensor must be 'image', 'gt' or 'ideal', got {sensor!r}")
    nodes.append({"id": "controller", "plugin": controller, "rate": 1000, "params": dict(controller_params or {}),
                  "inputs": {"leader_opening": {"from": "leader.gripper_opening", "max_age": WIRE_MAX_AGE},
                             "leader_velocity": "leader.gripper_velocity",
                             "follower_opening": {"from": "gripper.opening", "max_age": WIRE_MAX_AGE},
                             "force": "force.force"}})
    nodes += list(extra_nodes or [])
    return {"name": name, "clock": "sim", "duration": duration, "faults": {"startup_grace": SIM_STARTUP_GRACE},
            "nodes": nodes}


def build_runtime(doc: dict, registry: Any = None) -> Any:
    import yaml

    from teletouch.graph import load_graph_text
    from teletouch.runtime import Runtime

    spec = load_graph_text(yaml.safe_dump(doc, sort_keys=False), f"<{doc.get('name', 'experiment')}>",
                           registry=registry)
    return Runtime(spec, log=lambda m: None)


class Recorder:
    """A tap that keeps chosen ports as lists of (t, value)."""

    def __init__(self, keys: list[str]):
        self.want: dict[str, list[str]] = {}
        for k in keys:
            node, port = k.split(".", 1)
            self.want.setdefault(node, []).append(port)
        self.data: dict[str, list[tuple[float, Any]]] = {k: [] for k in keys}

    def __call__(self, node: str, t: float, out: dict) -> None:
        ports = self.want.get(node)
        if not ports:
            return
        for port in ports:
            v = out.get(port)
            if v is not None:
                if v.__class__ is Sample:
                    v = v.value
                self.data[f"{node}.{port}"].append((t, v))

    def series(self, key: str) -> tuple[Any, Any]:
        import numpy as np

        d = self.data[key]
        if not d:
            return np.zeros(0), np.zeros(0)
        t = np.array([x[0] for x in d], dtype=float)
        v = np.array([x[1] for x in d], dtype=float)
        return t, v


SENSORS = ("image", "gt", "ideal")


def finite_json(v: Any) -> Any:
    """``v`` with every non-finite float replaced by None (JSON has no NaN or Infinity: ``json.dumps`` would write
    tokens that strict readers refuse)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: finite_json(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [finite_json(x) for x in v]
    return v


def dumps(result: dict[str, Any], **kw: Any) -> str:
    """An experiment's result as strict JSON (non-finite figures as null)."""
    return json.dumps(finite_json(result), allow_nan=False, **kw)


def check_run(res: Any, what: str) -> None:
    """Raise unless the run ``res`` (a RunResult) ended ok or stopped: KeyboardInterrupt where a Ctrl-C ended it (an
    interruption, exit 130 on the command line, not a fault), RuntimeError naming ``what`` otherwise."""
    if res.status == "interrupted":
        raise KeyboardInterrupt(f"{what}: {res.message}")
    if res.status not in ("ok", "stopped"):
        raise RuntimeError(f"{what} ended with {res.status}: {res.message}")


def out_dir_problem(out: str | Path) -> str | None:
    """None if ``out`` is (or could be made) a folder for the results; else what is wrong, before anything runs."""
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"{out}: cannot make a folder there ({exc.strerror or exc})"
    return None


def save_outputs(out: str | Path, name: str, result: dict[str, Any], plot: Any = None) -> None:
    """Write an experiment's metrics to ``out/<name>.json`` and, when ``plot`` is given, its figure by
    ``plot(out/<name>.png)``; the paths go into ``result["files"]``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(dumps(result, indent=2) + "\n")
    result["files"] = [str(out / f"{name}.json")]
    if plot is not None:
        plot(out / f"{name}.png")
        result["files"].append(str(out / f"{name}.png"))


# ================================================================================================ contact


CONTACT_KEYS = ["leader.gripper_opening", "leader.intended_opening", "gripper.opening", "gripper.contact",
                "gripper.contact_force", "force.force", "controller.gripper_force", "controller.energy"]


def run_contact_once(feedback: bool | str, *, sensor: str = "image", duration: float = 6.0, registry: Any = None,
                     settle: float = 0.0) -> tuple[dict[str, Any], Recorder]:
    """One run of the rigid-object contact experiment. ``feedback``: True (position-force), False (no-feedback)
    or a controller plugin name. Returns (metrics, recorder); a run that faults raises RuntimeError, one ended by
    Ctrl-C KeyboardInterrupt (:func:`check_run`)."""
    import numpy as np

    hold = max(0.5, duration - 0.5 - 2.0 - 2.0)
    intent = {"type": "close-and-hold", "start_opening": 0.02, "target_opening": 0.010, "speed": 0.005,
              "start_time": 0.5, "hold_time": hold, "release": True}
    controller = feedback if isinstance(feedback, str) else "position-force" if feedback else "no-feedback"
    doc = sim_graph(controller, sensor, duration=duration, intent=intent, name="contact-" + controller)
    rt = build_runtime(doc, registry)
    rec = Recorder(CONTACT_KEYS)
    rt.add_tap(rec)
    w0 = time.perf_counter()
    res = rt.run()
    wall = time.perf_counter() - w0
    label = feedback if isinstance(feedback, str) else "with feedback" if feedback else "without feedback"
    check_run(res, f"contact run ({label})")
    tl, xl = rec.series("leader.gripper_opening")
    tf, xf = rec.series("gripper.opening")
    tc, c = rec.series("gripper.contact")
    tg, fg = rec.series("gripper.contact_force")
    te, fe = rec.series("force.force")
    tr, fr = rec.series("controller.gripper_force")
    xf_l = np.interp(tl, tf, xf)
    cont = np.interp(tl, tc, c.astype(float)) > 0.5
    if settle > 0 and cont.any():
        first = tl[cont][0]
        cont &= tl >= first + settle
    err = np.abs(xl - xf_l)
    touched = bool(cont.any())
    # no contact at all (a run too short to reach the object): the in-contact figures are None, not NaN
    mean_err = float(err[cont].mean()) if touched else None
    fg_at_e = np.interp(te, tg, fg) if len(te) else np.zeros(0)
    in_c = fg_at_e > 0.05
    est_err = float(np.mean(np.abs(fe[in_c] - fg_at_e[in_c]))) if in_c.any() else None
    # the rendered force's ripple in contact: its largest deviation from a 50 ms moving average (chatter)
    ripple = 0.0
    if len(fr) > 51:
        k = np.ones(51) / 51.0
        smooth = np.convolve(fr, k, mode="same")
        in_contact = np.interp(tr, tc, c.astype(float)) > 0.5
        in_contact[:25] = in_contact[-25:] = False
        if in_contact.any():
            ripple = float(np.abs(fr - smooth)[in_contact].max())
    metrics = {
        "contact": touched,
        "mean_error_m": mean_err,
        "max_error_m": float(err[cont].max()) if touched else None,
        "time_in_contact_s": float(cont.sum() * (tl[1] - tl[0])) if len(tl) > 1 and touched else 0.0,
        "max_contact_force_n": float(fg.max()) if len(fg) else 0.0,
        "max_rendered_force_n": float(np.abs(fr).max()) if len(fr) else 0.0,
        "min_rendered_force_n": float(fr.min()) if len(fr) else 0.0,
        "rendered_force_ripple_n": ripple,
        "force_estimate_mae_n": est_err,
        "sim_time_s": res.sim_time,
        "wall_time_s": wall,
        "status": res.status,
    }
    return metrics, rec


def contact_plot(path: Path, runs: dict[str, Recorder]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(runs), figsize=(6 * len(runs), 6.5), sharex=True, squeeze=False)
    for j, (label, rec) in enumerate(runs.items()):
        ax = axes[0][j]
        t, x = rec.series("leader.gripper_opening")
        ax.plot(t, x * 1e3, label="desired (leader)")
        t, x = rec.series("gripper.opening")
        ax.plot(t, x * 1e3, label="actual (follower)")
        t, x = rec.series("leader.intended_opening")
        ax.plot(t, x * 1e3, ":", color="grey", label="operator's intent")
        ax.set_ylabel("opening (mm)")
        ax.set_title(label)
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
        ax = axes[1][j]
        t, f = rec.series("gripper.contact_force")
        ax.plot(t, f, label="contact force (ground truth)")
        t, f = rec.series("force.force")
        ax.step(t, f, where="post", label="estimated (camera rate)")
        t, f = rec.series("controller.gripper_force")
        ax.plot(t, f, label="rendered to the operator")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("force (N)")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: the operator closes from 20 mm at 5 mm/s from 0.5 s: the fingers reach the 15 mm object at about 1.5 s
CONTACT_MIN_DURATION = 2.0


def _contact_duration_problem(duration: Any) -> str | None:
    if isinstance(duration, bool) or not isinstance(duration, (int, float)) or not math.isfinite(duration):
        return f"expected a finite number of seconds, got {duration!r}"
    if duration < CONTACT_MIN_DURATION:
        return (f"must be at least {CONTACT_MIN_DURATION:g} s (the fingers reach the object at about 1.5 s), "
                f"got {duration:g} s")
    return None


def experiment_contact(duration: float = 6.0, sensor: str = "image", out: str | Path | None = None,
                       registry: Any = None, plot: bool = True, baselines: bool = False) -> dict[str, Any]:
    """Run the contact experiment with and without feedback; write metrics JSON and the Fig.-4 plot."""
    problem = _contact_duration_problem(duration)
    if problem:
        raise ValueError(f"duration: {problem}")
    if sensor not in SENSORS:
        raise ValueError(f"sensor: expected one of {', '.join(SENSORS)}, got {sensor!r}")
    problem = None if out is None else out_dir_problem(out)
    if problem:
        raise ValueError(f"out: {problem}")
    with_m, with_r = run_contact_once(True, sensor=sensor, duration=duration, registry=registry)
    without_m, without_r = run_contact_once(False, sensor=sensor, duration=duration, registry=registry)
    e_with, e_without = with_m["mean_error_m"], without_m["mean_error_m"]
    result: dict[str, Any] = {
        "experiment": "contact",
        "sensor": sensor,
        "duration_s": duration,
        "with_feedback": with_m,
        "without_feedback": without_m,
        # None where a run had no contact or the error with feedback is exactly zero
        "ratio_without_to_with": (e_without / e_with if e_with is not None and e_without is not None and e_with > 0
                                  else None),
        "paper_mean_error_m": 0.0006,
        "target_with_feedback_m": 0.0003,
    }
    runs = {"with force feedback": with_r, "without force feedback": without_r}
    if baselines:
        pp_m, pp_r = run_contact_once("position-position", sensor=sensor, duration=duration, registry=registry)
        result["position_position"] = pp_m
        runs["position-position baseline"] = pp_r
    if out is not None:
        save_outputs(out, "contact", result, (lambda path: contact_plot(path, runs)) if plot else None)
    return result


# ================================================================================================ pivot


PIVOT_KEYS = ["pivot.angle", "pivot.dropped", "gripper.contact_force", "controller.gripper_force"]

#: rad/s: the object is at rest when the operator finishes if it turns slower than this (1 deg/s: over the operator's
#: 1 s settle time, a fifth of the 5 deg tolerance); sim-pivot's object stuck in the grip turns at exactly 0
PIVOT_REST_SPEED = math.radians(1.0)


def run_pivot_trial(feedback: bool, seed: int, *, sensor: str = "ideal", time_limit: float = 30.0,
                    registry: Any = None, operator: dict[str, Any] | None = None,
                    pivot: dict[str, Any] | None = None, record: bool = False) -> dict[str, Any]:
    """One pivoting trial. Success: the operator finishes within the time limit with the object at rest (true
    angular velocity below PIVOT_REST_SPEED) within the tolerance of the target angle (true angle), not dropped.
    Outcomes: success, dropped, timeout, overshoot or undershoot (the angle outside the tolerance, moving or not),
    moving (within the tolerance, not at rest). A trial that faults raises RuntimeError, one ended by Ctrl-C
    KeyboardInterrupt (:func:`check_run`)."""
    op_params = {"strategy": "force" if feedback else "position", "seed": seed, **(operator or {})}
    extra = [
        {"id": "pivot", "plugin": "sim-pivot", "rate": 1000, "params": dict(pivot or {}),
         "inputs": {"grip_force": "gripper.contact_force"}},
        {"id": "operator", "plugin": "pivot-operator", "rate": 100, "params": op_params,
         "inputs": {"angle": "pivot.angle", "contact": "gripper.contact", "felt_force": "controller.gripper_force",
                    "leader_opening": "leader.gripper_opening"}},
    ]
    width = 0.02
    doc = sim_graph("position-force" if feedback else "no-feedback", sensor, duration=time_limit,
                    intent={"type": "hold", "opening": op_params.get("start_opening", 0.022)},
                    object_width=width, extra_nodes=extra, seed=seed,
                    gripper_params={"initial_opening": 0.022},
                    name=f"pivot-{'force' if feedback else 'visual'}-{seed}")
    doc["nodes"][0]["inputs"]["intent_opening"] = "operator.intent_opening"
    rt = build_runtime(doc, registry)
    rec = Recorder(PIVOT_KEYS) if record else None
    if rec is not None:
        rt.add_tap(rec)
    res = rt.run()
    check_run(res, f"pivot trial {seed}")
    op = rt.component("operator")
    pv = rt.component("pivot")
    target, tol = op.params.target_angle, op.params.tolerance
    angle, omega = pv.theta, pv.omega
    done = op.done_at is not None
    on_target = abs(angle - target) <= tol
    at_rest = abs(omega) < PIVOT_REST_SPEED
    success = bool(done and not pv.dropped and on_target and at_rest)
    if pv.dropped:
        outcome = "dropped"
    elif not done:
        outcome = "timeout"
    elif success:
        outcome = "success"
    elif on_target:
        outcome = "moving"
    else:
        outcome = "overshoot" if angle > target else "undershoot"
    trial = {"seed": seed, "success": success, "outcome": outcome,
             # the operator's clock sums 1 ms steps: 8.860000000000001 -> 8.86 (to the microsecond)
             "completion_time_s": round(op.done_at, 6) if done else None,
             "final_angle_rad": float(angle), "target_rad": float(target), "tolerance_rad": float(tol),
             "final_angle_deg": math.degrees(angle), "target_deg": math.degrees(target),
             "tolerance_deg": math.degrees(tol), "final_angular_velocity_rad_s": float(omega), "at_rest": at_rest,
             "dropped": pv.dropped}
    if rec is not None:
        trial["_recorder"] = rec
    return trial


def _summary(trials: list[dict[str, Any]]) -> dict[str, Any]:
    import numpy as np

    ok = [t for t in trials if t["success"]]
    times = [t["completion_time_s"] for t in ok]
    outcomes: dict[str, int] = {}
    for t in trials:
        outcomes[t["outcome"]] = outcomes.get(t["outcome"], 0) + 1
    return {
        "trials": len(trials),
        "successes": len(ok),
        "success_rate": len(ok) / len(trials) if trials else math.nan,
        "median_completion_s": float(np.median(times)) if times else None,
        "mean_completion_s": float(np.mean(times)) if times else None,
        "outcomes": outcomes,
        "completion_times_s": times,
    }


def pivot_plot(path: Path, summary: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ["visual + force", "visual only"]
    data = [summary["visual_force"]["completion_times_s"], summary["visual_only"]["completion_times_s"]]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    ax.boxplot([d if d else [math.nan] for d in data])
    ax.set_xticks([1, 2], labels)
    ax.set_ylabel("completion time of successful trials (s)")
    ax.set_title("completion time")
    ax.grid(alpha=0.3)
    ax = axes[1]
    rates = [summary["visual_force"]["success_rate"] * 100, summary["visual_only"]["success_rate"] * 100]
    ax.bar(labels, rates, color=["tab:blue", "tab:orange"])
    ax.axhline(86.7, color="tab:blue", ls=":", label="paper, visual + force")
    ax.axhline(40.0, color="tab:orange", ls=":", label="paper, visual only")
    ax.set_ylim(0, 100)
    ax.set_ylabel("success rate (%)")
    ax.set_title("success rate")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def experiment_pivot(trials: int = 15, sensor: str = "ideal", time_limit: float = 30.0, seed: int = 0,
                     out: str | Path | None = None, registry: Any = None, plot: bool = True,
                     progress: bool = False, operator: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run ``trials`` seeded trials per condition (the same seeds in both conditions: ``seed`` ...
    ``seed + trials - 1``)."""
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ValueError(f"trials: expected a whole number of at least 1, got {trials!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed: expected a whole number, got {seed!r}")
    if (isinstance(time_limit, bool) or not isinstance(time_limit, (int, float)) or not math.isfinite(time_limit)
            or time_limit <= 0):
        raise ValueError(f"time_limit: expected a positive, finite number of seconds, got {time_limit!r}")
    if sensor not in SENSORS:
        raise ValueError(f"sensor: expected one of {', '.join(SENSORS)}, got {sensor!r}")
    problem = None if out is None else out_dir_problem(out)
    if problem:
        raise ValueError(f"out: {problem}")
    res: dict[str, Any] = {"experiment": "pivot", "sensor": sensor, "time_limit_s": time_limit, "first_seed": seed}
    per: dict[str, list[dict[str, Any]]] = {"visual_force": [], "visual_only": []}
    w0 = time.perf_counter()
    for i in range(trials):
        for key, fb in (("visual_force", True), ("visual_only", False)):
            tr = run_pivot_trial(fb, seed + i, sensor=sensor, time_limit=time_limit, registry=registry,
                                 operator=operator)
            per[key].append(tr)
            if progress:
                print(f"pivot {key:<13} trial {i + 1}/{trials}: {tr['outcome']:<10} "
                      f"angle {tr['final_angle_deg']:5.1f} deg  "
                      f"t={'-' if tr['completion_time_s'] is None else format(tr['completion_time_s'], '.2f') + ' s'}",
                      file=sys.stderr)
    for key in per:
        res[key] = _summary(per[key])
        res[key]["per_trial"] = per[key]
    res["paper"] = {"visual_force": {"success_rate": 0.867, "median_completion_s": 13.75},
                    "visual_only": {"success_rate": 0.40, "median_completion_s": 15.37}}
    res["wall_time_s"] = time.perf_counter() - w0
    if out is not None:
        save_outputs(out, "pivot", res, (lambda path: pivot_plot(path, res)) if plot else None)
    return res


# ================================================================================================ CLI
def _cmd_contact(args: argparse.Namespace) -> int:
    from teletouch.units import parse_quantity

    try:
        duration = parse_quantity(args.duration, "s")
        problem = _contact_duration_problem(duration)
        if problem:
            raise ValueError(problem)
    except ValueError as exc:
        print(f"teletouch experiment contact: --duration: {exc}", file=sys.stderr)
        return 2
    problem = out_dir_problem(args.out)
    if problem:
        print(f"teletouch experiment contact: --out {problem}", file=sys.stderr)
        return 2
    try:
        res = experiment_contact(duration=duration, sensor=args.sensor, out=args.out, baselines=args.baselines)
    except RuntimeError as exc:  # a run that faulted: its reason, not a traceback
        print(f"teletouch experiment contact: {exc}", file=sys.stderr)
        return 3
    if args.json:
        print(dumps(res))
    else:
        w, wo = res["with_feedback"], res["without_feedback"]

        def mm(e: float | None) -> str:
            return "- (no contact)" if e is None else f"{e * 1e3:.3f} mm"

        print(f"mean |leader - follower| in contact: with feedback {mm(w['mean_error_m'])}, without "
              f"{mm(wo['mean_error_m'])} (paper: 0.6 mm with feedback)")
        if "position_position" in res:
            print(f"position-position baseline: {mm(res['position_position']['mean_error_m'])}")
        for f in res.get("files", []):
            print(f"wrote {f}")
    return 0


def _cmd_pivot(args: argparse.Namespace) -> int:
    from teletouch.units import parse_quantity

    try:
        time_limit = parse_quantity(args.time_limit, "s")
        if not time_limit > 0:
            raise ValueError(f"must be positive, got {args.time_limit!r}")
    except ValueError as exc:
        print(f"teletouch experiment pivot: --time-limit: {exc}", file=sys.stderr)
        return 2
    if args.trials < 1:
        print(f"teletouch experiment pivot: --trials: expected at least 1, got {args.trials}", file=sys.stderr)
        return 2
    problem = out_dir_problem(args.out)
    if problem:
        print(f"teletouch experiment pivot: --out {problem}", file=sys.stderr)
        return 2
    try:
        res = experiment_pivot(trials=args.trials, sensor=args.sensor, time_limit=time_limit,
                               seed=args.seed, out=args.out, progress=not args.json)
    except RuntimeError as exc:  # a trial that faulted: its reason, not a traceback
        print(f"teletouch experiment pivot: {exc}", file=sys.stderr)
        return 3
    if args.json:
        slim = {k: ({kk: vv for kk, vv in v.items() if kk != "per_trial"} if isinstance(v, dict) and "per_trial" in v
                    else v) for k, v in res.items()}
        print(dumps(slim))
    else:
        for key, label in (("visual_force", "visual + force"), ("visual_only", "visual only")):
            s = res[key]
            med = f"{s['median_completion_s']:.2f} s" if s["median_completion_s"] is not None else "-"
            print(f"{label:<15} success {s['successes']}/{s['trials']} ({s['success_rate'] * 100:.1f} %), "
                  f"median completion {med}, outcomes {s['outcomes']}")
        print("paper: visual + force 86.7 %, 13.75 s; visual only 40 %, 15.37 s")
        for f in res.get("files", []):
            print(f"wrote {f}")
    return 0


@hookimpl
def teletouch_add_commands(subparsers: Any) -> None:
    p = subparsers.add_parser("experiment", help="the paper's experiments in simulation (contact, pivot)")
    sub = p.add_subparsers(dest="experiment", metavar="NAME")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
    c = sub.add_parser("contact", help="rigid-object contact with and without force feedback (paper Fig. 4)")
    c.add_argument("--duration", default="6", help="length of each run, s (default 6, at least 2: the fingers "
                                                      "reach the object at about 1.5 s)")
    c.add_argument("--sensor", choices=("image", "gt", "ideal"), default="image",
                   help="image: sim-digit + depth + poly-force (default); gt: sim-digit's true max depth + "
                        "poly-force; ideal: true force at camera rate")
    c.add_argument("--out", default="teletouch-experiments", help="folder for contact.json and contact.png")
    c.add_argument("--json", action="store_true", help="print the metrics as one JSON object")
    c.add_argument("--baselines", action="store_true", help="also run the position-position baseline")
    c.set_defaults(func=_cmd_contact)
    q = sub.add_parser("pivot", help="in-hand pivoting, visual + force vs visual only, seeded trials")
    q.add_argument("--trials", type=int, default=15, help="trials per condition (default 15, as the paper)")
    q.add_argument("--time-limit", default="30", help="time limit of a trial, s (default 30)")
    q.add_argument("--seed", type=int, default=0, help="first seed (trial i uses seed + i, in both conditions)")
    q.add_argument("--sensor", choices=("image", "gt", "ideal"), default="ideal",
                   help="ideal: camera-rate ground truth (default, fast); gt: sim-digit's true max depth + "
                        "poly-force; image: the full estimator chain (sim-digit + depth + poly-force)")
    q.add_argument("--out", default="teletouch-experiments", help="folder for pivot.json and pivot.png")
    q.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    q.set_defaults(func=_cmd_pivot)
