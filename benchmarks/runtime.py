"""Runtime benchmark: scheduler overhead, simulated-clock speed, wall-clock jitter under load.

    python benchmarks/runtime.py [--quick]

Prints one JSON object as its last line. Targets (issue 2): <= 5 us scheduler overhead per node step; >= 50x real
time for a 6-node graph on the simulated clock; p99 |period error| <= 0.25 ms for a 1 kHz node while a 60 Hz node
burns 8 ms of CPU per step in numpy; the same under SCHED_FIFO 50 for the 1 kHz thread (``sched_fifo_applied``
says whether the process was allowed it), and with a pure-Python burn inline and in an isolated process. The last two
run side by side for ``isolation_p99_ratio_inline_over_isolated``: ``isolation_rounds`` runs of each, a quarter of the
duration each, alternating (inline, isolated, isolated, inline, ...), their period errors pooled per case (each run's
figures under ``runs``), so that a change of load on the shared machine hits both alike. A run that ends in a fault
(or is stopped) is named on stderr and in ``faulted_runs``, and the exit status is 1.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

from teletouch import Component, Kind, Port, hookimpl
from teletouch.testing import load_text, make_registry
from teletouch.runtime import Runtime
from machine import cpu_times, machine_noise
from bench_common import alternating, emit, sched_fifo_refused, warn_if_no_sched_fifo


class Trivial(Component):
    """Reads one input, writes one output."""
    name = "bench-trivial"
    kind = Kind.ESTIMATOR
    inputs = {"x": Port("float64", (), "", required=False)}
    outputs = {"y": Port("float64", (), "")}

    def step(self, t, inputs):
        s = inputs["x"]
        return {"y": (s.value if s is not None else 0.0) + 1.0}


class Stamp(Component):
    """Records the wall time at which each step starts (for jitter)."""
    name = "bench-stamp"
    kind = Kind.CONTROLLER

    def configure(self):
        self.starts = []

    def step(self, t, inputs):
        self.starts.append(time.perf_counter())
        return None


class Burn(Component):
    """Burns a fixed amount of CPU in numpy each step (like an image estimator)."""
    name = "bench-burn"
    kind = Kind.ESTIMATOR

    class Params(Component.Params):
        ms: float = 8.0

    def configure(self):
        self.a = np.random.default_rng(0).random(100_000)  # ~1 ms per sort: the burn lands close to 8 ms

    def step(self, t, inputs):
        t0 = time.perf_counter()
        end = t0 + self.params.ms * 1e-3
        while time.perf_counter() < end:
            np.sort(self.a)
        return None


class Plugin:
    @hookimpl
    def teletouch_components(self):
        return [Trivial, Stamp, Burn]


REG = make_registry(Plugin())


def overhead(steps_target: int) -> dict:
    n_nodes = 10
    dur = steps_target / (n_nodes * 1000.0)
    text = "clock: sim\nnodes:\n" + "".join(f"  - {{id: n{i}, plugin: noop, rate: 1000}}\n" for i in range(n_nodes))
    rt = Runtime(load_text(text, REG), log=lambda m: None)
    res = rt.run(dur)
    steps = sum(n.steps for n in res.nodes)
    # side by side: a bare Python loop calling the same step functions the same number of times
    fns = [n.step for n in rt.nodes]
    inp = rt.nodes[0].inputs
    t0 = time.perf_counter()
    for k in range(steps // n_nodes):
        t = k * 1e-3
        for f in fns:
            f(t, inp)
    bare = time.perf_counter() - t0
    per = res.wall_time / steps
    return {"status": res.status, "message": res.message,
            "steps": steps, "per_step_us": per * 1e6, "bare_call_us": bare / steps * 1e6,
            "overhead_vs_bare_call_us": (res.wall_time - bare) / steps * 1e6, "target_us": 5.0,
            "pass": per * 1e6 <= 5.0}


SIX = """
clock: sim
nodes:
  - {id: cam1, plugin: bench-trivial, rate: 60}
  - {id: cam2, plugin: bench-trivial, rate: 60, inputs: {x: cam1.y}}
  - {id: est, plugin: bench-trivial, rate: 500, inputs: {x: cam2.y}}
  - {id: ctl, plugin: bench-trivial, rate: 1000, inputs: {x: est.y}}
  - {id: lead, plugin: bench-trivial, rate: 1000, inputs: {x: ctl.y}}
  - {id: foll, plugin: bench-trivial, rate: 1000, inputs: {x: lead.y}}
