"""Components: the unit every plugin supplies.

A component has a *kind* (sensor, estimator, device, controller, bridge), typed input and output *ports*, validated
*parameters* (a pydantic model with defaults and units in its schema) and a *lifecycle*::

    unconfigured --configure()--> inactive --activate()--> active --step()...--> deactivate() --> inactive
                                                                                   close() --> finalized

A :class:`Device` also has a safe state (:meth:`Device.safe_state`) that the runtime drives it to on any fault,
on Ctrl-C and at the end of every run: zero force on a leader, hold position on a follower.

Data flows as :class:`Sample` objects (a value and the time it was measured, in seconds on the graph's clock).
Ports hold the latest sample; a consumer reads whatever is newest and can tell how old it is.
"""

from __future__ import annotations

import enum
import math
import numbers
import re
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Iterator, Mapping

from pydantic import BaseModel, ConfigDict, ValidationError, model_validator

__all__ = [
    "Kind", "Port", "Sample", "Inputs", "Params", "Component", "Device", "Context", "NAME_RE", "value_checker",
]

#: the slowest and fastest node rates (Hz) a graph, a plugin's default_rate and Harness accept: the simulated clock
#: counts whole nanoseconds (a faster tick repeats graph times), and a slower one overflowed the clocks' step times
#: (1e-300 Hz: an infinite period; 1e-12 Hz on the wall clock: past the platform's time_t)
MIN_RATE = 1e-3
MAX_RATE = 1e6


def rate_problem(hz: Any) -> str | None:
    """Why ``hz`` is no node rate (what was expected), or None: a number of Hz from MIN_RATE to MAX_RATE."""
    if isinstance(hz, bool) or not isinstance(hz, (int, float)) or not (hz > 0 and math.isfinite(hz)):
        return "must be a positive number of Hz"
    if hz > MAX_RATE:
        return (f"at most {MAX_RATE:.0f} Hz (1 MHz: the simulated clock counts whole nanoseconds, and a faster tick "
                f"repeats graph times)")
    if hz < MIN_RATE:
        return f"at least {MIN_RATE:g} Hz (one step per {1 / MIN_RATE:.0f} s)"
    return None


#: seconds: stamps this close count as equal in :meth:`Sample.is_fresh` (the simulated clock counts whole ns)
STAMP_TOLERANCE = 1e-9

NAME_RE = re.compile(r"^[a-z][a-z0-9]*(?:-[a-z0-9]+)*$")


class Kind(str, enum.Enum):
    SENSOR = "sensor"
    ESTIMATOR = "estimator"
    DEVICE = "device"
    CONTROLLER = "controller"
    BRIDGE = "bridge"

    def __str__(self) -> str:  # pragma: no cover - trivial
        return self.value


def shapes_differ(a: tuple[int | None, ...], b: tuple[int | None, ...]) -> bool:
    """Whether shapes ``a`` and ``b`` cannot be one (another number of dimensions, or two sizes that differ; ``None``:
    any size)."""
    return len(a) != len(b) or any(x is not None and y is not None and x != y for x, y in zip(a, b))


def plain_results(got: Mapping[Any, Any]) -> dict[str, Any]:
    """A component's :meth:`Component.results` as JSON can hold them: keys as text, numbers as int or float, bools,
    text and None as they are, anything else as its repr."""
    out: dict[str, Any] = {}
    for k, v in got.items():
        if isinstance(v, (bool, str)) or v is None:
            out[str(k)] = v
        elif isinstance(v, numbers.Integral):
            out[str(k)] = int(v)
        elif isinstance(v, numbers.Real):
            out[str(k)] = float(v)
        else:
            out[str(k)] = repr(v)
    return out


def has_warm_up(cls: type, params: Any = None) -> bool:
    """Whether the runtime calls :meth:`Component.warm` of a node of class ``cls`` (under the wall clock): a warm()
    of its own, and no device's (a warm-up must never command one). For an isolated node, its class in the child.
    With the node's validated ``params``, also whether that node wants it (:meth:`Component.wants_warm_up`): the
    runtime asks so once the node has configured, inline or isolated (then no round trip to its child)."""
    if cls.warm is Component.warm or issubclass(cls, Device):
        return False
    return params is None or bool(cls.wants_warm_up(params))


