"""The DST-I Poisson solver against the discrete Laplacian and analytic surfaces (sphere cap, Gaussian, paraboloid)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.fft
import torch

from teletouch.plugins.estimators import poisson as P

ROWS, COLS = 320, 240
R_BALL_PX = 3.0 * 17.15  # a 6 mm ball at the paper's QVGA scale


def _sampled(fn, ss: int):
    """Gradient field (gx, gy) of a surface, averaged over each pixel with ss x ss sub-samples (ss=1: centres)."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    yy, xx = np.mgrid[0:ROWS, 0:COLS].astype(np.float64)
    gx = np.zeros((ROWS, COLS))
    gy = np.zeros((ROWS, COLS))
    for dy in o:
        for dx in o:
            a, b = fn(yy + dy, xx + dx)
            gx += a
            gy += b
    return gx / ss ** 2, gy / ss ** 2


def sphere_cap(cy, cx, R, a):
    def fn(y, x):
        y = y - cy
        x = x - cx
        r2 = x * x + y * y
        inside = r2 < a * a
        s = np.sqrt(np.maximum(R * R - r2, 1e-12))
        return np.where(inside, -x / s, 0.0), np.where(inside, -y / s, 0.0)
    return fn, R - np.sqrt(R * R - a * a)


def gaussian(cy, cx, A, sig):
    def fn(y, x):
        y = y - cy
        x = x - cx
        z = A * np.exp(-(x * x + y * y) / (2 * sig * sig))
        return -x / sig ** 2 * z, -y / sig ** 2 * z
    return fn, A


def paraboloid(cy, cx, c, a):
    def fn(y, x):
        y = y - cy
        x = x - cx
        inside = x * x + y * y < a * a
        return np.where(inside, -2 * c * x, 0.0), np.where(inside, -2 * c * y, 0.0)
    return fn, c * a * a


def test_eigenvalues_are_the_discrete_laplacians():
    n, m = 7, 5
    lam = P.eigenvalues(n, m) / (4.0 * (n + 1) * (m + 1))
    k = np.arange(1, n + 1)
    assert np.allclose(lam[:, 0], 2 * np.cos(np.pi * k / (n + 1)) - 2 + 2 * np.cos(np.pi / (m + 1)) - 2)
    # the solution satisfies the 5-point Laplacian with zero boundary exactly
    rng = np.random.default_rng(0)
    f = rng.normal(size=(n, m))
    z = P.solve_poisson(f)
    zp = np.pad(z, 1)
    lap = zp[2:, 1:-1] + zp[:-2, 1:-1] + zp[1:-1, 2:] + zp[1:-1, :-2] - 4 * zp[1:-1, 1:-1]
    assert np.allclose(lap, f, atol=1e-9)


def test_padding_to_fast_sizes_keeps_the_laplacian_exact():
    rng = np.random.default_rng(1)
    f = np.zeros((ROWS, COLS))
    f[100:200, 60:180] = rng.normal(size=(100, 120))
    z = P.solve_poisson(f)
    assert P.fast_size(COLS) != COLS  # 2 x 241 is prime: the domain really is padded
    zp = np.pad(z, 1)
    lap = zp[2:, 1:-1] + zp[:-2, 1:-1] + zp[1:-1, 2:] + zp[1:-1, :-2] - 4 * zp[1:-1, 1:-1]
    # exact inside the image; on the last row/column the padded domain continues (z is not forced to 0 there)
    assert np.allclose(lap[:-1, :-1], f[:-1, :-1], atol=1e-9)


@pytest.mark.parametrize("case", ["sphere-a20", "sphere-a28", "sphere-a34", "gauss", "paraboloid"])
@pytest.mark.parametrize("ss", [1, 4])
def test_analytic_surfaces_within_1_percent(case, ss):
    fn, peak = {
        "sphere-a20": sphere_cap(150.3, 120.6, R_BALL_PX, 20.0),
        "sphere-a28": sphere_cap(101.7, 70.2, R_BALL_PX, 28.0),
        "sphere-a34": sphere_cap(220.5, 160.5, R_BALL_PX, 34.0),
        "gauss": gaussian(160.2, 119.7, 10.0, 15.0),
        "paraboloid": paraboloid(170.4, 100.1, 0.01, 30.0),
    }[case]
    gx, gy = _sampled(fn, ss)
    z = P.integrate(gx, gy)
    assert abs(z.max() / peak - 1) <= 0.01
    # the surface is also right away from the peak: flat far outside
    assert np.abs(z[:20, :20]).max() < 0.01 * peak


def test_the_n_plus_2_denominator_of_the_2014_solver_is_measurably_wrong():
    fn, peak = sphere_cap(150.3, 120.6, R_BALL_PX, 28.0)
    gx, gy = _sampled(fn, 4)
    f = P.divergence(gx, gy)[1:-1, 1:-1]
    n, m = f.shape
    k1, k2 = np.arange(1, n + 1), np.arange(1, m + 1)
    wrong = (2 * np.cos(np.pi * k1 / (n + 2)) - 2)[:, None] + (2 * np.cos(np.pi * k2 / (m + 2)) - 2)[None, :]
    z_wrong = scipy.fft.idstn(scipy.fft.dstn(f, type=1) / wrong, type=1)
    right = P.integrate(gx, gy).max()
    assert z_wrong.max() / right - 1 > 0.005        # systematically deeper (more on smaller frames)
    assert abs(right / peak - 1) < abs(z_wrong.max() / peak - 1)


def test_window_solve_matches_full_solve_for_a_local_contact():
    fn, peak = sphere_cap(150.3, 120.6, R_BALL_PX, 25.0)
    gx, gy = _sampled(fn, 2)
    full = P.integrate(gx, gy)
    win = P.integrate_window(gx, gy, (110, 192, 80, 162))
    assert abs(win.max() - full.max()) < 0.01 * peak
    assert np.all(win[:100] == 0) and np.all(win[:, :70] == 0)
    assert np.all(P.integrate_window(gx, gy, None) == 0)


def test_torch_solver_equals_scipy_and_batches():
    fn, _ = gaussian(100.0, 80.0, 5.0, 12.0)
    gx, gy = _sampled(fn, 1)
    x = np.random.default_rng(2).normal(size=(9, 11))
    assert np.allclose(P.dst1_torch(torch.tensor(x)).numpy(), scipy.fft.dst(x, type=1), atol=1e-10)
    ref = P.integrate(gx, gy)
    tg = torch.tensor(np.stack([gx, 2 * gx]))
    th = torch.tensor(np.stack([gy, 2 * gy]))
    z = P.integrate_torch(tg, th).numpy()
    assert np.allclose(z[0], ref, atol=1e-8)
    assert np.allclose(z[1], 2 * ref, atol=1e-8)
    assert np.allclose(P.divergence_torch(torch.tensor(gx), torch.tensor(gy)).numpy(), P.divergence(gx, gy))
