"""The `depth` estimator on simulated DIGIT frames with ground truth (packaged model sim-digit-qvga)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from teletouch import ComponentFault, ModelFileError
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.estimators.depth_pipeline import DepthPipeline
from teletouch.plugins.sensors import gel
from teletouch.plugins.sensors.sim_digit import DigitSimulator
from teletouch.testing import Harness, make_registry, run_yaml

from helpers_depth import model_fixture, sim_fixture


model = model_fixture()
sim = sim_fixture()   # another seed than the one the packaged model was trained with


@pytest.mark.parametrize("pos,d", [((0.0, 0.0), 0.8e-3), ((-2.5e-3, -4e-3), 0.5e-3), ((2.5e-3, 3.5e-3), 1.0e-3)])
def test_ball_press_depth_against_ground_truth(model, sim, pos, d):
    pipe = DepthPipeline(model)
    img, surf = sim.render(d, pos, 0.0)
    res = pipe(img)
    gt = surf.depth
    assert res.depth.dtype == np.float32 and res.depth.shape == (320, 240)
    assert res.max_depth == pytest.approx(float(gt.max()), rel=0.3)
    # the deepest point is where the ball is (within a third of the contact radius: the cap's top is nearly flat,
    # so its argmax moves with the pixel noise)
    r, c = np.unravel_index(np.argmax(res.depth), res.depth.shape)
    m = model.m_per_px
    a = gel.contact_radius(d, gel.Indenter.sphere(0.003))
    assert math.hypot((c - 119.5) * m - pos[0], (r - 159.5) * m - pos[1]) < max(0.4e-3, a / 3)
    assert np.allclose(res.centroid, pos, atol=0.3e-3)
    # contact area of the same order as the true one (Hertz contact radius sqrt(R d))
    assert 0.3 * math.pi * a * a < res.contact_area < 3.0 * math.pi * a * a
    # no depth far from the contact
    rr, cc = np.mgrid[0:320, 0:240]
    far = np.hypot((cc - 119.5) * m - pos[0], (rr - 159.5) * m - pos[1]) > 4 * a
    assert np.abs(res.depth[far]).max() < 0.03e-3


def test_no_contact_gives_no_depth_under_noise_and_drift(model):
    s = DigitSimulator("qvga", noise=2.0, drift=4.0, drift_period=2.0, seed=5)
    pipe = DepthPipeline(model)
    for t in np.linspace(0, 2, 5):
        res = pipe(s.render(0.0, t=float(t))[0])
        assert res.max_depth < 0.02e-3
        assert res.contact_area == 0.0 and not res.contact_mask.any()
        assert np.isnan(res.centroid).all()
        # a zero grid takes a short cut: the same types and shapes as a frame with depth
        assert res.depth.dtype == np.float32 and res.depth.shape == (320, 240) and not res.depth.any()
        assert res.contact_mask.dtype == bool and res.contact_mask.shape == (320, 240)
        assert res.centroid.shape == (2,)


def test_deeper_press_reads_deeper(model, sim):
    pipe = DepthPipeline(model)
    depths = [pipe(sim.render(d, (0.001, 0.0))[0]).max_depth for d in (0.3e-3, 0.6e-3, 0.9e-3, 1.2e-3)]
    assert all(b > a for a, b in zip(depths, depths[1:]))


def test_sparse_and_dense_paths_agree(model, sim):
    img, _ = sim.render(0.7e-3, (0.0, 0.001))
    a = DepthPipeline(model, mode="sparse")(img)
    b = DepthPipeline(model, mode="dense")(img)
    assert a.max_depth == pytest.approx(b.max_depth, rel=0.03)
    assert np.abs(a.depth - b.depth).max() < 0.05 * b.max_depth
    z = DepthPipeline(model, mode="dense").batch_depth(np.stack([img, img])).numpy()
    assert z.shape == (2, 320, 240)
    assert np.abs(z[0] - b.depth).max() < 1e-6 + 0.02 * b.max_depth


def test_net_rim_runs_the_network_on_a_wider_rim_on_both_paths(model, sim):
    img, _ = sim.render(0.7e-3, (0.0, 0.001))
    cells = {}
    for rim in (0, 1):
        p = DepthPipeline(model, net_rim=rim)
        seen = []
        real = p._fast_mlp
        p._fast_mlp = lambda x, real=real, seen=seen: seen.append(x.shape[1]) or real(x)
        cells[rim] = (p(img), seen[0])
        dense = DepthPipeline(model, mode="dense", net_rim=rim)(img)
        assert cells[rim][0].max_depth == pytest.approx(dense.max_depth, rel=0.03)
    (a, na), (b, nb) = cells[0], cells[1]
    assert nb > na * 1.02                                    # one more ring of cells through the network
    assert b.max_depth == pytest.approx(a.max_depth, rel=0.05) and not np.array_equal(a.depth, b.depth)
    with Harness(DepthEstimator, {}) as h:
        assert h.comp.pipe.net_rim == 1                     # the default
    with Harness(DepthEstimator, {"net_rim": 0}) as h:
        assert h.comp.pipe.net_rim == 0


def test_plane_baseline_zero_reference(model, sim):
    """baseline="plane": the solved depth just outside the kept region is fitted by a plane and subtracted; both
    paths agree, no contact stays exactly zero, it reads about as deep or shallower and still orders presses."""
    img, _ = sim.render(0.7e-3, (0.5e-3, -1e-3))
    none = DepthPipeline(model, mode="sparse")
    plane = DepthPipeline(model, mode="sparse", baseline="plane")
    a = plane(img)
    b = DepthPipeline(model, mode="dense", baseline="plane")(img)
    assert a.max_depth == pytest.approx(b.max_depth, rel=0.03)
    zb = DepthPipeline(model, mode="dense", baseline="plane").batch_depth(np.stack([img, model.background])).numpy()
    assert np.abs(zb[0] - b.depth).max() < 1e-6 + 0.02 * b.max_depth and zb[1].max() == 0.0
    assert plane(model.background).max_depth == 0.0
    zn, zp = none.grid_depth(img), plane.grid_depth(img)
    assert 0.6 * zn.max() < zp.max() < 1.02 * zn.max()
    depths = [plane(sim.render(d, (0.001, 0.0))[0]).max_depth for d in (0.3e-3, 0.6e-3, 0.9e-3)]
    assert depths[0] < depths[1] < depths[2]
    with pytest.raises(ValueError, match="baseline"):
        DepthPipeline(model, baseline="cone")


def test_component_ports_stamps_and_errors(sim, monkeypatch):
    img, surf = sim.render(0.8e-3, (0.0, 0.0))
    with Harness(DepthEstimator, {"model": "sim-digit-qvga"}) as h:
        from teletouch import Sample

        out = h.step(0.5, image=Sample(img, 0.48))
        raw = h.comp.step(0.5, h.inputs)
        assert raw["max_depth"].stamp == 0.48   # the capture time of the image
        assert out["depth"].dtype == np.float32 and out["depth"].shape == (320, 240)
        assert out["contact_mask"].dtype == bool
        assert out["centroid"].dtype == np.float64 and out["centroid"].shape == (2,)
        assert isinstance(out["max_depth"], float) and out["max_depth"] > 0.3e-3
        assert out["contact_area"] > 0
        assert h.comp.status()["max_depth_m"] == pytest.approx(out["max_depth"])
        with pytest.raises(ComponentFault, match="expected a uint8 BGR image of 320x240x3"):
            h.step(0.6, image=np.zeros((640, 480, 3), np.uint8))
    with pytest.raises(ValueError, match="no such model file"):   # refused with the params (a graph's validation)
        Harness(DepthEstimator, {"model": "/nonexistent/x.model"}).comp.configure()
    # a machine without a CUDA GPU (torch says so, here on every machine; a GPU machine raised the error itself)
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ComponentFault, match=r"device 'cuda': torch sees no CUDA GPU here; use device: cpu"):
        Harness(DepthEstimator, {"device": "cuda"}).comp.configure()


def test_an_identical_frame_reuses_the_result_and_a_changed_one_does_not(sim):
    img, _ = sim.render(0.8e-3, (0.0, 0.0))
    with Harness(DepthEstimator, {"model": "sim-digit-qvga"}) as h:
        from teletouch import Sample

        calls = []
        real = h.comp.pipe.__call__
        h.comp.pipe = type("Counting", (), {"__call__": lambda self, f: calls.append(1) or real(f),
                                            "check_frame": h.comp.pipe.check_frame})()
        h.set(image=Sample(img, 0.48))
        a = h.comp.step(0.5, h.inputs)
        h.set(image=Sample(img.copy(), 0.58))
        b = h.comp.step(0.6, h.inputs)
        assert len(calls) == 1 and h.comp.reused == 1
        assert b["max_depth"].value == a["max_depth"].value > 0.3e-3
        assert b["max_depth"].stamp == 0.58 and b["depth"].stamp == 0.58   # the new frame's time
        changed = img.copy()
        changed[-1, -1, 2] ^= 1          # one bit in the last byte: not the same frame
        h.step(0.7, image=changed)
        assert len(calls) == 2
        img[...] = 0                     # the caller reusing its buffer does not alter what is remembered
        h.step(0.8, image=changed)
        assert len(calls) == 2 and h.comp.reused == 2
    with Harness(DepthEstimator, {"model": "sim-digit-qvga", "reuse_unchanged": False}) as h:
        h.step(0.5, image=changed)
        h.step(0.6, image=changed)
        assert h.comp.reused == 0


def test_background_adaptation_follows_illumination_drift(model):
    bg = model.background.astype(np.int16)
    # a strong local illumination change (not global: the median drift correction would remove that)
    frame = bg.copy()
    frame[100:160, 60:120] += 25
    frame = np.clip(frame, 0, 255).astype(np.uint8)
    with Harness(DepthEstimator, {"adapt_background": 0.0, "change_threshold": 200.0}) as h:
        h.step(0.0, image=frame)
        assert np.array_equal(h.comp.pipe._bg_grid_np, DepthPipeline(model)._bg_grid_np)
    with Harness(DepthEstimator, {"adapt_background": 0.5, "change_threshold": 200.0}) as h:
        for k in range(12):
            h.step(k * 0.02, image=frame)
        # the background has moved onto the new illumination: a normal threshold now sees no change there
        h.comp.pipe.change_threshold = model.change_threshold
        out = h.step(1.0, image=frame)
        assert out["max_depth"] == 0.0


def test_in_a_graph_with_sim_digit():
    text = """
