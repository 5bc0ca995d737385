"""A component name two plugins provide: the message names each origin once in parentheses (it read
"plugin 'm_dup' ((TELETOUCH_PLUGINS))" and "((registered))") and gives advice that fits how each came: an installed one
is uninstalled or blocked, one named in TELETOUCH_PLUGINS dropped from it or blocked, one given to make_registry()
left out of it (TELETOUCH_BLOCK, which the message used to advise, has no effect there).

make_registry() also refuses a component named like a built-in one (a plugin with a `sim-gripper` of its own passed
its make_registry tests and was refused once installed), unless it is the built-in itself; builtins=True loads them."""

from __future__ import annotations

import types

import pytest

from teletouch import Component, Kind, Port, hookimpl
from teletouch.errors import DuplicateComponentError
from teletouch.registry import Registry
from teletouch.testing import make_registry, run_yaml


def _plugin(modname: str, *names: str) -> types.ModuleType:
    """A plugin module ``modname`` providing a trivial sensor per name."""
    classes = []
    for n in names:
        classes.append(type(f"C{len(classes)}", (Component,), {
            "name": n, "kind": Kind.SENSOR, "outputs": {"force": Port("float64", (), "N", "f")},
            "step": lambda self, t, inputs: {"force": 1.0}, "__module__": modname}))
    mod = types.ModuleType(modname)
    mod.teletouch_components = hookimpl(lambda: list(classes))
    return mod


def test_two_registered_plugins_hear_to_give_only_one_not_to_block():
    with pytest.raises(DuplicateComponentError) as ei:
        make_registry(_plugin("acme_one", "acme-force"), _plugin("acme_two", "acme-force"))
    msg = str(ei.value)
    assert "plugin 'acme_one' (registered) and plugin 'acme_two' (registered)" in msg, msg
    assert "((" not in msg and "TELETOUCH_BLOCK=" not in msg and "--block" not in msg, msg
    assert "give only one of 'acme_one' and 'acme_two' to make_registry()" in msg, msg


def test_plugins_named_in_teletouch_plugins_hear_to_drop_or_block_one(monkeypatch):
    for name in ("tt_conflict_a", "tt_conflict_b"):
        monkeypatch.setitem(__import__("sys").modules, name, _plugin(name, "acme-force"))
    reg = Registry(autoload=False, extra_modules=["tt_conflict_a", "tt_conflict_b"]).load()
    (msg,) = reg.problems()
    assert ("plugin 'tt_conflict_a' (TELETOUCH_PLUGINS) and plugin 'tt_conflict_b' (TELETOUCH_PLUGINS)" in msg), msg
    assert "((" not in msg and "uninstall" not in msg, msg
    assert "drop one from TELETOUCH_PLUGINS or block one (TELETOUCH_BLOCK=tt_conflict_a or " in msg, msg


def test_make_registry_refuses_a_built_in_component_s_name():
    with pytest.raises(DuplicateComponentError) as ei:
        make_registry(_plugin("acme_dup", "acme-force", "sim-gripper"))
    msg = str(ei.value)
    assert "plugin 'acme_dup': component 'sim-gripper' has the name of a built-in component (plugin 'sim-gripper' " \
           "of teletouch " in msg, msg
    assert "rename yours" in msg, msg
    with pytest.raises(DuplicateComponentError, match="built-in component"):   # the mocks are built-ins too
        make_registry(_plugin("acme_mock", "mock-gain"), mocks=False)


def test_with_the_built_ins_loaded_the_clash_is_refused_too_saying_to_rename():
    with pytest.raises(DuplicateComponentError) as ei:
        make_registry(_plugin("acme_dup", "sim-gripper"), builtins=True)
    msg = str(ei.value)
    assert "plugin 'sim-gripper' (teletouch " in msg and "plugin 'acme_dup' (registered)" in msg, msg
    assert "rename the other component" in msg and "TELETOUCH_BLOCK=" not in msg, msg


def test_the_built_in_module_itself_is_no_clash():
    reg = make_registry("teletouch.plugins.devices.sim_gripper")
    assert "sim-gripper" in reg.components
    reg = make_registry("teletouch.plugins.devices.sim_gripper", "teletouch.mock", builtins=True)
    assert "sim-gripper" in reg.components and not reg.errors()


def test_builtins_true_holds_teletouch_s_own_components_for_a_graph():
    reg = make_registry(_plugin("acme_ok", "acme-force"), builtins=True)
    assert {"sim-gripper", "depth", "poly-force", "position-force", "mock-sensor", "acme-force"} <= set(reg.components)
    text = """
clock: sim
nodes:
  - {id: command, plugin: mock-sensor, rate: 100, params: {signal: constant, amplitude: 10mm}}
  - {id: gripper, plugin: sim-gripper, rate: 1000, inputs: {opening_command: command.value}}
"""
    result, _ = run_yaml(text, reg, duration=0.1)
    assert result.exit_code == 0, result.message


def test_an_installed_and_a_built_in_provider_keep_their_advice_and_hear_to_rename():
    import teletouch.mock as mock

    reg = Registry(autoload=False)   # both loaded as the entry-point loader loads them
    reg._load_one("mock", "teletouch.mock", lambda: mock, "teletouch", "0.1.0")
    reg._load_one("acme", "acme_mod", lambda: _plugin("acme_mod", "mock-gain"), "acme-dist", "1.0")
    (msg,) = [p for p in reg.problems() if "mock-gain" in p]
    assert "plugin 'mock' (teletouch 0.1.0) and plugin 'acme' (acme-dist 1.0)" in msg, msg
    assert "uninstall one or block one (TELETOUCH_BLOCK=mock or TELETOUCH_BLOCK=acme" in msg, msg
    assert "rename the other component" in msg, msg
