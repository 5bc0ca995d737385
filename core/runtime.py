"""The multi-rate runtime: builds a validated graph into running components and steps each at its own rate.

Two clocks:

- ``sim``: one thread, a priority queue of integer-nanosecond ticks. Deterministic: the same graph gives the same
  result on every run, as fast as the machine allows. At equal times producers step before consumers (data-flow
  order); a feedback edge reads the previous sample.
- ``wall``: real time. Nodes are grouped by rate and each group runs in its own thread with a precise sleep
  (timer slack 1 us, then a short spin), so a slow node (a 60 Hz image estimator) never delays a fast one (a 1 kHz
  haptic loop). Ports hold the latest sample; readers never wait.

Faults (an exception in a node, repeated overruns, an input older than its ``max_age``) stop or degrade the graph as
configured. Every device is driven to its safe state on every stop path: fault, Ctrl-C, SIGTERM, end of run.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import heapq
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

from .component import (
    Component, Context, Device, Inputs, Sample, _Slot, has_warm_up, plain_results, step_location, step_samples,
    value_checker,
)
from .errors import ComponentFault, exception_line, traceback_text, warm_places
from .graph import GraphSpec

EXIT_OK = 0
EXIT_INVALID = 1
EXIT_USAGE = 2
EXIT_FAULT = 3
EXIT_STARTUP = 4
EXIT_INTERRUPTED = 130

Tap = Callable[[str, float, dict], None]


class StartupError(ComponentFault):
    """Why a graph did not start: every node that failed to configure (or the one that failed to activate or to
    start), each with its reason. ``failures``: (node id, plugin, exception) in data-flow order; the first one's
    exception is the cause (``__cause__``). :meth:`Runtime.run` returns it as ``RunResult.error`` (it does not
    raise it: the result, with every device safe and every component closed, says the rest)."""

    def __init__(self, message: str, failures: list[tuple[str, str, BaseException]]):
        super().__init__(message)
        self.failures = list(failures)
        if failures:
            self.__cause__ = failures[0][2]


@dataclass
class Fault:
    node: str
    kind: str  # exception | overrun | stale | stall | timeout | upstream | hung | startup | shutdown | progress
    message: str
    time: float
    action: str  # stop | degrade | logged
    #: the full traceback of the exception the fault is about (:func:`errors.traceback_text`; ``teletouch run
    #: --traceback`` prints it); "" for a fault that no exception raised (an overrun, a stale input, a stall). Not
    #: part of :meth:`RunResult.as_dict`.
    traceback: str = field(default="", repr=False, compare=False)

    def line(self) -> str:
        return f"node '{self.node}' {self.kind} at t={self.time:.3f} s: {self.message}"

    def as_dict(self) -> dict[str, Any]:
        """The fault as ``teletouch run --json`` gives it (its traceback left out)."""
        return {"node": self.node, "kind": self.kind, "message": self.message, "time": self.time,
                "action": self.action}


@dataclass
class NodeStats:
    id: str
    plugin: str
    rate: float
    steps: int
    #: steps per second over the steps' own span, (steps - 1) / (time of the last step - time of the first); None
    #: with fewer than two steps
    achieved_rate: float | None
    overruns: int
    mean_step_s: float
    max_step_s: float
    faulted: bool
    period_jitter_p99_s: float | None = None
    #: what the run achieved (Component.results): {key: number or text}; empty where the node said nothing
    results: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class RunResult:
    status: str  # ok | stopped | degraded (ran to the end with nodes disabled by faults) | fault | interrupted |
    #              startup-failed
    exit_code: int
    message: str
    sim_time: float
    wall_time: float
    clock: str
    nodes: list[NodeStats] = field(default_factory=list)
    #: in the order they were found; one per failure: the first cause of a node's fault is its fault, and a later
    #: error of that node (its step, running when the watchdog faulted it, then raised) is only logged
    faults: list[Fault] = field(default_factory=list)
    startup_time: float = 0.0   # s of wall_time spent starting up (loading models, opening devices)
    error: StartupError | None = field(default=None, repr=False, compare=False)   # status startup-failed: why
    #: the signal (SIGINT/SIGTERM number) that arrived during the safe shutdown and made the run "interrupted"
    #: (held there, so the caller's own handler never saw it); None otherwise
    late_signal: int | None = field(default=None, repr=False, compare=False)
    #: the signal that interrupted the run (raised in it, or held in its shutdown: ``late_signal``), SIGINT for a plain
    #: KeyboardInterrupt; None where no signal did
    signal: int | None = field(default=None, repr=False, compare=False)

    @property
    def realtime_factor(self) -> float:
        """Graph seconds per wall second, start-up included."""
        return self.sim_time / self.wall_time if self.wall_time > 0 else math.inf

    @property
    def run_realtime_factor(self) -> float:
        """Graph seconds per wall second of the run itself (start-up excluded)."""
        run = self.wall_time - self.startup_time
        return self.sim_time / run if run > 0 else math.inf

    def as_dict(self) -> dict[str, Any]:
        return {"status": self.status, "exit_code": self.exit_code, "message": self.message,
                "sim_time_s": self.sim_time, "wall_time_s": self.wall_time, "clock": self.clock,
                "realtime_factor": self.realtime_factor, "startup_time_s": self.startup_time,
                "run_realtime_factor": self.run_realtime_factor, "nodes": [n.as_dict() for n in self.nodes],
                "faults": [f.as_dict() for f in self.faults]}

    @property
    def ending(self) -> str:
        """How the run ended, in one line for a person: "STATUS: message" (an interrupted run's message says so
        itself, and which signal came: "interrupted (SIGTERM): ...")."""
        return self.message if self.status == "interrupted" else f"{self.status}: {self.message}"

    def summary(self, header: bool = True) -> str:
        """The summary `teletouch run` prints at the end: status (``header``: the run's end, its message whole), clock
        and one row per node, with the period jitter p99 (ms; '-' where not measured: the simulated clock, or too
        few steps) next to the rates, as :meth:`as_dict` gives it in ``period_jitter_p99_s``."""
        head = [self.ending] if header else []
        lines = [*head,
                 f"clock {self.clock}: {self.sim_time:.3f} s graph time in {self.wall_time - self.startup_time:.3f} s "
                 f"wall after {self.startup_time:.3f} s start-up ({self.run_realtime_factor:.1f}x real time)",
                 f"  {'node':<16}{'plugin':<20}{'rate Hz':>9}{'achieved':>10}{'jitter p99 ms':>15}{'steps':>9}"
                 f"{'overruns':>9}{'mean ms':>9}{'max ms':>9}"]
        for n in self.nodes:
            jit = n.period_jitter_p99_s
            jit_text = f"{jit * 1e3:.3f}" if isinstance(jit, (int, float)) and math.isfinite(jit) else "-"
            rate_text = "-" if n.achieved_rate is None else f"{n.achieved_rate:.1f}"
            lines.append(f"  {n.id:<16}{n.plugin:<20}{n.rate:>9.1f}{rate_text:>10}{jit_text:>15}"
                         f"{n.steps:>9d}{n.overruns:>9d}{n.mean_step_s * 1e3:>9.3f}{n.max_step_s * 1e3:>9.3f}"
                         + ("  FAULTED" if n.faulted else ""))
        for f in self.faults:
            lines.append(f"  fault: {f.line()} -> {f.action}")
        return "\n".join(lines)


class _Node:
    __slots__ = ("id", "spec", "comp", "step", "rate", "period", "inputs", "out", "stale", "policy", "faulted",
                 "steps", "overruns", "consec_overruns", "busy", "max_step", "is_device", "order", "starts",
                 "nstarts", "last_dt", "state", "hung", "safe_thread", "in_step", "checks", "acts", "safe_mark",
                 "resafe", "first_t", "last_t", "warm", "warming", "warm_began", "warm_dt", "warm_skips", "results")

    def __init__(self, spec: Any, comp: Component, order: int, policy: str, in_slots: dict[str, _Slot],
                 out: dict[str, _Slot]):
        self.id = spec.id
        self.spec = spec
        self.comp = comp
        self.step = comp.step
        self.rate = float(spec.rate)
        self.period = 1.0 / self.rate
        self.inputs = Inputs(in_slots)
        self.out = out
        self.stale: list[tuple[str, _Slot, float, str]] = []
        self.policy = policy
        self.faulted = False
        self.steps = 0
        self.overruns = 0
        self.consec_overruns = 0
        self.busy = 0.0
        self.max_step = 0.0
        self.is_device = isinstance(comp, Device)
        self.order = order
        self.starts: list[float] = []
        self.nstarts = 0
        self.last_dt = 0.0
        self.state = "unconfigured"
        self.hung = False   # its safe_state() did not return within faults.safe_timeout: left behind
        self.results: dict[str, Any] = {}   # Component.results(), asked at the shutdown
        self.safe_thread: threading.Thread | None = None   # wall clock: the thread of its latest safe_state() call
        self.in_step = False   # wall clock: its step() is running in its rate group's thread
        # output port -> its value check (None: dtype "any"), see component.value_checker
        self.checks = {p: value_checker(port) for p, port in spec.cls.outputs.items()}
        self.acts = 0          # step() calls begun
        self.safe_mark: int | None = None   # `acts` when its latest safe_state() that returned began (no step then)
        # a safe_state() call began while its step was in flight (that step may command it after the call): the
        # step's end makes it safe again, faulted or not (at a stop too: the shutdown may have passed it by then)
        self.resafe = False
        self.first_t = 0.0     # graph time of its first step and of its latest (counted in `steps`)
        self.last_t = 0.0
        # wall clock: its Component.warm(), called WARM_LEAD before each step, or None (component.has_warm_up with
        # the node's parameters, decided once it has configured: _startup). The class is the spec's: for an isolated
        # node the one in its child (the proxy's warm() asks the child)
        self.warm: Callable[[], None] | None = None
        self.warming = False    # its warm() is running (in_step is set too: the watchdog names the warm-up)
        self.warm_began = 0.0   # graph time its latest warm() began
        self.warm_dt = 0.0      # how long its latest warm() took (s)
        self.warm_skips = 0     # warm-ups left out in a row (the budget): tried again after a second's worth

    def decide_warm(self) -> None:
        """Whether the runtime warms this node (:attr:`warm`), once it has configured: a warm() of its class's own,
        not a device's, wanted with its parameters (component.has_warm_up)."""
        self.warm = self.comp.warm if has_warm_up(self.spec.cls, self.comp.params) else None

    def last_start(self) -> float:
        """Graph time its latest step began (wall clock: kept in the ``starts`` ring); 0.0 before its first."""
        return self.starts[(self.nstarts - 1) % len(self.starts)] if self.nstarts else 0.0

    def achieved_rate(self) -> float | None:
        """Steps per second over the steps' own span: (steps - 1) intervals between the first and the latest step
        (steps / elapsed counted one too many: 101 Hz for a 100 Hz node over 1 s). None before two steps."""
        span = self.last_t - self.first_t
        return (self.steps - 1) / span if self.steps >= 2 and span > 0 else None


class _StopEvent:
    """The run's stop flag: ``is_set()``, ``set()`` and ``wait(timeout)`` of :class:`threading.Event`, safe in the
    main thread, where a Ctrl-C raises KeyboardInterrupt at any bytecode. ``Event.wait()`` takes its Condition's lock
    in Python code (``Condition.__enter__``/``__exit__``): an interrupt right after that acquire, or right before the
    release, left the lock held, and the shutdown's first ``set()`` then waited for it forever. Here no lock is held
    across Python code that anything waits for without a timeout: the first ``set()`` releases a gate (once) that
    ``wait()`` tries with its timeout; the flag, set first, is what every reader goes by."""

    def __init__(self) -> None:
        self._flag = False
        self._gate = threading.Lock()
        self._gate.acquire()                # released by the first set()
        self._opened = threading.Lock()     # taken by the first set(): the gate is released once

    def is_set(self) -> bool:
        return self._flag

    def set(self) -> None:
        self._flag = True
        if self._opened.acquire(False):
            self._gate.release()

    def wait(self, timeout: float | None = None) -> bool:
        if not self._flag and self._gate.acquire(True, -1 if timeout is None else timeout):
            self._gate.release()            # (open for the other waiters; one interrupted here: they time out)
        return self._flag


_libc = None


def _set_timer_slack(ns: int = 1000) -> None:
    """Ask Linux for precise sleeps in this thread (default slack is 50 us)."""
    global _libc
    if not sys.platform.startswith("linux"):
        return
    try:
        if _libc is None:
            _libc = ctypes.CDLL(None, use_errno=True)
        _libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0)  # PR_SET_TIMERSLACK
    except Exception:  # pragma: no cover - best effort
        pass


