"""Depth from a gradient field: a Poisson solver with zero Dirichlet boundary, by the type-I discrete sine transform.

Given the depth gradients ``gx = dz/dcol`` and ``gy = dz/drow`` (dimensionless, per pixel of spacing 1), the depth
``z`` that best fits them in the least-squares sense solves ``lap(z) = div(g)``. With ``z = 0`` on the boundary, the
5-point Laplacian on an interior of ``n x m`` points is diagonalised by the DST-I; its eigenvalues are

    lam[k, l] = (2 cos(pi (k+1) / (n+1)) - 2) + (2 cos(pi (l+1) / (m+1)) - 2),   k < n, l < m,

so ``z = IDST(DST(f) / lam)``. (A widely copied 2014 solver uses ``n + 2`` in these denominators, which makes depths
about 1.5% too deep on a 6 mm ball; see tests/test_depth_poisson.py.)

The unknowns are the image pixels themselves; the zero boundary lies just outside the image (or outside a window,
see :func:`integrate_window`). The domain is padded with zeros to the next size whose FFT is fast (DST-I of length n
is an FFT of length 2(n + 1): 240 columns would give 482 = 2 x 241, a prime); eigenvalues are cached per size.

Pure functions: numpy/scipy for the CPU, and a torch version (:func:`integrate_torch`; one frame that must be
valid: :func:`integrate_torch_strict`) for any torch device.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

__all__ = [
    "divergence", "fast_size", "eigenvalues", "dst1_matrix", "MATMUL_MAX", "solve_poisson", "integrate",
    "integrate_window", "integrate_torch", "integrate_torch_strict", "dst1_torch",
]

_DEFAULT_WORKERS = 1  # small transforms: one thread is fastest (more only pays for full VGA frames)


def divergence(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """div(g) with central differences (the one consistent with the 5-point Laplacian for gradients sampled at
    pixel centres); gradients beyond the image are taken as 0."""
    gx = np.asarray(gx)
    gy = np.asarray(gy)
    f = np.zeros(np.broadcast_shapes(gx.shape, gy.shape), dtype=np.result_type(gx, gy, np.float32))
    f[..., :, 1:-1] += gx[..., :, 2:] - gx[..., :, :-2]
    f[..., :, 0] += gx[..., :, 1]
    f[..., :, -1] -= gx[..., :, -2]
    f[..., 1:-1, :] += gy[..., 2:, :] - gy[..., :-2, :]
    f[..., 0, :] += gy[..., 1, :]
    f[..., -1, :] -= gy[..., -2, :]
    f *= 0.5
    return f


@functools.lru_cache(maxsize=64)
def fast_size(n: int) -> int:
    """The smallest interior size >= n whose DST-I (an FFT of length 2(n+1)) has only small prime factors."""
    import scipy.fft

    m = scipy.fft.next_fast_len(2 * (n + 1), real=True)
    while m % 2:
        m = scipy.fft.next_fast_len(m + 1, real=True)
    return m // 2 - 1


@functools.lru_cache(maxsize=64)
def eigenvalues(n: int, m: int, dtype: str = "float64") -> np.ndarray:
    """The eigenvalues of the 5-point Laplacian on an n x m interior with zero Dirichlet boundary, including the
    DST-I round-trip scale 1 / (4 (n+1) (m+1)), so that ``idst(dst(f) / lam)`` needs no further normalisation."""
    kr = np.arange(1, n + 1, dtype=np.float64)
    kc = np.arange(1, m + 1, dtype=np.float64)
    lr = 2.0 * np.cos(np.pi * kr / (n + 1)) - 2.0
    lc = 2.0 * np.cos(np.pi * kc / (m + 1)) - 2.0
    lam = lr[:, None] + lc[None, :]
    lam = lam * (4.0 * (n + 1) * (m + 1))
    out = lam.astype(dtype)
    out.setflags(write=False)
    return out


#: the largest padded side solved by matrix products (:func:`dst1_matrix`) instead of FFTs. A ball press's solve
#: window at QVGA is 53-71 cells a side: there the four products (one BLAS thread) took 0.3-0.5x the time of the two
#: scipy.fft DST-I calls (interleaved, this 2-core VM; docs/depth.md); at ~100 a side they break even, and OpenBLAS
#: starts a second thread
MATMUL_MAX = 72


@functools.lru_cache(maxsize=64)
def dst1_matrix(n: int, dtype: str = "float64") -> np.ndarray:
    """The DST-I of length n as a symmetric matrix, ``S[j, k] = 2 sin(pi (j+1) (k+1) / (n+1))``: ``S @ x`` is
    ``scipy.fft.dst(x, type=1)`` along the first axis, ``x @ S`` along the last."""
    k = np.arange(1, n + 1, dtype=np.float64)
    out = (2.0 * np.sin(np.pi * np.outer(k, k) / (n + 1))).astype(dtype)
    out.setflags(write=False)
    return out


def solve_poisson(f: np.ndarray, workers: int | None = None, method: str = "auto") -> np.ndarray:
    """Solve lap(z) = f on f's grid with z = 0 just outside it (the grid is padded to a fast size internally).

    ``method``: ``"fft"`` (scipy.fft DST-I, ``workers`` threads), ``"matmul"`` (the same transforms as products
    with :func:`dst1_matrix`; the zero padding is skipped by slicing the matrices, so the result is the FFT's up to
    rounding, ~1e-6 relative in float32), or ``"auto"``: matmul when both padded sides are at most
    :data:`MATMUL_MAX`."""
    f = np.asarray(f)
    dtype = np.float32 if f.dtype == np.float32 else np.float64
    n, m = f.shape
    pn, pm = fast_size(n), fast_size(m)
    if method == "auto":
        method = "matmul" if max(pn, pm) <= MATMUL_MAX else "fft"
    if method == "matmul":
        name = np.dtype(dtype).name
        sn, sm = dst1_matrix(pn, name), dst1_matrix(pm, name)
        spec = (sn[:, :n] @ f.astype(dtype, copy=False)) @ sm[:m, :]   # the DST of f padded with zeros to pn x pm
        spec /= eigenvalues(pn, pm, name)
        return (sn[:n, :] @ spec) @ sm[:, :m]                          # the inverse, only where f is
    if method != "fft":
        raise ValueError(f"method must be 'auto', 'fft' or 'matmul', got {method!r}")
    import scipy.fft

    if (pn, pm) != (n, m):
        fp = np.zeros((pn, pm), dtype=dtype)
        fp[:n, :m] = f
    else:
        fp = f.astype(dtype, copy=False)
    w = workers or _DEFAULT_WORKERS
    spec = scipy.fft.dstn(fp, type=1, workers=w, overwrite_x=fp is not f)
    spec /= eigenvalues(pn, pm, np.dtype(dtype).name)
    z = scipy.fft.dstn(spec, type=1, workers=w, overwrite_x=True)
    return z[:n, :m]


def integrate(gx: np.ndarray, gy: np.ndarray, workers: int | None = None) -> np.ndarray:
    """Depth (in pixel units, same shape as the gradients) whose gradient best fits (gx, gy), zero at the border.

    ValueError for gradients that are not finite, or so large that the depth overflows (one such cell would make
    the whole solve NaN: the DST spreads it over every pixel)."""
    _check_gradients(gx, gy)
    with np.errstate(over="ignore", invalid="ignore"):   # an overflow is refused just below, with its cause
        z = solve_poisson(divergence(gx, gy), workers=workers)
    return _finite_depth(z, gx, gy)


def _check_gradients(gx: Any, gy: Any, origin: tuple[int, int] = (0, 0)) -> None:
    """ValueError unless gx and gy are finite 2-D maps of at least 2 x 2 (``origin``: where they start in the
    maps the caller was given, for the message)."""
    for name, g in (("gx", gx), ("gy", gy)):
        g = np.asarray(g)
        if g.ndim != 2 or min(g.shape) < 2:
            raise ValueError(f"{name}: expected a 2-D gradient map of at least 2 x 2, got shape {g.shape}")
    _check_finite(gx, gy, origin)


def _check_finite(gx: Any, gy: Any, origin: tuple[int, int] = (0, 0)) -> None:
    """ValueError naming the first gradient of gx or gy that is NaN or inf (at its row and column + ``origin``)."""
    for name, g in (("gx", gx), ("gy", gy)):
        g = np.asarray(g)
        if not np.isfinite(g).all():
            bad = np.argwhere(~np.isfinite(g))
            raise ValueError(f"{name}: {len(bad)} gradients are NaN or inf (the first at row {bad[0][0] + origin[0]}, "
                             f"column {bad[0][1] + origin[1]}): expected finite slopes")


def _finite_depth(z: np.ndarray, gx: Any, gy: Any) -> np.ndarray:
    """z, or a ValueError when finite gradients gave a depth that is not (float overflow)."""
    if not np.isfinite(z).all():
        big = max(float(np.max(np.abs(gx))), float(np.max(np.abs(gy))))
        raise ValueError(f"the gradients are too large to integrate (largest |gradient| {big:.3g}): the depth "
                         f"overflows {z.dtype}")
    return z


def integrate_window(gx: np.ndarray, gy: np.ndarray, box: tuple[int, int, int, int] | None,
                     workers: int | None = None) -> np.ndarray:
    """Like :func:`integrate`, but solve only inside ``box = (r0, r1, c0, c1)`` (z = 0 around it).

    Exact when the true surface is flat (z = 0) outside the box, as it is around a contact once the gradients
    there are zero; much faster than a full-frame solve for a small contact. ``box=None`` means no contact: zeros.
    A box under 3 cells across gives zeros too, but its gradients must be finite (ValueError, as in a wider box).
    """
    z = np.zeros(np.broadcast_shapes(np.shape(gx), np.shape(gy)), dtype=np.float32)
    if box is None:
        return z
    if z.ndim != 2:
        raise ValueError(f"expected 2-D gradient maps, got shape {z.shape}")
    r0, r1, c0, c1 = (int(v) for v in box)
    if not (0 <= r0 <= r1 <= z.shape[0] and 0 <= c0 <= c1 <= z.shape[1]):
        # a negative index would silently solve another window (numpy counts it from the end)
        raise ValueError(f"box (r0, r1, c0, c1) = {tuple(box)}: expected 0 <= r0 <= r1 <= {z.shape[0]} and "
                         f"0 <= c0 <= c1 <= {z.shape[1]} (the gradients' rows and columns)")
    wx, wy = gx[r0:r1, c0:c1], gy[r0:r1, c0:c1]
    if r1 - r0 < 3 or c1 - c0 < 3:
        # no depth in so narrow a window, but a gradient that is not finite is refused as in a wider one (it was
        # given zero depth: NaN read as flat)
        _check_finite(wx, wy, (r0, c0))
        return z
    _check_gradients(wx, wy, (r0, c0))
    with np.errstate(over="ignore", invalid="ignore"):   # a depth beyond float32 becomes inf: refused below
        z[r0:r1, c0:c1] = solve_poisson(divergence(wx, wy), workers=workers)
    _finite_depth(z[r0:r1, c0:c1], wx, wy)
    return z


# --- torch -----------------------------------------------------------------------------------------------------

def dst1_torch(x: Any, dim: int = -1) -> Any:
    """Unnormalised DST-I along ``dim`` (same definition as scipy.fft.dst(type=1)) by a real FFT of the odd
    extension; works on any torch device and on batches."""
    import torch

    x = x.movedim(dim, -1)
    n = x.shape[-1]
    z = torch.zeros(x.shape[:-1] + (1,), dtype=x.dtype, device=x.device)
    y = torch.cat([z, x, z, -x.flip(-1)], dim=-1)
    spec = torch.fft.rfft(y, dim=-1)
    out = -spec.imag[..., 1:n + 1]
    return out.movedim(-1, dim)


_TORCH_EIG: dict[tuple[int, int, str, str], Any] = {}


def _eig_torch(n: int, m: int, dtype: Any, device: Any) -> Any:
    import torch

    key = (n, m, str(dtype), str(device))
    lam = _TORCH_EIG.get(key)
    if lam is None:
        lam = torch.as_tensor(np.array(eigenvalues(n, m)), dtype=dtype, device=device)
        _TORCH_EIG[key] = lam
    return lam


def divergence_torch(gx: Any, gy: Any) -> Any:
    """Torch version of :func:`divergence` (batched over leading dimensions)."""
    import torch.nn.functional as F

    px = F.pad(gx, (1, 1))
    py = F.pad(gy.transpose(-1, -2), (1, 1)).transpose(-1, -2)
    return 0.5 * ((px[..., :, 2:] - px[..., :, :-2]) + (py[..., 2:, :] - py[..., :-2, :]))


def _check_shapes_torch(gx: Any, gy: Any) -> None:
    """ValueError unless gx and gy have one shape (..., rows, cols) of at least 2 x 2, as :func:`integrate` refuses
    them (torch would broadcast a (rows, 1) map, or one map against a batch, without a word)."""
    if tuple(gx.shape) != tuple(gy.shape):
        raise ValueError(f"gx and gy: expected gradient maps of one shape, got {tuple(gx.shape)} and "
                         f"{tuple(gy.shape)}")
    if gx.ndim < 2 or min(gx.shape[-2:]) < 2:
        raise ValueError(f"gx: expected (..., rows, cols) gradient maps of at least 2 x 2, got shape "
                         f"{tuple(gx.shape)}")


def integrate_torch(gx: Any, gy: Any) -> Any:
    """Torch version of :func:`integrate` for (..., rows, cols) tensors on any device (batched).

    gx and gy of different shapes, or under 2 x 2, are refused (ValueError), as :func:`integrate` refuses them. Each
    frame (one index of the leading dimensions) is solved on its own, and where :func:`integrate` raises a
    ValueError this gives that frame NaN everywhere: gradients that are not all finite, or so large that the depth
    overflows. The other frames of the batch are the same as without it. (Unchecked, the DST spread a bad cell over
    its frame, in part only: a single gradient of 1e38 on a 40 x 30 grid left a row of finite, meaningless depth
    among the NaN.) The check is one isfinite reduction of ``z + gx + gy`` per frame, no host synchronisation."""
    import torch
    import torch.nn.functional as F

    _check_shapes_torch(gx, gy)
    f = divergence_torch(gx, gy)
    n, m = f.shape[-2:]
    pn, pm = fast_size(n), fast_size(m)
    if (pn, pm) != (n, m):
        f = F.pad(f, (0, pm - m, 0, pn - n))
    spec = dst1_torch(dst1_torch(f, -1), -2)
    spec = spec / _eig_torch(pn, pm, f.dtype, f.device)
    z = dst1_torch(dst1_torch(spec, -1), -2)[..., :n, :m]
    # a non-finite gradient anywhere in a frame, or an overflow in its solve, makes this sum non-finite somewhere
    ok = torch.isfinite(z + gx + gy).flatten(-2).all(dim=-1)
    return z.masked_fill(~ok[..., None, None], math.nan)


def integrate_torch_strict(gx: Any, gy: Any) -> Any:
    """:func:`integrate_torch` for gradients that must give a depth (one frame, or a batch that is refused as a
    whole): where it would give NaN, the ValueError :func:`integrate` raises for the same gradients (the first bad
    frame's; gradients that are not finite, named by row and column, or a depth that overflows). Costs one isfinite
    reduction and a host synchronisation (reading the depth back costs that anyway); only a refused solve copies
    the gradients to the host, to name the cause."""
    import torch

    z = integrate_torch(gx, gy)
    if bool(torch.isfinite(z).all()):
        return z
    bad = (~torch.isfinite(z)).flatten(-2).any(dim=-1).nonzero()[0].tolist() if z.ndim > 2 else []
    fx, fy = (g[tuple(bad)].detach().cpu().numpy() for g in (gx, gy))
    _check_finite(fx, fy)
    _finite_depth(z[tuple(bad)].detach().cpu().numpy(), fx, fy)   # finite gradients: the overflow is named
    raise AssertionError("unreachable: _finite_depth raises for a depth that is not finite")
