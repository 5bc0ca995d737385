"""Depth calibration from ball presses: background, automatic contact labels, ground-truth normals, training, metrics.

Used by ``teletouch calibrate depth`` (plugins/estimators/depth.py), by benchmarks/depth_accuracy.py and by
scripts/make_sim_depth_model.py, so every model is made by the same code.

Labels CSV (the format of ../shared/data/digit-presses-*/labels.csv): ``image,center_x,center_y,radius_px[,note]``
with x = column and y = row in pixels of the full-resolution image; an empty radius or a note starting with
"uncertain" or "no contact" excludes the press from training (a "no contact" row marks a background frame).
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from teletouch.errors import ModelFileError
from teletouch.reproducible import build_time, software_versions, source_date_epoch
from teletouch.units import UNDERSCORE

from .normal_model import (DEFAULT_FEATURES, DEFAULT_HIDDEN, NormalModel, atomic_write, feature_count, make_net,
                           max_stride)

__all__ = [
    "IMAGE_EXTS", "Label", "load_images", "median_background", "median_frames", "Background", "background_files",
    "resolved_path", "load_background", "MAX_BACKGROUND_FRAMES", "auto_label", "read_labels", "write_labels",
    "check_labels", "review_overlay", "pool_grid", "grid_images", "press_samples", "train_model", "cap_height_error",
    "sphere_fit_radius",
    "far_false_depth", "evaluate_press", "px_per_mm_from_caliper", "default_stride", "calibrate",
]

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass
class Label:
    image: str
    cx: float | None            # column, px (full resolution)
    cy: float | None            # row, px
    r: float | None             # contact radius, px
    note: str = ""
    line: int | None = field(default=None, compare=False, repr=False)   # line in the labels CSV it was read from

    @property
    def uncertain(self) -> bool:
        return (self.r is None or self.cx is None or self.cy is None or self.note.lower().startswith("uncertain")
                or (self.r <= 0 and not self.no_contact))

    @property
    def no_contact(self) -> bool:
        """A frame without contact (trained as flat everywhere): only when the note says so. A radius of 0 alone
        does not make one (:func:`read_labels` refuses it): an "uncertain" press with radius 0 was trained as a
        flat frame, teaching the network that its colour change means no slope."""
        return self.note.lower().startswith("no contact")

    @property
    def usable(self) -> bool:
        return not self.uncertain and not self.no_contact


# --- images and background -------------------------------------------------------------------------------------

def load_images(folder: str | os.PathLike[str], names: Iterable[str] | None = None) -> list[tuple[str, np.ndarray]]:
    """(name, uint8 BGR image) for every image in ``folder`` (sorted naturally), or for the given names.

    Refused with an error naming the file: an unreadable image, a grayscale one (the network reads colour: its
    three channels equal), images of different sizes (the odd ones out are named) and two images identical pixel
    for pixel (a copied press: it would count twice in the median background and could be trained on and held out
    at once). An alpha channel is dropped."""
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder of press images")
    if names is None:
        files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and ".review" not in p.name]
        files.sort(key=lambda p: _natural_key(p.name))
    else:
        files = [folder / n for n in names]
    out = []
    seen: dict[bytes, str] = {}
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"{p}: not a readable image (expected PNG/JPEG, {', '.join(IMAGE_EXTS)})")
        if is_grayscale(img):
            raise ValueError(f"{p}: a grayscale image (its three colour channels are equal); expected a colour "
                             f"frame of the DIGIT as its camera delivers it (the depth model reads the colours)")
        digest = hashlib.sha1(np.ascontiguousarray(img).data).digest()
        if digest in seen and np.array_equal(img, dict(out)[seen[digest]]):
            raise ValueError(f"{folder / seen[digest]} and {p.name} are identical pixel for pixel; remove the copy (a "
                             f"press counted twice biases the median background and the training)")
        seen.setdefault(digest, p.name)
        out.append((p.name, img))
    if not out:
        raise FileNotFoundError(f"{folder}: no images ({', '.join(IMAGE_EXTS)})")
    sizes: dict[tuple[int, ...], list[str]] = {}
    for n, im in out:
        sizes.setdefault(im.shape[:2], []).append(n)
    if len(sizes) != 1:
        common = max(sizes, key=lambda k: len(sizes[k]))
        odd = "; ".join(f"{', '.join(ns[:5])}{' ...' if len(ns) > 5 else ''} {k[0]}x{k[1]}"
                        for k, ns in sizes.items() if k != common)
        raise ValueError(f"{folder}: images differ in size: {len(sizes[common])} are {common[0]}x{common[1]} (rows x "
                         f"cols), but {odd}; all presses must share one resolution")
    return out


def is_grayscale(image: np.ndarray) -> bool:
    """True for an image whose three channels are equal within 2 levels (a grayscale frame saved as colour, or
    expanded to BGR by OpenCV): no colour to learn from. Asked of every frame by the depth node, so a colour frame is
    told on every 4th row and column first (~8 us for QVGA against ~70 us for all of it); only an image gray there is
    checked in full, which gives the same answer."""
    if image.ndim == 2:
        return True
    return _equal_channels(image[::4, ::4]) and _equal_channels(image)


def _equal_channels(image: np.ndarray) -> bool:
    b, g, r = (image[..., i].astype(np.int16) for i in range(3))
    return bool(np.abs(b - g).max() <= 2 and np.abs(g - r).max() <= 2)


def _natural_key(name: str) -> list[Any]:
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def median_background(images: Sequence[np.ndarray]) -> np.ndarray:
    """Per-pixel median of the presses: a clean background when the ball sits elsewhere in each image."""
    if len(images) < 3:
        raise ValueError("the background can be estimated from 3 or more presses (give --background otherwise)")
    return median_frames(images)


def median_frames(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Per-pixel median (uint8, rounded half to even) of one or more frames of one shape; one frame is returned as
    it is (a copy), two give their mean. Computed in bands of rows, so that the float work array stays small."""
    if not frames:
        raise ValueError("no frames to take the median of")
    shape = frames[0].shape
    if any(f.shape != shape for f in frames):
        raise ValueError(f"frames of different shapes: {sorted({f.shape for f in frames})}")
    if len(frames) == 1:
        return np.array(frames[0], dtype=np.uint8, copy=True)
    stack = np.stack(frames)
    out = np.empty(shape, np.uint8)
    band = max(1, (1 << 22) // max(1, stack[0, :1].size * len(frames)))   # ~4 M values (32 MiB float64) a band
    for r0 in range(0, shape[0], band):
        out[r0:r0 + band] = np.median(stack[:, r0:r0 + band], axis=0).round()
    return out


#: most no-contact frames one background is made from: the noise falls as 1 / sqrt(N) (10 frames take it to a third,
#: docs/depth.md "A background from several no-contact frames"); more add little, and all are held in memory at once
MAX_BACKGROUND_FRAMES = 100


@dataclass
class Background:
    """A no-contact background (uint8 BGR) and the frames it was made from (``--background``)."""

    image: np.ndarray
    files: list[Path]
    sources: list[str]          # the paths as given (frames and folders), for messages

    @property
    def frames(self) -> int:
        return len(self.files)

    def describe(self) -> str:
        """What the background is, for the log: 'the frame F' or 'per-pixel median of N frames from DIR'."""
        if self.frames == 1:
            return f"the frame {self.files[0]}"
        what = "per-pixel median" if self.frames >= 3 else "per-pixel median (the mean)"
        folders = [s for s in self.sources if Path(s).is_dir()]
        if len(self.sources) == 1 and folders:
            return f"{what} of {self.frames} frames from {folders[0]}"
        names = ", ".join(str(f) for f in self.files[:4]) + (" ..." if self.frames > 4 else "")
        return f"{what} of {self.frames} frames ({names})"

    def meta(self) -> dict[str, Any]:
        """The model file's record of it (``training.background``): file names only, no machine paths, so that a
        reproducible calibration (SOURCE_DATE_EPOCH) gives the same bytes from another folder."""
        return {"from": "no-contact frames", "frames": self.frames,
                "statistic": "frame" if self.frames == 1 else "per-pixel median",
                "files": [f.name for f in self.files]}


def resolved_path(p: str | os.PathLike[str]) -> Path:
    """The path with links and ``..`` resolved, to tell the same file given two ways; the absolute path where it
    cannot be resolved (a loop of links)."""
    try:
        return Path(p).resolve()
    except OSError:
        return Path(p).absolute()


def background_files(paths: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """The frames named by ``--background``: each path a frame, or a folder (all its images, sorted naturally, as
    :func:`load_images` lists a folder). FileNotFoundError for an empty folder, ValueError for a frame named twice
    (also through a folder); a path that is neither a folder nor a file is kept, its reading names it."""
    files: list[Path] = []
    seen: dict[Path, str] = {}
    for given in paths:
        p = Path(given)
        if p.is_dir():
            found = [q for q in p.iterdir() if q.suffix.lower() in IMAGE_EXTS and ".review" not in q.name
                     and q.is_file()]
            if not found:
                raise FileNotFoundError(f"{p}: no images ({', '.join(IMAGE_EXTS)}) in this background folder; "
                                        f"expected no-contact frames of the sensor")
            found.sort(key=lambda q: _natural_key(q.name))
        else:
            found = [p]
        for q in found:
            key = resolved_path(q)
            if key in seen:
                raise ValueError(f"{q}: given twice as a background frame (also as {seen[key]}); each frame counts "
                                 f"once in the median")
            seen[key] = str(q)
            files.append(q)
    return files


def load_background(paths: Sequence[str | os.PathLike[str]],
                    check_frame: Callable[[Path, np.ndarray], None] | None = None) -> Background:
    """The background from one or more no-contact frames (``--background``: frames and/or folders of them): one
    frame as it is, several as their per-pixel median (:func:`median_frames`; two: their mean).

    Refused with an error naming the file: nothing given, an unreadable image, one ``check_frame(path, image)``
    refuses (the caller's size check: the presses' or the model's), a grayscale one, frames of different sizes (both
    sizes and files named), two frames identical pixel for pixel (a copy: it would count twice), more than
    MAX_BACKGROUND_FRAMES frames."""
    import cv2

    if not paths:
        raise ValueError("--background: no frame given; expected a no-contact frame or a folder of them")
    files = background_files(paths)
    if len(files) > MAX_BACKGROUND_FRAMES:
        raise ValueError(f"{', '.join(str(p) for p in paths)}: {len(files)} background frames; at most "
                         f"{MAX_BACKGROUND_FRAMES} are used (10-20 no-contact frames take the noise to a third or "
                         f"less); give a folder with fewer")
    frames: list[np.ndarray] = []
    seen: dict[bytes, int] = {}
    for i, f in enumerate(files):
        # not read when it is no file: OpenCV warns on stderr about a path it cannot open
        img = cv2.imread(str(f), cv2.IMREAD_COLOR) if f.is_file() else None
        if img is None:
            why = "" if f.is_file() else " (no such file or folder)"
            raise FileNotFoundError(f"{f}: not a readable image file{why}; expected a no-contact frame "
                                    f"({', '.join(IMAGE_EXTS)}) or a folder of them")
        if check_frame is not None:
            check_frame(f, img)
        if is_grayscale(img):
            raise ValueError(f"{f}: a grayscale image (its three colour channels are equal); expected a colour "
                             f"no-contact frame of the DIGIT as its camera delivers it")
        if frames and img.shape != frames[0].shape:
            raise ValueError(f"{f} is {img.shape[0]}x{img.shape[1]}, but {files[0]} is {frames[0].shape[0]}x"
                             f"{frames[0].shape[1]} (rows x cols); all background frames must share one resolution")
        digest = hashlib.sha1(np.ascontiguousarray(img).data).digest()
        if digest in seen and np.array_equal(img, frames[seen[digest]]):
            raise ValueError(f"{f} and {files[seen[digest]]} are identical pixel for pixel: a copy (it would count "
                             f"twice in the median); give each no-contact frame once")
        seen.setdefault(digest, i)
        frames.append(img)
    return Background(median_frames(frames), files, [str(p) for p in paths])


def default_stride(rows: int) -> int:
    """Work-grid stride so that the grid is about 160 rows (QVGA 2, VGA 4)."""
    return max(1, int(round(rows / 160)))


# --- automatic labelling ---------------------------------------------------------------------------------------

def _change_map(image: np.ndarray, background: np.ndarray, sigma: float) -> np.ndarray:
    """Smoothed colour change |frame - background| summed over channels, with slow drift removed (high-pass)."""
    import cv2

    d = image.astype(np.float32) - background.astype(np.float32)
    d -= np.median(d[::4, ::4].reshape(-1, 3), axis=0)
    big = max(9.0, 6.0 * sigma)
    d -= cv2.GaussianBlur(d, (0, 0), big)
    s = np.abs(d).sum(axis=2)
    return cv2.GaussianBlur(s, (0, 0), sigma)


def auto_label(name: str, image: np.ndarray, background: np.ndarray, ball_radius_px: float,
               level: float = 0.35) -> Label:
    """Find the contact circle (centre, equal-area radius) of one press; flag what it is unsure of.

    The colour-change map (drift high-passed, smoothed) of a ball press is an annulus (the flat centre of the cap
    barely changes colour), so it is first closed (grey-level morphology over 0.6 ball radii) to fill the centre;
    then thresholded at ``level`` x its robust peak; the region holding the most area is filled, and gives the
    centroid and the radius sqrt(area / pi). ``level`` 0.35 sits between the conventions of the two shared label
    sets (hand-drawn QVGA circles lie ~10% inside the colour change, VGA automatic ones on it).

    The flags ("uncertain: ..." notes, see :func:`_label_flags`) check the circle against the edge found
    independently on rays from the centre (:func:`edge_circle`).
    """
    import cv2

    h, w = image.shape[:2]
    sigma = max(1.0, ball_radius_px / 25.0)
    s = _change_map(image, background, sigma)
    s = s - float(np.median(s))
    noise = float(np.median(np.abs(s))) * 1.4826 + 1e-6
    k = int(ball_radius_px * 0.6) | 1
    sc = cv2.morphologyEx(s, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    peak = float(np.percentile(sc, 99.9))
    contrast = peak / noise
    if contrast < 12.0:
        return Label(name, None, None, 0.0, f"no contact: no colour change above the noise ({contrast:.0f} x noise)")
    m = (sc > level * peak).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return Label(name, None, None, 0.0, "no contact: no region above the threshold")
    areas = stats[1:, cv2.CC_STAT_AREA]
    k = int(np.argmax(areas)) + 1
    cnts, _ = cv2.findContours((lab == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cnt = max(cnts, key=len)
    filled = np.zeros((h, w), np.uint8)
    cv2.drawContours(filled, [cnt], -1, 1, -1)
    ys, xs = np.nonzero(filled)
    area = float(xs.size)
    r = math.sqrt(area / math.pi)
    # centre: centroid of the changed pixels themselves (the unclosed map above the threshold, inside the region);
    # the closing's fill can lean to one side where the annulus is weak (measured: closer to both shared label
    # sets, QVGA 8/10 and VGA 20/47 within 3 px, against 7/10 and 15/47 for the filled region's centroid, with the
    # presses' median as the background; 17/47 with frame_49: benchmarks/labeller_accuracy.py)
    cyy, cxx = np.nonzero((s > level * peak) & (filled > 0))
    if cxx.size >= 10:
        cx, cy = float(cxx.mean()), float(cyy.mean())
    else:
        cx, cy = float(xs.mean()), float(ys.mean())
    perim = cv2.arcLength(cnt, True)
    circ = 4 * math.pi * area / max(perim * perim, 1e-9)
    others = np.delete(areas, k - 1)
    notes = _label_flags(s, cx, cy, r, ball_radius_px, circularity=circ, contrast=contrast,
                         second=float(others.max()) / area if others.size else 0.0)
    note = ("uncertain: " + "; ".join(notes)) if notes else ""
    return Label(name, round(cx, 1), round(cy, 1), round(r, 1), note)


# flag thresholds (measured on the shared VGA presses against their labels, docs/depth.md "Limits"): a press is
# "off" when its centre is > 5 px or its radius > 10% from the label
EDGE_LEVEL = 0.5            # a ray's edge: where the change falls below this fraction of the ray's own peak
EDGE_MIN_RAYS = 0.25        # at least this fraction of the rays must find the edge inside the image
EDGE_MAX_RMS = 0.07         # edge points off the fitted circle: rms over the radius
EDGE_MIN_AXES = 0.85        # minor / major axis of the ellipse through the edge points
EDGE_MAX_SHIFT = 0.12       # the edge circle's centre from the centroid, over the radius
BORDER_MARGIN = 1.1         # the contact circle grown by this factor must lie inside the image


def _label_flags(s: np.ndarray, cx: float, cy: float, r: float, ball_radius_px: float, *, circularity: float,
                 contrast: float, second: float) -> list[str]:
    """Reasons to doubt a found contact circle (empty: none).

    - the contact circle (grown by 10%) reaches the image border: its edge cannot be seen all round (the colour
      change around it, out to ~1.3 radii, may be cut without harm: measured on VGA, presses whose change region
      touched the border but not their circle were as accurate as the others);
    - the edge found on rays from the centre (:func:`edge_circle`) is off a circle (fit residual), elliptic, or
      centred away from the changed pixels' centroid: two estimates of the centre that should agree do not;
    - the changed region is not round, not smaller than the ball, tiny, or there is a second contact;
    - the contrast is barely above the detection limit (12 x the noise).
    """
    h, w = s.shape
    notes = []
    g = BORDER_MARGIN * r
    if cx - g < 0 or cy - g < 0 or cx + g > w - 1 or cy + g > h - 1:
        notes.append("touches the image border")
    if r > 0.95 * ball_radius_px:
        notes.append(f"radius {r:.0f} px is not smaller than the ball's {ball_radius_px:.0f} px")
    if r < 3:
        notes.append("tiny contact")
    if circularity < 0.75:
        notes.append(f"not round (circularity {circularity:.2f})")
    if r >= 3:
        fit = edge_circle(s, cx, cy, r)
        if fit is None:
            notes.append("no edge found on most rays from the centre")
        else:
            ecx, ecy, er, rms, axes = fit
            if rms > EDGE_MAX_RMS:
                notes.append(f"edge off a circle (fit residual {100 * rms:.0f}% of the radius)")
            if axes < EDGE_MIN_AXES:
                notes.append(f"edge not round (ellipse axes ratio {axes:.2f})")
            shift = math.hypot(ecx - cx, ecy - cy)
            if shift > EDGE_MAX_SHIFT * r:
                notes.append(f"centre unsure (the edge circle's centre is {shift:.0f} px from the centroid)")
    if second > 0.3:
        notes.append("more than one contact")
    if contrast < 15.0:
        notes.append(f"weak contrast ({contrast:.0f} x noise)")
    return notes


def edge_points(s: np.ndarray, cx: float, cy: float, r: float, rays: int = 90, level: float = EDGE_LEVEL
                ) -> tuple[np.ndarray, np.ndarray]:
    """Edge points (x, y) of a contact on ``rays`` rays from (cx, cy) in the change map ``s`` (zero = no change).

    A ball pressed into the gel tilts the surface most at the contact edge and the slope falls steeply outside it,
    so along each ray the change rises to a peak near the edge and then falls; the edge point is where it falls
    below ``level`` x that ray's own peak (linearly interpolated), which makes it independent of how strongly the
    sensor's lights colour each side. The peak is sought between 0.3 and 1.3 x ``r``; a ray that leaves the image
    before its edge gives no point."""
    import cv2

    step = max(0.5, r / 60.0)
    rad = np.arange(0.0, 1.8 * r, step, dtype=np.float32)
    th = np.arange(rays, dtype=np.float32) * np.float32(2 * np.pi / rays)
    mx = cx + np.cos(th)[:, None] * rad[None, :]
    my = cy + np.sin(th)[:, None] * rad[None, :]
    h, w = s.shape
    p = cv2.remap(s.astype(np.float32), mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    outside = (mx < 0) | (my < 0) | (mx > w - 1) | (my > h - 1)
    idx = np.arange(rad.size)
    win = (rad >= 0.3 * r) & (rad <= 1.3 * r)
    q = np.where(win[None, :] & ~outside, p, -np.inf)
    k = np.argmax(q, axis=1)
    pk = p[np.arange(rays), k]
    below = (p < level * pk[:, None]) & (idx[None, :] > k[:, None]) & ~outside
    j = np.argmax(below, axis=1)
    cut = np.argmax(outside & (idx[None, :] > k[:, None]), axis=1)
    left = (outside & (idx[None, :] > k[:, None])).any(axis=1)
    ok = below.any(axis=1) & (pk > 0) & np.isfinite(q[np.arange(rays), k]) & ~(left & (cut < j))
    ok &= j > 0
    i = np.nonzero(ok)[0]
    j = j[i]
    a, b, t_level = p[i, j - 1], p[i, j], level * pk[i]
    frac = np.clip((a - t_level) / np.maximum(a - b, 1e-9), 0.0, 1.0)
    e = rad[j - 1] + frac * step
    return cx + np.cos(th[i]) * e, cy + np.sin(th[i]) * e


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares circle (cx, cy, r) through points (algebraic fit: x^2 + y^2 = 2 cx x + 2 cy y + c)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    cx, cy = sol[0] / 2.0, sol[1] / 2.0
    return float(cx), float(cy), float(math.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0)))


def edge_circle(s: np.ndarray, cx: float, cy: float, r: float, rays: int = 90
                ) -> tuple[float, float, float, float, float] | None:
    """The circle through the contact's edge points (:func:`edge_points`), refitted without outliers (points more
    than 2.5 robust deviations off, e.g. rays that ran into another contact): (cx, cy, r, rms residual / r, minor /
    major axis of the ellipse through the kept points); None when fewer than a quarter of the rays found the edge."""
    import cv2

    x, y = edge_points(s, cx, cy, r, rays)
    if x.size < max(8, EDGE_MIN_RAYS * rays):
        return None
    keep = np.ones(x.size, bool)
    for _ in range(3):
        fcx, fcy, fr = fit_circle(x[keep], y[keep])
        res = np.hypot(x - fcx, y - fcy) - fr
        mad = 1.4826 * float(np.median(np.abs(res[keep]))) + 0.5
        new = np.abs(res) < 2.5 * mad
        if new.sum() < max(8, EDGE_MIN_RAYS * rays) or np.array_equal(new, keep):
            break
        keep = new
    fcx, fcy, fr = fit_circle(x[keep], y[keep])
    if fr <= 0:
        return None
    res = np.hypot(x[keep] - fcx, y[keep] - fcy) - fr
    (_, _), (ea, eb), _ = cv2.fitEllipse(np.stack([x[keep], y[keep]], axis=1).astype(np.float32))
    axes = min(ea, eb) / max(ea, eb, 1e-9)
    return fcx, fcy, fr, float(np.sqrt(np.mean(res * res))) / fr, float(axes)


LABEL_COLUMNS = ("image", "center_x", "center_y", "radius_px")


def read_labels(path: str | os.PathLike[str]) -> dict[str, Label]:
    """Read a labels CSV; errors name the file, the line and the field.

    UTF-8 (a byte-order mark is fine), any line ending; lines starting with ``#`` are comments; blank lines are
    skipped; spaces around names and values are ignored; extra columns are ignored when the header names them.
    Refused: a row with more fields than the header (a note typed into a file without a note column was dropped,
    and the press trained) or without a required one, an image named twice (the later row won silently), a
    non-number (also one with an underscore: float() read '1_45' as 145), a negative radius, a radius of 0 without
    a note saying "no contact" (such a row was trained as a frame without contact), a radius above 0 with that
    note (a press trained as flat gel: its colour change raised the change threshold above every press), and a
    quoted field running on over several lines (an unclosed quote took the rows after it into its note). Empty
    fields or a note starting with "uncertain" exclude the press from training."""
    path = Path(path)
    out: dict[str, Label] = {}
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the labels file: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ModelFileError(f"{path}:{line}: not UTF-8 text ({exc.reason} at byte {exc.start}); expected a labels "
                             f"CSV (image,center_x,center_y,radius_px[,note]) saved as UTF-8") from None
    # comments become blank lines (skipped by the reader), so that line numbers stay those of the file; the lines
    # are the CSV reader's (\n, \r\n or \r), not str.splitlines's, which also ends one at a form feed, U+0085 or
    # U+2028 inside a note (a '#' after it cut the note there)
    text = "".join("\n" if ln.lstrip().startswith("#") else ln for ln in io.StringIO(text, newline=""))
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        header: list[str] | None = None
        end = 0
        for row in reader:
            start, end = end + 1, reader.line_num
            if end > start:
                _refuse_multiline(path, start, end)
            if not any(f.strip() for f in row):
                continue
            if header is None:
                header = [f.strip() for f in row]
                hline = reader.line_num
                if not set(LABEL_COLUMNS) <= set(header):
                    hint = "; fields are separated by commas" if len(row) == 1 and ";" in row[0] else ""
                    raise ModelFileError(f"{path}:{hline}: expected the columns image,center_x,center_y,radius_px"
                                         f"[,note], got {header}{hint}")
                dup = sorted({h for h in header if h and header.count(h) > 1})
                if dup:
                    raise ModelFileError(f"{path}:{hline}: the column {dup[0]} is named twice")
                continue
            i = reader.line_num
            missing = header[len(row):]
            if len(row) < len(header) and not set(missing) & set(LABEL_COLUMNS):
                row = row + [""] * len(missing)       # an empty trailing note (or other extra column) left out
            if len(row) != len(header):
                raise ModelFileError(f"{path}:{i}: {len(row)} fields, expected {len(header)} as in the header "
                                     f"({','.join(header)}); a note needs a note column, a value with a comma "
                                     f"needs quotes")
            rec = {h: f.strip() for h, f in zip(header, row)}
            vals: list[float | None] = []
            for k in LABEL_COLUMNS[1:]:
                t = rec[k]
                if t == "":
                    vals.append(None)
                    continue
                if "_" in t:   # float() reads '1_45' as 145: a typo, as everywhere else (teletouch.units)
                    raise ModelFileError(f"{path}:{i}: field {k} = {t!r} is not a number ({UNDERSCORE}); expected "
                                         f"a number of px such as 145 or 145.5")
                try:
                    v = float(t)
                except ValueError:
                    raise ModelFileError(f"{path}:{i}: field {k} = {t!r} is not a number") from None
                if not math.isfinite(v) or (k == "radius_px" and v < 0):
                    raise ModelFileError(f"{path}:{i}: field {k} = {t!r}, expected a finite number"
                                         f"{' >= 0 (px)' if k == 'radius_px' else ' (px)'}")
                vals.append(v)
            name = rec["image"]
            if not name:
                raise ModelFileError(f"{path}:{i}: field image is empty")
            if name in out:
                raise ModelFileError(f"{path}:{i}: image {name} is labelled twice (also on line {out[name].line}); "
                                     f"keep one row per image")
            lb = Label(name, vals[0], vals[1], vals[2], rec.get("note", ""), line=i)
            if lb.r == 0 and not lb.no_contact and not lb.note.lower().startswith("uncertain"):
                raise ModelFileError(f"{path}:{i}: field radius_px = 0 for {name}; expected the contact radius in px "
                                     f"(> 0), or the note 'no contact' for a frame without contact")
            if lb.no_contact and lb.r:
                # a circle and "no contact" contradict each other: such a press was trained as flat gel, and its
                # colour change, counted as the gel's noise, raised the change threshold above every press
                raise ModelFileError(f"{path}:{i}: field radius_px = {rec['radius_px']!r} for {name} with the note "
                                     f"{lb.note!r}; a frame without contact has radius_px 0 (or empty): give 0 if "
                                     f"nothing touches the gel in {name}, or remove the note if it shows a press")
            out[name] = lb
    if header is None:
        raise ModelFileError(f"{path}:1: expected the columns image,center_x,center_y,radius_px[,note], got an "
                             f"empty file")
    return out


def _refuse_multiline(path: Path, start: int, end: int) -> None:
    """A row of the labels CSV must be one line: a quoted field running on over several lines is an unclosed quote
    (measured: a note opened with a quote and never closed took every later row into it, those presses silently
    unlabelled)."""
    raise ModelFileError(f"{path}:{start}: a quoted field runs on over {end - start + 1} lines (to line {end}): an "
                         f"unclosed quote? Expected one row per line (a quote in a field: the field in quotes, the "
                         f"quote doubled)")


def check_labels(labels: dict[str, Label], images: Sequence[tuple[str, np.ndarray]], ball_radius_px: float,
                 source: str = "labels") -> None:
    """The usable labels of the given images must fit them: centre inside the image, contact radius smaller than
    the ball's (a cap of a sphere is narrower than the sphere); ValueError naming ``source`` (the labels file), the
    line or image and the field."""
    for name, img in images:
        lb = labels.get(name)
        if lb is None or not lb.usable:
            continue
        h, w = img.shape[:2]
        where = f"{source}:{lb.line}" if lb.line else f"{source}: {name}"
        for k, v, n in (("center_x", lb.cx, w), ("center_y", lb.cy, h)):
            if not 0 <= v < n:
                raise ValueError(f"{where}: field {k} = {v:g} lies outside the image {name} ({h}x{w} rows x cols); "
                                 f"expected 0 <= {k} < {n} px")
        if not lb.r < ball_radius_px:
            raise ValueError(f"{where}: field radius_px = {lb.r:g} is not smaller than the ball radius "
                             f"({ball_radius_px:.1f} px at this scale); expected the contact circle's radius in px "
                             f"(or check the scale, --px-per-mm, and the ball size)")


def write_labels(path: str | os.PathLike[str], labels: Iterable[Label]) -> Path:
    """Write a labels CSV (atomically: an interrupted write leaves the file as it was); a note's line breaks are
    written as spaces, so that the file reads back (:func:`read_labels`: one row per line)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def num(v: float | None) -> str:
        return "" if v is None else f"{v:g}"

    buf = io.StringIO(newline="")
    wr = csv.writer(buf)
    wr.writerow(["image", "center_x", "center_y", "radius_px", "note"])
    for lb in labels:
        wr.writerow([lb.image, num(lb.cx), num(lb.cy), num(lb.r), _one_line(lb.note)])
    atomic_write(path, buf.getvalue().encode("utf-8"))
    return path


def _one_line(text: str) -> str:
    """A note for the labels CSV: line breaks become spaces (:func:`read_labels` reads one row per line)."""
    return " ".join(part.strip() for part in text.replace("\r\n", "\n").replace("\r", "\n").split("\n"))


def review_overlay(image: np.ndarray, background: np.ndarray, label: Label) -> np.ndarray:
    """The press beside its difference image, with the contact circle drawn (green; red when uncertain)."""
    import cv2

    d = np.clip((image.astype(np.float32) - background.astype(np.float32)) * 3 + 128, 0, 255).astype(np.uint8)
    out = np.hstack([image.copy(), d])
    if label.cx is not None and label.cy is not None and label.r:
        col = (0, 0, 255) if label.uncertain else (0, 255, 0)
        for off in (0, image.shape[1]):
            cv2.circle(out, (int(round(label.cx)) + off, int(round(label.cy))), int(round(label.r)), col, 1)
    # the whole note, wrapped to the overlay's width (its first 60 characters ran off the image mid-reason)
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.4
    lines, line = [], ""
    for word in (label.note or "ok").split():
        trial = f"{line} {word}".strip()
        if line and cv2.getTextSize(trial, font, scale, 1)[0][0] > out.shape[1] - 8:
            lines.append(line)
            line = word
        else:
            line = trial
    lines.append(line)
    for i, text in enumerate(lines):
        cv2.putText(out, text, (4, 14 + 13 * i), font, scale, (255, 255, 255), 1)
    return out


# --- training data ---------------------------------------------------------------------------------------------

def pool_grid(a: np.ndarray, stride: int, offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Block means of a (rows, cols, 3) image in ``stride x stride`` blocks starting at ``offset``, float32."""
    oy, ox = offset
    h, w = a.shape[:2]
    gr, gc = (h - oy) // stride, (w - ox) // stride
    a = a[oy: oy + gr * stride, ox: ox + gc * stride].astype(np.float32)
    return a.reshape(gr, stride, gc, stride, 3).sum(axis=(1, 3)) * (1.0 / (stride * stride))


def grid_images(image: np.ndarray, background: np.ndarray, stride: int, offset: tuple[int, int] = (0, 0),
                drift: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block-averaged frame, diff and background on the work grid (float32 (gr, gc, 3)), exactly as the estimator
    computes them: block means of frame and background, their difference minus its per-channel median over every
    4th cell (global illumination drift, :func:`depth_pipeline.channel_offset`)."""
    from .depth_pipeline import channel_offset

    x = pool_grid(image, stride, offset)
    b = pool_grid(background, stride, offset)
    d = x - b
    if drift:
        d -= channel_offset(d)
    return x, d, b


def sphere_normals(rows: np.ndarray, cols: np.ndarray, label: Label, ball_radius_px: float) -> np.ndarray:
    """Ground-truth normals (nx, ny, nz) at full-resolution pixel positions: the ball's inside the contact circle,
    (0, 0, 1) outside. nx = dx / R, ny = dy / R (dx along columns, dy along rows); depth gradient = -n_xy / nz."""
    dx = np.asarray(cols, dtype=np.float64) - label.cx
    dy = np.asarray(rows, dtype=np.float64) - label.cy
    inside = dx * dx + dy * dy < label.r * label.r
    nx = np.where(inside, dx / ball_radius_px, 0.0)
    ny = np.where(inside, dy / ball_radius_px, 0.0)
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, 1.0))
    return np.stack([nx, ny, nz], axis=1).astype(np.float32)


def press_samples(image: np.ndarray, background: np.ndarray, label: Label | None, feature_set: str, stride: int,
                  ball_radius_px: float, rng: np.random.Generator, flat_ratio: float = 1.0,
                  offsets: Sequence[tuple[int, int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Features and target normals of one press (or one no-contact frame when ``label`` is None / no contact).

    Every contact cell is used; flat cells are sampled to ``flat_ratio`` x the contact count, half of them in the
    ring between 1 and 2.5 contact radii (where the gel is nearly flat but the colours change), half anywhere.
    Each grid phase (``offsets``; default 0 and stride/2 in each direction) gives another view of the same press.
    """
    from .normal_model import colour_maps, features

    h, w = image.shape[:2]
    if offsets is None:
        hs = stride // 2
        offsets = sorted({(0, 0), (0, hs), (hs, 0), (hs, hs)})
    xs_all, ys_all = [], []
    for off in offsets:
        gx_img, gd, gb = grid_images(image, background, stride, off)
        cmaps = colour_maps(feature_set, gx_img, gd, gb)
        gr, gc = gx_img.shape[:2]
        rr, cc = np.mgrid[0:gr, 0:gc]
        # full-resolution position of each cell's centre
        prow = rr * stride + off[0] + (stride - 1) / 2.0
        pcol = cc * stride + off[1] + (stride - 1) / 2.0
        prow, pcol = prow.ravel(), pcol.ravel()
        if label is None or not label.usable:
            sel = rng.choice(prow.size, size=min(prow.size, 400), replace=False)
        else:
            d2 = (pcol - label.cx) ** 2 + (prow - label.cy) ** 2
            a2 = label.r ** 2
            inside = np.nonzero(d2 < a2)[0]
            ring = np.nonzero((d2 >= a2) & (d2 < 6.25 * a2))[0]
            rest = np.nonzero(d2 >= 6.25 * a2)[0]
            nflat = int(round(flat_ratio * inside.size))
            pick_ring = rng.choice(ring, size=min(ring.size, nflat // 2), replace=False) if ring.size else ring
            pick_rest = rng.choice(rest, size=min(rest.size, nflat - pick_ring.size), replace=False)
            sel = np.concatenate([inside, pick_ring, pick_rest])
        xs_all.append(features(feature_set, cmaps.reshape(gr * gc, -1)[sel], prow[sel], pcol[sel], (h, w)))
        if label is None or not label.usable:
            ys_all.append(np.tile(np.array([[0, 0, 1]], np.float32), (sel.size, 1)))
        else:
            ys_all.append(sphere_normals(prow[sel], pcol[sel], label, ball_radius_px))
    return np.concatenate(xs_all), np.concatenate(ys_all)


# --- training --------------------------------------------------------------------------------------------------

def train_model(images: Sequence[tuple[str, np.ndarray]], labels: dict[str, Label], background: np.ndarray,
                px_per_m: float, ball_radius_m: float = 0.003, feature_set: str = DEFAULT_FEATURES,
                hidden: Sequence[int] = DEFAULT_HIDDEN, epochs: int = 40, lr: float = 1e-3, batch: int = 1024,
                dropout: float = 0.05, seed: int = 0, stride: int | None = None, flat_ratio: float = 1.0,
                validation: Sequence[str] = (), progress: bool = True, fit_gain: bool = True,
                log: Callable[[str], None] | None = None) -> NormalModel:
    """Train the normal MLP on the usable presses (minus ``validation`` names) and return the model.

    Adam (lr 1e-3), MSE on the unit normal, dropout 0.05 (the paper's defaults); seeded and reproducible (same
    seed, same data, same thread count -> same weights). Validation presses are evaluated with the full depth
    pipeline (cap-height error, sphere radius, far-field false depth) and the numbers go into the model file.
    """
    import torch

    t_start = time.perf_counter()
    h, w = images[0][1].shape[:2]
    stride = default_stride(h) if stride is None else stride
    if not 1 <= stride <= max_stride((h, w)):
        raise ValueError(f"stride {stride}: expected an integer from 1 to {max_stride((h, w))} px for {h}x{w} images "
                         f"(a work grid of at least 8 cells across)")
    check_training_params(epochs=epochs, lr=lr, batch=batch, dropout=dropout, seed=seed, hidden=hidden,
                          flat_ratio=flat_ratio)
    # numpy numbers pass the check; as Python's: torch's generator refused a numpy seed ("an integer is required"),
    # and the model file's JSON record a numpy number
    epochs, batch, seed, hidden = int(epochs), int(batch), int(seed), tuple(int(h) for h in hidden)
    lr, dropout, flat_ratio = float(lr), float(dropout), float(flat_ratio)
    ball_radius_px = ball_radius_m * px_per_m
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    train_names, X, Y = [], [], []
    for name, img in images:
        lb = labels.get(name)
        if name in validation:
            continue
        if lb is None:
            continue
        if lb.no_contact:
            x, y = press_samples(img, background, None, feature_set, stride, ball_radius_px, rng)
        elif lb.usable:
            x, y = press_samples(img, background, lb, feature_set, stride, ball_radius_px, rng, flat_ratio)
        else:
            continue
        train_names.append(name)
        X.append(x)
        Y.append(y)
    # the background itself: no contact anywhere
    x, y = press_samples(background, background, None, feature_set, stride, ball_radius_px, rng)
    X.append(x)
    Y.append(y)
    if not any(labels.get(n) is not None and labels[n].usable for n in train_names):
        raise ValueError("no usable labelled press to train on (all missing, uncertain or held out)")
    Xa = np.concatenate(X)
    Ya = np.concatenate(Y)
    mean = Xa.mean(axis=0)
    std = Xa.std(axis=0) + 1e-6
    Xn = torch.from_numpy((Xa - mean) / std)
    Yt = torch.from_numpy(Ya)
    net = make_net(feature_count(feature_set), tuple(hidden), dropout)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    n = Xn.shape[0]
    it: Iterable[int] = range(epochs)
    bar = None
    lines = None
    if progress and _stderr_is_terminal():
        from tqdm import tqdm

        bar = tqdm(it, desc="training", unit="epoch", leave=False)
        it = bar
    elif progress:
        lines = _ProgressLines(epochs)
    loss_v = float("nan")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)       # small batches: one thread is fastest and does not fight other processes
    try:
        net.train()
        for epoch in it:
            perm = torch.randperm(n, generator=gen)
            tot = 0.0
            for i in range(0, n, batch):
                idx = perm[i:i + batch]
                opt.zero_grad()
                loss = torch.nn.functional.mse_loss(net(Xn[idx]), Yt[idx])
                loss.backward()
                opt.step()
                tot += float(loss.detach()) * idx.numel()
            loss_v = tot / n
            if not math.isfinite(loss_v):
                raise ValueError(f"training diverged: the loss is {loss_v} in epoch {epoch + 1} of {epochs} (lr "
                                 f"{lr:g}); no model written; try a smaller learning rate")
            if bar is not None:
                bar.set_postfix(loss=f"{loss_v:.5f}")
            if lines is not None:
                lines.epoch_done(epoch + 1, loss_v)
    finally:
        torch.set_num_threads(threads)
        if bar is not None:
            bar.close()
    net.eval()
    bad = [k for k, v in net.state_dict().items() if not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"training diverged: the weights {', '.join(bad)} hold NaN or inf (lr {lr:g}); no model "
                         f"written; try a smaller learning rate")
    # the targets are unit normals: predicting (0, 0, 0) everywhere scores 1/3; a final loss above 1 is divergence
    # (measured: lr 10 ends at 63, lr 1e6 at 1.8e21, both were written as models with the depth gain clipped to 2)
    if loss_v > 1.0:
        raise ValueError(f"training diverged: the final loss is {loss_v:.4g} (expected well below 1 for unit normals; "
                         f"lr {lr:g}); no model written; try a smaller learning rate")
    model = NormalModel.from_net(
        net, feature_set=feature_set, hidden=tuple(hidden), feat_mean=mean.astype(np.float32),
        feat_std=std.astype(np.float32), background=np.ascontiguousarray(background, dtype=np.uint8),
        px_per_m=px_per_m, ball_radius_m=ball_radius_m, stride=stride,
        change_threshold=change_threshold(images, labels, background, stride, train_names))
    # depth gain: the regression shrinks the normals a little; one scale, fitted on the training presses' cap
    # heights (measured / expected), corrects it.
    from .depth_pipeline import DepthPipeline

    pipe = DepthPipeline(model)
    ratios = []
    if fit_gain:
        # the training presses well inside the image; those of them that read no depth; those of them in which the
        # change mask sees nothing at all (their colour change below the change threshold)
        gauged, no_depth, unseen = [], [], []
        for name, img in images:
            lb = labels.get(name)
            if name in train_names and lb is not None and lb.usable and _inside(lb, img.shape, GAIN_MARGIN):
                gauged.append(name)
                res = pipe(img)
                measured, expected, _ = cap_height_error(res.depth, lb, px_per_m, ball_radius_m)
                if measured > 0:
                    ratios.append(expected / measured)
                else:
                    no_depth.append(name)
                    if not res.changed:
                        unseen.append(name)
        if gauged and not ratios and unseen:
            # before: the gain fit was skipped without a word and the model written (depth gain 1.0, every press
            # read 0 mm, validation 100% off, exit code 0)
            raise ValueError(_no_depth_message(images, labels, background, stride, train_names, gauged, unseen,
                                               model.change_threshold))
        if ratios:
            model.depth_gain = float(np.clip(np.median(ratios), 0.5, 2.0))
        if log and not gauged:
            log(f"depth gain not fitted, kept at 1.0: no training press has its circle of {GAIN_MARGIN:g} contact "
                f"radii inside the image (the cap height needs the ring around the contact); record presses away "
                f"from the border")
        elif log and not ratios:
            # the change mask sees the presses, the network gives them no slope: not the data (which are refused
            # above) but the training
            log(f"depth gain not fitted, kept at 1.0: none of the {len(gauged)} training presses it is fitted on "
                f"reads any depth after {epochs} epoch(s), although the change mask sees them: the network has not "
                f"learnt the slopes; this model reads no depth (train longer: --epochs, 40 by default)")
        elif log and len(ratios) < MIN_GAIN_PRESSES:
            log(f"depth gain {model.depth_gain:.3f} fitted on {len(ratios)} press(es) only (of {len(gauged)} training "
                f"presses with their circle of {GAIN_MARGIN:g} contact radii inside the image; {MIN_GAIN_PRESSES} or "
                f"more make a firmer fit)")
        if log and no_depth and ratios:
            log(f"{len(no_depth)} training press(es) read no depth with the trained model, left out of the depth gain "
                f"fit: {', '.join(no_depth[:5])}{' ...' if len(no_depth) > 5 else ''}"
                + (f"; the change mask sees nothing in {', '.join(unseen[:5])}{' ...' if len(unseen) > 5 else ''} "
                   f"(change threshold {model.change_threshold:.1f} levels): check their labels and the background"
                   if unseen else " (check their labels)"))
    train_s = time.perf_counter() - t_start
    model.training = {"presses": train_names, "samples": int(n), "epochs": epochs, "lr": lr, "batch": batch,
                      "dropout": dropout, "seed": seed, "loss": "mse", "optimizer": "adam", "final_loss": loss_v,
                      "flat_ratio": flat_ratio, "seconds": round(train_s, 2), "gain_presses": len(ratios),
                      "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(build_time())),
                      "software": software_versions()}
    if source_date_epoch() is not None:
        del model.training["seconds"]   # reproducible: a duration differs from run to run (docs/depth.md)
    if log:
        log(f"trained on {len(train_names)} frames, {n} samples, {epochs} epochs, loss {loss_v:.5f}, "
            f"{train_s:.1f} s")
    if validation:
        from .depth_pipeline import DepthPipeline

        pipe = DepthPipeline(model)
        per = []
        for name, img in images:
            if name in validation and name in labels and labels[name].usable:
                per.append(evaluate_press(pipe, img, labels[name], ball_radius_m))
        model.validation = summarize(per)
        if log and per:
            log(f"validation on {len(per)} presses: median cap-height error "
                f"{100 * model.validation['median_abs_cap_error']:.1f}%, sphere radius "
                f"{1000 * model.validation['median_sphere_radius_m']:.2f} mm")
    return model


#: seconds between the plain progress lines of a training whose stderr is not a terminal (a log file, CI)
PROGRESS_LINE_S = 10.0


def _stderr_is_terminal() -> bool:
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):   # no stderr, or a closed one
        return False


class _ProgressLines:
    """Training progress for a log: a plain line every PROGRESS_LINE_S seconds (none for a training shorter than
    that), where tqdm's bar on a terminal wrote ~80 carriage-return updates on one line of the log."""

    def __init__(self, epochs: int) -> None:
        self.epochs = epochs
        self.t0 = self.last = time.monotonic()

    def epoch_done(self, epoch: int, loss: float) -> None:
        now = time.monotonic()
        if now - self.last >= PROGRESS_LINE_S and epoch < self.epochs:
            self.last = now
            print(f"training: epoch {epoch}/{self.epochs}, loss {loss:.5f}, {now - self.t0:.0f} s", file=sys.stderr,
                  flush=True)


def check_training_params(*, epochs: Any, lr: Any, batch: Any, dropout: Any, seed: Any, hidden: Any,
                          flat_ratio: Any) -> None:
    """ValueError naming the first training parameter out of range (before any work: epochs 0 wrote a model with a
    NaN loss, a negative seed gave numpy's bare "expected non-negative integer")."""
    def integer(v: Any) -> bool:
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    def number(v: Any) -> bool:
        return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)

    checks = (("epochs", epochs, integer(epochs) and epochs >= 1, "an integer >= 1"),
              ("batch", batch, integer(batch) and batch >= 1, "an integer >= 1"),
              ("seed", seed, integer(seed) and 0 <= seed < 2 ** 63, "an integer from 0 to 2**63 - 1"),
              ("lr", lr, number(lr) and lr > 0, "a finite number > 0"),
              ("dropout", dropout, number(dropout) and 0 <= dropout < 1, "a number from 0 to below 1"),
              ("flat_ratio", flat_ratio, number(flat_ratio) and flat_ratio >= 0, "a finite number >= 0"),
              ("hidden", hidden, isinstance(hidden, (list, tuple)) and len(hidden) >= 1
               and all(integer(h) and h >= 1 for h in hidden), "one or more layer sizes (integers >= 1)"))
    for name, v, ok, what in checks:
        if not ok:
            raise ValueError(f"training parameter {name} = {v!r}: expected {what}")


#: the depth gain is fitted on the training presses whose circle of this many contact radii lies inside the image
GAIN_MARGIN = 1.2
#: fewer presses than this in the depth gain's fit are said in the log (one press's cap height sets the gain alone)
MIN_GAIN_PRESSES = 3


def _no_depth_message(images: Sequence[tuple[str, np.ndarray]], labels: dict[str, Label], background: np.ndarray,
                      stride: int, train_names: Sequence[str], gauged: Sequence[str], unseen: Sequence[str],
                      threshold: float) -> str:
    """Why a calibration whose training presses all read no depth, some of them not even seen by the change mask, is
    refused, naming the likely causes: the frames whose colour change set the change threshold (a press labelled
    "no contact" or labelled far from its circle), the background, the labels."""
    def names(ns: Sequence[str]) -> str:
        return ", ".join(ns[:5]) + (" ..." if len(ns) > 5 else "")

    msg = (f"no training press measured any depth: all {len(gauged)} that the depth gain is fitted on "
           f"({names(gauged)}) read a cap height of 0 with the trained model, and in {len(unseen)} of them "
           f"({names(unseen)}) the change mask sees nothing: the model's change threshold, {threshold:.1f} levels "
           f"(the shared QVGA DIGIT's: about 16), is above their colour change; no model written. The threshold is "
           f"taken from the frames' colour change away from the labelled contacts, so likely causes are: a frame "
           f"labelled 'no contact' that shows a press")
    flat = [n for n in train_names if n in labels and labels[n].no_contact]
    if flat:
        msg += f" (labelled so: {', '.join(flat[:5])}{' ...' if len(flat) > 5 else ''})"
    msg += ("; a background that is not this sensor's no-contact frame (another sensor's, or one with a press in "
            "it); labels whose centre or radius miss the press (a radius far too small, another image's row)")
    top = _threshold_frames(images, labels, background, stride, train_names)
    if len(top) >= 2 and top[0][1] > 2.0 * top[len(top) // 2][1]:
        msg += (f". The largest change away from the labelled contacts is in {top[0][0]} ({top[0][1]:.0f} levels; "
                f"median over the frames {top[len(top) // 2][1]:.0f}): check its label first")
    return msg


def _inside(label: Label, shape: tuple[int, ...], k: float) -> bool:
    """True when the circle of k contact radii around the press lies inside the image."""
    h, w = shape[:2]
    return (label.cx - k * label.r >= 0 and label.cy - k * label.r >= 0 and label.cx + k * label.r <= w - 1
            and label.cy + k * label.r <= h - 1)


def change_threshold(images: Sequence[tuple[str, np.ndarray]], labels: dict[str, Label], background: np.ndarray,
                     stride: int, names: Sequence[str]) -> float:
    """The estimator's contact threshold for this sensor: 1.25 x the 99.9th percentile of its change statistic
    (|diff| summed over channels on the work grid, 3 x 3 box-blurred) away from the presses (beyond 2.5 radii)."""
    vals = [v for _, v in _far_change(images, labels, background, stride, names)]
    if not vals:
        return 16.0
    return float(max(6.0, 1.25 * np.percentile(np.concatenate(vals), 99.9)))


def _far_change(images: Sequence[tuple[str, np.ndarray]], labels: dict[str, Label], background: np.ndarray,
                stride: int, names: Sequence[str]) -> list[tuple[str, np.ndarray]]:
    """(name, the change statistic on the cells beyond 2.5 contact radii; all cells of a no-contact frame) of each
    frame of ``names`` that :func:`change_threshold` takes its statistic from."""
    import cv2

    out = []
    for name, img in images:
        lb = labels.get(name)
        if name not in names or lb is None or not (lb.usable or lb.no_contact):
            continue
        _, gd, _ = grid_images(img, background, stride)
        a = cv2.blur(np.abs(gd).sum(axis=2), (3, 3), borderType=cv2.BORDER_REPLICATE)
        if lb.usable:
            gr, gc = a.shape
            rr, cc = np.mgrid[0:gr, 0:gc]
            far = ((cc * stride + (stride - 1) / 2 - lb.cx) ** 2 + (rr * stride + (stride - 1) / 2 - lb.cy) ** 2
                   > (2.5 * lb.r) ** 2)
            out.append((name, a[far]))
        else:
            out.append((name, a.ravel()))
    return out


def _threshold_frames(images: Sequence[tuple[str, np.ndarray]], labels: dict[str, Label], background: np.ndarray,
                      stride: int, names: Sequence[str]) -> list[tuple[str, float]]:
    """(name, 99.9th percentile of its :func:`_far_change`), the largest first: which frames raise the threshold."""
    per = [(n, float(np.percentile(v, 99.9))) for n, v in _far_change(images, labels, background, stride, names)
           if v.size]
    return sorted(per, key=lambda nv: -nv[1])


# --- metrics ---------------------------------------------------------------------------------------------------

def cap_height_error(depth: np.ndarray, label: Label, px_per_m: float, ball_radius_m: float = 0.003
                     ) -> tuple[float, float, float]:
    """(measured, expected, relative error) of the cap height: depth at the centre (disk of radius
    max(2 px, a/10)) minus depth on the ring a-2 <= r <= a+2 px, against R - sqrt(R^2 - a^2)."""
    h, w = depth.shape
    rr, cc = np.ogrid[0:h, 0:w]
    r = np.sqrt((cc - label.cx) ** 2 + (rr - label.cy) ** 2)
    a = label.r
    centre = depth[r <= max(2.0, a / 10.0)].mean()
    ring = depth[(r >= a - 2) & (r <= a + 2)].mean()
    measured = float(centre - ring)
    a_m = a / px_per_m
    R = ball_radius_m
    expected = R - math.sqrt(max(R * R - a_m * a_m, 0.0))
    return measured, expected, measured / expected - 1.0


def sphere_fit_radius(depth: np.ndarray, label: Label, px_per_m: float) -> float:
    """Radius (m) of the sphere fitted (algebraically, least squares) to the reconstructed surface inside the
    contact circle (r <= 0.9 a)."""
    h, w = depth.shape
    rr, cc = np.mgrid[0:h, 0:w]
    sel = (cc - label.cx) ** 2 + (rr - label.cy) ** 2 <= (0.9 * label.r) ** 2
    x = cc[sel] / px_per_m
    y = rr[sel] / px_per_m
    z = -depth[sel].astype(np.float64)      # the ball's surface: depth grows into the gel
    A = np.stack([x, y, z, np.ones_like(x)], axis=1)
    b = -(x * x + y * y + z * z)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    D, E, F, G = sol
    val = (D * D + E * E + F * F) / 4.0 - G
    return float(math.sqrt(val)) if val > 0 else float("nan")


def far_false_depth(depth: np.ndarray, label: Label) -> float:
    """max |depth| (m) beyond twice the contact radius."""
    h, w = depth.shape
    rr, cc = np.ogrid[0:h, 0:w]
    far = (cc - label.cx) ** 2 + (rr - label.cy) ** 2 > (2 * label.r) ** 2
    return float(np.abs(depth[far]).max()) if far.any() else 0.0


def evaluate_press(pipe: Any, image: np.ndarray, label: Label, ball_radius_m: float = 0.003) -> dict[str, Any]:
    res = pipe(image)
    px_per_m = pipe.model.px_per_m
    measured, expected, err = cap_height_error(res.depth, label, px_per_m, ball_radius_m)
    return {"image": label.image, "cx": label.cx, "cy": label.cy, "radius_px": label.r,
            "cap_measured_mm": round(measured * 1e3, 4), "cap_expected_mm": round(expected * 1e3, 4),
            "cap_error": round(err, 4), "sphere_radius_mm": round(sphere_fit_radius(res.depth, label,
                                                                                       px_per_m) * 1e3, 3),
            "max_depth_mm": round(res.max_depth * 1e3, 4),
            "far_false_depth_mm": round(far_false_depth(res.depth, label) * 1e3, 4)}


def summarize(per: Sequence[dict[str, Any]]) -> dict[str, Any]:
    if not per:
        return {}
    err = np.array([p["cap_error"] for p in per])
    rad = np.array([p["sphere_radius_mm"] for p in per]) * 1e-3
    far = np.array([p["far_false_depth_mm"] for p in per]) * 1e-3
    return {"presses": len(per), "median_abs_cap_error": float(np.median(np.abs(err))),
            "median_cap_error": float(np.median(err)), "median_sphere_radius_m": float(np.nanmedian(rad)),
            "max_far_false_depth_m": float(far.max()), "per_press": list(per)}


# --- scale from a caliper image --------------------------------------------------------------------------------

def px_per_mm_from_caliper(image: np.ndarray, background: np.ndarray, gap_m: float) -> float:
    """px per mm from an image of the two tips of a caliper (set to ``gap_m``) pressed into the gel: the distance
    between the centroids of the two strongest contact regions, divided by the gap."""
    import cv2

    if not (isinstance(gap_m, (int, float)) and math.isfinite(gap_m) and gap_m > 0):
        raise ValueError(f"caliper gap {gap_m!r} m: expected a finite distance > 0 (e.g. 5mm)")
    if image.shape != background.shape:
        raise ValueError(f"the caliper image is {image.shape[0]}x{image.shape[1]}, the background "
                         f"{background.shape[0]}x{background.shape[1]} (rows x cols); expected an image of the same "
                         f"sensor at the presses' resolution")
    s = _change_map(image, background, 1.5)
    floor = float(np.median(s))
    peak = float(np.percentile(s, 99.9))
    m = (s > floor + 0.4 * (peak - floor)).astype(np.uint8)
    n, lab, stats, cents = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n < 3:
        raise ValueError("the caliper image must show two separate contacts (the two tips); found "
                         f"{max(n - 1, 0)}")
    order = np.argsort(stats[1:, cv2.CC_STAT_AREA])[::-1][:2] + 1
    (x1, y1), (x2, y2) = cents[order[0]], cents[order[1]]
    dist_px = math.hypot(x2 - x1, y2 - y1)
    return dist_px / (gap_m * 1e3)


# --- the whole calibration -------------------------------------------------------------------------------------

def _images_median_record(images: Sequence[tuple[str, np.ndarray]], labels: dict[str, Label]) -> dict[str, Any]:
    """The model file's record (``training.background``) of a background taken as the per-pixel median of all the
    images: how many, and how many of them are labelled presses (usable or not), no-contact frames, or have no label
    (all of them are in the median, whatever their labels)."""
    names = [n for n, _ in images]
    no_contact = sum(1 for n in names if n in labels and labels[n].no_contact)
    unlabelled = sum(1 for n in names if n not in labels)
    return {"from": "images", "frames": len(names), "statistic": "per-pixel median",
            "presses": len(names) - no_contact - unlabelled, "no_contact": no_contact, "unlabelled": unlabelled}


@dataclass
class CalibrationResult:
    model: NormalModel
    labels: list[Label]
    background: np.ndarray
    seconds: float
    notes: list[str] = field(default_factory=list)


def calibrate(images: Sequence[tuple[str, np.ndarray]], ball_radius_m: float, px_per_m: float,
              labels: dict[str, Label] | None = None, background: np.ndarray | None = None,
              holdout: int = 2, log: Callable[[str], None] | None = None,
              background_source: dict[str, Any] | None = None, **train_kw: Any) -> CalibrationResult:
    """The whole calibration: background (given, or the per-pixel median of the images), labels (given, or found
    by :func:`auto_label`), training on the usable presses with ``holdout`` of them (spread over the sensor) held
    out and evaluated; their metrics go into the model file.

    The model file records where the background came from (``training.background``): ``background_source`` (e.g.
    :meth:`Background.meta`) for a given background, :func:`_images_median_record` for the median of the images,
    {"from": "given"} for an array given without a source."""
    t0 = time.perf_counter()
    log = log or (lambda m: None)
    source_date_epoch()   # a malformed SOURCE_DATE_EPOCH is refused before the work, not when the time is written
    median_of_images = background is None   # (recorded once the labels say what the images are)
    if background is None:
        background = median_background([im for _, im in images])
        log(f"background: per-pixel median of the {len(images)} images")   # (a no-contact frame may be among them)
    elif background.shape != images[0][1].shape:
        raise ValueError(f"background is {background.shape}, the presses are {images[0][1].shape}")
    elif is_grayscale(background):
        raise ValueError("the background frame is a grayscale image (its three colour channels are equal); expected "
                         "a colour no-contact frame of the same sensor")
    ball_px = ball_radius_m * px_per_m
    if labels is not None:
        check_labels(labels, images, ball_px)
    if labels is None:
        labels = {name: auto_label(name, img, background, ball_px) for name, img in images}
        n_unc = sum(1 for lb in labels.values() if lb.uncertain and not lb.no_contact)
        log(f"labelled {len(labels)} presses automatically ({n_unc} uncertain, excluded)")
    else:
        missing = [n for n, _ in images if n not in labels]
        if missing:
            log(f"no label for {len(missing)} image(s), not used: {', '.join(missing[:5])}")
        names = {n for n, _ in images}
        stray = [n for n in labels if n not in names]
        if stray:   # (a labels file for another folder?)
            log(f"{len(stray)} label(s) name no image in the folder, ignored: {', '.join(stray[:5])}")
        unc = [n for n, _ in images if n in labels and labels[n].uncertain and not labels[n].no_contact]
        if unc:
            log(f"{len(unc)} press(es) marked uncertain or without a complete circle, not used: {', '.join(unc[:5])}"
                f"{' ...' if len(unc) > 5 else ''}")
    flat = [n for n, _ in images if n in labels and labels[n].no_contact]
    if flat:
        log(f"{len(flat)} no-contact frame(s) trained as flat gel: {', '.join(flat[:5])}"
            f"{' ...' if len(flat) > 5 else ''}")
    usable = [n for n, _ in images if n in labels and labels[n].usable]
    if len(usable) < 2:
        raise ValueError(f"only {len(usable)} usable press(es); record more (the paper used ~40) or fix the labels")
    if holdout > len(usable) - 1:
        log(f"holding out {len(usable) - 1} press(es) instead of {holdout}: {len(usable)} usable, at least one is "
            f"trained on")
    holdout = max(0, min(holdout, len(usable) - 1))
    # hold out presses spread over the sensor: every k-th in order of position along the rows
    val: list[str] = []
    if holdout:
        order = sorted(usable, key=lambda n: (labels[n].cy, labels[n].cx))
        step = len(order) / holdout
        val = [order[int((i + 0.5) * step)] for i in range(holdout)]
    model = train_model(images, labels, background, px_per_m, ball_radius_m, validation=val, log=log, **train_kw)
    if median_of_images:
        background_source = _images_median_record(images, labels)
    model.training["background"] = dict(background_source) if background_source is not None else {"from": "given"}
    return CalibrationResult(model=model, labels=[labels[n] for n, _ in images if n in labels],
                             background=background, seconds=time.perf_counter() - t0)
