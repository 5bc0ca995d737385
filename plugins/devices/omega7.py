"""Leader: Force Dimension Omega.7 through the vendor SDK (libdhd, via the ctypes binding in ``dhd.py``).

This module also holds what every leader shares (ports of docs/ports.md, the force guard), so ``sim-omega7`` and
``hid-leader`` swap with ``omega7`` by changing only ``plugin:`` in a graph.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from teletouch import ComponentFault, Device, Kind, Params, Port, hookimpl
from teletouch.units import Newtons, Seconds

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
    ``timeout`` seconds (or stamped more than that ahead, or with a NaN stamp) gives zero force (no fault: the
    runtime's ``max_age`` turns staleness into a fault where the graph asks for it). Counts clamped and stale cycles
    for status().
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
            if self.timeout is not None and not s.is_fresh(t, self.timeout):
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
            if self.timeout is not None and not s.is_fresh(t, self.timeout):
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


# ======================================================================================================= omega7


class Omega7(Device):
    """Force Dimension Omega.7 leader through libdhd (ctypes; SDK loaded lazily)."""

    name = "omega7"
    kind = Kind.DEVICE
    default_rate = 1000.0
    requires_wall_clock = True
    inputs = dict(LEADER_INPUTS)
    outputs = dict(LEADER_OUTPUTS)

    class Params(Params):
        sdk_path: str | None = Field(None, description="Force Dimension SDK folder or libdhd file (default: "
                                                        "$FORCEDIM_SDK, then the system library path)")
        serial: int | None = Field(None, ge=0, description="open the device with this serial number")
        index: int | None = Field(None, ge=0, le=127, description="open the device at this index (default: first)")
        max_gripper_force: Newtons = Field(OMEGA7_MAX_GRIPPER_FORCE, ge=0, le=OMEGA7_MAX_GRIPPER_FORCE,
                                           description="gripper force limit (also set in the SDK)",
                                           json_schema_extra={"unit": "N"})
        max_force: Newtons = Field(OMEGA7_MAX_FORCE, ge=0, le=OMEGA7_MAX_FORCE,
                                   description="translational force limit, norm (also set in the SDK)",
                                   json_schema_extra={"unit": "N"})
        command_timeout: Seconds = Field(0.1, gt=0, le=1.0, description="a command older than this gives zero "
                                         "force (at most 1 s: a hand is never left with the force of a dead "
                                         "controller)", json_schema_extra={"unit": "s"})
        gravity_compensation: bool = Field(True, description="let the SDK hold the handle against gravity")
        brakes_on_stop: bool = Field(True, description="engage the brakes in the safe state and when inactive")
        handedness: Literal["auto", "right", "left"] = Field(
            "auto", description="auto: from the system type; a left unit's gripper axis is mirrored so the ports "
                                "keep one sign convention")
        button_index: int = Field(0, ge=0, le=15, description="which device button drives the button output")
        allow_other_devices: bool = Field(False, description="accept a sigma.7 (also has a gripper) besides the "
                                                             "omega.7")
        com_freq_interval: Seconds = Field(0.5, gt=0, description="how often to read dhdGetComFreq",
                                           json_schema_extra={"unit": "s"})

        @model_validator(mode="after")
        def _one_selector(self) -> "Omega7.Params":
            if self.serial is not None and self.index is not None:
                raise ValueError("give serial or index, not both")
            return self

    # ------------------------------------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        from . import dhd as dhdmod

        p = self.params
        self.guard = ForceGuard(p.max_gripper_force, p.max_force, p.command_timeout)
        self.dhd = None
        self.active = False
        self.lost: str | None = None
        self.sign = 1.0
        self.com_freq_hz = math.nan
        self._next_freq = 0.0
        self.timeguards = 0
        self.saturated = 0
        self.faults = 0
        self.safe_errors = 0
        self.g_sent = 0.0
        self.f_sent = np.zeros(3)
        self._lock = threading.Lock()
        lib = dhdmod.load(p.sdk_path)
        lib.open(serial=p.serial, index=p.index)
        self.dhd = lib
        stype = lib.system_type()
        allowed = {dhdmod.OMEGA7_RIGHT, dhdmod.OMEGA7_LEFT}
        if p.allow_other_devices:
            allowed |= dhdmod.WITH_GRIPPER
        if stype not in allowed:
            name = dhdmod.SYSTEM_NAMES.get(stype, f"system type {stype}")
            raise dhdmod.DhdError(f"the Force Dimension device found is a {name}, not an omega.7 "
                                  f"(system type {dhdmod.OMEGA7_RIGHT} or {dhdmod.OMEGA7_LEFT}); connect the "
                                  f"omega.7 or set allow_other_devices: true for a sigma.7")
        self.system_type = stype
        left = stype in dhdmod.LEFT_HANDED if p.handedness == "auto" else p.handedness == "left"
        self.sign = -1.0 if left else 1.0
        lib.enable_force(False)
        lib.set_max_force(p.max_force)
        lib.set_max_gripper_force(p.max_gripper_force)
        lib.set_gravity_compensation(p.gravity_compensation)
        lib.set_brakes(p.brakes_on_stop)
        self.ctx.log(f"opened {dhdmod.SYSTEM_NAMES.get(stype, stype)} through {lib.path} "
                     f"(SDK {lib.sdk_version()}); limits {p.max_force:g} N, gripper {p.max_gripper_force:g} N")

    def activate(self) -> None:
        d = self.dhd
        with self._lock:
            d.set_forces(0.0, 0.0, 0.0, 0.0)
            d.enable_force(True)
            d.set_gravity_compensation(self.params.gravity_compensation)
            d.set_brakes(False)
            self.active = True

    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        g, f, problem = self.guard.apply(t, inputs)
        if problem is not None:
            self.faults += 1
            self.safe_state()
            raise ComponentFault(problem, self.id)
        d = self.dhd
        try:
            with self._lock:
                if not self.active:            # (checked under the lock: a safe_state() from another thread
                    g, f = 0.0, self.guard.zero3   # between the guard and the write is never undone)
                x, y, z = d.position()
                gap = d.gripper_gap()
                gvel = d.gripper_velocity()
                button = d.button(self.params.button_index)
                rc = d.set_forces(float(f[0]), float(f[1]), float(f[2]), self.sign * g)
                if t >= self._next_freq:
                    self._next_freq = t + self.params.com_freq_interval
                    self.com_freq_hz = d.com_freq()
        except Exception as exc:
            self.lost = str(exc)
            self.active = False
            raise
        if rc == 1:
            self.timeguards += 1
        elif rc == 2:
            self.saturated += 1
        self.g_sent, self.f_sent = g, f
        return {"gripper_opening": gap, "gripper_velocity": self.sign * gvel,
                "position": np.array((x, y, z)), "button": button}

    def safe_state(self) -> None:
        """Zero force, then the brakes (if configured). Each call is tried on its own; never raises."""
        self.active = False
        self.g_sent, self.f_sent = 0.0, np.zeros(3)
        d = getattr(self, "dhd", None)
        if d is None:
            return
        with self._lock:
            for call in (self._zero_forces,
                         (lambda: d.set_brakes(True)) if self.params.brakes_on_stop else None):
                if call is None:
                    continue
                try:
                    call()
                except Exception:
                    self.safe_errors += 1

    def _zero_forces(self) -> None:
        """Zero force, written until the SDK takes it: a write the time guard skips (DHD_TIMEGUARD: too soon after
        the step's write) is tried again; if it never goes through, forces are disabled altogether."""
        from .dhd import DHD_TIMEGUARD

        d = self.dhd
        for _ in range(20):
            if d.set_forces(0.0, 0.0, 0.0, 0.0) != DHD_TIMEGUARD:
                return
            time.sleep(2e-4)
        self.safe_errors += 1
        d.enable_force(False)

    def deactivate(self) -> None:
        self.safe_state()
        d = getattr(self, "dhd", None)
        if d is not None:
            try:
                with self._lock:
                    d.enable_force(False)
            except Exception:
                self.safe_errors += 1

    def close(self) -> None:
        d = getattr(self, "dhd", None)
        if d is not None:
            self.dhd = None
            try:
                d.close()
            except Exception:
                pass

    def status(self) -> dict[str, Any]:
        if not hasattr(self, "guard"):
            return {}
        return {"com_freq_hz": self.com_freq_hz, "gripper_force": self.g_sent,
                "force_norm": float(np.linalg.norm(self.f_sent)), "timeguards": self.timeguards,
                "saturated": self.saturated, "clamped": self.guard.clamped, "stale_commands": self.guard.stale,
                "left_handed": self.sign < 0, "lost": self.lost or ""}


@hookimpl
def teletouch_components():
    return [Omega7]


@hookimpl
def teletouch_discover_devices():
    """Force Dimension devices the SDK can see (nothing when the SDK is not installed)."""
    try:
        from . import dhd as dhdmod

        lib = dhdmod.load(None)
        n = lib.device_count()
    except Exception:
        return []
    if not n:
        return []
    return [{"kind": "omega7", "id": f"dhd:{i}", "path": lib.path,
             "details": {"sdk": lib.sdk_version(), "plugin": "omega7", "params": {"index": i}}}
            for i in range(n)]
