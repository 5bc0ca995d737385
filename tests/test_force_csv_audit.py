"""The pairs CSV of `teletouch calibrate force --csv`: exactly one depth and one force column, no column named twice
or unknown, no underscore in a number, and a --csv path that cannot be read is a usage error (exit 2)."""

from __future__ import annotations

import pytest

from teletouch.cli import main
from teletouch.plugins.estimators.poly_force import CSV_COLUMNS, CalibrationError, read_pairs_csv, write_pairs_csv

DEPTHS_M = [2e-4 * i for i in range(1, 9)]


def _force(d: float) -> float:
    return 3000 * d + 2e5 * d * d


def _write(path, header: str, row) -> None:
    path.write_text(header + "\n" + "".join(row(d, _force(d)) + "\n" for d in DEPTHS_M))


@pytest.mark.parametrize("header, row, kind, both", [
    # before: depth_mm was used and depth_m ignored; with the columns swapped, depth_m was used (another fit)
    ("depth_mm,depth_m,force_n", lambda d, f: f"{d * 1e3:.4f},{1.5 * d:.6f},{f:.4f}", "depth",
     "'depth_mm' and 'depth_m'"),
    ("depth_m,depth_mm,force_n", lambda d, f: f"{1.5 * d:.6f},{d * 1e3:.4f},{f:.4f}", "depth",
     "'depth_m' and 'depth_mm'"),
    # before: 'force' was used, force_n ignored
    ("depth_m,force,force_n", lambda d, f: f"{d:.6f},{f:.4f},{2 * f:.4f}", "force", "'force' and 'force_n'"),
    ("Depth_M,max_depth_mm,depth,force_n", lambda d, f: f"{d:.6f},{d * 1e3:.4f},{d:.6f},{f:.4f}", "depth",
     "'depth_m', 'max_depth_mm' and 'depth'"),
])
def test_two_depth_or_force_columns_are_refused_naming_both(tmp_path, header, row, kind, both):
    p = tmp_path / "pairs.csv"
    _write(p, header, row)
    n = both.count("'") // 2
    with pytest.raises(CalibrationError, match=rf"{p.name}:1: {n} {kind} columns, {both}: expected exactly one"):
        read_pairs_csv(p)


def test_a_column_named_twice_is_refused(tmp_path):
    # before: the first force_n was used, the second ignored
    p = tmp_path / "dup.csv"
    _write(p, "depth_m,force_n,Force_N", lambda d, f: f"{d:.6f},{f:.4f},{2 * f:.4f}")
    with pytest.raises(CalibrationError, match=rf"{p.name}:1: the column force_n is named twice \(columns 2 and 3\)"):
        read_pairs_csv(p)


def test_an_unknown_column_is_refused_and_the_routines_own_columns_read_back(tmp_path):
    # before: a typo of phase was ignored: the phases were lost (no hysteresis, --use loading fitted nothing apart)
    p = tmp_path / "typo.csv"
    _write(p, "# pressed at the centre\ndepth_m,force_n,phse", lambda d, f: f"{d:.6f},{f:.4f},loading")
    with pytest.raises(CalibrationError, match=rf"{p.name}:2: unknown column 'phse' \(did you mean 'phase'\?\); "
                                               r"expected a depth column, a force column and optionally phase, cycle"):
        read_pairs_csv(p)
    _write(p, "depth_m,force_n,temperature", lambda d, f: f"{d:.6f},{f:.4f},21")
    with pytest.raises(CalibrationError, match=rf"{p.name}:1: unknown column 'temperature'; expected"):
        read_pairs_csv(p)
    # a header without a depth column says which column was likely meant
    _write(p, "dept_m,force_n", lambda d, f: f"{d:.6f},{f:.4f}")
    with pytest.raises(CalibrationError, match=r":1: header \['dept_m', 'force_n'\] needs a depth column .*; unknown "
                                               r"column 'dept_m' \(did you mean 'depth_m' or 'depth_mm'\?\)$"):
        read_pairs_csv(p)
    # what the press routine writes (every column of CSV_COLUMNS) is read back, and a free-text note column too
    rows = [{"depth_m": d, "force_n": _force(d), "phase": "loading", "cycle": 1, "displacement_m": 2 * d,
             "gt_max_depth_m": d, "gt_force_n": _force(d), "x_m": 1e-3, "y_m": -1e-3} for d in DEPTHS_M]
    data = read_pairs_csv(write_pairs_csv(tmp_path / "routine.csv", rows))
    assert data["depth_m"].tolist() == pytest.approx(DEPTHS_M) and data["phase"] == ["loading"] * len(DEPTHS_M)
    assert (tmp_path / "routine.csv").read_text().splitlines()[0] == ",".join(CSV_COLUMNS)
    _write(p, "depth_m,force_n,note", lambda d, f: f"{d:.6f},{f:.4f},probe B")
    assert read_pairs_csv(p)["force_n"].tolist() == pytest.approx([_force(d) for d in DEPTHS_M], abs=1e-4)


