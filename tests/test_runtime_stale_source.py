"""A stale input's fault says what the device feeding it reports (its status()'s ``problem``): a follower that stopped
answering faults only at its own read_timeout, so the consumer's `max_age` fault came first and said nothing of why."""

from __future__ import annotations

from teletouch import Device, Port, hookimpl
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry


class Fading(Device):
    """Publishes until t = 0.2 s, then nothing; says why in status()."""
    name = "t-fading"
    outputs = {"value": Port("float64", (), "")}

    def configure(self):
        self.quiet = False

    def step(self, t, inputs):
        if t >= 0.2:
            self.quiet = True
            return None
        return {"value": 1.0}

    def safe_state(self):
        pass

    def status(self):
        return {"problem": "no valid state for 0.120 s (read_timeout 0.5 s): port /dev/ttyUSB0, 12 failed reads"
                if self.quiet else None}


class Silent(Fading):
    name = "t-silent"

    def status(self):
        return {"value": 1.0}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [Fading, Silent]


def _run(plugin: str):
    spec = load_text(f"""
clock: sim
nodes:
  - {{id: gripper, plugin: {plugin}, rate: 100}}
  - id: controller
    plugin: mock-gain
    rate: 100
    inputs: {{x: {{from: gripper.value, max_age: 0.05}}}}
""", make_registry(_Plugin()))
    return Runtime(spec, log=lambda m: None).run(1.0)


def test_a_stale_input_names_what_its_device_reports():
    res = _run("t-fading")
    f = res.faults[0]
    assert (f.node, f.kind) == ("controller", "stale"), res.faults
    assert "input 'x' from gripper.value is" in f.message and "(limit 0.05 s)" in f.message, f.message
    assert f.message.endswith("; node 'gripper' reports: no valid state for 0.120 s (read_timeout 0.5 s): port "
                              "/dev/ttyUSB0, 12 failed reads"), f.message


def test_a_device_without_a_problem_adds_nothing():
    res = _run("t-silent")
    assert res.faults[0].message.endswith("(limit 0.05 s)"), res.faults[0].message
