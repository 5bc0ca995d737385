"""Depth calibration inputs a person gets wrong: labels CSV rows, image folders, training parameters, interrupted
writes. Each error names the file (and line, field) and what was expected; nothing is trained on silently wrong."""

from __future__ import annotations

import os
import shutil
import stat

import cv2
import numpy as np
import pytest

from teletouch import ModelFileError
from teletouch.plugins.estimators import depth_calibration as C
from teletouch.plugins.estimators import normal_model as NM

from helpers_depth import qvga_fixture

HEADER = "image,center_x,center_y,radius_px"


qvga = qvga_fixture()


def _csv(tmp_path, text, name="l.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8", newline="")
    return p


# --- labels CSV ------------------------------------------------------------------------------------------------

def test_a_note_in_a_file_without_a_note_column_is_refused_not_dropped(tmp_path):
    # the note went to no column and was dropped: the press a person marked uncertain was trained on
    p = _csv(tmp_path, HEADER + "\n0000.png,145,130,23\n0001.png,148,81,27,uncertain: blurry\n")
    with pytest.raises(ModelFileError, match=r"l\.csv:3: 5 fields, expected 4 as in the header "
                                             r"\(image,center_x,center_y,radius_px\)"):
        C.read_labels(p)


def test_a_row_without_a_required_field_is_refused_an_empty_trailing_note_may_be_left_out(tmp_path):
    p = _csv(tmp_path, HEADER + "\n0000.png,145\n")
    with pytest.raises(ModelFileError, match=r"l\.csv:2: 2 fields, expected 4"):
        C.read_labels(p)
    labs = C.read_labels(_csv(tmp_path, HEADER + ",note\n0000.png,145,130,23\n0001.png,148,81,27,uncertain: x\n"))
    assert labs["0000.png"].usable and labs["0000.png"].note == ""
    assert labs["0001.png"].uncertain and not labs["0001.png"].usable


def test_an_image_labelled_twice_is_refused_naming_both_lines(tmp_path):
    # the later row won silently
    p = _csv(tmp_path, HEADER + "\n0000.png,145,130,23\n0001.png,148,81,27\n0000.png,150,130,23\n")
    with pytest.raises(ModelFileError, match=r"l\.csv:4: image 0000\.png is labelled twice \(also on line 2\)"):
        C.read_labels(p)


def test_radius_zero_needs_the_no_contact_note(tmp_path):
    # a 0 radius typed for a press made it a no-contact frame: its colour change was trained as flat gel
    p = _csv(tmp_path, HEADER + ",note\n0000.png,145,130,0,\n")
    with pytest.raises(ModelFileError, match=r"l\.csv:2: field radius_px = 0 for 0000\.png; expected the contact "
                                             r"radius in px \(> 0\), or the note 'no contact'"):
        C.read_labels(p)
    labs = C.read_labels(_csv(tmp_path, HEADER + ",note\nbg.png,,,0,no contact: background\n"
                                                 "0001.png,148,81,0,uncertain: cannot tell\n"))
    assert labs["bg.png"].no_contact and not labs["bg.png"].usable
    assert labs["0001.png"].uncertain and not labs["0001.png"].no_contact


def test_an_uncertain_press_with_radius_zero_is_not_trained_as_a_flat_frame(qvga):
    ims, labs, bg = qvga
    labs = dict(labs, **{"0003.png": C.Label("0003.png", 68.0, 117.0, 0.0, "uncertain: cannot tell")})
    m = C.train_model(ims, labs, bg, 17150.0, epochs=1, progress=False, hidden=(8,), fit_gain=False)
    assert "0003.png" not in m.training["presses"]
    assert len(m.training["presses"]) == 9


def test_a_row_without_center_y_is_excluded_not_a_crash(qvga, tmp_path):
    # check_labels raised TypeError ('<=' between int and None): the label counted as usable without a centre row
    ims, labs, bg = qvga
    p = _csv(tmp_path, HEADER + "\n" + "\n".join(
        f"{n},{lb.cx:g},{'' if n == '0000.png' else f'{lb.cy:g}'},{lb.r:g}" for n, lb in labs.items()) + "\n")
    got = C.read_labels(p)
    assert not got["0000.png"].usable and got["0000.png"].uncertain
    C.check_labels(got, ims, 3 * 17.15, str(p))
    logs: list[str] = []
    res = C.calibrate(ims, 0.003, 17150.0, labels=got, background=bg, epochs=1, progress=False, hidden=(8,),
                      log=logs.append)
    assert "0000.png" not in res.model.training["presses"]
    assert any(m.startswith("1 press(es) marked uncertain or without a complete circle, not used: 0000.png")
               for m in logs)


