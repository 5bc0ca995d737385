"""The fast paths of the simulated loop give the same numbers as the reference code they replace."""

from __future__ import annotations

import math
import random

import pytest

from teletouch.plugins.devices import follower_contact as fc
from teletouch.plugins.sensors import gel

INDENTERS = [gel.Indenter.sphere(0.003), gel.Indenter.probe(0.005, 0.010), gel.Indenter.probe(0.004, 0.004),
             gel.Indenter.flat(0.003)]
MATERIALS = [gel.GelMaterial(), gel.GelMaterial(1e6, 0.45, 0.004)]


@pytest.mark.parametrize("indenter", INDENTERS, ids=lambda i: i.kind)
@pytest.mark.parametrize("material", MATERIALS, ids=("half-space", "thin-layer"))
def test_force_law_is_gel_force(indenter, material):
    law = gel.force_law(indenter, material)
    rng = random.Random(1)
    ds = [0.0, -1e-3, indenter.radius, 0.0025, 0.01] + [10 ** rng.uniform(-9, -1.5) for _ in range(400)]
    for d in ds:
        assert law(d) == gel.gel_force(d, indenter, material)  # the same arithmetic: the same number
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match="finite"):
            law(bad)


def test_force_law_other_shapes_call_gel_force():
    tilted = gel.force_law(gel.Indenter.probe(0.005, 0.010), tilt_rad=0.2)
    assert tilted(8e-4) == gel.gel_force(8e-4, gel.Indenter.probe(0.005, 0.010), tilt_rad=0.2)


def _brent_blocked(width, target, kp, fmax, law, n, k_object):
    from scipy.optimize import brentq

    comp = 0.0 if k_object is None else 1.0 / k_object

    def h(d):
        f = law(d)
        return f - min(fmax, kp * (width - n * d - f * comp - target))

    hi = (width - target) / n
    d = hi if h(hi) <= 0 else brentq(h, 0.0, hi, xtol=fc.XTOL)
    return width - n * d - law(d) * comp


@pytest.mark.parametrize("indenter", INDENTERS, ids=lambda i: i.kind)
def test_tabulated_solvers_match_brent(indenter):
    rng = random.Random(7)
    for material in MATERIALS:
        law = gel.force_law(indenter, material)
        for width in (0.04, 0.005):
            tab = fc.TabulatedGel(law, width)
            assert tab(1e-3) == law(1e-3)
            for _ in range(60):
                target = rng.choice([width - 10 ** rng.uniform(-9, -2.4), rng.uniform(0.0, width)])
                kp, fmax = rng.choice([300.0, 4000.0, 1e5]), rng.choice([0.01, 1.0, 16.0, 100.0])
                n = rng.choice([1, 2])
                k_obj = rng.choice([None, 3000.0, 1e6])
                x = fc.blocked_opening(width, target, kp, fmax, tab, n, k_obj)
                # the object's compliance multiplies the tolerance on d by (n + F' / k) on the opening
                assert x == pytest.approx(_brent_blocked(width, target, kp, fmax, law, n, k_obj), abs=1e-12)
                if k_obj is not None:
                    pen = rng.uniform(0.0, width)
                    d, f = fc.split_penetration(pen, tab, n, k_obj)
                    d_ref, _ = fc.split_penetration(pen, law, n, k_obj)  # a plain callable: Brent's method
                    assert d == pytest.approx(d_ref, abs=1e-12)
                    assert f == law(d)
                    assert n * d + f / k_obj == pytest.approx(pen, abs=1e-12)


def test_tabulated_gel_beyond_its_table_and_bad_laws():
    law = gel.force_law(gel.Indenter.sphere(0.003))
    tab = fc.TabulatedGel(law, 0.002)  # the solvers are asked about penetrations beyond the table
    x = fc.blocked_opening(0.04, 0.0, 1e5, 100.0, tab)
    assert x == pytest.approx(_brent_blocked(0.04, 0.0, 1e5, 100.0, law, 1, None), abs=1e-12)
    assert 0.04 - x > 0.002
    with pytest.raises(ValueError, match="not increasing"):
        fc.TabulatedGel(lambda d: -d, 0.01)
    with pytest.raises(ValueError, match="d_max > d_min"):
        fc.TabulatedGel(law, 0.0)


def test_poly_force_scalar_path_is_the_array_path():
    import numpy as np

    from teletouch.plugins.estimators.poly_force import ForceCalibration

    cal = ForceCalibration.load("sim-digit-qvga")
    lo, hi = cal.depth_range
    rng = random.Random(3)
    depths = [0.0, -0.0, -1e-4, lo, hi, 0.5 * lo, 2 * hi, 1e9] + [rng.uniform(-1e-3, 3 * hi) for _ in range(500)]
    for d in depths:
        for mode in ("clamp", "extrapolate"):
            f, code = cal.evaluate(d, mode)
            ref = (float(f), ("ok", "extrapolated", "clamped")[int(code)])
            assert cal.predict_with_status(d, mode) == ref
            assert cal.predict_with_status(np.float64(d), mode) == ref
    with pytest.raises(ValueError, match="NaN"):
        cal.predict_with_status(math.nan)
    with pytest.raises(ValueError, match="out_of_range"):
        cal.predict_with_status(1e-4, "wrap")


def test_sim_digit_frames_do_not_depend_on_its_caches():
    """A simulator that has rendered other poses gives every frame the numbers a fresh one gives, and the max depth
    it keeps with the pose is the surface's."""
    import numpy as np

    from teletouch.plugins.sensors.sim_digit import DigitSimulator

    poses = [(1.2e-3, (0.0, 0.0)), (3e-4, (0.0013, -0.0021)), (1.5e-3, (0.0, 0.0)), (8e-4, (0.0013, -0.0021)),
             (1.1e-3, (-0.004, 0.003)), (6e-4, (0.0, 0.0))]
    warm = DigitSimulator(indenter=gel.Indenter.probe(0.005, 0.010))
    for d, pos in poses:
        img, surf = warm.render(d, pos)
        cold = DigitSimulator(indenter=gel.Indenter.probe(0.005, 0.010))
        img_c, surf_c = cold.render(d, pos)
        assert np.array_equal(img, img_c) and np.array_equal(surf.depth, surf_c.depth)
        assert np.array_equal(surf.mask, surf_c.mask)
        assert warm.max_depth == float(surf.depth.max()) > 0
        assert (img != warm.background_u8).any()
