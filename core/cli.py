"""The ``teletouch`` command line.

Core commands: plugins, validate, schema, run, devices. Plugins add their own (calibrate, estimate, experiment, ...)
through the ``teletouch_add_commands`` hook; a plugin whose hook raises (or takes a name already in use) has its
commands skipped with a warning, a command that sets no ``func`` is left out with a warning naming it, and every
other command still works.

Global option ``--block NAME[,NAME]`` (repeatable) blocks plugins, adding to the environment's ``TELETOUCH_BLOCK``.
Exit codes are those of :mod:`teletouch.runtime` (0 ok, 1 invalid input, 2 usage, 3 fault, 4 start-up failure, 130
interrupted by Ctrl-C), and 143 (128 + SIGTERM) for a run ended by SIGTERM, after the same safe stop as Ctrl-C;
`teletouch plugins` exits 1 when a plugin failed to load, a component name is refused for a conflict, a plugin's
commands were skipped or left out, or a blocked name matches nothing (a block itself changes no exit status, nor
does ``TELETOUCH_DISABLE_PLUGIN_AUTOLOAD``, which the listing mentions).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import numbers
import os
import shutil
import signal
import sys
import threading
from typing import Any, Iterator, Sequence

from . import __version__, runtime
from .errors import ComponentFault, GraphValidationError, TeletouchError, exception_line, traceback_text
from .registry import ENV_PLUGINS, Registry, default_registry
from .runtime import (
    EXIT_INTERRUPTED, EXIT_INVALID, EXIT_OK, EXIT_STARTUP, EXIT_USAGE, Runtime, _say_held, run_stopping,
)

EXIT_TERMINATED = 128 + signal.SIGTERM   # 143: the shell's code for a process ended by SIGTERM (130 is Ctrl-C)


class Terminated(KeyboardInterrupt):
    """SIGTERM during a command: raised where Ctrl-C raises KeyboardInterrupt, so the runtime makes the same safe stop
    (and names the signal, ``signum``, in its result); the command then exits :data:`EXIT_TERMINATED` instead of
    130."""

    signum = signal.SIGTERM


def _add_graph_args(p: argparse.ArgumentParser) -> None:
    from .graph import set_argument

    p.add_argument("graph", help="graph file (YAML)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="NODE.FIELD=VALUE", type=set_argument,
                   help="override a parameter, the plugin or the rate of a node (repeatable)")
    p.add_argument("--clock", choices=("sim", "wall"), default=None, help="override the graph's clock")


def _seconds(text: str) -> float:
    """argparse type of ``--duration``: a positive, finite time ('10', '10s', '500ms')."""
    from .units import parse_quantity

    try:
        value = parse_quantity(text, "s")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive time in s, got {text!r}")
    return value


def _positive_seconds(text: str) -> float:
    """argparse type of ``--progress-interval``: a positive, finite time ('0.5', '500ms'), as ``--duration``."""
    from .units import parse_quantity

    try:
        value = parse_quantity(text, "s")   # a plain number is seconds; an underscore is refused as a typo
    except ValueError as exc:
        if text.strip().lower().lstrip("+-") in ("inf", "infinity", "nan"):
            raise argparse.ArgumentTypeError(f"must be a positive, finite number of seconds, got {text!r}") from None
        raise argparse.ArgumentTypeError(str(exc)) from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive, finite number of seconds, got {text!r}")
    return value


def cmd_plugins(args: argparse.Namespace) -> int:
    reg = default_registry()
    rows = reg.describe()
    problems = reg.problems() + list(getattr(args, "command_errors", []))
    status = EXIT_INVALID if problems else EXIT_OK
    off = reg.autoload_off_why()
    # autoload off is a choice (not a problem, exit status unchanged); said, so an empty list is not read as none
    note = f"installed plugins are not loaded ({off}); only the modules named in {ENV_PLUGINS} are listed"
    names = list(getattr(args, "names", None) or [])
    if names:
        keys = ("name", "plugin", "distribution")
        bare = {p.name for p in reg.plugins.values()}   # (also a plugin with commands only: listed below)
        unknown = [n for n in names if n not in bare and not any(r.get(k) == n for r in rows for k in keys)]
        if unknown:
            from .graph import _suggest

            known = {str(r.get(k)) for r in rows for k in keys if r.get(k)} | bare
            for n in unknown:
                print(f"teletouch: no component, plugin or distribution named {n!r}{_suggest(n, known)}"
                      + (f" ({note})" if off else "; `teletouch plugins` lists them all"), file=sys.stderr)
            failed = [f"plugin '{p.name}' ({p.origin}): {p.error}" for p in reg.errors()]
            if failed:   # the one that provides it may be among them (the doc's `teletouch plugins NAME` said nothing)
                print(f"teletouch: {len(failed)} plugin(s) failed to load, which may provide it:", file=sys.stderr)
                for line in failed:
                    print(f"  {line}", file=sys.stderr)
            return EXIT_INVALID
        # a component's own name first: "position-force" is that component, not its plugin's three
        rows = [r for r in rows if r.get("name") in names
                or any(r.get(k) == n for n in names if not any(q.get("name") == n for q in rows) for k in keys[1:])]
    if args.json:
        print(json.dumps(rows, indent=2, default=str))
        if off:   # stdout stays JSON
            print(f"teletouch: {note}", file=sys.stderr)
        _say_problems(problems, status)
        return status
    for r in rows:
        if r.get("blocked"):
            by = ", ".join(_block_text(b) for b in r.get("blocked_by") or []) or "?"
            print(f"{r['name']}  [BLOCKED by {by}]  {r['distribution']} {r['version']}".rstrip())
            print("    not loaded (not even imported): its components are not listed\n")
            continue
        if r.get("error"):
            if r["name"] in reg.conflicts:   # the message names every origin
                print(f"{r['name']}  [REFUSED: provided by more than one plugin]\n    error: {r['error']}\n")
            else:
                print(f"{r['name']}  [FAILED TO LOAD]  {r['distribution']} {r['version']}\n    error: {r['error']}\n")
            continue
        print(f"{r['name']}  ({r['kind']})  {r['distribution']} {r['version']}  (plugin {r['plugin']})")
        if r.get("description"):
            print(f"    {r['description']}")
        for p in r["ports"]:
            shape = "scalar" if not p["shape"] else "x".join("*" if d is None else str(d) for d in p["shape"])
            arrow = "<-" if p["direction"] == "in" else "->"
            opt = "" if p.get("required", True) else " (optional)"
            print(f"    {arrow} {p['name']:<16} {p['dtype']}[{shape}] {p['unit'] or '1'}{opt}")
        for prm in r["params"]:
            unit = f" {prm['unit']}" if prm.get("unit") else ""
            print(f"    .  {prm['name']:<16} = {prm['default']!r}{unit}   {prm.get('description', '')}")
        print()
    others = [f"{p.name} ({p.origin}: {', '.join(h.removeprefix('teletouch_') for h in p.hooks) or 'nothing'})"
              for p in reg.plugins.values() if not (p.components or p.error or p.blocked) and (
                  not names or p.name in names)]
    if others:
        print("plugins without components: " + ", ".join(others))
    if off:
        print(note)
    _say_problems(problems, status)
    return status


def _say_problems(problems: list[str], status: int) -> None:
    """The plugin problems behind a nonzero exit status, each on its own line (on stderr): a filtered list, the JSON
    rows and a command a plugin could not add do not show them all (it said "`teletouch plugins` lists them")."""
    if problems:
        print(f"teletouch: {len(problems)} plugin problem(s), exit status {status}:", file=sys.stderr)
        for line in problems:
            print(f"  {line}", file=sys.stderr)


def _block_text(origin: dict[str, str]) -> str:
    """One block as the user set it: ``--block NAME`` or ``TELETOUCH_BLOCK=NAME``."""
    setting, name = origin.get("setting", "?"), origin.get("name", "?")
    return f"{setting} {name}" if setting.startswith("--") else f"{setting}={name}"


#: a graph on the simulated clock without a duration (it would never end)
SIM_NEEDS_DURATION = "the simulated clock needs a duration: add 'duration:' to the graph or pass --duration S"


def cmd_validate(args: argparse.Namespace) -> int:
    from .graph import load_graph

    spec = load_graph(args.graph, sets=args.sets, clock=args.clock)
    _print_warnings(spec)
    rates = ", ".join(f"{n.id}@{n.rate:g}Hz" for n in spec.order())
    count = len(spec.warnings)
    if spec.clock == "sim" and spec.duration is None:   # valid, but `teletouch run` refuses it without --duration
        print(f"{args.graph}: warning: the graph has no duration, which `teletouch run` needs on the simulated clock: "
              f"add 'duration:' to the graph or pass --duration S to run", file=sys.stderr)
        count += 1
    note = f"; {count} warning{'s' if count > 1 else ''}" if count else ""
    nodes = len(spec.nodes)
    print(f"{args.graph}: OK ({nodes} node{'s' if nodes != 1 else ''}: {rates}; clock {spec.clock}{note})")
    return EXIT_OK


def _print_warnings(spec: Any) -> None:
    """The graph's warnings (``GraphSpec.warnings``: it is valid and runs, but may not do what was meant), on stderr."""
    for line in spec.warnings:
        print(f"teletouch: warning: {line}", file=sys.stderr)


