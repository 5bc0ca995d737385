"""``replay``: DIGIT frames from a folder of images, a video file or a teletouch recording (MCAP), at a given rate.

A folder plays in natural order (frame_2 before frame_10), or in time order where every name is a time in seconds (as
ROS tools export frames); a file that starts as MCAP does is a recording whatever its suffix.

Same output port as the real driver (``image``: uint8 BGR, portrait). Frame k is due ``k / rate`` seconds after the
first step (``rate`` None: the video's own fps, the recording's own stamps, one image per step for a folder); each
step publishes the newest due frame, stamped with the graph time it became due, so replays are deterministic under
the simulated clock. Landscape frames are turned portrait the way the ``digit`` driver does (``orientation``).
At the end the run stops normally (or starts again with ``loop``: each pass starts at least one frame period after
the last frame of the one before; a recording of one frame, or whose stamps never advance, loops at the node's rate;
a recorded stamp that goes backwards counts as the one before it, so stamps never go backwards). A corrupt,
unreadable or vanished frame is reported with its file name (and frame number) when it is due, and why (a read error
such as permission denied, or cannot be decoded): logged and skipped, once however often a loop meets it
(``on_corrupt: report``), or a fault (``on_corrupt: fault``); its slot stays empty. In a video, the frames after a
corrupt one are played; undecodable frames up to the end are a video cut short: one report, and the end (without a
frame count, :data:`UNCOUNTED_GAP` failed frames in a row are the end, without a report). In a recording, an image
message that cannot be decoded is reported (file, channel, time) and skipped, its recorded slot kept. A video's
frames that the rate skips are only grabbed, not retrieved (cv2 grab without retrieve: with OpenCV's FFmpeg backend
grab decodes, and only the conversion to BGR is saved, ~5-25% of a read), where the container's count says a later
frame follows.
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
from teletouch.paths import looked_at
from teletouch.units import Hertz

__all__ = ["Replay", "IMAGE_SUFFIXES", "list_images"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".webm", ".mpg", ".mpeg", ".m4v")


def _natural_key(name: str) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


#: a frame named by its time: seconds, with a fraction or not (``1700000000.123.png``, as ROS tools export frames)
_TIME_NAME = re.compile(r"\d+(?:\.\d+)?")


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files of a folder in natural order (frame_2 before frame_10); where every name is a number of seconds
    with a fraction (``1700000000.5.png``, ``1700000000.123.png``), in the order of those numbers (natural order put
    .5 before .123). Other files are ignored."""
    files = [f for f in Path(folder).iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES]
    if files and all(_TIME_NAME.fullmatch(f.stem) for f in files):
        return sorted(files, key=lambda f: (float(f.stem), f.name))
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
        try:
            self.files = list_images(path)
        except OSError as e:
            raise ModelFileError(f"{path}: cannot list the folder ({e.strerror or e})") from None
        if not self.files:
            raise ModelFileError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        # fail at configure time if not one frame can be read (reads up to the first good one)
        first_why = None
        for f in self.files:
            got = self._read(f)
            if not isinstance(got, str):
                break
            first_why = first_why or f"{f.name}: {got}"
        else:
            raise ModelFileError(f"no readable image in {path}: {len(self.files)} files could not be read, "
                                 f"e.g. {first_why}")

    @staticmethod
    def _read(f: Path) -> np.ndarray | str:
        """The image as 8-bit BGR (grey, alpha and 16 bits converted, as cv2.imread does), or why there is none:
        the file's own read error (cv2.imread tells none: a file this user may not read looked corrupt), or that it
        cannot be decoded."""
        import cv2

        try:
            data = np.fromfile(f, np.uint8)
        except FileNotFoundError:
            return "no longer exists (removed since the replay was configured)"
        except OSError as e:
            return f"cannot be read ({e.strerror or e})"
        try:
            img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        except cv2.error:
            img = None
        return "cannot decode the image (corrupt or not an image)" if img is None else img

    def frames(self):
        for f in self.files:
            got = self._read(f)
            if isinstance(got, str):
                yield f.name, CorruptFrame(str(f), got), None
            else:
                yield f.name, got, None


#: without a frame count (raw streams, some containers), this many undecodable frames in a row are the end of the
#: video; a good frame after fewer makes them corrupt frames (a read past the end fails at once: ~1 us each)
UNCOUNTED_GAP = 100


