"""Graph files: loading, includes/overrides, --set, and every bad-input case with its error (file and line)."""

from __future__ import annotations

import json
import math
import os
import textwrap
from pathlib import Path

import pytest

from teletouch.errors import GraphValidationError
from teletouch.graph import graph_json_schema, load_graph, load_graph_text
from teletouch.testing import make_registry

GOOD = textwrap.dedent("""\
    name: demo
    clock: sim
    duration: 1
    nodes:
      - id: source
        plugin: mock-sensor
        rate: 100
        params: {signal: step, amplitude: 2.0}
      - id: gain
        plugin: mock-gain
        rate: 100 Hz
        params: {gain: 3}
        inputs: {x: source.value}
      - id: dev
        plugin: mock-device
        rate: 1kHz
        inputs:
          command: {from: gain.y, max_age: 50ms}
    """)


@pytest.fixture(scope="module")
def reg():
    return make_registry()


def errors_of(text, reg, **kw):
    with pytest.raises(GraphValidationError) as ei:
        load_graph_text(text, "g.yaml", registry=reg, **kw)
    return [str(e) for e in ei.value.errors]


def test_good_graph_parses_units_and_wires(reg):
    spec = load_graph_text(GOOD, "g.yaml", registry=reg)
    assert [n.id for n in spec.order()] == ["source", "gain", "dev"]
    dev = spec.node("dev")
    assert dev.rate == 1000.0
    assert dev.inputs["command"].max_age == pytest.approx(0.05)
    assert spec.node("gain").params_obj.gain == 3.0
    assert spec.clock == "sim" and spec.duration == 1.0


def test_yaml_syntax_error_names_line(reg):
    errs = errors_of("nodes:\n  - id: a\n    plugin: [mock-sensor\n", reg)
    assert len(errs) == 1 and errs[0].startswith("g.yaml:") and "YAML syntax error" in errs[0]


def test_unknown_plugin_suggests(reg):
    errs = errors_of(GOOD.replace("plugin: mock-gain", "plugin: mock-gian"), reg)
    assert any("g.yaml:10:" in e and "unknown plugin 'mock-gian'" in e and "did you mean 'mock-gain'" in e
               for e in errs), errs


def test_unknown_port_and_unknown_source(reg):
    errs = errors_of(GOOD.replace("inputs: {x: source.value}", "inputs: {xx: source.value}"), reg)
    assert any("has no input 'xx'" in e and "did you mean 'x'" in e for e in errs), errs
    assert any("required input 'x'" in e for e in errs), errs
    errs = errors_of(GOOD.replace("inputs: {x: source.value}", "inputs: {x: source.valeu}"), reg)
    assert any("g.yaml:13:" in e and "has no output 'valeu'" in e and "did you mean 'value'" in e for e in errs)
    errs = errors_of(GOOD.replace("inputs: {x: source.value}", "inputs: {x: sorce.value}"), reg)
    assert any("unknown node 'sorce'" in e and "did you mean 'source'" in e for e in errs)
    errs = errors_of(GOOD.replace("inputs: {x: source.value}", "inputs: {x: source}"), reg)
    assert any("expected 'node.port'" in e for e in errs)


def test_type_and_unit_mismatch():
    from teletouch import Component, Kind, Port, hookimpl

    class Meters(Component):
        name = "meters"
        kind = Kind.SENSOR
        outputs = {"d": Port("float64", (), "m"), "img": Port("uint8", (None, None, 3), "")}

        def step(self, t, inputs):
            return None

    class Newtons(Component):
        name = "newtons"
        kind = Kind.ESTIMATOR
        inputs = {"f": Port("float64", (), "N"), "img": Port("float64", (None, None, 3), "", required=False)}

        def step(self, t, inputs):
            return None

    class P:
        @hookimpl
        def teletouch_components(self):
            return [Meters, Newtons]

    reg = make_registry(P())
    text = ("nodes:\n  - {id: a, plugin: meters, rate: 10}\n"
            "  - {id: b, plugin: newtons, rate: 10, inputs: {f: a.d, img: a.img}}\n")
    errs = errors_of(text, reg)
    assert any("g.yaml:3:" in e and "unit mismatch: 'm' -> 'N'" in e for e in errs), errs
    assert any("type mismatch: uint8 -> float64" in e for e in errs), errs


