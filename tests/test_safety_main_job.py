"""Fault injection into the main job, end to end: the simulated paper graph (examples/paper-sim.yaml, built by
``experiments.sim_graph`` / ``build_runtime``), simulated clock, deterministic.

For each node (leader sim-omega7, gripper sim-gripper, digit sim-digit, depth, force poly-force, controller
position-force) a fault is injected at 2.5 s (the fingers squeeze the 15 mm object: they reach it at ~1.5 s) and at
0.8 s (free motion, the fingers closing): step() raises (RuntimeError; SystemExit for the controller; HardwareError
for the two devices), NaN in every float output, outputs that stop (stale), a value of the wrong type; under
``on_fault: stop`` (the default) and, for raise and stale, ``degrade``. How: tests/fakes/fault_injection.py (one
shared warm-up up to the fault time, then one forked child per case; the parent goes on as the fault-free baseline).

The promises checked on every step of the leader and the follower after the fault (README, docs/teleoperation.md,
docs/graphs.md): the force sent to the hand is finite, within the controller's max_force, rises no faster than
max_force_rate, and is 0 from a deadline on (the documented detection time of the lost source plus fade_time; or the
run stopped and the leader's safe_state() left it at 0); the follower's opening stays within 0.5 mm of its opening at
the fault (it holds: neither opens nor squeezes harder); the run ends as documented (fault, exit 3; degraded, exit 3);
every device's safe_state() is called.

In free motion a lost estimate is noticed after stale_after plus a frame: those cases (DETECTION_LAG below) assert
that bound instead of the 0.5 mm band.
"""

from __future__ import annotations

import math
import time

import pytest

from teletouch.plugins.controllers.experiments import DEFAULT_INTENT, build_runtime, sim_graph
from teletouch.plugins.controllers.position_force import PositionForce
from teletouch.plugins.sensors.sim_digit import INPUT_MAX_AGE

from tests.fakes.fault_injection import Case, Injector, Observed

PHASES = {"contact": 2.5, "free": 0.8}   # fault times (s)
WINDOW = 1.0                              # s of graph time observed after the fault
BAND = 0.5e-3                             # m: the follower holds within this of its opening at the fault
HAND_SPEED = DEFAULT_INTENT["speed"]      # m/s: the simulated operator closes the hand this fast
NODES = ("leader", "gripper", "digit", "depth", "force", "controller")
DEVICES = ("leader", "gripper")
FORCE_PATH = ("digit", "depth", "force")


def all_cases() -> list[Case]:
    cases = []
    for node in NODES:
        kinds = ["raise", "nan", "stale", "type"] + (["hardware"] if node in DEVICES else [])
        cases += [Case(node, k) for k in kinds]
        cases += [Case(node, k, "degrade") for k in ("raise", "stale")]
    cases.append(Case("controller", "exit"))
    return cases


CASES = all_cases()

#: NaN in outputs that no node of the graph reads (sim-digit's ground truth gt_*: its one wired output, the image,
#: is uint8 and cannot be NaN): no fault reaches the job; it must run exactly as the fault-free baseline
NO_EFFECT = {("digit", "nan", "stop")}

# ------------------------------------------------------------------------------------------ known defects
# Fixed (plain tests now): SQUEEZE in contact (position-force holds the follower command while the estimate is
# lost: hold_on_lost_force), FOLLOWER_BLIND (the controller's follower_opening wire has a max_age, checked from
# sim_graph's startup_grace of 0.1 s on), SILENT for a lost leader, controller or estimate (the 1 kHz wires' max_age;
# position-force's fault_after_lost, 0.5 s).

#: The estimate is noticed lost only after stale_after (0.1 s) plus up to one camera frame: in free motion the hand
#: closes at 5 mm/s meanwhile, and the held command is 0.507 mm from the opening at the fault (the band for these
#: cases: what the hand covers in stale_after + one frame, 0.58 mm); in contact the object blocks the follower and
#: the grip holds within the 0.5 mm band. A NaN depth is one of these:
#: poly-force gives no force for an invalid input (it gave a fresh 0 N, which the controller could not tell from a
#: real one: the follower followed the operator's closing hand onto the object, 1.2 -> 10 N of grip, and the run
#: ended ok), so the controller sees the estimate go stale.
DETECTION_LAG = ({(n, "stale", "stop") for n in FORCE_PATH} | {(n, k, "degrade") for n in FORCE_PATH
                                                              for k in ("raise", "stale")} | {("depth", "nan", "stop")})


def key(case: Case) -> tuple[str, str, str]:
    return (case.node, case.kind, case.policy)


# ------------------------------------------------------------------------------------------ the runs
_RUNS: dict[str, dict] = {}


