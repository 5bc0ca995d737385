"""Seeded fuzzing of the follower's safety promise: on any fault the follower holds position; set-points within
limits and speed.

Each follower driver is stepped with random sequences of ``opening_command`` samples: late, out of order, repeated,
stamped NaN/inf or in the future, valued NaN/inf/huge/not a number, a stream that stops, steps that repeat a time or
stall, ``safe_state()`` at random moments (then more commands, which it must ignore, and sometimes a new
``activate()``, with the gripper moved outside [min_opening, max_opening] while inactive). On every set-point the
hardware receives:

- it is finite, within ``[min_opening, max_opening]`` or, from outside, no further out than the last one (walked in);
- it moved by at most ``max_speed * min(dt, 2 periods)`` since the last step's (the late-step allowance);
- it is exactly what the promise makes it: the usable command (fresh: stamped within ``command_timeout`` either way,
  a number, finite, at most 1 m either way, not older than the last command used), clamped and rate limited; with no
  usable command the measured opening taken when the hold began (walked into the range); after ``safe_state()``
  that hold (or ``max_opening`` with ``safe_mode: open``), whatever the commands say, and the hold is the last thing
  sent.

sim-gripper is fuzzed by hand (many cases, its writes recorded at ``_hw_write``, the hardware boundary);
dynamixel-gripper against its Protocol 2.0 emulator (the Goal_Positions the emulated servo received) and
canopen-gripper against its CiA 402 drive on virtual CAN (the set-points the drive latched) with a few cases each.
Everything is seeded and no assertion depends on the wall clock: the drivers are stepped at the case's times, the
emulators' motion only changes the measured openings, which the oracle reads from the driver's outputs.

A failure prints the seed and a shrunk event sequence (what a regression test needs).
"""

from __future__ import annotations

import math
import random
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes import fuzzing  # noqa: E402
from fakes.dynamixel_emulator import DynamixelEmulator, slow_adapter  # noqa: E402
from fakes.fuzzing import Violation  # noqa: E402
from fakes.realtime import WAIT, wait_for  # noqa: E402

from teletouch import Sample  # noqa: E402
from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.canopen_gripper import CanopenGripper  # noqa: E402
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper  # noqa: E402
from teletouch.plugins.devices.sim_gripper import SimGripper  # noqa: E402

pytestmark = pytest.mark.timeout(120)

NAN, INF = math.nan, math.inf
#: command values that must never be followed (not a number, not finite, or beyond any gripper's 1 m)
BAD_VALUES = [NAN, INF, -INF, 1e300, -1e300, 1e30, -1e30, 2.0, -2.0, 1.0000001, "x", "0.03", None, True, b"0.03",
              [0.03]]
#: odd but valid command values (clamped into the range)
ODD_VALUES = [5e-324, -5e-324, 0.0, -0.5, 0.5, 1.0, -1.0]
BAD_STAMPS = [NAN, INF, -INF]
MAX_OPENING_M = 1.0  # commands beyond this either way are invalid input (units.MAX_PLAUSIBLE_OPENING)
EPS = 1e-12


# ================================================================================================ cases
@dataclass
class Case:
    """One fuzz case: the driver's params and per step (time, events). Events: ``"cmd": (value, stamp)`` with
    ``value`` None for the trajectory's good value (a tuple ``("v", x)`` for a given one) and ``stamp`` an offset from
    the step's time when finite, else the stamp itself; ``"cmd": "repeat"`` re-sends the last sample object;
    ``"safe": True`` calls safe_state() after the step; ``"activate": x`` re-activates before the step (x: where the
    gripper was moved meanwhile, None: left where it is)."""

    seed: int
    driver: str
    params: dict[str, Any]
    steps: list[tuple[float, dict[str, Any]]]
    world: dict[str, float] = field(default_factory=dict)

    def describe(self) -> str:
        lines = [f"seed={self.seed} driver={self.driver!r}", f"params={self.params!r}", f"world={self.world!r}",
                 "steps (time, events; steps without events left out) ="]
        for i, (t, ev) in enumerate(self.steps):
            if ev:
                lines.append(f"  [{i}] t={t!r}: {ev!r}")
        lines.append(f"  (last step [{len(self.steps) - 1}] t={self.steps[-1][0]!r})")
        return "\n".join(lines)


