"""Review of the command line and the unit parser: quantities typed as people type them, messages that name what was
expected, outputs refused before the work, and Ctrl-C's exit status wherever it lands."""

from __future__ import annotations

import datetime as dt
import os
import subprocess
import sys
from pathlib import Path

import pytest

from teletouch import cli
from teletouch.paths import output_problem
from teletouch.reproducible import build_time, source_date_epoch
from teletouch.units import parse_quantity

REPO = Path(__file__).resolve().parents[1]
GRAPH = str(REPO / "examples" / "mock-loop.yaml")


def _cli(*args: str, site: Path | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    if site is not None:
        env["PYTHONPATH"] = str(site)
    return subprocess.run([sys.executable, "-m", "teletouch", *args], capture_output=True, text=True, env=env,
                          timeout=120, cwd=REPO)


# ------------------------------------------------------------------------------------------------------ units

@pytest.mark.parametrize("text, unit, value", [
    ("12 \u03bcm", "m", 12e-6),      # GREEK SMALL LETTER MU, what NFKC makes of the micro sign and Greek keyboards type
    ("12\u03bcs", "s", 12e-6),
    ("12 \u00b5m", "m", 12e-6),      # MICRO SIGN (the table's own spelling)
])
def test_both_micro_signs_are_micro(text, unit, value):
    # before: 'unknown unit 'μm' ...; known: ..., µm, µs' -- refused, listing a unit that looks the same
    assert parse_quantity(text, unit) == pytest.approx(value)


@pytest.mark.parametrize("text, unit, wanted", [
    ("2min", "s", "expected a quantity in s (s, ms, us, µs)"),
    ("5 parsec", "m", "expected a quantity in m (m, cm, mm, um, µm)"),
])
def test_an_unknown_unit_says_which_units_fit(text, unit, wanted):
    # before: every unit of every dimension (50 of them) and not what was expected
    with pytest.raises(ValueError) as exc:
        parse_quantity(text, unit)
    msg = str(exc.value)
    assert msg.startswith(f"unknown unit {text.lstrip('0123456789 ')!r} in {text!r}") and wanted in msg, msg
    assert "kg" not in msg and "Pa" not in msg


@pytest.mark.parametrize("text, unit, hint", [
    ("5 hz", "Hz", "did you mean 'Hz'?"),
    ("1khz", "Hz", "did you mean 'kHz'?"),
    ("10 Deg", "rad", "did you mean 'deg'?"),
    ("5kpa", "Pa", "did you mean 'kPa'?"),
    ("6MM", "m", "did you mean 'mm'?"),
    ("6MM", None, "did you mean 'mm'?"),
])
def test_a_unit_in_the_wrong_case_is_refused_with_the_right_spelling(text, unit, hint):
    # refused, not guessed: 'mpa' could be milli- or mega-pascal (a factor of 1e9)
    with pytest.raises(ValueError, match="unknown unit") as exc:
        parse_quantity(text, unit)
    assert hint in str(exc.value), str(exc.value)


@pytest.mark.parametrize("text", ["inf", "-inf", "nan", "infinity", "inf mm", "NaN ms"])
def test_inf_and_nan_are_refused_as_not_finite(text):
    # before: "expected a number in m such as '6mm' or '0.006', got 'inf'" -- as if inf were not a number
    for unit in ("m", "s", None):
        with pytest.raises(ValueError, match=r"expected a finite number"):
            parse_quantity(text, unit)


def test_the_quantities_people_write_still_parse():
    cases = {("6mm", "m"): 6e-3, ("0.006m", "m"): 6e-3, ("10deg", "rad"): 0.17453292519943295,
             ("5kPa", "Pa"): 5e3, (" 6 mm ", "m"): 6e-3, ("-5mm", "m"): -5e-3, ("1.5E-3 m", "m"): 1.5e-3,
             ("2e3mm", "m"): 2.0, (".5ms", "s"): 5e-4, ("+1kHz", "Hz"): 1e3, ("17.15px/mm", "px/m"): 17150.0}
    for (text, unit), value in cases.items():
        assert parse_quantity(text, unit) == pytest.approx(value), text
    with pytest.raises(ValueError, match=r"'10deg' is in rad, expected a quantity in m"):
        parse_quantity("10deg", "m")


# --------------------------------------------------------------------------------------------------------- cli

def test_progress_interval_takes_a_time_with_its_unit_like_duration(capsys):
    # before: --duration 500ms ran, --progress-interval 500ms was "expected a number of seconds, got '500ms'"
    code = cli.main(["run", GRAPH, "--duration", "0.2", "--progress-interval", "500ms", "--quiet"])
    assert code == 0, capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", GRAPH, "--progress-interval", "5mm"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "argument --progress-interval: '5mm' is in m, expected a quantity in s" in err


def _install(root: Path, mod: str, source: str) -> Path:
    info = root / f"acme_{mod}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: acme-{mod}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[teletouch]\n{mod} = tt_{mod}\n")
    (root / f"tt_{mod}.py").write_text(source)
    return root


