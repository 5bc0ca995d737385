"""The command line's signal handling at its edges: two signals that land together (the second handler runs nested
in the first, between two of its bytecodes) stop the command once instead of both being held; a signal that lands
while the handlers are being restored neither leaves teletouch's handler installed nor the stop list set for a later
command in the same process, and a first signal there still stops the command."""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest

from teletouch import cli, runtime


def test_two_signals_landing_together_stop_the_command_once():
    # before: the first handler appended, the nested second one appended too, and both saw two signals: both
    # said "already stopping" and neither raised, so the command went on
    state = {"sent": False}

    def prof(frame, event, arg):
        if (event == "c_return" and not state["sent"] and frame.f_code.co_name == "_handler"
                and getattr(arg, "__name__", "") == "append"):
            state["sent"] = True
            os.kill(os.getpid(), signal.SIGINT)   # pending at the next bytecode boundary, inside the first handler
            time.sleep(0.01)

    raised = None
    try:
        with cli._interrupts() as signals:
            sys.setprofile(prof)
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100000):
                pass
            sys.setprofile(None)
    except KeyboardInterrupt as exc:
        sys.setprofile(None)
        raised = exc
    assert state["sent"]
    assert raised is not None and sorted(signals) == [signal.SIGINT, signal.SIGTERM], (raised, signals)


def test_a_signal_while_the_handlers_are_restored_leaves_nothing_behind(monkeypatch, capsys):
    # before: a signal that landed between two handlers' restores raised inside the restore: the other handler stayed
    # teletouch's and runtime._stop_signals stayed set, so a later block installed nothing and a later signal was held
    # forever. Now SIGTERM is restored first and SIGINT last; a Ctrl-C between the two is the command's first signal
    real = signal.signal
    old_term = signal.getsignal(signal.SIGTERM)
    state = {"armed": True}

    def wrapped(sig, handler):
        prev = real(sig, handler)
        if state["armed"] and sig == signal.SIGTERM and handler is old_term:
            state["armed"] = False
            os.kill(os.getpid(), signal.SIGINT)   # SIGINT's handler is still teletouch's
        return prev

    signal.signal(signal.SIGINT, signal.default_int_handler)
    monkeypatch.setattr(cli.signal, "signal", wrapped)
    code = cli.main(["--version"])
    monkeypatch.setattr(cli.signal, "signal", real)
    assert not state["armed"]
    assert runtime._stop_signals is None
    assert signal.getsignal(signal.SIGTERM) is old_term
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert code == cli.EXIT_INTERRUPTED, code   # the signal that came as the command ended still stops it
    assert "interrupted (Ctrl-C)" in capsys.readouterr().err
    with cli._interrupts() as s:   # a later command: its own list and handlers
        assert s == [] and signal.getsignal(signal.SIGTERM) is not old_term


@pytest.fixture(autouse=True)
def _restore_handlers():
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)
    runtime._stop_signals = None


def test_a_ctrl_c_right_after_sigint_is_restored_leaves_sigterm_restored_too(monkeypatch):
    # before: SIGINT was restored first; a Ctrl-C right then raised in the restore loop, before SIGTERM's turn, and
    # teletouch's handler stayed on SIGTERM (holding every later SIGTERM silently)
    real = signal.signal
    state = {"armed": True}

    def wrapped(sig, handler):
        prev = real(sig, handler)
        if state["armed"] and sig == signal.SIGINT and handler is signal.default_int_handler:
            state["armed"] = False
            os.kill(os.getpid(), signal.SIGINT)
        return prev

    signal.signal(signal.SIGINT, signal.default_int_handler)
    old_term = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(cli.signal, "signal", wrapped)
    with pytest.raises(KeyboardInterrupt):
        with cli._interrupts():
            pass
        for _ in range(1000):   # (the pending Ctrl-C is raised at the next bytecode boundary)
            pass
    monkeypatch.setattr(cli.signal, "signal", real)
    assert not state["armed"]
    assert signal.getsignal(signal.SIGTERM) is old_term
    assert runtime._stop_signals is None