def test_comments_byte_order_mark_and_spaces_are_read(tmp_path):
    # a BOM (Excel's "CSV UTF-8") and "image, center_x" made the header unrecognisable; a comment line made a label
    text = ("\ufeff# labels of sensor A, checked by hand\n"
            "image, center_x, center_y, radius_px, note\n"
            "  # 0000 was re-drawn\n"
            "0000.png, 145, 130, 23,\n")
    labs = C.read_labels(_csv(tmp_path, text))
    assert list(labs) == ["0000.png"]
    assert (labs["0000.png"].cx, labs["0000.png"].cy, labs["0000.png"].r) == (145, 130, 23)
    assert labs["0000.png"].line == 4


def test_error_lines_count_blank_and_comment_lines(tmp_path):
    # the line number came from a counter of rows, not of the file's lines: off by every blank line
    p = _csv(tmp_path, HEADER + "\r\n0000.png,145,130,23\r\n\r\n# x\r\n0001.png,x,1,2\r\n")
    with pytest.raises(ModelFileError, match=r"l\.csv:5: field center_x = 'x' is not a number"):
        C.read_labels(p)


def test_semicolon_separated_labels_get_a_hint_and_an_empty_file_says_so(tmp_path):
    with pytest.raises(ModelFileError, match=r"l\.csv:1: expected the columns .*; fields are separated by commas"):
        C.read_labels(_csv(tmp_path, "image;center_x;center_y;radius_px\n0000.png;1;2;3\n"))
    with pytest.raises(ModelFileError, match=r"e\.csv:1: expected the columns .* got an empty file"):
        C.read_labels(_csv(tmp_path, "", "e.csv"))


def test_written_labels_read_back_and_the_write_is_atomic(tmp_path, monkeypatch, qvga):
    _, labs, _ = qvga
    p = C.write_labels(tmp_path / "l.csv", labs.values())
    assert C.read_labels(p) == labs
    before = p.read_bytes()

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(NM.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        C.write_labels(p, [C.Label("a.png", 1.0, 2.0, 3.0)])
    assert p.read_bytes() == before
    assert os.listdir(tmp_path) == ["l.csv"]


# --- image folders ---------------------------------------------------------------------------------------------

def _copy(shared_data, tmp_path, n=10):
    d = tmp_path / "imgs"
    d.mkdir()
    for f in sorted((shared_data / "digit-presses-qvga").glob("*.png"))[:n]:
        shutil.copy(f, d)
    return d


def test_a_grayscale_image_is_refused_naming_it(shared_data, tmp_path):
    # it was read as BGR with three equal channels and labelled/trained without a word
    d = _copy(shared_data, tmp_path)
    im = cv2.imread(str(d / "0003.png"))
    cv2.imwrite(str(d / "0003.png"), cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))
    with pytest.raises(ValueError, match=r"imgs/0003\.png: a grayscale image"):
        C.load_images(d)
    cv2.imwrite(str(d / "0003.png"), cv2.cvtColor(im, cv2.COLOR_BGR2BGRA))    # alpha: dropped, fine
    assert np.array_equal(dict(C.load_images(d))["0003.png"], im)


def test_a_copied_image_is_refused_naming_both(shared_data, tmp_path):
    # three frames and a copy: half the median background was the copied press's ball
    d = _copy(shared_data, tmp_path, 3)
    shutil.copy(d / "0000.png", d / "0000 copy.png")
    with pytest.raises(ValueError, match=r"imgs/0000 copy\.png and 0000\.png are identical pixel for pixel; "
                                         r"remove the copy"):
        C.load_images(d)


def test_images_of_another_size_are_named(shared_data, tmp_path):
    d = _copy(shared_data, tmp_path)
    im = cv2.imread(str(d / "0003.png"))
    cv2.imwrite(str(d / "0003.png"), cv2.resize(im, (480, 640)))
    with pytest.raises(ValueError, match=r"images differ in size: 9 are 320x240 \(rows x cols\), but 0003\.png "
                                         r"640x480"):
        C.load_images(d)


