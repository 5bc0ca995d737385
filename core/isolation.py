"""Run a node's component in a process of its own (wall clock only): ``isolate: process`` in a graph.

Python runs one thread at a time (the GIL). An image estimator that spends milliseconds per frame in Python code or
in C calls that keep the lock can delay a 1 kHz haptic thread of the same process by as much. Isolated, the
component runs in a child process: the parent's thread for that node sends the latest inputs through a pipe and waits
for the outputs with the lock released, so the fast loop never waits for it.

Large arrays (images, depth maps: >= 16 kB) do not go through the pipe: each side writes them into shared-memory
blocks of its own, one per port, and sends only their names, shapes and types; the receiver copies them out at once
(the protocol is request/reply, so a block is never rewritten before it has been read; after a call timed out, while the
child has not answered since, each step's inputs go into fresh blocks: a request still queued reads its own). Pickled
through the pipe, a QVGA frame and its depth map cost the parent ~2.5 ms per step and held its interpreter lock while
unpickling. A block's pages are reserved when it is made, so a full /dev/shm is a fault of the node, not a SIGBUS of the
process that writes into it. Every block of a node is named ``teletouch_<token>_...``; when the node is closed the
parent removes all of them, also those of a child that was killed before it could say their names.

The child is started with the ``spawn`` method (no fork of a threaded process). The component class is sent by
reference (its module must be importable; a failed import in the child is a start-up failure with its reason), its
parameters as a plain dict. Graph time is the same in both processes (``time.perf_counter`` and ``time.monotonic``
are system-wide clocks on Linux and macOS). Exceptions in the child come back as faults of the node, with the original
type, message and place, and the input a ComponentFault is about (``input_port``: the runtime adds what feeds it, as
inline). Under the simulated clock isolation is ignored: the node runs inline, so runs stay deterministic.

An input whose sample is the same object as the one the child already holds (a camera image that has not changed
since the last step of a faster node) is not sent again: the child's component sees the same Sample, as inline.
Values other than numbers, numeric arrays and text cross pickled one by one, so a value the child cannot unpickle
(its class is not importable there) is a fault of the node that names the plugin and the input; the child lives on.
Each step request also carries the node's Context.disabled_upstream (the nodes feeding it that a fault has disabled,
as the parent's runtime knows them when the step is sent): the child's Context returns that list. A component's own
warm() (Component.warm: 1 ms before each step) runs in the child, on the inputs it holds; the proxy waits for it as for
a step. For a class without one, a device, or a node whose parameters turn it off (Component.wants_warm_up: the depth
node's ``warm: false``), nothing crosses.

Every request carries a number that its reply repeats: a reply that comes after its call timed out is recognised and
dropped, never taken for a later call's. The child answers every request once, in order, so a reply without its number
(to a request the child could not unpickle, or one the parent cannot unpickle) answers the oldest request not answered
yet: a late one is dropped, not taken for the call in progress. A step in flight can be abandoned from another thread
(:meth:`ProcessProxy.abandon_step`: the runtime's watchdog, when the node's rate group has devices that the step keeps
from being stepped): the node's thread stops waiting at once and its step raises :class:`StepAbandoned`; the child's
late answer is dropped as a timed-out one's. One call at a time: the runtime's shutdown (main thread) waits for a step
still running in the node's thread (at most until that step's own timeout) before it sends deactivate/close. The
child ignores SIGINT and SIGTERM (Ctrl-C reaches the whole process group; the parent ends the child through the pipe
after its devices are safe) and, on Linux, is killed when the parent dies. A child that does not answer
deactivate/close within ``SHUTDOWN_TIMEOUT`` is killed, and so is one still running when the interpreter exits.
"""

from __future__ import annotations

import errno
import multiprocessing as mp
import os
import pickle
import secrets
import select
import signal
import sys
import threading
import time
import traceback
from collections import deque
from multiprocessing import resource_tracker, shared_memory
from multiprocessing.reduction import ForkingPickler
from typing import Any, NamedTuple

import numpy as np

from .component import Component, Context, Inputs, Sample, _Slot, has_warm_up, plain_results
from .errors import ComponentFault, exception_place

