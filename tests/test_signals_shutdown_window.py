"""A signal whose handler raises (the stop's first under the command line, or Python's own Ctrl-C) as the runtime takes
its shutdown's hold, or gives it back, is held like one inside it. Landing before the hold was taken, it skipped the
whole shutdown (no safe state, no close: KeyboardInterrupt out of run()); between the two handlers taken, it also left
SIGINT held by the finished run for good; and between the two given back, SIGTERM's."""

from __future__ import annotations

import contextlib
import signal
import sys

import pytest

from teletouch import Device, Port, cli, hookimpl, runtime
from teletouch.graph import load_graph
from teletouch.runtime import EXIT_INTERRUPTED, Runtime
from teletouch.testing import make_registry

HELD = "already stopping safely, please wait"
NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}


class _Calls(Device):
    """A device that notes its safe state and its close."""

    name = "notes-calls"
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
        return [_Calls]


GRAPH = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: notes-calls, rate: 100, inputs: {command: src.value}}
"""


pytestmark = pytest.mark.usefixtures("signal_handlers_restored")


def _signal_at(where: str, sig: signal.Signals, outer: dict):
    """A profile function that runs the handler of ``sig`` (as the process has it then) in the shutdown's hold at
    ``where``: "taking" (its start, before any handler is taken), "between the holds" (as the first handler taken
    returns) or "between the returns" (as the first one given back returns): where a real signal's handler runs, as
    a call returns. ``outer``: the handlers before the run."""
    code = runtime._signals_deferred.__wrapped__.__code__
    state = {"sent": False, "held": False}

    def ours() -> list[bool]:
        return [signal.getsignal(s) is outer[s] for s in (signal.SIGINT, signal.SIGTERM)]

    def send(frame) -> None:
        state["sent"] = True
        handler = signal.getsignal(sig)
        handler(sig, frame)   # (raises, as the process's handler of a first signal does)

    def prof(frame, event, arg):
        if state["sent"]:
            return
        if where == "taking" and event == "call" and frame.f_code is code:
            send(frame)
        # (signal.signal is Python's wrapper of _signal.signal: its return to the hold's own frame)
        if event != "return" or frame.f_code.co_name != "signal" or frame.f_back.f_code is not code:
            return
        mine = ours()
        if not any(mine):
            state["held"] = True
        elif where == "between the holds" and not state["held"] and mine.count(True) == 1:
            send(frame)
        elif where == "between the returns" and state["held"] and mine.count(True) == 1:
            send(frame)

    return prof, state


@pytest.mark.parametrize("where, sig, command_line", [("taking", signal.SIGINT, False),
                                                      ("taking", signal.SIGTERM, True),
                                                      ("between the holds", signal.SIGTERM, True),
                                                      ("between the returns", signal.SIGINT, True),
                                                      ("between the returns", signal.SIGTERM, True)])
def test_a_signal_as_the_shutdown_s_hold_is_taken_or_given_back_is_held(tmp_path, monkeypatch, capsys, python_sigint,
                                                                         where, sig, command_line):
    path = tmp_path / "g.yaml"
    path.write_text(GRAPH)
    monkeypatch.setattr(_Calls, "calls", [])
    rt = Runtime(load_graph(path, registry=make_registry(_Plugin())))
    escaped = None
    with cli._interrupts() if command_line else contextlib.nullcontext() as signals:
        outer = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        prof, state = _signal_at(where, sig, outer)
        sys.setprofile(prof)
        try:
            result = rt.run(0.2)
        except KeyboardInterrupt as exc:   # before: the signal cut the shutdown short
            escaped = exc
        finally:
            sys.setprofile(None)
        after = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    assert state["sent"], where
    assert escaped is None, f"{type(escaped).__name__} out of run(); device calls {_Calls.calls}"
    assert _Calls.calls == ["safe", "close"]
    assert after == outer   # none of the run's hold is left behind
    assert (result.status, result.exit_code, result.late_signal) == ("interrupted", EXIT_INTERRUPTED, sig)
    assert result.message == f"interrupted ({NAMES[sig]}): devices driven to their safe state"
    if command_line:
        assert signals == [sig]   # counted once: the command line's handler noted it as it raised
    assert capsys.readouterr().err.splitlines() == [f"teletouch: {NAMES[sig]}: {HELD}"]


def test_in_a_program_without_the_command_line_a_second_ctrl_c_as_the_first_is_held_is_held_too(
        tmp_path, monkeypatch, capsys, python_sigint):
    """Python's own Ctrl-C handler raises on every Ctrl-C: a first one landing as the shutdown's hold is taken is held
    by run()'s retry, but a second one landing while that first one was being held (said) escaped run(): no safe
    state, no close. Once the run is stopping a Ctrl-C is held now (runtime._ctrl_c_until_stopping)."""
    path = tmp_path / "g.yaml"
    path.write_text(GRAPH)
    monkeypatch.setattr(_Calls, "calls", [])
    rt = Runtime(load_graph(path, registry=make_registry(_Plugin())))
    hold = runtime._signals_deferred.__wrapped__.__code__
    state = {"n": 0}

    def prof(frame, event, arg):   # the first Ctrl-C: its handler runs as the hold begins
        if event == "call" and frame.f_code is hold and state["n"] == 0:
            state["n"] = 1
            signal.getsignal(signal.SIGINT)(signal.SIGINT, frame)

    say = runtime._say_held

    def second_while_saying(signum):   # the second: its handler runs as the first is said
        if state["n"] == 1:
            state["n"] = 2
            signal.getsignal(signal.SIGINT)(signal.SIGINT, None)
        say(signum)

    monkeypatch.setattr(runtime, "_say_held", second_while_saying)
    escaped = None
    sys.setprofile(prof)
    try:
        result = rt.run(0.2)
    except KeyboardInterrupt as exc:
        escaped = exc
    finally:
        sys.setprofile(None)
    assert state["n"] == 2
    assert escaped is None, f"KeyboardInterrupt out of run(); device calls {_Calls.calls}"
    assert _Calls.calls == ["safe", "close"]
    assert (result.status, result.late_signal) == ("interrupted", signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler   # Python's handler is back after the run
    assert capsys.readouterr().err.count(f"teletouch: Ctrl-C: {HELD}") == 2
