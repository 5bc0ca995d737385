"""Validating a graph with a `depth` node reads its model file's header once: the ``model`` validator reads it
(check_model_file) and ``port_shapes`` takes the frames' size from the same header (model_image_shape), which read it
again. The header is kept per file (its resolved path, inode, mtime and size): a changed file is read anew."""

from __future__ import annotations

import os
import shutil

import pytest

from helpers_depth import qvga_and_vga_models_fixture

from teletouch.errors import GraphValidationError
from teletouch.plugins.estimators import normal_model
from teletouch.testing import load_text, make_registry


@pytest.fixture(scope="module")
def reg():
    return make_registry("teletouch.plugins.sensors.sim_digit", "teletouch.plugins.estimators.depth")


models = qvga_and_vga_models_fixture()


@pytest.fixture
def reads(monkeypatch) -> list[str]:
    """The model files whose archive is opened to read a header (normal_model._check_archive, its first step)."""
    seen: list[str] = []
    check = normal_model._check_archive

    def spy(p):
        seen.append(str(p))
        return check(p)

    monkeypatch.setattr(normal_model, "_check_archive", spy)
    return seen


def _graph(model: str) -> str:
    return f"""
clock: sim
nodes:
  - {{id: digit, plugin: sim-digit, rate: 60}}
  - {{id: depth, plugin: depth, rate: 60, params: {{model: '{model}'}}, inputs: {{image: digit.image}}}}
"""


def test_validating_a_graph_reads_the_depth_models_header_once(reg, models, reads, tmp_path):
    model = tmp_path / "sensor.model"
    shutil.copyfile(models["qvga"], model)
    spec = load_text(_graph(str(model)), reg)
    assert [n.id for n in spec.nodes] == ["digit", "depth"]
    assert reads == [str(model)]   # the validator's read; port_shapes took the size from the same header
    load_text(_graph(str(model)), reg)
    assert reads == [str(model)]   # the file has not changed: not read again


def test_a_changed_model_file_is_read_again(reg, models, reads, tmp_path):
    model = tmp_path / "sensor.model"
    shutil.copyfile(models["qvga"], model)
    load_text(_graph(str(model)), reg)
    assert len(reads) == 1
    shutil.copyfile(models["vga"], model)   # rewritten in place: another size and mtime, the same inode
    with pytest.raises(GraphValidationError) as caught:
        load_text(_graph(str(model)), reg)
    assert "takes 640x480" in str(caught.value) and "made for 640x480 frames" in str(caught.value), caught.value
    assert len(reads) == 2   # read anew, and once
    st = model.stat()
    os.utime(model, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))   # touched: the same bytes, a later mtime
    assert normal_model.model_image_shape(str(model)) == (640, 480)
    assert len(reads) == 3
    assert normal_model.model_image_shape(model) == (640, 480) and len(reads) == 3


def test_a_bad_header_is_not_kept(models, reads, tmp_path):
    model = tmp_path / "sensor.model"
    model.write_bytes(b'{"not": "a model"}')
    for _ in range(2):
        with pytest.raises(normal_model.ModelFileError, match="not a teletouch depth model"):
            normal_model.check_model_file(model)
    assert len(reads) == 2
    shutil.copyfile(models["qvga"], model)
    assert normal_model.model_image_shape(model) == (320, 240) and len(reads) == 3
