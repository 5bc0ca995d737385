"""An audit of `teletouch calibrate depth` on the real QVGA presses: a wrong label or background made a model whose
every press read 0 mm (change threshold 15.5 -> 114.6 levels, the depth gain fit skipped without a word, exit code 0);
a "no contact" row with a circle, an underscore in a number and the labels of a background frame kept in the presses
folder. Each test failed before its fix; the calibrations are short (2 epochs, 8 hidden units)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import cv2
import pytest

from teletouch import ModelFileError
from teletouch.cli import main
from teletouch.plugins.estimators import depth_calibration as C
from teletouch.plugins.estimators.normal_model import load_model

from helpers_depth import qvga_fixture

qvga = qvga_fixture()

QUICK = ["--epochs", "2", "--hidden", "8", "--quiet"]


@pytest.fixture
def presses(shared_data, tmp_path) -> tuple[Path, list[str]]:
    """A copy of the QVGA presses and the rows of their labels.csv (header with a note column first)."""
    folder = tmp_path / "q"
    shutil.copytree(shared_data / "digit-presses-qvga", folder)
    rows = (folder / "labels.csv").read_text().splitlines()
    rows[0] += ",note"
    return folder, rows


def _write(folder: Path, rows: list[str], name: str = "l.csv") -> Path:
    p = folder / name
    p.write_text("\n".join(rows) + "\n", encoding="utf-8")
    return p


def _calibrate(folder: Path, labels: Path, out: Path, *extra: str) -> int:
    return main(["calibrate", "depth", "--images", str(folder), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
                 "--labels", str(labels), *QUICK, *extra, "-o", str(out)])


# --- labels CSV --------------------------------------------------------------------------------------------------

def test_a_no_contact_row_with_a_radius_is_refused(presses):
    # before: read as a no-contact frame; the press in it was trained as flat gel and raised the change threshold
    folder, rows = presses
    p = _write(folder, [rows[0], "0000.png,145,130,23,no contact", *rows[2:]])
    with pytest.raises(ModelFileError, match=r"l\.csv:2: field radius_px = '23' for 0000\.png with the note 'no "
                                             r"contact'; a frame without contact has radius_px 0"):
        C.read_labels(p)
    labs = C.read_labels(_write(folder, [rows[0], "0000.png,,,0,no contact: at rest", "0001.png,,,,no contact"]))
    assert labs["0000.png"].no_contact and labs["0001.png"].no_contact   # radius 0 or empty: as documented


@pytest.mark.parametrize("row, field", [("0000.png,1_45,130,23", "center_x"), ("0000.png,145,130,2_3", "radius_px")])
def test_an_underscore_in_a_number_is_refused_with_file_line_and_field(presses, row, field):
    # before: float() read '1_45' as 145
    folder, rows = presses
    p = _write(folder, [rows[0], rows[1], row])
    with pytest.raises(ModelFileError, match=rf"l\.csv:3: field {field} = '\d+_\d+' is not a number \(an underscore "
                                             rf"in a number is taken for a typo"):
        C.read_labels(p)


# --- a calibration in which no press reads any depth ------------------------------------------------------------

def test_a_pressed_frame_labelled_no_contact_is_refused_not_written_as_a_flat_model(presses, tmp_path, capsys):
    folder, rows = presses
    labels = _write(folder, [rows[0], "0000.png,,,0,no contact", *rows[2:]])
    out = tmp_path / "nc.model"
    rc = _calibrate(folder, labels, out)
    err = capsys.readouterr().err
    # before: exit code 0, the model written with depth gain 1.0 and a 100% cap-height error on the held-out presses
    assert rc == 2, err
    assert not out.exists()
    assert "teletouch calibrate depth: error: no training press measured any depth" in err
    assert "no model written" in err
    assert "the change mask sees nothing" in err
    assert "a frame labelled 'no contact' that shows a press (labelled so: 0000.png)" in err
    assert "a background that is not this sensor's no-contact frame" in err
    assert "The largest change away from the labelled contacts is in 0000.png" in err
    threshold = re.search(r"the model's change threshold, (\d+\.\d) levels", err)
    assert threshold and float(threshold.group(1)) > 60, err
    # no false alarm: the same presses with their hand labels make a model that reads depth
    assert _calibrate(folder, folder / "labels.csv", out) == 0, capsys.readouterr().err
    m = load_model(out)
    assert m.training["gain_presses"] >= 3 and m.depth_gain != 1.0 and m.change_threshold < 30   # 15.5


def test_a_background_of_another_sensor_is_refused(presses, tmp_path, capsys, shared_data):
    folder, rows = presses
    out = tmp_path / "o.model"
    rc = _calibrate(folder, folder / "labels.csv", out, "--background",
                    str(shared_data / "digit-backgrounds" / "bg_1.jpg"))
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists(), err
    assert "no training press measured any depth" in err


def test_the_depth_gain_fit_says_when_it_has_too_few_presses_or_none(qvga, monkeypatch):
    ims, labs, bg = qvga
    said: list[str] = []
    m = C.train_model(ims[:2], labs, bg, 17150.0, epochs=10, hidden=(8,), progress=False, log=said.append)
    # before: a gain fitted on two presses was not mentioned
    assert m.training["gain_presses"] == 2
    assert any(f"depth gain {m.depth_gain:.3f} fitted on 2 press(es) only" in s for s in said), said
    said.clear()
    monkeypatch.setattr(C, "GAIN_MARGIN", 50.0)   # no press's circle of 50 radii lies inside the image
    m = C.train_model(ims[:2], labs, bg, 17150.0, epochs=10, hidden=(8,), progress=False, log=said.append)
    assert m.depth_gain == 1.0 and m.training["gain_presses"] == 0
    assert any(s.startswith("depth gain not fitted, kept at 1.0: no training press has its circle of 50 contact "
                            "radii inside the image") for s in said), said


def test_a_training_too_short_to_read_depth_is_said_to_be_so(qvga):
    """Two epochs of 8 hidden units on two presses: the change mask sees the presses (the data are right), but the
    network gives them no slope. Not refused (a quick model for a test), but no longer silent."""
    ims, labs, bg = qvga
    said: list[str] = []
    m = C.train_model(ims[:2], labs, bg, 17150.0, epochs=2, hidden=(8,), progress=False, log=said.append)
    assert m.depth_gain == 1.0 and m.training["gain_presses"] == 0
    assert any(s.startswith("depth gain not fitted, kept at 1.0: none of the 2 training presses it is fitted on reads "
                            "any depth after 2 epoch(s), although the change mask sees them") for s in said), said


# --- a background frame in the presses folder --------------------------------------------------------------------

def test_the_label_of_a_background_frame_in_the_folder_is_said_to_be_the_background(presses, tmp_path, capsys):
    folder, rows = presses
    cv2.imwrite(str(folder / "rest.png"), C.median_background([im for _, im in C.load_images(folder)]))
    labels = _write(folder, [*rows, "rest.png,,,0,no contact: the gel at rest"])
    out = tmp_path / "bg.model"
    rc = main(["calibrate", "depth", "--images", str(folder), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
               "--labels", str(labels), "--epochs", "2", "--hidden", "8", "--background", str(folder / "rest.png"),
               "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0, err
    # before: "1 label(s) name no image in the folder, ignored: rest.png"
    assert "name no image in the folder" not in err
    assert "1 label(s) not used: rest.png: taken as the background (--background), not as a press" in err


def test_a_background_frame_labelled_as_a_press_is_refused(presses, tmp_path, capsys):
    folder, _ = presses
    out = tmp_path / "p.model"
    rc = _calibrate(folder, folder / "labels.csv", out, "--background", str(folder / "0000.png"))
    err = capsys.readouterr().err
    # before: the press taken as the background, exit code 0, every press read 0 mm
    assert rc == 2 and not out.exists(), err
    assert (f"error: {folder / 'labels.csv'}:2: 0000.png is labelled as a press (radius 23 px), but it is given as "
            f"--background, which must be a frame without contact") in err


def test_labels_only_keeps_and_reviews_the_given_labels(presses, tmp_path, capsys):
    """--labels-only read and checked --labels, then labelled every press automatically: the given file, named as
    --write-labels too ("it is rewritten with this folder's presses only"), lost its hand circles, and the review
    overlays showed the automatic ones. The given rows are kept now; presses without one are labelled."""
    folder, rows = presses
    given = _write(folder, rows[:1] + [r + "," for r in rows[1:-1]], "hand.csv")   # the last press has no row
    out = tmp_path / "out.csv"
    rc = main(["calibrate", "depth", "--images", str(folder), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
               "--labels", str(given), "--labels-only", "--write-labels", str(out), "--review", str(tmp_path / "rv")])
    assert rc == 0
    written = C.read_labels(out)
    hand = C.read_labels(given)
    for name, lb in hand.items():
        assert (written[name].cx, written[name].cy, written[name].r) == (lb.cx, lb.cy, lb.r), name
    last = rows[-1].split(",")[0]
    assert last in written and last not in hand   # labelled automatically
    assert "9 label(s) as given in" in capsys.readouterr().err
    assert len(list((tmp_path / "rv").glob("*.review.png"))) == 10


def test_a_review_overlay_shows_the_whole_note():
    """The overlay drew the note's first 60 characters at a size that ran off the 480 px image: a flagged press's
    second reason ("edge off a circle (") was cut mid-word. The note is wrapped to the overlay's width now."""
    import numpy as np

    img = np.full((320, 240, 3), 90, np.uint8)
    note = ("uncertain: not round (circularity 0.74); edge off a circle (fit residual 9% of the radius); centre unsure "
            "(the edge circle's centre is 4 px from the changed pixels' centroid)")
    out = C.review_overlay(img, img, C.Label("x.png", 120.0, 160.0, 30.0, note))
    text_rows = np.where((out == 255).all(axis=2).any(axis=1))[0]
    assert text_rows.max() > 18   # a second line of text (the first ends at row ~15)
    assert not (out[:, -3:] == 255).all(axis=2).any()   # nothing drawn to the right edge (cut off)
