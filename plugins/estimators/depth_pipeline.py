"""Frame -> depth map, the estimator's computation (no framework code; the `depth` component wraps it).

Two implementations of the same steps:

- ``mode="dense"`` (the default on a GPU): torch tensors end to end on any torch device, kornia for the blur,
  batched (:meth:`DepthPipeline.batch_depth`), the network on every cell (masked), the whole-grid DST solve by
  torch.fft (scipy.fft on CPU).
- ``mode="sparse"`` (the default on CPU): OpenCV for block means and morphology (several times faster than the
  same torch calls on small CPU images), the torch network on the changed cells only (input scaling folded into
  the first layer), the scipy.fft DST solve on their window (on the whole grid where that window reaches the
  grid's border: a contact cut by the image border). Both agree within ~1-2% of max depth (tested).

Steps:

1. Work grid: frame and background are block-averaged in ``stride x stride`` blocks (the DIGIT's optics blur far
   more than one pixel, so nothing is lost; the model was trained on the same grid); ``diff = frame - background``
   minus its per-channel median over every 4th cell (global illumination drift cancels).
2. Change mask: cells whose colour change (|diff| summed over the channels, 3 x 3 box) exceeds
   ``change_threshold`` (0..255 levels; the model's, fitted to the sensor's noise), opened (noise specks go),
   dilated by ``dilate`` + 1 cells, plus what it encloses (:func:`fill_enclosed`: a press's flat centre changes
   less than its rim). Outside it the gel is flat by definition: normal (0, 0, 1), zero slope. This is the zero
   reference: without contact there is no slope, hence no depth.
3. The MLP gives normals; slopes ``gx = -nx / max(nz, nz_min)`` (and gy), dimensionless.
4. Depth by the DST Poisson solve on the mask's bounding box plus ``margin`` cells (sparse; the whole grid where
   that box reaches the grid's border) or on the whole grid (dense); depth outside the change mask is set to 0
   and, unless ``clamp_negative=False``, negative depth (the gel does not rise above its rest plane by more than
   microns) to 0; then metres (x stride / px_per_m x the model's depth gain) and bilinear upsampling to the
   frame's size.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from teletouch.errors import ModelFileError

from . import poisson
from .normal_model import NormalModel, colour_maps_torch, colour_parts, context_cells, feature_count, uses_xy

__all__ = ["DepthResult", "DepthPipeline", "contact_summary", "channel_offset", "fill_enclosed", "fill_enclosed_torch",
           "DEVICES", "device_form_problem", "device_problem"]

#: the torch devices the pipeline runs on: the CPU (sparse path by default), a CUDA GPU (by index) or Apple's MPS
DEVICES = "cpu, cuda, cuda:N (N: the GPU's index, from 0) or mps"
_DEVICE_FORM = re.compile(r"cpu|cuda(:\d+)?|mps")


def device_form_problem(device: Any) -> str:
    """Why ``device`` is not one of the accepted forms (:data:`DEVICES`; '' if it is), without importing torch: asked
    when the graph is validated. Before, any torch device type passed (``meta``: tensors without data, the run failed
    at start-up; ``xpu``, ``hip``: never tried here) and a typo (``gpu``) was found only at start-up."""
    if isinstance(device, str) and _DEVICE_FORM.fullmatch(device):
        return ""
    hint = ""
    if isinstance(device, str) and device.strip().lower() in ("gpu", "nvidia"):
        hint = "; an NVIDIA GPU is 'cuda'"
    elif isinstance(device, str) and _DEVICE_FORM.fullmatch(device.strip().lower()):
        hint = f"; did you mean {device.strip().lower()!r}?"
    return f"expected {DEVICES}, got {device!r}{hint}"


def device_problem(device: Any, name: str) -> str:
    """Why the pipeline cannot run on ``device`` here ('' if it can), led by the parameter's ``name`` ('device',
    '--device'): not an accepted form (:func:`device_form_problem`), or no such device on this machine."""
    form = device_form_problem(device)
    if form:
        return f"{name}: {form}"
    import torch

    dev = torch.device(device)
    cpu = "device: cpu" if name == "device" else f"{name} cpu"
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            return f"{name} {device!r}: torch sees no CUDA GPU here; use {cpu}"
        n = torch.cuda.device_count()
        if dev.index is not None and dev.index >= n:
            return f"{name} {device!r}: torch sees {n} CUDA GPU(s) here (cuda:0 to cuda:{n - 1})"
    if dev.type == "mps" and not torch.backends.mps.is_available():
        return f"{name} {device!r}: MPS is not available; use {cpu}"
    return ""


@dataclass
class DepthResult:
    depth: np.ndarray          # float32 (rows, cols) m, positive into the gel
    max_depth: float           # m
    contact_mask: np.ndarray   # bool (rows, cols)
    contact_area: float        # m^2
    centroid: np.ndarray       # float64 (2,) m from the image centre (x along columns, y along rows); NaN if none
    # the frame's global colour change from the background per channel (B, G, R; 0-255 levels): the drift
    # correction's estimate (the `depth` node flags a frame whose change is implausibly large: LEDs off, saturated)
    offset: np.ndarray | None = None
    changed: bool = False      # some cell of the work grid counts as touched (the change mask after opening)


def contact_summary(depth: np.ndarray, m_per_px: float, contact_depth: float, contact_fraction: float = 0.5,
                    origin: tuple[int, int] = (0, 0), shape: tuple[int, int] | None = None
                    ) -> tuple[np.ndarray, float, np.ndarray]:
    """Contact mask, its area (m^2) and depth-weighted centroid (m from the image centre).

    A pixel is in contact where depth > max(contact_depth, contact_fraction x max depth): around a contact the gel
    sags as well, and for a ball on an elastic half space (Hertz) the contact edge lies at half the indentation.
    ``depth`` may be a window of the image (zero depth outside it): ``origin`` is its (row, col) in the image and
    ``shape`` the image's (rows, cols); the mask is then the window's and the centroid is from the image's centre.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.dtype.kind != "f":
        raise ValueError(f"contact_summary: expected a 2-D float depth map (m), got {depth.dtype} {depth.shape}")
    if depth.dtype not in (np.float32, np.float64):
        depth = depth.astype(np.float32)   # OpenCV's moments take float32 or float64
    top = float(depth.max()) if depth.size else 0.0
    if depth.size and not (math.isfinite(top) and math.isfinite(float(depth.min()))):
        # an inf would read as no contact (nothing exceeds half of it), a NaN would drop the contact_fraction test
        bad = np.argwhere(~np.isfinite(depth))
        raise ValueError(f"contact_summary: {len(bad)} depths are NaN or inf (the first at row {bad[0][0]}, column "
                         f"{bad[0][1]}): expected a finite depth map (m)")
    mask = depth > max(contact_depth, contact_fraction * top)
    n = int(np.count_nonzero(mask))
    if n == 0:
        return mask, 0.0, np.array([math.nan, math.nan])
    import cv2

    # depth-weighted first moments of the contact (OpenCV sums in double; np.nonzero + gathers cost twice as much)
    mo = cv2.moments(np.where(mask, depth, np.zeros((), depth.dtype)))
    h, wd = depth.shape if shape is None else shape
    cx = mo["m10"] / mo["m00"] + origin[1] - (wd - 1) / 2.0
    cy = mo["m01"] / mo["m00"] + origin[0] - (h - 1) / 2.0
    return mask, n * m_per_px * m_per_px, np.array([cx * m_per_px, cy * m_per_px])