@dataclass(frozen=True)
class Port:
    """A typed port.

    dtype: numpy dtype name ("float64", "uint8", "bool", ...) or "any".
    shape: () for a scalar; ``None`` in a dimension means any size (an image is ``(None, None, 3)``); ``None`` for
        the whole shape means any number of dimensions.
    unit: SI unit symbol ("m", "N", "s", "m^2", "m/s"); "" for dimensionless; "any" to accept anything.
    required: for inputs, whether the graph must wire it.
    max_age: for inputs, the default staleness limit in seconds (None: no limit); a graph may override it.
    """

    dtype: str = "float64"
    shape: tuple[int | None, ...] | None = ()
    unit: str = ""
    description: str = ""
    required: bool = True
    max_age: float | None = None

    def describe(self) -> str:
        if self.shape is None:
            shape = "any shape"
        else:
            shape = "scalar" if self.shape == () else "x".join("*" if d is None else str(d) for d in self.shape)
        unit = self.unit or "1"
        return f"{self.dtype}[{shape}] {unit}"

    def accepts(self, source: "Port") -> str | None:
        """Return None if data from ``source`` may flow into this (input) port, else why not."""
        if self.dtype != "any" and source.dtype != "any" and self.dtype != source.dtype:
            return f"type mismatch: {source.dtype} -> {self.dtype}"
        if self.unit != "any" and source.unit != "any" and self.unit != source.unit:
            return f"unit mismatch: '{source.unit or '1'}' -> '{self.unit or '1'}'"
        if self.shape is not None and source.shape is not None and shapes_differ(self.shape, source.shape):
            return f"shape mismatch: {source.describe()} -> {self.describe()}"
        return None

    def describe_value(self) -> str:
        """What a value of this port is, for a person: "float64 scalar", "uint8 array of shape (*, *, 3)"."""
        if self.dtype == "any":
            return "any value"
        if self.shape == ():
            return f"{self.dtype} scalar"
        if self.shape is None:
            return f"{self.dtype} scalar or array of any shape"
        dims = ", ".join("*" if d is None else str(d) for d in self.shape)
        return f"{self.dtype} array of shape ({dims}{',' if len(self.shape) == 1 else ''})"

    def value_problem(self, value: Any) -> str | None:
        """None if ``value`` may be written to this (output) port, else what came instead ("str", "float64 array
        of shape (240, 320)"). See :func:`value_checker` for the rules."""
        check = value_checker(self)
        return None if check is None else check(value)

    def as_dict(self, name: str) -> dict[str, Any]:
        shape = None if self.shape is None else list(self.shape)
        d: dict[str, Any] = {"name": name, "dtype": self.dtype, "shape": shape, "unit": self.unit}
        if self.description:
            d["description"] = self.description
        return d


def _what(value: Any) -> str:
    """What a value is, for a message: its dtype and shape for an array, else its type."""
    import numpy as np

    if isinstance(value, np.ndarray):
        if value.ndim == 0:
            return f"{value.dtype} 0-d array"
        return f"{value.dtype} array of shape {value.shape}"
    if isinstance(value, np.generic):
        return f"numpy {value.dtype} scalar"
    return "None" if value is None else type(value).__name__


