"""The benchmarks' ratios come from cases timed side by side in alternating rounds, not from whole runs one after
the other: a burst of load on the shared machine during one block moved the ratio. Timings here are fakes (a clock
that the fake work advances): the interleaving and the arithmetic are tested, never the machine's speed."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from helpers_scripts import load_bench, load_follower_bench


@pytest.fixture()
def bench_common(monkeypatch):
    return load_bench(monkeypatch, "bench_common.py", "bench_common_s14")


class FakeClock:
    """A wall (and CPU) clock that only the fake work moves."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _fake_run(name: str, cost: float, clock: FakeClock, order: list, end: float = 3.0, step: float = 0.1):
    """A run of ``end`` simulated s in steps of ``step``, each costing ``cost`` s of the fake clock, reporting its
    progress at every step (as Runtime.run's progress callback does)."""
    def run(checkpoint):
        k = 0
        while k * step < end - 1e-9:
            k += 1
            clock.now += cost
            order.append(name)
            checkpoint(k * step)
        clock.now += 100.0   # the shut-down: never timed
        return f"{name} done"
    return run


# --- bench_common.in_turns: whole runs, timed side by side in alternating turns ------------------------------------

def test_in_turns_alternates_the_runs_and_times_only_their_turns(bench_common):
    clock, order, ready = FakeClock(), [], []
    runs = {"a": _fake_run("a", 0.01, clock, order), "b": _fake_run("b", 0.03, clock, order)}
    marks = [0.5, 1.0, 1.5, 2.0, 2.5]
    results, turns = bench_common.in_turns(runs, marks, ready=lambda: ready.append(list(order)), clock=clock,
                                           cpu=clock)
    assert results == {"a": "a done", "b": "b done"}
    # start-up to the first mark one after the other, then ready(), then 4 rounds: a b, b a, a b, b a
    assert ready == [["a"] * 5 + ["b"] * 5]
    blocks = [order[0]] + [y for x, y in zip(order, order[1:]) if x != y]
    assert blocks == ["a", "b", "a", "b", "a", "b", "a", "b"], blocks   # (a)(b) | a b | b a | a b | b a -> merged
    for name, cost in (("a", 0.01), ("b", 0.03)):
        assert [t["round"] for t in turns[name]] == [0, 1, 2, 3]
        assert all(not t["ended"] for t in turns[name])
        assert [t["progress"] for t in turns[name]] == pytest.approx([0.5] * 4)
        assert [t["wall_s"] for t in turns[name]] == pytest.approx([5 * cost] * 4)   # 5 steps a turn, no shut-down
        assert [t["cpu_s"] for t in turns[name]] == pytest.approx([5 * cost] * 4)


def test_in_turns_a_run_that_ends_early_is_marked_and_the_others_go_on(bench_common):
    clock, order = FakeClock(), []
    runs = {"short": _fake_run("short", 0.01, clock, order, end=1.2),
            "long": _fake_run("long", 0.01, clock, order)}
    results, turns = bench_common.in_turns(runs, [0.5, 1.0, 1.5, 2.0], clock=clock, cpu=clock)
    assert results == {"short": "short done", "long": "long done"}
    assert [t["ended"] for t in turns["short"]] == [False, True]   # its second turn is its end (and shut-down)
    assert turns["short"][1]["wall_s"] > 100.0
    assert [t["round"] for t in turns["long"]] == [0, 1, 2] and not any(t["ended"] for t in turns["long"])


def test_in_turns_says_which_run_raised(bench_common):
    def boom(checkpoint):
        checkpoint(0.6)
        raise ValueError("boom")

    clock, order = FakeClock(), []
    with pytest.raises(RuntimeError, match="'bad'.*ValueError: boom"):
        bench_common.in_turns({"ok": _fake_run("ok", 0.01, clock, order), "bad": boom}, [0.5, 1.0, 1.5],
                              clock=clock, cpu=clock)


# --- teleop_loop: image_chain_cost_ratio from the chains' runs side by side ----------------------------------------

class FakeRuntime:
    """A stand-in for the simulated loop's Runtime: each simulated ms costs the chain's share of the fake clock."""

    COST = {"image": 2e-4, "noise": 3e-4, "ideal": 5e-5}   # wall s per simulated ms: image 5x, noise 3.33x, ideal 20x

    def __init__(self, doc: dict, clock: FakeClock, order: list):
        plugins = {n["plugin"]: n for n in doc["nodes"]}
        self.chain = ("ideal" if "sim-force-sensor" in plugins else
                      "noise" if plugins["sim-digit"]["params"].get("noise") else "image")
        self.duration, self.clock, self.order = doc["duration"], clock, order

    def run(self, progress=None, progress_interval=0.5):
        steps = int(round(self.duration * 1000))
        for k in range(1, steps + 1):
            self.clock.now += self.COST[self.chain]
            self.order.append(self.chain)
            if progress is not None and k % 300 == 0:   # every 0.3 simulated s, as every 1024 steps does
                progress(self, k / 1000)
        node = SimpleNamespace(id="controller", mean_step_s=1e-6, steps=steps)
        return SimpleNamespace(sim_time=self.duration, wall_time=1.0, realtime_factor=1.0, status="ok",
                               message=f"ran {self.duration:.3f} s", nodes=[node])


