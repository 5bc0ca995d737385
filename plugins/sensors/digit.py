"""``digit``: the real DIGIT tactile sensor through OpenCV (V4L2 on Linux).

- Finds the sensor by serial number (or takes the only one connected) from the USB ids 2833:0209 in sysfs and pyusb
  (:mod:`.discovery`); ``source`` opens a /dev node, a video file or a URL instead, through the same capture code.
- Stream modes qvga60, qvga30 (320 x 240), vga30, vga15 (640 x 480); LED intensity 0-15 per channel, packed
  (r << 8) | (g << 4) | b and sent through CAP_PROP_ZOOM as the DIGIT firmware expects (firmware revision < 200:
  one global intensity, 17 x level).
- Orientation (the one convention of teletouch): the camera delivers landscape frames; the driver rotates them
  90 degrees counter-clockwise (transpose, then flip the rows: what digit-interface's get_frame returns), so images
  are **portrait**, QVGA 320 rows x 240 cols. Frames that are already portrait (a recorded teletouch video) are
  passed through unchanged.
- A capture thread reads continuously and keeps only the newest frame, stamped with its capture time: the V4L2
  buffer's time (CLOCK_MONOTONIC, start of exposure, via CAP_PROP_POS_MSEC) when it is plausible, else
  time.monotonic() right after the read; mapped to the graph clock. Frames the graph never took are counted as
  dropped, a frame captured during start-up, before graph time 0, or before activate() (one left from before a
  deactivate()) is not passed on (``before_start``), and a frame is published once: a step without a new frame
  publishes nothing, so the port's sample ages.
- A video file plays from its first frame: the capture thread starts reading it at activate(), during start-up; at
  the node's first step (which publishes nothing), when graph time runs, what start-up read is counted in
  ``before_start``, the file is started again at frame 0 and its first frame is held until a step takes it, so it
  is the first frame published; the pace runs from then on.
- Errors say what to do and name the DIGIT (serial and node): no DIGIT, two DIGITs and no serial, wrong serial
  (lists what is connected), permission denied (the udev rule), unplugged or re-enumerated mid-run, a failed read,
  no frame for ``frame_timeout``, a frame of another size or format than expected (the node faults; the runtime
  applies its fault policy).
- The capture is never released while the thread is inside a read (OpenCV would free the buffers under it): a read
  that outlives deactivate() releases it when it returns. OpenCV's V4L2 wait for a frame (10 s by default) is
  shortened to ``frame_timeout`` (whole seconds) through OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT unless it is set.
"""

from __future__ import annotations

import math
import os
import stat
import sys
import threading
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import Component, HardwareError, Kind, Params, Port, Sample, hookimpl
from teletouch.units import Hertz, Seconds

from . import discovery

__all__ = ["Digit", "FrameGrabber", "STREAMS", "led_value", "led_command", "to_portrait"]

#: stream mode -> (width, height, fps) as the camera sends it (landscape)
STREAMS: dict[str, tuple[int, int, int]] = {
    "qvga60": (320, 240, 60), "qvga30": (320, 240, 30), "vga30": (640, 480, 30), "vga15": (640, 480, 15),
}


def led_value(intensity: int | tuple[int, int, int] | list[int]) -> int:
    """Packed LED command: (r << 8) | (g << 4) | b, each channel 0..15."""
    if isinstance(intensity, int):
        r = g = b = intensity
    else:
        r, g, b = intensity
    for c in (r, g, b):
        if not (isinstance(c, (int, np.integer)) and 0 <= c <= 15):
            raise ValueError(f"LED intensity must be 0..15 per channel, got {intensity!r}")
    return (int(r) << 8) | (int(g) << 4) | int(b)


def led_command(intensity: int | tuple[int, int, int] | list[int], firmware_revision: int | None) -> int:
    """The CAP_PROP_ZOOM value for an LED intensity (0..15 per channel). Firmware revision >= 200 (or unknown):
    per channel, (r << 8) | (g << 4) | b. Older firmware has one global intensity on a 0..255 scale (17 per level)
    and no per-channel control: the brightest channel is used."""
    packed = led_value(intensity)
    if firmware_revision is not None and firmware_revision < 200:
        level = max((packed >> 8) & 0xF, (packed >> 4) & 0xF, packed & 0xF)
        return level * 17
    return packed


