"""Force calibration open items: an untared force CSV, near-duplicate depths, a poor fit's R^2, and poly-force's light
touch without a centroid. Each test failed on the code before its fix."""

from __future__ import annotations

import json

import numpy as np
import pytest

from teletouch.plugins.estimators.force_calibration import NEGATIVE_FORCE_TOLERANCE_N, fit_samples
from teletouch.plugins.estimators.poly_force import (
    DEFAULT_MIN_R2, DEPTH_LEVEL_TOLERANCE_M, CalibrationError, ForceCalibration, PolyForce, read_pairs_csv,
)
from teletouch.plugins.sensors.gel import Indenter, gel_force
from teletouch.testing import Harness

TRUE = [0.02, 1500.0, 4.0e5, 5.0e7]  # N, N/m, N/m^2, N/m^3: 0.02 N .. ~5.6 N over 0..2 mm


def truth(d):
    d = np.asarray(d, float)
    return TRUE[0] + TRUE[1] * d + TRUE[2] * d ** 2 + TRUE[3] * d ** 3


def _cli(*args):
    from teletouch.cli import main

    return main(["calibrate", "force", *[str(a) for a in args]])


def _pairs_csv(path, depths, forces, comment=""):
    path.write_text(comment + "depth_m,force_n\n" + "".join(f"{d:.9g},{f:.9g}\n" for d, f in zip(depths, forces)))
    return path


# ------------------------------------------------------------------------------------------------ 1. missing tare
def test_untared_forces_are_refused_naming_the_file_the_first_line_and_the_cause(tmp_path, capsys):
    # before: every force 0.3 N low fitted silently (R^2 1.0) and left a 0 N band up to 0.18 mm
    d = np.r_[0.0, 0.0, np.linspace(0.05e-3, 2e-3, 20)]          # two rows at rest (no contact), then the presses
    f = np.r_[0.0, 0.0, truth(d[2:])] - 0.3
    csv = _pairs_csv(tmp_path / "untared.csv", d, f, comment="# a press run\n# operator: \"tare, skipped\n")
    out = tmp_path / "u.force.json"
    assert _cli("--csv", csv, "-o", out) != 0
    err = capsys.readouterr().err
    # line 1-2: comments, 3: header, 4-5: no contact, 6: the first sample in contact (0.05 mm, -0.20 N)
    assert "untared.csv:6: column 'force_n': force -0.2" in err
    assert "without a tare" in err and "Re-tare" in err and f"{NEGATIVE_FORCE_TOLERANCE_N:g} N tolerance" in err
    assert "median of -0.300 N" in err
    assert not out.exists()
    # the same data tared fits
    _pairs_csv(csv, d, f + 0.3)
    assert _cli("--csv", csv, "-o", out) == 0 and out.exists()


def test_forces_a_little_below_zero_within_the_tolerance_are_fitted():
    d = np.linspace(0.05e-3, 2e-3, 20)
    f = truth(d) - 0.13   # the shallowest at -0.034 N: noise, not a missing tare
    assert f.min() < 0 and f.min() > -NEGATIVE_FORCE_TOLERANCE_N
    cal = fit_samples([{"depth_m": a, "force_n": b} for a, b in zip(d, f)], 3)
    assert cal.r2 > 0.999


def test_untared_routine_samples_name_the_sample():
    d = np.linspace(0.1e-3, 2e-3, 12)
    samples = [{"depth_m": float(x), "force_n": gel_force(x, Indenter.probe()) - 0.5, "phase": "loading",
                "cycle": 1} for x in d]
    with pytest.raises(CalibrationError, match=r"^sample 0 \(cycle 1, loading\): force -0\.4.* without a tare"):
        fit_samples(samples, 3)


def test_csv_errors_name_the_physical_line_after_a_quoted_cell_spanning_lines(tmp_path):
    # before: the line was the CSV row's number, one short after a row whose quoted cell spans two lines
    p = tmp_path / "q.csv"
    p.write_text('depth_m,force_n,note\n0.0001,0.1,one\n0.0002,0.2,"two\nlines"\n0.0003,abc,three\n')
    with pytest.raises(CalibrationError, match=r"q\.csv:5: column 'force_n'"):
        read_pairs_csv(p)


def test_a_quote_in_a_comment_does_not_swallow_the_rows_after_it(tmp_path):
    # before: a comment was parsed as CSV first: a cell of it starting with a quote joined the rows below into it
    p = tmp_path / "c.csv"
    p.write_text('# run 3, "probe B\ndepth_m,force_n\n0.0001,0.1\n0.0002,0.2\n')
    data = read_pairs_csv(p)
    assert data["depth_m"].tolist() == [0.0001, 0.0002] and data["line"] == [3, 4]


