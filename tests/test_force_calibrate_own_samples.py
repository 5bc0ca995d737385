"""`teletouch calibrate force` whose press routine finished after a node feeding it was disabled by a fault: the command
writes no calibration and marks its own samples CSV partial. The routine's own ``samples_csv`` was left as the routine
wrote it when it finished, unmarked: `--csv` fitted it without a word. Now it is marked partial with the same reason,
and `--csv` refuses it saying the samples may be stale (before, it said "a run that did not finish may lack the deeper
steps", untrue of a run that finished). The graph is test_force_calibrate_faults's: a spare mock-sensor that the routine
reads as its reference depth faults at t = 6 s, before 8 of its 13 samples; the routine is blinded to it (a fault it
could not see at its step: seen, it aborts at once, test_runtime_disabled_upstream)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_force_calibrate_faults import _graph, blind_routine  # noqa: E402

from teletouch.cli import main  # noqa: E402
from teletouch.plugins.estimators.poly_force import read_pairs_csv  # noqa: E402

WHY = ("node 'spare' (exception at t=6.000 s) feeds the press routine and was disabled before 8 of its 13 samples were "
       "recorded: they may hold stale values")


def _calibrate_with_own_samples(tmp_path: Path, capsys, monkeypatch) -> tuple[int, str, Path]:
    blind_routine(monkeypatch)
    own = tmp_path / "routine.csv"
    capsys.readouterr()
    rc = main(["calibrate", "force", "--graph", _graph(tmp_path, 6.0, read=True), "-o", str(tmp_path / "x.force.json"),
               "--quiet", "--set", f"routine.samples_csv={own}"])
    return rc, capsys.readouterr().err, own


def test_the_routine_s_own_samples_csv_is_marked_partial_when_a_fault_upstream_may_have_spoiled_it(tmp_path, capsys,
                                                                                                   monkeypatch):
    rc, err, own = _calibrate_with_own_samples(tmp_path, capsys, monkeypatch)
    assert rc == 3 and not (tmp_path / "x.force.json").exists(), err[-3000:]
    for path in (tmp_path / "x.samples.csv", own):   # the command's samples and the routine's own samples_csv
        rows = read_pairs_csv(path)
        assert len(rows["depth_m"]) == 13 and rows["partial"] == WHY, (path, rows["partial"])   # before: None (own)
    assert f"marked the routine's samples_csv {own} partial too" in err, err[-3000:]


def test_a_fit_of_stale_samples_is_refused_saying_they_may_be_stale_not_that_the_run_did_not_finish(tmp_path,
                                                                                                 capsys, monkeypatch):
    rc, err, own = _calibrate_with_own_samples(tmp_path, capsys, monkeypatch)
    assert rc == 3, err[-3000:]
    fitted = tmp_path / "fit.force.json"
    for path in (tmp_path / "x.samples.csv", own):
        capsys.readouterr()
        assert main(["calibrate", "force", "--csv", str(path), "-o", str(fitted)]) != 0
        said = capsys.readouterr().err
        assert not fitted.exists()
        assert f"{path}: partial samples ({WHY}): a fit of them may not be the sensor's force curve" in said, said
        assert "did not finish" not in said and "deeper steps" not in said, said   # before: said of a finished run
        assert "--allow-partial" in said


def test_a_fit_of_an_unfinished_run_s_samples_is_still_refused_saying_it_may_lack_the_deeper_steps(tmp_path, capsys):
    path = tmp_path / "cut.csv"
    path.write_text("# partial: press routine aborted: abort input; 4 of 13 planned steps recorded\n"
                    "depth_m,force_n\n0.0001,0.1\n0.0002,0.3\n0.0003,0.6\n0.0004,1.0\n")
    capsys.readouterr()
    assert main(["calibrate", "force", "--csv", str(path), "-o", str(tmp_path / "fit.force.json")]) != 0
    said = capsys.readouterr().err
    assert "a run that did not finish may lack the deeper steps" in said and "stale" not in said, said
