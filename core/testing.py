"""Helpers for testing components and graphs (for teletouch's own tests and for third-party plugin authors).

    from teletouch.testing import Harness, make_registry, run_yaml, safe_states
    with Harness(MyFilter, {"cutoff": "2Hz"}) as h:        # one component, driven by hand
        out = h.step(0.0, x=1.0)                             # outputs checked against their ports, as at run time
    reg = make_registry("my_plugin.module")                  # mocks are always included; a broken plugin raises
    reg = make_registry(my_plugin, builtins=True)            # with teletouch's own components (sim-gripper, ...)
    result, rt = run_yaml(GRAPH_TEXT, registry=reg, duration=1.0)
    safe_states(rt)["gripper"]                               # graph times of each safe_state() call of a device
"""

from __future__ import annotations

import difflib
import importlib
import math
import weakref
from typing import Any, Callable, Iterable

from .component import Component, Context, Device, Inputs, Sample, _Slot, rate_problem, step_samples, value_checker
from .errors import DuplicateComponentError, PluginError
from .graph import GraphSpec, load_graph_text
from .registry import BUILTIN_DISTRIBUTION, ComponentInfo, Registry, check_component
from .runtime import RunResult, Runtime, graph_time
from .units import parse_quantity

__all__ = ["Harness", "make_registry", "load_text", "run_yaml", "safe_states"]


def make_registry(*plugins: Any, mocks: bool = True, builtins: bool = False) -> Registry:
    """A registry without entry-point autoload, holding the mock plugin and the given modules/objects; with
    ``builtins=True`` also teletouch's own plugins (``sim-gripper``, ``depth``, ...; the mocks with them), as an
    installed teletouch has them, whatever ``TELETOUCH_BLOCK`` says.

    A plugin that breaks the rules (a ``teletouch_*`` function without ``@hookimpl``, a device without
    ``safe_state()``, a unit in mm, ...) raises :class:`PluginError` with the reason `teletouch plugins` would show,
    instead of leaving its components out (a test would then only see "unknown plugin"); so does a module that
    implements no teletouch hook at all. A component named like a built-in one (its own class, not the built-in's)
    raises :class:`DuplicateComponentError`, also without ``builtins``: installed beside teletouch, the plugin would
    have that name refused."""
    reg = Registry(autoload=False, blocked=(), extra_modules=())
    given: set[int] = set()   # the modules registered here: a test may name one of them again
    if mocks or builtins:
        from . import mock

        reg.register(mock, name="mock", distribution=BUILTIN_DISTRIBUTION)
        given.add(id(mock))
    if builtins:
        for rec in reg.register_builtins(skip=["mock"]):
            if not rec.error:
                given.add(id(reg.pm.get_plugin(rec.name)))
    for p in plugins:
        mod = importlib.import_module(p) if isinstance(p, str) else p
        if id(mod) in given:
            continue
        name = getattr(mod, "__name__", None)
        rec = reg.register(mod, name=name)
        if rec.error:
            raise PluginError(f"plugin '{rec.name}' failed to load: {rec.error}")
        if not rec.hooks:
            raise PluginError(f"plugin '{rec.name}' implements no teletouch hook: it needs a function "
                              f"teletouch_components() decorated with @teletouch.hookimpl that returns a list of "
                              f"Component classes")
        if not builtins:
            _refuse_builtin_names(reg, rec.name)
    return reg


#: teletouch's own components by name (see :func:`_builtin_components`)
_BUILTINS: dict[str, ComponentInfo] | None = None


def _builtin_components() -> dict[str, ComponentInfo]:
    """teletouch's own components by name, as the entry points of its distribution give them (imported once per
    process)."""
    global _BUILTINS
    if _BUILTINS is None:
        reg = Registry(autoload=False, blocked=(), extra_modules=())
        reg.register_builtins()
        _BUILTINS = dict(reg.components)
    return _BUILTINS


def _same_class(a: type, b: type) -> bool:
    """Whether ``a`` and ``b`` are one class (also when its module was imported twice, or reloaded)."""
    return a is b or (a.__module__, a.__qualname__) == (b.__module__, b.__qualname__)