def test_a_value_under_an_unnamed_column_is_refused(tmp_path):
    # before: '3' under the header's trailing separator was dropped silently
    p = tmp_path / "unnamed.csv"
    p.write_text("depth_m,force_n,\n0.0002,0.6,\n0.0004,1.2,3\n")
    with pytest.raises(CalibrationError, match=rf"{p.name}:3: '3' in column 3, which the header \(line 1\) leaves "
                                               r"without a name"):
        read_pairs_csv(p)
    p.write_text("depth_m,force_n,\n0.0002,0.6,\n0.0004,1.2, \n")   # a trailing separator with empty cells is fine
    assert read_pairs_csv(p)["force_n"].tolist() == [0.6, 1.2]


@pytest.mark.parametrize("header, rows, line, column, text", [
    # before: float('1_2') is 12 (N), int('1_0') is 10
    ("depth_m,force_n", "0.0002,0.6\n0.0005,1_2\n", 3, "force_n", "1_2"),
    ("depth_mm,force_n", "0.2,0.6\n0_5,1.2\n", 3, "depth_mm", "0_5"),
    ("depth_m,force_n,x_m,y_m", "0.0002,0.6,0.001,0.0_01\n", 2, "y_m", "0.0_01"),
    ("depth_m,force_n,cycle", "0.0002,0.6,1\n0.0004,1.2,1_0\n", 3, "cycle", "1_0"),
])
def test_an_underscore_in_a_number_is_refused_naming_the_line_and_column(tmp_path, header, rows, line, column, text):
    p = tmp_path / "u.csv"
    p.write_text(f"{header}\n{rows}")
    with pytest.raises(CalibrationError, match=rf"{p.name}:{line}: column '{column}': expected (a number|an integer)"
                                               rf".*, got '{text}' \(an underscore in a number is taken for a typo"):
        read_pairs_csv(p)


@pytest.mark.parametrize("what", ["missing", "folder"])
def test_a_csv_path_that_cannot_be_read_is_a_usage_error(tmp_path, capsys, what):
    # before: exit 1 (an invalid file), where `calibrate depth --labels nope.csv` and `estimate nope.png` exit 2
    path = tmp_path / "nope.csv" if what == "missing" else tmp_path
    out = tmp_path / "cal.force.json"
    assert main(["calibrate", "force", "--csv", str(path), "-o", str(out)]) == 2
    why = "No such file or directory" if what == "missing" else "Is a directory"
    assert f"error: --csv: {path}: cannot read the CSV file: {why}" in capsys.readouterr().err
    assert not out.exists()


