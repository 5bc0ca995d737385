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

from helpers_depth import presses_fixture

REPO = Path(__file__).resolve().parents[1]
FORCE_JSON = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.force.json"


sim_presses = presses_fixture(6, seed=11)


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


def test_estimate_refuses_an_implausible_frame_instead_of_a_confident_depth(sim_presses, tmp_path, capsys):
    # a black frame (LEDs off) read as a ~2.7 mm contact; now it is reported, with no numbers, and the exit code says
    # so; the good image beside it is still measured
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((320, 240, 3), np.uint8))
    press = sorted(sim_presses.glob("press_*.png"))[0]
    rc = main(["estimate", "--model", "sim-digit-qvga", str(black), str(press), "--json"])
    out = capsys.readouterr()
    assert rc == 2 and "black.png: implausible frame" in out.err and "LEDs off" in out.err
    bad, good = _json_lines(out.out)
    assert bad["valid"] is False and bad["max_depth_m"] is None and "max_global_change 24" in bad["problem"]
    assert good["valid"] is True and 0.1e-3 < good["max_depth_m"] < 1.5e-3
    with pytest.raises(SystemExit) as exc:
        main(["estimate", "--model", "sim-digit-qvga", str(press), "--max-global-change", "0"])
    assert exc.value.code == 2 and "expected a number of levels in (0, 255]" in capsys.readouterr().err


def test_estimate_errors(tmp_path, capsys):
    rc = main(["estimate", "--model", str(tmp_path / "missing.model"), "x.png"])
    assert rc == 2 and "missing.model: no such model file" in capsys.readouterr().err
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), np.zeros((640, 480, 3), np.uint8))
    rc = main(["estimate", "--model", "sim-digit-qvga", str(big), "--json"])
    assert rc == 2 and "expected a uint8 BGR image of 320x240x3" in capsys.readouterr().err


def test_estimate_background_and_output_errors(tmp_path, capsys):
    press = tmp_path / "press.png"
    cv2.imwrite(str(press), np.zeros((320, 240, 3), np.uint8))
    rc = main(["estimate", "--model", "sim-digit-qvga", str(press), "--background", str(tmp_path / "nope.png")])
    assert rc == 2 and "teletouch estimate: error: " in (err := capsys.readouterr().err)
    assert "nope.png: not a readable image file" in err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 100, 3), np.uint8))
    rc = main(["estimate", "--model", "sim-digit-qvga", str(press), "--background", str(small)])
    assert rc == 2 and "small.png: background frame is 100x100, the model" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("x")
    rc = main(["estimate", "--model", "sim-digit-qvga", str(press), "--save-depth", str(afile)])
    assert rc == 2 and "--save-depth" in (err := capsys.readouterr().err) and "exists and is not a folder" in err
    rc = main(["estimate", "--model", "sim-digit-qvga", str(press), "--save-depth", str(afile / "d")])
    assert rc == 2 and "afile is a file, not a folder" in capsys.readouterr().err


def _cal(folder, *extra):
    return main(["calibrate", "depth", "--images", str(folder), "--quiet", *extra])


@pytest.mark.parametrize("args, msg", [
    (["--ball-diameter", "6mm", "--px-per-mm", "0"], "--px-per-mm 0: a scale of 0 px/mm; expected a finite number > 0"),
    (["--ball-diameter", "6mm", "--px-per-mm=-17"], "a scale of -17 px/mm; expected a finite number > 0"),
    (["--ball-diameter", "6mm", "--px-per-mm", "nan"], "a scale of nan px/mm; expected a finite number > 0"),
    (["--ball-diameter", "6mm", "--px-per-mm", "inf"], "a scale of inf px/mm; expected a finite number > 0"),
    (["--ball-diameter", "6mm", "--px-per-mm", "1715"], "the ball radius of 3 mm is 5.14e+03 px, the images are "
                                                          "320x240 px; expected 3 to 240 px"),
    (["--ball-diameter", "6mm", "--px-per-mm", "0.01"], "the ball radius of 3 mm is 0.03 px"),
    (["--ball-diameter", "6mm", "--ball-radius", "10mm", "--px-per-mm", "17.15"],
     "--ball-diameter 6mm and --ball-radius 10mm disagree (a radius of 3 mm against 10 mm)"),
    (["--ball-diameter", "6", "--px-per-mm", "17.15"], "a bare number is metres: did you mean 6mm?"),
    (["--ball-diameter", "6mm", "--px-per-mm", "abc"],
     "--px-per-mm 'abc': expected pixels per millimetre, e.g. 17.15, 17.15px/mm or 17150px/m"),
])
def test_calibrate_depth_checks_scale_and_ball_size(sim_presses, tmp_path, capsys, args, msg):
    rc = _cal(sim_presses, *args, "--labels-only", "--write-labels", str(tmp_path / "l.csv"))
    assert rc == 2 and msg in capsys.readouterr().err
    assert not (tmp_path / "l.csv").exists()


