"""Accuracy of the `depth` estimator on real DIGIT presses (leave-some-out) and on simulated frames with ground truth.

Real data (../shared/data): digit-presses-qvga (10 presses, hand labels, 17.15 px/mm) and digit-presses-vga (47
usable presses + frame_49 without contact, 0.0266 mm/px). The presses are split into folds; a model is calibrated
(`depth_calibration.train_model`, the code behind `teletouch calibrate depth`) on the other folds, with the
background = per-pixel median of its training frames, and evaluated on the held-out presses:

- cap-height error: depth at the centre (disk of radius max(2 px, a/10)) minus depth on the ring a-2..a+2 px,
  against the cap height R - sqrt(R^2 - a^2) of the 3 mm ball (a = labelled contact radius);
- the radius of a sphere fitted to the reconstructed surface inside 0.9 a (target: 3 mm within 10%);
- false depth: max |depth| beyond 2 contact radii; max depth of a frame without contact (VGA: the real frame_49;
  QVGA has none, so a synthetic one: the background + noise (2 levels) + a global drift of 4 levels).

VGA is run a second time with the real no-contact frame_49 as every fold's background (as `teletouch calibrate depth
--background frame_49.jpg`).

QVGA is run with four network inputs (ratio+gradxy, the default = relative change from the background, its Sobel
gradients and X, Y; ratioxy without the gradients; diffxy = difference from the background + X, Y; rgbxy = the
paper's R, G, B, X, Y) and VGA with the default and diffxy, to show what each input brings. 40 epochs (the
calibration's default) everywhere; --quick: 20 epochs, the default inputs only, one VGA fold, fewer simulated
frames.

Simulated (sim-digit, Taxim's optical model of a real DIGIT, pixel noise 2 levels): the packaged model
sim-digit-qvga over indenters (6 and 10 mm balls, the paper's probe, a 4 mm flat punch), positions and
indentations: depth RMSE over the disturbed region and max-depth error.

    python benchmarks/depth_accuracy.py [--quick] [--no-vga] [--no-sim]

Prints one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings

import numpy as np

from bench_common import DATA, data_folder, emit


def real(ds: str, folds: int, feature_set: str, epochs: int, log, fold_limit: int | None = None,
         background: str | None = None) -> dict:
    """Leave-some-out on one data set; ``background``: a frame of the folder (the no-contact frame_49) as every
    fold's background instead of the median of its training frames (`teletouch calibrate depth --background`)."""
    from teletouch.plugins.estimators import depth_calibration as C
    from teletouch.plugins.estimators.depth_pipeline import DepthPipeline

    folder = DATA / f"digit-presses-{ds}"
    ims = C.load_images(folder)
    labs = C.read_labels(folder / "labels.csv")
    px_per_m = {"qvga": 17150.0, "vga": 1.0 / 0.0266e-3}[ds]
    usable = [n for n, _ in ims if n in labs and labs[n].usable]
    nocontact = [n for n, _ in ims if n in labs and labs[n].no_contact]
    # folds spread over the sensor: sort by position, deal round-robin
    order = sorted(usable, key=lambda n: (labs[n].cy, labs[n].cx))
    per, nc, times, gains, thresholds = [], [], [], [], []
    per_plane = []   # the same models with the optional plane zero reference (`baseline: plane`)
    by = dict(ims)
    rng = np.random.default_rng(0)
    for f in range(folds if fold_limit is None else min(folds, fold_limit)):
        val = order[f::folds]
        train_imgs = [(n, im) for n, im in ims if n not in val and n not in nocontact]
        bg = by[background] if background else C.median_background([im for _, im in train_imgs])
        t0 = time.perf_counter()
        model = C.train_model(train_imgs, labs, bg, px_per_m, feature_set=feature_set, epochs=epochs,
                              progress=False, seed=0)
        times.append(time.perf_counter() - t0)
        gains.append(model.depth_gain)
        thresholds.append(model.change_threshold)
        pipe = DepthPipeline(model, threads=1)
        pipe_plane = DepthPipeline(model, threads=1, baseline="plane")
        for n in val:
            per.append(C.evaluate_press(pipe, by[n], labs[n]))
            per_plane.append(C.evaluate_press(pipe_plane, by[n], labs[n]))
        if nocontact:
            for n in nocontact:
                nc.append(pipe(by[n]).max_depth)
        else:
            noisy = bg.astype(np.float32) + rng.normal(0, 2.0, bg.shape) + 4.0
            nc.append(pipe(np.clip(noisy + 0.5, 0, 255).astype(np.uint8)).max_depth)
        log(f"{ds} {feature_set}{' bg ' + background if background else ''} fold {f}: "
            f"{[p['cap_error'] for p in per[-len(val):]]}")
    err = np.array([p["cap_error"] for p in per])
    rad = np.array([p["sphere_radius_mm"] for p in per])
    far = np.array([p["far_false_depth_mm"] for p in per])
    return {
        "dataset": ds, "feature_set": feature_set, "folds": folds, "evaluated_presses": len(per),
        "background": background or "per-pixel median of the fold's training frames",
        "change_threshold": [round(t, 1) for t in thresholds],
        "median_abs_cap_error": round(float(np.median(np.abs(err))), 4),
        "median_cap_error": round(float(np.median(err)), 4),
        "share_within_10pct": round(float(np.mean(np.abs(err) <= 0.10)), 3),
        "median_sphere_radius_mm": round(float(np.nanmedian(rad)), 3),
        "sphere_radius_within_10pct_share": round(float(np.mean(np.abs(rad / 3.0 - 1) <= 0.10)), 3),
        "no_contact_max_depth_mm": round(float(max(nc)) * 1e3, 4) if nc else None,
        "no_contact_frame": "frame_49 (real)" if nocontact else "background + noise 2 + drift 4 levels (synthetic)",
        "far_false_depth_mm_median": round(float(np.median(far)), 4),
        "far_false_depth_mm_max": round(float(far.max()), 4),
        "far_false_depth_share_below_0.03mm": round(float(np.mean(far < 0.03)), 3),
        "baseline_plane": _brief(per_plane),
        "train_seconds_per_fold": round(float(np.mean(times)), 1), "depth_gain": [round(g, 3) for g in gains],
        "per_press": per,
    }