def _refuse_builtin_names(reg: Registry, plugin: str) -> None:
    """DuplicateComponentError for the first component of ``plugin`` in ``reg`` that is named like a built-in one
    (and is not that one): installed, teletouch would refuse the name, where this registry, without the built-ins,
    would have let it pass."""
    for cname in reg.plugins[plugin].components:
        builtin = _builtin_components().get(cname)
        if builtin is not None and not _same_class(builtin.cls, reg.components[cname].cls):
            raise DuplicateComponentError(
                f"plugin '{plugin}': component '{cname}' has the name of a built-in component (plugin "
                f"'{builtin.plugin}' of {builtin.origin}): once your plugin is installed, teletouch refuses the name "
                f"and a graph can use neither; rename yours")


def load_text(text: str, registry: Registry, **kw: Any) -> GraphSpec:
    return load_graph_text(text, "<test>", registry=registry, **kw)


# graph times of each safe_state() call, per device node, of the runtimes built by run_yaml
_SAFE_LOGS: "weakref.WeakKeyDictionary[Runtime, dict[str, list[float]]]" = weakref.WeakKeyDictionary()


def _spy_safe_states(rt: Runtime, spec: GraphSpec) -> None:
    log: dict[str, list[float]] = {}
    for node in spec.nodes:
        comp = rt.component(node.id)
        if not isinstance(comp, Device):
            continue
        calls = log.setdefault(node.id, [])
        original = comp.safe_state

        def spy(_original: Callable[[], None] = original, _calls: list[float] = calls) -> None:
            _calls.append(rt.now())
            _original()

        comp.safe_state = spy   # type: ignore[method-assign]   # an instance attribute: the runtime calls this one
    _SAFE_LOGS[rt] = log


def run_yaml(text: str, registry: Registry, duration: float | None = None, clock: str | None = None,
             taps: Iterable[Any] = (), **kw: Any) -> tuple[RunResult, Runtime]:
    """Run a graph given as YAML text (the simulated clock unless it or ``clock`` says otherwise). ``taps`` are
    called as ``tap(node_id, t, outputs)`` for every step of every node. Every device's ``safe_state()`` calls are
    recorded: :func:`safe_states` lists them."""
    spec = load_text(text, registry, clock=clock, **kw)
    rt = Runtime(spec, clock=clock, log=lambda m: None)
    _spy_safe_states(rt, spec)
    for tap in taps:
        rt.add_tap(tap)
    return rt.run(duration), rt


def safe_states(rt: Runtime) -> dict[str, list[float]]:
    """For a runtime made by :func:`run_yaml`: each device node's id -> the graph times (s) at which the runtime
    called its ``safe_state()`` (on a fault, on a stop, at the end of the run). Nodes that are not devices are not
    listed."""
    try:
        return {k: list(v) for k, v in _SAFE_LOGS[rt].items()}
    except (KeyError, TypeError):
        raise ValueError("safe_states() knows only the runtimes that run_yaml() built") from None


def _node_rate(cls: type[Component], rate: Any) -> float:
    """``Harness(..., rate=)`` as a graph takes a node's ``rate:``: Hz, a number or a quantity (``"1kHz"``), positive,
    finite and from MIN_RATE to MAX_RATE; otherwise ValueError naming the class and what was expected (the graph refuses
    such a rate: run() looped for ever above 1 GHz, and a negative one froze a speed limit counted from it)."""
    try:
        hz = parse_quantity(rate, "Hz")
        problem = rate_problem(hz)
        if problem:
            raise ValueError(f"{problem} (as in a graph), got {rate!r}")
    except (TypeError, ValueError) as exc:
        raise ValueError(f"Harness({cls.__qualname__}): rate: {exc}") from None
    return hz


def _tick_ns(k: int, rate: float) -> int:
    """Graph time (ns) of a node's k-th step on the simulated clock, as the runtime counts it (Runtime._run_sim):
    k periods rounded once, not k rounded periods (7 Hz: 1.000000001 s for the step at 1 s)."""
    return int(round(k * 1e9 / rate))


