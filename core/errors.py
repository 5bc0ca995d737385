"""Exceptions raised by teletouch. Every user-facing error says where (file, line, field) and what was expected."""

from __future__ import annotations

import math
import traceback
from typing import Any


class TeletouchError(Exception):
    """Base class for all teletouch errors."""


class PluginError(TeletouchError):
    """A plugin could not be loaded or registered."""


class DuplicateComponentError(PluginError):
    """Two distributions provide a component with the same name."""


class UnknownComponentError(PluginError):
    """No component with the requested name is registered."""


class Location:
    """A place in a text file (1-based line), used to point users at their mistake."""

    __slots__ = ("file", "line")

    def __init__(self, file: str | None, line: int | None):
        self.file = file
        self.line = line

    def __str__(self) -> str:
        if self.file and self.line:
            return f"{self.file}:{self.line}"
        return self.file or "<graph>"

    def __repr__(self) -> str:
        return f"Location({self.file!r}, {self.line!r})"


class GraphError(TeletouchError):
    """One problem in a graph file, with its location."""

    def __init__(self, message: str, where: Location | None = None):
        self.message = message
        self.where = where or Location(None, None)
        super().__init__(f"{self.where}: {message}")


class GraphValidationError(TeletouchError):
    """All the problems found while validating a graph (validation never stops at the first)."""

    def __init__(self, errors: list[GraphError]):
        self.errors = list(errors)
        lines = [str(e) for e in self.errors]
        super().__init__(f"{len(lines)} error(s) in graph:\n  " + "\n  ".join(lines))


class ComponentFault(TeletouchError):
    """Raised by a component (or the runtime on its behalf) when it cannot go on safely."""

    #: where a person should look, when that is not where it was raised (an output that does not fit its port is
    #: found by the runtime, but made by the plugin's step): ``exception_line`` gives it instead of the frame
    where: str | None = None
    #: the input port the fault is about (an input lost for too long), or None: the runtime, which knows the wires,
    #: adds to the fault the node and port that feed it (a component cannot know its graph)
    input_port: str | None = None

    def __init__(self, message: str, node: str | None = None, *, input_port: str | None = None):
        self.node = node
        self.input_port = input_port
        super().__init__(f"node '{node}': {message}" if node else message)


class HardwareError(ComponentFault):
    """The hardware cannot be reached or answered wrongly. The message says what to check."""


class ModelFileError(TeletouchError):
    """A model or calibration file is missing, corrupt or of the wrong version."""


def exception_place(exc: BaseException) -> str:
    """Where a person should look for ``exc``: its own ``where`` (see :class:`ComponentFault`), else ``file.py:line``
    of the innermost frame that raised; "" when it has neither (never raised)."""
    if getattr(exc, "where", None):
        return str(exc.where)
    tb = traceback.extract_tb(exc.__traceback__)
    return f"{tb[-1].filename.rsplit('/', 1)[-1]}:{tb[-1].lineno}" if tb else ""


def exception_line(exc: BaseException, more: str = "") -> str:
    """One line for a person: ``Type: message (place)`` (:func:`exception_place`); ``more`` is added to the message,
    before the place."""
    place = exception_place(exc)
    return f"{type(exc).__name__}: {exc}{more}" + (f" ({place})" if place else "")


def value_text(value: Any) -> str:
    """``repr(value)`` for a message, but an int too large for a float as its size: a float64 port takes any int,
    Python refuses to write one of more than 4300 digits as text (ValueError), and a 400-digit one says no more than
    its size."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 1024:
        return f"an integer of about {'-' if value < 0 else ''}1e{int(value.bit_length() * math.log10(2))}"
    return repr(value)
