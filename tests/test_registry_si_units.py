"""The SI check of declared units parses the unit: products, quotients and powers of SI symbols pass, any other symbol
is refused, naming it and the SI unit meant. Before, only the symbols of the unit table (mm, deg, ms, ...) were refused:
'deg/s', 'm/ms', 'rpm' and a misspelt 'newton' loaded, for ports and parameters alike, although
docs/writing-a-plugin.md says an interface is SI."""

from __future__ import annotations

import pytest
from pydantic import Field

from teletouch import Component, Kind, Params, PluginError, Port
from teletouch.registry import check_component
from teletouch.testing import make_registry


def _port_cls(unit: str) -> type[Component]:
    class Spin(Component):
        name = "acme-spin"
        kind = Kind.SENSOR
        outputs = {"speed": Port("float64", (), unit, "wheel speed")}

        def step(self, t, inputs):
            return None

    return Spin


def _param_cls(unit: str) -> type[Component]:
    class Spin(Component):
        name = "acme-spin"
        kind = Kind.SENSOR
        outputs = {"speed": Port("float64", (), "rad/s", "wheel speed")}

        class Params(Params):
            limit: float = Field(1.0, json_schema_extra={"unit": unit})

        def step(self, t, inputs):
            return None

    return Spin


REFUSED = [   # unit, the SI unit to declare, the symbol named
    ("deg/s", "rad/s", "deg"),
    ("m/ms", "m/s", "ms"),
    ("rpm", "rad/s", "rpm"),
    ("newton", "N", "newton"),
    ("N*m/rpm", "N*m/(rad/s)", "rpm"),
    ("mN/s", "N/s", "mN"),
]


@pytest.mark.parametrize(("unit", "si", "symbol"), REFUSED)
def test_a_port_in_a_unit_that_is_not_si_is_refused_naming_the_si_unit(unit, si, symbol):
    with pytest.raises(PluginError) as ei:
        check_component(_port_cls(unit))
    msg = str(ei.value)
    assert f"Spin.outputs['speed'] unit '{unit}' is not SI: '{symbol}' is not an SI unit symbol" in msg, msg
    assert msg.endswith(f"declare '{si}'"), msg


@pytest.mark.parametrize(("unit", "si", "symbol"), REFUSED)
def test_a_parameter_in_a_unit_that_is_not_si_is_refused_naming_the_si_unit(unit, si, symbol):
    with pytest.raises(PluginError) as ei:
        check_component(_param_cls(unit))
    msg = str(ei.value)
    assert f"Spin.Params.limit unit '{unit}' is not SI: '{symbol}'" in msg and f"declare '{si}'" in msg, msg


def test_a_symbol_with_no_obvious_si_unit_is_refused_naming_the_si_symbols():
    with pytest.raises(PluginError) as ei:
        check_component(_port_cls("counts/s"))
    msg = str(ei.value)
    assert "'counts' is not an SI unit symbol" in msg and "'' for a plain number (a count" in msg, msg
    assert "m, kg, s, A, K" in msg, msg


@pytest.mark.parametrize("unit", ["N m", "m2", "m^", "(m/s", "m**2"])
def test_what_is_not_a_unit_expression_is_refused_saying_how_to_write_one(unit):
    with pytest.raises(PluginError, match=r"is not a unit .*joined by '\*' and '/', with powers as '\^2'"):
        check_component(_port_cls(unit))


@pytest.mark.parametrize("unit", ["", "1", "any", "m", "kg", "N*s/m", "m^2", "m^-1", "1/s", "m/(N*s)", "N*m*s/rad",
                                  "rad/s", "N/A", "bit/s", "px/m", "N/m^3", "V", "Ohm", "K"])
def test_si_units_and_their_products_quotients_and_powers_pass(unit):
    check_component(_port_cls(unit))
    if unit != "any":   # ('any' is for ports only)
        check_component(_param_cls(unit))


def test_the_table_s_units_keep_their_message():
    with pytest.raises(PluginError, match=r"unit 'mm' is not SI: declare 'm'"):
        check_component(_port_cls("mm"))


def test_every_unit_a_built_in_component_declares_passes():
    reg = make_registry(builtins=True)
    assert not reg.errors(), [(p.name, p.error) for p in reg.errors()]
    units = set()
    for info in reg.components.values():
        check_component(info.cls)   # raises for a unit the check refuses
        units |= {p.unit for side in (info.cls.inputs, info.cls.outputs) for p in side.values()}
        units |= {prm.get("unit") or "" for prm in info.cls.describe()["params"]}
    assert len(reg.components) >= 25 and {"N*m*s/rad", "m/(N*s)", "bit/s", "N/A", "m^2"} <= units, sorted(units)
