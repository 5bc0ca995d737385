"""Quantities with units on the command line and in graph files.

Every interface in teletouch is SI (m, N, s, rad, Hz). People may write ``6mm``, ``0.006 m``, ``5 N`` or ``2ms``;
:func:`parse_quantity` turns that into the SI float. Plain numbers are taken as already SI.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any

from pydantic import BeforeValidator, Field

# unit symbol -> (SI unit, factor)
_UNITS: dict[str, tuple[str, float]] = {
    "m": ("m", 1.0), "cm": ("m", 1e-2), "mm": ("m", 1e-3), "um": ("m", 1e-6), "µm": ("m", 1e-6),
    "N": ("N", 1.0), "mN": ("N", 1e-3), "kN": ("N", 1e3),
    "s": ("s", 1.0), "ms": ("s", 1e-3), "us": ("s", 1e-6), "µs": ("s", 1e-6),
    "Hz": ("Hz", 1.0), "kHz": ("Hz", 1e3),
    "rad": ("rad", 1.0), "deg": ("rad", math.pi / 180.0),
    "N/m": ("N/m", 1.0), "N/mm": ("N/m", 1e3), "kN/m": ("N/m", 1e3),
    "N*s/m": ("N*s/m", 1.0), "Ns/m": ("N*s/m", 1.0),
    "m/s": ("m/s", 1.0), "mm/s": ("m/s", 1e-3),
    "kg": ("kg", 1.0), "g": ("kg", 1e-3),
    "Pa": ("Pa", 1.0), "kPa": ("Pa", 1e3), "MPa": ("Pa", 1e6),
    "px/mm": ("px/m", 1e3), "px/m": ("px/m", 1.0),
    "m^2": ("m^2", 1.0), "mm^2": ("m^2", 1e-6), "cm^2": ("m^2", 1e-4),
    "N/s": ("N/s", 1.0), "J": ("J", 1.0), "mJ": ("J", 1e-3), "W": ("W", 1.0), "mW": ("W", 1e-3),
    "1/s": ("1/s", 1.0), "N/A": ("N/A", 1.0), "bit/s": ("bit/s", 1.0), "kbit/s": ("bit/s", 1e3),
    "Mbit/s": ("bit/s", 1e6),
    "N*m*s/rad": ("N*m*s/rad", 1.0), "m/(N*s)": ("m/(N*s)", 1.0), "N/(m*s)": ("N/(m*s)", 1.0),
}

#: the SI units the table converts to: a field declared in another unit takes only a plain number
_SI_UNITS: tuple[str, ...] = tuple(dict.fromkeys(si for si, _ in _UNITS.values()))

_QTY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\d\s].*|1/\S.*)?\s*$")
#: inf, nan (what float() takes for a number that is not finite), with or without a unit after them
_NON_FINITE = re.compile(r"^\s*[-+]?(?:inf(?:inity)?|nan)(?![a-z])", re.IGNORECASE)
#: GREEK SMALL LETTER MU, what Greek keyboards type and NFKC makes of the table's MICRO SIGN: the same prefix
_GREEK_MU, _MICRO = "\u03bc", "\u00b5"

#: what an example quantity of each SI unit looks like in a message
_EXAMPLES: dict[str | None, str] = {
    "m": "'6mm' or '0.006'", "N": "'5N' or '5'", "s": "'2ms' or '0.002'", "Hz": "'1kHz' or '1000'",
    "rad": "'30deg' or '0.52'", "px/m": "'17.15px/mm'", "m/s": "'20mm/s' or '0.02'", "N/m": "'2N/mm' or '2000'",
    None: "'6mm' or '0.006'",
}

#: why a number with an underscore is refused (Python's float() and int() take '1_0' for 10)
UNDERSCORE = "an underscore in a number is taken for a typo, not for a digit separator"

#: no gripper opens wider than this (the PAL gripper: 0.09 m); a larger opening, offset or limit in a metre field
#: is millimetres typed there
MAX_PLAUSIBLE_OPENING = 1.0        # m


#: a DIGIT's gel is 4-5 mm thick: no depth into it, nor a threshold, tolerance or margin on one, is larger; a larger
#: one in a metre field is millimetres typed there (``contact_threshold: 30`` read 30 m and saw no contact at all)
MAX_PLAUSIBLE_GEL_DEPTH = 5e-3     # m
#: no limit on a measured depth is set deeper than this, even one beyond the gel for a test rig or a calibration of
#: a thicker gel (calibrated depths stop below 10 mm); a deeper one is millimetres typed in the metre field
MAX_PLAUSIBLE_DEPTH_LIMIT = 0.1    # m
#: a DIGIT's sensing area is about 15-20 x 20-25 mm: no contact is larger; a larger area in a m^2 field is mm^2 typed
#: there
MAX_PLAUSIBLE_CONTACT_AREA = 20e-3 * 25e-3   # m^2


def _metres_typed(name: str, value: float, limit: float, beyond: str, note: str = "") -> str | None:
    """None if ``|value|`` (m) is at most ``limit``; else why ``name`` looks like millimetres typed in a metre field:
    it is ``beyond`` what is plausible (``note``: said with the limit)."""
    if abs(value) <= limit:
        return None
    head = f"{name} ({value:g} m) is {beyond} ({limit:g} m at most{note})"
    for small, factor in (("mm", 1e-3), ("um", 1e-6)):   # the unit meant: the first in which the value fits
        if abs(value) * factor <= limit:
            what = "millimetres" if small == "mm" else "micrometres"
            return (f"{head}: {what} in the metre field? a bare number is metres: for {value:g} {small} write "
                    f"{value * factor:g} or \"{value:g}{small}\"")
    return f"{head}: a bare number is metres"


def millimetres_in_metres(name: str, value: float, limit: float = MAX_PLAUSIBLE_OPENING) -> str | None:
    """None if ``|value|`` (m) is a plausible gripper opening; else why ``name`` looks like millimetres typed in a
    metre field (``opening_max: 90`` meant 90 mm and was taken as 90 m)."""
    return _metres_typed(name, value, limit, "beyond any gripper's opening")


def too_deep(name: str, value: float, limit: float = MAX_PLAUSIBLE_GEL_DEPTH) -> str | None:
    """None if ``|value|`` (m) is a plausible depth into a DIGIT's gel (or a threshold, tolerance or margin on one);
    else why ``name`` looks like millimetres typed in a metre field (``contact_threshold: 0.03`` meant 0.03 mm). With
    ``limit`` beyond the gel (:data:`MAX_PLAUSIBLE_DEPTH_LIMIT`: a limit on the measured depth) it says so."""
    if limit > MAX_PLAUSIBLE_GEL_DEPTH:
        return _metres_typed(name, value, limit, "deeper than a gel is pressed, even on a test rig")
    return _metres_typed(name, value, limit, "more than a DIGIT's gel is thick", "; the gel is 4-5 mm")


def plausible_depth(name: str, value: float, limit: float = MAX_PLAUSIBLE_GEL_DEPTH) -> float:
    """``value`` if it is a plausible depth into the gel (:func:`too_deep`), else a ValueError with its message: for
    validators of depth fields."""
    return _refused(too_deep(name, value, limit), value)


def too_large_an_area(name: str, value: float, limit: float = MAX_PLAUSIBLE_CONTACT_AREA) -> str | None:
    """None if ``|value|`` (m^2) is a plausible contact area on a DIGIT; else why ``name`` looks like mm^2 typed in
    the m^2 field (``min_contact_area: 4`` meant 4 mm^2 and was taken as 4 m^2)."""
    return _in_smaller_unit(name, value, limit, "m^2", "mm^2", "larger than a DIGIT's sensing area",
                            "; about 15-20 x 20-25 mm", factor=1e-6)


def plausible_contact_area(name: str, value: float, limit: float = MAX_PLAUSIBLE_CONTACT_AREA) -> float:
    """``value`` if it is a plausible contact area (:func:`too_large_an_area`), else a ValueError with its message:
    for validators of area fields."""
    return _refused(too_large_an_area(name, value, limit), value)


def _refused(problem: str | None, value: float) -> float:
    """``value`` when ``problem`` is None or empty, else a ValueError with it (for validators)."""
    if problem:
        raise ValueError(problem)
    return value


def plausible_opening(name: str, value: float, limit: float = MAX_PLAUSIBLE_OPENING) -> float:
    """``value`` if it is a plausible gripper opening (:func:`millimetres_in_metres`), else a ValueError with its
    message: for validators that refuse such a value (``opening: 15`` held 15 m)."""
    return _refused(millimetres_in_metres(name, value, limit), value)


#: no parallel gripper closes, nor does a person's pinch move, faster than this (the PAL gripper: 0.1 m/s; a quick
#: pinch: well below 1 m/s); a faster gripper or intent speed in a m/s field is millimetres per second typed there
MAX_PLAUSIBLE_SPEED = 2.0          # m/s

#: no haptic device renders more on a hand than this (the Omega.7's grip: 8 N, its translations: 12 N; larger
#: desktop devices: some tens of N): a larger limit of the force sent to a person's hand is millinewtons typed in the
#: newton field, or a typo, and would let a controller's error through to the hand unchecked
MAX_PLAUSIBLE_HAND_FORCE = 50.0    # N


def _in_smaller_unit(name: str, value: float, limit: float, unit: str, small: str, beyond: str, note: str = "",
                     factor: float = 1e-3) -> str | None:
    """None if ``|value|`` (``unit``) is at most ``limit``; else why ``name`` looks like a smaller unit (``small``,
    ``factor`` of ``unit``: e.g. mm/s, 1e-3 m/s) typed in the ``unit`` field: it is ``beyond`` what is plausible
    (``note``: said with the limit)."""
    if abs(value) <= limit:
        return None
    head = f"{name} ({value:g} {unit}) is {beyond} ({limit:g} {unit} at most{note})"
    if abs(value) * factor > limit:   # too large in the smaller unit as well: no value to suggest
        return f"{head}: a bare number is {unit}"
    # the value meant, with its unit where a field parses it (mN/s is not one: the bare number)
    write = f"'{value:g}{small}' ({value * factor:g} {unit})" if small in _UNITS else f"{value * factor:g}"
    return f"{head}: {small} in the {unit} field? a bare number is {unit}: for {value:g} {small} write {write}"


def too_fast(name: str, value: float, limit: float = MAX_PLAUSIBLE_SPEED) -> str | None:
    """None if ``|value|`` (m/s) is a plausible gripper or hand speed; else why ``name`` looks like mm/s typed in a
    m/s field (``max_speed: 100`` meant 100 mm/s and was taken as 100 m/s)."""
    return _in_smaller_unit(name, value, limit, "m/s", "mm/s", "faster than any gripper closes or a hand pinches")


def plausible_speed(name: str, value: float, limit: float = MAX_PLAUSIBLE_SPEED) -> float:
    """``value`` if it is a plausible gripper or hand speed (:func:`too_fast`), else a ValueError with its message:
    for validators of speed fields."""
    return _refused(too_fast(name, value, limit), value)


def too_strong_for_a_hand(name: str, value: float, limit: float = MAX_PLAUSIBLE_HAND_FORCE) -> str | None:
    """None if ``|value|`` (N) is a force a haptic device may render on a person's hand; else why ``name`` looks like
    millinewtons typed in the newton field (``max_force: 8000`` meant 8000 mN)."""
    return _in_smaller_unit(name, value, limit, "N", "mN", "beyond what a haptic device renders on a hand",
                            "; the Omega.7's grip: 8 N")


def plausible_hand_force(name: str, value: float, limit: float = MAX_PLAUSIBLE_HAND_FORCE) -> float:
    """``value`` if it is a force a haptic device may render on a hand (:func:`too_strong_for_a_hand`), else a
    ValueError with its message: for validators of the limits of the force sent to a person's hand."""
    return _refused(too_strong_for_a_hand(name, value, limit), value)