def test_calibrate_depth_agreeing_ball_sizes_are_accepted(sim_presses, tmp_path):
    rc = _cal(sim_presses, "--ball-diameter", "6mm", "--ball-radius", "3mm", "--px-per-mm", "17.15",
              "--background", str(sim_presses / "background.png"), "--labels-only", "--write-labels",
              str(tmp_path / "l.csv"))
    assert rc == 0 and (tmp_path / "l.csv").is_file()


def test_calibrate_depth_file_errors_come_before_any_work(sim_presses, tmp_path, capsys, monkeypatch):
    from teletouch.plugins.estimators import depth_calibration

    def no_training(*a, **k):
        raise AssertionError("calibrate() must not run")

    monkeypatch.setattr(depth_calibration, "calibrate", no_training)
    base = ["--ball-diameter", "6mm", "--px-per-mm", "17.15"]
    bg = str(sim_presses / "background.png")
    afile = tmp_path / "afile"
    afile.write_text("x")
    few = tmp_path / "few"
    few.mkdir()
    for p in sorted(sim_presses.glob("press_*.png"))[:2]:
        shutil.copy(p, few)
    rc = _cal(few, *base, "--labels-only", "--write-labels", str(tmp_path / "l.csv"))
    assert rc == 2 and "3 or more presses (give --background otherwise)" in capsys.readouterr().err
    rc = _cal(sim_presses, *base, "--labels", str(tmp_path / "nope.csv"), "--labels-only")
    assert rc == 2 and "nope.csv: cannot read the labels file: No such file" in capsys.readouterr().err
    utf16 = tmp_path / "utf16.csv"
    utf16.write_text("image,center_x,center_y,radius_px\n", encoding="utf-16")
    rc = _cal(sim_presses, *base, "--labels", str(utf16), "--labels-only")
    assert rc == 2 and "utf16.csv:1: not UTF-8 text" in capsys.readouterr().err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 100, 3), np.uint8))
    rc = _cal(sim_presses, *base, "--background", str(small), "--labels-only")
    assert rc == 2 and "small.png: the background frame is 100x100, the presses in" in capsys.readouterr().err
    rc = _cal(sim_presses, *base, "--background", bg, "--labels-only", "--write-labels", str(afile / "x.csv"))
    assert rc == 2 and "--write-labels" in (err := capsys.readouterr().err) and "is a file, not a folder" in err
    rc = _cal(sim_presses, *base, "--background", bg, "--labels-only", "--write-labels", str(tmp_path / "l.csv"),
              "--review", str(afile))
    assert rc == 2 and "--review" in (err := capsys.readouterr().err) and "exists and is not a folder" in err
    assert not (tmp_path / "l.csv").exists()
    labels = str(sim_presses / "labels.csv")
    rc = _cal(sim_presses, *base, "--background", bg, "--labels", labels, "-o", str(afile / "t.model"))
    assert rc == 2 and "-o " in (err := capsys.readouterr().err) and "afile is a file, not a folder" in err
    rc = _cal(sim_presses, *base, "--background", bg, "--labels", labels, "-o", str(tmp_path))
    assert rc == 2 and "is a folder, expected a file name" in capsys.readouterr().err
    rc = _cal(sim_presses, *base, "--background", bg, "-o", str(tmp_path / "t.model"), "--stride", "100")
    assert rc == 2 and "--stride 100: expected at most 30 px for 320x240 images" in capsys.readouterr().err


def test_calibrate_depth_checks_labels_against_the_images(sim_presses, tmp_path, capsys):
    text = (sim_presses / "labels.csv").read_text().splitlines()
    head, first = text[0], text[1].split(",")
    base = ["--ball-diameter", "6mm", "--px-per-mm", "17.15", "--background", str(sim_presses / "background.png"),
            "--epochs", "1", "--hidden", "8", "--holdout", "0"]
    for field, value, msg in (("center_x", "-500", "field center_x = -500 lies outside the image"),
                              ("center_y", "9999", "field center_y = 9999 lies outside the image"),
                              ("radius_px", "500", "field radius_px = 500 is not smaller than the ball radius "
                                                   "(51.5 px")):
        row = dict(zip(head.split(","), first))
        row[field] = value
        bad = tmp_path / f"{field}.csv"
        bad.write_text("\n".join([head, ",".join(row[k] for k in head.split(","))] + text[2:]) + "\n")
        out = tmp_path / f"{field}.model"
        rc = _cal(sim_presses, *base, "--labels", str(bad), "-o", str(out))
        err = capsys.readouterr().err
        assert rc == 2 and f"{field}.csv:2: {msg}" in err, err
        assert not out.exists()