def cmd_schema(args: argparse.Namespace) -> int:
    from .graph import dump_schema

    text = dump_schema()
    if args.output:
        with open(args.output, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")
        print(f"wrote {args.output}", file=sys.stderr)
    else:
        print(text)
    return EXIT_OK


class _Progress:
    """The live view on stderr: graph time and overruns, then one row per node (achieved rate and its ``status()``
    numbers, as many as fit). On a terminal the block is redrawn in place (ANSI: cursor up, clear line), each row cut
    to the terminal's width, so every node stays in view on an 80-column terminal (one long line lost the controller
    and the leader there); elsewhere (a log file, a pipe) one plain line per update."""

    MAX_STATUS = 6   # status() numbers shown per node

    def __init__(self, stream: Any = None):
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.drawn = 0   # rows of the block on screen (terminal)

    def rows(self, rt: Runtime, t: float) -> list[str]:
        overruns = sum(n.overruns for n in rt.nodes)
        width = max((len(n.id) for n in rt.nodes), default=4)
        rows = [f"t={t:8.2f} s  overruns {overruns}"]
        for n in rt.nodes:
            rate = n.achieved_rate()
            rate_text = "-" if rate is None else f"{rate:.1f}"
            rows.append(f"  {n.id:<{width}} {rate_text:>7} Hz  {self._status_text(n.comp)}".rstrip())
        return rows

    def _status_text(self, comp: Any) -> str:
        """The first ``status()`` numbers as ``key=value``, a number under a unit suffix in a person's unit
        (:func:`_status_item`); nothing when status() raises, is not a mapping or holds a value that cannot be
        printed (a plugin's bug there must not stop the run: the live view raising does)."""
        try:
            items = list(comp.status().items())[:self.MAX_STATUS]
            return " ".join(_status_item(k, v) for k, v in items)
        except Exception:
            return ""

    def _width(self) -> int:
        try:
            return os.get_terminal_size(self.stream.fileno()).columns
        except (AttributeError, OSError, ValueError):
            return shutil.get_terminal_size().columns

    def __call__(self, rt: Runtime, t: float) -> None:
        rows = self.rows(rt, t)
        if self.tty:
            width = max(self._width() - 1, 20)
            up = f"\x1b[{self.drawn}F" if self.drawn else ""   # to the first row of the block drawn last time
            self.stream.write(up + "".join(f"\x1b[2K{_fit(r, width)}\n" for r in rows))
            self.drawn = len(rows)
        else:
            self.stream.write(rows[0] + " | " + " | ".join(r.strip() for r in rows[1:]) + "\n")
        self.stream.flush()

    def done(self) -> None:
        self.drawn = 0   # the block stays on screen above what follows


def _fit(row: str, width: int) -> str:
    """``row`` cut to ``width`` columns between two items, never inside one: a number cut short reads as another
    number (``feedback=1`` of ``feedback=1.18N``)."""
    if len(row) <= width:
        return row
    cut = row.rfind(" ", 0, width + 1)
    return row[:cut].rstrip() if cut > 0 else row[:width]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _fixed(v: float, decimals: int) -> str:
    """``v`` with ``decimals`` decimals, but as 4 significant digits from 1e6 up: a plugin's absurd value (a 1e300 N
    force passed on from ROS 2) would otherwise print as 300 digits."""
    return f"{v:.{decimals}f}" if abs(v) < 1e6 else f"{v:.4g}"


def _time_text(v: float) -> str:
    return f"{v * 1e3:.1f}ms" if abs(v) < 1.0 else f"{_fixed(v, 2)}s"


#: the unit suffixes of status() keys (docs/writing-a-plugin.md), longest first, and how the live view shows a value
#: (SI) under each for a person: lengths in mm, energies in mJ, times below 1 s in ms
STATUS_UNITS: tuple[tuple[str, Any], ...] = (
    ("_n_s_per_m", lambda v: f"{_fixed(v, 2)}N*s/m"),
    ("_n_per_m", lambda v: f"{_fixed(v, 0)}N/m"),
    ("_m_per_s", lambda v: f"{v:.4g}m/s"),
    ("_m2", lambda v: f"{_fixed(v * 1e6, 2)}mm^2"),
    ("_hz", lambda v: f"{_fixed(v, 1)}Hz"),
    ("_rad", lambda v: f"{_fixed(v, 3)}rad"),
    ("_m", lambda v: f"{_fixed(v * 1e3, 2)}mm"),
    ("_n", lambda v: f"{_fixed(v, 2)}N"),
    ("_j", lambda v: f"{_fixed(v * 1e3, 3)}mJ"),
    ("_s", _time_text),
)


def _status_item(key: Any, value: Any) -> str:
    """One status() item for the live view: a finite number under a key with a unit suffix (STATUS_UNITS) without
    the suffix, in a person's unit (``opening_m=0.0123`` -> ``opening=12.30mm``); anything else as ``key=value``."""
    name = str(key)
    number = isinstance(value, numbers.Real) and not isinstance(value, bool)
    for suffix, show in STATUS_UNITS:
        if name.endswith(suffix) and len(name) > len(suffix):
            if number and math.isfinite(value):
                return f"{name[:-len(suffix)]}={show(float(value))}"
            return f"{name[:-len(suffix)]}={_fmt(value)}"
    return f"{name}={_fmt(value)}"


def cmd_run(args: argparse.Namespace) -> int:
    from .graph import load_graph

    if args.record_images is not None and not args.record:   # (it was ignored without a word)
        print("teletouch: error: --record-images: only with --record FILE.mcap (it sets how that recording stores "
              "images)", file=sys.stderr)
        return EXIT_USAGE
    spec = load_graph(args.graph, sets=args.sets, clock=args.clock, duration=args.duration)
    _print_warnings(spec)
    if spec.clock == "sim" and spec.duration is None:
        print(f"{args.graph}: {SIM_NEEDS_DURATION}", file=sys.stderr)
        return EXIT_INVALID
    tracebacks = _tracebacks_wanted(args)
    try:
        rt = Runtime(spec)
    except ComponentFault as exc:   # a plugin's constructor (the runtime names the node): nothing is live yet
        if tracebacks:
            print(f"teletouch: traceback:\n{traceback_text(exc).rstrip()}", file=sys.stderr)
        print(f"teletouch: startup-failed: {exc}", file=sys.stderr)
        return EXIT_STARTUP
    except TeletouchError:
        raise
    except Exception as exc:
        if tracebacks:
            print(f"teletouch: traceback:\n{traceback_text(exc).rstrip()}", file=sys.stderr)
        print(f"teletouch: startup-failed: a component could not be created: {exception_line(exc)}", file=sys.stderr)
        return EXIT_STARTUP
    recorder = None
    if getattr(args, "record", None):
        from .recording import Recorder

        recorder = Recorder(args.record, spec, image_format=args.record_images or "png")
        recorder.graph_now = rt.now   # graph time 0's Unix time from the clock, not from a step's end
        rt.add_tap(recorder.tap)
    progress = None if args.quiet else _Progress()
    record_error = None
    # a signal after the first is held until the recording is closed too; the exit code is that of the signal the
    # run stopped for (RunResult.signal: also one the runtime held in its safe shutdown of a run that was ending)
    with _interrupts():
        try:
            result = rt.run(spec.duration, progress=progress, progress_interval=args.progress_interval)
        finally:
            if progress is not None:
                progress.done()
            if recorder is not None:
                try:
                    recorder.close()
                except TeletouchError as exc:  # the recording failed (disk full): the run's own result still counts
                    record_error = exc
                    print(f"teletouch: error: {exc}", file=sys.stderr)
    code = result.exit_code
    # the signal the run stopped for (not one a plugin swallowed before it), where not a fault that had stopped it
    if result.signal == signal.SIGTERM and result.exit_code == EXIT_INTERRUPTED:
        code = EXIT_TERMINATED
    if record_error is not None and code == EXIT_OK:   # the run was ok, its recording was not
        code = EXIT_INVALID
    if not args.quiet:   # without the summary's first line: how the run ended, said once, last (below)
        print(result.summary(header=False), file=sys.stderr)
        for line in _results_lines(result):
            print(line, file=sys.stderr)
    if tracebacks:   # the faults' own, in full, above the last line
        for fault in result.faults:
            if fault.traceback:
                print(f"teletouch: traceback of {fault.line()}\n{fault.traceback.rstrip()}", file=sys.stderr)
    if args.json:   # exit_code: what the shell sees
        # strict JSON: a plugin's NaN (in its status or results) becomes null
        print(json.dumps(_json_safe(dict(result.as_dict(), exit_code=code,
                                         recording_error=None if record_error is None else str(record_error))),
                         default=str, allow_nan=False))
    print(f"teletouch: {result.ending}", file=sys.stderr)   # (said once)
    return code


#: set (to anything but "" or "0"): `teletouch run` prints the full traceback of each fault an exception made, as
#: --traceback does
ENV_TRACEBACK = "TELETOUCH_TRACEBACK"


def _tracebacks_wanted(args: argparse.Namespace) -> bool:
    """Whether `teletouch run` prints the faults' tracebacks: --traceback, or TELETOUCH_TRACEBACK set."""
    return bool(getattr(args, "traceback", False)) or os.environ.get(ENV_TRACEBACK, "") not in ("", "0")


def _results_lines(result: Any) -> list[str]:
    """What the run achieved (Component.results), one row per node that said something, in a person's units as the
    live view shows status() (``peak_force=1.20N contact_time=4.93s``); nothing where no node did."""
    rows = [f"  {n.id:<16}" + " ".join(_status_item(k, v) for k, v in n.results.items())
            for n in result.nodes if n.results]
    return ["results:", *rows] if rows else []


def _json_safe(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, inf: not JSON) turned into None, in nested dicts/lists/tuples."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _device_rows(reg: Registry) -> list[dict[str, Any]]:
    """Every plugin's discovery rows, each as strict JSON can carry it (a plugin's NaN becomes null; a value JSON
    cannot encode becomes its text); a row that still cannot be encoded becomes an error row of its kind."""
    rows = []
    for row in reg.discover_devices():
        safe = _json_safe(row)
        try:
            json.dumps(safe, allow_nan=False, default=str)
        except (TypeError, ValueError) as exc:   # e.g. a NaN inside an object that default=str does not reach
            safe = {"kind": str(row.get("kind", "?")), "id": str(row.get("id", "")), "path": str(row.get("path", "")),
                    "error": f"this row cannot be shown as JSON: {exc}"}
        rows.append(safe)
    return rows


def _device_sources(reg: Registry) -> list[str]:
    """The plugins whose ``teletouch_discover_devices`` was asked, in the order they are asked."""
    return [impl.plugin_name for impl in reg.pm.hook.teletouch_discover_devices.get_hookimpls()]


def _param_text(params: Any) -> str:
    """A row's ``params`` as they go into a graph node: ``serial=D20001 device=spacemouse``."""
    if isinstance(params, dict):
        return " ".join(f"{k}={v}" for k, v in params.items())
    return str(params)


def _indented(label: str, text: str) -> str:
    """``label: text`` on a line indented under its row; the text's own line breaks keep the indentation."""
    return "    " + f"{label}: {text}".replace("\n", "\n    ")


def cmd_devices(args: argparse.Namespace) -> int:
    reg = default_registry()
    found = _device_rows(reg)
    if args.json:
        print(json.dumps(found, indent=2, default=str, allow_nan=False))
        return EXIT_OK
    for d in found:
        kind, ident, path = (str(d.get(k) or "") for k in ("kind", "id", "path"))
        if d.get("error"):
            print(f"{kind or '?':<12} {'(source not read)':<20} {path}".rstrip())
            print(_indented("error", str(d["error"])))
            continue
        details = dict(d.get("details") or {})
        problem = details.pop("problem", None)
        plugin = details.pop("plugin", None)
        params = details.pop("params", None)
        use = f"plugin: {plugin}" if plugin else ""
        if params:
            use += (" " if use else "") + _param_text(params)
        det = "  ".join(f"{k}={_fmt(v) if v is not None else '?'}" for k, v in details.items())
        print(f"{kind or '?':<12} {ident:<20} {path:<20} {det}".rstrip())
        if use:
            print(_indented("use", use))
        if problem:
            print(_indented("problem", str(problem)))
    if not any(not d.get("error") for d in found):
        failed = sorted({str(d.get("kind") or "?") for d in found if d.get("error")})
        note = f"; not read: {', '.join(failed)} (see the errors above)" if failed else ""
        sources = ", ".join(_device_sources(reg)) or "none: no plugin discovers devices"
        print(f"no supported hardware found (sources checked: {sources}{note})")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="teletouch", description="Tactile force estimation and position-force "
                                     "teleoperation. See `teletouch COMMAND -h`.")
    parser.add_argument("--version", action="version", version=f"teletouch {__version__}")
    parser.add_argument("--block", action="append", default=[], metavar="NAME[,NAME]",
                        help="do not load these plugins (plugin or distribution names; repeatable); adds to the "
                             f"environment's TELETOUCH_BLOCK (names separated by ',' or '{os.pathsep}')")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("plugins", help="list installed components, plugins that failed to load and blocked ones",
                       description="List every installed component (kind, distribution, version, plugin, ports, "
                                   "parameters), every plugin that failed to load or whose component name is refused "
                                   "(provided twice), and every blocked plugin with where the block came from "
                                   "(--block or TELETOUCH_BLOCK). Exit status 1 when a plugin failed, a name is "
                                   "refused or a blocked name matches nothing; a block itself is not a problem.")
    p.add_argument("names", nargs="*", metavar="NAME",
                   help="list only these components (or every component of these plugins or distributions)")
    p.add_argument("--json", action="store_true", help="machine-readable list")
    p.set_defaults(func=cmd_plugins)

    p = sub.add_parser("validate", help="check a graph file without running it")
    _add_graph_args(p)
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("schema", help="print the JSON Schema of the graph format (for editors)")
    p.add_argument("-o", "--output", help="write to this file")
    p.set_defaults(func=cmd_schema)

    p = sub.add_parser("run", help="run a graph",
                       description="Run a graph with a live view on stderr and, at the end, a summary table (per "
                                   "node: rate, achieved rate, period jitter p99, steps, overruns, step times). Every "
                                   "stop drives the devices to their safe state. Exit status: 0 ok, 1 invalid graph "
                                   "(or a failed --record), 2 usage, 3 fault (or degraded), 4 start-up failure, 130 "
                                   "Ctrl-C, 143 SIGTERM.")
    _add_graph_args(p)
    p.add_argument("--duration", type=_seconds, default=None, metavar="S",
                   help="seconds (or '10s'); default: the graph's")
    p.add_argument("--quiet", action="store_true", help="no live view and no summary table")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON on stdout")
    p.add_argument("--progress-interval", type=_positive_seconds, default=0.5, metavar="S",
                   help="live view period: seconds (or '500ms'); default 0.5")
    p.add_argument("--record", metavar="FILE.mcap", default=None, help="record every port to an MCAP file")
    p.add_argument("--record-images", choices=("png", "jpeg"), default=None,
                   help="with --record: image compression in the recording: png (lossless, ~17 ms/frame; the "
                        "default) or jpeg (~1 ms/frame)")
    p.add_argument("--traceback", action="store_true",
                   help=f"print the full traceback of each fault an exception made (a plugin's step that raised), "
                        f"on stderr before the last line; or set {ENV_TRACEBACK}=1")
    p.set_defaults(func=cmd_run)

    calp = sub.add_parser("calibrate", help="calibrate a sensor model (see `teletouch calibrate -h`)")
    cal = calp.add_subparsers(dest="calibrate_command", metavar="WHAT")
    calp.set_defaults(func=lambda a: _what_missing(calp, cal), _calibrate=cal)

    p = sub.add_parser("devices", help="list connected supported hardware",
                       description="List the supported hardware connected to this machine, one row per device, "
                                   "with the plugin and params that select it in a graph and, for a device that "
                                   "cannot be used as it is, the problem and what to do. A source that cannot be "
                                   "read (a missing SDK or library, no USB or sysfs access) is an error row saying "
                                   "why. The exit status is 0 also then: the rows tell what was found and what was "
                                   "not looked at.")
    p.add_argument("--json", action="store_true", help="the rows as strict JSON (no NaN: a missing number is null)")
    p.set_defaults(func=cmd_devices)
    return parser