# ------------------------------------------------------------------------------------------------ 2. depth levels
def test_repeated_depths_count_as_one_level_towards_the_minimum():
    # before: ten readings of a stuck probe (and two more depths) passed the sample count and were "fitted"
    rng = np.random.default_rng(0)
    d = np.r_[1e-3 + rng.normal(0, 0.5e-6, 10), 0.5e-3, 1.5e-3, 1.9e-3]
    f = truth(d)
    with pytest.raises(CalibrationError, match=r"4 distinct depth levels \(13 samples, all\) for a degree-3 fit: need "
                                               r"at least 5 .*stuck probe"):
        ForceCalibration.fit(d, f, 3)
    # one more level beyond the tolerance: a cubic with a residual
    d = np.r_[d, 0.2e-3]
    assert ForceCalibration.fit(d, truth(d), 3).degree == 3


def test_depth_levels_do_not_chain():
    from teletouch.plugins.estimators.poly_force import depth_levels

    tol = DEPTH_LEVEL_TOLERANCE_M
    assert depth_levels([1e-3] * 10) == 1
    assert depth_levels(1e-3 + np.arange(10) * 0.6 * tol) == 5     # a slow drift is several levels, not one chain
    assert depth_levels([1e-3, 1e-3 + 2 * tol, 1e-3 + 4 * tol]) == 3


# ------------------------------------------------------------------------------------------------ 3. minimum R^2
def _poor_fit_data():
    rng = np.random.default_rng(1)
    d = np.repeat(np.linspace(0.1e-3, 2e-3, 20), 3)
    return d, truth(d) + np.abs(rng.normal(0, 0.6, d.size))   # never below zero: not a missing tare


def test_a_fit_below_the_minimum_r2_is_refused_and_not_written(tmp_path, capsys):
    d, f = _poor_fit_data()
    r2 = ForceCalibration.fit(d, f, 3).r2
    assert 0.93 < r2 < 0.97          # the open item's example: R^2 0.95
    csv = _pairs_csv(tmp_path / "noisy.csv", d, f)
    out = tmp_path / "n.force.json"
    assert _cli("--csv", csv, "-o", out) != 0
    err = capsys.readouterr().err
    assert f"R^2 is {r2:.4f}, below the minimum R^2 {DEFAULT_MIN_R2:g}" in err and "--min-r2" in err
    assert not out.exists() and not (tmp_path / "n.png").exists()
    assert _cli("--csv", csv, "-o", out, "--min-r2", "0.9") == 0
    assert ForceCalibration.load(out).r2 == pytest.approx(r2)
    assert _cli("--csv", csv, "-o", out, "--min-r2", "1.5") == 2
    assert "--min-r2: expected an R^2 from 0" in capsys.readouterr().err


def test_the_packaged_calibration_and_the_tests_data_pass_the_minimum_r2():
    from teletouch.plugins.estimators.poly_force import resolve_calibration

    doc = json.loads(resolve_calibration("sim-digit-qvga").read_text())
    assert doc["quality"]["r2"] > DEFAULT_MIN_R2 + 0.009                       # 0.9992
    # refitting its samples under the default limit gives the same curve (the fit of the same data is unchanged)
    s = doc["samples"]
    refit = ForceCalibration.fit([x["depth_m"] for x in s], [x["force_n"] for x in s], 3,
                                 positions=[(x["x_m"], x["y_m"]) for x in s], position_degree=4,
                                 min_r2=DEFAULT_MIN_R2)
    np.testing.assert_allclose(refit.coefficients, doc["model"]["coefficients"], rtol=1e-9)
    d = np.linspace(0.1e-3, 2e-3, 15)
    assert ForceCalibration.fit(d, [gel_force(x, Indenter.probe()) for x in d], 3, min_r2=DEFAULT_MIN_R2).r2 > 0.999


# ------------------------------------------------------------------------------------------------ 4. light touch
def _pos_cal_file(tmp_path):
    rows = []
    for x in np.linspace(-2e-3, 2e-3, 5):
        for y in np.linspace(-4e-3, 4e-3, 5):
            for d in np.linspace(0.02e-3, 2.0e-3, 12):
                rows.append((d, float(truth(d)) * (1.0 + 0.2 * x / 2e-3), x, y))
    a = np.array(rows)
    cal = ForceCalibration.fit(a[:, 0], a[:, 1], 3, positions=a[:, 2:], position_degree=1)
    return cal, str(cal.save(tmp_path / "p.force.json"))