class Harness:
    """Drive one component by hand: set inputs, call step, read outputs; what the runtime would refuse is refused.

    - The class is checked as a plugin's components are checked when it loads (:class:`PluginError` naming the
      class and attribute: a device without ``safe_state()``, a unit in mm, ...).
    - ``h.step(t, **inputs)`` sets the inputs and steps at graph time ``t``; a value is stamped ``t``, a
      :class:`Sample` keeps its own stamp (``Sample(v, t - 0.5)`` is half a second old: a stale input), ``None``
      empties the input (nothing received). It returns the outputs as values; ``h.samples`` has them as Samples,
      and ``h.history`` has ``(t, {port: Sample})`` of every step so far (``h.run``'s too: the stamps over a run;
      ``h.history.clear()`` forgets them).
      The outputs are checked against their ports as the runtime checks them (dtype and shape, output names,
      stamps): what would fault the node in a graph raises :class:`ComponentFault` with the runtime's message.
    - ``h.run(until, **inputs)`` steps on a simulated clock at the node's rate (``rate=`` or the class's
      ``default_rate``) from the next tick up to ``until``, on the ticks of a graph's simulated clock; an input given
      as a function is called with ``t``. A ``rate=`` that a graph refuses is refused (ValueError); one with its unit
      (``"1kHz"``) is taken as a graph takes it.
    - Devices: ``h.safe_state()`` calls the device's safe state, and leaving the ``with`` block calls it too (as the
      runtime does at the end of every run, and after a fault: also when the block raised) before ``deactivate()``
      and ``close()``, which are still called when it raises (its error goes on after them, as the runtime reports
      it and still shuts the node down); ``h.safe_calls`` counts the calls made through the harness.
    - ``h.warm()`` calls the component's ``warm()`` (not a device's, nor one its ``wants_warm_up`` turns off for
      these parameters: the runtime never calls those).
    - ``h.stopped`` is the reason given to ``ctx.request_stop()`` (None if not called).
    - ``h.disabled_upstream`` (a list of node ids, [] at first) is what ``ctx.disabled_upstream()`` returns: set it
      to see how the component takes a node feeding it that a fault has disabled.
    """

    def __init__(self, cls: type[Component], params: Any = None, *, rate: float | None = None, **kw: Any):
        check_component(cls)
        self.cls = cls
        self.t = 0.0
        self.rate = cls.default_rate if rate is None else _node_rate(cls, rate)
        self.disabled_upstream: list[str] = []
        self.ctx = Context(now=lambda: self.t, clock_kind="sim", request_stop=self._stop,
                           log=lambda m: None, from_monotonic=lambda m: self.t, rate=self.rate,
                           disabled_upstream=lambda: self.disabled_upstream)
        self.comp = cls(params, node_id=cls.name, ctx=self.ctx, **kw)
        self.slots = {name: _Slot() for name in cls.inputs}
        self.inputs = Inputs(self.slots)
        self.checks = {name: value_checker(port) for name, port in cls.outputs.items()}
        self.samples: dict[str, Sample] = {}
        #: ``(t, {port: Sample})`` of every step made through the harness, in order (``{}``: the step returned None)
        self.history: list[tuple[float, dict[str, Sample]]] = []
        self.stopped: str | None = None
        self.safe_calls = 0
        self._steps = 0

    def _stop(self, reason: str) -> None:
        self.stopped = reason

    def __enter__(self) -> "Harness":
        """configure() and activate(), as the runtime starts a node; when either raises, what the runtime does
        then: a device is made safe (it may be half set up), the component is closed, and the error goes on (the
        ``with`` body does not run, so ``__exit__`` would not close it: a driver that holds a port or a
        one-per-process registration leaked into the next test)."""
        try:
            self.comp.configure()
            self.comp.activate()
        except BaseException:
            try:
                if isinstance(self.comp, Device):
                    self.safe_state()
            finally:
                self.comp.close()
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        """safe_state() (a device), deactivate() and close(), as the runtime ends a run: each is called also when
        the one before it raised (a driver whose safe state failed is still stopped and its port closed), and the
        error goes on after close() (an error of a later call goes on instead, the earlier one as its context)."""
        try:
            try:
                if isinstance(self.comp, Device):
                    self.safe_state()
            finally:
                self.comp.deactivate()
        finally:
            self.comp.close()

    def safe_state(self) -> None:
        """Drive a device to its safe state, as the runtime does on a fault or a stop."""
        if not isinstance(self.comp, Device):
            raise TypeError(f"{self.cls.__qualname__} is a {self.cls.kind.value}, not a device: it has no safe state")
        self.safe_calls += 1
        self.comp.safe_state()

    def warm(self) -> None:
        """Call the component's ``warm()`` as the runtime does before a step under the wall clock (its result is
        thrown away; an exception goes on). A device's is refused (TypeError): the runtime never calls it; nor where
        the class's ``wants_warm_up(params)`` says no for these parameters (the depth node's ``warm: false``)."""
        if isinstance(self.comp, Device):
            raise TypeError(f"{self.cls.__qualname__} is a device: the runtime never calls a device's warm() (a "
                            f"warm-up must never command it)")
        if not self.cls.wants_warm_up(self.comp.params):
            raise TypeError(f"{self.cls.__qualname__}.wants_warm_up says no for these parameters: the runtime never "
                            f"calls this node's warm()")
        self.comp.warm()

    def set(self, **values: Any) -> None:
        """Set inputs without stepping: a value is stamped with the harness time, a Sample keeps its stamp, None
        empties the input."""
        for k, v in values.items():
            slot = self.slots.get(k)
            if slot is None:
                close = difflib.get_close_matches(k, list(self.slots), n=1, cutoff=0.6)
                hint = f" (did you mean '{close[0]}'?)" if close else ""
                raise KeyError(f"{self.cls.__qualname__} has no input '{k}'{hint}; inputs: "
                               f"{', '.join(self.slots) or '(none)'}")
            slot.sample = None if v is None else v if isinstance(v, Sample) else Sample(v, self.t)

    def step(self, t: float | None = None, **values: Any) -> dict[str, Any]:
        """Set ``values`` (see :meth:`set`), step at ``t`` (default: the harness time) and return the outputs."""
        if t is not None:
            self.t = t
        self.set(**values)
        self._steps += 1
        out = self.comp.step(self.t, self.inputs)
        self.samples = self._check(out)
        self.history.append((self.t, self.samples))
        return {k: s.value for k, s in self.samples.items()}

    def run(self, until: float, **values: Any) -> list[tuple[float, dict[str, Any]]]:
        """Step at the node's rate on a simulated clock, from the next tick after the harness time (from 0.0 if it
        has not stepped yet) up to and including ``until`` (s); returns ``[(t, outputs), ...]`` (the values; with their
        stamps in ``h.history[-len(result):]``). Each input value is set before every step (stamped with that step's
        time); a function is called with ``t`` for its value."""
        rate = self.rate
        if not rate or not math.isfinite(rate) or rate <= 0:
            raise ValueError(f"{self.cls.__qualname__} has no default_rate: give Harness(..., rate=HZ)")
        tick = 0
        if self._steps:   # the first tick after the harness time
            now_ns = round(self.t * 1e9)
            tick = max(0, math.floor(now_ns * rate / 1e9))
            while tick > 0 and _tick_ns(tick - 1, rate) > now_ns:
                tick -= 1
            while _tick_ns(tick, rate) <= now_ns:
                tick += 1
        result = []
        while _tick_ns(tick, rate) <= round(until * 1e9):
            t = graph_time(_tick_ns(tick, rate))
            self.t = t
            now = {k: (v(t) if callable(v) else v) for k, v in values.items()}
            result.append((t, self.step(t, **now)))
            tick += 1
        return result

    def _check(self, out: Any) -> dict[str, Sample]:
        """The runtime's checks of a step's outputs (component.step_samples); returns them as Samples."""
        if out is None:
            return {}
        return dict(step_samples(out, self.cls.outputs, self.checks, self.t))
