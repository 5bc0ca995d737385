"""An outside audit of `teletouch calibrate depth`, `calibrate force` and `estimate` following the docs: a length typed
as a bare number (metres, meant as millimetres) was taken silently or refused without naming the option and the value
as read (`--caliper-gap 5` gave a scale of 0.012 px/mm, then "the ball radius ... is 0.036 px"; `--min-depth 0.03`, the
default written without its unit, refused every sample "of at least 30.000 mm"); `estimate` spoke of a graph file it
does not read; `calibrate force` printed its errors as `teletouch: error:`, the other commands under their own name."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from teletouch.cli import main
from teletouch.plugins.estimators import force_calibration
from teletouch.plugins.estimators.poly_force import ForceCalibration
from teletouch.plugins.sensors.sim_digit import DigitSimulator

from helpers_depth import presses_fixture

sim_presses = presses_fixture(6, seed=11)


def _no_work(*args, **kwargs):
    raise AssertionError("the command should have refused its arguments before any work")


# --- calibrate depth: --caliper-gap and the ball size ---------------------------------------------------------------

def _caliper_image(folder, tmp_path):
    """Two presses' change added onto the background (as two caliper tips in one frame); their distance in mm."""
    bg = cv2.imread(str(folder / "background.png")).astype(np.int16)
    a, b = (cv2.imread(str(folder / f"press_0{k}.png")).astype(np.int16) for k in (1, 2))
    path = tmp_path / "caliper.png"
    cv2.imwrite(str(path), np.clip(bg + (a - bg) + (b - bg), 0, 255).astype(np.uint8))
    dist_px = math.hypot(191.7 - 75.63, 91.59 - 267.64)   # press_01 and press_02 in labels.csv
    return path, dist_px * DigitSimulator("qvga").m_per_px * 1e3


def _cal_depth(folder, tmp_path, *extra):
    return main(["calibrate", "depth", "--images", str(folder), "--background", str(folder / "background.png"),
                 "--labels-only", "--write-labels", str(tmp_path / "l.csv"), *extra])


def test_a_bare_caliper_gap_is_refused_as_metres_before_the_scale_is_taken(sim_presses, tmp_path, capsys):
    caliper, gap_mm = _caliper_image(sim_presses, tmp_path)
    rc = _cal_depth(sim_presses, tmp_path, "--ball-diameter", "6mm", "--caliper", str(caliper), "--caliper-gap", "5")
    err = capsys.readouterr().err
    # before: "scale from the caliper image: 0.0... px/mm", then "... the ball radius of 3 mm is 0.0... px"
    assert rc == 2 and ("teletouch calibrate depth: error: --caliper-gap 5 (read as 5 m): expected the distance "
                        "between the caliper's tips on the gel") in err, err
    assert err.rstrip().endswith("a bare number is metres: did you mean 5mm?"), err
    assert "scale from the caliper image" not in err and not (tmp_path / "l.csv").exists()
    # the gap with its unit gives about the simulated sensor's scale (the contacts' centroids, not the labels' centres)
    rc = _cal_depth(sim_presses, tmp_path, "--ball-diameter", "6mm", "--caliper", str(caliper), "--caliper-gap",
                    f"{gap_mm:.3f}mm")
    err = capsys.readouterr().err
    assert rc == 0, err
    scale = float(err.split("scale from the caliper image: ")[1].split(" px/mm")[0])
    assert scale == pytest.approx(1e-3 / DigitSimulator("qvga").m_per_px, rel=0.2), err


@pytest.mark.parametrize("gap, msg", [
    ("0.5", "--caliper-gap 0.5 (read as 0.5 m): expected"),
    ("0mm", "--caliper-gap 0mm (read as 0 m): expected"),
    ("5parsecs", "--caliper-gap: unknown unit 'parsecs'"),
])
def test_other_caliper_gaps_name_the_option(sim_presses, tmp_path, capsys, gap, msg):
    caliper, _ = _caliper_image(sim_presses, tmp_path)
    rc = _cal_depth(sim_presses, tmp_path, "--ball-diameter", "6mm", "--caliper", str(caliper), "--caliper-gap", gap)
    err = capsys.readouterr().err
    assert rc == 2 and f"teletouch calibrate depth: error: {msg}" in err, err
    assert ("did you mean 0.5mm?" in err) == (gap == "0.5"), err


@pytest.mark.parametrize("args, msg", [
    # before: "ball radius 3000 mm is implausible (expected e.g. --ball-diameter 6mm); ...": the option typed and its
    # value (a diameter) were not named
    (["--ball-diameter", "6"], "--ball-diameter 6 (read as 6 m): ball radius 3000 mm is implausible (expected e.g. "
                               "--ball-diameter 6mm); a bare number is metres: did you mean 6mm?"),
    (["--ball-radius", "3"], "--ball-radius 3 (read as 3 m): ball radius 3000 mm is implausible (expected e.g. "
                             "--ball-radius 3mm); a bare number is metres: did you mean 3mm?"),
    (["--ball-diameter", "6parsecs"], "--ball-diameter: unknown unit 'parsecs'"),
])
def test_an_implausible_ball_names_the_option_and_the_value_as_read(sim_presses, tmp_path, capsys, args, msg):
    rc = _cal_depth(sim_presses, tmp_path, *args, "--px-per-mm", "17.15")
    err = capsys.readouterr().err
    assert rc == 2 and f"teletouch calibrate depth: error: {msg}" in err, err