def random_times(rng: random.Random, n: int, period: float) -> list[float]:
    """Step times at the node's period, with repeated times, jitter and stalls."""
    t, out = 0.0, []
    for _ in range(n):
        out.append(t)
        r = rng.random()
        t += (0.0 if r < 0.01 else rng.uniform(0.1, 3.0) * period if r < 0.05
              else rng.uniform(3.0, 300.0) * period if r < 0.055 else period)
    return out


class CommandStream:
    """Events of opening_command: normal samples with a latency, and modes (dropout, garbage values, odd values, bad
    stamps, late/out-of-order deliveries, repeats, future stamps) switched at random."""

    def __init__(self, rng: random.Random, timeout: float):
        self.rng = rng
        self.timeout = timeout
        self.mode = "normal"
        self.left = 0
        self.latency = rng.choice([0.0, rng.uniform(0.0, 0.004)])  # constant: a normal stream arrives in order

    def event(self) -> Any:
        rng = self.rng
        if self.left <= 0:
            r = rng.random()
            self.mode = ("normal" if r < 0.6 else "dropout" if r < 0.68 else "garbage" if r < 0.76 else
                         "odd" if r < 0.8 else "badstamp" if r < 0.84 else "late" if r < 0.92 else
                         "future" if r < 0.96 else "repeat")
            self.left = rng.choice([1, 3, 20, 100])
        self.left -= 1
        mode, lat = self.mode, -self.latency
        if mode == "dropout":
            return None
        if mode == "repeat":
            return "repeat" if rng.random() < 0.5 else None
        if mode == "normal":
            return (None, lat)
        if mode == "garbage":
            return (("v", rng.choice(BAD_VALUES)), lat if rng.random() < 0.8 else rng.choice(BAD_STAMPS))
        if mode == "odd":
            return (("v", rng.choice(ODD_VALUES)), lat)
        if mode == "badstamp":
            return (None, rng.choice(BAD_STAMPS))
        if mode == "late":  # older than the last used one (out of order), some beyond command_timeout (stale)
            return (None, -rng.uniform(0.0, 2.0 * self.timeout))
        return (None, rng.uniform(0.0, 2.0 * self.timeout) if rng.random() < 0.8 else 3600.0)  # future


def random_params(rng: random.Random, driver: str) -> dict[str, Any]:
    top = {"sim": 0.09, "dynamixel": 0.075, "canopen": 0.08}[driver]
    lo = rng.choice([0.0, 0.0, rng.uniform(0.0, 0.4 * top)])
    hi = rng.choice([top, top, rng.uniform(0.6 * top, top)])
    p: dict[str, Any] = {
        "min_opening": lo, "max_opening": hi,
        "max_speed": rng.choice([0.05, 0.1, 0.01, rng.uniform(0.005, 0.2)]),
        "command_timeout": rng.choice([0.2, 0.05, rng.uniform(0.02, 0.5)]),
        "safe_mode": rng.choice(["hold", "hold", "open"]),
    }
    if driver == "sim":
        p["object_width"] = rng.choice([None, rng.uniform(lo + 1e-3, hi)])
        p["initial_opening"] = rng.uniform(lo, hi)
    return p


def random_case(seed: int, driver: str, n_steps: int, period: float) -> Case:
    rng = random.Random(seed)
    params = random_params(rng, driver)
    times = random_times(rng, n_steps, period)
    stream = CommandStream(rng, params["command_timeout"])
    top = {"sim": 0.09, "dynamixel": 0.075, "canopen": 0.08}[driver]
    steps = []
    safe = False
    for t in times:
        ev: dict[str, Any] = {}
        if safe and rng.random() < 0.02:
            # re-activated; the gripper moved meanwhile (only sim-gripper can be moved by hand), maybe out of range
            ev["activate"] = rng.uniform(0.0, top) if driver == "sim" and rng.random() < 0.7 else None
            safe = False
        e = stream.event()
        if e is not None:
            ev["cmd"] = e
        if not safe and rng.random() < 0.004:
            ev["safe"] = True
            safe = True
        steps.append((t, ev))
    world = {"mid": rng.uniform(0.2, 0.8) * top, "amp": rng.uniform(0.0, 0.6) * top, "freq": rng.uniform(0.1, 3.0),
             "phase": rng.uniform(0.0, 6.3)}
    return Case(seed, driver, params, steps, world)


