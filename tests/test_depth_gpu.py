"""The depth estimator on a CUDA GPU against the same computation on the CPU.

Collected only where torch sees a CUDA GPU (tests/conftest.py leaves this file out elsewhere: CI's machines have
none, so CI runs none of these); on a GPU machine `./dev test` runs them with the rest. What they check: the dense
path on the GPU gives the CPU's dense path's outputs (float32 round-off apart) and the CPU's default (sparse) path's
within the tolerance the CPU paths keep between themselves; the hole fill, the Poisson solve and the batched path
on the GPU; errors on the GPU are the CPU's errors; the `depth` node and `teletouch estimate` with ``device: cuda``.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from teletouch import Sample
from teletouch.plugins.estimators import depth_pipeline as DP
from teletouch.plugins.estimators import poisson as P
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.estimators.depth_pipeline import DepthPipeline
from teletouch.testing import Harness

from helpers_depth import model_fixture, sim_fixture
from test_depth_poisson import R_BALL_PX, _sampled, gaussian, paraboloid, sphere_cap
from test_depth_vga_background import _maze, _spiral
from test_open_items_review import _BadNormals

if not torch.cuda.is_available():   # named on the command line (a whole-suite run does not collect this file here)
    pytest.skip("torch sees no CUDA GPU here", allow_module_level=True)

model = model_fixture()
sim = sim_fixture()

GPU = "cuda"
#: float32 round-off between two devices on a depth map of ~1 mm (seen on an H100: 2.3e-10 m)
ATOL_M = 1e-8


@pytest.fixture(scope="module")
def frames(sim):
    """Presses of a 6 mm ball at several depths and places (one cut by the image's border) and a frame at rest."""
    presses = [(0.8e-3, (0.0, 0.0)), (0.4e-3, (-2.5e-3, -4e-3)), (1.1e-3, (2.5e-3, 3.5e-3)),
               (0.7e-3, (-3.4e-3, 7.6e-3)), (0.0, (0.0, 0.0))]
    return [sim.render(d, pos, 0.0)[0] for d, pos in presses]


def test_the_dense_path_on_the_gpu_gives_the_cpu_outputs(model, frames):
    gpu = DepthPipeline(model, device=GPU)
    assert gpu.mode == "dense"                               # the default on a GPU
    cpu_dense, cpu_sparse = DepthPipeline(model, mode="dense"), DepthPipeline(model)
    for i, fr in enumerate(frames):
        g, c, s = gpu(fr), cpu_dense(fr), cpu_sparse(fr)
        assert g.depth.dtype == np.float32 and g.depth.shape == (320, 240)
        assert np.abs(g.depth - c.depth).max() < ATOL_M, i
        assert g.max_depth == pytest.approx(c.max_depth, abs=ATOL_M)
        assert np.array_equal(g.contact_mask, c.contact_mask), i
        assert g.contact_area == pytest.approx(c.contact_area, rel=1e-6, abs=1e-12)
        assert np.allclose(g.centroid, c.centroid, atol=1e-9, equal_nan=True), i
        assert np.allclose(g.offset, c.offset, atol=1e-4) and g.changed == c.changed
        # the CPU's default path: the tolerance the two CPU paths keep (tests/test_depth_estimator.py)
        assert g.max_depth == pytest.approx(s.max_depth, rel=0.03, abs=1e-6), i
    assert gpu(frames[-1]).max_depth == 0.0                  # the zero reference: no contact, no depth
    assert gpu.max_depth(frames[0]) == pytest.approx(cpu_dense.max_depth(frames[0]), abs=ATOL_M)


def test_a_batch_on_the_gpu_is_its_frames_one_by_one(model, frames):
    gpu = DepthPipeline(model, device=GPU)
    z = gpu.batch_depth(np.stack(frames))
    assert z.device.type == "cuda" and z.shape == (len(frames), 320, 240)
    cpu = DepthPipeline(model, mode="dense").batch_depth(np.stack(frames)).numpy()
    assert np.abs(z.cpu().numpy() - cpu).max() < ATOL_M
    for k, fr in enumerate(frames):
        assert np.abs(z[k].cpu().numpy() - gpu(fr).depth).max() < ATOL_M
    # a tensor already on the GPU is taken as it is
    zt = gpu.batch_depth(torch.from_numpy(np.stack(frames)).to(GPU))
    assert torch.equal(zt, z)


def test_the_hole_fill_on_the_gpu_is_opencvs(model):
    rng = np.random.default_rng(11)
    masks = [_spiral(41, gap=True), _spiral(41, gap=False)] + [_maze(rng, 41, 41) for _ in range(20)]
    masks += [(rng.random((41, 41)) < rng.uniform(0.05, 0.5)).astype(np.uint8) for _ in range(20)]
    for close in (0, DP.FILL_CLOSE):
        ref = np.stack([DP.fill_enclosed(m.copy(), close=close) for m in masks])
        got = DP.fill_enclosed_torch(torch.from_numpy(np.stack(masks)).float()[:, None].to(GPU), close=close)
        assert got.device.type == "cuda"
        assert np.array_equal(ref, got[:, 0].cpu().numpy().astype(np.uint8)), close


@pytest.mark.parametrize("case", ["sphere", "gauss", "paraboloid"])
def test_the_poisson_solve_on_the_gpu_within_1_percent_of_analytic_surfaces(case):
    fn, peak = {"sphere": sphere_cap(150.3, 120.6, R_BALL_PX, 28.0), "gauss": gaussian(160.2, 119.7, 10.0, 15.0),
                "paraboloid": paraboloid(170.4, 100.1, 0.01, 30.0)}[case]
    gx, gy = _sampled(fn, 4)
    for dtype in (torch.float64, torch.float32):
        z = P.integrate_torch(torch.tensor(gx, dtype=dtype, device=GPU), torch.tensor(gy, dtype=dtype, device=GPU))
        assert z.device.type == "cuda"
        assert abs(float(z.max()) / peak - 1) <= 0.01, dtype
    assert np.allclose(P.integrate_torch(torch.tensor(gx, device=GPU), torch.tensor(gy, device=GPU)).cpu().numpy(),
                       P.integrate(gx, gy), atol=1e-8)


def test_bad_normals_on_the_gpu_raise_the_cpus_error_and_a_batch_marks_only_that_frame(model, frames):
    gpu = DepthPipeline(model, device=GPU)
    gpu.net = _BadNormals(gpu.net, math.nan)   # non-finite normals on rows 10-11, columns 20-21
    with pytest.raises(ValueError, match=r"gx: \d+ gradients are NaN or inf \(the first at row 10, column 20\)"):
        gpu.grid_depth(frames[0])
    z = gpu.batch_depth(np.stack(frames[:2]))
    assert torch.isnan(z).all()                              # every frame runs the broken network
    good = DepthPipeline(model, device=GPU)
    gx = torch.zeros(2, 40, 30, device=GPU)
    gy = torch.zeros(2, 40, 30, device=GPU)
    gx[1, 5, 5] = math.inf
    gx[0, 20:24, 14:18] = 0.01
    zz = P.integrate_torch(gx, gy)
    assert torch.isfinite(zz[0]).all() and torch.isnan(zz[1]).all()
    assert good.batch_depth(np.stack(frames[:1])).isfinite().all()


def test_the_depth_node_on_the_gpu(frames):
    with Harness(DepthEstimator, {"model": "sim-digit-qvga", "device": GPU}) as g, \
            Harness(DepthEstimator, {"model": "sim-digit-qvga", "mode": "dense"}) as c:
        assert g.comp.pipe.device.type == "cuda"
        for k, fr in enumerate(frames):
            a = g.step(0.1 * (k + 1), image=Sample(fr, 0.1 * (k + 1) - 0.02))
            b = c.step(0.1 * (k + 1), image=Sample(fr, 0.1 * (k + 1) - 0.02))
            assert g.samples["max_depth"].stamp == pytest.approx(0.1 * (k + 1) - 0.02)   # the capture time
            assert a["max_depth"] == pytest.approx(b["max_depth"], abs=ATOL_M)
            assert np.abs(a["depth"] - b["depth"]).max() < ATOL_M
            assert a["contact_area"] == pytest.approx(b["contact_area"], rel=1e-6, abs=1e-12)


def test_estimate_on_the_gpu(model, frames, tmp_path, capsys):
    import cv2

    from teletouch.cli import main

    paths = []
    for k, fr in enumerate(frames[:3]):
        paths.append(str(tmp_path / f"press{k}.png"))
        cv2.imwrite(paths[-1], fr)
    rows = {}
    for device in ("cpu", GPU):
        assert main(["estimate", "--model", "sim-digit-qvga", "--device", device, "--json", *paths]) == 0
        rows[device] = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(rows[GPU]) == 3
    dense = DepthPipeline(model, mode="dense")
    for fr, g, c in zip(frames, rows[GPU], rows["cpu"]):
        assert g["max_depth_m"] == pytest.approx(dense(fr).max_depth, abs=ATOL_M)
        assert g["max_depth_m"] == pytest.approx(c["max_depth_m"], rel=0.03)