#: no desktop haptic leader's handle moves farther than this (the Omega.7's workspace: 0.075 m in radius): a larger
#: workspace, position scale or travel in a metre field is millimetres typed there
MAX_PLAUSIBLE_WORKSPACE = 1.0       # m

#: the smaller unit a bare number in each SI unit is mistyped in
_SMALLER = {"m/s": "mm/s", "N": "mN", "N/s": "mN/s"}


def plausible_quantity(name: str, value: float, limit: float, unit: str, beyond: str, note: str = "") -> float:
    """``value`` if ``|value|`` (``unit``: m, m/s, N or N/s) is at most ``limit``, else a ValueError naming ``name``,
    saying it is ``beyond`` what is plausible (``note``: said with the limit) and how to write the smaller unit (mm,
    mm/s, mN; for mN/s, which no field parses, the bare number) meant: for a bound of a plugin's own that this module
    has no check for."""
    if unit == "m":
        return _refused(_metres_typed(name, value, limit, beyond, note), value)
    if unit not in _SMALLER:
        raise ValueError(f"plausible_quantity: unit {unit!r}: expected one of m, {', '.join(_SMALLER)}")
    return _refused(_in_smaller_unit(name, value, limit, unit, _SMALLER[unit], beyond, note), value)


def plausible_travel(name: str, value: float, limit: float = MAX_PLAUSIBLE_WORKSPACE) -> float:
    """``value`` if it is a plausible length in a haptic leader's workspace (m), else a ValueError: millimetres in
    the metre field."""
    return plausible_quantity(name, value, limit, "m", "beyond a haptic leader's workspace",
                              "; the Omega.7's: 0.075 m in radius")