#: seconds a child may take to answer a lifecycle call (configure may load a model)
LIFECYCLE_TIMEOUT = 120.0
#: seconds deactivate() and close() each wait for the child's answer at the end of a run; then it is killed
SHUTDOWN_TIMEOUT = 10.0
#: arrays of at least this many bytes cross through shared memory instead of the pipe
SHARED_MIN_BYTES = 16384
#: names of the shared-memory blocks of isolated nodes start with this (then a random token per node)
BLOCK_PREFIX = "teletouch_"
_SHM_DIR = "/dev/shm"
_TERMINAL_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: the number of the child's reply to a request it could not unpickle (its number unknown): the answer to the oldest
#: request not answered yet (the child answers each request once, in order)
_UNREADABLE = -1


class StepAbandoned(ComponentFault):
    """An isolated step whose wait another thread cut short (:meth:`ProcessProxy.abandon_step`). The one who cut it
    has reported why (the runtime's watchdog: a fault of the node), so the runtime does not report it again."""

    abandoned = True


#: children started and not yet ended: killed at interpreter exit (they ignore the SIGTERM multiprocessing sends
#: its daemon children then, and its join() that follows has no timeout)
_LIVE: set[Any] = set()
_live_lock = threading.Lock()
_atexit_set = False


def _kill_leftovers() -> None:
    with _live_lock:
        procs = list(_LIVE)
        _LIVE.clear()
    for proc in procs:
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=5.0)


def _track(proc: Any, live: bool) -> None:
    global _atexit_set
    with _live_lock:
        if live:
            _LIVE.add(proc)
            if not _atexit_set:   # registered after multiprocessing's own exit hook, so it runs before it
                import atexit

                atexit.register(_kill_leftovers)
                _atexit_set = True
        else:
            _LIVE.discard(proc)


class SharedRef(NamedTuple):
    """An array left in a shared-memory block: what crosses the pipe instead of its bytes."""

    name: str
    shape: tuple[int, ...]
    dtype: str


class ArrayLanes:
    """One side's shared-memory blocks for large arrays, and the blocks of the other side it has read from.

    ``pack(key, value)`` -> the value itself, or a :class:`SharedRef` after writing it into this side's
    block for ``key`` (made, or remade larger, on demand); ``unpack(ref, key)`` -> a fresh array copied out of the
    named block. The side that made a block unlinks it (``close``, or when it remakes it larger); the reader keeps
    one mapping per key and lets go of the old one when a new block comes for that key (a port whose arrays grow
    step after step would otherwise pile up mappings and file descriptors). ``close(unlink_peer=True)`` also unlinks
    the blocks read from the other side (when it may have died without doing so). ``prefix``: names of this side's
    blocks (``prefix`` + a number); empty: random names.

    ``retire()``: this side's blocks are not written again (the next ``pack`` of each key makes a fresh one) but kept,
    for a reader that may still have to read them: requests that name them wait unread in the pipe. They are unlinked
    by ``release_retired()`` (the reader has answered a later request: it has read them all) or ``close``.
    """

    def __init__(self, prefix: str = "") -> None:
        self._own: dict[str, shared_memory.SharedMemory] = {}
        self._peer: dict[str, shared_memory.SharedMemory] = {}
        self._retired: list[shared_memory.SharedMemory] = []
        self._prefix = prefix
        self._made = 0

    def pack(self, key: str, value: Any) -> Any:
        if not (isinstance(value, np.ndarray) and value.nbytes >= SHARED_MIN_BYTES and value.dtype.kind in "biufc"):
            return value
        blk = self._own.get(key)
        if blk is None or blk.size < value.nbytes:
            if blk is not None:
                del self._own[key]
                _release(blk, unlink=True)
            blk = self._own[key] = self._create(value.nbytes)
        np.copyto(np.ndarray(value.shape, value.dtype, buffer=blk.buf), value, casting="no")
        return SharedRef(blk.name, value.shape, value.dtype.str)

    def _create(self, size: int) -> shared_memory.SharedMemory:
        while True:
            name = None
            if self._prefix:
                self._made += 1
                name = f"{self._prefix}{self._made}"
            try:
                return _create(size, name)
            except FileExistsError:
                continue

    def unpack(self, value: Any, key: str | None = None) -> Any:
        if not isinstance(value, SharedRef):
            return value
        key = value.name if key is None else key
        blk = self._peer.get(key)
        if blk is None or blk.name != value.name:
            if blk is not None:
                del self._peer[key]
                _release(blk, unlink=False)   # its maker has unlinked it when it made the new one
            blk = self._peer[key] = _attach(value.name)
        return np.ndarray(value.shape, np.dtype(value.dtype), buffer=blk.buf).copy()

    def retire(self) -> None:
        self._retired.extend(self._own.values())
        self._own.clear()

    def release_retired(self) -> None:
        retired, self._retired = self._retired, []
        for blk in retired:
            _release(blk, unlink=True)

    def close(self, unlink_peer: bool = False) -> None:
        self.release_retired()
        for blk in self._own.values():
            _release(blk, unlink=True)
        for blk in self._peer.values():
            _release(blk, unlink=unlink_peer)
        self._own.clear()
        self._peer.clear()


