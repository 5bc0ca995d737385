"""Contact between a parallel gripper's gel fingertip(s) and an object (pure functions, used by sim-gripper).

Geometry along the closing axis: the object (width ``w``) sits between the fingers; with the opening ``x < w`` the
fingers penetrate it by ``p = w - x``. The penetration is shared, in series, by the gel of each gel fingertip
(indentation ``d`` each, ``n`` gel fingers) and the object's own compliance (``c = F / k``, zero for a rigid object)::

    p = n * d + F / k,      F = gel(d)          (the same force passes through every element in series)

A compliant object has a solid core: its compression stops at ``c_max`` (its width less its core's), where it
becomes rigid, so ``p = n * d + min(F / k, c_max)`` and the fingers stop at the core as on a rigid object of the
core's width (a linear spring alone let a soft object be squeezed to nothing, and the fingers close through it).

``gel`` is the fingertip gel's force-indentation law: sim-digit's ``gel_force`` so that the simulated sensor and
the simulated gripper agree on what a given squeeze looks like and how hard it is.

A position servo with stiffness ``kp`` and effort limit ``fmax`` commanded to ``target`` pushes with
``min(fmax, kp * (x - target))``; the blocked opening is where that equals the contact force.

Both problems are one equation ``a F(d) + b d = c`` (a >= 0, b >= 0) for a monotonic law. With a plain callable
``gel`` it is solved by Brent's method (scipy); with a :class:`TabulatedGel` (what sim-gripper uses: 1 kHz, a few
solves a step) by Newton's method started from a table of the law made once per configuration, safeguarded by
bisection, to the same tolerance (``XTOL``): a few microseconds instead of tens.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from typing import Callable

GelLaw = Callable[[float], float]

XTOL = 1e-13


class TabulatedGel:
    """A gel law ``F(d)`` (N of m: 0 at and below 0, continuous, increasing) with a table of it for solving.

    Calling it evaluates ``law`` itself, so forces are exact; the table (``points`` indentations spaced
    geometrically from ``d_min`` to ``d_max``, and the law's slope there) only gives the solvers their starting
    point and Newton slope. Beyond ``d_max`` the solvers fall back to Brent's method.
    """

    def __init__(self, law: GelLaw, d_max: float, d_min: float = 1e-9, points: int = 1200):
        if not (d_max > d_min > 0):
            raise ValueError(f"table range must satisfy d_max > d_min > 0, got {d_min!r}, {d_max!r}")
        self.law = law
        r = (d_max / d_min) ** (1.0 / (points - 1))
        ds = [0.0] + [d_min * r ** i for i in range(points)]
        ds[-1] = d_max
        fs = [float(law(d)) for d in ds]
        for i in range(1, len(fs)):
            if not (fs[i] >= fs[i - 1]) or not math.isfinite(fs[i]):
                raise ValueError(f"gel law is not increasing and finite: F({ds[i]:.4g} m) = {fs[i]!r} after "
                                 f"F({ds[i - 1]:.4g} m) = {fs[i - 1]!r}")
        # slope at each node: centred differences of the table (one-sided at the ends)
        sl = [0.0] * len(ds)
        for i in range(1, len(ds) - 1):
            sl[i] = (fs[i + 1] - fs[i - 1]) / (ds[i + 1] - ds[i - 1])
        sl[0] = (fs[1] - fs[0]) / (ds[1] - ds[0])
        sl[-1] = (fs[-1] - fs[-2]) / (ds[-1] - ds[-2])
        self.d, self.f, self.slope = ds, fs, sl
        self.d_max = d_max
        self._seg = 0  # table segment of the last solution (a cache: the result does not depend on it)

    def __call__(self, d: float) -> float:
        return self.law(d)

    def _slope_at(self, d: float) -> float:
        ds = self.d
        i = bisect_right(ds, d) - 1
        if i < 0:
            return self.slope[0]
        if i >= len(ds) - 1:
            return self.slope[-1]
        w = (d - ds[i]) / (ds[i + 1] - ds[i])
        return self.slope[i] + w * (self.slope[i + 1] - self.slope[i])

    def solve(self, a: float, b: float, c: float, hi: float) -> float:
        """The root in [0, hi] of ``a F(d) + b d = c`` (a, b >= 0, not both 0; c > 0): d (m) to ``XTOL``.
        The root must be bracketed: ``a F(hi) + b hi >= c``."""
        ds, fs = self.d, self.f
        F = self.law
        n = len(ds)
        # start: the table segment where the tabulated left side crosses c (the last call's segment first: in
        # steady contact it is the same), linear interpolation in it, and its chord as the first Newton slope
        i = self._seg
        if not (a * fs[i] + b * ds[i] < c <= a * fs[i + 1] + b * ds[i + 1]):
            lo_i, hi_i = 0, n - 1
            if a * fs[hi_i] + b * ds[hi_i] < c:
                lo_i = hi_i - 1  # beyond the table: start at its end (Newton and bisection take it from there)
            else:
                while hi_i - lo_i > 1:
                    mid = (lo_i + hi_i) >> 1
                    if a * fs[mid] + b * ds[mid] < c:
                        lo_i = mid
                    else:
                        hi_i = mid
            i = self._seg = lo_i
        q0 = a * fs[i] + b * ds[i]
        g = (a * fs[i + 1] + b * ds[i + 1] - q0) / (ds[i + 1] - ds[i])
        d = ds[i] + (c - q0) / g if g > 0.0 else 0.5 * (ds[i] + ds[i + 1])
        lo, up = 0.0, hi
        if not (lo < d < up):
            d = 0.5 * (lo + up)
        d_prev = q_prev = None
        for _ in range(200):
            q = a * F(d) + b * d - c
            if q > 0.0:
                up = d
            elif q < 0.0:
                lo = d
            else:
                return d
            if d_prev is not None and d != d_prev:  # then secant slopes of the last two (exact) evaluations
                s = (q - q_prev) / (d - d_prev)
                g = s if s > 0.0 else a * self._slope_at(d) + b
            nd = d - q / g if g > 0.0 else 0.5 * (lo + up)
            if not (lo < nd < up):
                nd = 0.5 * (lo + up)
            if abs(nd - d) <= XTOL or up - lo <= XTOL:
                return nd
            d_prev, q_prev, d = d, q, nd
        return d


def _solve(gel: GelLaw, a: float, b: float, c: float, hi: float) -> float:
    """Root in [0, hi] of a gel(d) + b d = c (increasing in d; negative at 0, >= 0 at hi)."""
    if isinstance(gel, TabulatedGel):
        return gel.solve(a, b, c, hi)
    from scipy.optimize import brentq

    return brentq(lambda d: a * float(gel(d)) + b * d - c, 0.0, hi, xtol=XTOL)


def _rigid(k_object: float | None) -> bool:
    return k_object is None or math.isinf(k_object)


def split_penetration(p: float, gel: GelLaw, n_gel: int = 1, k_object: float | None = None,
                      max_compression: float | None = None) -> tuple[float, float]:
    """Indentation of each gel ``d`` (m) and the contact force ``F`` (N) for a total penetration ``p`` (m).
    ``max_compression`` (m, None: none): the compliant object's compression stops there (its solid core)."""
    if p <= 0:
        return 0.0, 0.0
    if _rigid(k_object):
        d = p / n_gel
        return d, float(gel(d))
    if max_compression is not None and p > max_compression:
        # the object squeezed down to its core: the gels take the rest, if their force holds it there
        d = (p - max_compression) / n_gel
        f = float(gel(d))
        if f >= k_object * max_compression:
            return d, f
    hi = p / n_gel
    # n d + gel(d) / k = p
    if n_gel * hi + float(gel(hi)) / k_object - p <= 0:  # numerically no compliance left for the object
        return hi, float(gel(hi))
    d = _solve(gel, 1.0 / k_object, float(n_gel), p, hi)
    return d, float(gel(d))


def blocked_opening(width: float, target: float, kp: float, fmax: float, gel: GelLaw, n_gel: int = 1,
                    k_object: float | None = None, max_compression: float | None = None) -> float:
    """The opening at which a servo commanded to ``target`` (< width) balances the contact force.
    ``max_compression`` (m, None: none): the compliant object's compression stops there (its solid core); where
    the balance needs more, the fingers stop as on a rigid object of the core's width."""
    x, force = _blocked(width, target, kp, fmax, gel, n_gel, k_object)
    if max_compression is None or _rigid(k_object) or force <= k_object * max_compression:
        return x
    # the balance is monotonic in the indentation: where the spring's own balance compresses the object past its
    # core, the true balance is on the core, as for a rigid object of the core's width
    return _blocked(width - max_compression, target, kp, fmax, gel, n_gel, None)[0]


def _blocked(width: float, target: float, kp: float, fmax: float, gel: GelLaw, n_gel: int,
             k_object: float | None) -> tuple[float, float]:
    """The blocked opening (m) without a compression limit, and the contact force there (N)."""
    if target >= width:
        return width, 0.0
    comp = 0.0 if _rigid(k_object) else 1.0 / k_object
    hi = (width - target) / n_gel
    # h(d) = F - min(fmax, kp (x(d) - target)), x(d) = width - n d - F comp: increasing in d, negative at 0
    f_hi = float(gel(hi))
    if f_hi - min(fmax, kp * (width - n_gel * hi - f_hi * comp - target)) <= 0:
        d = hi
    else:
        # saturated servo: F(d) = fmax, if the servo's spring force there is above fmax
        d = None
        if f_hi > fmax:
            d_sat = _solve(gel, 1.0, 0.0, fmax, hi)
            if kp * (width - n_gel * d_sat - fmax * comp - target) >= fmax:
                d = d_sat
        if d is None:
            # spring: F = kp (width - n d - F comp - target)  <=>  (1 + kp comp) F + kp n d = kp (width - target)
            d = _solve(gel, 1.0 + kp * comp, kp * n_gel, kp * (width - target), hi)
    force = float(gel(d))
    return width - n_gel * d - force * comp, force