def good_command(w: dict[str, float], t: float) -> float:
    """The leader's opening: a sine that may leave [min_opening, max_opening] (it is clamped)."""
    return w["mid"] + w["amp"] * math.sin(2.0 * math.pi * w["freq"] * t + w["phase"])


# ================================================================================================ the oracle
def usable_value(s: Sample | None) -> float | None:
    """The command value if it is a real number, finite and at most 1 m either way (None otherwise)."""
    if s is None:
        return None
    v = s.value
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    v = float(v)
    return v if math.isfinite(v) and abs(v) <= MAX_OPENING_M else None


class SetpointOracle:
    """The set-point the promise makes, step by step (an independent model), and the invariants on what was sent."""

    def __init__(self, p: Any, rate: float):
        self.p = p
        self.max_dt = 2.0 / rate

    def activate(self, measured: float) -> None:
        self.sp = measured            # the set-point starts at the measured opening
        self.sent = measured          # what the hardware last had (the invariants' previous set-point)
        self.t: float | None = None
        self.hold_at: float | None = None
        self.safe = False
        self.last_stamp = -INF

    def command(self, t: float, s: Sample | None) -> float | None:
        """The usable command at ``t``: fresh, a finite number within 1 m, not older than the last one used."""
        v = usable_value(s)
        if v is None or not (-self.p.command_timeout <= t - s.stamp <= self.p.command_timeout):
            return None
        if s.stamp < self.last_stamp:
            return None  # out of order: older than a command already used
        self.last_stamp = s.stamp
        return v

    def expect(self, t: float, s: Sample | None, measured: float) -> tuple[float, float]:
        """The set-point of this step, and the step (s) the speed limit counts."""
        p = self.p
        dt = 0.0 if self.t is None else min(max(t - self.t, 0.0), self.max_dt)
        self.t = t
        cmd = None if self.safe else self.command(t, s)
        if cmd is None:
            if self.hold_at is None:
                self.hold_at = measured  # taken once, when the hold begins
            target = self.hold_at
        else:
            self.hold_at = None
            target = cmd
        target = min(max(target, p.min_opening), p.max_opening)
        reach = p.max_speed * dt
        self.sp = min(max(target, self.sp - reach), self.sp + reach)
        return self.sp, dt

    def safe_state(self, measured: float) -> float:
        self.safe = True
        self.hold_at = self.p.max_opening if self.p.safe_mode == "open" else measured
        self.sp = self.hold_at
        return self.sp

    def check_sent(self, i: int, w: float, dt: float, tol: float) -> None:
        """Invariants on a step's set-point ``w``, independent of the model."""
        p = self.p
        if not (isinstance(w, float) and math.isfinite(w)):
            raise Violation("non-finite set-point", i, f"{w!r}")
        out_now = max(p.min_opening - w, w - p.max_opening, 0.0)
        out_before = max(p.min_opening - self.sent, self.sent - p.max_opening, 0.0)
        if out_now > tol and out_now > out_before + tol:
            raise Violation("set-point out of range", i, f"{w!r} m outside [{p.min_opening}, {p.max_opening}] m "
                                                         f"(the last was {self.sent!r} m)")
        allowed = p.max_speed * dt
        if abs(w - self.sent) > allowed + tol:
            raise Violation("speed limit", i, f"set-point {self.sent!r} -> {w!r} m in a step counting {dt!r} s "
                                              f"(at most {allowed!r} m at max_speed {p.max_speed} m/s)")
        self.sent = w


# ================================================================================================ drivers
class SimRig:
    """sim-gripper stepped by hand; its set-points recorded at _hw_write (the simulated servo's input)."""

    driver, period, tol = "sim", 1e-3, 1e-12
    reads_first = False       # sim-gripper works out the set-point, then moves and reads
    check_each_step = True    # cheap: the first broken promise is found at its step

    def __init__(self, case: Case):
        self.h = Harness(SimGripper, case.params)
        self.writes: list[float] = []

    def __enter__(self) -> "SimRig":
        comp = self.h.comp
        self.h.__enter__()
        original = comp._hw_write

        def record(opening: float) -> None:
            self.writes.append(opening)
            original(opening)

        comp._hw_write = record
        return self

    def __exit__(self, *exc: Any) -> None:
        self.h.__exit__(*exc)

    def move(self, x: float) -> None:
        self.h.comp.x = x

    def sent(self) -> list[float]:
        return list(self.writes)

    def on_wire(self, expected: list[tuple[int, float, float, str]]) -> list[tuple[int, float, float, str]]:
        return expected