# --- calibrate force: --min-depth and the command's prefix ----------------------------------------------------------

def _pairs(tmp_path):
    csv = tmp_path / "pairs.csv"
    d = np.linspace(0.1e-3, 1.5e-3, 12)
    csv.write_text("depth_m,force_n\n" + "".join(f"{x:.6g},{3e3 * x + 1e6 * x * x:.6g}\n" for x in d))
    return csv


def test_a_bare_min_depth_deeper_than_any_gel_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(force_calibration, "fit_samples", _no_work)
    monkeypatch.setattr(force_calibration, "run_press_calibration", _no_work)
    out = tmp_path / "cal.force.json"
    # before: the fit's "teletouch: error: no sample with a max depth of at least 30.000 mm: did the probe touch the
    # gel?" (after the whole press run with --graph), not naming --min-depth nor that 0.03 was read as metres
    assert main(["calibrate", "force", "--csv", str(_pairs(tmp_path)), "--min-depth", "0.03", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("teletouch calibrate force: error: --min-depth 0.03 (read as 0.03 m): samples shallower "
                          "than 30 mm would all be left out"), err
    assert err.rstrip().endswith("a bare number is metres: did you mean 0.03mm?") and not out.exists(), err
    graph = tmp_path / "press.yaml"
    graph.write_text("nodes: []\n")
    assert main(["calibrate", "force", "--graph", str(graph), "--min-depth", "0.03", "-o", str(out)]) == 2
    assert "--min-depth 0.03 (read as 0.03 m)" in capsys.readouterr().err


def test_no_sample_as_deep_as_min_depth_names_the_option_as_read(tmp_path, capsys):
    out = tmp_path / "cal.force.json"
    assert main(["calibrate", "force", "--csv", str(_pairs(tmp_path)), "--min-depth", "0.005", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.strip() == ("teletouch calibrate force: error: no sample with a max depth of at least 5.000 mm "
                           "(--min-depth 0.005, read as 0.005 m; the deepest is 1.500 mm): a bare number is metres: "
                           "did you mean 0.005mm?"), err
    assert main(["calibrate", "force", "--csv", str(_pairs(tmp_path)), "--min-depth", "5mm", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "(--min-depth 5mm, read as 0.005 m; the deepest is 1.500 mm): did the probe touch the gel?" in err, err
    assert "bare number" not in err and not out.exists()


def test_min_depth_help_gives_its_unit_and_default(capsys):
    with pytest.raises(SystemExit):
        main(["calibrate", "force", "-h"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--min-depth DEPTH" in out and "e.g. 0.03mm (a bare number is metres; default 0.03mm)" in out, out


def test_calibrate_force_errors_carry_the_commands_prefix(tmp_path, capsys, monkeypatch):
    csv = tmp_path / "few.csv"
    csv.write_text("depth_m,force_n\n" + "".join(f"{d},{d * 3e3}\n" for d in (5e-4, 1e-3, 1.5e-3, 2e-3)))
    out = tmp_path / "few.force.json"
    # a usage error, a fit refused (before: the CLI's "teletouch: error:"), an output that could not be written
    assert main(["calibrate", "force", "--csv", str(csv), "--degree", "99", "-o", str(out)]) == 2
    assert capsys.readouterr().err.startswith("teletouch calibrate force: error: --degree: expected")
    assert main(["calibrate", "force", "--csv", str(csv), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"teletouch calibrate force: error: {csv}: 4 distinct depth levels"), err

    def full(self, path):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(ForceCalibration, "save", full)
    assert main(["calibrate", "force", "--csv", str(_pairs(tmp_path)), "--degree", "2", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"teletouch calibrate force: error: No space left on device: {out}"), err
    assert "teletouch: error" not in err


# --- estimate: no graph is read -------------------------------------------------------------------------------------

@pytest.mark.parametrize("opt, name, noun", [("--model", "nope.model", "model"),
                                             ("--force-calibration", "nope.json", "force calibration")])
def test_estimate_says_where_it_looked_without_the_graph_note(sim_presses, tmp_path, capsys, monkeypatch, opt, name,
                                                              noun):
    monkeypatch.chdir(tmp_path)
    args = ["--model", "sim-digit-qvga", "--force-calibration", name] if opt != "--model" else ["--model", name]
    assert main(["estimate", *args, str(sim_presses / "press_00.png")]) == 2
    err = capsys.readouterr().err
    # before: "(looked at ...: a relative path is taken from the current folder, not the graph file's)"
    assert (f"teletouch estimate: error: {opt} {name}: no such {noun} file (looked at {tmp_path / name}), and no "
            f"packaged {noun}") in err, err
    assert "graph" not in err, err