def _what_missing(parser: argparse.ArgumentParser, what: argparse._SubParsersAction) -> int:
    """`teletouch calibrate` without WHAT (or a plugin's group of commands without one of them): its help and, as
    the top level says of a missing COMMAND, what is missing (a usage error)."""
    parser.print_help(sys.stderr)
    choices = " or ".join(what.choices) or "none installed"
    print(f"\n{parser.prog}: error: {what.metavar or 'COMMAND'} is required ({choices})", file=sys.stderr)
    return EXIT_USAGE


def _blocked_from(argv: Sequence[str] | None) -> list[str]:
    """The ``--block`` names, read before the plugins load (their commands are part of the parser)."""
    pre = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    pre.add_argument("--block", action="append", default=[])
    try:
        known, _ = pre.parse_known_args(list(sys.argv[1:] if argv is None else argv))
    except argparse.ArgumentError:   # the full parser reports it, with the real usage line
        return []
    return [n.strip() for item in known.block for n in item.split(",") if n.strip()]


def add_plugin_commands(reg: Registry, sub: argparse._SubParsersAction, cal: argparse._SubParsersAction) -> list[str]:
    """Let each plugin add its commands. One whose hook raises (or reuses a taken name) is skipped, with what it had
    added removed; a command that sets no ``func`` is removed (see :func:`_drop_funcless`). Returns one line per
    skipped plugin and per removed command."""
    errors = []
    kwargs = {"subparsers": sub, "calibrate": cal}
    for impl in reversed(reg.pm.hook.teletouch_add_commands.get_hookimpls()):   # registration order
        before = [(a, dict(a._name_parser_map), list(a._choices_actions)) for a in (sub, cal)]
        rec = reg.plugins.get(impl.plugin_name)
        who = f"plugin '{impl.plugin_name}'" + (f" ({rec.origin})" if rec is not None else "")
        try:
            impl.function(*[kwargs[name] for name in impl.argnames])
        except (Exception, SystemExit) as exc:
            for action, names, choices in before:
                action._name_parser_map.clear()
                action._name_parser_map.update(names)
                action._choices_actions[:] = choices
            errors.append(f"{who}: its commands are skipped: teletouch_add_commands raised {exception_line(exc)}")
            continue
        for action, names, _ in before:
            prefix = "calibrate " if action is cal else ""
            errors += [f"{who}: {line}" for line in _drop_funcless(action, set(names), prefix)]
    return errors


