"""Seeded fuzzing of the safety promise: a force sent to a person's hand is always finite and within limits.

Each teleoperation controller (position-force, position-position, no-feedback) is driven with random sequences of
inputs for thousands of steps: samples late, out of order, repeated, stamped NaN/inf or in the future, valued
NaN/inf/huge/not a number, inputs that stop, controller steps that repeat a time or stall. On every output sample:

- every output is a finite float; ``opening_command`` within ``[opening_min, opening_max]``;
- ``|gripper_force| <= max_force``;
- ``|change| <= max_force_rate * min(dt, 2 periods)`` (the rate limit counts at most two nominal periods);
- position-force never pulls the fingers closed (``>= 0``) unless leader_damping or the damping TDPA is configured;
- no-feedback sends exactly 0 (but the configured damping: leader_damping, the damping TDPA);
- zero once the leader (all controllers) has given nothing fresh and finite for ``fade_time`` (or the time the rate
  limit needs from ``max_force``), counted in the rate limit's capped steps; zero once the force's source
  (position-force: the estimate; position-position: the follower opening) has given nothing fresh and finite for
  ``fade_time`` (and ``smoothing_time``) and that again (a leader lost during the fade fades what is left), and
  meanwhile never larger in magnitude (unless a damping is configured);

The chain tests feed the controller's ``gripper_force`` to ``sim-omega7`` (closed loop: the simulated hand moves the
gripper, the controller sees it) and to ``omega7`` against the C stand-in of libdhd, and assert on the force the
device really renders: finite, within both limits, zero for a stale command, and never a step up onto the hand
faster than ``max_force_rate`` (dropping to zero on a stale command or a fault is the safe reaction and allowed).

A failure prints the seed and a shrunk input sequence (what a regression test needs). Everything is seeded: no
timing, no wall clock (omega7 runs with its firmware watchdog off and the stand-in's time guard off).
"""

from __future__ import annotations

import bisect
import math
import random
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes.fuzzing import Violation, check_case  # noqa: E402

from teletouch import ComponentFault, Sample  # noqa: E402
from teletouch.plugins.controllers.position_force import NoFeedback, PositionForce, PositionPosition
from teletouch.testing import Harness

CLASSES = {"position-force": PositionForce, "position-position": PositionPosition, "no-feedback": NoFeedback}
NAN, INF = math.nan, math.inf
#: values an input may carry besides good ones
BAD_VALUES = [NAN, INF, -INF, 1e300, -1e300, 1e30, -1e30, 5e-324, -5e-324, "x", None, 1e-3 * 1e308]
#: stamp offsets (relative to the step's time) or absolute stamps (non-finite) besides good ones
BAD_STAMPS = [NAN, INF, -INF]
EPS = 1e-9


# ================================================================================================ cases
@dataclass
class Case:
    """One fuzz case: the controller, its params, and per step (time, events). An event is ``(value, stamp)``:
    ``value`` None stands for "the model's good value" (a tuple ``("bad", v)`` for a bad one), ``stamp`` is an
    offset from the step's time when finite, else the stamp itself; ``"repeat"`` re-sends the last sample object.
    Chain cases add ``"skip_ctl": n`` (the controller stalls for the next n steps while the leader runs on) and
    ``world["device"]``, the leader's params."""

    seed: int
    cls: str
    params: dict[str, Any]
    steps: list[tuple[float, dict[str, Any]]]
    world: dict[str, float] = field(default_factory=dict)

    def describe(self, upto: int | None = None) -> str:
        lines = [f"seed={self.seed} cls={self.cls!r}", f"params={self.params!r}", f"world={self.world!r}",
                 "steps (time, events; steps without events left out) ="]
        for i, (t, ev) in enumerate(self.steps[:upto]):
            if ev:
                lines.append(f"  [{i}] t={t!r}: {ev!r}")
        lines.append(f"  (last step [{len(self.steps) - 1}] t={self.steps[-1][0]!r})")
        return "\n".join(lines)


