"""A simulated operator for the simulated leader (``sim-omega7``): a hand impedance that tracks an intent.

The operator is modelled the way motor-control and haptics studies model a hand holding a device: the nervous system
commands an *equilibrium* (the intended opening of the pinch and its rate, Hogan's "virtual trajectory"), and the
hand behaves around it as a spring-damper. The force the hand puts on the gripper (positive = opening it) is::

    F_hand = clip(K_hand * (x_intent - x) + B_hand * (v_intent - v), -F_max, +F_max)

so when the leader renders a force F that pushes the fingers apart the hand settles where ``x = x_intent + F/K_hand``,
exactly as a person's pinch gives way under a resisting force. Typical values (see docs/leaders.md for sources):
fingertip / pinch stiffness a few hundred N/m (rising with grip force, roughly 100-1000 N/m), damping a few N*s/m,
moving finger mass of the order of 10 g.

Intents
-------
An intent says what the operator wants: ``desired(t, state) -> (opening, velocity)`` in m and m/s, or ``None`` when
the hand is off the gripper (no force at all). Built in:

- ``none``: no hand on the device (force calibration: a press rig drives the handle instead).
- ``hold``: hold one opening.
- ``close-and-hold``: wait, then close slowly from ``start_opening`` to ``target_opening`` at ``speed``, hold for
  ``hold_time``, then optionally open again (the rigid-object contact experiment).
- ``trajectory``: piecewise-linear through ``waypoints`` [[t, opening], ...].

Other modules add intents (e.g. a pivoting operator that reacts to the perceived angle) with :func:`register_intent`,
or a graph names a class by import path (``type: "my_pkg.my_module:PivotIntent"``). An intent class has a ``name``,
a pydantic ``Params`` model (fields may use unit strings such as "5mm") and ``desired``; ``reset()`` is optional
(``sim-omega7`` calls it at every activation: an intent that keeps state, a latch, starts afresh in a new run).
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from teletouch.graph import _suggest
from teletouch.units import Meters, MetersPerSecond, Seconds, plausible_opening, plausible_speed

__all__ = [
    "OperatorState", "Intent", "IntentParams", "register_intent", "intent_names", "make_intent", "validate_intent",
    "HandImpedance", "NoneIntent", "HoldIntent", "CloseAndHoldIntent", "TrajectoryIntent",
]


@dataclass
class OperatorState:
    """What the simulated operator can perceive at time ``t`` (all SI)."""

    t: float = 0.0
    opening: float = 0.0  # m, gripper gap
    velocity: float = 0.0  # m/s, d(gap)/dt
    gripper_force: float = 0.0  # N, the force the leader renders on the fingers (positive pushes them apart)
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m, handle position
    extra: dict[str, Any] = field(default_factory=dict)  # whatever the graph feeds in (e.g. a perceived angle)


@runtime_checkable
class Intent(Protocol):
    """What the operator wants to do. ``desired`` returns (opening m, velocity m/s), or None for "hand off"."""

    name: ClassVar[str]

    def desired(self, t: float, state: OperatorState) -> tuple[float, float] | None: ...


class IntentParams(BaseModel):
    """Base of intent parameter models: unknown fields are refused, numbers must be finite (an ``.inf`` opening or
    time would pass ``ge=0`` and make the hand push with its full force or never move)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


_INTENTS: dict[str, type] = {}


def register_intent(cls: type) -> type:
    """Register an intent class under ``cls.name`` (usable as a decorator). Re-registering the same class is fine;
    a different class under a taken name is an error."""
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise ValueError(f"intent class {cls.__name__} needs a non-empty string attribute 'name'")
    if not callable(getattr(cls, "desired", None)):
        raise ValueError(f"intent class {cls.__name__} must define desired(t, state)")
    old = _INTENTS.get(name)
    if old is not None and old is not cls and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"intent name '{name}' is already taken by {old.__module__}.{old.__qualname__}")
    _INTENTS[name] = cls
    return cls


def intent_names() -> list[str]:
    return sorted(_INTENTS)


