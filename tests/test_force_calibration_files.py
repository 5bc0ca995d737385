"""A wrong file as force calibration: a binary or text file that is no calibration is named as such (not as a UTF-8
codec's complaint), and `teletouch validate` refuses what start-up would: a poly-force `calibration` that is missing
or no calibration of this version, a `depth_model` it was not made for, a `depth_limit` inside its range."""

from __future__ import annotations

import json
from importlib.resources import files
from pathlib import Path

import pytest

from teletouch.cli import main
from teletouch.errors import GraphValidationError, ModelFileError
from teletouch.graph import load_graph
from teletouch.plugins.estimators.poly_force import ForceCalibration, PolyForce, resolve_calibration

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = REPO / "examples" / "paper-sim.yaml"
NOT_ONE = "not a force calibration (expected the JSON written by `teletouch calibrate force`)"


@pytest.fixture
def binary(tmp_path) -> Path:
    """A depth model where the calibration belongs (a zip archive: not UTF-8)."""
    p = tmp_path / "sensor.model"
    p.write_bytes((REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model").read_bytes()[:4096])
    return p


@pytest.fixture
def packaged() -> dict:
    return json.loads(resolve_calibration("sim-digit-qvga").read_text())


def test_a_binary_file_is_not_a_force_calibration(binary):
    # before: "sensor.model: cannot read the force calibration file: 'utf-8' codec can't decode byte 0xb9 ..."
    with pytest.raises(ModelFileError) as exc:
        ForceCalibration.load(binary)
    assert str(exc.value) == f"{binary}: {NOT_ONE}"


def test_a_text_file_that_is_no_json_is_not_a_force_calibration(tmp_path):
    p = tmp_path / "pairs.csv"
    p.write_text("depth_m,force_n\n0.001,1.0\n")
    with pytest.raises(ModelFileError) as exc:
        ForceCalibration.load(p)
    assert str(exc.value) == f"{p}: {NOT_ONE}"


def test_teletouch_estimate_names_the_wrong_calibration_file(binary, capsys):
    assert main(["estimate", "--model", "sim-digit-qvga", "--force-calibration", str(binary), "none.png"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"teletouch estimate: error: --force-calibration {binary}: {NOT_ONE}"), err   # (exit 2:
    assert "codec" not in err, err                                                                   # an input error)


def _validate_errors(sets) -> list[str]:
    with pytest.raises(GraphValidationError) as exc:
        load_graph(PAPER_SIM, sets=sets)
    return [str(e) for e in exc.value.errors]


def test_validate_refuses_a_calibration_that_is_no_calibration(binary, capsys):
    # before: `teletouch validate` said OK and `teletouch run` failed at start-up (exit 4)
    item = f"force.calibration={binary}"
    assert main(["validate", str(PAPER_SIM), "--set", item]) == 1
    err = capsys.readouterr().err
    assert f"--set {item}: node 'force': param 'calibration' = '{binary}': {binary}: {NOT_ONE}" in err, err


def test_validate_refuses_a_calibration_file_at_its_line(tmp_path, binary):
    graph = tmp_path / "g.yaml"
    graph.write_text(f"include: {PAPER_SIM}\nnodes:\n  - id: force\n    params: {{calibration: {binary}}}\n")
    with pytest.raises(GraphValidationError) as exc:
        load_graph(graph)
    (line,) = [str(e) for e in exc.value.errors]
    assert line.startswith(f"{graph}:4: node 'force': param 'calibration' = ") and NOT_ONE in line, line


@pytest.mark.parametrize("mutate, why", [
    (lambda d: d.update(version=2), "field 'version': file version 2, this teletouch reads version 1"),
    (lambda d: d.update(format="teletouch-depth-model"), "field 'format': expected 'teletouch-force-calibration'"),
    (lambda d: None, None),
])
def test_validate_refuses_a_calibration_of_another_format_or_version(tmp_path, packaged, mutate, why):
    p = tmp_path / "c.force.json"
    mutate(packaged)
    p.write_text(json.dumps(packaged))
    if why is None:   # the packaged calibration, copied: valid
        assert load_graph(PAPER_SIM, sets=[f"force.calibration={p}"]).node("force").params["calibration"] == str(p)
        return
    (line,) = _validate_errors([f"force.calibration={p}"])
    assert line.startswith(f"--set force.calibration={p}: node 'force': param 'calibration' = ") and why in line


def test_validate_refuses_a_missing_calibration(tmp_path):
    (line,) = _validate_errors([f"force.calibration={tmp_path / 'nope.force.json'}"])
    assert "nope.force.json: no such force calibration file" in line, line


def test_validate_refuses_a_depth_model_the_calibration_was_not_made_for(tmp_path):
    # (the depth models named must exist: a missing one is named as missing)
    src = files("teletouch.plugins.estimators") / "data" / "sim-digit-qvga.model"
    (tmp_path / "models").mkdir()
    for name in ("my-digit.model", "models/sim-digit-qvga.model"):
        (tmp_path / name).write_bytes(src.read_bytes())
    mine = tmp_path / "my-digit.model"
    (line,) = _validate_errors([f"force.depth_model={mine}"])
    assert line.startswith(f"--set force.depth_model={mine}: node 'force': "), line
    assert f"was made for 'sim-digit-qvga', not for '{mine}'" in line
    same = tmp_path / "models" / "sim-digit-qvga.model"
    assert load_graph(PAPER_SIM, sets=[f"force.depth_model={same}"]).nodes   # the same model


def test_validate_refuses_a_depth_limit_inside_the_calibrated_range():
    (line,) = _validate_errors(["force.depth_limit=1mm"])
    assert line.startswith("--set force.depth_limit=1mm: node 'force': "), line
    assert "must be deeper than the calibration's deepest depth" in line


def test_start_up_still_refuses_a_file_that_changed_after_validation(tmp_path, packaged):
    p = tmp_path / "c.force.json"
    p.write_text(json.dumps(packaged))
    params = PolyForce.Params(calibration=str(p))
    p.write_bytes(b"\x00\x88binary")
    with pytest.raises(ModelFileError, match="not a force calibration"):
        PolyForce(params).configure()


@pytest.mark.parametrize("edit", [lambda c: [c[0] - 1.5] + c[1:], lambda c: [c[0] + 1.7] + c[1:],
                                  lambda c: [c[0]] + [x * 1.9 for x in c[1:]], lambda c: [x * 0.55 for x in c]],
                         ids=["c0-1.5N", "c0+1.7N", "c1-c3x1.9", "all-x0.55"])
def test_coefficients_that_do_not_fit_the_files_own_samples_are_refused(tmp_path, edit):
    """The load compared only the curve's two ends with force_range_n: a constant term moved by 1.5 N (0 N, status
    ok, up to 0.5 mm into the contact), or every coefficient scaled (half the force), loaded, the file still saying
    R^2 0.99996."""
    d = [2e-4 * i for i in range(1, 18)]
    cal = ForceCalibration.fit(d, [3000 * x + 2e6 * x * x - 4e8 * x ** 3 for x in d], degree=3)
    doc = cal.to_dict()
    assert ForceCalibration.from_dict(doc, "ok.force.json").r2 > 0.9999   # the file as written loads
    doc["model"]["coefficients"] = edit(list(doc["model"]["coefficients"]))
    with pytest.raises(ModelFileError, match=r"e.force.json: field 'model.coefficients': the coefficients do not "
                                             r"fit the file's own 17 samples: R\^2 -?\d\.\d{4} with them, the file "
                                             r"says 1\.0000"):
        ForceCalibration.from_dict(doc, "e.force.json")