def _create(size: int, name: str | None = None) -> shared_memory.SharedMemory:
    hint = "is /dev/shm mounted and large enough (containers: --shm-size)?"
    try:
        blk = shared_memory.SharedMemory(name=name, create=True, size=size)
    except FileExistsError:
        raise
    except OSError as exc:
        raise ComponentFault(f"isolated node: cannot make a {size} B shared-memory block for its arrays ({exc}); "
                             f"{hint}") from None
    # A block is a sparse file in a tmpfs: made larger than the space left there, it is made all the same, and the
    # first write to a page that cannot be had kills the writing process with SIGBUS (the parent: no safe state).
    # Reserving the pages now turns that into an error here.
    fd = getattr(blk, "_fd", -1)
    if fd >= 0 and hasattr(os, "posix_fallocate"):
        try:
            os.posix_fallocate(fd, 0, size)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG):
                _release(blk, unlink=True)
                raise ComponentFault(f"isolated node: cannot make a {size} B shared-memory block for its arrays "
                                     f"({os.strerror(exc.errno)}); {hint}") from None
    return blk


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


def remove_blocks(prefix: str) -> list[str]:
    """Unlink every shared-memory block whose name starts with ``prefix`` (Linux: the entries of /dev/shm; elsewhere
    nothing is listed) and return their names. For the blocks of a child that died before it could name them."""
    try:
        names = sorted(n for n in os.listdir(_SHM_DIR) if n.startswith(prefix))
    except OSError:
        return []
    for name in names:
        try:
            blk = shared_memory.SharedMemory(name=name)   # attach + unlink: its resource-tracker entry goes too
        except FileNotFoundError:
            continue
        except (OSError, ValueError):   # e.g. empty (its maker died before sizing it): never registered
            try:
                os.unlink(os.path.join(_SHM_DIR, name))
            except OSError:
                pass
            continue
        _release(blk, unlink=True)
    return names


def _send(conn: Any, msg: Any, values: dict[str, Any], what: str, where: str) -> None:
    """``conn.send(msg)``; a message that cannot be pickled (nothing was written) names the port that cannot cross."""
    try:
        conn.send(msg)
    except OSError:
        raise
    except Exception as exc:
        for name, v in values.items():
            try:
                ForkingPickler.dumps(v)
            except Exception as bad:
                raise ComponentFault(f"{what} '{name}' cannot cross to {where}: {type(bad).__name__}: {bad}") \
                    from None
        raise ComponentFault(f"cannot send to {where}: {type(exc).__name__}: {exc}") from None


_PLAIN = (float, int, bool, str, bytes, type(None), SharedRef)


def _to_wire(name: str, value: Any) -> tuple[str, Any]:
    """An input value as it crosses the pipe: ("V", value) for numbers, text and numeric arrays (the child can
    always unpickle them), ("P", pickled bytes) for anything else, so the child can say which input it could not
    unpickle (a class it cannot import) instead of dying on the whole request."""
    cls = value.__class__
    if cls in _PLAIN or (cls is np.ndarray and value.dtype.kind in "biufc") or (
            isinstance(value, np.generic) and value.dtype.kind in "biufc"):
        return "V", value
    try:
        return "P", bytes(ForkingPickler.dumps(value))
    except Exception as bad:
        raise ComponentFault(f"input '{name}' cannot cross to the isolated process: {type(bad).__name__}: {bad}") \
            from None


def _from_wire(name: str, kind: str, payload: Any, plugin: str) -> Any:
    """The child's side of :func:`_to_wire`."""
    if kind != "P":
        return payload
    try:
        return pickle.loads(payload)
    except Exception as exc:
        raise ComponentFault(f"input '{name}' of {plugin} cannot be received in the isolated process: "
                             f"{type(exc).__name__}: {exc} (a value crosses pickled: its class must be importable "
                             f"by name in a new process); the input was not delivered") from None


