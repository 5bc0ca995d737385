"""``replay``: DIGIT frames from a folder of images, a video file or a teletouch recording (MCAP), at a given rate.

Same output port as the real driver (``image``: uint8 BGR, portrait). Frame k is due ``k / rate`` seconds after the
first step (``rate`` None: the video's own fps, the recording's own stamps, one image per step for a folder); each
step publishes the newest due frame, stamped with the graph time it became due, so replays are deterministic under
the simulated clock. Landscape frames are turned portrait the way the ``digit`` driver does (``orientation``).
At the end the run stops normally (or starts again with ``loop``: each pass starts at least one frame period after
the last frame of the one before; a recording of one frame, or whose stamps never advance, loops at the node's rate;
a recorded stamp that goes backwards counts as the one before it, so stamps never go backwards). A corrupt,
unreadable or vanished frame is reported with its file name (and frame number): logged and skipped
(``on_corrupt: report``) or a fault (``on_corrupt: fault``).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any, Callable, Iterator, Literal

import numpy as np
from pydantic import Field, model_validator

from teletouch import Component, ComponentFault, Kind, Params, Port, Sample, hookimpl
from teletouch.errors import ModelFileError
from teletouch.units import Hertz

__all__ = ["Replay", "IMAGE_SUFFIXES", "list_images"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".webm", ".mpg", ".mpeg", ".m4v")


def _natural_key(name: str) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files of a folder in natural order (frame_2 before frame_10); other files are ignored."""
    files = [f for f in Path(folder).iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda f: _natural_key(f.name))


class CorruptFrame(Exception):
    def __init__(self, where: str, why: str):
        self.where = where
        super().__init__(f"{where}: {why}")


class _Source:
    """Frames as (name, image or CorruptFrame, stamp_s or None)."""

    kind = ""
    native_rate: float | None = None

    def frames(self) -> Iterator[tuple[str, np.ndarray | CorruptFrame, float | None]]:  # pragma: no cover
        raise NotImplementedError

    def close(self) -> None:
        pass


class _Folder(_Source):
    kind = "folder"

    def __init__(self, path: Path):
        self.files = list_images(path)
        if not self.files:
            raise ModelFileError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        # fail at configure time if not one frame can be read (reads up to the first good one)
        if all(self._read(f) is None for f in self.files):
            raise ModelFileError(f"no readable image in {path}: {len(self.files)} files could not be read "
                                 f"(corrupt or not images), e.g. {self.files[0].name}")

    @staticmethod
    def _read(f: Path) -> np.ndarray | None:
        import cv2

        try:
            return cv2.imread(str(f), cv2.IMREAD_COLOR)
        except cv2.error:
            return None

    def frames(self):
        for f in self.files:
            img = self._read(f)
            if img is None:
                why = ("cannot decode the image (corrupt or not an image)" if f.exists() else
                       "no longer exists (removed since the replay was configured)")
                yield f.name, CorruptFrame(str(f), why), None
            else:
                yield f.name, img, None


class _Video(_Source):
    kind = "video"

    def __init__(self, path: Path):
        import cv2

        self.path = path
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise ModelFileError(f"{path}: cannot open the video (corrupt or unsupported codec)")
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.native_rate = fps if fps and math.isfinite(fps) and fps > 0 else None
        self.count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        # fail at configure time, as a folder or a recording does, if not one frame can be decoded
        ok, img = cap.read()
        cap.release()
        if not ok or img is None:
            raise ModelFileError(f"{path}: no frame can be decoded (an empty, truncated or corrupt video)")

    def frames(self):
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        try:
            k = 0
            while True:
                ok, img = cap.read()
                if not ok or img is None:
                    if self.count and k < self.count - 1:  # (some containers count one frame too many)
                        yield (f"{self.path.name}#{k}",
                               CorruptFrame(f"{self.path}#frame{k}", f"cannot decode frame {k} of {self.count}: "
                                                                     f"truncated or corrupt video"), None)
                    return
                yield f"{self.path.name}#{k}", img, None
                k += 1
        finally:
            cap.release()


