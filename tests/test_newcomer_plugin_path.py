"""`TELETOUCH_PLUGINS=acme_force` (the no-install route) failed with "ModuleNotFoundError: No module named
'acme_force'" unless the module's folder was on PYTHONPATH, and neither the error nor docs/writing-a-plugin.md said
so. The error now says to put its folder on PYTHONPATH or install its package; the page says it in section 2."""

from __future__ import annotations

from pathlib import Path

from teletouch.registry import Registry

REPO = Path(__file__).resolve().parents[1]
MODULE = """
from teletouch import Component, Port, hookimpl


class Double(Component):
    name = "acme-double"
    inputs = {"x": Port("float64", (), "N")}
    outputs = {"y": Port("float64", (), "N")}

    def step(self, t, inputs):
        return None


@hookimpl
def teletouch_components():
    return [Double]
"""


def _error(monkeypatch, modname: str) -> str:
    monkeypatch.setenv("TELETOUCH_PLUGINS", modname)
    reg = Registry(autoload=False).load()
    return reg.plugins[modname].error or ""


def test_a_module_python_cannot_find_says_to_put_its_folder_on_pythonpath(monkeypatch):
    err = _error(monkeypatch, "acme_force_s15_nowhere")
    assert "No module named 'acme_force_s15_nowhere'" in err, err
    assert "PYTHONPATH" in err and "acme_force_s15_nowhere.py" in err and "install" in err, err


def test_a_submodule_of_a_missing_package_says_the_same(monkeypatch):
    err = _error(monkeypatch, "acme_s15_nowhere.force")
    assert "No module named 'acme_s15_nowhere'" in err and "PYTHONPATH" in err, err
    assert "folder that holds the package acme_s15_nowhere" in err, err


def test_a_missing_dependency_of_a_module_that_was_found_is_not_blamed_on_the_path(monkeypatch, tmp_path):
    (tmp_path / "acme_s15_deps.py").write_text("import acme_s15_missing_dependency\n" + MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    err = _error(monkeypatch, "acme_s15_deps")
    assert "No module named 'acme_s15_missing_dependency'" in err and "PYTHONPATH" not in err, err


def test_with_its_folder_on_the_path_it_loads(monkeypatch, tmp_path):
    (tmp_path / "acme_s15_found.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("TELETOUCH_PLUGINS", "acme_s15_found")
    reg = Registry(autoload=False).load()
    assert reg.plugins["acme_s15_found"].error is None and "acme-double" in reg.components


def test_the_page_says_it_where_the_entry_point_is_explained():
    text = (REPO / "docs" / "writing-a-plugin.md").read_text()
    section = text[text.index("## 2. The entry point"):text.index("## 3. Use it in a graph")]
    assert "TELETOUCH_PLUGINS=" in section and "PYTHONPATH" in section, section


def test_a_missing_submodule_of_a_package_that_was_found_is_not_blamed_on_the_path(monkeypatch, tmp_path):
    # before: "put the folder that holds the package acme_s15_pkg.sub on PYTHONPATH", which cannot help: a
    # subpackage is found through its parent package, not through Python's path
    (tmp_path / "acme_s15_pkg").mkdir()
    (tmp_path / "acme_s15_pkg" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    err = _error(monkeypatch, "acme_s15_pkg.sub.mod")
    assert "No module named 'acme_s15_pkg.sub'" in err and "PYTHONPATH" not in err, err