def _resolve(type_name: str) -> type:
    if type_name in _INTENTS:
        return _INTENTS[type_name]
    if ":" in type_name:
        mod_name, _, attr = type_name.partition(":")
        try:
            mod = importlib.import_module(mod_name)
        except ImportError as exc:
            raise ValueError(f"intent type '{type_name}': cannot import module '{mod_name}' ({exc})") from None
        except Exception as exc:   # the module is there but fails as it loads (a SyntaxError, an error at import)
            where = f" ({exc.filename}:{exc.lineno})" if isinstance(exc, SyntaxError) else ""
            raise ValueError(f"intent type '{type_name}': module '{mod_name}' failed to load{where}: "
                             f"{type(exc).__name__}: {exc}") from None
        cls = getattr(mod, attr, None)
        if cls is None:
            raise ValueError(f"intent type '{type_name}': module '{mod_name}' has no attribute '{attr}'")
        if not callable(getattr(cls, "desired", None)):
            raise ValueError(f"intent type '{type_name}' has no desired(t, state) method")
        return cls
    raise ValueError(f"unknown intent type '{type_name}'; known: {', '.join(intent_names())} "
                     f"(or 'package.module:ClassName')")


def validate_intent(spec: Any) -> dict[str, Any]:
    """Normalise an intent spec (a name, or a mapping with ``type`` and the intent's parameters) to
    ``{"type": name, **validated params}``; raises ValueError naming the bad field."""
    if spec is None:
        spec = "none"
    if isinstance(spec, str):
        spec = {"type": spec}
    if not isinstance(spec, dict):
        raise ValueError(f"intent must be a name or a mapping with 'type', got {spec!r}")
    spec = dict(spec)
    type_name = spec.pop("type", None)
    if not isinstance(type_name, str):
        raise ValueError(f"intent needs 'type' (one of {', '.join(intent_names())}), got {type_name!r}")
    cls = _resolve(type_name)
    pcls = getattr(cls, "Params", None)
    if pcls is not None:
        from pydantic import ValidationError

        try:
            p = pcls(**spec)
        except ValidationError as exc:
            raise ValueError(_params_error(type_name, pcls, exc.errors())) from None
        return {"type": type_name, **p.model_dump()}
    return {"type": type_name, **spec}


def _params_error(type_name: str, pcls: type, errors: list[dict[str, Any]]) -> str:
    """The message of an intent's refused parameters: an unknown field first, with the fields the intent type takes
    (a misnamed one is the likelier mistake), then each other problem led by its field."""
    unknown = [str(e["loc"][0]) for e in errors if e["type"] == "extra_forbidden" and len(e["loc"]) == 1]
    errs = [f"intent.{'.'.join(map(str, e['loc']))}: {e['msg'].removeprefix('Value error, ')}"
            for e in errors if not (e["type"] == "extra_forbidden" and len(e["loc"]) == 1)]
    if not unknown:
        return f"intent '{type_name}': {'; '.join(errs)}"
    known = list(getattr(pcls, "model_fields", {}))
    names = ", ".join(f"'{n}'{_suggest(n, known)}" for n in unknown)
    head = f"intent '{type_name}' has no field{'s' if len(unknown) > 1 else ''} {names}; {_fields_text(pcls)}"
    return "; ".join([head, *errs])


def _fields_text(pcls: type) -> str:
    """The fields an intent's ``Params`` take, each with its unit where it has one: "its fields: opening (m), ..."."""
    fields = []
    for name, info in getattr(pcls, "model_fields", {}).items():
        extra = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
        fields.append(f"{name} ({extra['unit']})" if extra.get("unit") else name)
    return f"its fields: {', '.join(fields)}" if fields else "it takes no fields"


def make_intent(spec: Any) -> Intent:
    """Build an intent object from a spec (see :func:`validate_intent`)."""
    spec = validate_intent(spec)
    type_name = spec.pop("type")
    cls = _resolve(type_name)
    pcls = getattr(cls, "Params", None)
    if pcls is not None:
        return cls(pcls(**spec))
    return cls(**spec)


# --------------------------------------------------------------------------------------------------- built-ins
@register_intent
class NoneIntent:
    """No hand on the device."""

    name = "none"

    class Params(IntentParams):
        pass

    def __init__(self, params: Any = None):
        self.params = params

    def desired(self, t: float, state: OperatorState) -> tuple[float, float] | None:
        return None


@register_intent
class HoldIntent:
    """Hold one opening."""

    name = "hold"

    class Params(IntentParams):
        opening: Meters = Field(0.015, ge=0, description="opening to hold", json_schema_extra={"unit": "m"})

        @field_validator("opening")
        @classmethod
        def _plausible(cls, v: float, info: Any) -> float:
            return plausible_opening(info.field_name, v)

    def __init__(self, params: "HoldIntent.Params"):
        self.params = params

    def desired(self, t: float, state: OperatorState) -> tuple[float, float]:
        return self.params.opening, 0.0


