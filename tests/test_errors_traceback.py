"""A fault's one line names one place; the full traceback is there when that is not enough: each fault an exception
made keeps it (``Fault.traceback``; not in ``--json``), and ``teletouch run --traceback`` (or ``TELETOUCH_TRACEBACK=1``)
prints it on stderr, above the last line. Before, nothing showed it."""

from __future__ import annotations

import json

import pytest

from teletouch import Component, Kind, Port, hookimpl
from teletouch.cli import main
from teletouch.testing import make_registry, run_yaml


def _parse_config(text):
    return json.loads(text)   # the library call that fails


class _Fails(Component):
    name = "tb-fails"
    kind = Kind.SENSOR
    outputs = {"force": Port("float64", (), "N", "f")}

    def step(self, t, inputs):
        if t >= 0.2:
            return {"force": _parse_config("{bad json")["f"]}
        return {"force": 1.0}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Fails]


GRAPH = """
clock: sim
duration: 1
nodes:
  - {id: force, plugin: tb-fails, rate: 10}
  - {id: dev, plugin: mock-device, rate: 10}
  - {id: src, plugin: mock-sensor, rate: 10}
"""


def test_a_fault_an_exception_made_keeps_its_traceback_and_others_have_none():
    res, _ = run_yaml(GRAPH, make_registry(_Plugin()), duration=1.0)
    (fault,) = res.faults
    assert fault.kind == "exception"
    assert fault.traceback.startswith("Traceback (most recent call last):"), fault.traceback
    assert "in _parse_config" in fault.traceback and "json.decoder.JSONDecodeError" in fault.traceback
    assert "traceback" not in res.as_dict()["faults"][0]   # --json as before
    res2, _ = run_yaml("clock: sim\nnodes:\n  - {id: s, plugin: mock-sensor, rate: 10, params: {silent_at: 0.5}}\n"
                       "  - {id: g, plugin: mock-gain, rate: 10, inputs: {x: {from: s.value, max_age: 0.3}}}\n",
                       make_registry(), duration=3.0)
    assert res2.faults and res2.faults[0].kind == "stale" and res2.faults[0].traceback == ""


@pytest.mark.parametrize("how", ["option", "environment", "neither", "environment 0"])
def test_teletouch_run_prints_the_faults_traceback_when_asked(how, tmp_path, monkeypatch, capsys):
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_Plugin()))
    monkeypatch.delenv("TELETOUCH_TRACEBACK", raising=False)
    if how.startswith("environment"):
        monkeypatch.setenv("TELETOUCH_TRACEBACK", "0" if how.endswith("0") else "1")
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH)
    argv = ["run", str(graph), "--quiet"] + (["--traceback"] if how == "option" else [])
    assert main(argv) == 3
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("teletouch: fault: node 'force' exception: JSONDecodeError: "), err
    if how in ("option", "environment"):
        assert err.count("Traceback (most recent call last):") == 1, err
        assert "teletouch: traceback of node 'force' exception at t=0.200 s: JSONDecodeError: " in err, err
        assert "in _parse_config" in err and 'return json.loads(text)' in err, err
        assert lines[-2].startswith("json.decoder.JSONDecodeError: "), err   # the traceback, then the last line
    else:
        assert "Traceback (most recent" not in err and "teletouch: traceback" not in err, err


def test_the_option_is_in_run_help(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "--traceback" in out and "TELETOUCH_TRACEBACK" in out
