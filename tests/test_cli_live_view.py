"""The live view of `teletouch run`: on a terminal every node stays in view (one row each, redrawn in place, cut to
the terminal's width); in a log or a pipe one plain line per update."""

from __future__ import annotations

import io
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
    assert "force_N=" in controller and "leader_mm=" in controller and "follower_mm=" in controller


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