def params_of(rt) -> dict[str, float]:
    ctl, leader = rt.component("controller").params, rt.component("leader").params
    return {"max_force": ctl.max_force, "max_force_rate": ctl.max_force_rate, "fade_time": ctl.fade_time,
            "stale_after": ctl.stale_after, "leader_stale_after": ctl.leader_stale_after,
            "command_timeout": leader.command_timeout, "device_max_force": leader.max_gripper_force,
            "camera_period": 1.0 / next(n.rate for n in rt.nodes if n.id == "digit")}


def run_phase(phase: str, cases: list[Case] = CASES, **graph_kw) -> dict:
    """Run the main job once up to the fault time of ``phase`` and every case from there (cached per phase)."""
    cache = not graph_kw and cases is CASES
    if cache and phase in _RUNS:
        return _RUNS[phase]
    tf = PHASES[phase]
    w0 = time.perf_counter()
    rt = build_runtime(sim_graph(duration=tf + WINDOW, **graph_kw))
    params = params_of(rt)
    results, baseline = Injector(rt, tf, cases).run()
    run = {"tf": tf, "results": results, "baseline": baseline, "params": params, "wall_s": time.perf_counter() - w0}
    if cache:
        _RUNS[phase] = run
    return run


def deadline(case: Case, tf: float, p: dict[str, float]) -> float:
    """When the hand's force must be 0 (or the run stopped): the documented time to notice the lost source, plus
    position-force's fade_time; 2 ms for the 1 kHz steps."""
    slack = 0.002
    if case.node == "controller":      # the leader zeroes a command older than its command_timeout
        return tf + p["command_timeout"] + slack
    if case.node == "leader":          # the controller: leader_stale_after, then a fade over fade_time
        return tf + p["leader_stale_after"] + p["fade_time"] + slack
    # the force estimate: stale after stale_after (its stamp is its camera frame's: up to a frame older), then the
    # fade; the follower's outputs are noticed by sim-digit's input check (INPUT_MAX_AGE) first
    d = tf + p["stale_after"] + p["fade_time"] + p["camera_period"] + slack
    return d + INPUT_MAX_AGE if case.node == "gripper" else d


# ------------------------------------------------------------------------------------------ the checks
def check_hand_force(o: Observed, case: Case, tf: float, p: dict[str, float]) -> None:
    """Finite, within max_force, no faster rise than max_force_rate, 0 from the deadline on, 0 at the end."""
    limit = min(p["max_force"], p["device_max_force"])
    prev_t, prev_g = tf, o.g_fault
    for t, g, cmd, _raised in o.leader:
        assert math.isfinite(g) and abs(g) <= limit, f"t={t:.3f} s: the leader rendered {g} N (limit {limit} N)"
        if cmd is not None and not (case.node == "controller" and case.kind == "nan"):   # (that NaN is injected)
            assert math.isfinite(cmd) and abs(cmd) <= p["max_force"], \
                f"t={t:.3f} s: the controller commanded {cmd} N to the hand (limit {p['max_force']} N)"
        rise = abs(g) - abs(prev_g)
        assert rise <= p["max_force_rate"] * max(t - prev_t, 1e-3) + 1e-9, \
            f"t={t:.3f} s: the force on the hand rose by {rise:.4f} N in {t - prev_t:.4f} s"
        prev_t, prev_g = t, g
    due = deadline(case, tf, p)
    late = [(t, g) for t, g, _c, _r in o.leader if t >= due and g != 0.0]
    assert not late, (f"the hand still felt {late[0][1]:.4f} N at t={late[0][0]:.3f} s, {late[-1][1]:.4f} N at "
                      f"t={late[-1][0]:.3f} s (expected 0 from t={due:.3f} s)")
    calls = [(t, g) for d, t, g in o.safe_calls if d == "leader"]
    assert calls, "the leader's safe_state() was never called"
    assert calls[-1][1] == 0.0 and o.leader_end["gripper_force_n"] == 0.0 and o.leader_end["safe"], \
        f"the leader ended with {o.leader_end}"
    after = [t for t, *_ in o.leader if t > calls[-1][0]]
    assert not after, f"the leader was stepped at t={after[0]:.3f} s after its last safe_state()"


def check_follower_holds(o: Observed, case: Case, band: float = BAND) -> None:
    """Every step after the fault within ``band`` of the opening at the fault; a follower made safe holds there."""
    worst = max(o.follower, key=lambda r: abs(r[1] - o.x_fault), default=None)
    if worst is not None:
        t, x, f = worst
        assert abs(x - o.x_fault) <= band, (
            f"the follower moved from {o.x_fault * 1e3:.3f} mm at the fault to {x * 1e3:.3f} mm at t={t:.3f} s "
            f"(grip force {f:.2f} N; band {band * 1e3:g} mm)")
    end = o.follower_end
    assert end["safe"], f"the follower did not end in its safe state: {end}"
    assert abs(end["setpoint_m"] - o.x_fault) <= band, \
        f"the follower's safe set-point is {end['setpoint_m'] * 1e3:.3f} mm (at the fault: {o.x_fault * 1e3:.3f} mm)"


