"""A SIGINT or SIGTERM that comes while the runtime drives the devices to their safe state and closes the components
is held (RunResult.late_signal). It was held silently, where the command line says a held signal ("already stopping
safely, please wait"); and when it was the stop's FIRST signal (a run that was ending on its own, at its duration),
the command line was never told that a stop began: a later signal raised KeyboardInterrupt in a command's own code
after the run (a force calibration lost its samples file), and a SIGTERM there exited 130 (Ctrl-C's code) where an
experiment reported it."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

from teletouch import Device, Port, hookimpl
from teletouch.cli import EXIT_TERMINATED, main
from teletouch.graph import load_graph
from teletouch.runtime import EXIT_INTERRUPTED, Runtime
from teletouch.testing import make_registry

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_cli_signals import HELD, REPO, _program, _signalled  # noqa: E402


# --- as programs: the first signal lands in the runtime's shutdown of a run that was ending ---------------------------
@pytest.mark.parametrize("first, second, code", [(signal.SIGTERM, signal.SIGINT, EXIT_TERMINATED),
                                                 (signal.SIGINT, signal.SIGTERM, EXIT_INTERRUPTED)])
def test_a_signal_after_one_the_runtime_held_is_held_while_a_force_calibration_writes_its_samples(tmp_path, first,
                                                                                                   second, code):
    # before: the second signal raised in write_pairs_csv: no samples file, "interrupted" with the second's code
    program = _program(("teletouch.runtime:Runtime._shutdown", first, "True"),
                       ("teletouch.plugins.estimators.force_calibration:write_pairs_csv", second, "True"))
    graph = str(REPO / "examples" / "calibrate-force-sim.yaml")
    got, err = _signalled(program, ["calibrate", "force", "--graph", graph, "--duration", "15", "--quiet",
                                    "-o", str(tmp_path / "x.force.json")], tmp_path)
    names = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
    assert got == code, err[-3000:]
    assert f"teletouch: {names[first]}: {HELD}" in err, err[-3000:]    # the runtime's, said
    assert f"teletouch: {names[second]}: {HELD}" in err, err[-3000:]   # the command line's
    samples = tmp_path / "x.samples.csv"
    assert samples.exists() and "samples to" in err, err[-3000:]
    assert len(samples.read_text().splitlines()) > 2
    assert f"interrupted ({names[first]})" in err and "no calibration written" in err, err[-3000:]
    assert not (tmp_path / "x.force.json").exists() and "Traceback" not in err


def test_a_sigterm_the_runtime_held_ends_an_experiment_with_sigterm_s_exit_code(tmp_path):
    # before: 130 and "interrupted (Ctrl-C)": the command line had seen no signal, the experiment raised
    # KeyboardInterrupt for the interrupted trial
    program = _program(("teletouch.runtime:Runtime._shutdown", signal.SIGTERM, "True"))
    got, err = _signalled(program, ["experiment", "pivot", "--trials", "8", "--time-limit", "10", "--out",
                                    str(tmp_path)], tmp_path)
    assert got == EXIT_TERMINATED, err[-3000:]
    assert f"teletouch: SIGTERM: {HELD}" in err, err[-3000:]
    assert err.rstrip().endswith("teletouch: interrupted (SIGTERM)"), err[-3000:]
    assert "Traceback" not in err and "trial 2/8" not in err


# --- in this process ------------------------------------------------------------------------------------------------
class _SignalsAtSafe(Device):
    """A device whose safe state gets the signals ``signals`` (the operator's Ctrl-C as the devices are made safe)."""

    name = "signals-at-safe"
    inputs = {"command": Port("float64", (), "", required=False)}

    class Params(Device.Params):
        signals: list[str] = ["SIGTERM"]

    def step(self, t, inputs):
        return {}

    def safe_state(self):
        for name in self.params.signals:
            os.kill(os.getpid(), signal.Signals[name])


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_SignalsAtSafe]


def _graph(tmp_path: Path, signals: list[str]) -> Path:
    path = tmp_path / "g.yaml"
    path.write_text("clock: sim\nnodes:\n  - {id: src, plugin: mock-sensor, rate: 100}\n"
                    f"  - {{id: dev, plugin: signals-at-safe, rate: 100, params: {{signals: {signals}}}, "
                    "inputs: {command: src.value}}\n")
    return path


def test_a_signal_the_runtime_holds_is_said_on_stderr(tmp_path, monkeypatch, capsys, python_sigint):
    # before: held silently (the operator saw nothing happen and pressed again)
    reg = make_registry(_Plugin())
    rt = Runtime(load_graph(_graph(tmp_path, ["SIGTERM", "SIGINT"]), registry=reg))
    result = rt.run(0.2)
    assert (result.status, result.exit_code, result.late_signal) == ("interrupted", EXIT_INTERRUPTED,
                                                                      signal.SIGTERM)
    err = capsys.readouterr().err
    assert err.splitlines() == [f"teletouch: SIGTERM: {HELD}", f"teletouch: Ctrl-C: {HELD}"], err


def test_a_signal_the_runtime_holds_during_teletouch_run_is_said_once_and_sets_the_exit_code(tmp_path, monkeypatch,
                                                                                             capsys, python_sigint):
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_Plugin()))
    assert main(["run", str(_graph(tmp_path, ["SIGTERM", "SIGINT"])), "--duration", "0.2",
                 "--quiet"]) == EXIT_TERMINATED
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"teletouch: SIGTERM: {HELD}", f"teletouch: Ctrl-C: {HELD}",
                   "teletouch: interrupted (SIGTERM): devices driven to their safe state"], err


def test_an_ignored_signal_stays_ignored_while_the_runtime_holds_signals():
    # before: the shutdown's hold took over SIGINT also where it was ignored (a job started with nohup or `&`): a
    # Ctrl-C meant for the shell's foreground job was then said and counted by the background run
    import signal

    from teletouch.runtime import _signals_deferred

    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with _signals_deferred():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN   # (held as before)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, old)
