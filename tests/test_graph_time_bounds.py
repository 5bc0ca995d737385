"""A wire's max_age and faults.watchdog are bounded: `100` meant as milliseconds is refused, not taken as 100 s."""

from __future__ import annotations

import pytest

from teletouch.errors import GraphValidationError
from teletouch.graph import MAX_AGE_LIMIT, load_graph_text

WIRED = """\
nodes:
  - {{id: source, plugin: mock-sensor, rate: 100}}
  - id: gain
    plugin: mock-gain
    rate: 100
    inputs:
      x: {{from: source.value, max_age: {age}}}
"""


@pytest.mark.parametrize("bad", ["100", "61", "1e308", "inf", "61000ms", "0", "-1", "nan"])
def test_a_wire_max_age_beyond_a_minute_or_not_positive_is_refused_with_its_line(bad):
    with pytest.raises(GraphValidationError) as exc:
        load_graph_text(WIRED.format(age=bad), "g.yaml")
    msg = str(exc.value)
    assert "node 'gain': input 'x': max_age:" in msg and "g.yaml:7" in msg, msg
    if bad not in ("nan", "inf"):   # parse_quantity refuses these itself
        assert f"at most {MAX_AGE_LIMIT:g} s" in msg and "100ms" in msg, msg


@pytest.mark.parametrize("good, seconds", [("60", 60.0), ("100ms", 0.1), ("0.05", 0.05)])
def test_a_wire_max_age_within_a_minute_is_taken_in_seconds(good, seconds):
    spec = load_graph_text(WIRED.format(age=good), "g.yaml")
    gain = next(n for n in spec.nodes if n.id == "gain")
    assert gain.inputs["x"].max_age == pytest.approx(seconds)


@pytest.mark.parametrize("bad", ["100", "61", "1e9"])
def test_a_watchdog_beyond_a_minute_is_refused(bad):
    with pytest.raises(GraphValidationError, match=r"faults.watchdog: expected at most 60 s .*100ms"):
        load_graph_text(f"faults: {{watchdog: {bad}}}\nnodes:\n  - {{id: d, plugin: mock-device}}\n", "<t>")


@pytest.mark.parametrize("good, seconds", [("60", 60.0), ("0", 0.0), ("100ms", 0.1)])
def test_a_watchdog_up_to_a_minute_or_off_is_taken(good, seconds):
    spec = load_graph_text(f"faults: {{watchdog: {good}}}\nnodes:\n  - {{id: d, plugin: mock-device}}\n", "<t>")
    assert spec.faults.watchdog == pytest.approx(seconds)
