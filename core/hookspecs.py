"""The one hookspec module of teletouch.

A plugin is a module (or any object) with functions decorated by ``teletouch.hookimpl``, registered through the
``teletouch`` entry-point group. Built-in plugins register exactly like third-party ones::

    [project.entry-points.teletouch]
    my-gripper = "my_package.gripper"
"""

from __future__ import annotations

import argparse
from typing import Any

import pluggy

hookspec = pluggy.HookspecMarker("teletouch")
hookimpl = pluggy.HookimplMarker("teletouch")


@hookspec
def teletouch_components() -> list[type]:
    """Return the component classes (subclasses of ``teletouch.Component``) this plugin provides."""


@hookspec
def teletouch_add_commands(subparsers: argparse._SubParsersAction, calibrate: argparse._SubParsersAction) -> None:
    """Add sub-commands to the ``teletouch`` command line. Each sub-parser sets ``func=callable(args) -> int``.

    ``subparsers`` is the top level (``teletouch NAME``); ``calibrate`` is the group ``teletouch calibrate NAME``.
    An implementation may take only the arguments it needs.
    """


@hookspec
def teletouch_discover_devices() -> list[dict[str, Any]]:
    """Return the supported hardware this plugin can see right now, for ``teletouch devices``.

    Each entry is a dict with at least ``kind`` (e.g. "digit"), ``id`` (serial or port) and ``path``; it may add
    ``details``, where these keys are shown specially: ``plugin`` and ``params`` (what selects this device in a
    graph, e.g. ``{"serial": "D20001"}``), ``readable`` (whether this user may open it) and ``problem`` (why it cannot
    be used as it is, and what to do). A source that could not be read (a missing SDK or library, an unreadable
    folder) is an entry with ``kind``, empty ``id`` and ``path``, and ``error`` saying why: not an empty list, so the
    user learns why nothing shows. Must be fast and must not raise.
    """
