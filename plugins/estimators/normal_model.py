"""The per-pixel normal network and its model file.

Network: an MLP from per-pixel features to the surface normal (nx, ny, nz) of the gel, as in the paper (R, G, B,
X, Y -> normal), or with the pixel's change from the background frame instead of its colour (it helps most; see
docs/depth.md). Layers: Linear(in, 32) -> ReLU -> Dropout(0.05) -> Linear(32, 32) -> ReLU ->
Dropout(0.05) -> Linear(32, 32) -> ReLU -> Linear(32, 3).

Features (same function in training and inference, so coordinates are normalised identically):
  rgb:  the pixel's B, G, R / 255;  diff: (pixel - background) / 255;  ratio: (pixel - background) / background
  (relative change); grad: Sobel derivatives of the ratio (local context); xy: column and row mapped to [-1, 1] by
  the image size (x = (col + 0.5) / cols * 2 - 1). See :func:`colour_maps`. Each feature is then standardised by a
  mean and std fitted on the training pixels and stored in the model file.

Model file (``*.model``): a NumPy .npz archive written without pickling (``np.load(..., allow_pickle=False)``
reads it; no code can be executed by loading it):
  ``meta``        JSON text: format "teletouch-depth-model", version, features, hidden sizes, image rows/cols,
                  orientation "portrait-bgr", px_per_m, ball radius, work stride, change threshold, depth gain,
                  training metadata, validation metrics
  ``w.<name>``    each tensor of the network's state_dict (float32)
  ``feat_mean``, ``feat_std``   the input normalisation
  ``background``  uint8 (rows, cols, 3) BGR no-contact frame
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from teletouch.errors import ModelFileError
from teletouch.paths import input_file

__all__ = [
    "FORMAT", "VERSION", "FEATURE_SETS", "DEFAULT_FEATURES", "make_net", "colour_maps", "colour_maps_torch",
    "features", "uses_xy", "context_cells", "feature_count", "NormalModel", "load_model", "packaged_model_path",
    "resolve_model", "check_model_file", "model_image_shape", "atomic_write",
]

FORMAT = "teletouch-depth-model"
VERSION = 1
FEATURE_SETS = {"rgbxy": 5, "diffxy": 5, "rgbxy+diff": 8, "diff": 3, "ratioxy": 5, "ratio+gradxy": 11}
DEFAULT_FEATURES = "ratio+gradxy"   # the most accurate on the shared real presses (docs/depth.md)
#: hidden layer sizes of the calibration's network. Two layers of 32: on the shared QVGA presses (5 folds, six
#: training seeds) a median cap-height error of 5.9-10.3% (mean 8.0%) against 7.4-11.9% (9.4%) with three layers of
#: 32 (the default before), and a third fewer multiply-adds per cell (docs/depth.md)
DEFAULT_HIDDEN: tuple[int, ...] = (32, 32)
DATA_DIR = Path(__file__).resolve().parent / "data"


def feature_count(feature_set: str) -> int:
    try:
        return FEATURE_SETS[feature_set]
    except KeyError:
        raise ValueError(f"unknown feature set {feature_set!r}; expected one of {sorted(FEATURE_SETS)}") from None


def make_net(n_in: int, hidden: tuple[int, ...] = DEFAULT_HIDDEN, dropout: float = 0.05) -> Any:
    """The MLP (torch.nn.Sequential); dropout after every hidden layer but the last."""
    import torch.nn as nn

    layers: list[Any] = []
    prev = n_in
    for i, h in enumerate(hidden):
        layers += [nn.Linear(prev, h), nn.ReLU()]
        if dropout > 0 and i < len(hidden) - 1:
            layers.append(nn.Dropout(dropout))
        prev = h
    layers.append(nn.Linear(prev, 3))
    return nn.Sequential(*layers)


def xy_features(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates mapped to [-1, 1] by the image size (the one definition used everywhere)."""
    h, w = shape
    x = (np.asarray(cols, dtype=np.float32) + 0.5) * (2.0 / w) - 1.0
    y = (np.asarray(rows, dtype=np.float32) + 0.5) * (2.0 / h) - 1.0
    return x, y


RATIO_FLOOR = 16.0   # background level (0..255) below which the relative change is taken against this floor