def parse_quantity(text: Any, unit: str | None = None) -> float:
    """Parse ``text`` (a number or a string like ``"6mm"``) into a float in the SI unit ``unit``.

    Raises ValueError naming the text and the expected unit when the unit does not match.
    """
    if isinstance(text, bool):
        raise ValueError(f"expected a number{_in(unit)}, got {text!r}")
    if isinstance(text, (int, float)):
        try:
            value = float(text)
        except OverflowError:
            raise ValueError(f"{str(text)[:12]}... ({len(str(text))} digits) is too large for a number{_in(unit)}"
                             ) from None
        if not math.isfinite(value):
            raise ValueError(f"expected a finite number{_in(unit)}, got {text!r}")
        return value
    if not isinstance(text, str):
        raise ValueError(f"expected a number{_in(unit)}, got {text!r}")
    if "_" in text:   # float() reads '1_0' as 10; no unit has one either
        raise ValueError(f"expected a number{_in(unit)} such as {_example(unit)}, got {text!r} ({UNDERSCORE})")
    m = _QTY.match(text)
    if not m and _NON_FINITE.match(text):
        raise ValueError(f"expected a finite number{_in(unit)}, got {text!r}")
    if not m:
        raise ValueError(f"expected a number{_in(unit)} such as {_example(unit)}, got {text!r}")
    value = float(m.group(1))
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is too large for a number{_in(unit)}")
    sym = (m.group(2) or "").strip().replace(_GREEK_MU, _MICRO)
    if not sym:
        return value
    if unit is not None and unit not in _SI_UNITS:   # a plugin's own unit (N/m^3): nothing to convert it from
        raise ValueError(_not_convertible(sym, text, unit, m.group(1)))
    if sym not in _UNITS:
        raise ValueError(_unknown_unit(sym, text, unit))
    si, factor = _UNITS[sym]
    if unit is not None and si != unit:
        raise ValueError(f"{text!r} is in {si}, expected a quantity in {unit}")
    return value * factor


