"""Force from depth: a least-squares polynomial from the sensor's max depth (m) to the normal force (N).

Two parts:

- :class:`ForceCalibration`: the fit (``ForceCalibration.fit``), the range guard (``predict``), the versioned JSON
  calibration file (``save`` / ``load``), the CSV reader for (depth, force) pairs and the Fig.-3-style plot.
- ``poly-force``: the graph component that applies a calibration at camera rate, with a contact gate (exactly 0 N
  without contact), input guards, an optional median/low-pass filter and a ``status`` port.

Model: ``F(d) = sum_k c_k d^k`` inside the calibrated depth range ``[d_lo, d_hi]`` (coefficients ascending, SI:
N/m^k). Outside it the cubic is never evaluated:

- above ``d_hi``: ``clamp`` (the default) holds ``F(d_hi)`` (status ``clamped``); ``extrapolate`` continues the fit on
  the straight line of its end slope, ``F(d_hi) + F'(d_hi) (d - d_hi)`` (status ``extrapolated``);
- between 0 and ``d_lo``: a straight line from (0, 0) to (d_lo, F(d_lo)) (status ``extrapolated``).

Forces are never negative. A fit that is not strictly increasing inside its range is refused.
"""

from __future__ import annotations

import csv
import datetime as _dt
import json
import math
import os
from collections import deque
from pathlib import Path
from typing import Any, Iterable, Literal, Sequence

import numpy as np
from pydantic import Field

from teletouch import Component, Kind, ModelFileError, Params, Port, Sample, TeletouchError, hookimpl
from teletouch.errors import ComponentFault
from teletouch.units import Hertz, Meters, Newtons

__all__ = ["ForceCalibration", "CalibrationError", "PolyForce", "read_pairs_csv", "write_pairs_csv",
           "packaged_calibrations", "resolve_calibration", "FORMAT", "VERSION"]

FORMAT = "teletouch-force-calibration"
VERSION = 1
DATA_DIR = Path(__file__).resolve().parent / "data"
SUFFIX = ".force.json"
PHASES = ("loading", "unloading", "")


class CalibrationError(TeletouchError, ValueError):
    """The data cannot give a usable force calibration (too few points, NaN, a non-monotonic fit, ...)."""


# ------------------------------------------------------------------------------------------------ polynomial maths
def _polyval(coef: Sequence[float], d: np.ndarray) -> np.ndarray:
    """Horner evaluation of ascending coefficients."""
    out = np.zeros_like(d, dtype=float)
    for c in reversed(coef):
        out = out * d + c
    return out


def _polyder(coef: Sequence[float]) -> list[float]:
    return [k * coef[k] for k in range(1, len(coef))] or [0.0]


def _lstsq(depths: np.ndarray, forces: np.ndarray, degree: int, zero_intercept: bool) -> list[float]:
    """Least squares on a scaled variable u = d / s (well conditioned), returned as SI coefficients."""
    s = float(np.max(np.abs(depths))) or 1.0
    u = depths / s
    first = 1 if zero_intercept else 0
    A = np.stack([u ** k for k in range(first, degree + 1)], axis=1)
    a, *_ = np.linalg.lstsq(A, forces, rcond=None)
    coef = [0.0] * (degree + 1)
    for j, k in enumerate(range(first, degree + 1)):
        coef[k] = float(a[j] / s ** k)
    return coef


def _monotonic_problem(coef: Sequence[float], lo: float, hi: float) -> str | None:
    """None if F is strictly increasing on [lo, hi], else where it is not."""
    der = _polyder(coef)
    span = hi - lo
    grid = np.linspace(lo, hi, 2001)
    slope = _polyval(der, grid)
    # scale-aware tolerance: a slope that is a tiny fraction of the mean slope counts as flat
    mean_slope = abs(_polyval(coef, np.array([hi]))[0] - _polyval(coef, np.array([lo]))[0]) / max(span, 1e-300)
    bad = slope <= 1e-6 * max(mean_slope, 1e-300)
    if bad.any():
        d = float(grid[np.argmax(bad)])
        return (f"dF/dd = {float(slope[np.argmax(bad)]):.4g} N/m at depth {d * 1e3:.4f} mm (the fit must be "
                f"strictly increasing from {lo * 1e3:.4f} to {hi * 1e3:.4f} mm)")
    if len(der) > 1 and any(der):
        roots = np.roots(list(reversed(der)))
        for r in roots:
            if abs(r.imag) < 1e-12 * max(1.0, abs(r.real)) and lo < r.real < hi:
                return f"dF/dd = 0 at depth {r.real * 1e3:.4f} mm, inside the calibrated range"
    return None