class Runtime:
    """Runs one graph. Build with :meth:`from_spec`; then :meth:`run`."""

    JITTER_RING = 8192
    #: under the wall clock the interpreter's GIL switch interval is at most this fraction of the fastest rate's
    #: period (20 us at 1 kHz): a thread that waits for the GIL (the 1 kHz loop, woken for its tick) gets it after
    #: at most one interval of another thread's Python code. Measured on the simulated teleoperation loop (wall
    #: clock, SCHED_FIFO; three sessions of interleaved A/B, 3-4 rounds; docs/teleoperation.md): controller jitter
    #: p99 median 0.25-0.28 -> 0.17-0.23 ms against 0.1 (100 us), the frame-to-force latency p99 not consistently
    #: moved (within the run-to-run spread)
    SWITCH_FRACTION = 0.02
    #: under the wall clock a node's Component.warm() is called this long before its step (s), in a rate group
    #: whose period is at least 5 times as long (a 60 Hz estimator's; not a 1 kHz loop's). The caches stay warm for
    #: a few milliseconds: the depth pipeline's step after a 16 ms pause took 1.6-1.8 ms of CPU time, after a
    #: rehearsal of it 1 ms before 0.9-1.0 ms, 4 ms before 1.1-1.2 ms (docs/depth.md, `warm`)
    WARM_LEAD = 1e-3
    #: under the wall clock, how long the shutdown waits for a node's deactivate(), results() or close() (s): one
    #: that has not returned by then is left behind (see _bounded)
    LIFECYCLE_TIMEOUT = 10.0
    #: how long a stale input's fault waits for the source device's status() to say its problem (s; wall clock):
    #: see _source_problem
    PROBLEM_WAIT = 0.01

    def __init__(self, spec: GraphSpec, registry: Any = None, *, clock: str | None = None,
                 log: Callable[[str], None] | None = None):
        self.spec = spec
        self.clock = clock or spec.clock
        self._log = log or (lambda msg: print(msg, file=sys.stderr))
        self.taps: list[Tap] = []
        self.faults: list[Fault] = []
        self._unsafe: list[Fault] = []   # faults that leave a device perhaps not in its safe state (see _finish)
        self._now = 0.0
        self._stop_evt = _StopEvent()   # (not a threading.Event: see _StopEvent)
        self._late: list[int] | None = None   # once run() has reached its shutdown: the signals held there
        self._stop_reason: tuple[str, int, str] | None = None  # (status, exit code, message)
        self._lock = threading.Lock()
        self._t0 = 0.0
        self._t0_mono = 0.0
        self._ran = False
        self._safe_lock = threading.Lock()   # one safe_state() call at a time per device (see _safe)
        self.nodes: list[_Node] = []
        #: each node's id -> the nodes that feed it (:func:`feeders`), for its Context.disabled_upstream
        self._feeders: dict[str, tuple[_Node, ...]] = {}
        #: the graph's warnings under this runtime's clock (``spec.warnings`` are those of the clock it was loaded
        #: for, which the loader's caller has shown); each of them that the loader did not give is logged here
        self.warnings = spec.warnings_for(self.clock)
        for line in self.warnings:
            if line not in spec.warnings:
                self.log(f"warning: {line}")
        self._build()
        warm_places()   # what a fault's place needs, read now: not on the first fault's way to the safe states

    def log(self, msg: str) -> None:
        """Log a line. A logger that fails (stderr closed: a pipe whose reader has gone) must not take the fault
        handling with it: the line is dropped; every fault is in the run's result anyway."""
        try:
            self._log(msg)
        except Exception:
            pass

    # ------------------------------------------------------------------------------------------------- building
    def _build(self) -> None:
        order = self.spec.order()
        slots: dict[tuple[str, str], _Slot] = {}
        for n in order:
            for port in n.cls.outputs:
                slots[(n.id, port)] = _Slot()
        for i, n in enumerate(order):
            ctx = Context(now=self.now, clock_kind=self.clock, request_stop=self.request_stop,
                          log=lambda m, nid=n.id: self.log(f"[{nid}] {m}"), from_monotonic=self.from_monotonic,
                          rate=float(n.rate), disabled_upstream=lambda nid=n.id: self._disabled_upstream(nid))
            params = n.params_obj if n.params_obj is not None else n.cls.Params.model_validate(n.params)
            if n.isolate == "process" and self.clock == "wall":
                from .isolation import ProcessProxy

                comp = ProcessProxy(n.cls, params, node_id=n.id, ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                                    step_timeout=max(1.0, 20.0 / float(n.rate)),
                                    priority=thread_priority(self.spec.realtime_priority, n.rate, [n.priority]))
            else:
                try:
                    comp = n.cls(params, node_id=n.id, ctx=ctx)
                except Exception as exc:   # nothing is configured yet, so nothing is live: name the node
                    raise ComponentFault(f"{n.plugin} could not be created: {exception_line(exc)}",
                                         node=n.id) from exc
            in_slots: dict[str, _Slot] = {}
            for port in n.cls.inputs:
                w = n.inputs.get(port)
                in_slots[port] = slots[(w.node, w.source_port)] if w is not None else _Slot()
            out = {p: slots[(n.id, p)] for p in n.cls.outputs}
            node = _Node(n, comp, i, n.on_fault or self.spec.faults.on_fault, in_slots, out)
            for port, w in n.inputs.items():
                if w.max_age is not None:
                    node.stale.append((port, in_slots[port], w.max_age, f"{w.node}.{w.source_port}"))
            self.nodes.append(node)
        by_id = self._by_id = {node.id: node for node in self.nodes}
        self._feeders = {nid: tuple(by_id[f] for f in ids) for nid, ids in feeders(self.spec).items()}

    def _commanded_from(self, node: _Node) -> list[tuple[_Node, str, str]]:
        """The devices whose inputs carry ``node``'s outputs: wired from it, or from a node it feeds that does not
        guard its devices itself (``Component.guards_upstream``: a filter or a gain passes a dead node's last value on
        with fresh stamps), through any number of those; each once, as (device, its input port, the node that input is
        wired from), in graph order."""
        found: dict[str, tuple[_Node, str, str]] = {}
        seen, todo = {node.id}, [node.id]
        while todo:
            src = todo.pop(0)
            for other in self.nodes:
                port = next((p for p, w in other.spec.inputs.items() if w.node == src), None)
                if port is None or other.id in seen:
                    continue
                if other.is_device:
                    found.setdefault(other.id, (other, port, src))
                elif not getattr(other.spec.cls, "guards_upstream", False):
                    seen.add(other.id)
                    todo.append(other.id)
        return sorted(found.values(), key=lambda f: f[0].order)

    def _disabled_upstream(self, node_id: str) -> list[str]:
        """Context.disabled_upstream of node ``node_id``: its feeders (precomputed in :meth:`_build`) that a fault
        has disabled, in data-flow order."""
        return [n.id for n in self._feeders.get(node_id, ()) if n.faulted]

    def component(self, node_id: str) -> Component:
        for n in self.nodes:
            if n.id == node_id:
                return n.comp
        raise KeyError(node_id)

    def latest(self, node_id: str, port: str) -> Sample | None:
        for n in self.nodes:
            if n.id == node_id:
                return n.out[port].sample
        raise KeyError(node_id)

    def add_tap(self, tap: Tap) -> None:
        """Call ``tap(node_id, t, outputs)`` after every step that produced outputs (recording, experiments):
        ``t`` the step's graph time, ``outputs`` the mapping the step returned, as it returned it (a bare value, or a
        Sample where the step gave its own stamp; docs/recording.md). In wall-clock mode it is called from the
        node's thread: it must be quick and thread-safe."""
        self.taps.append(tap)

    # ------------------------------------------------------------------------------------------------- clock
    def now(self) -> float:
        if self.clock == "sim":
            return self._now
        return time.perf_counter() - self._t0

    def from_monotonic(self, mono: float) -> float:
        """Convert a time.monotonic() reading (e.g. a camera capture time) to graph time."""
        if self.clock == "sim":
            return self._now
        return mono - self._t0_mono

    def request_stop(self, reason: str = "stop requested") -> None:
        with self._lock:
            if self._stop_reason is None:
                self._stop_reason = ("stopped", EXIT_OK, reason)
        self._stop_evt.set()

    # ------------------------------------------------------------------------------------------------- faults
    def _fault(self, node: _Node, kind: str, message: str, t: float, safe: bool = True,
               exc: BaseException | None = None) -> list[_Node]:
        """Record a fault of ``node`` and act on it (its policy). One fault per node: the first cause wins. A node
        faulted already (the watchdog faulted it while its step ran; that step then raised) gets no second fault
        (the run's result would list two for one failure, the later one stamped at the step's start, before the
        first): the later error is only logged. The devices it faults (the node itself, those wired from it under
        degrade) are made safe side by side (:meth:`_safe_many`) and returned; with ``safe`` False they are only
        returned, for a caller that makes them safe with others. ``exc``: the exception the fault is about (its
        traceback is kept in the fault)."""
        action = node.policy
        fault = Fault(node.id, kind, message, t, action)
        with self._lock:
            first = not node.faulted
            if first:
                self.faults.append(fault)
                if action == "stop" and self._stop_reason is None:
                    self._stop_reason = ("fault", EXIT_FAULT, f"node '{node.id}' {kind}: {message}")
                # under the lock: a step in flight (the watchdog faults a node whose step still runs) checks it
                # there before it stores its outputs (see _write), so nothing of the node is published after its
                # fault
                node.faulted = True
        if not first:   # (a device among them is made safe again by its rate group once that step returned)
            self.log(f"[{node.id}] {kind} after its fault (not recorded: the first one stands): {message}")
            return []
        todo = [node] if node.is_device else []
        if action == "stop":
            self._stop_evt.set()
        else:
            self.log(f"[{node.id}] {kind}: {message} -> node disabled (degrade)")
            # a device commanded by the disabled node would keep its last command: it goes to its safe state and
            # is disabled too; so does one commanded through nodes that pass their last value on (a filter, a gain:
            # fresh stamps on a dead node's value), up to a node that guards its devices itself (guards_upstream:
            # the controller fades the force of a dead estimator and holds the follower)
            for other, port, via in self._commanded_from(node):
                if not other.faulted:
                    through = f", fed by node '{node.id}'" if via != node.id else ""
                    todo += self._fault(other, "upstream", f"input '{port}' comes from node '{via}'{through}, which "
                                                           f"was disabled by a fault", t, safe=False)
        if safe:
            self._safe_many(todo)
        if exc is not None:   # after the safe states: formatting it reads the source files
            fault.traceback = traceback_text(exc)
        return todo

    def _safe(self, node: _Node) -> None:
        """``safe_state()`` of one device: :meth:`_safe_many`."""
        self._safe_many([node])

    def _safe_many(self, nodes: list[_Node], again: bool = True) -> None:
        """``safe_state()`` of each device (not again for one still safe from an earlier call, see
        :meth:`_still_safe`, nor for one left behind). Under the wall clock the calls are bounded and made side by
        side: each runs in a helper thread, all are started before any is waited for, and they are waited for
        until one deadline, ``faults.safe_timeout`` from now (one device whose call hangs does not hold up the
        others': made one after the other, N hung devices kept the next one's force on a hand N x safe_timeout). A
        driver whose step hangs inside a hardware call usually holds the lock its safe_state() needs; unbounded, that
        one call would block the caller (the watchdog's main thread, a rate group's exit, the shutdown) and with it
        every other device's safe state and the end of the run. Such a node is left behind (``hung``: no further
        lifecycle calls) and reported.

        Calls for one device never overlap: a caller that finds a call still running (started by another thread,
        or one whose wait a Ctrl-C cut short) waits for that call instead of starting a second one; when it has
        returned and the device is not safe by it (it began while a step was in flight, which may have commanded
        the device after it, or it raised), the caller makes a call of its own (``again``). A call begun while the
        device's step was in flight marks it (``resafe``): that step's end makes it safe again.

        Under the simulated clock the calls are made inline, in the one thread that also steps the devices: there
        is no hardware that could hang (hardware plugins need the wall clock), and a simulated device that hung
        would block that thread in its step just the same. A KeyboardInterrupt raised by one of them comes out
        once the others were made."""
        nodes = [n for n in nodes if not n.hung and not self._still_safe(n)]
        if not nodes:
            return
        if self.clock == "sim":
            interrupt: BaseException | None = None
            for node in nodes:
                mark = None if node.in_step else node.acts
                try:
                    node.comp.safe_state()
                except BaseException as exc:
                    self._safe_raised(node, exc)
                    if isinstance(exc, KeyboardInterrupt) and interrupt is None:
                        interrupt = exc
                else:
                    node.safe_mark = mark
            if interrupt is not None:
                raise interrupt
            return
        timeout = self.spec.faults.safe_timeout
        calls = [(node, *self._safe_begin(node)) for node in nodes]
        deadline = time.monotonic() + timeout
        retry = []
        for node, th, own in calls:
            if th is None:   # a call that has just ended (while this caller waited for the lock) made it safe
                continue
            th.join(max(0.0, deadline - time.monotonic()))
            if th.is_alive():
                self._safe_hung(node, timeout)
            elif again and not own and not node.in_step and not self._still_safe(node):
                retry.append(node)
        if retry:
            self._safe_many(retry, again=False)

    def _safe_begin(self, node: _Node) -> tuple[threading.Thread | None, bool]:
        """The thread of ``node``'s safe_state() call and whether this caller started it: the call still running if
        there is one, else a new one (None: none needed, a call that has just ended made it safe)."""
        with self._safe_lock:
            th = node.safe_thread
            if th is not None and th.is_alive():
                return th, False
            if self._still_safe(node):
                return None, False
            mark = node.acts   # read before in_step: a step begun after this read changes `acts`
            if node.in_step:   # a step in flight (it hangs: the watchdog) may command the device after the call
                mark = None
                node.resafe = True
            th = threading.Thread(target=self._safe_call, args=(node, mark), name=f"teletouch-safe-{node.id}",
                                  daemon=True)
            node.safe_thread = th
            th.start()
            return th, True

    def _safe_hung(self, node: _Node, timeout: float) -> None:
        with self._lock:
            if node.hung:   # another caller has reported it
                return
            node.hung = True
            msg = (f"safe_state() did not return within {timeout:g} s (faults.safe_timeout; a call into its "
                   f"hardware hangs?): left behind, the other devices were made safe")
            fault = Fault(node.id, "hung", msg, self._now, "logged")
            self.faults.append(fault)
            self._unsafe.append(fault)
        self.log(f"[{node.id}] {msg}")

    def _safe_call(self, node: _Node, mark: int | None) -> None:
        try:
            node.comp.safe_state()
        except BaseException as exc:   # (SystemExit, or a KeyboardInterrupt raised by the driver: still its error)
            self._safe_raised(node, exc)
        else:
            node.safe_mark = mark

    @staticmethod
    def _still_safe(node: _Node) -> bool:
        """Whether the device's latest safe_state() returned (did not raise) and no step() of it has begun since
        (none was in flight when it began): then it is still in its safe state and is not called again. A call that
        raised, or a step after it (a step that hung through it and then went on), makes the next stop path call it
        again."""
        return node.safe_mark is not None and node.safe_mark == node.acts and not node.in_step

    def _safe_raised(self, node: _Node, exc: BaseException) -> None:
        fault = Fault(node.id, "shutdown", f"safe_state() raised {exception_line(exc)}", self._now, "logged",
                      traceback_text(exc))   # (formatted outside the lock: it reads the source files)
        with self._lock:
            self.faults.append(fault)
            self._unsafe.append(fault)

    @staticmethod
    def _step_error(node: _Node, exc: BaseException) -> str:
        """The fault's text for an exception from a node's step (or warm-up): :func:`exception_line`, and where the
        exception is a ComponentFault about one of the node's inputs (``input_port``: a plugin cannot know its
        graph), which node and port feed that input."""
        port = getattr(exc, "input_port", None) if isinstance(exc, ComponentFault) else None
        if not isinstance(port, str):
            return exception_line(exc)
        wire = node.spec.inputs.get(port)
        if wire is not None:
            more = f"; input '{port}' is fed by node '{wire.node}' port '{wire.source_port}'"
        elif port in node.spec.cls.inputs:
            more = f"; input '{port}' is not wired in the graph"
        else:
            more = (f"; the fault names input '{port}', which {node.spec.plugin} does not have (inputs: "
                    f"{', '.join(node.spec.cls.inputs) or '(none)'})")
        return exception_line(exc, more)

    def _check_stale(self, node: _Node, t: float) -> bool:
        if t < self.spec.faults.startup_grace:
            return True
        for port, slot, max_age, src in node.stale:
            s = slot.sample
            if s is None:
                self._fault(node, "stale", f"input '{port}' from {src}: nothing received after "
                                           f"{t:.3f} s (limit {max_age:g} s){self._source_problem(src)}", t)
                return False
            if not s.is_fresh(t, max_age):
                age = t - s.stamp
                what = f"{age:.3f} s old" if age > 0 else (f"stamped {-age:.3f} s ahead of the graph clock"
                                                           if age < 0 else f"stamped {s.stamp!r}")
                self._fault(node, "stale", f"input '{port}' from {src} is {what} (limit {max_age:g} s)"
                                           f"{self._source_problem(src)}", t)
                return False
        return True

    def _source_problem(self, src: str) -> str:
        """What the device feeding a stale input says is wrong now, for the stale fault ("; node 'gripper' reports:
        ..."): the ``problem`` of its status() (a follower whose reads fail: for how long, and the last error), or ''.
        A stale input is most often a device that stopped answering, which faults only at its own, longer timeout
        (``read_timeout``): the consumer's fault came first and said nothing of why. Only a device is asked (an
        isolated node's status() is a round trip to its process); under the wall clock in a helper thread, waited for
        at most ``PROBLEM_WAIT``: a status() that blocks must not hold up the fault and the safe state."""
        n = self._by_id.get(src.split(".", 1)[0])
        if n is None or not n.is_device or n.hung:
            return ""
        got: list[Any] = []

        def ask() -> None:
            try:
                got.append(n.comp.status().get("problem"))
            except BaseException:   # (a status() that fails, even by SystemExit, says nothing here)
                pass

        if self.clock == "sim":
            ask()
        else:   # asked from the consumer's rate-group thread: a status() that blocks (a lock its hung reader holds)
            _returned_within(ask, f"teletouch-status-{n.id}", self.PROBLEM_WAIT)   # must not hold it
        problem = got[0] if got else None
        return f"; node '{n.id}' reports: {problem}" if isinstance(problem, str) and problem else ""

    def _write(self, node: _Node, out: Any, t: float, guard: Any = None) -> None:
        """Store a step's outputs. Each value is checked against its port (dtype and shape, see
        ``component.value_checker``) and each stamp: one that does not fit is a fault of the node, and then none of
        that step's outputs is stored (consumers never see half of a step).

        ``guard`` (wall clock: the runtime's lock, under which :meth:`_fault` disables a node): the outputs are
        stored, and the taps called, only if the node was not faulted while its step ran (the watchdog faults an
        inline node whose step runs past its bound; that step returns later): a disabled node publishes nothing."""
        slots = node.out
        try:
            samples = step_samples(out, node.spec.cls.outputs, node.checks, t)
        except ComponentFault as exc:   # found here, made by the plugin: point at its step(), not at the runtime
            exc.where = step_location(node.spec.cls)
            raise
        if guard is None:   # the simulated clock: one thread, nothing faults a node while its step runs
            for name, v in samples:
                slots[name].sample = v
        else:
            with guard:
                if node.faulted:
                    return
                for name, v in samples:
                    slots[name].sample = v
        for tap in self.taps:
            tap(node.id, t, out)

    # ------------------------------------------------------------------------------------------------- lifecycle
    def _startup(self) -> StartupError | None:
        """Configure every node (data-flow order), then activate every node. A node that fails to configure does
        not stop the others from being configured (a lab learns about every missing device in one run): it is made
        safe (a device: it may be half set up) and closed at once, and after the last node nothing is activated.
        Activation stops at the first failure (activating means acting). Returns the start-up error, or None."""
        failed: list[tuple[_Node, BaseException]] = []
        for node in self.nodes:
            node.state = "configuring"   # from here on a device may be live: a stop path makes it safe
            try:
                node.comp.configure()
                node.state = "inactive"
                node.decide_warm()   # (a plugin's wants_warm_up that raises: a failure to configure, as isolated)
            except (Exception, SystemExit) as exc:   # a plugin's sys.exit() is its failure, not the process's
                failed.append((node, exc))
                self._startup_fault(node, f"failed to configure: {exception_line(exc)}", exc)
                self._configure_failed(node)
        if failed:
            return self._startup_error(failed, "failed to configure")
        for node in self.nodes:
            try:
                node.comp.activate()
                node.state = "active"
            except (Exception, SystemExit) as exc:
                self._startup_fault(node, f"failed to activate: {exception_line(exc)}", exc)
                return self._startup_error([(node, exc)], "failed to activate")
        return None

    def _startup_fault(self, node: _Node, what: str, exc: BaseException | None = None) -> None:
        tb = traceback_text(exc) if exc is not None else ""
        with self._lock:
            self.faults.append(Fault(node.id, "startup", f"node '{node.id}' ({node.spec.plugin}) {what}", 0.0,
                                     "stop", tb))

    @staticmethod
    def _startup_error(failed: list[tuple[_Node, BaseException]], what: str) -> StartupError:
        lines = [f"node '{n.id}' ({n.spec.plugin}) {what}: {exception_line(exc)}" for n, exc in failed]
        msg = "; ".join(lines)
        if len(failed) > 1:
            msg += f" ({len(failed)} nodes {what}; none was activated)"
        return StartupError(msg, [(n.id, n.spec.plugin, exc) for n, exc in failed])

    def _configure_failed(self, node: _Node) -> None:
        """A node whose configure() raised: it may have set up part of its hardware (opened the port, enabled the
        torque or the forces) before it failed. A device is driven to its safe state (best effort, bounded as
        every safe_state() call; an error there is a fault of its own beside the start-up one), then the node is
        closed, at once: what it holds (a serial port, a USB handle) is released before the next node configures."""
        if node.is_device:
            self._safe(node)
        if node.hung:
            with self._lock:
                self.faults.append(Fault(node.id, "shutdown", "close() skipped: its safe_state() hung", self._now,
                                         "logged"))
        else:
            self._lifecycle_call(node, "close")
        node.state = "finalized"

    def _start_clock(self) -> StartupError | None:
        """Wall clock: graph time 0 is the end of start-up (loading models, opening devices, spawning processes)."""
        from .isolation import ProcessProxy

        self._t0 = time.perf_counter()
        self._t0_mono = time.monotonic()
        for node in self.nodes:
            if isinstance(node.comp, ProcessProxy):
                try:
                    node.comp.set_origin(self._t0, self._t0_mono)
                except (Exception, SystemExit) as exc:
                    self._startup_fault(node, f"failed to start: {exception_line(exc)}", exc)
                    return self._startup_error([(node, exc)], "failed to start")
        return None

    def _shutdown(self) -> None:
        """Every device to its safe state (data-flow order; not again for one still safe from an earlier call, see
        :meth:`_still_safe`), then deactivate() in reverse order, then close() in
        reverse order; each call once. An error in one call (any exception, also SystemExit or a KeyboardInterrupt
        raised by a component) is reported and the others are still made. A node that is left behind gets no
        further calls: one whose safe_state() hung, and one whose step() still runs in its rate group's thread
        (wall clock: it hangs; deactivate() or close() would pull its resources from under it)."""
        running = self._still_stepping()
        try:   # (finalized: closed already)
            self._safe_many([n for n in self.nodes if n.is_device and n.state not in ("unconfigured", "finalized")])
        except KeyboardInterrupt:   # raised by a driver itself (signals are held here): reported by _safe_many
            pass
        for node in reversed(self.nodes):
            if node.state == "finalized":   # failed to configure: made safe and closed then
                continue
            if node.hung:   # its safe_state() hung (holding the driver's lock): deactivate/close would hang too
                self.faults.append(Fault(node.id, "shutdown", "deactivate() and close() skipped: its safe_state() "
                                                              "hung", self._now, "logged"))
                node.state = "finalized"
                continue
            if node in running:
                fault = Fault(node.id, "shutdown", "deactivate() and close() skipped: its step() was still running "
                                                   "when the run ended (it hangs?)" + (
                                                       "; made safe again if that step returns" if node.is_device
                                                       else ""), self._now, "logged")
                self.faults.append(fault)
                if node.is_device:   # its step may command it after its safe state (resafe: again once it returns)
                    self._unsafe.append(fault)
                node.state = "finalized"
                continue
            if node.state == "active":
                node.state = "inactive" if self._lifecycle_call(node, "deactivate") else "finalized"
        for node in self.nodes:
            if node.state != "finalized" and node.steps:
                node.results = self._results_of(node)
        for node in reversed(self.nodes):
            if node.state == "finalized":
                continue
            self._lifecycle_call(node, "close")
            node.state = "finalized"

    def _results_of(self, node: _Node) -> dict[str, Any]:
        """``node``'s Component.results(), its values as numbers or text (JSON can hold them; anything else as its
        repr); an error there is a logged shutdown fault and no results (the run's result stays). An isolated node's
        proxy asks its child process (none from a child that died or hangs)."""
        got: list[Any] = []
        if not self._bounded(node, "results", lambda: got.append(node.comp.results())):
            node.state = "finalized"   # left behind: no close() beside it
            return {}
        if not got:   # it raised (a fault says so)
            return {}
        try:
            return plain_results(got[0] or {})
        except BaseException as exc:
            self.faults.append(Fault(node.id, "shutdown", f"results() raised {exception_line(exc)}", self._now,
                                     "logged", traceback_text(exc)))
            return {}

    def _lifecycle_call(self, node: _Node, name: str) -> bool:
        """``deactivate()`` or ``close()`` of ``node`` (:meth:`_bounded`); whether it returned in time."""
        return self._bounded(node, name, getattr(node.comp, name))

    def _bounded(self, node: _Node, name: str, call: Callable[[], Any]) -> bool:
        """A shutdown call of ``node`` (``deactivate``, ``results``, ``close``): an error there is a logged shutdown
        fault and the others are still made. Under the wall clock it is bounded as safe_state() is: it runs in a
        helper thread and is waited for at most ``LIFECYCLE_TIMEOUT``; one that has not returned by then (a driver's
        close() that hangs on a port that vanished) is left behind, reported, and the node gets no further calls (a
        hung deactivate() held the run, and every close() after it, for good: signals are held during the
        shutdown, so only a kill ended it; the devices were safe already). Returns whether it returned in time. An
        isolated node's proxy is called inline: it bounds its calls itself, by its step's timeout (a deactivate()
        waits for a step in flight) and its shutdown timeout, and its close() ends the child process whatever it
        does. A signal that cuts the wait short (a Ctrl-C while a node that failed to configure is closed) leaves
        the call running: the node gets no further calls."""
        from .isolation import ProcessProxy

        raised: list[BaseException] = []

        def run() -> None:
            try:
                call()
            except BaseException as exc:   # (also SystemExit, or a KeyboardInterrupt raised by the plugin)
                raised.append(exc)

        if self.clock == "sim" or isinstance(node.comp, ProcessProxy):
            returned = True
            run()
        else:
            try:
                returned = _returned_within(run, f"teletouch-{name}-{node.id}", self.LIFECYCLE_TIMEOUT)
            except BaseException:   # (KeyboardInterrupt: the call goes on; a second one beside it could free twice)
                node.state = "finalized"
                raise
        if not returned:
            later = {"deactivate": "; its results() and close() are skipped", "results": "; its close() is skipped",
                     "close": ""}.get(name, "")
            self.faults.append(Fault(node.id, "shutdown", f"{name}() did not return within "
                                     f"{self.LIFECYCLE_TIMEOUT:g} s: left behind{later}", self._now, "logged"))
            return False
        if raised:
            self.faults.append(Fault(node.id, "shutdown", f"{name}() raised {exception_line(raised[0])}", self._now,
                                     "logged", traceback_text(raised[0])))
        return True

    def _still_stepping(self) -> set[_Node]:
        """Nodes whose step() still runs in a rate group's thread that did not end when joined (wall clock). An
        isolated node is not among them: its proxy waits for the step in flight itself."""
        busy = [n for n in self.nodes if n.in_step]
        if not busy:
            return set()
        from .isolation import ProcessProxy

        return {n for n in busy if not isinstance(n.comp, ProcessProxy)}

    # ------------------------------------------------------------------------------------------------- running
    def run(self, duration: float | None = None, progress: Callable[["Runtime", float], None] | None = None,
            progress_interval: float = 0.5) -> RunResult:
        """Start the components, run the graph for ``duration`` s (None: the graph's; the simulated clock needs one)
        or until it stops, drive the devices to their safe state and close everything; the result says how it ended.
        A Ctrl-C stops the run safely (status "interrupted"); in a program without the command line's handlers a
        Ctrl-C once the run is stopping is said and held, as under the command line (:func:`_ctrl_c_until_stopping`)."""
        here = threading.current_thread() is threading.main_thread()
        if here:
            _runs.append(self)
        try:
            with _ctrl_c_until_stopping(self._hold_ctrl_c):
                return self._run(duration, progress, progress_interval)
        finally:
            if here:
                _runs.remove(self)

    def _run(self, duration: float | None, progress: Callable[["Runtime", float], None] | None,
             progress_interval: float) -> RunResult:
        if self._ran:
            raise RuntimeError(f"graph '{self.spec.name}': this Runtime has already run and its components are "
                               f"closed; build a new Runtime for another run")
        duration = duration if duration is not None else self.spec.duration
        if self.clock == "sim" and duration is None:
            raise ValueError("the simulated clock needs a duration (graph 'duration:' or --duration)")
        self._ran = True
        wall0 = time.perf_counter()
        self._t0 = wall0
        self._t0_mono = time.monotonic()
        status = None
        error: StartupError | None = None
        startup = 0.0
        interrupted = False
        signum: int | None = None   # the signal that interrupted the run (SIGINT: Ctrl-C)
        late_signal: int | None = None
        fault_first: tuple[str, int, str] | None = None   # a fault that stopped the run before the interrupt
        # Start-up (importing torch, loading models) makes hundreds of thousands of long-lived objects. The cyclic
        # garbage collector is off while it runs (paper-sim: three full collections, ~0.25 s, were spent there)
        # and they are then frozen out of its scans, so a full collection while the graph runs (one would stall
        # every thread ~0.1 s) only looks at what the run itself allocates. Restored at the end of the run.
        gc_was_enabled, gc_frozen = gc.isenabled(), gc.get_freeze_count() == 0
        gc.disable()
        try:
            try:
                err = self._startup()
            finally:
                if gc_frozen:
                    gc.freeze()
                if gc_was_enabled:
                    gc.enable()
            if err is None and self.clock == "wall":
                err = self._start_clock()
            startup = time.perf_counter() - wall0
            if err is not None:
                status = ("startup-failed", EXIT_STARTUP, str(err))
                error = err
            elif self.clock == "sim":
                self._run_sim(duration, progress, progress_interval)
            else:
                self._run_wall(duration, progress, progress_interval)
        except KeyboardInterrupt as exc:   # Ctrl-C, or a caller's SIGTERM handler raising one with its signum
            self._late = []   # first, before any call: a second Ctrl-C is held from here on (_hold_ctrl_c)
            interrupted, fault_first = True, self._fault_reason()
            signum = getattr(exc, "signum", None) or _SIGINT
            self._stop_evt.set()
        finally:
            # the signals held while the devices are made safe and the components closed; first, before any call
            # (where a pending handler could run): a Ctrl-C from here on is held (:meth:`_hold_ctrl_c`)
            if self._late is None:
                self._late = []
            late = self._late
            stopped: list[bool] = []
            while not stopped:   # (again where a signal came before the hold was taken)
                try:
                    self._stop_held(late, stopped)
                except KeyboardInterrupt as exc:   # its handler raised as the hold was taken or given back: held
                    _held_as_it_came(late, exc)
            if late and not interrupted:
                interrupted, fault_first = True, self._fault_reason()
                late_signal = signum = late[0]
                if _stop_signals is not None and len(_stop_signals) > len(late):
                    # the command line's signals before these stopped nothing (a plugin swallowed them: the run
                    # was not interrupted): the stop's first is this one, and its exit code
                    del _stop_signals[:len(_stop_signals) - len(late)]
            if gc_frozen:
                gc.unfreeze()
        wall = time.perf_counter() - wall0
        if status is None and interrupted:
            # a fault that had already stopped the run stays its result (the operator's Ctrl-C after it, even during
            # the shutdown, must not hide why the run stopped)
            by = _signal_text(signum)
            status = ((fault_first[0], fault_first[1], fault_first[2] + f"; then interrupted ({by})")
                      if fault_first else
                      ("interrupted", EXIT_INTERRUPTED, f"interrupted ({by}): devices driven to their safe state"))
        if status is None:
            status = self._stop_reason or ("ok", EXIT_OK, f"ran {self._now:.3f} s")
            # a fault that came after a node had asked the run to stop (a step of another rate group then running)
            # found the stop's reason set: it is the run's result all the same (it was "stopped", exit 0)
            after_stop = [f for f in self.faults if f.action == "stop"]
            degraded = [f for f in self.faults if f.action == "degrade"]
            disabled = "; nodes disabled by faults: " + ", ".join(
                f"'{f.node}' ({f.kind} at t={f.time:.3f} s)" for f in degraded) if degraded else ""
            if after_stop and status[0] == "stopped":
                f = after_stop[0]
                what = f"node '{f.node}' {f.kind}" if f.node else f.kind   # (the progress callback has no node)
                status = ("fault", EXIT_FAULT, f"{what}: {f.message} (as the run stopped: {status[2]}){disabled}")
            elif degraded and status[0] in ("ok", "stopped"):
                status = ("degraded", EXIT_FAULT, status[2] + disabled)
        # a device whose safe_state() raised or hung may not be safe: never a run that ended ok (exit 0 let a script's
        # `&&` go on with a leader that may still push on a hand), and said where the message says they are safe
        unsafe = list(self._unsafe)   # (a device whose step still ran at the end may command it after its safe state)
        if unsafe and status[0] in ("ok", "stopped", "degraded"):
            status = ("fault", EXIT_FAULT, status[2])
        if status[0] in ("fault", "interrupted"):
            f = unsafe[0] if unsafe else None
            more = len({u.node for u in unsafe} - {f.node}) if f else 0
            but = (f" but node '{f.node}', which may not be in it ({f.kind}: {f.message})"
                   + (f", nor {more} other device(s)" if more else "")) if f else ""
            if status[0] == "fault":
                status = (status[0], status[1], status[2] + "; devices driven to their safe state" + but)
            elif but:
                status = (status[0], status[1], status[2] + but)
        elif status[0] == "startup-failed" and unsafe:   # (its exit code stays 4: the start-up is what failed)
            f = unsafe[0]
            more = len({u.node for u in unsafe} - {f.node})
            status = (status[0], status[1], status[2] + f"; and node '{f.node}' may not be in its safe state "
                      f"({f.kind}: {f.message})" + (f", nor {more} other device(s)" if more else ""))
        return RunResult(status=status[0], exit_code=status[1], message=status[2], sim_time=self._now,
                         wall_time=wall, clock=self.clock, nodes=self.stats(), faults=list(self.faults),
                         startup_time=startup, error=error, late_signal=late_signal,
                         signal=signum if interrupted else None)

    def _hold_ctrl_c(self, signum: int) -> bool:
        """Whether a Ctrl-C (:func:`_ctrl_c_until_stopping`) is held: once the run has reached its shutdown, noted
        among the signals held there (the run ends "interrupted")."""
        if self._late is None:
            return False
        self._late.append(signum)
        return True

    def _stop_held(self, late: list[int], stopped: list[bool]) -> None:
        """The end of every run: :meth:`_join` and :meth:`_shutdown` with SIGINT and SIGTERM held into ``late`` (see
        :func:`_signals_deferred`); ``stopped`` gets True once they are made. A signal whose handler raised as the
        hold was taken or given back comes out of here: the caller holds it too and, where the shutdown was not made
        yet, calls this again (a Ctrl-C there skipped the shutdown: no safe state, no close)."""
        with _signals_deferred(late):
            self._join()
            self._shutdown()
            stopped.append(True)

    def _fault_reason(self) -> tuple[str, int, str] | None:
        with self._lock:
            reason = self._stop_reason
        return reason if reason is not None and reason[0] == "fault" else None

    def _progress_failed(self, exc: Exception, t: float) -> None:
        """A progress callback (the caller's live view) raised: the run stops with that as its fault, and its
        result (with every device safe) is still returned."""
        msg = f"the progress callback raised {exception_line(exc)}"
        tb = traceback_text(exc)
        with self._lock:
            self.faults.append(Fault("", "progress", msg, t, "stop", tb))
            if self._stop_reason is None:
                self._stop_reason = ("fault", EXIT_FAULT, msg)
        self._stop_evt.set()

    def stats(self) -> list[NodeStats]:
        out = []
        for n in self.nodes:
            jit = None
            if n.nstarts > 10:
                k = min(n.nstarts, self.JITTER_RING)
                ts = sorted(n.starts[:k])
                errs = sorted(abs((b - a) - n.period) for a, b in zip(ts, ts[1:]))
                jit = errs[min(len(errs) - 1, int(0.99 * len(errs)))]
            # a node with fewer than two steps (a fault at t = 0) has no rate to show: 1 step / 1e-12 s read 1e12 Hz
            out.append(NodeStats(n.id, n.spec.plugin, n.rate, n.steps, n.achieved_rate(), n.overruns,
                                 n.busy / n.steps if n.steps else 0.0, n.max_step, n.faulted, jit,
                                 dict(n.results)))
        return out

    def _run_sim(self, duration: float, progress: Any, interval: float) -> None:
        end_ns = int(round(duration * 1e9))
        nodes = self.nodes
        heap = [(0, n.order) for n in nodes]
        heapq.heapify(heap)
        stop = self._stop_evt
        perf = time.perf_counter
        write = self._write
        next_progress = perf() + interval
        counter = 0
        while heap:
            t_ns, i = heap[0]
            if t_ns > end_ns:
                break
            node = nodes[i]
            if node.faulted:   # disabled after it was scheduled (a device behind a node degraded by a fault, made
                heapq.heappop(heap)   # safe then): it must not be stepped again
                continue
            t = graph_time(t_ns)
            self._now = t
            ok = True
            if node.stale:
                ok = self._check_stale(node, t)
            if ok:
                t1 = perf()
                node.acts += 1
                try:
                    out = node.step(t, node.inputs)
                    if out:
                        write(node, out, t)
                except KeyboardInterrupt:   # Ctrl-C (the main thread steps): ends the run as interrupted
                    raise
                except BaseException as exc:   # also SystemExit from a plugin: a fault of its node
                    self._fault(node, "exception", self._step_error(node, exc), t, exc=exc)
                dt = perf() - t1
                node.busy += dt
                if dt > node.max_step:
                    node.max_step = dt
            if not node.steps:
                node.first_t = t
            node.last_t = t
            node.steps += 1
            if stop.is_set():
                break
            if node.faulted:
                heapq.heappop(heap)
            else:
                heapq.heapreplace(heap, (int(round((node.steps) * 1e9 / node.rate)), i))
            counter += 1
            if progress is not None and counter & 1023 == 0:
                now = perf()
                if now >= next_progress:
                    next_progress = now + interval
                    try:
                        progress(self, t)
                    except Exception as exc:
                        self._progress_failed(exc, t)
                        break
        if not stop.is_set():  # ran out of ticks before the end (or every node degraded): the graph reached it
            self._now = duration

    def _run_wall(self, duration: float | None, progress: Any, interval: float) -> None:
        groups: dict[float, list[_Node]] = {}
        for n in self.nodes:
            groups.setdefault(n.rate, []).append(n)
        fast = max(groups) if groups else 1.0
        old_switch = sys.getswitchinterval()
        self._threads = []
        group_of: list[tuple[threading.Thread, list[_Node]]] = []
        for rate, members in sorted(groups.items(), reverse=True):
            th = threading.Thread(target=self._wall_loop, args=(members, rate), name=f"teletouch-{rate:g}Hz",
                                  daemon=True)
            self._threads.append(th)
            group_of.append((th, members))
        # the watchdog: a device whose thread has not started a step for `faults.watchdog` (at least 3 of its
        # periods) is driven to its safe state from here and faults (a step that hangs, a stalled thread); when that
        # thread waits for the step of another node at its rate, that node is at fault (see _stalled)
        wd = self.spec.faults.watchdog
        watched = [(n, max(wd, 3.0 * n.period), groups[n.rate]) for n in self.nodes if n.is_device] if wd > 0 else []
        poll = min(0.02, wd / 4.0) if watched else 0.02
        try:   # (from here on: a Ctrl-C while the threads start stops the ones started and restores the interval)
            # the fastest loop must get the GIL back within a fraction of its period (the default interval, 5 ms,
            # is half the period of a 100 Hz loop); not below 5 us, where the hand-overs themselves would dominate
            sys.setswitchinterval(min(old_switch, max(self.SWITCH_FRACTION / fast, 5e-6)))
            for th in self._threads:
                th.start()
            next_progress = time.perf_counter() + interval
            while not self._stop_evt.wait(poll):
                self._now = time.perf_counter() - self._t0
                if duration is not None and self._now >= duration:
                    self._stop_evt.set()
                    break
                for n, limit, members in watched:
                    last = n.last_start()
                    if not n.faulted and self._now - last > limit:
                        self._stalled(n, self._now - last, limit, members)
                if progress is not None and time.perf_counter() >= next_progress:
                    next_progress += interval
                    try:
                        progress(self, self._now)
                    except Exception as exc:
                        self._progress_failed(exc, self._now)
                        break
        finally:
            self._stop_evt.set()
            # the run's end: before the join, which a device's safe state on its way out may hold up to safe_timeout
            # (a run of 0.3 s was said to have "ran 0.804 s")
            ended = time.perf_counter() - self._t0
            try:
                self._safe_blocked(group_of, wd)
                self._join()
            finally:   # also when a second Ctrl-C cuts the join short (the run's shutdown joins them again)
                sys.setswitchinterval(old_switch)
            self._now = max(self._now, ended)
            if duration is not None and self._stop_reason is None and duration <= self._now < duration + 0.05:
                self._now = duration  # ended by its duration (the main thread polls every 20 ms)

    def _safe_blocked(self, group_of: list[tuple[threading.Thread, list[_Node]]], wd: float) -> None:
        """At the run's stop, before the rate groups' threads are joined (the watchdog has ended with the stop): a
        thread still inside one step (a device's own, or another node's at its rate: an estimator that hangs, an
        isolated node waiting for its process) past the watchdog's limit for its group (``faults.watchdog``, at
        least 3 of its periods; 1 s with the watchdog off), counted from that step's start, has its devices made
        safe from here, then, instead of after the joins (1 s a thread; a leader kept its 2 N on a hand for 2 s
        after a Ctrl-C). A step within its limit is waited for: no safe_state() beside a healthy slow step (the
        group makes its devices safe itself as it leaves). A device whose own step is in flight is made safe again
        when that step returns (``resafe``)."""
        pending = [(th, members, max(wd if wd > 0 else 1.0, 3.0 * members[0].period))
                   for th, members in group_of if th is not threading.current_thread()]
        give_up = time.perf_counter() + max((lim + members[0].period for _, members, lim in pending), default=0.0)
        while pending and time.perf_counter() < give_up:
            now = time.perf_counter() - self._t0
            left = []
            for th, members, limit in pending:
                if not th.is_alive():   # (ended, or never started: a Ctrl-C while the threads were being started)
                    continue
                m = next((m for m in members if m.in_step), None)
                began = None if m is None else (m.warm_began if m.warming else m.last_start())
                if began is not None and now - began > limit:
                    self._safe_many([n for n in members if n.is_device and n.state == "active"])
                else:   # within its limit, or between two steps (it sees the stop after its sleep, within a period)
                    left.append((th, members, limit))
            pending = left
            if pending:
                time.sleep(0.005)

    def _stalled(self, dev: _Node, idle: float, limit: float, members: list[_Node]) -> None:
        """The watchdog found device ``dev`` not stepped for ``idle`` s, more than its ``limit``: it is made safe and
        faults (``stall``). When its rate group's thread is blocked in a step (its own, or another node's: an
        isolated node waiting for its process, an inline node that hangs), that node is the cause: it faults first
        (``timeout``, naming its plugin: under ``stop`` its fault is the run's reason; a device whose own step
        hangs: ``stall``); then every other device at its rate (none of them is stepped while it runs) faults,
        naming it; all of them are made safe side by side (a device whose hung step holds the lock its safe state
        needs does not hold up the others' by safe_timeout); then the wait for an isolated node's step is cut short
        (``ProcessProxy.abandon_step``), so that the group's thread is free at once instead of after the step's own
        timeout (20 periods, at least 1 s)."""
        now = self._now
        blocker = next((m for m in members if m.in_step), None)
        if blocker is None:   # the thread is stalled outside any step
            self._fault(dev, "stall", f"not stepped for {idle:.3f} s (watchdog {limit:g} s): made safe", now)
            return
        from .isolation import ProcessProxy

        isolated = isinstance(blocker.comp, ProcessProxy)
        what = f"{blocker.spec.plugin}, isolated process" if isolated else blocker.spec.plugin
        blamed = not blocker.faulted
        warming = blocker.warming   # (read once: the warm-up may end meanwhile)
        act = "warm()" if warming else "step"
        began = blocker.warm_began if warming else blocker.last_start()
        todo: list[_Node] = []   # every device faulted here, made safe side by side at the end
        if blamed and blocker.is_device:   # a device whose own step hangs: its stall, as when it is alone
            todo += self._fault(blocker, "stall", f"not stepped for {now - began:.3f} s (watchdog {limit:g} s): "
                                                  f"made safe", now, safe=False)
        elif blamed:
            devices = ", ".join(f"'{m.id}'" for m in members if m.is_device)
            todo += self._fault(blocker, "timeout", f"({what}) {act} did not return within {limit:g} s "
                                                    f"(faults.watchdog; it began at t={began:.3f} s): the devices at "
                                                    f"its rate ({devices}) are not stepped while it runs", now,
                                safe=False)
        for m in members:   # (one already disabled is skipped: a device wired from it, under degrade)
            if m.is_device and not m.faulted:
                last = m.last_start()
                todo += self._fault(m, "stall", f"not stepped for {now - last:.3f} s: its rate group waits for the "
                                                f"{act} of node '{blocker.id}' ({what}), past the watchdog's "
                                                f"{limit:g} s: made safe", now, safe=False)
        self._safe_many(todo)
        if blamed and isolated:   # after the devices are safe: the group's thread, freed, must not step them first
            blocker.comp.abandon_step(f"the watchdog faulted it after {limit:g} s (faults.watchdog): the devices at "
                                      f"its rate were not stepped meanwhile")

    def _wall_loop(self, members: list[_Node], rate: float) -> None:
        _set_timer_slack(1000)
        prio = thread_priority(self.spec.realtime_priority, rate, [n.spec.priority for n in members])
        if prio:
            try:
                os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(prio))
            except (OSError, AttributeError) as exc:
                self.log(f"priority {prio}: cannot use SCHED_FIFO ({exc}); running with normal "
                         f"scheduling (grant CAP_SYS_NICE or an rtprio limit in /etc/security/limits.conf)")
        period = 1.0 / rate
        spin = min(2e-4, period * 0.2)
        perf = time.perf_counter
        sleep = time.sleep
        t0 = self._t0
        stop = self._stop_evt
        max_over = self.spec.faults.max_overruns
        ring = self.JITTER_RING
        for n in members:
            n.starts = [0.0] * ring
        try:
            self._wall_steps(members, period, spin, perf, sleep, t0, stop, max_over, ring)
        except BaseException as exc:   # the loop itself failed (not a step: those are caught per node)
            self._group_died(members, exc)
        finally:
            # leaving (stop, fault elsewhere): this group's devices are made safe at once by their own thread,
            # not after the other threads are joined (the shutdown calls safe_state() again only for a device
            # whose call raised or that was stepped after it: see _still_safe)
            for node in members:
                if node.is_device and node.state == "active":
                    self._safe(node)

    def _wall_steps(self, members: list[_Node], period: float, spin: float, perf: Any, sleep: Any, t0: float,
                    stop: _StopEvent, max_over: int, ring: int) -> None:
        k = 0
        late = 0   # consecutive late cycles of the group
        lock = self._lock
        warmers = [n for n in members if n.warm is not None] if period >= 5 * self.WARM_LEAD else []
        cycle = 0.0   # the members' steps' time in the latest cycle (s)
        while not stop.is_set():
            deadline = t0 + k * period
            if warmers:
                rem = deadline - self.WARM_LEAD - perf()
                if rem > 0:   # (a group running late steps at once)
                    sleep(rem)
                    self._warm(warmers, period, cycle, stop)
            rem = deadline - perf()
            if rem > spin:
                sleep(rem - spin)
            while perf() < deadline:
                pass
            worst: _Node | None = None   # the member whose step took longest in this cycle
            worst_dt = -1.0
            cycle = 0.0
            for node in members:
                if node.faulted or stop.is_set():
                    continue
                t1 = perf()
                t = t1 - t0
                node.starts[node.nstarts % ring] = t
                node.nstarts += 1
                if node.stale and not self._check_stale(node, t):
                    continue
                node.in_step = True   # before `acts`: a safe call reads `acts`, then `in_step` (see _safe_begin)
                node.acts += 1
                try:
                    out = node.step(t, node.inputs)
                    if out and not node.faulted:   # faulted while it ran (the watchdog): its outputs are dropped
                        self._write(node, out, t, lock)
                except BaseException as exc:   # also SystemExit or KeyboardInterrupt raised by a plugin in this
                    node.in_step = False       # thread (a signal reaches the main one)
                    if not (node.faulted and getattr(exc, "abandoned", False)):   # the watchdog cut it short: it
                        self._fault(node, "exception", self._step_error(node, exc), t,   # has reported its fault
                                    exc=exc)
                node.in_step = False
                if not node.steps:
                    node.first_t = t
                node.last_t = t
                node.steps += 1
                dt = perf() - t1
                node.busy += dt
                cycle += dt
                if dt > node.max_step:
                    node.max_step = dt
                if dt > worst_dt:
                    worst, worst_dt = node, dt
                if node.is_device and (node.faulted or node.resafe):   # faulted, or a safe call began, while its
                    node.resafe = False   # step ran (the watchdog, a stop): that step may have commanded it after
                    self._safe(node)      # its safe_state(): made safe again now
            k += 1
            now = perf()
            if now > t0 + k * period:
                missed = int((now - (t0 + k * period)) / period) + 1
                k += missed
                late += 1
                for node in members:   # every member missed these ticks; one disabled by a fault (not stepped
                    if not node.faulted:   # again) has no ticks to miss
                        node.overruns += missed
                        node.consec_overruns = late
                # the fault goes to the member that made the group late, not to every member: a healthy device that
                # shares its rate with a slow estimator goes on under `degrade`, and `stop` names the slow node
                if max_over and late > max_over and worst is not None and not worst.faulted:
                    share = (f", the longest of the {len(members)} nodes at this rate" if len(members) > 1 else "")
                    self._fault(worst, "overrun", f"missed its {period * 1e3:.3f} ms period {late} times in a row "
                                                  f"(its last step took {worst_dt * 1e3:.3f} ms{share})", now - t0)
                    late = 0
            else:
                late = 0
                for node in members:
                    node.consec_overruns = 0
            if all(n.faulted for n in members):
                return

    def _warm(self, warmers: list[_Node], period: float, cycle: float, stop: _StopEvent) -> None:
        """Each node's Component.warm() before its step (:attr:`WARM_LEAD`), where its latest warm-up and the group's
        latest cycle of steps (``cycle``, s) take at most half the ``period`` (a warm-up that would make the group
        overrun is left out: the overrun would be blamed on a step that fits alone). An exception faults the node as
        one in its step does; the watchdog sees the warm-up as in its step (``in_step``) and names it (``warming``).
        A warm-up left out is tried again after a second's worth of cycles: one slow warm-up (a loaded machine's
        pause) must not leave the node cold for the rest of the run."""
        perf = time.perf_counter
        retry = max(1, round(1.0 / period))
        for node in warmers:
            if node.faulted or stop.is_set():
                continue
            if node.warm_dt + cycle > 0.5 * period:
                node.warm_skips += 1
                if node.warm_skips < retry:
                    continue
            node.warm_skips = 0
            t1 = perf()
            node.warm_began = t1 - self._t0
            node.warming = True
            node.in_step = True
            try:
                node.warm()
            except BaseException as exc:   # (as a step's: also SystemExit or KeyboardInterrupt raised in it)
                node.in_step = False
                if not (node.faulted and getattr(exc, "abandoned", False)):   # the watchdog cut it short: it has
                    self._fault(node, "exception", f"warm(): {self._step_error(node, exc)}",   # said so
                                node.warm_began, exc=exc)
            node.in_step = False
            node.warming = False
            node.warm_dt = perf() - t1

    def _group_died(self, members: list[_Node], exc: BaseException) -> None:
        """A rate group's loop ended by an error outside the steps (in a tap or a fault handler): none of its nodes
        would be stepped again. That is a fault that stops the run, never a silent end of the thread."""
        ids = ", ".join(f"'{n.id}'" for n in members)
        msg = f"the thread of {ids} ended with {exception_line(exc)}"
        tb = traceback_text(exc)
        with self._lock:
            self.faults.append(Fault(members[0].id, "exception", msg, self._now, "stop", tb))
            if self._stop_reason is None:
                self._stop_reason = ("fault", EXIT_FAULT, f"node {msg}" if len(members) == 1 else msg)
        for n in members:
            n.faulted = True
        self._stop_evt.set()

    def _join(self) -> None:
        for th in getattr(self, "_threads", []):
            if th is not threading.current_thread():
                try:
                    th.join(timeout=1.0)
                except RuntimeError:   # never started: a Ctrl-C while the threads were being started (its
                    pass               # KeyboardInterrupt, not this, is what ends the run)