class _Recording(_Source):
    kind = "recording"

    def __init__(self, path: Path, port: str | None, log: Callable[[str], None] | None = None):
        try:
            from teletouch.recording import iter_images
        except ImportError as e:  # pragma: no cover - the core ships it
            raise ModelFileError(f"{path}: replaying recordings needs teletouch.recording.iter_images ({e})") from None
        self.iter_images = iter_images
        self.path = path
        self.port = port
        # fail at configure time on a wrong port or an empty recording; warn about one cut short (a crashed run)
        warnings: list[str] = []
        try:
            next(iter(iter_images(path, port=port, log=warnings.append)))
        except StopIteration:
            raise ModelFileError(f"{path}: the recording has no images"
                                 + (f" on channel '{port}'" if port else "")
                                 + "".join(f"; {w.removeprefix(f'warning: {path}: ')}" for w in warnings)
                                 ) from None
        except Exception as e:
            raise ModelFileError(str(e) if str(path) in str(e) else f"{path}: {e}") from None
        if log is not None:
            for w in warnings:
                log(f"replay: {w}")

    def frames(self):
        it = iter(self.iter_images(self.path, port=self.port))
        k = 0
        while True:
            try:
                stamp, img = next(it)
            except StopIteration:
                return
            except Exception as e:  # a damaged message: iteration cannot go on reliably
                yield f"{self.path.name}#{k}", CorruptFrame(f"{self.path}#message{k}", str(e)), None
                return
            yield f"{self.path.name}#{k}", img, float(stamp)
            k += 1


def _port_only_for_mcap(port: str, why: str) -> str:
    return (f"port {port!r} applies only to a .mcap recording (it picks the image channel to replay); {why}: "
            f"remove port")


