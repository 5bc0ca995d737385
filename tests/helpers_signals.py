"""Signalling a teletouch command that runs in a child process at the right moment: its stderr is read line by line
in a thread, so a test reacts to the lines the command (or a test plugin) writes, handshakes rather than sleeps."""

from __future__ import annotations

import queue
import subprocess
import threading


def stderr_lines(p: subprocess.Popen) -> queue.Queue:
    """The lines of ``p``'s stderr (opened as text) as they come, then None once it is closed."""
    out: queue.Queue = queue.Queue()

    def read() -> None:
        for line in p.stderr:
            out.put(line)
        out.put(None)

    threading.Thread(target=read, daemon=True).start()
    return out
