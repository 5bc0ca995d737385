"""Image sizes that the nodes' parameters fix are checked when a graph is validated (``Component.port_shapes``).

Ports declare images as (None, None, 3): a depth model made for VGA frames (640 x 480) on the QVGA simulated sensor
(320 x 240) passed `teletouch validate` and the run faulted at the first frame. Now sim-digit gives its image size from
``resolution``, digit from ``stream``, depth from its model's header, and the graph refuses a wire whose two ends fix
different sizes, naming both nodes, both sizes and what fixes each, and what to do."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import Field

from helpers_depth import qvga_and_vga_models_fixture

from teletouch import Component, Kind, Params, Port, hookimpl
from teletouch.cli import main
from teletouch.errors import GraphValidationError, ModelFileError
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.estimators import normal_model
from teletouch.plugins.estimators.normal_model import load_model
from teletouch.plugins.sensors.digit import Digit
from teletouch.plugins.sensors.sim_digit import SimDigit
from teletouch.testing import load_text, make_registry, run_yaml

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = str(REPO / "examples" / "paper-sim.yaml")


class _AnySize(Component):
    """A camera whose size no parameter fixes (as a mock or a replay)."""

    name = "s15-any-size"
    kind = Kind.SENSOR
    default_rate = 60.0
    outputs = {"image": Port("uint8", (None, None, 3), "", "BGR")}

    def step(self, t, inputs):
        return {"image": np.zeros((320, 240, 3), np.uint8)}


class _BrokenCheck(_AnySize):
    """A camera whose size check raises."""

    name = "s15-broken-check"

    class Params(Params):
        gain: float = Field(1.0, description="a parameter")

    @classmethod
    def port_shapes(cls, params):
        raise RuntimeError("no size today")


class _QvgaOnly(_AnySize):
    """A camera whose port itself declares its size."""

    name = "s15-qvga-only"
    outputs = {"image": Port("uint8", (320, 240, 3), "", "BGR")}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_AnySize, _BrokenCheck, _QvgaOnly]


@pytest.fixture(scope="module")
def reg():
    return make_registry("teletouch.plugins.sensors.sim_digit", "teletouch.plugins.sensors.digit",
                         "teletouch.plugins.sensors.replay", "teletouch.plugins.estimators.depth", _Plugin())


models = qvga_and_vga_models_fixture()


def _validate(capsys, graph: str, *sets: str) -> tuple[int, str]:
    code = main(["validate", graph, *[a for s in sets for a in ("--set", s)]])
    return code, capsys.readouterr().err


def _errors(text: str, reg, **kw) -> list[str]:
    with pytest.raises(GraphValidationError) as ei:
        load_text(text, reg, **kw)
    return [str(e) for e in ei.value.errors]


# --------------------------------------------------------------------------------------------- the classmethod
def test_a_component_fixes_no_port_shape_by_default():
    assert Component.port_shapes(Component.Params()) == {}
    assert _AnySize.port_shapes(_AnySize.Params()) == {}


def test_sim_digit_fixes_its_image_size_by_its_resolution():
    shapes = SimDigit.port_shapes(SimDigit.Params(resolution="qvga"))
    assert shapes["image"][:2] == ((320, 240, 3), "resolution 'qvga'")
    assert shapes["gt_depth"][0] == (320, 240) and shapes["gt_contact_mask"][0] == (320, 240)
    assert SimDigit.port_shapes(SimDigit.Params(resolution="vga"))["image"][0] == (640, 480, 3)


def test_digit_fixes_its_image_size_by_its_stream_for_a_camera_only():
    # portrait rows x cols, after the driver's transpose
    assert Digit.port_shapes(Digit.Params(stream="qvga30"))["image"][:2] == ((320, 240, 3), "stream 'qvga30'")
    assert Digit.port_shapes(Digit.Params(stream="vga15"))["image"][0] == (640, 480, 3)
    assert Digit.port_shapes(Digit.Params(stream="vga30", source="/dev/video7"))["image"][0] == (640, 480, 3)
    # a video file, a URL or check_resolution false: the first frame's size, not known before the run
    assert Digit.port_shapes(Digit.Params(stream="vga30", source="recording.mp4")) == {}
    assert Digit.port_shapes(Digit.Params(stream="vga30", source="rtsp://cam/1")) == {}
    assert Digit.port_shapes(Digit.Params(stream="vga30", check_resolution=False)) == {}


def test_depth_takes_the_size_its_model_was_made_for(models):
    image = DepthEstimator.port_shapes(DepthEstimator.Params(model=models["vga"]))["image"]
    assert image[:2] == ((640, 480, 3), f"model '{models['vga']}', made for 640x480 frames")
    assert "teletouch calibrate depth" in image[2]
    packaged = DepthEstimator.port_shapes(DepthEstimator.Params())
    assert packaged["image"][:2] == ((320, 240, 3), "model 'sim-digit-qvga', made for 320x240 frames")
    assert packaged["depth"][0] == (320, 240) and packaged["contact_mask"][0] == (320, 240)


def test_the_model_header_gives_the_image_shape_without_the_weights(models, tmp_path):
    assert normal_model.model_image_shape("sim-digit-qvga") == (320, 240)
    assert normal_model.model_image_shape(models["vga"]) == (640, 480)
    m = load_model(models["vga"])
    sd = {k: np.full_like(v, np.nan) for k, v in m.state_dict.items()}
    bad = dataclasses.replace(m, state_dict=sd).save(tmp_path / "nan.model")
    with pytest.raises(ModelFileError, match="NaN"):
        load_model(bad)   # the weights are read by load_model only
    assert normal_model.model_image_shape(bad) == (640, 480)


def test_a_header_without_its_size_is_a_model_file_error(models, tmp_path):
    with np.load(models["qvga"], allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    del meta["rows"]
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "norows.model", **arrays)
    p = tmp_path / "norows.model.npz"
    with pytest.raises(ModelFileError, match=r"norows.model.npz: meta field rows is None, expected an integer >= 1"):
        normal_model.model_image_shape(p)


# --------------------------------------------------------------------------------------------- teletouch validate
def test_a_vga_model_on_the_qvga_sim_digit_is_refused_by_validate(capsys, models):
    code, err = _validate(capsys, PAPER_SIM, f"depth.model={models['vga']}")
    assert code == 1, err
    lines = [line.strip() for line in err.splitlines() if "size" in line]
    assert len(lines) == 1, err
    line = lines[0]
    assert "paper-sim.yaml:" in line and "node 'depth': input 'image' <- digit.image:" in line, line
    assert "node 'digit' (sim-digit) sends 320x240 (rows x cols; fixed by resolution 'qvga')" in line, line
    assert (f"node 'depth' (depth) takes 640x480 (rows x cols; fixed by model '{models['vga']}', made for 640x480 "
            f"frames)") in line, line
    assert "use a depth model calibrated on this sensor's frames (`teletouch calibrate depth`)" in line, line
    assert "set resolution: qvga (320x240) or vga (640x480)" in line, line


def _calibration_for(model: str, folder: Path) -> str:
    """The packaged force calibration, recorded as made for the depth model file ``model``: poly-force refuses a
    depth node of another model (Component.port_sources), which is not what these tests check."""
    from teletouch.plugins.estimators.poly_force import ForceCalibration

    cal = ForceCalibration.load("sim-digit-qvga")
    cal.sensor_model_id = Path(model).name
    return str(cal.save(folder / (Path(model).stem + ".force.json")))


def test_the_same_model_at_qvga_passes_and_a_vga_sensor_takes_the_vga_model(capsys, models, tmp_path):
    qvga_cal, vga_cal = _calibration_for(models["qvga"], tmp_path), _calibration_for(models["vga"], tmp_path)
    assert _validate(capsys, PAPER_SIM, f"depth.model={models['qvga']}", f"force.calibration={qvga_cal}")[0] == 0
    assert _validate(capsys, PAPER_SIM)[0] == 0   # the packaged model
    assert _validate(capsys, PAPER_SIM, f"depth.model={models['vga']}", "digit.resolution=vga",
                     f"force.calibration={vga_cal}")[0] == 0
    code, err = _validate(capsys, PAPER_SIM, "digit.resolution=vga")   # the packaged QVGA model on a VGA sensor
    assert code == 1 and "takes 320x240 (rows x cols; fixed by model 'sim-digit-qvga'" in err, err


def test_a_sensor_whose_size_no_parameter_fixes_passes(reg, models, tmp_path):
    cv2.imwrite(str(tmp_path / "frame_0.png"), np.zeros((320, 240, 3), np.uint8))
    for sensor in ("{plugin: s15-any-size}", f"{{plugin: replay, params: {{path: '{tmp_path}'}}}}"):
        spec = load_text(f"""
