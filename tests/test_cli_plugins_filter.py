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


CMD_ONLY = ("from teletouch import hookimpl\n@hookimpl\ndef teletouch_add_commands(subparsers):\n"
            "    subparsers.add_parser('acme-hello').set_defaults(func=lambda args: 0)\n")


def test_a_filtered_list_says_where_the_problems_it_does_not_show_are(tmp_path):
    """A review found: `teletouch plugins position-force` beside a broken plugin exited 1 saying "N plugin problem(s)"
    of a list that did not show them; and a plugin with commands only could not be named."""
    from test_core_plugins_cli import BROKEN, cli, install

    site = install(tmp_path / "site", {"broken": BROKEN, "cmdonly": CMD_ONLY})
    r = cli("plugins", "position-force", site=site)
    assert r.returncode == 1 and "broken" not in r.stdout
    assert "1 plugin problem(s); `teletouch plugins` lists them; exit status 1" in r.stderr, r.stderr
    r = cli("plugins", "cmdonly", site=site)
    assert "plugins without components: cmdonly (acme-cmdonly 1.0: add_commands)" in r.stdout, (r.stdout, r.stderr)
    assert "position-force" not in r.stdout
