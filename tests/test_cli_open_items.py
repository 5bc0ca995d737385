"""Open items of the plugins and CLI work: blocked plugins in `teletouch plugins`, the TELETOUCH_BLOCK environment
variable, SIGTERM's exit status (143) after the safe stop, and the jitter column of the run summary."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from helpers_signals import stderr_lines

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes.plugin_dists import estimator_source, make_dist  # noqa: E402

from teletouch.registry import Registry  # noqa: E402
from teletouch.runtime import NodeStats, RunResult  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
GRAPH = str(REPO / "examples" / "mock-loop.yaml")
BROKEN = "import not_a_real_module_xyz\n"
GOOD = estimator_source("acme-c")
# a slow wall-clock graph that cannot fault on a loaded machine (overruns never fault); ends only by a signal
WALL_GRAPH = """name: term-test
clock: wall
faults: {max_overruns: 0}
nodes:
  - {id: source, plugin: mock-sensor, rate: 20}
  - {id: device, plugin: mock-device, rate: 20, inputs: {command: source.value}}
"""


@pytest.fixture(autouse=True)
def _no_block_env(monkeypatch):
    monkeypatch.delenv("TELETOUCH_BLOCK", raising=False)
    monkeypatch.delenv("TELETOUCH_BLOCK_PLUGINS", raising=False)


def _env(site: Path | None = None, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    if site is not None:
        env["PYTHONPATH"] = str(site)
    env.update(extra)
    return env


def run_cli(*args: str, site: Path | None = None, **extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "teletouch", *args], capture_output=True, text=True,
                          env=_env(site, **extra), timeout=120, cwd=REPO)


def _install_two(site: Path) -> None:
    make_dist(site, "acme-broken", "1.0", {"broken": "tt_broken"}, {"tt_broken": BROKEN})
    make_dist(site, "acme-good", "2.0", {"good": "tt_good"}, {"tt_good": GOOD})


# --- 1. blocked plugins are listed -----------------------------------------------------------------------------------
def test_plugins_json_lists_blocked_plugins_with_where_each_block_came_from(site):
    """Blocked plugins were left out of `teletouch plugins --json` (and only named on one text line)."""
    _install_two(site)
    r = run_cli("--block", "good", "plugins", "--json", site=site, TELETOUCH_BLOCK="acme-broken")
    assert r.returncode == 0, r.stderr   # a block is no problem: the broken plugin was never imported
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    assert rows["broken"]["blocked"] is True and rows["broken"]["kind"] is None
    assert rows["broken"]["distribution"] == "acme-broken" and "error" not in rows["broken"]
    assert rows["broken"]["blocked_by"] == [{"name": "acme-broken", "source": "environment",
                                             "setting": "TELETOUCH_BLOCK"}]
    assert rows["good"]["blocked_by"] == [{"name": "good", "source": "command line", "setting": "--block"}]
    assert "acme-c" not in rows and not rows["mock-sensor"].get("blocked")


def test_plugins_text_lists_blocked_plugins_and_the_exit_status_ignores_them(site):
    _install_two(site)
    r = run_cli("--block", "good", "plugins", site=site, TELETOUCH_BLOCK_PLUGINS="broken")
    assert r.returncode == 0, r.stderr
    assert "broken  [BLOCKED by TELETOUCH_BLOCK_PLUGINS=broken]  acme-broken 1.0" in r.stdout
    assert "good  [BLOCKED by --block good]  acme-good 2.0" in r.stdout
    r = run_cli("plugins", site=site)   # unblocked, the broken plugin is the only problem: exit 1 as before
    assert r.returncode == 1 and "BLOCKED" not in r.stdout and "broken  [FAILED TO LOAD]" in r.stdout


def test_a_name_blocked_twice_reports_both_settings(site, monkeypatch):
    _install_two(site)
    monkeypatch.setenv("TELETOUCH_BLOCK", "good")
    reg = Registry(autoload=True, blocked=["good"], blocked_setting="--block").load()
    (row,) = [r for r in reg.describe() if r["name"] == "good"]
    assert [(b["source"], b["setting"]) for b in row["blocked_by"]] == [("environment", "TELETOUCH_BLOCK"),
                                                                        ("command line", "--block")]


# --- 2. TELETOUCH_BLOCK ----------------------------------------------------------------------------------------------
def test_env_block_takes_names_separated_by_comma_or_pathsep(site, monkeypatch):
    _install_two(site)
    monkeypatch.setenv("TELETOUCH_BLOCK", f" broken{os.pathsep}mock , digit{os.pathsep}")
    reg = Registry(autoload=True).load()
    assert reg.blocked == {"broken", "mock", "digit"}
    assert all(reg.plugins[n].blocked for n in ("broken", "mock", "digit"))
    assert "mock-sensor" not in reg.components and "acme-c" in reg.components and not reg.errors()
    assert reg.unknown_blocked() == []


def test_env_block_applies_to_every_command(site):
    _install_two(site)
    r = run_cli("validate", GRAPH, site=site, TELETOUCH_BLOCK="mock")
    assert r.returncode == 1 and "unknown plugin 'mock-sensor'" in r.stderr
    assert "blocked plugins (not loaded): mock" in r.stderr


def test_unknown_name_in_env_block_is_warned_about_naming_the_variable_and_a_close_match():
    r = run_cli("validate", GRAPH, TELETOUCH_BLOCK=f"mokc{os.pathsep}sim-digit")
    assert r.returncode == 0, r.stderr
    assert ("teletouch: warning: blocked name 'mokc' (from TELETOUCH_BLOCK) matches no installed plugin or "
            "distribution (did you mean 'mock'?)") in r.stderr
    assert "'sim-digit'" not in r.stderr   # a real plugin name: no warning


def test_unknown_name_on_both_settings_names_both():
    r = run_cli("--block", "mokc", "validate", GRAPH, TELETOUCH_BLOCK="mokc")
    assert "blocked name 'mokc' (from TELETOUCH_BLOCK and --block) matches no installed" in r.stderr


# --- 3. SIGTERM ------------------------------------------------------------------------------------------------------
def _wait_for(lines: queue.Queue, seen: list[str], predicate, timeout: float = 120.0) -> bool:
    """Read lines (kept in ``seen``) until one satisfies ``predicate``; False at the end of the stream. Bounded by
    ``timeout`` per line."""
    while True:
        line = lines.get(timeout=timeout)
        if line is None:
            return False
        seen.append(line)
        if predicate(line):
            return True


# the CLI with Python's own Ctrl-C handler even where this test runs with SIGINT ignored (a background job)
CLI_WITH_SIGINT = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
                   "from teletouch.cli import main; sys.exit(main())")


@pytest.mark.parametrize("sig, code, last", [(signal.SIGTERM, 143, "teletouch: interrupted (SIGTERM): "),
                                             (signal.SIGINT, 130, "teletouch: interrupted (Ctrl-C): ")])
def test_sigterm_ends_a_run_with_143_after_the_safe_stop_and_prints_the_summary(tmp_path, sig, code, last):
    """SIGTERM was turned into Ctrl-C's KeyboardInterrupt and the command exited 130; the convention is 143 (128 +
    15). Ctrl-C stays 130. Both make the same safe stop and print the summary."""
    graph = tmp_path / "wall.yaml"
    graph.write_text(WALL_GRAPH)
    p = subprocess.Popen([sys.executable, "-c", CLI_WITH_SIGINT, "run", str(graph), "--duration", "600",
                          "--progress-interval", "0.1", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=_env(), cwd=REPO)
    try:
        lines = stderr_lines(p)
        seen: list[str] = []
        assert _wait_for(lines, seen, lambda s: s.startswith("t=")), "".join(seen)   # the live view: running
        os.kill(p.pid, sig)
        out = p.stdout.read()
        got = p.wait(timeout=120)
        while _wait_for(lines, seen, lambda s: False):
            pass
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=60)
    err = "".join(seen)
    assert got == code, err
    assert "Traceback" not in err
    name = "SIGTERM" if sig == signal.SIGTERM else "Ctrl-C"
    assert err.count(f"interrupted ({name}): devices driven to their safe state") == 1   # said once, last (below)
    assert "  node            plugin" in err and "  device          mock-device" in err
    assert err.rstrip().splitlines()[-1].startswith(last)
    result = json.loads(out.strip().splitlines()[-1])
    assert result["status"] == "interrupted" and result["exit_code"] == code   # the JSON says what the shell sees


# --- 4. the summary's jitter column ----------------------------------------------------------------------------------
def _result(jitter: float | None) -> RunResult:
    node = NodeStats("ctl", "position-force", 1000.0, 5000, 999.8, 2, 0.0001, 0.002, False, jitter)
    return RunResult("ok", 0, "ran 5.000 s", 5.0, 5.1, "wall", [node], [], 0.1)


def test_summary_table_has_a_jitter_column_in_ms_next_to_the_rates():
    text = _result(0.00123).summary()
    header, row = text.splitlines()[2:4]
    assert header.split()[:6] == ["node", "plugin", "rate", "Hz", "achieved", "jitter"]
    cols = row.split()
    assert cols[:5] == ["ctl", "position-force", "1000.0", "999.8", "1.230"]   # ms, next to the achieved rate
    assert header.index("jitter p99 ms") + len("jitter p99 ms") == row.index("1.230") + len("1.230")   # aligned
    assert _result(None).summary().splitlines()[3].split()[4] == "-"   # not measured (simulated clock)


def test_run_prints_the_jitter_it_reports_in_json_and_the_json_is_unchanged(tmp_path):
    graph = tmp_path / "wall.yaml"
    graph.write_text(WALL_GRAPH)
    r = run_cli("run", str(graph), "--duration", "1", "--json")
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(result["nodes"][0]) == set(NodeStats.__dataclass_fields__)   # no new JSON field
    rows = {line.split()[0]: line.split() for line in r.stderr.splitlines() if line.startswith("  source ")
            or line.startswith("  device ")}
    for node in result["nodes"]:
        assert node["period_jitter_p99_s"] is not None
        assert rows[node["id"]][4] == f"{node['period_jitter_p99_s'] * 1e3:.3f}"


LATE_TERM = '''
import os, signal
from teletouch import Device, Port, hookimpl


class SelfTerm(Device):
    """A device whose safe_state() (at the end of the run) gets a SIGTERM: it arrives during the safe shutdown."""
    name = "self-term"
    outputs = {"y": Port("float64", (), "m")}

    def step(self, t, inputs):
        return {"y": 0.0}

    def safe_state(self):
        os.kill(os.getpid(), signal.SIGTERM)


@hookimpl
def teletouch_components():
    return [SelfTerm]
'''


def test_a_sigterm_during_the_safe_shutdown_exits_143_too(tmp_path, plugin_module, capsys):
    # before: the runtime holds signals while it makes the devices safe, so the CLI's own SIGTERM handler never saw
    # one that came then: the run ended 'interrupted' with 130, Ctrl-C's code
    plugin_module("tt_late_term", LATE_TERM)
    graph = tmp_path / "g.yaml"
    graph.write_text("clock: sim\nduration: 0.1\nnodes:\n  - {id: dev, plugin: self-term, rate: 100}\n")
    from teletouch.cli import main

    assert main(["run", str(graph), "--quiet", "--json"]) == 143
    cap = capsys.readouterr()
    assert json.loads(cap.out.strip().splitlines()[-1])["exit_code"] == 143
    assert "teletouch: interrupted (SIGTERM): " in cap.err
