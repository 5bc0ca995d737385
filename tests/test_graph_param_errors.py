"""Every problem of a node's params at once: a quantity with a unit that does not parse was checked before pydantic's
own validation and ended it, so the unknown params beside it were found only after it was fixed (the lab-setup audit:
`bitrate: 500k` hid `dxl: 1` and `interfce: socketcan`)."""

from __future__ import annotations

import pytest

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph_text

GRAPH = """\
nodes:
  - id: source
    plugin: mock-sensor
    rate: 100
    params: {{{params}}}
"""


def _errors(params: str) -> str:
    with pytest.raises(GraphValidationError) as exc:
        load_graph_text(GRAPH.format(params=params), "g.yaml")
    return str(exc.value)


def test_a_bad_unit_and_unknown_params_are_all_reported():
    msg = _errors("frequency: 5 kHzz, amplitde: 2, colour: red")
    assert "3 error(s)" in msg, msg
    assert "param 'frequency' = '5 kHzz': unknown unit" in msg, msg
    assert "unknown param 'amplitde' for mock-sensor (did you mean 'amplitude'?)" in msg, msg
    assert "unknown param 'colour' for mock-sensor" in msg, msg
    assert msg.count("g.yaml:5") == 3, msg


def test_unknown_params_alone_are_reported_once():
    msg = _errors("amplitde: 2")
    assert "1 error(s)" in msg and msg.count("unknown param 'amplitde'") == 1, msg