def value_checker(port: Port) -> Callable[[Any], str | None] | None:
    """A function ``check(value) -> None | what came`` for the values written to an output ``port``; None for a
    port of dtype "any" (nothing is checked). Built once per port: the runtime calls it for every output it stores.

    - Scalar ports (shape ``()``): a float port (float64, float32) takes a Python float or int (not a bool) and a
      numpy float or integer scalar; an integer port takes a Python int (not a bool) and a numpy integer scalar; a
      bool port a Python or numpy bool; a str port a str. A 0-d numpy array counts as its scalar. NaN and inf are
      numbers: they pass (consumers guard).
    - Array ports: a numpy array of exactly the port's dtype (a float64 image on a uint8 port is refused), with as
      many dimensions as the shape has and each fixed dimension equal (``None`` is any size). A list or tuple is not
      an array.
    - Shape ``None``: an array of the dtype with any shape, or a scalar as above.
    - The unit is not checked: a value carries none.
    """
    import numpy as np

    if port.dtype == "any":
        return None
    dt = np.dtype(port.dtype)
    kind = dt.kind
    if kind == "f":
        py: tuple[type, ...] = (float, int)
        gen: tuple[type, ...] = (np.floating, np.integer)
        kinds = "fiu"
    elif kind in "iu":
        py, gen, kinds = (int,), (np.integer,), "iu"
    elif kind == "b":
        py, gen, kinds = (bool,), (np.bool_,), "b"
    elif kind == "U":
        py, gen, kinds = (str,), (np.str_,), "U"
    elif kind == "c":
        py, gen, kinds = (complex, float, int), (np.number,), "fiuc"
    else:
        py, gen, kinds = (), (np.generic,), kind
    no_bool = kind != "b"
    fast = {c for c in (float, int, bool, str, np.float64, np.float32, np.int64, np.bool_, np.str_)
            if issubclass(c, py + gen) and not (no_bool and c in (bool, np.bool_))}
    shape = port.shape
    ndarray = np.ndarray

    def scalar(value: Any) -> str | None:
        if value.__class__ in fast:
            return None
        if isinstance(value, (bool, np.bool_)) and no_bool:
            return _what(value)
        if isinstance(value, py + gen):
            if isinstance(value, np.generic) and value.dtype.kind not in kinds:
                return _what(value)
            return None
        if isinstance(value, ndarray) and value.ndim == 0 and value.dtype.kind in kinds:
            return None
        return _what(value)

    if shape == ():
        return scalar
    ndim = None if shape is None else len(shape)
    fixed = [] if shape is None else [(i, d) for i, d in enumerate(shape) if d is not None]

    def array(value: Any) -> str | None:
        if value.__class__ is not ndarray and not isinstance(value, ndarray):
            return scalar(value) if shape is None else _what(value)
        vdt = value.dtype
        if vdt is not dt and vdt != dt and not (kind == "U" and vdt.kind == "U"):   # (built-in dtypes: one object)
            return _what(value)
        if ndim is not None:
            s = value.shape
            if len(s) != ndim:
                return _what(value)
            for i, d in fixed:
                if s[i] != d:
                    return _what(value)
        return None

    return array


class Sample:
    """A value and the time (s, graph clock) at which it was measured."""

    __slots__ = ("value", "stamp")

    def __init__(self, value: Any, stamp: float):
        self.value = value
        self.stamp = stamp

    def age(self, now: float) -> float:
        return now - self.stamp

    def is_fresh(self, now: float, max_age: float) -> bool:
        """Whether the sample may be used at ``now``: at most ``max_age`` old and at most ``max_age`` ahead of
        ``now`` (a stamp from the future beyond that is a clock fault, not a fresh sample). False for a NaN stamp,
        so a bad stamp counts as stale rather than as fresh forever. Within a nanosecond (STAMP_TOLERANCE, the
        simulated clock's tick) of the limit counts as at the limit: graph times are floats, and a sample exactly
        max_age old was fresh at one time and stale at another (1.59 - 1.49 > 0.1)."""
        return -max_age - STAMP_TOLERANCE <= now - self.stamp <= max_age + STAMP_TOLERANCE

    def __repr__(self) -> str:
        return f"Sample({self.value!r}, stamp={self.stamp:.6f})"


def finite_stamp(stamp: Any) -> bool:
    """Whether ``stamp`` is a finite real number of seconds (a bool, a Decimal or an array is not one)."""
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float, numbers.Real)):
        return False
    try:
        return math.isfinite(stamp)
    except (TypeError, ValueError, OverflowError):
        return False


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def step_location(cls: type) -> str:
    """Where a person finds a component's step(): ``returned by Class.step (file.py:line)``."""
    code = getattr(getattr(cls, "step", None), "__code__", None)
    at = f" ({code.co_filename.rsplit('/', 1)[-1]}:{code.co_firstlineno})" if code is not None else ""
    return f"returned by {cls.__name__}.step{at}"


