"""`teletouch plugins NAME...`: one component's entry without reading ~700 lines (a newcomer checking a plugin of
their own got "unrecognized arguments")."""

from __future__ import annotations

import json

from teletouch.cli import main


def _names(text: str) -> list[str]:
    return [line.split()[0] for line in text.splitlines() if line and not line.startswith(" ") and "  (" in line]


def test_a_component_name_lists_that_component_only(capsys):
    assert main(["plugins", "position-force"]) == 0
    assert _names(capsys.readouterr().out) == ["position-force"]   # not its plugin's no-feedback, position-position


def test_a_plugin_or_distribution_name_lists_its_components(capsys):
    assert main(["plugins", "--json", "teletouch"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {"depth", "poly-force", "sim-digit", "position-force"} <= {r["name"] for r in rows}


def test_several_names_and_json(capsys):
    assert main(["plugins", "--json", "depth", "sim-digit"]) == 0
    assert [r["name"] for r in json.loads(capsys.readouterr().out)] == ["depth", "sim-digit"]


def test_a_name_that_matches_nothing_is_an_error_with_a_suggestion(capsys):
    assert main(["plugins", "postion-force"]) == 1
    err = capsys.readouterr().err
    assert "no component, plugin or distribution named 'postion-force'" in err and "'position-force'" in err
