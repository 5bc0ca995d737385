"""Gel model of a DIGIT: indenter shapes, the deformed gel surface (height map) and the normal force.

Pure numpy, no teletouch imports, so estimators, benchmarks and simulated devices can use it directly::

    from teletouch.plugins.sensors.gel import Indenter, gel_force, height_map
    ball = Indenter.sphere(0.003)
    f = gel_force(0.0008, ball)                                   # N
    z = height_map(ball, 0.0008, (0.0, 0.0), 0.0, (320, 240), 1 / 17150)   # m, positive into the gel

Force model (normal load of a rigid indenter on an elastic half space, Sneddon's framework):

- sphere of radius R (Hertz):            F = 4/3 E* sqrt(R) d^1.5
- flat punch of radius a (Boussinesq):   F = 2 E* a d
- the paper's probe (a cylinder of radius a = 5 mm whose end is a spherical cap of radius Rt): Hertz on the cap
  while the contact radius sqrt(Rt d) is below a, then the whole end face is in contact and the load grows like a
  flat punch: F = 4/3 E* sqrt(Rt) d1^1.5 + 2 E* a (d - d1) for d > d1 = a^2 / Rt (continuous in value and slope).
- any other shape (a user height map): the incremental stiffness dF/dd = 2 E* a_c(d) with the contact radius
  a_c(d) = sqrt(A(d/2) / pi), where A(s) is the area where the rigid shape dips more than s below the gel plane.
  This is exact for the flat punch and the paraboloid (Hertz), and is integrated numerically.

E* = E / (1 - nu^2) (rigid indenter). Default E = 0.41 MPa, nu = 0.5: Gent's relation between Shore A hardness and
Young's modulus, E[MPa] = 0.0981 (56 + 7.62336 S) / (0.137505 (254 - 2.54 S)), gives 0.41 MPa for the DIGIT's
Shore 10A silicone (hardware notes); this yields 2.3 N at 1.25 mm and 3.0 N at 1.5 mm for a 5 mm radius sphere,
the few newtons a DIGIT is used at. The gel is a 4-5 mm layer on a rigid window, which stiffens it; set
``thickness`` to apply the bonded thin-layer correction of Dimitriadis et al. (Biophys. J. 2002, nu = 0.5):
F *= 1 + 1.133 x + 1.283 x^2 + 0.769 x^3 + 0.0975 x^4, x = a_c / h (used for every shape, an approximation
beyond the sphere; these are the coefficients for an incompressible gel, nu = 0.5, and are used for any Poisson ratio:
at nu = 0.45 the paper's linear term would be 1.04 instead of 1.133, a few per cent less force).

Surface (height map) model: the gel touches the indenter where its face is within d/2 of its lowest point (Hertz:
r <= sqrt(R d); a flat punch or a fully pressed probe: the whole end face) and takes the indenter's shape there (the
analytic cap, d - face). Around the contact it sags as an elastic half space does around a Hertz contact,
u(r) = [(2 a^2 - r^2) asin(a/r) + r a sqrt(1 - a^2/r^2)] / (pi R) for r > a (R = a^2 / d; around a full end face:
Boussinesq's u = u_rim (2/pi) asin(a/r)), tapered by a cosine to zero between SAG_TAPER = 1.5 and 2.5 contact radii
because the real gel is a thin layer on a rigid window (it keeps the render local; the sag near the contact is what
the realism benchmark sees). General shapes use the same rule, the sag centred on the contact patch with its
equivalent radius. ``deformation=False`` gives the rigid cap (the plain geometric intersection) instead. Depth
maps are float32 in metres, positive into the gel.

Positions are in metres from the image centre, x along columns, y along rows (docs/ports.md). ``tilt`` rotates the
indenter about the axis through its centre parallel to the rows (y): its lowest point moves towards +x. The tilted
face is projected onto the gel plane exactly (:meth:`Indenter.surface_at`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal, Sequence

import numpy as np

__all__ = [
    "Indenter", "GelMaterial", "gel_force", "height_map", "contact_radius", "indentation_for_contact_radius",
    "shore_a_to_modulus", "contact_mask", "gel_surface", "GelSurface", "radial_depth", "is_radial",
    "support_radius", "contact_edge_radius", "force_law", "DEFAULT_MODULUS", "DEFAULT_POISSON", "QVGA_M_PER_PX",
    "VGA_M_PER_PX",
]

#: Paper's unit: 17.15 px per mm at QVGA (320 x 240).
QVGA_M_PER_PX = 1.0 / 17150.0
#: Taxim's DIGIT: 0.0266 mm per px at VGA (640 x 480).
VGA_M_PER_PX = 0.0266e-3
#: sampling of the radial profile in GelSurface.profile (pixels)
PROFILE_STEP_PX = 1.0 / 16.0
#: the gel's sag around a contact is tapered to zero between these many contact radii from the axis
SAG_TAPER = (1.5, 2.5)


def shore_a_to_modulus(shore: float) -> float:
    """Young's modulus (Pa) from a Shore A hardness, by Gent's relation (valid for roughly 10-90 A)."""
    return 0.0981e6 * (56.0 + 7.62336 * shore) / (0.137505 * (254.0 - 2.54 * shore))


DEFAULT_MODULUS = shore_a_to_modulus(10.0)  # ~0.41 MPa
DEFAULT_POISSON = 0.5

#: largest plausible value (m) of the gel model's length parameters: a larger one is millimetres typed in a metre
#: field ("indenter_radius: 3" is a 3 m sphere)
MAX_LENGTH = {"indenter_radius": 0.1, "tip_radius": 1.0, "gel_thickness": 0.1}
#: gel Young's modulus range (Pa): soft silicone gels are 10 kPa - 10 MPa; outside it, kPa or MPa typed as Pa
MODULUS_RANGE = (1e3, 1e9)


def length_problem(name: str, value: float, limit: float | None = None) -> str | None:
    """None if the length ``value`` (m) of parameter ``name`` is at most ``limit`` (default MAX_LENGTH[name]) in
    size; else why it looks like millimetres typed in a metre field."""
    limit = MAX_LENGTH[name] if limit is None else limit
    if abs(value) <= limit:
        return None
    return (f"{name} ({value:g} m) is larger than {limit * 1e3:g} mm, which no DIGIT setup has: millimetres typed "
            f"in a metre field? write {value / 1e3:g} or \"{value:g}mm\"")


def modulus_problem(value: float) -> str | None:
    """None if ``value`` (Pa) is a soft gel's Young's modulus (MODULUS_RANGE); else why not."""
    lo, hi = MODULUS_RANGE
    if lo <= value <= hi:
        return None
    return (f"modulus {value:g} Pa is outside {lo:g}-{hi:g} Pa (a soft gel; Shore 10A silicone is ~0.41 MPa): kPa "
            f"or MPa typed as Pa? write e.g. '0.41MPa' or 410000")


def check_gel_params(params: object) -> None:
    """Raise ValueError for the first implausible gel parameter of ``params`` (any object with some of the
    attributes indenter_radius, tip_radius, gel_thickness, modulus; None values are defaults and pass)."""
    for name in MAX_LENGTH:
        v = getattr(params, name, None)
        if v is not None and (why := length_problem(name, v)):
            raise ValueError(why)
    m = getattr(params, "modulus", None)
    if m is not None and (why := modulus_problem(m)):
        raise ValueError(why)


@dataclass(frozen=True)
class GelMaterial:
    """Elastic constants of the gel. ``thickness`` (m) enables the bonded thin-layer correction."""

    modulus: float = DEFAULT_MODULUS
    poisson: float = DEFAULT_POISSON
    thickness: float | None = None

    def __post_init__(self) -> None:
        if not (self.modulus > 0 and math.isfinite(self.modulus)):
            raise ValueError(f"gel modulus must be a positive number of Pa, got {self.modulus!r}")
        if not (0.0 <= self.poisson < 0.5 + 1e-12):
            raise ValueError(f"gel Poisson ratio must be in [0, 0.5], got {self.poisson!r}")
        if self.thickness is not None and not self.thickness > 0:
            raise ValueError(f"gel thickness must be > 0 m, got {self.thickness!r}")

    @property
    def reduced_modulus(self) -> float:
        return self.modulus / (1.0 - self.poisson ** 2)


@dataclass(frozen=True, eq=False)
class Indenter:
    """A rigid indenter. Build with :meth:`sphere`, :meth:`probe`, :meth:`flat` or :meth:`from_height_map`.

    kind: "sphere" (radius), "probe" (radius of the cylinder, tip_radius of its spherical end), "flat" (radius of
    the punch), "map" (surface: heights in m above the indenter's lowest point, sampled every map_m_per_px metres,
    centred on the indenter's axis; NaN or inf where there is no material).
    """

    kind: Literal["sphere", "probe", "flat", "map"]
    radius: float = 0.0
    tip_radius: float = 0.0
    surface: np.ndarray | None = field(default=None, repr=False)
    map_m_per_px: float = 0.0

    # constructors ----------------------------------------------------------------------------------------------
    @classmethod
    def sphere(cls, radius: float) -> "Indenter":
        _positive("sphere radius", radius)
        return cls("sphere", radius=float(radius))

    @classmethod
    def probe(cls, radius: float = 0.005, tip_radius: float = 0.010) -> "Indenter":
        """The paper's calibration probe: a cylinder of ``radius`` ending in a spherical cap of ``tip_radius``."""
        _positive("probe radius", radius)
        _positive("probe tip radius", tip_radius)
        if tip_radius < radius:
            raise ValueError(f"probe tip radius ({tip_radius} m) must be >= the cylinder radius ({radius} m)")
        return cls("probe", radius=float(radius), tip_radius=float(tip_radius))

    @classmethod
    def flat(cls, radius: float) -> "Indenter":
        _positive("flat punch radius", radius)
        return cls("flat", radius=float(radius))

    @classmethod
    def from_height_map(cls, surface: np.ndarray, m_per_px: float) -> "Indenter":
        """A user shape: ``surface[row, col]`` is the height (m) of the indenter's face above its lowest point."""
        s = np.asarray(surface, dtype=np.float64)
        if s.ndim != 2 or s.shape[0] < 2 or s.shape[1] < 2:
            raise ValueError(f"indenter height map must be a 2-D array, got shape {s.shape}")
        _positive("indenter height map m_per_px", m_per_px)
        s = np.where(np.isfinite(s), s, np.inf)
        if not np.isfinite(s).any():
            raise ValueError("indenter height map has no finite value")
        s = s - s[np.isfinite(s)].min()
        return cls("map", surface=s, map_m_per_px=float(m_per_px))

    # geometry --------------------------------------------------------------------------------------------------
    @property
    def extent(self) -> float:
        """Radius (m) of the indenter's footprint."""
        if self.kind == "map":
            assert self.surface is not None
            h, w = self.surface.shape
            return 0.5 * math.hypot(h, w) * self.map_m_per_px
        return self.radius

    def profile(self, r: np.ndarray) -> np.ndarray:
        """Height (m) of an axisymmetric indenter's face above its lowest point at radius r (inf outside)."""
        r = np.asarray(r, dtype=np.float64)
        if self.kind == "sphere":
            R = self.radius
            return np.where(r < R, R - np.sqrt(np.maximum(R * R - r * r, 0.0)), np.inf)
        if self.kind == "probe":
            Rt, a = self.tip_radius, self.radius
            return np.where(r <= a, Rt - np.sqrt(np.maximum(Rt * Rt - r * r, 0.0)), np.inf)
        if self.kind == "flat":
            return np.where(r <= self.radius, 0.0, np.inf)
        raise ValueError("profile() is for axisymmetric indenters")

    def surface_at(self, x: np.ndarray, y: np.ndarray, tilt: float = 0.0) -> np.ndarray:
        """Height (m) of the indenter's face above its lowest point at offsets (x, y) (m) from its axis.

        Tilted (about the y axis through the lowest point of the untilted face), a face point (u, y, h(u, y)) goes
        to (u c + h s, y, -u s + h c) (c, s: cosine and sine of the tilt), and the face seen from below is the
        lower envelope of those points, exactly: the probe's cap stays a sphere of ``tip_radius`` (its footprint
        at a depth is the untilted one while it is within the cap), the punch's end a plane, a height map a
        staircase of its samples. Heights are from the tilted face's own lowest point, wherever it is."""
        if tilt != 0.0 and self.kind != "sphere":  # a sphere is the same shape under any rotation
            return _tilted_face(self, np.asarray(x, np.float64), np.asarray(y, np.float64), float(tilt))
        return self._surface_untilted(x, y)

    @property
    def face_height(self) -> float:
        """Height (m) of the face's highest finite point above its lowest (the rim of a probe's cap)."""
        if self.kind == "sphere":
            return self.radius
        if self.kind == "probe":
            Rt, a = self.tip_radius, self.radius
            return Rt - math.sqrt(Rt * Rt - a * a)
        if self.kind == "flat":
            return 0.0
        assert self.surface is not None
        return float(self.surface[np.isfinite(self.surface)].max())

    def tilted_extent(self, tilt: float = 0.0) -> float:
        """Radius (m) around the axis that holds the face when tilted (:attr:`extent` untilted)."""
        if tilt == 0.0 or self.kind == "sphere":
            return self.extent
        return max(self.extent, self.extent * abs(math.cos(tilt)) + self.face_height * abs(math.sin(tilt)))

    def _surface_untilted(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        if self.kind != "map":
            return self.profile(np.hypot(x, y))
        assert self.surface is not None
        s = self.surface
        h, w = s.shape
        col = np.asarray(x) / self.map_m_per_px + (w - 1) / 2.0
        row = np.asarray(y) / self.map_m_per_px + (h - 1) / 2.0
        ci = np.rint(col).astype(np.int64)
        ri = np.rint(row).astype(np.int64)
        inside = (ci >= 0) & (ci < w) & (ri >= 0) & (ri < h)
        out = np.full(np.broadcast(ci, ri).shape, np.inf)
        out[inside] = s[ri[inside], ci[inside]]
        return out

    def contact_area(self, s: float, tilt: float = 0.0) -> float:
        """Geometric footprint (m^2) at depth ``s``: the area where the rigid face is less than ``s`` above its
        lowest point."""
        if s <= 0:
            return 0.0
        if self.kind == "sphere":
            R = self.radius
            s = min(s, R)
            return math.pi * (2 * R * s - s * s)
        if self.kind == "flat" and tilt == 0.0:
            return math.pi * self.radius ** 2
        if self.kind == "probe" and tilt == 0.0:
            Rt, a = self.tip_radius, self.radius
            r2 = 2 * Rt * s - s * s if s < Rt else Rt * Rt
            return math.pi * min(r2, a * a)
        heights, cell = _face_samples(self, float(tilt))
        return float(np.searchsorted(heights, s, side="left")) * cell


def _tilted_face(ind: Indenter, x: np.ndarray, y: np.ndarray, tilt: float) -> np.ndarray:
    """:meth:`Indenter.surface_at` of a tilted probe, punch or height map (see there): exact projection onto the
    gel plane of the rotated face. (The first-order projection h(x / c) c - x tan(tilt) before this one narrowed the
    face along x by c^2: a probe's footprint shrank 4% at 0.2 rad, its force 2.6%.)"""
    c, s = math.cos(tilt), math.sin(tilt)
    x, y = np.broadcast_arrays(x, y)
    if ind.kind == "flat":
        a = ind.radius
        # the end face stays a plane: x = u c, height -u s; lowest at its rim, u = a sign(s)
        z = np.where((x / c) ** 2 + y * y <= a * a, -x * (s / c) + a * abs(s), np.inf)
        return np.maximum(z, 0.0)
    if ind.kind == "probe":
        Rt, a = ind.tip_radius, ind.radius
        # the cap is a sphere of Rt about (0, 0, Rt), rotated to (Rt s, 0, Rt c): its lower half, where the point
        # comes from the cap (u^2 + y^2 <= a^2 and h <= Rt before the rotation; the cylinder's sides never touch
        # the gel)
        q = Rt * Rt - (x - Rt * s) ** 2 - y * y
        zr = Rt * c - np.sqrt(np.maximum(q, 0.0))
        u, h = x * c - zr * s, x * s + zr * c
        z = np.where((q >= 0.0) & (u * u + y * y <= a * a) & (h <= Rt), zr, np.inf)
        # lowest point: the sphere's, if on the cap; else the cap's rim on the side it tilts to
        zmin = Rt * c - Rt if Rt * abs(s) <= a else -a * abs(s) + (Rt - math.sqrt(Rt * Rt - a * a)) * c
        return np.maximum(z - zmin, 0.0)
    return _tilted_map(ind, x, y, c, s)


def _tilted_map(ind: Indenter, x: np.ndarray, y: np.ndarray, c: float, s: float) -> np.ndarray:
    """A tilted height map seen from below. Each map row (constant y: the tilt axis) is a polyline through its
    samples, each run of finite samples extended flat by half a sample at its ends (the untilted map is sampled
    nearest-neighbour, so its footprint reaches there too); rotated exactly, the gel sees the segments that face
    down (x growing along the row) and at each (x, y) the lowest of them (a row may fold where it climbs steeply away
    from the tilt). Query points take the nearest map row, as untilted."""
    assert ind.surface is not None
    S = ind.surface
    hm, wm = S.shape
    m = ind.map_m_per_px
    u = (np.arange(wm) - (wm - 1) / 2.0) * m
    fin = np.isfinite(S)
    left_open = np.ones_like(fin)
    left_open[:, 1:] = ~fin[:, :-1]
    right_open = np.ones_like(fin)
    right_open[:, :-1] = ~fin[:, 1:]
    # three vertex slots per sample: the run's left end (u - m/2), the sample (u), the run's right end (u + m/2)
    valid = np.stack([fin & left_open, fin, fin & right_open], axis=2).reshape(hm, 3 * wm)
    uv = np.stack([u - m / 2.0, u, u + m / 2.0], axis=1).ravel()
    rows, slots = np.nonzero(valid)                                       # row-major: along each row in order
    hv = S[rows, slots // 3]
    X = uv[slots] * c + hv * s
    Z = -uv[slots] * s + hv * c
    zmin = float(Z.min())
    # a segment joins each vertex to the next one of its run (a run ends at its right-end vertex)
    pair = (rows[:-1] == rows[1:]) & (slots[:-1] % 3 != 2)
    X0, X1, Z0, Z1 = X[:-1][pair], X[1:][pair], Z[:-1][pair], Z[1:][pair]
    seg_row = rows[:-1][pair]
    down = X1 > X0
    X0, X1, Z0, Z1, seg_row = X0[down], X1[down], Z0[down], Z1[down], seg_row[down]
    # queries: the map row of each point (nearest sample, as untilted), sorted by (row, x)
    xq = x.ravel()
    rq = np.rint(y.ravel() / m + (hm - 1) / 2.0)
    out = np.full(xq.shape, np.inf)
    ok = (rq >= 0) & (rq < hm) & np.isfinite(xq)
    if not ok.any() or seg_row.size == 0:
        return out.reshape(x.shape)
    qi = np.flatnonzero(ok)
    span = 2.0 * (float(np.abs(xq[qi]).max()) + float(np.abs(X).max())) + 1.0  # keys keep the rows apart
    key = rq[qi] * span + xq[qi]
    order = np.argsort(key, kind="stable")
    key, qi = key[order], qi[order]
    lo = np.searchsorted(key, seg_row * span + X0, side="left")
    hi = np.searchsorted(key, seg_row * span + X1, side="right")
    n = hi - lo
    if n.sum() == 0:
        return out.reshape(x.shape)
    seg = np.repeat(np.arange(n.size), n)
    pos = lo[seg] + (np.arange(seg.size) - np.repeat(np.cumsum(n) - n, n))
    q = qi[pos]
    w = (xq[q] - X0[seg]) / (X1[seg] - X0[seg])
    np.minimum.at(out, q, Z0[seg] + w * (Z1[seg] - Z0[seg]))
    return np.maximum(out - zmin, 0.0).reshape(x.shape)


@lru_cache(maxsize=32)
def _face_samples(indenter: Indenter, tilt: float) -> tuple[np.ndarray, float]:
    """Sorted finite face heights (m) of an indenter sampled on a grid, and the area (m^2) of one sample: the
    footprint at depth s is (number of heights < s) x area. A user map is its own grid when untilted."""
    if indenter.kind == "map" and tilt == 0.0:
        assert indenter.surface is not None
        z = indenter.surface.ravel()
        cell = indenter.map_m_per_px ** 2
    else:
        ext = indenter.tilted_extent(tilt)
        n = 513
        g = np.linspace(-ext, ext, n)
        X, Y = np.meshgrid(g, g)
        z = indenter.surface_at(X, Y, tilt).ravel()
        cell = (g[1] - g[0]) ** 2
    z = np.sort(z[np.isfinite(z)])
    return z, float(cell)


def _positive(what: str, v: float) -> None:
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be a positive number of metres, got {v!r}")


def _material(modulus: float | GelMaterial | None, poisson: float | None, thickness: float | None) -> GelMaterial:
    if isinstance(modulus, GelMaterial):
        return modulus
    return GelMaterial(DEFAULT_MODULUS if modulus is None else float(modulus),
                       DEFAULT_POISSON if poisson is None else float(poisson), thickness)


def contact_radius(indentation_m: float, indenter: Indenter, tilt_rad: float = 0.0) -> float:
    """Radius (m) of the contact patch at an indentation (Hertz: sqrt(R d); flat punch: its radius)."""
    d = float(indentation_m)
    if d <= 0:
        return 0.0
    if indenter.kind == "sphere":
        return math.sqrt(indenter.radius * min(d, indenter.radius))
    if indenter.kind == "flat" and tilt_rad == 0.0:
        return indenter.radius
    if indenter.kind == "probe" and tilt_rad == 0.0:
        return min(math.sqrt(indenter.tip_radius * d), indenter.radius)
    return math.sqrt(indenter.contact_area(d / 2.0, tilt_rad) / math.pi)


def indentation_for_contact_radius(a_m: float, indenter: Indenter) -> float:
    """Inverse of :func:`contact_radius` for a sphere or the probe's cap (Hertz: d = a^2 / R)."""
    if indenter.kind == "sphere":
        return a_m * a_m / indenter.radius
    if indenter.kind == "probe":
        return a_m * a_m / indenter.tip_radius
    raise ValueError(f"contact radius does not determine the indentation of a {indenter.kind} indenter")


def _thin_layer(a_c: float, h: float | None) -> float:
    if h is None:
        return 1.0
    x = a_c / h
    return 1.0 + 1.133 * x + 1.283 * x * x + 0.769 * x ** 3 + 0.0975 * x ** 4


def gel_force(indentation_m: float, indenter: Indenter, modulus: float | GelMaterial | None = None,
              poisson: float | None = None, thickness: float | None = None, tilt_rad: float = 0.0) -> float:
    """Normal force (N) the gel pushes back with at an indentation (m); 0 at or below 0, monotonic increasing.

    ``modulus`` is Young's modulus (Pa) or a :class:`GelMaterial`; see the module docstring for the laws.
    """
    d = float(indentation_m)
    if not math.isfinite(d):
        raise ValueError(f"indentation must be a finite number of metres, got {indentation_m!r}")
    if d <= 0.0:
        return 0.0
    mat = _material(modulus, poisson, thickness)
    Es = mat.reduced_modulus
    k = indenter.kind
    if k == "sphere":
        F = 4.0 / 3.0 * Es * math.sqrt(indenter.radius) * d ** 1.5
    elif k == "flat" and tilt_rad == 0.0:
        F = 2.0 * Es * indenter.radius * d
    elif k == "probe" and tilt_rad == 0.0:
        Rt, a = indenter.tip_radius, indenter.radius
        d1 = a * a / Rt
        if d <= d1:
            F = 4.0 / 3.0 * Es * math.sqrt(Rt) * d ** 1.5
        else:
            F = 4.0 / 3.0 * Es * math.sqrt(Rt) * d1 ** 1.5 + 2.0 * Es * a * (d - d1)
    else:
        F = _numeric_force(d, indenter, Es, tilt_rad)
    return float(F * _thin_layer(contact_radius(d, indenter, tilt_rad), mat.thickness))


def _no_indentation(d: float) -> float:
    """force_law's off-the-hot-path branch: 0 N for d <= 0, an error for NaN or infinity."""
    if not math.isfinite(d):
        raise ValueError(f"indentation must be a finite number of metres, got {d!r}")
    return 0.0


def force_law(indenter: Indenter, modulus: float | GelMaterial | None = None, poisson: float | None = None,
              thickness: float | None = None, tilt_rad: float = 0.0):
    """``gel_force`` for one indenter and gel as a function of the indentation alone, ``F(d)`` (N, d in m).

    For the closed-form laws (sphere; flat punch and probe untilted) the constants are computed once and the
    arithmetic is the same as :func:`gel_force`'s, operation for operation, so the result is the same number about
    ten times faster (a 1 kHz simulation solves the law several times a step). Other shapes call ``gel_force``.
    """
    mat = _material(modulus, poisson, thickness)
    Es = mat.reduced_modulus
    h = mat.thickness
    k = indenter.kind
    sqrt = math.sqrt

    def layer(a_c: float) -> float:  # _thin_layer's polynomial
        x = a_c / h
        return 1.0 + 1.133 * x + 1.283 * x * x + 0.769 * x ** 3 + 0.0975 * x ** 4

    if k == "sphere":
        R = indenter.radius
        c = 4.0 / 3.0 * Es * math.sqrt(R)

        def law(d: float) -> float:
            d = float(d)
            if d <= 0.0 or not d < math.inf:
                return _no_indentation(d)
            F = c * d ** 1.5
            if h is None:
                return F * 1.0
            return F * layer(sqrt(R * (d if d < R else R)))
    elif k == "flat" and tilt_rad == 0.0:
        c = 2.0 * Es * indenter.radius
        fac = 1.0 if h is None else layer(indenter.radius)

        def law(d: float) -> float:
            d = float(d)
            if d <= 0.0 or not d < math.inf:
                return _no_indentation(d)
            return c * d * fac
    elif k == "probe" and tilt_rad == 0.0:
        Rt, a = indenter.tip_radius, indenter.radius
        d1 = a * a / Rt
        c = 4.0 / 3.0 * Es * math.sqrt(Rt)
        f1 = 4.0 / 3.0 * Es * math.sqrt(Rt) * d1 ** 1.5
        c2 = 2.0 * Es * a

        def law(d: float) -> float:
            d = float(d)
            if d <= 0.0 or not d < math.inf:
                return _no_indentation(d)
            F = c * d ** 1.5 if d <= d1 else f1 + c2 * (d - d1)
            if h is None:
                return F * 1.0
            a_c = sqrt(Rt * d)
            return F * layer(a_c if a_c < a else a)
    else:
        def law(d: float) -> float:
            return gel_force(d, indenter, mat, tilt_rad=tilt_rad)
    return law


def _numeric_force(d: float, indenter: Indenter, Es: float, tilt: float, n: int = 128) -> float:
    # dF/ds = 2 E* sqrt(A(s/2)/pi), integrated by the midpoint rule on n steps (A is monotonic in s).
    heights, cell = _face_samples(indenter, float(tilt))
    ds = d / n
    s = (np.arange(n) + 0.5) * ds
    area = np.searchsorted(heights, s / 2.0, side="left") * cell
    return float(2.0 * Es * np.sqrt(area / math.pi).sum() * ds)


def _hertz_sag(r: np.ndarray, a: float, R: float) -> np.ndarray:
    """Surface displacement (m, into the gel) outside a Hertz contact of radius a, equivalent radius R."""
    ratio = np.clip(a / np.maximum(r, 1e-12), 0.0, 1.0)
    return ((2 * a * a - r * r) * np.arcsin(ratio) + r * a * np.sqrt(np.maximum(1.0 - ratio * ratio, 0.0))) / (
        math.pi * R)


def height_map(indenter: Indenter, indentation_m: float, position_m: Sequence[float] = (0.0, 0.0),
               tilt_rad: float = 0.0, shape: tuple[int, int] = (320, 240), m_per_px: float = QVGA_M_PER_PX,
               deformation: bool = True) -> np.ndarray:
    """Depth (m, positive into the gel) of the gel surface, float32 of ``shape`` (rows, cols).

    ``position_m`` is the indenter's axis relative to the image centre (x along columns, y along rows, m).
    Inside the contact the depth is the indentation minus the indenter's face height (the analytic cap for a
    sphere); with ``deformation`` the gel around it sags like an elastic half space (Hertz), else it stays flat.
    """
    return gel_surface(indenter, indentation_m, position_m, tilt_rad, shape, m_per_px, deformation).depth


def contact_mask(indenter: Indenter, indentation_m: float, position_m: Sequence[float] = (0.0, 0.0),
                 tilt_rad: float = 0.0, shape: tuple[int, int] = (320, 240), m_per_px: float = QVGA_M_PER_PX
                 ) -> np.ndarray:
    """Bool (rows, cols): pixels where the gel touches the indenter."""
    return gel_surface(indenter, indentation_m, position_m, tilt_rad, shape, m_per_px, False).mask


@dataclass
class GelSurface:
    """Result of :func:`gel_surface`: full-size depth (m) and contact mask, the window (r0, r1, c0, c1) outside
    which both are zero, and the indenter's axis in pixels (row, col)."""

    depth: np.ndarray
    mask: np.ndarray
    window: tuple[int, int, int, int]
    center_px: tuple[float, float] = (0.0, 0.0)
    #: radial surfaces: the depth (m, float32) against the distance from the axis, every PROFILE_STEP_PX pixels
    profile: np.ndarray | None = None


def is_radial(indenter: Indenter, tilt_rad: float = 0.0) -> bool:
    """Whether the gel surface under this indenter is a function of the distance to its axis only."""
    return indenter.kind == "sphere" or (indenter.kind in ("probe", "flat") and tilt_rad == 0.0)


def support_radius(indenter: Indenter, indentation_m: float, tilt_rad: float = 0.0, deformation: bool = True
                   ) -> float:
    """Distance (m) from the axis beyond which the gel is undisturbed."""
    d = float(indentation_m)
    if d <= 0:
        return 0.0
    a_c = contact_radius(d, indenter, tilt_rad)
    if not deformation:
        if indenter.kind == "sphere":
            return math.sqrt(max(2 * indenter.radius * min(d, indenter.radius) - min(d, indenter.radius) ** 2, 0))
        return indenter.tilted_extent(tilt_rad)
    if is_radial(indenter, tilt_rad):
        return SAG_TAPER[1] * a_c
    # the sag is centred on the contact, somewhere in the footprint
    return indenter.tilted_extent(tilt_rad) + SAG_TAPER[1] * a_c


def _compose(face: np.ndarray, r: np.ndarray, d: float, indenter: Indenter, tilt_rad: float, deformation: bool
             ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) and contact from the face height above its lowest point and the distance to the axis."""
    cap = np.maximum(d - face, 0.0)  # rigid intersection (0 where the face is inf)
    a_c = contact_radius(d, indenter, tilt_rad)
    full_face = indenter.kind in ("flat", "probe") and is_radial(indenter, tilt_rad) and a_c >= indenter.radius
    if full_face:
        inside = np.isfinite(face)
    else:
        # Hertz: the gel touches the face where it is within d/2 of the face's lowest point (r <= sqrt(R d))
        inside = face <= d / 2.0
    if not deformation:
        return np.clip(cap, 0.0, d), inside
    if full_face:
        # outside the end face the gel sags like around a flat punch (Boussinesq), from the depth at the rim
        a = indenter.radius
        rim = d - float(indenter.profile(np.array(a)))
        sag = rim * (2.0 / math.pi) * np.arcsin(np.clip(a / np.maximum(r, 1e-12), 0.0, 1.0))
        limit = d
    else:
        a = a_c
        sag = _hertz_sag(r, a_c, a_c * a_c / d)
        limit = d / 2.0
    # the gel is a layer on a rigid window, so its sag dies out sooner than a half space's: the half-space sag,
    # tapered smoothly (cosine) to zero between SAG_TAPER[0] and SAG_TAPER[1] contact radii
    t0, t1 = SAG_TAPER[0] * a, SAG_TAPER[1] * a
    u = np.clip((r - t0) / max(t1 - t0, 1e-12), 0.0, 1.0)
    sag = sag * (0.5 + 0.5 * np.cos(np.pi * u))
    z = np.where(inside, cap, np.minimum(sag, limit))
    return np.clip(z, 0.0, d), inside


def contact_edge_radius(indenter: Indenter, indentation_m: float) -> float:
    """Radius (m) of the contact patch of a radial indenter in the surface model: where the face is within d/2 of
    its lowest point (sqrt(R d - d^2/4) for a sphere), or the whole end face of a flat punch or a fully pressed
    probe."""
    d = float(indentation_m)
    if d <= 0:
        return 0.0
    k = indenter.kind
    if k == "flat":
        return indenter.radius
    R = indenter.radius if k == "sphere" else indenter.tip_radius
    h = min(d / 2.0, R)
    re = math.sqrt(max(2 * R * h - h * h, 0.0))
    if k == "probe":
        if contact_radius(d, indenter) >= indenter.radius:
            return indenter.radius
        return min(re, indenter.radius)
    return re


def radial_depth(indenter: Indenter, indentation_m: float, r_m: np.ndarray, deformation: bool = True
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) and contact (bool) at distances ``r_m`` from the axis, for an indenter where
    :func:`is_radial` holds (float64 1-D profile; the same model as :func:`gel_surface`)."""
    r = np.asarray(r_m, np.float64)
    d = float(indentation_m)
    if d <= 0:
        return np.zeros_like(r), np.zeros(r.shape, bool)
    return _compose(indenter.profile(r), r, d, indenter, 0.0, deformation)


def gel_surface(indenter: Indenter, indentation_m: float, position_m: Sequence[float] = (0.0, 0.0),
                tilt_rad: float = 0.0, shape: tuple[int, int] = (320, 240), m_per_px: float = QVGA_M_PER_PX,
                deformation: bool = True) -> GelSurface:
    """Depth map, contact mask and the window that holds them (see :func:`height_map`)."""
    rows, cols = int(shape[0]), int(shape[1])
    d = float(indentation_m)
    if not math.isfinite(d):
        raise ValueError(f"indentation must be a finite number of metres, got {indentation_m!r}")
    px, py = float(position_m[0]), float(position_m[1])
    if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(float(tilt_rad))):
        raise ValueError(f"position and tilt must be finite, got {position_m!r}, {tilt_rad!r}")
    if not m_per_px > 0:
        raise ValueError(f"m_per_px must be > 0, got {m_per_px!r}")
    depth = np.zeros((rows, cols), np.float32)
    mask = np.zeros((rows, cols), bool)
    cc = (cols - 1) / 2.0 + px / m_per_px
    rc = (rows - 1) / 2.0 + py / m_per_px
    empty = GelSurface(depth, mask, (0, 0, 0, 0), (rc, cc))
    if d <= 0.0:
        return empty
    reach = support_radius(indenter, d, tilt_rad, deformation) + 2 * m_per_px
    rr = int(math.ceil(reach / m_per_px))
    r0, r1 = max(0, int(math.floor(rc)) - rr), min(rows, int(math.ceil(rc)) + rr + 1)
    c0, c1 = max(0, int(math.floor(cc)) - rr), min(cols, int(math.ceil(cc)) + rr + 1)
    if r0 >= r1 or c0 >= c1:
        return empty
    if deformation and is_radial(indenter, tilt_rad):
        # the (continuous) surface is a function of r: evaluate the model on a fine 1-D grid (1/16 px) and
        # interpolate linearly (float32, in pixel units)
        h = PROFILE_STEP_PX
        n = int(math.ceil(reach / m_per_px / h)) + 3
        zg, _ = radial_depth(indenter, d, np.arange(n) * (h * m_per_px), deformation)
        zg = zg.astype(np.float32)
        yp = (np.arange(r0, r1) - rc).astype(np.float32)
        xp = (np.arange(c0, c1) - cc).astype(np.float32)
        r2 = yp[:, None] ** 2 + xp[None, :] ** 2
        t = np.sqrt(r2) * np.float32(1.0 / h)
        i = np.minimum(t.astype(np.int32), n - 2)
        frac = np.minimum(t - i, np.float32(1.0))
        z = zg[i] + frac * (zg[i + 1] - zg[i])
        # contact: where the face is within d/2 of its lowest point (or the whole end face)
        re = contact_edge_radius(indenter, d) / m_per_px
        inside = r2 <= np.float32(re * re)
    elif deformation:
        # general shape: the contact patch (its centre and area set the sag around it) is found on the whole
        # window around the axis, then cut to the image: near the image's edge the part of the patch off the image
        # counts too (measured on the visible part only, the sag moved and shrank with the edge)
        R0, C0 = int(math.floor(rc)) - rr, int(math.floor(cc)) - rr
        y = (np.arange(R0, int(math.ceil(rc)) + rr + 1, dtype=np.float64) - rc) * m_per_px
        x = (np.arange(C0, int(math.ceil(cc)) + rr + 1, dtype=np.float64) - cc) * m_per_px
        X, Y = np.meshgrid(x, y)
        face = indenter.surface_at(X, Y, tilt_rad)
        # the gel touches the face where it is within d/2 of its lowest point (as in Hertz); around that patch
        # the gel sags like around a Hertz contact of the same area, centred on the patch
        inside = face <= d / 2.0
        if inside.any():
            xc, yc = float(X[inside].mean()), float(Y[inside].mean())
            a_eq = math.sqrt(inside.sum() * m_per_px * m_per_px / math.pi)
            rc_ = np.hypot(X - xc, Y - yc)
            t0, t1 = SAG_TAPER[0] * a_eq, SAG_TAPER[1] * a_eq
            u = np.clip((rc_ - t0) / max(t1 - t0, 1e-12), 0.0, 1.0)
            sag = _hertz_sag(rc_, a_eq, a_eq * a_eq / d) * (0.5 + 0.5 * np.cos(np.pi * u))
            z = np.clip(np.where(inside, np.maximum(d - face, 0.0), np.minimum(sag, d / 2.0)), 0.0, d)
        else:  # the patch is smaller than a pixel
            z = np.clip(d - face, 0.0, d)
        z, inside = z[r0 - R0:r1 - R0, c0 - C0:c1 - C0], inside[r0 - R0:r1 - R0, c0 - C0:c1 - C0]
    else:
        y = (np.arange(r0, r1, dtype=np.float64) - rc) * m_per_px
        x = (np.arange(c0, c1, dtype=np.float64) - cc) * m_per_px
        r = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2)
        X, Y = np.meshgrid(x, y)
        face = indenter.surface_at(X, Y, tilt_rad)
        z, inside = _compose(face, r, d, indenter, tilt_rad, deformation)
    depth[r0:r1, c0:c1] = z
    mask[r0:r1, c0:c1] = inside
    return GelSurface(depth, mask, (r0, r1, c0, c1), (rc, cc), zg if deformation and is_radial(indenter, tilt_rad)
                      else None)
