"""What the machine was doing while a benchmark measured: hypervisor steal, idle share, load (Linux /proc/stat).

Timing results on a shared VM mean little without it. Imported by the benchmarks that measure wall-clock timing
(they run as `python benchmarks/NAME.py`, so this folder is on sys.path).
"""

from __future__ import annotations

import os


def cpu_times() -> list[int] | None:
    """The machine-wide CPU time counters of /proc/stat (None where there is no /proc)."""
    try:
        with open("/proc/stat") as fh:
            return [int(x) for x in fh.readline().split()[1:]]
    except OSError:
        return None


def machine_noise(before: list[int] | None, after: list[int] | None) -> dict:
    """Share of the machine's CPU time stolen by the hypervisor, idle, and the load, between two cpu_times()."""
    if not before or not after:
        return {}
    d = [b - a for a, b in zip(before, after)]
    total = sum(d) or 1
    return {"steal_fraction": d[7] / total if len(d) > 7 else None, "idle_fraction": d[3] / total,
            "loadavg_1min": os.getloadavg()[0]}
