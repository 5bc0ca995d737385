"""Fault injection into a running graph (tests/test_safety_main_job*.py).

The runtime steps a node through ``_Node.step``, which it binds to ``component.step`` when it builds the graph
(core/runtime.py, ``_Node.__init__``): replacing ``component.step`` after the build changes nothing. The injector
wraps ``_Node.step`` of every node, so the real components run until the fault and the runtime's own fault handling
(the exception path, the output checks against the ports, the staleness checks, the safe states) is what is tested.

One warm-up, many faults: the graph runs (simulated clock, deterministic) up to the fault time once; there the
process forks once per case (sequentially; the parent waits for each child). Each child switches its case on and
runs the rest of the graph with the fault; the parent goes on as the fault-free baseline. So every case starts from
the very same state, and the shared warm-up is paid once.

Fault kinds (from the fault time on, for every step of the node):

- ``raise``: step() raises RuntimeError; ``exit``: SystemExit; ``hardware``: HardwareError (a lost device);
- ``nan``: the real step runs and every float output is replaced by NaN (arrays filled with NaN);
- ``stale``: the real step runs (a device still acts) and its outputs are dropped: consumers see them go stale;
- ``type``: the real step runs and its first output port gets a str (the runtime checks outputs against ports).

Observed (in the child): every step of the leader (the command at its input, the force it rendered after the
step), every step of the follower (its measured opening and grip force), every safe_state() call of every device
(graph time; the leader's rendered force after it), the run's result.
"""

from __future__ import annotations

import math
import os
import pickle
import select
import signal
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from teletouch import Device, HardwareError, Sample

KINDS = ("raise", "exit", "hardware", "nan", "stale", "type")


@dataclass(frozen=True)
class Case:
    node: str
    kind: str
    policy: str = "stop"   # stop | degrade: every node's on_fault in this case

    @property
    def id(self) -> str:
        return f"{self.node}-{self.kind}" + ("" if self.policy == "stop" else f"-{self.policy}")


def nan_like(v: Any) -> Any:
    """``v`` with every float replaced by NaN (a Sample keeps its stamp); other values as they are."""
    if isinstance(v, Sample):
        return Sample(nan_like(v.value), v.stamp)
    if isinstance(v, (bool, np.bool_)):
        return v
    if isinstance(v, (float, np.floating)):
        return math.nan
    if isinstance(v, np.ndarray) and v.dtype.kind == "f":
        return np.full_like(v, np.nan)
    return v


@dataclass
class Observed:
    """What a child saw after the fault (plain data: it crosses the pipe)."""

    case: Case | None
    t_fault: float
    x_fault: float = math.nan          # follower opening (m) when the fault began
    g_fault: float = math.nan          # force the leader rendered (N) when the fault began
    contact_fault: bool = False        # the fingers touched the object then
    leader: list[tuple[float, float, float | None, bool]] = field(default_factory=list)
    #   (t, rendered gripper force after the step, command at its input (None: none), step raised)
    follower: list[tuple[float, float, float]] = field(default_factory=list)   # (t, opening, contact force)
    safe_calls: list[tuple[str, float, float | None]] = field(default_factory=list)
    #   (device, graph time, the leader's rendered force after the call: None for the follower)
    status: str = ""
    exit_code: int = -1
    message: str = ""
    faults: list[dict[str, Any]] = field(default_factory=list)
    end_time: float = math.nan
    leader_end: dict[str, Any] = field(default_factory=dict)    # leader status() after the run
    follower_end: dict[str, Any] = field(default_factory=dict)  # follower status() after the run
    controller_end: dict[str, Any] = field(default_factory=dict)
    error: str | None = None           # the child failed outside the graph (a bug of the harness)
    wall_s: float = 0.0


