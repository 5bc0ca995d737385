"""Every example graph shipped in examples/ validates against the installed plugins."""

from __future__ import annotations

from pathlib import Path

import pytest

from teletouch.graph import load_graph
from teletouch.registry import Registry

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.yaml"))


@pytest.fixture(scope="module")
def registry():
    reg = Registry(autoload=True, blocked=()).load()
    assert not reg.errors(), [(p.name, p.error) for p in reg.errors()]
    return reg


def test_there_are_examples():
    assert {"paper.yaml", "paper-sim.yaml"} <= {p.name for p in EXAMPLES}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_example_validates(path, registry):
    spec = load_graph(path, registry=registry)
    assert spec.nodes
