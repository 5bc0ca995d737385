"""A second Ctrl-C or SIGTERM while a command stops safely is said ("already stopping safely, please wait") and held:
it must not cut the stop short. The runtime held one that came during its own shutdown, but not one that came after
the run returned, while the command finished its stop (a force calibration writing its samples file, `teletouch run`
closing its recording, an experiment reporting the interrupt): that one raised again, so the samples were lost, or
ended the process (return code -2 or -15, a traceback), or turned a Ctrl-C's 130 into SIGTERM's 143. The exit code
is the first signal's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from helpers_signals import stderr_lines

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.cli import EXIT_TERMINATED, main
from teletouch.runtime import EXIT_INTERRUPTED
from teletouch.testing import make_registry

REPO = Path(__file__).resolve().parents[1]
HELD = "already stopping safely, please wait"


# --- the commands as programs: each signal sent at a set point of the command -----------------------------------------
def _program(*patches: tuple[str, signal.Signals, str], after: signal.Signals | None = None) -> str:
    """The CLI as `teletouch` runs it (Python's own Ctrl-C handler, also where this test runs as a background job
    with SIGINT ignored), each patch ``(target, sig, when)`` making ``target`` ("module:name" or "module:Class.name")
    send ``sig`` to the process where it is called with arguments ``a`` for which ``when`` is true: the signal
    arrives at that point, every time. ``after``: a signal sent once main() has returned, as the process exits."""
    lines = ["import importlib, os, signal, sys", "signal.signal(signal.SIGINT, signal.default_int_handler)",
             "def patch(target, sig, when):",
             "    module, _, path = target.partition(':')",
             "    owner = importlib.import_module(module)",
             "    *outer, name = path.split('.')",
             "    for part in outer:",
             "        owner = getattr(owner, part)",
             "    real = getattr(owner, name)",
             "    def signalled(*a, **k):",
             "        if eval(when, {'a': a}):",
             "            os.kill(os.getpid(), sig)",
             "        return real(*a, **k)",
             "    setattr(owner, name, signalled)"]
    lines += [f"patch({target!r}, {int(sig)}, {when!r})" for target, sig, when in patches]
    lines += ["from teletouch.cli import main", "code = main()"]
    if after is not None:
        lines += [f"os.kill(os.getpid(), {int(after)})"]
    lines += ["sys.exit(code)"]
    return "\n".join(lines) + "\n"


def _signalled(program: str, args: list[str], cwd: Path, marker: str = "",
               first: signal.Signals = signal.SIGINT) -> tuple[int, str]:
    """Run ``program`` with ``args`` (and, given a ``marker``, send ``first`` once it shows on stderr: the test fails
    where it never shows); its return code and stderr."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-c", program, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=env, cwd=cwd)
    seen: list[str] = []
    try:
        lines = stderr_lines(p)
        sent = not marker
        while (line := lines.get(timeout=120)) is not None:
            seen.append(line)
            if not sent and marker in line:
                p.send_signal(first)
                sent = True
        assert sent, "".join(seen)[-3000:]
        p.stdout.read()
        code = p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=60)
    return code, "".join(seen)


@pytest.mark.parametrize("first, second, code", [(signal.SIGINT, signal.SIGINT, 130),
                                                 (signal.SIGTERM, signal.SIGINT, 143)])
def test_a_second_signal_while_a_force_calibration_writes_its_samples_is_held(tmp_path, first, second, code):
    program = _program(("teletouch.plugins.estimators.force_calibration:write_pairs_csv", second, "True"))
    graph = str(REPO / "examples" / "calibrate-force-sim.yaml")
    got, err = _signalled(program, ["calibrate", "force", "--graph", graph, "-o", str(tmp_path / "x.force.json")],
                          tmp_path, "t=", first)
    assert got == code, err[-3000:]
    assert f"teletouch: {'Ctrl-C' if second == signal.SIGINT else 'SIGTERM'}: {HELD}" in err, err[-3000:]
    samples = tmp_path / "x.samples.csv"
    assert samples.exists() and "samples to" in err, err[-3000:]   # before: lost to the second signal
    assert len(samples.read_text().splitlines()) > 2
    assert "no calibration written" in err and not (tmp_path / "x.force.json").exists()
    assert "Traceback" not in err


def test_a_sigterm_after_a_ctrl_c_in_an_experiment_keeps_ctrl_c_s_exit_code(tmp_path):
    # before: 143 (the SIGTERM raised again while the experiment reported the Ctrl-C)
    program = _program(("teletouch.runtime:Runtime._run_sim", signal.SIGINT, "True"),   # in the first trial's run
                       ("teletouch.plugins.controllers.experiments:check_run", signal.SIGTERM,
                        "a[0].status == 'interrupted'"))
    got, err = _signalled(program, ["experiment", "pivot", "--trials", "8", "--time-limit", "10", "--out",
                                    str(tmp_path)], tmp_path)
    assert got == EXIT_INTERRUPTED, err[-3000:]
    assert f"teletouch: SIGTERM: {HELD}" in err, err[-3000:]
    assert err.rstrip().endswith("teletouch: interrupted (Ctrl-C)"), err[-3000:]
    assert "Traceback" not in err and "trial 1/8" not in err