class Injector:
    """Wraps every node of ``rt`` (a built, not yet run, Runtime); :meth:`run` returns {case id: Observed} and the
    baseline (the parent's own fault-free run, observed the same way)."""

    def __init__(self, rt: Any, t_fault: float, cases: list[Case], *, leader: str = "leader",
                 follower: str = "gripper", timeout: float = 120.0):
        self.rt = rt
        self.t_fault = t_fault
        self.cases = list(cases)
        self.leader_id, self.follower_id = leader, follower
        self.timeout = timeout
        self.case: Case | None = None
        self.child = False
        self.forked = False
        self.results: dict[str, Observed] = {}
        self.obs = Observed(None, t_fault)
        self._wfd: int | None = None
        self._w0 = 0.0
        for node in rt.nodes:
            node.step = self._wrap(node, node.step)
            if isinstance(node.comp, Device):
                node.comp.safe_state = self._spy(node.id, node.comp.safe_state)

    # ----------------------------------------------------------------------------------------- wrapping
    def _active(self, node_id: str, t: float) -> str | None:
        c = self.case
        return c.kind if c is not None and c.node == node_id and t >= self.t_fault else None

    def _wrap(self, node: Any, real: Callable[[float, Any], Any]) -> Callable[[float, Any], Any]:
        nid = node.id
        ports = list(node.spec.cls.outputs)
        comp = node.comp

        def step(t: float, inputs: Any) -> Any:
            if not self.forked and t >= self.t_fault:
                self._fork_cases()
            kind = self._active(nid, t)
            raised = True
            try:
                if kind == "raise":
                    raise RuntimeError(f"injected fault in {nid} at t={t:.3f} s")
                if kind == "exit":
                    raise SystemExit(f"injected SystemExit in {nid} at t={t:.3f} s")
                if kind == "hardware":
                    raise HardwareError(f"injected: {nid} lost (cable pulled) at t={t:.3f} s")
                out = real(t, inputs)
                if kind == "nan" and out:
                    out = {k: nan_like(v) for k, v in out.items()}
                elif kind == "stale":
                    out = {}
                elif kind == "type":
                    out = dict(out or {})
                    out[ports[0]] = "wrong type"
                raised = False
                return out
            finally:
                if t >= self.t_fault:
                    self._observe(nid, comp, t, inputs, raised)

        return step

    def _spy(self, nid: str, real: Callable[[], None]) -> Callable[[], None]:
        def safe_state() -> None:
            try:
                real()
            finally:
                g = float(self.rt.component(nid).g_applied) if nid == self.leader_id else None
                self.obs.safe_calls.append((nid, self.rt.now(), g))

        return safe_state

    def _observe(self, nid: str, comp: Any, t: float, inputs: Any, raised: bool) -> None:
        if nid == self.leader_id:
            s = inputs.get("gripper_force")
            cmd = None if s is None else float(s.value) if isinstance(s.value, (int, float)) else math.nan
            self.obs.leader.append((t, float(comp.g_applied), cmd, raised))
        elif nid == self.follower_id:
            self.obs.follower.append((t, float(comp.x), float(comp.force)))

    # ----------------------------------------------------------------------------------------- forking
    def _fork_cases(self) -> None:
        self.forked = True
        leader, follower = self.rt.component(self.leader_id), self.rt.component(self.follower_id)
        self.obs.x_fault, self.obs.g_fault = float(follower.x), float(leader.g_applied)
        self.obs.contact_fault = bool(follower.force > 0.0)
        for case in self.cases:
            r, w = os.pipe()
            w0 = time.perf_counter()
            pid = os.fork()
            if pid == 0:   # the child: this case, from here on
                os.close(r)
                self.child, self.case, self._wfd, self._w0 = True, case, w, w0
                self.obs.case = case
                if case.policy != "stop":
                    for node in self.rt.nodes:
                        node.policy = case.policy
                return
            os.close(w)
            self.results[case.id] = self._collect(case, pid, r, w0)
        # the parent goes on: the baseline

    def _collect(self, case: Case, pid: int, r: int, w0: float) -> Observed:
        chunks: list[bytes] = []
        deadline = time.monotonic() + self.timeout
        with os.fdopen(r, "rb") as f:
            while True:
                left = deadline - time.monotonic()
                ready, _, _ = select.select([f], [], [], max(left, 0.0))
                if not ready:
                    os.kill(pid, signal.SIGKILL)
                    break
                chunk = f.read1(1 << 16)
                if not chunk:
                    break
                chunks.append(chunk)
        os.waitpid(pid, 0)
        try:
            obs = pickle.loads(b"".join(chunks))
        except Exception as exc:
            obs = Observed(case, self.t_fault, error=f"no result from the child ({exc!r}; timeout "
                                                     f"{self.timeout:g} s?)")
        obs.wall_s = time.perf_counter() - w0
        return obs

    def finish(self, result: Any = None, error: BaseException | None = None) -> None:
        """After rt.run() (or its exception): in a child, send what it saw and end the process here."""
        o = self.obs
        if error is not None:
            o.error = "".join(traceback.format_exception(error))
        if result is not None:
            o.status, o.exit_code, o.message = result.status, result.exit_code, result.message
            o.faults = [dict(f.__dict__) for f in result.faults]
            o.end_time = result.sim_time
        try:
            o.leader_end = dict(self.rt.component(self.leader_id).status())
            o.follower_end = dict(self.rt.component(self.follower_id).status())
            o.controller_end = dict(self.rt.component("controller").status())
        except Exception as exc:   # pragma: no cover - reported, not hidden
            o.error = (o.error or "") + f"status(): {exc!r}"
        if not self.child:
            return
        code = 0
        try:
            data = pickle.dumps(o)
            with os.fdopen(self._wfd, "wb") as f:   # type: ignore[arg-type]
                f.write(data)
        except BaseException:
            code = 1
        finally:
            os._exit(code)

    def run(self) -> tuple[dict[str, Observed], Observed]:
        try:
            res = self.rt.run()
        except BaseException as exc:
            self.finish(error=exc)      # a child ends here
            raise
        self.finish(res)                # a child ends here
        return self.results, self.obs
