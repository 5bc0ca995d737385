"""The command line's messages a newcomer met: a malformed --set is a usage error (exit 2) naming the --set and the
form NODE.FIELD=VALUE; an interrupt says once which signal arrived ("teletouch: interrupted (Ctrl-C)" /
"teletouch: interrupted (SIGTERM)")."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from teletouch import Component, Kind, Port, hookimpl
from teletouch.cli import EXIT_TERMINATED, Terminated, main
from teletouch.runtime import EXIT_INTERRUPTED
from teletouch.testing import make_registry, run_yaml

REPO = Path(__file__).resolve().parents[1]
PAPER_SIM = str(REPO / "examples" / "paper-sim.yaml")


# --- 1. a malformed --set is a usage error ---------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["run", "validate"])
@pytest.mark.parametrize("item", ["gripper", "gripper=3", "=3", ".max_speed=3", "gripper.=3", "gripper..x=3",
                                  "gripper.params=3"])
def test_a_malformed_set_is_a_usage_error_naming_the_set_and_its_form(command, item, capsys):
    # before: exit 1, as for an invalid graph, with "1 error(s) in graph: --set: 'gripper': ..."
    with pytest.raises(SystemExit) as exc:
        main([command, PAPER_SIM, "--set", item, "--duration", "0.01"] if command == "run"
             else [command, PAPER_SIM, "--set", item])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"error: argument --set: {item!r}: expected NODE." in err, err
    assert "error(s) in graph" not in err


def test_a_well_formed_set_that_names_no_node_is_still_an_invalid_graph(capsys):
    # what --set names depends on the graph: that stays exit 1, led by the --set
    assert main(["validate", PAPER_SIM, "--set", "griper.max_speed=0.01"]) == 1
    err = capsys.readouterr().err
    assert "--set griper.max_speed=0.01: no node 'griper' (did you mean 'gripper'?)" in err, err


def test_calibrate_force_takes_set_in_the_same_form(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "force", "--graph", "x.yaml", "--set", "routine"])
    assert exc.value.code == 2
    assert "argument --set: 'routine': expected NODE.FIELD=VALUE" in capsys.readouterr().err


# --- 3. the interrupt says which signal, once ------------------------------------------------------------------------
class _Interrupts(Component):
    name = "interrupts"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "")}

    class Params(Component.Params):
        signal: str = "SIGINT"

    def step(self, t, inputs):
        if t >= 0.05 and self.params.signal == "kill-SIGTERM":   # as a real SIGTERM: teletouch run's handler
            os.kill(os.getpid(), signal.SIGTERM)
        elif t >= 0.05:
            raise KeyboardInterrupt if self.params.signal == "SIGINT" else Terminated
        return {"y": 1.0}


class _InterruptsPlugin:
    @hookimpl
    def teletouch_components(self):
        return [_Interrupts]


GRAPH = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 100}
  - {id: dev, plugin: mock-device, rate: 100, inputs: {command: src.value}}
  - {id: k, plugin: interrupts, rate: 100, params: {signal: SIG}}
"""


@pytest.mark.parametrize("sig, name", [("SIGINT", "Ctrl-C"), ("SIGTERM", "SIGTERM")])
def test_the_run_result_names_the_signal_that_interrupted_it(sig, name):
    # before: "interrupted (Ctrl-C or SIGTERM): ..." whichever came
    res, _ = run_yaml(GRAPH.replace("SIG}", sig + "}"), make_registry(_InterruptsPlugin()), duration=1.0)
    assert res.status == "interrupted" and res.exit_code == EXIT_INTERRUPTED
    assert res.message == f"interrupted ({name}): devices driven to their safe state"
    assert res.summary().splitlines()[0] == res.message   # not "interrupted: interrupted (...)"


@pytest.mark.parametrize("sig, name, code", [("SIGINT", "Ctrl-C", EXIT_INTERRUPTED),
                                             ("kill-SIGTERM", "SIGTERM", EXIT_TERMINATED)])
def test_teletouch_run_says_once_which_signal_arrived(sig, name, code, tmp_path, monkeypatch, capsys):
    # before: "teletouch: interrupted: interrupted (Ctrl-C or SIGTERM): ..." and "teletouch: interrupted by SIGTERM:
    # interrupted (Ctrl-C or SIGTERM): ..."
    import teletouch.registry as registry

    monkeypatch.setattr(registry, "_default", make_registry(_InterruptsPlugin()))
    graph = tmp_path / "g.yaml"
    graph.write_text(GRAPH.replace("SIG}", sig + "}"))
    assert main(["run", str(graph), "--duration", "1", "--quiet"]) == code
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1] == f"teletouch: interrupted ({name}): devices driven to their safe state"
    assert "Ctrl-C or SIGTERM" not in err and err.count("interrupted") == 1, err


@pytest.mark.parametrize("exc, line, code", [(KeyboardInterrupt, "teletouch: interrupted (Ctrl-C)", EXIT_INTERRUPTED),
                                             (Terminated, "teletouch: interrupted (SIGTERM)", EXIT_TERMINATED)])
def test_an_interrupt_outside_a_run_says_which_signal(exc, line, code, monkeypatch, capsys):
    import teletouch.cli as cli

    def interrupted(argv):
        raise exc

    monkeypatch.setattr(cli, "_main", interrupted)
    assert main(["plugins"]) == code
    assert capsys.readouterr().err.strip() == line


def test_terminated_carries_its_signal():
    assert Terminated.signum == signal.SIGTERM
