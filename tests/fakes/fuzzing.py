"""What the seeded safety fuzz tests share: the violation they raise, shrinking a failing case, and the report.

A case is a dataclass with ``seed``, ``steps`` (a list of (time, {event name: event})) and ``describe()``. ``run``
raises :class:`Violation` at the first broken promise, naming its kind and the step.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import pytest


class Violation(AssertionError):
    """A broken promise: its ``kind`` (e.g. "rate") and the ``index`` of the step where it broke."""

    def __init__(self, kind: str, index: int, message: str):
        super().__init__(f"{kind} at step {index}: {message}")
        self.kind, self.index = kind, index


class Attempts:
    """``fails(case)``: the violation of ``kind`` that running ``case`` raises, else None; after ``budget`` runs
    every call answers None (a shrinker's bound), and ``left`` is False."""

    def __init__(self, run: Callable[[Any], None], kind: str, budget: int):
        self.run, self.kind, self.budget, self.tries = run, kind, budget, 0

    @property
    def left(self) -> bool:
        return self.tries < self.budget

    def __call__(self, case: Any) -> Violation | None:
        if not self.left:
            return None
        self.tries += 1
        try:
            self.run(case)
        except Violation as v:
            return v if v.kind == self.kind else None
        return None


def shrink(case: Any, run: Callable[[Any], None], kind: str, budget: int = 300) -> Any:
    """A smaller case that still fails with the same kind of violation: cut after the failing step, then drop events
    (halves, quarters, ... of them) while the failure stays; at most ``budget`` runs."""
    fails = Attempts(run, kind, budget)
    v = fails(case)
    if v is None:
        return case
    case = dataclasses.replace(case, steps=case.steps[:v.index + 1])
    keys = [(i, k) for i, (_, ev) in enumerate(case.steps) for k in ev]
    n = 2
    while keys and n <= 2 * len(keys) and fails.left:
        size = max(1, len(keys) // n)
        removed = False
        for start in range(0, len(keys), size):
            drop = set(keys[start:start + size])
            steps = [(t, {k: e for k, e in ev.items() if (i, k) not in drop}) for i, (t, ev) in enumerate(case.steps)]
            v = fails(dataclasses.replace(case, steps=steps))
            if v is not None:
                case = dataclasses.replace(case, steps=steps[:v.index + 1])
                keys = [k for k in keys if k not in drop and k[0] <= v.index]
                removed = True
                break
        if not removed:
            if size == 1:
                break
            n *= 2
    return case


def check_case(case: Any, run: Callable[[Any], None], budget: int = 300) -> None:
    """Run a case; on a violation fail the test with the seed and the shrunk sequence of events."""
    try:
        run(case)
        return
    except Violation as v:
        failure = v
    small = shrink(case, run, failure.kind, budget)
    pytest.fail(f"{failure}\nrerun: seed {case.seed}; shrunk sequence of events:\n{small.describe()}", pytrace=False)
