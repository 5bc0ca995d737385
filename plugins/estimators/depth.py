"""`depth`: DIGIT frame -> depth map, max depth, contact mask, area and centroid (the paper's method, made fast).

A per-pixel MLP (calibrated per sensor on ball presses, see ``teletouch calibrate depth``) turns colour into the gel's
surface normal; normals become depth gradients; a DST Poisson solve turns them into depth (m, positive into the
gel). The network only runs where the frame differs from the background, which is also the zero reference: an
untouched gel has no gradient and hence no depth. Details: docs/depth.md; the computation: depth_pipeline.py.

CLI (added by this plugin):
  teletouch calibrate depth --images DIR --ball-diameter 6mm --px-per-mm 17.15 [--labels CSV] -o sensor.model
  teletouch estimate --model sensor.model IMAGE... [--background F|DIR ...] [--json] [--save-depth DIR]
                     [--force-calibration force.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator

from teletouch import Component, ComponentFault, Kind, ModelFileError, Params, Port, Sample, hookimpl
from teletouch.argtypes import bare_metres_hint, int_at_least, number
from teletouch.paths import looked_at, output_problem
from teletouch.reproducible import source_date_epoch
from teletouch.units import Meters, parse_quantity, plausible_depth

from .depth_pipeline import DEVICES, device_form_problem, device_problem
from .normal_model import DEFAULT_FEATURES, DEFAULT_HIDDEN, FEATURE_SETS, max_stride

__all__ = ["DepthEstimator"]

#: deepest plausible contact_depth (m): a DIGIT's gel is 4-5 mm thick (as poly-force's depth_limit); deeper, no
#: pixel is ever in contact ("0.03", meant in mm, read every press as no contact)
MAX_CONTACT_DEPTH = 5e-3

class DepthEstimator(Component):
    """DIGIT image -> depth map (m), max depth, contact mask/area/centroid (normal MLP + DST Poisson)."""

    name = "depth"
    kind = Kind.ESTIMATOR
    default_rate = 60.0
    inputs = {"image": Port("uint8", (None, None, 3), "", "BGR portrait frame (rows x cols x 3)", required=True)}
    outputs = {
        "depth": Port("float32", (None, None), "m", "depth map, positive where the gel is pressed in"),
        "max_depth": Port("float64", (), "m", "largest depth"),
        "contact_mask": Port("bool", (None, None), "", "pixels deeper than contact_depth"),
        "contact_area": Port("float64", (), "m^2", "area of the contact mask"),
        "centroid": Port("float64", (2,), "m", "depth-weighted contact centre from the image centre (x along "
                                             "columns, y along rows); NaN without contact"),
    }

    class Params(Params):
        model: str = Field("sim-digit-qvga", description="model file (.model from `teletouch calibrate depth`) "
                           "or the name of a packaged model (sim-digit-qvga)")
        device: str = Field("cpu", description=f"torch device: {DEVICES}")
        mode: Literal["auto", "sparse", "dense"] = Field(
            "auto", description="sparse: network only on changed pixels (CPU default); dense: every pixel, "
            "masked (GPU default)")
        background: str | list[str] | None = Field(
            None, description="no-contact frames replacing the model's background, e.g. recorded at start-up: an "
            "image file, a folder of them or a list of files and folders (several: their per-pixel median, which "
            "takes out a single frame's noise; at most 100 frames)")
        contact_depth: Meters = Field(3e-5, gt=0, description="depth above which a pixel is in contact",
                                      json_schema_extra={"unit": "m"})
        contact_fraction: float = Field(0.5, ge=0.0, lt=1.0, description="in contact where depth > this fraction of "
                                        "the max depth too (Hertz: the contact edge is at half the indentation)")
        change_threshold: float | None = Field(None, gt=0, description="colour change (0-255 levels summed over "
                                               "B, G, R) that counts as touched; default: the model's")
        adapt_background: float = Field(0.0, ge=0.0, le=0.5, description="blend weight of each untouched frame "
                                        "(no cell above the change threshold) into the background (0: off), follows "
                                        "slow illumination drift within adapt_limit")
        adapt_limit: float | None = Field(None, gt=0, le=255, description="the adapted background stays within "
                                          "this many levels per channel of the configured one, apart from a global "
                                          "offset (bounded by max_global_change): what a contact absorbed into it (a "
                                          "slow press, a touch below the threshold) can take off a reading at most; "
                                          "default: change_threshold / 3")
        max_global_change: float = Field(24.0, gt=0, le=255, description="a frame whose global colour change from "
                                         "the background (per-channel median, 0-255 levels) exceeds this is not "
                                         "a plausible DIGIT frame (LEDs off or changing, saturated, exposure "
                                         "changed): its outputs are NaN, it is never blended into the background")
        max_background_mismatch: float = Field(6.0, ge=0, le=255, description="the closest of the first frames "
                                               "(10; a contact in some of them is no mismatch) must match the "
                                               "background: the median over the image of |frame - background| "
                                               "in block means (8 x 8 px at QVGA: pixel noise averages out) after "
                                               "the global offset, mean over B, G, R, at most this many levels (a "
                                               "sensor's own frames: 1-2, sim-digit at its maximum noise 32: 3-4; "
                                               "another DIGIT unit's: 9-20), else the node faults: another sensor's "
                                               "model or background (0: no check)")
        fault_after_bad: int = Field(30, ge=0, description="fault the node after this many implausible frames in "
                                     "a row (0: never; at 60 Hz, 30 is half a second)")
        fault_after_repeats: int = Field(0, ge=0, description="fault the node after this many bit-identical "
                                         "frames in a row with new stamps (a frozen camera: a real camera's noise "
                                         "never repeats; 0: never, as a simulated sensor without noise repeats)")
        workers: int = Field(1, ge=1, le=64, description="scipy.fft worker threads for the CPU solve")
        baseline: Literal["none", "plane"] = Field(
            "none", description="zero reference: none (depth outside the change region is 0) or plane (also "
            "subtract the plane the solved depth has just outside it: less false depth beside a contact, reads "
            "shallower; see docs/depth.md)")
        net_rim: int = Field(1, ge=0, le=2, description="extra rings of cells around the change region that the "
                             "network also runs on (1, the default, follows the full-frame reference within 2% and "
                             "leaves less far false depth than 0; the model's depth gain is fitted with 1; "
                             "docs/depth.md)")
        threads: int | None = Field(1, ge=1, le=64, description="torch intra-op threads on CPU (process-wide; 1 is "
                                    "fastest for one frame on a busy machine; None: leave torch's setting)")
        reuse_unchanged: bool = Field(True, description="a frame identical to the previous one (bit for bit: a "
                                      "simulated sensor at rest without noise; a camera's noise never repeats) "
                                      "gives the previous result again, stamped with the new frame's time, "
                                      "without recomputing it")
        warm: bool = Field(True, description="under the wall clock, run the last new frame through the pipeline "
                           "again 1 ms before each step and throw the result away, so that the step finds the "
                           "pipeline in the CPU's caches (on a shared machine a step after the 16 ms pause took up "
                           "to twice its time; docs/depth.md); costs that frame's CPU time once more per step")

        @field_validator("model")
        @classmethod
        def _model_file(cls, v: str) -> str:
            """The model file's header when the graph is validated (a missing file, a JSON or text file, another
            format or version): before, `teletouch validate` said OK and the run failed at start-up."""
            from .normal_model import check_model_file

            try:
                check_model_file(v)
            except ModelFileError as exc:
                raise ValueError(str(exc)) from None
            return v

        @field_validator("device")
        @classmethod
        def _device(cls, v: str) -> str:
            """The device's form when the graph is validated (whether it is there is asked at start-up)."""
            problem = device_form_problem(v)
            if problem:
                raise ValueError(problem)
            return v

        @field_validator("contact_depth")
        @classmethod
        def _contact_depth(cls, v: float, info: Any) -> float:
            return plausible_depth(info.field_name, v, MAX_CONTACT_DEPTH)   # deeper, no pixel is ever in contact

    @classmethod
    def port_shapes(cls, params: Any) -> dict[str, tuple]:
        """The frames' size is the model's (from its header): a sensor wired to ``image`` whose parameters fix
        another size is refused when the graph is validated (the run faulted at its first frame); the depth map
        and the contact mask have it too."""
        from .normal_model import model_image_shape

        rows, cols = model_image_shape(params.model)
        why = f"model {params.model!r}, made for {rows}x{cols} frames"
        how = "use a depth model calibrated on this sensor's frames (`teletouch calibrate depth`)"
        return {"image": ((rows, cols, 3), why, how), "depth": ((rows, cols), why, how),
                "contact_mask": ((rows, cols), why, how)}

    @classmethod
    def port_sources(cls, params: Any) -> dict[str, tuple]:
        """The depths (``max_depth`` and the depth map) are on the model's scale: tied to its name, as `teletouch
        calibrate force` records it in a calibration (``sensor_model_id``: the file's name) and poly-force compares
        it (folders and '.model' left out: poly_force._model_name), so that a force calibration made for another
        depth model is refused when the graph is validated. The name only: no file is read."""
        from .poly_force import _model_name

        identity = _model_name(params.model)
        why = f"model {params.model!r}"
        how = "set model to the depth model that the other end was made for"
        return {"max_depth": (identity, why, how), "depth": (identity, why, how)}

    def configure(self) -> None:
        from .depth_pipeline import DepthPipeline
        from .normal_model import load_model

        p = self.params
        try:
            model = load_model(p.model)
        except ModelFileError as exc:
            raise ModelFileError(f"model: {exc}") from None   # the error names the parameter
        bg = None
        if p.background:
            try:
                given = [p.background] if isinstance(p.background, str) else p.background
                bg, what = _background_for_model(given, model)
            except (FileNotFoundError, ValueError) as exc:
                raise ModelFileError(f"background: {exc}") from None
            self.ctx.log(f"background: {what}")
        device = _check_device(p.device)
        self.pipe = DepthPipeline(model, device=device, mode=p.mode, change_threshold=p.change_threshold,
                                  contact_depth=p.contact_depth, contact_fraction=p.contact_fraction,
                                  workers=p.workers, background=bg, threads=p.threads, baseline=p.baseline,
                                  net_rim=p.net_rim)
        self.pipe.warm_up()
        self.model = model
        self._ref_bg = (bg if bg is not None else model.background).astype(np.float32)   # the configured one
        self._adapt_limit = (p.adapt_limit if p.adapt_limit is not None else self.pipe.change_threshold / 3.0)
        self._last: dict[str, float] = {}
        self._step_s = math.nan
        self.reused = 0
        self.bad_frames = 0      # implausible frames (outputs NaN), in all
        self.last_problem = ""   # why the last of them was
        self.activate()

    def activate(self) -> None:
        """Start as configured: the configured background (the adaptation starts over), no remembered frame."""
        self._bg = self._ref_bg.copy()
        if getattr(self.pipe, "set_background", None) is not None:
            self.pipe.set_background(self._bg)
        self._reuse: Any = None   # the result of the last frame (self._seen's) kept for reuse: None when not kept
        self._bad_run = 0        # implausible frames in a row
        self._repeat_run = 0     # bit-identical frames with new stamps in a row
        # (the last frame, its stamp): the repeats are counted against it whether or not its result is kept for reuse
        # (with adapt_background on untouched gel, or reuse_unchanged off, they were never counted: a frozen camera
        # went on as "no contact", freshly stamped)
        self._seen: tuple[np.ndarray, float] | None = None
        self._mismatch: list[float] = []   # background_mismatch() of the first MATCH_FRAMES plausible frames
        # the last input sample handled and its outputs: the port's sample read again is no new frame
        self._handled: tuple[Sample, dict[str, Any]] | None = None
        self._rehearse: np.ndarray | None = None   # the last frame computed anew: what warm() runs again

    @classmethod
    def wants_warm_up(cls, params: Any) -> bool:
        """``warm: false``: no warm-up (an isolated node's process is not even asked, ProcessProxy.warm)."""
        return params.warm

    def warm(self) -> None:
        """Run the last frame computed anew through the pipeline again, the result thrown away (``warm``,
        DepthPipeline.rehearse): the runtime calls this 1 ms before each step under the wall clock."""
        if self._rehearse is not None and self.params.warm:
            self.pipe.rehearse(self._rehearse)

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        s = inputs["image"]
        if s is None:
            return None
        if self._handled is not None and s is self._handled[0]:
            # the sample handled last, read again (this node steps faster than the camera delivers): its outputs
            # again, with its stamp; not another frame, so not counted (bad, repeated) nor blended in again
            return dict(self._handled[1])
        out = self._frame(s)
        self._handled = (s, out)   # not when it raised: a sample that faulted the node faults it again
        return dict(out)

    def _frame(self, s: Sample) -> dict[str, Any]:
        frame = s.value
        try:
            self.pipe.check_frame(frame)
        except ValueError as exc:
            raise ComponentFault(str(exc), self.id) from None
        t0 = time.perf_counter()
        p = self.params
        seen = self._seen
        same = seen is not None and _same_frame(seen[0], frame)
        if same and s.stamp != seen[1]:
            self._repeat_run += 1
            self._seen = (seen[0], s.stamp)
            if p.fault_after_repeats and self._repeat_run >= p.fault_after_repeats:
                raise ComponentFault(f"{self._repeat_run} bit-identical frames in a row with new stamps: the "
                                     f"camera is frozen (fault_after_repeats {p.fault_after_repeats})", self.id)
        elif not same:
            self._repeat_run = 0
            self._seen = (frame.copy(), s.stamp)
        if same and self._reuse is not None:
            res = self._reuse
            self.reused += 1
        else:
            try:
                res = self.pipe(frame)
            except ValueError as exc:   # a depth that is not finite: no output is better than a wrong one
                self._reuse = None
                raise ComponentFault(f"the depth of this frame could not be computed: {exc}", self.id) from None
            problem = self._frame_problem(res) or colour_problem(frame)
            if problem:
                self._reuse = None
                return self._bad(problem, s.stamp, t0)
            self._rehearse = frame
            if p.max_background_mismatch and len(self._mismatch) < MATCH_FRAMES:
                self._check_match(frame)
            if p.adapt_background > 0 and not res.changed and res.contact_area == 0.0:
                self._adapt(frame)
                self._reuse = None   # the background moved: the same frame would now read differently
            elif p.reuse_unchanged:
                self._reuse = res   # (its frame is self._seen's)
        self._bad_run = 0
        self._step_s = time.perf_counter() - t0
        self._last = {"max_depth_m": float(res.max_depth), "contact_area_m2": float(res.contact_area),
                      "step_s": self._step_s, "bad_frames": self.bad_frames, "repeated_frames": self._repeat_run}
        st = s.stamp
        return {"depth": Sample(res.depth, st), "max_depth": Sample(float(res.max_depth), st),
                "contact_mask": Sample(res.contact_mask, st), "contact_area": Sample(float(res.contact_area), st),
                "centroid": Sample(res.centroid.astype(np.float64), st)}

    def _frame_problem(self, res: Any) -> str:
        return frame_problem(res, self.params.max_global_change)

    def _check_match(self, frame: np.ndarray) -> None:
        """The first MATCH_FRAMES plausible frames against the background: a model (or background) of another
        sensor reads another unit's pattern of colours as contacts (0.1-2 mm and a force from nothing), and the
        packaged model is the simulated sensor's. The level is the least of the frames' (:func:`match_level`): a
        contact among them, however deep, cannot make a sensor's own frames read as another's."""
        self._mismatch.append(background_mismatch(frame, self._ref_bg))
        if len(self._mismatch) == MATCH_FRAMES:
            level = match_level(self._mismatch)
            self.background_mismatch = level
            limit = self.params.max_background_mismatch
            if level > limit:
                raise ComponentFault(
                    f"the camera's frames do not match the depth model's background: they differ by {level:.1f} "
                    f"levels (the closest of the first {MATCH_FRAMES}; median over the image in block means, after "
                    f"the global offset; a sensor's own frames: 1-2, another DIGIT unit's: 9-20; "
                    f"max_background_mismatch {limit:g}): model "
                    f"{self.params.model!r} was made for another sensor (the packaged one is the simulated sensor's). "
                    f"Calibrate this sensor "
                    f"(`teletouch calibrate depth`), or give background: a no-contact frame of it", self.id)

    def _bad(self, problem: str, stamp: float, t0: float) -> dict[str, Any]:
        """An implausible frame: NaN outputs (poly-force reads them as invalid input: 0 N), a fault after
        ``fault_after_bad`` of them in a row."""
        self.bad_frames += 1
        self._bad_run += 1
        self.last_problem = problem
        n = self.params.fault_after_bad
        if n and self._bad_run >= n:
            raise ComponentFault(f"{self._bad_run} implausible frames in a row (fault_after_bad {n}); the last: "
                                 f"{problem}", self.id)
        self._step_s = time.perf_counter() - t0
        self._last = {"max_depth_m": math.nan, "contact_area_m2": math.nan, "step_s": self._step_s,
                      "bad_frames": self.bad_frames, "repeated_frames": 0}
        rows, cols = self.model.shape
        nan = math.nan
        return {"depth": Sample(np.full((rows, cols), nan, np.float32), stamp), "max_depth": Sample(nan, stamp),
                "contact_mask": Sample(np.zeros((rows, cols), bool), stamp), "contact_area": Sample(nan, stamp),
                "centroid": Sample(np.array([nan, nan]), stamp)}

    def _adapt(self, frame: np.ndarray) -> None:
        """Blend an untouched frame into the background. The adapted background keeps within ``adapt_limit``
        levels per channel of the configured one, apart from a global offset per channel (within
        ``max_global_change``), so that a contact absorbed into it (a slow press, a light touch below the change
        threshold) can take at most a sub-threshold change off a later reading, and a touch's imprint left in it
        after release stays below the threshold (and is blended out again)."""
        from .depth_pipeline import channel_offset

        bg = self._bg
        bg += self.params.adapt_background * (frame.astype(np.float32) - bg)
        dev = bg - self._ref_bg
        g = np.clip(channel_offset(dev), -self.params.max_global_change, self.params.max_global_change)
        lim = self._adapt_limit
        np.clip(dev - g, -lim, lim, out=dev)
        np.add(dev, g, out=dev)
        np.add(self._ref_bg, dev, out=bg)
        self.pipe.set_background(bg)

    def status(self) -> dict[str, Any]:
        return {**self._last, "background_mismatch": getattr(self, "background_mismatch", math.nan)}