def random_params(rng: random.Random, cls: str) -> dict[str, Any]:
    """Valid params, spread over their ranges (the validators refuse the rest)."""
    p: dict[str, Any] = {
        "max_force": rng.choice([0.5, 2.0, 5.0, 8.0, rng.uniform(0.1, 8.0)]),
        "max_force_rate": rng.choice([10.0, 50.0, 200.0, 1000.0, 1e5, rng.uniform(1.0, 2000.0)]),
        "fade_time": rng.choice([0.001, 0.05, 0.2, rng.uniform(0.001, 0.5)]),
        "leader_stale_after": rng.choice([0.005, 0.05, rng.uniform(0.002, 0.2)]),
        "passivity": rng.random() < 0.7,
        "passivity_gain_adaptation": rng.random() < 0.3,
        "energy_leak_time": rng.choice([None, 1.0, 0.05]),
        "free_space_reset": rng.choice([None, 0.2]),
        "scale": rng.choice([1.0, 2.0, 0.5, rng.uniform(0.1, 4.0)]),
        "offset": rng.choice([0.0, 0.005, -0.005]),
        "velocity_cutoff": rng.choice([50.0, 5.0, 400.0]),
        "max_leader_velocity": rng.choice([2.0, 0.1, 50.0]),
        "damping_smoothing": rng.choice([0.005, 0.0]),
        "damping_release": rng.choice([0.05, 0.0]),
        "reduction_time": rng.choice([0.01, 0.0]),
        "fault_after_lost": None,   # a lasting loss is a fault (tested in test_lost_force_hold): here, the fade
    }
    if rng.random() < 0.2:
        p["leader_damping"] = rng.choice([1.0, 10.0])
    if rng.random() < 0.3:
        p["passivity_controller"] = rng.choice(["force", "damping"])
    if rng.random() < 0.3:
        p["passivity_observer"] = rng.choice(["two-port", "leader-port"])
    if cls == "position-force":
        p.update({
            "force_scale": rng.choice([1.0, 0.0, 3.0, rng.uniform(0.0, 10.0)]),
            "deadband": rng.choice([0.0, 0.02, 0.5]),
            "smoothing_time": rng.choice([0.0, 1.0 / 60.0, 0.1]),
            "stale_after": rng.choice([0.1, 0.02, rng.uniform(0.005, 0.3)]),
            "force_prediction": rng.random() < 0.7,
            "prediction_max_stiffness": rng.choice([2e4, 1e6]),
            "prediction_max_change": rng.choice([1.0, 5.0]),
        })
    elif cls == "position-position":
        p.update({"kp": rng.choice([400.0, 0.0, 5000.0]), "kd": rng.choice([2.0, 0.0, 20.0])})
    if p.get("kd", 0.0) + p.get("leader_damping", 0.0) > 40.0:
        p["kd"] = 0.0
    return p


def random_times(rng: random.Random, n: int) -> list[float]:
    """Controller step times: 1 kHz with repeated times, jitter and stalls."""
    t, out = 0.0, []
    for _ in range(n):
        out.append(t)
        r = rng.random()
        t += (0.0 if r < 0.01 else rng.uniform(2e-4, 3e-3) if r < 0.03 else rng.uniform(0.01, 0.4) if r < 0.033
              else 1e-3)
    return out


class PortStream:
    """Events of one input port: normal samples at a rate with a latency, and modes (dropout, garbage values, bad
    stamps, late/out-of-order deliveries, repeats, future stamps) switched at random."""

    def __init__(self, rng: random.Random, period_steps: int, latency: tuple[float, float]):
        self.rng = rng
        self.period = period_steps
        self.latency = latency
        self.mode = "normal"
        self.left = 0
        self.phase = rng.randrange(period_steps)

    def event(self, k: int) -> Any:
        rng = self.rng
        if self.left <= 0:
            r = rng.random()
            self.mode = ("normal" if r < 0.75 else "dropout" if r < 0.83 else "garbage" if r < 0.88 else
                         "badstamp" if r < 0.91 else "late" if r < 0.95 else "future" if r < 0.97 else "repeat")
            self.left = rng.choice([1, 3, 20, 100, 400])
        self.left -= 1
        mode = self.mode
        if mode == "dropout":
            return None
        if mode == "repeat":
            return "repeat" if rng.random() < 0.5 else None
        if (k + self.phase) % self.period != 0 and rng.random() > 0.02:
            return None
        lat = -rng.uniform(*self.latency)
        if mode == "normal":
            return (None, lat)
        if mode == "garbage":
            return (("bad", rng.choice(BAD_VALUES)), lat if rng.random() < 0.8 else rng.choice(BAD_STAMPS))
        if mode == "badstamp":
            return (None, rng.choice(BAD_STAMPS))
        if mode == "late":
            return (None, -rng.uniform(0.0, 0.6))
        return (None, rng.uniform(0.0, 3.0) if rng.random() < 0.7 else 3600.0)     # future


