"""`calibrate force` records the depth model the calibration was made for: the depth node's `model`, also when
the graph leaves it at its default (before: the sensor node's name, "digit", which no depth model is named, so
poly-force's `depth_model` check refused the calibration it had just made)."""

from __future__ import annotations

from pathlib import Path

from teletouch.graph import load_graph
from teletouch.plugins.estimators.force_calibration import _sensor_model_id
from teletouch.plugins.estimators.depth import DepthEstimator

REPO = Path(__file__).resolve().parents[1]


def test_a_depth_node_at_its_default_model_records_that_model_not_the_sensor():
    spec = load_graph(REPO / "examples" / "calibrate-force.yaml")
    model_id, source = _sensor_model_id(spec)
    assert model_id == DepthEstimator.Params().model == "sim-digit-qvga"
    assert source == "depth.max_depth (depth)"


def test_a_depth_model_given_by_set_is_recorded_by_its_file_name():
    spec = load_graph(REPO / "examples" / "calibrate-force-sim.yaml",
                      sets=["depth.model=plugins/estimators/data/sim-digit-qvga.model"])
    assert _sensor_model_id(spec)[0] == "sim-digit-qvga.model"
