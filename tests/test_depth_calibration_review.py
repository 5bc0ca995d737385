"""Depth calibration review: labels rows that swallow others, corrupt or inconsistent model files, numpy-typed
training parameters, and gradients that are not finite in a small solve window. Each was demonstrated failing."""

from __future__ import annotations

import json
import struct
import zipfile

import numpy as np
import pytest

from teletouch import ModelFileError
from teletouch.plugins.estimators import depth_calibration as C
from teletouch.plugins.estimators import poisson as P
from teletouch.plugins.estimators.normal_model import NormalModel, load_model, make_net

HEADER = "image,center_x,center_y,radius_px,note\n"


def _csv(tmp_path, text, name="l.csv"):
    p = tmp_path / name
    p.write_bytes(text.encode("utf-8"))
    return p


def _model(rows=32, cols=24):
    import torch

    torch.manual_seed(0)
    net = make_net(5, (8, 8))
    bg = np.random.default_rng(0).integers(0, 255, (rows, cols, 3), dtype=np.uint8)
    return NormalModel.from_net(net, feature_set="diffxy", hidden=(8, 8), feat_mean=np.zeros(5, np.float32),
                                feat_std=np.ones(5, np.float32), background=bg, px_per_m=17150.0, stride=2)


def _rewrite(src, dst, meta):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    m = json.loads(str(arrays["meta"]))
    m.update(meta)
    arrays["meta"] = np.array(json.dumps(m))
    np.savez(dst, **arrays)
    return dst


# --- labels CSV --------------------------------------------------------------------------------------------------

def test_an_unclosed_quote_is_refused_not_swallowing_the_rows_after_it(tmp_path):
    # the quote opened in a's note ran to the end of the file: b and c became part of that note, silently not
    # labelled (and a bad value in them was never read); the label of a was reported on the last line
    text = HEADER + 'a.png,1,2,3,"uncertain: edge\nb.png,4,5,6,\nc.png,7,8,x,\n'
    with pytest.raises(ModelFileError, match=r"l\.csv:2: a quoted field runs on over 3 lines \(to line 4\)"):
        C.read_labels(_csv(tmp_path, text))


def test_a_quote_closed_on_a_later_line_is_refused_too(tmp_path):
    # the stray quote is closed by a later one: b's row became the rest of a's note
    text = HEADER + 'a.png,1,2,3,"uncertain: edge\nb.png,4,5,6,"x"\nc.png,7,8,9,\n'
    with pytest.raises(ModelFileError, match=r"l\.csv:2: a quoted field runs on over 2 lines \(to line 3\).*quote"):
        C.read_labels(_csv(tmp_path, text))


def test_a_line_inside_a_note_is_not_a_comment_line_break_characters_are_not_lines(tmp_path):
    # the comment filter split the text at characters the CSV reader does not end lines at (form feed, U+0085
    # NEL, U+2028): what followed such a character and a '#' was dropped from the note
    text = HEADER + "a.png,1,2,3,uncertain\x85#2 ridge\nb.png,4,5,6,ok\u2028# kept\n"
    labs = C.read_labels(_csv(tmp_path, text))
    assert labs["a.png"].note == "uncertain\x85#2 ridge" and not labs["a.png"].usable
    assert labs["b.png"].note == "ok\u2028# kept" and labs["b.png"].line == 3


def test_written_labels_with_a_line_break_in_a_note_read_back(tmp_path):
    labs = [C.Label("a.png", 1.0, 2.0, 3.0, "uncertain: edge\nsecond look"), C.Label("b.png", 4.0, 5.0, 6.0)]
    back = C.read_labels(C.write_labels(tmp_path / "w.csv", labs))
    assert back["a.png"].note == "uncertain: edge second look" and back["a.png"].uncertain
    assert back["b.png"].usable and back["b.png"].line == 3


# --- model file --------------------------------------------------------------------------------------------------

def _member_data_offset(path, member):
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member)
    raw = path.read_bytes()
    n_name, n_extra = struct.unpack("<HH", raw[info.header_offset + 26: info.header_offset + 30])
    return info.header_offset + 30 + n_name + n_extra


def test_a_corrupt_compressed_entry_is_a_model_file_error_naming_the_file(tmp_path):
    # a damaged deflate stream raised zlib.error, which named neither the file nor what was expected
    p = _model().save(tmp_path / "a.model")
    raw = bytearray(p.read_bytes())
    raw[_member_data_offset(p, "background.npy")] = 0xFF     # deflate block type 3: "invalid block type"
    bad = tmp_path / "bad.model"
    bad.write_bytes(bytes(raw))
    with pytest.raises(ModelFileError, match=r"bad\.model: not a readable teletouch depth model .*invalid block type"):
        load_model(bad)


