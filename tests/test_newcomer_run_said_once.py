"""`teletouch run P` printed how the run ended twice: "ok: ran 10.000 s" as the summary table's first line, and
"teletouch: ok: ran 10.000 s" as the last line. It is said once, last (the line scripts read; also with --quiet)."""

from __future__ import annotations

from teletouch.cli import main
from teletouch.testing import make_registry

GRAPH = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {fail_at: FAIL}}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: src.value}}
"""


def _run(monkeypatch, tmp_path, capsys, fail_at: str, *flags: str) -> tuple[int, list[str]]:
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry())
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH.replace("FAIL", fail_at))
    code = main(["run", str(graph), "--duration", "1", *flags])
    return code, capsys.readouterr().err.strip().splitlines()


def test_a_run_says_once_how_it_ended(monkeypatch, tmp_path, capsys):
    code, err = _run(monkeypatch, tmp_path, capsys, "null")
    assert code == 0
    assert [line for line in err if "ran 1.000 s" in line] == ["teletouch: ok: ran 1.000 s"], err
    assert err[-1] == "teletouch: ok: ran 1.000 s"
    assert any(line.startswith("clock sim: 1.000 s graph time") for line in err), err   # the table is still shown
    assert any(line.split()[:2] == ["dev", "mock-device"] for line in err), err


def test_a_fault_is_said_once_and_its_rows_stay(monkeypatch, tmp_path, capsys):
    code, err = _run(monkeypatch, tmp_path, capsys, "0.5")
    assert code == 3
    assert sum("mock-sensor failure" in line and "fault:" in line and "->" not in line for line in err) == 1, err
    assert err[-1].startswith("teletouch: fault: ") and "mock-sensor failure" in err[-1], err
    assert any(line.startswith("  fault: ") and " -> " in line for line in err), err   # the summary's fault rows


def test_quiet_keeps_the_one_line(monkeypatch, tmp_path, capsys):
    code, err = _run(monkeypatch, tmp_path, capsys, "null", "--quiet")
    assert code == 0 and err == ["teletouch: ok: ran 1.000 s"], err


def test_a_status_message_of_several_lines_is_not_split_above_the_table():
    # before: the summary's first line was cut off by splitting at the first newline, so the rest of a message of
    # several lines (a plugin's request_stop("done\n  wrote out.json")) stood above the table and was said again
    from teletouch.runtime import RunResult

    res = RunResult(status="ok", exit_code=0, message="done\n  wrote out.json", nodes=[], faults=[], sim_time=1.0,
                    wall_time=1.0, startup_time=0.0, clock="sim")
    body = res.summary(header=False)
    assert "wrote out.json" not in body and body.startswith("clock sim: 1.000 s graph time"), body
    assert res.summary().startswith("ok: done\n  wrote out.json\nclock sim")
