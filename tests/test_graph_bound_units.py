"""A parameter refused for a bound names the bound's unit (SI): "less than or equal to 8 N", not "to 8" (a person who
typed 800 may have meant mN, or another unit)."""

from __future__ import annotations

import pytest

from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph

SIM = "examples/paper-sim.yaml"


@pytest.mark.parametrize("item, bound", [("leader.max_gripper_force=800", "less than or equal to 8 N"),
                                         ("leader.max_gripper_force=-1", "greater than or equal to 0 N"),
                                         ("gripper.max_effort=-2", "greater than 0 N")])
def test_a_bound_names_its_unit(item, bound):
    with pytest.raises(GraphValidationError) as err:
        load_graph(SIM, sets=[item])
    assert f"Input should be {bound}" in str(err.value), str(err.value)
    assert f"{bound} N" not in str(err.value)   # once


def test_a_bound_of_a_field_without_a_unit_is_as_pydantic_says():
    with pytest.raises(GraphValidationError) as err:
        load_graph("examples/paper.yaml", sets=["leader.index=200"])   # omega7's device index: a count
    msg = str(err.value)
    assert msg.rstrip().endswith("Input should be less than or equal to 127"), msg