@pytest.fixture()
def teleop_bench(monkeypatch):
    return load_bench(monkeypatch, "teleop_loop.py", "teleop_loop_s14")


def test_teleop_image_chain_cost_ratio_times_the_chains_side_by_side(teleop_bench, monkeypatch, capsys):
    """image_chain_cost_ratio divided the steady factors of the ideal and the image chains' whole runs, one after
    the other: load on the shared machine during either run moved it. The chains' runs now alternate in turns."""
    import json

    import bench_common

    clock, order = FakeClock(), []
    monkeypatch.setattr(teleop_bench, "build_runtime", lambda doc: FakeRuntime(doc, clock, order))
    monkeypatch.setattr(teleop_bench, "step_costs", lambda n: {"x": 1.0})
    monkeypatch.setattr(teleop_bench, "in_turns", lambda runs, marks, ready=None: bench_common.in_turns(
        runs, marks, ready, clock=clock, cpu=clock), raising=False)
    monkeypatch.setattr(sys, "argv", ["teleop_loop.py", "--wall-configs", ""])
    assert teleop_bench.main() == 0
    got = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # the three whole runs (one after the other), then the three again in 10 rounds of alternating turns
    blocks = [order[0]] + [y for x, y in zip(order, order[1:]) if x != y]
    assert blocks[:3] == ["image", "noise", "ideal"] and len(blocks) >= 3 + 3 + 2 * 9, blocks
    rounds = got["sim_rounds"]
    assert rounds["rounds"] == 10 and rounds["timed_from_s"] == 0.5 and rounds["timed_to_s"] == 9.5
    chains = rounds["chains"]
    assert chains["image"]["realtime_factor_steady"] == pytest.approx(5.0)
    assert chains["noise"]["realtime_factor_steady"] == pytest.approx(1 / 0.3)
    assert chains["ideal"]["realtime_factor_steady"] == pytest.approx(20.0)
    assert all(c["turns"] == 10 and c["status"] == "ok" for c in chains.values())
    assert got["image_chain_cost_ratio"] == pytest.approx(4.0)
    spread = got["image_chain_cost_ratio_rounds"]
    assert spread["rounds"] == 10 and spread["min"] == pytest.approx(4.0) and spread["max"] == pytest.approx(4.0)
    assert rounds["noise_cost_ratio"]["ratio"] == pytest.approx(1.5)
    assert got["faulted_runs"] == []


def test_teleop_round_ratio_spread_is_round_by_round(teleop_bench):
    num = {"realtime_factor_steady": 20.0, "per_round": {0: 30.0, 1: 20.0, 2: 10.0}}
    den = {"realtime_factor_steady": 5.0, "per_round": {0: 10.0, 1: 5.0, 2: 1.0}}
    r = teleop_bench.round_ratio(num, den)
    assert r == {"ratio": 4.0, "rounds": 3, "min": 3.0, "median": 4.0, "max": 10.0}


def test_teleop_round_factors_leave_out_a_turn_that_ended_its_run(teleop_bench):
    turns = [{"round": 0, "wall_s": 0.1, "cpu_s": 0.05, "progress": 1.0, "ended": False},
             {"round": 1, "wall_s": 0.3, "cpu_s": 0.15, "progress": 1.0, "ended": False},
             {"round": 2, "wall_s": 9.0, "cpu_s": 9.0, "progress": 0.0, "ended": True}]
    f = teleop_bench.round_factors(turns)
    assert f["realtime_factor_steady"] == pytest.approx(5.0) and f["realtime_factor_steady_cpu"] == pytest.approx(10.0)
    assert f["turns"] == 2 and f["per_round"] == {0: pytest.approx(10.0), 1: pytest.approx(10 / 3)}


# --- ros2_latency: the cases in alternating rounds, their messages pooled ------------------------------------------

@pytest.fixture()
def ros2_bench(monkeypatch):
    for var in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY"):   # main sets them
        monkeypatch.setenv(var, "0")
    return load_bench(monkeypatch, "ros2_latency.py", "ros2_latency_s14")