def _drop_funcless(action: argparse._SubParsersAction, kept: set[str], prefix: str) -> list[str]:
    """Remove from ``action`` each sub-parser added since (not named in ``kept``) that sets no ``func`` default
    (the hook's contract): argparse would accept its command and then find nothing to run, and the user read "a
    COMMAND is required" after giving one. A group of sub-commands without a func keeps those of its commands that
    set one (checked the same way) and, given none of them, says which are missing. Returns one line per command
    removed; ``prefix`` is the words before the command's name (``calibrate ``)."""
    added: dict[int, tuple[str, argparse.ArgumentParser]] = {}
    for name, parser in action._name_parser_map.items():
        if name not in kept:
            added.setdefault(id(parser), (name, parser))   # its first name: the one its aliases follow
    lines = []
    for name, parser in added.values():
        if callable(parser.get_default("func")):
            continue
        group = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if group is not None:
            lines += _drop_funcless(group, set(), f"{prefix}{name} ")
            if group._name_parser_map:
                parser.set_defaults(func=lambda a, p=parser, g=group: _what_missing(p, g))
                continue
        for alias in [n for n, p in action._name_parser_map.items() if p is parser]:
            del action._name_parser_map[alias]
        action._choices_actions[:] = [c for c in action._choices_actions if c.dest != name]
        lines.append(f"command '{prefix}{name}' sets no func=callable(args) -> int; it is not added")
    return lines


