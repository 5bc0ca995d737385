"""Stability sweep of the simulated position-force loop: force scale x contact stiffness, passivity control off/on.

Modes (``MODES`` below; the JSON's keys): ``off`` (no passivity control, no prediction), ``tdpa-damping`` (the
previous default: leader-port observer, damping capped at 40 N*s/m), ``tdpa-damping+force-reduction`` (also cuts the
rendered force towards zero when the capped damping is not enough), ``tdpa-force`` (the passivity controller on the
force path, no prediction), ``prediction-only`` (the contact-model prediction, passivity off), ``default`` (the
controller's defaults: prediction + two-port passivity on the force path) and ``default-leader-port``.

For each (force_scale k_f, gel modulus E) the simulated operator closes on a rigid object and holds; the loop
"oscillates" when the peak-to-peak contact force (ground truth, sim-gripper) in steady contact exceeds 0.2 N. The
peak-to-peak force rendered to the operator is reported too (it also carries k_f times the estimate's noise). The
contact stiffness is set by the fingertip gel's Young's modulus (sim-gripper's gel law: stiffness ~ E). The sensed force
is sim-force-sensor (ground truth at 60 Hz, one frame late, 0.02 N noise: the timing of the DIGIT + estimator chain), so
the sweep runs in seconds; ``--sensor image`` uses the real estimators instead.

    python benchmarks/stability_sweep.py [--quick] [--sensor ideal|image]

Prints one JSON object as its last line. A run that ends in a fault (or is stopped) is named on stderr and in
``faulted_runs``, counts neither as oscillating nor as not (``oscillates``: null) and makes the exit status 1.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from teletouch.plugins.controllers.experiments import Recorder, build_runtime, sim_graph
from bench_common import emit, strict

THRESHOLD_N = 0.2


OLD = {"force_prediction": False, "passivity_observer": "leader-port", "passivity_controller": "damping"}
MODES = {
    # no passivity control, no prediction (the loop as it was before either)
    "off": {"passivity": False, "force_prediction": False},
    # the previous default: leader-port observer, damping capped at 40 N*s/m, no prediction
    "tdpa-damping": {"passivity": True, **OLD},
    "tdpa-damping+force-reduction": {"passivity": True, "passivity_force_reduction": True, **OLD},
    # the new force path (damping + force cut, nothing in free space) without the contact-model prediction
    "tdpa-force": {"passivity": True, "force_prediction": False},
    # the prediction alone, passivity control off
    "prediction-only": {"passivity": False},
    # the default: contact-model prediction + passivity control on the force path, two-port observer
    "default": {},
    "default-leader-port": {"passivity_observer": "leader-port"},
}


def run_one(force_scale: float, modulus: float, mode: str, sensor: str, duration: float) -> dict:
    intent = {"type": "close-and-hold", "start_opening": 0.02, "target_opening": 0.010, "speed": 0.005,
              "start_time": 0.5, "hold_time": 100.0, "release": False}
    doc = sim_graph("position-force", sensor, duration=duration, intent=intent,
                    controller_params={"force_scale": force_scale, **MODES[mode]},
                    gripper_params={"modulus": modulus})
    if sensor == "image":
        for n in doc["nodes"]:
            if n["id"] == "digit":
                n["params"]["modulus"] = modulus
    rt = build_runtime(doc)
    rec = Recorder(["controller.gripper_force", "gripper.contact_force", "controller.damping"])
    rt.add_tap(rec)
    res = rt.run()
    t, f = rec.series("controller.gripper_force")
    tg, fg = rec.series("gripper.contact_force")
    _, d = rec.series("controller.damping")
    w0 = duration - 1.5                       # steady contact: the last 1.5 s of the hold
    win = t >= w0
    p2p = float(np.ptp(f[win])) if win.any() else float("nan")
    p2p_gt = float(np.ptp(fg[tg >= w0])) if (tg >= w0).any() else float("nan")
    return {"force_scale": force_scale, "gel_modulus_pa": modulus, "mode": mode,
            "p2p_leader_force_n": p2p, "p2p_contact_force_n": p2p_gt,
            "mean_leader_force_n": float(np.mean(f[win])) if win.any() else float("nan"),
            "mean_contact_force_n": float(np.mean(fg[tg >= w0])) if (tg >= w0).any() else float("nan"),
            "force_scale_gain_final": float(rt.component("controller").gain),
            # a run that did not end ok (a fault, a stop) has no steady contact to judge: neither oscillating nor not
            "oscillates": bool(p2p_gt > THRESHOLD_N) if res.status == "ok" else None,
            "max_damping_used": float(np.max(d)) if len(d) else 0.0, "status": res.status, "message": res.message}


def out_problem(path: Path) -> str | None:
    """Why the JSON cannot be written to ``path`` (None if it can): its folder missing or not writable, or the path
    itself a folder."""
    folder = path.resolve().parent
    if path.is_dir():
        return "is a folder (give a file name, e.g. sweep.json)"
    if not folder.is_dir():
        return f"the folder {folder} does not exist"
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        return f"cannot write there ({path if path.exists() else folder} is not writable)"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 2 x 2 grid (k_f 1, 4; E 0.41, 1 MPa)")
    ap.add_argument("--out", default=None, help="also write the JSON to this file")
    ap.add_argument("--sensor", choices=("ideal", "image"), default="ideal")
    args = ap.parse_args(argv)
    if args.out:   # refused now, not after the sweep
        problem = out_problem(Path(args.out))
        if problem:
            ap.error(f"--out {args.out}: {problem}")
    if args.quick:
        scales, moduli, duration = [1.0, 4.0], [0.41e6, 1.0e6], 5.0
    else:
        scales, moduli, duration = [0.5, 1.0, 2.0, 4.0], [0.2e6, 0.41e6, 1.0e6], 5.0
    w0 = time.perf_counter()
    rows = []
    for k in scales:
        for e in moduli:
            for mode in MODES:
                r = run_one(k, e, mode, args.sensor, duration)
                rows.append(r)
                print(f"k_f={k:4.1f} E={e / 1e6:4.2f} MPa {mode:<21}: p2p leader "
                      f"{r['p2p_leader_force_n']:.3f} N, contact {r['p2p_contact_force_n']:.3f} N"
                      + ("  OSCILLATES" if r["oscillates"] else "")
                      + (f"  ended {r['status']}: {r['message']}" if r["status"] != "ok" else ""), file=sys.stderr)
    # a run that ended in a fault (or was stopped) has no figures: named here, and the benchmark fails
    faulted = [{"force_scale": r["force_scale"], "gel_modulus_pa": r["gel_modulus_pa"], "mode": r["mode"],
                "status": r["status"], "message": r["message"]} for r in rows if r["status"] != "ok"]
    for f in faulted:
        print(f"k_f={f['force_scale']:g} E={f['gel_modulus_pa'] / 1e6:g} MPa {f['mode']}: ended {f['status']}: "
              f"{f['message']}", file=sys.stderr)
    by = {m: {(r["force_scale"], r["gel_modulus_pa"]): r for r in rows if r["mode"] == m} for m in MODES}
    osc = {m: [list(key) for key, r in by[m].items() if r["oscillates"]] for m in MODES}
    n_off = len(osc["off"])
    summary = {
        "benchmark": "stability_sweep",
        "sensor": args.sensor,
        "threshold_p2p_n": THRESHOLD_N,
        "grid": {"force_scale": scales, "gel_modulus_pa": moduli},
        "oscillating": osc,
        "oscillating_cases": {m: len(v) for m, v in osc.items()},
        "removed_by": {m: sum(1 for key in osc["off"] if by[m][tuple(key)]["oscillates"] is False)
                       for m in MODES if m != "off"},
        "fraction_removed": {m: (sum(1 for key in osc["off"] if by[m][tuple(key)]["oscillates"] is False) / n_off
                                 if n_off else None) for m in MODES if m != "off"},
        "median_p2p_contact_n": {m: float(np.median([r["p2p_contact_force_n"] for r in by[m].values()]))
                                 for m in MODES},
        "faulted_runs": faulted,
        "rows": rows,
        "wall_time_s": time.perf_counter() - w0,
    }
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump(strict(summary), fh, indent=2, allow_nan=False)
    emit(summary)
    return 1 if faulted else 0


if __name__ == "__main__":
    sys.exit(main())
