"""Leader: Force Dimension Omega.7 through the vendor SDK (libdhd, via the ctypes binding in ``dhd.py``).

This module also holds what every leader shares (ports of docs/ports.md, the force guard), so ``sim-omega7`` and
``hid-leader`` swap with ``omega7`` by changing only ``plugin:`` in a graph.
"""

from __future__ import annotations

import math
import threading
import time
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import ComponentFault, Device, Kind, Params, Port, hookimpl
from teletouch.paths import looked_at
from teletouch.units import Newtons, Seconds

#: Device limits of the Omega.7 (CHAI3D's device table; hardware notes).
OMEGA7_MAX_FORCE = 12.0  # N, translation
OMEGA7_MAX_GRIPPER_FORCE = 8.0  # N
OMEGA7_WORKSPACE_RADIUS = 0.075  # m
OMEGA7_GRIPPER_RANGE = 0.025  # m, about 25 mm of grasping range
#: The device firmware's watchdog (dhdSetWatchdog, SDK 3.3.2+) counts in units of 125 us, at most 255 of them.
WATCHDOG_UNITS_PER_S = 8000
WATCHDOG_MAX_UNITS = 255  # 31.875 ms
#: after a watchdog trip, forces come back faded in over this time (s): no step on the operator's hand
WATCHDOG_FADE_IN = 0.05
#: a command that was stale (the guard rendered zero) and is fresh again is faded in over this time (s), from zero: a
#: controller that stalled past command_timeout comes back with the force it had before (0 -> 5 N in one step)
COMMAND_FADE_IN = WATCHDOG_FADE_IN
WATCHDOG_RANGE = "0 (off) or from 125 us to 31.875 ms (the device counts it in units of 125 us, at most 255)"


def _decimal(seconds: float) -> Fraction:
    """The value as the decimal it was written as: 12 significant digits, so the binary rounding of e.g. "875 us"
    (0.0008749999999999999) does not drop a whole unit."""
    return Fraction(f"{float(seconds):.12g}")


