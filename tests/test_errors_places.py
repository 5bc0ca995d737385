"""The place a fault names (errors.exception_place) is the plugin's own line, not a library's: a step that gives
``json.loads`` bad text said "(decoder.py:353)", the standard library's line; an entry point naming a module that does
not exist said "(<frozen importlib._bootstrap>:1140)". Now: the innermost frame that is no library's (Python's standard
library, or an installed distribution that provides no teletouch plugin), with the library's line that raised beside
it, and the entry point itself where no code of the plugin was reached."""

from __future__ import annotations

import json
import re
import sys
import textwrap
from importlib import metadata

import pytest
from pydantic import BaseModel

from teletouch import Component, Kind, Port, hookimpl
from teletouch.errors import ComponentFault, exception_line, exception_place
from teletouch.testing import make_registry, run_yaml

HERE = "test_errors_places.py"


def _line_of(text: str) -> int:
    """The line of this file that holds ``text`` (once)."""
    with open(__file__) as f:
        hits = [i for i, line in enumerate(f, 1) if text in line and "_line_of(" not in line]
    assert len(hits) == 1, hits
    return hits[0]


class _Conf(BaseModel):
    f: float


class _Lib(Component):
    """A sensor whose step calls a library with bad input: the standard library's json, or pydantic (installed in
    site-packages, no teletouch plugin)."""

    name = "places-lib"
    kind = Kind.SENSOR
    outputs = {"force": Port("float64", (), "N", "f")}

    class Params(Component.Params):
        lib: str = "json"

    def step(self, t, inputs):
        if self.params.lib == "json":
            cfg = json.loads("{bad json")   # json-call
        elif self.params.lib == "pydantic":
            cfg = _Conf.model_validate({"f": "many"}).model_dump()   # pydantic-call
        else:
            raise RuntimeError("own error")   # own-raise
        return {"force": cfg["f"]}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Lib]


def _fault(lib: str) -> str:
    res, _ = run_yaml(f"clock: sim\nnodes:\n  - {{id: force, plugin: places-lib, rate: 10, params: {{lib: {lib}}}}}\n",
                      make_registry(_Plugin()), duration=0.5)
    assert res.status == "fault", res.message
    return res.faults[0].message


def test_a_step_that_a_stdlib_call_fails_in_names_the_plugins_line_and_the_librarys():
    # before: "JSONDecodeError: Expecting property name ... (decoder.py:353)"
    msg = _fault("json")
    assert msg.startswith("JSONDecodeError: Expecting property name enclosed in double quotes"), msg
    assert re.search(rf" \({HERE}:{_line_of('# json-call')}, raised in json/decoder\.py:\d+\)$", msg), msg


def test_a_step_that_a_site_packages_library_fails_in_names_the_plugins_line_and_the_librarys():
    msg = _fault("pydantic")
    assert msg.startswith("ValidationError: "), msg
    assert re.search(rf" \({HERE}:{_line_of('# pydantic-call')}, raised in pydantic/[\w/]+\.py:\d+\)$", msg), msg


def test_an_error_raised_by_the_plugins_own_line_reads_as_before():
    assert _fault("own").endswith(f"RuntimeError: own error ({HERE}:{_line_of('# own-raise')})")


def test_a_component_faults_where_or_a_never_raised_exception_reads_as_before():
    fault = ComponentFault("x")
    fault.where = "the input values sent to p"
    assert exception_place(fault) == "the input values sent to p"
    assert exception_place(ValueError("never raised")) == ""
    assert exception_line(ValueError("v")) == "ValueError: v"


@pytest.fixture(autouse=True)
def _forget_packages():
    """The test packages imported here are not left in ``sys.modules`` (each test's folder is another)."""
    yield
    for name in [m for m in sys.modules if m.startswith("acme_places_")]:
        del sys.modules[name]


def _dist(tmp_path, value: str):
    """An installed distribution (its metadata in ``tmp_path``, which the caller puts on Python's path) whose teletouch
    entry point 'typo' is ``value``; its package (named as ``value`` names it, a new one for each test) exists and
    holds ``ok`` only."""
    pkg = re.split(r"[.:]", value)[0]
    (tmp_path / pkg).mkdir()
    (tmp_path / pkg / "__init__.py").write_text("ok = 1\n")
    info = tmp_path / "acme_places-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-places\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[teletouch]\ntypo = {value}\n")
    (ep,) = [e for d in metadata.distributions(path=[str(tmp_path)]) for e in d.entry_points if e.name == "typo"]
    return ep


@pytest.mark.parametrize("value, error", [("acme_places_a.nonexistent_module", "ModuleNotFoundError"),
                                          ("acme_places_b:nothing", "AttributeError")])
def test_an_entry_point_that_names_nothing_is_named_not_the_importers_frozen_frame(tmp_path, monkeypatch, value,
                                                                                     error):
    # before: "ModuleNotFoundError: No module named 'acme_places.nonexistent_module' (<frozen importlib._bootstrap>:
    # 1140)", the attribute "(__init__.py:NNN)" of importlib.metadata: nothing a plugin's author can look at
    monkeypatch.syspath_prepend(str(tmp_path))
    ep = _dist(tmp_path, value)
    with pytest.raises(Exception) as caught:
        ep.load()   # as the registry loads a plugin
    line = exception_line(caught.value)
    assert line.startswith(f"{error}: "), line
    assert "frozen" not in line and "__init__.py" not in line, line
    assert line.endswith(f" (entry point 'typo = {value}' in [project.entry-points.teletouch] of acme-places)"), line


def test_an_entry_points_module_that_raises_names_its_own_line(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    ep = _dist(tmp_path, "acme_places_c.broken")
    (tmp_path / "acme_places_c" / "broken.py").write_text(textwrap.dedent("""\
        import json
        x = 1
        json.loads("{")
        """))
    with pytest.raises(json.JSONDecodeError) as caught:
        ep.load()
    assert re.search(r" \(broken\.py:3, raised in json/decoder\.py:\d+\)$", exception_line(caught.value))


def test_a_plugin_module_registered_from_site_packages_is_the_plugins_own_code(tmp_path, monkeypatch):
    """A plugin installed without a teletouch entry point (named in TELETOUCH_PLUGINS, or given to register()) lies in
    site-packages like a library: its line is named, not the runtime's that called it."""
    site = tmp_path / "lib" / "site-packages"
    (site / "acme_places").mkdir(parents=True)
    (site / "acme_places" / "__init__.py").write_text(textwrap.dedent("""\
        import json
        from teletouch import Component, Kind, Port, hookimpl

        class Sensor(Component):
            name = "acme-places"
            kind = Kind.SENSOR
            outputs = {"force": Port("float64", (), "N", "f")}

            def step(self, t, inputs):
                return {"force": json.loads("{bad json")["f"]}

        @hookimpl
        def teletouch_components():
            return [Sensor]
        """))
    monkeypatch.syspath_prepend(str(site))
    import acme_places

    res, _ = run_yaml("clock: sim\nnodes:\n  - {id: force, plugin: acme-places, rate: 10}\n",
                      make_registry(acme_places), duration=0.5)
    assert res.status == "fault"
    assert re.search(r"\(__init__\.py:10, raised in json/decoder\.py:\d+\)$", res.faults[0].message), res.faults[0]