def run_case(case: Case, rig_cls: Callable[[Case], Any]) -> None:
    """Runs the case; raises Violation at the first broken promise."""
    with rig_cls(case) as rig:
        h = rig.h
        comp = h.comp
        oracle = SetpointOracle(comp.params, float(h.ctx.rate))
        oracle.activate(comp.status()["opening_m"])
        checker = WriteChecker(rig, oracle)
        # (step, set-point or measured opening, speed-limit step, what): "activate" entries send nothing
        expected: list[tuple[int, float, float, str]] = [(0, oracle.sp, 0.0, "activate")]
        last: Sample | None = None
        slot = h.slots["opening_command"]
        for i, (t, ev) in enumerate(case.steps):
            h.t = t
            if "activate" in ev:
                if ev["activate"] is not None:
                    rig.move(ev["activate"])
                comp.activate()
                oracle.activate(comp.status()["opening_m"])
                expected.append((i, oracle.sp, 0.0, "activate"))
            e = ev.get("cmd")
            if e == "repeat":
                s = last
            elif e is not None:
                value, stamp = e
                v = value[1] if isinstance(value, tuple) else good_command(case.world, t)
                s = Sample(v, t + stamp if math.isfinite(stamp) else stamp)
            else:
                s = slot.sample
            slot.sample = s
            last = s if s is not None else last
            measured = comp.status()["opening_m"]
            try:
                out = comp.step(t, h.inputs) or {}
            except Exception as exc:
                raise Violation("exception", i, f"{type(exc).__name__}: {exc}") from exc
            if rig.reads_first:  # the set-point is worked out from this step's reading
                measured = out["opening"].value
            sp, dt = oracle.expect(t, s, measured)
            expected.append((i, sp, dt, "step"))
            if ev.get("safe"):
                comp.safe_state()
                expected.append((i, oracle.safe_state(comp.status()["opening_m"]), -1.0, "safe_state"))
            if rig.check_each_step:
                checker.check(expected)
        checker.check(expected, final=True)


class WriteChecker:
    """Compares the set-points the hardware received (in m) with the model and checks the invariants on them,
    incrementally (each call goes on from where the last stopped)."""

    def __init__(self, rig: Any, oracle: SetpointOracle):
        self.rig, self.oracle = rig, oracle
        self.j = self.k = 0   # next expected entry, next set-point received

    def check(self, expected: list[tuple[int, float, float, str]], final: bool = False) -> None:
        rig, oracle = self.rig, self.oracle
        want = rig.on_wire(expected)   # first: it waits until the hardware has what was sent
        got = rig.sent()
        for i, sp, dt, what in want[self.j:]:
            if what == "activate":
                oracle.sent = sp  # the set-point starts at the measured opening
                self.j += 1
                continue
            if self.k >= len(got):
                raise Violation("set-points sent", i, f"{len(got)} set-points reached the hardware, expected "
                                                      f"{sum(w[3] != 'activate' for w in want)}")
            w = got[self.k]
            self.k += 1
            self.j += 1
            if what == "step":
                oracle.check_sent(i, w, dt, rig.tol)
            oracle.sent = w
            if not abs(w - sp) <= rig.tol + EPS * abs(sp):
                raise Violation(f"{what} set-point", i, f"the hardware received {w!r} m, the promise makes it "
                                                        f"{sp!r} m")
        if self.k != len(got):
            raise Violation("set-points sent", want[-1][0], f"{len(got)} set-points reached the hardware, expected "
                                                            f"{self.k}: extra {got[self.k:][:5]!r}")
        if final and self.k:
            last = [w for w in want if w[3] != "activate"][-1]
            if not abs(got[-1] - last[1]) <= rig.tol + EPS:
                raise Violation("last set-point", last[0], f"the last thing sent was {got[-1]!r} m, not the "
                                                           f"{last[3]}'s {last[1]!r} m")


# ================================================================================================ shrinking
def check_case(case: Case, rig_cls: Callable[[Case], Any], budget: int = 200) -> None:
    fuzzing.check_case(case, lambda c: run_case(c, rig_cls), budget)