"""


def sim_speed(duration: float) -> dict:
    rt = Runtime(load_text(SIX, REG), log=lambda m: None)
    res = rt.run(duration)
    return {"status": res.status, "message": res.message,
            "sim_seconds": duration, "wall_seconds": res.wall_time, "realtime_factor": res.realtime_factor,
            "steps": sum(n.steps for n in res.nodes), "target_factor": 50.0, "pass": res.realtime_factor >= 50.0}


def _jitter_run(duration: float, burn_ms: float, priority: int = 0, python_burn: bool = False,
                isolate: bool = False) -> tuple[dict, np.ndarray]:
    """One wall-clock run of the 1 kHz node beside the burn: its figures, and the |period error| (ms) of each of its
    periods after the warm-up."""
    burn = (f"{{id: burn, plugin: mock-burn, rate: 60, params: {{burn: {burn_ms}ms}}"
            + (", isolate: process}" if isolate else "}")) if python_burn else \
        f"{{id: burn, plugin: bench-burn, rate: 60, params: {{ms: {burn_ms}}}}}"
    text = f"""
clock: wall
realtime_priority: {priority}
faults: {{max_overruns: 0}}
nodes:
  - {{id: fast, plugin: bench-stamp, rate: 1000}}
  - {burn}
"""
    rt = Runtime(load_text(text, REG), log=lambda m: None)
    refused = sched_fifo_refused(priority)
    cpu0 = cpu_times()
    res = rt.run(duration)
    noise = machine_noise(cpu0, cpu_times())
    starts = np.array(rt.component("fast").starts)
    periods = np.diff(starts[100:])  # skip warm-up
    err = np.abs(periods - 1e-3) * 1e3
    # the burn node's step times as the runtime measured them (the same for the numpy and the Python burn)
    burn_node = next(n for n in res.nodes if n.id == "burn")
    return {"burn": ("python (holds the GIL)" if python_burn else "numpy") + (", isolated process" if isolate else ""),
            "status": res.status, "message": res.message,
            "duration_s": duration, "steps": int(len(starts)),
            "mean_period_ms": float(periods.mean() * 1e3) if len(periods) else float("nan"),
            "burn_ms_mean": burn_node.mean_step_s * 1e3,
            "burn_steps": burn_node.steps, "overruns": {n.id: n.overruns for n in res.nodes},
            "realtime_priority": priority, "sched_fifo_applied": priority > 0 and refused is None,
            "sched_fifo_refused": refused, "machine_noise": noise}, err


def _period_error(err: np.ndarray) -> dict:
    """p50, p99 and max of the |period errors| ``err`` (ms); NaN (null in the JSON) without any."""
    if not len(err):
        return dict.fromkeys(("p50", "p99", "max"), float("nan"))
    return {"p50": float(np.percentile(err, 50)), "p99": float(np.percentile(err, 99)), "max": float(err.max())}


def jitter(duration: float, burn_ms: float, priority: int = 0, python_burn: bool = False,
           isolate: bool = False) -> dict:
    """The 1 kHz node's |period error| over one wall-clock run beside the burn (:func:`_jitter_run`)."""
    run, err = _jitter_run(duration, burn_ms, priority, python_burn, isolate)
    p = _period_error(err)
    return dict(run, period_error_ms=p, target_p99_ms=0.25, **{"pass": bool(p["p99"] <= 0.25)})


