"""Helpers for testing components and graphs (for teletouch's own tests and for third-party plugin authors).

    from teletouch.testing import make_registry, run_yaml
    reg = make_registry("my_plugin.module")          # mocks are always included
    result, rt = run_yaml(GRAPH_TEXT, registry=reg, duration=1.0)
"""

from __future__ import annotations

import importlib
from typing import Any, Iterable

from .component import Component, Context, Inputs, Sample, _Slot
from .graph import GraphSpec, load_graph_text
from .registry import Registry
from .runtime import RunResult, Runtime


def make_registry(*plugins: Any, mocks: bool = True) -> Registry:
    """A registry without entry-point autoload, holding the mock plugin and the given modules/objects."""
    reg = Registry(autoload=False, blocked=(), extra_modules=())
    if mocks:
        from . import mock

        reg.register(mock, name="mock", distribution="teletouch")
    for p in plugins:
        mod = importlib.import_module(p) if isinstance(p, str) else p
        reg.register(mod, name=getattr(mod, "__name__", None))
    return reg


def load_text(text: str, registry: Registry, **kw: Any) -> GraphSpec:
    return load_graph_text(text, "<test>", registry=registry, **kw)


def run_yaml(text: str, registry: Registry, duration: float | None = None, clock: str | None = None,
             taps: Iterable[Any] = (), **kw: Any) -> tuple[RunResult, Runtime]:
    spec = load_text(text, registry, clock=clock, **kw)
    rt = Runtime(spec, clock=clock, log=lambda m: None)
    for tap in taps:
        rt.add_tap(tap)
    return rt.run(duration), rt


class Harness:
    """Drive one component by hand: set inputs, call step, read outputs."""

    def __init__(self, cls: type[Component], params: Any = None, **kw: Any):
        self.t = 0.0
        self.ctx = Context(now=lambda: self.t, clock_kind="sim", request_stop=self._stop,
                           log=lambda m: None, from_monotonic=lambda m: self.t, rate=cls.default_rate)
        self.comp = cls(params, node_id=cls.name, ctx=self.ctx, **kw)
        self.slots = {name: _Slot() for name in cls.inputs}
        self.inputs = Inputs(self.slots)
        self.stopped: str | None = None

    def _stop(self, reason: str) -> None:
        self.stopped = reason

    def __enter__(self) -> "Harness":
        self.comp.configure()
        self.comp.activate()
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            self.comp.deactivate()
        finally:
            self.comp.close()

    def set(self, **values: Any) -> None:
        for k, v in values.items():
            self.slots[k].sample = v if isinstance(v, Sample) else Sample(v, self.t)

    def step(self, t: float | None = None, **values: Any) -> dict[str, Any]:
        if t is not None:
            self.t = t
        self.set(**values)
        out = self.comp.step(self.t, self.inputs) or {}
        return {k: (v.value if isinstance(v, Sample) else v) for k, v in out.items()}
