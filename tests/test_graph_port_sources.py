"""What the values on a port are tied to is checked when a graph is validated (``Component.port_sources``).

`teletouch validate examples/paper-sim.yaml --set depth.model=sensor.model` said OK, and the run went on, while
`poly-force` still loaded the packaged calibration `sim-digit-qvga`, fitted on another depth model's depths (each
depth model has its own depth scale): on hardware, wrong forces in the operator's hand. poly-force refused it only
when its own `depth_model` was set too. Now the depth node says which model its depths are made with, poly-force which
model its calibration was made for (its `sensor_model_id`), and the graph refuses a wire whose two ends name different
ones, naming both nodes, both identities, what ties each and what to do, at the wire's line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from helpers_depth import qvga_and_vga_models_fixture

from teletouch import Component, Kind, Params, Port, hookimpl
from teletouch.cli import main
from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.estimators.force_calibration import _sensor_model_id
from teletouch.plugins.estimators.poly_force import ForceCalibration, PolyForce
from teletouch.testing import load_text, make_registry

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = str(REPO / "examples" / "paper-sim.yaml")
CALIBRATE_SIM = REPO / "examples" / "calibrate-force-sim.yaml"
HOW_FORCE = ("calibrate the force with this depth model (`teletouch calibrate force --set depth.model=...`) or set "
             "calibration to one made for it")


def _wire_line(path: str, text: str) -> int:
    """The line of ``path`` that holds ``text`` (1-based)."""
    lines = Path(path).read_text().splitlines()
    return next(i for i, line in enumerate(lines, 1) if text in line)


# --------------------------------------------------------------------------------------------- two tiny components
class _Maker(Component):
    """Gives values made with the model its parameter names."""

    name = "s17-maker"
    kind = Kind.SENSOR
    default_rate = 10.0
    outputs = {"value": Port("float64", (), "m", "a value"), "other": Port("float64", (), "m", "another")}

    class Params(Params):
        made_with: str = Field("", description="the model ('' none)")

    @classmethod
    def port_sources(cls, params):
        if not params.made_with:
            return {}
        return {"value": (params.made_with, f"made_with {params.made_with!r}", "set made_with to the user's")}

    def step(self, t, inputs):
        return {"value": 0.0, "other": 0.0}


class _User(Component):
    """Takes values made with the model its parameter names."""

    name = "s17-user"
    kind = Kind.ESTIMATOR
    default_rate = 10.0
    inputs = {"value": Port("float64", (), "m", "a value")}
    outputs = {"y": Port("float64", (), "m", "the value")}

    class Params(Params):
        made_for: str = Field("", description="the model ('' none)")

    @classmethod
    def port_sources(cls, params):
        return {"value": (params.made_for, f"made_for {params.made_for!r}")} if params.made_for else {}

    def step(self, t, inputs):
        return {"y": inputs.value("value", 0.0)}


class _Broken(_Maker):
    """A maker whose check raises."""

    name = "s17-broken"

    @classmethod
    def port_sources(cls, params):
        raise RuntimeError("no model today")


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Maker, _User, _Broken]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugin())


models = qvga_and_vga_models_fixture()


def _errors(text: str, reg) -> list[str]:
    with pytest.raises(GraphValidationError) as ei:
        load_text(text, reg)
    return [str(e) for e in ei.value.errors]


def _graph(made_with: str, made_for: str, port: str = "value") -> str:
    return f"""
clock: sim
nodes:
  - {{id: src, plugin: s17-maker, rate: 10, params: {{made_with: '{made_with}'}}}}
  - id: dst
    plugin: s17-user
    rate: 10
    params: {{made_for: '{made_for}'}}
    inputs: {{value: src.{port}}}