def _returned_within(call: Callable[[], None], name: str, timeout: float) -> bool:
    """Run ``call`` (which catches its own errors) in a daemon thread ``name``, waited for at most ``timeout`` s:
    whether it returned; one that did not is left running."""
    th = threading.Thread(target=call, name=name, daemon=True)
    th.start()
    th.join(timeout)
    return not th.is_alive()


def _signal_text(signum: int | None) -> str:
    """How a person knows the signal that interrupted a run: Ctrl-C for SIGINT (and for a KeyboardInterrupt that
    names none), else its name (SIGTERM)."""
    import signal

    if signum is None or signum == signal.SIGINT:
        return "Ctrl-C"
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


#: the signals of the stop under way, first first, where the process keeps them (the command line's
#: :func:`teletouch.cli._interrupts` block sets it); None: none is kept. A signal :func:`_signals_deferred` holds is
#: added too, so that one landing in the runtime's shutdown of a run that was ending counts as the stop's first: a
#: later one is held as well (not raised in the command's own code after the run), and the exit code is the first's
_stop_signals: list[int] | None = None

_SIGINT = 2   # signal.SIGINT on every platform Python runs on (signal is imported where it is used)

#: the runs under way in the main thread (where signal handlers run), innermost last: see :func:`run_stopping`
_runs: list["Runtime"] = []