def to_portrait(frame: np.ndarray) -> np.ndarray:
    """Rotate a landscape camera frame to the portrait convention (transpose + flip rows = 90 deg CCW)."""
    import cv2

    if frame.shape[1] > frame.shape[0]:
        return cv2.rotate(frame, cv2.ROTATE_90_COUNTERCLOCKWISE)
    return frame


class FrameGrabber:
    """Reads an opened cv2.VideoCapture in a thread and keeps the newest frame.

    ``pace`` (Hz): for files, deliver frames at this rate (a camera paces itself). ``on_eof``: what the end of a
    file means: "stop" (eof flag), "loop" (start again) or "fault" (treated like a lost device).
    ``lost`` is called after read failures and returns why the device is gone, or None.
    ``device_clock``: take the capture time from the driver's buffer stamp (V4L2: CAP_PROP_POS_MSEC, CLOCK_MONOTONIC
    in ms) when it is plausible (at most ``MAX_QUEUED`` s before the read returned, not after it); else, and always
    for files, the time.monotonic() right after the read.
    The thread owns the capture from :meth:`start` on: :meth:`release` releases it at once if the thread has ended,
    else the thread does as its current read returns (releasing under a read crashes OpenCV).
    ``start(hold_first=True)``: the first frame read is kept until :meth:`take` takes it (or :meth:`stop`) before the
    next read, whatever the pace (a file's first frame is never dropped); the pace counts from that take.
    """

    MAX_FAILURES = 10
    MAX_QUEUED = 10.0

    def __init__(self, cap: Any, name: str, *, is_file: bool = False, pace: float | None = None,
                 on_eof: str = "stop", lost: Any = None, device_clock: bool = False):
        self.cap = cap
        self.name = name
        self.is_file = is_file
        self.pace = pace
        self.on_eof = on_eof
        self.lost = lost or (lambda: None)
        self.device_clock = device_clock
        self._lock = threading.Lock()
        self._latest: tuple[np.ndarray, float, int] | None = None
        self._taken_seq = 0
        self.seq = 0
        self.dropped = 0
        self.error: str | None = None
        self.eof = False
        self.last_received: float | None = None  # time.monotonic() when the newest frame arrived (taken or not)
        self.read_time = 0.0  # total seconds spent in read + rotate (benchmark)
        self._last_stamp = -math.inf
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cap_lock = threading.Lock()
        self._running = False          # the thread is in its loop (under _cap_lock with the next two)
        self._release_on_exit = False
        self._released = False
        self._hold_first = False
        self._first_taken = threading.Event()   # set by take() and by stop(): the held first frame may go

    def start(self, hold_first: bool = False) -> None:
        if self._thread is not None and self._thread.is_alive():
            raise HardwareError(f"{self.name}: the capture thread of the previous activation is still blocked in a "
                                f"read; unplug and replug the DIGIT")
        self._stop.clear()
        self._hold_first = hold_first
        self._first_taken.clear()
        self.error = None      # what ended the previous activation's thread; this one reads afresh
        self.eof = False
        with self._cap_lock:
            if self._released:
                raise HardwareError(f"{self.name}: the capture was released (closed)")
            self._running = True
        self._thread = threading.Thread(target=self._run, name=f"digit-capture-{self.name}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> bool:
        """Ask the thread to end and wait up to ``timeout`` s; whether it ended (False: it is inside a read)."""
        self._stop.set()
        self._first_taken.set()
        th = self._thread
        if th is not None:
            th.join(timeout)
            if th.is_alive():
                return False
            self._thread = None
        return True

    def release(self) -> None:
        """Release the capture: now if the thread is not reading, else by the thread when its read returns."""
        with self._cap_lock:
            if self._released:
                return
            if self._running:
                self._release_on_exit = True
                return
            self._release_now()

    def _release_now(self) -> None:   # with _cap_lock held
        self._released = True
        try:
            self.cap.release()
        except Exception:
            pass

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def take(self) -> tuple[np.ndarray, float, int] | None:
        """The newest frame (image, monotonic capture time, sequence number) if it is new since the last take."""
        with self._lock:
            latest = self._latest
            if latest is None or latest[2] == self._taken_seq:
                return None
            self._taken_seq = latest[2]
        if not self._first_taken.is_set():
            self._first_taken.set()
        return latest

    def restart_counts(self) -> int:
        """Forget the frames read so far (the thread has ended: :meth:`stop` returned True); the counts (``seq``,
        ``dropped``, ``read_time``) start again. Returns how many frames had been read."""
        with self._lock:
            n = self.seq
            self._latest = None
            self._taken_seq = self.seq = self.dropped = 0
            self.last_received = None
            self.read_time = 0.0
        return n

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:   # a read that raises (an OpenCV error on a vanished device), a frame it cannot turn
            self.error = f"{self.name}: capture failed: {type(exc).__name__}: {exc}; check the USB cable and `dmesg`"
        finally:
            with self._cap_lock:
                self._running = False
                if self._release_on_exit:
                    self._release_now()

    def _stamp(self, received: float) -> float:
        stamp = received
        if self.device_clock:
            import cv2

            try:
                ms = float(self.cap.get(cv2.CAP_PROP_POS_MSEC))
            except Exception:
                ms = math.nan
            t = ms * 1e-3
            if math.isfinite(t) and received - self.MAX_QUEUED <= t <= received:
                stamp = t
        stamp = max(stamp, self._last_stamp)   # never backwards
        self._last_stamp = stamp
        return stamp

    def _loop(self) -> None:
        import cv2

        failures = 0
        next_t = time.monotonic()
        while not self._stop.is_set():
            t0 = time.perf_counter()
            ok, frame = self.cap.read()
            received = time.monotonic()
            if not ok or frame is None:
                if self.is_file and self.on_eof != "fault":
                    if self.on_eof == "loop" and self.seq > 0:
                        self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                        failures += 1
                        if failures <= 2:
                            continue
                    self.eof = True
                    return
                if self._stop.is_set():
                    return
                failures += 1
                reason = self.lost()
                if reason or failures >= self.MAX_FAILURES or self.is_file:
                    self.error = reason or (
                        f"{self.name}: end of the file (on_eof: fault)" if self.is_file else
                        f"{self.name}: the camera stopped delivering frames ({failures} failed reads); "
                        f"check the USB cable and `dmesg`")
                    return
                time.sleep(0.01)
                continue
            failures = 0
            stamp = self._stamp(received)
            if isinstance(frame, np.ndarray) and frame.ndim >= 2:
                frame = to_portrait(frame)
            self.read_time += time.perf_counter() - t0
            with self._lock:
                self.seq += 1
                if self._latest is not None and self._latest[2] != self._taken_seq:
                    self.dropped += 1
                self._latest = (frame, stamp, self.seq)
                self.last_received = received
            if self._hold_first:
                self._hold_first = False
                self._first_taken.wait()    # until a step took it (or stop()): no later frame overwrites it
                next_t = time.monotonic()   # the pace counts from there
            if self.pace:
                next_t = max(next_t + 1.0 / self.pace, time.monotonic() - 1.0 / self.pace)
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)


