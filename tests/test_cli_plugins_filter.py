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
    # the problem itself, not "`teletouch plugins` lists them" (which a command a plugin could not add was not in)
    assert "1 plugin problem(s), exit status 1:\n  plugin 'broken' (acme-broken 1.0) failed to load: " in r.stderr, \
        r.stderr
    r = cli("plugins", "cmdonly", site=site)
    assert "plugins without components: cmdonly (acme-cmdonly 1.0: add_commands)" in r.stdout, (r.stdout, r.stderr)
    assert "position-force" not in r.stdout


def test_a_name_that_matches_nothing_names_the_plugins_that_failed_to_load(tmp_path):
    """docs/writing-a-plugin.md has an author check their plugin with `teletouch plugins NAME`: when that plugin failed
    to load, the command said only "no component ... named NAME" (exit 1), never why (`validate` did)."""
    from test_core_plugins_cli import BROKEN, cli, install

    site = install(tmp_path / "site", {"broken": BROKEN})
    r = cli("plugins", "acme-lowpass", site=site)
    assert r.returncode == 1
    assert "no component, plugin or distribution named 'acme-lowpass'" in r.stderr, r.stderr
    said = "1 plugin(s) failed to load, which may provide it:\n  plugin 'broken' (acme-broken 1.0): ModuleNotFoundError"
    assert said in r.stderr, r.stderr


def test_a_module_in_teletouch_plugins_that_is_installed_too_is_loaded_once_without_an_error(tmp_path):
    """The doc's "try a module without installing" (TELETOUCH_PLUGINS=module), then `pip install -e .` with the
    variable still set: pluggy's "Plugin already registered under a different name" and a 2 KB dump of every plugin,
    exit 1, for a plugin that works."""
    from test_core_plugins_cli import cli, estimator_source, install

    site = install(tmp_path / "site", {"twice": estimator_source("twice-est")})
    r = cli("plugins", "twice-est", site=site, TELETOUCH_PLUGINS="tt_twice")
    assert r.returncode == 0, r.stderr
    assert "twice-est" in r.stdout and "already registered" not in r.stderr + r.stdout
    r = cli("plugins", site=site, TELETOUCH_PLUGINS="tt_twice")
    assert r.returncode == 0 and "FAILED TO LOAD" not in r.stdout, r.stdout[-2000:]
