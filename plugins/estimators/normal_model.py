"""The per-pixel normal network and its model file.

Network: an MLP from per-pixel features to the surface normal (nx, ny, nz) of the gel, as in the paper (R, G, B,
X, Y -> normal), optionally with the pixel's difference from the background frame as three more inputs (it helps
most; see docs/depth.md). Layers: Linear(in, 32) -> ReLU -> Dropout(0.05) -> Linear(32, 32) -> ReLU ->
Dropout(0.05) -> Linear(32, 32) -> ReLU -> Linear(32, 3).

Features (same function in training and inference, so coordinates are normalised identically):
  rgb:  the pixel's B, G, R / 255;  diff: (pixel - background) / 255;  xy: column and row mapped to [-1, 1] by the
  image size (x = (col + 0.5) / cols * 2 - 1). Each feature is then standardised by a mean and std fitted on the
  training pixels and stored in the model file.

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

import io
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from teletouch.errors import ModelFileError

__all__ = [
    "FORMAT", "VERSION", "FEATURE_SETS", "make_net", "features", "feature_count", "NormalModel", "load_model",
    "packaged_model_path", "resolve_model",
]

FORMAT = "teletouch-depth-model"
VERSION = 1
FEATURE_SETS = {"rgbxy": 5, "diffxy": 5, "rgbxy+diff": 8, "diff": 3}
DATA_DIR = Path(__file__).resolve().parent / "data"


def feature_count(feature_set: str) -> int:
    try:
        return FEATURE_SETS[feature_set]
    except KeyError:
        raise ValueError(f"unknown feature set {feature_set!r}; expected one of {sorted(FEATURE_SETS)}") from None


def make_net(n_in: int, hidden: tuple[int, ...] = (32, 32, 32), dropout: float = 0.05) -> Any:
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


def features(feature_set: str, pix: np.ndarray, diff: np.ndarray, rows: np.ndarray, cols: np.ndarray,
             shape: tuple[int, int]) -> np.ndarray:
    """Raw (unstandardised) features, float32 (N, F).

    pix: (N, 3) BGR 0..255 of the frame; diff: (N, 3) frame - background (0..255 scale); rows/cols: pixel indices.
    """
    x, y = xy_features(rows, cols, shape)
    parts: list[np.ndarray] = []
    if feature_set in ("rgbxy", "rgbxy+diff"):
        parts.append(np.asarray(pix, dtype=np.float32) * (1.0 / 255.0))
    if feature_set in ("diffxy", "rgbxy+diff", "diff"):
        parts.append(np.asarray(diff, dtype=np.float32) * (1.0 / 255.0))
    if feature_set not in FEATURE_SETS:
        feature_count(feature_set)
    if feature_set != "diff":
        parts.append(x[:, None])
        parts.append(y[:, None])
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

        net = make_net(feature_count(self.feature_set), self.hidden)
        sd = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in self.state_dict.items()}
        try:
            net.load_state_dict(sd)
        except RuntimeError as exc:
            raise ModelFileError(f"{self.source}: the weights do not fit a {self.feature_set} network with hidden "
                                 f"sizes {list(self.hidden)}: {exc}") from None
        return net.to(device).eval()

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
        arrays: dict[str, np.ndarray] = {"meta": np.array(json.dumps(self.meta(), sort_keys=True))}
        for k, v in self.state_dict.items():
            arrays["w." + k] = np.asarray(v, dtype=np.float32)
        arrays["feat_mean"] = np.asarray(self.feat_mean, dtype=np.float32)
        arrays["feat_std"] = np.asarray(self.feat_std, dtype=np.float32)
        arrays["background"] = np.ascontiguousarray(self.background, dtype=np.uint8)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(buf.getvalue())
        os.replace(tmp, path)
        return path

    @classmethod
    def from_net(cls, net: Any, **kw: Any) -> "NormalModel":
        sd = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in net.state_dict().items()}
        return cls(state_dict=sd, **kw)


def packaged_model_path(name: str) -> Path | None:
    """The file of a model shipped with teletouch (e.g. ``sim-digit-qvga``), or None."""
    p = DATA_DIR / f"{name}.model"
    return p if p.is_file() else None


def resolve_model(spec: str | os.PathLike[str]) -> Path:
    """A packaged model name (``sim-digit-qvga``) or a path -> an existing file, else ModelFileError."""
    s = str(spec)
    p = Path(s).expanduser()
    if p.is_file():
        return p
    if os.sep not in s and not s.endswith(".model"):
        q = packaged_model_path(s)
        if q is not None:
            return q
    shipped = sorted(f.stem for f in DATA_DIR.glob("*.model")) if DATA_DIR.is_dir() else []
    raise ModelFileError(f"{s}: no such model file (and no packaged model of that name; packaged: "
                         f"{', '.join(shipped) or 'none'})")


def load_model(path: str | os.PathLike[str], expect_shape: tuple[int, int] | None = None) -> NormalModel:
    """Read a model file; ModelFileError naming the file and what was expected on any problem."""
    p = resolve_model(path)
    name = str(p)
    try:
        with np.load(p, allow_pickle=False) as z:
            files = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError) as exc:
        raise ModelFileError(f"{name}: not a readable teletouch depth model (expected a .npz archive written by "
                             f"`teletouch calibrate depth`): {exc}") from None
    if "meta" not in files:
        raise ModelFileError(f"{name}: no 'meta' entry; expected a {FORMAT} file written by `teletouch calibrate "
                             f"depth`")
    try:
        meta = json.loads(str(files["meta"]))
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{name}: the 'meta' entry is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelFileError(f"{name}: format is {meta.get('format') if isinstance(meta, dict) else meta!r}, "
                             f"expected {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise ModelFileError(f"{name}: model file version {meta.get('version')!r}, this teletouch reads version "
                             f"{VERSION}; recalibrate with `teletouch calibrate depth`")
    need = ["feature_set", "hidden", "rows", "cols", "px_per_m", "orientation"]
    missing = [k for k in need if k not in meta]
    if missing:
        raise ModelFileError(f"{name}: meta lacks {', '.join(missing)}")
    if meta["orientation"] != "portrait-bgr":
        raise ModelFileError(f"{name}: orientation {meta['orientation']!r}, expected 'portrait-bgr'")
    if meta["feature_set"] not in FEATURE_SETS:
        raise ModelFileError(f"{name}: feature set {meta['feature_set']!r}, expected one of {sorted(FEATURE_SETS)}")
    for k in ("feat_mean", "feat_std", "background"):
        if k not in files:
            raise ModelFileError(f"{name}: the entry {k!r} is missing")
    rows, cols = int(meta["rows"]), int(meta["cols"])
    bg = files["background"]
    if bg.dtype != np.uint8 or bg.shape != (rows, cols, 3):
        raise ModelFileError(f"{name}: background is {bg.dtype} {bg.shape}, expected uint8 {(rows, cols, 3)}")
    nf = feature_count(meta["feature_set"])
    if files["feat_mean"].shape != (nf,) or files["feat_std"].shape != (nf,) or not np.all(files["feat_std"] > 0):
        raise ModelFileError(f"{name}: input normalisation has shape {files['feat_mean'].shape}, expected ({nf},) "
                             f"with positive std")
    if expect_shape is not None and tuple(expect_shape) != (rows, cols):
        raise ModelFileError(f"{name}: the model is for {rows}x{cols} (rows x cols) images, expected "
                             f"{expect_shape[0]}x{expect_shape[1]}; calibrate a model at this resolution")
    sd = {k[2:]: v for k, v in files.items() if k.startswith("w.")}
    if not sd:
        raise ModelFileError(f"{name}: no network weights (entries 'w.*')")
    for k, v in sd.items():
        if not np.all(np.isfinite(v)):
            raise ModelFileError(f"{name}: weight {k} holds NaN or inf")
    model = NormalModel(feature_set=meta["feature_set"], hidden=tuple(int(h) for h in meta["hidden"]),
                        state_dict=sd, feat_mean=files["feat_mean"], feat_std=files["feat_std"], background=bg,
                        px_per_m=float(meta["px_per_m"]), ball_radius_m=float(meta.get("ball_radius_m", 0.003)),
                        stride=int(meta.get("stride", 1)),
                        change_threshold=float(meta.get("change_threshold", 16.0)),
                        depth_gain=float(meta.get("depth_gain", 1.0)), training=dict(meta.get("training", {})),
                        validation=dict(meta.get("validation", {})), source=name)
    model.net()  # the weights must fit the declared architecture
    return model