PORTS = {  # port: (period in steps, latency range s)
    "leader_opening": (1, (0.0, 0.002)),
    "leader_velocity": (1, (0.0, 0.002)),
    "follower_opening": (2, (0.0, 0.004)),
    "force": (17, (0.015, 0.06)),
}


def random_case(seed: int, cls: str, n_steps: int, chain: bool = False) -> Case:
    rng = random.Random(seed)
    params = random_params(rng, cls)
    times = random_times(rng, n_steps)
    ports = [p for p in PORTS if not (p == "leader_velocity" and rng.random() < 0.4)]
    streams = {p: PortStream(rng, *PORTS[p]) for p in ports}
    steps = []
    for k, t in enumerate(times):
        ev = {}
        for p, s in streams.items():
            e = s.event(k)
            if e is not None:
                ev[p] = e
        if chain and rng.random() < 0.002:
            ev["skip_ctl"] = rng.choice([5, 50, 150, 400])        # the controller stalls for this many steps
        steps.append((t, ev))
    world = {"x_obj": rng.uniform(0.0, 0.03), "k_obj": rng.choice([200.0, 2000.0, 2e4]),
             "amp": rng.uniform(0.0, 0.015), "freq": rng.uniform(0.1, 5.0), "phase": rng.uniform(0, 6.3),
             "follower_tau": rng.choice([0.005, 0.03])}
    return Case(seed, cls, params, steps, world)


# ================================================================================================ the oracle
class Usable:
    """Whether an input has a sample that is fresh at ``t`` and finite (a conservative view of what the controller
    may use: any such sample fed so far)."""

    def __init__(self, max_age: float):
        self.max_age = max_age
        self.stamps: list[float] = []

    def add(self, s: Sample) -> None:
        try:
            v = float(s.value)
        except (TypeError, ValueError):
            return
        if math.isfinite(v) and math.isfinite(s.stamp):
            bisect.insort(self.stamps, s.stamp)

    def __call__(self, t: float) -> bool:
        i = bisect.bisect_left(self.stamps, t - self.max_age)
        return i < len(self.stamps) and self.stamps[i] <= t + self.max_age