@contextlib.contextmanager
def _interrupts(program: bool = False) -> Iterator[list[int]]:
    """Inside the block the first SIGINT or SIGTERM stops the command: it raises KeyboardInterrupt (SIGTERM:
    :class:`Terminated`, the same safe stop as Ctrl-C). Each one is recorded in the yielded list, first first; one after
    it (or after one the runtime held in its safe shutdown: it adds those to this list, ``runtime._stop_signals``) is
    said on stderr ("already stopping safely, please wait") and raises nothing: it must not cut the safe stop short (the
    samples file, the recording) nor change the exit code (it raised again, or ended the process). Inside a run that
    is not stopping yet it raises as the first does, and becomes the list's first: the ones before it stopped nothing
    (a plugin swallowed their KeyboardInterrupt, see :func:`_held_here`). A block inside another shares its list and
    handlers. SIGINT is taken over only from Python's own handler (a background job's
    ignored SIGINT stays ignored). The previous handlers are restored after; with ``program`` (the block is the
    process's life: it exits next) and a signal seen, :func:`_after_stop` handles them instead: the stop is done, so
    one ends the process at once with the command's exit code (no traceback, no -2 or -15), also where it hangs on its
    way out. Only the main thread may set handlers: elsewhere nothing is changed."""
    if runtime._stop_signals is not None:
        yield runtime._stop_signals
        return
    signals: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield signals
        return

    closing: list[int] = []   # set once the handlers are being restored; then the first signal if it came there

    def _handler(signum: int, frame: Any) -> None:
        first = not signals   # decided before the append: a second handler nested right after it is not the first
        signals.append(signum)
        if not first and _held_here(frame, _handler.__code__):
            _say_held(signum)
        elif closing:
            closing.append(signum)   # raised once the handlers are restored (below)
        else:
            if not first:   # those before it stopped nothing (swallowed): this one is the stop's first, its code
                del signals[:-1]
            raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt

    old: dict[int, Any] = {}
    try:
        runtime._stop_signals = signals
        for sig in (signal.SIGINT, signal.SIGTERM):
            prev = signal.getsignal(sig)
            if prev is None or (sig == signal.SIGINT and prev is not signal.default_int_handler):
                continue   # installed from outside Python, or SIGINT ignored or the caller's own: left alone
            old[sig] = prev
            signal.signal(sig, _handler)
        yield signals
    finally:
        try:
            closing.append(0)
        finally:   # (also when a first signal raised just before the line above)
            try:   # SIGINT last: its restored handler (Python's) raises, which must leave nothing unrestored
                for sig, prev in sorted(old.items(), key=lambda item: item[0] == signal.SIGINT):
                    signal.signal(sig, _after_stop if program and signals else prev)
                if program and signals:   # a first signal between two give-backs: both to _after_stop, none left
                    for sig in old:       # at its previous handler (SIGTERM's SIG_DFL: -15, not the exit code)
                        signal.signal(sig, _after_stop)
                    if old:
                        _after_stop_on_any_thread()
            finally:
                runtime._stop_signals = None
        if len(closing) > 1:   # the first signal came while the handlers were restored: it stops the command, as
            raise Terminated if closing[1] == signal.SIGTERM else KeyboardInterrupt   # it would have a moment before


