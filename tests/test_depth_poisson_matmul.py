"""The Poisson solve by matrix products (small windows) against the scipy.fft DST-I solve and the 5-point Laplacian."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.fft

from teletouch.plugins.estimators import poisson as P


def _laplacian(z: np.ndarray) -> np.ndarray:
    zp = np.pad(z, 1)
    return zp[2:, 1:-1] + zp[:-2, 1:-1] + zp[1:-1, 2:] + zp[1:-1, :-2] - 4 * zp[1:-1, 1:-1]


@pytest.mark.parametrize("n", [1, 2, 7, 40, 71])
def test_dst1_matrix_is_scipys_dst1_along_either_axis(n):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(n, 5))
    s = P.dst1_matrix(n)
    assert np.allclose(s @ x, scipy.fft.dst(x, type=1, axis=0), atol=1e-10 * n)
    assert np.allclose(x.T @ s, scipy.fft.dst(x.T, type=1, axis=1), atol=1e-10 * n)
    assert not s.flags.writeable   # cached: a caller must not change it for the others


@pytest.mark.parametrize("shape", [(7, 5), (62, 58), (60, 64), (71, 71), (3, 70)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_matmul_solve_equals_the_fft_solve(shape, dtype):
    rng = np.random.default_rng(sum(shape))
    f = rng.normal(size=shape).astype(dtype)
    a = P.solve_poisson(f, method="fft")
    b = P.solve_poisson(f, method="matmul")
    assert b.dtype == a.dtype == dtype and b.shape == a.shape == shape
    tol = 1e-5 if dtype == np.float32 else 1e-12
    assert np.abs(b - a).max() <= tol * np.abs(a).max()


def test_matmul_solve_satisfies_the_laplacian_with_a_padded_domain():
    # 64 columns pad to a fast size of 71: the zero boundary is beyond the padding, as on the FFT path
    rng = np.random.default_rng(3)
    f = rng.normal(size=(40, 64))
    assert P.fast_size(64) != 64
    z = P.solve_poisson(f, method="matmul")
    assert np.allclose(_laplacian(z)[:-1, :-1], f[:-1, :-1], atol=1e-9)
    assert not np.allclose(_laplacian(z)[:, -1], f[:, -1], atol=1e-6)   # the padded domain goes on past the edge


def test_auto_takes_matmul_for_small_windows_and_fft_for_large(monkeypatch):
    calls = []
    real = scipy.fft.dstn
    monkeypatch.setattr(scipy.fft, "dstn", lambda *a, **k: calls.append(a[0].shape) or real(*a, **k))
    P.solve_poisson(np.ones((60, 60), np.float32))
    assert calls == []   # 60 pads to 63 <= MATMUL_MAX
    big = P.MATMUL_MAX + 20
    P.solve_poisson(np.ones((big, 30), np.float32))
    assert len(calls) == 2
    with pytest.raises(ValueError, match="method must be 'auto', 'fft' or 'matmul', got 'dct'"):
        P.solve_poisson(np.ones((4, 4)), method="dct")


def test_window_integration_is_the_same_either_way(monkeypatch):
    # a sphere cap's gradients on a window of a QVGA work grid: the estimator's use
    yy, xx = np.mgrid[0:160, 0:120].astype(np.float64)
    r2 = (yy - 80.3) ** 2 + (xx - 60.6) ** 2
    R, a = 25.7, 10.0
    s = np.sqrt(np.maximum(R * R - r2, 1e-12))
    gx = np.where(r2 < a * a, -(xx - 60.6) / s, 0.0).astype(np.float32)
    gy = np.where(r2 < a * a, -(yy - 80.3) / s, 0.0).astype(np.float32)
    box = (52, 110, 31, 92)
    z_mm = P.integrate_window(gx, gy, box)
    monkeypatch.setattr(P, "MATMUL_MAX", 0)
    z_fft = P.integrate_window(gx, gy, box)
    assert z_mm.max() > 1.5   # a real cap, not zeros
    assert np.abs(z_mm - z_fft).max() <= 1e-5 * z_fft.max()
