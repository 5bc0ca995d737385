"""`teletouch calibrate depth` and `teletouch estimate` end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from teletouch.cli import main
from teletouch.plugins.estimators.normal_model import load_model

REPO = Path(__file__).resolve().parents[1]
FORCE_JSON = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.force.json"


@pytest.fixture(scope="module")
def sim_presses(tmp_path_factory):
    import sys

    sys.path.insert(0, str(REPO / "scripts"))
    try:
        from make_sim_depth_model import render_presses
    finally:
        sys.path.pop(0)
    folder = tmp_path_factory.mktemp("presses")
    render_presses(folder, 6, seed=11)
    return folder


def _json_lines(text: str):
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def test_calibrate_depth_writes_a_model(sim_presses, tmp_path, capsys):
    out = tmp_path / "sensor.model"
    rc = main(["calibrate", "depth", "--images", str(sim_presses), "--ball-diameter", "6mm", "--px-per-mm",
               "17.15px/mm", "--labels", str(sim_presses / "labels.csv"), "--background",
               str(sim_presses / "background.png"), "--epochs", "2", "--holdout", "1", "--hidden", "16", "16",
               "--quiet", "-o", str(out), "--review", str(tmp_path / "review")])
    assert rc == 0
    summary = _json_lines(capsys.readouterr().out)[-1]
    assert summary["model"] == str(out) and summary["validation_presses"] == 1
    assert len(summary["presses"]) == 5 and "background.png" not in summary["presses"]
    m = load_model(out)
    assert m.px_per_m == pytest.approx(17150.0) and m.ball_radius_m == pytest.approx(0.003)
    assert m.hidden == (16, 16) and m.training["epochs"] == 2
    assert np.array_equal(m.background, cv2.imread(str(sim_presses / "background.png")))
    assert len(list((tmp_path / "review").glob("*.review.png"))) == 6


def test_calibrate_depth_labels_automatically(shared_data, tmp_path, capsys):
    imgs = tmp_path / "imgs"
    shutil.copytree(shared_data / "digit-presses-qvga", imgs, ignore=shutil.ignore_patterns("*.csv"))
    rc = main(["calibrate", "depth", "--images", str(imgs), "--ball-radius", "3mm", "--px-per-mm", "17.15",
               "--labels-only", "--write-labels", str(tmp_path / "auto.csv")])
    assert rc == 0
    text = (tmp_path / "auto.csv").read_text().splitlines()
    assert text[0] == "image,center_x,center_y,radius_px,note" and len(text) == 11
    from teletouch.plugins.estimators.depth_calibration import read_labels

    labs = read_labels(tmp_path / "auto.csv")
    assert abs(labs["0004.png"].cx - 182) < 4 and abs(labs["0004.png"].cy - 193) < 4


def test_calibrate_depth_input_errors(sim_presses, tmp_path, capsys):
    rc = main(["calibrate", "depth", "--images", str(sim_presses), "--px-per-mm", "17.15", "-o",
               str(tmp_path / "x.model")])
    assert rc == 2 and "--ball-diameter 6mm" in capsys.readouterr().err
    rc = main(["calibrate", "depth", "--images", str(tmp_path / "nope"), "--ball-diameter", "6mm",
               "--px-per-mm", "17.15", "-o", str(tmp_path / "x.model")])
    assert rc == 2 and "no such folder" in capsys.readouterr().err
    rc = main(["calibrate", "depth", "--images", str(sim_presses), "--ball-diameter", "6 kg",
               "--px-per-mm", "17.15", "-o", str(tmp_path / "x.model")])
    assert rc == 2 and "expected a quantity in m" in capsys.readouterr().err


def test_estimate_json_depth_files_and_force(sim_presses, tmp_path, capsys, monkeypatch):
    press = sorted(sim_presses.glob("press_*.png"))[0]
    bg = sim_presses / "background.png"
    from teletouch.plugins.estimators.depth_pipeline import DepthPipeline

    calls = []   # the pipeline is warmed up before the first image, so its "ms" is that image's own computation
    for name in ("warm_up", "__call__"):
        real = getattr(DepthPipeline, name)
        monkeypatch.setattr(DepthPipeline, name, lambda self, *a, _r=real, _n=name: calls.append(_n) or _r(self, *a))
    rc = main(["estimate", "--model", "sim-digit-qvga", str(press), str(bg), "--json", "--save-depth",
               str(tmp_path / "d"), "--force-calibration", str(FORCE_JSON)])
    assert rc == 0
    assert calls[0] == "warm_up" and calls.count("warm_up") == 1
    rows = _json_lines(capsys.readouterr().out)
    assert [Path(r["image"]).name for r in rows] == [press.name, "background.png"]
    pr, nc = rows
    assert 0.1e-3 < pr["max_depth_m"] < 1.5e-3 and pr["contact_area_m2"] > 0 and pr["force_N"] > 0
    assert nc["max_depth_m"] == 0.0 and nc["contact_area_m2"] == 0.0 and nc["force_N"] == 0.0
    assert nc["centroid_m"] == [None, None]
    # the packaged calibration has position terms: the force is the one at the press's centroid
    from teletouch.plugins.estimators.poly_force import ForceCalibration

    cal = ForceCalibration.load(FORCE_JSON)
    assert pr["force_N"] == pytest.approx(cal.predict(pr["max_depth_m"], position=tuple(pr["centroid_m"])))
    d = np.load(tmp_path / "d" / f"{press.stem}.npy")
    assert d.dtype == np.float32 and d.shape == (320, 240) and d.max() == pytest.approx(pr["max_depth_m"],
                                                                                         rel=0.05)
    png = cv2.imread(str(tmp_path / "d" / f"{press.stem}.png"))
    assert png.shape == (320, 240, 3)


def test_estimate_errors(tmp_path, capsys):
    rc = main(["estimate", "--model", str(tmp_path / "missing.model"), "x.png"])
    assert rc == 1 and "missing.model: no such model file" in capsys.readouterr().err
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), np.zeros((640, 480, 3), np.uint8))
    rc = main(["estimate", "--model", "sim-digit-qvga", str(big), "--json"])
    assert rc == 2 and "expected a uint8 BGR image of 320x240x3" in capsys.readouterr().err