def colour_maps(feature_set: str, frame: np.ndarray, diff: np.ndarray, background: np.ndarray) -> np.ndarray:
    """The per-cell colour features of a work grid (all inputs but x, y), float32 (rows, cols, k): the parts of
    :func:`colour_parts` side by side."""
    parts = colour_parts(feature_set, frame, diff, background)
    out = np.concatenate(parts, axis=2) if len(parts) > 1 else parts[0]
    return out.astype(np.float32, copy=False)


def colour_parts(feature_set: str, frame: np.ndarray, diff: np.ndarray, background: np.ndarray
                 ) -> list[np.ndarray]:
    """The colour features as a list of float32 (rows, cols, 3) maps, in input order (no copy into one array:
    numpy's concatenation along a last axis of 3 is slow, ~0.45 ms for a QVGA work grid).

    frame, diff, background: float32 (rows, cols, 3) BGR on the work grid (0..255 scale; diff drift-corrected).
    rgb = frame / 255; diff = diff / 255; ratio = diff / max(background, RATIO_FLOOR), the relative colour change
    (the light of each LED falls off across the gel, and a slope changes a pixel's colour in proportion to the
    light it gets, so the ratio depends less on where the press is); grad = the 3 x 3 Sobel derivatives / 8 of the
    ratio along columns and rows (replicated border), the local context of each cell.
    """
    import cv2

    parts: list[np.ndarray] = []
    if feature_set in ("rgbxy", "rgbxy+diff"):
        parts.append(frame * np.float32(1.0 / 255.0))
    if feature_set in ("diffxy", "rgbxy+diff", "diff"):
        parts.append(diff * np.float32(1.0 / 255.0))
    if feature_set in ("ratioxy", "ratio+gradxy"):
        r = diff / np.maximum(background, np.float32(RATIO_FLOOR))
        parts.append(r)
        if feature_set == "ratio+gradxy":
            parts.append(cv2.Sobel(r, cv2.CV_32F, 1, 0, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE))
            parts.append(cv2.Sobel(r, cv2.CV_32F, 0, 1, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE))
    if not parts:
        feature_count(feature_set)
    return [np.asarray(p_, dtype=np.float32) for p_ in parts]


def colour_maps_torch(feature_set: str, frame: Any, diff: Any, background: Any) -> Any:
    """:func:`colour_maps` on torch tensors (B, 3, rows, cols) -> (B, k, rows, cols), with kornia's Sobel."""
    import torch

    parts: list[Any] = []
    if feature_set in ("rgbxy", "rgbxy+diff"):
        parts.append(frame * (1.0 / 255.0))
    if feature_set in ("diffxy", "rgbxy+diff", "diff"):
        parts.append(diff * (1.0 / 255.0))
    if feature_set in ("ratioxy", "ratio+gradxy"):
        r = diff / background.clamp_min(RATIO_FLOOR)
        parts.append(r)
        if feature_set == "ratio+gradxy":
            import kornia.filters as KF

            g = KF.spatial_gradient(r, mode="sobel", normalized=False) * 0.125   # (B, 3, 2, rows, cols)
            parts += [g[:, :, 0], g[:, :, 1]]
    if not parts:
        feature_count(feature_set)
    return torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]


def uses_xy(feature_set: str) -> bool:
    return feature_set != "diff"


def context_cells(feature_set: str) -> int:
    """How many cells on each side of a cell its colour features read (the Sobel of ratio+gradxy: 1)."""
    return 1 if feature_set == "ratio+gradxy" else 0


def features(feature_set: str, colours: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]
             ) -> np.ndarray:
    """Raw (unstandardised) network inputs, float32 (N, F): the cells' colour features (N, k) from
    :func:`colour_maps`, then x, y of their full-resolution positions (rows/cols, px) when the set uses them."""
    parts = [np.asarray(colours, dtype=np.float32)]
    if uses_xy(feature_set):
        x, y = xy_features(rows, cols, shape)
        parts += [x[:, None], y[:, None]]
    return np.concatenate(parts, axis=1).astype(np.float32, copy=False)