@register_intent
class CloseAndHoldIntent:
    """Wait ``start_time``, close from ``start_opening`` to ``target_opening`` at ``speed``, hold ``hold_time``;
    then open back at the same speed if ``release``, else keep holding."""

    name = "close-and-hold"

    class Params(IntentParams):
        start_opening: Meters = Field(0.02, ge=0, description="opening before closing",
                                      json_schema_extra={"unit": "m"})
        target_opening: Meters = Field(0.005, ge=0, description="opening to close to (narrower than the object)",
                                       json_schema_extra={"unit": "m"})
        speed: MetersPerSecond = Field(0.005, gt=0, description="closing speed", json_schema_extra={"unit": "m/s"})
        start_time: Seconds = Field(0.5, ge=0, description="when closing starts", json_schema_extra={"unit": "s"})
        hold_time: Seconds = Field(2.0, ge=0, description="how long to hold the target",
                                   json_schema_extra={"unit": "s"})
        release: bool = Field(False, description="open back to start_opening after the hold")

        @field_validator("start_opening", "target_opening")
        @classmethod
        def _plausible(cls, v: float, info: Any) -> float:
            return plausible_opening(info.field_name, v)

        @field_validator("speed")
        @classmethod
        def _plausible_speed(cls, v: float, info: Any) -> float:
            return plausible_speed(info.field_name, v)

    def __init__(self, params: "CloseAndHoldIntent.Params"):
        p = self.params = params
        self.t_close = abs(p.start_opening - p.target_opening) / p.speed
        self.sign = -1.0 if p.target_opening < p.start_opening else 1.0

    def phase(self, t: float) -> str:
        p = self.params
        if t < p.start_time:
            return "wait"
        if t < p.start_time + self.t_close:
            return "closing"
        if t < p.start_time + self.t_close + p.hold_time or not p.release:
            return "hold"
        if t < p.start_time + 2 * self.t_close + p.hold_time:
            return "release"
        return "done"

    def desired(self, t: float, state: OperatorState) -> tuple[float, float]:
        p = self.params
        ph = self.phase(t)
        if ph == "wait":
            return p.start_opening, 0.0
        if ph == "closing":
            return p.start_opening + self.sign * p.speed * (t - p.start_time), self.sign * p.speed
        if ph == "hold":
            return p.target_opening, 0.0
        if ph == "release":
            t_rel = t - (p.start_time + self.t_close + p.hold_time)
            return p.target_opening - self.sign * p.speed * t_rel, -self.sign * p.speed
        return p.start_opening, 0.0


@register_intent
class TrajectoryIntent:
    """Piecewise-linear opening through waypoints [[t, opening], ...] (t increasing); constant outside them."""

    name = "trajectory"

    class Params(IntentParams):
        waypoints: list[tuple[Seconds, Meters]] = Field(..., min_length=1,
                                                        description="[[t (s), opening (m)], ...]")

        @field_validator("waypoints")
        @classmethod
        def _increasing(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
            for i, (a, b) in enumerate(zip(v, v[1:])):
                if not b[0] > a[0]:
                    raise ValueError(f"waypoint {i + 1}: times must increase ({a[0]} then {b[0]})")
            for i, (t, x) in enumerate(v):
                if not (math.isfinite(t) and math.isfinite(x)) or x < 0:
                    raise ValueError(f"waypoint {i}: expected finite t and opening >= 0, got ({t}, {x})")
                plausible_opening(f"waypoint {i} opening", x)
            return v

    def __init__(self, params: "TrajectoryIntent.Params"):
        self.params = params
        self.t = np.array([w[0] for w in params.waypoints], dtype=float)
        self.x = np.array([w[1] for w in params.waypoints], dtype=float)

    def desired(self, t: float, state: OperatorState) -> tuple[float, float]:
        ts, xs = self.t, self.x
        if t <= ts[0]:
            return float(xs[0]), 0.0
        if t >= ts[-1]:
            return float(xs[-1]), 0.0
        i = int(np.searchsorted(ts, t, side="right")) - 1
        slope = (xs[i + 1] - xs[i]) / (ts[i + 1] - ts[i])
        return float(xs[i] + slope * (t - ts[i])), float(slope)


# --------------------------------------------------------------------------------------------------- the hand
@dataclass
class HandImpedance:
    """A spring-damper hand around an equilibrium; ``force`` is the force on the device (positive opens it)."""

    stiffness: float = 300.0  # N/m
    damping: float = 3.0  # N*s/m
    max_force: float = 40.0  # N, pinch strength the operator will use

    def force(self, x: float, v: float, x_d: float, v_d: float) -> float:
        f = self.stiffness * (x_d - x) + self.damping * (v_d - v)
        return min(max(f, -self.max_force), self.max_force)


IntentFactory = Callable[[Any], Intent]
