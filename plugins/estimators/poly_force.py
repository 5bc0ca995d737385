"""Force from depth: a least-squares polynomial from the sensor's max depth (m) to the normal force (N).

Two parts:

- :class:`ForceCalibration`: the fit (``ForceCalibration.fit``), the range guard (``predict``), the versioned JSON
  calibration file (``save`` / ``load``), the CSV reader for (depth, force) pairs and the Fig.-3-style plot.
- ``poly-force``: the graph component that applies a calibration at camera rate, with a contact gate (exactly 0 N
  without contact), input guards, an optional median/low-pass filter and a ``status`` port.

Model: ``F(d) = sum_k c_k d^k`` inside the calibrated depth range ``[d_lo, d_hi]`` (coefficients ascending, SI:
N/m^k). Outside it the cubic is never evaluated:

- above ``d_hi``: ``clamp`` (the default) holds ``F(d_hi)`` (status ``clamped``); ``extrapolate`` continues the fit on
  the straight line of its end slope, ``F(d_hi) + F'(d_hi) (d - d_hi)`` (status ``extrapolated``), up to
  ``MAX_DEPTH_M`` (10 mm, deeper than any gel) and holds it beyond (status ``clamped``);
- between 0 and ``d_lo``: a straight line from (0, 0) to (d_lo, F(d_lo)) (status ``extrapolated``).

Forces are never negative; a non-finite depth (NaN, inf) raises ValueError. A fit that is not strictly increasing
inside its range is refused, and so is one outside the limits a calibration file is held to (``_limits_problem``).

Optional position terms (``position_degree`` p > 0, beyond the paper): the coefficients vary over the sensor as 2-D
polynomials of total degree p in the contact centroid, ``c_k(x, y) = sum_j P[k][j] u^a_j v^b_j`` with ``(u, v)`` the
centroid scaled to the calibrated area (the box spanned by the press points) as [-1, 1]^2. A depth estimator whose
max depth for the same press varies with where the press is (measured: 5-9 % on sim-digit) is then calibrated by
pressing at points across the sensor. A centroid outside the calibrated area is held at its edge (status
``clamped``): a polynomial is never extrapolated. At the centre of the area the model is ``coefficients``.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import errno
import json
import math
import os
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterable, Literal, Sequence

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import Component, Kind, ModelFileError, Params, Port, Sample, TeletouchError, hookimpl
from teletouch.errors import ComponentFault
from teletouch.paths import input_file
from teletouch.reproducible import build_time
from teletouch.units import (
    MAX_PLAUSIBLE_DEPTH_LIMIT, UNDERSCORE, Hertz, Meters, Newtons, Seconds, plausible_contact_area, plausible_depth,
)

__all__ = ["ForceCalibration", "CalibrationError", "PolyForce", "read_pairs_csv", "write_pairs_csv",
           "packaged_calibrations", "resolve_calibration", "check_calibration_file", "depth_levels", "FORMAT",
           "VERSION", "DEFAULT_MIN_R2", "DEPTH_LEVEL_TOLERANCE_M", "MAX_DEGREE", "MAX_POSITION_DEGREE", "MAX_DEPTH_M"]

FORMAT = "teletouch-force-calibration"
VERSION = 1
DATA_DIR = Path(__file__).resolve().parent / "data"
SUFFIX = ".force.json"
PHASES = ("loading", "unloading", "")
UNITS = "force in N, depth in m: F(d) = sum_k coefficients[k] * d**k"
BASIS = "power-ascending"
#: depths closer than this (m) are one depth level when counting the levels a fit needs: the max-depth estimate of a
#: held press jitters by 0.4-3 um (standard deviation of single frames, 0.1-1 mm presses on sim-digit) while a press
#: routine steps 0.1 mm, so samples of a stuck probe or a repeated reading fall in one level
DEPTH_LEVEL_TOLERANCE_M = 5e-6
#: the smallest R^2 ``teletouch calibrate force`` accepts (``--min-r2``): the paper's fit reaches 0.9987, the packaged
#: simulated calibration 0.9992 and the paper's protocol in simulation 0.99995; 0.99 leaves room for a noisier real
#: sensor while a fit that explains only 95% of the force's variance is refused
DEFAULT_MIN_R2 = 0.99
#: with position terms, the smallest singular value of the fit's column-normalised design matrix relative to the
#: largest below which the samples do not determine the terms (readings of one depth level at a press point leave
#: ~1e-10; the packaged calibration's samples give 4e-4, and 2e-5 with position degree 6)
POSITION_FIT_MIN_SV = 1e-7
#: the highest polynomial degree in depth, and of the position terms, that a fit and a calibration file may have
MAX_DEGREE = 9
MAX_POSITION_DEGREE = 6


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


def depth_levels(depths: Any, tolerance: float = DEPTH_LEVEL_TOLERANCE_M) -> int:
    """How many distinct depth levels the depths hold: sorted, a depth more than ``tolerance`` (m) above the first
    depth of the current level starts a new one (near-duplicates never chain into a long level)."""
    levels, start = 0, -math.inf
    for x in np.sort(np.asarray(depths, dtype=float).ravel()):
        if x > start + tolerance:
            levels, start = levels + 1, x
    return levels


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


# ------------------------------------------------------------------------------------------------ position terms
def position_exponents(degree: int) -> list[tuple[int, int]]:
    """Exponents (a, b) of the terms u^a v^b of a 2-D polynomial of total degree <= ``degree``, lowest first."""
    return [(n - b, b) for n in range(degree + 1) for b in range(n + 1)]


class PositionModel:
    """The depth polynomial's coefficients as 2-D polynomials of the contact centroid (see the module doc).

    ``coefficients[k][j]`` (SI: N/m^k) multiplies ``d^k u^a_j v^b_j`` with ``(a_j, b_j) = position_exponents(
    degree)[j]``, ``u = (x - center[0]) / half_extent[0]`` and ``v = (y - center[1]) / half_extent[1]`` (x along
    the image columns, y along its rows, m from the image centre: the depth estimator's ``centroid``).

    The calibrated depth range depends on the position too (a press reads shallower where the estimator reads
    shallow): ``depth_high[i][j]`` is the deepest sample near the grid node ``(u_i, v_j)`` (``GRID`` x ``GRID``
    nodes over [-1, 1]^2, "near": within ``NEAR`` in scaled units); between nodes it is interpolated bilinearly. Above
    it the out-of-range policy applies, as above the global range without position terms."""

    GRID = 9     # nodes per axis of the depth-limit grid, where monotonicity is checked too
    NEAR = 0.4   # scaled distance within which a sample counts for a node's depth limit

    def __init__(self, degree: int, center: Sequence[float], half_extent: Sequence[float],
                 coefficients: Sequence[Sequence[float]], depth_high: Any = None):
        self.degree = int(degree)
        self.center = (float(center[0]), float(center[1]))
        self.half_extent = (float(half_extent[0]), float(half_extent[1]))
        self.exponents = position_exponents(self.degree)
        self.P = np.array(coefficients, dtype=float)
        self._a = np.array([e[0] for e in self.exponents])
        self._b = np.array([e[1] for e in self.exponents])
        self.depth_high = None if depth_high is None else np.array(depth_high, dtype=float)

    def high(self, u: float, v: float) -> float:
        """The deepest calibrated depth (m) at a scaled position (bilinear between the grid's nodes)."""
        g = self.GRID - 1
        fu, fv = (u + 1.0) * 0.5 * g, (v + 1.0) * 0.5 * g
        i, j = min(int(fu), g - 1), min(int(fv), g - 1)
        a, b = fu - i, fv - j
        h = self.depth_high
        return float((1 - a) * ((1 - b) * h[i, j] + b * h[i, j + 1])
                     + a * ((1 - b) * h[i + 1, j] + b * h[i + 1, j + 1]))

    def high_many(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """:meth:`high` at many scaled positions in [-1, 1]^2 at once."""
        g = self.GRID - 1
        fu, fv = (np.asarray(u, float) + 1.0) * 0.5 * g, (np.asarray(v, float) + 1.0) * 0.5 * g
        i, j = np.minimum(fu.astype(int), g - 1), np.minimum(fv.astype(int), g - 1)
        a, b = fu - i, fv - j
        h = self.depth_high
        return ((1 - a) * ((1 - b) * h[i, j] + b * h[i, j + 1]) + a * ((1 - b) * h[i + 1, j] + b * h[i + 1, j + 1]))

    def local_many(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(n, degree + 1) depth polynomials (ascending SI coefficients) at n scaled positions."""
        return self.basis(u, v) @ self.P.T

    def set_depth_high(self, u: np.ndarray, v: np.ndarray, d: np.ndarray) -> None:
        """Each node's limit: the deepest sample within NEAR of it; nodes without one take the smallest limit of
        the others (the conservative choice)."""
        g = np.linspace(-1.0, 1.0, self.GRID)
        h = np.full((self.GRID, self.GRID), np.nan)
        for i, gu in enumerate(g):
            for j, gv in enumerate(g):
                near = np.hypot(u - gu, v - gv) < self.NEAR
                if near.any():
                    h[i, j] = d[near].max()
        h[np.isnan(h)] = np.nanmin(h)
        self.depth_high = h

    def scaled(self, x: float, y: float) -> tuple[float, float, bool]:
        """(u, v) clipped to [-1, 1]^2 and whether the point was outside the calibrated area."""
        u = (x - self.center[0]) / self.half_extent[0]
        v = (y - self.center[1]) / self.half_extent[1]
        outside = not (-1.0 <= u <= 1.0 and -1.0 <= v <= 1.0)
        return min(max(u, -1.0), 1.0), min(max(v, -1.0), 1.0), outside

    def basis(self, u: Any, v: Any) -> np.ndarray:
        """(..., n_terms) values of the terms at scaled positions."""
        u = np.asarray(u, dtype=float)[..., None]
        v = np.asarray(v, dtype=float)[..., None]
        return u ** self._a * v ** self._b

    def local(self, u: float, v: float) -> list[float]:
        """The depth polynomial (ascending SI coefficients) at a scaled position."""
        return (self.P @ self.basis(u, v)).tolist()

    def grid(self) -> list[tuple[float, float]]:
        g = np.linspace(-1.0, 1.0, self.GRID)
        return [(float(u), float(v)) for u in g for v in g]

    def to_dict(self) -> dict[str, Any]:
        return {"degree": self.degree, "center_m": list(self.center), "half_extent_m": list(self.half_extent),
                "terms": [f"u^{a} v^{b}" for a, b in self.exponents],
                "coefficients": self.P.tolist(),
                "depth_high_m": self.depth_high.tolist(),
                "note": "c_k(x, y) = sum_j coefficients[k][j] * u**a_j * v**b_j, u = (x - center_m[0]) / "
                        "half_extent_m[0], v = (y - center_m[1]) / half_extent_m[1], clipped to [-1, 1]; "
                        "depth_high_m[i][j]: the calibrated depth limit at u = -1 + 2 i / 8, v = -1 + 2 j / 8"}

    @classmethod
    def from_dict(cls, doc: Any, depth_degree: int, bad: Callable[..., Exception]) -> "PositionModel":
        """The model of a file's ``model.position``, its structure checked (its limits: :func:`_limits_problem`)."""
        if not isinstance(doc, dict):
            raise bad("model.position", "an object (or absent)", doc)
        deg = doc.get("degree")
        if not isinstance(deg, int) or isinstance(deg, bool) or not 1 <= deg <= MAX_POSITION_DEGREE:
            raise bad("model.position.degree", f"an integer from 1 to {MAX_POSITION_DEGREE}", deg)
        for key in ("center_m", "half_extent_m"):
            v = doc.get(key)
            if not isinstance(v, list) or len(v) != 2 or not all(_finite(x) for x in v):
                raise bad(f"model.position.{key}", "[x, y] in m, finite numbers", v)
        if not all(h > 0 for h in doc["half_extent_m"]):
            raise bad("model.position.half_extent_m", "two positive half widths in m", doc["half_extent_m"])
        n = len(position_exponents(deg))
        coef = doc.get("coefficients")
        if (not isinstance(coef, list) or len(coef) != depth_degree + 1
                or not all(isinstance(r, list) and len(r) == n and all(_finite(c) for c in r) for r in coef)):
            raise bad("model.position.coefficients", f"{depth_degree + 1} lists (depth degree {depth_degree}) of {n} "
                      f"finite numbers (position degree {deg})", coef)
        hi = doc.get("depth_high_m")
        g = cls.GRID
        if (not isinstance(hi, list) or len(hi) != g
                or not all(isinstance(r, list) and len(r) == g and all(_finite(x) for x in r) for r in hi)):
            raise bad("model.position.depth_high_m", f"{g} lists of {g} depths in m", hi)
        return cls(deg, doc["center_m"], doc["half_extent_m"], coef, hi)


def _fit_position(d: np.ndarray, f: np.ndarray, pos: np.ndarray, degree: int, pdeg: int,
                  zero_intercept: bool) -> PositionModel:
    """Least squares of F on d^k u^a v^b (d scaled for conditioning) over the box the positions span."""
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    half = (hi - lo) / 2.0
    if (half < 1e-4).any():
        axis = "x" if half[0] < 1e-4 else "y"
        raise CalibrationError(f"position_degree {pdeg} needs presses across the sensor, but the contact centroids "
                               f"span only {2 * half[0] * 1e3:.3f} x {2 * half[1] * 1e3:.3f} mm (too little along "
                               f"{axis}): press at several points (press-routine positions) or use position_degree 0")
    center = (hi + lo) / 2.0
    model = PositionModel(pdeg, center, half, np.zeros((degree + 1, len(position_exponents(pdeg)))))
    u_pos, v_pos = (pos[:, 0] - center[0]) / half[0], (pos[:, 1] - center[1]) / half[1]
    phi = model.basis(u_pos, v_pos)
    sv = np.linalg.svd(phi / np.linalg.norm(phi, axis=0), compute_uv=False)
    if sv[-1] < 1e-3 * sv[0]:
        raise CalibrationError(f"the press points do not determine a position model of degree {pdeg} "
                               f"({phi.shape[1]} terms): press at more points spread over the area (at least "
                               f"{phi.shape[1]}, e.g. a 5 x 5 grid for degree 3) or lower position_degree")
    s = float(np.max(np.abs(d))) or 1.0
    u = d / s
    first = 1 if zero_intercept else 0
    A = np.concatenate([u[:, None] ** k * phi for k in range(first, degree + 1)], axis=1)
    # enough depth levels in all and enough press points do not make enough depth levels away from the centre: a
    # point pressed to one depth only leaves its curve's shape free there (least squares then takes the smallest
    # coefficients, silently: R^2 1 with wrong forces at the other depths); the packaged calibration's ratio is 4e-4
    sva = np.linalg.svd(A / np.linalg.norm(A, axis=0), compute_uv=False)
    if sva[-1] < POSITION_FIT_MIN_SV * sva[0]:
        raise CalibrationError(f"the samples do not determine a degree-{degree} depth curve with position terms of "
                               f"degree {pdeg} ({A.shape[1]} terms): the depth levels are not spread over the press "
                               f"points (a point pressed to too few depths?); press every point to at least "
                               f"{degree + (1 if zero_intercept else 2)} depths, or lower position_degree or degree")
    a, *_ = np.linalg.lstsq(A, f, rcond=None)
    n = phi.shape[1]
    for i, k in enumerate(range(first, degree + 1)):
        model.P[k] = a[i * n:(i + 1) * n] / s ** k
    model.set_depth_high(u_pos, v_pos, d)
    return model


def _monotonic_everywhere(coef: Sequence[float], lo: float, hi: float, pmodel: PositionModel | None) -> str | None:
    """:func:`_monotonic_problem` of the polynomial; with position terms, everywhere over the calibrated area up to
    each position's own depth limit: exactly (in depth) at every node of the depth-limit grid, then densely between
    them (:func:`_position_slope_problem`)."""
    if pmodel is None:
        return _monotonic_problem(coef, lo, hi)
    for u, v in pmodel.grid():
        problem = _monotonic_problem(pmodel.local(u, v), lo, pmodel.high(u, v))
        if problem is not None:
            return _at_position(pmodel, u, v, problem)
    return _position_slope_problem(pmodel, lo)


def _at_position(pmodel: PositionModel, u: float, v: float, problem: str) -> str:
    x = pmodel.center[0] + u * pmodel.half_extent[0]
    y = pmodel.center[1] + v * pmodel.half_extent[1]
    return f"at the contact position ({x * 1e3:.2f}, {y * 1e3:.2f}) mm: {problem}"


SLOPE_GRID = 65      # positions per axis of the dense monotonicity scan (the 9 x 9 depth-limit nodes are among them)
SLOPE_DEPTHS = 257   # depths per position in the scan, from the shallowest calibrated depth to the position's limit
SLOPE_REFINE = 8     # positions of lowest slope refined further (a dip narrower than the scan's spacing)


def _min_relative_slope(pmodel: PositionModel, lo: float, u: np.ndarray, v: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Per scaled position: the smallest dF/dd over [lo, limit] relative to the mean slope there (<= 1e-6: flat or
    falling), and the depth where it is."""
    coef = pmodel.local_many(u, v)                                     # (n, deg + 1)
    high = pmodel.high_many(u, v)                                      # (n,)
    d = lo + (high - lo)[:, None] * np.linspace(0.0, 1.0, SLOPE_DEPTHS)[None, :]
    slope = np.zeros_like(d)
    for k in range(coef.shape[1] - 1, 0, -1):                          # Horner on the derivative
        slope = slope * d + k * coef[:, k, None]
    f_hi, f_lo = np.zeros_like(high), np.zeros_like(high)
    for k in range(coef.shape[1] - 1, -1, -1):
        f_hi = f_hi * high + coef[:, k]
        f_lo = f_lo * lo + coef[:, k]
    mean = np.abs(f_hi - f_lo) / np.maximum(high - lo, 1e-300)
    rel = slope / np.maximum(mean, 1e-300)[:, None]
    i = np.argmin(rel, axis=1)
    rows = np.arange(len(u))
    return rel[rows, i], d[rows, i]


def _position_slope_problem(pmodel: PositionModel, lo: float) -> str | None:
    """Where F(d, x, y) is not strictly increasing in d between the depth-limit grid's nodes, or None.

    A 65 x 65 scan of the area (257 depths each), the lowest-slope positions refined on ever finer local grids, and
    at the worst position found the exact check in depth (roots of dF/dd)."""
    g = np.linspace(-1.0, 1.0, SLOPE_GRID)
    uu, vv = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    rel, _ = _min_relative_slope(pmodel, lo, uu, vv)
    candidates = [(float(uu[i]), float(vv[i])) for i in np.argsort(rel)[:SLOPE_REFINE]]
    offsets = np.linspace(-1.0, 1.0, 9)
    for u0, v0 in candidates:
        h = 2.0 / (SLOPE_GRID - 1)
        for _ in range(6):   # each round: a 9 x 9 grid over +-h around the lowest point so far, h shrinking 4x
            cu, cv = (a.ravel() for a in np.meshgrid(np.clip(u0 + h * offsets, -1, 1), np.clip(v0 + h * offsets, -1, 1),
                                                       indexing="ij"))
            r, _ = _min_relative_slope(pmodel, lo, cu, cv)
            k = int(np.argmin(r))
            u0, v0 = float(cu[k]), float(cv[k])
            h /= 4.0
        problem = _monotonic_problem(pmodel.local(u0, v0), lo, pmodel.high(u0, v0))
        if problem is not None:
            return _at_position(pmodel, u0, v0, problem)
    return None


def _curve_at(coef: Sequence[float], pmodel: "PositionModel | None", d: np.ndarray, pos: Any) -> np.ndarray:
    """The fitted curve as fitted (not clamped, not extrapolated) at depths ``d``; with position terms at each
    sample's centroid ``pos`` ((x, y) m per depth). What the fit's residuals and R^2 are computed from, when it is
    made and when a file's samples are checked against it."""
    if pmodel is None:
        return _polyval(list(coef), d)
    local = [pmodel.local(*pmodel.scaled(float(x), float(y))[:2]) for x, y in pos]
    return np.array([_polyval(c, np.array([di]))[0] for c, di in zip(local, d)])


#: how far below the file's own R^2 the curve may fit the samples the file holds (rounding, not an edit)
SAMPLES_R2_SLACK = 0.01


def _samples_problem(cal: "ForceCalibration") -> str | None:
    """Why the curve does not fit the samples its own file holds (None where it does, or where the file holds too
    few, or no R^2 to compare with): R^2 of the used samples with the loaded coefficients against the file's
    ``quality.r2``. The limits check compares only the curve's ends with the force range: a constant term moved by
    1.5 N (0 N, status ok, well into the contact) or every coefficient scaled (half the force) loaded, reporting the
    R^2 of the fit that was edited."""
    used = [s for s in cal.samples if s.get("used", True)]
    if len(used) < 3 or not math.isfinite(cal.r2):
        return None
    d = np.array([s["depth_m"] for s in used], dtype=float)
    f = np.array([s["force_n"] for s in used], dtype=float)
    pos = None
    if cal.position is not None:
        if not all(isinstance(s.get("x_m"), (int, float)) and isinstance(s.get("y_m"), (int, float)) for s in used):
            return None
        pos = [(s["x_m"], s["y_m"]) for s in used]
    pred = _curve_at(list(cal.coefficients), cal.position, d, pos)
    ss_tot = float(np.sum((f - f.mean()) ** 2))
    if not ss_tot > 0:
        return None
    r2 = 1.0 - float(np.sum((f - pred) ** 2)) / ss_tot
    if r2 >= cal.r2 - SAMPLES_R2_SLACK:
        return None
    worst = int(np.argmax(np.abs(f - pred)))
    return (f"the coefficients do not fit the file's own {len(used)} samples: R^2 {r2:.4f} with them, the file says "
            f"{cal.r2:.4f} (worst: {f[worst]:.3f} N recorded at {d[worst] * 1e3:.3f} mm, the curve gives "
            f"{pred[worst]:.3f} N); a hand-edited coefficient, or samples of another fit: refit the samples "
            f"(teletouch calibrate force --csv)")


def _limits_problem(cal: "ForceCalibration", monotonic: bool = True) -> tuple[str, str, Any, str] | None:
    """The first plausibility limit a calibration breaks, or None: (the file's field, what it should hold, what it
    holds, what that means for the data fitted). One check for both ends: :meth:`ForceCalibration.load` refuses such
    a file and :meth:`ForceCalibration.fit` such a fit, so every calibration the fit accepts loads from its file.
    ``monotonic``: check that the curve is strictly increasing too (the fit checks it first, in its own words)."""
    (lo, hi), (f_lo, f_hi) = cal.depth_range, cal.force_range
    if hi >= MAX_DEPTH_M:
        return ("model.depth_range_m", f"depths in m below {MAX_DEPTH_M:g} m ({MAX_DEPTH_M * 1e3:g} mm, deeper than a "
                f"gel: millimetres written as metres?)", [lo, hi], "are the depths in mm? give them in m")
    if abs(f_lo) >= MAX_FORCE_N or abs(f_hi) >= MAX_FORCE_N:
        return ("model.force_range_n", f"[low, high] in N with low <= high, below {MAX_FORCE_N:g} N", [f_lo, f_hi],
                "are the forces in mN? give them in N")
    pm = cal.position
    if pm is not None:
        for key, v in (("center_m", pm.center), ("half_extent_m", pm.half_extent)):
            if not all(abs(x) < MAX_CENTROID_M for x in v):
                return (f"model.position.{key}", f"[x, y] in m within {MAX_CENTROID_M:g} m of the image centre "
                        f"(millimetres written as metres?)", list(v), "are the contact centroids in mm? give them in m")
        h = pm.depth_high
        outside = ~((h > lo) & (h <= hi))
        if outside.any():
            i, j = np.argwhere(outside)[0]
            g = pm.GRID
            x = pm.center[0] + (-1.0 + 2.0 * i / (g - 1)) * pm.half_extent[0]
            y = pm.center[1] + (-1.0 + 2.0 * j / (g - 1)) * pm.half_extent[1]
            return ("model.position.depth_high_m", f"{g} lists of {g} depths in m inside the depth range "
                    f"({lo:.6g}, {hi:.6g}]", h.tolist(),
                    f"at the contact position ({x * 1e3:.2f}, {y * 1e3:.2f}) mm the calibrated depth limit is "
                    f"{h[i, j] * 1e3:.4f} mm: no sample is deeper than the shallowest ({lo * 1e3:.4f} mm) there or "
                    f"nearer it, so the curve there is not calibrated (press every point of the area to several "
                    f"depths)")
    problem = _monotonic_everywhere(cal.coefficients, lo, hi, pm) if monotonic else None   # up to the limits above
    if problem is not None:
        return ("model.coefficients", f"a strictly increasing polynomial on the depth range ({problem})",
                list(cal.coefficients), "the curve is not strictly increasing")
    # the curve starts where the recorded forces do: a hand-edited constant term gave a force step at contact onset
    # (4.5 N at 30 um) or a dead zone in contact (0 N down to 0.375 mm), both loading
    bottom = cal._f_lo   # (the curve at the shallowest calibrated depth, evaluated once when it was made)
    if not abs(bottom - f_lo) <= 0.25 * (f_hi - f_lo) + 0.1:
        return ("model.coefficients", f"a polynomial whose force at the shallowest calibrated depth is near the "
                f"recorded force range's bottom ({f_lo:.4g} N, model.force_range_n), but it gives {bottom:.4g} N",
                list(cal.coefficients),
                f"the curve's force at the shallowest depth ({bottom:.4g} N) is far from the smallest force recorded "
                f"({f_lo:.4g} N): an outlier, or forces that do not follow one curve of the depth; check the data")
    # coefficients in other units (N/mm^k, mN) give forces far from the ones the calibration recorded
    top = cal.largest_force("clamp")
    if not 0.5 * f_hi - 0.1 <= top <= 2.0 * f_hi + 0.1:
        return ("model.coefficients", f"a polynomial whose force at the deepest calibrated depth is near the "
                f"recorded force range's top ({f_hi:.4g} N, model.force_range_n), but it gives {top:.4g} N: "
                f"coefficients in other units than N/m^k?", list(cal.coefficients),
                f"the curve's force at the deepest depth ({top:.4g} N) is far from the largest force recorded "
                f"({f_hi:.4g} N): an outlier, or forces that do not follow one curve of the depth; check the data")
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
                 zero_intercept: bool = False, extra: dict[str, Any] | None = None,
                 position: PositionModel | None = None):
        self.position = position
        if position is not None:  # at the centre of the calibrated area only the constant position terms remain
            coefficients = position.P[:, 0]
            if position.depth_high is None:   # built by hand without per-position limits: the global one
                position.depth_high = np.full((position.GRID, position.GRID), float(depth_range[1]))
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
        # SOURCE_DATE_EPOCH, when set, is the time written (teletouch.reproducible: byte-identical files)
        self.created = created or _dt.datetime.fromtimestamp(int(build_time()), _dt.timezone.utc).isoformat()
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
            extra: dict[str, Any] | None = None, positions: Any = None,
            position_degree: int = 0, min_r2: float | None = None) -> "ForceCalibration":
        """Least-squares polynomial fit of force (N) on max depth (m).

        phases: optional per-sample "loading"/"unloading" labels. Loading and unloading are fitted apart too and
        the gap between the two curves (the gel's hysteresis) is reported in ``hysteresis``.
        use: which samples make the calibration: "all" (default), "loading" or "unloading".
        positions, position_degree: the contact centroid (x, y) in m of each sample and the degree of the position
        terms (0: none, the paper's model; see the module doc).
        min_r2: refuse a fit whose R^2 is below this (None: no limit; ``teletouch calibrate force`` uses
        :data:`DEFAULT_MIN_R2`).
        Raises :class:`CalibrationError` for too few/invalid samples or depth levels (:func:`depth_levels`), a fit
        that is not strictly increasing, or one below ``min_r2``.
        """
        d = np.asarray(list(depths_m), dtype=float).ravel()
        f = np.asarray(list(forces_n), dtype=float).ravel()
        if d.shape != f.shape:
            raise CalibrationError(f"{d.size} depths but {f.size} forces")
        if not isinstance(degree, (int, np.integer)) or not 1 <= degree <= MAX_DEGREE:
            raise CalibrationError(f"degree must be an integer from 1 to {MAX_DEGREE}, got {degree!r}")
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
            raise CalibrationError(f"sample {i}: depth {float(d[i])!r} m, force {float(f[i])!r} N is not finite")
        if (d < 0).any():
            i = int(np.argmax(d < 0))
            raise CalibrationError(f"sample {i}: depth {d[i]:.6g} m is negative (depth is positive into the gel)")
        if use not in ("all", "loading", "unloading"):
            raise CalibrationError(f"use must be 'all', 'loading' or 'unloading', got {use!r}")
        sel = np.ones(d.size, bool) if use == "all" else np.array([p == use for p in ph])
        dsel, fsel = d[sel], f[sel]
        if not isinstance(position_degree, (int, np.integer)) or not 0 <= position_degree <= MAX_POSITION_DEGREE:
            raise CalibrationError(f"position_degree must be an integer from 0 (none) to {MAX_POSITION_DEGREE}, got "
                                   f"{position_degree!r}")
        pos = None
        if position_degree:
            if positions is None:
                raise CalibrationError(f"position_degree {position_degree} needs the contact centroid (x, y) of "
                                       f"each sample")
            pos = np.asarray(positions, dtype=float)
            if pos.shape != (d.size, 2):
                raise CalibrationError(f"positions must be {d.size} (x, y) pairs in m, got shape {pos.shape}")
            badp = ~np.isfinite(pos).all(axis=1)
            if badp.any():
                i = int(np.argmax(badp))
                raise CalibrationError(f"sample {i}: contact centroid {pos[i].tolist()} m is not finite")
        nfree = degree + (0 if zero_intercept else 1)
        levels = depth_levels(dsel)
        if levels < nfree + 1:
            raise CalibrationError(f"{levels} distinct depth levels ({dsel.size} samples, {use}) for a degree-{degree} "
                                   f"fit: need at least {nfree + 1} (depths within "
                                   f"{DEPTH_LEVEL_TOLERANCE_M * 1e3:g} mm of each other count as one level: a stuck "
                                   f"probe or a repeated reading adds samples, not levels); press to more depths")
        lo, hi = float(dsel.min()), float(dsel.max())
        if hi <= 0 or hi - lo < 1e-7:
            raise CalibrationError(f"the depth range {lo * 1e3:.4f}..{hi * 1e3:.4f} mm is too small to calibrate")
        pmodel = None
        if pos is not None:
            pmodel = _fit_position(dsel, fsel, pos[sel], degree, int(position_degree), zero_intercept)
            coef = list(pmodel.P[:, 0])
        else:
            coef = _lstsq(dsel, fsel, degree, zero_intercept)
        problem = _monotonic_everywhere(coef, lo, hi, pmodel)
        if problem is not None:
            raise CalibrationError(f"the degree-{degree} fit is not monotonic inside the calibrated range: "
                                   f"{problem}; refusing it (use a lower degree, more samples or check the data)")
        pred_all = _curve_at(coef, pmodel, d, pos)
        res = fsel - pred_all[sel]
        ss_res = float(np.sum(res ** 2))
        ss_tot = float(np.sum((fsel - fsel.mean()) ** 2))
        r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else math.nan
        rmse = math.sqrt(ss_res / dsel.size)
        if min_r2 is not None and not r2 >= min_r2:   # NaN (all forces equal) is refused too
            frange = float(fsel.max() - fsel.min())
            raise CalibrationError(f"the degree-{degree} fit's R^2 is {r2:.4f}, below the minimum R^2 {min_r2:g} (RMSE "
                                   f"{rmse:.4f} N, {100 * rmse / frange if frange > 0 else math.nan:.1f}% of the force "
                                   f"range, {dsel.size} samples): the forces do not follow one curve of the depth "
                                   f"(noise, a drifting tare, presses at several points without position terms?); "
                                   f"refusing it: check the data, or lower the limit with --min-r2 (min_r2)")
        samples = [{"depth_m": float(d[i]), "force_n": float(f[i]), "predicted_n": float(pred_all[i]),
                    "residual_n": float(f[i] - pred_all[i]), "phase": ph[i], "cycle": cy[i], "used": bool(sel[i])}
                   for i in range(d.size)]
        if pos is not None:
            for smp, (x, y) in zip(samples, pos):
                smp["x_m"], smp["y_m"] = float(x), float(y)
        # with position terms the phases are compared at the same position: each sample's force is moved onto the
        # centre's curve by the model's own position dependence (f - F(d, x, y) + F(d, centre))
        f_h = f if pmodel is None else f - pred_all + _polyval(coef, d)
        hyst = _hysteresis(d, f_h, ph, degree, zero_intercept)
        frange = (float(fsel.min()), float(fsel.max()))
        cal = cls(coef, (lo, hi), frange, r2=r2, rmse=rmse, samples=samples, hysteresis=hyst,
                  sensor_model_id=sensor_model_id, depth_source=depth_source, source=source,
                  zero_intercept=zero_intercept, extra=dict(extra or {}, use=use), position=pmodel)
        # the file's checks (monotonicity: above): a fit its own file would not load is refused here
        limits = _limits_problem(cal, monotonic=False)
        if limits is not None:
            field, expected, got, means = limits
            got = repr(got) if len(repr(got)) <= 120 else repr(got)[:117] + "..."
            raise CalibrationError(f"the fitted calibration is implausible: {field}: expected {expected}, got {got}; "
                                   f"{means}; refusing it (its file would not load)")
        return cal

    # ---------------------------------------------------------------------------------------------------- predict
    def evaluate(self, max_depth_m: Any, out_of_range: str = "clamp",
                 position: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised map with the range guard. Returns (force N, code) with code 0 ok, 1 extrapolated, 2 clamped.

        Negative depths give 0 N (code 0); a non-finite one (NaN, inf) raises ValueError. ``position``: the contact
        centroid (x, y) in m, one pair or one per depth, for a calibration with position terms (None: the centre of
        its area). ``extrapolate`` continues the end slope up to :data:`MAX_DEPTH_M` (no gel is that deep) and holds
        the force there beyond it (code 2): the force is at most ``largest_force("extrapolate", MAX_DEPTH_M)``.
        """
        d = np.asarray(max_depth_m, dtype=float)
        bad = ~np.isfinite(d)
        if bad.any():
            _refuse_depth(float(d[bad].flat[0]))
        if out_of_range not in ("extrapolate", "clamp"):
            raise ValueError(f"out_of_range must be 'extrapolate' or 'clamp', got {out_of_range!r}")
        if self.position is not None:
            pos = np.broadcast_to(np.asarray((np.nan, np.nan) if position is None else position, dtype=float),
                                  d.shape + (2,))
            codes = {"ok": 0, "extrapolated": 1, "clamped": 2}
            out = [self._evaluate_scalar(float(di), out_of_range, None if np.isnan(p).any() else (float(p[0]),
                                                                                             float(p[1])))
                   for di, p in zip(d.ravel(), pos.reshape(-1, 2))]
            return (np.array([o[0] for o in out]).reshape(d.shape),
                    np.array([codes[o[1]] for o in out], dtype=np.int8).reshape(d.shape))
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
                end = max(MAX_DEPTH_M, hi)
                f[above] = self._f_hi + self._slope_hi * (np.minimum(d[above], end) - hi)
                code[above] = np.where(d[above] > end, 2, 1)
        f = np.maximum(f, 0.0)
        return f, code

    def predict(self, max_depth_m: Any, out_of_range: str = "clamp", position: Any = None) -> Any:
        """Force (N) for max depth (m): a float for a scalar, an array for an array. Never negative, never a cubic
        tail outside the calibrated range (see the module doc)."""
        f, _ = self.evaluate(max_depth_m, out_of_range, position)
        return float(f) if f.ndim == 0 else f

    def predict_with_status(self, max_depth_m: float, out_of_range: str = "clamp",
                            position: tuple[float, float] | None = None) -> tuple[float, str]:
        if isinstance(max_depth_m, float):  # a Python or numpy scalar: the same arithmetic without arrays
            return self._evaluate_scalar(float(max_depth_m), out_of_range, position)
        f, code = self.evaluate(max_depth_m, out_of_range, position)
        return float(f), ("ok", "extrapolated", "clamped")[int(code)]

    def _evaluate_scalar(self, d: float, out_of_range: str,
                         position: tuple[float, float] | None = None) -> tuple[float, str]:
        """:meth:`evaluate` for one float, operation for operation (60 Hz x a few us of numpy saved)."""
        if not math.isfinite(d):
            _refuse_depth(d)
        if out_of_range not in ("extrapolate", "clamp"):
            raise ValueError(f"out_of_range must be 'extrapolate' or 'clamp', got {out_of_range!r}")
        lo, hi = self.depth_range
        coef, f_lo, f_hi, slope_hi = self.coefficients, self._f_lo, self._f_hi, self._slope_hi
        status = "ok"
        if self.position is not None:
            u, v, outside = (0.0, 0.0, False) if position is None else self.position.scaled(position[0], position[1])
            if outside:
                status = "clamped"
            coef = self.position.local(u, v)
            hi = self.position.high(u, v)
            if d < lo:
                f_lo = _polyval(coef, np.array([lo]))[0]
            elif d > hi:
                f_hi = _polyval(coef, np.array([hi]))[0]
                slope_hi = _polyval(_polyder(coef), np.array([hi]))[0]
        if lo <= d <= hi:
            f = 0.0
            for c in reversed(coef):
                f = f * d + c
        elif 0 < d < lo:
            f = max(f_lo, 0.0) * d / lo
            status = "extrapolated"
        elif d > hi:
            if out_of_range == "clamp":
                f, status = f_hi, "clamped"
            else:
                end = max(MAX_DEPTH_M, hi)
                f = f_hi + slope_hi * (min(d, end) - hi)
                status = "extrapolated" if d <= end else "clamped"
        else:
            f = 0.0
        return float(max(f, 0.0)), status

    def largest_force(self, out_of_range: str = "clamp", depth_limit: float = 5e-3) -> float:
        """The largest force (N) :meth:`predict` gives for depths up to ``depth_limit`` (m), at any position: the
        force at the calibrated limit (clamp) or on the end slope at ``depth_limit`` (extrapolate; at most at
        :data:`MAX_DEPTH_M`, where it stops). With position terms the maximum over a 65 x 65 grid of the area
        (``poly-force`` caps its output there)."""
        if self.position is None:
            coef = np.array([self.coefficients])
            high = np.array([self.depth_range[1]])
        else:
            g = np.linspace(-1.0, 1.0, SLOPE_GRID)
            uu, vv = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
            coef, high = self.position.local_many(uu, vv), self.position.high_many(uu, vv)
        f, slope = np.zeros_like(high), np.zeros_like(high)
        for k in range(coef.shape[1] - 1, -1, -1):
            f = f * high + coef[:, k]
            if k:
                slope = slope * high + k * coef[:, k]
        if out_of_range == "extrapolate":
            f = f + slope * np.maximum(np.minimum(depth_limit, np.maximum(MAX_DEPTH_M, high)) - high, 0.0)
        return float(max(np.max(f), 0.0))

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
                "basis": BASIS,
                "units": UNITS,
                "degree": self.degree,
                "coefficients": list(self.coefficients),
                "zero_intercept": self.zero_intercept,
                "depth_range_m": list(self.depth_range),
                "force_range_n": list(self.force_range),
                **({"position": self.position.to_dict()} if self.position is not None else {}),
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
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, "is a directory, expected the calibration file to write", str(path))
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n", encoding="utf-8")
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        self.path = str(path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ForceCalibration":
        """Read a calibration file (or a packaged one by name, e.g. ``sim-digit-qvga``). Raises ModelFileError
        naming the file and the field for any problem."""
        path = resolve_calibration(str(path))
        cal = cls.from_dict(_read_document(path), str(path))
        cal.path = str(path)
        return cal

    @classmethod
    def from_dict(cls, doc: Any, where: str = "<calibration>") -> "ForceCalibration":
        def bad(field: str, expected: str, got: Any = ...) -> ModelFileError:
            tail = "" if got is ... else f", got {got!r}"[:200]
            return ModelFileError(f"{where}: field '{field}': expected {expected}{tail}")

        _check_header(doc, where)
        model = doc.get("model")
        if not isinstance(model, dict):
            raise bad("model", "an object")
        if model.get("basis", BASIS) != BASIS:   # another order or basis would give wrong forces, not an error
            raise bad("model.basis", f"{BASIS!r} (coefficients c_k of d^k, lowest power first) or absent",
                      model.get("basis"))
        deg = model.get("degree")
        if not isinstance(deg, int) or isinstance(deg, bool) or not 1 <= deg <= MAX_DEGREE:
            raise bad("model.degree", f"an integer from 1 to {MAX_DEGREE}", deg)
        coef = model.get("coefficients")
        if not isinstance(coef, list) or len(coef) != deg + 1 or not all(_finite(c) for c in coef):
            raise bad("model.coefficients", f"a list of {deg + 1} finite numbers (degree {deg})", coef)
        dr = model.get("depth_range_m")
        if (not isinstance(dr, list) or len(dr) != 2 or not all(_finite(x) for x in dr) or dr[0] < 0
                or dr[1] <= dr[0]):
            raise bad("model.depth_range_m", "[low, high] in m with 0 <= low < high", dr)
        fr = model.get("force_range_n")
        if not isinstance(fr, list) or len(fr) != 2 or not all(_finite(x) for x in fr) or fr[1] < fr[0]:
            raise bad("model.force_range_n", f"[low, high] in N with low <= high, below {MAX_FORCE_N:g} N", fr)
        pmodel = None
        if model.get("position") is not None:
            pmodel = PositionModel.from_dict(model["position"], deg, bad)
            if not np.allclose(pmodel.P[:, 0], coef, rtol=1e-9, atol=0.0):
                raise bad("model.coefficients", "the constant position terms (model.position.coefficients[k][0]: "
                          "the polynomial at the centre of the calibrated area)", coef)
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
        for key in ("max_gap_n", "mean_gap_n", "max_gap_pct_of_force_range", "max_gap_at_depth_m"):
            if hyst and hyst.get(key) is not None and not _finite(hyst[key]):
                raise bad(f"hysteresis.{key}", "a finite number or null", hyst[key])
        extra = doc.get("extra")
        if extra is not None and not isinstance(extra, dict):
            raise bad("extra", "an object or null", extra)
        zi = model.get("zero_intercept", False)
        if not isinstance(zi, bool):
            raise bad("model.zero_intercept", "true or false", zi)
        units = model.get("units")
        if units is not None and units != UNITS:
            raise bad("model.units", f"{UNITS!r} (teletouch reads SI coefficients only: refit the pairs in m and N)",
                      units)
        cal = cls(coef, (dr[0], dr[1]), (fr[0], fr[1]), r2=_float_or_nan(q.get("r2")),
                  rmse=_float_or_nan(q.get("rmse_n")), samples=samples, hysteresis=hyst,
                  sensor_model_id=doc.get("sensor_model_id") or "", depth_source=doc.get("depth_source") or "",
                  source=doc.get("source") or "", created=doc.get("created"),
                  zero_intercept=zi, extra=extra or {},
                  position=pmodel)
        limits = _limits_problem(cal)   # the limits a fit is held to too
        if limits is not None:
            raise bad(*limits[:3])
        mismatch = _samples_problem(cal)
        if mismatch is not None:
            raise ModelFileError(f"{where}: field 'model.coefficients': {mismatch}")
        return cal

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
        lines.append(f"  F(d) = sum c_k d^k, c = [{coef}] (N, m)"
                     + (" at the centre of the calibrated area" if self.position is not None else ""))
        pm = self.position
        if pm is not None:
            (x0, y0), (hx, hy) = pm.center, pm.half_extent
            lines.append(f"  position terms: degree {pm.degree} ({len(pm.exponents)} per power of d) over x "
                         f"{(x0 - hx) * 1e3:.2f}..{(x0 + hx) * 1e3:.2f} mm, y {(y0 - hy) * 1e3:.2f}.."
                         f"{(y0 + hy) * 1e3:.2f} mm (contact centroid); depth limit "
                         f"{pm.depth_high.min() * 1e3:.3f}..{pm.depth_high.max() * 1e3:.3f} mm over the area")
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
                r = np.array([s["force_n"] - self.predict(s["depth_m"], position=(s["x_m"], s["y_m"])
                                                          if "x_m" in s else None) for s in pts])
                ax.scatter(x, y, s=14, c=color, marker=marker, alpha=0.7, label=label)
                axr.scatter(x, r, s=10, c=color, marker=marker, alpha=0.7)
            pm = self.position
            xs = np.linspace(lo, hi if pm is None else pm.high(0.0, 0.0), 300)
            ax.plot(xs * 1e3, _polyval(self.coefficients, xs), "k-", lw=1.6,
                    label=f"degree-{self.degree} fit, $R^2$ = {self.r2:.5f}"
                    + (f"\n(at the centre; position terms of degree {pm.degree})" if pm is not None else ""))
            if pm is not None:
                for i, (u, v) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
                    xl = np.linspace(lo, pm.high(u, v), 200)
                    ax.plot(xl * 1e3, _polyval(pm.local(u, v), xl), "-", color="0.6", lw=0.9,
                            label="at the corners of the calibrated area" if i == 0 else None)
            h = self.hysteresis or {}
            for ph, color in (("loading", "tab:blue"), ("unloading", "tab:orange")):
                sub = h.get(ph)
                if isinstance(sub, dict) and sub.get("coefficients"):
                    a, b = sub["depth_range_m"]
                    if pm is not None:   # the phases were compared as if at the centre: drawn over its range
                        b = min(b, pm.high(0.0, 0.0))
                    xx = np.linspace(a, b, 200)
                    ax.plot(xx * 1e3, _polyval(sub["coefficients"], xx), "--", color=color, lw=1,
                            label=f"{ph} fit" + (" (at the centre)" if pm is not None else ""))
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
        # the degree each phase's depth levels allow (near-duplicate depths are one level, as for the main fit)
        deg = min(degree, max(1, depth_levels(d[m]) - 2)) if n else 0
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


def _refuse_depth(d: float) -> None:
    """A non-finite max depth has no force: raise ValueError (an inf is no more a depth than a NaN)."""
    raise ValueError(f"max depth is {'NaN' if d != d else d}; a force cannot be computed from it")


def _model_name(name: str) -> str:
    """A depth model's name as a calibration records it: the file name without folders and '.model'."""
    n = Path(str(name).strip()).name
    return n[: -len(".model")] if n.endswith(".model") else n


def _finite(x: Any) -> bool:
    try:
        return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
    except OverflowError:   # an integer too large for a float (e.g. 400 digits in a JSON file)
        return False


def _float_or_nan(x: Any) -> float:
    return float(x) if _finite(x) else math.nan


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# ------------------------------------------------------------------------------------------------ CSV of pairs
DEPTH_COLUMNS = {"depth_m": 1.0, "max_depth_m": 1.0, "depth": 1.0, "max_depth": 1.0, "depth_mm": 1e-3,
                 "max_depth_mm": 1e-3}
FORCE_COLUMNS = {"force_n": 1.0, "force": 1.0, "device_force_n": 1.0}
# plausibility limits of a tactile gel's pairs: beyond them a column is almost surely in the wrong unit
MAX_DEPTH_M = 0.01        # 10 mm of indentation
MAX_FORCE_N = 200.0       # N
MAX_CENTROID_M = 0.1      # 100 mm from the image centre
PARTIAL_MARK = "# partial:"   # first line of a samples CSV from a press run that did not finish
MODEL_MARK = "# sensor_model_id:"   # the depth model a samples CSV's depths came from
CSV_COLUMNS = ["depth_m", "force_n", "phase", "cycle", "displacement_m", "gt_max_depth_m", "gt_force_n", "x_m", "y_m"]
#: the other columns a pairs CSV may have: read (phase, cycle, the centroid), or written by the press routine for a look
#: and ignored when read (the displacement, the simulation's ground truth), or a free-text note; any other is refused
OTHER_COLUMNS = ("phase", "cycle", "x_m", "y_m", "displacement_m", "gt_max_depth_m", "gt_force_n", "note")


class PairsFileError(CalibrationError):
    """A pairs CSV that cannot be opened at all (missing, a folder, no permission): the path given is wrong, a usage
    error for the command, not a refused file."""


def read_pairs_csv(path: str | os.PathLike) -> dict[str, Any]:
    """Read (depth, force) pairs. Header required: exactly one depth column (DEPTH_COLUMNS: depth_m, depth_mm, ...)
    and exactly one force column (FORCE_COLUMNS, N); optional phase (loading/unloading), cycle, x_m, y_m (the contact
    centroid, m; both or neither), and columns read back but ignored (displacement_m, gt_max_depth_m, gt_force_n: the
    press routine's, and note). A column named twice or an unknown one is refused (did you mean ...?), and so is a
    number with an underscore ('1_2'). A file that cannot be opened raises PairsFileError (a CalibrationError).
    Lines starting with ``#`` are comments (skipped before the CSV is parsed, so a quote in a comment cannot join
    the rows after it); errors name the file's line (a quoted cell may span lines: the row's first line).
    Returns {"depth_m": array, "force_n": array, "phase": list | None, "cycle": list | None, "x_m": array | None,
    "y_m": array | None, "line": each row's line in the file, "force_column": the force column's name, "partial": why
    the samples are incomplete (a ``# partial: why`` line) or None}."""
    path = Path(path)
    try:
        fh = path.open(newline="", encoding="utf-8-sig")   # -sig: a spreadsheet's byte order mark is no header
    except OSError as exc:
        raise PairsFileError(f"{path}: cannot read the CSV file: {exc.strerror or exc} (expected a CSV file of "
                             f"depth, force pairs)") from None
    with fh:
        try:
            text = list(fh)   # newline="": lines split on any line end, left as they are (the csv module's way)
        except UnicodeDecodeError as exc:
            raise CalibrationError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x}: {exc.reason}): "
                                   f"expected a CSV file of depth, force pairs (save it as UTF-8 CSV)") from None
    comment = [t.lstrip().startswith("#") for t in text]
    def marked(mark: str) -> str | None:   # the text after the first comment line that starts with ``mark``
        return next((t.strip().split(":", 1)[1].strip() for t, c in zip(text, comment)
                     if c and t.lstrip().startswith(mark)), None)

    partial = marked(PARTIAL_MARK)
    partial = (partial or "no reason given") if partial is not None else None
    model_id = marked(MODEL_MARK) or ""
    first = [0]   # the line the row being parsed starts on

    def source() -> Iterable[str]:
        for n, t in enumerate(text, 1):
            if not comment[n - 1]:
                first[0] = first[0] or n
                yield t

    lines: list[tuple[int, list[str]]] = []
    try:
        for r in csv.reader(source()):
            if r and any(c.strip() for c in r):
                lines.append((first[0], r))
            first[0] = 0
    except csv.Error as exc:
        raise CalibrationError(f"{path}:{first[0]}: not a readable CSV file ({exc})") from None
    if not lines:
        raise CalibrationError(f"{path}: empty CSV file (expected a header such as 'depth_m,force_n')")
    hline, header = lines[0]
    names = [h.strip().lower() for h in header]
    dcol, fcol = _pairs_header(path, hline, header, names)
    dscale = DEPTH_COLUMNS[names[dcol]]
    pcol = names.index("phase") if "phase" in names else None
    ccol = names.index("cycle") if "cycle" in names else None
    xcol = names.index("x_m") if "x_m" in names else None
    ycol = names.index("y_m") if "y_m" in names else None
    if (xcol is None) != (ycol is None):
        raise CalibrationError(f"{path}:{hline}: header has {'x_m' if ycol is None else 'y_m'} without "
                               f"{'y_m' if ycol is None else 'x_m'}: the contact centroid needs both columns")
    unnamed = [i for i, n in enumerate(names) if not n]   # a trailing separator: only empty cells below it
    depth, force, phase, cycle, xs, ys, where = [], [], [], [], [], [], []
    for ln, r in lines[1:]:
        where.append(ln)
        if len(r) > len(header) and any(c.strip() for c in r[len(header):]):
            raise CalibrationError(f"{path}:{ln}: {len(r)} cells but the header (line {hline}) names "
                                   f"{len(header)} columns: a missing header name or a stray separator?")
        lost = next((i for i in unnamed if i < len(r) and r[i].strip()), None)
        if lost is not None:
            raise CalibrationError(f"{path}:{ln}: {r[lost].strip()!r} in column {lost + 1}, which the header (line "
                                   f"{hline}) leaves without a name: a missing header name or a stray separator?")

        def cell(i: int | None, what: str) -> str:
            if i is None:
                return ""
            if i >= len(r):
                raise CalibrationError(f"{path}:{ln}: missing column '{names[i]}' ({what})")
            return r[i].strip()

        cols = [(dcol, depth, dscale, "depth"), (fcol, force, 1.0, "force (N)")]
        if xcol is not None:
            cols += [(xcol, xs, 1.0, "centroid x (m)"), (ycol, ys, 1.0, "centroid y (m)")]
        for col, sink, scale, what in cols:
            txt = cell(col, what)
            if col in (xcol, ycol) and not txt:   # an empty centroid (e.g. a no-contact sample)
                sink.append(None)
                continue
            if "_" in txt:   # float() reads '1_2' as 12
                raise CalibrationError(f"{path}:{ln}: column '{names[col]}': expected a number ({what}), got {txt!r} "
                                       f"({UNDERSCORE})")
            try:
                v = float(txt) * scale
            except ValueError:
                raise CalibrationError(f"{path}:{ln}: column '{names[col]}': expected a number ({what}), "
                                       f"got {txt!r}") from None
            if not math.isfinite(v):
                raise CalibrationError(f"{path}:{ln}: column '{names[col]}': {txt!r} is not finite")
            problem = _implausible(names[col], v, col == dcol, col == fcol)
            if problem:
                raise CalibrationError(f"{path}:{ln}: column '{names[col]}': {txt!r} {problem}")
            sink.append(v)
        p = cell(pcol, "phase").lower()
        if p not in PHASES:
            raise CalibrationError(f"{path}:{ln}: column 'phase': expected loading or unloading, got {p!r}")
        phase.append(p)
        c = cell(ccol, "cycle")
        if "_" in c:   # int() reads '1_0' as 10
            raise CalibrationError(f"{path}:{ln}: column 'cycle': expected an integer, got {c!r} ({UNDERSCORE})")
        try:
            cycle.append(int(c) if c else 0)
        except ValueError:
            raise CalibrationError(f"{path}:{ln}: column 'cycle': expected an integer, got {c!r}") from None
    if not depth:
        raise CalibrationError(f"{path}: no data rows after the header")
    return {"depth_m": np.array(depth), "force_n": np.array(force),
            "phase": phase if pcol is not None else None, "cycle": cycle if ccol is not None else None,
            "x_m": xs if xcol is not None else None, "y_m": ys if ycol is not None else None, "line": where,
            "force_column": names[fcol], "partial": partial, "sensor_model_id": model_id}


def _pairs_header(path: Path, hline: int, header: list[str], names: list[str]) -> tuple[int, int]:
    """The depth and the force column of a pairs CSV's header (``names``: lower case, stripped). Refused, naming the
    file and line: a column named twice, a header without exactly one depth and one force column (of two, which one
    was meant cannot be told: the first was taken), and an unknown column (a typo of ``phase`` lost the phases)."""
    dup = next((n for i, n in enumerate(names) if n and n in names[:i]), None)
    if dup is not None:
        at = [str(i + 1) for i, n in enumerate(names) if n == dup]
        raise CalibrationError(f"{path}:{hline}: the column {dup} is named twice (columns {' and '.join(at)}): keep "
                               f"one")
    found = []
    for kind, columns in (("depth", DEPTH_COLUMNS), ("force", FORCE_COLUMNS)):
        cols = [i for i, n in enumerate(names) if n in columns]
        if len(cols) > 1:
            both = ", ".join(f"'{names[i]}'" for i in cols[:-1]) + f" and '{names[cols[-1]]}'"
            raise CalibrationError(f"{path}:{hline}: {len(cols)} {kind} columns, {both}: expected exactly one (which "
                                   f"one is meant cannot be told); keep one")
        found.append(cols[0] if cols else None)
    known = [*DEPTH_COLUMNS, *FORCE_COLUMNS, *OTHER_COLUMNS]
    unknown = [n for n in names if n and n not in known]
    if unknown:
        from teletouch.graph import _suggest   # the graph's "did you mean" for unknown keys

        unknown_said = (f"unknown column{'s' if len(unknown) > 1 else ''} "
                        + ", ".join(f"'{n}'{_suggest(n, known)}" for n in unknown))
    if None in found:
        raise CalibrationError(f"{path}:{hline}: header {header!r} needs a depth column ({', '.join(DEPTH_COLUMNS)}) "
                               f"and a force column ({', '.join(FORCE_COLUMNS)})"
                               + (f"; {unknown_said}" if unknown else ""))
    if unknown:
        raise CalibrationError(f"{path}:{hline}: {unknown_said}; expected a depth column, a force column and "
                               f"optionally {', '.join(OTHER_COLUMNS)}")
    return found[0], found[1]


def _implausible(name: str, v: float, is_depth: bool, is_force: bool) -> str | None:
    """Why a value (SI) of a CSV column is implausible for a tactile gel (a unit mistake), or None."""
    if is_depth and abs(v) >= MAX_DEPTH_M:
        hint = ("check the unit" if name.endswith("_mm")
                else f"is the column in mm? then name it {name.removesuffix('_m')}_mm")
        return (f"is a depth of {v * 1e3:g} mm, implausible for a gel (expected below {MAX_DEPTH_M * 1e3:g} mm): "
                f"{hint}")
    if is_force and abs(v) >= MAX_FORCE_N:
        return (f"is a force of {v:g} N, implausible for a tactile sensor (expected below {MAX_FORCE_N:g} N): is "
                f"the column in mN? convert it to N")
    if not (is_depth or is_force) and abs(v) >= MAX_CENTROID_M:
        return (f"is a contact centroid {v * 1e3:g} mm from the image centre, implausible (expected within "
                f"{MAX_CENTROID_M * 1e3:g} mm): is the column in mm? convert it to m")
    return None


def write_pairs_csv(path: str | os.PathLike, rows: Iterable[dict[str, Any]], partial: str | None = None,
                    sensor_model_id: str = "") -> Path:
    """Write samples (dicts with keys from CSV_COLUMNS; missing ones left empty) as a CSV read_pairs_csv reads.
    ``partial``: why the samples are incomplete (a press run that did not finish): written as a first comment line
    ``# partial: <why>`` that read_pairs_csv reports and ``teletouch calibrate force --csv`` refuses.
    ``sensor_model_id``: the depth model the depths came from, as a comment line ``# sensor_model_id: <id>``, which
    a refit with ``--csv`` takes as its default (the refit's file was tied to no model, and `estimate` refused it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as fh:
        if partial is not None:
            fh.write(f"{PARTIAL_MARK} {' '.join(str(partial).split()) or 'no reason given'}\n")
        if sensor_model_id and "\n" not in sensor_model_id and "\r" not in sensor_model_id:
            fh.write(f"{MODEL_MARK} {sensor_model_id}\n")
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            w.writerow(["" if r.get(k) is None else (f"{r[k]:.9g}" if isinstance(r[k], float) else r[k])
                        for k in CSV_COLUMNS])
    return path


# ------------------------------------------------------------------------------------------------ reading files
#: what a file given as a force calibration must be
EXPECTED_FILE = "expected the JSON written by `teletouch calibrate force`"


def _read_document(path: Path) -> Any:
    """The JSON document of the calibration file ``path``; ModelFileError naming the file when it cannot be read or
    is no JSON text (a depth model, a CSV or an image given as the calibration)."""
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ModelFileError(f"{path}: force calibration file not found") from None
    except UnicodeDecodeError:   # a binary file (a depth model is a zip archive)
        raise ModelFileError(f"{path}: not a force calibration ({EXPECTED_FILE})") from None
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the force calibration file: {exc.strerror or exc}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        if not text.lstrip().startswith(("{", "[")):   # no JSON at all
            raise ModelFileError(f"{path}: not a force calibration ({EXPECTED_FILE})") from None
        raise ModelFileError(f"{path}: not a force calibration file (corrupt JSON at line {exc.lineno}, "
                             f"column {exc.colno}: {exc.msg})") from None


def _check_header(doc: Any, where: str) -> None:
    """ModelFileError unless ``doc`` is a JSON object of this format and version."""
    if not isinstance(doc, dict):
        raise ModelFileError(f"{where}: not a force calibration ({EXPECTED_FILE}: an object; this JSON is a "
                             f"{type(doc).__name__})")
    if doc.get("format") != FORMAT:
        raise ModelFileError(f"{where}: field 'format': expected '{FORMAT}' (is this a force calibration file?), "
                             f"got {repr(doc.get('format'))[:200]}")
    ver = doc.get("version")
    if ver != VERSION or not isinstance(ver, int) or isinstance(ver, bool):   # `true` == 1 in Python
        raise ModelFileError(f"{where}: field 'version': file version {ver!r}, this teletouch reads version "
                             f"{VERSION}; recalibrate with `teletouch calibrate force` or update teletouch")


def check_calibration_file(spec: str) -> dict[str, Any]:
    """The document of the calibration ``spec`` (a file or a packaged name) if it is a force calibration of this
    format and version, else ModelFileError naming the file and what was expected: the cheap check a graph's
    validation makes (no curve, no limits: :meth:`ForceCalibration.load` checks every field at start-up)."""
    path = resolve_calibration(spec)
    doc = _read_document(path)
    _check_header(doc, str(path))
    return doc


# ------------------------------------------------------------------------------------------------ finding files
def packaged_calibrations() -> list[str]:
    """Names of the calibrations shipped with teletouch (data/<name>.force.json)."""
    if not DATA_DIR.is_dir():
        return []
    return sorted(p.name[: -len(SUFFIX)] for p in DATA_DIR.glob("*" + SUFFIX))


def resolve_calibration(name_or_path: str) -> Path:
    """A path to an existing file, or the name of a packaged calibration (e.g. 'sim-digit-qvga'), else ModelFileError
    (:func:`teletouch.paths.input_file`)."""
    def packaged(s: str) -> Path | None:
        q = DATA_DIR / (s + SUFFIX)
        return q if q.is_file() else None

    return input_file(name_or_path, "force calibration", SUFFIX, "`teletouch calibrate force`", packaged,
                      packaged_calibrations())


# ------------------------------------------------------------------------------------------------ the component
def _deepest(doc: dict[str, Any]) -> float | None:
    """The deepest calibrated depth (m) a calibration's document records, or None where it holds none that is valid
    (loading the file at start-up says what is wrong with it)."""
    model = doc.get("model")
    dr = model.get("depth_range_m") if isinstance(model, dict) else None
    return float(dr[1]) if isinstance(dr, list) and len(dr) == 2 and _finite(dr[1]) else None


#: the depth estimator whose max depth a calibration's ``depth_source`` names (``"NODE.PORT (depth)"``): its model is
#: what the calibration was made for (PolyForce.port_sources)
DEPTH_PLUGIN = "depth"

#: what poly-force's ``depth_model`` must name
EXPECTED_DEPTH_MODEL = ("depth_model must name the depth node's `model`: an existing depth model file or a packaged "
                        "model's name")


def _depth_model_problem(spec: str | None) -> str | None:
    """Why ``depth_model`` names no depth model (no such file, a folder, an unreadable file, no depth model: read from
    its header), or None (also when it is not given). Checked before its name is compared with the calibration's
    record, so that a typo in the path does not read as a calibration made for another model, nor a missing file of
    the recorded name as the model it was made for."""
    if spec is None:
        return None
    from .normal_model import check_model_file

    try:
        check_model_file(spec)
    except ModelFileError as exc:
        return f"{exc}; {EXPECTED_DEPTH_MODEL}"
    return None


def _use_problem(p: Any, path: str, deepest: float | None, made_for_id: Any) -> str | None:
    """Why poly-force's params ``p`` cannot use the calibration ``path`` (its deepest depth, m, and the depth model it
    was made for), or None: a depth_limit inside the calibrated depths, a depth_model it was not made for. The same
    words when a graph is validated and at start-up."""
    if deepest is not None and p.depth_limit <= deepest:
        return (f"depth_limit ({p.depth_limit * 1e3:.3f} mm) must be deeper than the calibration's deepest depth "
                f"({deepest * 1e3:.3f} mm, {path}): calibrated depths would be invalid input")
    made_for_id = made_for_id if isinstance(made_for_id, str) else ""
    if p.depth_model is not None and _model_name(p.depth_model) != _model_name(made_for_id):
        made_for = repr(made_for_id) if made_for_id else "an unnamed depth model"   # (not quoted as if a name)
        return (f"depth_model: the calibration {path} was made for {made_for}, not for {p.depth_model!r}: "
                f"calibrate the force with this depth model (`teletouch calibrate force --set depth.model=...`) or "
                f"give --sensor-model-id when fitting a CSV")
    return None


STATUS_VALUES = ("ok", "no-contact", "clamped", "extrapolated", "invalid-input", "no-centroid")
#: the inputs taken with a depth sample, each the one of the depth's frame (its stamp) where it can be found
CONTACT_INPUTS = ("contact_area", "contact_mask", "centroid")
#: samples of each contact input kept to find a depth frame's (at 60 Hz: 0.13 s)
RECENT_CONTACT_SAMPLES = 8


def _stamp_of(smp: Any) -> float:
    """A sample's stamp as a float; NaN for one that is no number."""
    try:
        return float(smp.stamp)
    except (TypeError, ValueError):
        return math.nan


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
        "centroid": Port("float64", (2,), "m", "contact centroid (x, y) from the image centre (depth.centroid); "
                         "needed by a calibration with position terms", required=False),
    }
    outputs = {
        "force": Port("float64", (), "N", "normal force (>= 0, exactly 0 without contact); stamp of the depth"),
        "status": Port("str", (), "", "ok | no-contact | clamped (depth beyond the calibrated range, or the "
                       "centroid outside the calibrated area) | extrapolated | invalid-input | no-centroid (a light "
                       "touch without a centroid: the force at the fallback position, see centroid_band)"),
    }

    class Params(Params):
        calibration: str = Field("sim-digit-qvga", description="force calibration file, or the name of a "
                                 "packaged one (sim-digit-qvga)")
        out_of_range: Literal["extrapolate", "clamp"] = Field(
            "clamp", description="beyond the calibrated depth: hold the end force (default; safer and, measured on "
            "held-out sim presses, more accurate) or continue on the end slope")
        contact_threshold: Meters = Field(3e-5, ge=0, description="max depth below this is no contact (0 N)",
                                          json_schema_extra={"unit": "m"})
        min_contact_area: float = Field(0.0, ge=0, description="contact area at or below this is no contact (when "
                                        "contact_area is wired), within centroid_band of contact_threshold; deeper "
                                        "it is invalid input (pressed in without an area)",
                                        json_schema_extra={"unit": "m^2"})
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
        fault_after_invalid: int = Field(30, ge=0, description="fault the node after this many invalid inputs in "
                                         "a row (0 = never; no force sample while invalid, so the consumer sees "
                                         "its estimate go stale; at 60 Hz, 30 is half a second, as the depth "
                                         "node's fault_after_bad): a lasting invalid input must stop the run")
        depth_model: str | None = Field(None, description="the depth estimator's model (its 'model' parameter): "
                                        "when given, the calibration must have been made with it (its "
                                        "sensor_model_id); a calibration is per sensor and per depth model")
        depth_limit: Meters = Field(5e-3, gt=0, description="a max depth above this is invalid input (0 N): deeper "
                                    "than a DIGIT's gel is thick (4-5 mm), an estimator or unit fault (mm sent as "
                                    "m?); also bounds the extrapolated force", json_schema_extra={"unit": "m"})
        centroid_band: Meters = Field(2e-5, ge=0, description="with position terms, a NaN centroid while the "
                                      "max depth is at most this above contact_threshold is a light touch that the "
                                      "depth node's full-size contact mask misses (its max depth is the work grid's, "
                                      "a little deeper): the force is taken at the contact's last centroid, else at "
                                      "the centre of the calibrated area (status no-centroid); deeper, a NaN centroid "
                                      "is invalid input; 0: always invalid", json_schema_extra={"unit": "m"})
        max_clock_skew: Seconds = Field(0.05, ge=0, description="a depth stamped further ahead of the graph clock "
                                        "is invalid (a clock fault): no output, counted as invalid",
                                        json_schema_extra={"unit": "s"})

        @field_validator("calibration")
        @classmethod
        def _calibration_file(cls, v: str) -> str:
            """The file's header when the graph is validated (missing, no calibration, another format or version):
            before, `teletouch validate` said OK and the run failed at start-up."""
            try:
                check_calibration_file(v)
            except ModelFileError as exc:
                raise ValueError(str(exc)) from None
            return v

        @field_validator("contact_threshold", "negative_tolerance", "centroid_band")
        @classmethod
        def _gel_depth(cls, v: float, info: Any) -> float:
            return plausible_depth(info.field_name, v)   # 0.03 meant 0.03 mm: no gel is 30 mm thick

        @field_validator("depth_limit")
        @classmethod
        def _depth_limit(cls, v: float, info: Any) -> float:
            # beyond the gel is allowed (a test rig, a calibration of a thicker gel), not 5 m: that is 5 mm
            return plausible_depth(info.field_name, v, MAX_PLAUSIBLE_DEPTH_LIMIT)

        @field_validator("min_contact_area")
        @classmethod
        def _contact_area(cls, v: float, info: Any) -> float:
            return plausible_contact_area(info.field_name, v)   # 4 meant 4 mm^2: no DIGIT senses over 4 m^2

        @field_validator("depth_model")
        @classmethod
        def _depth_model_file(cls, v: str | None) -> str | None:
            problem = _depth_model_problem(v)
            if problem:
                raise ValueError(problem)
            return v

        @model_validator(mode="after")
        def _fits_the_calibration(self) -> "PolyForce.Params":
            """What configure refuses of the calibration's use (depth_limit, depth_model), read from its file."""
            doc = check_calibration_file(self.calibration)
            problem = _use_problem(self, str(resolve_calibration(self.calibration)), _deepest(doc),
                                   doc.get("sensor_model_id"))
            if problem:
                raise ValueError(problem)
            return self

    @classmethod
    def port_sources(cls, params: Any) -> dict[str, tuple]:
        """The max depth the calibration takes is the depth model's it was made for (its ``sensor_model_id``, by
        name: folders and '.model' left out, as the depth node gives its own): a depth node of another model wired
        to ``max_depth`` is refused when the graph is validated, whether or not ``depth_model`` is set. Only where the
        calibration's depth came from a `depth` node (its ``depth_source`` says so, as `teletouch calibrate force`
        records it): one whose press routine read another node (a filter in between: then it records the sensor), a
        CSV fitted with any --sensor-model-id, an old file without the record, tie nothing (``depth_model`` still
        checks them)."""
        path = resolve_calibration(params.calibration)
        doc = check_calibration_file(str(path))
        made_for, source = doc.get("sensor_model_id"), doc.get("depth_source")
        if not (isinstance(source, str) and source.endswith(f"({DEPTH_PLUGIN})")):
            return {}
        identity = _model_name(made_for) if isinstance(made_for, str) else ""
        if not identity:
            return {}
        how = ("calibrate the force with this depth model (`teletouch calibrate force --set depth.model=...`) or set "
               "calibration to one made for it")
        return {"max_depth": (identity, f"calibration {path}, made for depth model {made_for!r}", how)}

    def configure(self) -> None:
        p = self.params
        self.cal = ForceCalibration.load(resolve_calibration(p.calibration))
        problem = (_depth_model_problem(p.depth_model)   # (the file may have gone since the graph was validated)
                   or _use_problem(p, self.cal.path, self.cal.depth_range[1], self.cal.sensor_model_id))
        if problem:
            raise ValueError(problem)
        made_for = self.cal.sensor_model_id or "an unnamed depth model"
        self.ctx.log(f"force calibration {self.cal.path} (depth model {made_for}, depth "
                     f"{self.cal.depth_range[0] * 1e3:.3f}..{self.cal.depth_range[1] * 1e3:.3f} mm)")
        self.force_limit = self.cal.largest_force(p.out_of_range, p.depth_limit)
        if p.max_force is not None:
            self.force_limit = min(self.force_limit, float(p.max_force))
        self._reset()
        self.counts = {s: 0 for s in STATUS_VALUES}
        self.skipped = {"out_of_order": 0, "bad_stamp": 0}
        self.centroid_fallbacks = 0   # light touches evaluated at the fallback position (status no-centroid)
        self.unmatched_inputs = 0     # contact_area / contact_mask / centroid samples not of the depth's frame
        self._unmatched_said: set[str] = set()
        self.last_force = 0.0
        self.last_status = "no-contact"
        self.invalid_run = 0

    def _reset(self) -> None:
        self._window: deque[float] = deque(maxlen=self.params.median_window)
        self._filt: float | None = None
        self._filt_t: float | None = None
        self._last_stamp: float | None = None
        self._seen: Any = None
        self._last_pos: tuple[float, float] | None = None
        # the last samples of each contact input, to find the one of a depth frame that came before its depth
        self._recent: dict[str, deque[Any]] = {n: deque(maxlen=RECENT_CONTACT_SAMPLES) for n in CONTACT_INPUTS}

    def activate(self) -> None:
        self._reset()
        self.invalid_run = 0   # "in a row" starts over: a reactivated node may not fault on its first bad input

    def _invalid(self, why: str) -> None:
        """Count an invalid input; fault after fault_after_invalid in a row."""
        self.invalid_run += 1
        n = self.params.fault_after_invalid
        if n and self.invalid_run >= n:
            raise ComponentFault(f"{self.invalid_run} invalid max-depth inputs in a row (last: {why})", self.id)

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        self._remember(inputs)
        s = inputs["max_depth"]
        if s is None or s is self._seen:
            return None
        self._seen = s
        # the force carries the depth's stamp: a sample without a usable one gives no force (the consumer's
        # staleness check takes over), and only newer samples are taken, so an old frame arriving late cannot
        # enter the median or the low-pass, nor bring back an older force; a stamp ahead of the clock is refused
        # rather than taken, so it cannot lock out the frames after it
        st = _stamp_of(s)
        if not math.isfinite(st) or st > t + self.params.max_clock_skew:
            self.skipped["bad_stamp"] += 1
            self._reset_filters()
            self._invalid(f"stamp {s.stamp!r}" + (f", {st - t:.3f} s ahead of the clock" if math.isfinite(st)
                                                    else ""))
            return None
        if self._last_stamp is not None and st <= self._last_stamp:
            self.skipped["out_of_order"] += 1
            return None
        self._last_stamp = st
        contact = self._match(inputs, st)
        centroid = None
        if self.cal.position is not None:
            centroid = contact["centroid"]
            if centroid is None:
                raise ComponentFault(f"the calibration {self.cal.path} has position terms (degree "
                                     f"{self.cal.position.degree}): wire the contact centroid into its 'centroid' "
                                     f"input (centroid: depth.centroid)", self.id)
        force, status = self.compute(s.value, contact["contact_area"], contact["contact_mask"], s.stamp, centroid)
        self.last_force, self.last_status = force, status
        self.counts[status] += 1
        if status == "invalid-input":
            # no force sample: the consumer sees its estimate go stale and takes it as lost (position-force fades
            # the hand force and holds the follower); a fresh 0 N here read as "the object is gone", so the
            # operator closed the hand while the follower followed onto the object
            self._invalid(f"{s.value!r}")
            return {"status": Sample(status, s.stamp)}
        self.invalid_run = 0
        return {"force": Sample(force, s.stamp), "status": Sample(status, s.stamp)}

    def _remember(self, inputs: Any) -> None:
        """Keep each contact input's last :data:`RECENT_CONTACT_SAMPLES` samples (a new sample each time it changes)."""
        for name in CONTACT_INPUTS:
            smp = inputs.get(name)
            q = self._recent[name]
            if smp is not None and (not q or q[-1] is not smp):
                q.append(smp)

    def _match(self, inputs: Any, stamp: float) -> dict[str, Any]:
        """The contact_area, contact_mask and centroid of the depth sample's frame (None where not wired): the latest
        sample, which from one depth node is of the same step and stamp; else the newest of the input's last
        :data:`RECENT_CONTACT_SAMPLES` samples with the depth's stamp (wired from another node, or through a bridge
        that delivers each topic on its own: the frame's area came a step before its depth). Where none has it (the
        area comes after its depth, or another node stamps it otherwise) the latest value is taken, counted
        (status unmatched_inputs) and said once per input."""
        out: dict[str, Any] = {}
        for name in CONTACT_INPUTS:
            smp = inputs.get(name)
            out[name] = None if smp is None else smp.value
            if smp is None or _stamp_of(smp) == stamp:
                continue
            hit = next((r for r in reversed(self._recent[name]) if _stamp_of(r) == stamp), None)
            if hit is not None:
                out[name] = hit.value
                continue
            self.unmatched_inputs += 1
            if name not in self._unmatched_said:
                self._unmatched_said.add(name)
                self.ctx.log(f"input {name} is stamped {(_stamp_of(smp) - stamp) * 1e3:+.1f} ms from the max_depth "
                             f"sample it is taken with (t={stamp:.3f} s), and none of its last "
                             f"{RECENT_CONTACT_SAMPLES} samples is of that depth frame: the latest value is used; wire "
                             f"max_depth, {name} and the others from one depth node (counted in status "
                             f"unmatched_inputs; said once)")
        return out

    def compute(self, depth: Any, area: Any = None, mask: Any = None, stamp: float = 0.0,
                centroid: Any = None) -> tuple[float, str]:
        p = self.params
        try:
            if isinstance(depth, (bool, np.bool_)):   # float(True) would be a 1 m press
                raise TypeError("a boolean is not a depth")
            d = float(depth)
        except (TypeError, ValueError):
            self._reset_filters()
            return 0.0, "invalid-input"
        if not math.isfinite(d) or d < -p.negative_tolerance or d > p.depth_limit:
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
        # a depth of 0 (or a small negative one) is no contact, also with contact_threshold 0: else the untouched
        # gel would be "in contact" (invalid input without a centroid, a median's older depths on release)
        contact = d > 0.0 and d >= p.contact_threshold
        if contact and ((area is not None and float(area) <= p.min_contact_area)
                        or (mask is not None and not bool(np.any(mask)))):
            if d > p.contact_threshold + p.centroid_band:
                # pressed in, yet no contact area: the inputs disagree. Not a fresh 0 N, which reads as "the object
                # is gone" (the operator closes the hand onto it): invalid, so the estimate goes stale (a 1.5 mm press
                # over 0.8 mm^2 with min_contact_area 1 mm^2 read 0 N, no contact)
                self._reset_filters()
                return 0.0, "invalid-input"
            contact = False   # a light touch the full-size mask misses (see centroid_band), or noise
        if not contact:
            self._reset_filters()
            return 0.0, "no-contact"
        pos, fallback = None, False
        if centroid is not None and self.cal.position is not None:
            try:
                pos = (float(centroid[0]), float(centroid[1]))
            except (TypeError, ValueError, IndexError):
                pos = (math.nan, math.nan)
            if math.isfinite(pos[0]) and math.isfinite(pos[1]):
                self._last_pos = pos
            elif d <= p.contact_threshold + p.centroid_band:
                # a light touch: the depth node's max depth is its work grid's, a little deeper than the full-size
                # map its contact mask and centroid come from, so just above the threshold no pixel may be in contact
                pos, fallback = self._last_pos, True   # None: the centre of the calibrated area
            else:   # in contact, pressed in, but where is unknown
                self._reset_filters()
                return 0.0, "invalid-input"
        self._window.append(d)
        if len(self._window) > 1:
            d = float(np.median(self._window))
        force, status = self.cal.predict_with_status(d, p.out_of_range, pos)
        if fallback:
            self.centroid_fallbacks += 1
            status = "no-centroid"
        if p.lowpass_cutoff is not None:
            if self._filt is None:
                self._filt = force
            else:
                dt = max(stamp - (self._filt_t if self._filt_t is not None else stamp), 0.0)
                tau = 1.0 / (2.0 * math.pi * p.lowpass_cutoff)
                self._filt += (force - self._filt) * (dt / (tau + dt) if dt > 0 else 0.0)
            self._filt_t = stamp
            force = self._filt
        if force > self.force_limit:   # max_force, or the calibration's own largest force (see largest_force)
            force, status = self.force_limit, "clamped"
        if not math.isfinite(force) or force < 0:  # cannot happen with a validated calibration; never emit it
            return 0.0, "invalid-input"
        return float(force), status

    def _reset_filters(self) -> None:
        self._last_pos = None
        self._window.clear()
        self._filt = None
        self._filt_t = None

    def status(self) -> dict[str, Any]:
        return {"force_n": getattr(self, "last_force", 0.0), "status": getattr(self, "last_status", ""),
                "invalid": getattr(self, "counts", {}).get("invalid-input", 0),
                "force_limit_n": getattr(self, "force_limit", None),
                "centroid_fallbacks": getattr(self, "centroid_fallbacks", 0),
                "unmatched_inputs": getattr(self, "unmatched_inputs", 0), **getattr(self, "skipped", {})}


@hookimpl
def teletouch_components():
    return [PolyForce]
