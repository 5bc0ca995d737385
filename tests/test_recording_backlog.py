"""The recorder's queue accounting under taps from several node threads at once: the admission check (max_queue,
max_queue_bytes) and ``max_backlog`` were read and written outside the lock that guards the queue's byte count.

The interleavings are forced, not hoped for: a queue stand-in lets one thread stop right inside the check (after it
has read the queue's size, or the old ``max_backlog``) until a second thread has gone through the tap, or has come
to the recorder's lock and has to wait for it (the fixed recorder checks under ``_q_lock``; the stand-in lock below
reports a thread arriving at it). Events only; the waits' timeouts are a guard against a hang, not the schedule.
"""

from __future__ import annotations

import threading

import numpy as np

from teletouch.recording import Recorder

GUARD = 30.0   # s: only a broken test waits this long


class _Stall:
    """Stops thread "tap-A" once, where :meth:`point` is called, until the other tap is through or waits for the
    recorder's lock (``resume``)."""

    def __init__(self):
        self.armed = False
        self.stopped = threading.Event()
        self.resume = threading.Event()

    def point(self) -> None:
        if self.armed and threading.current_thread().name == "tap-A" and not self.stopped.is_set():
            self.stopped.set()
            assert self.resume.wait(GUARD), "the other tap never came through or to the lock"


class _Queue:
    """Stands in for the recorder's queue: keeps what is put (nothing leaves it); with ``stall_in_qsize`` thread A
    stops in qsize() after reading the size. The writer thread may have taken it for its own queue (it reads
    ``_q`` once, when it starts): get() waits on the writer's real queue, where close() puts its stop."""

    def __init__(self, stall: _Stall, real, items: int = 0, stall_in_qsize: bool = False):
        self.items: list = [object()] * items
        self.stall, self.stall_in_qsize, self.real = stall, stall_in_qsize, real

    def get(self, timeout=None):
        return self.real.get(timeout=timeout)

    def qsize(self) -> int:
        n = len(self.items)
        if self.stall_in_qsize:
            self.stall.point()
        return n

    def put(self, item) -> None:
        self.items.append(item)


class _ReportingLock:
    """The recorder's lock, reporting (``arrived``) when thread "tap-B" comes to it, before it waits for it."""

    def __init__(self, arrived: threading.Event):
        self._lock = threading.Lock()
        self.arrived = arrived

    def __enter__(self):
        if threading.current_thread().name == "tap-B":
            self.arrived.set()
        self._lock.acquire()
        return self

    def __exit__(self, *exc):
        self._lock.release()


def _stalling(attr: str) -> type[Recorder]:
    """A Recorder whose attribute ``attr`` is read in two halves: thread A reads the value, then stops (the
    recorder's ``_stall``) before it uses it, as a thread switch can make it."""

    def get(self):
        value = self.__dict__.get("_v_" + attr, 0)
        stall = self.__dict__.get("_stall")
        if stall is not None:
            stall.point()
        return value

    def put(self, value):
        self.__dict__["_v_" + attr] = value

    return type(f"Stalling_{attr}", (Recorder,), {attr: property(get, put)})


def _race(tmp_path, tap_a: dict, tap_b: dict, items: int = 0, stall_attr: str | None = None, **kw):
    """Tap ``tap_a`` from thread A, stopped inside its check (in qsize(), or reading ``stall_attr``), then
    ``tap_b`` from thread B; A goes on once B is through or waits for the lock A holds. Returns the recorder (its
    writer's own queue put back) and the queue stand-in (what was queued)."""
    rec = (_stalling(stall_attr) if stall_attr else Recorder)(tmp_path / "r.mcap", None, log=lambda m: None, **kw)
    rec.tap("warm", 0.0, {"x": 0.0})          # sets the epoch (its metadata item goes on the writer's queue)
    real = rec._q
    stall, b_through = _Stall(), threading.Event()
    q = _Queue(stall, real, items, stall_in_qsize=stall_attr is None)
    rec._q = q
    rec._q_lock = _ReportingLock(b_through)   # an attribute the recorder before the fix did not use
    rec.max_backlog = 0
    rec._stall = stall
    stall.armed = True

    def run_b():
        try:
            rec.tap("b", 0.1, tap_b)
        finally:
            b_through.set()

    a = threading.Thread(target=rec.tap, args=("a", 0.1, tap_a), name="tap-A")
    b = threading.Thread(target=run_b, name="tap-B")
    try:
        a.start()
        assert stall.stopped.wait(GUARD)
        b.start()
        assert b_through.wait(GUARD)
        stall.resume.set()
        a.join(GUARD)
        b.join(GUARD)
        assert not a.is_alive() and not b.is_alive()
    finally:
        stall.resume.set()
        rec._stall = None
        rec._q = real
        rec.close()
    return rec, q


def test_two_taps_cannot_both_take_the_last_place_in_the_queue(tmp_path):
    rec, q = _race(tmp_path, {"force": 1.0}, {"force": 2.0, "depth_max": 1e-4}, items=2, max_queue=3)
    assert len(q.items) == 3, f"{len(q.items)} items queued with max_queue 3"
    assert [it[0] for it in q.items[2:]] == ["a"]   # A checked first and holds the place; B's two samples dropped
    assert rec.dropped == 2
    assert rec.max_backlog == 3


def test_two_taps_cannot_both_take_the_last_free_bytes(tmp_path):
    img = np.zeros((10, 10), np.uint8)          # 100 bytes each; room for one more
    rec, q = _race(tmp_path, {"image": img}, {"image": img}, stall_attr="_queued_bytes", max_queue=100,
                   max_queue_bytes=150)
    assert [it[0] for it in q.items] == ["a"], "both images queued past max_queue_bytes 150"
    assert rec.dropped == 1


def test_a_larger_backlog_seen_by_another_tap_is_not_overwritten_by_a_smaller_one(tmp_path):
    rec, q = _race(tmp_path, {"force": 1.0}, {"force": 2.0}, items=1, stall_attr="max_backlog", max_queue=100)
    assert len(q.items) == 3                    # the one waiting, A's and B's
    assert rec.max_backlog == 3, f"max_backlog {rec.max_backlog} while 3 items waited for the writer"


def test_max_backlog_counts_the_item_just_queued_also_without_a_queue_limit(tmp_path):
    for limit in (0, 20000):   # 0: no limit (max_backlog stayed 0 before: it was only measured with a limit)
        rec = Recorder(tmp_path / f"r{limit}.mcap", None, max_queue=limit, log=lambda m: None)
        rec.tap("warm", 0.0, {"x": 0.0})
        real = rec._q
        q = _Queue(_Stall(), real)
        rec._q, rec.max_backlog = q, 0
        try:
            rec.tap("a", 0.1, {"force": 1.0})
            assert rec.max_backlog == 1, f"max_queue {limit}: max_backlog {rec.max_backlog} with 1 item waiting"
            rec.tap("a", 0.2, {"force": 1.0})
            assert rec.max_backlog == 2
        finally:
            rec._q = real
            rec.close()
