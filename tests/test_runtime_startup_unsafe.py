"""A start-up that failed while a device's safe_state() raised says so on its result line: it said only which node
failed to configure (exit 4), the device that may still push on a hand only in the JSON's shutdown fault."""

import pytest

from teletouch import Component, Device, Kind, Port, hookimpl
from teletouch.runtime import EXIT_STARTUP
from teletouch.testing import make_registry, run_yaml


class Unsafe(Device):
    name = "test-unsafe-device"
    inputs = {"command": Port("float64", (), "N", "force", required=False)}
    default_rate = 100.0

    def step(self, t, inputs):
        return None

    def safe_state(self):
        raise RuntimeError("the amplifier did not answer")


class Broken(Component):
    name = "test-broken-node"
    kind = Kind.ESTIMATOR
    outputs = {"y": Port("float64", (), "N", "force")}
    default_rate = 100.0

    def configure(self):
        raise RuntimeError("no model")

    def step(self, t, inputs):
        return {"y": 0.0}


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [Unsafe, Broken]


@pytest.fixture(scope="module")
def reg():
    return make_registry(_Plugin())


GRAPH = """
clock: sim
nodes:
  - {id: dev, plugin: test-unsafe-device}
  - {id: est, plugin: test-broken-node}
"""


def test_a_failed_start_up_names_the_device_whose_safe_state_raised(reg):
    res, _ = run_yaml(GRAPH, reg, duration=1.0)
    assert res.status == "startup-failed" and res.exit_code == EXIT_STARTUP
    assert "node 'est' (test-broken-node) failed to configure" in res.message
    assert res.message.endswith("; and node 'dev' may not be in its safe state (shutdown: safe_state() raised "
                                "RuntimeError: the amplifier did not answer (test_runtime_startup_unsafe.py:20))")


def test_a_failed_start_up_with_every_device_safe_says_nothing_more(reg):
    res, _ = run_yaml(GRAPH.replace("test-unsafe-device", "mock-device"), reg, duration=1.0)
    assert res.status == "startup-failed" and "safe state" not in res.message
