"""Adversarial third-party plugins (fake installed distributions on sys.path): every mistake is reported against the
plugin that made it, with what was expected, and the rest still loads."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes.plugin_dists import make_dist  # noqa: E402

from teletouch.errors import DuplicateComponentError, GraphValidationError
from teletouch.registry import Registry
from teletouch.testing import load_text

GOOD = '''
from teletouch import Component, Device, Kind, Params, Port, hookimpl

class C(Component):
    """A good component."""
    name = "{comp}"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "N")}
    outputs = {"y": Port("float64", (), "N")}

    def step(self, t, inputs):
        return {"y": 2.0 * inputs.value("x", 0.0)}

@hookimpl
def teletouch_components():
    return [C]
'''


def one(site: Path, src: str, comp: str = "acme-c", ep: str = "acme", dist: str = "acme-dist") -> Registry:
    """Install one distribution whose module is ``src`` (with ``{comp}`` replaced by ``comp``)."""
    make_dist(site, dist, "1.0", {ep: f"tt_{ep.replace('-', '_')}"},
              {f"tt_{ep.replace('-', '_')}": src.replace("{comp}", comp)})
    reg = Registry(autoload=True, blocked=()).load()
    assert "mock-sensor" in reg.components   # whatever the plugin does, the rest still loads
    return reg


def error_of(reg: Registry, name: str = "acme") -> str:
    rec = reg.plugins[name]
    assert rec.error, f"plugin '{name}' loaded without an error: {rec}"
    assert not rec.components
    assert "\n" not in rec.error   # one line, as `teletouch plugins` prints it
    return rec.error


# --- hooks ---------------------------------------------------------------------------------------------------------
def test_misspelt_hook_name_is_an_error_with_a_suggestion(site):
    reg = one(site, GOOD.replace("def teletouch_components", "def teletouch_component"))
    err = error_of(reg)
    assert "unknown hook 'teletouch_component'" in err and "did you mean 'teletouch_components'" in err


def test_hook_function_without_hookimpl_marker_is_an_error(site):
    reg = one(site, GOOD.replace("@hookimpl\n", ""))
    assert "'teletouch_components' is not decorated with @teletouch.hookimpl" in error_of(reg)


def test_hookimpl_with_argument_not_in_spec_is_one_line_naming_the_argument(site):
    reg = one(site, GOOD.replace("def teletouch_components()", "def teletouch_components(registry)"))
    err = error_of(reg)
    assert "PluginValidationError" in err and "'registry'" in err


def test_hook_returning_a_class_instead_of_a_list_says_so(site):
    reg = one(site, GOOD.replace("return [C]", "return C"))
    assert "must return a list of Component classes" in error_of(reg) and "[C]" in error_of(reg)


def test_hook_that_raises_is_reported_with_the_plugin_line(site):
    reg = one(site, GOOD.replace("return [C]", "raise RuntimeError('no SDK')"))
    err = error_of(reg)
    assert err.startswith("RuntimeError: no SDK") and "tt_acme.py" in err


def test_plugin_that_exits_at_import_is_reported_not_fatal(site):
    reg = one(site, "import sys\nsys.exit('bye')\n")
    assert "SystemExit('bye')" in error_of(reg)


def test_what_a_plugin_prints_while_loading_goes_to_stderr(site, capsys):
    reg = one(site, "print('hello from import')\n" + GOOD.replace("return [C]", "print('hello from hook')\n"
                                                                   "    return [C]"))
    assert reg.get("acme-c").plugin == "acme"
    out, err = capsys.readouterr()
    assert out == "" and "hello from import" in err and "hello from hook" in err


# --- component rules -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("change, expected", [
    (("def step", "def stepp"), "C must define step(self, t, inputs)"),
    (("kind = Kind.ESTIMATOR", "kind = Kind.DEVICE"), "does not subclass teletouch.Device"),
    (("    def step", "    from pydantic import BaseModel\n    class Params(BaseModel):\n        k: float = 1.0\n"
      "    def step"), "C.Params must subclass teletouch.Params"),
    (("kind = Kind.ESTIMATOR", "kind = Kind.ESTIMATOR\n    default_rate = -5"), "C.default_rate must be None or"),
    (("kind = Kind.ESTIMATOR", "kind = Kind.ESTIMATOR\n    default_rate = float('nan')"), "C.default_rate"),
    (('outputs = {"y"', 'outputs = {"y.z"'), "port name 'y.z' must be a Python identifier"),
    (('outputs = {"y": Port("float64", (), "N")}', 'outputs = [Port()]'), "C.outputs must be a dict"),
    (('inputs = {"x": Port("float64", (), "N")}', 'inputs = {"x": Port("float64", (), "mm")}'),
     "C.inputs['x'] unit 'mm' is not SI: declare 'm'"),
    (("    def step", "    class Params(Params):\n        span: float = Field(1.0, json_schema_extra={'unit': 'deg'})\n"
      "    def step"), "C.Params.span unit 'deg' is not SI: declare 'rad'"),
])
def test_component_that_cannot_run_is_refused_at_load(site, change, expected):
    src = GOOD.replace(*change).replace("from teletouch import", "from pydantic import Field\nfrom teletouch import")
    reg = one(site, src)
    assert expected in error_of(reg)
    assert "acme-c" not in reg.components


def test_default_rate_refused_before_a_graph_can_use_it(site):
    """A negative default rate passed validation ('a@-5Hz') and the run never ended."""
    reg = one(site, GOOD.replace("kind = Kind.ESTIMATOR", "kind = Kind.ESTIMATOR\n    default_rate = -5"))
    with pytest.raises(GraphValidationError, match="failed to load: C.default_rate"):
        load_text("clock: sim\nduration: 0.1\nnodes:\n  - {id: a, plugin: acme-c}\n", reg)


def test_two_components_with_one_name_in_one_plugin_are_refused(site):
    reg = one(site, GOOD.replace("return [C]", "return [C, D]") + "\nclass D(C):\n    pass\n")
    assert "provides two components named 'acme-c': C and D" in error_of(reg)


# --- duplicates ----------------------------------------------------------------------------------------------------
def test_component_name_taken_from_a_builtin_is_refused_naming_both_not_fatal(site):
    make_dist(site, "acme-dist", "1.0", {"acme": "tt_acme"},
              {"tt_acme": GOOD.replace("{comp}", "mock-sensor")})
    reg = Registry(autoload=True, blocked=()).load()   # raised before: every command of the CLI was dead
    assert "mock-gain" in reg.components and "mock-sensor" not in reg.components
    with pytest.raises(DuplicateComponentError) as ei:
        reg.get("mock-sensor")
    msg = str(ei.value)
    assert "plugin 'acme' (acme-dist 1.0)" in msg and "plugin 'mock' (teletouch " in msg
    assert "TELETOUCH_BLOCK=acme" in msg and "TELETOUCH_BLOCK=mock" in msg
    with pytest.raises(GraphValidationError) as ei:
        load_text("clock: sim\nduration: 1\nnodes:\n  - {id: s, plugin: mock-sensor}\n", reg)
    assert "<test>:4: node 's': component 'mock-sensor' is provided by both" in str(ei.value)
    row = next(r for r in reg.describe() if r["name"] == "mock-sensor")
    assert row["kind"] is None and "acme-dist" in row["error"]
    # blocking the intruder gives the built-in its name back
    assert Registry(autoload=True, blocked=["acme"]).load().get("mock-sensor").distribution == "teletouch"


def test_same_plugin_name_in_two_distributions_resolved_by_blocking_a_distribution(site):
    make_dist(site, "one-dist", "1.0", {"same": "tt_one"}, {"tt_one": GOOD.replace("{comp}", "one-c")
                                                            })
    make_dist(site, "two-dist", "1.0", {"same": "tt_two"}, {"tt_two": GOOD.replace("{comp}", "two-c")
                                                            })
    reg = Registry(autoload=True, blocked=()).load()
    assert "mock-sensor" in reg.components
    err = reg.plugins["same"].error
    assert "'one-dist'" in err and "'two-dist'" in err and "TELETOUCH_BLOCK=two-dist" in err
    reg = Registry(autoload=True, blocked=["two-dist"]).load()   # the remedy the message gives works
    assert "one-c" in reg.components and "two-c" not in reg.components and not reg.errors()


def test_entry_point_name_that_cannot_be_blocked_is_refused(site):
    reg = one(site, GOOD, ep="my plugin,x")
    assert "plugin name 'my plugin,x' is not loaded" in error_of(reg, "my plugin,x")


# --- blocking ------------------------------------------------------------------------------------------------------
def test_blocked_name_that_matches_nothing_is_reported_with_a_suggestion(site):
    reg = Registry(autoload=True, blocked=["mokc", "mock-sensor", "digit"]).load()
    lines = reg.unknown_blocked()
    assert len(lines) == 2
    assert "'mokc'" in lines[1] and "did you mean 'mock'" in lines[1]
    assert "'mock-sensor' is a component of plugin 'mock'" in lines[0]
    assert reg.plugins["digit"].blocked and "digit" not in reg.components
    assert any("'mokc'" in p for p in reg.problems())


def test_blocked_plugin_is_never_imported_even_if_broken(site):
    make_dist(site, "broken-dist", "0.1", {"broken": "tt_broken"}, {"tt_broken": "import sys\nsys.exit(3)\n"})
    reg = Registry(autoload=True, blocked=["broken-dist"]).load()
    assert reg.plugins["broken"].blocked and not reg.errors() and "tt_broken" not in sys.modules
    assert reg.unknown_blocked() == []



def test_blocked_names_given_as_one_string_block_those_plugins(site, monkeypatch):
    # before: a string was iterated, so Registry(blocked="digit") blocked 'd', 'i', 'g', 't' and loaded digit
    reg = Registry(autoload=True, blocked="digit,mock").load()
    assert reg.plugins["digit"].blocked and reg.plugins["mock"].blocked and "mock-gain" not in reg.components
    assert sorted(reg.blocked) == ["digit", "mock"] and reg.unknown_blocked() == []
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", None)
    assert registry.default_registry(blocked="digit").plugins["digit"].blocked
    make_dist(site, "acme-dist", "1.0", {}, {"tt_extra": GOOD.replace("{comp}", "acme-c")})
    reg = Registry(autoload=False, extra_modules="tt_extra").load()
    assert "acme-c" in reg.components and not reg.errors()

def test_unknown_name_mentions_blocked_plugins(site):
    reg = Registry(autoload=True, blocked=["mock"]).load()
    msg = reg.unknown_message("mock-gain")
    assert "blocked plugins (not loaded): mock" in msg


def test_device_discovery_returning_one_dict_is_an_error_row_not_a_crash(site):
    src = ("from teletouch import hookimpl\n@hookimpl\ndef teletouch_discover_devices():\n"
           "    print('scanning')\n    return {'kind': 'acme', 'id': '1', 'path': '/dev/acme0'}\n")
    reg = one(site, src)
    rows = [d for d in reg.discover_devices() if d["kind"] == "acme"]
    assert len(rows) == 1 and "must return a list of dicts" in rows[0]["error"]
    assert all(isinstance(d, dict) for d in reg.discover_devices())


def test_unknown_plugin_in_a_registry_made_without_autoload_says_why_truthfully(monkeypatch):
    # before: a test registry (autoload=False) said "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD is set" and "run `teletouch
    # plugins`", both wrong for it
    monkeypatch.delenv("TELETOUCH_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    msg = Registry(autoload=False).load().unknown_message("acme-linear-force")
    assert "autoload=False" in msg and "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD" not in msg and "teletouch plugins" not in msg
    monkeypatch.setenv("TELETOUCH_DISABLE_PLUGIN_AUTOLOAD", "1")
    assert "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD is set" in Registry().load().unknown_message("acme-linear-force")
