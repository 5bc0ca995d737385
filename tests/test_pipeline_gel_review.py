"""Review of the depth pipeline's two paths and the simulated gel: contacts at the image border, the background
buffer, the force law and the gel surface under tilt, at the border, at zero indentation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from teletouch.plugins.estimators.depth_pipeline import DepthPipeline, contact_summary
from teletouch.plugins.sensors import gel

from helpers_depth import model_fixture, sim_fixture


model = model_fixture()
sim = sim_fixture()


# --- the sparse path against the dense (whole-grid) reference --------------------------------------------------------

#: presses whose contact is cut by the image border (a 6 mm ball at 9.2 mm from the centre along the rows is within a
#: few pixels of the top or bottom row; at 3.4 mm along the columns, of the left or right column)
BORDER = [(0.0, 9.2e-3), (0.0, -9.2e-3), (3.45e-3, 9.25e-3), (-3.4e-3, -9.2e-3)]


@pytest.mark.parametrize("pos", BORDER)
@pytest.mark.parametrize("d", [0.3e-3, 1.0e-3])
def test_sparse_and_dense_paths_agree_on_a_contact_cut_by_the_image_border(model, sim, pos, d):
    """The sparse path solved the Poisson equation on the contact's window (z = 0 around it), exact only where the
    whole-grid solution is zero around the window. A contact cut by the image border is not: the grid's own zero
    boundary runs through it, and the solve's residual spreads along the border, so the window read 12-28% off the
    dense path's max depth here (40% at stride 7), against the documented 1-2%."""
    img, _ = sim.render(d, pos)
    a = DepthPipeline(model, mode="sparse")(img)
    b = DepthPipeline(model, mode="dense")(img)
    assert b.max_depth > 0.02e-3
    assert a.max_depth == pytest.approx(b.max_depth, rel=0.02)
    assert np.abs(a.depth - b.depth).max() < 0.02 * b.max_depth
    assert a.contact_area == pytest.approx(b.contact_area, rel=0.03)
    np.testing.assert_allclose(a.centroid, b.centroid, atol=0.05e-3)


@pytest.mark.parametrize("stride", [3, 7])
def test_border_contact_agrees_with_strides_that_do_not_divide_the_image(model, sim, stride):
    """320 x 240 in blocks of 3 or 7 pixels leaves rows (and columns) over at the bottom and right."""
    m = dataclasses.replace(model, stride=stride)
    for pos in [(3.45e-3, 9.25e-3), (0.0, 0.0)]:
        img, _ = sim.render(1.0e-3, pos)
        a = DepthPipeline(m, mode="sparse")(img)
        b = DepthPipeline(m, mode="dense")(img)
        assert a.depth.shape == b.depth.shape == (320, 240)
        assert a.max_depth == pytest.approx(b.max_depth, rel=0.02)


@pytest.mark.parametrize("pos", BORDER[:2])
def test_a_border_contacts_outputs_from_the_window_equal_the_whole_frame(model, sim, pos):
    """The whole-grid solve leaves the outputs' window as it was: upsampling and summing it alone gives the same
    outputs as the whole frame."""
    img, _ = sim.render(1.0e-3, pos)
    pipe = DepthPipeline(model)
    res = pipe(img)
    zg, w = pipe._grid_depth(img)
    assert w is not None and w != (0, pipe.grows, 0, pipe.gcols)   # the window, not the whole grid
    full = pipe.upsample(zg)
    mask, area, centroid = contact_summary(full, 1.0 / model.px_per_m, pipe.contact_depth, pipe.contact_fraction)
    assert np.array_equal(res.depth, full)
    assert np.array_equal(res.contact_mask, mask) and res.contact_area == area
    np.testing.assert_allclose(res.centroid, centroid, rtol=0, atol=1e-12)


def test_plane_baseline_agrees_on_a_border_contact(model, sim):
    img, _ = sim.render(1.0e-3, (0.0, 9.2e-3))
    a = DepthPipeline(model, mode="sparse", baseline="plane")(img)
    b = DepthPipeline(model, mode="dense", baseline="plane")(img)
    assert b.max_depth > 0.02e-3
    assert a.max_depth == pytest.approx(b.max_depth, rel=0.02)


# --- the background buffer -------------------------------------------------------------------------------------------

def test_the_background_is_copied_not_kept_as_a_view_of_the_callers_array(model, sim):
    """set_background(bg) with a float32 background at stride 1: the dense path kept a view of the caller's array
    (torch.as_tensor shares memory, .float() of a float tensor is itself), so writing into that array later (as the
    `depth` node's background adaptation does to its own) changed the background under the pipeline, while the
    sparse path had taken a copy."""
    m = dataclasses.replace(model, stride=1)
    img, _ = sim.render(0.8e-3, (0.0, 0.0))
    bg = model.background.astype(np.float32)
    pipe = DepthPipeline(m, mode="dense")
    pipe.set_background(bg)
    before = pipe(img).depth.copy()
    bg[40:80, 60:120] += 40.0   # the caller's array, after the call (a uniform change is drift: cancelled)
    after = pipe(img).depth
    assert before.max() > 0.1e-3
    np.testing.assert_array_equal(after, before)


# --- the gel -------------------------------------------------------------------------------------------------------

