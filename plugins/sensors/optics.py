"""Optical model of a real DIGIT: render a camera image from a gel height map.

The model is Taxim's polynomial table (vocdex/Taxim, MIT), fitted on ball presses of a real DIGIT at VGA: for a
surface point with gradient angle m = arctan(|grad z|) and direction d = atan2(dz/drow, dz/dcol) the intensity change
of each channel at pixel (x = column, y = row of the 640 x 480 portrait image) is c0 x^2 + c1 y^2 + c2 x y + c3 x +
c4 y + c5 with c = table[channel, m_bin, d_bin]. Channel k of the table applies to OpenCV's channel k (B, G, R).
Rendering adds (table(gradient) - table(flat)) to a real background frame, so an untouched gel is exactly the
background. Coordinates of other resolutions are scaled to the 640 x 480 frame.

Package data (plugins/sensors/data/, from ../shared/data, MIT, see data/README.md): ``polycalib.npz`` (the table,
float32), ``background_qvga.png`` (per-pixel median of the 10 digit-presses-qvga images, the paper's DIGIT) and
``background_vga.png`` (per-pixel median of the digit-presses-vga frames, the DIGIT the table was fitted on).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from teletouch.errors import ModelFileError

DATA = Path(__file__).resolve().parent / "data"
TABLE_FILE = DATA / "polycalib.npz"
BINS = 125
TABLE_ROWS, TABLE_COLS = 640, 480  # portrait VGA frame the table's pixel coordinates refer to
#: (rows, cols) of each resolution, portrait
RESOLUTIONS = {"qvga": (320, 240), "vga": (640, 480)}


def load_table(path: str | Path | None = None) -> np.ndarray:
    """The table as float32 (3, bins, bins, 6), channels in OpenCV order (B, G, R)."""
    p = Path(path) if path is not None else TABLE_FILE
    try:
        with np.load(p) as z:
            t = np.stack([np.asarray(z[k], np.float32) for k in ("grad_r", "grad_g", "grad_b")])
    except FileNotFoundError:
        raise ModelFileError(f"{p}: optical model not found") from None
    except KeyError as e:
        raise ModelFileError(f"{p}: optical model lacks array {e}; expected grad_r, grad_g, grad_b") from None
    except Exception as e:  # zip/pickle errors
        raise ModelFileError(f"{p}: cannot read optical model ({e})") from None
    if t.shape[1:] != (BINS, BINS, 6):
        raise ModelFileError(f"{p}: optical table has shape {t.shape[1:]}, expected ({BINS}, {BINS}, 6)")
    if not np.isfinite(t).all():
        raise ModelFileError(f"{p}: optical table holds non-finite values")
    return t


def load_background(resolution: str = "qvga", path: str | Path | None = None) -> np.ndarray:
    """A real no-contact frame as float32 BGR (rows, cols, 3), resized to ``resolution`` if needed."""
    import cv2

    rows, cols = RESOLUTIONS[resolution]
    p = Path(path) if path is not None else DATA / f"background_{resolution}.png"
    if p.is_dir():
        img = median_background(p)
    else:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise ModelFileError(f"{p}: cannot read background image (missing or not an image)")
    if img.shape[1] > img.shape[0]:  # a landscape frame (of any size): rotate to the portrait convention first
        img = np.ascontiguousarray(np.rot90(img))
    h, w = img.shape[:2]
    if abs((h / w) / (rows / cols) - 1.0) > 0.02:
        raise ModelFileError(f"{p}: background is {h} x {w} px (rows x cols, after turning it portrait), not the "
                             f"DIGIT's 4:3 ({rows} x {cols} for {resolution}): it would be stretched")
    if img.shape[:2] != (rows, cols):
        img = cv2.resize(img, (cols, rows), interpolation=cv2.INTER_AREA)
    return img.astype(np.float32)


def median_background(folder: str | Path) -> np.ndarray:
    """Per-pixel median (uint8 BGR) of the images in a folder: a clean background when the contact moves."""
    import cv2

    files = sorted(f for f in Path(folder).iterdir() if f.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp"))
    imgs = [cv2.imread(str(f), cv2.IMREAD_COLOR) for f in files]
    imgs = [i for i in imgs if i is not None]
    if not imgs:
        raise ModelFileError(f"{folder}: no readable images for a background")
    shape = imgs[0].shape
    imgs = [i for i in imgs if i.shape == shape]
    return np.median(np.stack(imgs), axis=0).astype(np.uint8)


class OpticalRenderer:
    """Renders the intensity change caused by a height map.

    ``gain`` (3,) scales each channel's response (per-unit variation); ``offset_px`` shifts the optical centre of the
    polynomial (per-unit variation of the LED placement), in pixels of this resolution.
    """

    def __init__(self, table: np.ndarray, shape: tuple[int, int], gain: np.ndarray | None = None,
                 offset_px: tuple[float, float] = (0.0, 0.0)):
        rows, cols = shape
        self.shape = (int(rows), int(cols))
        self.sy, self.sx = TABLE_ROWS / rows, TABLE_COLS / cols
        self.offset = (float(offset_px[0]), float(offset_px[1]))
        g = np.ones(3, np.float32) if gain is None else np.asarray(gain, np.float32).reshape(3)
        t = table.astype(np.float32) * g[:, None, None, None]
        flat = t[:, 0, _DIR_FLAT, :]  # (3, 6): the bin of a zero gradient
        # table relative to the flat surface, one row of 18 per bin: coefficient j of channel k at column 3 j + k
        rel = (t - flat[:, None, None, :]).transpose(1, 2, 3, 0).reshape(BINS * BINS, 18)
        self.rel = np.ascontiguousarray(rel)
        self.flat_index = 0 * BINS + _DIR_FLAT

    @staticmethod
    def bins(gr: np.ndarray, gc: np.ndarray) -> np.ndarray:
        """Flat table index (m_bin * bins + d_bin) of slopes gr = dz/drow, gc = dz/dcol (dimensionless)."""
        m = np.arctan(np.sqrt(gr * gr + gc * gc))
        d = np.arctan2(gr, gc)
        mb = np.minimum((m * (124.0 / (0.5 * math.pi))).astype(np.int32), BINS - 1)
        db = np.minimum(((d + math.pi) * (124.0 / (2 * math.pi))).astype(np.int32), BINS - 1)
        return mb * BINS + db

    def shade(self, index: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Intensity change (float32 (n, 3), BGR) of table bins ``index`` at pixels (rows, cols) of this image."""
        x = ((cols.astype(np.float32) + np.float32(self.offset[0])) * np.float32(self.sx))[:, None]
        y = ((rows.astype(np.float32) + np.float32(self.offset[1])) * np.float32(self.sy))[:, None]
        c = np.take(self.rel, index, axis=0)  # = self.rel[index], several times faster for rows
        # c0 x^2 + c1 y^2 + c2 x y + c3 x + c4 y + c5, in Horner form
        return c[:, 15:18] + x * (c[:, 9:12] + x * c[:, 0:3] + y * c[:, 6:9]) + y * (c[:, 12:15] + y * c[:, 3:6])

    def delta(self, depth_m: np.ndarray, m_per_px: float, window: tuple[int, int, int, int] | None = None
              ) -> np.ndarray:
        """Intensity change (float32 (h, w, 3), BGR) over ``window`` = (r0, r1, c0, c1) of a depth map (m)."""
        rows, cols = depth_m.shape
        r0, r1, c0, c1 = window if window is not None else (0, rows, 0, cols)
        # one pixel of margin for the central differences
        R0, R1, C0, C1 = max(r0 - 1, 0), min(r1 + 1, rows), max(c0 - 1, 0), min(c1 + 1, cols)
        z = depth_m[R0:R1, C0:C1].astype(np.float32) * np.float32(1.0 / m_per_px)
        gr, gc = np.gradient(z) if min(z.shape) > 1 else (np.zeros_like(z), np.zeros_like(z))
        sl = (slice(r0 - R0, r0 - R0 + (r1 - r0)), slice(c0 - C0, c0 - C0 + (c1 - c0)))
        idx = self.bins(gr[sl], gc[sl]).ravel()
        out = np.zeros((idx.size, 3), np.float32)
        # slopes in the first angle bin (< 0.73 deg) render as the flat gel: that bin's direction is meaningless
        sel = np.flatnonzero(idx >= BINS)
        if sel.size:
            w = c1 - c0
            out[sel] = self.shade(idx[sel], sel // w + r0, sel % w + c0)
        return out.reshape(r1 - r0, c1 - c0, 3)


class RadialBlur:
    """Exact 2-D Gaussian blur of a radially symmetric profile sampled every ``h`` px from r = 0, as a banded
    matrix: g(r) = int f(r') r' / s^2 exp(-(r - r')^2 / 2 s^2) i0e(r r' / s^2) dr' (rows normalised to 1)."""

    def __init__(self, sigma_px: float, h: float, n: int):
        from scipy.special import i0e

        self.h, self.n = h, n
        half = int(math.ceil(4.0 * sigma_px / h)) if sigma_px > 0 else 0
        offs = np.arange(-half, half + 1)
        i = np.arange(n)[:, None]
        j = i + offs[None, :]
        valid = (j >= 0) & (j < n)
        jc = np.clip(j, 0, n - 1)
        if sigma_px > 0:
            r, rp = i * h, jc * h
            s2 = sigma_px * sigma_px
            w = np.where(valid, rp / s2 * np.exp(-((r - rp) ** 2) / (2 * s2)) * i0e(r * rp / s2), 0.0)
            w[0] = np.where(offs == 0, 1.0, 0.0) if w[0].sum() <= 0 else w[0]
            w /= w.sum(axis=1, keepdims=True)
        else:
            w = (offs[None, :] == 0).astype(np.float64) * np.ones((n, 1))
        self.index = jc.astype(np.int32)
        self.weight = w.astype(np.float32)

    def __call__(self, f: np.ndarray) -> np.ndarray:
        m = f.shape[0]
        if m > self.n:
            raise ValueError(f"profile of {m} samples is longer than the blur's {self.n}")
        idx = np.minimum(self.index[:m], m - 1)
        return (f[idx] * self.weight[:m]).sum(axis=1)


_DIR_FLAT = int((0.0 + math.pi) * (124.0 / (2 * math.pi)))  # direction bin of atan2(0, 0) = 0 -> 62
