"""Shared by the benchmarks: the one strict-JSON last line, argument types that refuse bad values, the shared data.

The benchmarks run as ``python benchmarks/NAME.py``, so this folder is on sys.path and they import this module by
its bare name (as they import ``machine``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

from teletouch.argtypes import int_at_least, number

REPO = Path(__file__).resolve().parents[1]
#: the real DIGIT images (../shared/data next to the checkout; TELETOUCH_SHARED_DATA moves it)
DATA = Path(os.environ.get("TELETOUCH_SHARED_DATA", REPO.parent / "shared" / "data"))


def strict(obj: Any, path: str = "", bad: list[str] | None = None) -> Any:
    """``obj`` made fit for strict JSON: NaN and +-Infinity become null (their paths appended to ``bad``), numpy
    scalars and arrays become Python numbers and lists, tuples lists, paths strings, keys strings."""
    if isinstance(obj, dict):
        return {str(k): strict(v, f"{path}.{k}" if path else str(k), bad) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v, f"{path}[{i}]", bad) for i, v in enumerate(obj)]
    if isinstance(obj, (bool, str, int)) or obj is None:
        return obj
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        if bad is not None:
            bad.append(path or "<top>")
        return None
    if isinstance(obj, Path):
        return str(obj)
    tolist = getattr(obj, "tolist", None)      # numpy scalars (np.float64, np.int64, np.bool_) and arrays
    if callable(tolist):
        return strict(tolist(), path, bad)
    raise TypeError(f"benchmark result {path or '<top>'}: {type(obj).__name__} is not JSON ({obj!r:.80})")


def dumps(obj: Any, bad: list[str] | None = None) -> str:
    """One line of strict JSON (no NaN, no Infinity: those are null, and their fields listed under
    ``non_finite_fields`` of a top-level object, so no measurement goes missing unnoticed; also appended to
    ``bad``)."""
    bad = [] if bad is None else bad
    clean = strict(obj, "", bad)
    if bad and isinstance(clean, dict):
        clean["non_finite_fields"] = list(bad)
    return json.dumps(clean, allow_nan=False)


def emit(obj: Any) -> None:
    """Print the benchmark's result as its last line of stdout (strict JSON, see :func:`dumps`); fields that were
    NaN or infinite are named on stderr."""
    bad: list[str] = []
    line = dumps(obj, bad)
    if bad:
        print(f"note: no finite value for {', '.join(bad)} (null in the JSON)", file=sys.stderr)
    print(line, flush=True)


def min_samples(q: float) -> int:
    """The fewest samples over which the ``q``-th percentile (0 < q < 100) is more than the maximum or the minimum:
    100 / (100 - q), at least 2 (a p99 needs 100, a p90 10, a median 2)."""
    return max(2, math.ceil(100.0 / (100.0 - q) - 1e-9))


def percentile_ms(xs: Any, q: float) -> float:
    """The ``q``-th percentile of the times ``xs`` (s) in ms; NaN (null in the JSON) over fewer than
    :func:`min_samples` of them, where it would only be the largest."""
    xs = [float(x) for x in xs]
    if len(xs) < min_samples(q):
        return float("nan")
    import numpy as np

    return float(np.percentile(xs, q)) * 1e3


positive_int = int_at_least(1)
nonnegative_int = int_at_least(0)
positive_float = number(float, "a finite number > 0", lo=0.0, lo_open=True)
nonnegative_float = number(float, "a finite number >= 0", lo=0.0)


def quantity(unit: str, lo: float, hi: float, what: str) -> Callable[[str], float]:
    """An argument in ``unit`` (SI; "3mm" or a bare SI number), refused outside (lo, hi] with a hint at the unit."""
    from teletouch.units import parse_quantity

    def parse(text: str) -> float:
        try:
            v = parse_quantity(text, unit)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
        if not lo < v <= hi:
            bare = _is_number(text)
            raise argparse.ArgumentTypeError(f"{what} must be above {lo:g} and at most {hi:g} {unit}, got {text!r}"
                                             + (f" (millimetres? write {text}mm)" if unit == "m" and v > hi and bare
                                                else ""))
        return v
    parse.__name__ = what
    return parse


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def rate_list(text: str) -> list[float]:
    """Comma-separated loop rates in Hz (``1000,4000`` or ``1kHz,4kHz``), each > 0."""
    from teletouch.units import parse_quantity

    out = []
    for part in text.split(","):
        try:
            v = parse_quantity(part.strip(), "Hz")
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"rate {part.strip()!r}: {e}") from None
        if v <= 0:
            raise argparse.ArgumentTypeError(f"rate {part.strip()!r}: must be above 0 Hz")
        out.append(v)
    return out


def data_folder(name: str, base: Path | None = None) -> Path:
    """``base``/``name`` (default base: :data:`DATA`), or exit with a message saying where the data were looked for."""
    folder = (DATA if base is None else Path(base)) / name
    if not folder.is_dir():
        sys.exit(f"{folder}: no such folder: the real DIGIT images are expected in ../shared/data next to the "
                 f"checkout (set TELETOUCH_SHARED_DATA to their folder)")
    return folder


def sched_fifo_refused(priority: int) -> str | None:
    """None if a thread of this process may run under SCHED_FIFO ``priority`` (probed on a short-lived thread, the
    way the runtime sets its loop threads); else why not. The runtime only logs a refusal and runs on with normal
    scheduling, and the benchmarks silence its log: without this, a result labelled SCHED_FIFO was not."""
    if priority <= 0:
        return None
    why: list[str] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as e:
            why.append(f"{type(e).__name__}: {e}")

    t = threading.Thread(target=probe, name="sched-fifo-probe")
    t.start()
    t.join()
    return why[0] if why else None


def warn_if_no_sched_fifo(priority: int) -> str | None:
    """:func:`sched_fifo_refused`, said on stderr when refused (the runs asking for it use normal scheduling)."""
    why = sched_fifo_refused(priority)
    if why:
        print(f"note: SCHED_FIFO {priority} is not permitted here ({why}): the runs that ask for it use normal "
              f"scheduling and say so (sched_fifo_applied: false); grant CAP_SYS_NICE or an rtprio limit",
              file=sys.stderr)
    return why


#: rounds of a side-by-side timing (:func:`interleaved`)
ROUNDS = 10


def interleaved_clocks(cases: dict[str, Callable[[int], Any]], cycles: int | dict[str, int],
                       rounds: int = ROUNDS) -> dict[str, dict[str, float]]:
    """Each of ``cases`` (name -> ``run(n)``, which does the next n cycles) timed side by side, so that a change of
    load on the shared machine hits them alike: ``rounds`` rounds, each running every case for its share of
    ``cycles`` (one count for all, or name -> count), the order reversed every other round. Per case: wall and CPU
    (this process) seconds per cycle, and the cycles run."""
    names = list(cases)
    counts = cycles if isinstance(cycles, dict) else dict.fromkeys(names, cycles)
    per = {name: max(1, counts[name] // rounds) for name in names}
    wall = dict.fromkeys(names, 0.0)
    cpu = dict.fromkeys(names, 0.0)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            t0, c0 = time.perf_counter(), time.process_time()
            cases[name](per[name])
            wall[name] += time.perf_counter() - t0
            cpu[name] += time.process_time() - c0
    return {name: {"wall_s": wall[name] / (per[name] * rounds), "cpu_s": cpu[name] / (per[name] * rounds),
                   "cycles": per[name] * rounds} for name in names}


def interleaved(cases: dict[str, Callable[[int], Any]], cycles: int | dict[str, int],
                rounds: int = ROUNDS) -> dict[str, float]:
    """Wall seconds per cycle of each of ``cases``, timed side by side (:func:`interleaved_clocks`)."""
    return {name: v["wall_s"] for name, v in interleaved_clocks(cases, cycles, rounds).items()}


def alternating(names: list[str], rounds: int) -> list[str]:
    """The order in which ``rounds`` rounds of ``names`` run side by side: each round runs every name once, the
    order reversed every other round (A B, B A, ...)."""
    return [name for r in range(rounds) for name in (names if r % 2 == 0 else names[::-1])]


def missing_data(name: str, base: Path | None = None) -> str | None:
    """Why ``base``/``name`` cannot be read as a data folder (None if it can): the message of :func:`data_folder`,
    for a benchmark that refuses a bad ``--data`` as a usage error."""
    folder = (DATA if base is None else Path(base)) / name
    if folder.is_dir():
        return None
    return (f"{folder}: no such folder: the real DIGIT images are expected in ../shared/data next to the checkout "
            f"(set TELETOUCH_SHARED_DATA to their folder)")


def in_turns(runs: dict[str, Callable[[Callable[[float], None]], Any]], marks: list[float],
             ready: Callable[[], Any] | None = None, clock: Callable[[], float] | None = None,
             cpu: Callable[[], float] | None = None) -> tuple[dict[str, Any], dict[str, list[dict]]]:
    """Whole runs that cannot be cut into short ones (a simulated run is one scenario from its start to its end)
    timed side by side all the same. Each of ``runs`` (name -> ``run(checkpoint)``: runs to its end, calling
    ``checkpoint(p)`` every so often with its progress ``p``, e.g. simulated seconds, and returns its result) runs in
    a thread of its own, and only one of them at a time: a run's checkpoint at or past the next of ``marks`` pauses
    it and hands over to the next run. Every run is first taken to ``marks[0]`` (its start-up, not timed), one after
    the other; then ``ready()``; then ``len(marks) - 1`` rounds, each taking every run to its next mark, the order
    reversed every other round (:func:`alternating`), so that a change of load on the shared machine hits them
    alike; then every run to its end (not timed). Returns each run's result, and per run its turns: round, wall and
    CPU (this process: only the run in its turn is working) seconds, progress made, and ``ended`` (the run ended
    inside the turn, before its mark: that turn's time includes its shut-down). ``clock`` and ``cpu``: the wall and
    CPU clocks (default time.perf_counter, time.process_time)."""
    clock = clock or time.perf_counter
    cpu = cpu or time.process_time
    names = list(runs)
    turns: dict[str, list[dict]] = {name: [] for name in names}
    results: dict[str, Any] = {}
    errors: dict[str, BaseException] = {}
    go = {name: threading.Semaphore(0) for name in names}
    back = {name: threading.Semaphore(0) for name in names}
    at = dict.fromkeys(names, 0.0)          # each run's progress at its last hand-over
    due = dict.fromkeys(names, 0)           # the index in marks of each run's next stop
    done = dict.fromkeys(names, False)

    def worker(name: str) -> None:
        def checkpoint(p: float) -> None:
            if due[name] < len(marks) and p >= marks[due[name]]:
                while due[name] < len(marks) and p >= marks[due[name]]:   # past several marks: one turn
                    due[name] += 1
                at[name] = p
                back[name].release()
                go[name].acquire()

        go[name].acquire()
        try:
            results[name] = runs[name](checkpoint)
        except BaseException as exc:   # said by the caller's thread, after the others have ended
            errors[name] = exc
        finally:
            done[name] = True
            back[name].release()

    def turn(name: str) -> None:
        go[name].release()
        back[name].acquire()

    threads = [threading.Thread(target=worker, args=(name,), name=f"in-turns-{name}", daemon=True) for name in names]
    for th in threads:
        th.start()
    try:
        for name in names:
            turn(name)
        if ready is not None:
            ready()
        for k, name in enumerate(alternating(names, len(marks) - 1)):
            if done[name]:
                continue
            p0, t0, c0 = at[name], clock(), cpu()
            turn(name)
            wall, used = clock() - t0, cpu() - c0
            turns[name].append({"round": k // len(names), "wall_s": wall, "cpu_s": used,
                                "progress": at[name] - p0, "ended": done[name]})
    finally:
        for name in names:
            while not done[name]:
                turn(name)
        for th in threads:
            th.join()
    if errors:
        name, exc = next(iter(errors.items()))
        raise RuntimeError(f"run {name!r} (timed in turns) raised {type(exc).__name__}: {exc}") from exc
    return results, turns
