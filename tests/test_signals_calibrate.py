"""`teletouch calibrate force` whose press routine finished, but whose run a Ctrl-C or SIGTERM ended as it stopped (the
runtime held it in its shutdown: RunResult.late_signal), writes its calibration (it is complete) and exits as
`teletouch run` does for that run: 130 (143 for SIGTERM), saying so. It exited 0, as if no signal had come."""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path

import pytest

from teletouch.cli import EXIT_TERMINATED
from teletouch.runtime import EXIT_INTERRUPTED

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_cli_signals import HELD, REPO, _program, _signalled  # noqa: E402

NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, EXIT_INTERRUPTED), (signal.SIGTERM, EXIT_TERMINATED)])
def test_a_signal_held_as_a_finished_press_run_stops_writes_the_calibration_and_exits_with_its_code(tmp_path, sig,
                                                                                                      code):
    program = _program(("teletouch.runtime:Runtime._shutdown", sig, "True"))
    graph = str(REPO / "examples" / "calibrate-force-sim.yaml")
    out = tmp_path / "x.force.json"
    got, err = _signalled(program, ["calibrate", "force", "--graph", graph, "--quiet", "--degree", "2",
                                    "--set", "routine.cycles=1", "--set", "routine.max_displacement=0.6mm",
                                    "-o", str(out)], tmp_path)
    assert got == code, err[-3000:]   # before: 0
    assert f"teletouch: {NAMES[sig]}: {HELD}" in err, err[-3000:]
    assert out.exists() and json.loads(out.read_text()), err[-3000:]   # complete: written
    assert (tmp_path / "x.samples.csv").exists() and (tmp_path / "x.png").exists()
    assert err.rstrip().splitlines()[-1] == (f"teletouch: interrupted ({NAMES[sig]}): devices driven to their safe "
                                             f"state; the press routine had finished: its calibration is written")
    assert "no calibration written" not in err and "Traceback" not in err


def test_a_signal_held_as_a_finished_press_run_stops_keeps_its_code_when_the_fit_refuses_the_samples(tmp_path):
    program = _program(("teletouch.runtime:Runtime._shutdown", signal.SIGINT, "True"))
    graph = str(REPO / "examples" / "calibrate-force-sim.yaml")
    out = tmp_path / "x.force.json"
    got, err = _signalled(program, ["calibrate", "force", "--graph", graph, "--quiet", "--degree", "2",
                                    "--min-depth", "5mm", "--set", "routine.cycles=1",
                                    "--set", "routine.max_displacement=0.6mm", "-o", str(out)], tmp_path)
    assert got == EXIT_INTERRUPTED, err[-3000:]   # before: 1, the fit's refusal, as if no signal had come
    assert "no sample with a max depth of at least 5.000 mm" in err, err[-3000:]
    assert not out.exists() and (tmp_path / "x.samples.csv").exists()   # the samples are kept for --csv
    assert err.rstrip().splitlines()[-1] == ("teletouch: interrupted (Ctrl-C): devices driven to their safe state; "
                                             "the press routine had finished but its samples gave no calibration: "
                                             "none written")
    assert "Traceback" not in err