def jitter_side_by_side(cases: dict[str, dict], duration: float, rounds: int, burn_ms: float = 8.0) -> dict:
    """:func:`jitter` of each of ``cases`` (name -> its keyword arguments), side by side: ``rounds`` runs of each,
    of ``duration / rounds`` seconds, alternating (A B, B A, ...), so that a change of load on the shared machine
    hits them alike; the period errors of a case's runs are pooled. Per case: the pooled figures, and each run's
    figures under ``runs``."""
    runs: dict[str, list[dict]] = {name: [] for name in cases}
    errs: dict[str, list[np.ndarray]] = {name: [] for name in cases}
    for name in alternating(list(cases), rounds):
        run, err = _jitter_run(duration / rounds, burn_ms, **cases[name])
        runs[name].append(dict(run, period_error_ms=_period_error(err)))
        errs[name].append(err)
    out = {}
    for name, rs in runs.items():
        pooled = np.concatenate(errs[name]) if errs[name] else np.zeros(0)
        p = _period_error(pooled)
        first = rs[0]
        out[name] = {"burn": first["burn"], "duration_s": duration, "rounds": rounds,
                     "status": "ok" if all(r["status"] == "ok" for r in rs) else
                     next(r["status"] for r in rs if r["status"] != "ok"),
                     "steps": sum(r["steps"] for r in rs), "period_error_ms": p,
                     "realtime_priority": first["realtime_priority"], "sched_fifo_applied": first["sched_fifo_applied"],
                     "sched_fifo_refused": first["sched_fifo_refused"], "target_p99_ms": 0.25,
                     "pass": bool(p["p99"] <= 0.25), "runs": rs}
    return out


def faulted_runs(out: dict) -> list[dict]:
    """The runs of ``out`` (the benchmark's sections) that did not end ``ok``: section, run, status and message."""
    bad = []
    for key, sec in out.items():
        if not isinstance(sec, dict) or "status" not in sec:
            continue
        for i, r in enumerate(sec.get("runs", [sec])):
            if r["status"] != "ok":
                bad.append({"section": key, "run": i, "status": r["status"], "message": r["message"]})
    return bad


#: runs of each of the two Python-burn cases (inline, isolated), alternating: their p99 ratio compares like with like
ISOLATION_ROUNDS = 4


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="shorter runs (CI smoke)")
    args = ap.parse_args(argv)
    out = {"benchmark": "runtime", "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    out["sched_fifo_refused"] = warn_if_no_sched_fifo(50)
    out["scheduler_overhead"] = overhead(50_000 if args.quick else 300_000)
    print(f"overhead: {out['scheduler_overhead']['per_step_us']:.2f} us/step", file=sys.stderr)
    out["sim_clock_6_nodes"] = sim_speed(10.0 if args.quick else 60.0)
    print(f"sim speed: {out['sim_clock_6_nodes']['realtime_factor']:.1f}x real time", file=sys.stderr)
    dur = 5.0 if args.quick else 20.0
    out["wall_clock_jitter"] = jitter(dur, 8.0)
    print(f"jitter p99: {out['wall_clock_jitter']['period_error_ms']['p99']:.3f} ms", file=sys.stderr)
    # the same with SCHED_FIFO for the 1 kHz thread (as ros2_control runs its control loop), where permitted
    out["wall_clock_jitter_sched_fifo"] = jitter(dur, 8.0, priority=50)
    print(f"jitter p99 (SCHED_FIFO): {out['wall_clock_jitter_sched_fifo']['period_error_ms']['p99']:.3f} ms",
          file=sys.stderr)
    # an estimator that holds the GIL (pure Python) in the same process, and the same isolated in a process: side
    # by side, in alternating runs
    pair = jitter_side_by_side({"python_burn_inline": {"priority": 50, "python_burn": True, "isolate": False},
                                "python_burn_isolated": {"priority": 50, "python_burn": True, "isolate": True}},
                               dur, ISOLATION_ROUNDS)
    for key, r in pair.items():
        out[f"wall_clock_jitter_{key}"] = r
        print(f"jitter p99 ({key}, SCHED_FIFO, {r['rounds']} alternating runs): "
              f"{r['period_error_ms']['p99']:.3f} ms", file=sys.stderr)
    a = out["wall_clock_jitter_python_burn_inline"]["period_error_ms"]["p99"]
    b = out["wall_clock_jitter_python_burn_isolated"]["period_error_ms"]["p99"]
    out["isolation_p99_ratio_inline_over_isolated"] = a / b if b > 0 else None
    out["isolation_rounds"] = ISOLATION_ROUNDS
    # a run that ended in a fault (or was stopped) has no figures: named here, and the benchmark fails
    out["faulted_runs"] = faulted = faulted_runs(out)
    for f in faulted:
        print(f"{f['section']} run {f['run']}: ended {f['status']}: {f['message']}", file=sys.stderr)
    emit(out)
    return 1 if faulted else 0


if __name__ == "__main__":
    sys.exit(main())