@dataclass
class NormalModel:
    """Everything the estimator needs: the network, its input normalisation, the background and the geometry."""

    feature_set: str
    hidden: tuple[int, ...]
    state_dict: dict[str, np.ndarray]
    feat_mean: np.ndarray
    feat_std: np.ndarray
    background: np.ndarray                # uint8 (rows, cols, 3) BGR
    px_per_m: float
    ball_radius_m: float = 0.003
    stride: int = 1                       # evaluate the network every `stride` px (then interpolate)
    change_threshold: float = 16.0        # colour change (0..255 levels, summed over B, G, R) that counts as contact
    depth_gain: float = 1.0               # scale fitted on the training presses' cap heights
    training: dict[str, Any] = field(default_factory=dict)
    validation: dict[str, Any] = field(default_factory=dict)
    source: str = "<memory>"

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.background.shape[0]), int(self.background.shape[1])

    @property
    def m_per_px(self) -> float:
        return 1.0 / self.px_per_m

    def net(self, device: Any = "cpu") -> Any:
        """A torch module in eval mode holding the weights."""
        import torch

        self._check_weights()
        net = make_net(feature_count(self.feature_set), self.hidden)
        sd = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in self.state_dict.items()}
        try:
            net.load_state_dict(sd)
        except RuntimeError as exc:
            raise ModelFileError(f"{self.source}: the weights do not fit a {self.feature_set} network with hidden "
                                 f"sizes {list(self.hidden)}: {exc}") from None
        return net.to(device).eval()

    def _check_weights(self) -> None:
        """ModelFileError unless the weights have the names and shapes of the declared network, compared before
        that network is built (hidden sizes [2**40] that did not fit the weights made torch allocate 20 TB first:
        a RuntimeError from the allocator, no file named)."""
        import torch

        with torch.device("meta"):   # shapes only, no memory
            want = {k: tuple(v.shape) for k, v in make_net(feature_count(self.feature_set), self.hidden)
                    .state_dict().items()}
        have = {k: tuple(np.shape(v)) for k, v in self.state_dict.items()}
        what = (f"{self.source}: the weights do not fit a {self.feature_set} network with hidden sizes "
                f"{list(self.hidden)}")
        missing = [k for k in want if k not in have]
        extra = [k for k in have if k not in want]
        if missing or extra:
            raise ModelFileError(f"{what}: {'missing ' + ', '.join(missing) if missing else ''}"
                                 f"{'; ' if missing and extra else ''}"
                                 f"{'unexpected ' + ', '.join(extra) if extra else ''}")
        for k, shape in want.items():
            if have[k] != shape:
                raise ModelFileError(f"{what}: weight {k} is {have[k]}, expected {shape}")

    def meta(self) -> dict[str, Any]:
        rows, cols = self.shape
        return {
            "format": FORMAT, "version": VERSION, "feature_set": self.feature_set, "hidden": list(self.hidden),
            "rows": rows, "cols": cols, "orientation": "portrait-bgr", "px_per_m": float(self.px_per_m),
            "px_per_mm": float(self.px_per_m) / 1000.0, "ball_radius_m": float(self.ball_radius_m),
            "stride": int(self.stride), "change_threshold": float(self.change_threshold),
            "depth_gain": float(self.depth_gain), "training": self.training, "validation": self.validation,
        }

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model file (atomically: a temporary file renamed into place)."""
        path = Path(path)
        arrays: dict[str, np.ndarray] = {"meta": np.array(json.dumps(self.meta(), sort_keys=True,
                                                                     default=_json_number))}
        for k, v in self.state_dict.items():
            arrays["w." + k] = np.asarray(v, dtype=np.float32)
        arrays["feat_mean"] = np.asarray(self.feat_mean, dtype=np.float32)
        arrays["feat_std"] = np.asarray(self.feat_std, dtype=np.float32)
        arrays["background"] = np.ascontiguousarray(self.background, dtype=np.uint8)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)   # numpy stamps every member 1980-01-01: the same arrays, the same bytes
        atomic_write(path, buf.getvalue())
        return path

    @classmethod
    def from_net(cls, net: Any, **kw: Any) -> "NormalModel":
        sd = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in net.state_dict().items()}
        return cls(state_dict=sd, **kw)


def _json_number(v: Any) -> Any:
    """A numpy number in the metadata (a training parameter, a metric) as JSON's; anything else is refused as
    json.dumps refuses it."""
    if isinstance(v, (np.integer, np.floating, np.bool_)):
        return v.item()
    raise TypeError(f"Object of type {type(v).__name__} is not JSON serializable")


def atomic_write(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file of its own in the same folder, renamed into place: a
    reader sees the old file or the new one, never a part. On any interruption (an error, Ctrl-C) the temporary
    file is removed and ``path`` is left as it was. (Before: a fixed ``<name>.tmp``, left behind by an interrupted
    write and shared by two calibrations writing the same file.) The file gets the permissions of a new file
    (mkstemp's are 0600)."""
    import tempfile

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _umask() -> int:
    """The process's umask, read without changing it (os.umask sets it, racing other threads creating files)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


def packaged_model_path(name: str) -> Path | None:
    """The file of a model shipped with teletouch (e.g. ``sim-digit-qvga``), or None."""
    p = DATA_DIR / f"{name}.model"
    return p if p.is_file() else None


def resolve_model(spec: str | os.PathLike[str]) -> Path:
    """A packaged model name (``sim-digit-qvga``) or a path -> an existing file, else ModelFileError
    (:func:`teletouch.paths.input_file`)."""
    def packaged(s: str) -> Path | None:
        return packaged_model_path(s) if os.sep not in s and not s.endswith(".model") else None

    shipped = sorted(f.stem for f in DATA_DIR.glob("*.model")) if DATA_DIR.is_dir() else []
    return input_file(spec, "model", ".model", "`teletouch calibrate depth`", packaged, shipped)


def _meta_number(name: str, meta: dict[str, Any], key: str, default: float | None = None, *,
                 integer: bool = False, low: float | None = None, above: bool = False,
                 high: int | None = None) -> Any:
    """meta[key] (``default`` when absent): a JSON number (an integer when ``integer``), finite, >= ``low``
    (> ``low`` when ``above``) and <= ``high``; else ModelFileError naming the file, the field and what was
    expected."""
    v = meta.get(key, default)
    ok = isinstance(v, int if integer else (int, float)) and not isinstance(v, bool)
    if ok and not integer:
        ok = math.isfinite(v)
    if ok and low is not None:
        ok = v > low if above else v >= low
    if ok and high is not None:
        ok = v <= high
    if not ok:
        what = "an integer" if integer else "a finite number"
        if low is not None and high is not None:
            what += f" from {low:g} to {high:g}"
        elif low is not None:
            what += f" {'>' if above else '>='} {low:g}"
        raise ModelFileError(f"{name}: meta field {key} is {v!r}, expected {what}")
    return int(v) if integer else float(v)


def _meta_dict(name: str, meta: dict[str, Any], key: str) -> dict[str, Any]:
    v = meta.get(key, {})
    if not isinstance(v, dict):
        raise ModelFileError(f"{name}: meta field {key} is {v!r}, expected a JSON object")
    return dict(v)


def max_stride(shape: tuple[int, int]) -> int:
    """The largest work-grid stride for images of ``shape`` (rows, cols): at least 8 cells across."""
    return max(1, min(shape) // 8)


_EXPECTED = "expected a .npz archive written by `teletouch calibrate depth`"
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")   # a zip archive (an .npz): with entries, empty
_NPY_MAGIC = b"\x93NUMPY"


def _check_archive(p: Path) -> None:
    """ModelFileError unless the file starts as a zip archive (an .npz) does. np.load reads any other file (JSON,
    text, a PNG) as pickled data and refuses it with a hint to load it unsafely: nothing here is pickled."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(6)
    except OSError as exc:
        raise ModelFileError(f"{p}: cannot read the model file: {exc.strerror or exc}") from None
    if head == _NPY_MAGIC:
        raise ModelFileError(f"{p}: a single NumPy array, not a teletouch depth model ({_EXPECTED})")
    if head[:4] not in _ZIP_MAGIC:
        raise ModelFileError(f"{p}: not a teletouch depth model ({_EXPECTED})")