name: depth-sim
clock: sim
nodes:
  - id: digit
    plugin: sim-digit
    rate: 30
    params: {indentation: 0.8mm, noise: 2}
  - id: depth
    plugin: depth
    rate: 30
    inputs: {image: digit.image}
"""
    rows = []
    reg = make_registry("teletouch.plugins.sensors.sim_digit", "teletouch.plugins.estimators.depth")
    res, rt = run_yaml(text, reg, duration=0.2,
                       taps=[lambda n, t, o: rows.append((n, t, o)) if n == "depth" else None])
    assert res.status == "ok", res.message
    md = [o["max_depth"] for n, t, o in rows if "max_depth" in o]
    md = [v.value if hasattr(v, "value") else v for v in md]
    assert len(md) >= 5
    assert all(0.5e-3 < v < 1.1e-3 for v in md)


def test_contact_summary_is_the_depth_weighted_centre_of_the_contact():
    from teletouch.plugins.estimators.depth_pipeline import contact_summary

    rng = np.random.default_rng(0)
    rr, cc = np.mgrid[0:320, 0:240]
    z = (np.maximum(0.0, 1e-3 - ((rr - 100.3) ** 2 + (cc - 170.7) ** 2) * 1e-6)
         + rng.random((320, 240)) * 1e-6).astype(np.float32)
    mask, area, centroid = contact_summary(z, 5.8e-5, 3e-5, 0.5)
    assert np.array_equal(mask, z > 0.5 * z.max())
    rows, cols = np.nonzero(mask)
    w = z[rows, cols].astype(np.float64)
    expected = np.array([(cols * w).sum() / w.sum() - 119.5, (rows * w).sum() / w.sum() - 159.5]) * 5.8e-5
    np.testing.assert_allclose(centroid, expected, rtol=1e-9)
    assert area == pytest.approx(mask.sum() * 5.8e-5 ** 2)
    m0, a0, c0 = contact_summary(np.zeros((10, 10), np.float32), 1e-4, 3e-5)
    assert not m0.any() and a0 == 0.0 and np.isnan(c0).all()
    # a window of the image: the same mask (inside it), area and centroid as the whole image
    zw = np.zeros_like(z)
    zw[60:150, 120:220] = z[60:150, 120:220]
    mw, aw, cw = contact_summary(zw[60:150, 120:220], 5.8e-5, 3e-5, 0.5, origin=(60, 120), shape=(320, 240))
    mf, af, cf = contact_summary(zw, 5.8e-5, 3e-5, 0.5)
    assert np.array_equal(mw, mf[60:150, 120:220]) and not mf[:60].any() and aw == af
    np.testing.assert_allclose(cw, cf, rtol=1e-9)


@pytest.mark.parametrize("pos", [(0.0, 0.0), (-3.2e-3, -7.5e-3), (3.0e-3, 7.4e-3), (-3.4e-3, 0.0)])
@pytest.mark.parametrize("indenter", ["sphere", "probe"])
def test_outputs_from_the_solve_window_equal_the_whole_frame(model, pos, indenter):
    """The sparse path computes the full-size outputs on its solve window only; they must equal upsampling and
    summing the whole grid (presses at the centre and near the edges, where the window meets the grid border)."""
    from teletouch.plugins.estimators.depth_pipeline import contact_summary

    ind = gel.Indenter.sphere(0.003) if indenter == "sphere" else gel.Indenter.probe(0.005, 0.010)
    img, _ = DigitSimulator("qvga", indenter=ind, noise=2.0, seed=11).render(0.8e-3, pos, 0.0)
    pipe = DepthPipeline(model)
    res = pipe(img)
    zg = pipe.grid_depth(img)
    full = pipe.upsample(zg)
    mask, area, centroid = contact_summary(full, 1.0 / model.px_per_m, pipe.contact_depth, pipe.contact_fraction)
    assert res.max_depth > 0.1e-3
    assert np.array_equal(res.depth, full)
    assert np.array_equal(res.contact_mask, mask) and res.contact_area == area
    np.testing.assert_allclose(res.centroid, centroid, rtol=0, atol=1e-12)
    assert pipe._window_outputs and pipe._grid_depth(img)[1] is not None   # the window path was taken


# ------------------------------------------------------------------------------------------- run-time robustness
def _led_dim(bg: np.ndarray, channel: int, gain: float) -> np.ndarray:
    f = bg.astype(np.float32)
    f[..., channel] *= gain
    return np.clip(f, 0, 255).astype(np.uint8)


def test_implausible_frames_give_nan_outputs_not_a_deep_contact(model, sim):
    """LEDs off, a saturated frame or one LED mid-change read as a deep, wide contact (2.7 mm, 67 mm^2 for a black
    frame before): now NaN outputs with the frame's stamp (poly-force: invalid input, 0 N), never blended into the
    background, and the next good frame reads as usual."""
    from teletouch import Sample

    good, _ = sim.render(0.6e-3, (0.001, 0.0), 0.0)
    with Harness(DepthEstimator, {}) as h:
        ref = h.step(0.0, image=good)["max_depth"]
    bad = {"black": np.zeros((320, 240, 3), np.uint8), "saturated": np.full((320, 240, 3), 255, np.uint8),
           "red LED at 60%": _led_dim(model.background, 2, 0.6), "half brightness": model.background // 2}
    with Harness(DepthEstimator, {"adapt_background": 0.5}) as h:
        bg0 = h.comp.pipe._bg_grid_np.copy()
        for k, (what, frame) in enumerate(bad.items()):
            h.set(image=Sample(frame, 0.1 + k))
            raw = h.comp.step(0.2 + k, h.inputs)
            assert all(v.stamp == 0.1 + k for v in raw.values()), what
            out = {n: v.value for n, v in raw.items()}
            assert math.isnan(out["max_depth"]) and math.isnan(out["contact_area"]), (what, out["max_depth"])
            assert np.isnan(out["centroid"]).all() and np.isnan(out["depth"]).all(), what
            assert out["depth"].shape == (320, 240) and out["depth"].dtype == np.float32
            assert not out["contact_mask"].any() and out["contact_mask"].shape == (320, 240)
            assert "global colour change" in h.comp.last_problem
        assert h.comp.bad_frames == 4 and h.comp.status()["bad_frames"] == 4
        assert np.array_equal(h.comp.pipe._bg_grid_np, bg0)           # none of them was blended in
        assert h.step(9.0, image=good)["max_depth"] == ref
    # the force node reads NaN as invalid input: no force (the controller takes the estimate as lost), not a force
    # from a phantom contact
    from teletouch.plugins.estimators.poly_force import PolyForce

    with Harness(PolyForce, {}) as f:
        out = f.step(1.0, max_depth=math.nan, contact_area=math.nan, centroid=np.array([math.nan, math.nan]))
        assert out == {"status": "invalid-input"}


def test_a_sensor_that_keeps_delivering_implausible_frames_faults(model):
    black = np.zeros((320, 240, 3), np.uint8)
    with Harness(DepthEstimator, {"fault_after_bad": 3}) as h:
        h.step(0.0, image=black)
        h.step(0.1, image=black)
        h.step(0.2, image=model.background)              # a good frame in between starts the count again
        h.step(0.3, image=black)
        h.step(0.4, image=black)
        with pytest.raises(ComponentFault, match=r"3 implausible frames in a row.*LEDs off"):
            h.step(0.5, image=black)
    with Harness(DepthEstimator, {"fault_after_bad": 0}) as h:
        for k in range(40):
            assert math.isnan(h.step(k * 0.1, image=black)["max_depth"])


def test_background_adaptation_does_not_absorb_a_slow_press(sim):
    """A press that builds up slowly stays below the change threshold from frame to frame against a background that
    follows it: before, a 0.6 mm press over one second read 0.0 mm with adapt_background 0.5 (and 12% low with 0.05),
    and a light touch (no contact yet: below contact_depth) held for half a second took 10% off the press after it."""
    final, _ = sim.render(0.6e-3, (0.001, 0.0), 0.0)
    with Harness(DepthEstimator, {}) as h:
        fresh = h.step(0.0, image=final)["max_depth"]
    assert fresh > 0.4e-3
    for a in (0.05, 0.5):
        with Harness(DepthEstimator, {"adapt_background": a}) as h:
            for k in range(61):
                out = h.step(k / 60, image=sim.render(0.6e-3 * k / 60, (0.001, 0.0), 0.0)[0])
            assert out["max_depth"] == pytest.approx(fresh, rel=0.05), a
            # released: what was absorbed leaves no imprint that reads as a contact
            for k in range(10):
                out = h.step(2 + k / 60, image=sim.render(0.0, (0.001, 0.0), 0.0)[0])
            assert out["max_depth"] == 0.0
        with Harness(DepthEstimator, {"adapt_background": a}) as h:
            for k in range(30):
                out = h.step(k / 60, image=sim.render(0.05e-3, (0.001, 0.0), 0.0)[0])
            assert out["contact_area"] == 0.0          # a light touch: no contact yet
            assert h.step(1.0, image=final)["max_depth"] == pytest.approx(fresh, rel=0.03), a


def test_background_adaptation_is_bounded(model):
    """The adapted background keeps within adapt_limit levels per channel of the configured one (apart from a
    global offset): a local change it cannot tell from drift moves it that far and no further."""
    frame = model.background.astype(np.int16)
    frame[100:160, 60:120] += 25
    frame = np.clip(frame, 0, 255).astype(np.uint8)
    with Harness(DepthEstimator, {"adapt_background": 0.5, "change_threshold": 200.0, "adapt_limit": 6.0}) as h:
        for k in range(20):
            h.step(k * 0.02, image=frame)
        dev = h.comp._bg - model.background.astype(np.float32)
        assert np.abs(dev).max() <= 6.0 + 1e-4 and dev[100:160, 60:120].min() >= 6.0 - 1e-4
    with Harness(DepthEstimator, {"adapt_background": 0.5}) as h:
        assert h.comp._adapt_limit == pytest.approx(h.comp.pipe.change_threshold / 3)


def test_activate_starts_over_with_the_configured_background_and_no_remembered_frame(model):
    frame = model.background.astype(np.int16)
    frame[100:160, 60:120] += 25
    frame = np.clip(frame, 0, 255).astype(np.uint8)
    bg0 = DepthPipeline(model)._bg_grid_np
    with Harness(DepthEstimator, {"adapt_background": 0.5, "change_threshold": 200.0}) as h:
        for k in range(5):
            h.step(k * 0.02, image=frame)
        assert not np.array_equal(h.comp.pipe._bg_grid_np, bg0)
        h.comp.deactivate()
        h.comp.activate()
        assert np.array_equal(h.comp.pipe._bg_grid_np, bg0)
    with Harness(DepthEstimator, {}) as h:
        h.step(0.0, image=frame)
        h.comp.deactivate()
        h.comp.activate()
        h.step(1.0, image=frame)
        assert h.comp.reused == 0        # computed again after activate, not answered from before


@pytest.mark.parametrize("params", [{"adapt_background": 0.02}, {"reuse_unchanged": False}],
                         ids=["adapt_background", "no-reuse"])
def test_a_frozen_camera_on_untouched_gel_faults_whatever_the_reuse(sim, params):
    """The repeats were counted only against a frame kept for reuse: with adapt_background on untouched gel (the
    setting a real camera's drift asks for) or reuse_unchanged off, a camera frozen on an untouched frame went on as
    "no contact", freshly stamped, and never faulted (repeated_frames stayed 0)."""
    from teletouch import Sample

    frame, _ = sim.render(0.0, (0.0, 0.0), 0.0)
    with Harness(DepthEstimator, {"fault_after_repeats": 5, "warm": False, **params}) as h:
        for k in range(5):
            h.step(k / 60, image=Sample(frame.copy(), k / 60))
        assert h.comp.status()["repeated_frames"] == 4   # before: 0
        with pytest.raises(ComponentFault, match="5 bit-identical frames in a row.*frozen"):
            h.step(5 / 60, image=Sample(frame.copy(), 5 / 60))


def test_a_frozen_camera_is_counted_and_can_fault(sim):
    """Bit-identical frames with new stamps (a frozen camera; a real camera's noise never repeats) are answered from
    the last result, stamped with the new time, counted in status; fault_after_repeats faults the node. The same
    sample read again (no new frame: the same stamp) is not a repeat."""
    from teletouch import Sample

    img, _ = sim.render(0.5e-3, (0.0, 0.0), 0.0)
    with Harness(DepthEstimator, {"fault_after_repeats": 3}) as h:
        h.set(image=Sample(img, 0.0))
        h.comp.step(0.0, h.inputs)
        h.comp.step(0.01, h.inputs)                  # the same sample again: not a new frame
        assert h.comp.status()["repeated_frames"] == 0
        for k in (1, 2):
            h.set(image=Sample(img.copy(), k * 0.1))
            out = h.comp.step(k * 0.1, h.inputs)
            assert out["max_depth"].stamp == k * 0.1 and h.comp.status()["repeated_frames"] == k
        h.set(image=Sample(img.copy(), 0.3))
        with pytest.raises(ComponentFault, match="3 bit-identical frames in a row.*frozen"):
            h.comp.step(0.3, h.inputs)
    with Harness(DepthEstimator, {}) as h:           # default: never (a simulated sensor without noise repeats)
        for k in range(50):
            h.step(k * 0.1, image=img)
        assert h.comp.reused == 49 and h.comp.status()["repeated_frames"] == 49


def test_a_frame_of_another_size_or_dtype_mid_run_faults(sim):
    img, _ = sim.render(0.5e-3, (0.0, 0.0), 0.0)
    with Harness(DepthEstimator, {}) as h:
        h.step(0.0, image=img)
        for bad in (img.astype(np.float32) / 255, np.full((320, 240, 3), np.nan, np.float32),
                    img[:, :, :1], img[:-2], img.astype(np.uint16)):
            with pytest.raises(ComponentFault, match="expected a uint8 BGR image of 320x240x3"):
                h.step(0.1, image=bad)


def test_configuration_errors_name_the_parameter(tmp_path):
    with pytest.raises(ModelFileError, match=r"^background: .*bg.png: not a readable image file"):
        Harness(DepthEstimator, {"background": str(tmp_path / "bg.png")}).comp.configure()
    import cv2

    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ModelFileError, match=r"^background: .*small.png: background frame is 10x10"):
        Harness(DepthEstimator, {"background": str(tmp_path / "small.png")}).comp.configure()
    with pytest.raises(ValueError, match=r"model\n  Value error, .*x\.model: no such model file"):   # validation
        Harness(DepthEstimator, {"model": str(tmp_path / "x.model")})
    import shutil

    from teletouch.plugins.estimators.normal_model import packaged_model_path

    gone = shutil.copy(packaged_model_path("sim-digit-qvga"), tmp_path / "gone.model")
    h = Harness(DepthEstimator, {"model": str(gone)})
    Path(gone).unlink()   # removed after the graph was validated: configure names the parameter
    with pytest.raises(ModelFileError, match=r"^model: .*gone\.model: no such model file"):
        h.comp.configure()
    for field, value in (("adapt_background", 0.7), ("adapt_limit", 0.0), ("max_global_change", -1.0),
                         ("fault_after_bad", -1), ("fault_after_repeats", -1), ("contact_depth", "-1mm")):
        with pytest.raises(ValueError, match=field):
            DepthEstimator.Params(**{field: value})


def _other_unit_frame(shared_data, k: int = 0) -> np.ndarray:
    import cv2

    files = sorted((shared_data / "digit-backgrounds").iterdir())
    img = cv2.imread(str(files[k % len(files)]))
    return img if img.shape[:2] == (320, 240) else cv2.resize(np.ascontiguousarray(np.rot90(img)), (240, 320))


def test_another_sensors_frames_are_refused_at_start_not_read_as_contacts(shared_data):
    """A real DIGIT with the packaged (simulated sensor's) model, or another unit's model: its own colour pattern read
    as contacts of 0.1-2 mm and became a force from nothing. The first frames are now compared with the model's
    background (another unit's: 9-20 levels apart, a sensor's own frames: 1-2)."""
    import cv2
    from teletouch import Sample

    with Harness(DepthEstimator, {}) as h:
        with pytest.raises(ComponentFault, match=r"the camera's frames do not match the depth model's background: "
                                                 r"they differ by \d+\.\d levels .* made for another sensor .*"
                                                 r"Calibrate this sensor"):
            for k in range(10):
                h.step(k / 60, image=Sample(_other_unit_frame(shared_data, k), k / 60))
    presses = sorted((shared_data / "digit-presses-qvga").glob("*.png"))
    with Harness(DepthEstimator, {}) as h:   # the QVGA unit whose optics the simulated sensor reproduces: 1.1 levels
        for k, path in enumerate(presses):
            h.step(k / 60, image=Sample(cv2.imread(str(path)), k / 60))
        assert 0.8 <= h.comp.status()["background_mismatch"] <= 1.6
    with Harness(DepthEstimator, {"max_background_mismatch": 0}) as h:   # the check off: frames read as before
        for k in range(12):
            h.step(k / 60, image=Sample(_other_unit_frame(shared_data, k), k / 60))
        assert math.isnan(h.comp.status()["background_mismatch"])


def test_estimate_reports_another_sensors_frame_as_implausible(shared_data, capsys):
    import json

    from teletouch.cli import main

    other = sorted((shared_data / "digit-backgrounds").iterdir())[0]
    rc = main(["estimate", "--model", "sim-digit-qvga", str(shared_data / "digit-presses-qvga" / "0003.png"),
               str(other), "--json"])
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 2
    assert rows[0]["valid"] and 0.8 <= rows[0]["background_mismatch"] <= 1.6
    assert not rows[1]["valid"] and "the model (or --background) is another sensor's" in rows[1]["problem"]
    rc = main(["estimate", "--model", "sim-digit-qvga", str(other), "--json", "--max-background-mismatch", "0"])
    assert rc == 0 and json.loads(capsys.readouterr().out)["valid"]
