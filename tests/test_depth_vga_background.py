"""VGA calibration with a real no-contact frame as background (`--background frame_49.jpg`) read the cap height 38%
wrong against 12.7% with the median background. The cause: a single frame carries its own noise and lighting, so
the calibration's change threshold comes out higher (VGA: 40 levels against 27-31), and then the weakly changing
flat centre of a press (and the rim's weakly lit side) falls below it; the estimator took those cells as untouched
gel, its zero reference, and forced their depth to 0: a crater at the deepest point. Now what the change mask
encloses (after a small closing) counts as changed (docs/depth.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from teletouch.plugins.estimators import depth_pipeline as DP
from teletouch.plugins.estimators.normal_model import load_model
from teletouch.plugins.sensors import gel
from teletouch.plugins.sensors.sim_digit import DigitSimulator


@pytest.fixture(scope="module")
def press():
    """sim-digit, a 6 mm ball pressed 0.6 mm at the centre, and the row and column of the deepest true point."""
    s = DigitSimulator("qvga", indenter=gel.Indenter.sphere(0.003), noise=2.0, seed=5)
    img, surf = s.render(0.6e-3, (0.0, 0.0), 0.0, t=0.0)
    r, c = np.unravel_index(int(surf.depth.argmax()), surf.depth.shape)
    return img, int(r), int(c)


@pytest.mark.parametrize("mode", ["sparse", "dense"])
@pytest.mark.parametrize("threshold", [50.0, 60.0])
def test_a_press_whose_centre_changes_less_than_the_threshold_has_no_crater(press, mode, threshold):
    """With the change threshold raised (as a single-frame background raises it), the press's flat centre is below
    it and the mask is a ring. Before, the centre was set to zero depth: at 60 levels it read 0.046 mm against a
    max depth of 0.43 mm (50 levels: 0.19 against 0.49); now it reads about the max depth."""
    img, r, c = press
    pipe = DP.DepthPipeline(load_model("sim-digit-qvga"), threads=1, mode=mode, change_threshold=threshold)
    res = pipe(img)
    centre = float(res.depth[r - 3:r + 4, c - 3:c + 4].mean())
    assert res.max_depth > 0.3e-3
    assert centre >= 0.9 * res.max_depth, (centre, res.max_depth)
    # the ring is still what the mask sees: the centre itself is below the threshold (else the test shows nothing)
    b = pipe._buffers() if mode == "sparse" else None
    if b is not None:
        s = pipe.stride
        assert not b["mb"][r // s, c // s]


def test_fill_enclosed_fills_a_ring_and_a_ring_with_a_narrow_gap_but_not_an_open_bay():
    m = np.zeros((40, 40), np.uint8)
    yy, xx = np.mgrid[0:40, 0:40]
    rr = np.hypot(yy - 20, xx - 20)
    ring = ((rr >= 8) & (rr <= 11)).astype(np.uint8)
    got = DP.fill_enclosed(ring.copy())
    assert got[20, 20] == 1 and got[rr < 8].all()
    assert (got[rr > 12] == 0).all()                   # nothing outside the ring is added
    gap = ring.copy()
    gap[18:23, 28:33] = 0                              # a gap of 5 cells in the rim (the weakly lit side)
    got = DP.fill_enclosed(gap.copy())
    assert got[rr < 8].all()
    assert (got[rr > 12] == 0).all()
    bay = ring.copy()
    bay[12:29, 26:40] = 0                              # half the ring open: not enclosed
    got = DP.fill_enclosed(bay.copy())
    assert got[20, 20] == 0
    m[0:6, 0:6] = 1                                    # a blob in a corner encloses nothing
    assert np.array_equal(DP.fill_enclosed(m.copy(), close=0), m)


def test_fill_enclosed_is_the_same_on_the_torch_path():
    rng = np.random.default_rng(0)
    for close in (0, 3):
        for i in range(60):
            m = (rng.random((30, 25)) < rng.uniform(0.05, 0.5)).astype(np.uint8)
            a = DP.fill_enclosed(m.copy(), close=close)
            t = DP.fill_enclosed_torch(torch.from_numpy(m).float()[None, None], close=close)[0, 0]
            assert np.array_equal(a, t.numpy().astype(np.uint8)), (close, i)
            assert (a >= m).all()


def test_an_untouched_frame_still_reads_zero_with_a_low_threshold():
    """The zero reference is unchanged: noise specks enclose nothing that survives the opening."""
    s = DigitSimulator("qvga", noise=2.0, drift=4.0, seed=3)
    img, _ = s.render(0.0, (0.0, 0.0), 0.0, t=0.0)
    for mode in ("sparse", "dense"):
        pipe = DP.DepthPipeline(load_model("sim-digit-qvga"), threads=1, mode=mode)
        assert pipe(img).max_depth == 0.0


def test_fill_enclosed_on_the_contact_box_is_the_fill_of_the_whole_grid():
    """fill_enclosed works on the changed cells' bounding box (plus close + 1 cells), which is 10x cheaper than the
    whole grid; its result must be the whole grid's (here: the torch path's, which works on the whole grid), also for
    contacts at the grid's edges and corners, where the box is cut by the border."""
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:60, 0:80]
    for close in (0, 1, 3):
        for i in range(80):
            cy, cx = rng.integers(-3, 63), rng.integers(-3, 83)
            r_in = rng.uniform(2, 9)
            rr = np.hypot(yy - cy, xx - cx)
            m = ((rr >= r_in) & (rr <= r_in + rng.uniform(1, 4))).astype(np.uint8)
            m[rng.random(m.shape) < 0.15] = 0          # gaps in the rim
            m[rng.random(m.shape) < 0.002] = 1         # specks elsewhere
            a = DP.fill_enclosed(m.copy(), close=close)
            t = DP.fill_enclosed_torch(torch.from_numpy(m).float()[None, None], close=close)[0, 0]
            assert np.array_equal(a, t.numpy().astype(np.uint8)), (close, i, cy, cx)