@pytest.mark.parametrize("opt, value, msg", [
    ("--epochs", "0", "argument --epochs: expected an integer >= 1, got 0"),
    ("--hidden", "0", "argument --hidden: expected an integer >= 1, got 0"),
    ("--stride", "-3", "argument --stride: expected an integer >= 1, got -3"),
    ("--stride", "0", "argument --stride: expected an integer >= 1, got 0"),
    ("--holdout", "-1", "argument --holdout: expected an integer >= 0, got -1"),
    ("--epochs", "two", "argument --epochs: expected an integer >= 1, got 'two'"),
])
def test_calibrate_depth_training_options_are_range_checked(sim_presses, tmp_path, capsys, opt, value, msg):
    out = tmp_path / "t.model"
    with pytest.raises(SystemExit) as exc:
        _cal(sim_presses, "--ball-diameter", "6mm", "--px-per-mm", "17.15", "--background",
             str(sim_presses / "background.png"), "--labels", str(sim_presses / "labels.csv"), "--epochs", "1",
             "--hidden", "8", opt, value, "-o", str(out))
    assert exc.value.code == 2 and msg in capsys.readouterr().err
    assert not out.exists()


def _train_args(folder, out, *extra):
    return ["--ball-diameter", "6mm", "--px-per-mm", "17.15", "--background", str(folder / "background.png"),
            "--epochs", "1", "--holdout", "1", "--hidden", "8", "-o", str(out), *extra]


def test_calibrate_depth_writes_the_model_before_the_labels_and_says_what_failed(sim_presses, tmp_path, capsys,
                                                                                 monkeypatch):
    from teletouch.plugins.estimators import depth_calibration

    def full_disk(path, labels):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(depth_calibration, "write_labels", full_disk)
    out = tmp_path / "sensor.model"
    labels_out = tmp_path / "labels.out.csv"
    rc = _cal(sim_presses, *_train_args(sim_presses, out, "--labels", str(sim_presses / "labels.csv"),
                                        "--write-labels", str(labels_out)))
    err = capsys.readouterr().err
    assert rc == 1, err
    assert f"the model was written to {out}, but {labels_out}: No space left on device" in err
    assert load_model(out).hidden == (8,)


def test_calibrate_depth_interrupted_writes_nothing(sim_presses, tmp_path, capsys, monkeypatch):
    from teletouch.plugins.estimators import depth_calibration

    def ctrl_c(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(depth_calibration, "calibrate", ctrl_c)
    out = tmp_path / "sensor.model"
    rc = _cal(sim_presses, *_train_args(sim_presses, out))
    assert rc == 130 and "interrupted; no model written" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_calibrate_depth_refuses_an_output_in_a_folder_nothing_can_be_written_to(sim_presses, capsys, monkeypatch):
    from teletouch.plugins.estimators import depth_calibration

    monkeypatch.setattr(depth_calibration, "calibrate", lambda *a, **k: pytest.fail("trained before the check"))
    rc = _cal(sim_presses, *_train_args(sim_presses, "/proc/teletouch-test.model"))
    assert rc == 2 and "-o /proc/teletouch-test.model: cannot write in the folder /proc" in capsys.readouterr().err


def test_review_overlays_of_images_with_one_stem_do_not_overwrite_each_other(sim_presses, tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    presses = sorted(sim_presses.glob("press_*.png"))
    for p in presses[2:]:
        shutil.copy(p, imgs)
    shutil.copy(presses[0], imgs / "twin.png")
    shutil.copy(presses[1], imgs / "twin.jpg")  # PNG data under a .jpg name: OpenCV reads it by its content
    rc = _cal(imgs, "--ball-diameter", "6mm", "--px-per-mm", "17.15", "--background",
              str(sim_presses / "background.png"), "--labels-only", "--write-labels", str(tmp_path / "l.csv"),
              "--review", str(tmp_path / "review"))
    assert rc == 0
    names = sorted(p.name for p in (tmp_path / "review").iterdir())
    assert "twin.png.review.png" in names and "twin.jpg.review.png" in names
    assert len(names) == len(presses)


def test_calibrate_depth_warns_when_it_rewrites_the_labels_file_it_reads(sim_presses, tmp_path, capsys):
    labels = tmp_path / "labels.csv"
    shutil.copy(sim_presses / "labels.csv", labels)
    rc = _cal(sim_presses, *_train_args(sim_presses, tmp_path / "s.model", "--labels", str(labels),
                                        "--write-labels", str(labels)))
    assert rc == 0
    assert f"warning: --write-labels {labels} is the --labels file" in capsys.readouterr().err
