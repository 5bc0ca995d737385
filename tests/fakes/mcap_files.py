"""MCAP files as a crashed run leaves them: written by the real Recorder in two flushes, so a test can cut the file
inside the records of the second flush (the first still readable). Also: disks that fill up or stall, a value that
holds the Recorder's writer thread (a slow disk: what is tapped meanwhile waits in the queue), and a teletouch-style
recording of camera images, one of which can be damaged."""

from __future__ import annotations

import threading
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


class StuckValue:
    """A value whose encoding (the JSON codec's repr) holds the Recorder's writer thread until ``release`` is set:
    what is tapped meanwhile waits in the queue, as behind a slow disk. ``entered`` is set once the writer holds it;
    it waits ``guard`` s at most for ``release``."""

    def __init__(self, guard: float = 10.0):
        self.entered, self.release = threading.Event(), threading.Event()
        self.guard = guard

    def __repr__(self) -> str:
        if threading.current_thread().name != "teletouch-recorder":   # (pytest's report of a failed assert)
            return "stuck"
        self.entered.set()
        assert self.release.wait(self.guard), "never released"
        return "stuck"


def hold_writer(rec: Any, guard: float = 10.0) -> StuckValue:
    """Tap a StuckValue into the Recorder ``rec`` (node "slow", port "obj", at 0 s) and return it once the writer
    holds it (the queue is then empty); set its ``release`` to let the writer go on."""
    stuck = StuckValue(guard)
    rec.tap("slow", 0.0, {"obj": stuck})
    assert stuck.entered.wait(guard), "the writer never took the first sample"
    return stuck


def damage_png(data: bytes) -> bytes:
    """The CDR bytes of a CompressedImage message with its PNG signature overwritten: the message itself is intact,
    its image cannot be decoded."""
    at = data.index(b"\x89PNG")
    return data[:at] + b"\x00" * 8 + data[at + 8:]


def write_image_recording(path: Path, messages: list[tuple[int, bytes]]) -> None:
    """A teletouch-style recording (graph epoch 0) of CDR sensor_msgs/msg/CompressedImage messages on the channel
    /cam/image (node cam, port image): each message is (log time in ns, data)."""
    from mcap.writer import Writer

    from teletouch.recording import ros2msg_definition

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="teletouch")
        w.add_metadata("teletouch.time", {"graph_epoch_ns": "0"})
        sid = w.register_schema("sensor_msgs/msg/CompressedImage", "ros2msg",
                                ros2msg_definition("sensor_msgs/msg/CompressedImage").encode())
        cid = w.register_channel("/cam/image", "cdr", sid, {"node": "cam", "port": "image", "codec": "compressed",
                                                              "dtype": "uint8", "shape": "[null, null, 3]"})
        for t, data in messages:
            w.add_message(cid, log_time=t, publish_time=t, data=data)
        w.finish()
