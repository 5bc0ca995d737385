"""The live view of `teletouch run`: on a terminal every node stays in view (one row each, redrawn in place, cut to
the terminal's width); in a log or a pipe one plain line per update."""

from __future__ import annotations

import io
import math
import os
import re

import pytest

from teletouch import cli
from teletouch.plugins.controllers.experiments import build_runtime, sim_graph


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _run(stream) -> list[str]:
    view = cli._Progress(stream)
    rt = build_runtime(sim_graph(sensor="image", duration=2.0))
    res = rt.run(progress=view, progress_interval=0.0)
    view.done()
    assert res.status == "ok"
    return [n.id for n in rt.nodes]


def test_on_an_80_column_terminal_every_node_and_the_feedback_numbers_stay_in_view(monkeypatch):
    # before: one line of all nodes cut at 79 columns showed the gripper and part of the camera; the controller's
    # force and passivity energy and the leader were never on screen
    monkeypatch.setattr(cli.shutil, "get_terminal_size", lambda *a, **k: os.terminal_size((80, 24)))
    term = _Terminal()
    ids = _run(term)
    text = term.getvalue()
    draws = re.split(r"\x1b\[\d+F", text)
    assert len(draws) >= 3, "the block is redrawn in place (cursor up) after the first draw"
    assert re.search(rf"\x1b\[{len(ids) + 1}F", text), "cursor up over the whole block: time row + one per node"
    last = [r.replace("\x1b[2K", "") for r in draws[-1].splitlines() if r]
    assert len(last) == len(ids) + 1 and last[0].startswith("t=")
    assert all(len(r) <= 79 for r in last), [len(r) for r in last]
    for node_id, row in zip(ids, last[1:]):
        assert row.split()[0] == node_id and "Hz" in row
    controller = next(r for r in last if r.split()[0] == "controller")
    # SI in status() (force_n, leader_m, follower_m), in N and mm on screen
    assert re.search(r" force=-?\d+\.\d\dN leader=\d+\.\d\dmm follower=\d+\.\d\dmm", controller), controller


def test_in_a_log_each_update_is_one_plain_line_with_every_node():
    log = io.StringIO()
    ids = _run(log)
    lines = log.getvalue().splitlines()
    assert lines and "\x1b" not in log.getvalue()
    for line in lines:
        assert line.startswith("t=") and all(f"| {i} " in line for i in ids)


@pytest.mark.parametrize("columns", [20, 40])
def test_a_narrow_terminal_cuts_rows_but_keeps_one_per_node(monkeypatch, columns):
    monkeypatch.setattr(cli.shutil, "get_terminal_size", lambda *a, **k: os.terminal_size((columns, 24)))
    term = _Terminal()
    ids = _run(term)
    last = [r.replace("\x1b[2K", "") for r in re.split(r"\x1b\[\d+F", term.getvalue())[-1].splitlines() if r]
    assert len(last) == len(ids) + 1 and all(len(r) <= max(columns - 1, 20) for r in last)


class _Status:
    def __init__(self, status):
        self.value = status

    def status(self):
        return self.value


def _text(status) -> str:
    return cli._Progress(io.StringIO())._status_text(_Status(status))


def test_a_number_under_a_unit_suffix_is_shown_in_a_persons_unit_without_the_suffix():
    # before: raw SI next to millimetres, `opening=0.0123 leader_mm=12.3`
    st = {"opening_m": 0.0123, "area_m2": 1.5e-6, "energy_j": 0.0021, "step_s": 0.0032, "since_last_s": 2.5,
          "force_n": 1.234, "frames": 7}
    assert _text(st) == "opening=12.30mm area=1.50mm^2 energy=2.100mJ step=3.2ms since_last=2.50s force=1.23N"
    st = {"stiffness_n_per_m": 1234.4, "damping_n_s_per_m": 2.0, "rate_hz": 3900.0, "angle_rad": 0.5,
          "speed_m_per_s": 0.005, "frames": 3}
    assert _text(st) == "stiffness=1234N/m damping=2.00N*s/m rate=3900.0Hz angle=0.500rad speed=0.005m/s frames=3"


def test_a_value_that_is_no_finite_number_and_a_key_without_a_unit_are_shown_as_they_are():
    st = {"leader_m": None, "lag_s": math.nan, "since_last_s": math.inf, "safe": True, "state": "ok", "ratio": 0.123456}
    assert _text(st) == "leader=None lag=nan since_last=inf safe=True state=ok ratio=0.1235"
    assert _text({"flag_n": True, 3: 0.5, "_m": 1.0}) == "flag=True 3=0.5 _m=1"


def test_a_row_is_cut_between_items_never_inside_a_number():
    # before: cut at the width, `feedback=1.18N` showed as `feedback=1`, another number
    row = "  controller  1000.0 Hz  force=1.18N leader=14.53mm follower=14.65mm feedback=1.18N"
    cut = cli._fit(row, row.index("feedback=") + 10)
    assert cut.endswith("follower=14.65mm") and "feedback" not in cut
    assert cli._fit(row, len(row)) == row and cli._fit(row, 200) == row
    assert cli._fit("x" * 30, 10) == "x" * 10   # one item wider than the line: cut (nothing else fits)
