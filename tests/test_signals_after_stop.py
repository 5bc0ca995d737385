"""Once a program's command has stopped safely (devices safe, files written, its exit code decided), a Ctrl-C or
SIGTERM ends the process again. After the first signal the program ignored both until it exited: one that then hung on
its way out (an atexit hook, a plugin's non-daemon thread) could only be ended with SIGKILL."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers_signals import stderr_lines

from teletouch.cli import EXIT_TERMINATED
from teletouch.runtime import EXIT_INTERRUPTED

MARKER = "hanging on the way out"
GRAPH = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: src.value}}
"""
#: the CLI as `teletouch` runs it, the command's first signal sent as the run starts, and a hang after main() returned
PROGRAM = """
import atexit, os, signal, sys, threading, time
signal.signal(signal.SIGINT, signal.default_int_handler)
from teletouch.runtime import Runtime
real = Runtime._run_sim
def signalled(*a, **k):
    os.kill(os.getpid(), {first})
    return real(*a, **k)
Runtime._run_sim = signalled
def hang():
    print({marker!r}, file=sys.stderr, flush=True)
    time.sleep(60)
if {hang!r} == 'atexit':
    atexit.register(hang)
from teletouch.cli import main
code = main()
if {hang!r} == 'thread':
    threading.Thread(target=hang, daemon=False).start()
sys.exit(code)
"""


def _signalled_in_its_hang(p: subprocess.Popen, sig: signal.Signals) -> tuple[int | None, float, str]:
    """Wait until ``p`` says it hangs on its way out (:data:`MARKER` on stderr), send it ``sig``: (its exit code, or
    None when it was still running 20 s later; seconds from the signal to its end; its stderr up to the hang)."""
    seen: list[str] = []
    try:
        lines = stderr_lines(p)
        while (line := lines.get(timeout=120)) is not None and MARKER not in line:
            seen.append(line)
        assert line is not None, "".join(seen)[-3000:]   # it reached its hang
        sent = time.monotonic()
        p.send_signal(sig)
        try:
            got = p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            got = None
        return got, time.monotonic() - sent, "".join(seen)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=60)


@pytest.mark.parametrize("hang, first, second, code", [("atexit", signal.SIGINT, signal.SIGINT, EXIT_INTERRUPTED),
                                                       ("thread", signal.SIGTERM, signal.SIGTERM, EXIT_TERMINATED),
                                                       ("thread", signal.SIGINT, signal.SIGTERM, EXIT_INTERRUPTED)])
