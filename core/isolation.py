"""Run a node's component in a process of its own (wall clock only): ``isolate: process`` in a graph.

Python runs one thread at a time (the GIL). An image estimator that spends milliseconds per frame in Python code or
in C calls that keep the lock can delay a 1 kHz haptic thread of the same process by as much. Isolated, the
component runs in a child process: the parent's thread for that node sends the latest inputs through a pipe and waits
for the outputs with the lock released, so the fast loop never waits for it.

Large arrays (images, depth maps: >= 16 kB) do not go through the pipe: each side writes them into shared-memory
blocks of its own, one per port, and sends only their names, shapes and types; the receiver copies them out at once
(the protocol is request/reply, so a block is never rewritten before it has been read). Pickled through the pipe, a
QVGA frame and its depth map cost the parent ~2.5 ms per step and held its interpreter lock while unpickling.

The child is started with the ``spawn`` method (no fork of a threaded process). The component class is sent by
reference (its module must be importable), its parameters as a plain dict. Graph time is the same in both processes
(``time.perf_counter`` and ``time.monotonic`` are system-wide clocks on Linux and macOS). Exceptions in the child come
back as faults of the node, with the original type, message and place. Under the simulated clock isolation is
ignored: the node runs inline, so runs stay deterministic.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from multiprocessing import shared_memory
from typing import Any, NamedTuple

import numpy as np

from .component import Component, Context, Inputs, Sample, _Slot
from .errors import ComponentFault, exception_line

#: seconds a child may take to answer a lifecycle call (configure may load a model)
LIFECYCLE_TIMEOUT = 120.0
#: arrays of at least this many bytes cross through shared memory instead of the pipe
SHARED_MIN_BYTES = 16384


class SharedRef(NamedTuple):
    """An array left in a shared-memory block: what crosses the pipe instead of its bytes."""

    name: str
    shape: tuple[int, ...]
    dtype: str


class ArrayLanes:
    """One side's shared-memory blocks for large arrays, and the blocks of the other side it has read from.

    ``pack(key, value)`` -> the value itself, or a :class:`SharedRef` after writing it into this side's
    block for ``key`` (made, or remade larger, on demand); ``unpack(ref)`` -> a fresh array copied out of the
    named block. The side that made a block unlinks it (``close``); ``close(unlink_peer=True)`` also unlinks the
    blocks read from the other side (when it may have died without doing so).
    """

    def __init__(self) -> None:
        self._own: dict[str, shared_memory.SharedMemory] = {}
        self._peer: dict[str, shared_memory.SharedMemory] = {}

    def pack(self, key: str, value: Any) -> Any:
        if not (isinstance(value, np.ndarray) and value.nbytes >= SHARED_MIN_BYTES and value.dtype.kind in "biufc"):
            return value
        blk = self._own.get(key)
        if blk is None or blk.size < value.nbytes:
            if blk is not None:
                _release(blk, unlink=True)
            blk = self._own[key] = _create(value.nbytes)
        np.copyto(np.ndarray(value.shape, value.dtype, buffer=blk.buf), value, casting="no")
        return SharedRef(blk.name, value.shape, value.dtype.str)

    def unpack(self, value: Any) -> Any:
        if not isinstance(value, SharedRef):
            return value
        blk = self._peer.get(value.name)
        if blk is None:
            blk = self._peer[value.name] = _attach(value.name)
        return np.ndarray(value.shape, np.dtype(value.dtype), buffer=blk.buf).copy()

    def close(self, unlink_peer: bool = False) -> None:
        for blk in self._own.values():
            _release(blk, unlink=True)
        for blk in self._peer.values():
            _release(blk, unlink=unlink_peer)
        self._own.clear()
        self._peer.clear()


def _create(size: int) -> shared_memory.SharedMemory:
    try:
        return shared_memory.SharedMemory(create=True, size=size)
    except OSError as exc:
        raise ComponentFault(f"isolated node: cannot make a {size} B shared-memory block for its arrays ({exc}); "
                             f"is /dev/shm mounted and large enough (containers: --shm-size)?") from None


def _attach(name: str) -> shared_memory.SharedMemory:
    # Python < 3.13 registers an attached block with the resource tracker as if this side had made it. The child is
    # spawned by this module and shares the parent's tracker, so that is the same entry again (a set), removed when
    # the maker unlinks the block; the tracker unlinks what is left if both processes die.
    return shared_memory.SharedMemory(name=name)


def _release(blk: shared_memory.SharedMemory, unlink: bool) -> None:
    try:
        blk.close()
    except BufferError:  # pragma: no cover - an array still views it: the mapping goes with the process
        pass
    if unlink:
        try:
            blk.unlink()
        except FileNotFoundError:
            pass


def _child_main(conn: Any, cls: type[Component], params: dict, node_id: str, t0_perf: float,
                t0_mono: float, priority: int = 0, rate: float | None = None) -> None:
    lanes = ArrayLanes()
    try:
        _serve(conn, cls, params, node_id, t0_perf, t0_mono, priority, lanes, rate)
    finally:
        lanes.close()
        conn.close()


def _serve(conn: Any, cls: type[Component], params: dict, node_id: str, t0_perf: float, t0_mono: float,
           priority: int, lanes: ArrayLanes, rate: float | None = None) -> None:
    stop_reason: list[str] = []
    logs: list[str] = []
    if priority:
        # the node's own priority (its thread's, had it run in the parent), for the whole child process
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as exc:
            logs.append(f"priority {priority}: cannot use SCHED_FIFO in the isolated process ({exc}); running "
                        f"with normal scheduling")
    origin = [t0_perf, t0_mono]
    ctx = Context(now=lambda: time.perf_counter() - origin[0], clock_kind="wall",
                  request_stop=lambda r: stop_reason.append(r), log=logs.append,
                  from_monotonic=lambda m: m - origin[1], rate=rate)
    slots = {name: _Slot() for name in cls.inputs}
    inputs = Inputs(slots)
    comp: Component | None = None
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            break
        op = msg[0]
        try:
            if op == "step":
                _, t, ins = msg
                for name, v in ins.items():
                    slots[name].sample = None if v is None else Sample(lanes.unpack(v[0]), v[1])
                out = comp.step(t, inputs) or {}  # type: ignore[union-attr]
                packed = {k: (("S", lanes.pack(k, v.value), v.stamp) if isinstance(v, Sample)
                              else ("V", lanes.pack(k, v))) for k, v in out.items()}
                conn.send(("out", packed, comp.status(), stop_reason[:], logs[:]))  # type: ignore[union-attr]
                stop_reason.clear()
                logs.clear()
                continue
            if op == "configure":
                comp = cls(cls.Params.model_validate(params), node_id=node_id, ctx=ctx)
                comp.configure()
            elif op in ("activate", "deactivate"):
                getattr(comp, op)()
            elif op == "clock":
                origin[:] = msg[1:]
            elif op == "close":
                if comp is not None:
                    comp.close()
                conn.send(("ok", logs[:]))
                break
            conn.send(("ok", logs[:]))
            logs.clear()
        except BaseException as exc:  # noqa: BLE001 - everything goes back to the parent
            conn.send(("exc", exception_line(exc), logs[:]))
            logs.clear()


class ProcessProxy(Component):
    """Stands in for a component that runs in a child process; the runtime treats it like the component."""

    def __init__(self, cls: type[Component], params: Any, *, node_id: str, ctx: Context, t0_perf: float,
                 t0_mono: float, step_timeout: float, priority: int = 0):
        super().__init__(params, node_id=node_id, ctx=ctx)
        self.target = cls
        self.inputs = cls.inputs
        self.outputs = cls.outputs
        self.name = cls.name
        self.kind = cls.kind
        self._t0 = (t0_perf, t0_mono)
        self._step_timeout = step_timeout
        self._priority = int(priority)
        self._status: dict[str, Any] = {}
        self._conn: Any = None
        self._proc: Any = None
        self._lanes = ArrayLanes()
        self._owed = 0   # replies still owed by the child for calls that timed out (read and dropped first)

    # -------------------------------------------------------------------------------------------------- plumbing
    def _call(self, *msg: Any, timeout: float) -> Any:
        conn = self._conn
        try:
            # a call that timed out still gets its reply later: read and drop it first, so that this call reads
            # its own reply (not, say, deactivate() the late answer of a step)
            while self._owed:
                if not conn.poll(timeout):
                    raise ComponentFault(f"isolated process is still busy with an earlier call; '{msg[0]}' not sent "
                                         f"after {timeout:.3g} s")
                conn.recv()
                self._owed -= 1
            conn.send(msg)
            if not conn.poll(timeout):
                self._owed += 1
                raise ComponentFault(f"isolated process did not answer '{msg[0]}' within {timeout:.3g} s")
            reply = conn.recv()
        except (EOFError, BrokenPipeError, ConnectionResetError, OSError) as exc:
            code = self._proc.exitcode if self._proc is not None else None
            raise ComponentFault(f"isolated process died (exit code {code}) during '{msg[0]}': "
                                 f"{type(exc).__name__}") from None
        for line in reply[-1]:
            self.ctx.log(line)
        if reply[0] == "exc":
            raise ComponentFault(f"in isolated process: {reply[1]}")
        return reply

    def configure(self) -> None:
        mpctx = mp.get_context("spawn")
        parent, child = mpctx.Pipe()
        self._proc = mpctx.Process(target=_child_main, name=f"teletouch-{self.id}", daemon=True,
                                   args=(child, self.target, self.params.model_dump(), self.id, *self._t0,
                                         self._priority, self.ctx.rate))
        self._proc.start()
        child.close()
        self._conn = parent
        self._call("configure", timeout=LIFECYCLE_TIMEOUT)

    def set_origin(self, t0_perf: float, t0_mono: float) -> None:
        """The graph clock's origin (set by the runtime after start-up, before the first step)."""
        self._t0 = (t0_perf, t0_mono)
        self._call("clock", t0_perf, t0_mono, timeout=LIFECYCLE_TIMEOUT)

    def activate(self) -> None:
        self._call("activate", timeout=LIFECYCLE_TIMEOUT)

    def step(self, t: float, inputs: Inputs) -> dict[str, Any]:
        ins = {}
        for name in self.inputs:
            s = inputs[name]
            ins[name] = None if s is None else (self._lanes.pack(name, s.value), s.stamp)
        _, packed, status, stop, _logs = self._call("step", t, ins, timeout=self._step_timeout)
        self._status = status
        if stop:
            self.ctx.request_stop(stop[0])
        unpack = self._lanes.unpack
        return {k: (Sample(unpack(v[1]), v[2]) if v[0] == "S" else unpack(v[1])) for k, v in packed.items()}

    def deactivate(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._call("deactivate", timeout=LIFECYCLE_TIMEOUT)

    def close(self) -> None:
        try:
            if self._proc is not None and self._proc.is_alive():
                self._call("close", timeout=10.0)
        finally:
            if self._proc is not None:
                self._proc.join(timeout=5.0)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join(timeout=5.0)
            if self._conn is not None:
                self._conn.close()
            # the child unlinks its blocks as it ends; if it died first, its blocks go with the parent's
            self._lanes.close(unlink_peer=True)

    def status(self) -> dict[str, Any]:
        return self._status
