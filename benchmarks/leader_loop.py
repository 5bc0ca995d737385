"""Haptic loop rate of the omega7 driver against the stand-in libdhd (tests/fakes/dhd_standin.c), in wall-clock time.

For each rate (1 kHz, 4 kHz) it runs a graph `force source -> omega7` on the core runtime with the wall clock and
reports the achieved rate, the p99 period jitter and the overruns, next to the same graph with `sim-omega7` (pure
Python physics) as a reference. It also times the raw ctypes calls of one driver cycle (3 reads + button + one force
write) and one full driver step() outside the runtime, each side by side with its reference (the bare ctypes calls,
sim-omega7's step) in alternating rounds. Each loop runs under normal scheduling and again under
SCHED_FIFO (``--realtime-priority``, default 20; 0: not); where the process may not use SCHED_FIFO the runs say so
(``sched_fifo_applied: false``) and ran with normal scheduling.

    python benchmarks/leader_loop.py [--quick] [--duration S] [--rates 1000,4000] [--realtime-priority P]

Prints one JSON object as its last line. Timings on a shared 2-core machine are noisy: read the ratios.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_common import (
    ROUNDS, emit, interleaved, nonnegative_int, positive_float, rate_list, sched_fifo_refused, warn_if_no_sched_fifo,
)

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "tests" / "fakes" / "dhd_standin.c"

GRAPH = """
name: leader-loop
clock: wall
realtime_priority: PRIO
nodes:
  - id: source
    plugin: mock-sensor
    rate: RATE
    params: {signal: sine, amplitude: 2.0, frequency: 1.0}
  - id: leader
    plugin: PLUGIN
    rate: RATE
    params: {PARAMS}
    inputs: {gripper_force: source.value}
