"""Contact between a parallel gripper's gel fingertip(s) and an object (pure functions, used by sim-gripper).

Geometry along the closing axis: the object (width ``w``) sits between the fingers; with the opening ``x < w`` the
fingers penetrate it by ``p = w - x``. The penetration is shared, in series, by the gel of each gel fingertip
(indentation ``d`` each, ``n`` gel fingers) and the object's own compliance (``c = F / k``, zero for a rigid object)::

    p = n * d + F / k,      F = gel(d)          (the same force passes through every element in series)

``gel`` is the fingertip gel's force-indentation law: sim-digit's ``gel_force`` so that the simulated sensor and
the simulated gripper agree on what a given squeeze looks like and how hard it is.

A position servo with stiffness ``kp`` and effort limit ``fmax`` commanded to ``target`` pushes with
``min(fmax, kp * (x - target))``; the blocked opening is where that equals the contact force.
"""

from __future__ import annotations

import math
from typing import Callable

GelLaw = Callable[[float], float]

XTOL = 1e-13


def split_penetration(p: float, gel: GelLaw, n_gel: int = 1, k_object: float | None = None) -> tuple[float, float]:
    """Indentation of each gel ``d`` (m) and the contact force ``F`` (N) for a total penetration ``p`` (m)."""
    if p <= 0:
        return 0.0, 0.0
    if k_object is None or math.isinf(k_object):
        d = p / n_gel
        return d, float(gel(d))
    from scipy.optimize import brentq

    hi = p / n_gel
    f = lambda d: n_gel * d + float(gel(d)) / k_object - p  # noqa: E731
    if f(hi) <= 0:  # numerically no compliance left for the object
        return hi, float(gel(hi))
    d = brentq(f, 0.0, hi, xtol=XTOL)
    return d, float(gel(d))


def blocked_opening(width: float, target: float, kp: float, fmax: float, gel: GelLaw, n_gel: int = 1,
                    k_object: float | None = None) -> float:
    """The opening at which a servo commanded to ``target`` (< width) balances the contact force."""
    if target >= width:
        return width
    from scipy.optimize import brentq

    comp = 0.0 if k_object is None or math.isinf(k_object) else 1.0 / k_object

    def h(d: float) -> float:
        force = float(gel(d))
        x = width - n_gel * d - force * comp
        return force - min(fmax, kp * (x - target))

    hi = (width - target) / n_gel
    if h(hi) <= 0:
        d = hi
    else:
        d = brentq(h, 0.0, hi, xtol=XTOL)
    force = float(gel(d))
    return width - n_gel * d - force * comp
