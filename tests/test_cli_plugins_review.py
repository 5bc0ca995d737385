"""Review of the plugin-facing command line: plugin commands without a func, device-discovery entries without the
keys the hook's contract names, the achieved rate (summary and live view), warning and summary texts."""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes.plugin_dists import make_dist  # noqa: E402

from teletouch import cli  # noqa: E402
from teletouch.graph import load_graph  # noqa: E402
from teletouch.registry import Registry  # noqa: E402
from teletouch.runtime import Runtime  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
GRAPH = str(REPO / "examples" / "mock-loop.yaml")

NO_FUNC = '''
from teletouch import hookimpl

def _hello(args):
    print("hello from acme")
    return 0

@hookimpl
def teletouch_add_commands(subparsers, calibrate):
    subparsers.add_parser("acme-hello", help="forgot set_defaults(func=...)")
    calibrate.add_parser("acme", help="forgot it too")
    p = subparsers.add_parser("acme-ok", help="a command that works")
    p.set_defaults(func=_hello)
'''

NESTED = '''
from teletouch import hookimpl

def _go(args):
    print("acme go ran")
    return 0

@hookimpl
def teletouch_add_commands(subparsers):
    p = subparsers.add_parser("acme-tools", help="a group of commands")
    sub = p.add_subparsers(dest="acme_tool", metavar="TOOL")
    sub.add_parser("go").set_defaults(func=_go)
    sub.add_parser("broken", help="no func")
'''

CMD_RAISES = ("from teletouch import hookimpl\n@hookimpl\ndef teletouch_add_commands(subparsers):\n"
              "    raise RuntimeError('boom')\n")

DISCOVER = '''
from teletouch import hookimpl

@hookimpl
def teletouch_discover_devices():
    return [{"name": "acme thing"},
            {"kind": "acme", "path": "/dev/acme0"},
            {"kind": "acme", "id": "A1", "path": "/dev/acme1"}]
'''


def _install(site: Path, src: str, ep: str = "acme") -> None:
    mod = f"tt_{ep.replace('-', '_')}"
    make_dist(site, f"{ep}-dist", "1.0", {ep: mod}, {mod: src})


