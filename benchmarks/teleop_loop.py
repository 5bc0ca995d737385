"""The full simulated teleoperation loop: speed under the simulated clock, timing under the wall clock.

The graph is examples/paper-sim.yaml (sim-omega7 + sim-gripper at 1 kHz, sim-digit + depth + poly-force at 60 Hz, the
position-force controller at 1 kHz), built by teletouch.plugins.controllers.experiments.sim_graph.

- sim clock: graph seconds per wall second (target >= 5x real time), side by side with the same loop on the
  ``ideal`` camera-rate sensor (no image pipeline), so the ratio shows what the image chain costs;
- wall clock: the controller's period jitter p99, in the full loop and, side by side, alone (mock leader, estimate
  and device: what the controller itself costs the 1 kHz thread) (target <= 0.25 ms, RunResult.nodes[i].period_jitter_p99_s) and the
  sensor-to-leader-force latency: from the moment a frame is out of sim-digit to the end of the first controller
  step that uses the force estimated from it (target p99 <= 5 ms; it includes the estimators' own time), and from
  the estimate being out of poly-force to that controller step (the controller's pick-up). The smoothing ramp
  (smoothing_time, 1/60 s) comes on top of that by design and is reported separately.

    python benchmarks/teleop_loop.py [--quick] [--sensor image|ideal]

Prints one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import numpy as np

from teletouch.plugins.controllers.experiments import build_runtime, sim_graph


def sim_speed(sensor: str, duration: float) -> dict:
    """Graph seconds per wall second; ``steady`` excludes start-up (model loading, caches, the first 0.5 s)."""
    rt = build_runtime(sim_graph(sensor=sensor, duration=duration))
    mark: list[tuple[float, float]] = []

    def progress(_rt, t: float) -> None:
        if not mark and t >= 0.5:
            mark.append((time.perf_counter(), t))

    res = rt.run(progress=progress, progress_interval=0.0)
    end = time.perf_counter()
    steady = (res.sim_time - mark[0][1]) / (end - mark[0][0]) if mark else float("nan")
    ctl = next(n for n in res.nodes if n.id == "controller")
    return {"sensor": sensor, "sim_time_s": res.sim_time, "wall_time_s": res.wall_time,
            "realtime_factor": res.realtime_factor, "realtime_factor_steady": steady, "status": res.status,
            "controller_mean_step_us": ctl.mean_step_s * 1e6,
            "mean_step_us": {n.id: n.mean_step_s * 1e6 for n in res.nodes}}


def wall_timing(sensor: str, duration: float, realtime_priority: int = 0) -> dict:
    doc = sim_graph(sensor=sensor, duration=duration)
    doc["clock"] = "wall"
    if realtime_priority:
        doc["realtime_priority"] = realtime_priority
    rt = build_runtime(doc)
    ctl = rt.component("controller")
    lock = threading.Lock()
    frame_ready = [None]                          # graph time the latest frame came out of the sensor
    force_frame: dict[float, tuple[float, float]] = {}   # force sample stamp -> (frame ready, estimate ready)
    first_use: list[tuple[float, float, float]] = []   # (frame ready, estimate ready, controller step end)
    last_seen = [None]
    sensor_node = "force" if sensor == "ideal" else "digit"

    def tap(node: str, t: float, out: dict) -> None:
        if node == sensor_node and ("image" in out or sensor == "ideal"):
            frame_ready[0] = rt.now()
        if node == "force" and "force" in out:
            s = rt.latest("force", "force")
            if s is not None and frame_ready[0] is not None:
                with lock:
                    force_frame[s.stamp] = (frame_ready[0], rt.now())
        if node == "controller":
            st = ctl.last_stamp
            if st is not None and st != last_seen[0]:
                last_seen[0] = st
                with lock:
                    fr = force_frame.get(st)
                if fr is not None:
                    first_use.append((fr[0], fr[1], rt.now()))

    rt.add_tap(tap)
    res = rt.run()
    ctl_stats = next(n for n in res.nodes if n.id == "controller")
    lat = np.array([c - a for a, b, c in first_use[5:]]) if len(first_use) > 6 else np.array([np.nan])
    pick = np.array([c - b for a, b, c in first_use[5:]]) if len(first_use) > 6 else np.array([np.nan])
    return {
        "sensor": sensor, "status": res.status, "duration_s": res.sim_time,
        "controller_rate_hz": ctl_stats.achieved_rate, "controller_overruns": ctl_stats.overruns,
        "controller_jitter_p99_ms": (ctl_stats.period_jitter_p99_s or float("nan")) * 1e3,
        "latency_samples": int(lat.size),
        "frame_to_leader_force_p50_ms": float(np.nanpercentile(lat, 50) * 1e3),
        "frame_to_leader_force_p99_ms": float(np.nanpercentile(lat, 99) * 1e3),
        "frame_to_leader_force_max_ms": float(np.nanmax(lat) * 1e3),
        "estimate_to_leader_force_p50_ms": float(np.nanpercentile(pick, 50) * 1e3),
        "estimate_to_leader_force_p99_ms": float(np.nanpercentile(pick, 99) * 1e3),
        "smoothing_ramp_ms": ctl.params.smoothing_time * 1e3,
        "nodes": {n.id: {"achieved_hz": n.achieved_rate, "overruns": n.overruns, "mean_step_ms": n.mean_step_s * 1e3,
                         "max_step_ms": n.max_step_s * 1e3,
                         "jitter_p99_ms": (n.period_jitter_p99_s or float("nan")) * 1e3} for n in res.nodes},
    }


CONTROLLER_ONLY = """
name: controller-only
clock: wall
nodes:
  - {id: hand, plugin: mock-sensor, rate: 1kHz, params: {signal: sine, amplitude: 0.002, offset: 0.014, frequency: 1}}
  - {id: est, plugin: mock-sensor, rate: 60, params: {signal: sine, amplitude: 1.0, offset: 1.5, frequency: 0.5}}
  - id: controller
    plugin: position-force
    rate: 1kHz
    inputs: {leader_opening: hand.value, force: est.value}
  - {id: leader, plugin: mock-device, rate: 1kHz, inputs: {command: controller.gripper_force}}