class ControllerOracle:
    """Checks every output sample of a controller against the invariants of the module's docstring."""

    def __init__(self, comp: Any, cls: str):
        self.comp = comp
        p = self.p = comp.params
        self.cls = cls
        self.max_dt = 2.0 / float(comp.ctx.rate)
        self.leader = Usable(p.leader_stale_after)
        src_age = p.stale_after if cls == "position-force" else p.leader_stale_after
        self.source = Usable(src_age) if cls != "no-feedback" else None
        self.source_port = "force" if cls == "position-force" else "follower_opening"
        smoothing = getattr(p, "smoothing_time", 0.0)
        # a lost leader: the force goes to zero at |force| / fade_time, within the rate limit
        self.zero_after = max(p.fade_time, p.max_force / p.max_force_rate) + 2 * self.max_dt
        # a stale source: the estimate (and the prediction) fade over fade_time (smoothing_time); the output follows
        # within the rate limit, or, if the leader is lost on the way, within the leader's fade
        self.source_zero_after = max(p.fade_time, smoothing) + self.zero_after
        self.lost_leader: float | None = None
        self.lost_source: float | None = None
        self.f_prev: float | None = None
        self.t_prev: float | None = None
        # damping forces (leader_damping, the passivity controller's damping) oppose the leader's motion whatever the
        # force's source says; the damping TDPA (or leader_damping) may also pull
        self.damped = p.leader_damping > 0.0 or p.passivity
        self.may_pull = p.leader_damping > 0.0 or (p.passivity and p.passivity_controller == "damping")
        self.speeds: list[tuple[float, float]] = []       # (clock, |leader velocity|) over the last zero_after
        self.clock = 0.0                                   # the sum of the capped steps (the rate limit's time)

    def feed(self, port: str, s: Sample) -> None:
        if port == "leader_opening":
            self.leader.add(s)
        elif self.source is not None and port == self.source_port:
            self.source.add(s)

    def check(self, i: int, t: float, out: dict[str, Any]) -> float:
        p = self.p
        for name, v in out.items():
            if not (isinstance(v, float) and math.isfinite(v)):
                raise Violation("non-finite output", i, f"{name} = {v!r}")
        f = out["gripper_force"]
        if abs(f) > p.max_force:
            raise Violation("beyond max_force", i, f"gripper_force {f!r} N, max_force {p.max_force} N")
        if "opening_command" in out and not p.opening_min <= out["opening_command"] <= p.opening_max:
            raise Violation("opening_command out of range", i, f"{out['opening_command']!r} m")
        dt = 0.0 if self.t_prev is None else max(0.0, t - self.t_prev)
        if self.f_prev is not None:
            allowed = p.max_force_rate * min(dt, self.max_dt)
            if abs(f - self.f_prev) > allowed + EPS * (1.0 + abs(f)):
                raise Violation("rate limit", i, f"gripper_force {self.f_prev!r} -> {f!r} N in {dt!r} s (at most "
                                                 f"{allowed!r} N)")
        step = min(dt, self.max_dt)
        self.clock += step
        if self.damped:
            self.speeds.append((self.clock, abs(self.comp.v_l) if self.comp.leader_ok else 0.0))
            while self.speeds and self.speeds[0][0] < self.clock - self.source_zero_after - self.max_dt:
                self.speeds.pop(0)
        if self.cls == "no-feedback" and f != 0.0 and not (self.damped and self._damping_only(f)):
            raise Violation("no-feedback sent a force", i, f"{f!r} N")
        if self.cls == "position-force" and not self.may_pull and f < 0.0:
            raise Violation("pull", i, f"position-force pulls the fingers closed: {f!r} N")
        self.lost_leader = None if self.leader(t) else (0.0 if self.lost_leader is None else self.lost_leader + step)
        if self.source is not None:
            self.lost_source = (None if self.source(t) else
                                0.0 if self.lost_source is None else self.lost_source + step)
        if self.lost_leader is not None and self.lost_leader >= self.zero_after and f != 0.0:
            raise Violation("force without a leader", i, f"{f!r} N after {self.lost_leader:.4f} s (capped steps) "
                                                          f"without a fresh finite leader opening")
        if (self.lost_source is not None and not self.damped and self.f_prev is not None
                and abs(f) > abs(self.f_prev) + EPS):
            raise Violation("stale source raised the force", i, f"{self.f_prev!r} -> {f!r} N without a fresh finite "
                                                                 f"{self.source_port}")
        if (self.lost_source is not None and self.lost_source >= self.source_zero_after and f != 0.0
                and not (self.damped and self._damping_only(f))):
            raise Violation("force from a stale source", i, f"{f!r} N after {self.lost_source:.4f} s (capped steps)"
                                                             f" without a fresh finite {self.source_port}")
        self.f_prev, self.t_prev = f, t
        return f

    def _damping_only(self, f: float) -> bool:
        """With a damping configured (leader_damping, the classic damping TDPA), a damping force of the leader's
        recent velocity is allowed: within max_damping x the largest speed over the window (the rate limit lags)."""
        return abs(f) <= self.p.max_damping * max((v for _, v in self.speeds), default=0.0) + EPS


# ================================================================================================ running a case
def _feed(ev: dict[str, Any], t: float, good: dict[str, float], last: dict[str, Sample | None], slots: Any,
          oracle: Any) -> None:
    """A step's input events as samples into the controller's slots and the oracle (``last``: the sample last sent
    per port, what a "repeat" re-sends)."""
    for port, e in ev.items():
        if port not in PORTS or port not in slots:
            continue
        s = _materialize(e, t, good[port], last.get(port))
        if s is None:
            continue
        last[port] = s
        slots[port].sample = s
        oracle.feed(port, s)


def _materialize(ev: Any, t: float, good: float, last: Sample | None) -> Sample | None:
    if ev == "repeat":
        return last
    value, stamp = ev
    v = value[1] if isinstance(value, tuple) else good
    return Sample(v, t + stamp if math.isfinite(stamp) else stamp)


class World:
    """The good values: a leader opening trajectory, a follower tracking the command, a contact on the follower."""

    def __init__(self, w: dict[str, float]):
        self.w = w
        self.x_f = 0.02
        self.t = 0.0

    def leader(self, t: float) -> tuple[float, float]:
        w = self.w
        a = 2 * math.pi * w["freq"]
        x = 0.0125 + w["amp"] * math.sin(a * t + w["phase"])
        return x, w["amp"] * a * math.cos(a * t + w["phase"])

    def follow(self, t: float, command: float | None) -> None:
        dt = max(0.0, t - self.t)
        self.t = t
        if command is not None:
            self.x_f += (command - self.x_f) * (1.0 - math.exp(-dt / self.w["follower_tau"]))

    def force(self) -> float:
        d = self.w["x_obj"] - self.x_f
        return self.w["k_obj"] * d if d > 0 else 0.0