def test_bad_param_names_field_value_and_expectation(reg):
    errs = errors_of(GOOD.replace("{gain: 3}", "{gain: three}"), reg)
    assert any("g.yaml:12:" in e and "param 'gain' = 'three'" in e and "number" in e for e in errs), errs
    errs = errors_of(GOOD.replace("{gain: 3}", "{gian: 3}"), reg)
    assert any("unknown param 'gian'" in e and "did you mean 'gain'" in e for e in errs), errs
    errs = errors_of(GOOD.replace("signal: step", "signal: square"), reg)
    assert any("param 'signal' = 'square'" in e and "'sine'" in e for e in errs), errs


def test_rate_must_be_positive_and_ids_unique(reg):
    errs = errors_of(GOOD.replace("rate: 1kHz", "rate: 0"), reg)
    assert any("g.yaml:16:" in e and "rate" in e and "positive" in e for e in errs), errs
    errs = errors_of(GOOD.replace("rate: 1kHz", "rate: fast"), reg)
    assert any("rate" in e and "'fast'" in e for e in errs), errs
    errs = errors_of(GOOD.replace("id: dev", "id: gain"), reg)
    assert any("g.yaml:14:" in e and "duplicate node id 'gain'" in e and "g.yaml:9" in e for e in errs), errs


def test_rate_above_one_megahertz_is_refused(reg):
    # the simulated clock counts whole nanoseconds: at 2 GHz the ticks repeated graph times (0, 0, 1, 2, 2, ... ns),
    # and `rate: 1e9` (a typo for 1 kHz) was a run of 10^9 steps per graph second that never seemed to end
    for bad, shown in (("1e9", "'1e9'"), ("2000000", "2000000"), ("2000kHz", "'2000kHz'")):
        errs = errors_of(GOOD.replace("rate: 1kHz", f"rate: {bad}"), reg)
        assert any(e.startswith("g.yaml:16: node 'dev': rate: at most 1000000 Hz") and e.endswith(f"got {shown}")
                   for e in errs), errs
    assert load_graph_text(GOOD.replace("rate: 1kHz", "rate: 1000kHz"), "g.yaml", registry=reg).node("dev").rate == 1e6


def test_rate_below_a_millihertz_is_refused(reg):
    # `validate` said OK for rate: 1e-300, then `run` died with OverflowError (an infinite period on the simulated
    # clock; 1e-12 Hz on the wall clock: past the platform's time_t)
    for bad, shown in (("1e-300", "'1e-300'"), ("1e-12", "'1e-12'"), ("0.0005", "0.0005")):
        errs = errors_of(GOOD.replace("rate: 1kHz", f"rate: {bad}"), reg)
        assert any(e.startswith("g.yaml:16: node 'dev': rate: at least 0.001 Hz (one step per 1000 s)")
                   and e.endswith(f"got {shown}") for e in errs), errs
    assert load_graph_text(GOOD.replace("rate: 1kHz", "rate: 0.001"), "g.yaml", registry=reg).node("dev").rate == 1e-3


def test_harness_and_default_rate_take_the_graphs_rate_limits():
    from teletouch.errors import PluginError
    from teletouch.mock import MockGain
    from teletouch.registry import check_component
    from teletouch.testing import Harness

    with pytest.raises(ValueError, match=r"Harness\(MockGain\): rate: at least 0.001 Hz .*got 1e-09"):
        Harness(MockGain, rate=1e-9)

    class Slow(MockGain):
        name = "slow-gain"
        default_rate = 1e-6

    with pytest.raises(PluginError, match=r"Slow.default_rate must be None or a number of Hz from 0.001 to 1e\+06"):
        check_component(Slow)


def test_duplicate_yaml_key_and_unknown_keys(reg):
    errs = errors_of(GOOD.replace("    rate: 100\n", "    rate: 100\n    rate: 200\n", 1), reg)
    assert any("duplicate key 'rate'" in e for e in errs), errs
    errs = errors_of("nodez: []\n", reg)
    assert any("unknown top-level key 'nodez'" in e and "did you mean 'nodes'" in e for e in errs)
    assert any("missing 'nodes'" in e for e in errs)
    errs = errors_of(GOOD.replace("    rate: 100\n", "    rat: 100\n", 1), reg)
    assert any("unknown key 'rat'" in e and "did you mean 'rate'" in e for e in errs), errs


def test_bad_clock_duration_and_faults(reg):
    errs = errors_of(GOOD.replace("clock: sim", "clock: fast").replace("duration: 1", "duration: -1"), reg)
    assert any("g.yaml:2:" in e and "clock" in e for e in errs)
    assert any("g.yaml:3:" in e and "duration" in e for e in errs)
    errs = errors_of("faults: {on_fault: explode}\n" + GOOD, reg)
    assert any("faults.on_fault" in e and "'explode'" in e for e in errs)


