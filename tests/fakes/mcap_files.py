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