class _Grabbed:
    """A video frame read from the file (cv2 grab) but not yet turned into an image: :meth:`image` does that (cv2
    retrieve), and only until the next frame is grabbed. A replay whose rate skips the frame leaves it so.
    ``skippable``: the container's count says a later frame follows (the last two are always decoded: some
    containers count one frame too many, and a last frame left undecoded could not be published at the end; a
    later frame that turns out corrupt leaves that step without a new frame, its slot empty).
    ``next_due``: when the next frame is due (set by the replay; inf: never skipped)."""

    def __init__(self, cap: Any, corrupt: CorruptFrame, skippable: bool):
        self.cap, self.corrupt, self.skippable = cap, corrupt, skippable
        self.valid = True
        self.next_due = math.inf

    def image(self) -> np.ndarray | CorruptFrame:
        """The frame as an image, or ``corrupt`` (what to report) if it cannot be decoded."""
        assert self.valid, "a grabbed frame is decoded before the next one is grabbed"
        ok, img = self.cap.retrieve()
        return img if ok and img is not None else self.corrupt


class _Video(_Source):
    kind = "video"

    def __init__(self, path: Path):
        import cv2

        self.path = path
        try:   # OpenCV tells no read error: a video this user may not read would look corrupt
            with open(path, "rb"):
                pass
        except OSError as e:
            raise ModelFileError(f"{path}: cannot be read ({e.strerror or e})") from None
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise ModelFileError(f"{path}: cannot open the video (corrupt or unsupported codec)")
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.native_rate = fps if fps and math.isfinite(fps) and fps > 0 else None
        count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self.count = int(count) if count and math.isfinite(count) and count > 0 else 0   # 0: not known
        # fail at configure time, as a folder or a recording does, if not one frame can be decoded
        ok, img = cap.read()
        cap.release()
        if not ok or img is None:
            raise ModelFileError(f"{path}: no frame can be decoded (an empty, truncated or corrupt video)")

    def frames(self):
        """Frame k as the k-th item (its stamp is k / fps), a :class:`_Grabbed` (decoded only if the replay uses
        it). A frame that cannot be decoded, with good ones after it, is one CorruptFrame each (OpenCV's next grab
        goes on after it); undecodable frames up to the end that the container counts are the video cut short: one
        CorruptFrame at the first of them, and the end. Without a count, the end is :data:`UNCOUNTED_GAP` failed
        frames in a row (undecodable frames up to it cannot be told from the end: no report)."""
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        try:
            k = 0
            failed_from: int | None = None   # the first of a run of undecodable frames, not yet reported
            while True:
                if cap.grab():
                    for j in range(k if failed_from is None else failed_from, k):
                        yield f"{self.path.name}#{j}", self._corrupt(j), None
                    failed_from = None
                    frame = _Grabbed(cap, self._corrupt(k), skippable=0 < self.count and k < self.count - 2)
                    yield f"{self.path.name}#{k}", frame, None
                    frame.valid = False
                elif self._more_may_follow(k, failed_from):
                    failed_from = k if failed_from is None else failed_from
                else:
                    if failed_from is not None and self.count:
                        yield (f"{self.path.name}#{failed_from}",
                               CorruptFrame(f"{self.path}#frame{failed_from}",
                                            f"cannot decode frame {failed_from} of {self.count} nor any after it: "
                                            f"truncated or corrupt video"), None)
                    return
                k += 1
        finally:
            cap.release()

    def _corrupt(self, k: int) -> CorruptFrame:
        of = f" of {self.count}" if self.count else ""
        return CorruptFrame(f"{self.path}#frame{k}", f"cannot decode frame {k}{of} (a corrupt frame)")

    def _more_may_follow(self, k: int, failed_from: int | None) -> bool:
        """Whether frame ``k``, which failed, may have good frames after it: before the last the container counts
        (some count one frame too many), or without a count fewer than :data:`UNCOUNTED_GAP` failures in a row."""
        if self.count:
            return k < self.count - 1
        return k - (k if failed_from is None else failed_from) < UNCOUNTED_GAP - 1