# ================================================================================================ sim-gripper
N_SIM_CASES = 24
N_SIM_STEPS = 2500


@pytest.mark.parametrize("block", range(3))
def test_fuzz_sim_gripper_set_points_finite_limited_and_hold_on_faults(block):
    for j in range(N_SIM_CASES // 3):
        seed = 5000 + block * (N_SIM_CASES // 3) + j
        check_case(random_case(seed, "sim", N_SIM_STEPS, SimRig.period), SimRig)


@pytest.fixture(autouse=True)
def _slow_adapter():
    """The Dynamixel emulator's adapter for a loaded machine (fakes/dynamixel_emulator.py, slow_adapter)."""
    with slow_adapter():
        yield


# ================================================================================================ emulated hardware
class EmulatedRig:
    """A driver Harness (``h``) against an emulator of its hardware (``hw``, with start() and stop()): what the
    hardware recorded from the driver's start on (``recorded()``, counted from ``n0``) is what the oracle checks."""

    h: Any
    hw: Any

    def recorded(self) -> int:
        raise NotImplementedError

    def __enter__(self) -> "EmulatedRig":
        self.hw.start()
        self.h.__enter__()
        self.n0 = self.recorded()
        self.tol = 1.01 * abs(self.h.comp.map.scale)
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            self.h.__exit__(*exc)
        finally:
            self.hw.stop()

    def move(self, x: float) -> None:
        raise AssertionError("the emulated hardware is not moved by hand")


class DynamixelRig(EmulatedRig):
    """dynamixel-gripper against its Protocol 2.0 emulator: the Goal_Positions of the SYNC_WRITEs the servo got."""

    driver, period = "dynamixel", 0.01
    reads_first = True        # the base class reads, then works out the set-point
    check_each_step = False   # the emulator's packets are compared at the end

    def __init__(self, case: Case):
        rng = random.Random(case.seed)
        # resting where the fuzz puts it: maybe outside [min_opening, max_opening] (walked in)
        self.emu = DynamixelEmulator(15, position=rng.choice([1024, 2048, rng.randrange(1024, 2049)]), block_at=None,
                                     speed=rng.choice([3000.0, 300.0]))
        self.hw = self.emu
        self.h = Harness(DynamixelGripper, dict(case.params, port=self.emu.port, baudrate=1000000))

    def recorded(self) -> int:
        return len(self.emu.rx_packets)

    def goal_ticks(self) -> list[int]:
        return [int.from_bytes(p[5:9], "little", signed=True) for (_t, _i, inst, p) in self.emu.rx_packets[self.n0:]
                if inst == 0x83]

    def sent(self) -> list[float]:
        ticks = self.goal_ticks()
        # a repeat of the same Goal_Position changes nothing on the servo: compared without repeats
        return [self.h.comp.map.opening(g) for k, g in enumerate(ticks) if k == 0 or g != ticks[k - 1]]

    def on_wire(self, expected: list[tuple[int, float, float, str]]) -> list[tuple[int, float, float, str]]:
        n = sum(w[3] != "activate" for w in expected)
        wait_for(lambda: len(self.goal_ticks()) >= n, timeout=WAIT)  # the emulator reads the port in its thread
        counts = self.h.comp.map.counts
        out, last = [], None
        for e in expected:
            if e[3] == "activate":
                out.append(e)
            elif counts(e[1]) != last:
                out.append(e)
                last = counts(e[1])
        return out


class RecordingDrive(Cia402Drive):
    """The CiA 402 drive, recording every set-point it latched (rising edge of the new-set-point bit)."""

    def __init__(self, *args: Any, **kw: Any):
        super().__init__(*args, **kw)
        self.latches: list[int] = []

    def _controlword(self, cw: int) -> None:
        with self._lock:
            rising = bool(cw & 0x10 and not self._cw & 0x10)
            super()._controlword(cw)
            if rising and self.state == "OPERATION ENABLED":
                self.latches.append(self.latched)


class CanopenRig(EmulatedRig):
    """canopen-gripper against its CiA 402 drive on virtual CAN: the set-points the drive latched. The driver raises a
    set-point (controlword bit 4 high) only when its counts change and the handshake with the one before is over (every
    other step at most), and the safe state's always: the drive gets those steps' set-points, a subsequence of the
    model's, each checked against its step's and the speed limit over the steps since the one before."""

    driver, period = "canopen", 0.01
    reads_first = True
    check_each_step = False

    def __init__(self, case: Case):
        channel = f"tt-fz-{uuid.uuid4().hex[:8]}"
        self.drive = self.hw = RecordingDrive(5, channel, position=0)
        self.h = Harness(CanopenGripper, dict(case.params, interface="virtual", channel=channel, node_id=5))

    def __enter__(self) -> "CanopenRig":
        super().__enter__()
        comp = self.h.comp
        self.raised: list[bool] = []   # per step() and safe_state() call: whether it raised a set-point
        self._now = False
        send = comp._send_setpoint

        def send_setpoint(counts: int, new: bool) -> None:
            send(counts, new)
            self._now = self._now or new

        comp._send_setpoint = send_setpoint
        for name in ("step", "safe_state"):
            def call(*a: Any, _real: Any = getattr(comp, name), **k: Any) -> Any:
                self._now = False
                try:
                    return _real(*a, **k)
                finally:
                    self.raised.append(self._now)

            setattr(comp, name, call)
        return self

    def recorded(self) -> int:
        return len(self.drive.latches)

    def sent(self) -> list[float]:
        return [self.h.comp.map.opening(c) for c in self.drive.latches[self.n0:]]

    def on_wire(self, expected: list[tuple[int, float, float, str]]) -> list[tuple[int, float, float, str]]:
        out, calls, waited = [], iter(self.raised), 0.0
        for i, sp, dt, what in expected:
            if what == "activate":
                out.append((i, sp, dt, what))
                waited = 0.0
                continue
            if what == "step":
                waited += dt
            if next(calls):
                out.append((i, sp, waited if what == "step" else dt, what))
                waited = 0.0
        n = sum(w[3] != "activate" for w in out)
        wait_for(lambda: len(self.drive.latches) - self.n0 >= n, timeout=WAIT)   # (a bound: the drive's thread)
        return out


N_HW_CASES = 2
N_HW_STEPS = 300


@pytest.mark.parametrize("rig", [DynamixelRig, CanopenRig], ids=["dynamixel", "canopen"])
def test_fuzz_hardware_followers_set_points_finite_limited_and_hold_on_faults(rig):
    for j in range(N_HW_CASES):
        seed = 7000 + j
        case = random_case(seed, rig.driver, N_HW_STEPS, rig.period)
        # a few safe states for sure (the random ones are rare in a short case), with commands after them
        steps = list(case.steps)
        for k in (N_HW_STEPS // 3, 2 * N_HW_STEPS // 3):
            t, ev = steps[k]
            steps[k] = (t, dict(ev, safe=True))
            t, ev = steps[k + 20]
            steps[k + 20] = (t, dict(ev, activate=None))
        steps = [(t, {k: e for k, e in ev.items() if k != "activate" or e is None}) for t, ev in steps]
        check_case(Case(case.seed, case.driver, case.params, steps, case.world), rig, budget=3)


# ================================================================================================ regressions
@pytest.mark.parametrize("value", [True, "0.03", b"0.03", [0.03], 1e30, -1e30, 2.0, 1e300])
def test_regression_a_non_numeric_or_huge_command_holds_the_measured_opening(value):
    """float() took True as 1 m (the gripper opened fully), "0.03" as 30 mm and 1e30 m as max_opening."""
    with Harness(SimGripper, {"object_width": None, "initial_opening": 0.03}) as h:
        h.step(0.0, opening_command=0.03)
        for k in range(1, 50):
            h.step(k * 1e-3, opening_command=value)
        assert h.comp._setpoint == pytest.approx(0.03, abs=1e-9)
        assert h.comp.status()["holding"] == "bad command"


def test_regression_an_out_of_order_command_holds_the_measured_opening():
    """A command stamped before the last one used moved the set-point back to an older opening."""
    with Harness(SimGripper, {"object_width": None, "initial_opening": 0.03, "max_speed": 1.0}) as h:
        for k in range(20):
            h.step(k * 1e-3, opening_command=Sample(0.03, k * 1e-3))
        for k in range(20, 60):
            h.step(k * 1e-3, opening_command=Sample(0.0, 0.005))   # old (still within command_timeout)
        assert h.comp._setpoint == pytest.approx(0.03, abs=1e-4)
        assert h.comp.status()["holding"] == "out-of-order command"
