"""``sim-digit``: a simulated DIGIT whose images come from the optical model of a real DIGIT.

Pipeline per frame: indenter + indentation + position + tilt -> gel surface (:mod:`.gel`: Hertz contact with the
elastic sag around it) -> the surface seen through the gel's thickness (Gaussian smoothing of the height map,
``smoothing`` m) -> Taxim's polynomial table (:mod:`.optics`) on a real background frame -> per-unit variation,
illumination drift, sensor noise -> uint8 BGR, portrait (QVGA 320 x 240, VGA 640 x 480).

Ground truth on the side: ``gt_depth`` (the gel surface, m, positive into the gel, before the optical smoothing),
``gt_max_depth``, ``gt_force`` (the gel model's normal force, N) and ``gt_contact_mask``. The ground-truth arrays are
read-only (they are shared while the pose does not change); ``image`` is a fresh array every step, stamped with the
step's time.

Bad values fault rather than render something silently wrong: lengths no DIGIT setup has (millimetres typed in metre
fields, MAX_LENGTH; the indentation input too), a pixel size below MIN_M_PER_PX or a blur wider than
MAX_SMOOTHING_PX, an indenter axis off the image, a tilt beyond 45 degrees, an indentation through the gel, inputs
that are not finite or older than INPUT_MAX_AGE.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import Component, Kind, Params, Port, hookimpl
from teletouch.errors import ModelFileError
from teletouch.paths import looked_at
from teletouch.units import Meters, Pascals, Radians, Seconds, parse_quantity

from . import gel as _gel

__all__ = ["SimDigit", "DigitSimulator", "M_PER_PX"]

#: default pixel size per resolution: the paper's 17.15 px/mm at QVGA, Taxim's 0.0266 mm/px at VGA
M_PER_PX = {"qvga": _gel.QVGA_M_PER_PX, "vga": _gel.VGA_M_PER_PX}
DEFAULT_RADIUS = {"sphere": 0.003, "probe": 0.005, "flat": 0.003}
#: smallest per-unit gain of a channel's contact response and of the gel blur (unit_variation up to 3)
MIN_GAIN = 0.1
#: largest plausible value (m) of each length parameter: a larger one is millimetres typed in a metre field
#: ("indenter_radius: 3" is 3 m; "smoothing: 0.08" would be an 80 mm blur that needs gigabytes to render)
MAX_LENGTH = {**_gel.MAX_LENGTH, "m_per_px": 1e-3, "indenter_map_m_per_px": 1e-3, "smoothing": 1e-3,
              "indentation": 0.02, "position": 0.1}
#: smallest plausible pixel size (m): 1 um, 27x finer than the DIGIT at VGA; below it a contact's profile takes
#: gigabytes (1e-9: 4.5 GB and 14 s a frame)
MIN_M_PER_PX = 1e-6
#: widest blur the renderer takes (px, before the unit's blur gain): the largest smoothing (1 mm) at the default
#: pixel sizes is 17 px (QVGA) and 38 px (VGA); 0.08 mm at m_per_px 1e-9 would be 80000 px (a 47.7 TiB matrix)
MAX_SMOOTHING_PX = 64
#: the gel model tilts the indenter's face only (its sides never touch the gel): at most this tilt (rad)
MAX_TILT = math.pi / 4
MODULUS_RANGE = _gel.MODULUS_RANGE
#: input staleness limit (s): an indentation, position or tilt older than this faults the node (the runtime's
#: max_age; a graph may set another per wire)
INPUT_MAX_AGE = 0.25
#: the stream name that keeps a seed's own random stream (the node's default id, the component's name)
SEED_STREAM = "sim-digit"


def seed_sequence(seed: int, stream: str | None = None) -> np.random.SeedSequence:
    """The seed of a simulator's random stream: ``seed``'s own (``np.random.default_rng(seed)``) for ``stream``
    None or SEED_STREAM, else one of its own for each stream name, independent of the others and reproducible (the
    name enters as its SHA-256, not Python's per-process hash)."""
    if stream is None or stream == SEED_STREAM:
        return np.random.SeedSequence(seed)
    words = np.frombuffer(hashlib.sha256(stream.encode("utf-8")).digest(), dtype="<u4")
    return np.random.SeedSequence([int(seed), *(int(w) for w in words)])


class DigitSimulator:
    """Renders DIGIT frames and their ground truth; the engine behind ``sim-digit`` (usable on its own).

    ``render(indentation, position, tilt, t)`` returns (image uint8, GelSurface); results of the last pose are
    cached, so a resting indenter costs a copy and the noise. A position off the image (:meth:`check_on_gel`) or a
    tilt beyond MAX_TILT is refused (ValueError) with the node's messages.

    The noise, drift phase and unit variation come from ``seed`` and ``stream`` (:func:`seed_sequence`): two
    simulators with one seed and different stream names are two sensors with independent noise.
    """

    def __init__(self, resolution: str = "qvga", m_per_px: float | None = None,
                 indenter: _gel.Indenter | None = None, material: _gel.GelMaterial | None = None,
                 smoothing: float = 0.08e-3, deformation: bool = True, noise: float = 0.0, drift: float = 0.0,
                 drift_period: float = 10.0, unit_variation: float = 0.0, seed: int = 0,
                 background: str | Path | np.ndarray | None = None, optical_model: str | Path | None = None,
                 stride: int = 2, stream: str | None = None):
        import cv2

        from . import optics

        self._cv2 = cv2
        if resolution not in optics.RESOLUTIONS:
            raise ValueError(f"resolution must be one of {sorted(optics.RESOLUTIONS)}, got {resolution!r}")
        self.shape = optics.RESOLUTIONS[resolution]
        self.m_per_px = float(m_per_px) if m_per_px else M_PER_PX[resolution]
        why = scale_problem(self.m_per_px, float(smoothing))
        if why:
            raise ValueError(why)
        self.indenter = indenter or _gel.Indenter.sphere(0.003)
        self.material = material or _gel.GelMaterial()
        self.smoothing_px = float(smoothing) / self.m_per_px
        self.deformation = deformation
        self.noise = float(noise)
        self.drift = float(drift)
        self.drift_period = float(drift_period)
        rng = np.random.default_rng(seed_sequence(seed, stream))
        self.rng = np.random.default_rng(rng.integers(2 ** 63))
        # per-unit variation: channel gains of the contact response and of the background, LED centre offset
        uv = float(unit_variation)
        # gains stay positive (>= MIN_GAIN): beyond unit_variation ~2 a bare 1 + uv x would invert a channel's
        # response or make the blur negative (= none)
        resp_gain = np.maximum(1.0 + uv * np.clip(rng.normal(0.0, 0.15, 3), -0.4, 0.4), MIN_GAIN)
        bg_gain = 1.0 + uv * np.clip(rng.normal(0.0, 0.05, 3), -0.15, 0.15)
        offset = tuple(uv * rng.normal(0.0, 0.03, 2) * np.array(self.shape[::-1]))
        self.drift_phase = float(rng.uniform(0, 2 * math.pi))
        # ... and the gel's/LED diffusion: how much the surface is blurred
        blur_gain = max(float(1.0 + uv * np.clip(rng.normal(0.0, 0.2), -0.5, 0.5)), MIN_GAIN)
        self.smoothing_px *= blur_gain
        table = optics.load_table(optical_model)
        if isinstance(background, np.ndarray):
            bg = background.astype(np.float32)
            if bg.shape != (*self.shape, 3):
                raise ValueError(f"background array has shape {bg.shape}, expected {(*self.shape, 3)}")
            if not (np.isfinite(bg).all() and bg.min() >= 0 and bg.max() <= 255):
                raise ValueError("background array must hold finite intensities in 0..255 (BGR levels), got "
                                 f"{np.nanmin(bg) if np.isfinite(bg).any() else 'nan'}.."
                                 f"{np.nanmax(bg) if np.isfinite(bg).any() else 'nan'}"
                                 f"{' and NaN/inf' if not np.isfinite(bg).all() else ''}")
        else:
            bg = optics.load_background(resolution, background)
        self.background = np.clip(bg * bg_gain[None, None, :].astype(np.float32), 0, 255)
        self.background_u8 = np.rint(self.background).astype(np.uint8)
        self.renderer = optics.OpticalRenderer(table, self.shape, gain=resp_gain, offset_px=offset)
        self.unit = {"response_gain": resp_gain.tolist(), "background_gain": bg_gain.tolist(),
                     "optical_offset_px": [float(o) for o in offset], "blur_gain": blur_gain}
        # sensor noise: a long buffer of Gaussian noise; each frame takes a slice at a random offset
        self._noise_buf: np.ndarray | None = None
        self._npix = self.shape[0] * self.shape[1] * 3
        if self.noise > 0:
            noise = self.rng.standard_normal(4 * self._npix, dtype=np.float32) * np.float32(self.noise)
            self._noise_buf = np.clip(np.rint(noise), -127, 127).astype(np.int16)
        # radial renderer: profiles sampled every 1/4 px, blurred exactly (see optics.RadialBlur)
        self._h = 0.25
        reach = math.hypot(*self.shape) + 8 * self.smoothing_px + 8
        self._blur = optics.RadialBlur(self.smoothing_px, self._h, int(math.ceil(reach / self._h)) + 1)
        self._bg_flat = self.background.reshape(-1, 3)
        self.fast = True  # use the radial renderer where the surface is radial (False: the generic 2-D path)
        self.stride = int(stride)
        if self.stride not in (1, 2, 3, 4):
            raise ValueError(f"render stride must be 1..4 px, got {stride!r}")
        self._key: tuple | None = None
        self._clean: np.ndarray = self.background_u8
        self._surface = _gel.gel_surface(self.indenter, 0.0, (0.0, 0.0), 0.0, self.shape, self.m_per_px)
        self.max_depth = 0.0  # of the last rendered surface (m)
        self.renders = 0

    def check_on_gel(self, position) -> None:
        """The indenter's axis (x, y) (m from the image centre) must be on the gel's sensing area (the image), else
        nothing could be seen of a contact whose force the ground truth would still report: ValueError if not."""
        rows, cols = self.shape
        mpp = self.m_per_px
        hx, hy = cols / 2 * mpp, rows / 2 * mpp
        x, y = float(position[0]), float(position[1])
        if not (abs(x) <= hx and abs(y) <= hy):
            raise ValueError(f"indenter position ({x * 1e3:.4g} mm, {y * 1e3:.4g} mm) is off the gel: the image "
                             f"spans x +-{hx * 1e3:.3g} mm, y +-{hy * 1e3:.3g} mm ({cols} x {rows} px at "
                             f"{mpp * 1e3:.4g} mm/px); positions are in m")

    def surface(self, indentation: float, position=(0.0, 0.0), tilt: float = 0.0) -> _gel.GelSurface:
        """The gel surface of a pose (a contact, indentation > 0, must be on the gel: :meth:`check_on_gel`)."""
        _check_tilt("tilt", float(tilt))
        if float(indentation) > 0:
            self.check_on_gel(position)
        return _gel.gel_surface(self.indenter, indentation, position, tilt, self.shape, self.m_per_px,
                                self.deformation)

    def force(self, indentation: float, tilt: float = 0.0) -> float:
        return _gel.gel_force(indentation, self.indenter, self.material, tilt_rad=tilt)

    def clean_image(self, surf: _gel.GelSurface, indentation: float | None = None, tilt: float = 0.0
                    ) -> np.ndarray:
        """The noise-free frame (uint8) for a gel surface (``indentation`` given: the radial renderer may be used)."""
        if (self.fast and indentation is not None and indentation > 0
                and _gel.is_radial(self.indenter, tilt)):
            img = self._radial_image(indentation, surf)
            if img is not None:
                return img
        img = self.background_u8.copy()
        r0, r1, c0, c1 = surf.window
        if r1 <= r0 or c1 <= c0:
            return img
        rows, cols = self.shape
        s = self.smoothing_px
        m = int(math.ceil(3 * s)) + 1 if s > 0 else 1
        w = (max(r0 - m, 0), min(r1 + m, rows), max(c0 - m, 0), min(c1 + m, cols))
        z = surf.depth[w[0]:w[1], w[2]:w[3]]
        if s > 0:
            z = self._cv2.GaussianBlur(z, (0, 0), s, borderType=self._cv2.BORDER_REPLICATE)
        full = np.zeros(self.shape, np.float32)
        full[w[0]:w[1], w[2]:w[3]] = z
        delta = self.renderer.delta(full, self.m_per_px, w)
        img[w[0]:w[1], w[2]:w[3]] = np.clip(self.background[w[0]:w[1], w[2]:w[3]] + delta + 0.5, 0, 255
                                            ).astype(np.uint8)
        return img

    def _radial_image(self, d: float, surf: _gel.GelSurface) -> np.ndarray | None:
        """Render a radially symmetric surface from its 1-D profile: exact blur, analytic slopes, and only the
        pixels whose slope reaches the table's second angle bin are shaded. None if the profile is too long."""
        h, mpp = self._h, self.m_per_px
        rows, cols = self.shape
        rc, cc = surf.center_px
        sup = _gel.support_radius(self.indenter, d, 0.0, self.deformation) / mpp
        n = int(math.ceil((sup + 4 * self.smoothing_px + 2) / h)) + 1
        if n > self._blur.n:
            return None
        step = int(round(h / _gel.PROFILE_STEP_PX))
        if surf.profile is not None and abs(step * _gel.PROFILE_STEP_PX - h) < 1e-12:
            zp = surf.profile[::step]
            z = np.zeros(n, np.float32)
            m = min(n, zp.shape[0])
            z[:m] = zp[:m]
        else:
            z, _ = _gel.radial_depth(self.indenter, d, np.arange(n) * (h * mpp), self.deformation)
        g = self._blur(z * np.float32(1.0 / mpp))
        slope = np.empty_like(g)
        slope[1:-1] = (g[2:] - g[:-2]) * (0.5 / h)
        slope[0] = 0.0
        slope[-1] = (g[-1] - g[-2]) / h
        mbg = np.minimum((np.arctan(np.abs(slope)) * (124.0 / (0.5 * math.pi))).astype(np.int32), 124)
        nz = np.flatnonzero(mbg >= 1)
        img = self.background_u8.copy()
        if nz.size == 0:
            return img
        r_lim = (nz[-1] + 1) * h
        r0, r1 = max(0, int(math.floor(rc - r_lim))), min(rows, int(math.ceil(rc + r_lim)) + 1)
        c0, c1 = max(0, int(math.floor(cc - r_lim))), min(cols, int(math.ceil(cc + r_lim)) + 1)
        if r0 >= r1 or c0 >= c1:
            return img
        # shade a grid of every k-th pixel (at the centres of k x k blocks) and interpolate bilinearly: the
        # gel's image is smooth at the pixel scale (k = 1: every pixel)
        k = self.stride
        ch, cw = -(-(r1 - r0) // k), -(-(c1 - c0) // k)
        off = (k - 1) / 2.0
        ys = r0 + off + k * np.arange(ch)
        xs = c0 + off + k * np.arange(cw)
        dy = (ys - rc).astype(np.float32)
        dx = (xs - cc).astype(np.float32)
        r = np.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2)
        i = np.minimum((r * np.float32(1.0 / h) + np.float32(0.5)).astype(np.int32), n - 1).ravel()
        mb = mbg[i]
        sel = np.flatnonzero(mb >= 1)
        if sel.size == 0:
            return img
        sr, sc = sel // cw, sel % cw
        # the depth falls away from the axis, so its gradient points at the axis: the table's direction bin
        # floor((atan2(gr, gc) + pi) / (2 pi / 124)) is the bin of the pixel's own angle around the axis in [0, 2 pi)
        ang = np.arctan2(dy[sr], dx[sc])
        ang = ang + np.where(slope[i[sel]] > 0, np.float32(math.pi), np.float32(0.0))  # rising: reversed
        ang = np.mod(ang, np.float32(2 * math.pi))
        db = np.minimum((ang * np.float32(124.0 / (2 * math.pi))).astype(np.int32), 124)
        shade = self.renderer.shade(mb[sel] * 125 + db, ys[sr], xs[sc])
        if k == 1:
            gidx = (sr + r0) * cols + (sc + c0)
            flat = img.reshape(-1, 3)
            flat[gidx] = np.clip(self._bg_flat[gidx] + shade + np.float32(0.5), 0, 255).astype(np.uint8)
            return img
        coarse = np.zeros((ch * cw, 3), np.float32)
        coarse[sel] = shade
        delta = self._cv2.resize(coarse.reshape(ch, cw, 3), (cw * k, ch * k), interpolation=self._cv2.INTER_LINEAR)
        hh, ww = r1 - r0, c1 - c0
        region = self.background[r0:r1, c0:c1] + delta[:hh, :ww]
        region += np.float32(0.5)
        np.clip(region, 0, 255, out=region)
        img[r0:r1, c0:c1] = region.astype(np.uint8)
        return img

    def render(self, indentation: float, position=(0.0, 0.0), tilt: float = 0.0, t: float = 0.0
               ) -> tuple[np.ndarray, _gel.GelSurface]:
        d = max(float(indentation), 0.0)
        key = (d, float(position[0]), float(position[1]), float(tilt)) if d > 0 else (0.0,)
        _check_tilt("tilt", float(tilt))  # (and a contact off the gel: by surface(), for each new pose)
        if key != self._key:
            self._surface = self.surface(d, position, tilt)
            # shared by every step at this pose (and by every consumer): read-only
            self._surface.depth.flags.writeable = False
            self._surface.mask.flags.writeable = False
            self._clean = self.clean_image(self._surface, d, float(tilt))
            self.max_depth = float(self._surface.depth.max())
            self._key = key
            self.renders += 1
        img = self._clean
        offset = self.drift * math.sin(2 * math.pi * t / self.drift_period + self.drift_phase) if self.drift else 0.0
        if self._noise_buf is None and offset == 0.0:
            return img.copy(), self._surface
        acc = img.astype(np.int16)
        if self._noise_buf is not None:
            o = int(self.rng.integers(0, self._noise_buf.size - self._npix + 1))
            acc += self._noise_buf[o:o + self._npix].reshape(acc.shape)
        if offset:
            acc += np.int16(round(offset))
        return np.clip(acc, 0, 255).astype(np.uint8), self._surface


def load_height_map(path: str | None) -> np.ndarray:
    """An indenter height map (``indenter: map``): a 2-D float array in a .npy file (m above the lowest point).
    ValueError naming the file and what was expected: none given, missing, a folder, not .npy data, pickled
    (object) data (numpy's advice to load it unsafely is not passed on), not 2-D, no finite value."""
    if not path:
        raise ValueError("indenter=map needs indenter_map (a .npy height map in m)")
    p = Path(path).expanduser()
    what = "expected a .npy file of a 2-D float array of heights in m (numpy.save)"
    if not p.exists():
        raise ValueError(f"indenter_map {path!r} does not exist{looked_at(p)}; {what}")
    if p.is_dir():
        raise ValueError(f"indenter_map {path!r} is a folder; {what}")
    try:
        surface = np.load(p, allow_pickle=False)
    except ValueError as e:
        why = "it holds pickled (object) data" if "pickle" in str(e) else str(e)
        raise ValueError(f"indenter_map {path!r}: cannot read the height map ({why}); {what}") from None
    except OSError as e:
        raise ValueError(f"indenter_map {path!r}: cannot read the height map ({e.strerror or e}); {what}") from None
    if not isinstance(surface, np.ndarray) or surface.dtype.kind not in "fiu":
        raise ValueError(f"indenter_map {path!r}: not a numeric array; {what}")
    try:
        _gel.Indenter.from_height_map(surface, 1e-4)   # (its checks: 2-D, a finite value)
    except ValueError as e:
        raise ValueError(f"indenter_map {path!r}: {e}; {what}") from None
    return surface


class SimDigit(Component):
    """Simulated DIGIT: realistic images from the optical model of a real DIGIT, with ground truth."""

    name = "sim-digit"
    kind = Kind.SENSOR
    default_rate = 60.0
    inputs = {
        "indentation": Port("float64", (), "m", "how far the indenter presses into the gel (<= 0: no contact)",
                            required=False, max_age=INPUT_MAX_AGE),
        "position": Port("float64", (2,), "m", "indenter centre from the image centre (x along columns, y rows); "
                         "on the image", required=False, max_age=INPUT_MAX_AGE),
        "tilt": Port("float64", (), "rad", "indenter tilt about the axis along the rows (at most 45 deg)",
                     required=False, max_age=INPUT_MAX_AGE),
    }
    outputs = {
        "image": Port("uint8", (None, None, 3), "", "BGR, portrait (QVGA 320x240, VGA 640x480)"),
        "gt_depth": Port("float32", (None, None), "m", "true gel depth map, positive into the gel"),
        "gt_max_depth": Port("float64", (), "m", "maximum of gt_depth"),
        "gt_force": Port("float64", (), "N", "normal force of the gel model"),
        "gt_contact_mask": Port("bool", (None, None), "", "pixels where the gel touches the indenter"),
        "gt_position": Port("float64", (2,), "m", "indenter axis from the image centre (x along columns, y along "
                            "rows): the contact centre of a sphere and of an untilted probe or punch; NaN without "
                            "contact"),
    }

    class Params(Params):
        resolution: Literal["qvga", "vga"] = Field("qvga", description="qvga: 320x240 rows x cols, vga: 640x480")
        m_per_px: Meters | None = Field(None, gt=0, description="pixel size (default 1/17150 m at QVGA, "
                                        "0.0266 mm at VGA)", json_schema_extra={"unit": "m"})
        indenter: Literal["sphere", "probe", "flat", "map"] = Field("sphere", description="indenter shape")
        indenter_radius: Meters | None = Field(None, gt=0, description="sphere/flat/probe radius (default 3 mm; "
                                               "probe 5 mm)", json_schema_extra={"unit": "m"})
        tip_radius: Meters = Field(0.010, gt=0, description="radius of the probe's curved tip",
                                   json_schema_extra={"unit": "m"})
        indenter_map: str | None = Field(None, description=".npy height map (m above the lowest point) for "
                                         "indenter=map")
        indenter_map_m_per_px: Meters | None = Field(None, gt=0, description="sample spacing of indenter_map "
                                                     "(default: the image's)", json_schema_extra={"unit": "m"})
        modulus: Pascals = Field(_gel.DEFAULT_MODULUS, gt=0, description="gel Young's modulus (Shore 10A ~0.41 MPa)",
                                 json_schema_extra={"unit": "Pa"})
        poisson: float = Field(0.5, ge=0, le=0.5, description="gel Poisson ratio")
        gel_thickness: Meters | None = Field(None, gt=0, description="apply the bonded thin-layer correction for "
                                             "this thickness (None: half space)", json_schema_extra={"unit": "m"})
        deformation: bool = Field(True, description="gel sags around the contact (False: rigid cap)")
        smoothing: Meters = Field(0.08e-3, ge=0, description="blur of the surface seen through the gel",
                                  json_schema_extra={"unit": "m"})
        indentation: Meters = Field(0.0, description="static indentation when the input is not wired",
                                    json_schema_extra={"unit": "m"})
        position: tuple[Meters, Meters] = Field((0.0, 0.0), description="static indenter position (x, y) in m, "
                                                "e.g. [0.002, -0.001] or '2mm, -1mm'")
        tilt: Radians = Field(0.0, description="static tilt", json_schema_extra={"unit": "rad"})
        noise: float = Field(0.0, ge=0, le=32, description="std of pixel noise (intensity levels, at most 32: a "
                             "real DIGIT's is 1-2)")
        drift: float = Field(0.0, ge=0, le=255, description="amplitude of global illumination drift (intensity "
                             "levels)")
        drift_period: Seconds = Field(10.0, gt=0, description="period of the illumination drift",
                                      json_schema_extra={"unit": "s"})
        unit_variation: float = Field(0.0, ge=0, le=3, description="per-unit variation (0: the reference DIGIT; "
                                      "1: typical spread of LED colour, gain, centring and gel blur)")
        seed: int = Field(0, ge=0, description="random seed (noise, drift phase, unit variation), drawn per unit")
        unit: str | None = Field(None, min_length=1, description="which physical DIGIT this node is: its noise, "
                                 "drift phase and unit variation come from (seed, unit). Default: the node's id, so "
                                 "two nodes of a graph draw independent noise; one unit for two nodes makes them one "
                                 "sensor; 'sim-digit' (a node made outside a graph) draws the seed's own stream")
        background: str | None = Field(None, description="background image or folder of no-contact frames "
                                       "(default: the shipped real frame)")
        optical_model: str | None = Field(None, description="polynomial table .npz (default: the shipped one)")
        render_stride: int = Field(2, ge=1, le=4, description="shade every n-th pixel and interpolate (1: every "
                                   "pixel; 2 is 4x cheaper and indistinguishable at the gel's blur)")

        @field_validator("position", mode="before")
        @classmethod
        def _pos(cls, v: Any) -> Any:
            if isinstance(v, str):
                # "2mm, -1mm" or "2 mm, -1 mm" (comma-separated); "0.002 -0.001" (plain numbers, spaces)
                parts = [p.strip() for p in v.split(",")] if "," in v else v.split()
                v = [parse_quantity(p, "m") for p in parts if p]
            if isinstance(v, (list, tuple)) and len(v) != 2:
                raise ValueError(f"position needs two values (x, y) in m, got {v!r}")
            return v

        @field_validator("indenter_radius", "tip_radius", "m_per_px", "indenter_map_m_per_px", "smoothing",
                         "gel_thickness", "indentation", "position")
        @classmethod
        def _plausible_length(cls, v: Any, info) -> Any:
            for x in (v if isinstance(v, tuple) else (v,)):
                if x is not None:
                    _check_length(info.field_name, x)
            return v

        @field_validator("tilt")
        @classmethod
        def _tilt(cls, v: float) -> float:
            _check_tilt("tilt", v)
            return v

        @field_validator("modulus")
        @classmethod
        def _modulus(cls, v: float) -> float:
            why = _gel.modulus_problem(v)
            if why:
                raise ValueError(why)
            return v

        @model_validator(mode="after")
        def _scale(self):
            why = scale_problem(self.m_per_px or M_PER_PX[self.resolution], self.smoothing)
            if why:
                raise ValueError(why)
            return self

        @model_validator(mode="after")
        def _height_map(self):
            """indenter: map needs a readable height map: checked when the graph is validated (`validate` said OK,
            and the run failed at start-up)."""
            if self.indenter == "map":
                load_height_map(self.indenter_map)
            return self

        @model_validator(mode="after")
        def _indentation_within_gel(self):
            h = self.gel_thickness
            if h is not None and self.indentation >= h:
                raise ValueError(f"indentation ({self.indentation * 1e3:g} mm) reaches through the gel "
                                 f"(gel_thickness {h * 1e3:g} mm)")
            return self

    @classmethod
    def port_shapes(cls, params: Any) -> dict[str, tuple]:
        """The image and ground-truth maps are ``resolution``'s size (portrait rows x cols): checked against a
        consumer's (a depth model's) when the graph is validated."""
        from .optics import RESOLUTIONS

        rows, cols = RESOLUTIONS[params.resolution]
        why = f"resolution {params.resolution!r}"
        how = "set resolution: " + " or ".join(f"{k} ({r}x{c})" for k, (r, c) in RESOLUTIONS.items())
        return {"image": ((rows, cols, 3), why, how), "gt_depth": ((rows, cols), why, how),
                "gt_contact_mask": ((rows, cols), why, how)}

    def configure(self) -> None:
        p = self.params
        self.sim = DigitSimulator(
            resolution=p.resolution, m_per_px=p.m_per_px, indenter=self._indenter(),
            material=_gel.GelMaterial(p.modulus, p.poisson, p.gel_thickness), smoothing=p.smoothing,
            deformation=p.deformation, noise=p.noise, drift=p.drift, drift_period=p.drift_period,
            unit_variation=p.unit_variation, seed=p.seed, background=p.background, optical_model=p.optical_model,
            stride=p.render_stride, stream=p.unit if p.unit is not None else self.id)
        self._force = _gel.force_law(self.sim.indenter, self.sim.material)  # gel_force, constants computed once
        self._last: dict[str, float] = {}
        try:
            self.sim.check_on_gel(p.position)
        except ValueError as e:
            raise ValueError(f"position: {e}") from None

    def _indenter(self) -> _gel.Indenter:
        p = self.params
        if p.indenter == "map":
            try:
                surface = load_height_map(p.indenter_map)
            except ValueError as e:   # (removed since the graph was validated)
                raise ModelFileError(str(e)) from None
            mpp = p.indenter_map_m_per_px or p.m_per_px or M_PER_PX[p.resolution]
            try:
                return _gel.Indenter.from_height_map(surface, mpp)
            except ValueError as e:
                raise ModelFileError(f"{p.indenter_map}: {e}") from None
        radius = p.indenter_radius or DEFAULT_RADIUS[p.indenter]
        if p.indenter == "probe":
            return _gel.Indenter.probe(radius, p.tip_radius)
        return _gel.Indenter.sphere(radius) if p.indenter == "sphere" else _gel.Indenter.flat(radius)

    def step(self, t: float, inputs) -> dict[str, Any]:
        p = self.params
        d = _finite(inputs.value("indentation", p.indentation), "indentation")
        if not abs(d) <= MAX_LENGTH["indentation"]:
            raise ValueError(f"indentation input ({d:g} m) is larger than {MAX_LENGTH['indentation'] * 1e3:g} mm, "
                             f"which no DIGIT setup has: the input is in m (its producer sends mm?)")
        if p.gel_thickness is not None and d >= p.gel_thickness:
            raise ValueError(f"indentation {d * 1e3:.4g} mm reaches through the gel (gel_thickness "
                             f"{p.gel_thickness * 1e3:.4g} mm)")
        pos = inputs.value("position", p.position)
        pos = np.array(pos, np.float64).reshape(-1)  # a copy: gt_position must not alias the producer's array
        if pos.shape != (2,) or not np.isfinite(pos).all():
            raise ValueError(f"position must be two finite values (x, y) in m, got {pos!r}")
        tilt = _finite(inputs.value("tilt", p.tilt), "tilt")
        img, surf = self.sim.render(d, pos, tilt, t)    # refuses a tilt beyond MAX_TILT, a contact off the gel
        force = self._force(max(d, 0.0)) if tilt == 0.0 else self.sim.force(max(d, 0.0), tilt)
        max_depth = self.sim.max_depth if d > 0 else 0.0
        # the simulation's truth ("true_": the live view shows it beside the depth node's estimate of max depth)
        self._last = {"true_indentation_m": max(d, 0.0), "true_force_n": force, "true_max_depth_m": max_depth}
        return {"image": img, "gt_depth": surf.depth, "gt_max_depth": max_depth, "gt_force": force,
                "gt_contact_mask": surf.mask, "gt_position": pos if d > 0 else np.full(2, np.nan)}

    def status(self) -> dict[str, Any]:
        return dict(self._last)


def _check_length(name: str, value: float) -> None:
    """A length parameter beyond MAX_LENGTH[name] is millimetres typed in a metre field: say so."""
    why = _gel.length_problem(name, value, MAX_LENGTH[name])
    if why:
        raise ValueError(why)


def scale_problem(m_per_px: float, smoothing: float) -> str | None:
    """None if the pixel size (m) and the blur (m) can be rendered; else why not (a pixel size no DIGIT setup has,
    or a blur so many pixels wide that its matrix would not fit in memory)."""
    if not m_per_px >= MIN_M_PER_PX:
        return (f"m_per_px ({m_per_px:g} m) is below {MIN_M_PER_PX * 1e3:g} mm, which no DIGIT setup has (QVGA "
                f"{M_PER_PX['qvga'] * 1e3:.4g} mm, VGA {M_PER_PX['vga'] * 1e3:.4g} mm): an exponent off?")
    px = smoothing / m_per_px
    if px > MAX_SMOOTHING_PX:
        return (f"smoothing ({smoothing * 1e3:g} mm) is a blur of {px:.4g} px at m_per_px {m_per_px * 1e3:.4g} mm: "
                f"expected at most {MAX_SMOOTHING_PX} px (a wider blur leaves no contact to see and takes gigabytes "
                f"to render)")
    return None


def _check_tilt(name: str, value: float) -> None:
    if not abs(value) <= MAX_TILT:
        raise ValueError(f"{name} ({value:g} rad = {math.degrees(value):.4g} deg) is beyond +-45 deg "
                         f"({MAX_TILT:.4g} rad): the gel model tilts the indenter's face only; degrees typed as "
                         f"radians? write \"{value:g}deg\"")


def _finite(v: Any, what: str) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise ValueError(f"{what} must be finite, got {f!r}")
    return f


@hookimpl
def teletouch_components():
    return [SimDigit]