def _drain(fd: int) -> None:
    """Read a non-blocking pipe empty."""
    try:
        while os.read(fd, 64):
            pass
    except BlockingIOError:
        pass


def _status_of(comp: Any) -> dict[str, Any]:
    """In the child: ``comp.status()`` for the parent's live view, or {} when it raises or cannot cross the pipe. As
    inline, where the live view shows nothing for such a status: a plugin's bug there does not stop the run (it
    made every step of the isolated node a fault)."""
    try:
        status = comp.status()
        ForkingPickler.dumps(status)
    except Exception:
        return {}
    return status


def _crossing(exc: BaseException) -> tuple[str, dict[str, str]]:
    """In the child: an exception as it crosses to the parent (as text: its class may not be importable there, nor
    its arguments picklable): ``Type: message`` and what :func:`exception_line` and the runtime read besides, as far
    as the exception has it: ``where`` (its own, else the innermost frame that raised: the plugin's line in the
    child) and ``input_port`` (a :class:`ComponentFault` about one of the node's inputs)."""
    info: dict[str, str] = {}
    place = exception_place(exc)
    if place:
        info["where"] = place
    port = getattr(exc, "input_port", None) if isinstance(exc, ComponentFault) else None
    if isinstance(port, str):
        info["input_port"] = port
    return f"{type(exc).__name__}: {exc}", info


def _child_fault(text: str, info: dict[str, str]) -> ComponentFault:
    """In the parent: the fault of the node for an exception in the child (:func:`_crossing`), with the child's place
    as its ``where`` (not this module's line) and the input it is about, for the runtime to say what feeds it."""
    fault = ComponentFault(f"in isolated process: {text}", input_port=info.get("input_port"))
    if info.get("where"):
        fault.where = info["where"]
    return fault


def _child_signals(parent_pid: int) -> None:
    """In the child: Ctrl-C (SIGINT to the whole process group) and SIGTERM are for the parent, which ends the child
    through the pipe once its devices are safe; a child that died first would be a fault of its own and never
    deactivate or close its component. They stay ignored (not merely handled: no EINTR in the component's C calls).
    The parent spawns the child with both blocked, so none is lost to the default action while Python starts. On
    Linux the child is killed if the parent (its thread that spawned it) dies: a child hung in a step would
    otherwise outlive it, holding its camera or GPU."""
    for sig in _TERMINAL_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _TERMINAL_SIGNALS)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)   # PR_SET_PDEATHSIG
        except Exception:  # pragma: no cover - best effort
            pass
        if os.getppid() != parent_pid:   # the parent died before that: nobody to serve
            os._exit(1)


def _import_failure(exc: BaseException, module: str, qualname: str) -> tuple[str, dict[str, str]]:
    """In the child: the error of a component class that cannot be imported here, as :func:`_crossing` gives one.
    Its place is the plugin's line that raised as its module was imported (a dependency missing here), else the class
    by name (its module missing here, or the class not in it): never this module's line, which says nothing."""
    tb = traceback.extract_tb(exc.__traceback__)
    where = exception_place(exc) if tb and tb[-1].filename != __file__ else f"class {qualname} of module {module}"
    return f"cannot import the component class: {type(exc).__name__}: {exc}", {"where": where}


def _child_main(conn: Any, cls_ref: bytes, params: dict, node_id: str, t0_perf: float, t0_mono: float,
                priority: int = 0, rate: float | None = None, prefix: str = "", parent_pid: int = 0,
                target: tuple[str, str] = ("?", "?")) -> None:
    """The isolated process; ``target``: the component class's module and qualified name (said if it cannot be
    imported here)."""
    _child_signals(parent_pid or os.getppid())
    lanes = ArrayLanes(prefix)
    try:
        try:
            cls, error = pickle.loads(cls_ref), None
        except BaseException as exc:  # noqa: BLE001 - reported as configure's failure
            cls, error = None, _import_failure(exc, *target)
        _serve(conn, cls, error, params, node_id, t0_perf, t0_mono, priority, lanes, rate)
    finally:
        lanes.close()
        conn.close()