def watchdog_units(seconds: float) -> int:
    """``firmware_watchdog`` (s) -> the device's units of 125 us, rounded down so the watchdog is never longer than
    asked (20 ms is exactly 160 units, 20.1 ms is 160 too); 0 stays 0 (off), otherwise at least 1."""
    if seconds == 0:
        return 0
    return max(1, math.floor(_decimal(seconds) * WATCHDOG_UNITS_PER_S))


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
    runtime's ``max_age`` turns staleness into a fault where the graph asks for it). A command that was stale and is
    fresh again is faded in from zero over ``fade_in`` seconds of graph time, never stepped onto the hand. Counts
    clamped, stale, invalid and faded-in commands for status() (from zero again after :meth:`clear_counts`).
    """

    def __init__(self, max_gripper_force: float, max_force: float, timeout: float | None,
                 fade_in: float = COMMAND_FADE_IN):
        self.max_g = float(max_gripper_force)
        self.max_f = float(max_force)
        self.timeout = timeout
        self.fade_in = float(fade_in)
        self.clamped = 0
        self.stale = 0
        self.invalid = 0
        self.faded_in = 0
        self.zero3 = np.zeros(3)
        self._back: dict[str, float | None] = {}   # per port that went stale: None while stale, then when it came back

    def reset(self) -> None:
        """Forget which ports were stale (at activation: the device starts from zero force anyway)."""
        self._back = {}

    def clear_counts(self) -> None:
        """The counters from zero (omega7: at each activation, so that status() is of one activation)."""
        self.clamped = self.stale = self.invalid = self.faded_in = 0

    def _fade(self, port: str, t: float) -> float:
        """Scale (0..1) of a fresh command on ``port``: rising over ``fade_in`` from its first fresh step after it
        was stale; 1 when it never was (or has finished fading in)."""
        if port not in self._back:
            return 1.0
        t0 = self._back[port]
        if t0 is None:
            t0 = self._back[port] = t
            self.faded_in += 1
        k = (t - t0) / self.fade_in if self.fade_in > 0 else 1.0
        if k >= 1.0:
            del self._back[port]
            return 1.0
        return max(0.0, k)

    def apply(self, t: float, inputs: Any) -> tuple[float, np.ndarray, str | None]:
        g = 0.0
        f = self.zero3
        s = inputs.get("gripper_force")
        if s is not None:
            if self.timeout is not None and not s.is_fresh(t, self.timeout):
                self.stale += 1
                self._back["gripper_force"] = None
            else:
                try:
                    g = float(s.value)
                except (TypeError, ValueError):
                    self.invalid += 1
                    return 0.0, self.zero3, f"gripper_force command is not a number: {s.value!r}"
                except OverflowError:   # an int beyond any float (a float64 port takes any int)
                    self.invalid += 1
                    return 0.0, self.zero3, ("gripper_force command is an integer too large for a float (not "
                                             "finite): force set to zero")
                if not math.isfinite(g):
                    self.invalid += 1
                    return 0.0, self.zero3, f"gripper_force command is {g} (not finite): force set to zero"
                if g > self.max_g:
                    g = self.max_g
                    self.clamped += 1
                elif g < -self.max_g:
                    g = -self.max_g
                    self.clamped += 1
                g *= self._fade("gripper_force", t)
        s = inputs.get("force") if "force" in inputs else None
        if s is not None:
            if self.timeout is not None and not s.is_fresh(t, self.timeout):
                self.stale += 1
                self._back["force"] = None
            else:
                try:
                    f = np.asarray(s.value, dtype=float).reshape(3)
                except (TypeError, ValueError):
                    self.invalid += 1
                    return 0.0, self.zero3, f"force command is not a 3-vector: {s.value!r}"
                except OverflowError:
                    self.invalid += 1
                    return 0.0, self.zero3, ("force command has an integer component too large for a float (not "
                                             "finite): force set to zero")
                if not np.all(np.isfinite(f)):
                    self.invalid += 1
                    return 0.0, self.zero3, f"force command {f.tolist()} is not finite: force set to zero"
                if math.hypot(*f) > self.max_f:   # (hypot: no overflow of the squares, up to ~1e308 N)
                    u = f / float(np.max(np.abs(f)))   # components within [-1, 1]: its norm is finite
                    f = u * (self.max_f / math.hypot(*u))
                    self.clamped += 1
                k = self._fade("force", t)
                if k < 1.0:
                    f = f * k
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
        firmware_watchdog: Seconds = Field(
            0.02, description="the device firmware's own watchdog (dhdSetWatchdog, SDK 3.3.2 or newer): with no new "
                              "force command for this long the device switches its forces off by itself, also while "
                              "a libdhd call hangs; 0 (off) or 125 us to 31.875 ms, rounded down to units of 125 us; "
                              "at least 2 periods of the node's rate",
            json_schema_extra={"unit": "s"})

        @field_validator("sdk_path")
        @classmethod
        def _sdk_path_exists(cls, v: str | None) -> str | None:
            # when the graph is validated (`validate` said OK, the run failed at start-up); what the path holds is
            # for the SDK's loader (dhd.load) to say at configure, with the library it tried
            if not v:
                return v   # not given: $FORCEDIM_SDK, then the system library path
            where = Path(v).expanduser()
            expected = ("expected the Force Dimension SDK's folder (e.g. /opt/sdk-3.17.0) or its libdhd library file, "
                        "or no sdk_path at all to use $FORCEDIM_SDK, then the system library path")
            if not where.exists():
                raise ValueError(f"sdk_path {v!r} does not exist{looked_at(where)}; {expected}")
            if not (where.is_dir() or where.is_file()):
                raise ValueError(f"sdk_path {v!r} is neither a folder nor a file; {expected}")
            return v

        @field_validator("firmware_watchdog")
        @classmethod
        def _watchdog_range(cls, v: float) -> float:
            if v != 0 and not (v > 0 and Fraction(1, WATCHDOG_UNITS_PER_S) <= _decimal(v)
                               <= Fraction(WATCHDOG_MAX_UNITS, WATCHDOG_UNITS_PER_S)):
                raise ValueError(f"firmware_watchdog must be {WATCHDOG_RANGE}; got {v:g} s")
            return v

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
        self.sign = 1.0
        self._new_session()
        self.safe_errors = 0
        self.g_sent = 0.0
        self.f_sent = np.zeros(3)
        self._lock = threading.Lock()
        # the firmware watchdog: its duration in the device's units, whether it is set on the device now, when the
        # device last got a force command (monotonic, taken before the call), how often the loop came too late
        self.watchdog_units = watchdog_units(p.firmware_watchdog)
        self._wd_s = self.watchdog_units / WATCHDOG_UNITS_PER_S
        self._wd_set = False
        self._last_cmd = 0.0
        self._first_write = True
        self._fade_until = 0.0    # monotonic time until which forces fade back in after a watchdog trip
        self._off_cause: int | None = None
        rate = self.ctx.rate
        if self.watchdog_units and rate and self._wd_s < 2.0 / rate:
            raise ValueError(f"firmware_watchdog ({self._wd_s * 1e3:g} ms) must be at least 2 periods of the node's "
                             f"rate ({rate:g} Hz: {2e3 / rate:g} ms), or the device would cut the forces at every "
                             f"late step; raise it, or set firmware_watchdog: 0 (off)")
        lib = dhdmod.load(p.sdk_path)
        if self.watchdog_units and not lib.has_watchdog():
            raise dhdmod.DhdError(
                f"firmware_watchdog: {lib.path} (SDK {lib.sdk_version()}) has no dhdSetWatchdog (added in Force "
                f"Dimension SDK 3.3.2): install SDK 3.3.2 or newer, or set firmware_watchdog: 0 to run without the "
                f"device's own watchdog (then a libdhd call that hangs leaves the last force on the operator's hand "
                f"until it returns)")
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
        sdk_limits = lib.set_max_force(p.max_force) & lib.set_max_gripper_force(p.max_gripper_force)
        lib.set_gravity_compensation(p.gravity_compensation)
        lib.set_brakes(p.brakes_on_stop)
        wd = f"firmware watchdog {self._wd_s * 1e3:g} ms" if self.watchdog_units else "firmware watchdog off"
        limits = "" if sdk_limits else " (the driver's own: this SDK has no dhdSetMaxForce/dhdSetMaxGripperForce)"
        self.ctx.log(f"opened {dhdmod.SYSTEM_NAMES.get(stype, stype)} through {lib.path} "
                     f"(SDK {lib.sdk_version()}); limits {p.max_force:g} N, gripper {p.max_gripper_force:g} N{limits}; "
                     f"{wd}")

    def activate(self) -> None:
        d = self.dhd
        with self._lock:
            if self.watchdog_units:
                self._set_watchdog(d)
            self._last_cmd = time.monotonic()
            d.set_forces(0.0, 0.0, 0.0, 0.0)
            self.guard.reset()
            self._first_write = True
            self._fade_until, self._off_cause = 0.0, None
            self._new_session()
            d.set_gravity_compensation(self.params.gravity_compensation)
            # the brakes released before forces are enabled: dhdSetBrakes(DHD_OFF) after dhdEnableForce(DHD_ON) puts
            # the device in IDLE mode, where no current reaches the motors (every later force write did nothing)
            d.set_brakes(False)
            d.enable_force(True)
            st = d.force_status()
            if st is not None and not st[0]:   # (the force button, a safety feature): said, as a late step says it
                from .dhd import FORCEOFF_CAUSES

                self._off_cause = st[1]
                self.ctx.log(f"forces did not come on (dhdEnableForce): off by {FORCEOFF_CAUSES.get(st[1], st[1])}: "
                             f"the operator feels no force until they are switched on at the device")
            self.active = True

    def _new_session(self) -> None:
        """What status() reports of one activation, from afresh: the device's loss, another failure of a step, the
        SDK's communication rate (read at the first step, whatever the graph time: it starts from 0 again in a new
        run) and the counters (the guard's, time guards, saturations, watchdog trips, faults of a step)."""
        self.lost: str | None = None
        self.error: str | None = None
        self.faults = 0
        self.com_freq_hz = math.nan
        self._next_freq = -math.inf
        self.timeguards = 0
        self.saturated = 0
        self.watchdog_trips = 0
        self.guard.clear_counts()

    def _after_late_gap(self, d: Any, sent: float) -> bool:
        """Before a write that comes later than the firmware watchdog (under the lock). If the watchdog switched the
        forces off: zero force, forces on, and the command faded in over WATCHDOG_FADE_IN from now (after a stall;
        not after start-up, where forces were zero). If something else switched them off (the force button, the
        velocity threshold, the dead-man switch: the operator's or the device's decision), they stay off. Returns
        whether this counts as a trip (not the first write after activate)."""
        from .dhd import DHD_FORCEOFF_WATCHDOG, FORCEOFF_CAUSES

        st = d.force_status()
        if st is not None and (st[0] or st[1] != DHD_FORCEOFF_WATCHDOG):
            if not st[0] and st[1] != self._off_cause:
                self.ctx.log(f"forces are off by {FORCEOFF_CAUSES.get(st[1], st[1])}: left off")
            self._off_cause = None if st[0] else st[1]
            return False
        d.set_forces(0.0, 0.0, 0.0, 0.0)   # the device may still hold the command from before the stall
        d.enable_force(True)
        if self._first_write:
            return False
        self._fade_until = sent + WATCHDOG_FADE_IN
        return True

    def _set_watchdog(self, d: Any) -> None:
        """The firmware watchdog on, before forces are enabled; refuses to go on when the device does not take it."""
        from .dhd import DhdError

        units = self.watchdog_units
        hint = ("set firmware_watchdog: 0 to run without the device's own watchdog (then a libdhd call that hangs "
                "leaves the last force on the operator's hand until it returns)")
        try:
            d.set_watchdog(units)
            self._wd_set = True
            got = d.watchdog()
        except DhdError as exc:
            raise DhdError(f"firmware_watchdog: could not set the device's watchdog to {units} x 125 us "
                           f"({self._wd_s * 1e3:g} ms): {exc}; forces stay off; {hint}", exc.code) from None
        if got is not None and got != units:
            raise DhdError(f"firmware_watchdog: the device reports a watchdog of {got} x 125 us after {units} was "
                           f"set; forces stay off; {hint}")

    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        g, f, problem = self.guard.apply(t, inputs)
        if problem is not None:
            self.faults += 1
            self.error = problem
            self.safe_state()
            raise ComponentFault(problem, self.id)
        d = self.dhd
        late = False
        try:
            with self._lock:
                x, y, z = d.position()
                gap = d.gripper_gap()
                gvel = d.gripper_velocity()
                button = d.button(self.params.button_index)
                # checked under the lock, right before the write: a safe_state() called from another thread since
                # the guard, or while a read above hung, is never undone by this step's force
                if not self.active:
                    g, f = 0.0, self.guard.zero3
                sent = time.monotonic()
                if self._wd_set and self.active and sent - self._last_cmd > self._wd_s:
                    # no force command for longer than the firmware watchdog: the device has (or may have)
                    # switched its forces off (the first write after activate is late whenever start-up goes on
                    # after activate(): not counted)
                    late = self._after_late_gap(d, sent)
                if sent < self._fade_until:   # forces back on after a watchdog trip: faded in, not stepped
                    k = max(0.0, 1.0 - (self._fade_until - sent) / WATCHDOG_FADE_IN)
                    g, f = g * k, f * k
                rc = d.set_forces(float(f[0]), float(f[1]), float(f[2]), self.sign * g)
                if self._wd_set and rc != 1:   # (a write the time guard skipped never reached the device)
                    self._last_cmd = sent
                    self._first_write = False
                if t >= self._next_freq:
                    self._next_freq = t + self.params.com_freq_interval
                    self.com_freq_hz = d.com_freq()
        except Exception as exc:
            self._step_failed(exc)
            raise
        if rc == 1:
            self.timeguards += 1
        elif rc == 2:
            self.saturated += 1
        if late:
            self.watchdog_trips += 1
            self.ctx.log(f"no force command for more than firmware_watchdog ({self._wd_s * 1e3:g} ms): the device "
                         f"may have cut its forces; switched on again ({self.watchdog_trips} times so far)")
        self.g_sent, self.f_sent = g, f
        return {"gripper_opening": gap, "gripper_velocity": self.sign * gvel,
                "position": np.array((x, y, z)), "button": button}

    def _step_failed(self, exc: Exception) -> None:
        """A call of the step raised (outside the lock; the step raises it on, faulting the node). A device that
        stopped answering (DeviceLostError: the SDK's communication error or timeout) is ``lost``: nothing can be
        set on it (its firmware switches the forces off on a USB disconnection; the runtime's safe_state() still
        tries). Any other failure (an SDK error of a device that still answers, a bug in this driver) is an
        ``error``, named with its type, and the device is made safe at once (zero force, brakes), not left with the
        step before's force until the runtime's safe_state()."""
        from .dhd import DeviceLostError

        self.faults += 1
        if isinstance(exc, DeviceLostError):
            self.lost = str(exc)
            self.active = False
            return
        self.error = f"{type(exc).__name__}: {exc}"
        self.safe_state()

    def safe_state(self) -> None:
        """Zero force, then the brakes (if configured), each tried on its own. A device that is gone
        (DeviceLostError) is only counted in safe_errors: nothing can be set on it, and its firmware takes the forces
        off. One that answers but whose forces could be neither zeroed nor switched off raises a DhdError that says
        so, after the brakes were tried (the forces may still be on: the runtime reports it, the run ends as a fault;
        this was counted only, and status() said 0 N)."""
        from .dhd import DeviceLostError, DhdError

        self.active = False
        d = getattr(self, "dhd", None)
        if d is None:
            self.g_sent, self.f_sent = 0.0, np.zeros(3)
            return
        failed: Exception | None = None
        with self._lock:
            try:
                self._zero_forces()
                self.g_sent, self.f_sent = 0.0, np.zeros(3)
            except Exception as exc:
                self.safe_errors += 1
                if not isinstance(exc, DeviceLostError):
                    failed = exc
            if self.params.brakes_on_stop:
                try:
                    d.set_brakes(True)
                except Exception:
                    self.safe_errors += 1
        if failed is not None:
            msg = (f"safe_state: the zero-force write did not go through and dhdEnableForce(0) failed ({failed}): the "
                   f"forces may still be on; {self._forces_left_text()}")
            self.ctx.log(msg)
            raise DhdError(msg, getattr(failed, "code", None)) from failed

    def _zero_forces(self) -> None:
        """Zero force, written until the SDK takes it: a write the time guard skips (DHD_TIMEGUARD: too soon after
        the step's write) is tried again; if it never goes through, or fails (-1), forces are disabled altogether
        (raises when that fails too, or when the device is gone)."""
        from .dhd import DHD_TIMEGUARD, DeviceLostError

        d = self.dhd
        try:
            for _ in range(20):
                if d.set_forces(0.0, 0.0, 0.0, 0.0) != DHD_TIMEGUARD:
                    return
                time.sleep(2e-4)
        except DeviceLostError:
            raise
        except Exception:
            pass   # the zero-force write failed: the last force would stay on the hand
        self.safe_errors += 1
        d.enable_force(False)

    def deactivate(self) -> None:
        self.safe_state()
        d = getattr(self, "dhd", None)
        if d is not None:
            with self._lock:
                self._forces_off(d, "deactivate")

    def _forces_off(self, d: Any, when: str) -> None:
        """Forces off (dhdEnableForce(0)), then the firmware watchdog off, so the device does not keep it for the
        next program. When dhdEnableForce(0) fails the forces may still be on: the watchdog, the last protection that
        takes them off the hand once no force command comes, stays on, and the failure is raised as a DhdError that
        says so. A device that stopped answering (DeviceLostError) is only counted in safe_errors: nothing can be set
        on it, its firmware switches the forces off on a USB disconnection, and the watchdog stays on."""
        from .dhd import DeviceLostError, DhdError

        try:
            d.enable_force(False)
        except Exception as exc:
            self.safe_errors += 1
            if isinstance(exc, DeviceLostError):
                return
            msg = f"{when}: dhdEnableForce(0) failed ({exc}): the forces may still be on; {self._forces_left_text()}"
            self.ctx.log(msg)
            raise DhdError(msg, getattr(exc, "code", None)) from exc
        self._watchdog_off(d)

    def _forces_left_text(self) -> str:
        """What takes forces that may still be on off the operator's hand."""
        if getattr(self, "_wd_set", False):
            return (f"the firmware watchdog ({self._wd_s * 1e3:g} ms) is left on, so the device switches them off by "
                    f"itself once no force command comes")
        return ("no firmware watchdog is set (firmware_watchdog: 0): switch them off at the device (its force button) "
                "or power it off")

    def _watchdog_off(self, d: Any) -> None:
        """The firmware watchdog off (only once the forces are off: see :meth:`_forces_off`)."""
        if getattr(self, "_wd_set", False):
            try:
                d.set_watchdog(0)
                self._wd_set = False
            except Exception:
                self.safe_errors += 1

    def close(self) -> None:
        d = getattr(self, "dhd", None)
        if d is None:
            return
        self.dhd = None
        try:
            self._forces_off(d, "close")   # (already off after deactivate; close may come without it)
        finally:
            try:
                d.close()
            except Exception:
                pass

    def status(self) -> dict[str, Any]:
        if not hasattr(self, "guard"):
            return {}
        return {"com_freq_hz": self.com_freq_hz, "gripper_force_n": self.g_sent,
                "force_norm_n": float(np.linalg.norm(self.f_sent)), "timeguards": self.timeguards,
                "saturated": self.saturated, "clamped": self.guard.clamped, "stale_commands": self.guard.stale,
                "faded_in": self.guard.faded_in, "left_handed": self.sign < 0, "lost": self.lost or "",
                "error": self.error or "", "firmware_watchdog_s": self._wd_s if self._wd_set else 0.0,
                "watchdog_trips": self.watchdog_trips, "faults": self.faults, "safe_errors": self.safe_errors}


@hookimpl
def teletouch_components():
    return [Omega7]


def discover(sdk_path: str | None = None) -> list[dict[str, Any]]:
    """The rows of ``teletouch devices`` for Force Dimension devices (never raises): one per device the SDK counts,
    with the ``omega7`` params that open it; or one ``error`` row saying why none can be listed: the SDK not found
    (and where it was looked for: a plugged-in omega.7 is invisible without it), or a device count the SDK cannot
    give (no dhdGetDeviceCount, or -1 with the SDK's last error).

    A device's params are ``serial`` where the SDK gives its serial number (dhdGetSerialNumber; the device is opened
    for it and closed again): ``index`` is the SDK's enumeration order, which can change between boots with two
    devices plugged in. ``index`` where there is no serial number: an SDK without dhdGetSerialNumber, or a device
    that cannot be opened (held by another program: said in the row's ``problem``)."""
    try:
        from . import dhd as dhdmod

        lib = dhdmod.load(sdk_path)
    except Exception as exc:  # SdkNotFoundError (says where it looked), or a library that breaks at load
        return [_error_row(f"Force Dimension devices cannot be listed: {exc}")]
    where = f"{lib.path}, SDK {lib.sdk_version()}"
    try:
        n = lib.device_count()
    except Exception as exc:
        return [_error_row(f"dhdGetDeviceCount failed ({where}): {type(exc).__name__}: {exc}", lib.path)]
    if n is None:
        return [_error_row(f"this libdhd ({where}) has no dhdGetDeviceCount, so its devices cannot be listed; an "
                           f"omega7 node still opens the first device (or the one given by serial or index)",
                           lib.path)]
    if n < 0:
        code, text = lib.last_error()
        return [_error_row(f"dhdGetDeviceCount failed ({where}): {text} (error {code}); {dhdmod.DEVICE_HINT}",
                           lib.path)]
    return [_device_row(lib, i) for i in range(n)]


def _device_row(lib: Any, index: int) -> dict[str, Any]:
    """The row of the device at ``index``: selected by its serial number where the SDK gives it, else by index."""
    from .dhd import DEVICE_HINT

    serial, problem = None, None
    try:
        serial = lib.serial_at(index)
    except Exception as exc:
        problem = (f"its serial number could not be read ({exc}): select it by index, the SDK's enumeration order, "
                   f"which can change between boots with two devices; {DEVICE_HINT}")
    details: dict[str, Any] = {"sdk": lib.sdk_version(), "serial": serial, "plugin": "omega7",
                               "params": {"index": index} if serial is None else {"serial": serial}}
    if problem:
        details["problem"] = problem
    return {"kind": "omega7", "id": f"dhd:{index}", "path": lib.path, "details": details}


def _error_row(message: str, path: str = "") -> dict[str, Any]:
    return {"kind": "omega7", "id": "", "path": path, "error": message}


@hookimpl
def teletouch_discover_devices():
    """Force Dimension devices the SDK can see; an error row when it cannot tell (see :func:`discover`)."""
    return discover()