def _why(exc: BaseException) -> str:
    """An error reading the archive, without numpy's advice to load pickled data unsafely (an entry holding
    Python objects: no model file written here has one)."""
    if "allow_pickle" in str(exc):
        return "an entry holds pickled Python objects, which a model file never does"
    return str(exc)


def _check_meta(name: str, entry: Any) -> dict[str, Any]:
    """The 'meta' entry as a dict of a model file of this format and version, else ModelFileError."""
    try:
        meta = json.loads(str(entry))
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{name}: the 'meta' entry is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelFileError(f"{name}: format is {meta.get('format') if isinstance(meta, dict) else meta!r}, "
                             f"expected {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise ModelFileError(f"{name}: model file version {meta.get('version')!r}, this teletouch reads version "
                             f"{VERSION}; recalibrate with `teletouch calibrate depth`")
    return meta


def check_model_file(spec: str | os.PathLike[str]) -> Path:
    """The model file of ``spec`` (a path or a packaged model's name) if it is a model file of this format and
    version, read from its header (the 'meta' entry only: no weights, no network), else ModelFileError naming the
    file and what was expected. What a graph's validation checks; :func:`load_model` checks the rest."""
    return _read_header(spec)[0]


def model_image_shape(spec: str | os.PathLike[str]) -> tuple[int, int]:
    """The (rows, cols) of the portrait frames the model file ``spec`` (a path or a packaged model's name) was made
    for, from its header (the 'meta' entry only: no weights, no network), else ModelFileError naming the file and
    the field. What a graph's validation compares with the frames of the sensor wired to a ``depth`` node."""
    p, meta = _read_header(spec)
    return (_meta_number(str(p), meta, "rows", None, integer=True, low=1),
            _meta_number(str(p), meta, "cols", None, integer=True, low=1))


