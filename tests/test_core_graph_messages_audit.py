"""Graph messages an outside audit (a third-party plugin written from the docs) found misleading: the "unwire it in the
override" hint for a typo written in the override itself, a unit mismatch "'1' -> 'N'" that did not say '1' is a port
that declares no unit, pydantic's "unable to parse string as a number" for a unit given to a parameter that takes
none, a unit error that hid the node's other parameter errors, and `rate: null` in an override blamed on the included
file."""

from __future__ import annotations

import textwrap

import pytest
from pydantic import Field

from teletouch import Component, Kind, Params, Port, hookimpl
from teletouch.errors import GraphValidationError
from teletouch.graph import load_graph, load_graph_text
from teletouch.testing import make_registry


class _Plain(Component):
    """A sensor whose output declares no unit (dimensionless), and parameters with and without units."""

    name = "audit-plain"
    kind = Kind.SENSOR
    default_rate = 100.0
    outputs = {"force": Port("float64", ())}

    class Params(Params):
        amplitude: float = Field(1.0, description="amplitude in N")
        count: int = Field(1, description="how many")
        latency: float = Field(0.01, ge=0, le=1.0, description="latency", json_schema_extra={"unit": "s"})
        offset: float = Field(0.0, ge=0, description="offset", json_schema_extra={"unit": "N"})

    def step(self, t, inputs):
        return {"force": 1.0}


class _Newton(Component):
    """A consumer of a force in N."""

    name = "audit-newton"
    kind = Kind.CONTROLLER
    default_rate = 100.0
    inputs = {"force": Port("float64", (), "N", "a force")}
    outputs = {}

    def step(self, t, inputs):
        return None


class _NoRate(Component):
    name = "audit-norate"
    kind = Kind.SENSOR
    default_rate = None
    outputs = {"x": Port("float64", (), "m", "x")}

    def step(self, t, inputs):
        return {"x": 0.0}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [_Plain, _Newton, _NoRate]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugin())


def _errors(reg, text=None, path=None):
    with pytest.raises(GraphValidationError) as ei:
        if path is not None:
            load_graph(path, registry=reg)
        else:
            load_graph_text(textwrap.dedent(text), "g.yaml", registry=reg)
    return [str(e) for e in ei.value.errors]


BASE = textwrap.dedent("""\
    clock: sim
    duration: 1
    nodes:
      - id: source
        plugin: mock-sensor
        rate: 100
      - id: gain
        plugin: mock-gain
        rate: 100
        inputs: {x: source.value}
    """)


# --- 2. the "unwire it in the override" hint only for a wire that the override did not write ------------------------
def test_a_misspelt_input_in_an_override_gets_no_unwire_hint(tmp_path, reg):
    # before: "... mock-gain has no input 'xx'; inputs: x; the wire comes from over.yaml: unwire it in the override
    # with 'inputs: {xx: null}'": the plugin was named in base.yaml, so the wire was taken for an inherited one
    (tmp_path / "base.yaml").write_text(BASE)
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - id: gain\n    inputs: {xx: source.value}\n")
    errs = _errors(reg, path=tmp_path / "over.yaml")
    assert len(errs) == 1, errs
    assert errs[0].endswith("over.yaml:4: node 'gain': mock-gain has no input 'xx' (did you mean 'x'?); inputs: x"), \
        errs


def test_the_hint_stays_for_the_wire_an_override_kept_and_not_for_one_written_after_it(tmp_path, reg):
    # mid.yaml swaps the plugin (mock-sensor has no input 'x': the wire kept from base.yaml is the one to unwire);
    # top.yaml, which includes it, misspells a wire of its own: that one is a typo in top.yaml, no hint
    (tmp_path / "base.yaml").write_text(BASE)
    (tmp_path / "mid.yaml").write_text("include: base.yaml\nnodes:\n  - {id: gain, plugin: mock-sensor}\n")
    (tmp_path / "top.yaml").write_text("include: mid.yaml\nnodes:\n  - id: gain\n    inputs: {xy: source.value}\n")
    errs = _errors(reg, path=tmp_path / "top.yaml")
    kept = [e for e in errs if "no input 'x';" in e]
    typo = [e for e in errs if "no input 'xy'" in e]
    assert len(kept) == 1 and "base.yaml:10:" in kept[0], errs
    assert kept[0].endswith("; the wire comes from " + str(tmp_path / "base.yaml")
                            + ": unwire it in the override with 'inputs: {x: null}'"), kept
    assert len(typo) == 1 and "top.yaml:4:" in typo[0] and "the wire comes from" not in typo[0], typo


def test_a_wire_the_swapping_override_writes_itself_gets_no_hint(tmp_path, reg):
    (tmp_path / "base.yaml").write_text(BASE)
    (tmp_path / "swap.yaml").write_text("include: base.yaml\nnodes:\n  - id: gain\n    plugin: mock-burn\n"
                                        "    inputs: {xx: source.value}\n")
    errs = _errors(reg, path=tmp_path / "swap.yaml")
    assert len(errs) == 1 and "swap.yaml:5:" in errs[0] and "mock-burn has no input 'xx'" in errs[0], errs
    assert "the wire comes from" not in errs[0], errs