def test_validation_reports_all_errors_at_once(reg):
    bad = GOOD.replace("mock-gain", "mock-gian").replace("rate: 1kHz", "rate: -5").replace(
        "signal: step", "signal: 7")
    errs = errors_of(bad, reg)
    assert len(errs) == 3, errs   # one per mistake, each with its line and node
    assert any(e.startswith("g.yaml:8: node 'source': param 'signal' = 7") for e in errs), errs
    assert any(e.startswith("g.yaml:10: node 'gain': unknown plugin 'mock-gian'") for e in errs), errs
    assert any(e.startswith("g.yaml:16: node 'dev': rate: must be a positive number of Hz") for e in errs), errs


def test_include_override_and_set(tmp_path, reg):
    (tmp_path / "base.yaml").write_text(GOOD)
    (tmp_path / "over.yaml").write_text(textwrap.dedent("""\
        include: base.yaml
        nodes:
          - id: gain
            params: {gain: 5}
          - id: extra
            plugin: noop
            rate: 10
        """))
    spec = load_graph(tmp_path / "over.yaml", registry=reg)
    assert spec.node("gain").params_obj.gain == 5.0
    assert spec.node("gain").inputs["x"].node == "source"  # inherited
    assert [n.id for n in spec.nodes] == ["source", "gain", "dev", "extra"]
    spec = load_graph(tmp_path / "over.yaml", registry=reg, sets=["gain.gain=7", "dev.rate=500",
                                                                  "source.plugin=mock-sensor"])
    assert spec.node("gain").params_obj.gain == 7.0 and spec.node("dev").rate == 500.0
    # swapping a plugin drops the old plugin's params
    (tmp_path / "same.yaml").write_text("include: base.yaml\nnodes:\n  - {id: gain, plugin: mock-gain}\n")
    assert load_graph(tmp_path / "same.yaml", registry=reg).node("gain").params_obj.gain == 3.0
    (tmp_path / "swap.yaml").write_text("include: base.yaml\nnodes:\n  - {id: gain, plugin: mock-sensor}\n")
    with pytest.raises(GraphValidationError) as ei:
        load_graph(tmp_path / "swap.yaml", registry=reg)
    msg = str(ei.value)
    assert "mock-sensor has no input 'x'" in msg and "unknown param" not in msg
    # errors in an included file name that file
    (tmp_path / "bad.yaml").write_text(GOOD.replace("rate: 1kHz", "rate: 0"))
    (tmp_path / "inc_bad.yaml").write_text("include: bad.yaml\n")
    with pytest.raises(GraphValidationError) as ei:
        load_graph(tmp_path / "inc_bad.yaml", registry=reg)
    assert "bad.yaml:16:" in str(ei.value)


def test_an_override_that_swaps_a_plugin_unwires_inputs_with_null(tmp_path, reg):
    # before: the override kept the old plugin's wires and 'x: null' was refused ("expected 'node.port', got None"),
    # so swapping a node for a plugin with other inputs could not be written as an override at all
    (tmp_path / "base.yaml").write_text(GOOD)
    (tmp_path / "swap.yaml").write_text("include: base.yaml\nnodes:\n  - {id: gain, plugin: mock-sensor}\n")
    with pytest.raises(GraphValidationError) as ei:
        load_graph(tmp_path / "swap.yaml", registry=reg)
    assert "the wire comes from " in str(ei.value) and "unwire it in the override with 'inputs: {x: null}'" in str(
        ei.value)
    (tmp_path / "swap.yaml").write_text("include: base.yaml\nnodes:\n  - {id: gain, plugin: mock-sensor, "
                                        "inputs: {x: null}}\n  - {id: dev, inputs: {command: gain.value}}\n")
    spec = load_graph(tmp_path / "swap.yaml", registry=reg)
    assert spec.node("gain").plugin == "mock-sensor" and spec.node("gain").inputs == {}
    # --set changed the plugin: the hint says to write an override
    with pytest.raises(GraphValidationError) as ei:
        load_graph(tmp_path / "base.yaml", registry=reg, sets=["gain.plugin=mock-sensor"])
    assert "--set gain.plugin=mock-sensor changed the plugin" in str(ei.value)
    # null outside an override is still an error, saying where it works
    with pytest.raises(GraphValidationError) as ei:
        load_graph_text(GOOD.replace("x: source.value", "x: null"), registry=reg)
    assert "null unwires an input only in an override" in str(ei.value)