def test_a_signal_after_the_safe_stop_ends_a_process_that_hangs_on_its_way_out(tmp_path, hang, first, second, code):
    # before: the second signal was ignored: the process slept its 60 s (SIGKILL was the only way out)
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH)
    env = dict(os.environ, TELETOUCH_DISABLE_PLUGIN_AUTOLOAD="1", TELETOUCH_PLUGINS="teletouch.mock")
    env.pop("PYTHONUNBUFFERED", None)   # stdout block-buffered, as in a pipe: what is in its buffer must still come out
    program = PROGRAM.format(first=int(first), marker=MARKER, hang=hang)
    p = subprocess.Popen([sys.executable, "-c", program, "run", str(graph), "--duration", "5", "--quiet", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    got, took, err = _signalled_in_its_hang(p, second)
    assert got is not None and took < 10, f"still running {took:.1f} s after the {second.name} (ignored)"
    out = p.stdout.read()
    assert got == code, (got, err[-3000:])   # the command's own code: the signal only cut its exit short
    name = "Ctrl-C" if first == signal.SIGINT else "SIGTERM"
    assert f"teletouch: interrupted ({name})" in err and "Traceback" not in err, err[-3000:]
    assert json.loads(out)["exit_code"] == code   # its output, still in stdout's buffer, is not lost


def test_a_signal_the_kernel_gives_the_hanging_thread_ends_the_process_too(tmp_path):
    """A process-directed signal may land on any thread; CPython runs its handler in the main thread only, and that
    one waits, blocked, for the hanging thread to end: the signal did nothing for the hang's 60 s (one CI run saw it,
    the kernel having handed the SIGTERM to the hanging thread). Here the thread gets the signal itself."""
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH)
    env = dict(os.environ, TELETOUCH_DISABLE_PLUGIN_AUTOLOAD="1", TELETOUCH_PLUGINS="teletouch.mock")
    program = PROGRAM.format(first=int(signal.SIGINT), marker=MARKER, hang="thread").replace(
        "    time.sleep(60)", "    signal.pthread_kill(threading.get_ident(), signal.SIGTERM)\n    time.sleep(60)")
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", program, "run", str(graph), "--duration", "5", "--quiet", "--json"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert MARKER in p.stderr and time.monotonic() - t0 < 30, p.stderr[-3000:]   # not after the 60 s hang
    assert p.returncode == EXIT_INTERRUPTED, p.stderr[-3000:]
    assert json.loads(p.stdout)["exit_code"] == EXIT_INTERRUPTED   # stdout's buffer written first


def test_the_program_s_signal_handlers_end_the_process_only_once_its_exit_code_is_known(tmp_path):
    # the hold stays until main() has decided the exit code (said "already stopping safely"): a signal as the command
    # ends must not end the process before its last line is said
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH)
    program = "\n".join([
        "import os, signal, sys, time",
        "signal.signal(signal.SIGINT, signal.default_int_handler)",
        "from teletouch import cli",
        "def command(argv):",   # a command that a Ctrl-C stops by its KeyboardInterrupt: main() says how it ended
        "    os.kill(os.getpid(), signal.SIGINT)",
        "    time.sleep(30)",
        "cli._main = command",
        "def said(*a, **k):",   # main() says its last line: a Ctrl-C right then
        "    if a and str(a[0]) == 'teletouch: interrupted (Ctrl-C)':",
        "        os.kill(os.getpid(), signal.SIGINT)",
        "    return print(*a, **k)",
        "cli.print = said",
        "code = cli.main()",
        "print('main returned', code, file=sys.stderr, flush=True)",
        "sys.exit(code)"])
    env = dict(os.environ, TELETOUCH_DISABLE_PLUGIN_AUTOLOAD="1", TELETOUCH_PLUGINS="teletouch.mock")
    p = subprocess.run([sys.executable, "-c", program, "run", str(graph), "--duration", "5", "--quiet"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert p.returncode == EXIT_INTERRUPTED, p.stderr[-3000:]
    assert "teletouch: Ctrl-C: already stopping safely, please wait" in p.stderr, p.stderr[-3000:]
    assert p.stderr.rstrip().endswith("main returned 130") and "Traceback" not in p.stderr, p.stderr[-3000:]


def test_the_docs_say_a_signal_after_the_safe_stop_ends_the_process():
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    start = text.index("A second Ctrl-C or SIGTERM while a command stops")
    assert "ends the process at once" in text[start:start + 800], text[start:start + 800]


@pytest.mark.parametrize("ending, code", [("raise RuntimeError('a bug after the safe stop')", 1),
                                          ("sys.exit(5)", 5)])
def test_a_signal_after_a_stopped_command_crashed_ends_the_process_with_the_crash_s_status(tmp_path, ending, code):
    """A command stopped by a signal that then raised (a bug after its safe stop) or exited by itself: main() never
    decided its code, so every later signal was held ("already stopping safely") and a hang on the way out needed
    SIGKILL. The status is the one Python gives that exception (found by review)."""
    program = "\n".join([
        "import atexit, os, signal, sys, time",
        "signal.signal(signal.SIGINT, signal.default_int_handler)",
        "from teletouch import cli",
        "def command(argv):",
        "    try:",
        "        os.kill(os.getpid(), signal.SIGINT)",
        "        time.sleep(30)",
        "    except KeyboardInterrupt:",
        "        pass",   # the command handles its stop itself, as run does, then:
        f"    {ending}",
        "cli._main = command",
        "def hang():",
        f"    print({MARKER!r}, file=sys.stderr, flush=True)",
        "    time.sleep(60)",
        "atexit.register(hang)",
        "sys.exit(cli.main())"])
    p = subprocess.Popen([sys.executable, "-c", program], stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    got, _, err = _signalled_in_its_hang(p, signal.SIGTERM)
    assert got == code, (got, err[-3000:])
