"""The depth model file: round trip, packaged names, and clear errors for wrong version, size or corrupt files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from teletouch import ModelFileError
from teletouch.plugins.estimators.normal_model import (FEATURE_SETS, FORMAT, VERSION, NormalModel, colour_maps,
                                                       colour_maps_torch, feature_count, load_model, make_net,
                                                       resolve_model, uses_xy)


def _model(rows=32, cols=24, feature_set="diffxy"):
    import torch

    torch.manual_seed(0)
    net = make_net(5, (8, 8))
    rng = np.random.default_rng(0)
    bg = rng.integers(0, 255, (rows, cols, 3), dtype=np.uint8)
    return NormalModel.from_net(net, feature_set=feature_set, hidden=(8, 8), feat_mean=np.zeros(5, np.float32),
                                feat_std=np.ones(5, np.float32), background=bg, px_per_m=17150.0, stride=2,
                                change_threshold=12.5, depth_gain=1.1, training={"epochs": 3},
                                validation={"median_abs_cap_error": 0.05})


def test_round_trip(tmp_path):
    m = _model()
    p = m.save(tmp_path / "s.model")
    m2 = load_model(p)
    assert m2.meta() == m.meta()
    assert m2.shape == (32, 24) and m2.stride == 2 and m2.depth_gain == 1.1 and m2.change_threshold == 12.5
    assert np.array_equal(m2.background, m.background)
    for k, v in m.state_dict.items():
        assert np.array_equal(m2.state_dict[k], v)
    x = __import__("torch").randn(7, 5)
    assert np.allclose(m.net()(x).detach().numpy(), m2.net()(x).detach().numpy())
    # no pickled objects inside: plain numpy arrays, readable with allow_pickle=False
    with np.load(p, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
    assert meta["format"] == FORMAT and meta["version"] == VERSION and meta["orientation"] == "portrait-bgr"
    assert meta["px_per_mm"] == pytest.approx(17.15)


def _rewrite(src, dst, **changes):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    for k, v in changes.pop("meta", {}).items():
        meta[k] = v
    arrays["meta"] = np.array(json.dumps(meta))
    for k, v in changes.items():
        if v is None:
            arrays.pop(k, None)
        else:
            arrays[k] = v
    np.savez(dst, **arrays)
    return dst


def test_wrong_version_names_file_and_versions(tmp_path):
    p = _model().save(tmp_path / "a.model")
    bad = _rewrite(p, tmp_path / "v2.npz", meta={"version": 2})
    with pytest.raises(ModelFileError, match=r"v2\.npz.*version 2.*reads version 1"):
        load_model(bad)


def test_wrong_size(tmp_path):
    p = _model().save(tmp_path / "a.model")
    with pytest.raises(ModelFileError, match=r"a\.model: the model is for 32x24.*expected 320x240"):
        load_model(p, expect_shape=(320, 240))
    bad = _rewrite(p, tmp_path / "bg.npz", background=np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ModelFileError, match=r"background is uint8 \(10, 10, 3\), expected uint8 \(32, 24, 3\)"):
        load_model(bad)


def test_corrupt_and_foreign_files(tmp_path):
    p = _model().save(tmp_path / "a.model")
    data = p.read_bytes()
    trunc = tmp_path / "trunc.model"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match=r"trunc\.model: not a readable teletouch depth model"):
        load_model(trunc)
    text = tmp_path / "text.model"
    text.write_text("hello")
    with pytest.raises(ModelFileError, match="text.model"):
        load_model(text)
    other = tmp_path / "other.npz"
    np.savez(other, meta=np.array(json.dumps({"format": "something-else"})))
    with pytest.raises(ModelFileError, match="expected 'teletouch-depth-model'"):
        load_model(other)
    nometa = tmp_path / "nometa.npz"
    np.savez(nometa, x=np.zeros(3))
    with pytest.raises(ModelFileError, match="no 'meta' entry"):
        load_model(nometa)
    # a pickled object is refused (never executed)
    pick = tmp_path / "pickle.npz"
    np.savez(pick, meta=np.array([{"format": FORMAT}], dtype=object))
    with pytest.raises(ModelFileError, match="pickle.npz"):
        load_model(pick)


def test_weights_must_fit_and_be_finite(tmp_path):
    p = _model().save(tmp_path / "a.model")
    with np.load(p) as z:
        w = z["w.0.weight"].copy()
    w[0, 0] = np.nan
    bad = _rewrite(p, tmp_path / "nan.npz", **{"w.0.weight": w})
    with pytest.raises(ModelFileError, match="weight 0.weight holds NaN"):
        load_model(bad)
    bad = _rewrite(p, tmp_path / "arch.npz", meta={"hidden": [16, 16]})
    with pytest.raises(ModelFileError, match="do not fit a diffxy network with hidden sizes \\[16, 16\\]"):
        load_model(bad)
    bad = _rewrite(p, tmp_path / "norm.npz", feat_std=np.zeros(5, np.float32))
    with pytest.raises(ModelFileError, match="input normalisation"):
        load_model(bad)


def test_packaged_model_by_name_and_unknown_names():
    p = resolve_model("sim-digit-qvga")
    assert p.name == "sim-digit-qvga.model"
    m = load_model("sim-digit-qvga")
    assert m.shape == (320, 240) and m.px_per_m == pytest.approx(17150.0)
    assert m.validation and m.training["presses"]
    assert p.stat().st_size < 2 * 1024 * 1024
    with pytest.raises(ModelFileError, match=r"no-such: no such model file.*packaged: .*sim-digit-qvga"):
        load_model("no-such")


@pytest.mark.parametrize("feature_set", sorted(FEATURE_SETS))
def test_colour_features_agree_between_numpy_and_torch_and_on_windows(feature_set):
    """Training and the CPU path use colour_maps (NumPy/OpenCV), the dense path colour_maps_torch (kornia): the same
    numbers. The CPU path computes them on a window around the changed cells: inside it they equal the whole grid's."""
    import torch

    rng = np.random.default_rng(1)
    bg = rng.uniform(0, 255, (20, 16, 3)).astype(np.float32)
    bg[0, 0] = 3.0                                             # below the ratio's floor
    frame = np.clip(bg + rng.normal(0, 20, bg.shape), 0, 255).astype(np.float32)
    diff = frame - bg
    a = colour_maps(feature_set, frame, diff, bg)
    k = feature_count(feature_set) - (2 if uses_xy(feature_set) else 0)
    assert a.shape == (20, 16, k) and a.dtype == np.float32 and np.isfinite(a).all()
    t = lambda v: torch.from_numpy(v).permute(2, 0, 1)[None]  # noqa: E731
    b = colour_maps_torch(feature_set, t(frame), t(diff), t(bg))[0].permute(1, 2, 0).numpy()
    assert np.allclose(a, b, atol=1e-5)
    w = colour_maps(feature_set, frame[4:12, 3:10], diff[4:12, 3:10], bg[4:12, 3:10])
    assert np.allclose(w[1:-1, 1:-1], a[5:11, 4:9], atol=1e-6)
    if feature_set.startswith("ratio"):
        assert a[0, 0, 0] == pytest.approx(diff[0, 0, 0] / 16.0)  # the floor, not a blow-up
        assert a[3, 5, 2] == pytest.approx(diff[3, 5, 2] / bg[3, 5, 2])