"""


def test_a_component_ties_no_port_by_default():
    assert Component.port_sources(Component.Params()) == {}
    assert _Maker.port_sources(_Maker.Params()) == {}


def test_a_wire_whose_ends_are_tied_to_different_identities_is_refused_at_its_line(reg):
    errs = _errors(_graph("model-a", "model-b"), reg)
    assert len(errs) == 1, errs
    e = errs[0]
    assert e.startswith("<test>:9: node 'dst': input 'value' <- src.value: "), e   # the wire's line
    assert ("node 'src' (s17-maker) sends values tied to 'model-a' (made_with 'model-a') and node 'dst' (s17-user) "
            "takes values tied to 'model-b' (made_for 'model-b')") in e, e
    assert e.endswith("to make them match: on node 'src', set made_with to the user's"), e


def test_the_same_identity_or_an_end_that_declares_none_passes(reg):
    assert [n.id for n in load_text(_graph("model-a", "model-a"), reg).nodes] == ["src", "dst"]
    assert [n.id for n in load_text(_graph("", "model-b"), reg).nodes] == ["src", "dst"]
    assert [n.id for n in load_text(_graph("model-a", ""), reg).nodes] == ["src", "dst"]
    # a port the maker declares nothing for (as a bridge, a replay or a filter in between): not checked
    assert [n.id for n in load_text(_graph("model-a", "model-b", "other"), reg).nodes] == ["src", "dst"]


def test_a_failing_source_check_is_reported_naming_the_plugin_without_hiding_other_errors(reg):
    errs = _errors("""
clock: sim
nodes:
  - {id: bad, plugin: s17-broken, rate: 10}
  - {id: use, plugin: s17-user, rate: 10, params: {made_for: b}, inputs: {value: bad.value}}
  - {id: src, plugin: s17-maker, rate: 10, params: {made_with: a}}
  - {id: dst, plugin: s17-user, rate: 10, params: {made_for: b}, inputs: {value: src.value}}
  - {id: dst2, plugin: s17-user, rate: 10, inputs: {value: src.nope}}