def _fake_round(rate: float, latency: float, seconds: float, keep_every: int = 1) -> dict:
    """What a round sees: messages every 1/rate s of the publisher's ramp (its graph time) from 2 s, arriving
    ``latency`` after their stamp, every ``keep_every``-th one (the others lost); graph outputs 1 ms later."""
    import numpy as np

    n = int(round(seconds * rate))
    ramp = 2.0 + np.arange(n) / rate
    stamp = 1.7e9 + ramp
    arr = np.stack([stamp + latency, stamp, ramp], axis=1)[::keep_every]
    outs = np.stack([ramp + latency + 1e-3, ramp, ramp], axis=1)[::keep_every]
    return {"published": n + int(2 * rate), "received": len(arr) + 5, "arrivals": arr, "outputs": outs}


def test_ros2_cases_alternate_in_rounds_and_the_ratio_is_of_the_pooled_rounds(ros2_bench, monkeypatch, capsys):
    """Each case was one whole run with its own publisher process, one after the other: khz_vs_camera_transport_p50_
    ratio divided p50s measured at different times. The cases now alternate in rounds."""
    import json

    calls: list[tuple[float, str, float]] = []

    def fake(rate, rel, duration, domain, tmp):
        calls.append((rate, rel, duration))
        slow = 2.0 if sum(c[:2] == (rate, rel) for c in calls) == 2 else 1.0   # every case's 2nd round: loaded
        return _fake_round(rate, (1e-3 if rate == 60.0 else 0.5e-3) * slow, duration + 1.0)
    monkeypatch.setattr(ros2_bench, "run_round", fake)
    monkeypatch.setattr(sys, "argv", ["ros2_latency.py", "--quick"])
    ros2_bench.main()
    got = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    cases = [(60.0, "reliable"), (60.0, "best_effort"), (1000.0, "reliable"), (1000.0, "best_effort")]
    assert calls == [c + (1.0,) for c in cases + cases[::-1]]   # 2 rounds of 1 s each, the order reversed
    assert got["rounds"] == 2 and got["round_duration_s"] == 1.0 and got["duration_s"] == 2.0
    cam = got["cases"][0]
    assert cam["rounds"] == 2 and cam["round_transport_p50_ms"] == pytest.approx([1.0, 2.0], rel=1e-3)
    assert cam["published"] == 2 * (120 + 120) and cam["received"] == 2 * (120 + 5)
    # the two rounds' 120 messages each, pooled
    assert got["camera_rate_transport_p50_ms"] == pytest.approx(1.5, rel=1e-3)
    assert got["khz_vs_camera_transport_p50_ratio"] == pytest.approx(0.5, rel=1e-3)
    spread = got["khz_vs_camera_transport_p50_ratio_rounds"]
    assert spread["rounds"] == 2
    assert spread["min"] == pytest.approx(0.5, rel=1e-3) and spread["max"] == pytest.approx(0.5, rel=1e-3)


def test_ros2_case_figures_pool_rate_and_losses_over_the_rounds(ros2_bench):
    rounds = [_fake_round(1000.0, 1e-3, 2.0), _fake_round(1000.0, 1e-3, 2.0, keep_every=2)]
    c = ros2_bench.case_figures(1000.0, "reliable", rounds)
    assert c["rounds"] == 2 and c["achieved_rate_hz"] == pytest.approx(1000.0 * (1999 + 999) / (1999 + 1998), rel=1e-6)
    assert c["loss_fraction"] == pytest.approx(1.0 - 3000 / (2000 + 1999), rel=1e-6)   # spans 1.999 + 1.998 s
    assert c["transport_latency_ms"]["p50"] == pytest.approx(1.0, rel=1e-3)
    assert c["graph_latency_ms"]["p50"] == pytest.approx(2.0, rel=1e-3)   # output 1 ms after arrival
    empty = ros2_bench.case_figures(60.0, "reliable", [dict(rounds[0], arrivals=rounds[0]["arrivals"][:0],
                                                            outputs=rounds[0]["outputs"][:0])])
    assert empty["achieved_rate_hz"] == 0.0 and empty["loss_fraction"] is None
    assert empty["transport_latency_ms"]["p50"] is None and empty["round_transport_p50_ms"] == [None]


# --- follower_latency: PAL's round trips in the rounds too, its emulator stopped outside its turns ------------------

@pytest.fixture()
def follower_bench(monkeypatch):
    return load_follower_bench(monkeypatch, "follower_latency_s14")


class FakeEmulator:
    """An emulator that says whether it is running; ``pausable`` as the PAL process is."""

    def __init__(self, name: str, log: list, pausable: bool):
        self.name, self.log, self.running = name, log, True
        if pausable:
            self.pause = lambda: self._set(False)
            self.resume = lambda: self._set(True)

    def _set(self, running: bool) -> None:
        self.running = running
        self.log.append((self.name, "resume" if running else "pause"))

    def stop(self) -> None:
        self.log.append((self.name, "stop"))