def _held_here(frame: Any, handler: Any) -> bool:
    """Whether a signal after the command's first, landing in ``frame``, is held (said, raising nothing) because a stop
    is under way. Nested in the handler of an earlier one (``handler``: its code), always: that one stops the command.
    Inside a run (:func:`runtime.run_stopping`) only once that run is stopping, or while a KeyboardInterrupt is on its
    way out to it (an except or finally clause handles it: cutting that short gains nothing, the run stops for it):
    an earlier signal that a plugin swallowed (its configure(), or its close() at start-up, catching KeyboardInterrupt
    and carrying on) stopped nothing, so this one raises as a first does, as in a program of its own
    (``runtime._ctrl_c_until_stopping``). Outside a run always: the command's own code, where the earlier one may be
    its stop under way (a samples file, a recording)."""
    while frame is not None:
        if frame.f_code is handler:
            return True
        frame = frame.f_back
    stopping = run_stopping()
    if stopping is None or stopping:
        return True
    exc, seen = sys.exc_info()[1], 0
    while exc is not None and seen < 100:   # (the one handled, and those it was raised while handling)
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc, seen = exc.__context__, seen + 1
    return False


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; returns the exit status (argparse's usage errors, a malformed --set among them, exit 2
    themselves). A Ctrl-C anywhere, also while the plugins are imported, ends with "teletouch: interrupted (Ctrl-C)"
    and 130; SIGTERM, during any command, the same safe stop with "teletouch: interrupted (SIGTERM)" and 143. A second
    Ctrl-C or SIGTERM while the command stops is said and held; the exit status is the first's. ``argv`` None: main
    is the program (the console script, ``python -m teletouch``), which exits on its return: after a signal, a Ctrl-C
    or SIGTERM once the exit status is decided ends the process at once with it (see :func:`_after_stop`)."""
    # SIGTERM (a service manager, `kill`) stops every command as Ctrl-C does, so a calibration or an experiment
    # drives its devices to their safe state too (it ended the process at once: no safe stop, no samples file); a
    # second signal while the command stops is held (see _interrupts); `teletouch run` also notes them for its own run
    # (its summary's exit code)
    global _exit_code
    _exit_code = None
    signals: list[int] = []
    try:
        with _interrupts(program=argv is None) as signals:   # argv None: the console script, python -m teletouch
            code = _main(argv)
    except KeyboardInterrupt as exc:
        if (signals[0] if signals else getattr(exc, "signum", signal.SIGINT)) == signal.SIGTERM:
            print("teletouch: interrupted (SIGTERM)", file=sys.stderr)
            code = EXIT_TERMINATED
        else:
            print("teletouch: interrupted (Ctrl-C)", file=sys.stderr)
            code = EXIT_INTERRUPTED
    except BaseException as exc:   # a crash after the stop (a traceback follows) or a command's own sys.exit
        if argv is None:   # a signal from now on ends the process as that would (else: held for good, see below)
            _exit_code = _status_of_exit(exc)
        raise
    else:   # a command that handled the interrupt itself (its own message, exit 130) was ended by SIGTERM: 143
        code = EXIT_TERMINATED if signals and signals[0] == signal.SIGTERM and code == EXIT_INTERRUPTED else code
    if argv is None:
        _exit_code = code   # the safe stop is done and said: a signal from now on ends the process with it
    return code


#: the program's exit status once main() has decided it (see :func:`_after_stop`); None until then
_exit_code: int | None = None


def _status_of_exit(exc: BaseException) -> int:
    """The exit status Python gives a process that ``exc`` ends: SystemExit's code (None: 0; a message: 1; its low 8
    bits, as the system keeps them), else 1."""
    if isinstance(exc, SystemExit):
        return exc.code % 256 if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 1


def _after_stop(signum: int, frame: Any) -> None:
    """The program's SIGINT and SIGTERM handler once its command has stopped after a signal (see :func:`_interrupts`):
    one is said and held while main() says how the command ended; after that the process ends at once with main()'s
    exit status (stdout's buffer written first). Nothing is left to protect then: the devices are safe and the files
    written, and a process that hangs on its way out (an atexit hook, a plugin's non-daemon thread) must not need
    SIGKILL. The exit status stays the command's, as for any later signal (the first signal's 130 or 143)."""
    if _exit_code is None:
        _say_held(signum)
        return
    _flush_std_streams()
    os._exit(_exit_code)


def _after_stop_on_any_thread() -> None:
    """:func:`_after_stop` for a signal the kernel hands to another thread than the main one. CPython runs a handler
    in the main thread only, and at the program's end that one may wait, blocked, for a plugin's non-daemon thread
    that hangs: a Ctrl-C or SIGTERM that landed on that thread did nothing until it ended. The signal module's wakeup
    fd is written by whichever thread a signal lands on: a daemon thread reading it ends the process as
    :func:`_after_stop` does once the exit status is decided (before, the main thread's handler says the signal is
    held). Called from the main thread, once the program's handlers are :func:`_after_stop` (it replaces a wakeup fd
    set before: nothing but the process's end is waited for any more)."""
    r, w = os.pipe()
    os.set_blocking(w, False)
    try:
        signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    except (ValueError, OSError):   # not the main thread, after all
        os.close(r)
        os.close(w)
        return
    wanted = {int(signal.SIGINT), int(signal.SIGTERM)}

    def watch() -> None:
        while True:
            try:
                data = os.read(r, 64)
            except OSError:
                return
            if not data:
                return
            if wanted.intersection(data) and _exit_code is not None:
                # stdout's buffer written first, unless a write to it is stuck (a full pipe no one reads)
                flush = threading.Thread(target=_flush_std_streams, daemon=True)
                flush.start()
                flush.join(1.0)
                os._exit(_exit_code)

    threading.Thread(target=watch, name="teletouch-after-stop", daemon=True).start()


def _flush_std_streams() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):   # (a signal that cut into a write to it: the reentrant flush fails)
            stream.flush()


