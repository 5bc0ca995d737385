"""`teletouch devices` (core/cli.py cmd_devices): strict JSON, rows a user can act on, and what was looked at."""

from __future__ import annotations

import json
import math
import types

import pytest

from teletouch import cli, hookimpl
from teletouch.testing import make_registry


def _plugin(name: str, rows=None, error: Exception | None = None) -> types.ModuleType:
    mod = types.ModuleType(name)

    @hookimpl
    def teletouch_discover_devices():
        if error is not None:
            raise error
        return rows

    mod.teletouch_discover_devices = teletouch_discover_devices
    return mod


@pytest.fixture
def use_plugins(monkeypatch):
    """Run `teletouch devices` with exactly these plugins' discovery hooks."""
    def install(*mods):
        reg = make_registry(*mods, mocks=False)
        monkeypatch.setattr(cli, "default_registry", lambda **kw: reg)
        return reg
    return install


def _strict(text: str):
    return json.loads(text, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))


def test_json_stays_strict_when_a_plugin_reports_nan(use_plugins, capsys):
    """A plugin's NaN was printed as the bare word NaN: invalid JSON for every strict parser (jq, JavaScript)."""
    use_plugins(_plugin("acme", [{"kind": "acme", "id": "A1", "path": "/dev/acme0",
                                  "details": {"temperature": math.nan, "range": [0.0, math.inf],
                                              "plugin": "acme", "params": {"gain": -math.inf}}}]))
    assert cli.main(["devices", "--json"]) == 0
    rows = _strict(capsys.readouterr().out)
    det = rows[0]["details"]
    assert det["temperature"] is None and det["range"] == [0.0, None] and det["params"] == {"gain": None}


def test_text_rows_give_params_as_a_graph_takes_them_and_the_problem_on_its_own_line(use_plugins, capsys):
    """params were printed as a Python dict (params={'serial': 'D20001'}) and the problem, many lines long, inside the
    row among the details."""
    problem = "permission denied on /dev/video0: add the udev rules\n    RULE-1\n    RULE-2\nand replug the DIGIT"
    use_plugins(_plugin("acme", [{"kind": "digit", "id": "D20001", "path": "/dev/video0",
                                  "details": {"firmware": "0101", "readable": False, "plugin": "digit",
                                              "params": {"serial": "D20001"}, "problem": problem}}]))
    assert cli.main(["devices"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["digit", "D20001", "/dev/video0"] and "firmware=0101" in lines[0]
    assert "{" not in "\n".join(lines) and "problem" not in lines[0]
    assert lines[1] == "    use: plugin: digit serial=D20001"
    assert lines[2] == "    problem: permission denied on /dev/video0: add the udev rules"
    assert lines[3:6] == ["        RULE-1", "        RULE-2", "    and replug the DIGIT"]


def test_nothing_found_says_which_sources_were_checked(use_plugins, capsys):
    """'no supported hardware found' did not say what had been looked at, nor that a source could not be read."""
    use_plugins(_plugin("acme", []), _plugin("beta", None))
    assert cli.main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "no supported hardware found" in out and "sources checked: " in out
    assert "acme" in out and "beta" in out
    use_plugins(_plugin("acme", []), _plugin("beta", error=OSError("bus not readable")))
    assert cli.main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "    error: " in out and "bus not readable" in out
    assert "no supported hardware found" in out and "not read: beta" in out


def test_a_failing_source_keeps_exit_status_0_and_the_help_says_so(use_plugins, capsys):
    use_plugins(_plugin("acme", [{"kind": "acme", "id": "A1", "path": "/dev/acme0"}]),
                _plugin("beta", error=RuntimeError("driver crashed")))
    assert cli.main(["devices", "--json"]) == 0
    rows = _strict(capsys.readouterr().out)
    assert [r["kind"] for r in rows if not r.get("error")] == ["acme"]
    assert any("driver crashed" in r.get("error", "") for r in rows)
    with pytest.raises(SystemExit) as ei:
        cli.main(["devices", "-h"])
    assert ei.value.code == 0
    helptext = " ".join(capsys.readouterr().out.split())
    assert "exit status is 0" in helptext and "error row" in helptext
