"""SIGTERM stops every command as Ctrl-C does, not only `teletouch run`: a force calibration (which drives an Omega.7
on the real setup) given SIGTERM used to die at once (return code -15: no safe stop, no message, no samples file)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _start(args: list[str], cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "teletouch", *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _term_when(proc: subprocess.Popen, marker: str, timeout: float = 120.0) -> tuple[str, str]:
    """SIGTERM once ``marker`` shows on stderr (the command is working), then its output."""
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line and proc.poll() is not None:
            break
        seen.append(line)
        if marker in line:
            proc.send_signal(signal.SIGTERM)
            break
    out, err = proc.communicate(timeout=120)
    return out, "".join(seen) + err


def test_sigterm_during_a_force_calibration_is_a_safe_stop_with_its_samples(tmp_path):
    proc = _start(["calibrate", "force", "--graph", str(REPO / "examples" / "calibrate-force-sim.yaml"), "-o",
                   str(tmp_path / "x.force.json")], tmp_path)
    out, err = _term_when(proc, "t=")   # the live view's first line: the press run is going
    assert proc.returncode == 143, err[-2000:]
    assert "interrupted (SIGTERM)" in err and "safe state" in err, err[-2000:]
    assert "run interrupted: interrupted" not in err   # said once
    assert not (tmp_path / "x.force.json").exists()
    assert "samples to" in err and (tmp_path / "x.samples.csv").exists(), err[-2000:]


def test_sigterm_during_an_experiment_exits_143(tmp_path):
    proc = _start(["experiment", "pivot", "--trials", "8", "--time-limit", "10", "--out", str(tmp_path)], tmp_path)
    out, err = _term_when(proc, "trial 1/8")   # its first trial done: the next one is running
    assert proc.returncode == 143, err[-2000:]
    assert err.rstrip().endswith("teletouch: interrupted (SIGTERM)"), err[-2000:]
    assert "trial 8/8" not in err
