"""A third-party teletouch plugin: a first-order low-pass filter for a force signal."""

import math

from pydantic import Field

from teletouch import Component, Kind, Params, Port, Sample, hookimpl


class LowPass(Component):
    """First-order low-pass filter: y' = (x - y) / tau, with tau = 1 / (2 pi cutoff)."""

    name = "example-lowpass"
    kind = Kind.ESTIMATOR
    default_rate = 1000.0
    inputs = {"x": Port("float64", (), "N", "raw force")}
    outputs = {"y": Port("float64", (), "N", "filtered force")}

    class Params(Params):
        cutoff: float = Field(5.0, gt=0, description="cut-off frequency", json_schema_extra={"unit": "Hz"})

    def configure(self):
        self.y = None
        self.last_t = None

    def step(self, t, inputs):
        x = inputs.value("x")
        if x is None or not math.isfinite(x):
            return None                      # nothing (valid) to filter yet
        if self.y is None:
            self.y = x
        else:
            tau = 1.0 / (2.0 * math.pi * self.params.cutoff)
            self.y += (x - self.y) * (1.0 - math.exp(-(t - self.last_t) / tau))
        self.last_t = t
        return {"y": Sample(self.y, inputs["x"].stamp)}   # as old as the newest measurement in it


@hookimpl
def teletouch_components():
    return [LowPass]
