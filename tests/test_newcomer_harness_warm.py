"""Testing a component's warm() needed `h.comp.warm()`, undocumented: `Harness.warm()` calls it (and refuses a
device's, which the runtime never calls); docs/writing-a-plugin.md's testing section says so, and how to test a
`port_shapes`."""

from __future__ import annotations

from pathlib import Path

import pytest

from teletouch import Component, Device, Port
from teletouch.testing import Harness

REPO = Path(__file__).resolve().parents[1]


class Rehearses(Component):
    """Rehearses the last step's work in warm(), without changing its output."""

    name = "s15-rehearses"
    default_rate = 60.0
    inputs = {"x": Port("float64", (), "N")}
    outputs = {"y": Port("float64", (), "N")}

    def configure(self):
        self.last = None
        self.warms = 0

    def step(self, t, inputs):
        self.last = inputs.value("x")
        return {"y": 2.0 * self.last}

    def warm(self):
        self.warms += 1
        return 2.0 * self.last   # thrown away by the runtime


class Arm(Device):
    name = "s15-arm"
    default_rate = 1000.0
    inputs = {"command": Port("float64", (), "m")}

    def step(self, t, inputs):
        return None

    def warm(self):
        raise AssertionError("the runtime never warms a device")

    def safe_state(self):
        pass


def test_warm_calls_the_component_s_warm():
    with Harness(Rehearses) as h:
        h.step(0.0, x=1.5)
        assert h.warm() is None          # the runtime throws the result away
        assert h.comp.warms == 1
        assert h.step(1 / 60)["y"] == 3.0


def test_a_warm_that_raises_raises():
    with Harness(Rehearses) as h:
        with pytest.raises(TypeError):   # before any step: `2.0 * None`
            h.warm()


def test_a_device_s_warm_is_refused():
    with Harness(Arm) as h:
        with pytest.raises(TypeError, match=r"^Arm is a device: the runtime never calls a device's warm\(\)"):
            h.warm()


def test_the_page_says_how():
    text = (REPO / "docs" / "writing-a-plugin.md").read_text()
    section = text[text.index("## 4. Test it"):text.index("## 5. A device")]
    assert "h.warm()" in section and "port_shapes" in section, section