def step_samples(out: Any, ports: Mapping[str, Port], checks: Mapping[str, Callable[[Any], str | None] | None],
                 t: float) -> list[tuple[str, Sample]]:
    """A step's outputs as (port name, Sample), each checked as the runtime checks it (and the test Harness, the
    same way): ``out`` a mapping of output name to value or Sample; a value is stamped ``t``, a Sample's stamp must
    be a finite number of seconds (kept, as float); each value must fit its port (``checks``: port name ->
    :func:`value_checker`'s check, None for dtype "any"). Raises ComponentFault naming the output and what was
    expected: then none of the step's outputs may be stored (consumers never see half of a step)."""
    from .errors import ComponentFault

    try:
        items = out.items()
    except AttributeError:
        raise ComponentFault(f"step() returned {type(out).__name__} {_short(out)}; expected a mapping of output "
                             f"name to value (outputs: {', '.join(ports) or '(none)'}) or None") from None
    ready = []
    for name, v in items:
        if name not in checks:
            raise ComponentFault(f"step() returned unknown output '{name}'; outputs: {', '.join(ports)}")
        if v.__class__ is Sample:
            if v.stamp.__class__ is not float or not math.isfinite(v.stamp):   # fast path: a finite float
                if not finite_stamp(v.stamp):
                    raise ComponentFault(f"step() returned output '{name}' stamped {v.stamp!r}: a stamp must be a "
                                         f"finite graph time in seconds")
                v = Sample(v.value, float(v.stamp))
        else:
            v = Sample(v, t)
        check = checks[name]
        if check is not None:
            got = check(v.value)
            if got is not None:
                raise ComponentFault(f"output '{name}': expected {ports[name].describe_value()}, got {got}")
        ready.append((name, v))
    return ready


class _Slot:
    """Holds the latest sample of one output port. Assignment of a reference is atomic in CPython."""

    __slots__ = ("sample",)

    def __init__(self) -> None:
        self.sample: Sample | None = None


class Inputs:
    """Read-only view of a node's inputs: ``inputs["force"]`` is the latest :class:`Sample` (or None)."""

    __slots__ = ("_slots",)

    def __init__(self, slots: Mapping[str, _Slot]):
        self._slots = dict(slots)

    def __getitem__(self, name: str) -> Sample | None:
        return self._slots[name].sample

    def __contains__(self, name: object) -> bool:
        return name in self._slots

    def __iter__(self) -> Iterator[str]:
        return iter(self._slots)

    def get(self, name: str) -> Sample | None:
        slot = self._slots.get(name)
        return None if slot is None else slot.sample

    def value(self, name: str, default: Any = None) -> Any:
        """The latest value of ``name``, or ``default`` if it is unwired or nothing arrived yet."""
        slot = self._slots.get(name)
        if slot is None or slot.sample is None:
            return default
        return slot.sample.value

    def age(self, name: str, now: float) -> float:
        """Seconds since the latest sample of ``name`` was measured (inf if none yet)."""
        slot = self._slots.get(name)
        if slot is None or slot.sample is None:
            return math.inf
        return now - slot.sample.stamp

    def fresh(self, name: str, now: float, max_age: float) -> Any:
        """The latest value if it is at most ``max_age`` seconds old, else None."""
        slot = self._slots.get(name)
        if slot is None or slot.sample is None or not slot.sample.is_fresh(now, max_age):
            return None
        return slot.sample.value


def _field_unit(f: Any) -> str | None:
    """The SI unit a Params field's schema names (``json_schema_extra={"unit": "Hz"}``), None for none or "1"."""
    extra = f.json_schema_extra
    unit = extra.get("unit") if isinstance(extra, dict) else None
    return unit if unit and unit not in ("", "1") else None


_BOOLEAN_NUMBER = "expected a number, got a boolean (YAML reads yes, no, on and off as true and false)"


