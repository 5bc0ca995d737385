"""Gel model open item: a tilted face is projected onto the gel plane exactly (the footprint of a spherical face keeps
its area under tilt), with heights from its true lowest point, also where the image shows only part of it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teletouch.plugins.sensors import gel

MPP = gel.QVGA_M_PER_PX
PROBE = gel.Indenter.probe(0.005, 0.010)


def sphere_map(R=0.003, cut=0.95, m=MPP / 2, n=221):
    """A user height map of a spherical cap (radius R, cut at cut * R from its axis)."""
    g = (np.arange(n) - (n - 1) / 2) * m
    X, Y = np.meshgrid(g, g)
    r2 = X ** 2 + Y ** 2
    return gel.Indenter.from_height_map(np.where(r2 < (cut * R) ** 2, R - np.sqrt(np.maximum(R * R - r2, 0)),
                                                 np.nan), m)


def sphere_footprint(R, s):
    """Geometric footprint (m^2) of a sphere of radius R cut by a plane s above its lowest point."""
    return math.pi * (2 * R * s - s * s)


def cap_limit(R, a, tilt):
    """Largest depth s whose footprint stays on the cap (radius a) of a sphere R tilted by ``tilt``."""
    r = a - R * abs(math.sin(tilt))
    return R - math.sqrt(R * R - r * r)


@pytest.mark.parametrize("tilt", [0.2, -0.3])
def test_a_tilted_probes_cap_keeps_its_footprint(tilt):
    """Before: the first-order projection h(x/c) c - x tan(tilt) narrowed the face by cos^2(tilt) along x: the
    probe's footprint was 4% small at 0.2 rad, 9% at -0.3 rad."""
    s_max = cap_limit(PROBE.tip_radius, PROBE.radius, tilt)
    for s in (0.5 * s_max, 0.9 * s_max):
        assert PROBE.contact_area(s, tilt) == pytest.approx(sphere_footprint(PROBE.tip_radius, s), rel=0.01)


@pytest.mark.parametrize("tilt", [0.2, -0.35, 0.6])
def test_a_tilted_height_map_of_a_sphere_keeps_its_footprint(tilt):
    """Before: 4.7% small at 0.2 rad, 14% at -0.35 rad, 39% at 0.6 rad."""
    ball = sphere_map()
    s_max = cap_limit(0.003, 0.95 * 0.003, tilt)
    for s in (0.3 * s_max, 0.9 * s_max):
        assert ball.contact_area(s, tilt) == pytest.approx(sphere_footprint(0.003, s), rel=0.01)


def test_the_contact_patch_and_force_of_a_tilted_probe_are_the_untilted_ones_on_its_cap():
    d, tilt = 0.0008, 0.2                        # the patch (face within d/2 of its lowest point) is on the cap
    assert d / 2 < cap_limit(PROBE.tip_radius, PROBE.radius, tilt)
    want = sphere_footprint(PROBE.tip_radius, d / 2) / MPP ** 2        # px
    surf = gel.gel_surface(PROBE, d, (0.0, 0.0), tilt, (320, 240), MPP)
    assert surf.mask.sum() == pytest.approx(want, rel=0.01)             # before: 3.8% small
    assert gel.gel_force(d, PROBE, tilt_rad=tilt) == pytest.approx(gel.gel_force(d, PROBE), rel=0.01)  # was -2.6%


@pytest.mark.parametrize("ind", [PROBE, gel.Indenter.flat(0.003), sphere_map()], ids=["probe", "flat", "map"])
def test_heights_are_from_the_faces_lowest_point_whatever_part_is_asked(ind):
    """Before: heights were taken from the lowest of the points asked for: half a face (an image edge) was lifted
    to touch the gel with its own lowest point."""
    tilt = 0.3
    g = np.linspace(-ind.tilted_extent(tilt), ind.tilted_extent(tilt), 201)
    X, Y = np.meshgrid(g, g)
    full = ind.surface_at(X, Y, tilt)
    assert np.nanmin(full) == pytest.approx(0.0, abs=math.tan(tilt) * (g[1] - g[0]))  # a sample from its rim
    left = X < -0.25 * ind.extent                                         # away from where it tilts to
    part = ind.surface_at(X[left], Y[left], tilt)
    assert np.array_equal(part, full[left]) and np.min(part) > 1e-4


def test_a_tilted_probe_at_the_image_edge_has_the_depth_of_the_same_pose_on_a_wider_image():
    """Before: with its lowest point off the image, the visible rest of a tilted probe reached the full indentation
    (0.8 mm where the pose gives 0.39 mm), and the sag was centred on the visible part of the patch."""
    d, x_edge = 0.0008, 119 * MPP
    edge = gel.gel_surface(PROBE, d, (x_edge, 0.0), 0.3, (320, 240), MPP)
    wide = gel.gel_surface(PROBE, d, (x_edge - 120 * MPP, 0.0), 0.3, (320, 480), MPP)
    assert np.array_equal(edge.depth, wide.depth[:, :240]) and np.array_equal(edge.mask, wide.mask[:, :240])
    assert edge.depth.max() < 0.6 * d


def test_the_untilted_and_the_sphere_faces_are_unchanged():
    g = np.linspace(-0.005, 0.005, 101)
    X, Y = np.meshgrid(g, g)
    for ind in (PROBE, gel.Indenter.flat(0.003), sphere_map()):
        assert np.array_equal(ind.surface_at(X, Y, 0.0), ind._surface_untilted(X, Y))
    ball = gel.Indenter.sphere(0.003)
    assert np.array_equal(ball.surface_at(X, Y, 0.4), ball.surface_at(X, Y, 0.0))