def run_stopping() -> bool | None:
    """Whether the innermost run under way in the main thread is stopping: it has reached its shutdown (or a
    Ctrl-C has stopped it), where it holds signals itself; None where no run is under way. For a signal handler of
    the process (the command line's) to tell a run that a signal may still stop from one already stopping."""
    return (_runs[-1]._late is not None) if _runs else None


def _say_held(signum: int) -> None:
    """Say on stderr, from a signal handler, that the signal ``signum`` is held while the stop under way finishes."""
    _say_now(f"teletouch: {_signal_text(signum)}: already stopping safely, please wait\n")


def _say_now(text: str) -> None:
    """``text`` on stderr from a signal handler: straight to the file descriptor (the handler may have cut into a
    write to ``sys.stderr``, whose buffer refuses a reentrant one), through ``sys.stderr`` where it has none."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):   # (io.UnsupportedOperation: a test's capture)
        print(text, end="", file=sys.stderr)
        return
    with contextlib.suppress(OSError):
        os.write(fd, text.encode(errors="replace"))


@contextlib.contextmanager
def _ctrl_c_until_stopping(hold: Callable[[int], bool]) -> Iterator[None]:
    """A run in a program without the command line's handlers (a script, a notebook, a test: SIGINT is Python's own
    handler, which raises KeyboardInterrupt on every Ctrl-C): for the run, a Ctrl-C raises as before until the run
    holds it (``hold(signum)``: its shutdown under way, or over), and is said and held from then on, as under the
    command line.
    With Python's handler a second Ctrl-C that landed as the shutdown's hold was taken (or while a first one that
    landed there was being held) cut the shutdown short: no safe state, no close. Python's handler is given back
    after, unless something else replaced the run's meanwhile. Elsewhere (the command line's block, a caller's own
    handler, a run inside a run, another thread) nothing is changed."""
    import signal

    if (_stop_signals is not None or threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return

    def _handler(signum: int, frame: Any) -> None:
        if not hold(signum):   # (also a Ctrl-C after one that something swallowed: the run still stops for it)
            raise KeyboardInterrupt
        _say_held(signum)

    try:
        signal.signal(signal.SIGINT, _handler)
        yield
    finally:   # (a Ctrl-C pending as it is given back runs _handler first: the run is over, so it is held, not raised)
        if signal.getsignal(signal.SIGINT) is _handler:
            signal.signal(signal.SIGINT, signal.default_int_handler)


def _held_as_it_came(late: list[int], exc: KeyboardInterrupt) -> None:
    """The signal whose handler raised ``exc`` as the runtime's shutdown hold was taken or given back: held as one
    inside it is (added to ``late`` and said; the command line's handler, which raised it as a stop's first, has it in
    :data:`_stop_signals` already)."""
    import signal

    signum = getattr(exc, "signum", None) or signal.SIGINT   # (Python's own Ctrl-C names none)
    late.append(signum)
    _say_held(signum)


@contextlib.contextmanager
def _signals_deferred(late: list[int] | None = None) -> Iterator[list[int]]:
    """SIGINT and SIGTERM that arrive inside the block are recorded in the yielded list (``late``, a new one where
    None) instead of raising (a second Ctrl-C must not cut the safe-state sequence short), said on stderr ("already
    stopping safely, please wait") and added to :data:`_stop_signals` where the process keeps them. A signal whose
    handler raises as the handlers are taken or given back leaves none of them taken (SIGINT is given back last, also
    where SIGTERM's handler raised as it was given back). Only the main thread can set signal handlers: elsewhere the
    block runs as it is."""
    import signal

    late = [] if late is None else late
    if threading.current_thread() is not threading.main_thread():
        yield late
        return
    stop = _stop_signals

    def _hold(signum: int, _frame: Any) -> None:
        late.append(signum)
        if stop is not None:
            stop.append(signum)
        _say_held(signum)

    old: dict[int, Any] = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            prev = signal.getsignal(sig)
            if prev is None or prev == signal.SIG_IGN:   # installed from outside Python, or ignored (a job
                continue                                  # started with `&`): left alone
            old[sig] = prev
            signal.signal(sig, _hold)
        yield late
    finally:
        try:
            if signal.SIGTERM in old:
                signal.signal(signal.SIGTERM, old[signal.SIGTERM])
        finally:   # SIGINT last: each handler given back may raise at once (the command line's, for a stop's first)
            if signal.SIGINT in old:
                signal.signal(signal.SIGINT, old[signal.SIGINT])


def feeders(spec: GraphSpec) -> dict[str, list[str]]:
    """Each node's id -> the ids of the nodes whose outputs reach it through the graph's wiring, directly or through
    other nodes (not itself, also where a feedback edge leads back to it), in data-flow order."""
    order = [n.id for n in spec.order()]
    direct = {n.id: {w.node for w in n.inputs.values()} for n in spec.nodes}
    out: dict[str, list[str]] = {}
    for nid in order:
        seen: set[str] = set()
        todo = list(direct.get(nid, ()))
        while todo:
            f = todo.pop()
            if f not in seen:
                seen.add(f)
                todo.extend(direct.get(f, ()))
        seen.discard(nid)
        out[nid] = [f for f in order if f in seen]
    return out


def graph_time(t_ns: int) -> float:
    """A tick of the simulated clock (integer ns) in seconds: the nearest double (``t_ns / 1e9``: 30 ms is 0.03, where
    ``t_ns * 1e-9`` gives 0.030000000000000002). The one conversion of the runtime and of
    :class:`~teletouch.testing.Harness`, so that a component sees the same times in its test as in a graph."""
    return t_ns / 1e9


def thread_priority(realtime_priority: int, rate: float, node_priorities: list[int | None]) -> int:
    """SCHED_FIFO priority of a rate group's thread (0: normal scheduling): the highest priority a member node
    asks for; without one, ``realtime_priority`` for groups at >= 200 Hz."""
    asked = [p for p in node_priorities if p is not None]
    if asked:
        return max(asked)
    return realtime_priority if rate >= 200 else 0


def run_graph(spec: GraphSpec, *, duration: float | None = None, clock: str | None = None,
              taps: list[Tap] | None = None, **kw: Any) -> RunResult:
    """Convenience: build and run a validated graph."""
    rt = Runtime(spec, clock=clock)
    for tap in taps or []:
        rt.add_tap(tap)
    return rt.run(duration, **kw)
