"""Output paths checked before long work (training, a press run, trials): so that results are not lost at the end."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["output_problem"]


def output_problem(path: str | os.PathLike, folder: bool = False) -> str | None:
    """Why nothing can be written at ``path`` (a file; with ``folder`` a folder to write files into), or None if it
    can. Creates nothing: folders missing below the nearest existing one are made when the output is written."""
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
    return None