def check_status(o: Observed, case: Case, tf: float) -> None:
    want = ("fault", 3) if case.policy == "stop" else ("degraded", 3)
    assert (o.status, o.exit_code) == want, f"the run ended {o.status!r}, exit {o.exit_code}: {o.message}"
    assert o.faults and o.faults[0]["time"] >= tf, f"a fault before the injection: {o.faults}"


def check_devices_safe(o: Observed, tf: float) -> None:
    for dev in DEVICES:
        times = [t for d, t, _g in o.safe_calls if d == dev]
        assert times and times[0] >= tf, f"{dev}: safe_state() calls after the fault at t={tf}: {times}"


# ------------------------------------------------------------------------------------------ the tests

def params(check: str) -> list:
    return [pytest.param(phase, case, id=f"{phase}-{case.id}") for phase in PHASES for case in CASES]


def observed(phase: str, case: Case) -> tuple[Observed, dict]:
    run = run_phase(phase)
    o = run["results"][case.id]
    assert o.error is None, o.error
    return o, run


@pytest.mark.parametrize("phase,case", params("force"))
def test_hand_force_finite_limited_and_faded(phase, case):
    o, run = observed(phase, case)
    if key(case) in NO_EFFECT:
        assert [r[:2] for r in o.leader] == [r[:2] for r in run["baseline"].leader]
        return
    check_hand_force(o, case, run["tf"], run["params"])


@pytest.mark.parametrize("phase,case", params("follower"))
def test_follower_holds_its_opening(phase, case):
    o, run = observed(phase, case)
    if key(case) in NO_EFFECT:
        assert o.follower == run["baseline"].follower
        return
    band = BAND
    if key(case) in DETECTION_LAG and phase == "free":
        # the hold starts when the loss is noticed: until then the follower follows the closing hand, so the band
        # is what the hand covers in stale_after plus one camera frame (0.58 mm; 0.507 mm measured); without the
        # hold the follower closed 4.6 mm
        p = run["params"]
        band = HAND_SPEED * (p["stale_after"] + p["camera_period"])
    check_follower_holds(o, case, band)


@pytest.mark.parametrize("phase,case", params("status"))
def test_run_ends_as_documented(phase, case):
    o, run = observed(phase, case)
    if key(case) in NO_EFFECT:
        assert (o.status, o.exit_code, o.faults) == ("ok", 0, [])
        return
    check_status(o, case, run["tf"])


@pytest.mark.parametrize("phase,case", params("safe"))
def test_every_device_made_safe(phase, case):
    o, run = observed(phase, case)
    check_devices_safe(o, run["tf"])


@pytest.mark.parametrize("phase", PHASES)
def test_fault_times_are_in_contact_and_in_free_motion(phase):
    """The baseline (no fault) at the fault time: in contact with a felt force at 2.5 s, and still feeling it at
    the latest deadline (so a force of 0 there is the fault's doing); not in contact at 0.8 s, fingers closing."""
    run = run_phase(phase)
    b, p, tf = run["baseline"], run["params"], run["tf"]
    assert b.error is None and b.status == "ok"
    if phase == "contact":
        assert b.contact_fault and b.g_fault > 0.5
        latest = max(deadline(c, tf, p) for c in CASES)
        assert min(g for t, g, _c, _r in b.leader if t >= latest) > 0.5
        assert max(abs(x - b.x_fault) for _t, x, _f in b.follower) < 0.1e-3   # the baseline holds the grip
    else:
        assert not b.contact_fault and b.g_fault == 0.0
        assert b.x_fault - min(x for _t, x, _f in b.follower) > 2e-3            # the baseline closes on
    assert len(run["results"]) == len(CASES)


def test_checks_catch_a_broken_controller_and_a_follower_that_opens(monkeypatch):
    """The test of the test: a controller that keeps the last force on a stale estimate (its fade removed), and a
    follower whose safe state opens (safe_mode: open): the checks above must fail on them."""
    monkeypatch.setattr(PositionForce, "_fade", lambda self, t: None)
    cases = [Case("force", "stale"), Case("controller", "raise")]
    run = run_phase("contact", cases, gripper_params={"safe_mode": "open"})
    stale, ctl = run["results"]["force-stale"], run["results"]["controller-raise"]
    assert stale.error is None and ctl.error is None
    with pytest.raises(AssertionError, match="the hand still felt"):
        check_hand_force(stale, cases[0], run["tf"], run["params"])
    with pytest.raises(AssertionError, match="safe set-point"):
        check_follower_holds(ctl, cases[1])
    # and the same checks pass on the same cases with the real controller and follower
    monkeypatch.undo()
    good = run_phase("contact")
    check_follower_holds(good["results"]["controller-raise"], cases[1])
    check_hand_force(good["results"]["force-stale"], cases[0], good["tf"], good["params"])