def test_foreign_or_mistyped_entries_are_model_file_errors(tmp_path):
    """Wrong types in a model file are refused with the file and the field named, never a TypeError/ValueError."""
    p = _model().save(tmp_path / "a.model")
    npy = tmp_path / "array.model"                 # a .npy file renamed: np.load gives an array, not an archive
    with open(npy, "wb") as fh:
        np.save(fh, np.zeros(3))
    with pytest.raises(ModelFileError, match=r"array\.model: a single NumPy array, not a teletouch depth model"):
        load_model(npy)
    cases = [
        ({"meta": {"rows": "abc"}}, r"meta field rows is 'abc', expected an integer >= 1"),
        ({"meta": {"cols": 2.5}}, r"meta field cols is 2\.5, expected an integer >= 1"),
        ({"meta": {"hidden": 5}}, r"meta field hidden is 5, expected a list of layer sizes"),
        ({"meta": {"hidden": [8, "8"]}}, r"meta field hidden is \[8, '8'\], expected a list of layer sizes"),
        ({"meta": {"training": "abc"}}, r"meta field training is 'abc', expected a JSON object"),
        ({"meta": {"validation": [1]}}, r"meta field validation is \[1\], expected a JSON object"),
        ({"meta": {"feature_set": ["diffxy"]}}, r"feature set \['diffxy'\], expected one of"),
        ({"meta": {"px_per_m": "17150"}}, r"meta field px_per_m is '17150', expected a finite number > 0"),
        ({"feat_std": np.array(list("abcde"))}, r"input normalisation feat_std is <U1 \(5,\), expected 5 numbers"),
        ({"w.0.weight": np.full((8, 5), "x")}, r"weight 0\.weight is <U1, expected float32 numbers"),
    ]
    for i, (changes, msg) in enumerate(cases):
        bad = _rewrite(p, tmp_path / f"bad{i}.npz", **changes)
        with pytest.raises(ModelFileError, match=rf"bad{i}\.npz: {msg}"):
            load_model(bad)


