"""Leader: Force Dimension Omega.7 through the vendor SDK (libdhd, via the ctypes binding in ``dhd.py``).

This module also holds what every leader shares (ports of docs/ports.md, the force guard), so ``sim-omega7`` and
``hid-leader`` swap with ``omega7`` by changing only ``plugin:`` in a graph.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from teletouch import Port

#: Device limits of the Omega.7 (CHAI3D's device table; hardware notes).
OMEGA7_MAX_FORCE = 12.0  # N, translation
OMEGA7_MAX_GRIPPER_FORCE = 8.0  # N
OMEGA7_WORKSPACE_RADIUS = 0.075  # m
OMEGA7_GRIPPER_RANGE = 0.025  # m, about 25 mm of grasping range

LEADER_INPUTS: dict[str, Port] = {
    "gripper_force": Port("float64", (), "N", "commanded gripper force; positive pushes the operator's fingers "
                                              "apart (resists closing)", required=False),
    "force": Port("float64", (3,), "N", "translational force on the handle", required=False),
}
LEADER_OUTPUTS: dict[str, Port] = {
    "gripper_opening": Port("float64", (), "m", "gripper gap"),
    "gripper_velocity": Port("float64", (), "m/s", "d(gap)/dt, positive opening"),
    "position": Port("float64", (3,), "m", "end-effector position"),
    "button": Port("bool", (), "", "user button"),
}


class ForceGuard:
    """Turns the latest commands into forces that are always finite and within limits.

    ``apply(t, inputs)`` returns (gripper force N, force (3,) N, problem) where ``problem`` is None, or a message when
    a command was NaN/inf or malformed (then both forces are zero and the caller must fault). A command older than
    ``timeout`` seconds gives zero force (no fault: the runtime's ``max_age`` turns staleness into a fault where the
    graph asks for it). Counts clamped and stale cycles for status().
    """

    def __init__(self, max_gripper_force: float, max_force: float, timeout: float | None):
        self.max_g = float(max_gripper_force)
        self.max_f = float(max_force)
        self.timeout = timeout
        self.clamped = 0
        self.stale = 0
        self.invalid = 0
        self.zero3 = np.zeros(3)

    def apply(self, t: float, inputs: Any) -> tuple[float, np.ndarray, str | None]:
        g = 0.0
        f = self.zero3
        s = inputs.get("gripper_force")
        if s is not None:
            if self.timeout is not None and t - s.stamp > self.timeout:
                self.stale += 1
            else:
                try:
                    g = float(s.value)
                except (TypeError, ValueError):
                    self.invalid += 1
                    return 0.0, self.zero3, f"gripper_force command is not a number: {s.value!r}"
                if not math.isfinite(g):
                    self.invalid += 1
                    return 0.0, self.zero3, f"gripper_force command is {g} (not finite): force set to zero"
                if g > self.max_g:
                    g = self.max_g
                    self.clamped += 1
                elif g < -self.max_g:
                    g = -self.max_g
                    self.clamped += 1
        s = inputs.get("force") if "force" in inputs else None
        if s is not None:
            if self.timeout is not None and t - s.stamp > self.timeout:
                self.stale += 1
            else:
                try:
                    f = np.asarray(s.value, dtype=float).reshape(3)
                except (TypeError, ValueError):
                    self.invalid += 1
                    return 0.0, self.zero3, f"force command is not a 3-vector: {s.value!r}"
                if not np.all(np.isfinite(f)):
                    self.invalid += 1
                    return 0.0, self.zero3, f"force command {f.tolist()} is not finite: force set to zero"
                n = float(np.linalg.norm(f))
                if n > self.max_f:
                    f = f * (self.max_f / n)
                    self.clamped += 1
        return g, f, None