def _serve(conn: Any, cls: type[Component] | None, import_error: tuple[str, dict[str, str]] | None, params: dict,
           node_id: str, t0_perf: float, t0_mono: float, priority: int, lanes: ArrayLanes,
           rate: float | None = None) -> None:
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
    lost: list[str] = []   # Context.disabled_upstream as the parent sent it with the latest step
    ctx = Context(now=lambda: time.perf_counter() - origin[0], clock_kind="wall",
                  request_stop=lambda r: stop_reason.append(r), log=logs.append,
                  from_monotonic=lambda m: m - origin[1], rate=rate, disabled_upstream=lambda: lost)
    slots = {name: _Slot() for name in cls.inputs} if cls is not None else {}
    inputs = Inputs(slots)
    comp: Component | None = None
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            break
        except Exception as exc:  # a request that cannot be unpickled: said, and the child goes on
            name = cls.name if cls is not None else "the component"
            try:   # (only a step's request carries the graph's values: its inputs)
                conn.send((_UNREADABLE, "exc", f"{name}: a request from the parent cannot be unpickled in the "
                                               f"isolated process: {type(exc).__name__}: {exc}",
                           {"where": f"the input values sent to {name}"}, logs[:]))
            except OSError:
                break
            logs.clear()
            continue
        seq, op = msg[0], msg[1]
        try:
            if op == "step":
                _, _, t, ins, lost[:] = msg
                # inputs not in the request are unchanged: their slots keep the Sample they hold. Every value is
                # unpacked before any slot changes, so an input that cannot be received changes none of them
                new = {}
                for name, v in ins.items():
                    if v is not None:
                        kind, payload, stamp = v
                        v = Sample(lanes.unpack(_from_wire(name, kind, payload, cls.name), name), stamp)
                    new[name] = v
                for name, smp in new.items():
                    slots[name].sample = smp
                out = comp.step(t, inputs) or {}  # type: ignore[union-attr]
                packed = {k: (("S", lanes.pack(k, v.value), v.stamp) if isinstance(v, Sample)
                              else ("V", lanes.pack(k, v))) for k, v in out.items()}
                reply = (seq, "out", packed, _status_of(comp), stop_reason[:], logs[:])
                _send(conn, reply, packed, "output", "the parent process")
                stop_reason.clear()
                logs.clear()
                continue
            if op == "configure":
                if cls is None:
                    conn.send((seq, "exc", *import_error, logs[:]))
                    logs.clear()
                    continue
                comp = cls(cls.Params.model_validate(params), node_id=node_id, ctx=ctx)
                comp.configure()
            elif op in ("activate", "deactivate", "warm"):   # warm: with the inputs the child holds
                getattr(comp, op)()
            elif op == "results":
                # as the runtime takes them (a value that is no number or text as its repr): nothing to unpickle
                conn.send((seq, "res", plain_results(comp.results() or {}) if comp is not None else {}, logs[:]))
                logs.clear()
                continue
            elif op == "clock":
                origin[:] = msg[2:]
            elif op == "close":
                if comp is not None:
                    comp.close()
                conn.send((seq, "ok", logs[:]))
                break
            conn.send((seq, "ok", logs[:]))
            logs.clear()
        except BaseException as exc:  # noqa: BLE001 - everything goes back to the parent
            try:
                conn.send((seq, "exc", *_crossing(exc), logs[:]))
            except OSError:
                break   # the parent is gone
            logs.clear()
            stop_reason.clear()
            if op == "close":
                break


