"""Harness.history keeps every step's outputs as Samples: Harness.run returned plain values and h.samples held only the
last step's, so a plugin author could not test the stamps a sensor gives over a run (a capture latency, a stamp that
must not go backwards)."""

from __future__ import annotations

import pytest
from pydantic import Field

from teletouch import Component, Kind, Params, Port, Sample
from teletouch.testing import Harness


class Latent(Component):
    """A force stamped ``latency`` before the step; nothing on odd steps."""

    name = "acme-latent"
    kind = Kind.SENSOR
    default_rate = 100.0
    outputs = {"force": Port("float64", (), "N", "sensed force")}

    class Params(Params):
        latency: float = Field(0.01, json_schema_extra={"unit": "s"})

    def configure(self):
        self.n = 0

    def step(self, t, inputs):
        self.n += 1
        if self.n % 2 == 0:
            return None
        return {"force": Sample(float(self.n), t - self.params.latency)}


def test_every_step_of_a_run_keeps_its_stamps():
    with Harness(Latent, {"latency": "10ms"}) as h:
        out = h.run(0.05)                               # t = 0, 0.01, ..., 0.05
        assert [t for t, _ in out] == [t for t, _ in h.history]
        stamped = [(t, s["force"]) for t, s in h.history if s]
        assert [t for t, _ in stamped] == pytest.approx([0.0, 0.02, 0.04])
        assert all(s.stamp == pytest.approx(t - 0.01) for t, s in stamped)
        assert [s.value for _, s in stamped] == [1.0, 3.0, 5.0]
        assert [s for _, s in h.history if not s] == [{}, {}, {}]   # the steps that returned None


def test_steps_by_hand_are_kept_too_and_clear_forgets():
    with Harness(Latent) as h:
        h.step(1.0)
        h.step(1.5)
        h.run(1.52)
        assert [t for t, _ in h.history] == pytest.approx([1.0, 1.5, 1.51, 1.52])
        assert h.history[0][1]["force"].stamp == pytest.approx(0.99) and h.history[0][1] is not h.history[2][1]
        h.history.clear()
        h.step(2.0)
        assert len(h.history) == 1 and h.history[-1][1] == h.samples