# --- 3. a unit mismatch with '1' says that the port declares no unit -------------------------------------------------
def test_a_unit_mismatch_with_a_port_without_unit_says_what_1_means(reg):
    # before: "unit mismatch: '1' -> 'N'", nothing saying that '1' is the unit of a port that declares none
    errs = _errors(reg, """\
        clock: sim
        nodes:
          - {id: s, plugin: audit-plain}
          - {id: c, plugin: audit-newton, inputs: {force: s.force}}
        """)
    assert errs == ["g.yaml:4: node 'c': input 'force' <- s.force: unit mismatch: '1' -> 'N' ('1' is dimensionless: "
                    "audit-plain's output 'force' declares no unit)"], errs


def test_a_unit_mismatch_between_two_units_reads_as_before(reg):
    errs = _errors(reg, """\
        clock: sim
        nodes:
          - {id: s, plugin: audit-norate, rate: 10}
          - {id: c, plugin: audit-newton, inputs: {force: s.x}}
        """)
    assert errs == ["g.yaml:4: node 'c': input 'force' <- s.x: unit mismatch: 'm' -> 'N'"], errs


# --- 4. a unit given to a parameter that takes none -----------------------------------------------------------------
@pytest.mark.parametrize("param, value", [("amplitude", "2N"), ("count", "3mm")])
def test_a_quantity_given_to_a_param_without_unit_says_it_takes_a_plain_number(reg, param, value):
    # before: "Input should be a valid number, unable to parse string as a number" (an int: "... as an integer")
    errs = _errors(reg, f"""\
        clock: sim
        nodes:
          - {{id: s, plugin: audit-plain, params: {{{param}: {value}}}}}
        """)
    assert len(errs) == 1, errs
    assert errs[0].startswith(f"g.yaml:3: node 's': param '{param}' = {value!r}: this param takes no unit "
                              f"(audit-plain declares none for it): expected a plain number"), errs
    assert "unable to parse" not in errs[0], errs
    if param == "amplitude":
        assert errs[0].endswith("(its description: 'amplitude in N')"), errs


def test_a_string_that_is_no_quantity_keeps_pydantics_message(reg):
    errs = _errors(reg, "clock: sim\nnodes:\n  - {id: s, plugin: audit-plain, params: {amplitude: lots}}\n")
    assert errs == ["g.yaml:3: node 's': param 'amplitude' = 'lots': Input should be a valid number, unable to parse "
                    "string as a number"], errs


# --- 5. a unit error does not hide the node's other parameter errors ------------------------------------------------
def test_a_unit_error_and_a_range_error_on_one_node_are_both_reported(reg):
    # before: only the unit error ('2mm' is in m): the check of the units ended pydantic's validation
    errs = _errors(reg, "clock: sim\nnodes:\n  - {id: s, plugin: audit-plain, params: {latency: -1, offset: 2mm}}\n")
    assert sorted(errs) == sorted([
        "g.yaml:3: node 's': param 'offset' = '2mm': '2mm' is in m, expected a quantity in N",
        "g.yaml:3: node 's': param 'latency' = -1: Input should be greater than or equal to 0 s",
    ]), errs


def test_beside_a_unit_error_each_problem_is_reported_once(reg):
    errs = _errors(reg, "clock: sim\nnodes:\n  - id: s\n    plugin: audit-plain\n"
                        "    params: {offset: 2mm, latency: 5mm, bogus: 1, amplitude: 2N, count: 1.5}\n")
    assert len(errs) == 5, errs
    assert sum("unknown param 'bogus'" in e for e in errs) == 1, errs
    assert sum("param 'offset' = '2mm'" in e for e in errs) == 1, errs
    assert sum("param 'latency' = '5mm'" in e for e in errs) == 1, errs
    assert sum("param 'amplitude' = '2N': this param takes no unit" in e for e in errs) == 1, errs
    assert sum("param 'count' = 1.5" in e for e in errs) == 1, errs


# --- 6. `rate: null` in an override ---------------------------------------------------------------------------------
def test_rate_null_in_an_override_is_blamed_on_the_override(tmp_path, reg):
    # before: "base.yaml:3: node 'n': missing 'rate' (Hz); audit-norate has no default rate", the included node's line
    (tmp_path / "base.yaml").write_text("clock: sim\nnodes:\n  - id: n\n    plugin: audit-norate\n    rate: 60\n")
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - id: n\n    rate: null\n")
    errs = _errors(reg, path=tmp_path / "over.yaml")
    assert errs == [f"{tmp_path / 'over.yaml'}:4: node 'n': missing 'rate' (Hz); audit-norate has no default rate "
                    f"('rate: null' asks for the plugin's default rate)"], errs


def test_rate_null_in_an_override_takes_the_plugins_default_rate(tmp_path, reg):
    (tmp_path / "base.yaml").write_text(BASE)
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - {id: gain, rate: null}\n")
    spec = load_graph(tmp_path / "over.yaml", registry=reg)
    assert spec.node("gain").rate == 100.0   # mock-gain's default_rate, not the included file's 100 by chance
    (tmp_path / "base2.yaml").write_text(BASE.replace("rate: 100\n    inputs", "rate: 7\n    inputs"))
    (tmp_path / "over2.yaml").write_text("include: base2.yaml\nnodes:\n  - {id: gain, rate: null}\n")
    assert load_graph(tmp_path / "base2.yaml", registry=reg).node("gain").rate == 7.0
    assert load_graph(tmp_path / "over2.yaml", registry=reg).node("gain").rate == 100.0


def test_a_missing_rate_without_null_reads_as_before(reg):
    errs = _errors(reg, "clock: sim\nnodes:\n  - {id: n, plugin: audit-norate}\n")
    assert errs == ["g.yaml:3: node 'n': missing 'rate' (Hz); audit-norate has no default rate"], errs