class ProcessProxy(Component):
    """Stands in for a component that runs in a child process; the runtime treats it like the component.

    One call crosses at a time (a lock): the node's thread steps it, the runtime's main thread starts it up and
    shuts it down. ``step_timeout``: seconds a step may take before it is a fault (the runtime gives 20 periods,
    at least 1 s); the child's late answer is then recognised by its number and dropped. Another thread may cut the
    wait for a step short before that (:meth:`abandon_step`)."""

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
        self._lock = threading.Lock()
        self._seq = 0          # number of the latest request; the child's reply repeats it
        self._unanswered: deque[int] = deque()   # numbers of the requests sent and not answered yet, oldest first
        self._stuck = False    # a call timed out and the child has not answered anything since
        self._prefix = f"{BLOCK_PREFIX}{secrets.token_hex(4)}_"   # names of this node's blocks, both sides
        self._lanes = ArrayLanes(self._prefix + "p")
        # port -> the Sample the child holds for it (sent, and its step answered): not sent again while unchanged
        self._held: dict[str, Sample | None] = {}
        self._wake: tuple[int, int] | None = None   # (read, write) ends of the pipe that wakes a waiting step
        self._abandon: str | None = None            # why the step in flight (or about to wait) is to be abandoned
        self._wake_lock = threading.Lock()
        self._poller: Any = None                    # select.poll() on the pipe and the wake-up pipe (steps)
        # whether warm() asks the child (as inline: _Node.warm; the runtime, which decides with the node's parameters
        # once it has configured, calls it only where Component.wants_warm_up says yes)
        self._warms = has_warm_up(cls)

    # -------------------------------------------------------------------------------------------------- plumbing
    def _started(self) -> bool:
        return self._proc is not None and self._proc.pid is not None

    def _call(self, op: str, *args: Any, timeout: float, wait: float | None = None) -> Any:
        """Send one request and return its reply; ``wait``: seconds to wait for a call in flight (default
        ``timeout``)."""
        if not self._lock.acquire(timeout=timeout if wait is None else wait):
            raise ComponentFault(f"'{op}' not sent: the isolated process is still busy with a step after "
                                 f"{timeout if wait is None else wait:.3g} s")
        try:
            return self._exchange(op, args, timeout)
        finally:
            self._lock.release()

    def _exchange(self, op: str, args: tuple, timeout: float, values: dict[str, Any] | None = None,
                  abandonable: bool = False) -> Any:
        """One request and its reply; the caller holds the lock. Replies to earlier requests (their call timed out
        or was interrupted) are dropped; their log lines are passed on. ``abandonable`` (steps): the wait also ends
        when :meth:`abandon_step` is called (:class:`StepAbandoned`)."""
        conn = self._conn
        self._seq += 1
        seq = self._seq
        sent = time.monotonic()
        deadline = sent + timeout
        poller = self._poller if abandonable else None   # watches the pipe and the wake-up pipe
        try:
            _send(conn, (seq, op, *args), values or {}, "input", "the isolated process")
            self._unanswered.append(seq)
            while True:
                left = deadline - time.monotonic()
                if poller is None:
                    if left <= 0 or not conn.poll(left):
                        self._stuck = True
                        raise ComponentFault(f"isolated process did not answer '{op}' within {timeout:.3g} s")
                else:
                    events = poller.poll(left * 1e3) if left > 0 else ()
                    if not events:
                        self._stuck = True
                        raise ComponentFault(f"isolated process did not answer '{op}' within {timeout:.3g} s")
                    if not self._answered(events, sent, op):   # a wake-up left over from a call that had ended
                        continue
                try:
                    reply = conn.recv()
                except (EOFError, OSError):
                    raise
                except Exception as exc:
                    why = f"cannot be unpickled here: {type(exc).__name__}: {exc}"
                    if self._answers(_UNREADABLE) == seq:
                        raise ComponentFault(f"a reply of the isolated process ({self.name}) to '{op}' {why}") \
                            from None
                    self.ctx.log(f"a late reply of the isolated process ({self.name}) dropped: it {why}")
                    continue
                for line in reply[-1]:
                    self.ctx.log(line)
                if self._answers(reply[0]) == seq:
                    break
        except (EOFError, OSError):
            raise self._died(op) from None
        self._stuck = False
        self._lanes.release_retired()   # the child has read every request before this one: their blocks may go
        if reply[1] == "exc":
            raise _child_fault(reply[2], reply[3])
        return reply

    def _answers(self, number: int) -> int | None:
        """The number of the request a reply with ``number`` answers (an :data:`_UNREADABLE` one: the oldest request
        not answered yet), forgotten with every request before it."""
        pending = self._unanswered
        if number == _UNREADABLE:
            return pending.popleft() if pending else None
        while pending and pending[0] <= number:
            pending.popleft()
        return number

    def _answered(self, events: list[tuple[int, int]], sent: float, op: str = "step") -> bool:
        """The events of a step's (or warm-up's) wait on the pipe and the wake-up pipe: True when the pipe has
        something, False after a wake-up that abandons nothing; raises :class:`StepAbandoned` after one that does."""
        wake = self._wake[0]   # type: ignore[index]
        answer = False
        for fd, _ in events:
            if fd != wake:
                answer = True   # (POLLHUP, POLLERR too: recv() then says how the child ended)
                continue
            _drain(wake)
            why, self._abandon = self._abandon, None
            if why is not None:
                self._stuck = True
                what = "step" if op == "step" else f"{op}()"
                raise StepAbandoned(f"{what} abandoned after {time.monotonic() - sent:.3f} s without an answer from "
                                    f"the isolated process: {why}")
        return answer

    def abandon_step(self, why: str) -> None:
        """From another thread: stop waiting for the step or warm-up (:meth:`warm`) in flight (or the next one to
        wait: one that has not reached its wait yet) at once; that call raises :class:`StepAbandoned` with ``why``.
        For a caller that has reported the node's fault already (the runtime's watchdog: the step keeps the devices of
        its rate group from being stepped). The child goes on with the call; its late answer is dropped."""
        self._abandon = why
        with self._wake_lock:   # not closed (and its number reused) while this writes to it
            if self._wake is not None:
                try:
                    os.write(self._wake[1], b"!")
                except BlockingIOError:   # full: bytes not drained yet, it wakes all the same
                    pass

    def _died(self, op: str) -> ComponentFault:
        proc = self._proc
        code = None
        if self._started():
            proc.join(1.0)   # the pipe closes a moment before the exit status can be read
            code = proc.exitcode
        if code is None:
            how = "closed its end of the pipe"
        elif code < 0:
            try:
                sig = signal.Signals(-code).name
            except ValueError:
                sig = "unknown signal"
            how = f"was killed by signal {-code} ({sig}" + (
                "; the out-of-memory killer sends it too" if -code == signal.SIGKILL else "") + ")"
        else:
            how = f"exited with code {code}"
        pid = proc.pid if proc is not None else None
        return ComponentFault(f"isolated process died during '{op}': {self.name} (pid {pid}) {how}")

    def configure(self) -> None:
        try:
            cls_ref = pickle.dumps(self.target)   # by reference: module and name
        except Exception as exc:
            raise ComponentFault(f"isolate: process needs a component class that a new process can import by name "
                                 f"(defined at the top level of a module), not {self.target.__module__}."
                                 f"{self.target.__qualname__}: {type(exc).__name__}: {exc}") from None
        mpctx = mp.get_context("spawn")
        self._held.clear()   # a new child holds no input yet
        self._unanswered.clear()
        parent, child = mpctx.Pipe()
        self._conn = parent
        if self._wake is None:
            r, w = os.pipe()
            os.set_blocking(r, False)
            os.set_blocking(w, False)
            self._wake = (r, w)
        self._poller = select.poll()   # kept: cheaper per step than conn.poll(), which makes a selector each time
        self._poller.register(parent.fileno(), select.POLLIN)
        self._poller.register(self._wake[0], select.POLLIN)
        self._proc = mpctx.Process(target=_child_main, name=f"teletouch-{self.id}", daemon=True,
                                   args=(child, cls_ref, self.params.model_dump(), self.id, *self._t0,
                                         self._priority, self.ctx.rate, self._prefix + "c", os.getpid(),
                                         (self.target.__module__, self.target.__qualname__)))
        # SIGINT/SIGTERM blocked in this thread while it spawns: the child inherits the mask and unblocks them once
        # it ignores them. The resource tracker is started first: starting it unblocks both in this thread.
        resource_tracker.ensure_running()
        mask = hasattr(signal, "pthread_sigmask")
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _TERMINAL_SIGNALS) if mask else None
        try:
            self._proc.start()
            _track(self._proc, True)
        finally:
            if mask:
                signal.pthread_sigmask(signal.SIG_SETMASK, old)
            child.close()
        self._call("configure", timeout=LIFECYCLE_TIMEOUT)

    def set_origin(self, t0_perf: float, t0_mono: float) -> None:
        """The graph clock's origin (set by the runtime after start-up, before the first step)."""
        self._t0 = (t0_perf, t0_mono)
        self._call("clock", t0_perf, t0_mono, timeout=LIFECYCLE_TIMEOUT)

    def activate(self) -> None:
        self._call("activate", timeout=LIFECYCLE_TIMEOUT)

    def step(self, t: float, inputs: Inputs) -> dict[str, Any]:
        if not self._lock.acquire(timeout=self._step_timeout):
            raise ComponentFault(f"step not sent: the isolated process is busy after {self._step_timeout:.3g} s")
        try:
            if not self._started():
                raise ComponentFault("isolated process not running")
            if self._stuck:
                # a call timed out or was abandoned and the child has not answered since: a request sent since may
                # still wait unread in the pipe, naming the input blocks. They are kept as they are for it, and this
                # step writes into fresh ones (before, a queued step read this step's array, or half of it, as its own)
                self._lanes.retire()
            held = self._held
            sent: dict[str, Sample | None] = {}
            ins = {}
            for name in self.inputs:
                s = inputs[name]
                if name in held and held[name] is s:
                    continue   # the child holds this very sample: an image is not copied again
                sent[name] = s
                ins[name] = None if s is None else (*_to_wire(name, self._lanes.pack(name, s.value)), s.stamp)
            try:
                reply = self._exchange("step", (t, ins, self.ctx.disabled_upstream()), self._step_timeout,
                                       abandonable=True)
            except BaseException:
                held.clear()   # the child may not have taken them (or only later): send everything next time
                raise
            held.update(sent)
            _, _, packed, status, stop, _logs = reply
            self._status = status
            unpack = self._lanes.unpack
            out = {k: (Sample(unpack(v[1], k), v[2]) if v[0] == "S" else unpack(v[1], k)) for k, v in packed.items()}
        finally:
            self._lock.release()
        if stop:
            self.ctx.request_stop(stop[0])
        return out

    def warm(self) -> None:
        """The component's warm() in the child (the runtime calls this :attr:`Runtime.WARM_LEAD` before each step),
        waited for as a step is: one call at a time, numbered, timed out after ``step_timeout``, cut short by
        :meth:`abandon_step`; an exception in it comes back as one in a step does. No input crosses: the child still
        holds the last step's. Nothing is sent for a class without a warm() of its own or for a device; the runtime
        does not call this for a node whose parameters turn its warm-up off (:meth:`Component.wants_warm_up`: the depth
        node's ``warm: false``)."""
        if not self._warms:
            return
        if not self._lock.acquire(timeout=self._step_timeout):
            raise ComponentFault(f"warm() not sent: the isolated process is busy after {self._step_timeout:.3g} s")
        try:
            if not self._started():
                raise ComponentFault("isolated process not running")
            self._exchange("warm", (), self._step_timeout, abandonable=True)
        finally:
            self._lock.release()

    def deactivate(self) -> None:
        if self._started() and self._proc.is_alive():
            # a step still running in the node's thread ends by its own timeout at the latest
            self._call("deactivate", timeout=SHUTDOWN_TIMEOUT, wait=self._step_timeout + 1.0)

    def results(self) -> dict[str, Any]:
        """The component's own results(), asked of the child process (the runtime asks after deactivate(), before
        close()), each value as a number or text as inline (:func:`plain_results`); none from a child that is gone or
        stuck in a step. An error there raises here as the node's fault (the runtime logs it as a shutdown fault)."""
        if not self._started() or not self._proc.is_alive() or self._stuck:
            return {}
        return dict(self._call("results", timeout=SHUTDOWN_TIMEOUT, wait=self._step_timeout + 1.0)[2])

    def close(self) -> None:
        got = self._lock.acquire(timeout=self._step_timeout + 1.0)
        try:
            answered = False
            try:
                if got and self._started() and self._proc.is_alive() and not self._stuck:
                    self._exchange("close", (), SHUTDOWN_TIMEOUT)
                    answered = True
            finally:
                # the wake-up pipe is kept while a step may still wait on it (the lock not had: two descriptors
                # left, rather than a number that another file may get while that step still reads it)
                self._end_child(wait=SHUTDOWN_TIMEOUT if answered else 0.0, close_wake=got)
        finally:
            if got:
                self._lock.release()

    def _end_child(self, wait: float, close_wake: bool = True) -> None:
        """The child gone (killed if it has not ended within ``wait`` s: it ignores SIGTERM), the pipe closed and
        every shared-memory block of this node removed, the child's included."""
        try:
            if self._started():
                self._proc.join(timeout=wait)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join(timeout=5.0)
                if not self._proc.is_alive():
                    _track(self._proc, False)
        finally:
            if self._conn is not None:
                self._conn.close()
            if close_wake:
                with self._wake_lock:
                    wake, self._wake, self._poller = self._wake, None, None
                for fd in wake or ():
                    os.close(fd)
            self._lanes.close(unlink_peer=True)
            remove_blocks(self._prefix)

    def status(self) -> dict[str, Any]:
        return self._status