# ------------------------------------------------------------------------------------------------ the calibration
class ForceCalibration:
    """A polynomial map from max depth (m) to normal force (N), with its range, quality and data.

    ``coefficients`` are ascending (``c0 + c1 d + c2 d^2 + ...``) in SI units (N/m^k).
    """

    def __init__(self, coefficients: Sequence[float], depth_range: tuple[float, float],
                 force_range: tuple[float, float] | None = None, *, r2: float = math.nan, rmse: float = math.nan,
                 samples: list[dict[str, Any]] | None = None, hysteresis: dict[str, Any] | None = None,
                 sensor_model_id: str = "", depth_source: str = "", source: str = "", created: str | None = None,
                 zero_intercept: bool = False, extra: dict[str, Any] | None = None):
        self.coefficients = [float(c) for c in coefficients]
        self.degree = len(self.coefficients) - 1
        lo, hi = float(depth_range[0]), float(depth_range[1])
        self.depth_range = (lo, hi)
        if force_range is None:
            f = _polyval(self.coefficients, np.array([lo, hi]))
            force_range = (float(f[0]), float(f[1]))
        self.force_range = (float(force_range[0]), float(force_range[1]))
        self.r2 = float(r2)
        self.rmse = float(rmse)
        self.samples = list(samples or [])
        self.hysteresis = hysteresis
        self.sensor_model_id = sensor_model_id
        self.depth_source = depth_source
        self.source = source
        self.created = created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
        self.zero_intercept = bool(zero_intercept)
        self.extra = dict(extra or {})
        self.path: str | None = None
        lo_f = float(_polyval(self.coefficients, np.array([lo]))[0])
        hi_f = float(_polyval(self.coefficients, np.array([hi]))[0])
        self._f_lo = lo_f
        self._f_hi = hi_f
        self._slope_hi = float(_polyval(_polyder(self.coefficients), np.array([hi]))[0])

    # ---------------------------------------------------------------------------------------------------- fit
    @classmethod
    def fit(cls, depths_m: Iterable[float], forces_n: Iterable[float], degree: int = 3, *,
            phases: Iterable[str] | None = None, cycles: Iterable[int] | None = None, use: str = "all",
            zero_intercept: bool = False, sensor_model_id: str = "", depth_source: str = "", source: str = "",
            extra: dict[str, Any] | None = None) -> "ForceCalibration":
        """Least-squares polynomial fit of force (N) on max depth (m).

        phases: optional per-sample "loading"/"unloading" labels. Loading and unloading are fitted apart too and
        the gap between the two curves (the gel's hysteresis) is reported in ``hysteresis``.
        use: which samples make the calibration: "all" (default), "loading" or "unloading".
        Raises :class:`CalibrationError` for too few/invalid samples or a fit that is not strictly increasing.
        """
        d = np.asarray(list(depths_m), dtype=float).ravel()
        f = np.asarray(list(forces_n), dtype=float).ravel()
        if d.shape != f.shape:
            raise CalibrationError(f"{d.size} depths but {f.size} forces")
        if not isinstance(degree, (int, np.integer)) or not 1 <= degree <= 9:
            raise CalibrationError(f"degree must be an integer from 1 to 9, got {degree!r}")
        ph = [str(p or "") for p in phases] if phases is not None else [""] * d.size
        cy = [int(c) for c in cycles] if cycles is not None else [0] * d.size
        if len(ph) != d.size or len(cy) != d.size:
            raise CalibrationError(f"phases/cycles must have one entry per sample ({d.size})")
        for i, p in enumerate(ph):
            if p not in PHASES:
                raise CalibrationError(f"sample {i}: phase must be 'loading', 'unloading' or empty, got {p!r}")
        bad = ~(np.isfinite(d) & np.isfinite(f))
        if bad.any():
            i = int(np.argmax(bad))
            raise CalibrationError(f"sample {i}: depth {d[i]!r} m, force {f[i]!r} N is not finite")
        if (d < 0).any():
            i = int(np.argmax(d < 0))
            raise CalibrationError(f"sample {i}: depth {d[i]:.6g} m is negative (depth is positive into the gel)")
        if use not in ("all", "loading", "unloading"):
            raise CalibrationError(f"use must be 'all', 'loading' or 'unloading', got {use!r}")
        sel = np.ones(d.size, bool) if use == "all" else np.array([p == use for p in ph])
        dsel, fsel = d[sel], f[sel]
        nfree = degree + (0 if zero_intercept else 1)
        if dsel.size < nfree + 1:
            raise CalibrationError(f"{dsel.size} samples ({use}) for a degree-{degree} fit: need at least "
                                   f"{nfree + 1}")
        lo, hi = float(dsel.min()), float(dsel.max())
        if np.unique(np.round(dsel, 12)).size < nfree:
            raise CalibrationError(f"only {np.unique(dsel).size} distinct depths for a degree-{degree} fit")
        if hi <= 0 or hi - lo < 1e-7:
            raise CalibrationError(f"the depth range {lo * 1e3:.4f}..{hi * 1e3:.4f} mm is too small to calibrate")
        coef = _lstsq(dsel, fsel, degree, zero_intercept)
        problem = _monotonic_problem(coef, lo, hi)
        if problem is not None:
            raise CalibrationError(f"the degree-{degree} fit is not monotonic inside the calibrated range: "
                                   f"{problem}; refusing it (use a lower degree, more samples or check the data)")
        pred_all = _polyval(coef, d)
        res = fsel - _polyval(coef, dsel)
        ss_res = float(np.sum(res ** 2))
        ss_tot = float(np.sum((fsel - fsel.mean()) ** 2))
        r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else math.nan
        rmse = math.sqrt(ss_res / dsel.size)
        samples = [{"depth_m": float(d[i]), "force_n": float(f[i]), "predicted_n": float(pred_all[i]),
                    "residual_n": float(f[i] - pred_all[i]), "phase": ph[i], "cycle": cy[i], "used": bool(sel[i])}
                   for i in range(d.size)]
        hyst = _hysteresis(d, f, ph, degree, zero_intercept)
        frange = (float(fsel.min()), float(fsel.max()))
        cal = cls(coef, (lo, hi), frange, r2=r2, rmse=rmse, samples=samples, hysteresis=hyst,
                  sensor_model_id=sensor_model_id, depth_source=depth_source, source=source,
                  zero_intercept=zero_intercept, extra=dict(extra or {}, use=use))
        return cal

    # ---------------------------------------------------------------------------------------------------- predict
    def evaluate(self, max_depth_m: Any, out_of_range: str = "clamp") -> tuple[np.ndarray, np.ndarray]:
        """Vectorised map with the range guard. Returns (force N, code) with code 0 ok, 1 extrapolated, 2 clamped.

        Negative depths give 0 N (code 0); NaN raises ValueError.
        """
        d = np.asarray(max_depth_m, dtype=float)
        if np.isnan(d).any():
            raise ValueError("max depth is NaN; a force cannot be computed from it")
        if out_of_range not in ("extrapolate", "clamp"):
            raise ValueError(f"out_of_range must be 'extrapolate' or 'clamp', got {out_of_range!r}")
        lo, hi = self.depth_range
        code = np.zeros(d.shape, dtype=np.int8)
        inside = (d >= lo) & (d <= hi)
        f = np.zeros(d.shape, dtype=float)
        f[inside] = _polyval(self.coefficients, d[inside])
        below = (d > 0) & (d < lo)
        if below.any():
            f[below] = max(self._f_lo, 0.0) * d[below] / lo
            code[below] = 1
        above = d > hi
        if above.any():
            if out_of_range == "clamp":
                f[above] = self._f_hi
                code[above] = 2
            else:
                f[above] = self._f_hi + self._slope_hi * np.minimum(d[above] - hi, 1e3)
                code[above] = 1
        f = np.maximum(f, 0.0)
        return f, code

    def predict(self, max_depth_m: Any, out_of_range: str = "clamp") -> Any:
        """Force (N) for max depth (m): a float for a scalar, an array for an array. Never negative, never a cubic
        tail outside the calibrated range (see the module doc)."""
        f, _ = self.evaluate(max_depth_m, out_of_range)
        return float(f) if f.ndim == 0 else f

    def predict_with_status(self, max_depth_m: float, out_of_range: str = "clamp") -> tuple[float, str]:
        if isinstance(max_depth_m, float):  # a Python or numpy scalar: the same arithmetic without arrays
            return self._evaluate_scalar(float(max_depth_m), out_of_range)
        f, code = self.evaluate(max_depth_m, out_of_range)
        return float(f), ("ok", "extrapolated", "clamped")[int(code)]

    def _evaluate_scalar(self, d: float, out_of_range: str) -> tuple[float, str]:
        """:meth:`evaluate` for one float, operation for operation (60 Hz x a few us of numpy saved)."""
        if d != d:
            raise ValueError("max depth is NaN; a force cannot be computed from it")
        if out_of_range not in ("extrapolate", "clamp"):
            raise ValueError(f"out_of_range must be 'extrapolate' or 'clamp', got {out_of_range!r}")
        lo, hi = self.depth_range
        status = "ok"
        if lo <= d <= hi:
            f = 0.0
            for c in reversed(self.coefficients):
                f = f * d + c
        elif 0 < d < lo:
            f = max(self._f_lo, 0.0) * d / lo
            status = "extrapolated"
        elif d > hi:
            if out_of_range == "clamp":
                f, status = self._f_hi, "clamped"
            else:
                f, status = self._f_hi + self._slope_hi * min(d - hi, 1e3), "extrapolated"
        else:
            f = 0.0
        return float(max(f, 0.0)), status

    def derivative(self, max_depth_m: float) -> float:
        return float(_polyval(_polyder(self.coefficients), np.array([float(max_depth_m)]))[0])

    # ---------------------------------------------------------------------------------------------------- file
    def to_dict(self) -> dict[str, Any]:
        used = [s for s in self.samples if s.get("used", True)]
        frange = self.force_range[1] - self.force_range[0]
        quality = {"r2": _num(self.r2), "rmse_n": _num(self.rmse),
                   "rmse_pct_of_force_range": _num(100.0 * self.rmse / frange) if frange > 0 else None,
                   "max_abs_residual_n": max((abs(s["residual_n"]) for s in used), default=None),
                   "n_samples": len(used)}
        return {
            "format": FORMAT,
            "version": VERSION,
            "model": {
                "basis": "power-ascending",
                "units": "force in N, depth in m: F(d) = sum_k coefficients[k] * d**k",
                "degree": self.degree,
                "coefficients": list(self.coefficients),
                "zero_intercept": self.zero_intercept,
                "depth_range_m": list(self.depth_range),
                "force_range_n": list(self.force_range),
            },
            "quality": quality,
            "hysteresis": self.hysteresis,
            "sensor_model_id": self.sensor_model_id,
            "depth_source": self.depth_source,
            "source": self.source,
            "created": self.created,
            "extra": self.extra,
            "samples": self.samples,
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the calibration as JSON (atomically)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, path)
        self.path = str(path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ForceCalibration":
        """Read a calibration file (or a packaged one by name, e.g. ``sim-digit-qvga``). Raises ModelFileError
        naming the file and the field for any problem."""
        path = resolve_calibration(str(path))
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ModelFileError(f"{path}: force calibration file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelFileError(f"{path}: cannot read the force calibration file: {exc}") from None
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelFileError(f"{path}: not a force calibration file (corrupt JSON at line {exc.lineno}, "
                                 f"column {exc.colno}: {exc.msg})") from None
        cal = cls.from_dict(doc, str(path))
        cal.path = str(path)
        return cal

    @classmethod
    def from_dict(cls, doc: Any, where: str = "<calibration>") -> "ForceCalibration":
        def bad(field: str, expected: str, got: Any = ...) -> ModelFileError:
            tail = "" if got is ... else f", got {got!r}"[:200]
            return ModelFileError(f"{where}: field '{field}': expected {expected}{tail}")

        if not isinstance(doc, dict):
            raise bad("(top level)", "a JSON object", type(doc).__name__)
        if doc.get("format") != FORMAT:
            raise bad("format", f"'{FORMAT}' (is this a force calibration file?)", doc.get("format"))
        ver = doc.get("version")
        if ver != VERSION:
            raise ModelFileError(f"{where}: field 'version': file version {ver!r}, this teletouch reads version "
                                 f"{VERSION}; recalibrate with `teletouch calibrate force` or update teletouch")
        model = doc.get("model")
        if not isinstance(model, dict):
            raise bad("model", "an object")
        deg = model.get("degree")
        if not isinstance(deg, int) or isinstance(deg, bool) or not 1 <= deg <= 9:
            raise bad("model.degree", "an integer from 1 to 9", deg)
        coef = model.get("coefficients")
        if not isinstance(coef, list) or len(coef) != deg + 1 or not all(_finite(c) for c in coef):
            raise bad("model.coefficients", f"a list of {deg + 1} finite numbers (degree {deg})", coef)
        dr = model.get("depth_range_m")
        if (not isinstance(dr, list) or len(dr) != 2 or not all(_finite(x) for x in dr) or dr[0] < 0
                or dr[1] <= dr[0]):
            raise bad("model.depth_range_m", "[low, high] in m with 0 <= low < high", dr)
        fr = model.get("force_range_n")
        if not isinstance(fr, list) or len(fr) != 2 or not all(_finite(x) for x in fr) or fr[1] < fr[0]:
            raise bad("model.force_range_n", "[low, high] in N with low <= high", fr)
        problem = _monotonic_problem(coef, dr[0], dr[1])
        if problem is not None:
            raise bad("model.coefficients", f"a strictly increasing polynomial on the depth range ({problem})")
        q = doc.get("quality", {})
        if not isinstance(q, dict):
            raise bad("quality", "an object", q)
        samples = doc.get("samples", [])
        if not isinstance(samples, list):
            raise bad("samples", "a list", type(samples).__name__)
        for i, s in enumerate(samples):
            if not isinstance(s, dict) or not _finite(s.get("depth_m")) or not _finite(s.get("force_n")):
                raise bad(f"samples[{i}]", "an object with finite depth_m and force_n", s)
        for key in ("sensor_model_id", "depth_source", "source", "created"):
            if key in doc and doc[key] is not None and not isinstance(doc[key], str):
                raise bad(key, "a string", doc[key])
        hyst = doc.get("hysteresis")
        if hyst is not None and not isinstance(hyst, dict):
            raise bad("hysteresis", "an object or null", hyst)
        return cls(coef, (dr[0], dr[1]), (fr[0], fr[1]), r2=_float_or_nan(q.get("r2")),
                   rmse=_float_or_nan(q.get("rmse_n")), samples=samples, hysteresis=hyst,
                   sensor_model_id=doc.get("sensor_model_id") or "", depth_source=doc.get("depth_source") or "",
                   source=doc.get("source") or "", created=doc.get("created"),
                   zero_intercept=bool(model.get("zero_intercept", False)), extra=doc.get("extra") or {})

    # ---------------------------------------------------------------------------------------------------- report
    def summary(self) -> str:
        lo, hi = self.depth_range
        frange = self.force_range[1] - self.force_range[0]
        lines = [f"force calibration: degree {self.degree}, depth {lo * 1e3:.3f}..{hi * 1e3:.3f} mm, "
                 f"force {self.force_range[0]:.3f}..{self.force_range[1]:.3f} N",
                 f"  R^2 {self.r2:.5f}, RMSE {self.rmse:.4f} N"
                 + (f" ({100 * self.rmse / frange:.2f}% of the force range)" if frange > 0 else "")
                 + f", {sum(1 for s in self.samples if s.get('used', True))} samples"]
        coef = ", ".join(f"{c:.6g}" for c in self.coefficients)
        lines.append(f"  F(d) = sum c_k d^k, c = [{coef}] (N, m)")
        h = self.hysteresis
        if h and h.get("max_gap_n") is not None:
            lines.append(f"  hysteresis (loading - unloading): max gap {h['max_gap_n']:.4f} N, mean "
                         f"{h['mean_gap_n']:.4f} N ({h['max_gap_pct_of_force_range']:.2f}% of the force range)")
        elif h:
            lines.append(f"  hysteresis: {h.get('note', 'not measured')}")
        return "\n".join(lines)

    def save_plot(self, path: str | os.PathLike, title: str | None = None) -> Path:
        """A plot like the paper's Fig. 3: samples, the fit and the residuals (PNG)."""
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        path = Path(path)
        lo, hi = self.depth_range
        fig, (ax, axr) = plt.subplots(2, 1, figsize=(6.8, 6.6), sharex=True, layout="constrained",
                                      gridspec_kw={"height_ratios": [3, 1.3]})
        try:
            styles = {"loading": ("tab:blue", "^", "loading"), "unloading": ("tab:orange", "v", "unloading"),
                      "": ("tab:blue", "o", "samples")}
            for ph, (color, marker, label) in styles.items():
                pts = [s for s in self.samples if (s.get("phase") or "") == ph]
                if not pts:
                    continue
                x = np.array([s["depth_m"] for s in pts]) * 1e3
                y = np.array([s["force_n"] for s in pts])
                r = np.array([s["force_n"] - self.predict(s["depth_m"]) for s in pts])
                ax.scatter(x, y, s=14, c=color, marker=marker, alpha=0.7, label=label)
                axr.scatter(x, r, s=10, c=color, marker=marker, alpha=0.7)
            xs = np.linspace(lo, hi, 300)
            ax.plot(xs * 1e3, _polyval(self.coefficients, xs), "k-", lw=1.6,
                    label=f"degree-{self.degree} fit, $R^2$ = {self.r2:.5f}")
            h = self.hysteresis or {}
            for ph, color in (("loading", "tab:blue"), ("unloading", "tab:orange")):
                sub = h.get(ph)
                if isinstance(sub, dict) and sub.get("coefficients"):
                    a, b = sub["depth_range_m"]
                    xx = np.linspace(a, b, 200)
                    ax.plot(xx * 1e3, _polyval(sub["coefficients"], xx), "--", color=color, lw=1,
                            label=f"{ph} fit")
            ax.set_ylabel("force (N)")
            ax.set_title(title or f"Force calibration ({self.sensor_model_id or 'sensor'})")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="upper left", fontsize=8)
            axr.axhline(0.0, color="k", lw=0.8)
            axr.set_xlabel("max depth (mm)")
            axr.set_ylabel("residual (N)")
            frange = self.force_range[1] - self.force_range[0]
            pct = f" ({100 * self.rmse / frange:.2f}% of the force range)" if frange > 0 else ""
            axr.set_title(f"residuals: RMSE {self.rmse:.4f} N{pct}", fontsize=9)
            axr.grid(True, alpha=0.3)
            path.parent.mkdir(parents=True, exist_ok=True)
            fig.savefig(path, dpi=110)
        finally:
            plt.close(fig)
        return path


def _hysteresis(d: np.ndarray, f: np.ndarray, ph: list[str], degree: int, zero_intercept: bool) -> dict | None:
    """Fit loading and unloading apart and measure the gap between the curves on their common depth range."""
    has = {p: np.array([x == p for x in ph]) for p in ("loading", "unloading")}
    if not has["loading"].any() and not has["unloading"].any():
        return None
    out: dict[str, Any] = {}
    fits = {}
    for p, m in has.items():
        n = int(m.sum())
        deg = min(degree, max(1, np.unique(d[m]).size - 2)) if n else 0
        if n < 3 or deg < 1:
            out[p] = {"n_samples": n}
            continue
        coef = _lstsq(d[m], f[m], deg, zero_intercept)
        fits[p] = coef
        out[p] = {"n_samples": n, "degree": deg, "coefficients": coef,
                  "depth_range_m": [float(d[m].min()), float(d[m].max())]}
    if len(fits) == 2:
        lo = max(out["loading"]["depth_range_m"][0], out["unloading"]["depth_range_m"][0])
        hi = min(out["loading"]["depth_range_m"][1], out["unloading"]["depth_range_m"][1])
        if hi > lo:
            x = np.linspace(lo, hi, 200)
            gap = _polyval(fits["loading"], x) - _polyval(fits["unloading"], x)
            frange = float(f.max() - f.min()) or 1.0
            i = int(np.argmax(np.abs(gap)))
            out.update({"max_gap_n": float(gap[i]), "max_gap_at_depth_m": float(x[i]),
                        "mean_gap_n": float(np.mean(gap)),
                        "max_gap_pct_of_force_range": float(100.0 * abs(gap[i]) / frange),
                        "note": "gap = loading fit - unloading fit over the common depth range"})
            return out
    out.update({"max_gap_n": None, "note": "needs both loading and unloading samples"})
    return out


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _float_or_nan(x: Any) -> float:
    return float(x) if _finite(x) else math.nan


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# ------------------------------------------------------------------------------------------------ CSV of pairs
DEPTH_COLUMNS = {"depth_m": 1.0, "max_depth_m": 1.0, "depth": 1.0, "max_depth": 1.0, "depth_mm": 1e-3,
                 "max_depth_mm": 1e-3}
FORCE_COLUMNS = {"force_n": 1.0, "force": 1.0, "device_force_n": 1.0}
CSV_COLUMNS = ["depth_m", "force_n", "phase", "cycle", "displacement_m", "gt_max_depth_m", "gt_force_n"]


def read_pairs_csv(path: str | os.PathLike) -> dict[str, Any]:
    """Read (depth, force) pairs. Header required: a depth column (depth_m, max_depth_m, depth or depth_mm) and a
    force column (force_n or force, N); optional phase (loading/unloading) and cycle.
    Returns {"depth_m": array, "force_n": array, "phase": list | None, "cycle": list | None}."""
    path = Path(path)
    try:
        fh = path.open(newline="", encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot open the CSV file: {exc}") from None
    with fh:
        rows = [r for r in csv.reader(fh)]
    lines = [(i + 1, r) for i, r in enumerate(rows) if r and not r[0].lstrip().startswith("#")
             and any(c.strip() for c in r)]
    if not lines:
        raise CalibrationError(f"{path}: empty CSV file (expected a header such as 'depth_m,force_n')")
    hline, header = lines[0]
    names = [h.strip().lower() for h in header]
    dcol = next((i for i, n in enumerate(names) if n in DEPTH_COLUMNS), None)
    fcol = next((i for i, n in enumerate(names) if n in FORCE_COLUMNS), None)
    if dcol is None or fcol is None:
        raise CalibrationError(f"{path}:{hline}: header {header!r} needs a depth column ("
                               f"{', '.join(DEPTH_COLUMNS)}) and a force column ({', '.join(FORCE_COLUMNS)})")
    dscale = DEPTH_COLUMNS[names[dcol]]
    pcol = names.index("phase") if "phase" in names else None
    ccol = names.index("cycle") if "cycle" in names else None
    depth, force, phase, cycle = [], [], [], []
    for ln, r in lines[1:]:
        def cell(i: int | None, what: str) -> str:
            if i is None:
                return ""
            if i >= len(r):
                raise CalibrationError(f"{path}:{ln}: missing column '{names[i]}' ({what})")
            return r[i].strip()

        for col, sink, scale, what in ((dcol, depth, dscale, "depth"), (fcol, force, 1.0, "force (N)")):
            txt = cell(col, what)
            try:
                v = float(txt) * scale
            except ValueError:
                raise CalibrationError(f"{path}:{ln}: column '{names[col]}': expected a number ({what}), "
                                       f"got {txt!r}") from None
            if not math.isfinite(v):
                raise CalibrationError(f"{path}:{ln}: column '{names[col]}': {txt!r} is not finite")
            sink.append(v)
        p = cell(pcol, "phase").lower()
        if p not in PHASES:
            raise CalibrationError(f"{path}:{ln}: column 'phase': expected loading or unloading, got {p!r}")
        phase.append(p)
        c = cell(ccol, "cycle")
        try:
            cycle.append(int(c) if c else 0)
        except ValueError:
            raise CalibrationError(f"{path}:{ln}: column 'cycle': expected an integer, got {c!r}") from None
    if not depth:
        raise CalibrationError(f"{path}: no data rows after the header")
    return {"depth_m": np.array(depth), "force_n": np.array(force),
            "phase": phase if pcol is not None else None, "cycle": cycle if ccol is not None else None}


def write_pairs_csv(path: str | os.PathLike, rows: Iterable[dict[str, Any]]) -> Path:
    """Write samples (dicts with keys from CSV_COLUMNS; missing ones left empty) as a CSV read_pairs_csv reads."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            w.writerow(["" if r.get(k) is None else (f"{r[k]:.9g}" if isinstance(r[k], float) else r[k])
                        for k in CSV_COLUMNS])
    return path


# ------------------------------------------------------------------------------------------------ finding files
def packaged_calibrations() -> list[str]:
    """Names of the calibrations shipped with teletouch (data/<name>.force.json)."""
    if not DATA_DIR.is_dir():
        return []
    return sorted(p.name[: -len(SUFFIX)] for p in DATA_DIR.glob("*" + SUFFIX))


def resolve_calibration(name_or_path: str) -> Path:
    """A path to an existing file, or the name of a packaged calibration (e.g. 'sim-digit-qvga')."""
    p = Path(os.path.expanduser(str(name_or_path)))
    if p.is_file():
        return p
    packaged = DATA_DIR / (str(name_or_path) + SUFFIX)
    if packaged.is_file():
        return packaged
    known = ", ".join(packaged_calibrations()) or "none"
    raise ModelFileError(f"force calibration '{name_or_path}' not found: not a file and not a packaged calibration "
                         f"(packaged: {known}); make one with `teletouch calibrate force`")


# ------------------------------------------------------------------------------------------------ the component
STATUS_VALUES = ("ok", "no-contact", "clamped", "extrapolated", "invalid-input")


class PolyForce(Component):
    """Normal force (N) from the sensor's max depth (m) by a calibrated polynomial (exactly 0 N without contact)."""

    name = "poly-force"
    kind = Kind.ESTIMATOR
    default_rate = 60.0
    inputs = {
        "max_depth": Port("float64", (), "m", "max depth of the gel surface (positive into the gel)", required=True),
        "contact_area": Port("float64", (), "m^2", "contact area; below min_contact_area means no contact",
                             required=False),
        "contact_mask": Port("bool", (None, None), "", "contact mask; all False means no contact",
                             required=False),
    }
    outputs = {
        "force": Port("float64", (), "N", "normal force (>= 0, exactly 0 without contact); stamp of the depth"),
        "status": Port("str", (), "", "ok | no-contact | clamped | extrapolated | invalid-input"),
    }

    class Params(Params):
        calibration: str = Field("sim-digit-qvga", description="force calibration file, or the name of a "
                                 "packaged one (sim-digit-qvga)")
        out_of_range: Literal["extrapolate", "clamp"] = Field(
            "clamp", description="beyond the calibrated depth: hold the end force (default; safer and, measured on "
            "held-out sim presses, more accurate) or continue on the end slope")
        contact_threshold: Meters = Field(3e-5, ge=0, description="max depth below this is no contact (0 N)",
                                          json_schema_extra={"unit": "m"})
        min_contact_area: float = Field(0.0, ge=0, description="contact area below this is no contact (when "
                                        "contact_area is wired)", json_schema_extra={"unit": "m^2"})
        negative_tolerance: Meters = Field(1e-4, ge=0, description="a max depth below -tolerance is invalid "
                                           "input (small negative values are no contact)",
                                           json_schema_extra={"unit": "m"})
        max_force: Newtons | None = Field(None, gt=0, description="cap on the output force (status clamped)",
                                          json_schema_extra={"unit": "N"})
        median_window: int = Field(1, ge=1, le=15, description="median over the last N depth samples (outlier "
                                   "rejection; adds (N-1)/2 samples of latency; 1 = off)")
        lowpass_cutoff: Hertz | None = Field(None, gt=0, description="first-order low-pass on the force (adds "
                                             "about 1/(2 pi fc) s of delay; None = off)",
                                             json_schema_extra={"unit": "Hz"})
        fault_after_invalid: int = Field(0, ge=0, description="fault the node after this many invalid inputs in "
                                         "a row (0 = never; force stays 0 while invalid)")

    def configure(self) -> None:
        self.cal = ForceCalibration.load(resolve_calibration(self.params.calibration))
        self._reset()
        self.counts = {s: 0 for s in STATUS_VALUES}
        self.last_force = 0.0
        self.last_status = "no-contact"
        self.invalid_run = 0

    def _reset(self) -> None:
        self._window: deque[float] = deque(maxlen=self.params.median_window)
        self._filt: float | None = None
        self._filt_t: float | None = None
        self._last_stamp: float | None = None

    def activate(self) -> None:
        self._reset()

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        s = inputs["max_depth"]
        if s is None or s.stamp == self._last_stamp:
            return None
        self._last_stamp = s.stamp
        force, status = self.compute(s.value, inputs.value("contact_area"), inputs.value("contact_mask"), s.stamp)
        self.last_force, self.last_status = force, status
        self.counts[status] += 1
        if status == "invalid-input":
            self.invalid_run += 1
            n = self.params.fault_after_invalid
            if n and self.invalid_run >= n:
                raise ComponentFault(f"{self.invalid_run} invalid max-depth inputs in a row (last {s.value!r})",
                                     self.id)
        else:
            self.invalid_run = 0
        return {"force": Sample(force, s.stamp), "status": Sample(status, s.stamp)}

    def compute(self, depth: Any, area: Any = None, mask: Any = None, stamp: float = 0.0) -> tuple[float, str]:
        p = self.params
        try:
            d = float(depth)
        except (TypeError, ValueError):
            self._reset_filters()
            return 0.0, "invalid-input"
        if not math.isfinite(d) or d < -p.negative_tolerance:
            self._reset_filters()
            return 0.0, "invalid-input"
        if area is not None:
            try:
                a = float(area)
            except (TypeError, ValueError):
                a = math.nan
            if not math.isfinite(a) or a < 0:
                self._reset_filters()
                return 0.0, "invalid-input"
        contact = d >= p.contact_threshold
        if contact and area is not None and float(area) <= p.min_contact_area:
            contact = False
        if contact and mask is not None and not bool(np.any(mask)):
            contact = False
        if not contact:
            self._reset_filters()
            return 0.0, "no-contact"
        self._window.append(d)
        if len(self._window) > 1:
            d = float(np.median(self._window))
        force, status = self.cal.predict_with_status(d, p.out_of_range)
        if p.lowpass_cutoff is not None:
            if self._filt is None:
                self._filt = force
            else:
                dt = max(stamp - (self._filt_t if self._filt_t is not None else stamp), 0.0)
                tau = 1.0 / (2.0 * math.pi * p.lowpass_cutoff)
                self._filt += (force - self._filt) * (dt / (tau + dt) if dt > 0 else 0.0)
            self._filt_t = stamp
            force = self._filt
        if p.max_force is not None and force > p.max_force:
            force, status = float(p.max_force), "clamped"
        if not math.isfinite(force) or force < 0:  # cannot happen with a validated calibration; never emit it
            return 0.0, "invalid-input"
        return float(force), status

    def _reset_filters(self) -> None:
        self._window.clear()
        self._filt = None
        self._filt_t = None

    def status(self) -> dict[str, Any]:
        return {"force_n": getattr(self, "last_force", 0.0), "status": getattr(self, "last_status", ""),
                "invalid": getattr(self, "counts", {}).get("invalid-input", 0)}


@hookimpl
def teletouch_components():
    return [PolyForce]