#: headers read (:func:`_read_header`): (resolved path, device, inode, mtime ns, size, digest of the 'meta' entry's
#: bytes) -> the 'meta' entry. A graph's validation reads a depth model's header twice (the ``model`` validator, then
#: port_shapes for the frames' size)
_HEADERS: dict[tuple, dict[str, Any]] = {}
_HEADERS_KEPT = 32


def _read_header(spec: str | os.PathLike[str]) -> tuple[Path, dict[str, Any]]:
    """The model file of ``spec`` and its 'meta' entry (this format and version), read without the rest of the
    archive; else ModelFileError. Parsed once while the file is unchanged: the same path, inode, mtime and size, and
    the same bytes of its 'meta' entry (read each time: a file replaced by one of the same size with its mtime put
    back, as `cp -p` does, keeps the rest); a file that is not a model is read again each time (its error said
    again)."""
    p = resolve_model(spec)
    try:
        st = p.stat()
        raw: bytes | None = _meta_bytes(p)
    except (ModelFileError, zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError):
        raw = None   # (the read below says why)
    key = ((str(p.resolve()), st.st_dev, st.st_ino, st.st_mtime_ns, st.st_size, hashlib.sha256(raw).digest())
           if raw is not None else None)
    meta = _HEADERS.get(key) if key is not None else None
    if meta is None:
        meta = _read_meta(p, raw)
        if key is not None:
            if len(_HEADERS) >= _HEADERS_KEPT:
                _HEADERS.pop(next(iter(_HEADERS)), None)   # the oldest
            _HEADERS[key] = meta
    return p, dict(meta)


def _meta_bytes(p: Path) -> bytes:
    """The bytes of the 'meta' entry (meta.npy) of the zip archive ``p``; ModelFileError where it has none, zipfile's
    and the system's errors where it cannot be read."""
    with zipfile.ZipFile(p) as zf:
        if "meta.npy" not in zf.namelist():
            raise ModelFileError(f"{p}: no 'meta' entry; expected a {FORMAT} file written by `teletouch calibrate "
                                 f"depth`")
        return zf.read("meta.npy")


def _read_meta(p: Path, raw: bytes | None = None) -> dict[str, Any]:
    """The 'meta' entry of the model file ``p`` (this format and version), from ``raw`` (its bytes, already read) or
    read here; else ModelFileError."""
    _check_archive(p)
    try:
        entry = np.lib.format.read_array(io.BytesIO(_meta_bytes(p) if raw is None else raw), allow_pickle=False)
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError) as exc:
        raise ModelFileError(f"{p}: not a readable teletouch depth model ({_EXPECTED}): {_why(exc)}") from None
    return _check_meta(str(p), entry)