""", reg)
    assert any("node 'bad': the port source check of s17-broken failed: RuntimeError: no model today" in e
               for e in errs), errs
    assert any("node 'dst': input 'value' <- src.value: " in e and "tied to 'a'" in e for e in errs), errs
    assert any("node 'dst2': input 'value': s17-maker node 'src' has no output 'nope'" in e for e in errs), errs
    assert len(errs) == 3, errs


def test_a_source_check_returning_nonsense_is_reported_as_failed(reg, monkeypatch):
    monkeypatch.setattr(_Maker, "port_sources", classmethod(lambda cls, params: {"valeu": ("a", "x")}))
    errs = _errors(_graph("a", "b"), reg)
    assert len(errs) == 1 and "node 'src': the port source check of s17-maker failed: " in errs[0], errs
    assert "'valeu' is not a port of s17-maker" in errs[0], errs
    monkeypatch.setattr(_Maker, "port_sources", classmethod(lambda cls, params: {"value": ("", "x")}))
    errs = _errors(_graph("a", "b"), reg)
    assert len(errs) == 1 and "port 'value': identity '', expected a non-empty string" in errs[0], errs
    monkeypatch.setattr(_Maker, "port_sources", classmethod(lambda cls, params: {"value": ("a",)}))
    errs = _errors(_graph("a", "b"), reg)
    assert len(errs) == 1 and "port 'value': expected (identity, why) or (identity, why, how)" in errs[0], errs


# --------------------------------------------------------------------------------------------- depth and poly-force
def test_the_packaged_depth_model_and_force_calibration_are_tied_to_the_same_model():
    depth = DepthEstimator.port_sources(DepthEstimator.Params())
    force = PolyForce.port_sources(PolyForce.Params())
    assert depth["max_depth"][:2] == ("sim-digit-qvga", "model 'sim-digit-qvga'"), depth
    assert depth["depth"][0] == "sim-digit-qvga"
    assert force["max_depth"][0] == "sim-digit-qvga", force
    assert "made for depth model 'sim-digit-qvga'" in force["max_depth"][1], force
    assert force["max_depth"][2] == HOW_FORCE
    assert load_graph(PAPER_SIM).nodes   # the example validates


def _validate(capsys, graph: str, *sets: str) -> tuple[int, str]:
    code = main(["validate", graph, *[a for s in sets for a in ("--set", s)]])
    return code, capsys.readouterr().err


def test_another_depth_model_with_the_packaged_calibration_is_refused_by_validate_and_run(capsys, models):
    # before: OK, and the run gave forces from a calibration fitted on another model's depths
    line = _wire_line(PAPER_SIM, "max_depth: depth.max_depth")
    for command in ("validate", "run"):
        code = main([command, PAPER_SIM, "--set", f"depth.model={models['qvga']}", "--duration", "0.1"]
                    if command == "run" else [command, PAPER_SIM, "--set", f"depth.model={models['qvga']}"])
        err = capsys.readouterr().err
        assert code == 1, (command, err)
        lines = [x.strip() for x in err.splitlines() if "tied to" in x]
        assert len(lines) == 1, (command, err)
        e = lines[0]
        assert f"paper-sim.yaml:{line}:" in e and "node 'force': input 'max_depth' <- depth.max_depth: " in e, e
        assert f"node 'depth' (depth) sends values tied to 'qvga' (model '{models['qvga']}')" in e, e
        assert "node 'force' (poly-force) takes values tied to 'sim-digit-qvga' (calibration " in e, e
        assert "sim-digit-qvga.force.json, made for depth model 'sim-digit-qvga')" in e, e
        assert f"to make them match: on node 'force', {HOW_FORCE}; or on node 'depth', " in e, e


def _calibration(path: Path, sensor_model_id: str, depth_source: str = "depth.max_depth (depth)") -> str:
    """A force calibration fitted on a made-up curve, recording ``sensor_model_id`` and where its depth came from
    (as `teletouch calibrate force` does: a depth node's max_depth unless said), saved to ``path``."""
    d = np.linspace(5e-5, 1.5e-3, 40)
    cal = ForceCalibration.fit(d, 4000.0 * d + 1e6 * d ** 2, degree=2, sensor_model_id=sensor_model_id,
                               depth_source=depth_source)
    return str(cal.save(path))


def test_a_calibration_whose_depth_came_through_another_node_ties_nothing(capsys, tmp_path):
    """A review found: a press routine reading a filter (or any node but depth) records the sensor as the model;
    such a calibration was refused beside every depth node, and its error called 'sim-digit' a depth model."""
    graph = load_graph(CALIBRATE_SIM)
    assert _sensor_model_id(graph)[1] == "depth.max_depth (depth)"
    cal = _calibration(tmp_path / "filtered.force.json", "sim-digit", "lp.y (mock-gain)")
    assert PolyForce.port_sources(PolyForce.Params(calibration=cal)) == {}
    code, err = _validate(capsys, PAPER_SIM, f"force.calibration={cal}")
    assert code == 0, err
    # force.depth_model still checks it where the user says which model it was made for
    code, err = _validate(capsys, PAPER_SIM, f"force.calibration={cal}", "force.depth_model=sim-digit-qvga")
    assert code == 1 and "made for 'sim-digit'" in err, err


def test_a_calibration_made_for_that_model_passes(capsys, models, tmp_path):
    # the id `teletouch calibrate force --set depth.model=FILE` records for that model
    recorded = _sensor_model_id(load_graph(CALIBRATE_SIM, sets=[f"depth.model={models['qvga']}"]))[0]
    assert recorded == "qvga.model"
    cal = _calibration(tmp_path / "qvga.force.json", recorded)
    assert PolyForce.port_sources(PolyForce.Params(calibration=cal))["max_depth"][0] == "qvga"
    code, err = _validate(capsys, PAPER_SIM, f"depth.model={models['qvga']}", f"force.calibration={cal}")
    assert code == 0, err
    # and the packaged model against it is refused
    code, err = _validate(capsys, PAPER_SIM, f"force.calibration={cal}")
    assert code == 1 and "sends values tied to 'sim-digit-qvga'" in err and "takes values tied to 'qvga'" in err, err


def test_a_calibration_that_records_no_depth_model_is_not_checked(capsys, models, tmp_path):
    cal = _calibration(tmp_path / "old.force.json", "")
    assert PolyForce.port_sources(PolyForce.Params(calibration=cal)) == {}
    code, err = _validate(capsys, PAPER_SIM, f"depth.model={models['qvga']}", f"force.calibration={cal}")
    assert code == 0, err
