"""argparse ``type=`` functions for numbers with bounds, shared by the command line, the scripts and the benchmarks:
a value out of range is a usage error (exit 2) naming what was expected, before any work starts."""

from __future__ import annotations

import argparse
import math
from typing import Any, Callable

from .units import UNDERSCORE

__all__ = ["number", "int_at_least", "bare_metres_hint"]


def number(kind: type, what: str, lo: float | None = None, lo_open: bool = False,
           hi: float | None = None) -> Callable[[str], Any]:
    """A parser of ``kind`` (int or float) within ``lo`` (excluded if ``lo_open``) and ``hi`` (included), finite;
    else 'expected WHAT, got TEXT' (the text quoted when it is not a number at all: also '1_0', which int() and
    float() would read as 10)."""
    def parse(text: str) -> Any:
        if "_" in text:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r} ({UNDERSCORE})")
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if (isinstance(v, float) and not math.isfinite(v)) or (lo is not None and (v <= lo if lo_open else v < lo)) \
                or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text}")
        return v
    parse.__name__ = what          # argparse names the type in its own messages
    return parse


def int_at_least(low: int) -> Callable[[str], int]:
    """An integer >= ``low``."""
    return number(int, f"an integer >= {low}", lo=low)


def bare_metres_hint(text: object) -> str:
    """For a length option whose value is refused: '; a bare number is metres: did you mean 5mm?' when ``text`` (as
    typed) is a bare number, the likely millimetres read as metres (``--caliper-gap 5`` is 5 m); else ''."""
    t = str(text).strip()
    try:
        if "_" in t or not math.isfinite(float(t)):
            return ""
    except ValueError:
        return ""
    return f"; a bare number is metres: did you mean {t}mm?"