clock: sim
nodes:
  - {{id: cam, rate: 60, {sensor[1:-1]}}}
  - {{id: depth, plugin: depth, rate: 60, params: {{model: '{models['vga']}'}}, inputs: {{image: cam.image}}}}
""", reg)
        assert [n.id for n in spec.nodes] == ["cam", "depth"]


def test_a_size_a_port_declares_is_checked_against_one_the_parameters_fix(reg, models):
    text = f"""
clock: sim
nodes:
  - {{id: cam, plugin: s15-qvga-only, rate: 60}}
  - {{id: depth, plugin: depth, rate: 60, params: {{model: '{models['vga']}'}}, inputs: {{image: cam.image}}}}
"""
    errs = _errors(text, reg)
    assert len(errs) == 1, errs
    assert ("node 'cam' (s15-qvga-only) sends 320x240 (rows x cols; fixed by its port) and node 'depth' (depth) "
            "takes 640x480") in errs[0], errs
    assert errs[0].endswith("to make them match: on node 'depth', use a depth model calibrated on this sensor's "
                            "frames (`teletouch calibrate depth`)"), errs
    assert [n.id for n in load_text(text.replace(models["vga"], models["qvga"]), reg).nodes] == ["cam", "depth"]


def test_the_real_digit_stream_is_checked_too(reg, models):
    text = """