@pytest.mark.parametrize("hidden, msg", [
    ([2 ** 40, 8], r"\[1099511627776, 8\]: weight 0\.weight is \(8, 5\), expected \(1099511627776, 5\)"),
    ([2 ** 20, 2 ** 20], r"\[1048576, 1048576\]: weight 0\.weight is \(8, 5\), expected \(1048576, 5\)"),
    ([9, 8], r"\[9, 8\]: weight 0\.weight is \(8, 5\), expected \(9, 5\)"),
    ([2 ** 40], r"\[1099511627776\]: missing 2\.weight, 2\.bias; unexpected 3\.weight, 3\.bias, 5\.weight"),
])
def test_hidden_sizes_that_do_not_fit_the_weights_are_refused_without_building_that_network(tmp_path, hidden, msg):
    # meta hidden [2**40] made torch allocate 20 TB for the declared network before the weights were compared
    # (a RuntimeError from the allocator, no file named; a size that fits in memory was allocated and initialised)
    p = _model().save(tmp_path / "a.model")
    bad = _rewrite(p, tmp_path / "h.npz", {"hidden": hidden})
    with pytest.raises(ModelFileError, match=rf"h\.npz: the weights do not fit a diffxy network with hidden sizes "
                                             rf"{msg}"):
        load_model(bad)
    assert load_model(p).hidden == (8, 8)


def test_numpy_numbers_in_the_metadata_are_written_as_json_numbers(tmp_path):
    m = _model()
    m.hidden = (np.int64(8), np.int64(8))
    m.training = {"seed": np.int64(3), "lr": np.float32(0.001), "presses": ["a.png"]}
    m.validation = {"median_abs_cap_error": np.float32(0.05), "per_press": [{"cap_error": np.float64(0.1)}]}
    back = load_model(m.save(tmp_path / "a.model"))
    assert back.hidden == (8, 8) and back.training["seed"] == 3 and back.training["lr"] == pytest.approx(0.001)
    assert back.validation["median_abs_cap_error"] == pytest.approx(0.05)


@pytest.fixture(scope="module")
def few(shared_data):
    folder = shared_data / "digit-presses-qvga"
    ims = C.load_images(folder)[:5]
    labs = C.read_labels(folder / "labels.csv")
    return ims, labs, C.median_background([im for _, im in C.load_images(folder)])


def test_numpy_training_parameters_train_and_save_the_same_model(few, tmp_path):
    # check_training_params accepts numpy numbers; a numpy seed then failed in torch ("an integer is required")
    # after the samples were built, and numpy numbers in the training record failed the save (not JSON)
    ims, labs, bg = few
    kw = dict(progress=False, fit_gain=False)
    a = C.train_model(ims, labs, bg, 17150.0, epochs=1, seed=3, lr=1e-3, batch=512, hidden=(8,), **kw)
    b = C.train_model(ims, labs, bg, 17150.0, epochs=np.int64(1), seed=np.int64(3), lr=np.float64(1e-3),
                      batch=np.int64(512), hidden=(np.int64(8),), **kw)
    for k in a.state_dict:
        assert np.array_equal(a.state_dict[k], b.state_dict[k])
    back = load_model(b.save(tmp_path / "b.model"))
    assert back.training["seed"] == 3 and back.training["epochs"] == 1 and back.hidden == (8,)


# --- Poisson solver ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("box", [(3, 5, 2, 12), (3, 4, 2, 12), (3, 13, 4, 6)])
def test_gradients_that_are_not_finite_are_refused_in_a_narrow_window_too(box):
    # a window under 3 cells across was given zero depth without looking at its gradients: NaN read as "flat"
    gx = np.zeros((20, 20))
    gy = np.zeros((20, 20))
    gx[box[0], box[2] + 1] = np.nan
    with pytest.raises(ValueError, match=rf"gx: 1 gradients are NaN or inf \(the first at row {box[0]}, column "
                                         rf"{box[2] + 1}\)"):
        P.integrate_window(gx, gy, box)
    gx[box[0], box[2] + 1] = 0.5
    assert np.all(P.integrate_window(gx, gy, box) == 0)     # finite: still no depth in so narrow a window
    assert np.all(P.integrate_window(np.full((20, 20), np.nan), gy, None) == 0)   # no contact: nothing solved
