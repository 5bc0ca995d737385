"""Exceptions raised by teletouch. Every user-facing error says where (file, line, field) and what was expected."""

from __future__ import annotations

import functools
import math
import os
import re
import sys
import sysconfig
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
    of the innermost frame of the code it came through that is not a library's (:func:`_library_root`: Python's
    standard library, or an installed distribution that provides no teletouch plugin), and where that is not the
    innermost frame, also the library's line that raised (``m_lib.py:11, raised in json/decoder.py:353``: a plugin's
    bad argument to ``json.loads`` is the plugin's line to fix, not the decoder's); an entry point whose module or
    attribute cannot be loaded (no frame of a plugin's own was reached) is named as the entry point, not by the
    importer's frozen frame. "" when it has neither (never raised)."""
    if getattr(exc, "where", None):
        return str(exc.where)
    try:
        return _place(exc)
    except Exception:   # (never on the fault path: the innermost frame, as a bare traceback would say)
        last = traceback.extract_tb(exc.__traceback__)[-1:]
        return f"{last[0].filename.rsplit('/', 1)[-1]}:{last[0].lineno}" if last else ""


#: the top-level packages of plugins registered by module (TELETOUCH_PLUGINS, ``Registry.register``): their code is
#: a plugin's own also where it lies in site-packages without a teletouch entry point
_REGISTERED_PACKAGES: set[str] = set()


def note_plugin_module(module: str) -> None:
    """Count ``module``'s top-level package as a plugin's own code in :func:`exception_place` (the registry calls it
    for each plugin it registers)."""
    top = str(module).split(".", 1)[0].strip()
    if top:
        _REGISTERED_PACKAGES.add(top)


def warm_places() -> None:
    """Read what :func:`exception_place` needs (the standard library's folders, the installed entry points) now,
    before a run, not on the first fault's path (a few ms of metadata reads)."""
    _stdlib_dirs()
    _plugin_packages(tuple(sys.path))


def _place(exc: BaseException) -> str:
    """:func:`exception_place` for an exception without its own ``where``."""
    frames = []
    tb = exc.__traceback__
    while tb is not None:
        frames.append((tb.tb_frame, tb.tb_lineno))
        tb = tb.tb_next
    if not frames:
        return ""
    roots = [_library_root(f.f_code.co_filename) for f, _ in frames]
    own = max((i for i, r in enumerate(roots) if r is None), default=None)
    entry = _entry_point_loading(frames)
    if entry is not None and (own is None or own < entry[0]):
        return entry[1]
    inner_frame, inner_line = frames[-1]
    inner = inner_frame.f_code.co_filename
    if own is None:
        return f"{inner.rsplit('/', 1)[-1]}:{inner_line}"
    frame, line = frames[own]
    place = f"{frame.f_code.co_filename.rsplit('/', 1)[-1]}:{line}"
    root = roots[-1]
    if own == len(frames) - 1 or not root:   # (the importer's frozen frames, root "", say nothing)
        return place
    return f"{place}, raised in {os.path.relpath(os.path.normpath(inner), root).replace(os.sep, '/')}:{inner_line}"


#: a folder of installed distributions, in a frame's file name
_SITE_DIR = re.compile(r"^(.*?[/\\](?:site|dist)-packages)(?=[/\\])")


@functools.lru_cache(maxsize=1)
def _stdlib_dirs() -> tuple[str, ...]:
    """Python's standard library folders (of this environment and of the Python it was made from)."""
    out = []
    for scheme_vars in ({}, {"base": sys.base_prefix, "platbase": sys.base_exec_prefix,
                             "installed_base": sys.base_prefix, "installed_platbase": sys.base_exec_prefix}):
        paths = sysconfig.get_paths(vars=scheme_vars)
        for key in ("stdlib", "platstdlib"):
            d = os.path.normpath(paths.get(key, "") or "")
            if d and d != "." and d not in out:
                out.append(d)
    return tuple(out)


def _library_root(filename: str) -> str | None:
    """The folder a library's file ``filename`` lies in (its path from there names it for a person:
    ``json/decoder.py``), or "" for the importer's frozen modules; None for a file that is no library's: a plugin's
    (installed with a teletouch entry point, or on Python's path), teletouch's own, a test's. A library is Python's
    standard library, or a package in a site-packages (dist-packages) folder that no teletouch entry point names."""
    if filename.startswith("<frozen "):
        return ""
    if filename.startswith("<"):
        return None
    site_dir = _SITE_DIR.match(filename)
    if site_dir:
        top = re.split(r"[/\\.]", filename[len(site_dir.group(1)):].lstrip("/\\"), maxsplit=1)[0]
        own = top in _REGISTERED_PACKAGES or top in _plugin_packages(tuple(sys.path))
        return None if own else os.path.normpath(site_dir.group(1))
    path = os.path.normpath(filename)
    return next((d for d in _stdlib_dirs() if path.startswith(d + os.sep)), None)


@functools.lru_cache(maxsize=4)
def _plugin_packages(path: tuple[str, ...]) -> frozenset[str]:
    """The top-level packages that the teletouch entry points installed on Python's ``path`` name (teletouch's own
    among them)."""
    from importlib import metadata

    try:
        eps = metadata.entry_points(group="teletouch")
        return frozenset(ep.value.split(":")[0].split(".")[0].strip() for ep in eps)
    except Exception:   # a broken distribution's metadata: no package counts as a plugin's
        return frozenset()


def _entry_point_loading(frames: list[tuple[Any, int]]) -> tuple[int, str] | None:
    """The innermost frame that loads an entry point (``importlib.metadata.EntryPoint.load``) among ``frames``, as
    its index and the entry point's place for a person; None where none does."""
    from importlib import metadata

    for i in range(len(frames) - 1, -1, -1):
        frame = frames[i][0]
        ep = frame.f_locals.get("self") if frame.f_code.co_name == "load" else None
        if isinstance(ep, metadata.EntryPoint):
            dist = getattr(ep, "dist", None)
            of = f" of {dist.name}" if dist is not None else ""
            return i, f"entry point '{ep.name} = {ep.value}' in [project.entry-points.{ep.group}]{of}"
    return None


def exception_line(exc: BaseException, more: str = "") -> str:
    """One line for a person: ``Type: message (place)`` (:func:`exception_place`); ``more`` is added to the message,
    before the place."""
    place = exception_place(exc)
    return f"{type(exc).__name__}: {exc}{more}" + (f" ({place})" if place else "")


def traceback_text(exc: BaseException) -> str:
    """The full traceback of ``exc`` as Python prints it (its causes and contexts included), for a person who needs
    more than :func:`exception_line`'s one place (``teletouch run --traceback``)."""
    try:
        return "".join(traceback.format_exception(exc))
    except Exception:   # (an exception whose str() raises)
        return f"{type(exc).__name__} (its traceback cannot be shown)\n"


def value_text(value: Any) -> str:
    """``repr(value)`` for a message, but an int too large for a float as its size: a float64 port takes any int,
    Python refuses to write one of more than 4300 digits as text (ValueError), and a 400-digit one says no more than
    its size."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 1024:
        return f"an integer of about {'-' if value < 0 else ''}1e{int(value.bit_length() * math.log10(2))}"
    return repr(value)