#: seconds a camera may take to send its first frame after activate, on top of frame_timeout
FIRST_FRAME_GRACE = 2.0


def _led_param(v: Any) -> Any:
    def is_int(c: Any) -> bool:
        return isinstance(c, (int, np.integer)) and not isinstance(c, (bool, np.bool_))

    if not (is_int(v) or (isinstance(v, (list, tuple)) and len(v) == 3 and all(is_int(c) for c in v))):
        raise ValueError(f"LED intensity: expected 0..15 or [r, g, b] with each channel 0..15, got {v!r}")
    led_value(v if is_int(v) else tuple(v))
    return v


def _describe_frame(frame: Any) -> str:
    if not isinstance(frame, np.ndarray):
        return f"a {type(frame).__name__}"
    if frame.ndim == 2:
        return f"{frame.shape[0]} rows x {frame.shape[1]} cols x 1 {frame.dtype}"
    if frame.ndim == 3:
        return f"{frame.shape[0]} rows x {frame.shape[1]} cols x {frame.shape[2]} {frame.dtype}"
    return f"an array of shape {frame.shape} {frame.dtype}"


class Digit(Component):
    """DIGIT tactile sensor (OpenCV/V4L2): newest frame, capture stamps, serial-number discovery."""

    name = "digit"
    kind = Kind.SENSOR
    default_rate = 60.0
    requires_wall_clock = True
    outputs = {"image": Port("uint8", (None, None, 3), "", "BGR, portrait (QVGA 320x240, VGA 640x480); "
                             "stamp = capture time")}

    class Params(Params):
        serial: str | None = Field(None, description="DIGIT serial number (on its back, e.g. D20001); "
                                   "None: the only one connected")
        source: str | None = Field(None, description="open this instead of discovering: /dev/videoN, a video "
                                   "file or a URL")
        stream: Literal["qvga60", "qvga30", "vga30", "vga15"] = Field("qvga60", description="resolution and fps")
        led_intensity: int | tuple[int, int, int] = Field(15, description="LED intensity 0..15 (or [r, g, b])")
        frame_timeout: Seconds = Field(1.0, gt=0, description="fault if no frame arrives for this long (at least "
                                       "two frame periods)", json_schema_extra={"unit": "s"})
        source_rate: Hertz | None = Field(None, gt=0, description="for file sources: play at this rate "
                                          "(default: the file's fps)", json_schema_extra={"unit": "Hz"})
        on_eof: Literal["stop", "loop", "fault"] = Field("stop", description="end of a file source: stop the run, "
                                                         "loop, or fault like an unplugged sensor")
        check_resolution: bool = Field(True, description="fault if the camera does not deliver the stream's size "
                                       "and fps (false: any size and fps, but the size must not change mid-run)")
        sysfs_root: str = Field("/sys", description="sysfs root for discovery (tests use a fake tree)")
        dev_root: str = Field("/dev", description="device root for discovery")

        @field_validator("led_intensity", mode="before")
        @classmethod
        def _led(cls, v: Any) -> Any:
            return _led_param(v)

        @model_validator(mode="after")
        def _timeout(self) -> "Digit.Params":
            # the camera's frame period (a /dev node or a discovered DIGIT), and a file source's pace if given
            rates = []
            if self.source is None or self.source.startswith("/dev/"):
                rates.append((STREAMS[self.stream][2], f"stream {self.stream}"))
            if self.source_rate is not None:
                rates.append((self.source_rate, f"source_rate {self.source_rate:g} Hz"))
            for fps, what in rates:
                if self.frame_timeout < 2.0 / fps:
                    raise ValueError(f"frame_timeout: {self.frame_timeout:g} s is shorter than two frame periods of "
                                     f"{what} ({fps:g} fps): expected at least {2.0 / fps:.3f} s")
            return self

    @classmethod
    def port_shapes(cls, params: Any) -> dict[str, tuple]:
        """A camera (a discovered DIGIT or a /dev node) with ``check_resolution`` gives the stream's size, portrait
        rows x cols after the driver's turn (the camera's width is the rows): checked against a consumer's (a depth
        model's) when the graph is validated. A video file or a URL gives its first frame's size: not known here."""
        if not params.check_resolution or (params.source is not None and not _is_char_device(params.source)):
            return {}
        rows, cols, _ = STREAMS[params.stream]
        sizes: dict[tuple[int, int], list[str]] = {}
        for name, (w, h, _) in STREAMS.items():
            sizes.setdefault((w, h), []).append(name)
        how = "set stream: " + ", ".join(f"{' or '.join(names)} ({w}x{h})" for (w, h), names in sizes.items())
        return {"image": ((rows, cols, 3), f"stream {params.stream!r}", how)}

    def configure(self) -> None:
        import cv2

        p = self.params
        self.info: discovery.DigitInfo | None = None
        self.cap = None
        width, height, fps = STREAMS[p.stream]
        self.is_file = False
        if p.source is not None:
            path = p.source
            is_device = _is_char_device(path)
            self.is_file = not is_device and "://" not in path
            if self.is_file and not os.path.exists(path):
                raise HardwareError(f"source {path!r} does not exist (expected a /dev/videoN node, a video file "
                                    f"or a URL)")
        else:
            self._scan_problems: list[str] = []
            digits = discovery.find_digits(p.sysfs_root, p.dev_root, problems=self._scan_problems)
            self.info = self._choose(digits)
            path = self.info.path or ""
            is_device = True
        self.path = path
        if self.info is not None:
            self.who = f"DIGIT {self.info.serial} ({path})"
        else:
            self.who = f"camera {path}" if is_device else f"source {path}"
        if is_device:
            _check_access(path, p.sysfs_root)
        v4l2 = is_device and sys.platform.startswith("linux")
        if v4l2:
            # OpenCV's V4L2 capture waits up to OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT s (10 by default, read once per
            # process) for each frame; a shorter wait lets the capture thread see a stop soon after the camera
            # stops sending
            os.environ.setdefault("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", str(max(1, math.ceil(p.frame_timeout))))
        api = cv2.CAP_V4L2 if v4l2 else cv2.CAP_ANY
        cap = cv2.VideoCapture(path, api)
        if not cap.isOpened():
            cap.release()
            raise HardwareError(f"cannot open {path!r} with OpenCV: "
                                + ("is another program using the DIGIT? unplug and replug it"
                                   if is_device else "not a readable video file or stream"))
        self.cap = cap
        rev = self.info.firmware_revision if self.info is not None else None
        self.led = led_command(p.led_intensity, rev)
        if rev is not None and rev < 200 and not isinstance(p.led_intensity, int) \
                and len(set(p.led_intensity)) > 1:
            self.ctx.log(f"DIGIT {self.info.serial}: firmware {self.info.firmware} has no per-channel LED control; "
                         f"using one intensity (update the DIGIT firmware)")
        if is_device:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            cap.set(cv2.CAP_PROP_FPS, fps)
            cap.set(cv2.CAP_PROP_ZOOM, self.led)
            got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if p.check_resolution and got != (width, height):
                cap.release()
                self.cap = None
                raise HardwareError(f"{self.who}: asked for {width}x{height} ({p.stream}) but the camera gives "
                                    f"{got[0]}x{got[1]}; is this a DIGIT?")
            # V4L2 (VIDIOC_S_PARM) snaps a frame rate the format does not offer to one it does, without an error;
            # OpenCV reports the rate in use (VIDIOC_G_PARM; -1 or 0 when the driver cannot tell)
            got_fps = float(cap.get(cv2.CAP_PROP_FPS))
            if math.isfinite(got_fps) and got_fps > 0 and not math.isclose(got_fps, fps, rel_tol=0.02):
                if p.check_resolution:
                    cap.release()
                    self.cap = None
                    raise HardwareError(f"{self.who}: asked for {fps} fps ({p.stream}) but the camera gives "
                                        f"{got_fps:g} fps; is this a DIGIT? (check_resolution: false accepts it)")
                self.ctx.log(f"{self.who}: asked for {fps} fps ({p.stream}) but the camera gives {got_fps:g} fps")
                fps = got_fps
        pace = None
        if self.is_file:
            pace = p.source_rate or (cap.get(cv2.CAP_PROP_FPS) or fps)
        # what every frame must be (portrait rows x cols); None: the first frame's size, kept for the run
        self._expect: tuple[int, int] | None = (width, height) if is_device and p.check_resolution else None
        self._expect_why = f"BGR portrait of stream {p.stream}" if self._expect else ""
        self._pace_text = (f"{fps:g} fps, stream {p.stream}" if is_device else
                           f"{pace:g} fps" if pace else "a continuous stream")
        self.grabber = FrameGrabber(cap, self.who, is_file=self.is_file, pace=pace, on_eof=p.on_eof,
                                    lost=self._lost, device_clock=v4l2)
        self.frames = 0
        self.before_start = 0   # frames captured before graph time 0, not passed on
        # a file source plays from its first frame, started again at the node's first step (see _play_from_start)
        self._from_start = self.is_file
        self._last_frame_mono = 0.0
        self._t_first: float | None = None
        self._activated = time.monotonic()

    def _choose(self, digits: list[discovery.DigitInfo]) -> discovery.DigitInfo:
        p = self.params
        with_node = [d for d in digits if d.path]
        if p.serial is not None:
            match = [d for d in digits if d.serial == p.serial]
            if not match:
                scan = getattr(self, "_scan_problems", [])
                raise HardwareError(f"DIGIT {p.serial} not found; connected: {discovery.describe(digits)}; plug it in "
                                    f"with a USB 2.0 data cable, or set serial to one connected (`teletouch devices` "
                                    f"lists what is seen, with the serial of each)" + "".join(f"; {s}" for s in scan))
            if len(match) > 1:
                raise HardwareError(f"serial: {len(match)} DIGITs report serial {p.serial}: "
                                    f"{discovery.describe(match)}; connect only the one this node reads, or open it "
                                    f"by its node with source: /dev/videoN")
            d = match[0]
            if not d.path:
                raise HardwareError(f"DIGIT {p.serial} is on USB but has no video node "
                                    f"({'DFU mode: flash its firmware' if d.mode == 'dfu' else 'is uvcvideo loaded?'})")
            return d
        if not with_node:
            extra = ""
            if digits:
                extra = f"; seen on USB without a video node: {discovery.describe(digits)}"
                if any(d.readable is False for d in digits):
                    extra += f"; USB access is denied: {discovery.UDEV_HINT}"
            scan = getattr(self, "_scan_problems", [])
            if scan:   # the USB scan could not run: a DIGIT in DFU mode or without uvcvideo would not show
                extra += "; " + "; ".join(scan)
            raise HardwareError("no DIGIT found (USB 2833:0209 with a video4linux node): plug it in with a USB 2.0 "
                                "data cable; `teletouch devices` lists what is seen" + extra)
        if len(with_node) > 1:
            # which one enumerates first can change from one boot (or replug) to the next: never guess
            raise HardwareError(f"serial: {len(with_node)} DIGITs are connected: {discovery.describe(with_node)}; "
                                f"set serial to the one this node reads (None takes a DIGIT only when it is the "
                                f"only one)")
        return with_node[0]

    def _lost(self) -> str | None:
        """Why reads fail, if the DIGIT (or file) is gone or moved; None if it looks present."""
        gone = not os.path.exists(self.path)
        if self.info is not None:
            try:
                paths = [d.path for d in discovery.scan_sysfs(self.params.sysfs_root, self.params.dev_root,
                                                              check_access=False) if d.serial == self.info.serial]
            except Exception:
                paths = None
            if paths is not None:
                if paths and self.path not in paths:
                    return (f"{self.who} re-enumerated on USB mid-run (a USB reset or a loose cable) and is now "
                            f"{paths[0]}; the run cannot follow it: restart the run, and check the cable and `dmesg`")
                gone = gone or not paths
            return f"{self.who} was unplugged or removed mid-run" if gone else None
        if gone and (self.is_file or _is_char_device(self.path)):
            return f"the {self.who} was unplugged or removed mid-run"
        return None

    def activate(self) -> None:
        self._activated = time.monotonic()
        self.grabber.start()

    def _check_frame(self, frame: Any) -> None:
        exp = self._expect
        if isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3 \
                and (exp is None or frame.shape[:2] == exp):
            if exp is None:
                self._expect = (frame.shape[0], frame.shape[1])
                self._expect_why = "the size of the first frame"
            return
        if exp is None:
            want = "an 8-bit BGR image (rows x cols x 3 uint8)"
        else:
            want = f"{exp[0]} rows x {exp[1]} cols x 3 uint8 ({self._expect_why})"
        colour = isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
        if self.frames or self.before_start:
            hint = ("the stream changed mid-run (a USB re-enumeration, another program changing the V4L2 format, or "
                    "a glitch of the camera); check `dmesg` and restart the run")
        elif colour:
            hint = "is this a DIGIT? (check_resolution: false accepts another size)"
        else:
            hint = "is this a DIGIT, in a colour format OpenCV converts to BGR?"
        raise HardwareError(f"{self.who}: a frame of {_describe_frame(frame)} instead of {want}: {hint}")

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        g = self.grabber
        if self._from_start:
            self._from_start = False
            self._play_from_start()
            return None
        got = g.take()
        if got is None:
            if g.error:
                raise HardwareError(g.error)
            if g.eof:
                self.ctx.request_stop(f"end of video source {self.path}")
                return None
            # liveness counts every frame the camera delivered, also the ones never taken (start-up)
            now = time.monotonic()
            last = g.last_received
            if last is None or last < self._activated:
                since, limit = self._activated, self.params.frame_timeout + FIRST_FRAME_GRACE  # the first frame
            else:
                since, limit = last, self.params.frame_timeout
            if now - since > limit:
                reason = self._lost()
                raise HardwareError(reason or f"{self.who}: no frame for {now - since:.2f} s (frame_timeout "
                                    f"{self.params.frame_timeout:g} s; expected {self._pace_text}); check the "
                                    f"USB cable and `dmesg`")
            return None
        frame, stamp, _ = got
        self._check_frame(frame)
        if stamp < self._activated:
            # captured before this activate(): left over from before a deactivate(), or a buffer the driver filled
            # while no one read; older than this activation, so not its sample (counted with before_start)
            self.before_start += 1
            return None
        t_cap = self.ctx.from_monotonic(stamp)
        if t_cap < 0.0:
            # captured during start-up, before graph time 0 (the capture thread starts at activate): older than the
            # run, so not its first sample; the next frame follows within a frame period
            self.before_start += 1
            return None
        self.frames += 1
        self._last_frame_mono = stamp
        if self._t_first is None:
            self._t_first = stamp
        return {"image": Sample(frame, t_cap)}

    def _play_from_start(self) -> None:
        """A file source's first step: the graph's clock runs. The frames the capture thread read during start-up
        (it starts at activate(), before graph time 0; a long start-up may have read many, or the whole file) are
        older than the run: they are counted in ``before_start`` and the file is played again from frame 0, its
        first frame held until a step takes it, so it is the first frame published."""
        import cv2

        g = self.grabber
        if not g.stop(timeout=1.0):
            raise HardwareError(f"{self.who}: the capture thread has been inside one read of the file for more than "
                                f"1 s: the file cannot be played from its first frame (a slow or stalled disk?)")
        self.before_start += g.restart_counts()
        try:
            rewound = bool(g.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)) and g.cap.get(cv2.CAP_PROP_POS_FRAMES) == 0
        except Exception:
            rewound = False
        if not rewound:   # a container that does not seek: open the file again (the thread has ended)
            cap = cv2.VideoCapture(self.path, cv2.CAP_ANY)
            if not cap.isOpened():
                cap.release()
                raise HardwareError(self._lost() or f"{self.who}: cannot play the file from its first frame (it "
                                                    f"does not seek to frame 0 and cannot be opened again)")
            g.cap.release()
            g.cap = self.cap = cap
        # the first frame is due from now (the first-frame grace of frame_timeout counts from here)
        self._activated = time.monotonic()
        g.start(hold_first=True)

    def deactivate(self) -> None:
        g = getattr(self, "grabber", None)
        if g is not None and not g.stop(timeout=1.0):
            self.ctx.log(f"{self.who}: the capture thread is still inside a read; the camera is released when the "
                         f"read returns")

    def close(self) -> None:
        g = getattr(self, "grabber", None)
        if g is not None:
            g.stop(timeout=0.2)
            g.release()     # now, or by the capture thread when its read returns: never under a read
        else:
            cap = getattr(self, "cap", None)
            if cap is not None:
                cap.release()
        self.cap = None

    def status(self) -> dict[str, Any]:
        g = getattr(self, "grabber", None)
        if g is None:
            return {}
        span = (self._last_frame_mono - self._t_first) if self._t_first is not None else 0.0
        return {"frames": self.frames, "captured": g.seq, "dropped": g.dropped,
                "before_start": self.before_start,
                "frame_rate_hz": (self.frames - 1) / span if span > 0 else 0.0}


def _is_char_device(path: str) -> bool:
    try:
        return stat.S_ISCHR(os.stat(path).st_mode)
    except OSError:
        return path.startswith("/dev/")


def _check_access(path: str, sysfs_root: str = "/sys") -> None:
    """Refuse a video node that cannot be opened as OpenCV opens it (discovery.check_node), saying what its errno
    means: permission (the udev rule; in a container, the device passed in), busy, or gone."""
    if not path:
        raise HardwareError("DIGIT has no video node")
    if not os.path.lexists(path):
        raise HardwareError(f"{path} does not exist: is the DIGIT plugged in?")
    acc = discovery.check_node(path, sysfs_root=sysfs_root)
    if acc.errno is not None:
        raise HardwareError(acc.problem(discovery.UDEV_HINT))


@hookimpl
def teletouch_components():
    return [Digit]


@hookimpl
def teletouch_discover_devices():
    root = os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys")
    dev = os.environ.get("TELETOUCH_DEV_ROOT", "/dev")
    return discovery.discover(root, dev)   # never raises: a source it could not read is an error row