def run_controller_case(case: Case) -> None:
    """Runs the case; raises Violation (or whatever the controller raised) at the first broken invariant."""
    h = Harness(CLASSES[case.cls], case.params)
    h.comp.configure()
    h.comp.activate()
    oracle = ControllerOracle(h.comp, case.cls)
    world = World(case.world)
    last: dict[str, Sample | None] = {}
    command = None
    for i, (t, ev) in enumerate(case.steps):
        world.follow(t, command)
        x, v = world.leader(t)
        good = {"leader_opening": x, "leader_velocity": v, "follower_opening": world.x_f, "force": world.force()}
        _feed(ev, t, good, last, h.slots, oracle)
        h.t = t
        try:
            out = h.comp.step(t, h.inputs) or {}
        except Violation:
            raise
        except Exception as exc:
            raise Violation("exception", i, f"{type(exc).__name__}: {exc}") from exc
        oracle.check(i, t, out)
        command = out.get("opening_command", command)


# ================================================================================================ shrinking
# ================================================================================================ the fuzz tests
N_CASES = 12
N_STEPS = 4000


@pytest.mark.parametrize("cls", list(CLASSES))
@pytest.mark.parametrize("block", range(2))
def test_fuzz_controller_force_is_finite_limited_rate_limited_and_zero_when_lost(cls, block):
    for j in range(N_CASES // 2):
        seed = 1000 * (list(CLASSES).index(cls) + 1) + block * N_CASES + j
        check_case(random_case(seed, cls, N_STEPS), run_controller_case)


# ================================================================================================ the chain
def random_device(rng: random.Random, device: str) -> dict[str, Any]:
    p: dict[str, Any] = {"max_gripper_force": rng.choice([8.0, 3.0, rng.uniform(0.0, 8.0)]),
                         "command_timeout": rng.choice([0.1, 0.02, 0.005, 1.0, rng.uniform(0.003, 0.3)])}
    if device == "omega7":
        p.update({"firmware_watchdog": 0, "brakes_on_stop": True})
    return p


def random_chain_case(seed: int, cls: str, n_steps: int, device: str) -> Case:
    case = random_case(seed, cls, n_steps, chain=True)
    case.world["device"] = random_device(random.Random(seed + 7), device)
    if device == "sim-omega7":
        # the leader's opening and velocity come from the simulated device (closed loop); the normal events on
        # these ports go, the bad ones (values, stamps, late, future) replace the device's reading
        for _, ev in case.steps:
            for port in ("leader_opening", "leader_velocity"):
                e = ev.get(port)
                if e == "repeat" or (e is not None and e[0] is None and math.isfinite(e[1]) and -0.01 < e[1] <= 0.0):
                    del ev[port]
    return case


#: a leader fades a command that comes back after being stale in over this time (omega7.COMMAND_FADE_IN)
FADE_IN = 0.05


class DeviceOracle:
    """Checks the force a leader really renders: finite, within its limit and the controller's, zero for a stale
    command, and never a step onto the hand beyond max_force_rate (a drop to zero is the safe reaction); for
    FADE_IN after a stale command, the leader's fade-in (limit / FADE_IN) may add to that rate."""

    def __init__(self, ctl_params: Any, dev_params: dict[str, Any]):
        self.limit = min(ctl_params.max_force, dev_params["max_gripper_force"])
        self.rate = ctl_params.max_force_rate
        self.timeout = dev_params["command_timeout"]
        self.g_prev: float | None = None
        self.t_prev = 0.0
        self.t_back: float | None = None         # the first fresh step after a stale command (the fade-in starts)

    def check(self, i: int, t: float, g: float, command: Sample | None, ctl_step: float = 0.0) -> None:
        """``ctl_step``: what the controller's rate limit counted in its step at ``t`` (``min(dt, 2 periods)``; 0
        when it did not run): after a stall the controller moves by that much within one step of the leader."""
        if not (isinstance(g, float) and math.isfinite(g)):
            raise Violation("device: non-finite force", i, f"rendered {g!r}")
        if abs(g) > self.limit + EPS:
            raise Violation("device: beyond the limit", i, f"rendered {g!r} N, limit {self.limit} N")
        if command is not None and not command.is_fresh(t, self.timeout):
            self.t_back = math.nan
            if g != 0.0:
                raise Violation("device: force from a stale command", i, f"rendered {g!r} N")
        elif self.t_back is not None and math.isnan(self.t_back):
            self.t_back = t
        if self.g_prev is not None and g != 0.0:
            fading_in = self.t_back is not None and self.t_prev < self.t_back + FADE_IN
            allowed = (self.rate * max(t - self.t_prev, ctl_step)
                       + (self.limit / FADE_IN * (t - self.t_prev) if fading_in else 0.0))
            if abs(g - self.g_prev) > allowed + EPS * (1.0 + abs(g)):
                raise Violation("device: step onto the hand", i, f"rendered {self.g_prev!r} -> {g!r} N in "
                                                                  f"{t - self.t_prev!r} s (at most {allowed!r} N)")
        self.g_prev, self.t_prev = g, t


def run_chain_case(case: Case, device: str = "sim-omega7", sdk: Any = None) -> None:
    """controller -> leader device, stepped in lockstep; raises Violation at the first broken invariant (controller
    outputs or the force the device rendered)."""
    from teletouch.plugins.devices.omega7 import Omega7
    from teletouch.plugins.devices.omega7 import COMMAND_FADE_IN
    from teletouch.plugins.devices.sim_omega7 import SimOmega7

    assert COMMAND_FADE_IN == FADE_IN

    dev_params = dict(case.world["device"])
    if device == "omega7":
        dev_params["sdk_path"] = str(sdk.folder)
        dev = Harness(Omega7, dev_params)
    else:
        dev = Harness(SimOmega7, dev_params)
    ctl = Harness(CLASSES[case.cls], case.params)
    ctl.comp.configure()
    ctl.comp.activate()
    dev.comp.configure()
    dev.comp.activate()
    try:
        oracle = ControllerOracle(ctl.comp, case.cls)
        dev_oracle = DeviceOracle(ctl.comp.params, dev_params)
        world = World(case.world)
        last: dict[str, Sample | None] = {}
        command = None
        dev_out: dict[str, Any] = {}
        stalled_until = -1
        t_ctl: float | None = None
        for i, (t, ev) in enumerate(case.steps):
            ctl_step = 0.0
            world.follow(t, command)
            x, v = world.leader(t)
            good = {"leader_opening": x, "leader_velocity": v, "follower_opening": world.x_f, "force": world.force()}
            if device == "sim-omega7":
                dev.slots["intent_opening"].sample = Sample(x, t)
                for port, out_port in (("leader_opening", "gripper_opening"), ("leader_velocity", "gripper_velocity")):
                    if out_port in dev_out and port not in ev:
                        s = Sample(dev_out[out_port], dev.t)
                        ctl.slots[port].sample = s
                        oracle.feed(port, s)
            if "skip_ctl" in ev:
                stalled_until = i + ev["skip_ctl"]
            _feed(ev, t, good, last, ctl.slots, oracle)
            if i > stalled_until:
                ctl.t = t
                try:
                    out = ctl.comp.step(t, ctl.inputs) or {}
                except Exception as exc:
                    raise Violation("exception", i, f"controller: {type(exc).__name__}: {exc}") from exc
                oracle.check(i, t, out)
                ctl_step = 0.0 if t_ctl is None else min(max(0.0, t - t_ctl), oracle.max_dt)
                t_ctl = t
                command = out.get("opening_command", command)
                dev.slots["gripper_force"].sample = Sample(out["gripper_force"], t)
            dev.t = t
            try:
                dev_out = dev.comp.step(t, dev.inputs) or {}
            except ComponentFault as exc:
                raise Violation("device fault", i, str(exc)) from exc
            g = sdk.rendered() if device == "omega7" else dev.comp.g_applied
            dev_oracle.check(i, t, g, dev.slots["gripper_force"].sample, ctl_step)
            if device == "sim-omega7" and not all(math.isfinite(dev_out[k]) for k in ("gripper_opening",
                                                                                     "gripper_velocity")):
                raise Violation("device: non-finite state", i, repr(dev_out))
    finally:
        for h in (dev, ctl):
            h.comp.deactivate()
            h.comp.close()


@pytest.mark.parametrize("cls", list(CLASSES))
def test_fuzz_chain_to_sim_omega7_renders_finite_limited_forces(cls):
    for j in range(4):
        seed = 20000 + 100 * list(CLASSES).index(cls) + j
        check_case(random_chain_case(seed, cls, N_STEPS, "sim-omega7"),
                   lambda c: run_chain_case(c, "sim-omega7"))


# ------------------------------------------------------------------------------------ omega7 against the stand-in
class StandInSdk:
    """The C stand-in of libdhd (tests/fakes/dhd_standin.c) built into ``folder``/lib/libdhd.so; ``rendered()``: the
    gripper force it applies (what the operator's hand gets)."""

    def __init__(self, folder: Any):
        import ctypes
        import shutil
        import subprocess
        from pathlib import Path

        self.folder = Path(folder)
        (self.folder / "lib").mkdir(parents=True, exist_ok=True)
        gcc = shutil.which("gcc") or shutil.which("cc")
        assert gcc, "a C compiler (gcc) is needed to build the libdhd stand-in"
        so = self.folder / "lib" / "libdhd.so"
        src = Path(__file__).parent / "fakes" / "dhd_standin.c"
        subprocess.run([gcc, "-shared", "-fPIC", "-O2", "-o", str(so), str(src), "-lm"], check=True,
                       capture_output=True, text=True)
        self.lib = ctypes.CDLL(str(so))
        self._applied = (ctypes.c_double * 4)()
        self._commanded = (ctypes.c_double * 4)()
        self.lib.standin_reset()

    def rendered(self) -> float:
        self.lib.standin_get_forces(self._applied, self._commanded)
        return float(self._applied[3])


@pytest.fixture(scope="module")
def standin_sdk(tmp_path_factory) -> StandInSdk:
    return StandInSdk(tmp_path_factory.mktemp("fdsdk-fuzz"))


@pytest.fixture
def sdk(standin_sdk, monkeypatch) -> StandInSdk:
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    standin_sdk.lib.standin_reset()
    yield standin_sdk
    standin_sdk.lib.standin_reset()


@pytest.mark.parametrize("cls", list(CLASSES))
def test_fuzz_chain_to_omega7_renders_finite_limited_forces(cls, sdk):
    for j in range(3):
        seed = 30000 + 100 * list(CLASSES).index(cls) + j
        case = random_chain_case(seed, cls, N_STEPS, "omega7")
        check_case(case, lambda c: run_chain_case(c, "omega7", sdk))


# ================================================================================================ regressions
# Deterministic tests from the shrunk sequences of what the fuzzing found (each failed before its fix).
def test_regression_a_huge_follower_opening_never_steps_the_force_to_zero():
    # fuzz seed 50096 (position-position): follower openings of 1e30 m and 1e305 m, 0.6 ms apart, were taken as
    # measurements; the differentiated velocity overflowed, kd * inf = NaN, and the force dropped from 8 N to 0 in
    # one step (200 N/s allows 0.2 N). An opening beyond 1 m is now invalid input, like NaN: the coupling fades.
    p = {"max_force": 8.0, "max_force_rate": 200.0, "kp": 400.0, "kd": 0.0, "scale": 0.5, "passivity": False,
         "velocity_cutoff": 400.0}
    with Harness(PositionPosition, p) as h:
        for k in range(100):
            out = h.step(k * 1e-3, leader_opening=0.01, follower_opening=0.02)
        f = [out["gripper_force"]]
        assert f[0] == 8.0
        f.append(h.step(0.100, leader_opening=0.01, follower_opening=Sample(1e30, 0.0994))["gripper_force"])
        f.append(h.step(0.101, leader_opening=0.01, follower_opening=Sample(1e305, 0.1000))["gripper_force"])
        assert h.comp.invalid_inputs == 2
        f += [h.step(0.101 + k * 1e-3, leader_opening=0.01)["gripper_force"] for k in range(1, 300)]
    assert max(abs(b - a) for a, b in zip(f, f[1:])) <= 0.2 + 1e-9
    assert f[-1] == 0.0


@pytest.mark.parametrize("cls", [PositionForce, PositionPosition])
def test_regression_a_huge_leader_opening_is_invalid_input(cls):
    # the same for the leader: 1e30 m is no opening; it no longer reaches the velocity, the damping or the observer
    p = {"leader_damping": 10.0, "passivity": False}
    with Harness(cls, p) as h:
        for k in range(50):
            h.step(k * 1e-3, leader_opening=0.01, follower_opening=0.01, force=Sample(0.0, k * 1e-3))
        out = h.step(0.050, leader_opening=Sample(-1e30, 0.0499), follower_opening=0.01, force=Sample(0.0, 0.05))
        assert h.comp.invalid_inputs == 1 and h.comp.v_l == 0.0 and h.comp.x_l == 0.01
        assert out["opening_command"] == 0.01 and out["gripper_force"] == 0.0


def test_regression_a_subnormal_estimate_never_lets_the_damping_pull():
    # fuzz seed 50127 (position-force): the passivity damping turned the feedback force round into a pull of
    # -alpha * v (0.2 N here, 4 N at 0.1 m/s) because the reversal test f_des * f_fb < 0 underflowed to -0.0 with a
    # subnormal estimate (5e-324 N)
    p = {"deadband": 0.0, "smoothing_time": 0.0, "force_prediction": False, "passivity_observer": "leader-port",
         "max_force_rate": 1000.0}
    with Harness(PositionForce, p) as h:
        f = []
        for k in range(200):
            t = k * 1e-3
            out = h.step(t, leader_opening=0.01 + 0.005 * t, leader_velocity=0.005,
                         force=Sample(3.0 if k < 150 else 5e-324, t))
            f.append(out["gripper_force"])
        assert h.comp.pas.alpha > 0.0           # the damping is at work: the opening fingers have a deficit to pay
    assert min(f) >= 0.0


def test_regression_same_sign_does_not_underflow():
    from teletouch.plugins.controllers.passivity import opposite_signs, reduce_force_to, same_sign

    assert 5e-324 * -0.2 == 0.0                  # (why a product cannot tell the signs)
    assert opposite_signs(5e-324, -0.2) and not same_sign(5e-324, -0.2)
    assert same_sign(-5e-324, -1e-10) and not opposite_signs(0.0, -1.0) and not same_sign(0.0, 1.0)
    assert reduce_force_to(5e-324, -1.0, 1e-10, 1e-3) == 0.0   # the deficit is paid: the force goes, not kept


def test_regression_a_stale_estimate_never_raises_the_force_when_the_leader_comes_back():
    # fuzz seed 50094 (position-force): the leader was lost (the force faded to 0) while the estimate went stale;
    # the leader came back during the estimate's fade and the force rose again towards the stale, fading value
    p = {"deadband": 0.0, "passivity": False, "force_prediction": False, "smoothing_time": 0.0, "stale_after": 0.02,
         "fade_time": 0.05, "max_force_rate": 200.0}
    with Harness(PositionForce, p) as h:
        for k in range(100):
            out = h.step(k * 1e-3, leader_opening=0.02, force=Sample(2.0, k * 1e-3))
        assert out["gripper_force"] == pytest.approx(2.0)
        f = [h.step(0.1 + k * 1e-3, leader_opening=math.nan)["gripper_force"] for k in range(55)]   # leader lost
        assert f[-1] == 0.0 and h.comp.hold.value(h.t) > 0.5                                       # still fading
        f = [h.step(0.155 + k * 1e-3, leader_opening=0.02)["gripper_force"] for k in range(100)]   # leader back
        assert h.comp.leader_ok and h.comp.state == "stale-force"
    assert max(f) == 0.0


def test_regression_sim_omega7_fades_a_command_back_in_after_a_controller_stall():
    # fuzz seed 20001 (controller -> sim-omega7): the controller stalled 50 ms, past command_timeout (20 ms); the
    # leader rendered zero meanwhile (right) and then stepped the controller's old force back onto the hand at once
    from teletouch.plugins.devices.sim_omega7 import SimOmega7

    with Harness(SimOmega7, {"command_timeout": 0.02}) as h:
        g = []
        for k in range(250):
            t = k * 1e-3
            if not 100 <= k < 150:                               # the controller stalls from 0.100 s to 0.150 s
                h.set(gripper_force=Sample(5.0, t))
            h.step(t)
            g.append(h.comp.g_applied)
        status = h.comp.status()
    assert g[99] == 5.0 and g[125] == 0.0                        # zero while the command is stale
    steps = [b - a for a, b in zip(g, g[1:])]
    assert max(steps[100:]) <= 5.0 * 1e-3 / FADE_IN + 1e-9      # faded in (COMMAND_FADE_IN), no step
    assert g[150 + int(FADE_IN * 1e3) + 1] == 5.0
    assert status["faded_in"] == 1


def test_omega7_fades_a_command_back_in_after_a_controller_stall(sdk):
    # fuzz seed 90000 (controller -> omega7 on its stand-in): after a controller stall past command_timeout the
    # device stepped the command back onto the hand (0 -> 5 N in one step); ForceGuard now fades it in, on both leaders
    from teletouch.plugins.devices.omega7 import Omega7

    with Harness(Omega7, {"sdk_path": str(sdk.folder), "command_timeout": 0.02, "firmware_watchdog": 0}) as h:
        g = []
        for k in range(200):
            t = k * 1e-3
            if not 100 <= k < 150:
                h.set(gripper_force=Sample(5.0, t))
            h.step(t)
            g.append(sdk.rendered())
    assert g[99] == pytest.approx(5.0) and g[125] == 0.0
    assert max(b - a for a, b in zip(g, g[1:])) <= 5.0 * 1e-3 / FADE_IN + 1e-9
