"""Graph includes: a node whose plugin is swapped by an override starts from the new plugin's params alone."""

from __future__ import annotations

import pytest

from teletouch.graph import load_graph
from teletouch.testing import make_registry

from tests.test_core_graph import GOOD


@pytest.fixture(scope="module")
def reg():
    return make_registry()


def test_a_plugin_swapped_with_params_of_its_own_does_not_inherit_the_old_plugins(tmp_path, reg):
    # before: the old plugin's params were merged into the new one's whenever the override gave `params:`, so
    # swapping mock-gain {gain: 3} for mock-burn {burn: 1ms} failed with "unknown param 'gain' for mock-burn"
    (tmp_path / "base.yaml").write_text(GOOD)
    (tmp_path / "swap.yaml").write_text(
        "include: base.yaml\nnodes:\n  - {id: gain, plugin: mock-burn, params: {burn: 1ms}}\n")
    node = load_graph(tmp_path / "swap.yaml", registry=reg).node("gain")
    assert node.plugin == "mock-burn" and node.params_obj.burn == pytest.approx(1e-3)


def test_the_same_plugin_named_again_still_merges_its_params_key_by_key(tmp_path, reg):
    (tmp_path / "base.yaml").write_text(GOOD.replace("params: {signal: step, amplitude: 2.0}",
                                                     "params: {signal: step, amplitude: 2.0, offset: 0.5}"))
    (tmp_path / "over.yaml").write_text(
        "include: base.yaml\nnodes:\n  - {id: source, plugin: mock-sensor, params: {amplitude: 4}}\n")
    p = load_graph(tmp_path / "over.yaml", registry=reg).node("source").params_obj
    assert (p.signal, p.amplitude, p.offset) == ("step", 4.0, 0.5)