#: how many plausible frames at start-up are compared with the background (max_background_mismatch)
MATCH_FRAMES = 10


def match_level(levels: list[float]) -> float:
    """The node's background mismatch from its first frames' :func:`background_mismatch`: the least of them. A
    contact changes a frame's colours over much of the image (a 5 mm probe 1.7 mm deep in sim-digit: 10 levels, all
    of the frame), so the median of 10 frames of a fast squeeze read as another sensor's; another unit's colour
    pattern is in every frame (9-20 levels each), while a sensor's own frames need only one untouched or lightly
    touched frame among them (1-2 levels)."""
    return float(min(levels))


def background_mismatch(frame: np.ndarray, background: np.ndarray) -> float:
    """How far a frame's colours are from the background's apart from a global offset, in levels: the frame minus
    the background in blocks of 1/30 of the shorter side (8 x 8 px at QVGA, 16 x 16 at VGA), block means, minus
    the per-channel median (the offset); then the median over the blocks of |that|, mean over B, G, R. A contact
    covers far less than half the image, so the median reads the gel around it. Block means, because zero-mean
    pixel noise of std s adds ~0.8 s to a per-pixel median (sim-digit with ``noise: 8`` read 6.3 levels, like
    another unit) and s / 8 here; another unit's colour pattern is smooth and stays. Measured on ../shared/data:
    1.1 levels for the QVGA unit's own presses, 1.6-1.9 for the VGA ones, 9.1-19.7 for another DIGIT unit's
    frames; sim-digit 0.2 (default noise) to 3.5 (``noise: 32``, its maximum)."""
    h, w = frame.shape[:2]
    k = max(1, min(h, w) // 30)
    h, w = h // k * k, w // k * k
    import cv2

    d = np.subtract(frame[:h, :w], np.asarray(background, np.float32)[:h, :w], dtype=np.float32)
    d = cv2.resize(d, (w // k, h // k), interpolation=cv2.INTER_AREA)   # exact block means (k divides h and w)
    d -= np.median(d.reshape(-1, d.shape[-1]), axis=0)
    return float(np.median(np.abs(d).mean(axis=-1)))


def frame_problem(res: Any, max_global_change: float) -> str:
    """Why a frame is not a plausible DIGIT frame ('' if it is): its global colour change from the background
    (``res.offset``, levels per channel). A frame with the LEDs off, saturated or mid-change reads as a deep, wide
    contact otherwise."""
    off = getattr(res, "offset", None)
    if off is None:
        return ""
    big = float(np.max(np.abs(off)))
    if not big <= max_global_change:   # also NaN
        return (f"the frame's global colour change from the background is {big:.0f} levels (B, G, R "
                f"{', '.join(f'{v:+.0f}' for v in off)}; max_global_change {max_global_change:g}): "
                f"LEDs off or changing, saturated, or the exposure changed")
    return ""


def colour_problem(frame: np.ndarray) -> str:
    """Why a frame of plausible brightness is no camera frame ('' if it is): a grayscale image (three equal channels:
    ``depth_calibration.is_grayscale``, ~8 us for a colour QVGA frame). The node and `estimate` ask it after the
    global change (:func:`frame_problem`), which names a black frame (LEDs off; its channels are equal too) as such.
    Unchecked, a grayscale copy of a real press read as another sensor's in `estimate` and as a contact in the node
    (3.2 mm on the packaged model)."""
    from .depth_calibration import is_grayscale

    if is_grayscale(frame):
        return ("a grayscale image (its three colour channels are equal); expected a colour BGR frame of the DIGIT "
                "as its camera delivers it (the depth model reads the colours)")
    return ""


def _same_frame(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit-identical frames; a sparse sample of the bytes first, so a new camera frame is told apart in ~2 us
    (the full comparison of a QVGA frame is ~20 us, against ~1-5 ms for the estimate it saves)."""
    if a.shape != b.shape:
        return False
    fa, fb = a.reshape(-1), b.reshape(-1)
    return bool(np.array_equal(fa[::4099], fb[::4099]) and np.array_equal(fa, fb))


def _check_device(device: str) -> str:
    """``device`` if the pipeline can run on it here, else a ComponentFault naming the parameter."""
    problem = device_problem(device, "device")
    if problem:
        raise ComponentFault(problem)
    return device


def _read_image(path: str | Path) -> np.ndarray:
    """The image at ``path`` (uint8 BGR), else FileNotFoundError naming it once: no such file, a folder, not a
    readable image. Checked before OpenCV reads it, which warns on stderr about a path it cannot open."""
    img, why = _try_read_image(path)
    if img is None:
        raise FileNotFoundError(f"{path}: {why}")
    return img


def _try_read_image(path: str | Path) -> tuple[np.ndarray | None, str]:
    """(the image, '') or (None, why it cannot be read, without the path)."""
    import cv2

    p = Path(path)
    if p.is_dir():
        return None, "a folder, expected an image file"
    if not p.is_file():
        return None, "no such file" if not p.exists() else "not a regular file, expected an image file"
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        return None, "not a readable image file (expected PNG or JPEG)"
    return img, ""


def _check_output(path: str | Path, what: str, folder: bool = False) -> None:
    """Refuse an output path that cannot be written with a ValueError naming the option (before any long work):
    also one whose folder does not exist (a file's folder; a folder's parent), which writing it made silently."""
    problem = output_problem(path, folder, make_folders=False)
    if problem:
        raise ValueError(f"{what} {path}: {problem}")


# ------------------------------------------------------------------------------------------------------------ CLI

def _px_per_m(text: str) -> float:
    """'17.15' (px per mm) or '17.15px/mm' or '17150px/m' -> px per m."""
    t = text.strip()
    try:
        return float(t) * 1e3
    except ValueError:
        pass
    try:
        return parse_quantity(t, "px/m")
    except ValueError:
        raise ValueError(f"--px-per-mm {text!r}: expected pixels per millimetre, e.g. 17.15, 17.15px/mm or "
                         f"17150px/m") from None


#: argparse types of the levels options (0-255 per channel)
_levels_or_zero = number(float, "a number of levels in [0, 255] (0: no check)", lo=0, hi=255)
_positive_levels = number(float, "a number of levels in (0, 255]", lo=0, lo_open=True, hi=255)


def _length(option: str, text: str) -> float:
    """The length option ``option``'s ``text`` in m (a bare number is metres), a ValueError naming the option."""
    try:
        return parse_quantity(text, "m")
    except ValueError as exc:
        raise ValueError(f"{option}: {exc}") from None


def _ball_radius(args: argparse.Namespace) -> float:
    """The ball radius (m) from --ball-diameter or --ball-radius (both only when they agree)."""
    if args.ball_diameter is None and args.ball_radius is None:
        raise ValueError("give the ball size: --ball-diameter 6mm (or --ball-radius 3mm)")
    from_d = _length("--ball-diameter", args.ball_diameter) / 2.0 if args.ball_diameter is not None else None
    from_r = _length("--ball-radius", args.ball_radius) if args.ball_radius is not None else None
    if from_d is not None and from_r is not None and not math.isclose(from_d, from_r, rel_tol=1e-6):
        raise ValueError(f"--ball-diameter {args.ball_diameter} and --ball-radius {args.ball_radius} disagree (a "
                         f"radius of {from_d * 1e3:g} mm against {from_r * 1e3:g} mm); give one of them")
    radius = from_r if from_r is not None else from_d
    assert radius is not None
    if not 0 < radius < 0.05:
        # what was typed, as read: "ball radius 3000 mm" alone did not say it came from --ball-diameter 6
        opt, given, read = (("--ball-radius", args.ball_radius, radius) if from_r is not None
                            else ("--ball-diameter", args.ball_diameter, 2.0 * radius))
        raise ValueError(f"{opt} {given} (read as {read:g} m): ball radius {radius * 1e3:g} mm is implausible "
                         f"(expected e.g. {opt} {'3mm' if from_r is not None else '6mm'}){bare_metres_hint(given)}")
    return radius


#: the largest caliper gap taken (m): both tips must press into the gel, a DIGIT's about 15-20 x 20-25 mm (as the
#: ball radius's limit); a bare 5 (meant 5 mm) was read as 5 m and gave a scale of 0.012 px/mm
MAX_CALIPER_GAP = 0.05


def _caliper_gap(text: str) -> float:
    """--caliper-gap in m: a distance between the tips that fits on a gel, else a ValueError naming the option, its
    value as read and (a bare number) the millimetres it likely meant."""
    gap = _length("--caliper-gap", text)
    if not 0 < gap < MAX_CALIPER_GAP:
        raise ValueError(f"--caliper-gap {text} (read as {gap:g} m): expected the distance between the caliper's "
                         f"tips on the gel, above 0 and below {MAX_CALIPER_GAP * 1e3:g} mm (e.g. --caliper-gap 5mm)"
                         f"{bare_metres_hint(text)}")
    return gap


def _check_scale(px_per_m: float, radius: float, shape: tuple[int, ...], source: str) -> None:
    """The image scale must be finite and > 0, and make the ball 3 px (below that no contact can be labelled) to the
    image's shorter side in radius."""
    if not (math.isfinite(px_per_m) and px_per_m > 0):
        raise ValueError(f"{source}: a scale of {px_per_m / 1e3:g} px/mm; expected a finite number > 0 (the DIGIT "
                         f"at QVGA: about 17 px/mm)")
    r_px = radius * px_per_m
    h, w = shape[:2]
    if not 3.0 <= r_px < min(h, w):
        raise ValueError(f"{source}: at {px_per_m / 1e3:g} px/mm the ball radius of {radius * 1e3:g} mm is "
                         f"{r_px:.3g} px, the images are {h}x{w} px; expected 3 to {min(h, w)} px: check the scale "
                         f"(the DIGIT at QVGA: about 17 px/mm) and the ball size")


def cmd_calibrate_depth(args: argparse.Namespace) -> int:
    from .depth_calibration import (auto_label, calibrate, check_labels, load_background, load_images,
                                    median_background, px_per_mm_from_caliper, read_labels, resolved_path,
                                    review_overlay, write_labels)

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    try:
        radius = _ball_radius(args)
        images = load_images(args.images)
        background = None
        background_source = None
        left: list[str] = []   # images of the folder given as --background: not presses
        if args.background:
            def same_size(path: Path, frame: np.ndarray) -> None:
                if frame.shape != images[0][1].shape:
                    raise ValueError(f"{path}: the background frame is {frame.shape[0]}x{frame.shape[1]}, the "
                                     f"presses in {args.images} are {images[0][1].shape[0]}x{images[0][1].shape[1]} "
                                     f"(rows x cols); expected no-contact frames of the same sensor and resolution")

            bgr = load_background(args.background, same_size)
            background, background_source = bgr.image, bgr.meta()
            # background frames kept in the presses folder are not presses (the same file, not the same name: two
            # recordings may both hold a 0001.png)
            own = {resolved_path(f) for f in bgr.files}
            left = [n for n, _ in images if resolved_path(Path(args.images) / n) in own]
            images = [(n, im) for n, im in images if n not in left]
            if not images:
                raise ValueError(f"{args.images}: no press images besides the background frame(s) "
                                 f"{', '.join(left[:5])}{' ...' if len(left) > 5 else ''}")
            if left:
                log(f"{len(left)} background frame(s) in {args.images} left out of the presses: "
                    f"{', '.join(left[:5])}{' ...' if len(left) > 5 else ''}")
            log(f"background: {bgr.describe()}")
        shape = images[0][1].shape[:2]
        if args.px_per_mm is not None:
            px_per_m = _px_per_m(args.px_per_mm)
            scale_from = f"--px-per-mm {args.px_per_mm}"
        elif args.caliper is not None:
            if args.caliper_gap is None:
                raise ValueError("--caliper needs --caliper-gap (the distance between the tips, e.g. 5mm)")
            gap = _caliper_gap(args.caliper_gap)   # before the image is read: a bare 5 is 5 m, said as such
            bgc = background if background is not None else median_background([im for _, im in images])
            px_per_m = px_per_mm_from_caliper(_read_image(args.caliper), bgc, gap) * 1e3
            scale_from = f"the caliper image {args.caliper} with --caliper-gap {args.caliper_gap} ({gap * 1e3:g} mm)"
            log(f"scale from the caliper image: {px_per_m / 1e3:.3f} px/mm")
        else:
            raise ValueError("give the scale: --px-per-mm 17.15, or --caliper IMAGE --caliper-gap 5mm")
        _check_scale(px_per_m, radius, shape, scale_from)
        if args.stride is not None and args.stride > max_stride(shape):
            raise ValueError(f"--stride {args.stride}: expected at most {max_stride(shape)} px for {shape[0]}x"
                             f"{shape[1]} images (a work grid of at least 8 cells across)")
        source_date_epoch()   # malformed: refused here, before the work
        labels = read_labels(args.labels) if args.labels else None
        if labels is not None:
            check_labels(labels, images, radius * px_per_m, args.labels)
            labels = _background_labels(labels, left, args.labels, log)
        # every output is checked before the work (training takes minutes)
        if args.labels_only:
            bg = background if background is not None else median_background([im for _, im in images])
            labels_out: str | Path | None = args.write_labels or Path(args.images) / "labels.auto.csv"
        else:
            if args.output is None:
                raise ValueError("give the model file to write with -o FILE")
            _check_output(args.output, "-o")
            labels_out = ((args.write_labels or Path(args.output).with_suffix(".labels.csv"))
                          if labels is None or args.write_labels else None)
        if labels_out is not None:
            _check_output(labels_out, "--write-labels" if args.write_labels else "labels file")
            if args.labels and _same_file(labels_out, args.labels):
                print(f"teletouch calibrate depth: warning: --write-labels {labels_out} is the --labels file: it is "
                      f"rewritten with this folder's presses only, without its comments", file=sys.stderr)
        if args.review:
            _check_output(args.review, "--review", folder=True)
    except (ValueError, FileNotFoundError, ModelFileError) as exc:
        print(f"teletouch calibrate depth: error: {exc}", file=sys.stderr)
        return 2
    if args.labels_only:
        # the --labels rows as given (rewritten and reviewed: the overlays show the given circles), the folder's other
        # presses labelled automatically (before, --labels was read and checked, then thrown away: its file, given as
        # --write-labels too, was overwritten with automatic circles)
        labs = [labels[n] if labels is not None and n in labels else auto_label(n, im, bg, radius * px_per_m)
                for n, im in images]
        if labels is not None:
            given = sum(1 for n, _ in images if n in labels)
            log(f"{given} label(s) as given in {args.labels}"
                + (f", {len(images) - given} labelled automatically" if given < len(images) else ""))
        try:
            out = write_labels(labels_out, labs)
            _write_review(args.review, images, bg, labs, review_overlay)
        except OSError as exc:
            print(f"teletouch calibrate depth: error: {_os_error(exc)}", file=sys.stderr)
            return 1
        n_unc = sum(1 for lb in labs if lb.uncertain and not lb.no_contact)
        log(f"wrote {out} ({len(labs)} presses, {n_unc} uncertain): check it, fix rows, pass it with --labels")
        return 0
    try:
        res = calibrate(images, radius, px_per_m, labels=labels, background=background, holdout=args.holdout,
                        log=log, background_source=background_source, feature_set=args.features,
                        epochs=args.epochs, seed=args.seed, stride=args.stride, progress=not args.quiet,
                        hidden=tuple(args.hidden))
    except ValueError as exc:
        print(f"teletouch calibrate depth: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"teletouch calibrate depth: interrupted; no model written ({args.output} is unchanged)",
              file=sys.stderr)
        return 130
    # the model first: it is the work of minutes; the labels and overlays can be made again with --labels-only
    if source_date_epoch() is None:   # reproducible files (SOURCE_DATE_EPOCH) leave out the durations
        res.model.training["total_seconds"] = round(res.seconds, 2)
    try:
        res.model.save(args.output)
    except OSError as exc:
        print(f"teletouch calibrate depth: error: the model could not be written: {_os_error(exc)}", file=sys.stderr)
        return 1
    try:
        if labels_out is not None:
            out = write_labels(labels_out, res.labels)
            log(f"labels written to {out} (correct them and pass back with --labels)")
        _write_review(args.review, images, res.background, res.labels, review_overlay)
    except OSError as exc:
        print(f"teletouch calibrate depth: error: the model was written to {args.output}, but {_os_error(exc)}",
              file=sys.stderr)
        return 1
    v = res.model.validation
    summary = {"model": str(args.output), "seconds": round(res.seconds, 2), "presses": res.model.training["presses"],
               "depth_gain": res.model.depth_gain, "change_threshold": res.model.change_threshold}
    if v:
        summary.update({"validation_presses": v["presses"], "median_abs_cap_error": v["median_abs_cap_error"],
                        "median_sphere_radius_mm": v["median_sphere_radius_m"] * 1e3})
    print(json.dumps(summary))
    return 0


def _background_labels(labels: dict[str, Any], background: list[str], source: str,
                       log: Any) -> dict[str, Any]:
    """The labels without those of the folder's images given as --background (``background``): they are the
    background, not presses (before, the log said their labels named no image in the folder). One labelled as a
    press (a usable circle) is refused: a background must show no contact, and one with a press in it raises the
    change threshold above every press."""
    pressed = [labels[n] for n in background if n in labels and labels[n].usable]
    if pressed:
        lb = pressed[0]
        raise ValueError(f"{source}:{lb.line}: {lb.image} is labelled as a press (radius {lb.r:g} px), but it is given "
                         f"as --background, which must be a frame without contact: give a no-contact frame of the "
                         f"sensor, or mark the row 'no contact' with radius_px 0 if nothing touches the gel in it")
    taken = [n for n in background if n in labels]
    if taken:
        log(f"{len(taken)} label(s) not used: {', '.join(taken[:5])}{' ...' if len(taken) > 5 else ''}: taken as "
            f"the background (--background), not as a press")
    return {n: lb for n, lb in labels.items() if n not in taken}


def _write_review(folder: str | None, images: list, bg: np.ndarray, labels: list, overlay: Any) -> None:
    if not folder:
        return
    import cv2

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    by = {lb.image: lb for lb in labels}
    stems = [Path(name).stem for name, _ in images]
    for name, im in images:
        if name in by:
            # a.png and a.jpg would both be a.review.png: then the full name (a.png.review.png) tells them apart
            base = Path(name).stem if stems.count(Path(name).stem) == 1 else Path(name).name
            path = out / (base + ".review.png")
            if not cv2.imwrite(str(path), overlay(im, bg, by[name])):
                raise OSError(f"--review: the overlay {path} could not be written")


def _background_for_model(paths: list[str], model: Any) -> tuple[np.ndarray, str]:
    """`estimate --background` and the node's `background`: one or more no-contact frames and/or folders of them
    (their per-pixel median), for this model's image size; (the background, what it is for the log).
    FileNotFoundError / ValueError naming the file."""
    from .depth_calibration import load_background

    def model_size(path: Path, frame: np.ndarray) -> None:
        if frame.shape != (*model.shape, 3):
            raise ValueError(f"{path}: background frame is {frame.shape[0]}x{frame.shape[1]}, the model "
                             f"{model.source} is for {model.shape[0]}x{model.shape[1]} images (rows x cols)")

    bgr = load_background(paths, model_size)
    return bgr.image, bgr.describe()


def _same_file(a: str | Path, b: str | Path) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def _os_error(exc: OSError) -> str:
    """An OSError as one line naming the file: 'PATH: reason' (or the message of one raised with a text only)."""
    if exc.filename is not None:
        return f"{exc.filename}: {exc.strerror or exc}"
    return str(exc)


def cmd_estimate(args: argparse.Namespace) -> int:
    from .depth_pipeline import DepthPipeline
    from .normal_model import load_model

    save = Path(args.save_depth) if args.save_depth else None
    try:
        try:
            model = load_model(args.model)
        except ModelFileError as exc:   # an input error as the others: the command's prefix and exit code
            raise ValueError(f"--model {_no_graph_note(exc, args.model)}") from None
        bg = None
        if args.background:
            bg, what = _background_for_model(args.background, model)
            print(f"teletouch estimate: background: {what}", file=sys.stderr)
        force = _force_calibration(args.force_calibration, args.model) if args.force_calibration else None
        device = device_problem(args.device, "--device")
        if device:
            raise ValueError(device)
        if save is not None:
            _check_output(save, "--save-depth", folder=True)
            try:
                save.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise ValueError(f"--save-depth {save}: cannot create the folder: {exc.strerror or exc}") from None
    except (FileNotFoundError, ValueError) as exc:
        print(f"teletouch estimate: error: {exc}", file=sys.stderr)
        return 2
    pipe = DepthPipeline(model, device=args.device, background=bg)
    pipe.warm_up()   # lazy imports and FFT set-up here, so that each image's "ms" is its own computation
    rc = 0
    for path in args.images:
        frame, why = _estimate_input(path, pipe)
        if frame is None:
            # every image given has its row: an unreadable one too, as an implausible one (exit code 2 all the same)
            print(f"teletouch estimate: error: {path}: {why}", file=sys.stderr)
            rc = 2
            if args.json:
                print(json.dumps({"image": str(path), "valid": False, "problem": why, "max_depth_m": None,
                                  "contact_area_m2": None, "centroid_m": [None, None], "ms": None}))
            continue
        t0 = time.perf_counter()
        res = pipe(frame)
        ms = (time.perf_counter() - t0) * 1e3
        problem = frame_problem(res, args.max_global_change) or colour_problem(frame)
        mismatch = background_mismatch(frame, bg if bg is not None else model.background)
        if not problem and args.max_background_mismatch and mismatch > args.max_background_mismatch:
            problem = (f"the frame differs from the model's background by {mismatch:.1f} levels (median over the "
                       f"image in block means after the global offset; a sensor's own frames: 1-2; "
                       f"--max-background-mismatch "
                       f"{args.max_background_mismatch:g}): the model (or --background) is another sensor's")
        if problem:
            # not a DIGIT frame the model can read (LEDs off, saturated, another sensor's background): no numbers,
            # they would be a confident wrong depth
            print(f"teletouch estimate: error: {path}: implausible frame: {problem}", file=sys.stderr)
            rc = 2
            if args.json:
                print(json.dumps({"image": str(path), "valid": False, "problem": problem, "max_depth_m": None,
                                  "contact_area_m2": None, "centroid_m": [None, None], "ms": round(ms, 3)}))
            continue
        row: dict[str, Any] = {"image": str(path), "valid": True, "background_mismatch": round(mismatch, 2),
                               "max_depth_m": res.max_depth,
                               "contact_area_m2": res.contact_area,
                               "centroid_m": [None if not math.isfinite(c) else float(c) for c in res.centroid],
                               "ms": round(ms, 3)}
        if force is not None:
            where = tuple(float(c) for c in res.centroid) if np.isfinite(res.centroid).all() else None
            row["force_N"] = float(force.predict(res.max_depth, position=where))
        if save is not None:
            stem = Path(path).stem
            np.save(save / f"{stem}.npy", res.depth)
            _save_depth_png(save / f"{stem}.png", res.depth)
            row["depth_file"] = str(save / f"{stem}.npy")
        if args.json:
            print(json.dumps(row))
        else:
            f = f"  force {row['force_N']:.3f} N" if "force_N" in row else ""
            print(f"{path}: max depth {res.max_depth * 1e3:.3f} mm  contact area {res.contact_area * 1e6:.2f} mm^2"
                  f"{f}")
    return rc


def _no_graph_note(exc: Exception, spec: str) -> str:
    """The message of a file named on the command line that was not found, without the note for a graph's parameters
    (a relative path is taken from the current folder, not the graph file's): `estimate` reads no graph. Where it was
    looked for stays."""
    p = Path(str(spec)).expanduser()
    note = looked_at(p)   # " (looked at CWD/p: a relative path ... not the graph file's)", as the message has it
    return str(exc).replace(note, f" (looked at {Path.cwd() / p})") if note else str(exc)


def _estimate_input(path: str, pipe: Any) -> tuple[np.ndarray | None, str]:
    """(the frame, '') or (None, why `estimate` cannot read it, without the path): no such file, a folder, not an
    image, another size than the model's."""
    frame, why = _try_read_image(path)
    if frame is None:
        return None, why
    try:
        pipe.check_frame(frame)
    except ValueError as exc:
        return None, str(exc)
    return frame, ""


def _force_calibration(path: str, model: str) -> Any:
    """`estimate --force-calibration`: the calibration, refused (ValueError) when it was made for another depth
    model than ``--model``, as poly-force refuses it with ``depth_model`` set: a calibration is per sensor and per
    depth model, and another model's depths give another force."""
    from teletouch.plugins.estimators.poly_force import ForceCalibration, _model_name

    try:
        cal = ForceCalibration.load(path)
    except ModelFileError as exc:   # an input error as the others: the command's prefix and exit code
        raise ValueError(f"--force-calibration {_no_graph_note(exc, path)}") from None
    if _model_name(model) != _model_name(cal.sensor_model_id):
        made_for = repr(cal.sensor_model_id) if cal.sensor_model_id else "an unnamed depth model"
        raise ValueError(f"--force-calibration {path}: the calibration {cal.path} was made for {made_for}, not for "
                         f"the depth model {model!r} (--model): calibrate the force with this depth model "
                         f"(`teletouch calibrate force --set depth.model=...`) or give --sensor-model-id when "
                         f"fitting a CSV")
    return cal


def _save_depth_png(path: Path, depth: np.ndarray) -> None:
    """Colour-mapped depth (turbo; 0 = dark blue, the scale's top = max(depth, 0.5 mm) = dark red), with a label."""
    import cv2

    top = max(float(depth.max()), 5e-4)
    v = np.clip(depth / top * 255.0, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(v, cv2.COLORMAP_TURBO)
    cv2.putText(img, f"0-{top * 1e3:.2f}mm", (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1)
    cv2.imwrite(str(path), img)


@hookimpl
def teletouch_components():
    return [DepthEstimator]


@hookimpl
def teletouch_add_commands(subparsers, calibrate):
    p = calibrate.add_parser("depth", help="calibrate the depth model of a DIGIT from ball presses",
                             description="Train the per-pixel normal network from images of a ball pressed into "
                             "the gel (~40 presses over the whole sensor; the ball somewhere else in each). "
                             "Writes one model file for `teletouch estimate` and the `depth` component.")
    p.add_argument("--images", required=True, help="folder of press images (PNG/JPEG), one resolution")
    p.add_argument("--ball-diameter", default=None, help="ball diameter, e.g. 6mm (a bare number is metres)")
    p.add_argument("--ball-radius", default=None, help="or the ball radius, e.g. 3mm (a bare number is metres)")
    p.add_argument("--px-per-mm", default=None, help="image scale: 17.15 (px per mm) or 17.15px/mm")
    p.add_argument("--caliper", default=None, help="or: an image of two caliper tips pressed into the gel")
    p.add_argument("--caliper-gap", default=None, help="the distance between those tips, e.g. 5mm (a bare number is "
                   "metres)")
    p.add_argument("--labels", default=None, help="contact circles CSV (image,center_x,center_y,radius_px[,note]); "
                   "default: found automatically")
    p.add_argument("--background", nargs="+", action="extend", default=None, metavar="FRAME|DIR",
                   help="no-contact frame(s) of the sensor, or a folder of them (repeatable): one frame is used as "
                   "it is, several as their per-pixel median (e.g. 10 frames with nothing touching: a lower change "
                   "threshold, so lighter touches count); default: per-pixel median of the presses")
    p.add_argument("--write-labels", default=None, help="where to write the labels used (default: beside -o)")
    p.add_argument("--labels-only", action="store_true", help="only label the presses (write the CSV), no training")
    p.add_argument("--review", default=None, metavar="DIR", help="write an overlay image per press for checking")
    p.add_argument("--holdout", type=int_at_least(0), default=2, help="presses held out for validation (default 2)")
    p.add_argument("--features", default=DEFAULT_FEATURES, choices=sorted(FEATURE_SETS),
                   help=f"network inputs (default {DEFAULT_FEATURES}: relative change from the background, its local "
                   "gradients and the position; rgbxy is the paper's R, G, B, X, Y; see docs/depth.md)")
    p.add_argument("--hidden", type=int_at_least(1), nargs="+", default=list(DEFAULT_HIDDEN),
                   help=f"hidden layer sizes (default {' '.join(map(str, DEFAULT_HIDDEN))})")
    p.add_argument("--epochs", type=int_at_least(1), default=40, help="training epochs (default 40)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stride", type=int_at_least(1), default=None, help="work-grid stride in px (default: rows / 160)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("-o", "--output", default=None, help="model file to write (e.g. sensor.model)")
    p.set_defaults(func=cmd_calibrate_depth)

    p = subparsers.add_parser("estimate", help="depth (and force) from DIGIT images with a calibrated model")
    p.add_argument("images", nargs="+", metavar="IMAGE")
    p.add_argument("--model", required=True, help="model file or packaged model name (sim-digit-qvga)")
    p.add_argument("--background", action="append", default=None, metavar="FRAME|DIR",
                   help="a no-contact frame replacing the model's background, or a folder of them (their per-pixel "
                   "median); repeat the option for several frames (one path per --background: the images follow)")
    p.add_argument("--force-calibration", default=None, metavar="FILE", help="force calibration (poly-force JSON): "
                   "adds force_N")
    p.add_argument("--device", default="cpu", help=f"torch device: {DEVICES} (default cpu)")
    p.add_argument("--json", action="store_true", help="one JSON object per image on stdout (SI units)")
    p.add_argument("--save-depth", default=None, metavar="DIR", help="write DIR/<stem>.npy (m) and a colour PNG")
    p.add_argument("--max-global-change", type=_positive_levels, default=24.0, metavar="LEVELS",
                   help="an image whose global colour change from the background exceeds this (0-255 levels per "
                        "channel; default 24, as the depth node's max_global_change) is reported as implausible "
                        "(LEDs off, saturated) instead of given a depth")
    p.add_argument("--max-background-mismatch", type=_levels_or_zero, default=6.0, metavar="LEVELS",
                   help="an image whose colours differ from the background by more than this apart from a global "
                        "offset (median over the image in block means, mean over B, G, R; a sensor's own frames: "
                        "1-2, another DIGIT unit's: 9-20; default 6, as the depth node's max_background_mismatch; 0: "
                        "no check) is reported as implausible: the model or --background is another sensor's")
    p.set_defaults(func=cmd_estimate)