def _finite_top(zg: np.ndarray) -> float:
    """The largest depth of a work-grid depth map, or a ValueError if the map is not finite (normals from the
    network that are not: ``max(0.0, nan)`` would read as no contact, with a NaN depth map)."""
    top = float(zg.max()) if zg.size else 0.0
    if not math.isfinite(top):
        raise ValueError(f"the depth solve gave {top} depth: the network's normals are not finite (a corrupt model "
                         f"in memory, or a numeric overflow)")
    return top


def _resize_linear(z: np.ndarray, s: int) -> np.ndarray:
    """Bilinear upsampling by an integer factor s (OpenCV; pixel centres aligned)."""
    import cv2

    return cv2.resize(z, (z.shape[1] * s, z.shape[0] * s), interpolation=cv2.INTER_LINEAR)


#: closing radius (cells) before the holes of the change mask are filled: a press's centre reached by a narrow bay of
#: unchanged cells (its rim's weakly lit side) is enclosed too
FILL_CLOSE = 3


def fill_enclosed(m: np.ndarray, close: int = FILL_CLOSE) -> np.ndarray:
    """Add, in place, to a (rows, cols) uint8 0/1 change mask what it encloses: its closing by a square of
    ``2 close + 1`` cells (the grid's outside counts as changed for the erosion, as on the torch path), then the holes
    of that, the cells no path of unchanged cells (4-connected) links to the grid's border.

    Why: a ball pressed in changes the colours on its sloped rim, least at its flat centre and on the rim's weakly
    lit side. Where the change there stays below the threshold, the mask is a ring, or a ring with a narrow gap, and
    the centre read as untouched gel: zero depth, a crater at the deepest point (the cap height 85-100% low; the VGA
    presses with a single-frame background, whose threshold is higher, docs/depth.md).

    The work is done on the changed cells' bounding box plus ``close + 1`` cells (a contact covers a small part of
    the grid), with the same result as on the whole grid: outside that box the closed mask is 0, and every unchanged
    cell there reaches the grid's border."""
    import cv2

    h, w = m.shape
    x, y, bw, bh = cv2.boundingRect(m)
    if bw == 0:
        return m
    e = close + 1
    r0, r1, c0, c1 = max(0, y - e), min(h, y + bh + e), max(0, x - e), min(w, x + bw + e)
    sub = m[r0:r1, c0:c1]   # a view: changed in place
    rh, rw = sub.shape
    if close > 0:
        k = np.ones((2 * close + 1,) * 2, np.uint8)
        grown = np.ones((rh + 2 * close, rw + 2 * close), np.uint8)   # 1: the grid's outside (counts as changed)
        grown[max(0, close - r0):min(rh + 2 * close, h - r0 + close),
              max(0, close - c0):min(rw + 2 * close, w - c0 + close)] = 0   # the grid's cells around the box: 0
        grown[close:close + rh, close:close + rw] = cv2.dilate(sub, k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        np.maximum(sub, cv2.erode(grown, k, borderType=cv2.BORDER_CONSTANT, borderValue=1)[close:close + rh,
                                                                                           close:close + rw], out=sub)
    framed = np.zeros((rh + 2, rw + 2), np.uint8)   # the frame: the grid's border, or unchanged cells reaching it
    framed[1:-1, 1:-1] = sub
    cv2.floodFill(framed, None, (0, 0), 2, flags=4)   # the unchanged cells reachable from the border (via the frame)
    sub[framed[1:-1, 1:-1] == 0] = 1
    return m


def fill_enclosed_torch(m: Any, close: int = FILL_CLOSE) -> Any:
    """:func:`fill_enclosed` for a batch of masks, float (B, 1, rows, cols) 0/1, on any torch device: the closing,
    then the unchanged cells reachable from the grid's border (4-connected), found by whole runs: along every row,
    then along every column, a run of unchanged cells that holds a reachable cell is reachable as a whole; the two
    passes alternate until a pair of them adds nothing. The outside of blobs takes two pairs (the second adds
    nothing), ~50 kernels and one host synchronisation; a path around the changed cells takes one pair more for each
    turn it must make. (Growing the reachable cells one cell a step, as before, took as many steps as the grid is
    wide: on an H100 ~330 kernel launches and 3.3 ms a fill; the whole frame's GPU work is now 0.4 ms.)"""
    free = _closing_torch(m, close)[:, 0] < 0.5
    free_t = free.transpose(1, 2).contiguous()   # columns as lines
    reach = free.clone()
    reach[:, 1:-1, 1:-1] = False                 # the unchanged cells on the border
    row_runs, col_runs = _run_index(free), _run_index(free_t)
    count = None
    while True:
        reach = _spread(reach, free, row_runs)
        reach = _spread(reach.transpose(1, 2), free_t, col_runs).transpose(1, 2)
        new = reach.sum()
        if count is not None and bool(new == count):   # the first pair never ends it: one host sync where two do
            return (~reach).to(m.dtype)[:, None]
        count = new


def _closing_torch(m: Any, close: int) -> Any:
    """Float (B, 1, rows, cols) 0/1 masks with their closing by a square of ``2 close + 1`` cells added (the grid's
    outside counts as changed for the erosion: max-pooling pads with -inf)."""
    import torch.nn.functional as F

    if close <= 0:
        return m
    k = 2 * close + 1
    return m.maximum(-F.max_pool2d(-F.max_pool2d(m, k, stride=1, padding=close), k, stride=1, padding=close))


def _run_index(free: Any) -> Any:
    """(B, lines, n) bool -> the index of each cell's run along the last axis, unique over the batch and lines: a
    changed cell starts a new run (it joins the run after it, harmlessly: it is never reachable)."""
    import torch

    lines = free.shape[0] * free.shape[1]
    n = free.shape[2]
    first = torch.arange(lines, device=free.device, dtype=torch.int64).view(free.shape[:2] + (1,)) * (n + 1)
    return (~free).to(torch.int64).cumsum(-1) + first


def _spread(reach: Any, free: Any, runs: Any) -> Any:
    """reach (B, lines, n) bool grown along the last axis to the whole of every run of free cells it touches."""
    import torch

    hits = torch.zeros(runs.shape[0] * runs.shape[1] * (runs.shape[2] + 1), dtype=torch.float32, device=runs.device)
    hits.index_add_(0, runs.reshape(-1), reach.reshape(-1).to(torch.float32))
    return (hits[runs] > 0) & free


def channel_offset(d: np.ndarray) -> np.ndarray:
    """Global per-channel offset of a (rows, cols, 3) difference image: the median over every 4th cell (the
    upper middle element; a contact covers a small part of the frame, so this is the illumination drift)."""
    sub = np.ascontiguousarray(d[::4, ::4].reshape(-1, 3).T)
    k = sub.shape[1] // 2
    return np.partition(sub, k, axis=1)[:, k].astype(np.float32)


class DepthPipeline:
    """A calibrated model + settings -> depth maps. ``pipeline(frame_bgr_uint8) -> DepthResult``.

    ``device``: one of :data:`DEVICES` (a ``torch.device`` of those forms too) that is there on this machine; another
    (``meta``, a typo, ``cuda:N`` beyond the GPUs torch sees, ``cuda`` or ``mps`` where there is none) is a ValueError
    here, naming it (:func:`device_problem`, which the ``depth`` node and ``teletouch estimate`` ask too), not a torch
    error in the first frame."""

    def __init__(self, model: NormalModel, device: str = "cpu", mode: str = "auto",
                 change_threshold: float | None = None, dilate: int = 2, net_rim: int = 1, nz_min: float = 0.3,
                 contact_depth: float = 3e-5, contact_fraction: float = 0.5, margin: int = 4,
                 workers: int | None = None, drift_correction: bool = True, background: np.ndarray | None = None,
                 clamp_negative: bool = True, threads: int | None = None, baseline: str = "none"):
        import torch

        if isinstance(device, torch.device):
            device = str(device)
        problem = device_problem(device, "device")
        if problem:
            raise ValueError(f"DepthPipeline: {problem}")
        if threads is not None and torch.device(device).type == "cpu":
            torch.set_num_threads(int(threads))   # process-wide; small tensors: 1 thread is fastest

        self.torch = torch
        self.model = model
        self.device = torch.device(device)
        if mode == "auto":
            mode = "sparse" if self.device.type == "cpu" else "dense"
        if mode not in ("sparse", "dense"):
            raise ValueError(f"mode must be 'auto', 'sparse' or 'dense', got {mode!r}")
        self.mode = mode
        # the dense path's solve: torch.fft where the tensors are (a GPU), else scipy.fft (:meth:`_solve_dense`)
        self._torch_solve = self.device.type != "cpu"
        self.change_threshold = float(model.change_threshold if change_threshold is None else change_threshold)
        self.depth_gain = float(model.depth_gain)
        self.dilate = int(dilate)
        self.net_rim = int(net_rim)
        self.nz_min = float(nz_min)
        self.contact_depth = float(contact_depth)
        self.contact_fraction = float(contact_fraction)
        self.margin = int(margin)
        self.workers = workers
        self.drift_correction = drift_correction
        self.clamp_negative = clamp_negative
        if baseline not in ("none", "plane"):
            raise ValueError(f"baseline must be 'none' or 'plane', got {baseline!r}")
        self.baseline = baseline
        self.stride = max(1, int(model.stride))
        self.rows, self.cols = model.shape
        self.grows, self.gcols = self.rows // self.stride, self.cols // self.stride
        self.net = model.net(self.device)
        self.mean = torch.as_tensor(model.feat_mean, dtype=torch.float32, device=self.device)
        self.inv_std = 1.0 / torch.as_tensor(model.feat_std, dtype=torch.float32, device=self.device)
        self.nfeat = feature_count(model.feature_set)
        # grid coordinates in [-1, 1] (block centres in full-resolution pixels; same mapping as in training)
        s = self.stride
        gr = (torch.arange(self.grows, dtype=torch.float32) * s + (s - 1) / 2.0 + 0.5) * (2.0 / self.rows) - 1.0
        gc = (torch.arange(self.gcols, dtype=torch.float32) * s + (s - 1) / 2.0 + 0.5) * (2.0 / self.cols) - 1.0
        self.grid_y = gr[:, None].expand(self.grows, self.gcols).contiguous().to(self.device)
        self.grid_x = gc[None, :].expand(self.grows, self.gcols).contiguous().to(self.device)
        self.set_background(model.background if background is None else background)
        self._offset = np.zeros(3, np.float32)   # the last frame's global colour change (DepthResult.offset)
        self._changed = False
        self._use_xy = uses_xy(model.feature_set)
        self._context = context_cells(model.feature_set)
        # x and y of every cell, one row each (the CPU path gathers a row per input)
        self._xy_np = np.ascontiguousarray(torch.stack([self.grid_x, self.grid_y]).reshape(2, -1).cpu().numpy())
        self._fold_layers()
        self._k3 = np.ones((3, 3), np.uint8)
        self._ones13 = np.ones((1, 3), np.float32)
        self._kd = np.ones((2 * (self.dilate + 1) + 1,) * 2, np.uint8)
        self._kn = np.ones((2 * (min(self.net_rim, self.dilate) + 1) + 1,) * 2, np.uint8)
        self.m_per_cell = s / model.px_per_m * self.depth_gain
        # the sparse path's outputs can be computed on its solve window alone (see __call__): where the window ends
        # inside the grid its outer cells are zero (``margin`` >= ``dilate`` + 2), so bilinear upsampling reads the
        # same zeros beyond them as the window's replicated edge; where it ends at the grid's border, both replicate
        # the same edge; and the frame must be a whole number of work cells (no edge padding)
        self._window_outputs = (s > 1 and self.margin >= self.dilate + 2
                                and (self.grows * s, self.gcols * s) == (self.rows, self.cols))

    # ---------------------------------------------------------------------------------------------------------
    def set_background(self, background: np.ndarray) -> None:
        bg = np.asarray(background)
        if bg.shape != (self.rows, self.cols, 3):
            raise ModelFileError(f"background is {bg.shape}, expected ({self.rows}, {self.cols}, 3) like the model")
        t = self.torch.as_tensor(np.ascontiguousarray(bg), device=self.device)
        self.background_grid = self._pool(t[None])
        self._bg_grid_np = self.background_grid[0].permute(1, 2, 0).cpu().numpy().copy()

    def _pool(self, frames: Any) -> Any:
        """(B, rows, cols, 3) uint8 (or float) -> (B, 3, gr, gc) float32 block means, a new tensor."""
        torch = self.torch
        s = self.stride
        b = frames.shape[0]
        x = frames[:, : self.grows * s, : self.gcols * s]
        if s > 1:
            x = x.reshape(b, self.grows, s, self.gcols, s, 3).sum(dim=(2, 4), dtype=torch.float32)
            x = x * (1.0 / (s * s))
        else:
            # a copy also of float input: .float() would return a float32 tensor itself, and a background given
            # as a float32 array (the `depth` node's adapted one) is then a view of the caller's array
            x = x.to(torch.float32, copy=True)
        return x.permute(0, 3, 1, 2)

    def check_frame(self, frame: np.ndarray) -> None:
        if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.shape != (self.rows, self.cols, 3):
            got = f"{frame.dtype} {frame.shape}" if isinstance(frame, np.ndarray) else type(frame).__name__
            raise ValueError(f"expected a uint8 BGR image of {self.rows}x{self.cols}x3 (rows x cols, portrait) "
                             f"like the model {self.model.source}, got {got}")

    def check_frames(self, frames: Any) -> None:
        """A batch for :meth:`batch_depth`: uint8 (B, rows, cols, 3), numpy or torch; else a ValueError (a float
        batch would be read without complaint, a NaN pixel as a NaN depth map)."""
        torch = self.torch
        shape = tuple(frames.shape) if isinstance(frames, (np.ndarray, torch.Tensor)) else None
        ok = (isinstance(frames, np.ndarray) and frames.dtype == np.uint8) or (
            isinstance(frames, torch.Tensor) and frames.dtype == torch.uint8)
        if not ok or shape is None or len(shape) != 4 or shape[1:] != (self.rows, self.cols, 3):
            got = f"{frames.dtype} {shape}" if shape is not None else type(frames).__name__
            raise ValueError(f"batch_depth: expected uint8 BGR frames of B x {self.rows} x {self.cols} x 3 (frames x "
                             f"rows x cols x channels, portrait) like the model {self.model.source}, got {got}")

    def _grid(self, frames: Any) -> tuple[Any, Any]:
        """(B, rows, cols, 3) uint8 tensor -> block-averaged frame and drift-corrected diff, (B, 3, gr, gc)."""
        x = self._pool(frames.to(self.device, non_blocking=True))
        d = x - self.background_grid
        # robust global offset per channel (the contact covers a small part of the frame)
        sub = d[:, :, ::4, ::4].reshape(d.shape[0], 3, -1)
        k = sub.shape[2] // 2
        off = self._offsets = sub.sort(dim=2).values[:, :, k]
        if self.drift_correction:
            d = d - off[:, :, None, None]
        return x, d

    def _mask(self, d: Any) -> tuple[Any, Any]:
        """(core, keep): the network's slopes count on core (change region + ``net_rim`` + 1 cells), the depth is
        kept on keep (change region + ``dilate`` + 1 cells), as on the sparse path."""
        import kornia.filters as KF
        import torch.nn.functional as F

        a = d.abs().sum(dim=1, keepdim=True)
        a = KF.box_blur(a, (3, 3), border_type="replicate")
        m = (a > self.change_threshold).float()
        # opening (drops specks of noise smaller than 3 x 3 cells), then dilation to take in the contact's rim
        m = -F.max_pool2d(-m, 3, stride=1, padding=1)
        k = 2 * (self.dilate + 1) + 1
        keep = F.max_pool2d(m, k, stride=1, padding=self.dilate + 1)
        rim = min(self.net_rim, self.dilate) + 1
        core = F.max_pool2d(m, 2 * rim + 1, stride=1, padding=rim)
        both = self._fill(self.torch.cat([core, keep]))[:, 0] > 0.5   # one call: half the kernel launches on a GPU
        return both[: m.shape[0]], both[m.shape[0]:]

    def _fill(self, m: Any) -> Any:
        """(B, 1, gr, gc) 0/1 masks with what they enclose, as on the sparse path (:func:`fill_enclosed`)."""
        if m.device.type != "cpu":
            return fill_enclosed_torch(m)
        mn = (m[:, 0] > 0.5).to(self.torch.uint8).numpy()   # OpenCV's flood fill: the torch steps are ~100x slower
        for f in mn:
            if f.any():
                fill_enclosed(f)
        return self.torch.from_numpy(mn).to(m.dtype)[:, None]

    def _features(self, x: Any, d: Any) -> Any:
        """(B, 3, gr, gc) frame and diff -> standardised (B, gr, gc, F) features."""
        torch = self.torch
        b = x.shape[0]
        parts = [colour_maps_torch(self.model.feature_set, x, d, self.background_grid)]
        if self._use_xy:
            parts.append(self.grid_x.expand(b, 1, -1, -1))
            parts.append(self.grid_y.expand(b, 1, -1, -1))
        f = torch.cat(parts, dim=1).permute(0, 2, 3, 1)
        return (f - self.mean) * self.inv_std

    def _fold_layers(self) -> None:
        """The network's linear layers with the input standardisation folded into the first one, for the CPU path:
        W' = W diag(1 / std), b' = b - W (mean / std); each as (W (out, in), b (out, 1)) for column-wise cells."""
        torch = self.torch
        lin = [m for m in self.net if isinstance(m, torch.nn.Linear)]
        with torch.no_grad():
            w0 = lin[0].weight * self.inv_std[None, :]
            b0 = lin[0].bias - lin[0].weight @ (self.mean * self.inv_std)
            layers = [(w0, b0)] + [(m.weight, m.bias) for m in lin[1:]]
            self._layers = [(w.detach().cpu().contiguous(), b.detach().cpu().reshape(-1, 1).contiguous())
                            for w, b in layers]

    def _fast_mlp(self, x: Any) -> Any:
        """The folded network on cells as columns: x (features, n) -> (3, n), a view of a preallocated buffer that
        the next call overwrites. Cells as columns: each layer is W (out x in) @ X (in x n), long rows for the
        BLAS kernel (on sim-digit's probe frames, 8600 cells: 1.5 -> 1.15 ms against cells as rows); preallocated
        outputs: fresh megabyte-sized tensors per layer and frame cost page faults (4.1 -> 3.3 ms a frame)."""
        torch = self.torch
        n = x.shape[1]
        with torch.inference_mode():
            outs = getattr(self, "_mlp_out", None)
            if outs is None or outs[0].numel() < self._layers[0][0].shape[0] * n:
                cells = max(n, self.grows * self.gcols)
                outs = self._mlp_out = [torch.empty(w.shape[0] * cells) for w, _ in self._layers]
            last = len(self._layers) - 1
            for i, (w, b) in enumerate(self._layers):
                out = outs[i][: w.shape[0] * n].view(w.shape[0], n)   # contiguous (out, n)
                torch.addmm(b, w, x, out=out)
                if i < last:
                    out.relu_()
                x = out
            return x

    def _gradients(self, n: Any) -> tuple[Any, Any]:
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        nz = n[..., 2].clamp_min(self.nz_min)
        return -n[..., 0] / nz, -n[..., 1] / nz

    # ---------------------------------------------------------------------------------------------------------
    def grid_depth(self, frame: np.ndarray) -> np.ndarray:
        """Depth on the work grid (grows, gcols), metres, numpy float32."""
        return self._grid_depth(frame)[0]

    def _grid_depth(self, frame: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int, int] | None]:
        """Depth on the work grid, and the sparse path's solve window (r0, r1, c0, c1) outside which it is zero
        (None: the dense path, or no change)."""
        self.check_frame(frame)
        if self.mode == "sparse":
            return self._sparse_depth(frame)
        torch = self.torch
        with torch.inference_mode():
            # contiguous: torch cannot take a view with negative strides (a frame flipped by numpy, frame[::-1])
            x, d = self._grid(torch.from_numpy(np.ascontiguousarray(frame))[None])
            core, m = self._mask(d)
            gx, gy = self._dense_gradients(x, d, core)
            z = self._solve_dense(gx[0], gy[0]) * self.m_per_cell
            if self.baseline == "plane":
                z = self._baseline_torch(z[None].double(), m)[0]
            z = z * m[0]
            if self.clamp_negative:
                z = z.clamp_min(0.0)
            zn = z.float().cpu().numpy()
            # read back after the depth: on a GPU each read waits for the work queued before it
            self._offset = self._offsets[0].float().cpu().numpy()
            self._changed = bool(core.any())
            return zn, None

    def _solve_dense(self, gx: Any, gy: Any) -> Any:
        """The dense path's whole-grid solve of one frame's slopes (gr, gc) -> depth in cells: torch.fft on the
        tensors' device, or scipy.fft on CPU (see ``_torch_solve``). Both raise :func:`poisson.integrate`'s
        ValueError for slopes that are not finite or a depth that overflows (the batched solve gives NaN then)."""
        if self._torch_solve:
            return poisson.integrate_torch_strict(gx, gy)
        return self.torch.from_numpy(poisson.integrate(gx.numpy(), gy.numpy(), self.workers))

    def _sparse_depth(self, frame: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int, int] | None]:
        """CPU fast path: OpenCV block means and morphology (measured several times faster than the same torch ops
        on small CPU images), the torch MLP on the changed cells only, the scipy DST solve on their window."""
        import cv2

        torch = self.torch
        gr, gc = self.grows, self.gcols
        s = self.stride
        b = self._buffers()   # preallocated: fresh large arrays would cost page faults on every frame
        x, d = b["x"], b["d"]
        if s > 1:
            # exact block means: 4 x the frame in uint16, OpenCV's area resize (integer), then / 4
            np.multiply(frame[: gr * s, : gc * s], 4, out=b["u16"], dtype=np.uint16)
            cv2.resize(b["u16"], (gc, gr), dst=b["x16"], interpolation=cv2.INTER_AREA)
            np.multiply(b["x16"], np.float32(0.25), out=x, dtype=np.float32)
        else:
            x[...] = frame
        np.subtract(x, self._bg_grid_np, out=d)
        off = self._offset = channel_offset(d)
        if self.drift_correction:
            # subtract per channel as one row of gc x 3 values: numpy's broadcast over a last axis of 3 runs its
            # inner loop 3 elements at a time (0.19 ms here against 0.03 ms, the same numbers)
            d2 = d.reshape(gr, gc * 3)
            np.subtract(d2, np.tile(off, gc), out=d2)
        np.abs(d, out=b["absd"])
        cv2.transform(b["absd"], self._ones13, dst=b["a"])
        cv2.blur(b["a"], (3, 3), dst=b["a2"], borderType=cv2.BORDER_REPLICATE)
        m = b["m"]
        np.greater(b["a2"], self.change_threshold, out=b["mb"])
        m[...] = b["mb"]
        cv2.erode(m, self._k3, dst=b["m2"])
        core = cv2.dilate(b["m2"], self._kn)   # the network runs here (change region + `net_rim` cells)
        keep = cv2.dilate(b["m2"], self._kd)   # depth is kept here (change region + `dilate` + 1 cells)
        nz_pts = cv2.findNonZero(core)
        if nz_pts is not None:
            # a press's flat centre, enclosed by its changed rim, is pressed in: not the untouched zero reference
            fill_enclosed(core)
            fill_enclosed(keep)
            nz_pts = cv2.findNonZero(core)
        self._changed = nz_pts is not None
        if nz_pts is None:
            return np.zeros((gr, gc), np.float32), None
        nz_pts = nz_pts.reshape(-1, 2)
        c = nz_pts[:, 0].astype(np.intp)
        r = nz_pts[:, 1].astype(np.intp)
        idx = r * gc + c
        # colour features on the cells' bounding box (+ the neighbourhood a feature reads; at the grid's border the
        # box ends where the grid does, so the replicated border is the same as on the whole grid)
        q = self._context
        ncell = idx.size
        feats = b["feats"][: self.nfeat * ncell].reshape(self.nfeat, ncell)   # one row per input, cells as columns
        k = 0
        if q == 0:
            # cell-wise inputs: gather the changed cells first, compute the inputs on them alone (np.take: ~3x
            # faster than fancy indexing for rows of 3)
            for part in colour_parts(self.model.feature_set, *(np.take(a.reshape(-1, 3), idx, axis=0)[:, None]
                                                              for a in (x, d, self._bg_grid_np))):
                feats[k:k + 3] = part[:, 0].T
                k += 3
        else:
            w0, w1 = max(int(r.min()) - q, 0), min(int(r.max()) + 1 + q, gr)
            v0, v1 = max(int(c.min()) - q, 0), min(int(c.max()) + 1 + q, gc)
            at = (r - w0) * (v1 - v0) + (c - v0)
            for part in colour_parts(self.model.feature_set, x[w0:w1, v0:v1], d[w0:w1, v0:v1],
                                     self._bg_grid_np[w0:w1, v0:v1]):
                feats[k:k + 3] = np.take(part.reshape(-1, 3), at, axis=0).T
                k += 3
        if self._use_xy:
            np.take(self._xy_np, idx, axis=1, out=feats[k:k + 2])
        nx, ny, nz = self._fast_mlp(torch.from_numpy(feats)).numpy()
        nrm = np.maximum(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-6)
        nz = np.maximum(nz / nrm, self.nz_min) * nrm
        gx = np.zeros(gr * gc, np.float32)
        gy = np.zeros(gr * gc, np.float32)
        gx[idx] = -nx / nz
        gy[idx] = -ny / nz
        r0 = max(int(r.min()) - self.margin, 0)
        r1 = min(int(r.max()) + 1 + self.margin, gr)
        c0 = max(int(c.min()) - self.margin, 0)
        c1 = min(int(c.max()) + 1 + self.margin, gc)
        z = poisson.integrate_window(gx.reshape(gr, gc), gy.reshape(gr, gc), self._solve_box(r0, r1, c0, c1),
                                     workers=self.workers)
        z *= self.m_per_cell
        if self.baseline != "none":
            self._subtract_baseline(z, keep, (r0, r1, c0, c1))
        z[keep == 0] = 0.0
        if self.clamp_negative:
            np.maximum(z, 0.0, out=z)
        return z, (r0, r1, c0, c1)

    def _solve_box(self, r0: int, r1: int, c0: int, c1: int) -> tuple[int, int, int, int]:
        """Where the sparse path solves: the window (r0, r1, c0, c1) around the changed cells, or the whole grid
        where the window reaches the grid's border.

        The window's solve (z = 0 around it) equals the whole grid's where that is zero around the window, as it is
        around a contact inside the grid. A contact cut by the image border is not: the grid's zero boundary runs
        through it, and the solve's residual spreads along the border, beyond any window (a 6 mm ball at the top or
        bottom row read 12-28% off the dense path's max depth, 40% at stride 7). The outputs still come from the
        window (the depth outside the kept region, which the window holds, is set to zero)."""
        if r0 == 0 or c0 == 0 or r1 == self.grows or c1 == self.gcols:
            return 0, self.grows, 0, self.gcols
        return r0, r1, c0, c1

    def _subtract_baseline(self, z: np.ndarray, keep: np.ndarray, box: tuple[int, int, int, int]) -> None:
        """``baseline="plane"``: the zero reference is the gel's rest plane around the contact. The solve's depth
        on the ring of cells just outside the kept region (flat by definition) is fitted by a plane (least squares)
        and subtracted inside the window, so the depth meets zero where the kept region ends."""
        import cv2

        r0, r1, c0, c1 = box
        kw = keep[r0:r1, c0:c1]
        ring = (cv2.dilate(kw, self._k3) > 0) & (kw == 0)
        rr, cc = np.nonzero(ring)
        if rr.size < 8:
            return
        gy = (np.arange(r0, r1) - self.grows / 2.0) / self.grows
        gx = (np.arange(c0, c1) - self.gcols / 2.0) / self.gcols
        A = np.column_stack([np.ones(rr.size), gy[rr], gx[cc]])
        coef, *_ = np.linalg.lstsq(A, z[r0:r1, c0:c1][rr, cc].astype(np.float64), rcond=None)
        z[r0:r1, c0:c1] -= (coef[0] + coef[1] * gy[:, None] + coef[2] * gx[None, :]).astype(np.float32)

    def _baseline_torch(self, z: Any, m: Any) -> Any:
        """The same plane baseline on the dense path, batched: z (B, gr, gc), m the kept region (B, gr, gc)."""
        import torch.nn.functional as F

        torch = self.torch
        mf = m.to(z.dtype)
        ring = (F.max_pool2d(mf[:, None], 3, stride=1, padding=1)[:, 0] - mf).clamp_min(0.0)
        gy = (torch.arange(self.grows, dtype=z.dtype, device=z.device) - self.grows / 2.0) / self.grows
        gx = (torch.arange(self.gcols, dtype=z.dtype, device=z.device) - self.gcols / 2.0) / self.gcols
        basis = torch.stack([torch.ones(self.grows, self.gcols, dtype=z.dtype, device=z.device),
                             gy[:, None].expand(-1, self.gcols), gx[None, :].expand(self.grows, -1)])  # (3, gr, gc)
        ata = torch.einsum("bhw,ihw,jhw->bij", ring, basis, basis)
        atz = torch.einsum("bhw,ihw,bhw->bi", ring, basis, z)
        ok = ring.sum(dim=(1, 2)) >= 8
        eye = torch.eye(3, dtype=z.dtype, device=z.device)
        coef = torch.linalg.solve(ata + 1e-9 * eye, atz[..., None])[..., 0] * ok[:, None]
        return z - torch.einsum("bi,ihw->bhw", coef, basis)

    def _buffers(self) -> dict[str, np.ndarray]:
        b = getattr(self, "_buf", None)
        if b is None:
            gr, gc, s = self.grows, self.gcols, self.stride
            b = {"u16": np.empty((gr * s, gc * s, 3), np.uint16), "x16": np.empty((gr, gc, 3), np.uint16),
                 "x": np.empty((gr, gc, 3), np.float32), "d": np.empty((gr, gc, 3), np.float32),
                 "absd": np.empty((gr, gc, 3), np.float32), "a": np.empty((gr, gc), np.float32),
                 "a2": np.empty((gr, gc), np.float32), "mb": np.empty((gr, gc), bool),
                 "m": np.empty((gr, gc), np.uint8), "m2": np.empty((gr, gc), np.uint8),
                 "feats": np.empty(gr * gc * self.nfeat, np.float32)}
            self._buf = b
        return b

    def _dense_gradients(self, x: Any, d: Any, m: Any) -> tuple[Any, Any]:
        f = self._features(x, d)
        gx, gy = self._gradients(self.net(f))
        mf = m.float()
        return gx * mf, gy * mf

    def batch_depth(self, frames: np.ndarray | Any) -> Any:
        """Dense, batched: (B, rows, cols, 3) uint8 -> (B, rows, cols) float32 depth tensor (m) on the device.

        Frames (a numpy array or a torch tensor) of another dtype or shape are refused with a ValueError, as
        :meth:`check_frame` refuses one frame. A frame whose depth cannot be computed (normals that are not finite:
        a corrupt model in memory; where one frame's call raises a ValueError) gets NaN everywhere; the other frames
        of the batch are the same as without it (:func:`poisson.integrate_torch`)."""
        import torch.nn.functional as F

        torch = self.torch
        self.check_frames(frames)
        with torch.inference_mode():
            t = frames if isinstance(frames, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(frames))
            x, d = self._grid(t)
            core, m = self._mask(d)
            gx, gy = self._dense_gradients(x, d, core)
            z = poisson.integrate_torch(gx, gy) * self.m_per_cell
            if self.baseline == "plane":
                z = self._baseline_torch(z, m)
            z = z * m
            if self.clamp_negative:
                z = z.clamp_min(0.0)
            if self.stride > 1:
                z = F.interpolate(z[:, None], size=(self.grows * self.stride, self.gcols * self.stride),
                                  mode="bilinear", align_corners=False)[:, 0]
                if z.shape[-2:] != (self.rows, self.cols):
                    z = F.pad(z, (0, self.cols - z.shape[-1], 0, self.rows - z.shape[-2]), mode="replicate")
            return z

    def upsample(self, zg: np.ndarray) -> np.ndarray:
        if self.stride == 1:
            return zg.astype(np.float32, copy=False)
        z = _resize_linear(zg, self.stride)
        if z.shape != (self.rows, self.cols):
            z = np.pad(z, ((0, self.rows - z.shape[0]), (0, self.cols - z.shape[1])), mode="edge")
        return z.astype(np.float32, copy=False)

    def warm_up(self) -> None:
        """Run the pipeline once on the background and on a synthetic touch, so that lazy imports and FFT set-up
        (~0.1 s) happen here and not on the first real frame."""
        bg = np.ascontiguousarray(self.model.background)
        self(bg)
        fake = bg.astype(np.int16)
        r, c = self.rows // 2, self.cols // 2
        k = max(self.rows // 16, 4)
        fake[r - k: r + k, c - k: c + k] += 40
        self(np.clip(fake, 0, 255).astype(np.uint8))

    def rehearse(self, frame: np.ndarray) -> None:
        """Run ``frame`` through the pipeline and throw the result away, the per-frame state (the frame's colour
        offset, whether it changed) put back: so that the next frame's computation finds its data and code in the
        CPU's caches, with the same outputs as without it (the depth node's warm())."""
        kept = (self._offset, self._changed)
        try:
            self(frame)
        finally:
            self._offset, self._changed = kept

    def max_depth(self, frame: np.ndarray) -> float:
        """The fast path for force estimation: frame -> max depth (m) without building the full-size map."""
        return max(0.0, _finite_top(self.grid_depth(frame)))

    def _cell_contact(self, zg: np.ndarray, top: float) -> tuple[np.ndarray, float, np.ndarray]:
        """The contact of a light touch at the threshold, on the work grid: max depth (the grid's largest cell)
        above ``contact_depth`` while no pixel of the upsampled map is (bilinear upsampling lowers a one-cell peak:
        at stride 2 a pixel takes at most 9/16 of its nearest cell). The cells deeper than max(contact_depth,
        contact_fraction x max depth), each its ``stride x stride`` pixels; the centroid weighted by their depths at
        their centres. Only when the full-size map gives no contact, so a frame with one is read as before."""
        s = self.stride
        cells = zg > max(self.contact_depth, self.contact_fraction * top)
        mask = np.zeros((self.rows, self.cols), bool)
        mask[: self.grows * s, : self.gcols * s] = np.repeat(np.repeat(cells, s, axis=0), s, axis=1)
        rr, cc = np.nonzero(cells)
        w = zg[rr, cc].astype(np.float64)
        m = 1.0 / self.model.px_per_m
        cy = float(np.dot(w, rr * s + (s - 1) / 2.0) / w.sum()) - (self.rows - 1) / 2.0
        cx = float(np.dot(w, cc * s + (s - 1) / 2.0) / w.sum()) - (self.cols - 1) / 2.0
        return mask, int(np.count_nonzero(mask)) * m * m, np.array([cx * m, cy * m])

    def __call__(self, frame: np.ndarray) -> DepthResult:
        zg, w = self._grid_depth(frame)
        top = _finite_top(zg)
        if not zg.any():
            # no depth anywhere (the gel at rest): the same outputs without upsampling and summing a zero map
            # (0.25 ms of the 0.5 ms such a frame costs)
            return DepthResult(depth=np.zeros((self.rows, self.cols), np.float32), max_depth=0.0,
                               contact_mask=np.zeros((self.rows, self.cols), bool), contact_area=0.0,
                               centroid=np.array([math.nan, math.nan]), offset=self._offset, changed=self._changed)
        if w is None or not self._window_outputs:
            depth = self.upsample(zg)
            mask, area, centroid = contact_summary(depth, 1.0 / self.model.px_per_m, self.contact_depth,
                                                   self.contact_fraction)
        else:
            # the sparse path's depth is zero outside its solve window, whose outer cells are zero too (the kept
            # region ends `margin - dilate - 1` cells inside it): upsampling and summing the window alone gives the
            # same outputs as the whole frame (tested) for a fraction of the pixels (a ball press: ~1/10)
            r0, r1, c0, c1 = w
            s = self.stride
            sub = _resize_linear(zg[r0:r1, c0:c1], s)
            depth = np.zeros((self.rows, self.cols), np.float32)
            depth[r0 * s:r1 * s, c0 * s:c1 * s] = sub
            msub, area, centroid = contact_summary(sub, 1.0 / self.model.px_per_m, self.contact_depth,
                                                   self.contact_fraction, origin=(r0 * s, c0 * s),
                                                   shape=(self.rows, self.cols))
            mask = np.zeros((self.rows, self.cols), bool)
            mask[r0 * s:r1 * s, c0 * s:c1 * s] = msub
        if area == 0.0 and top > self.contact_depth:
            mask, area, centroid = self._cell_contact(zg, top)
        return DepthResult(depth=depth, max_depth=max(0.0, top), contact_mask=mask,
                           contact_area=area, centroid=centroid, offset=self._offset, changed=self._changed)
