"""Review of the experiments (``teletouch experiment contact|pivot``): a Ctrl-C, a faulting baseline run, an --out
that cannot be a folder."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from teletouch.plugins.controllers import experiments
from teletouch.plugins.controllers.position_force import PositionPosition


@pytest.fixture
def ctrl_c_while_running(monkeypatch):
    """A real SIGINT to this process 0.3 s after the experiment's first graph starts running (its runtime is built:
    the signal lands in Runtime.run, where nearly all of an experiment's time goes)."""
    real = experiments.build_runtime
    timers: list[threading.Timer] = []

    def build(doc, registry=None):
        rt = real(doc, registry)
        if not timers:
            timers.append(threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)))
            timers[0].start()
        return rt

    monkeypatch.setattr(experiments, "build_runtime", build)
    yield
    for t in timers:
        t.join(5.0)


@pytest.mark.parametrize("argv", [["contact", "--sensor", "ideal", "--duration", "60"],
                                  ["pivot", "--trials", "3"]])
def test_ctrl_c_during_an_experiment_is_an_interruption_not_a_fault(ctrl_c_while_running, capsys, tmp_path, argv):
    """A Ctrl-C while a run stepped ended the command with exit 3 and 'contact run (with feedback) ended with
    interrupted' / 'pivot trial 0 ended with interrupted' (the code and words of a faulted run); Ctrl-C is 130
    ('teletouch: interrupted') everywhere else."""
    from teletouch.cli import main

    code = main(["experiment", *argv, "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 130, err
    assert "teletouch: interrupted" in err
    assert "ended with" not in err
    assert not (tmp_path / f"{argv[0]}.json").exists()


def test_a_faulting_baseline_run_is_named_as_the_baseline(capsys, monkeypatch, tmp_path):
    """The position-position baseline's fault was reported as 'contact run (with feedback) ended with fault'."""
    from teletouch.cli import main

    def broken(self, t, inputs):
        raise RuntimeError("baseline controller broke")

    monkeypatch.setattr(PositionPosition, "step", broken)
    assert main(["experiment", "contact", "--duration", "2", "--sensor", "ideal", "--baselines", "--out",
                 str(tmp_path)]) == 3
    err = capsys.readouterr().err
    assert "contact run (position-position) ended with fault" in err
    assert "baseline controller broke" in err
    assert "with feedback" not in err


@pytest.mark.parametrize("name", ["contact", "pivot"])
def test_an_out_that_cannot_be_a_folder_is_refused_before_any_run(monkeypatch, tmp_path, name):
    """experiment_contact/experiment_pivot ran every run (the pivot's 30 trials: minutes) and then raised
    FileExistsError from save_outputs; the out folder is checked first, as the CLI's --out is."""
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    ran = []
    monkeypatch.setattr(experiments, "build_runtime", lambda doc, registry=None: ran.append(doc) or 1 / 0)
    run = experiments.experiment_contact if name == "contact" else experiments.experiment_pivot
    kw = {"duration": 2.0, "sensor": "ideal"} if name == "contact" else {"trials": 1, "time_limit": 2.0}
    with pytest.raises(ValueError, match=rf"^out: {blocker}: cannot make a folder there"):
        run(**kw, out=blocker, plot=False)
    assert ran == []