def _main(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = cli.main(list(argv))
    except SystemExit as exc:   # argparse's own usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


# --- 1. a plugin command without func ------------------------------------------------------------------------------
def test_a_plugin_command_without_func_is_removed_with_a_warning_naming_plugin_and_command(site, capsys):
    # before: `teletouch acme-hello` printed the full help and "a COMMAND is required" although one was given, and
    # `teletouch calibrate acme` said "WHAT is required (acme or force or depth)"
    _install(site, NO_FUNC)
    code, out, err = _main(capsys, "acme-hello")
    assert code == 2 and "invalid choice: 'acme-hello'" in err and "a COMMAND is required" not in err
    assert ("teletouch: warning: plugin 'acme' (acme-dist 1.0): command 'acme-hello' sets no "
            "func=callable(args) -> int; it is not added") in err
    assert ("teletouch: warning: plugin 'acme' (acme-dist 1.0): command 'calibrate acme' sets no "
            "func=callable(args) -> int; it is not added") in err
    code, out, err = _main(capsys, "calibrate", "acme")
    assert code == 2 and "invalid choice: 'acme'" in err and "WHAT is required" not in err
    code, out, err = _main(capsys, "acme-ok")   # the plugin's good command stays
    assert code == 0 and out.strip() == "hello from acme"
    code, out, err = _main(capsys, "plugins")   # a plugin problem: `teletouch plugins` exits 1
    assert code == 1 and "command 'acme-hello' sets no func" in err


def test_a_plugin_group_of_commands_keeps_its_working_commands(site, capsys):
    _install(site, NESTED)
    code, out, err = _main(capsys, "acme-tools", "go")
    assert code == 0 and out.strip() == "acme go ran"
    assert "command 'acme-tools broken' sets no func=callable(args) -> int" in err
    code, out, err = _main(capsys, "acme-tools", "broken")
    assert code == 2 and "invalid choice: 'broken'" in err
    code, out, err = _main(capsys, "acme-tools")   # the group alone: what is missing, not "a COMMAND is required"
    assert code == 2 and "error: TOOL is required (go)" in err and "a COMMAND is required" not in err


# --- 2. device discovery entries without kind/id/path ----------------------------------------------------------------
def test_a_discovery_entry_without_kind_id_or_path_is_an_error_row_naming_plugin_and_key(site):
    # before: [{"name": "acme thing"}] went through as a device: a bare '?' row, and --json passed it on
    _install(site, DISCOVER)
    rows = [r for r in Registry(autoload=True).load().discover_devices() if r.get("kind") == "acme"
            or "acme thing" in str(r)]
    assert len(rows) == 3, rows
    bad1, bad2, good = rows
    assert bad1["kind"] == "acme" and bad1["id"] == "" and bad1["path"] == ""
    assert "'kind', 'id', 'path'" in bad1["error"] and "entry 1" in bad1["error"] and "acme thing" in bad1["error"]
    assert bad2["kind"] == "acme" and "'id'" in bad2["error"] and "'path'" not in bad2["error"].split(":")[0]
    assert good == {"kind": "acme", "id": "A1", "path": "/dev/acme1"}


def test_devices_shows_the_refused_entry_as_an_error_not_a_question_mark_row(site, capsys):
    _install(site, DISCOVER)
    code, out, err = _main(capsys, "devices")
    assert code == 0
    lines = out.splitlines()
    assert not any(line.startswith("? ") for line in lines), out
    assert any("has no 'kind', 'id', 'path'" in line for line in lines), out
    code, out, err = _main(capsys, "devices", "--json")
    rows = json.loads(out)
    assert {"name": "acme thing"} not in rows
    assert all({"kind", "id", "path"} <= set(r) for r in rows)


# --- 3. the achieved rate ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rate, duration", [(100.0, 1.0), (60.0, 10.0), (1000.0, 0.5)])
def test_the_achieved_rate_under_the_sim_clock_is_the_nodes_rate(rate, duration):
    # before: steps / elapsed counted the step at t = 0 and the one at the end: 101.0 for 100 Hz over 1 s
    spec = load_graph(GRAPH, sets=[f"source.rate={rate:g}", f"scale.rate={rate:g}", f"device.rate={rate:g}"],
                      duration=duration)
    res = Runtime(spec).run(spec.duration)
    assert res.status == "ok"
    for n in res.nodes:
        assert n.achieved_rate == pytest.approx(rate, rel=1e-9), (n.id, n.steps, n.achieved_rate)
    row = next(line for line in res.summary().splitlines() if line.startswith("  source "))
    assert row.split()[2:4] == [f"{rate:.1f}", f"{rate:.1f}"], row


def test_the_live_view_shows_the_same_achieved_rate_as_the_summary():
    spec = load_graph(GRAPH, sets=["device.rate=100"], duration=1.0)
    rt = Runtime(spec)
    res = rt.run(spec.duration)
    rows = cli._Progress(io.StringIO()).rows(rt, res.sim_time)
    for n, row in zip(res.nodes, rows[1:]):
        assert row.split()[:3] == [n.id, f"{n.achieved_rate:.1f}", "Hz"], row
    assert rows[1].split()[1] == "100.0"


def test_the_live_view_shows_no_rate_before_a_node_has_two_steps():
    spec = load_graph(GRAPH, duration=1.0)
    rt = Runtime(spec)
    rows = cli._Progress(io.StringIO()).rows(rt, 0.0)   # nothing stepped yet
    assert [r.split() for r in rows[1:]] == [[n.id, "-", "Hz"] for n in spec.nodes], rows   # a row per node


# --- 4. the origin of a plugin loaded through TELETOUCH_PLUGINS ------------------------------------------------------
def test_a_warning_about_a_plugin_from_teletouch_plugins_has_single_parentheses(site, capsys, monkeypatch):
    (site / "tt_cmds_raise.py").write_text(CMD_RAISES)
    monkeypatch.setenv("TELETOUCH_PLUGINS", "tt_cmds_raise")
    code, out, err = _main(capsys, "validate", GRAPH)
    assert code == 0
    assert "plugin 'tt_cmds_raise' (TELETOUCH_PLUGINS): its commands are skipped" in err, err
    assert "((" not in err


def test_a_failed_plugin_from_teletouch_plugins_is_reported_with_single_parentheses(monkeypatch):
    monkeypatch.setenv("TELETOUCH_PLUGINS", "tt_not_a_real_module_xyz")
    problems = Registry(autoload=False).load().problems()
    assert problems and problems[0].startswith("plugin 'tt_not_a_real_module_xyz' (TELETOUCH_PLUGINS) failed")


# --- 5. texts --------------------------------------------------------------------------------------------------------
def test_validate_says_1_node(tmp_path, capsys):
    g = tmp_path / "one.yaml"
    g.write_text("clock: sim\nduration: 1\nnodes:\n  - {id: src, plugin: mock-sensor, rate: 100}\n")
    code, out, err = _main(capsys, "validate", str(g))
    assert code == 0 and f"{g}: OK (1 node: src@100Hz; clock sim)" in out, out
    code, out, err = _main(capsys, "validate", GRAPH)
    assert code == 0 and "OK (3 nodes: " in out


def test_plugins_with_autoload_off_says_so(monkeypatch, capsys):
    # before: nothing at all on stdout or stderr, exit 0
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", None)
    monkeypatch.setenv("TELETOUCH_DISABLE_PLUGIN_AUTOLOAD", "1")
    code, out, err = _main(capsys, "plugins")
    assert code == 0   # autoload off is a choice, not a plugin problem (docs: exit 1 only for those)
    assert "installed plugins are not loaded (TELETOUCH_DISABLE_PLUGIN_AUTOLOAD is set)" in out, (out, err)
    monkeypatch.setattr(registry, "_default", None)
    code, out, err = _main(capsys, "plugins", "--json")
    assert code == 0 and json.loads(out) == []   # stdout stays JSON; the note goes to stderr
    assert "installed plugins are not loaded (TELETOUCH_DISABLE_PLUGIN_AUTOLOAD is set)" in err
    monkeypatch.setattr(registry, "_default", None)
    monkeypatch.delenv("TELETOUCH_DISABLE_PLUGIN_AUTOLOAD")
    code, out, err = _main(capsys, "plugins")
    assert "not loaded (TELETOUCH_DISABLE_PLUGIN_AUTOLOAD" not in out + err
