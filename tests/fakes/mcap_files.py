"""MCAP files as a crashed run leaves them: written by the real Recorder in two flushes, so a test can cut the file
inside the records of the second flush (the first still readable)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any


def messages_on_disk(path: Path) -> int:
    """How many messages a reader finds in the file as it is now (0 while it cannot be read)."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    n = 0
    try:
        with open(path, "rb") as fh:
            for r in StreamReader(fh).records:
                n += isinstance(r, Message)
    except Exception:
        pass
    return n


def chunk_offsets(path: Path) -> list[int]:
    """Byte offsets of the file's chunks."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    out = []
    with open(path, "rb") as fh:
        it = StreamReader(fh, emit_chunks=True).records
        while True:
            pos = fh.tell()
            r = next(it, None)
            if r is None:
                return out
            if isinstance(r, Chunk):
                out.append(pos)


def record_in_two_flushes(path: Path, taps: list[tuple[str, float, dict[str, Any]]], first: int,
                          messages_first: int) -> tuple[list[int], int]:
    """Record ``taps`` (node, t, outputs) with the Recorder, waiting after the first ``first`` of them until
    ``messages_first`` messages are on disk (the writer flushed them). Returns the chunk offsets and the file size
    after the first flush."""
    from teletouch.recording import Recorder

    first_go = 0
    with Recorder(path, None, flush_interval=0.01, log=lambda m: None) as rec:
        for k, (node, t, out) in enumerate(taps):
            rec.tap(node, t, out)
            if k == first - 1:
                deadline = time.monotonic() + 20
                while messages_on_disk(path) < messages_first and time.monotonic() < deadline:
                    time.sleep(0.01)
                first_go = path.stat().st_size
    return chunk_offsets(path), first_go


class FullDisk:
    """``open()`` for the recording module whose "wb" files take ``capacity`` bytes and then fail as a full disk
    does: a short write, then OSError ENOSPC on every write (reading is the real ``open``)."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.failures = 0

    def __call__(self, file: Any, mode: str = "r", *args: Any, **kw: Any) -> Any:
        import builtins
        import io

        if mode != "wb":
            return builtins.open(file, mode, *args, **kw)
        disk = self

        class _Raw(io.RawIOBase):
            def __init__(self) -> None:
                self.fh = builtins.open(file, "wb", buffering=0)

            def writable(self) -> bool:
                return True

            def seekable(self) -> bool:
                return True

            def tell(self) -> int:
                return self.fh.tell()

            def seek(self, pos: int, whence: int = 0) -> int:
                return self.fh.seek(pos, whence)

            def write(self, b: Any) -> int:
                room = disk.capacity - self.fh.tell()
                if room <= 0:
                    disk.failures += 1
                    raise OSError(28, "No space left on device")
                return self.fh.write(bytes(b)[:room])

            def close(self) -> None:
                self.fh.close()
                super().close()

        return io.BufferedWriter(_Raw())


class StalledDisk(FullDisk):
    """``open()`` for the recording module whose "wb" files take ``capacity`` bytes and then block every write until
    ``release`` is set, as a stalled network disk does (no error: the write never returns)."""

    def __init__(self, capacity: int):
        import threading

        super().__init__(capacity)
        self.release = threading.Event()
        self.blocked = threading.Event()

    def __call__(self, file: Any, mode: str = "r", *args: Any, **kw: Any) -> Any:
        fh = super().__call__(file, mode, *args, **kw)
        if mode != "wb":
            return fh
        raw = fh.raw
        full_write = type(raw).write
        disk = self

        def write(b: Any) -> int:
            if raw.fh.tell() + len(b) > disk.capacity:
                disk.blocked.set()
                disk.release.wait()
            return full_write(raw, b)

        raw.write = write
        return fh
