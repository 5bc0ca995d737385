"""Output paths checked before long work (training, a press run, trials): so that results are not lost at the end;
input files named by a path or a packaged name (a depth model, a force calibration), found or named as missing."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable, Sequence

from .errors import ModelFileError

__all__ = ["output_problem", "input_file"]


def input_file(spec: str | os.PathLike, noun: str, suffix: str, command: str,
               packaged: Callable[[str], Path | None], shipped: Sequence[str]) -> Path:
    """The existing file ``spec`` names: a path (``~`` expanded; a relative one from the current folder), else a
    packaged file's name (``packaged(name)``: its path or None). Else ModelFileError naming it as empty, a folder or
    missing, with what was expected: a ``noun`` file (its ``suffix``, made by ``command``, e.g. "`teletouch calibrate
    depth`"), where a relative path was looked for, the ``shipped`` names, how to make one."""
    made = f"{suffix} from {command}"
    s = str(spec)
    if not s.strip():
        raise ModelFileError(f"empty: expected a {noun} file ({made}) or a packaged {noun}'s name")
    p = Path(s).expanduser()
    if p.is_file():
        return p
    if p.is_dir():
        raise ModelFileError(f"{s}: a folder, expected a {noun} file ({made})")
    q = packaged(s)
    if q is not None:
        return q
    raise ModelFileError(f"{s}: no such {noun} file{looked_at(p)}, and no packaged {noun} of that name (packaged: "
                         f"{', '.join(shipped) or 'none'}); make one with {command}")


def looked_at(p: Path) -> str:
    """Where a relative path that names nothing was looked for, for an error (" (looked at ...)"; "" for an absolute
    one): a graph's parameters are taken from the current folder, not the graph file's, as `include:` is."""
    if p.is_absolute():
        return ""
    return f" (looked at {Path.cwd() / p}: a relative path is taken from the current folder, not the graph file's)"


def output_problem(path: str | os.PathLike, folder: bool = False, make_folders: bool = True) -> str | None:
    """Why nothing can be written at ``path`` (a file; with ``folder`` a folder to write files into), or None if it
    can. Leaves nothing behind: folders missing below the nearest existing one are made when the output is written
    (``make_folders`` False: the file's folder, or the folder's parent, must exist: a typo in a path would make
    folders silently), and the nearest existing folder is probed by creating and removing a temporary file in it
    (permission bits do not tell for root, a read-only file system or a pseudo file system such as /proc)."""
    text = os.fspath(path)
    try:
        problem = _problem(Path(text), folder)
    except OSError as exc:   # e.g. a name too long for the file system, met on stat()
        return f"{exc.strerror or exc}"
    if problem is None and not folder and text.endswith(("/", os.sep)):   # (Path drops the separator)
        return "ends in a separator, so it names a folder; expected a file name"
    if problem is None and not make_folders and not Path(text).parent.is_dir():
        return f"the folder {Path(text).parent} does not exist (create it first)"
    return problem


def _problem(p: Path, folder: bool) -> str | None:
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
    too_long = _name_too_long(d, p.relative_to(d).parts if p != d else ())
    if too_long:
        return too_long
    if not os.access(d, os.W_OK | os.X_OK):
        return f"the folder {d} is not writable"
    try:
        fd, probe = tempfile.mkstemp(prefix=".teletouch-probe-", dir=d)
    except OSError as exc:
        return f"cannot write in the folder {d}: {exc.strerror or exc}"
    os.close(fd)
    os.unlink(probe)
    return None


def _name_too_long(existing: Path, missing: tuple[str, ...]) -> str | None:
    """Why one of the ``missing`` names (folders to make, then the file) cannot be made in the folder ``existing``:
    longer than its file system allows (the probe, a short name in ``existing``, does not tell)."""
    try:
        limit = os.pathconf(existing, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for name in missing:
        if len(os.fsencode(name)) > limit:
            return f"the name {name[:24]}... is too long ({len(os.fsencode(name))} bytes; at most {limit} here)"
    return None
