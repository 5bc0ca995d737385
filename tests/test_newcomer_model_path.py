"""A relative path in a graph's parameters (`model: vga/vga.model`) is taken from the current folder, not the graph
file's (unlike `include:`), and the error ("vga/vga.model: no such model file") did not show where it looked nor how
to make a model. It now shows the absolute path it looked at and names `teletouch calibrate depth`; docs/graphs.md
says how relative paths are resolved."""

from __future__ import annotations

from pathlib import Path

import pytest

from teletouch.errors import ModelFileError
from teletouch.plugins.estimators.normal_model import resolve_model

REPO = Path(__file__).resolve().parents[1]


def test_a_missing_relative_model_shows_where_it_looked_and_how_to_make_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ModelFileError) as info:
        resolve_model("vga/vga.model")
    msg = str(info.value)
    assert msg.startswith("vga/vga.model: no such model file"), msg
    assert f"looked at {tmp_path / 'vga' / 'vga.model'}" in msg and "current folder" in msg, msg
    assert "teletouch calibrate depth" in msg and "packaged: " in msg and "sim-digit-qvga" in msg, msg


def test_a_missing_absolute_model_is_not_told_about_the_current_folder(tmp_path):
    missing = tmp_path / "gone.model"
    with pytest.raises(ModelFileError) as info:
        resolve_model(missing)
    msg = str(info.value)
    assert msg.startswith(f"{missing}: no such model file") and "current folder" not in msg, msg
    assert "teletouch calibrate depth" in msg, msg


def test_a_relative_model_that_exists_is_still_found(tmp_path, monkeypatch):
    (tmp_path / "vga").mkdir()
    (tmp_path / "vga" / "vga.model").write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    assert resolve_model("vga/vga.model") == Path("vga/vga.model")


def test_graphs_md_says_relative_paths_in_params_are_from_the_current_folder():
    text = (REPO / "docs" / "graphs.md").read_text()
    assert "current folder" in text and "not the graph file's" in text, "docs/graphs.md"