def test_include_errors(tmp_path, reg):
    (tmp_path / "a.yaml").write_text("include: b.yaml\nnodes: []\n")
    (tmp_path / "b.yaml").write_text("include: a.yaml\nnodes: []\n")
    with pytest.raises(GraphValidationError, match="include cycle"):
        load_graph(tmp_path / "a.yaml", registry=reg)
    (tmp_path / "c.yaml").write_text("include: missing.yaml\nnodes: []\n")
    with pytest.raises(GraphValidationError, match=r"c.yaml:1: included file 'missing.yaml' not found"):
        load_graph(tmp_path / "c.yaml", registry=reg)
    with pytest.raises(GraphValidationError, match="file not found"):
        load_graph(tmp_path / "nope.yaml", registry=reg)


def test_set_errors(tmp_path, reg):
    (tmp_path / "g.yaml").write_text(GOOD)
    with pytest.raises(GraphValidationError, match="no node 'gian'.*did you mean 'gain'"):
        load_graph(tmp_path / "g.yaml", registry=reg, sets=["gian.gain=1"])
    with pytest.raises(GraphValidationError, match="expected NODE.FIELD=VALUE"):
        load_graph(tmp_path / "g.yaml", registry=reg, sets=["gain"])
    with pytest.raises(GraphValidationError, match=r"--set gain.gain=x: node 'gain': param 'gain' = 'x'"):
        load_graph(tmp_path / "g.yaml", registry=reg, sets=["gain.gain=x"])


def test_wall_only_plugin_refused_on_sim_clock():
    from teletouch import Device, hookimpl

    class Hw(Device):
        name = "hw"
        requires_wall_clock = True

        def step(self, t, inputs):
            return None

        def safe_state(self):
            pass

    class P:
        @hookimpl
        def teletouch_components(self):
            return [Hw]

    reg = make_registry(P())
    errs = errors_of("clock: sim\nduration: 1\nnodes:\n  - {id: h, plugin: hw, rate: 10}\n", reg)
    assert any("cannot run on the simulated clock" in e for e in errs)
    load_graph_text("clock: wall\nnodes:\n  - {id: h, plugin: hw, rate: 10}\n", "g.yaml", registry=reg)


def test_json_schema_covers_plugins(reg):
    schema = graph_json_schema(reg)
    json.dumps(schema)
    node = schema["properties"]["nodes"]["items"]
    assert "mock-gain" in node["properties"]["plugin"]["enum"]
    thens = {c["if"]["properties"]["plugin"]["const"]: c["then"] for c in node["allOf"]}
    gain_params = thens["mock-gain"]["properties"]["params"]
    assert gain_params["properties"]["gain"]["default"] == 1.0
    assert gain_params["additionalProperties"] is False


def test_params_with_units_accept_quantities(reg):
    spec = load_graph_text(GOOD.replace("{signal: step, amplitude: 2.0}",
                                        "{signal: step, amplitude: 2.0, frequency: 2kHz, step_time: 20 ms}"),
                           "g.yaml", registry=reg)
    p = spec.node("source").params_obj
    assert p.frequency == 2000.0 and p.step_time == pytest.approx(0.02)
    errs = errors_of(GOOD.replace("{signal: step, amplitude: 2.0}", "{signal: step, frequency: 3 kg}"), reg)
    assert any("g.yaml:8:" in e and "param 'frequency' = '3 kg'" in e and "expected a quantity in Hz" in e
               for e in errs), errs


# ------------------------------------------------------------------------------------------------ bad input (audit)
def test_graph_file_that_is_not_text_or_recursive(tmp_path, reg):
    p = tmp_path / "bin.yaml"
    p.write_bytes(b"\xff\xfe\x00nodes")
    with pytest.raises(GraphValidationError, match="not UTF-8 text"):
        load_graph(p, registry=reg)
    errs = errors_of("a: &x [*x]\nnodes: []\n", reg)
    assert errs == ["g.yaml:1: a YAML alias refers to a collection that contains it (a recursive anchor)"]


def test_numbers_too_large_or_infinite_are_refused(reg):
    big = "1" + "0" * 400
    errs = errors_of(GOOD.replace("rate: 100 Hz", f"rate: {big}"), reg)
    assert any("g.yaml:11" in e and "too large" in e for e in errs), errs
    for dur in (".inf", "1e400"):
        errs = errors_of(GOOD.replace("duration: 1", f"duration: {dur}"), reg)
        assert any(e.startswith("g.yaml:3: duration:") for e in errs), errs
    # a bad --duration is the command line's, not the file's
    assert errors_of(GOOD, reg, duration=-1.0) == ["--duration: duration: must be positive, got -1.0"]


