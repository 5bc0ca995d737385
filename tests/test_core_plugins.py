"""Plugin discovery through real entry points (fake installed distributions on sys.path), errors, blocking."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes.plugin_dists import make_dist  # noqa: E402

from teletouch.errors import DuplicateComponentError
from teletouch.registry import Registry

PLUGIN_SRC = '''
from teletouch import Component, Kind, Port, hookimpl

class {cls}(Component):
    """{doc}"""
    name = "{comp}"
    kind = Kind.ESTIMATOR
    inputs = {{"x": Port("float64", (), "m")}}
    outputs = {{"y": Port("float64", (), "N")}}

    class Params(Component.Params):
        k: float = 2.0

    def step(self, t, inputs):
        return {{"y": self.params.k * inputs.value("x", 0.0)}}

@hookimpl
def teletouch_components():
    return [{cls}]
'''


def test_third_party_entry_point_discovered_with_distribution(site):
    make_dist(site, "acme-sensors", "1.2.3", {"acme": "tt_acme"},
              {"tt_acme": PLUGIN_SRC.format(cls="Spring", comp="acme-spring", doc="Hooke spring.")})
    reg = Registry(autoload=True, blocked=()).load()
    info = reg.get("acme-spring")
    assert (info.distribution, info.version, info.plugin) == ("acme-sensors", "1.2.3", "acme")
    # built-ins come through the same group
    assert reg.get("mock-device").distribution == "teletouch"
    row = next(r for r in reg.describe() if r["name"] == "acme-spring")
    assert set(row) >= {"name", "kind", "distribution", "version", "ports", "params"}
    assert {"name": "x", "dtype": "float64", "shape": [], "unit": "m", "direction": "in",
            "required": True}.items() <= row["ports"][0].items()
    assert row["params"][0]["name"] == "k" and row["params"][0]["default"] == 2.0


def test_broken_plugin_reported_and_skipped(site):
    make_dist(site, "broken-dist", "0.1", {"broken": "tt_broken"},
              {"tt_broken": "import not_a_real_module_xyz\n"})
    reg = Registry(autoload=True, blocked=()).load()
    assert "mock-sensor" in reg.components  # the rest still loads
    errs = {p.name: p for p in reg.errors()}
    assert "broken" in errs and "ModuleNotFoundError" in errs["broken"].error
    row = next(r for r in reg.describe() if r["name"] == "broken")
    assert row["error"].startswith("ModuleNotFoundError") and row["distribution"] == "broken-dist"


def test_invalid_component_reported(site):
    src = "from teletouch import hookimpl, Component\nclass Bad(Component):\n    name = 'Bad Name'\n" \
          "@hookimpl\ndef teletouch_components():\n    return [Bad]\n"
    make_dist(site, "bad-dist", "0.1", {"bad": "tt_bad"}, {"tt_bad": src})
    reg = Registry(autoload=True, blocked=()).load()
    assert "lower-case words" in reg.plugins["bad"].error


def test_duplicate_component_names_refused_naming_both(site):
    make_dist(site, "alpha-dist", "1.0", {"alpha": "tt_alpha"},
              {"tt_alpha": PLUGIN_SRC.format(cls="A", comp="same-name", doc="A.")})
    make_dist(site, "beta-dist", "2.0", {"beta": "tt_beta"},
              {"tt_beta": PLUGIN_SRC.format(cls="B", comp="same-name", doc="B.")})
    reg = Registry(autoload=True, blocked=()).load()   # refused, not fatal: everything else still loads
    assert "mock-sensor" in reg.components and "same-name" not in reg.components
    with pytest.raises(DuplicateComponentError) as ei:
        reg.get("same-name")
    assert "alpha-dist" in str(ei.value) and "beta-dist" in str(ei.value)
    # blocking one of them resolves it
    reg = Registry(autoload=True, blocked=["beta"]).load()
    assert reg.get("same-name").distribution == "alpha-dist" and reg.plugins["beta"].blocked


def test_env_block_and_autoload(site, monkeypatch):
    make_dist(site, "acme-sensors", "1.2.3", {"acme": "tt_acme"},
              {"tt_acme": PLUGIN_SRC.format(cls="Spring", comp="acme-spring", doc="Hooke spring.")})
    monkeypatch.setenv("TELETOUCH_BLOCK_PLUGINS", "acme, mock")
    reg = Registry().load()
    assert "acme-spring" not in reg.components and "mock-sensor" not in reg.components
    monkeypatch.delenv("TELETOUCH_BLOCK_PLUGINS")
    monkeypatch.setenv("TELETOUCH_DISABLE_PLUGIN_AUTOLOAD", "1")
    monkeypatch.setenv("TELETOUCH_PLUGINS", "tt_acme")
    reg = Registry().load()
    assert list(reg.components) == ["acme-spring"]


def test_unknown_component_message_mentions_broken_plugin(site):
    make_dist(site, "broken-dist", "0.1", {"acme-spring": "tt_broken2"}, {"tt_broken2": "raise RuntimeError('x')\n"})
    reg = Registry(autoload=True, blocked=()).load()
    msg = reg.unknown_message("acme-spring")
    assert "failed to load" in msg and "RuntimeError" in msg


def _cli(*args, env=None, cwd=None):
    return subprocess.run([sys.executable, "-m", "teletouch", *args], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=120)


def test_cli_plugins_json_lists_builtins():
    import os

    env = dict(os.environ, TELETOUCH_BLOCK_PLUGINS="")
    r = _cli("plugins", "--json", env=env)
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    names = {row["name"]: row for row in rows}
    assert names["mock-device"]["kind"] == "device" and names["mock-device"]["distribution"] == "teletouch"
    for row in rows:
        assert set(row) >= {"name", "kind", "distribution", "version", "ports", "params"}
    r = _cli("plugins", env=env)
    assert "mock-gain  (estimator)  teletouch" in r.stdout


def test_cli_validate_and_run_exit_codes(tmp_path):
    repo = Path(__file__).resolve().parents[1]
    r = _cli("validate", str(repo / "examples" / "mock-loop.yaml"))
    assert r.returncode == 0 and "OK (3 nodes" in r.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text(textwrap.dedent("""\
        clock: sim
        nodes:
          - {id: a, plugin: mock-sensr, rate: 10}
        """))
    r = _cli("validate", str(bad))
    assert r.returncode == 1 and f"{bad}:3: node 'a': unknown plugin 'mock-sensr'" in r.stderr
    r = _cli("run", str(repo / "examples" / "mock-loop.yaml"), "--duration", "0.5", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["status"] == "ok" and summary["sim_time_s"] == pytest.approx(0.5)
    r = _cli("run", str(repo / "examples" / "mock-loop.yaml"), "--set", "source.fail_at=0.2", "--quiet")
    assert r.returncode == 3
    assert r.stderr.strip().splitlines()[-1].startswith("teletouch: fault: node 'source' exception")
    r = _cli("schema")
    assert r.returncode == 0 and json.loads(r.stdout)["title"] == "teletouch graph"


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_stops_wall_clock_run_with_safe_devices(tmp_path, sig):
    import signal
    import time

    graph = tmp_path / "g.yaml"
    graph.write_text(textwrap.dedent("""\
        clock: wall
        nodes:
          - {id: src, plugin: mock-sensor, rate: 100}
          - {id: dev, plugin: mock-device, rate: 500, inputs: {command: src.value}}
        """))
    p = subprocess.Popen([sys.executable, "-m", "teletouch", "run", str(graph), "--progress-interval", "0.1"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    line = ""
    while time.time() < deadline:  # wait until the live view shows the graph running
        line = p.stderr.readline()
        if line.startswith("t="):
            break
    assert line.startswith("t="), line
    p.send_signal(getattr(signal, sig))
    _, err = p.communicate(timeout=60)
    assert p.returncode == {"SIGINT": 130, "SIGTERM": 143}[sig], err   # 128 + the signal's number, as a shell
    by = "SIGTERM" if sig == "SIGTERM" else "Ctrl-C"
    assert err.strip().splitlines()[-1] == f"teletouch: interrupted ({by}): devices driven to their safe state"


def test_cli_calibrate_without_what_shows_its_own_usage():
    r = _cli("calibrate")
    assert r.returncode == 2
    assert r.stderr.startswith("usage: teletouch calibrate") and "depth" in r.stderr and "force" in r.stderr