def test_ctrl_c_while_the_plugins_load_exits_130_without_a_traceback(tmp_path):
    # a Ctrl-C while the plugins are imported (seconds, with torch) came before main's handlers: a traceback, and
    # the process killed by SIGINT (returncode -2) instead of exiting 130
    site = _install(tmp_path / "site", "slow", "raise KeyboardInterrupt  # Ctrl-C during this import\n")
    r = _cli("plugins", site=site)
    assert r.returncode == 130, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr and r.stderr.strip().endswith("teletouch: interrupted (Ctrl-C)")


def test_calibrate_without_what_says_what_is_missing(capsys):
    code = cli.main(["calibrate"])
    err = capsys.readouterr().err
    assert code == 2 and "teletouch calibrate: error: WHAT is required" in err and "depth" in err


# ------------------------------------------------------------------------------------------------------ paths

def test_a_file_output_ending_in_a_separator_is_refused(tmp_path):
    # before: None for 'new/' (a folder that does not exist yet): the writers then wrote a file named 'new', or
    # failed with 'Is a directory' after the work
    for text in (f"{tmp_path}/new/", f"{tmp_path}/model.npz/", f"{tmp_path}/sub{os.sep}"):
        problem = output_problem(text)
        assert problem is not None and "folder" in problem and "file name" in problem, (text, problem)
    assert output_problem(f"{tmp_path}/new/", folder=True) is None
    assert output_problem(f"{tmp_path}/new/model.npz") is None


def test_a_name_too_long_for_the_file_system_is_a_reason_not_an_exception(tmp_path):
    # before: OSError (File name too long) out of output_problem, or None for a missing folder with such a name
    # (the probe runs in the nearest existing folder), and the write failed after the work
    long = "a" * 300
    for path, folder in ((tmp_path / f"{long}.json", False), (tmp_path / long / "x.json", False),
                         (tmp_path / long, True), (tmp_path / "ok" / long / "x.json", False)):
        problem = output_problem(path, folder)
        assert problem is not None and "too long" in problem, (path, problem)


# ------------------------------------------------------------------------------------------- SOURCE_DATE_EPOCH

@pytest.mark.parametrize("text", ["300000000000", "\u00b2"])
def test_a_source_date_epoch_no_file_can_record_is_refused_up_front(monkeypatch, text):
    # before: 3e11 (year 11476) was accepted, and the force calibration failed on writing its date after the press
    # run ('year 11476 is out of range'); '²' (str.isdigit) raised int()'s message without the variable's name
    monkeypatch.setenv("SOURCE_DATE_EPOCH", text)
    with pytest.raises(ValueError, match=r"SOURCE_DATE_EPOCH"):
        source_date_epoch()


def test_the_largest_source_date_epoch_is_written_as_a_date(monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "253402300799")   # 9999-12-31T23:59:59Z
    assert dt.datetime.fromtimestamp(int(build_time()), dt.timezone.utc).year == 9999
    monkeypatch.setenv("SOURCE_DATE_EPOCH", " 1700000000 ")
    assert source_date_epoch() == 1700000000


def test_run_help_names_the_time_options_as_the_docs_do(capsys):
    # README: `teletouch run GRAPH [--duration S] ...`; docs/graphs.md: `--progress-interval S`. Before: DURATION and
    # PROGRESS_INTERVAL, argparse's upper-cased option names
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", "-h"])
    out = " ".join(capsys.readouterr().out.split())
    assert exc.value.code == 0
    assert "[--duration S]" in out and "[--progress-interval S]" in out
    assert "[--duration S]" in (REPO / "README.md").read_text()
    assert "`--progress-interval S`" in " ".join((REPO / "docs" / "graphs.md").read_text().split())


# -------------------------------------------------------------------------------------------------- live view

class _BadStr:
    def __str__(self) -> str:
        raise RuntimeError("no text")


@pytest.mark.parametrize("status", [None, [1, 2], {"x": _BadStr()}])
def test_a_status_that_is_not_a_mapping_of_printable_values_does_not_stop_the_run(status):
    # a status() that raises was skipped, but one returning None (a `pass` body) or a value that cannot be printed
    # raised in the live view, and the run stopped as a 'progress' fault: a live-view bug ended a teleoperation
    import io

    from teletouch.graph import load_graph
    from teletouch.runtime import Runtime

    rt = Runtime(load_graph(GRAPH, duration=3.0))
    rt.component("scale").status = lambda: status
    log = io.StringIO()
    res = rt.run(progress=cli._Progress(log), progress_interval=0.0)
    assert res.status == "ok" and not res.faults, res.message
    assert "| scale " in log.getvalue() and "| device " in log.getvalue()
