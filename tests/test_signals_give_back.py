"""A program's first signal that lands while the command line gives its handlers back, after SIGTERM's was given back
and before SIGINT's, still stops the command, and leaves both signals to :func:`cli._after_stop`. Before, SIGINT got
``_after_stop`` but SIGTERM stayed at the handler it had before (SIG_DFL): a later SIGTERM ended the process with -15
instead of the command's exit code."""

from __future__ import annotations

import signal
import sys

import pytest

from teletouch import cli, runtime


pytestmark = pytest.mark.usefixtures("signal_handlers_restored")


def _signal_after_sigterm_is_given_back(sig: signal.Signals, before: dict):
    """A profile function that runs the handler of ``sig`` (as the process has it then) as the give-back's call that
    restored SIGTERM's previous handler returns: where a real signal's handler runs, between two bytecodes."""
    code = cli._interrupts.__wrapped__.__code__
    state = {"sent": False}

    def prof(frame, event, arg):
        if state["sent"] or event != "return" or frame.f_code.co_name != "signal" or frame.f_back.f_code is not code:
            return
        if signal.getsignal(signal.SIGTERM) is before[signal.SIGTERM]:
            state["sent"] = True
            signal.getsignal(sig)(sig, frame)   # teletouch's handler still: SIGINT's is given back last

    return prof, state


@pytest.mark.parametrize("program", [True, False])
def test_a_first_signal_between_the_two_give_backs_leaves_both_signals_to_the_same_handler(python_sigint, program):
    sigterm_before = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    before = {signal.SIGINT: signal.getsignal(signal.SIGINT), signal.SIGTERM: signal.SIG_DFL}
    prof, state = _signal_after_sigterm_is_given_back(signal.SIGINT, before)
    raised = None
    try:
        with cli._interrupts(program=program) as signals:
            sys.setprofile(prof)
    except KeyboardInterrupt as exc:   # the first signal still stops the command
        raised = exc
    finally:
        sys.setprofile(None)
        after = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        signal.signal(signal.SIGTERM, sigterm_before)
    assert state["sent"]
    assert raised is not None and signals == [signal.SIGINT]
    assert runtime._stop_signals is None
    if program:   # both end at the program's after-stop handler: a later SIGTERM exits with the command's code
        assert after == {signal.SIGINT: cli._after_stop, signal.SIGTERM: cli._after_stop}
    else:   # a block that is not the process's life gives both back as they were
        assert after == before
