"""`teletouch calibrate force` whose press routine finished in a run that ended degraded (or with a fault): it wrote the
calibration and exited 0, saying nothing of the fault. Now it says each fault on stderr, naming the node, and exits
with the run's code (3, as `teletouch run` gives that run). The calibration is written when no fault reached the
samples (a node the routine does not read, or one disabled after the last sample); a node that feeds the routine and
was disabled before a sample was recorded may have left stale values in it: no calibration then, and the samples CSV
is marked partial, naming the fault (the routine itself aborts on such a fault at its next step,
test_runtime_disabled_upstream; this check after the run is for one it could not see: here the routine is blinded to
it).

These graphs are the fast press graph of test_force_calibration (1 cycle, 13 samples recorded at t = 3.4 ... 10.8 s,
done at t = 11.8 s under the simulated clock) with a mock-sensor that faults at ``fail_at`` (on_fault: degrade)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_force_calibration import graph  # noqa: E402

from teletouch.cli import main  # noqa: E402
from teletouch.plugins.estimators.poly_force import read_pairs_csv  # noqa: E402

SPARE = """  - id: spare
    plugin: mock-sensor
    rate: 100
    on_fault: degrade
    params: {{signal: constant, amplitude: 1mm, fail_at: {fail_at}}}
"""


def _fault(t: str) -> str:
    """The stderr line of the spare's fault (ends with where it was raised, then its action)."""
    return f"teletouch: fault: node 'spare' exception at t={t} s: RuntimeError: mock-sensor failure at t={t} ("
DEGRADED = ("teletouch: degraded: press routine done: 13 samples in 1 cycle(s); nodes disabled by faults: 'spare' "
            "(exception at t={t} s)")


def _graph(tmp_path: Path, fail_at: float, read: bool) -> str:
    """The press graph with the spare node; ``read``: the routine records the spare's value as its reference depth."""
    g = graph() + SPARE.format(fail_at=fail_at)
    if read:
        g = g.replace("abort: leader.button", "abort: leader.button, reference_depth: spare.value")
        assert "spare.value" in g
    path = tmp_path / "press.yaml"
    path.write_text(g)
    return str(path)


def _calibrate(path: str, out: Path, capsys) -> tuple[int, str]:
    capsys.readouterr()
    rc = main(["calibrate", "force", "--graph", path, "-o", str(out), "--quiet"])
    return rc, capsys.readouterr().err


def _run(path: str, capsys) -> int:
    capsys.readouterr()
    rc = main(["run", path, "--quiet"])
    capsys.readouterr()
    return rc


def test_calibrate_force_fault_of_a_node_the_routine_does_not_read_writes_it_and_exits_as_run_does(tmp_path, capsys):
    path = _graph(tmp_path, 1.0, read=False)
    out = tmp_path / "x.force.json"
    rc, err = _calibrate(path, out, capsys)
    assert rc == 3 == _run(path, capsys), err[-3000:]   # before: 0 (`teletouch run`: 3, degraded)
    assert _fault("1.000") in err and ") -> degrade\n" in err, err[-3000:]   # before: not said
    assert err.rstrip().splitlines()[-1] == (DEGRADED.format(t="1.000") + "; the press routine had finished and no "
                                             "fault reached its samples: its calibration is written"), err[-3000:]
    assert json.loads(out.read_text())   # the samples are good: written
    assert (tmp_path / "x.png").exists()
    assert read_pairs_csv(tmp_path / "x.samples.csv")["partial"] is None


def test_calibrate_force_fault_after_the_last_sample_of_a_node_the_routine_reads_writes_it_and_exits_3(tmp_path,
                                                                                                   capsys):
    path = _graph(tmp_path, 11.0, read=True)   # after the last sample (10.8 s), before the routine is done (11.8 s)
    out = tmp_path / "x.force.json"
    rc, err = _calibrate(path, out, capsys)
    assert rc == 3, err[-3000:]   # before: 0
    assert _fault("11.000") in err and ") -> degrade\n" in err, err[-3000:]
    assert err.rstrip().splitlines()[-1] == (DEGRADED.format(t="11.000") + "; the press routine had finished and no "
                                             "fault reached its samples: its calibration is written"), err[-3000:]
    assert json.loads(out.read_text())
    rows = read_pairs_csv(tmp_path / "x.samples.csv")
    assert rows["partial"] is None and len(rows["depth_m"]) == 13


def blind_routine(monkeypatch) -> None:
    """The routine does not see a node feeding it disabled (Context.disabled_upstream says none), as with a fault it
    cannot see at its step (one in another rate group at the same instant, under the wall clock): the command's check
    after the run (_spoiled_samples) is then what finds it. Seen, the routine aborts at once:
    test_runtime_disabled_upstream."""
    from teletouch.component import Context

    monkeypatch.setattr(Context, "disabled_upstream", lambda self: [])


def test_calibrate_force_fault_before_a_sample_of_a_node_the_routine_reads_writes_no_calibration(tmp_path, capsys,
                                                                                                 monkeypatch):
    blind_routine(monkeypatch)
    path = _graph(tmp_path, 6.0, read=True)   # mid-run: samples 5 to 13 record its last value, stale
    out = tmp_path / "x.force.json"
    rc, err = _calibrate(path, out, capsys)
    assert rc == 3, err[-3000:]   # before: 0, and the calibration written
    assert not out.exists() and not (tmp_path / "x.png").exists(), err[-3000:]
    assert _fault("6.000") in err and ") -> degrade\n" in err, err[-3000:]
    why = ("node 'spare' (exception at t=6.000 s) feeds the press routine and was disabled before 8 of its 13 samples "
           "were recorded: they may hold stale values")
    assert err.rstrip().splitlines()[-1] == (DEGRADED.format(t="6.000") + f"; {why}; no calibration written"), \
        err[-3000:]
    # every sample is kept for a look, marked partial with the reason: `--csv` refuses it unless --allow-partial
    rows = read_pairs_csv(tmp_path / "x.samples.csv")
    assert len(rows["depth_m"]) == 13 and why in rows["partial"], rows["partial"]
    assert "marked partial" in err
    again = tmp_path / "again.force.json"
    capsys.readouterr()
    rc = main(["calibrate", "force", "--csv", str(tmp_path / "x.samples.csv"), "-o", str(again)])
    assert rc != 0 and why in capsys.readouterr().err and not again.exists()


def test_calibrate_force_fault_in_the_shutdown_is_said_and_the_exit_code_is_the_runs(tmp_path, capsys):
    # a shutdown error is logged by the runtime (the run stays "stopped", exit 0, as `teletouch run` gives it): the
    # calibration is written, the fault is said on stderr
    g = graph() + """  - id: burn
    plugin: mock-burn
    rate: 10
    params: {burn: 0, deactivate_error: true}
"""
    path = tmp_path / "press.yaml"
    path.write_text(g)
    out = tmp_path / "x.force.json"
    rc, err = _calibrate(str(path), out, capsys)
    assert rc == 0 == _run(str(path), capsys), err[-3000:]
    assert json.loads(out.read_text())
    said = re.search(r"^teletouch: fault: node 'burn' shutdown at t=[0-9.]+ s: deactivate\(\) raised RuntimeError: "
                     r"mock-burn deactivate failure \(mock\.py:\d+\) -> logged$", err, re.M)
    assert said, err[-3000:]   # before: not said