def _spiral(n: int, gap: bool) -> np.ndarray:
    """An n x n wall winding inwards (1 = changed): its corridor turns ~2n/3 times on its way to the centre; with
    ``gap`` its entrance from the border is open, else walled."""
    m = np.zeros((n, n), np.uint8)
    r0, c0, r1, c1 = 1, 1, n - 2, n - 2
    while r1 - r0 >= 2 and c1 - c0 >= 2:
        m[r0, c0:c1 + 1] = 1
        m[r0:r1 + 1, c1] = 1
        m[r1, c0:c1 + 1] = 1
        m[r0 + 2:r1 + 1, c0] = 1
        if r1 - r0 >= 4 and c1 - c0 >= 4:
            m[r0 + 2, c0:c0 + 3] = 1
        r0, c0, r1, c1 = r0 + 2, c0 + 2, r1 - 2, c1 - 2
    m[1:3, 1] = 0 if gap else 1
    m[0, 1] = 0
    if not gap:
        m[1:4, 1] = 1
    return m


def _maze(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A random maze (walls 1, corridors 0 between cells on odd rows and columns), its border open in a few places
    and a few walls knocked through: reachable corridors, enclosed pockets and long winding paths."""
    m = np.ones((h, w), np.uint8)
    stack = [(1, 1)]
    m[1, 1] = 0
    while stack:
        r, c = stack[-1]
        nxt = [(r + dr, c + dc) for dr, dc in ((2, 0), (-2, 0), (0, 2), (0, -2))
               if 0 < r + dr < h - 1 and 0 < c + dc < w - 1 and m[r + dr, c + dc]]
        if not nxt:
            stack.pop()
            continue
        nr, nc = nxt[rng.integers(len(nxt))]
        m[(r + nr) // 2, (c + nc) // 2] = 0
        m[nr, nc] = 0
        stack.append((nr, nc))
    for _ in range(rng.integers(0, 4)):
        side = rng.integers(4)
        k = 2 * rng.integers(0, (min(h, w) - 1) // 2) + 1
        m[(0, h - 1, k, k)[side], (k, k, 0, w - 1)[side]] = 0
    knock = rng.random(m.shape) < 0.02
    m[knock] = 0
    m[rng.random(m.shape) < 0.05] = 1                  # and some walls put up: pockets
    return m


def test_the_torch_fill_follows_paths_that_wind_like_the_opencv_flood_fill():
    """The torch fill spreads along whole rows and columns a pass: a corridor that turns many times takes a pass per
    turn. Spirals and random mazes (up to ~50 turns deep) against OpenCV's flood fill, each alone and all as one
    batch (a mask that needs more passes must not change the others)."""
    rng = np.random.default_rng(7)
    masks = [_spiral(41, gap=True), _spiral(41, gap=False)] + [_maze(rng, 41, 41) for _ in range(30)]
    ref = [DP.fill_enclosed(m.copy(), close=0) for m in masks]
    # the spiral open to the border encloses nothing; the walled one encloses its whole corridor
    assert np.array_equal(ref[0], masks[0])
    assert ref[1].sum() > masks[1].sum() + 300
    for i, (m, a) in enumerate(zip(masks, ref)):
        t = DP.fill_enclosed_torch(torch.from_numpy(m).float()[None, None], close=0)[0, 0]
        assert np.array_equal(a, t.numpy().astype(np.uint8)), i
    batch = DP.fill_enclosed_torch(torch.from_numpy(np.stack(masks)).float()[:, None], close=0)[:, 0]
    assert np.array_equal(np.stack(ref), batch.numpy().astype(np.uint8))
    # rectangular grids (rows != cols): rows and columns are not swapped
    for i in range(20):
        m = _maze(rng, 31, 57)
        t = DP.fill_enclosed_torch(torch.from_numpy(m).float()[None, None], close=int(i % 2) * 2)[0, 0]
        assert np.array_equal(DP.fill_enclosed(m.copy(), close=int(i % 2) * 2), t.numpy().astype(np.uint8)), i
