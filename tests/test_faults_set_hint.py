"""The --set that a refused nested --set's error suggests pastes into a shell as it is written, also with a value
that holds a single quote (it was put in single quotes unescaped: the shell read two strings and a dangling quote)."""

from __future__ import annotations

import shlex
import sys

import pytest
from pydantic import field_validator

from teletouch import Component, GraphValidationError, Kind, Params, Port, hookimpl
from teletouch.testing import load_text, make_registry

GRAPH = """
clock: sim
duration: 1
nodes:
  - {id: n, plugin: s16-labels, rate: 100, params: {label: {a: x}}}
"""


class Labels(Component):
    """``label``: one key at most (a mapping of more is refused); ``mode``: a name, or a mapping with a ``type``."""

    name = "s16-labels"
    kind = Kind.SENSOR
    outputs = {"value": Port("float64", (), "", "nothing")}
    default_rate = 100.0

    class Params(Params):
        label: dict[str, str] = {}
        mode: str | dict[str, str] = "it's"

        @field_validator("label")
        @classmethod
        def _one(cls, v):
            if len(v) > 1:
                raise ValueError("one key at most")
            return v

        @field_validator("mode")
        @classmethod
        def _typed(cls, v):
            if isinstance(v, dict) and "type" not in v:
                raise ValueError("a mode mapping needs 'type'")
            return v

    def step(self, t, inputs):
        return {"value": 0.0}


@hookimpl
def teletouch_components():
    return [Labels]


def _suggested(sets: list[str], lead: str) -> str:
    """The one argument the error's suggested ``--set ...`` (its last words, after ``lead``) gives to a shell."""
    with pytest.raises(GraphValidationError) as caught:
        load_text(GRAPH, make_registry(sys.modules[__name__]), sets=sets)
    text = str(caught.value)
    assert lead in text, text
    words = shlex.split(text.rsplit(lead, 1)[1])   # raises ValueError on an unbalanced quote
    assert len(words) == 1, (text, words)
    return words[0]


def test_give_the_whole_value_quotes_a_value_with_a_single_quote():
    arg = _suggested(["n.label.b=it's"], "give the whole value: --set ")
    assert arg == "n.label={b: it's}"
    spec = load_text(GRAPH, make_registry(sys.modules[__name__]), sets=[arg])   # what it says works
    assert spec.nodes[0].params_obj.label == {"b": "it's"}


def test_give_its_type_quotes_a_name_with_a_single_quote():
    arg = _suggested(["n.mode.x=y"], "give its type with it: --set ")
    assert arg == "n.mode.type=it's"
    spec = load_text(GRAPH, make_registry(sys.modules[__name__]), sets=[arg, "n.mode.x=y"])
    assert spec.nodes[0].params_obj.mode == {"type": "it's", "x": "y"}
