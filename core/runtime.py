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

from .component import Component, Context, Device, Inputs, Sample, _Slot
from .errors import ComponentFault, exception_line
from .graph import GraphSpec

EXIT_OK = 0
EXIT_INVALID = 1
EXIT_USAGE = 2
EXIT_FAULT = 3
EXIT_STARTUP = 4
EXIT_INTERRUPTED = 130

Tap = Callable[[str, float, dict], None]


@dataclass
class Fault:
    node: str
    kind: str  # exception | overrun | stale | startup | shutdown
    message: str
    time: float
    action: str  # stop | degrade | logged

    def line(self) -> str:
        return f"node '{self.node}' {self.kind} at t={self.time:.3f} s: {self.message}"


@dataclass
class NodeStats:
    id: str
    plugin: str
    rate: float
    steps: int
    achieved_rate: float
    overruns: int
    mean_step_s: float
    max_step_s: float
    faulted: bool
    period_jitter_p99_s: float | None = None

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
    faults: list[Fault] = field(default_factory=list)
    startup_time: float = 0.0   # s of wall_time spent starting up (loading models, opening devices)

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
                "faults": [f.__dict__ for f in self.faults]}

    def summary(self) -> str:
        lines = [f"{self.status}: {self.message}",
                 f"clock {self.clock}: {self.sim_time:.3f} s graph time in {self.wall_time - self.startup_time:.3f} s "
                 f"wall after {self.startup_time:.3f} s start-up ({self.run_realtime_factor:.1f}x real time)"]
        lines.append(f"  {'node':<16}{'plugin':<20}{'rate Hz':>9}{'achieved':>10}{'steps':>9}{'overruns':>9}"
                     f"{'mean ms':>9}{'max ms':>9}")
        for n in self.nodes:
            lines.append(f"  {n.id:<16}{n.plugin:<20}{n.rate:>9.1f}{n.achieved_rate:>10.1f}{n.steps:>9d}"
                         f"{n.overruns:>9d}{n.mean_step_s * 1e3:>9.3f}{n.max_step_s * 1e3:>9.3f}"
                         + ("  FAULTED" if n.faulted else ""))
        for f in self.faults:
            lines.append(f"  fault: {f.line()} -> {f.action}")
        return "\n".join(lines)