def _unknown_unit(sym: str, text: str, unit: str | None) -> str:
    """Why ``sym`` in ``text`` is refused: the units a quantity in ``unit`` may be written in (every unit when any
    goes), and the spelling meant when only the case is wrong. That is not guessed: 'mpa' may be milli- or
    megapascal."""
    fits = [s for s, (si, _) in _UNITS.items() if unit is None or si == unit]
    near = [s for s in fits if s.lower() == sym.lower()]
    msg = f"unknown unit {sym!r} in {text!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
    if unit is None:
        return f"{msg}; known: {', '.join(sorted(_UNITS))}"
    return f"{msg}; expected a quantity in {unit} ({', '.join(fits)})"


def _not_convertible(sym: str, text: str, unit: str, number: str) -> str:
    """Why ``text`` (``number`` with the unit ``sym``) is refused for a field whose declared ``unit`` is none that
    teletouch converts (a plugin may declare any unit): only a plain number, in that unit, is taken there."""
    return (f"{text!r} has a unit ({sym}), but the field's unit {unit} is not a unit teletouch converts (teletouch "
            f"converts {', '.join(_SI_UNITS)}): write a plain number, in {unit} (the field's own unit), e.g. {number}")


def _example(unit: str | None) -> str:
    return _EXAMPLES.get(unit, repr("1.5"))


def _in(unit: str | None) -> str:
    return f" in {unit}" if unit else ""


def quantity(unit: str, default: Any = ..., description: str = "", **kw: Any) -> Any:
    """A pydantic field for a float in SI ``unit`` that also accepts strings with units ("5mm").

    The unit is recorded in the JSON schema (``"unit": "m"``) so `teletouch plugins` and editors can show it.
    """
    extra = dict(kw.pop("json_schema_extra", {}) or {})
    extra["unit"] = unit
    return Field(default, description=description, json_schema_extra=extra, **kw)


def _validator(unit: str):
    def _v(value: Any) -> Any:
        if isinstance(value, (str, bool)):   # (pydantic would take a boolean, YAML's yes or on, as 1.0)
            return parse_quantity(value, unit)
        return value

    return BeforeValidator(_v)


# Annotated float types: a field typed ``Meters`` accepts 0.005, "5mm", "0.5 cm".
Meters = Annotated[float, _validator("m")]
Newtons = Annotated[float, _validator("N")]
Seconds = Annotated[float, _validator("s")]
Hertz = Annotated[float, _validator("Hz")]
Radians = Annotated[float, _validator("rad")]
NewtonsPerMeter = Annotated[float, _validator("N/m")]
NewtonSecondsPerMeter = Annotated[float, _validator("N*s/m")]
MetersPerSecond = Annotated[float, _validator("m/s")]
Kilograms = Annotated[float, _validator("kg")]
Pascals = Annotated[float, _validator("Pa")]
