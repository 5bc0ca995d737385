"""Simulated leader: an Omega.7 gripper and handle driven by a simulated operator (same ports as ``omega7``).

Gripper: a 1-DoF mass (device + the operator's fingers) with viscous and Coulomb friction and end stops at 0 and
``max_opening``. Forces on it: the rendered ``gripper_force`` (clamped to the device limit, positive opens) and the
operator's hand impedance tracking the intent (see ``operator.py``). So a rendered force pushes the hand back as it
would a person's: at rest ``opening = intent + F / hand_stiffness`` (within the Coulomb band).

Handle: 3 axes, mass and damping, gravity compensated, a spherical workspace. Forces: the commanded ``force``
(clamped to the device limit), the optional ``external_force`` (a simulated environment, e.g. the force-calibration
press rig) and, when the operator holds the device, an arm impedance around ``hand_position``.

Commands: through omega7's ``ForceGuard`` (finite, clamped, zero when older than ``command_timeout``; a command that
was stale and is fresh again, a controller that stalled past the timeout and comes back with the force it had, is
faded in over ``COMMAND_FADE_IN``, 0.05 s, not stepped onto the operator's hand), as on the real device.

Integration: semi-implicit Euler in substeps of at most ``substep``. Where that would be unstable (a stiff or heavily
damped hand or arm, a very light gripper or handle: ``h * c / m`` or ``h^2 * k / m`` above 0.5), the viscous and
spring terms are taken implicitly instead (stable for any step); with the default parameters the explicit path runs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import ComponentFault, Device, Kind, Params, Port, hookimpl
from teletouch.units import (
    MAX_PLAUSIBLE_WORKSPACE, Kilograms, Meters, NewtonSecondsPerMeter, Newtons, NewtonsPerMeter, Seconds,
    plausible_opening, plausible_quantity, plausible_travel,
)

from .omega7 import (
    LEADER_INPUTS, LEADER_OUTPUTS, OMEGA7_GRIPPER_RANGE, OMEGA7_MAX_FORCE, OMEGA7_MAX_GRIPPER_FORCE,
    OMEGA7_WORKSPACE_RADIUS, ForceGuard,
)
from .operator import HandImpedance, OperatorState, make_intent, validate_intent

#: the operator's intended opening (m) and its rate (m/s) are clipped to +-this: far beyond any hand, and small
#: enough that the hand's spring and damper forces stay finite (a huge but finite intent_opening, or a jump between
#: two, made them inf - inf = NaN and the gripper's state NaN for good)
INTENT_BOUND = 1e3


#: no person pinches harder than this (adults' key pinch: about 80-120 N, Mathiowetz et al. 1985): a larger
#: ``hand_max_force`` is millinewtons typed in the newton field (40000 meant 40000 mN, 40 N)
MAX_PLAUSIBLE_PINCH_FORCE = 200.0   # N

#: explicit (semi-implicit Euler) substeps are used while h*c/m and h^2*k/m stay below this; above it, implicit
STIFF_LIMIT = 0.5


def _u(unit: str) -> dict[str, str]:
    return {"unit": unit}


def _clip(v: float, bound: float = INTENT_BOUND) -> float:
    return bound if v > bound else (-bound if v < -bound else v)


def _outside_workspace(name: str, position: tuple[float, float, float], radius: float) -> str | None:
    """None if ``position`` (m) lies in the spherical workspace of ``radius`` (m); else why ``name`` is refused. A
    position beyond any haptic leader's workspace that fits this one as millimetres gets the value to write
    (``hand_position: [0, 0, 50]`` meant 50 mm and pulled the handle towards a point 50 m away)."""
    r = math.sqrt(sum(c * c for c in position))
    if r <= radius * (1 + 1e-12):
        return None
    msg = (f"{name} {list(position)} m is {r * 1e3:g} mm from the centre, outside workspace_radius "
           f"({radius * 1e3:g} mm)")
    if r <= MAX_PLAUSIBLE_WORKSPACE or r * 1e-3 > radius * (1 + 1e-12):   # metres meant, or no unit fits
        return msg
    m = ", ".join(f"{c * 1e-3:g}" for c in position)
    mm = ", ".join(f'"{c:g}mm"' for c in position)
    return f"{msg}: millimetres in the metre field? a bare number is metres: write [{m}] or [{mm}]"


class SimOmega7(Device):
    """Simulated Omega.7 leader with an operator hand model (sim and wall clocks)."""

    name = "sim-omega7"
    kind = Kind.DEVICE
    default_rate = 1000.0
    inputs = {
        **LEADER_INPUTS,
        "external_force": Port("float64", (3,), "N", "force of a simulated environment on the handle (press rig)",
                               required=False),
        "intent_opening": Port("float64", (), "m", "opening the operator wants now; overrides the scripted intent "
                                                   "while it is fresh", required=False),
        "intent_cue": Port("float64", (), "any", "what the operator perceives besides the force (e.g. the object's "
                                               "angle, rad): given to the intent as state.extra['cue']",
                           required=False),
    }
    outputs = {
        **LEADER_OUTPUTS,
        "hand_force": Port("float64", (), "N", "ground truth: force of the operator's fingers on the gripper "
                                               "(positive opens)"),
        "intended_opening": Port("float64", (), "m", "ground truth: the operator's intended opening (NaN: hand off)"),
    }

    class Params(Params):
        intent: Any = Field("hold", validate_default=True,
                            description="operator intent: a name (none | hold | close-and-hold | "
                                        "trajectory | registered) or {type: NAME, ...its parameters}")
        max_gripper_force: Newtons = Field(OMEGA7_MAX_GRIPPER_FORCE, ge=0, le=OMEGA7_MAX_GRIPPER_FORCE,
                                           description="gripper force limit", json_schema_extra=_u("N"))
        max_force: Newtons = Field(OMEGA7_MAX_FORCE, ge=0, le=OMEGA7_MAX_FORCE,
                                   description="translational force limit (norm)", json_schema_extra=_u("N"))
        command_timeout: Seconds = Field(0.1, gt=0, le=1.0, description="a command older than this gives zero force "
                                         "(at most 1 s, as on omega7)", json_schema_extra=_u("s"))
        # gripper mechanics
        max_opening: Meters = Field(OMEGA7_GRIPPER_RANGE, gt=0, description="gripper end stop",
                                    json_schema_extra=_u("m"))
        initial_opening: Meters | None = Field(None, ge=0, description="start opening (default: the intent's, "
                                                                       "else half open)", json_schema_extra=_u("m"))
        gripper_mass: Kilograms = Field(0.02, gt=0, description="effective gripper mass at the fingers",
                                        json_schema_extra=_u("kg"))
        gripper_damping: NewtonSecondsPerMeter = Field(0.5, ge=0, description="gripper viscous friction",
                                                       json_schema_extra=_u("N*s/m"))
        gripper_coulomb: Newtons = Field(0.05, ge=0, description="gripper Coulomb friction",
                                         json_schema_extra=_u("N"))
        # operator's hand (pinch) impedance
        hand_stiffness: NewtonsPerMeter = Field(300.0, gt=0, description="pinch stiffness of the operator",
                                                json_schema_extra=_u("N/m"))
        hand_damping: NewtonSecondsPerMeter = Field(3.0, ge=0, description="pinch damping of the operator",
                                                    json_schema_extra=_u("N*s/m"))
        hand_mass: Kilograms = Field(0.01, ge=0, description="moving finger mass added while holding",
                                     json_schema_extra=_u("kg"))
        hand_max_force: Newtons = Field(40.0, gt=0, description="largest pinch force the operator uses",
                                        json_schema_extra=_u("N"))
        # handle mechanics
        handle_mass: Kilograms = Field(0.25, gt=0, description="effective handle mass", json_schema_extra=_u("kg"))
        handle_damping: NewtonSecondsPerMeter = Field(5.0, ge=0, description="handle viscous damping",
                                                      json_schema_extra=_u("N*s/m"))
        workspace_radius: Meters = Field(OMEGA7_WORKSPACE_RADIUS, gt=0, description="spherical workspace",
                                         json_schema_extra=_u("m"))
        initial_position: tuple[Meters, Meters, Meters] = Field((0.0, 0.0, 0.0), description="start position (m)")
        # operator's arm impedance on the handle (only while a hand holds the device)
        arm_stiffness: NewtonsPerMeter = Field(300.0, ge=0, description="arm/hand stiffness on the handle",
                                               json_schema_extra=_u("N/m"))
        arm_damping: NewtonSecondsPerMeter = Field(10.0, ge=0, description="arm/hand damping on the handle",
                                                   json_schema_extra=_u("N*s/m"))
        hand_position: tuple[Meters, Meters, Meters] = Field((0.0, 0.0, 0.0),
                                                             description="where the operator holds the handle (m)")
        button_intervals: list[tuple[Seconds, Seconds]] = Field(default_factory=list,
                                                                description="[[t_on, t_off], ...] button pressed")
        substep: Seconds = Field(2.5e-4, gt=0, le=0.01, description="largest internal integration step",
                                 json_schema_extra=_u("s"))

        @field_validator("intent", mode="before")
        @classmethod
        def _intent(cls, v: Any) -> dict[str, Any]:
            return validate_intent(v)

        @field_validator("hand_max_force")
        @classmethod
        def _plausible_pinch(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_PINCH_FORCE, "N", "beyond any person's pinch")

        @field_validator("workspace_radius")
        @classmethod
        def _workspace(cls, v: float, info: Any) -> float:
            return plausible_travel(info.field_name, v)   # 75 meant 75 mm: the handle wandered 75 m

        @field_validator("button_intervals")
        @classmethod
        def _intervals(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
            for i, (a, b) in enumerate(v):
                if not b > a:
                    raise ValueError(f"button_intervals[{i}]: t_off must be after t_on, got ({a}, {b})")
            return v

        @model_validator(mode="after")
        def _start_inside(self) -> "SimOmega7.Params":
            plausible_opening("max_opening", self.max_opening)
            if self.initial_opening is not None and self.initial_opening > self.max_opening:
                raise ValueError(f"initial_opening ({self.initial_opening * 1e3:g} mm) is beyond max_opening "
                                 f"({self.max_opening * 1e3:g} mm, the gripper's end stop): expected 0 to "
                                 f"max_opening")
            for name in ("initial_position", "hand_position"):   # the hand holds the handle: both lie in its reach
                problem = _outside_workspace(name, getattr(self, name), self.workspace_radius)
                if problem:
                    raise ValueError(problem)
            return self

    # ------------------------------------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        p = self.params
        spec = validate_intent(p.intent)
        self.intent_name = spec["type"]
        self.intent = make_intent(spec)
        self.hand = HandImpedance(p.hand_stiffness, p.hand_damping, p.hand_max_force)
        self.guard = ForceGuard(p.max_gripper_force, p.max_force, p.command_timeout)
        self.state = OperatorState()
        self.faults = 0
        x0 = p.initial_opening
        if x0 is None:
            d = self._checked(self.intent.desired(0.0, self.state), "intent")
            x0 = d[0] if d is not None else 0.5 * p.max_opening
        self.x = min(max(float(x0), 0.0), p.max_opening)
        self.v = 0.0
        self.pos = np.array(p.initial_position, dtype=float)
        self.vel = np.zeros(3)
        self.hand_pos = np.array(p.hand_position, dtype=float)
        # the integrator's state as plain floats (small numpy arrays cost microseconds per operation)
        self._p = tuple(float(c) for c in self.pos)
        self._v = (0.0, 0.0, 0.0)
        self._hand_p = tuple(float(c) for c in self.hand_pos)
        self._zero3 = np.zeros(3)
        self._zero3.flags.writeable = False

        self.last_t: float | None = None
        self.g_applied = 0.0
        self.f_applied = np.zeros(3)
        self.f_hand = 0.0
        self.x_intent = math.nan
        self.enabled = False
        self.safe = True
        self._io_prev: tuple[float, float] | None = None  # last (stamp, value) of intent_opening
        self._io_vel = 0.0

    def activate(self) -> None:
        """Start (again) from zero force with the operator afresh: the intent's optional ``reset()`` is called, and
        nothing perceived in an earlier activation (the cue, the rate of intent_opening) is carried over; the graph's
        clock may start again from zero. The counters in status() (the guard's, faults) start from zero again (as
        omega7's)."""
        self.enabled = True
        self.safe = False
        self.last_t = None
        self.guard.reset()
        self.guard.clear_counts()   # status() is of one activation, as omega7's
        self.faults = 0
        self.state.extra.clear()
        self._io_prev = None
        self._io_vel = 0.0
        reset = getattr(self.intent, "reset", None)
        if callable(reset):
            reset()

    def deactivate(self) -> None:
        self.enabled = False
        self.g_applied = 0.0
        self.f_applied = np.zeros(3)

    def safe_state(self) -> None:
        self.safe = True
        self.g_applied = 0.0
        self.f_applied = np.zeros(3)

    # ------------------------------------------------------------------------------------------------ stepping
    def _checked(self, des: Any, source: str) -> tuple[float, float] | None:
        """An intent's answer as (opening, velocity) floats, finite and within +-INTENT_BOUND, or None (hand off).
        Anything else faults (after the safe state) naming the intent: a NaN taken into the hand's force would
        make the gripper's opening NaN for good."""
        if des is None:
            return None
        if des.__class__ is tuple and len(des) == 2:  # the usual answer: two floats in range (NaN fails these)
            x, v = des
            if (x.__class__ is float and v.__class__ is float and -INTENT_BOUND <= x <= INTENT_BOUND
                    and -INTENT_BOUND <= v <= INTENT_BOUND):
                return des
        try:
            if isinstance(des, (str, bytes)):
                raise TypeError
            x, v = des
            x, v = float(x), float(v)
        except (TypeError, ValueError, OverflowError):   # (OverflowError: an int beyond any float)
            problem = f"{source} '{self.intent_name}' returned {des!r}: expected (opening m, velocity m/s) or None"
        else:
            if math.isfinite(x) and math.isfinite(v):
                return _clip(x), _clip(v)
            problem = (f"{source} '{self.intent_name}' returned opening {x}, velocity {v} (not finite): "
                       f"expected finite (opening m, velocity m/s) or None")
        self.faults += 1
        self.safe_state()
        raise ComponentFault(problem, getattr(self, "id", None))

    def _desired(self, t: float, inputs: Any) -> tuple[float, float] | None:
        s = inputs.get("intent_opening")
        to = self.params.command_timeout
        if s is not None and (to is None or s.is_fresh(t, to)):
            try:
                x = float(s.value)
            except (TypeError, ValueError):
                self.faults += 1
                self.safe_state()
                raise ComponentFault(f"intent_opening is {s.value!r} (not a number)", self.id) from None
            except OverflowError:   # an int beyond any float (a float64 port takes any int)
                self.faults += 1
                self.safe_state()
                raise ComponentFault("intent_opening is an integer too large for a float (not finite)",
                                     self.id) from None
            if not math.isfinite(x):
                self.faults += 1
                self.safe_state()
                raise ComponentFault(f"intent_opening is {x} (not finite)", self.id)
            x = _clip(x)
            prev = self._io_prev
            if prev is not None and s.stamp > prev[0]:
                self._io_vel = _clip((x - prev[1]) / (s.stamp - prev[0]))
            if prev is None or s.stamp != prev[0]:
                self._io_prev = (s.stamp, x)
            return x, self._io_vel
        return self._checked(self.intent.desired(t, self.state), "intent")

    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        p = self.params
        g, f, problem = self.guard.apply(t, inputs)
        if problem is not None or self.safe or not self.enabled:
            g, f = 0.0, self._zero3
        self.g_applied, self.f_applied = g, f
        if problem is not None:
            self.faults += 1
            self.safe_state()
            raise ComponentFault(problem, self.id)
        ext = inputs.value("external_force") if "external_force" in inputs else None
        if ext is not None:
            ext = np.asarray(ext, dtype=float).reshape(3)
            if not np.all(np.isfinite(ext)):
                self.faults += 1
                self.safe_state()
                raise ComponentFault(f"external_force {ext.tolist()} is not finite", self.id)
        dt = 0.0 if self.last_t is None else max(0.0, t - self.last_t)
        self.last_t = t
        st = self.state
        st.t, st.opening, st.velocity, st.gripper_force, st.position = t, self.x, self.v, g, self.pos
        cue = inputs.get("intent_cue") if "intent_cue" in inputs else None
        if cue is not None:
            st.extra["cue"] = cue.value
            st.extra["cue_stamp"] = cue.stamp
        des = self._desired(t, inputs)
        if dt > 0:
            n = max(1, int(math.ceil(dt / p.substep - 1e-9)))
            self._integrate(dt / n, n, g, f, ext, des)
        else:
            self.f_hand = 0.0 if des is None else self.hand.force(self.x, self.v, des[0], des[1])
        self.x_intent = math.nan if des is None else des[0]
        intervals = p.button_intervals
        button = any(a <= t < b for a, b in intervals) if intervals else False
        return {"gripper_opening": self.x, "gripper_velocity": self.v,
                "position": np.array(self._p),  # a new array every step
                "button": button, "hand_force": self.f_hand, "intended_opening": self.x_intent}

    def _integrate(self, h: float, n: int, g: float, f: np.ndarray, ext: np.ndarray | None,
                   des: tuple[float, float] | None) -> None:
        """n semi-implicit Euler steps of h seconds (plain floats: this runs at up to 4 kHz x substeps); the stiff
        linear terms implicitly where the explicit update would be unstable (see the module's docstring)."""
        p = self.params
        x, v = self.x, self.v
        x_max = p.max_opening
        b, fc = p.gripper_damping, p.gripper_coulomb
        hand = des is not None
        m = p.gripper_mass + (p.hand_mass if hand else 0.0)
        fh = 0.0
        k_h = b_h = f_max = x_d = v_d = 0.0
        if hand:
            k_h, b_h, f_max = self.hand.stiffness, self.hand.damping, self.hand.max_force
            x_d, v_d = des
        a = h / m
        if a * (b + b_h) <= STIFF_LIMIT and a * h * k_h <= STIFF_LIMIT:
            for _ in range(n):
                # gripper: m x'' = F_render + F_hand - b x' - Coulomb
                if hand:
                    fh = k_h * (x_d - x) + b_h * (v_d - v)
                    fh = f_max if fh > f_max else (-f_max if fh < -f_max else fh)
                drive = g + fh - b * v
                if abs(v) < 1e-9 and abs(drive) <= fc:
                    v = 0.0  # static friction holds
                else:
                    sgn = math.copysign(1.0, v if abs(v) >= 1e-9 else drive)
                    v_new = v + h * (drive - fc * sgn) / m
                    if v != 0.0 and v_new * v < 0 and abs(drive) <= fc:
                        v_new = 0.0  # friction stops it, it does not reverse it
                    v = v_new
                x += h * v
                if x <= 0.0:
                    x, v = 0.0, max(v, 0.0)
                elif x >= x_max:
                    x, v = x_max, min(v, 0.0)
        else:
            # stiff: the viscous terms and the hand's spring implicit in the new velocity (the opening moves by
            # h * v_new); the hand's force, once saturated, is a constant force
            den = 1.0 + a * (b + b_h) + a * h * k_h
            for _ in range(n):
                f0 = k_h * (x_d - x) + b_h * v_d  # the hand's force were the gripper still
                still = g + (f_max if f0 > f_max else (-f_max if f0 < -f_max else f0))
                if abs(v) < 1e-9 and abs(still) <= fc:
                    v = 0.0  # static friction holds
                    fh = still - g
                else:
                    sgn = math.copysign(1.0, v if abs(v) >= 1e-9 else still)
                    if hand:
                        v_new = (v + a * (g + f0 - fc * sgn)) / den
                        fh = f0 - (k_h * h + b_h) * v_new
                        if fh > f_max or fh < -f_max:
                            fh = math.copysign(f_max, fh)
                            v_new = (v + a * (g + fh - fc * sgn)) / (1.0 + a * b)
                    else:
                        v_new = (v + a * (g - fc * sgn)) / (1.0 + a * b)
                    if v != 0.0 and v_new * v < 0 and abs(still) <= fc:
                        v_new = 0.0  # friction stops it, it does not reverse it
                    v = v_new
                x += h * v
                if x <= 0.0:
                    x, v = 0.0, max(v, 0.0)
                elif x >= x_max:
                    x, v = x_max, min(v, 0.0)
        self.x, self.v, self.f_hand = x, v, fh
        # handle: M p'' = F_cmd + F_ext + F_arm - b p'
        px, py, pz = self._p
        vx, vy, vz = self._v
        fx, fy, fz = f.tolist()
        if ext is not None:
            fx, fy, fz = fx + float(ext[0]), fy + float(ext[1]), fz + float(ext[2])
        k_a, b_a = (p.arm_stiffness, p.arm_damping) if hand else (0.0, 0.0)
        hx, hy, hz = self._hand_p
        r_max = p.workspace_radius
        if (vx == 0.0 and vy == 0.0 and vz == 0.0 and fx == 0.0 and fy == 0.0 and fz == 0.0
                and (k_a == 0.0 or (px == hx and py == hy and pz == hz))
                and px * px + py * py + pz * pz <= r_max * r_max):
            return  # at rest with no force on it: the steps below would leave it exactly where it is
        bt, mass = p.handle_damping, p.handle_mass
        bb = bt + b_a
        a = h / mass
        stiff = a * bb > STIFF_LIMIT or a * h * k_a > STIFF_LIMIT
        den = 1.0 + a * bb + a * h * k_a
        for _ in range(n):
            if stiff:  # damping and the arm's spring implicit in the new velocity
                vx = (vx + a * (fx + k_a * (hx - px))) / den
                vy = (vy + a * (fy + k_a * (hy - py))) / den
                vz = (vz + a * (fz + k_a * (hz - pz))) / den
            else:
                vx += h * (fx + k_a * (hx - px) - bb * vx) / mass
                vy += h * (fy + k_a * (hy - py) - bb * vy) / mass
                vz += h * (fz + k_a * (hz - pz) - bb * vz) / mass
            px += h * vx
            py += h * vy
            pz += h * vz
            r2 = px * px + py * py + pz * pz
            if r2 > r_max * r_max:
                r = math.sqrt(r2)
                nx, ny, nz = px / r, py / r, pz / r
                px, py, pz = nx * r_max, ny * r_max, nz * r_max
                out = vx * nx + vy * ny + vz * nz
                if out > 0:
                    vx, vy, vz = vx - out * nx, vy - out * ny, vz - out * nz
        self._p = (px, py, pz)
        self._v = (vx, vy, vz)
        self.pos = np.array(self._p)
        self.vel = np.array(self._v)

    def status(self) -> dict[str, Any]:
        if not hasattr(self, "guard"):
            return {}
        return {"gripper_opening_m": self.x, "gripper_force_n": self.g_applied, "hand_force_n": self.f_hand,
                "intended_opening_m": self.x_intent, "intent": self.intent_name,
                "force_norm_n": float(np.linalg.norm(self.f_applied)), "clamped": self.guard.clamped,
                "stale_commands": self.guard.stale, "faded_in": self.guard.faded_in, "faults": self.faults,
                "safe": self.safe}


@hookimpl
def teletouch_components():
    return [SimOmega7]
