"""Under the command line a signal that stopped nothing still counted as the stop's first: a plugin that caught the
KeyboardInterrupt of the first Ctrl-C and carried on (its configure(), or its close() when the start-up closes a node
that failed to configure) left every later signal only "held" ("already stopping safely, please wait") while the
start-up ran to its end and the run went on: the operator's second Ctrl-C seemed ignored. A signal now stops a run
until that run is stopping (its shutdown reached, or a KeyboardInterrupt on its way there), as a run in a program of
its own does (runtime._ctrl_c_until_stopping); the signal that stops it gives the exit code."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers_signals import stderr_lines

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.cli import EXIT_TERMINATED, main
from teletouch.runtime import EXIT_INTERRUPTED
from teletouch.testing import make_registry

HELD = "already stopping safely, please wait"
NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}

#: a plugin module (TELETOUCH_PLUGINS) whose nodes say on stderr where they are: the test's handshakes
PLUGIN = '''
import sys, time

from teletouch import Component, Device, Kind, Port, hookimpl


def say(text):
    print("s17: " + text, file=sys.stderr, flush=True)


def swallow_one():
    try:   # (said inside: the signal the test sends once it is said lands here)
        say("waiting for a signal")
        time.sleep(60)
    except KeyboardInterrupt:   # (Terminated, SIGTERM's, too)
        say("swallowed one")


def load():
    say("loading")
    time.sleep(60)   # a model, a device: the operator presses Ctrl-C again
    say("loaded to the end")


class Notes(Device):
    name = "s17-notes"
    inputs = {"command": Port("float64", (), "", required=False)}

    def step(self, t, inputs):
        return {}

    def safe_state(self):
        say("safe state")

    def close(self):
        say("closed")


class Swallows(Component):
    """configure() swallows one KeyboardInterrupt and goes on loading; with where=close, configure() fails and the
    close() the start-up then calls swallows it."""

    name = "s17-swallows"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        where: str = "configure"

    def configure(self):
        if self.params.where == "close":
            raise RuntimeError("no device")
        swallow_one()
        load()

    def close(self):
        if self.params.where == "close":
            swallow_one()

    def step(self, t, inputs):
        return {"y": 0.0}


class Loads(Component):
    name = "s17-loads"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    def configure(self):
        load()

    def step(self, t, inputs):
        return {"y": 0.0}


class Lingers(Device):
    name = "s17-lingers"
    inputs = {"command": Port("float64", (), "", required=False)}

    def step(self, t, inputs):
        return {}

    def safe_state(self):
        say("safe state")
        time.sleep(5.0)   # while the test's signal comes: held by the runtime's shutdown, it cannot raise here

    def close(self):
        say("closed")


class SwallowsOnce(Component):
    """configure() swallows the first signal and goes on (no long load): the run then runs and stops on its own, and
    the second signal lands in the shutdown (Lingers' safe_state waits for it)."""

    name = "s17-swallows-once"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    def configure(self):
        swallow_one()

    def step(self, t, inputs):
        return {"y": 0.0}


@hookimpl
def teletouch_components():
    return [Notes, Swallows, Loads, Lingers, SwallowsOnce]
'''

GRAPH = """
clock: sim
nodes:
  - {id: dev, plugin: s17-notes, rate: 100}
  - {id: a, plugin: s17-swallows, rate: 100, params: {where: WHERE}}
  - {id: b, plugin: s17-loads, rate: 100}
"""

#: the command line as `teletouch` runs it (Python's own Ctrl-C handler, also where the tests run as a background job)
PROGRAM = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
from teletouch.cli import main
sys.exit(main())
"""


def _spawn(tmp_path: Path, graph_text: str, duration: float) -> subprocess.Popen:
    """`teletouch run --quiet` of ``graph_text`` for ``duration`` s, with the test plugin, as a new process."""
    (tmp_path / "s17_swallow.py").write_text(PLUGIN)
    graph = tmp_path / "g.yaml"
    graph.write_text(graph_text)
    env = dict(os.environ, PYTHONUNBUFFERED="1", TELETOUCH_DISABLE_PLUGIN_AUTOLOAD="1",
               TELETOUCH_PLUGINS="teletouch.mock,s17_swallow",
               PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, "-c", PROGRAM, "run", str(graph), "--duration", str(duration), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)


def _run_signalled(tmp_path: Path, where: str, first: signal.Signals,
                   second: signal.Signals) -> tuple[int | None, float, str]:
    """`teletouch run` of the graph: ``first`` once a node waits for it, ``second`` once the start-up goes on after
    swallowing it. (Its exit code, or None when it still ran 20 s after the second; seconds from the second signal to
    its end; its stderr.)"""
    p = _spawn(tmp_path, GRAPH.replace("WHERE", where), duration=1)
    seen: list[str] = []
    try:
        lines = stderr_lines(p)
        sent = None
        while sent is None and (line := lines.get(timeout=120)) is not None:
            seen.append(line)
            if "s17: waiting for a signal" in line:
                p.send_signal(first)
            elif "s17: loading" in line and "s17: swallowed one\n" in seen:
                sent = time.monotonic()
                p.send_signal(second)
        assert sent is not None, "".join(seen)[-3000:]   # the first was swallowed and the start-up went on
        try:
            got = p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            got = None
        took = time.monotonic() - sent
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=60)
    p.stdout.read()
    while (line := lines.get(timeout=60)) is not None:
        seen.append(line)
    return got, took, "".join(seen)


@pytest.mark.parametrize("where", ["configure", "close"])
@pytest.mark.parametrize("first, second, code", [(signal.SIGINT, signal.SIGINT, EXIT_INTERRUPTED),
                                                 (signal.SIGTERM, signal.SIGINT, EXIT_INTERRUPTED),
                                                 (signal.SIGINT, signal.SIGTERM, EXIT_TERMINATED)],
                         ids=["int-int", "term-int", "int-term"])
def test_a_second_signal_stops_the_start_up_when_a_plugin_swallowed_the_first(tmp_path, where, first, second, code):
    # before: the second was only held ("already stopping safely") and the start-up loaded on for its 60 s
    got, took, err = _run_signalled(tmp_path, where, first, second)
    assert got is not None and took < 10, f"still running {took:.1f} s after the second signal: {err[-3000:]}"
    assert got == code, (got, err[-3000:])   # the signal that stopped it (the first stopped nothing)
    assert "s17: loaded to the end" not in err and HELD not in err, err[-3000:]
    lines = err.splitlines()
    assert "s17: safe state" in lines and "s17: closed" in lines, err[-3000:]   # the device: safe, then closed
    assert lines.index("s17: safe state") < lines.index("s17: closed")
    assert lines[-1] == f"teletouch: interrupted ({NAMES[second]}): devices driven to their safe state", err[-3000:]
    assert "Traceback" not in err, err[-3000:]


# --- in this process: a signal while a stop is on its way is held, as before ------------------------------------------
class _Cleans(Component):
    """configure() gets the first Ctrl-C; the second comes while the first is on its way out (its finally clause
    cleans up): that one must be held, not cut the clean-up short."""

    name = "s17-cleans"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}
    log: list[str] = []

    def configure(self):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
            type(self).log.append("not stopped")
        finally:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            type(self).log.append("cleaned up")

    def step(self, t, inputs):
        return {"y": 0.0}


class _Safe(Device):
    name = "s17-safe"
    inputs = {"command": Port("float64", (), "", required=False)}
    calls: list[str] = []

    def step(self, t, inputs):
        return {}

    def safe_state(self):
        type(self).calls.append("safe")

    def close(self):
        type(self).calls.append("close")


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Cleans, _Safe]


def test_a_signal_while_the_first_is_on_its_way_out_of_a_start_up_is_held(tmp_path, monkeypatch, capsys,
                                                                          python_sigint):
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_Plugin()))
    monkeypatch.setattr(_Cleans, "log", [])
    monkeypatch.setattr(_Safe, "calls", [])
    graph = tmp_path / "g.yaml"
    graph.write_text("clock: sim\nnodes:\n  - {id: dev, plugin: s17-safe, rate: 100}\n"
                     "  - {id: c, plugin: s17-cleans, rate: 100}\n")
    assert main(["run", str(graph), "--duration", "1", "--quiet"]) == EXIT_INTERRUPTED
    assert _Cleans.log == ["cleaned up"] and _Safe.calls == ["safe", "close"]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"teletouch: SIGTERM: {HELD}",
                   "teletouch: interrupted (Ctrl-C): devices driven to their safe state"], err


def test_the_signal_held_in_the_shutdown_after_a_swallowed_one_gives_the_exit_code(tmp_path):
    """A review found: Ctrl-C swallowed at start-up, then SIGTERM as the devices are made safe: stderr said SIGTERM
    but the exit code was the swallowed Ctrl-C's 130."""
    p = _spawn(tmp_path, "clock: sim\nnodes:\n  - {id: dev, plugin: s17-lingers, rate: 100}\n"
                         "  - {id: a, plugin: s17-swallows-once, rate: 100}\n", duration=0.5)
    seen: list[str] = []
    try:
        lines = stderr_lines(p)
        while (line := lines.get(timeout=120)) is not None:
            seen.append(line)
            if "s17: waiting for a signal" in line:
                p.send_signal(signal.SIGINT)
            elif "s17: safe state" in line:
                p.send_signal(signal.SIGTERM)
                break
        got = p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=60)
    while (line := lines.get(timeout=60)) is not None:
        seen.append(line)
    err = "".join(seen)
    assert "s17: swallowed one" in err and "s17: closed" in err, err[-3000:]
    assert err.splitlines()[-1] == "teletouch: interrupted (SIGTERM): devices driven to their safe state", err[-3000:]
    assert got == EXIT_TERMINATED, (got, err[-3000:])