def test_a_light_touch_without_a_centroid_falls_back_instead_of_invalid_input(tmp_path):
    # before: max depth 0.031 mm (just above contact_threshold 0.03 mm) with a NaN centroid gave 0 N, invalid-input,
    # counted towards fault_after_invalid
    cal, path = _pos_cal_file(tmp_path)
    nan = np.full(2, np.nan)
    with Harness(PolyForce, {"calibration": path, "fault_after_invalid": 2}) as h:
        out = h.step(0.1, max_depth=3.1e-5, centroid=nan)          # touch-down: the centre of the calibrated area
        assert out["status"] == "no-centroid" and out["force"] == pytest.approx(cal.predict(3.1e-5, position=(0, 0)))
        assert out["force"] > 0
        out = h.step(0.2, max_depth=3e-4, centroid=np.array([2e-3, 0.0]))
        assert out["status"] == "ok"
        out = h.step(0.3, max_depth=4e-5, centroid=nan)            # releasing: where the contact was
        assert out["status"] == "no-centroid"
        assert out["force"] == pytest.approx(cal.predict(4e-5, position=(2e-3, 0.0)))
        for k in range(3):                                         # a light touch lingering never faults the node
            assert h.step(0.4 + 0.1 * k, max_depth=3.2e-5, centroid=nan)["status"] == "no-centroid"
        assert h.comp.status()["centroid_fallbacks"] == 5 and h.comp.status()["invalid"] == 0


def test_a_deep_press_without_a_centroid_stays_invalid(tmp_path):
    _, path = _pos_cal_file(tmp_path)
    nan = np.full(2, np.nan)
    with Harness(PolyForce, {"calibration": path}) as h:
        out = h.step(0.1, max_depth=3e-5 + 2.1e-5, centroid=nan)   # beyond the band (0.02 mm above the threshold)
        assert out == {"status": "invalid-input"}                  # no force sample: the estimate is lost
        assert h.step(0.2, max_depth=1e-3, centroid=nan) == {"status": "invalid-input"}
    with Harness(PolyForce, {"calibration": path, "centroid_band": 0.0}) as h:   # the fallback off
        assert h.step(0.1, max_depth=3.1e-5, centroid=nan)["status"] == "invalid-input"


# ------------------------------------------------------------------------------------------------ reproducible files
def test_source_date_epoch_makes_force_calibrations_byte_identical(tmp_path, monkeypatch):
    # before: 'created' was the clock's time, so two fits of one CSV differed in their bytes
    d = np.linspace(0.05e-3, 2e-3, 20)
    csv = _pairs_csv(tmp_path / "pairs.csv", d, truth(d))
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    a, b = tmp_path / "a.force.json", tmp_path / "b.force.json"
    assert _cli("--csv", csv, "-o", a) == 0
    import time

    time.sleep(1.1)   # a second later: the clock's 'created' would differ (not a timing assertion)
    assert _cli("--csv", csv, "-o", b) == 0
    assert a.read_bytes() == b.read_bytes()
    assert json.loads(a.read_text())["created"] == "2023-11-14T22:13:20+00:00"


def test_a_malformed_source_date_epoch_is_refused_before_the_fit(tmp_path, monkeypatch, capsys):
    d = np.linspace(0.05e-3, 2e-3, 20)
    csv = _pairs_csv(tmp_path / "pairs.csv", d, truth(d))
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    out = tmp_path / "a.force.json"
    assert _cli("--csv", csv, "-o", out) == 2
    assert "SOURCE_DATE_EPOCH 'yesterday'" in capsys.readouterr().err and not out.exists()


def test_hysteresis_fits_count_depth_levels_not_near_duplicate_depths():
    # before: each phase's degree came from exact unique depths, so a stuck probe's jittering repeats (5 levels,
    # 40 samples) allowed a cubic through what is 5 levels with noise
    from teletouch.plugins.estimators.poly_force import _hysteresis

    rng = np.random.default_rng(0)
    levels = np.repeat(np.linspace(0.2e-3, 1.0e-3, 3), 8) + rng.normal(0, 1e-6, 24)   # 3 levels, 24 samples
    d = np.r_[levels, levels]
    f = truth(d)
    ph = ["loading"] * 24 + ["unloading"] * 24
    h = _hysteresis(d, f, ph, 3, False)
    assert h["loading"]["degree"] == 1 and h["unloading"]["degree"] == 1