def test_model_level_param_checks_name_their_field_and_every_bad_unit_is_reported():
    text = textwrap.dedent("""\
        clock: sim
        nodes:
          - id: hand
            plugin: mock-sensor
            rate: 1kHz
          - id: ctl
            plugin: position-force
            rate: 1kHz
            params:
              opening_min: 50mm
              opening_max: 10mm
          - id: ctl2
            plugin: position-force
            rate: 1kHz
            params:
              max_force_rate: 1 parsec
              reduction_margin: 5 N
              gain_adaptation_power: 2 mW
            inputs: {leader_opening: hand.value, force: hand.value}
        """)
    errs = errors_of(text, make_registry("teletouch.plugins.controllers.position_force"))
    assert "g.yaml:10: node 'ctl': params of position-force: opening_min (0.05 m) must be below opening_max " \
           "(0.01 m)" in errs
    assert not any("'?'" in e for e in errs)
    assert any(e.startswith("g.yaml:16: node 'ctl2': param 'max_force_rate'") and "unknown unit 'parsec'" in e
               for e in errs), errs
    assert any(e.startswith("g.yaml:17: node 'ctl2': param 'reduction_margin'") and "expected a quantity in J" in e
               for e in errs), errs
    assert not any("gain_adaptation_power" in e for e in errs)   # 2 mW is a power: accepted


def test_units_of_every_declared_parameter_are_known():
    from teletouch.registry import default_registry
    from teletouch.units import parse_quantity

    checked = set()
    for row in default_registry().describe():
        for prm in row.get("params", []):
            unit = prm.get("unit")
            if unit and unit not in ("", "1"):
                assert parse_quantity(f"1 {unit}", unit) == 1.0, (row["name"], prm["name"], unit)
                checked.add(unit)
    assert {"m", "s", "N", "Hz", "m/s", "N/m", "N*s/m"} <= checked, checked   # the built-ins' units were seen


def test_a_malformed_quantity_gets_an_example_in_its_own_unit():
    from teletouch.units import _EXAMPLES, parse_quantity

    with pytest.raises(ValueError, match=r"expected a number in px/m such as '17.15px/mm', got 'abc'"):
        parse_quantity("abc", "px/m")
    with pytest.raises(ValueError, match=r"expected a number in N such as '5N' or '5', got 'five'"):
        parse_quantity("five", "N")
    for unit, examples in _EXAMPLES.items():   # every example given is itself accepted in its unit
        for text in examples.replace(" or ", ",").split(","):
            assert math.isfinite(parse_quantity(text.strip().strip("'"), unit)), (unit, text)


def test_set_and_remove_errors_say_what_is_supported(tmp_path, reg):
    g = tmp_path / "g.yaml"
    g.write_text(GOOD)
    with pytest.raises(GraphValidationError, match=r"expected NODE.params.NAME=VALUE"):
        load_graph(g, registry=reg, sets=["source.params=5"])
    spec = load_graph(g, registry=reg, sets=["source.priority=5", "source.params.amplitude=4"])
    assert next(n for n in spec.nodes if n.id == "source").priority == 5
    with pytest.raises(GraphValidationError) as ei:
        load_graph(g, registry=reg, sets=["source.frequency.x=5"])
    assert all(str(e).startswith("--set source.frequency.x=5") for e in ei.value.errors), ei.value.errors
    over = tmp_path / "over.yaml"
    over.write_text("include: g.yaml\nnodes:\n  - {id: gian, remove: true}\n")
    with pytest.raises(GraphValidationError, match=r"no included graph has a node 'gian' \(did you mean 'gain'\?\)"):
        load_graph(over, registry=reg)
    over.write_text("include: g.yaml\nnodes:\n  - {id: gain, remove: 'no'}\n")
    with pytest.raises(GraphValidationError, match="remove: expected true or false, got 'no'"):
        load_graph(over, registry=reg)
    errs = errors_of(GOOD.replace("  - id: dev\n", "  - id: dev\n    remove: true\n"), reg)
    assert any("remove: true only removes a node of an included graph" in e for e in errs), errs
    assert errors_of("nodes: []\n", reg) == ["g.yaml:1: 'nodes' is empty: a graph needs at least one node"]
    assert any(e.startswith("g.yaml:1: name: expected text") for e in errors_of(GOOD.replace("name: demo",
                                                                                            "name: [1, 2]"), reg))