#: commands that end at once: not told that SIGINT is ignored (every other one, a plugin's too, may run for long)
QUICK_COMMANDS = ("plugins", "validate", "schema", "devices")


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    cal = sub.choices["calibrate"].get_default("_calibrate")
    try:
        reg = default_registry(blocked=_blocked_from(argv))
    except TeletouchError as exc:
        print(f"teletouch: error: {exc}", file=sys.stderr)
        return EXIT_INVALID
    command_errors = add_plugin_commands(reg, sub, cal)
    for line in command_errors + reg.unknown_blocked():
        print(f"teletouch: warning: {line}", file=sys.stderr)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        print("\nteletouch: error: a COMMAND is required", file=sys.stderr)
        return EXIT_USAGE
    args.command_errors = command_errors
    if argv is None and args.command not in QUICK_COMMANDS and signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        # kept ignored on purpose (see _interrupts), but `cmd & kill -INT $!` in a script then did nothing, silently
        print(f"teletouch: SIGINT is ignored (started in the background by a script): stop it with SIGTERM "
              f"(kill {os.getpid()})", file=sys.stderr)
    try:
        return int(args.func(args) or 0)
    except GraphValidationError as exc:
        print(f"teletouch: {exc}", file=sys.stderr)
        return EXIT_INVALID
    except TeletouchError as exc:
        print(f"teletouch: error: {exc}", file=sys.stderr)
        return EXIT_INVALID
    except BrokenPipeError:   # `teletouch schema | head`: the reader left; say nothing more, like git (141 = SIGPIPE)
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:   # a file that cannot be read or written: the user's path, not a bug
        names = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        print(f"teletouch: error: {exc.strerror or exc}{': ' + names if names else ''}", file=sys.stderr)
        return EXIT_INVALID
    except UnicodeDecodeError as exc:
        print(f"teletouch: error: a file is not UTF-8 text ({exc.reason} at byte {exc.start})", file=sys.stderr)
        return EXIT_INVALID


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