@pytest.mark.parametrize("changes, msg", [
    ({"meta": {"px_per_m": 0}}, r"meta field px_per_m is 0, expected a finite number > 0"),
    ({"meta": {"px_per_m": -17150.0}}, r"meta field px_per_m is -17150\.0, expected a finite number > 0"),
    ({"meta": {"px_per_m": float("nan")}}, r"meta field px_per_m is nan, expected a finite number > 0"),
    ({"meta": {"depth_gain": -1.0}}, r"meta field depth_gain is -1\.0, expected a finite number > 0"),
    ({"meta": {"depth_gain": float("inf")}}, r"meta field depth_gain is inf, expected a finite number > 0"),
    ({"meta": {"ball_radius_m": 0.0}}, r"meta field ball_radius_m is 0\.0, expected a finite number > 0"),
    ({"meta": {"stride": 0}}, r"meta field stride is 0, expected an integer from 1 to 3"),
    ({"meta": {"stride": -2}}, r"meta field stride is -2, expected an integer from 1 to 3"),
    ({"meta": {"stride": 100}}, r"meta field stride is 100, expected an integer from 1 to 3"),
    ({"meta": {"change_threshold": -5}}, r"meta field change_threshold is -5, expected a finite number >= 0"),
    ({"feat_mean": np.full(5, np.nan, np.float32)}, r"input normalisation feat_mean holds NaN or inf"),
    ({"feat_std": np.array([1, 1, np.inf, 1, 1], np.float32)}, r"input normalisation feat_std holds NaN or inf"),
    ({"feat_std": np.array([1, 1, -1, 1, 1], np.float32)}, r"input normalisation feat_std holds a std <= 0"),
])
def test_implausible_meta_values_are_refused(tmp_path, changes, msg):
    """Values that would divide by zero later (px_per_m 0) or silently give no depth (NaN) are refused on load."""
    p = _model().save(tmp_path / "a.model")
    bad = _rewrite(p, tmp_path / "bad.npz", **changes)
    with pytest.raises(ModelFileError, match=rf"bad\.npz: {msg}"):
        load_model(bad)


def test_change_threshold_zero_is_a_valid_model(tmp_path):
    """0 is meaningful: every cell that changes at all runs the network (the pipeline tests 'change > threshold')."""
    p = _model().save(tmp_path / "a.model")
    m = load_model(_rewrite(p, tmp_path / "t0.npz", meta={"change_threshold": 0}))
    assert m.change_threshold == 0.0
