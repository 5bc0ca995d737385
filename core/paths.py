"""Output paths checked before long work (training, a press run, trials): so that results are not lost at the end."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["output_problem"]


def output_problem(path: str | os.PathLike, folder: bool = False) -> str | None:
    """Why nothing can be written at ``path`` (a file; with ``folder`` a folder to write files into), or None if it
    can. Leaves nothing behind: folders missing below the nearest existing one are made when the output is written,
    and the nearest existing folder is probed by creating and removing a temporary file in it (permission bits do not
    tell for root, a read-only file system or a pseudo file system such as /proc)."""
    p = Path(path)
    if folder and p.exists() and not p.is_dir():
        return "exists and is not a folder"
    if not folder and p.is_dir():
        return "is a folder, expected a file name"
    if not folder and p.exists() and not os.access(p, os.W_OK):
        return "the file exists and is not writable"
    d = p if folder else p.parent
    while not os.path.lexists(d) and d != d.parent:
        d = d.parent
    if not d.is_dir():
        return f"{d} is a file, not a folder"
    if not os.access(d, os.W_OK | os.X_OK):
        return f"the folder {d} is not writable"
    try:
        fd, probe = tempfile.mkstemp(prefix=".teletouch-probe-", dir=d)
    except OSError as exc:
        return f"cannot write in the folder {d}: {exc.strerror or exc}"
    os.close(fd)
    os.unlink(probe)
    return None
