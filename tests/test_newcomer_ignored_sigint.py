"""A newcomer's `teletouch run P --clock wall --duration 20 & kill -INT $!` from a script ran all 20 s and exited 0,
silently: a background job of a non-interactive shell starts with SIGINT ignored, and teletouch keeps it ignored on
purpose (core/cli.py `_interrupts`). The program now says so once at the start of a long command, on stderr, with how
to stop it (SIGTERM); a quick command (validate, plugins, ...) and a caller of main(argv) are not told."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from helpers_signals import stderr_lines

from teletouch.cli import EXIT_TERMINATED, main
from teletouch.testing import make_registry

NOTE = "teletouch: SIGINT is ignored (started in the background by a script): stop it with SIGTERM (kill {pid})"
WALL = """
clock: wall
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: src.value}}
"""
SIM = WALL.replace("clock: wall", "clock: sim")


def test_a_run_started_with_sigint_ignored_says_so_and_stops_on_sigterm(tmp_path):
    graph = tmp_path / "g.yaml"
    graph.write_text(WALL)
    env = dict(os.environ, PYTHONUNBUFFERED="1", TELETOUCH_DISABLE_PLUGIN_AUTOLOAD="1",
               TELETOUCH_PLUGINS="teletouch.mock")
    p = subprocess.Popen([sys.executable, "-m", "teletouch", "run", str(graph), "--duration", "20", "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))   # as `cmd &` in a script
    seen: list[str] = []
    try:
        lines = stderr_lines(p)
        while (line := lines.get(timeout=120)) is not None:
            seen.append(line)
            if "SIGINT is ignored" in line:
                p.send_signal(signal.SIGINT)    # ignored, as the note says
                p.send_signal(signal.SIGTERM)   # what it says to send
        code = p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=60)
    err = "".join(seen)
    assert NOTE.format(pid=p.pid) in err.splitlines(), err[-3000:]
    assert err.count("SIGINT is ignored") == 1, err[-3000:]
    assert code == EXIT_TERMINATED and "interrupted (SIGTERM)" in err, (code, err[-3000:])


@pytest.fixture
def ignored_sigint():
    """SIGINT ignored in this process for the test (as a background job starts), the handler restored after."""
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _program(monkeypatch, tmp_path, *args: str) -> None:
    """main() as the program runs it (argv None: the command line from sys.argv), with the mocks only."""
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry())
    graph = tmp_path / "g.yaml"
    graph.write_text(SIM)
    monkeypatch.setattr(sys, "argv", ["teletouch", args[0], str(graph), *args[1:]])


def test_the_note_comes_first_and_once_in_a_run(ignored_sigint, monkeypatch, tmp_path, capsys):
    _program(monkeypatch, tmp_path, "run", "--duration", "0.5", "--quiet")
    assert main() == 0
    err = capsys.readouterr().err.splitlines()
    assert err[0] == NOTE.format(pid=os.getpid()), err
    assert sum("SIGINT is ignored" in line for line in err) == 1, err


def test_a_quick_command_is_not_told(ignored_sigint, monkeypatch, tmp_path, capsys):
    _program(monkeypatch, tmp_path, "validate")
    assert main() == 0
    assert "SIGINT" not in capsys.readouterr().err


def test_nothing_is_said_where_ctrl_c_works(monkeypatch, tmp_path, capsys):
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _program(monkeypatch, tmp_path, "run", "--duration", "0.5", "--quiet")
        assert main() == 0
    finally:
        signal.signal(signal.SIGINT, old)
    assert "SIGINT" not in capsys.readouterr().err


def test_a_caller_of_main_with_its_own_argv_is_not_told(ignored_sigint, monkeypatch, tmp_path, capsys):
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry())
    graph = tmp_path / "g.yaml"
    graph.write_text(SIM)
    assert main(["run", str(graph), "--duration", "0.5", "--quiet"]) == 0
    assert "SIGINT" not in capsys.readouterr().err


def test_the_readme_says_what_an_ignored_sigint_means():
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    start = text.index("Exit codes:")
    assert "SIGINT ignored" in text[start:start + 1500] and "kill PID" in text[start:start + 1500]
