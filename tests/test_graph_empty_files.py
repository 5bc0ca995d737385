"""An empty or folder path for the depth model or the force calibration is named as such at validation (before:
"param 'model' = '': : a folder, expected a model file"; a folder as calibration: "not found: not a file")."""

from __future__ import annotations

import pytest

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph


@pytest.mark.parametrize("item, why", [
    ("depth.model=", "param 'model' = '': empty: expected a model file"),
    ("force.calibration=", "param 'calibration' = '': empty: expected a force calibration file"),
    ("force.calibration=examples", "examples: a folder, expected a force calibration file"),
    ("depth.model=examples", "examples: a folder, expected a model file")])
def test_an_empty_or_folder_path_is_named_as_such(item, why):
    with pytest.raises(GraphValidationError) as err:
        load_graph("examples/paper-sim.yaml", sets=[item])
    assert why in str(err.value) and ": :" not in str(err.value), str(err.value)