class _Node:
    __slots__ = ("id", "spec", "comp", "step", "rate", "period", "inputs", "out", "stale", "policy", "faulted",
                 "steps", "overruns", "consec_overruns", "busy", "max_step", "is_device", "order", "starts",
                 "nstarts", "last_dt", "state", "hung")

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

    def __init__(self, spec: GraphSpec, registry: Any = None, *, clock: str | None = None,
                 log: Callable[[str], None] | None = None):
        self.spec = spec
        self.clock = clock or spec.clock
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self.taps: list[Tap] = []
        self.faults: list[Fault] = []
        self._now = 0.0
        self._stop_evt = threading.Event()
        self._stop_reason: tuple[str, int, str] | None = None  # (status, exit code, message)
        self._lock = threading.Lock()
        self._t0 = 0.0
        self._t0_mono = 0.0
        self.nodes: list[_Node] = []
        self._build()

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
                          rate=float(n.rate))
            params = n.params_obj if n.params_obj is not None else n.cls.Params.model_validate(n.params)
            if n.isolate == "process" and self.clock == "wall":
                from .isolation import ProcessProxy

                comp = ProcessProxy(n.cls, params, node_id=n.id, ctx=ctx, t0_perf=0.0, t0_mono=0.0,
                                    step_timeout=max(1.0, 20.0 / float(n.rate)),
                                    priority=thread_priority(self.spec.realtime_priority, n.rate, [n.priority]))
            else:
                comp = n.cls(params, node_id=n.id, ctx=ctx)
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
        """Call ``tap(node_id, t, outputs)`` after every step that produced outputs (recording, experiments).
        In wall-clock mode it is called from the node's thread: it must be quick and thread-safe."""
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
    def _fault(self, node: _Node, kind: str, message: str, t: float) -> None:
        action = node.policy
        with self._lock:
            self.faults.append(Fault(node.id, kind, message, t, action))
            if action == "stop" and self._stop_reason is None:
                self._stop_reason = ("fault", EXIT_FAULT, f"node '{node.id}' {kind}: {message}")
        node.faulted = True
        if node.is_device:
            self._safe(node)
        if action == "stop":
            self._stop_evt.set()
        else:
            self.log(f"[{node.id}] {kind}: {message} -> node disabled (degrade)")
            # a device commanded by the disabled node would keep its last command: it goes to its safe state and
            # is disabled too (nodes further down, e.g. a controller behind a dead estimator, handle their own
            # stale inputs)
            for other in self.nodes:
                if other.is_device and not other.faulted:
                    ports = [p for p, w in other.spec.inputs.items() if w.node == node.id]
                    if ports:
                        self._fault(other, "upstream", f"input '{ports[0]}' comes from node '{node.id}', which "
                                                       f"was disabled by a fault", t)

    def _safe(self, node: _Node) -> None:
        """``safe_state()``, bounded: it runs in a helper thread and is waited for at most ``faults.safe_timeout``.
        A driver whose step hangs inside a hardware call usually holds the lock its safe_state() needs; unbounded,
        that one call would block the caller (the watchdog's main thread, a rate group's exit, the shutdown) and
        with it every other device's safe state and the end of the run. Such a node is left behind (``hung``: no
        further lifecycle calls) and reported."""
        if node.hung:
            return
        error: list[BaseException] = []

        def call() -> None:
            try:
                node.comp.safe_state()
            except Exception as exc:
                error.append(exc)

        th = threading.Thread(target=call, name=f"teletouch-safe-{node.id}", daemon=True)
        th.start()
        th.join(self.spec.faults.safe_timeout)
        if th.is_alive():
            node.hung = True
            msg = (f"safe_state() did not return within {self.spec.faults.safe_timeout:g} s (faults.safe_timeout; "
                   f"a call into its hardware hangs?): left behind, the other devices were made safe")
            with self._lock:
                self.faults.append(Fault(node.id, "hung", msg, self._now, "logged"))
            self.log(f"[{node.id}] {msg}")
        elif error:
            with self._lock:
                self.faults.append(Fault(node.id, "shutdown", f"safe_state() raised {exception_line(error[0])}",
                                         self._now, "logged"))

    def _check_stale(self, node: _Node, t: float) -> bool:
        if t < self.spec.faults.startup_grace:
            return True
        for port, slot, max_age, src in node.stale:
            s = slot.sample
            if s is None:
                self._fault(node, "stale", f"input '{port}' from {src}: nothing received after "
                                           f"{t:.3f} s (limit {max_age:g} s)", t)
                return False
            if not s.is_fresh(t, max_age):
                age = t - s.stamp
                what = f"{age:.3f} s old" if age > 0 else (f"stamped {-age:.3f} s ahead of the graph clock"
                                                           if age < 0 else f"stamped {s.stamp!r}")
                self._fault(node, "stale", f"input '{port}' from {src} is {what} (limit {max_age:g} s)", t)
                return False
        return True

    def _write(self, node: _Node, out: Any, t: float) -> None:
        slots = node.out
        for name, v in out.items():
            slot = slots.get(name)
            if slot is None:
                raise ComponentFault(f"step() returned unknown output '{name}'; outputs: {', '.join(slots)}")
            if v.__class__ is Sample:
                if not _finite_stamp(v.stamp):
                    raise ComponentFault(f"step() returned output '{name}' stamped {v.stamp!r}: a stamp must be a "
                                         f"finite graph time in seconds")
                slot.sample = v
            else:
                slot.sample = Sample(v, t)
        for tap in self.taps:
            tap(node.id, t, out)

    # ------------------------------------------------------------------------------------------------- lifecycle
    def _startup(self) -> str | None:
        for node in self.nodes:
            try:
                node.comp.configure()
                node.state = "inactive"
            except Exception as exc:
                return f"node '{node.id}' ({node.spec.plugin}) failed to configure: {exception_line(exc)}"
        for node in self.nodes:
            try:
                node.comp.activate()
                node.state = "active"
            except Exception as exc:
                return f"node '{node.id}' ({node.spec.plugin}) failed to activate: {exception_line(exc)}"
        return None

    def _start_clock(self) -> str | None:
        """Wall clock: graph time 0 is the end of start-up (loading models, opening devices, spawning processes)."""
        from .isolation import ProcessProxy

        self._t0 = time.perf_counter()
        self._t0_mono = time.monotonic()
        for node in self.nodes:
            if isinstance(node.comp, ProcessProxy):
                try:
                    node.comp.set_origin(self._t0, self._t0_mono)
                except Exception as exc:
                    return f"node '{node.id}' ({node.spec.plugin}) failed to start: {exception_line(exc)}"
        return None

    def _shutdown(self) -> None:
        for node in self.nodes:
            if node.is_device and node.state != "unconfigured":
                self._safe(node)
        for node in reversed(self.nodes):
            if node.hung:   # its safe_state() hung (holding the driver's lock): deactivate/close would hang too
                self.faults.append(Fault(node.id, "shutdown", "deactivate() and close() skipped: its safe_state() "
                                                              "hung", self._now, "logged"))
                node.state = "finalized"
                continue
            if node.state == "active":
                try:
                    node.comp.deactivate()
                except Exception as exc:
                    self.faults.append(Fault(node.id, "shutdown", f"deactivate() raised {exception_line(exc)}",
                                             self._now, "logged"))
                node.state = "inactive"
        for node in reversed(self.nodes):
            if node.hung:
                continue
            try:
                node.comp.close()
            except Exception as exc:
                self.faults.append(Fault(node.id, "shutdown", f"close() raised {exception_line(exc)}", self._now,
                                         "logged"))
            node.state = "finalized"

    # ------------------------------------------------------------------------------------------------- running
    def run(self, duration: float | None = None, progress: Callable[["Runtime", float], None] | None = None,
            progress_interval: float = 0.5) -> RunResult:
        duration = duration if duration is not None else self.spec.duration
        if self.clock == "sim" and duration is None:
            raise ValueError("the simulated clock needs a duration (graph 'duration:' or --duration)")
        wall0 = time.perf_counter()
        self._t0 = wall0
        self._t0_mono = time.monotonic()
        status = None
        startup = 0.0
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
                status = ("startup-failed", EXIT_STARTUP, err)
                self.faults.append(Fault("", "startup", err, 0.0, "stop"))
            elif self.clock == "sim":
                self._run_sim(duration, progress, progress_interval)
            else:
                self._run_wall(duration, progress, progress_interval)
        except KeyboardInterrupt:
            status = ("interrupted", EXIT_INTERRUPTED,
                      "interrupted (Ctrl-C or SIGTERM): devices driven to their safe state")
            self._stop_evt.set()
        finally:
            with _signals_deferred() as late:
                self._join()
                self._shutdown()
            if late and status is None:
                status = ("interrupted", EXIT_INTERRUPTED,
                          "interrupted (Ctrl-C or SIGTERM): devices driven to their safe state")
            if gc_frozen:
                gc.unfreeze()
        wall = time.perf_counter() - wall0
        if status is None:
            status = self._stop_reason or ("ok", EXIT_OK, f"ran {self._now:.3f} s")
            degraded = [f for f in self.faults if f.action == "degrade"]
            if degraded and status[0] in ("ok", "stopped"):
                status = ("degraded", EXIT_FAULT, status[2] + "; nodes disabled by faults: " + ", ".join(
                    f"'{f.node}' ({f.kind} at t={f.time:.3f} s)" for f in degraded))
        if status[0] == "fault":
            status = (status[0], status[1], status[2] + "; devices driven to their safe state")
        return RunResult(status=status[0], exit_code=status[1], message=status[2], sim_time=self._now,
                         wall_time=wall, clock=self.clock, nodes=self.stats(), faults=list(self.faults),
                         startup_time=startup)

    def stats(self) -> list[NodeStats]:
        out = []
        elapsed = max(self._now, 1e-12)
        for n in self.nodes:
            jit = None
            if n.nstarts > 10:
                k = min(n.nstarts, self.JITTER_RING)
                ts = sorted(n.starts[:k])
                errs = sorted(abs((b - a) - n.period) for a, b in zip(ts, ts[1:]))
                jit = errs[min(len(errs) - 1, int(0.99 * len(errs)))]
            out.append(NodeStats(n.id, n.spec.plugin, n.rate, n.steps, n.steps / elapsed, n.overruns,
                                 n.busy / n.steps if n.steps else 0.0, n.max_step, n.faulted, jit))
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
            t = t_ns * 1e-9
            self._now = t
            ok = True
            if node.stale:
                ok = self._check_stale(node, t)
            if ok:
                t1 = perf()
                try:
                    out = node.step(t, node.inputs)
                    if out:
                        write(node, out, t)
                except Exception as exc:
                    self._fault(node, "exception", exception_line(exc), t)
                dt = perf() - t1
                node.busy += dt
                if dt > node.max_step:
                    node.max_step = dt
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
                    progress(self, t)
        if not stop.is_set():  # ran out of ticks before the end (or every node degraded): the graph reached it
            self._now = duration

    def _run_wall(self, duration: float | None, progress: Any, interval: float) -> None:
        groups: dict[float, list[_Node]] = {}
        for n in self.nodes:
            groups.setdefault(n.rate, []).append(n)
        fast = max(groups) if groups else 1.0
        old_switch = sys.getswitchinterval()
        # the fastest loop must get the GIL back within a fraction of its period (the default interval, 5 ms, is
        # half the period of a 100 Hz loop)
        sys.setswitchinterval(min(old_switch, 0.1 / fast))
        self._threads = []
        for rate, members in sorted(groups.items(), reverse=True):
            th = threading.Thread(target=self._wall_loop, args=(members, rate), name=f"teletouch-{rate:g}Hz",
                                  daemon=True)
            self._threads.append(th)
        for th in self._threads:
            th.start()
        # the watchdog: a device whose thread has not started a step for `faults.watchdog` (at least 3 of its
        # periods) is driven to its safe state from here and faults (a step that hangs, a stalled thread)
        wd = self.spec.faults.watchdog
        watched = [(n, max(wd, 3.0 * n.period)) for n in self.nodes if n.is_device] if wd > 0 else []
        poll = min(0.02, wd / 4.0) if watched else 0.02
        try:
            next_progress = time.perf_counter() + interval
            while not self._stop_evt.wait(poll):
                self._now = time.perf_counter() - self._t0
                if duration is not None and self._now >= duration:
                    self._stop_evt.set()
                    break
                for n, limit in watched:
                    last = n.starts[(n.nstarts - 1) % self.JITTER_RING] if n.nstarts else 0.0
                    if not n.faulted and self._now - last > limit:
                        self._fault(n, "stall", f"not stepped for {self._now - last:.3f} s (watchdog "
                                                f"{limit:g} s): made safe", self._now)
                if progress is not None and time.perf_counter() >= next_progress:
                    next_progress += interval
                    progress(self, self._now)
        finally:
            self._stop_evt.set()
            self._join()
            sys.setswitchinterval(old_switch)
            self._now = time.perf_counter() - self._t0
            if duration is not None and self._stop_reason is None and duration <= self._now < duration + 0.05:
                self._now = duration  # ended by its duration (the main thread polls every 20 ms)

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
        finally:
            # leaving (stop, fault elsewhere): this group's devices are made safe at once by their own thread,
            # not after the other threads are joined (the runtime's shutdown makes them safe once more)
            for node in members:
                if node.is_device and node.state == "active":
                    self._safe(node)

    def _wall_steps(self, members: list[_Node], period: float, spin: float, perf: Any, sleep: Any, t0: float,
                    stop: threading.Event, max_over: int, ring: int) -> None:
        k = 0
        while not stop.is_set():
            deadline = t0 + k * period
            rem = deadline - perf()
            if rem > spin:
                sleep(rem - spin)
            while perf() < deadline:
                pass
            for node in members:
                if node.faulted or stop.is_set():
                    continue
                t1 = perf()
                t = t1 - t0
                node.starts[node.nstarts % ring] = t
                node.nstarts += 1
                if node.stale and not self._check_stale(node, t):
                    continue
                try:
                    out = node.step(t, node.inputs)
                    if out:
                        self._write(node, out, t)
                except Exception as exc:
                    self._fault(node, "exception", exception_line(exc), t)
                node.steps += 1
                dt = perf() - t1
                node.busy += dt
                if dt > node.max_step:
                    node.max_step = dt
            k += 1
            now = perf()
            if now > t0 + k * period:
                missed = int((now - (t0 + k * period)) / period) + 1
                k += missed
                for node in members:
                    node.overruns += missed
                    node.consec_overruns += 1
                    if max_over and node.consec_overruns > max_over and not node.faulted:
                        self._fault(node, "overrun", f"missed its {period * 1e3:.3f} ms period "
                                                     f"{node.consec_overruns} times in a row "
                                                     f"(last step {node.max_step * 1e3:.3f} ms max)", now - t0)
            else:
                for node in members:
                    node.consec_overruns = 0
            if all(n.faulted for n in members):
                return

    def _join(self) -> None:
        for th in getattr(self, "_threads", []):
            if th is not threading.current_thread():
                th.join(timeout=1.0)


@contextlib.contextmanager
def _signals_deferred() -> Iterator[list[int]]:
    """SIGINT and SIGTERM that arrive inside the block are recorded in the yielded list instead of raising (a second
    Ctrl-C must not cut the safe-state sequence short). Only the main thread can set signal handlers: elsewhere the
    block runs as it is."""
    import signal

    late: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield late
        return
    old: dict[int, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        prev = signal.getsignal(sig)
        if prev is None:            # installed from outside Python: left alone
            continue
        old[sig] = prev
        signal.signal(sig, lambda s, _frame: late.append(s))
    try:
        yield late
    finally:
        for sig, prev in old.items():
            signal.signal(sig, prev)


def _finite_stamp(stamp: Any) -> bool:
    try:
        return math.isfinite(stamp)
    except TypeError:
        return False


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
