"""A newcomer's report on the depth node and the depth CLI (`teletouch estimate`, `teletouch calibrate depth`): each
test failed before its fix."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from teletouch import ComponentFault, ModelFileError, Sample
from teletouch.cli import main
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.estimators.normal_model import load_model, packaged_model_path
from teletouch.testing import Harness

from helpers_depth import presses_fixture

REPO = Path(__file__).resolve().parents[1]
PACKAGED = packaged_model_path("sim-digit-qvga")


sim_presses = presses_fixture(4, seed=5)


def _json_rows(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


# --- 1. a deep contact among the first frames is not another sensor ------------------------------------------------

def test_a_fast_squeeze_of_the_simulated_loop_runs_without_a_background_fault(capsys):
    # before: exit 3 at t=0.767 s, "they differ by 9.4 levels ... made for another sensor": the first new frames
    # of the noise-free sim were the contact's, and their median read the probe 1.7 mm deep as a mismatch
    rc = main(["run", str(REPO / "examples" / "paper-sim.yaml"), "--set", "leader.intent.speed=80mm/s",
               "--duration", "1.5"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "do not match the depth model's background" not in err


def _sim_frames(depths_mm: list[float]) -> list[np.ndarray]:
    from teletouch.plugins.sensors.sim_digit import DigitSimulator
    from teletouch.plugins.sensors import gel

    s = DigitSimulator("qvga", indenter=gel.Indenter.probe(5e-3), noise=2, seed=3)
    return [s.render(d * 1e-3, (0.0, 0.0), 0.0, t=k / 60)[0] for k, d in enumerate(depths_mm)]


def test_the_first_frames_may_hold_a_deep_contact_but_another_units_frames_still_fault(shared_data):
    frames = _sim_frames([0.0, 0.4, 1.0, 1.3, 1.6, 1.7, 1.8, 1.7, 1.7, 1.7])
    with Harness(DepthEstimator, {}) as h:
        for k, f in enumerate(frames):
            h.step(k / 60, image=Sample(f, k / 60))
        assert h.comp.status()["background_mismatch"] < 1.0   # the untouched frame's
    from tests.test_depth_estimator import _other_unit_frame

    with Harness(DepthEstimator, {}) as h:   # every frame another unit's: the closest of them is 9 levels away
        with pytest.raises(ComponentFault, match=r"they differ by \d+\.\d levels \(the closest of the first 10;"):
            for k in range(10):
                h.step(k / 60, image=Sample(_other_unit_frame(shared_data, k), k / 60))


# --- 2. the depth node's model is checked when the graph is validated ----------------------------------------------

def _write_meta_model(path: Path, **meta_changes) -> Path:
    """The packaged model with its meta changed, written to ``path`` as it is named (np.savez adds .npz to a name)."""
    with np.load(PACKAGED, allow_pickle=False) as z:
        files = {k: z[k] for k in z.files}
    meta = json.loads(str(files["meta"]))
    meta.update(meta_changes)
    files["meta"] = np.array(json.dumps(meta))
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **files)
    return path


def test_validate_refuses_a_missing_or_foreign_model_file(tmp_path, capsys):
    graph = str(REPO / "examples" / "paper-sim.yaml")
    # before: "OK", then `teletouch run` exited 4 at start-up
    rc = main(["validate", graph, "--set", "depth.model=nope.model"])
    err = capsys.readouterr().err
    assert rc != 0 and "param 'model' = 'nope.model'" in err and "nope.model: no such model file" in err
    text = tmp_path / "notes.json"
    text.write_text('{"format": "teletouch-depth-model"}')
    rc = main(["validate", graph, "--set", f"depth.model={text}"])
    err = capsys.readouterr().err
    assert rc != 0 and "notes.json: not a teletouch depth model (expected a .npz archive" in err
    _write_meta_model(tmp_path / "v2.model", version=2)
    rc = main(["validate", graph, "--set", f"depth.model={tmp_path / 'v2.model'}"])
    err = capsys.readouterr().err
    assert rc != 0 and "v2.model: model file version 2, this teletouch reads version 1" in err
    rc = main(["validate", graph, "--set", f"depth.model={tmp_path}"])
    assert rc != 0 and "a folder, expected a model file" in capsys.readouterr().err
    # (by the packaged model's name: the packaged force calibration was made for it, and poly-force refuses a depth
    # model of another name, Component.port_sources)
    good = shutil.copy(PACKAGED, tmp_path / "sim-digit-qvga.model")
    assert main(["validate", graph, "--set", f"depth.model={good}"]) == 0
    assert main(["validate", graph, "--set", "depth.model=sim-digit-qvga"]) == 0


# --- 3. a missing output folder is refused, not made ---------------------------------------------------------------

def test_calibrate_depth_refuses_a_missing_output_folder(sim_presses, tmp_path, capsys):
    base = ["calibrate", "depth", "--images", str(sim_presses), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
            "--labels", str(sim_presses / "labels.csv"), "--background", str(sim_presses / "background.png"),
            "--epochs", "1", "--holdout", "1", "--hidden", "8", "--quiet"]
    # before: /nonexist/ was made silently (and the model written into it)
    rc = main([*base, "-o", str(tmp_path / "nope" / "x.model")])
    err = capsys.readouterr().err
    assert rc == 2 and f"-o {tmp_path / 'nope' / 'x.model'}: the folder {tmp_path / 'nope'} does not exist" in err
    rc = main([*base, "-o", str(tmp_path / "x.model"), "--write-labels", str(tmp_path / "gone" / "l.csv")])
    assert rc == 2 and f"the folder {tmp_path / 'gone'} does not exist" in capsys.readouterr().err
    rc = main([*base, "-o", str(tmp_path / "x.model"), "--review", str(tmp_path / "a" / "b")])
    assert rc == 2 and f"--review {tmp_path / 'a' / 'b'}: the folder {tmp_path / 'a'} does not exist" in \
        capsys.readouterr().err
    assert not (tmp_path / "nope").exists() and not (tmp_path / "gone").exists() and not (tmp_path / "a").exists()
    assert not (tmp_path / "x.model").exists()
    # estimate's --save-depth DIR alike
    rc = main(["estimate", "--model", "sim-digit-qvga", str(sim_presses / "background.png"), "--save-depth",
               str(tmp_path / "c" / "d")])
    assert rc == 2 and f"--save-depth {tmp_path / 'c' / 'd'}: the folder {tmp_path / 'c'} does not exist" in \
        capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    # --review DIR is made when its parent exists
    rc = main([*base, "-o", str(tmp_path / "x.model"), "--review", str(tmp_path / "review")])
    assert rc == 0 and len(list((tmp_path / "review").glob("*.review.png"))) == 4


# --- 4. a file that is not an .npz archive: the project's message, never numpy's pickle advice ---------------------

@pytest.mark.parametrize("content", [b'{"format": "teletouch-depth-model"}', b"# README\n", b"\x89PNG\r\n\x1a\n0000",
                                     b""])
def test_a_foreign_file_as_model_names_it_without_numpys_pickle_advice(tmp_path, capsys, content):
    fake = tmp_path / "fake.model"
    fake.write_bytes(content)
    rc = main(["estimate", "--model", str(fake), str(tmp_path / "img.png")])
    err = capsys.readouterr().err
    assert rc == 2 and f"{fake}: not a teletouch depth model (expected a .npz archive written by `teletouch " \
                       "calibrate depth`)" in err
    assert "pickle" not in err
    with pytest.raises(ModelFileError) as exc:   # the graph path (configure) and validation
        load_model(fake)
    assert "pickle" not in str(exc.value) and str(fake) in str(exc.value)
    with pytest.raises(ValueError) as exc:
        DepthEstimator.Params(model=str(fake))
    assert "expected a .npz archive" in str(exc.value) and "pickle" not in str(exc.value)


def test_an_entry_of_pickled_objects_is_named_without_the_unsafe_advice(tmp_path):
    with np.load(PACKAGED, allow_pickle=False) as z:
        files = {k: z[k] for k in z.files}
    files["feat_mean"] = np.array([object()] * 11, dtype=object)
    bad = tmp_path / "obj.npz"
    np.savez(bad, **files)
    with pytest.raises(ModelFileError, match=r"obj\.npz: .*an entry holds pickled Python objects") as exc:
        load_model(bad)
    assert "allow_pickle" not in str(exc.value)


# --- 5-7. estimate's images: what is wrong with each, and a JSON row for each --------------------------------------

def test_estimate_says_a_grayscale_image_is_grayscale(tmp_path, capsys, shared_data):
    gray = tmp_path / "gray.png"
    cv2.imwrite(str(gray), cv2.cvtColor(cv2.imread(str(shared_data / "digit-presses-qvga" / "0003.png")),
                                        cv2.COLOR_BGR2GRAY))
    rc = main(["estimate", "--model", "sim-digit-qvga", str(gray)])
    err = capsys.readouterr().err
    # before: "differs from the model's background by 22.7 levels ... the model is another sensor's"
    assert rc == 2 and f"{gray}: implausible frame: a grayscale image" in err and "expected a colour BGR" in err
    assert "another sensor" not in err


def test_estimate_names_a_missing_file_or_folder_once_without_an_opencv_warning(tmp_path, capfd):
    missing = tmp_path / "missing.png"
    rc = main(["estimate", "--model", "sim-digit-qvga", str(missing), str(tmp_path)])
    err = capfd.readouterr().err
    # before: OpenCV's "[ WARN:0@0.147] global loadsave.cpp ... findDecoder", then "missing.png: missing.png: not a
    # readable image file"
    assert rc == 2 and "WARN" not in err and "findDecoder" not in err
    assert f"teletouch estimate: error: {missing}: no such file\n" in err and err.count(str(missing)) == 1
    assert f"teletouch estimate: error: {tmp_path}: a folder, expected an image file\n" in err
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    rc = main(["estimate", "--model", "sim-digit-qvga", str(junk)])
    err = capfd.readouterr().err
    assert rc == 2 and f"{junk}: not a readable image file" in err and err.count(str(junk)) == 1


def test_a_missing_background_frame_is_named_without_an_opencv_warning(tmp_path, capfd):
    from teletouch.plugins.estimators.depth_calibration import load_background

    with pytest.raises(FileNotFoundError, match=r"nope\.png: not a readable image file \(no such file or folder\)"):
        load_background([tmp_path / "nope.png"])
    assert "WARN" not in capfd.readouterr().err   # before: OpenCV's findDecoder warning first


def test_estimate_json_gives_every_image_a_row(tmp_path, capsys, shared_data):
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((100, 100, 3), (40, 90, 160), np.uint8))
    good = shared_data / "digit-presses-qvga" / "0000.png"
    missing = tmp_path / "missing.png"
    rc = main(["estimate", "--model", "sim-digit-qvga", str(small), str(good), str(missing), "--json"])
    out = capsys.readouterr()
    rows = _json_rows(out.out)
    # before: no row for small.png (nor the missing one), only a line on stderr
    assert rc == 2 and [r["image"] for r in rows] == [str(small), str(good), str(missing)]
    assert rows[0]["valid"] is False and "expected a uint8 BGR image of 320x240x3" in rows[0]["problem"]
    assert rows[0]["max_depth_m"] is None and rows[0]["centroid_m"] == [None, None]
    assert rows[1]["valid"] is True
    assert rows[2] == {"image": str(missing), "valid": False, "problem": "no such file", "max_depth_m": None,
                       "contact_area_m2": None, "centroid_m": [None, None], "ms": None}


# --- 8. a force calibration of another depth model ------------------------------------------------------------------

def test_estimate_refuses_a_force_calibration_made_for_another_depth_model(tmp_path, capsys, shared_data):
    model = shutil.copy(PACKAGED, tmp_path / "sensor.model")
    press = shared_data / "digit-presses-qvga" / "0000.png"
    rc = main(["estimate", "--model", str(model), "--force-calibration", "sim-digit-qvga", str(press)])
    out = capsys.readouterr()
    # before: a force printed with no word that the calibration was made for 'sim-digit-qvga'
    assert rc == 2 and out.out == ""
    assert re.search(r"--force-calibration sim-digit-qvga: the calibration .*sim-digit-qvga\.force\.json was made "
                     r"for 'sim-digit-qvga', not for the depth model '.*sensor\.model'", out.err)
    same = shutil.copy(PACKAGED, tmp_path / "sim-digit-qvga.model")   # the id is the file's name, as poly-force's
    rc = main(["estimate", "--model", str(same), "--force-calibration", "sim-digit-qvga", str(press), "--json"])
    assert rc == 0 and "force_N" in _json_rows(capsys.readouterr().out)[0]


# --- 9. no progress bar in a log ----------------------------------------------------------------------------------

def _train(sim_presses, tmp_path, name):
    return main(["calibrate", "depth", "--images", str(sim_presses), "--ball-diameter", "6mm", "--px-per-mm",
                 "17.15", "--labels", str(sim_presses / "labels.csv"), "--background",
                 str(sim_presses / "background.png"), "--epochs", "3", "--holdout", "1", "--hidden", "8",
                 "-o", str(tmp_path / name)])


def test_training_progress_is_plain_lines_when_stderr_is_not_a_terminal(sim_presses, tmp_path, capsys,
                                                                         monkeypatch):
    from teletouch.plugins.estimators import depth_calibration

    # a line after every epoch but the last (raising=False: the test fails on its assertions before the fix)
    monkeypatch.setattr(depth_calibration, "PROGRESS_LINE_S", 0.0, raising=False)
    assert _train(sim_presses, tmp_path, "a.model") == 0
    err = capsys.readouterr().err
    # before: tqdm's carriage-return updates, ~80 of them on one line of a log
    assert "\r" not in err
    assert re.findall(r"^training: epoch (\d)/3, loss \d\.\d{5}, \d+ s$", err, re.M) == ["1", "2"]
    monkeypatch.setattr(depth_calibration, "_stderr_is_terminal", lambda: True)   # on a terminal: the bar
    assert _train(sim_presses, tmp_path, "b.model") == 0
    err = capsys.readouterr().err
    assert "\r" in err and "training: epoch" not in err


# --- 10. the documented figure of the automatic-label calibration --------------------------------------------------

def test_the_documented_auto_label_figure_is_what_the_calibration_gives(shared_data, tmp_path, capsys):
    text = (REPO / "docs" / "depth.md").read_text()
    flat = " ".join(text.split())   # (the page may wrap anywhere)
    m = re.search(r"the two held-out presses read a (\d+\.\d)% cap-height error and a (\d\.\d\d) mm sphere", flat)
    assert m, "docs/depth.md step 4: the automatic-label figure"
    imgs = tmp_path / "presses"
    shutil.copytree(shared_data / "digit-presses-qvga", imgs, ignore=shutil.ignore_patterns("*.csv"))
    rc = main(["calibrate", "depth", "--images", str(imgs), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
               "--quiet", "-o", str(tmp_path / "sensor.model")])
    assert rc == 0
    summary = _json_rows(capsys.readouterr().out)[-1]
    # before: the page said 14.3%; the command gives 0.1419
    assert f"{100 * summary['median_abs_cap_error']:.1f}" == m.group(1)
    assert f"{summary['median_sphere_radius_mm']:.2f}" == m.group(2)