"""


def wall_controller_only(duration: float) -> dict:
    """The controller alone (mock leader, estimate and device) under the wall clock: its own share of the jitter."""
    from teletouch.graph import load_graph_text
    from teletouch.runtime import Runtime

    rt = Runtime(load_graph_text(CONTROLLER_ONLY, "<controller-only>"), log=lambda m: None)
    res = rt.run(duration)
    c = next(n for n in res.nodes if n.id == "controller")
    return {"controller_jitter_p99_ms": (c.period_jitter_p99_s or float("nan")) * 1e3,
            "controller_mean_step_us": c.mean_step_s * 1e6, "controller_overruns": c.overruns,
            "achieved_hz": c.achieved_rate}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 s runs instead of 10 s")
    ap.add_argument("--realtime", action="store_true", help="also the wall-clock run with realtime_priority 50 "
                    "(SCHED_FIFO for the fast threads; needs root or CAP_SYS_NICE)")
    ap.add_argument("--sensor", choices=("image", "gt", "ideal"), default="image", help="the sensor chain under "
                    "test (gt: sim-digit's true max depth into poly-force, no depth estimation)")
    args = ap.parse_args()
    dur = 3.0 if args.quick else 10.0
    w0 = time.perf_counter()
    sim = sim_speed(args.sensor, dur)
    print(f"sim clock, {args.sensor}: {sim['realtime_factor']:.2f}x real time "
          f"({sim['realtime_factor_steady']:.2f}x after start-up)", file=sys.stderr)
    sim_ref = sim_speed("ideal", dur) if args.sensor != "ideal" else None
    if sim_ref:
        print(f"sim clock, ideal: {sim_ref['realtime_factor']:.2f}x real time "
              f"({sim_ref['realtime_factor_steady']:.2f}x after start-up)", file=sys.stderr)
    wall = wall_timing(args.sensor, dur)
    wall_rt = wall_timing(args.sensor, dur, realtime_priority=50) if args.realtime else None
    if wall_rt:
        print(f"wall clock, SCHED_FIFO 50: controller jitter p99 {wall_rt['controller_jitter_p99_ms']:.3f} ms, "
              f"frame->leader force p99 {wall_rt['frame_to_leader_force_p99_ms']:.2f} ms", file=sys.stderr)
    print(f"wall clock: controller jitter p99 {wall['controller_jitter_p99_ms']:.3f} ms, frame->leader force "
          f"p50 {wall['frame_to_leader_force_p50_ms']:.2f} ms p99 {wall['frame_to_leader_force_p99_ms']:.2f} ms",
          file=sys.stderr)
    solo = wall_controller_only(dur)
    print(f"wall clock, controller alone: jitter p99 {solo['controller_jitter_p99_ms']:.3f} ms", file=sys.stderr)
    try:
        load = list(__import__("os").getloadavg())
    except OSError:
        load = None
    out = {
        "benchmark": "teleop_loop",
        "sensor": args.sensor,
        "sim_realtime_factor": sim["realtime_factor"],
        "sim_realtime_factor_steady": sim["realtime_factor_steady"],
        "sim_realtime_factor_ideal_sensor": sim_ref["realtime_factor_steady"] if sim_ref else None,
        "image_chain_cost_ratio": (sim_ref["realtime_factor_steady"] / sim["realtime_factor_steady"])
        if sim_ref else None,
        "sim_wall_share_per_node": {k: v * 60 / 1e6 if k in ("digit", "depth", "force") else v * 1000 / 1e6
                                    for k, v in sim["mean_step_us"].items()},
        "controller_jitter_p99_ms": wall["controller_jitter_p99_ms"],
        "frame_to_leader_force_p50_ms": wall["frame_to_leader_force_p50_ms"],
        "frame_to_leader_force_p99_ms": wall["frame_to_leader_force_p99_ms"],
        "estimate_to_leader_force_p50_ms": wall["estimate_to_leader_force_p50_ms"],
        "estimate_to_leader_force_p99_ms": wall["estimate_to_leader_force_p99_ms"],
        "targets": {"sim_realtime_factor": ">= 5", "controller_jitter_p99_ms": "<= 0.25",
                    "frame_to_leader_force_p99_ms": "<= 5"},
        "controller_alone_jitter_p99_ms": solo["controller_jitter_p99_ms"],
        "sched_fifo": None if wall_rt is None else {
            k: wall_rt[k] for k in ("controller_jitter_p99_ms", "frame_to_leader_force_p50_ms",
                                    "frame_to_leader_force_p99_ms", "estimate_to_leader_force_p99_ms")},
        "jitter_ratio_full_loop_to_controller_alone": wall["controller_jitter_p99_ms"] / solo["controller_jitter_p99_ms"],
        "load_average": load, "cpus": __import__("os").cpu_count(),
        "sim": sim, "sim_ideal": sim_ref, "wall": wall, "wall_controller_only": solo,
        "wall_time_s": time.perf_counter() - w0,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
