"""poly-force's ``depth_model`` names the depth node's model file: a path that is no such file (missing, a folder, not
a depth model) is named as such, when the graph is validated and at configure, before the calibration's record of
the model it was made for is compared with it. The record is the model's file name (``sensor_model_id``): a model of
that name in another folder is the same model to it."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph
from teletouch.plugins.estimators.poly_force import PolyForce, resolve_calibration
from teletouch.testing import Harness

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = REPO / "examples" / "paper-sim.yaml"
PACKAGED_MODEL = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model"
EXPECTED = "depth_model must name the depth node's `model`: an existing depth model file or a packaged model's name"


def _refused(depth_model: str) -> str:
    with pytest.raises(ValidationError) as exc:
        PolyForce.Params(depth_model=depth_model)
    return str(exc.value)


def test_a_missing_depth_model_with_the_calibrations_name_is_refused_not_taken_as_the_same_model(tmp_path):
    # before: accepted (the name matched the calibration's 'sim-digit-qvga'), though no such file exists
    missing = tmp_path / "models" / "sim-digit-qvga.model"
    msg = _refused(str(missing))
    assert f"{missing}: no such model file" in msg and EXPECTED in msg, msg


def test_a_missing_depth_model_is_named_missing_not_made_for_another_model(tmp_path):
    # before: "the calibration ... was made for 'sim-digit-qvga', not for '.../my-digit.model'": a typo in the path
    # read as a calibration of another model
    missing = tmp_path / "my-digit.model"
    msg = _refused(str(missing))
    assert f"{missing}: no such model file" in msg and EXPECTED in msg and "made for" not in msg, msg


def test_a_folder_or_another_file_as_depth_model_is_named_as_such(tmp_path):
    folder = tmp_path / "sim-digit-qvga.model"
    folder.mkdir()
    msg = _refused(str(folder))
    assert f"{folder}: a folder, expected a model file" in msg and EXPECTED in msg, msg
    other = tmp_path / "json" / "sim-digit-qvga.model"   # the calibration where the depth model belongs
    other.parent.mkdir()
    shutil.copy(resolve_calibration("sim-digit-qvga"), other)
    msg = _refused(str(other))
    assert f"{other}: not a teletouch depth model" in msg and EXPECTED in msg, msg


def test_graph_validation_names_the_param_and_the_missing_file(tmp_path):
    missing = tmp_path / "sim-digit-qvga.model"
    with pytest.raises(GraphValidationError) as exc:
        load_graph(PAPER_SIM, sets=[f"force.depth_model={missing}"])
    (line,) = [str(e) for e in exc.value.errors]
    assert line.startswith(f"--set force.depth_model={missing}: node 'force': "), line
    assert f"param 'depth_model' = '{missing}': {missing}: no such model file" in line, line
    assert EXPECTED in line and "made for" not in line, line


def test_configure_refuses_a_depth_model_that_went_missing_after_validation(tmp_path):
    model = tmp_path / "sim-digit-qvga.model"
    shutil.copy(PACKAGED_MODEL, model)
    h = Harness(PolyForce, {"depth_model": str(model)})
    model.unlink()
    with pytest.raises(ValueError, match=rf"{model}: no such model file.*; {EXPECTED[:40]}"):
        h.comp.configure()


def test_a_model_file_of_the_recorded_name_in_any_folder_is_the_model_the_calibration_was_made_for(tmp_path):
    """The calibration records the model's file name only (sensor_model_id, no path, no digest): a calibration is
    made in one folder (or machine) and used in another, so the folder cannot be part of the model's identity."""
    model = tmp_path / "elsewhere" / "sim-digit-qvga.model"
    model.parent.mkdir()
    shutil.copy(PACKAGED_MODEL, model)
    with Harness(PolyForce, {"depth_model": str(model)}) as h:
        assert h.comp.cal.sensor_model_id == "sim-digit-qvga"
        assert h.step(0.1, max_depth=1e-3, centroid=np.zeros(2))["status"] == "ok"
    with Harness(PolyForce, {"depth_model": "sim-digit-qvga"}) as h:   # the packaged model by its name
        assert h.step(0.1, max_depth=1e-3, centroid=np.zeros(2))["status"] == "ok"


def test_an_existing_model_of_another_name_is_still_refused_as_made_for_another_model(tmp_path):
    model = tmp_path / "my-digit.model"
    shutil.copy(PACKAGED_MODEL, model)
    msg = _refused(str(model))
    assert f"was made for 'sim-digit-qvga', not for '{model}'" in msg and "no such" not in msg, msg
    with pytest.raises(GraphValidationError) as exc:
        load_graph(PAPER_SIM, sets=[f"force.depth_model={model}"])
    (line,) = [str(e) for e in exc.value.errors]
    assert f"was made for 'sim-digit-qvga', not for '{model}'" in line, line