@pytest.mark.parametrize("after", [signal.SIGINT, signal.SIGTERM])
def test_a_second_signal_while_the_process_exits_keeps_its_exit_code(tmp_path, after):
    # before: -2 (a KeyboardInterrupt traceback) or -15: Python's shutdown (torch's clean-up) takes ~0.5 s; it may now
    # end the process sooner, with the command's code (test_signals_after_stop.py)
    program = _program(("teletouch.runtime:Runtime._run_sim", signal.SIGINT, "True"), after=after)
    got, err = _signalled(program, ["experiment", "pivot", "--trials", "8", "--out", str(tmp_path)], tmp_path)
    assert got == EXIT_INTERRUPTED, err[-3000:]
    assert err.rstrip().endswith("teletouch: interrupted (Ctrl-C)") and "Traceback" not in err, err[-3000:]


# --- in this process: `teletouch run` and the runtime's own shutdown --------------------------------------------------
class _Kills(Component):
    """Sends its process ``signal`` at t >= 0.05 s, as a real Ctrl-C or SIGTERM would arrive."""

    name = "kills"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        signal: str = "SIGINT"

    def step(self, t, inputs):
        if t >= 0.05:
            os.kill(os.getpid(), signal.Signals[self.params.signal])
        return {"y": 1.0}


class _SlowSafe(Device):
    """A device whose safe state gets the second signal ``signal`` (the operator's Ctrl-C while the devices are made
    safe; none: no signal)."""

    name = "slow-safe"
    inputs = {"command": Port("float64", (), "", required=False)}
    calls: list[str] = []

    class Params(Device.Params):
        signal: str = "SIGINT"

    def step(self, t, inputs):
        return {}

    def safe_state(self):
        if self.params.signal != "none":
            os.kill(os.getpid(), signal.Signals[self.params.signal])
        type(self).calls.append("safe")

    def close(self):
        type(self).calls.append("close")


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Kills, _SlowSafe]


GRAPH = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: slow-safe, rate: 100, params: {signal: SECOND}, inputs: {command: src.value}}
  - {id: k, plugin: kills, rate: 100, params: {signal: FIRST}}
"""


def _graph(tmp_path: Path, first: str, second: str) -> str:
    path = tmp_path / "g.yaml"
    path.write_text(GRAPH.replace("FIRST", first).replace("SECOND", second))
    return str(path)


@pytest.mark.parametrize("first, second, code", [("SIGINT", "SIGTERM", EXIT_INTERRUPTED),
                                                 ("SIGTERM", "SIGINT", EXIT_TERMINATED)])
def test_a_second_signal_while_the_devices_are_made_safe_is_held(tmp_path, monkeypatch, capsys, python_sigint,
                                                                 first, second, code):
    # already so before (the runtime holds signals during its shutdown): the safe stop completes, the first signal's
    # exit code
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_Plugin()))
    monkeypatch.setattr(_SlowSafe, "calls", [])
    assert main(["run", _graph(tmp_path, first, second), "--duration", "1", "--quiet"]) == code
    assert _SlowSafe.calls == ["safe", "close"]
    name = "Ctrl-C" if first == "SIGINT" else "SIGTERM"
    assert capsys.readouterr().err.strip().splitlines()[-1] == (f"teletouch: interrupted ({name}): devices driven "
                                                                f"to their safe state")


@pytest.mark.parametrize("first, second, code", [("SIGINT", "SIGTERM", EXIT_INTERRUPTED),
                                                 ("SIGTERM", "SIGINT", EXIT_TERMINATED),
                                                 ("SIGINT", "SIGINT", EXIT_INTERRUPTED)])
def test_a_second_signal_while_teletouch_run_closes_its_recording_is_held(tmp_path, monkeypatch, capsys,
                                                                          python_sigint, first, second, code):
    # before: the second signal raised in Recorder.close(): the recording was left unfinished, no summary, and a
    # SIGTERM after a Ctrl-C exited 143
    import teletouch.recording as recording
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_Plugin()))
    real = recording.Recorder.close
    closed = []

    def close(self):
        os.kill(os.getpid(), signal.Signals[second])
        real(self)
        closed.append(True)

    monkeypatch.setattr(recording.Recorder, "close", close)
    out = tmp_path / "run.mcap"
    assert main(["run", _graph(tmp_path, first, "none"), "--duration", "1", "--quiet",
                 "--record", str(out)]) == code
    err = capsys.readouterr().err
    assert closed and out.stat().st_size > 0, err
    assert f"teletouch: {'Ctrl-C' if second == 'SIGINT' else 'SIGTERM'}: {HELD}" in err, err
    name = "Ctrl-C" if first == "SIGINT" else "SIGTERM"
    assert err.strip().splitlines()[-1] == f"teletouch: interrupted ({name}): devices driven to their safe state"


def test_the_signal_handlers_are_restored_after_a_command(tmp_path, monkeypatch, python_sigint):
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_Plugin()))
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert main(["run", _graph(tmp_path, "SIGINT", "SIGINT"), "--duration", "1", "--quiet"]) == EXIT_INTERRUPTED
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