def _brief(per: list) -> dict:
    err = np.array([p["cap_error"] for p in per])
    far = np.array([p["far_false_depth_mm"] for p in per])
    return {"median_abs_cap_error": round(float(np.median(np.abs(err))), 4),
            "median_sphere_radius_mm": round(float(np.nanmedian([p["sphere_radius_mm"] for p in per])), 3),
            "far_false_depth_mm_median": round(float(np.median(far)), 4),
            "far_false_depth_mm_max": round(float(far.max()), 4),
            "far_false_depth_share_below_0.03mm": round(float(np.mean(far < 0.03)), 3),
            "median_max_depth_mm": round(float(np.median([p["max_depth_mm"] for p in per])), 4)}


def sim(quick: bool, log) -> dict:
    from teletouch.plugins.estimators.depth_pipeline import DepthPipeline
    from teletouch.plugins.estimators.normal_model import load_model
    from teletouch.plugins.sensors import gel
    from teletouch.plugins.sensors.sim_digit import DigitSimulator

    model = load_model("sim-digit-qvga")
    pipe = DepthPipeline(model, threads=1)
    pipe_plane = DepthPipeline(model, threads=1, baseline="plane")
    indenters = {"ball-6mm": gel.Indenter.sphere(0.003), "ball-10mm": gel.Indenter.sphere(0.005),
                 "probe": gel.Indenter.probe(0.005, 0.010), "flat-4mm": gel.Indenter.flat(0.002)}
    positions = [(0.0, 0.0), (-2.5e-3, -4e-3), (2.5e-3, 4e-3), (-3e-3, 3.5e-3), (3e-3, -3.5e-3)]
    depths = [0.3e-3, 0.6e-3, 1.0e-3]
    if quick:
        positions = positions[:3]
        depths = [0.4e-3, 0.9e-3]
    out = {}
    rows = []
    for name, ind in indenters.items():
        s = DigitSimulator("qvga", indenter=ind, noise=2.0, seed=123)
        errs, rmses, rel, rel_plane = [], [], [], []
        for pos in positions:
            for d in depths:
                img, surf = s.render(d, pos, 0.0, t=0.0)
                res = pipe(img)
                gt = surf.depth
                sel = (gt > 1e-6) | (res.depth > 1e-6)
                rmse = float(np.sqrt(np.mean((res.depth[sel] - gt[sel]) ** 2))) if sel.any() else 0.0
                e = res.max_depth - float(gt.max())
                errs.append(e)
                rel.append(e / float(gt.max()))
                rel_plane.append(pipe_plane.max_depth(img) / float(gt.max()) - 1.0)
                rmses.append(rmse)
                rows.append({"indenter": name, "x_mm": pos[0] * 1e3, "y_mm": pos[1] * 1e3, "depth_mm": d * 1e3,
                             "gt_max_mm": round(float(gt.max()) * 1e3, 4),
                             "est_max_mm": round(res.max_depth * 1e3, 4), "rmse_mm": round(rmse * 1e3, 4)})
        out[name] = {"frames": len(errs), "depth_rmse_mm_median": round(float(np.median(rmses)) * 1e3, 4),
                     "max_depth_error_mm_median": round(float(np.median(errs)) * 1e3, 4),
                     "max_depth_abs_rel_error_median": round(float(np.median(np.abs(rel))), 4),
                     "max_depth_abs_rel_error_max": round(float(np.max(np.abs(rel))), 4),
                     "max_depth_rel_error_std": round(float(np.std(rel)), 4),
                     "plane_max_depth_rel_error_median": round(float(np.median(rel_plane)), 4),
                     "plane_max_depth_rel_error_std": round(float(np.std(rel_plane)), 4)}
        log(f"sim {name}: {out[name]}")
    # how deep the simulated gel itself is beyond two contact radii (the far false depth criterion assumes a flat
    # gel there): the gel model's true depth, 6 mm ball at the centre, a from the true contact area
    s = DigitSimulator("qvga", indenter=indenters["ball-6mm"], noise=0.0, seed=0)
    tail = {}
    for d in (0.2e-3, 0.35e-3, 0.5e-3):
        _, surf = s.render(d, (0.0, 0.0), 0.0, t=0.0)
        rr, cc = np.mgrid[0:surf.depth.shape[0], 0:surf.depth.shape[1]]
        r = np.hypot(rr - (surf.depth.shape[0] - 1) / 2, cc - (surf.depth.shape[1] - 1) / 2)
        a = math.sqrt(surf.mask.sum() / math.pi)
        tail[f"{d * 1e3:g}mm"] = round(float(surf.depth[r > 2 * a].max()) * 1e3, 4)
    out["gel_model_true_depth_beyond_2a_mm"] = tail
    log(f"sim gel model, true depth beyond 2 contact radii (6 mm ball): {tail}")
    s = DigitSimulator("qvga", noise=2.0, drift=4.0, drift_period=4.0, seed=7)
    nc = [pipe(s.render(0.0, (0, 0), 0.0, t=t)[0]).max_depth for t in np.linspace(0, 4, 9)]
    out["no_contact_max_depth_mm"] = round(float(max(nc)) * 1e3, 4)
    out["no_contact_note"] = "noise 2 levels, illumination drift +-4 levels"
    out["model"] = "sim-digit-qvga (packaged; trained by scripts/make_sim_depth_model.py)"
    out["per_frame"] = rows
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer folds, epochs and simulated frames")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulated frames")
    ap.add_argument("--no-vga", action="store_true", help="skip the VGA presses")
    args = ap.parse_args()
    for ds in ("qvga",) if args.no_vga else ("qvga", "vga"):
        data_folder(f"digit-presses-{ds}")
    warnings.filterwarnings("ignore")
    import torch

    torch.set_num_threads(1)
    log = lambda m: print(m, file=sys.stderr)  # noqa: E731
    t0 = time.perf_counter()
    result: dict = {"benchmark": "depth_accuracy", "quick": args.quick}
    from teletouch.plugins.estimators.normal_model import DEFAULT_FEATURES

    epochs = 20 if args.quick else 40       # 40: the calibration's default
    comparison = ["ratioxy", "diffxy", "rgbxy"]
    features = [DEFAULT_FEATURES] if args.quick else [DEFAULT_FEATURES] + comparison
    result["default_features"] = DEFAULT_FEATURES
    result["qvga"] = {fs: real("qvga", 5, fs, epochs, log) for fs in features}
    if not args.no_vga:
        vga_features = [DEFAULT_FEATURES] if args.quick else [DEFAULT_FEATURES, "diffxy"]
        result["vga"] = {fs: real("vga", 3 if not args.quick else 4, fs, epochs, log,
                                  fold_limit=1 if args.quick else None) for fs in vga_features}
        # the real no-contact frame as the background (`--background frame_49.jpg`): a single frame's noise and
        # lighting raise the change threshold (docs/depth.md, "A recorded background frame")
        result["vga_background_frame_49"] = real("vga", 3 if not args.quick else 4, DEFAULT_FEATURES, epochs, log,
                                                 fold_limit=1 if args.quick else None, background="frame_49.jpg")
    if not args.no_sim:
        result["sim"] = sim(args.quick, log)
    q = result["qvga"][DEFAULT_FEATURES]
    summary = {"qvga_median_abs_cap_error": q["median_abs_cap_error"],
               "qvga_median_sphere_radius_mm": q["median_sphere_radius_mm"],
               "qvga_far_false_depth_mm_max": q["far_false_depth_mm_max"],
               "qvga_far_false_depth_share_below_0.03mm": q["far_false_depth_share_below_0.03mm"],
               "qvga_no_contact_max_depth_mm": q["no_contact_max_depth_mm"],
               "qvga_plane_far_false_depth_mm_max": q["baseline_plane"]["far_false_depth_mm_max"],
               "qvga_plane_far_false_depth_share_below_0.03mm": q["baseline_plane"][
                   "far_false_depth_share_below_0.03mm"]}
    for fs in features[1:]:
        summary[f"qvga_{fs}_median_abs_cap_error"] = result["qvga"][fs]["median_abs_cap_error"]
    if "vga" in result:
        v = result["vga"][DEFAULT_FEATURES]
        summary.update({"vga_median_abs_cap_error": v["median_abs_cap_error"],
                        "vga_median_sphere_radius_mm": v["median_sphere_radius_mm"],
                        "vga_far_false_depth_mm_max": v["far_false_depth_mm_max"],
                        "vga_far_false_depth_share_below_0.03mm": v["far_false_depth_share_below_0.03mm"],
                        "vga_no_contact_max_depth_mm": v["no_contact_max_depth_mm"],
                        "vga_plane_far_false_depth_mm_max": v["baseline_plane"]["far_false_depth_mm_max"],
                        "vga_plane_far_false_depth_share_below_0.03mm": v["baseline_plane"][
                            "far_false_depth_share_below_0.03mm"]})
        for fs in list(result["vga"])[1:]:
            summary[f"vga_{fs}_median_abs_cap_error"] = result["vga"][fs]["median_abs_cap_error"]
        summary["vga_background_frame_49_median_abs_cap_error"] = result["vga_background_frame_49"][
            "median_abs_cap_error"]
    if "sim" in result:
        summary["sim_ball_6mm_rmse_mm"] = result["sim"]["ball-6mm"]["depth_rmse_mm_median"]
        summary["sim_ball_6mm_max_depth_rel_error"] = result["sim"]["ball-6mm"]["max_depth_abs_rel_error_median"]
        summary["sim_no_contact_max_depth_mm"] = result["sim"]["no_contact_max_depth_mm"]
    result["summary"] = summary
    result["seconds"] = round(time.perf_counter() - t0, 1)
    emit(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