def load_model(path: str | os.PathLike[str], expect_shape: tuple[int, int] | None = None) -> NormalModel:
    """Read a model file; ModelFileError naming the file and what was expected on any problem."""
    p = resolve_model(path)
    name = str(p)
    _check_archive(p)
    try:
        with np.load(p, allow_pickle=False) as z:
            files = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError, KeyError) as exc:
        # zlib.error: a damaged compressed entry (not a subclass of any of the others)
        raise ModelFileError(f"{name}: not a readable teletouch depth model ({_EXPECTED}): {_why(exc)}") from None
    if "meta" not in files:
        raise ModelFileError(f"{name}: no 'meta' entry; expected a {FORMAT} file written by `teletouch calibrate "
                             f"depth`")
    meta = _check_meta(name, files["meta"])
    need = ["feature_set", "hidden", "rows", "cols", "px_per_m", "orientation"]
    missing = [k for k in need if k not in meta]
    if missing:
        raise ModelFileError(f"{name}: meta lacks {', '.join(missing)}")
    if meta["orientation"] != "portrait-bgr":
        raise ModelFileError(f"{name}: orientation {meta['orientation']!r}, expected 'portrait-bgr'")
    if not isinstance(meta["feature_set"], str) or meta["feature_set"] not in FEATURE_SETS:
        raise ModelFileError(f"{name}: feature set {meta['feature_set']!r}, expected one of {sorted(FEATURE_SETS)}")
    hidden = meta["hidden"]
    if (not isinstance(hidden, list) or not hidden
            or not all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in hidden)):
        raise ModelFileError(f"{name}: meta field hidden is {hidden!r}, expected a list of layer sizes (integers "
                             f">= 1)")
    for k in ("feat_mean", "feat_std", "background"):
        if k not in files:
            raise ModelFileError(f"{name}: the entry {k!r} is missing")
    rows = _meta_number(name, meta, "rows", integer=True, low=1)
    cols = _meta_number(name, meta, "cols", integer=True, low=1)
    bg = files["background"]
    if bg.dtype != np.uint8 or bg.shape != (rows, cols, 3):
        raise ModelFileError(f"{name}: background is {bg.dtype} {bg.shape}, expected uint8 {(rows, cols, 3)}")
    nf = feature_count(meta["feature_set"])
    for k in ("feat_mean", "feat_std"):
        a = files[k]
        if a.dtype.kind not in "fiu" or a.shape != (nf,):
            raise ModelFileError(f"{name}: input normalisation {k} is {a.dtype} {a.shape}, expected {nf} numbers")
        if not np.all(np.isfinite(a)) or (k == "feat_std" and not np.all(a > 0)):
            raise ModelFileError(f"{name}: input normalisation {k} holds "
                                 f"{'NaN or inf' if not np.all(np.isfinite(a)) else 'a std <= 0'}, expected finite "
                                 f"numbers{' > 0' if k == 'feat_std' else ''}")
    if expect_shape is not None and tuple(expect_shape) != (rows, cols):
        raise ModelFileError(f"{name}: the model is for {rows}x{cols} (rows x cols) images, expected "
                             f"{expect_shape[0]}x{expect_shape[1]}; calibrate a model at this resolution")
    sd = {k[2:]: v for k, v in files.items() if k.startswith("w.")}
    if not sd:
        raise ModelFileError(f"{name}: no network weights (entries 'w.*')")
    for k, v in sd.items():
        if v.dtype.kind not in "fiu":
            raise ModelFileError(f"{name}: weight {k} is {v.dtype}, expected float32 numbers")
        if not np.all(np.isfinite(v)):
            raise ModelFileError(f"{name}: weight {k} holds NaN or inf")
    model = NormalModel(feature_set=meta["feature_set"], hidden=tuple(hidden), state_dict=sd,
                        feat_mean=files["feat_mean"], feat_std=files["feat_std"], background=bg,
                        px_per_m=_meta_number(name, meta, "px_per_m", low=0, above=True),
                        ball_radius_m=_meta_number(name, meta, "ball_radius_m", 0.003, low=0, above=True),
                        stride=_meta_number(name, meta, "stride", 1, integer=True, low=1,
                                            high=max_stride((rows, cols))),
                        change_threshold=_meta_number(name, meta, "change_threshold", 16.0, low=0),
                        depth_gain=_meta_number(name, meta, "depth_gain", 1.0, low=0, above=True),
                        training=_meta_dict(name, meta, "training"),
                        validation=_meta_dict(name, meta, "validation"), source=name)
    model.net()  # the weights must fit the declared architecture
    return model