def test_cli_reports_file_errors_without_a_traceback(tmp_path, capsys):
    from teletouch.cli import main

    blocker = tmp_path / "afile"
    blocker.write_text("x")
    assert main(["schema", "-o", str(blocker / "schema.json")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("teletouch: error: Not a directory:") and "afile/schema.json" in err
    assert "Traceback" not in err


def test_json_schema_accepts_the_documented_unwiring_of_an_input(reg):
    """docs/graphs.md: ``inputs: {port: null}`` in an override unwires an input, and validate accepts it; the
    exported schema allowed only a wire string or {from, max_age} there, so an editor flagged documented syntax."""
    node = graph_json_schema(reg)["properties"]["nodes"]["items"]
    kinds = [alt.get("type") for alt in node["properties"]["inputs"]["additionalProperties"]["anyOf"]]
    assert sorted(kinds) == ["null", "object", "string"]


def test_the_exported_schema_accepts_every_example_graph_with_its_units():
    """`teletouch schema` is for editors: it typed every parameter with a unit as a number, so the examples' own
    quantities ('20mm', '20ms', '2Hz') were errors there. Checked with a JSON Schema validator (draft 2020-12)."""
    import jsonschema
    import yaml

    from teletouch.registry import default_registry

    schema = graph_json_schema(default_registry())
    validator = jsonschema.Draft202012Validator(schema)
    examples = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.yaml"))
    assert len(examples) >= 6
    checked = 0
    for path in examples:
        errors = [f"{path.name}: {'/'.join(map(str, e.absolute_path))}: {e.message}"
                  for e in validator.iter_errors(yaml.safe_load(path.read_text()))]
        assert errors == [], errors
        checked += 1
    assert checked == len(examples)
    quantity = {"nodes": [{"id": "g", "plugin": "sim-gripper", "params": {"max_opening": "80mm", "max_speed": 0.05}}]}
    assert not list(validator.iter_errors(quantity))
    wrong = {"nodes": [{"id": "g", "plugin": "sim-gripper", "params": {"max_opening": [1]}}]}
    assert list(validator.iter_errors(wrong))   # still typed: a list is no quantity


# ------------------------------------------------------------------------------------------------ bad input (review)
def test_an_explicit_yaml_tag_on_a_value_it_cannot_read_names_the_line(reg):
    # before: `!!int abc` raised a bare ValueError, `!!bool maybe` a KeyError, `!!timestamp x` an AttributeError
    for tag, value in (("!!int", "abc"), ("!!float", "''"), ("!!bool", "maybe"), ("!!timestamp", "soon")):
        errs = errors_of(GOOD.replace("{gain: 3}", f"{{gain: {tag} {value}}}"), reg)
        assert errs == [f"g.yaml:12: YAML error: '{value.strip(chr(39))}' is not a valid {tag}"], errs


def test_yaml_merge_keys_are_overridden_by_the_mappings_own_keys(reg):
    # YAML: a mapping's own keys override those of `<<: *anchor`; before, each override was a "duplicate key"
    text = GOOD + ("  - &extra {id: extra, plugin: mock-gain, rate: 10, inputs: {x: source.value}}\n"
                   "  - <<: *extra\n    id: extra2\n    params: {<<: [{gain: 4}, {gain: 5}]}\n")
    spec = load_graph_text(text, "g.yaml", registry=reg)
    assert spec.node("extra").rate == spec.node("extra2").rate == 10.0
    assert spec.node("extra2").params_obj.gain == 4.0   # the first of a list of merged mappings wins
    errs = errors_of(text.replace("    id: extra2\n", "    id: extra2\n    id: extra3\n"), reg)
    assert errs == ["g.yaml:22: duplicate key 'id' (first at line 21)"], errs   # a mapping's own keys, twice


def test_yaml_merge_key_order_does_not_depend_on_the_pyyaml_version(reg):
    # PyYAML 6.0.4 changed flatten_mapping's order: the last mapping of a merged list won (the first must, as the
    # YAML merge key type says); within a merged mapping its own keys still beat what it merged itself
    from teletouch.yamlio import load_yaml_text
    doc = load_yaml_text("a: &a {<<: {k: 1, j: 1}, k: 2}\nb: {<<: [{k: 4, m: 1}, *a, {m: 3, n: 5}], j: 9}\n", "m.yaml")
    assert dict(doc["b"]) == {"k": 4, "m": 1, "j": 9, "n": 5}
    assert dict(doc["a"]) == {"k": 2, "j": 1}
    for bad, what in (("[1, 2]", "int"), ("[[1]]", "seq"), ("7", "int")):
        errs = errors_of(GOOD.replace("params: {gain: 3}", f"params: {{<<: {bad}}}"), reg)
        assert len(errs) == 1 and errs[0].startswith("g.yaml:12: a merge key '<<' takes a mapping or a list of "
                                                     "mappings, not a "), errs


def test_a_graph_file_that_is_a_bare_value_names_the_file(tmp_path, reg):
    # before: "<graph>: a graph file must be a mapping ..." without the file's name
    assert errors_of("42\n", reg) == ["g.yaml:1: a graph file must be a mapping with a 'nodes' list"]
    (tmp_path / "scalar.yaml").write_text("hello\n")
    (tmp_path / "main.yaml").write_text("include: scalar.yaml\n")
    with pytest.raises(GraphValidationError) as ei:
        load_graph(tmp_path / "main.yaml", registry=reg)
    assert [str(e) for e in ei.value.errors] == [f"{tmp_path / 'scalar.yaml'}:1: a graph file must be a mapping with "
                                                 f"a 'nodes' list"]


def test_include_in_a_graph_given_as_text_is_refused(reg):
    # before: load_graph_text (run_yaml, the tests' helpers) left `include:` out without a word
    errs = errors_of("include: base.yaml\n" + GOOD, reg)
    assert errs == ["g.yaml:1: 'include' needs a graph file to resolve it from: load the file (load_graph, "
                    "`teletouch run FILE`) instead of its text"], errs


def test_include_of_nothing_or_of_a_folder(tmp_path, reg):
    (tmp_path / "g.yaml").write_text("include: []\n" + GOOD)   # before: AssertionError
    assert [n.id for n in load_graph(tmp_path / "g.yaml", registry=reg).nodes] == ["source", "gain", "dev"]
    (tmp_path / "g.yaml").write_text("include: .\n" + GOOD)    # before: named the folder, not the include's line
    with pytest.raises(GraphValidationError, match=r"g.yaml:1: included file '.' is a folder"):
        load_graph(tmp_path / "g.yaml", registry=reg)


def test_override_node_ids_that_are_not_text_are_reported_not_a_traceback(tmp_path, reg):
    # before: TypeError: unhashable type: 'LList' / 'LDict' while merging the node lists
    (tmp_path / "base.yaml").write_text(GOOD)
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - {id: [gain], plugin: noop, rate: 1}\n")
    with pytest.raises(GraphValidationError, match=r"over.yaml:3: node id \['gain'\]: use letters"):
        load_graph(tmp_path / "over.yaml", registry=reg)
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - {id: {a: 1}, remove: true}\n")
    with pytest.raises(GraphValidationError, match=r"over.yaml:3: node '\{'a': 1\}': remove: true, but no included"):
        load_graph(tmp_path / "over.yaml", registry=reg)
    (tmp_path / "b1.yaml").write_text("nodes: [{id: [a], plugin: noop, rate: 1}]\n")
    (tmp_path / "over.yaml").write_text("include: b1.yaml\nnodes: [{id: a, plugin: noop, rate: 1}]\n")
    with pytest.raises(GraphValidationError, match=r"b1.yaml:1: node id \['a'\]"):
        load_graph(tmp_path / "over.yaml", registry=reg)


def test_override_that_removes_a_node_and_adds_one_with_its_id(tmp_path, reg):
    # before: AttributeError ('NoneType' object has no attribute 'get'): the second entry merged into the removed one
    (tmp_path / "base.yaml").write_text(GOOD)
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - {id: dev, remove: true}\n"
                                        "  - {id: dev, plugin: noop, rate: 5}\n")
    spec = load_graph(tmp_path / "over.yaml", registry=reg)
    assert [(n.id, n.plugin, n.rate, n.inputs) for n in spec.nodes][-1] == ("dev", "noop", 5.0, {})


def test_duplicate_node_id_in_an_override_file_is_reported(tmp_path, reg):
    # before: the second entry was merged into the first without a word (rate 7 won), as if it were an override
    (tmp_path / "base.yaml").write_text(GOOD)
    for ids in (("gain", "gain"), ("n1", "n1")):
        (tmp_path / "over.yaml").write_text(f"include: base.yaml\nnodes:\n  - {{id: {ids[0]}, plugin: noop, rate: 5}}\n"
                                            f"  - {{id: {ids[1]}, plugin: noop, rate: 7}}\n")
        with pytest.raises(GraphValidationError) as ei:
            load_graph(tmp_path / "over.yaml", registry=reg)
        assert [str(e) for e in ei.value.errors] == [
            f"{tmp_path / 'over.yaml'}:4: duplicate node id '{ids[0]}' (first defined at {tmp_path / 'over.yaml'}:3)"]


def test_unwiring_an_input_the_included_node_does_not_have_is_an_error(tmp_path, reg):
    # before: `inputs: {xx: null}` (a typo for x) was dropped without a word, and the wire meant stayed
    (tmp_path / "base.yaml").write_text(GOOD)
    (tmp_path / "over.yaml").write_text("include: base.yaml\nnodes:\n  - id: gain\n    inputs: {xx: null}\n")
    with pytest.raises(GraphValidationError) as ei:
        load_graph(tmp_path / "over.yaml", registry=reg)
    assert [str(e) for e in ei.value.errors] == [
        f"{tmp_path / 'over.yaml'}:4: node 'gain': input 'xx': null unwires an input of the included node, and it has "
        f"no input 'xx' wired (did you mean 'x'?); wired: x"]


def test_a_boolean_for_a_number_parameter_is_refused(reg):
    # YAML reads `yes`/`on` as true, and pydantic took it as 1.0: `gain: yes` ran with gain 1, `step_time: on` at 1 s
    for text in ("{gain: yes}", "{gain: on}", "{gain: true}"):
        errs = errors_of(GOOD.replace("{gain: 3}", text), reg)
        assert errs == ["g.yaml:12: node 'gain': param 'gain' = True: expected a number, got a boolean (YAML reads "
                        "yes, no, on and off as true and false)"], errs
    errs = errors_of(GOOD.replace("amplitude: 2.0", "step_time: on"), reg)
    assert errs == ["g.yaml:8: node 'source': param 'step_time' = True: expected a number in s, got True"], errs


def test_params_built_in_python_refuse_a_boolean_for_a_number():
    # the check is the Params base class's, so it holds beside a graph file too (Harness, Component(params=...))
    from pydantic import ValidationError

    from teletouch.component import Params

    class P(Params):
        gain: float = 1.0
        count: int = 0
        flag: bool = False

    for field in ("gain", "count"):
        with pytest.raises(ValidationError, match=rf"{field}: expected a number, got a boolean"):
            P(**{field: True})
    assert P(flag=True, gain=2).flag is True


def test_unit_typed_fields_refuse_booleans():
    from pydantic import TypeAdapter, ValidationError

    from teletouch.units import Hertz, Meters, Seconds

    for typ in (Meters, Seconds, Hertz):
        with pytest.raises(ValidationError, match="expected a number in"):
            TypeAdapter(typ).validate_python(True)
        assert TypeAdapter(typ).validate_python(2) == 2.0


def test_a_graph_file_is_read_up_to_a_size_and_an_alias_bomb_is_refused(tmp_path, reg):
    """`include: /dev/zero` read until the kernel killed the process for its memory; nine levels of aliases of
    aliases expanded to 43 million values (a SystemError, or the same kill). Both are errors naming the file now; a
    graph from a pipe still reads."""
    g = tmp_path / "g.yaml"
    g.write_text("include: /dev/zero\nnodes: []\n")
    with pytest.raises(GraphValidationError, match=r"/dev/zero: larger than 1 MiB: a graph file is a few KB"):
        load_graph(g, registry=reg)
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 9)]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(lines) + "\nnodes: []\n")
    with pytest.raises(GraphValidationError, match=r"bomb.yaml:\d+: the YAML expands to more than 200000 values"):
        load_graph(bomb, registry=reg)
    r, w = os.pipe()
    os.write(w, GOOD.encode())
    os.close(w)
    try:
        assert load_graph(f"/dev/fd/{r}", registry=reg).node("dev").rate == 1000.0
    finally:
        os.close(r)


def test_top_level_x_keys_hold_anchors_and_are_ignored(reg):
    """docs/graphs.md says anchors and merge keys work, but a top-level `defaults: &d {...}` was an unknown key: an
    anchor could live only inside a node. Keys starting with `x-` are ignored now (as in Compose files)."""
    text = ("x-gain: &g {gain: 7}\n" + GOOD.replace("{gain: 3}", "{<<: *g}"))
    spec = load_graph_text(text, "g.yaml", registry=reg)
    assert spec.node("gain").params_obj.gain == 7.0
    errs = errors_of("defaults: &g {gain: 7}\n" + GOOD, reg)
    assert any("unknown top-level key 'defaults'" in e and "a key starting with 'x-'" in e for e in errs), errs