clock: wall
nodes:
  - {id: cam, plugin: digit, params: {stream: vga30, frame_timeout: 1s}}
  - {id: depth, plugin: depth, rate: 60, inputs: {image: cam.image}}
"""
    errs = _errors(text, reg)
    assert len(errs) == 1, errs
    assert ("node 'cam' (digit) sends 640x480 (rows x cols; fixed by stream 'vga30') and node 'depth' (depth) takes "
            "320x240") in errs[0], errs
    assert "set stream: qvga60 or qvga30 (320x240), vga30 or vga15 (640x480)" in errs[0], errs
    ok = text.replace("stream: vga30", "stream: qvga30").replace("rate: 60, inputs", f"rate: 60, params: "
                                                                   f"{{model: '{models['qvga']}'}}, inputs")
    assert [n.id for n in load_text(ok, reg).nodes] == ["cam", "depth"]


def test_a_failing_size_check_is_reported_naming_the_plugin_without_hiding_other_errors(reg, models):
    errs = _errors(f"""
clock: sim
nodes:
  - {{id: cam, plugin: s15-broken-check, rate: 60}}
  - {{id: depth, plugin: depth, rate: 60, inputs: {{image: cam.image}}}}
  - {{id: sim, plugin: sim-digit, rate: 60, params: {{resolution: vga}}}}
  - {{id: depth2, plugin: depth, rate: 60, params: {{model: '{models['qvga']}'}}, inputs: {{image: sim.image}}}}
  - {{id: depth3, plugin: depth, rate: 60, inputs: {{image: sim.nope}}}}
""", reg)
    assert any("node 'cam': the port size check of s15-broken-check failed: RuntimeError: no size today" in e
               for e in errs), errs
    assert any("node 'depth2': input 'image' <- sim.image: " in e and "sends 640x480" in e for e in errs), errs
    assert any("node 'depth3': input 'image': sim-digit node 'sim' has no output 'nope'" in e for e in errs), errs
    assert len(errs) == 3, errs


def test_a_size_check_returning_nonsense_is_reported_as_failed(reg, monkeypatch):
    monkeypatch.setattr(_AnySize, "port_shapes", classmethod(lambda cls, params: {"imgae": ((1, 2, 3), "x")}))
    errs = _errors("""
clock: sim
nodes:
  - {id: cam, plugin: s15-any-size, rate: 60}
  - {id: depth, plugin: depth, rate: 60, inputs: {image: cam.image}}
""", reg)
    assert len(errs) == 1 and "node 'cam': the port size check of s15-any-size failed: " in errs[0], errs
    assert "'imgae' is not a port of s15-any-size" in errs[0], errs


# --------------------------------------------------------------------------------------------- at run time
def test_the_first_frame_check_still_faults_what_validation_cannot_see(reg, models, tmp_path):
    cv2.imwrite(str(tmp_path / "frame_0.png"), np.zeros((320, 240, 3), np.uint8))
    res, _ = run_yaml(f"""
clock: sim
nodes:
  - {{id: cam, plugin: replay, rate: 60, params: {{path: '{tmp_path}', loop: true}}}}
  - {{id: depth, plugin: depth, rate: 60, params: {{model: '{models['vga']}'}}, inputs: {{image: cam.image}}}}
""", reg, duration=0.2)
    assert res.exit_code != 0
    text = " ".join(f.line() for f in res.faults)
    assert "expected a uint8 BGR image of 640x480x3 (rows x cols, portrait)" in text, text