INDENTERS = {
    "sphere": gel.Indenter.sphere(0.003),
    "probe": gel.Indenter.probe(0.005, 0.010),
    "flat": gel.Indenter.flat(0.002),
    "map": gel.Indenter.from_height_map(
        np.add.outer(np.linspace(-1, 1, 41) ** 2, np.linspace(-1, 1, 41) ** 2) * 1e-3, 0.1e-3),
}


@pytest.mark.parametrize("name", list(INDENTERS))
@pytest.mark.parametrize("tilt", [0.0, 0.05, -0.2])
@pytest.mark.parametrize("thickness", [None, 0.004])
def test_force_is_zero_at_and_below_zero_and_increases_with_indentation(name, tilt, thickness):
    ind = INDENTERS[name]
    ds = np.linspace(0.0, 3e-3, 121)
    f = np.array([gel.gel_force(d, ind, thickness=thickness, tilt_rad=tilt) for d in ds])
    law = gel.force_law(ind, thickness=thickness, tilt_rad=tilt)
    assert np.array_equal(f, [law(d) for d in ds])
    assert f[0] == 0.0 and gel.gel_force(-1e-3, ind, tilt_rad=tilt) == 0.0 and law(-1e-3) == 0.0
    assert (np.diff(f) > 0).all()


def test_force_units_hertz_in_newtons():
    # 4/3 E* sqrt(R) d^1.5, E* = 0.41 MPa / 0.75: a 5 mm sphere at 1.25 mm is ~2.3 N (the module's figure)
    f = gel.gel_force(1.25e-3, gel.Indenter.sphere(0.005))
    assert f == pytest.approx(4 / 3 * gel.DEFAULT_MODULUS / 0.75 * 0.005 ** 0.5 * 1.25e-3 ** 1.5)
    assert 2.2 < f < 2.4


@pytest.mark.parametrize("name", ["probe", "flat"])
def test_tilt_moves_the_deepest_point_towards_plus_x_and_mirrors(name):
    ind = INDENTERS[name]
    m = gel.QVGA_M_PER_PX
    pos = gel.gel_surface(ind, 1e-3, (0.0, 0.0), 0.2, (400, 400), m).depth
    neg = gel.gel_surface(ind, 1e-3, (0.0, 0.0), -0.2, (400, 400), m).depth
    r, c = np.unravel_index(np.argmax(pos), pos.shape)
    assert c - 199.5 > 20                       # ~2 mm towards +x at 0.2 rad
    np.testing.assert_array_equal(neg, pos[:, ::-1])


@pytest.mark.parametrize("name", list(INDENTERS))
@pytest.mark.parametrize("tilt", [0.0, 0.2])
def test_an_indenter_at_the_image_border_is_the_same_surface_cut(name, tilt):
    """The surface near the border is the one of a larger image, cut (the general shapes find their contact patch
    on the whole window, also off the image); and the same call gives the same surface."""
    ind = INDENTERS[name]
    m = gel.QVGA_M_PER_PX
    big = gel.gel_surface(ind, 1e-3, (0.0, 0.0), tilt, (800, 800), m).depth          # axis at (399.5, 399.5)
    pos = (-119.0 * m, -159.0 * m)                                                     # axis at (0.5, 0.5)
    cut = gel.gel_surface(ind, 1e-3, pos, tilt, (320, 240), m)
    np.testing.assert_array_equal(cut.depth, big[399:399 + 320, 399:399 + 240])
    assert cut.depth.max() > 0.9e-3
    np.testing.assert_array_equal(gel.gel_surface(ind, 1e-3, pos, tilt, (320, 240), m).depth, cut.depth)


@pytest.mark.parametrize("d", [0.0, -1e-3])
def test_zero_or_negative_indentation_leaves_the_gel_flat(d):
    for ind in INDENTERS.values():
        s = gel.gel_surface(ind, d, (0.0, 0.0), 0.1)
        assert not s.depth.any() and not s.mask.any()
        assert gel.support_radius(ind, d) == 0.0 and gel.contact_radius(d, ind) == 0.0
    with pytest.raises(ValueError, match="indentation"):
        gel.gel_surface(INDENTERS["sphere"], float("nan"))
    with pytest.raises(ValueError, match="indentation"):
        gel.gel_force(float("inf"), INDENTERS["sphere"])


@pytest.mark.parametrize("mode", ["sparse", "dense"])
def test_set_background_mid_run_reads_as_a_pipeline_built_with_it(model, sim, mode):
    img, _ = sim.render(0.8e-3, (0.0, 9.2e-3))
    other = np.clip(model.background.astype(np.int16) + 6, 0, 255).astype(np.uint8)
    other[10:30, 10:30] = model.background[10:30, 10:30]
    pipe = DepthPipeline(model, mode=mode)
    first = pipe(img)
    pipe.set_background(other)
    got = pipe(img)
    want = DepthPipeline(model, mode=mode, background=other)(img)
    np.testing.assert_array_equal(got.depth, want.depth)
    np.testing.assert_array_equal(got.offset, want.offset)
    assert not np.array_equal(got.offset, first.offset)   # the background did change
    assert first.depth.max() > 0.1e-3 and not np.shares_memory(first.depth, got.depth)
