"""A quantity or a number typed with an underscore ('1_0', '1_000.5') is refused as a typo, by every parser of
quantities and of bounded numbers: Python's float() and int() read '1_0' as 10."""

from __future__ import annotations

import argparse

import pytest

from teletouch.argtypes import int_at_least, number
from teletouch.units import Meters, parse_quantity

UNDERSCORED = ["1_0", "1_000.5", "1e1_0", " 1_0 ", "1_0mm", "0.00_6 m"]


@pytest.mark.parametrize("text", UNDERSCORED)
def test_parse_quantity_refuses_an_underscore_as_a_typo(text):
    # before: "unknown unit '_0' in '1_0'" (an underscore taken for the start of a unit), which says nothing of why
    with pytest.raises(ValueError) as err:
        parse_quantity(text, "m")
    msg = str(err.value)
    assert msg.startswith(f"expected a number in m such as '6mm' or '0.006', got {text!r}"), msg
    assert "underscore" in msg and "unknown unit" not in msg, msg


def test_a_field_with_units_refuses_an_underscore():
    from pydantic import BaseModel, ValidationError

    class P(BaseModel):
        opening: Meters = 0.0

    with pytest.raises(ValidationError, match=r"got '9_0mm' \(an underscore"):
        P(opening="9_0mm")
    assert P(opening="90mm").opening == pytest.approx(0.09)


@pytest.mark.parametrize("parse", [number(float, "a positive number", lo=0.0, lo_open=True),
                                   number(int, "an integer >= 1", lo=1), int_at_least(1)])
@pytest.mark.parametrize("text", ["1_0", "1_000", " 1_0 "])
def test_a_bounded_number_refuses_an_underscore(parse, text):
    # before: 10 and 1000 (float('1_0') == 10.0, int('1_000') == 1000)
    with pytest.raises(argparse.ArgumentTypeError) as err:
        parse(text)
    msg = str(err.value)
    assert msg.startswith(f"expected {parse.__name__}, got {text!r}") and "underscore" in msg, msg


def test_numbers_without_an_underscore_still_parse():
    assert number(float, "x", lo=0.0)("10") == 10.0 and number(float, "x")(" 2.5e-3 ") == 2.5e-3
    assert int_at_least(1)("10") == 10 and int_at_least(1)(" 7") == 7
    assert parse_quantity("10", "m") == 10.0 and parse_quantity("6 mm", "m") == pytest.approx(0.006)


@pytest.mark.parametrize("value", ["1_0", "0.00_6", "1_000"])
def test_a_graph_number_with_an_underscore_is_refused_naming_file_and_line(value):
    # before: YAML 1.1 read rate: 1_0 as 10 and 0.00_6 as 0.006, before any unit parser saw the text
    from teletouch.errors import GraphError
    from teletouch.yamlio import load_yaml_text

    with pytest.raises(GraphError) as err:
        load_yaml_text(f"name: g\nnodes:\n  - {{id: a, rate: {value}}}\n", "g.yaml")
    msg = str(err.value)
    assert "g.yaml" in msg and ":3" in msg and "underscore" in msg and repr(value) in msg, msg
    doc = load_yaml_text("nodes:\n  - {id: a, rate: 10, gain: '1_0', width: 6mm}\n", "g.yaml")
    assert doc["nodes"][0]["rate"] == 10 and doc["nodes"][0]["gain"] == "1_0"   # a quoted string is text


def test_progress_interval_refuses_an_underscore():
    # before: float('1_0') made --progress-interval 1_0 a 10 s live view
    from teletouch.cli import _positive_seconds

    with pytest.raises(argparse.ArgumentTypeError, match="underscore"):
        _positive_seconds("1_0")
    assert _positive_seconds("0.5") == 0.5 and _positive_seconds("500ms") == pytest.approx(0.5)
    for bad in ("0", "-1", "nan", "inf"):
        with pytest.raises(argparse.ArgumentTypeError, match="positive, finite number of seconds"):
            _positive_seconds(bad)


def test_a_sample_exactly_max_age_old_is_fresh_whatever_the_time():
    """docs/graphs.md: only a stamp more than max_age old is stale. With float graph times a sample exactly max_age
    old (a 100 Hz source gone silent, max_age 0.1) was fresh at 0.59 s and stale at 1.59 s ("0.100 s old (limit
    0.1 s)" as a fault)."""
    from teletouch.component import Sample

    for t0 in (0.49, 1.49, 7.3, 1234.56):
        assert Sample(0.0, t0).is_fresh(t0 + 0.1, 0.1), t0
        assert not Sample(0.0, t0).is_fresh(t0 + 0.1 + 1e-6, 0.1), t0
        assert Sample(0.0, t0 + 0.1).is_fresh(t0, 0.1), t0   # ahead by exactly max_age: still taken