def _fake_driver(name: str, log: list, emus: dict):
    """A driver class whose commands are logged with the emulators running at that moment."""
    from teletouch.component import Sample

    class Driver:
        def __init__(self, params, node_id, ctx):
            self.target, self._last_reading = 0.0, None

        def configure(self):
            pass

        def activate(self):
            pass

        def _hw_write(self, target):
            self.target = target
            log.append((name, "write", tuple(sorted(k for k, e in emus.items() if e.running))))

        def _hw_read(self):
            return SimpleNamespace(opening=self.target, mono=0.0)

        def step(self, t, inputs):
            self._hw_write(inputs["opening_command"].value)
            self._last_reading = SimpleNamespace(mono=t)
            return {"opening": Sample(self.target, t)}

        def safe_state(self):
            pass

        def deactivate(self):
            pass

        def close(self):
            pass
    Driver.name = name
    return Driver


def test_follower_pal_case_is_in_the_rounds_with_its_emulator_stopped_outside_its_turns(follower_bench):
    """PAL's round trips were timed in a block of their own, after the others: its ratio to the others compared
    times taken at different moments. Its emulator (1 kHz /joint_states from another process) would load the
    others' round trips: it now runs only in PAL's turns, stopped outside them."""
    log: list = []
    emus: dict = {}

    def spec(key, pausable):
        def setup():
            emus[key] = FakeEmulator(key, log, pausable)
            return emus[key]
        return (key, _fake_driver(key, log, emus), {}, setup)

    specs = {"dyn": spec("dyn", False), "can": spec("can", False), "pal": spec("pal", True)}
    res = follower_bench.side_by_side(specs, 40, 0.01)
    assert all(r["round_trips"] == 40 and r["round_trip_timeouts"] == 0 and r["rounds"] == 10 for r in res.values())
    writes = [(who, running) for who, what, *rest in log if what == "write" for running in rest]
    # the PAL emulator runs for every PAL command and for no other driver's
    assert all(("pal" in running) == (who == "pal") for who, running in writes), writes
    order = [who for who, _ in writes]
    switches = sum(a != b for a, b in zip(order, order[1:]))
    assert order.count("pal") > 40 and switches >= 2 * 10, switches   # round trips, then update-rate steps
    assert log[-1] == ("pal", "stop") and ("pal", "resume") in log[-3:]   # running again for its safe state


def test_follower_main_puts_pal_in_the_rounds(follower_bench, monkeypatch, capsys):
    import json

    seen: dict = {}
    alone: list[str] = []

    def fake_side_by_side(specs, n, seconds, rounds=10):
        seen["keys"] = list(specs)
        return {k: {"round_trip_ms_p50": 2.0 if k == "dynamixel-1000000" else 1.0} for k in specs}

    def fake_bench(name, *a, **k):
        alone.append(name)
        return {"round_trip_ms_p50": None}
    monkeypatch.setattr(follower_bench, "side_by_side", fake_side_by_side)
    monkeypatch.setattr(follower_bench, "bench", fake_bench)
    monkeypatch.setattr(follower_bench, "ros2_missing", lambda: None)
    assert follower_bench.main(["--quick"]) == 0
    got = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert seen["keys"] == ["dynamixel-57600", "dynamixel-1000000", "canopen-virtual", "pal-ros2-loopback"]
    assert alone == ["sim-gripper"]
    assert got["rounds"]["interleaved"] == seen["keys"] and got["rounds"]["alone"] == ["sim-gripper"]
    assert got["round_trip_p50_ratio_to_dynamixel_1mbaud"]["pal-ros2-loopback"] == 0.5


def test_follower_pal_process_is_stopped_and_continued(follower_bench, monkeypatch):
    """The pause is a real SIGSTOP (the process's state T), undone by resume and before the stop."""
    import subprocess

    def state(pid: int, stopped: bool = True) -> str:
        # the signal is delivered asynchronously: wait (up to 5 s) for the state it brings
        deadline = time.monotonic() + 5
        while True:
            st = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            if (st == "T") == stopped or time.monotonic() > deadline:
                return st
            time.sleep(0.005)

    monkeypatch.setattr(follower_bench, "RESUME_SETTLE_S", 0.0)
    pal = object.__new__(follower_bench.PalProcess)
    pal.proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE,
                                text=True)
    pal.paused_at = None
    try:
        pal.pause()
        assert state(pal.proc.pid) == "T"
        pal.pause()   # twice: still one pause
        pal.resume()
        assert state(pal.proc.pid, stopped=False) != "T" and pal.paused_at is None
        pal.pause()
        pal.stop()   # continued first, then its stdin closed: it ends by itself
        assert pal.proc.returncode == 0
    finally:
        if pal.proc.poll() is None:
            pal.proc.kill()