class Params(BaseModel):
    """Base class of component parameters: unknown fields are refused, values are validated on assignment, and
    numbers must be finite (``.inf`` would switch a limit off, NaN would pass every comparison) and not booleans
    (pydantic takes ``True`` as 1; YAML reads ``yes`` and ``on`` as true).

    A field whose schema names a unit (``json_schema_extra={"unit": "Hz"}``, or ``teletouch.units.quantity``)
    also accepts a string with units, converted to SI: ``cutoff: 2kHz`` -> 2000.0, ``radius: 5mm`` -> 0.005.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _parse_units(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        from .units import parse_quantity

        out = None
        problems = []
        for fname, f in cls.model_fields.items():
            unit = _field_unit(f)
            key = f.alias or fname
            value = data.get(key)
            if unit and isinstance(value, str):
                try:
                    parsed = parse_quantity(value, unit)
                except ValueError as exc:
                    problems.append(f"{key}: {exc}")
                    continue
                if out is None:
                    out = dict(data)
                out[key] = parsed
        if problems:   # every bad quantity at once, one per line, each led by its field name
            raise ValueError("\n".join(problems))
        return data if out is None else out

    @model_validator(mode="wrap")
    @classmethod
    def _no_boolean_numbers(cls, data: Any, handler: Any) -> Any:
        """A boolean given where the field keeps no boolean is refused, each led by its field name: pydantic takes
        it as 1 or 0 in a number field, and YAML reads yes, no, on and off as booleans (``gain: yes`` ran with gain
        1, ``step_time: on`` at 1 s)."""
        result = handler(data)
        if isinstance(data, dict) and isinstance(result, BaseModel):
            bad = [f"{k}: {_BOOLEAN_NUMBER}"
                   for k, v in data.items() if isinstance(v, bool) and k in cls.model_fields
                   and not isinstance(getattr(result, k, v), bool)]
            if bad:
                raise ValueError("\n".join(bad))
        return result

    def __setattr__(self, name: str, value: Any) -> None:
        """Assignment is validated (``validate_assignment``) as construction is: the model validators above see only
        the model there, not the value, so their two rules are applied here. A boolean for a field that keeps no
        boolean is refused (before, ``params.scale = True`` set 1.0); a string with units for a field whose schema
        names one is converted to SI (``params.cutoff = "2kHz"`` was refused). The same messages as at
        construction; on an error the field keeps its value."""
        f = type(self).model_fields.get(name)
        unit = None if f is None else _field_unit(f)
        if unit and isinstance(value, str):
            from .units import parse_quantity

            try:
                value = parse_quantity(value, unit)
            except ValueError as exc:
                raise self._assignment_error(name, value, str(exc)) from None
        elif f is not None and isinstance(value, bool):
            probe = self.model_copy()
            super(Params, probe).__setattr__(name, value)   # validated as the assignment would be (may raise)
            if not isinstance(getattr(probe, name), bool):
                raise self._assignment_error(name, value, _BOOLEAN_NUMBER)
        super().__setattr__(name, value)

    def _assignment_error(self, name: str, value: Any, problem: str) -> ValidationError:
        """The ValidationError that construction raises for ``problem`` of field ``name``: led by its name."""
        return ValidationError.from_exception_data(type(self).__name__, [{
            "type": "value_error", "loc": (), "input": value, "ctx": {"error": ValueError(f"{name}: {problem}")}}])


class Context:
    """What the runtime gives a component: the clock, a logger, a way to end the run, its step rate, and which of the
    nodes feeding it a fault has disabled (:meth:`disabled_upstream`)."""

    def __init__(self, now: Callable[[], float] | None = None, clock_kind: str = "sim",
                 request_stop: Callable[[str], None] | None = None,
                 log: Callable[[str], None] | None = None,
                 from_monotonic: Callable[[float], float] | None = None, rate: float | None = None,
                 disabled_upstream: Callable[[], list[str]] | None = None):
        import time

        t0 = time.monotonic()
        self.now = now or (lambda: time.monotonic() - t0)
        self.clock_kind = clock_kind
        self._request_stop = request_stop
        self._log = log
        self.from_monotonic = from_monotonic or (lambda m: m - t0)
        self.rate = rate   # the node's step rate (Hz) in the graph; None outside a graph
        self._disabled_upstream = disabled_upstream

    def disabled_upstream(self) -> list[str]:
        """The ids of the nodes that feed this node through the graph's wiring, directly or through other nodes, and
        that a fault has disabled so far (action stop or degrade), in data-flow order; [] while none is, and outside
        a graph. A node disabled by a fault publishes nothing more, but a node in between (a filter) may go on
        publishing its last value with fresh stamps: the inputs' own freshness cannot tell. Under degrade the runtime
        disables the devices such a node commands, directly or through nodes that do not guard them
        (:attr:`Component.guards_upstream`); a node that guards its devices, or must not go on with stale data (the
        press routine, position-force), asks here. Cheap enough to call every step. A fault in another rate group
        (the wall clock) shows from the moment the runtime records it; an isolated node (``isolate: process``) gets
        the list sent with each step, as it was when the step was sent."""
        if self._disabled_upstream is None:
            return []
        return list(self._disabled_upstream())

    def request_stop(self, reason: str = "done") -> None:
        """End the run normally (e.g. a calibration routine that has finished)."""
        if self._request_stop is not None:
            self._request_stop(reason)

    def log(self, message: str) -> None:
        if self._log is not None:
            self._log(message)


class Component:
    """Base class for all components. Subclasses set ``name``, ``kind``, ``Params``, ``inputs``, ``outputs``
    and implement :meth:`step`; lifecycle hooks are optional.

    ``step(t, inputs)`` is called at the node's rate with the current graph time ``t`` (s). It returns a mapping of
    output port name to value (stamped with ``t``) or to a :class:`Sample` (to give the measurement time, e.g. a
    camera's capture time), or None for no new outputs.
    """

    name: ClassVar[str] = ""
    kind: ClassVar[Kind] = Kind.ESTIMATOR
    description: ClassVar[str] = ""
    Params: ClassVar[type[Params]] = Params
    inputs: ClassVar[dict[str, Port]] = {}
    outputs: ClassVar[dict[str, Port]] = {}
    default_rate: ClassVar[float | None] = None
    #: True for drivers of real hardware: refused under the simulated clock.
    requires_wall_clock: ClassVar[bool] = False
    #: True for a component that brings the devices it commands to a safe end itself when a node feeding it is lost
    #: (its input goes stale or ``ctx.disabled_upstream()`` names it: position-force fades the force on the hand and
    #: holds the follower, the press routine aborts). False, the default (a filter, a gain: each passes its last value
    #: on with fresh stamps): under ``degrade`` a device it feeds, directly or through others like it, is made safe
    #: and disabled when a node upstream of it is disabled by a fault.
    guards_upstream: ClassVar[bool] = False

    def __init__(self, params: Params | Mapping[str, Any] | None = None, *, node_id: str | None = None,
                 ctx: Context | None = None):
        if params is None:
            params = self.Params()
        elif not isinstance(params, BaseModel):
            params = self.Params(**dict(params))
        self.params = params
        self.id = node_id or self.name
        self.ctx = ctx or Context()

    @classmethod
    def wiring_problems(cls, params: Any, inputs: Any, outputs: Any) -> dict[str, str]:
        """Wiring this component refuses beyond what its ports declare, checked when a graph is validated:
        ``params`` are the node's validated parameters, ``inputs`` its wired input ports, ``outputs`` its output
        ports that other nodes read. Returns {port: why}; empty when all is well (the default). Example: a bridge
        whose parameters leave a wired port without a topic."""
        return {}

    @classmethod
    def port_shapes(cls, params: Any) -> dict[str, tuple]:
        """The shapes of ports that the node's validated ``params`` fix where the port leaves them open (an image
        is declared ``(None, None, 3)``; a camera's resolution or a model file fixes its rows and cols), checked when
        a graph is validated: {port: (shape, why)} or {port: (shape, why, how)}, ``why`` what fixes it, for a person
        ("resolution 'qvga'"), ``how`` what changes it ("set resolution: qvga (320x240) or vga (640x480)"). A port
        name is an input's or an output's. A wire whose two ends fix shapes that differ (``None``: any size) is
        refused, naming both. Empty when the parameters fix none (the default)."""
        return {}

    @classmethod
    def port_sources(cls, params: Any) -> dict[str, tuple]:
        """What the values on ports are tied to by the node's validated ``params``, checked when a graph is validated:
        the model or calibration that gives them their scale. {port: (identity, why)} or {port: (identity, why,
        how)}: ``identity`` a non-empty string compared as it is (the depth node's max depth is tied to its model's
        name, ``'sim-digit-qvga'``; poly-force's max depth input to the depth model its calibration was made for),
        ``why`` what ties it, for a person ("model 'sim-digit-qvga'"), ``how`` what changes it. A port name is an
        input's or an output's. A wire whose two ends both declare an identity for their port, and the identities
        differ, is refused, naming both; an end that declares none is not checked (a bridge, a replay, a filter in
        between). Empty when the parameters tie none (the default)."""
        return {}

    # lifecycle hooks -------------------------------------------------------------------------------------------
    def configure(self) -> None:
        """Allocate resources, open connections, load models. May raise; then the run does not start."""

    def activate(self) -> None:
        """Start acting (enable forces, start capture)."""

    def step(self, t: float, inputs: Inputs) -> Mapping[str, Any] | None:
        raise NotImplementedError(f"{type(self).__name__}.step")

    def deactivate(self) -> None:
        """Stop acting; the component may be activated again."""

    def warm(self) -> None:
        """Optional, wall clock only: called in the node's rate-group thread :attr:`Runtime.WARM_LEAD` (1 ms)
        before each of its steps, so that the step finds its data and code in the CPU's caches. After a pause of
        several milliseconds they are cold again on a shared machine, and a 60 Hz estimator's step takes up to
        twice its time (docs/writing-a-plugin.md). A warm() must not change the outputs or anything a step reads:
        typically it rehearses the last step's work and throws the result away. It is not called for a device,
        under the simulated clock, in a group whose period is under 5 ms, when the step is already due, or where its
        latest warm-up and the group's latest steps took more than half the period (the group would overrun; it is
        tried again a second later); an isolated node's runs in its process (the runtime waits for it as for a step:
        isolation.ProcessProxy.warm). An exception faults the node as one in step() does; the watchdog names a
        warm-up that hangs."""

    @classmethod
    def wants_warm_up(cls, params: Any) -> bool:
        """Whether a node with these validated ``params`` wants its :meth:`warm` called (default: True). For a class
        whose parameters turn its warm-up off (the depth node's ``warm: false``): its warm() is then never called, and
        an isolated node's process is never asked (no round trip before each step; :func:`has_warm_up`)."""
        return True

    def close(self) -> None:
        """Release everything; called once, even after a failed configure."""

    def status(self) -> dict[str, Any]:
        """A few figures for the live view (the first six) and tests: SI, a key with a unit ending in it (``opening_m``,
        ``force_n``; counts, flags and text without; docs/writing-a-plugin.md)."""
        return {}

    def results(self) -> dict[str, Any]:
        """What the run achieved, said once after it: the command line's summary prints it below the table (and
        ``--json`` under each node's ``results``). SI under keys that end in their unit, as :meth:`status` (a
        controller's ``peak_force_n``, ``contact_time_s``). Called once, after deactivate() and before close(), also
        after a fault: keep the figures as the run goes, touch no hardware here. A node in its own process
        (``isolate: process``) is asked there. Empty (the default): nothing to say."""
        return {}

    # introspection ---------------------------------------------------------------------------------------------
    @classmethod
    def describe(cls) -> dict[str, Any]:
        schema = cls.Params.model_json_schema()
        params = []
        for pname, prop in schema.get("properties", {}).items():
            params.append({
                "name": pname,
                "type": _schema_type(prop),
                "default": prop.get("default"),
                "unit": prop.get("unit", ""),
                "description": prop.get("description", ""),
            })
        ports = [dict(p.as_dict(n), direction="in", required=p.required) for n, p in cls.inputs.items()]
        ports += [dict(p.as_dict(n), direction="out") for n, p in cls.outputs.items()]
        return {"name": cls.name, "kind": str(cls.kind.value), "description": cls.description or _doc1(cls),
                "ports": ports, "params": params}


class Device(Component):
    """A component that moves something in the world. It must define :meth:`safe_state`."""

    kind: ClassVar[Kind] = Kind.DEVICE

    def safe_state(self) -> None:
        """Drive the hardware to its safe state (zero leader force; follower holds position). Must not raise
        for a device that is already safe or disconnected; it is called on every stop path, also after a
        ``configure()`` that raised part-way (the port may be open and the torque on, or nothing set up at all).
        The runtime calls it once per stop unless that call raised or the device was stepped after it; a driver
        must still take a repeated call."""
        raise NotImplementedError(f"{type(self).__name__} must define safe_state()")


def _schema_type(prop: dict[str, Any]) -> str:
    if "type" in prop:
        return str(prop["type"])
    if "enum" in prop:
        return "enum(" + "|".join(map(str, prop["enum"])) + ")"
    if "anyOf" in prop:
        return "|".join(_schema_type(p) for p in prop["anyOf"])
    if "$ref" in prop:
        return prop["$ref"].rsplit("/", 1)[-1]
    return "any"


def _doc1(cls: type) -> str:
    doc = (cls.__doc__ or "").strip()
    return doc.splitlines()[0] if doc else ""