class Replay(Component):
    """Replays DIGIT frames from a folder of images, a video file or a teletouch recording (MCAP)."""

    name = "replay"
    kind = Kind.SENSOR
    default_rate = 30.0
    outputs = {"image": Port("uint8", (None, None, 3), "", "BGR, portrait, like the digit driver")}

    class Params(Params):
        path: str = Field(..., description="folder of images, video file, or .mcap recording")
        rate: Hertz | None = Field(None, gt=0, description="frames per second (None: the video's fps, the "
                                   "recording's stamps, one image per step for a folder)",
                                   json_schema_extra={"unit": "Hz"})
        loop: bool = Field(False, description="start again at the end (else the run stops)")
        port: str | None = Field(None, description="recording only: which image channel (node.port)")
        orientation: Literal["portrait", "as-is"] = Field("portrait", description="turn landscape frames "
                                                          "portrait like the digit driver, or leave them")
        on_corrupt: Literal["report", "fault"] = Field("report", description="a corrupt frame: log its file "
                                                       "name and skip it, or fault")

        @model_validator(mode="after")
        def _port(self) -> "Replay.Params":
            if not self.path.strip():   # Path("") is the working directory
                raise ValueError("path: empty; expected a folder of images, a video file or a .mcap recording")
            if self.port is not None and not self.path.lower().endswith(".mcap"):
                raise ValueError(_port_only_for_mcap(self.port, f"path {self.path!r} is not a .mcap file"))
            return self

    def configure(self) -> None:
        p = self.params
        path = Path(p.path).expanduser()
        if not path.exists():
            raise ModelFileError(f"replay path {str(path)!r} does not exist (expected a folder of images, a video "
                                 f"or a .mcap recording)")
        if path.is_dir():
            if p.port is not None:  # a folder named *.mcap: the Params check passed
                raise ModelFileError(_port_only_for_mcap(p.port, str(path) + " is a folder"))
            self.source: _Source = _Folder(path)
        elif path.suffix.lower() == ".mcap":
            self.source = _Recording(path, p.port, self.ctx.log)
        elif path.suffix.lower() in IMAGE_SUFFIXES:
            raise ModelFileError(f"{path}: a single image; give the folder that holds the frames")
        else:
            self.source = _Video(path)
        self.corrupt: list[str] = []
        self.published = 0
        self.skipped = 0
        self.passes = 0
        self._shape: tuple[int, ...] | None = None

    def activate(self) -> None:
        self._it = self._frames()
        self._t0: float | None = None
        self._pending: tuple[str, np.ndarray, float] | None = None
        self._done = False

    def _frames(self) -> Iterator[tuple[str, np.ndarray, float]]:
        """(name, image, due time relative to the start) for every good frame, across loops."""
        p = self.params
        offset = 0.0
        while True:
            k = -1
            first_stamp = None
            last_due = 0.0
            any_good = False
            for name, img, stamp in self.source.frames():
                k += 1
                if p.rate is not None:
                    due = k / p.rate
                elif stamp is not None:
                    first_stamp = stamp if first_stamp is None else first_stamp
                    due = max(stamp - first_stamp, last_due)   # a stamp that goes backwards: the one before it
                elif self.source.native_rate:
                    due = k / self.source.native_rate
                else:
                    due = None  # one per step
                if isinstance(img, CorruptFrame):
                    self._report(img)
                    continue
                img = self._orient(name, img)
                if img is None:
                    continue
                any_good = True
                last_due = due if due is not None else last_due
                yield name, img, (offset + due) if due is not None else math.nan
            self.passes += 1
            if not p.loop or not any_good:
                return
            if p.rate:
                period = 1.0 / p.rate
            elif self.source.native_rate:
                period = 1.0 / self.source.native_rate
            else:  # recorded stamps: the mean interval
                period = last_due / k if k > 0 else 0.0
            if not period > 0.0:
                # one frame, or stamps that never advance: without a period every pass would be due at once and the
                # step would loop over the recording forever; the node's own period
                period = 1.0 / (self.ctx.rate or self.default_rate)
            offset += last_due + period

    def _orient(self, name: str, img: np.ndarray) -> np.ndarray | None:
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            self._report(CorruptFrame(name, f"not an 8-bit colour image (shape {img.shape}, {img.dtype})"))
            return None
        if self.params.orientation == "portrait" and img.shape[1] > img.shape[0]:
            import cv2

            img = cv2.rotate(img, cv2.ROTATE_90_COUNTERCLOCKWISE)
        if self._shape is None:
            self._shape = img.shape
        elif img.shape != self._shape:
            self._report(CorruptFrame(name, f"size {img.shape[0]}x{img.shape[1]} differs from the first frame's "
                                            f"{self._shape[0]}x{self._shape[1]}"))
            return None
        return img

    def _report(self, err: CorruptFrame) -> None:
        self.corrupt.append(str(err))
        if self.params.on_corrupt == "fault":
            raise ComponentFault(f"corrupt frame {err}")
        self.ctx.log(f"replay: skipped corrupt frame {err}")

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        if self._done:
            return None
        if self._t0 is None:
            self._t0 = t
        rel = t - self._t0
        newest = None
        while True:
            if self._pending is None:
                nxt = next(self._it, None)
                if nxt is None:
                    break
                self._pending = nxt
            name, img, due = self._pending
            if math.isnan(due):  # one frame per step
                if newest is None:
                    newest = self._pending
                    self._pending = None
                break
            if due > rel + 1e-9:
                break
            if newest is not None:
                self.skipped += 1
            newest = self._pending
            self._pending = None
        if newest is None:
            if self._pending is None:
                self._done = True
                self.ctx.request_stop(f"replay of {self.params.path} finished: {self.published} frames"
                                      + (f", {len(self.corrupt)} corrupt" if self.corrupt else ""))
            return None
        name, img, due = newest
        self.published += 1
        self.current = name
        stamp = t if math.isnan(due) else self._t0 + due
        return {"image": Sample(img, stamp)}

    def deactivate(self) -> None:
        self._it = iter(())

    def status(self) -> dict[str, Any]:
        return {"frames": getattr(self, "published", 0), "skipped": getattr(self, "skipped", 0),
                "corrupt": len(getattr(self, "corrupt", []))}


@hookimpl
def teletouch_components():
    return [Replay]
