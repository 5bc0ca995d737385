"""Reproducible output files: the time a file records, taken from SOURCE_DATE_EPOCH when it is set.

The reproducible-builds convention (https://reproducible-builds.org/specs/source-date-epoch/): a tool that writes
the current time into what it makes writes SOURCE_DATE_EPOCH instead when the variable is set, so the same inputs
give byte-identical files. teletouch's depth models and force calibrations do.
"""

from __future__ import annotations

import os
import time

__all__ = ["source_date_epoch", "build_time", "software_versions"]

#: 9999-12-31T23:59:59Z: a later time is no date a file can record (datetime's and ISO 8601's four-digit year)
MAX_SOURCE_DATE_EPOCH = 253402300799


def source_date_epoch() -> int | None:
    """The environment's SOURCE_DATE_EPOCH (whole seconds since 1970-01-01 UTC), or None when unset or empty.
    ValueError naming the variable when it is not such a number (the convention: refuse, rather than write the
    clock's time)."""
    text = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if not text:
        return None
    if not (text.isascii() and text.isdigit()):
        raise ValueError(f"SOURCE_DATE_EPOCH {text!r}: expected a whole number of seconds since 1970-01-01 UTC, e.g. "
                         f"$(git log -1 --format=%ct) (reproducible builds), or leave it unset")
    value = int(text)
    if value > MAX_SOURCE_DATE_EPOCH:
        raise ValueError(f"SOURCE_DATE_EPOCH {text}: after 9999-12-31T23:59:59Z ({MAX_SOURCE_DATE_EPOCH}), the last "
                         f"time an output file can record as a date")
    return value


def build_time() -> float:
    """The time to write into an output file: SOURCE_DATE_EPOCH when set, else now (s since 1970-01-01 UTC)."""
    sde = source_date_epoch()
    return float(sde) if sde is not None else time.time()


def software_versions() -> dict[str, str]:
    """The versions of what a trained or fitted file's numbers depend on (Python, numpy, torch, OpenCV), recorded in
    it: the same inputs give the same file bit for bit only with the same versions (a training run amplifies a
    rounding difference), so a file that another run does not reproduce says with what it was made."""
    import platform

    out = {"python": platform.python_version(), "machine": platform.machine()}
    for name, module in (("numpy", "numpy"), ("torch", "torch"), ("opencv", "cv2")):
        try:
            out[name] = str(__import__(module).__version__)
        except ImportError:
            out[name] = "not installed"
    return out
