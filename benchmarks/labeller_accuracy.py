"""The automatic labeller of `teletouch calibrate depth` against the shared labels, and a third estimate to judge both.

The labeller (`depth_calibration.auto_label`) finds each press's contact circle from the colour change. Issue #4 asks
for its centre within 3 px and its radius within 10% of the shared labels on the presses it does not flag:

- digit-presses-qvga: 10 presses, circles drawn by hand by the dataset's authors; background = the per-pixel median
  of the presses (as `teletouch calibrate depth` does without --background);
- digit-presses-vga: 47 usable presses, circles from another automatic method (README: median background, drift
  high-pass, threshold, equal-area radius), background = the real no-contact frame_49.

How good are the labels themselves? At VGA 3 px is 0.08 mm, a twentieth of a contact's radius. The third estimate is a
fit of the optics, independent of both label methods: a 6 mm ball pressed into the gel (the simulator's gel model:
the spherical cap and the elastic sag around it, seen through the gel's thickness) is rendered with Taxim's optical
table, which was fitted on this very VGA sensor (`teletouch.plugins.sensors.optics`), and its centre (x, y) and
indentation are fitted to the press's colour change (least squares, one free gain per press, Nelder-Mead from the
labeller's circle). The fit's radius is the model's contact radius, a third convention, so only its centre is compared.
QVGA has no optical table of its own, so the fit runs on VGA only.

    python benchmarks/labeller_accuracy.py [--quick]

--quick fits the first 12 VGA presses. Prints one JSON object as its last line.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from bench_common import DATA, data_folder, emit

BALL_RADIUS = 0.003                       # m
PX_PER_M = {"qvga": 17150.0, "vga": 1.0 / 0.0266e-3}


def _dist(a, b) -> float:
    return math.hypot(a.cx - b.cx, a.cy - b.cy)


def _centre_summary(d: np.ndarray) -> dict:
    return {"presses": int(d.size), "centre_median_px": round(float(np.median(d)), 2) if d.size else None,
            "centre_within_3px": int(np.sum(d <= 3.0)), "centre_within_8px": int(np.sum(d <= 8.0))}


def labeller(ds: str) -> tuple[dict, dict, dict, list, np.ndarray]:
    """The labeller on one data set against its labels: summary, per press, the auto labels, the images and the
    background used."""
    from teletouch.plugins.estimators import depth_calibration as C

    folder = DATA / f"digit-presses-{ds}"
    ims = C.load_images(folder)
    labs = C.read_labels(folder / "labels.csv")
    no_contact = [n for n, _ in ims if n in labs and labs[n].no_contact]
    bg = dict(ims)[no_contact[0]] if no_contact else C.median_background([im for _, im in ims])
    ball_px = BALL_RADIUS * PX_PER_M[ds]
    auto, per = {}, []
    for name, im in ims:
        ref = labs.get(name)
        if ref is None or not ref.usable:
            continue
        lb = auto[name] = C.auto_label(name, im, bg, ball_px)
        if lb.cx is None:
            per.append({"image": name, "found": False})
            continue
        per.append({"image": name, "found": True, "flagged": lb.uncertain, "labeller": [lb.cx, lb.cy, lb.r],
                    "label": [ref.cx, ref.cy, ref.r], "centre_px": _dist(lb, ref),
                    "radius_ratio": lb.r / ref.r})
    found = [p for p in per if p["found"]]
    out = {"dataset": ds, "labels": "hand-drawn" if ds == "qvga" else "another automatic method",
           "background": no_contact[0] if no_contact else "per-pixel median of the presses",
           "usable_presses": len(per), "found": len(found)}
    for key, sel in (("all", found), ("unflagged", [p for p in found if not p["flagged"]])):
        d = np.array([p["centre_px"] for p in sel])
        r = np.array([p["radius_ratio"] for p in sel])
        out[key] = {**_centre_summary(d),
                    "radius_ratio_median": round(float(np.median(r)), 3) if r.size else None,
                    "radius_within_10pct": int(np.sum(np.abs(r - 1) <= 0.10))}
    return out, {p["image"]: p for p in per}, auto, ims, bg


def optical_fit(image: np.ndarray, background: np.ndarray, start: tuple[float, float, float], renderer,
                m_per_px: float) -> tuple[float, float, float, float]:
    """(cx, cy, indentation m, correlation) of the rendered ball press that best matches ``image`` - ``background``
    in a window around ``start`` (cx, cy, contact radius, px)."""
    from scipy.optimize import minimize

    from teletouch.plugins.sensors import gel

    rows, cols = image.shape[:2]
    ball = gel.Indenter.sphere(BALL_RADIUS)
    cx0, cy0, r0 = start
    half = int(round(1.8 * r0))
    win = (max(0, int(cy0) - half), min(rows, int(cy0) + half), max(0, int(cx0) - half), min(cols, int(cx0) + half))
    d = image.astype(np.float32) - background.astype(np.float32)
    d -= np.median(d[::4, ::4].reshape(-1, 3), axis=0)           # the frames' slow global brightness drift
    target = d[win[0]:win[1], win[2]:win[3]].astype(np.float64)
    smooth = 0.08e-3 / m_per_px                                   # sim-digit's default: the gel's thickness blur

    def render(p) -> np.ndarray:
        import cv2

        cx, cy, depth = p
        depth = float(np.clip(depth, 1e-5, 0.9 * BALL_RADIUS))
        pos = ((cx - (cols - 1) / 2.0) * m_per_px, (cy - (rows - 1) / 2.0) * m_per_px)
        z = gel.height_map(ball, depth, pos, shape=(rows, cols), m_per_px=m_per_px)
        z = cv2.GaussianBlur(z, (0, 0), smooth)
        return renderer.delta(z, m_per_px, win).astype(np.float64)

    def cost(p) -> float:
        m = render(p)
        k = float((m * target).sum() / max((m * m).sum(), 1e-9))  # the sensor's own gain: one per press
        return float(((target - k * m) ** 2).mean())

    d0 = ball.radius - math.sqrt(max(ball.radius ** 2 - (r0 * m_per_px) ** 2, 0.0))
    x0 = np.array([cx0, cy0, 2.0 * d0])                           # Hertz: twice the rigid cap
    simplex = np.array([x0, x0 + [3, 0, 0], x0 + [0, 3, 0], x0 + [0, 0, 0.5 * d0]])
    o = minimize(cost, x0, method="Nelder-Mead",
                 options={"xatol": 0.05, "fatol": 1e-4, "maxiter": 400, "initial_simplex": simplex})
    m = render(o.x).ravel()
    corr = float(np.corrcoef(m, target.ravel())[0, 1])
    return float(o.x[0]), float(o.x[1]), float(o.x[2]), corr


def third_estimate(per: dict, auto: dict, ims: list, bg: np.ndarray, limit: int | None, log) -> dict:
    """The optical fit on the VGA presses: its centre against the shared labels and against the labeller."""
    from teletouch.plugins.estimators import depth_calibration as C
    from teletouch.plugins.sensors import optics

    folder = DATA / "digit-presses-vga"
    labs = C.read_labels(folder / "labels.csv")
    m_per_px = 1.0 / PX_PER_M["vga"]
    renderer = optics.OpticalRenderer(optics.load_table(DATA / "digit-optical-model" / "polycalib.npz"),
                                      bg.shape[:2])
    by = dict(ims)
    names = [n for n in per if per[n]["found"]][:limit]
    rows = []
    t0 = time.perf_counter()
    for n in names:
        lb, ref = auto[n], labs[n]
        cx, cy, depth, corr = optical_fit(by[n], bg, (lb.cx, lb.cy, lb.r), renderer, m_per_px)
        a_px = math.sqrt(max(BALL_RADIUS * depth - depth * depth / 4, 0.0)) / m_per_px
        row = {"image": n, "flagged": lb.uncertain, "fit_centre_px": [round(cx, 1), round(cy, 1)],
               "fit_indentation_mm": round(depth * 1e3, 3), "fit_contact_radius_px": round(a_px, 1),
               "fit_correlation": round(corr, 3),
               "fit_to_labels_px": math.hypot(cx - ref.cx, cy - ref.cy),
               "fit_to_labeller_px": math.hypot(cx - lb.cx, cy - lb.cy),
               "labeller_to_labels_px": per[n]["centre_px"]}
        rows.append(row)
        log(f"{n}: fit-labels {row['fit_to_labels_px']:.2f} px, fit-labeller {row['fit_to_labeller_px']:.2f} px, "
            f"labeller-labels {row['labeller_to_labels_px']:.2f} px (corr {corr:.2f})")
    out = {"presses": len(rows), "seconds": round(time.perf_counter() - t0, 1),
           "fit_correlation_median": round(float(np.median([r["fit_correlation"] for r in rows])), 3)}
    for key, sel in (("all", rows), ("unflagged", [r for r in rows if not r["flagged"]])):
        out[key] = {pair: _centre_summary(np.array([r[pair] for r in sel]))
                    for pair in ("labeller_to_labels_px", "fit_to_labels_px", "fit_to_labeller_px")}
    # a bias common to the presses: the mean offset (columns, rows) of one centre from another
    at = {"fit": np.array([r["fit_centre_px"] for r in rows]).reshape(-1, 2),
          "labeller": np.array([per[r["image"]]["labeller"][:2] for r in rows]).reshape(-1, 2),
          "labels": np.array([per[r["image"]]["label"][:2] for r in rows]).reshape(-1, 2)}
    out["mean_offset_px_cols_rows"] = {f"{a}_minus_{b}": [round(float(v), 2) for v in (at[a] - at[b]).mean(axis=0)]
                                       for a, b in (("labeller", "labels"), ("fit", "labels"), ("labeller", "fit"))}
    out["per_press"] = rows
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fit the first 12 VGA presses only")
    args = ap.parse_args()

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    for name in ("digit-presses-qvga", "digit-presses-vga", "digit-optical-model"):
        data_folder(name)   # (or exit naming where the shared data were looked for)
    result: dict = {"benchmark": "labeller_accuracy"}
    qvga, per_q, *_ = labeller("qvga")
    vga, per_v, auto_v, ims_v, bg_v = labeller("vga")
    qvga["per_press"] = list(per_q.values())
    vga["per_press"] = list(per_v.values())
    result["qvga"], result["vga"] = qvga, vga
    result["vga_optical_fit"] = third_estimate(per_v, auto_v, ims_v, bg_v, 12 if args.quick else None, log)
    emit(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