def test_caliper_gap_and_image_size_are_checked(qvga):
    ims, _, bg = qvga
    frame = dict(ims)["0000.png"]
    for gap in (0.0, -0.004, float("nan")):
        with pytest.raises(ValueError, match=r"caliper gap .* m: expected a finite distance > 0"):
            C.px_per_mm_from_caliper(frame, bg, gap)
    with pytest.raises(ValueError, match=r"the caliper image is 640x480, the background 320x240"):
        C.px_per_mm_from_caliper(cv2.resize(frame, (480, 640)), bg, 0.004)


# --- training --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kw, msg", [
    ({"epochs": 0}, r"epochs = 0: expected an integer >= 1"),
    ({"seed": -1}, r"seed = -1: expected an integer from 0 to 2\*\*63 - 1"),
    ({"lr": float("nan")}, r"lr = nan: expected a finite number > 0"),
    ({"batch": 0}, r"batch = 0: expected an integer >= 1"),
    ({"dropout": 1.0}, r"dropout = 1.0: expected a number from 0 to below 1"),
    ({"hidden": ()}, r"hidden = \(\): expected one or more layer sizes"),
])
def test_training_parameters_are_checked_before_work(qvga, kw, msg):
    # epochs 0 wrote a model whose final loss was NaN; seed -1 gave numpy's bare "expected non-negative integer"
    ims, labs, bg = qvga
    with pytest.raises(ValueError, match="training parameter " + msg):
        C.train_model(ims, labs, bg, 17150.0, progress=False, **{"hidden": (8,), **kw})


@pytest.mark.parametrize("lr, msg", [(1e15, r"the loss is nan in epoch 1 of 2"),
                                     (10.0, r"the final loss is \d+\.?\d* \(expected well below 1")])
def test_a_diverged_training_is_an_error_not_a_model(qvga, lr, msg):
    # lr 10 ended at a loss of 63 and lr 1e6 at 1.8e21, and both were returned as models (depth gain clipped to 2)
    ims, labs, bg = qvga
    few = ims[:4]
    with pytest.raises(ValueError, match="training diverged: " + msg):
        C.train_model(few, labs, bg, 17150.0, epochs=2, lr=lr, progress=False, hidden=(8,))


def test_a_reduced_holdout_is_reported(qvga):
    ims, labs, bg = qvga
    two = {n: labs[n] for n in ("0000.png", "0001.png")}
    logs: list[str] = []
    res = C.calibrate(ims, 0.003, 17150.0, labels=two, background=bg, holdout=2, epochs=1, progress=False,
                      hidden=(8,), log=logs.append)
    assert "holding out 1 press(es) instead of 2: 2 usable, at least one is trained on" in logs
    assert res.model.validation["presses"] == 1 and len(res.model.training["presses"]) == 1


# --- the model file --------------------------------------------------------------------------------------------

def _model():
    import torch

    torch.manual_seed(0)
    bg = np.random.default_rng(0).integers(0, 255, (32, 24, 3), dtype=np.uint8)
    return NM.NormalModel.from_net(NM.make_net(5, (8,)), feature_set="diffxy", hidden=(8,),
                                   feat_mean=np.zeros(5, np.float32), feat_std=np.ones(5, np.float32),
                                   background=bg, px_per_m=17150.0, stride=2)


def test_an_interrupted_save_leaves_the_old_model_and_no_temporary_file(tmp_path, monkeypatch):
    # Ctrl-C during the write left <name>.tmp behind (a fixed name, also shared by two runs writing one file)
    p = _model().save(tmp_path / "s.model")
    before = p.read_bytes()
    calls = []

    def interrupted(src, dst):
        calls.append(src)
        raise KeyboardInterrupt

    monkeypatch.setattr(NM.os, "replace", interrupted)
    m2 = _model()
    m2.depth_gain = 1.5
    with pytest.raises(KeyboardInterrupt):
        m2.save(p)
    assert calls and os.listdir(tmp_path) == ["s.model"]
    assert p.read_bytes() == before and NM.load_model(p).depth_gain == 1.0


def test_a_saved_model_gets_the_permissions_of_a_new_file(tmp_path):
    old = os.umask(0o022)
    try:
        p = _model().save(tmp_path / "s.model")
    finally:
        os.umask(old)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