def test_the_command_refuses_an_ambiguous_header_and_writes_nothing(tmp_path, capsys):
    p = tmp_path / "pairs.csv"
    _write(p, "depth_mm,depth_m,force_n", lambda d, f: f"{d * 1e3:.4f},{1.5 * d:.6f},{f:.4f}")
    out = tmp_path / "cal.force.json"
    assert main(["calibrate", "force", "--csv", str(p), "-o", str(out), "--quiet"]) == 1
    assert f"{p}:1: 2 depth columns, 'depth_mm' and 'depth_m'" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "cal.png").exists()


@pytest.mark.parametrize("extra, says", [
    # before: the calibration was written, then matplotlib raised "Format 'txt' is not supported" (a traceback)
    (["--plot", "{tmp}/p1.plot.txt"], "--plot: '{tmp}/p1.plot.txt': expected an image file (.png, .svg, .pdf, .jpg, "
                                      ".jpeg), not .txt"),
    # before: the PNG overwrote the calibration JSON ("wrote fig.png and fig.png", exit 0)
    (["-o", "{tmp}/fig.png", "--plot", "{tmp}/fig.png"], "--plot: '{tmp}/fig.png' is also -o's file"),
])
def test_outputs_that_would_fail_or_overwrite_each_other_are_refused_before_the_fit(tmp_path, capsys, extra, says):
    p = tmp_path / "pairs.csv"
    _write(p, "depth_m,force_n", lambda d, f: f"{d:.6f},{f:.4f}")
    argv = ["calibrate", "force", "--csv", str(p), "--quiet", "--degree", "2"]
    if "-o" not in extra:
        argv += ["-o", str(tmp_path / "cal.force.json")]
    argv += [a.format(tmp=tmp_path) for a in extra]
    assert main(argv) == 2
    assert says.format(tmp=tmp_path) in capsys.readouterr().err
    assert not list(tmp_path.glob("*.json")) and not list(tmp_path.glob("*.png"))


def test_a_refit_of_a_press_runs_samples_keeps_the_depth_model(tmp_path, capsys):
    """The samples CSV did not say which depth model its depths came from: a refit with --csv (docs: "fits again to
    the same curve") was tied to no model, and `teletouch estimate` refused it with that model. The CSV carries it
    as a comment line now, and the refit takes it unless --sensor-model-id says otherwise."""
    import json
    from pathlib import Path

    graph = Path(__file__).resolve().parents[1] / "examples" / "calibrate-force-sim.yaml"
    out = tmp_path / "sim.force.json"
    rc = main(["calibrate", "force", "--graph", str(graph), "--quiet", "--degree", "2", "-o", str(out),
               "--set", "routine.cycles=1", "--set", "routine.max_displacement=0.6mm"])
    assert rc == 0, capsys.readouterr().err
    made_for = json.loads(out.read_text())["sensor_model_id"]
    samples = tmp_path / "sim.samples.csv"
    assert f"# sensor_model_id: {made_for}\n" in samples.read_text() and made_for
    assert read_pairs_csv(samples)["sensor_model_id"] == made_for
    refit = tmp_path / "refit.force.json"
    assert main(["calibrate", "force", "--csv", str(samples), "--degree", "2", "-o", str(refit), "--quiet"]) == 0
    assert json.loads(refit.read_text())["sensor_model_id"] == made_for   # before: ""
    other = tmp_path / "other.force.json"
    assert main(["calibrate", "force", "--csv", str(samples), "--degree", "2", "-o", str(other), "--quiet",
                 "--sensor-model-id", "mine.model"]) == 0
    assert json.loads(other.read_text())["sensor_model_id"] == "mine.model"


def test_the_samples_csv_round_trips_its_depth_model():
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        p = write_pairs_csv(Path(d) / "s.csv", [{"depth_m": x, "force_n": _force(x)} for x in DEPTHS_M],
                            partial="the run did not finish", sensor_model_id="sensor.model")
        data = read_pairs_csv(p)
        assert data["sensor_model_id"] == "sensor.model" and data["partial"] == "the run did not finish"
        assert len(data["depth_m"]) == len(DEPTHS_M)