faults: {max_overruns: 0}
"""


def build(folder: Path) -> Path:
    gcc = shutil.which("gcc") or shutil.which("cc")
    if not gcc:
        sys.exit("gcc is needed to build the libdhd stand-in")
    out = folder / "libdhd.so"
    subprocess.run([gcc, "-shared", "-fPIC", "-O2", "-o", str(out), str(SRC), "-lm"], check=True)
    return out


def run_graph(plugin: str, params: str, rate: float, duration: float, prio: int = 0) -> dict:
    from teletouch.testing import make_registry, run_yaml

    reg = make_registry("teletouch.plugins.devices.omega7", "teletouch.plugins.devices.sim_omega7")
    text = (GRAPH.replace("RATE", f"{rate:g}").replace("PLUGIN", plugin).replace("PARAMS", params)
            .replace("PRIO", str(prio)))
    result, rt = run_yaml(text, reg, duration=duration)
    node = next(n for n in result.nodes if n.id == "leader")
    out = {"status": result.status, "realtime_priority": prio,
           "sched_fifo_applied": prio > 0 and sched_fifo_refused(prio) is None, "rate_hz": rate,
           "achieved_rate_hz": round(node.achieved_rate, 1),
           "achieved_ratio": round(node.achieved_rate / rate, 4),
           "period_jitter_p99_us": None if node.period_jitter_p99_s is None
           else round(node.period_jitter_p99_s * 1e6, 1),
           "overruns": node.overruns, "mean_step_us": round(node.mean_step_s * 1e6, 2),
           "max_step_us": round(node.max_step_s * 1e6, 1), "steps": node.steps}
    if plugin == "omega7":
        st = rt.component("leader").status() if hasattr(rt.component("leader"), "guard") else {}
        out["timeguards"] = st.get("timeguards")
    return out


def raw_calls(lib_path: Path, cycles: int) -> dict:
    from teletouch.plugins.devices import dhd

    d = dhd.load(lib_path)
    d.open()
    d.enable_force(True)
    d.set_brakes(False)

    def binding(n: int) -> None:   # one driver cycle through the binding
        for _ in range(n):
            d.position()
            d.gripper_gap()
            d.gripper_velocity()
            d.button(0)
            d.set_forces(0.0, 0.0, 0.0, 1.0)

    # the same five calls on the bare ctypes functions (no Python wrapper, no error check)
    lib, i = d.lib, d.id
    px, py, pz, pg, pv = d._px, d._py, d._pz, d._pg, d._pv
    gp, gg, gv, gb, sf = (lib.dhdGetPosition, lib.dhdGetGripperGap, lib.dhdGetGripperLinearVelocity,
                          lib.dhdGetButton, lib.dhdSetForceAndGripperForce)

    def bare(n: int) -> None:
        for _ in range(n):
            gp(px, py, pz, i)
            gg(pg, i)
            gv(pv, i)
            gb(0, i)
            sf(0.0, 0.0, 0.0, 1.0, i)

    per = interleaved({"binding": binding, "bare": bare}, cycles)
    d.set_forces(0.0, 0.0, 0.0, 0.0)
    d.enable_force(False)
    d.close()
    return {"cycles": cycles, "rounds": ROUNDS, "binding_cycle_us": round(per["binding"] * 1e6, 3),
            "bare_ctypes_cycle_us": round(per["bare"] * 1e6, 3),
            "binding_overhead_ratio": round(per["binding"] / per["bare"], 2)}


def driver_step(sdk: Path, cycles: int) -> dict:
    """One step() of omega7 (on the stand-in SDK) and of sim-omega7, side by side (:func:`interleaved`)."""
    import numpy as np

    from teletouch import Sample
    from teletouch.plugins.devices.omega7 import Omega7
    from teletouch.plugins.devices.sim_omega7 import SimOmega7
    from teletouch.testing import Harness

    zero3 = np.zeros(3)

    def stepper(h):
        comp, inputs, slots = h.comp, h.inputs, h.slots
        k = [0]

        def run(n: int) -> None:
            for _ in range(n):
                t = k[0] * 1e-3  # 1 kHz steps: sim-omega7 does 4 substeps of 0.25 ms
                k[0] += 1
                slots["gripper_force"].sample = Sample(1.0, t)
                slots["force"].sample = Sample(zero3, t)
                comp.step(t, inputs)
        return run

    with Harness(Omega7, {"sdk_path": str(sdk)}) as ho, Harness(SimOmega7, {}) as hs:
        per = interleaved({"omega7": stepper(ho), "sim_omega7": stepper(hs)}, cycles)
    out = {f"{name}_step_us": round(v * 1e6, 3) for name, v in per.items()}
    out["rounds"] = ROUNDS
    out["omega7_vs_sim_step_ratio"] = round(out["omega7_step_us"] / out["sim_omega7_step_us"], 3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 s per run instead of 3 s")
    ap.add_argument("--duration", type=positive_float, default=None, help="seconds per run")
    ap.add_argument("--rates", type=rate_list, default=[1000.0, 4000.0],
                    help="comma-separated loop rates (Hz; default 1000,4000)")
    ap.add_argument("--realtime-priority", type=nonnegative_int, default=20,
                    help="also run the loops with this SCHED_FIFO priority (1-99; 0: only normal scheduling)")
    args = ap.parse_args(argv)
    if args.realtime_priority > 99:
        ap.error(f"--realtime-priority: SCHED_FIFO priorities are 1-99 (0: none), got {args.realtime_priority}")
    duration = args.duration if args.duration is not None else (1.0 if args.quick else 3.0)
    rates = args.rates
    with tempfile.TemporaryDirectory() as tmp:
        lib = build(Path(tmp))
        results: dict = {"benchmark": "leader_loop", "duration_s": duration, "runs": [],
                         "sched_fifo_refused": warn_if_no_sched_fifo(args.realtime_priority)}
        prios = [0] + ([args.realtime_priority] if args.realtime_priority > 0 else [])
        for prio in prios:
            for rate in rates:
                for plugin, params in (("omega7", f"sdk_path: {tmp}"), ("sim-omega7", "intent: hold")):
                    r = run_graph(plugin, params, rate, duration, prio)
                    r["plugin"] = plugin
                    results["runs"].append(r)
                    print(f"{plugin:<11} {rate:>6.0f} Hz prio {prio:>2}: achieved {r['achieved_rate_hz']:8.1f} Hz, "
                          f"jitter p99 {r['period_jitter_p99_us']} us, overruns {r['overruns']}, "
                          f"step {r['mean_step_us']} us", file=sys.stderr)
        cycles = 20000 if args.quick else 100000
        results["raw_ctypes"] = raw_calls(lib, cycles)
        results["driver_step"] = driver_step(Path(tmp), cycles // 4)
    emit(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