class _Recording(_Source):
    kind = "recording"

    def __init__(self, path: Path, port: str | None, log: Callable[[str], None] | None = None):
        try:
            from teletouch.recording import RecordingError, iter_images
        except ImportError as e:  # pragma: no cover - the core ships it
            raise ModelFileError(f"{path}: replaying recordings needs teletouch.recording.iter_images ({e})") from None
        self.iter_images = iter_images
        self.path = path
        self.port = port
        # fail at configure time on a wrong port or a recording without one image that can be decoded (damaged ones
        # before the first good one are reported when they are due); warn about one cut short (a crashed run) or
        # whose recorder dropped samples
        warnings: list[str] = []
        damaged: list[Exception] = []
        try:
            next(iter(iter_images(path, port=port, log=warnings.append, on_damaged=lambda s, e: damaged.append(e))))
        except StopIteration:
            raise RecordingError(f"{path}: " + (
                f"not one image can be decoded ({len(damaged)} damaged, e.g. "
                f"{str(damaged[0]).removeprefix(f'{path}: ')})" if damaged else "the recording has no images")
                + (f" on channel '{port}'" if port else "")
                + "".join(f"; {w.removeprefix(f'warning: {path}: ')}" for w in warnings)
            ) from None
        except Exception as e:   # a recording, not a model file: its own error type (the exit code is the same)
            raise RecordingError(str(e) if str(path) in str(e) else f"{path}: {e}") from None
        if log is not None:
            for w in warnings:
                log(f"replay: {w}")

    def frames(self):
        """The recording's images with their recorded stamps. An image message that cannot be decoded is a
        CorruptFrame with its stamp (its slot is kept), named by the file, the channel and its time; the images
        after it are played. Any other error (the file itself) ends the replay there, after one CorruptFrame."""
        damaged: list[tuple[float, Exception]] = []
        it = iter(self.iter_images(self.path, port=self.port, on_damaged=lambda s, e: damaged.append((s, e))))
        k = 0
        while True:
            try:
                got = next(it)
            except StopIteration:
                got = None
            except Exception as e:  # the file, not one message: iteration cannot go on reliably
                yield from self._damaged(damaged, k)
                k += len(damaged)
                yield f"{self.path.name}#{k}", CorruptFrame(f"{self.path}#message{k}", str(e)), None
                return
            yield from self._damaged(damaged, k)   # the messages before this image that could not be decoded
            k += len(damaged)
            damaged.clear()
            if got is None:
                return
            yield f"{self.path.name}#{k}", got[1], float(got[0])
            k += 1

    def _damaged(self, damaged: list[tuple[float, Exception]], k: int) -> Iterator[tuple[str, CorruptFrame, float]]:
        for j, (stamp, e) in enumerate(damaged):   # the error names the file first: named once
            yield (f"{self.path.name}#{k + j}", CorruptFrame(str(self.path), str(e).removeprefix(f"{self.path}: ")),
                   float(stamp))


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
            where = Path(self.path).expanduser()
            if not where.exists():   # when the graph is validated (`validate` said OK, the run failed at start-up)
                raise ValueError(f"path {self.path!r} does not exist{looked_at(where)}; expected a folder of images, "
                                 f"a video file or a .mcap recording")
            if where.is_file() and where.suffix.lower() in IMAGE_SUFFIXES:
                raise ValueError(f"path {self.path!r} is a single image; give the folder that holds the frames")
            if self.port is not None and not self.path.lower().endswith(".mcap"):
                from teletouch.recording import is_mcap   # a recording renamed (run.bag) starts as MCAP does

                if not is_mcap(Path(self.path).expanduser()):
                    raise ValueError(_port_only_for_mcap(self.port, f"path {self.path!r} is not a .mcap file (by "
                                                                    f"its name or its first bytes)"))
            return self

    def configure(self) -> None:
        from teletouch.recording import is_mcap   # (imported when the node starts, as iter_images is)

        p = self.params
        path = Path(p.path).expanduser()
        if not path.exists():
            raise ModelFileError(f"replay path {str(path)!r} does not exist (expected a folder of images, a video "
                                 f"or a .mcap recording)")
        if path.is_dir():
            if p.port is not None:  # a folder named *.mcap: the Params check passed
                raise ModelFileError(_port_only_for_mcap(p.port, str(path) + " is a folder"))
            self.source: _Source = _Folder(path)
        elif path.suffix.lower() == ".mcap" or is_mcap(path):   # (a recording renamed: not opened as a video)
            self.source = _Recording(path, p.port, self.ctx.log)
        elif path.suffix.lower() in IMAGE_SUFFIXES:
            raise ModelFileError(f"{path}: a single image; give the folder that holds the frames")
        else:
            self.source = _Video(path)
        self.corrupt: list[str] = []
        self._reported: set[str] = set()
        self.published = 0
        self.skipped = 0
        self.passes = 0
        self._shape: tuple[int, ...] | None = None

    def activate(self) -> None:
        self._it = self._frames()
        self._t0: float | None = None
        self._pending: tuple[str, np.ndarray | CorruptFrame | _Grabbed, float] | None = None
        self._done = False

    def _frames(self) -> Iterator[tuple[str, np.ndarray | CorruptFrame | _Grabbed, float]]:
        """(name, frame, due time relative to the start; NaN: one per step) for every frame, across loops; a frame
        is an image, a CorruptFrame or a video's :class:`_Grabbed` frame. A corrupt frame is reported by
        :meth:`step` when it is due, not here: the step that publishes frame k reads frame k + 1 ahead (a grabbed
        frame k is decoded, or left undecoded, before that)."""
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
                # a corrupt frame keeps its slot (empty), also the last one: the next pass starts one period after
                # it (recorded stamps: a damaged message keeps its own)
                last_due = due if due is not None else last_due
                if isinstance(img, _Grabbed):   # decoded when due, if no newer frame is (the next one's due time)
                    rate = p.rate or self.source.native_rate
                    img.next_due = offset + (k + 1) / rate if due is not None and rate else math.inf
                elif not isinstance(img, CorruptFrame):
                    img = self._orient(name, img)
                any_good = any_good or not isinstance(img, CorruptFrame)
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

    def _orient(self, name: str, img: np.ndarray) -> np.ndarray | CorruptFrame:
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            return CorruptFrame(name, f"not an 8-bit colour image (shape {img.shape}, {img.dtype})")
        if self.params.orientation == "portrait" and img.shape[1] > img.shape[0]:
            import cv2

            img = cv2.rotate(img, cv2.ROTATE_90_COUNTERCLOCKWISE)
        if self._shape is None:
            self._shape = img.shape
        elif img.shape != self._shape:
            return CorruptFrame(name, f"size {img.shape[0]}x{img.shape[1]} differs from the first frame's "
                                      f"{self._shape[0]}x{self._shape[1]}")
        return img

    def _decoded(self, name: str, frame: _Grabbed) -> np.ndarray | CorruptFrame:
        img = frame.image()
        return img if isinstance(img, CorruptFrame) else self._orient(name, img)

    def _report(self, err: CorruptFrame) -> None:
        """A corrupt frame: a fault, or logged and counted once (a loop meets it again on every pass; a file that
        changes, e.g. is removed, is a new report)."""
        if self.params.on_corrupt == "fault":
            self.corrupt.append(str(err))
            raise ComponentFault(f"corrupt frame {err}")
        if str(err) in self._reported:
            return
        self._reported.add(str(err))
        self.corrupt.append(str(err))
        self.ctx.log(f"replay: skipped corrupt frame {err}")

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        if self._done:
            return None
        if self._t0 is None:
            self._t0 = t
            rate = getattr(self.ctx, "rate", None)
            if self.ctx.clock_kind == "wall" and rate:
                # the tick the first step was due at, not its (late) run: a later step that ran less late missed its
                # frame by the difference, and 58 of 60 frames went out a period after their stamps
                self._t0 = min(t, math.floor(t * rate + 1e-6) / rate)
        rel = t - self._t0
        newest = None
        while True:
            if self._pending is None:
                nxt = next(self._it, None)
                if nxt is None:
                    break
                self._pending = nxt
            name, img, due = self._pending
            if not math.isnan(due) and due > rel + 1e-9:
                break
            self._pending = None
            if isinstance(img, _Grabbed):
                if img.skippable and img.next_due <= rel + 1e-9:   # a newer frame is due too: never decoded
                    self.skipped += 1
                    continue
                img = self._decoded(name, img)
            if isinstance(img, CorruptFrame):   # due now: reported (or a fault), and the next one is looked at
                self._report(img)
                continue
            if newest is not None:
                self.skipped += 1
            newest = (name, img, due)
            if math.isnan(due):  # one frame per step
                break
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
