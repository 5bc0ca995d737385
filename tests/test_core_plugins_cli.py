"""The `teletouch` command line against broken or conflicting plugins, blocking, and bad arguments: a clear message
and a documented exit code, never a traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fakes.plugin_dists import estimator_source

REPO = Path(__file__).resolve().parents[1]
GRAPH = str(REPO / "examples" / "mock-loop.yaml")

CMD_RAISES = ("from teletouch import hookimpl\n@hookimpl\ndef teletouch_add_commands(subparsers):\n"
              "    raise RuntimeError('boom')\n")
CMD_TAKES_RUN = '''
from teletouch import hookimpl

@hookimpl
def teletouch_add_commands(subparsers):
    subparsers.add_parser("acme-extra", help="added before the failure")
    subparsers.add_parser("run", help="takes the core's name")
'''
BROKEN = "import not_a_real_module_xyz\n"
NOISY = estimator_source("noisy-c", 'print("hello from the plugin")' + "\n")


def install(root: Path, modules: dict[str, str]) -> Path:
    """One fake distribution per module: 'acme-<mod>' 1.0 with the entry point '<mod>'."""
    root.mkdir(parents=True, exist_ok=True)
    for mod, src in modules.items():
        info = root / f"acme_{mod}-1.0.dist-info"
        info.mkdir()
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: acme-{mod}\nVersion: 1.0\n")
        (info / "entry_points.txt").write_text(f"[teletouch]\n{mod} = tt_{mod}\n")
        (root / f"tt_{mod}.py").write_text(src)
    return root


def cli(*args: str, site: Path | None = None, **env_extra: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    if site is not None:
        env["PYTHONPATH"] = str(site)
    env.update(env_extra)
    return subprocess.run([sys.executable, "-m", "teletouch", *args], capture_output=True, text=True, env=env,
                          timeout=120, cwd=REPO)


def test_plugin_whose_command_hook_raises_leaves_every_other_command_working(tmp_path):
    site = install(tmp_path / "site", {"cmd": CMD_RAISES})
    r = cli("validate", GRAPH, site=site)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert ("teletouch: warning: plugin 'cmd' (acme-cmd 1.0): its commands are skipped: teletouch_add_commands "
            "raised RuntimeError: boom (tt_cmd.py:4)") in r.stderr
    r = cli("plugins", site=site)
    assert r.returncode == 1 and "cmd (acme-cmd 1.0: add_commands)" in r.stdout


def test_plugin_command_that_takes_a_core_name_is_skipped_whole(tmp_path):
    site = install(tmp_path / "site", {"cmd": CMD_TAKES_RUN})
    r = cli("run", GRAPH, "--duration", "0.1", "--quiet", "--json", site=site)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1])["status"] == "ok"   # the core's run, not the plugin's
    assert "conflicting subparser: run" in r.stderr and "Traceback" not in r.stderr
    r = cli("acme-extra", site=site)   # what it added before failing is taken back too
    assert r.returncode == 2 and "invalid choice: 'acme-extra'" in r.stderr


def test_plugins_exits_1_and_lists_the_failure_while_json_stays_parseable(tmp_path):
    site = install(tmp_path / "site", {"broken": BROKEN, "noisy": NOISY})
    r = cli("plugins", "--json", site=site)
    assert r.returncode == 1
    rows = {row["name"]: row for row in json.loads(r.stdout)}   # the plugin's print went to stderr
    assert rows["broken"]["error"].startswith("ModuleNotFoundError") and rows["broken"]["distribution"] == "acme-broken"
    assert rows["noisy-c"]["distribution"] == "acme-noisy" and "hello from the plugin" in r.stderr
    r = cli("plugins", site=site)
    assert r.returncode == 1
    assert "broken  [FAILED TO LOAD]  acme-broken 1.0" in r.stdout
    assert "noisy-c  (estimator)  acme-noisy 1.0  (plugin noisy)" in r.stdout   # the name to block it by
    r = cli("plugins", site=site, TELETOUCH_BLOCK_PLUGINS="broken")
    assert r.returncode == 0, r.stderr
    assert "broken  [BLOCKED by TELETOUCH_BLOCK_PLUGINS=broken]  acme-broken 1.0" in r.stdout


def test_block_option_on_the_command_line(tmp_path):
    site = install(tmp_path / "site", {"broken": BROKEN})
    r = cli("--block", "broken", "--block", "acme-noisy,mock", "plugins", "--json", site=site)
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    assert rows["broken"]["blocked"] and rows["mock"]["blocked"] and "error" not in rows["broken"]
    assert "mock-sensor" not in rows and "digit" in rows
    assert "blocked name 'acme-noisy' (from --block) matches no installed plugin or distribution" in r.stderr
    assert r.returncode == 1   # the typo counts as a problem
    r = cli("--block", "mock", "validate", GRAPH)
    assert r.returncode == 1 and "unknown plugin 'mock-sensor'" in r.stderr and "blocked plugins (not loaded): mock" \
        in r.stderr


def test_blocked_name_that_matches_nothing_is_warned_about_on_every_command():
    r = cli("validate", GRAPH, TELETOUCH_BLOCK_PLUGINS="mokc")
    assert r.returncode == 0
    assert ("teletouch: warning: blocked name 'mokc' (from TELETOUCH_BLOCK_PLUGINS) matches no installed plugin or "
            "distribution (did you mean 'mock'?)") in r.stderr


def test_conflicting_component_refused_but_cli_still_works(tmp_path):
    src = NOISY.replace("noisy-c", "mock-gain").replace('print("hello from the plugin")', "")
    site = install(tmp_path / "site", {"acme": src})
    r = cli("--version", site=site)
    assert r.returncode == 0 and r.stdout.startswith("teletouch ")
    r = cli("validate", GRAPH, site=site)
    assert r.returncode == 1
    assert "node 'scale': component 'mock-gain' is provided by both plugin 'acme' (acme-acme 1.0) and plugin 'mock'" \
        in r.stderr
    r = cli("plugins", site=site)
    assert r.returncode == 1 and "mock-gain  [REFUSED: provided by more than one plugin]" in r.stdout
    r = cli("--block", "acme", "validate", GRAPH, site=site)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("args, message", [
    ((), "teletouch: error: a COMMAND is required"),
    (("run", GRAPH, "--progress-interval", "0"), "argument --progress-interval: must be a positive, finite number"),
    (("run", GRAPH, "--progress-interval", "nan"), "argument --progress-interval: must be a positive, finite"),
    (("run", GRAPH, "--duration", "-1"), "teletouch run: error: argument --duration: must be a positive time in s"),
    (("run", GRAPH, "--duration", "2kg"), "teletouch run: error: argument --duration: '2kg' is in kg, expected"),
    (("--block",), "usage: teletouch [-h] [--version] [--block NAME[,NAME]] COMMAND"),
])
def test_usage_errors_exit_2_with_a_message(args, message):
    r = cli(*args)
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert message in r.stderr and "Traceback" not in r.stderr


def test_component_constructor_that_raises_is_a_startup_failure_not_a_traceback(tmp_path):
    src = NOISY.replace('print("hello from the plugin")', "").replace(
        "    def step", "    def __init__(self, *a, **k):\n        super().__init__(*a, **k)\n"
        "        raise ValueError('bad init')\n    def step")
    site = install(tmp_path / "site", {"init": src})
    graph = tmp_path / "g.yaml"
    graph.write_text("clock: sim\nduration: 0.1\nnodes:\n  - {id: a, plugin: noisy-c, rate: 10}\n")
    r = cli("run", str(graph), "--quiet", site=site)
    assert r.returncode == 4, r.stderr
    assert "Traceback" not in r.stderr
    assert ("teletouch: startup-failed: node 'a': noisy-c could not be created: ValueError: bad init (tt_init.py:"
            in r.stderr)


def test_a_reader_that_leaves_early_is_not_an_error():
    """`teletouch schema | head`: the pipe closed under a 200 kB schema printed 'teletouch: error: Broken pipe' and
    exit 1; now nothing on stderr and 141 (SIGPIPE's code, as git)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    p = subprocess.Popen([sys.executable, "-m", "teletouch", "schema"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=env, cwd=REPO)
    assert p.stdout.read(100).startswith(b"{")
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141, err
    assert err == ""
