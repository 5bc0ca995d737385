"""``digit``: the real DIGIT tactile sensor through OpenCV (V4L2 on Linux).

- Finds the sensor by serial number (or takes the first one) from the USB ids 2833:0209 in sysfs and pyusb
  (:mod:`.discovery`); ``source`` opens a /dev node, a video file or a URL instead, through the same capture code.
- Stream modes qvga60, qvga30 (320 x 240), vga30, vga15 (640 x 480); LED intensity 0-15 per channel, packed
  (r << 8) | (g << 4) | b and sent through CAP_PROP_ZOOM as the DIGIT firmware expects (firmware revision < 200:
  one global intensity, 17 x level).
- Orientation (the one convention of teletouch): the camera delivers landscape frames; the driver rotates them
  90 degrees counter-clockwise (transpose, then flip the rows: what digit-interface's get_frame returns), so images
  are **portrait**, QVGA 320 rows x 240 cols. Frames that are already portrait (a recorded teletouch video) are
  passed through unchanged.
- A capture thread reads continuously and keeps only the newest frame, stamped with its capture time
  (time.monotonic() right after the read, mapped to the graph clock); frames the graph never took are counted as
  dropped, and a frame captured during start-up, before graph time 0, is not passed on (``before_start``).
- Errors say what to do: no DIGIT, wrong serial (lists what is connected), permission denied (the udev rule),
  unplugged mid-run or no frame for ``frame_timeout`` (the node faults; the runtime applies its fault policy).
"""

from __future__ import annotations

import os
import stat
import sys
import threading
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator

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
    """

    MAX_FAILURES = 10

    def __init__(self, cap: Any, name: str, *, is_file: bool = False, pace: float | None = None,
                 on_eof: str = "stop", lost: Any = None):
        self.cap = cap
        self.name = name
        self.is_file = is_file
        self.pace = pace
        self.on_eof = on_eof
        self.lost = lost or (lambda: None)
        self._lock = threading.Lock()
        self._latest: tuple[np.ndarray, float, int] | None = None
        self._taken_seq = 0
        self.seq = 0
        self.dropped = 0
        self.error: str | None = None
        self.eof = False
        self.read_time = 0.0  # total seconds spent in read + rotate (benchmark)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"digit-capture-{self.name}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

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
            return latest

    def _run(self) -> None:
        import cv2

        failures = 0
        next_t = time.monotonic()
        while not self._stop.is_set():
            t0 = time.perf_counter()
            ok, frame = self.cap.read()
            stamp = time.monotonic()
            if not ok or frame is None:
                if self.is_file and self.on_eof != "fault":
                    if self.on_eof == "loop" and self.seq > 0:
                        self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                        failures += 1
                        if failures <= 2:
                            continue
                    self.eof = True
                    return
                failures += 1
                reason = self.lost()
                if reason or failures >= self.MAX_FAILURES or self.is_file:
                    self.error = reason or f"{self.name}: the camera stopped delivering frames " \
                        f"({failures} failed reads); check the USB cable and `dmesg`"
                    return
                time.sleep(0.01)
                continue
            failures = 0
            frame = to_portrait(frame)
            self.read_time += time.perf_counter() - t0
            with self._lock:
                self.seq += 1
                if self._latest is not None and self._latest[2] != self._taken_seq:
                    self.dropped += 1
                self._latest = (frame, stamp, self.seq)
            if self.pace:
                next_t = max(next_t + 1.0 / self.pace, time.monotonic() - 1.0 / self.pace)
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)


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
                                   "None: the first one found")
        source: str | None = Field(None, description="open this instead of discovering: /dev/videoN, a video "
                                   "file or a URL")
        stream: Literal["qvga60", "qvga30", "vga30", "vga15"] = Field("qvga60", description="resolution and fps")
        led_intensity: int | tuple[int, int, int] = Field(15, description="LED intensity 0..15 (or [r, g, b])")
        frame_timeout: Seconds = Field(1.0, gt=0, description="fault if no frame arrives for this long",
                                       json_schema_extra={"unit": "s"})
        source_rate: Hertz | None = Field(None, gt=0, description="for file sources: play at this rate "
                                          "(default: the file's fps)", json_schema_extra={"unit": "Hz"})
        on_eof: Literal["stop", "loop", "fault"] = Field("stop", description="end of a file source: stop the run, "
                                                         "loop, or fault like an unplugged sensor")
        check_resolution: bool = Field(True, description="fault if the camera does not deliver the stream's size")
        sysfs_root: str = Field("/sys", description="sysfs root for discovery (tests use a fake tree)")
        dev_root: str = Field("/dev", description="device root for discovery")

        @field_validator("led_intensity")
        @classmethod
        def _led(cls, v: Any) -> Any:
            led_value(v)
            return v

    def configure(self) -> None:
        import cv2

        p = self.params
        self.info: discovery.DigitInfo | None = None
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
            digits = discovery.find_digits(p.sysfs_root, p.dev_root)
            self.info = self._choose(digits)
            path = self.info.path or ""
            is_device = True
        if is_device:
            _check_access(path)
        self.path = path
        api = cv2.CAP_V4L2 if is_device and sys.platform.startswith("linux") else cv2.CAP_ANY
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
                raise HardwareError(f"{path}: asked for {width}x{height} ({p.stream}) but the camera gives "
                                    f"{got[0]}x{got[1]}; is this a DIGIT?")
        self.expected_shape = (width, height) if is_device else None
        pace = None
        if self.is_file:
            pace = p.source_rate or (cap.get(cv2.CAP_PROP_FPS) or fps)
        self.grabber = FrameGrabber(cap, self.info.serial if self.info else os.path.basename(path),
                                    is_file=self.is_file, pace=pace, on_eof=p.on_eof, lost=self._lost)
        self.frames = 0
        self.before_start = 0   # frames captured before graph time 0, not passed on
        self._last_frame_mono = 0.0
        self._t_first: float | None = None

    def _choose(self, digits: list[discovery.DigitInfo]) -> discovery.DigitInfo:
        p = self.params
        with_node = [d for d in digits if d.path]
        if p.serial is not None:
            match = [d for d in digits if d.serial == p.serial]
            if not match:
                raise HardwareError(f"DIGIT {p.serial} not found; connected: {discovery.describe(digits)}")
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
            raise HardwareError("no DIGIT found (USB 2833:0209 with a video4linux node): plug it in with a USB 2.0 "
                                "data cable; `teletouch devices` lists what is seen" + extra)
        return with_node[0]

    def _lost(self) -> str | None:
        if self.info is not None or _is_char_device(self.path) or self.is_file:
            if not os.path.exists(self.path):
                who = f"DIGIT {self.info.serial}" if self.info else "the source"
                return f"{who} ({self.path}) was unplugged or removed mid-run"
        return None

    def activate(self) -> None:
        self._last_frame_mono = time.monotonic()
        self.grabber.start()

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        g = self.grabber
        got = g.take()
        now = time.monotonic()
        if got is None:
            if g.error:
                raise HardwareError(g.error)
            if g.eof:
                self.ctx.request_stop(f"end of video source {self.path}")
                return None
            # the first frame may take a moment after opening
            limit = self.params.frame_timeout + (2.0 if self.frames == 0 else 0.0)
            if now - self._last_frame_mono > limit:
                reason = self._lost()
                raise HardwareError(reason or f"no frame from {self.path} for {now - self._last_frame_mono:.2f} s "
                                    f"(frame_timeout {self.params.frame_timeout} s); check the cable and `dmesg`")
            return None
        frame, stamp, _ = got
        t_cap = self.ctx.from_monotonic(stamp)
        if t_cap < 0.0:
            # captured during start-up, before graph time 0 (the capture thread starts at activate): older than the
            # run, so not its first sample; the next frame follows within a frame period
            self.before_start += 1
            return None
        if self.expected_shape is not None and self.params.check_resolution:
            w, h = self.expected_shape
            if frame.shape[:2] != (w, h):
                raise HardwareError(f"{self.path}: frame of {frame.shape[1]}x{frame.shape[0]} (cols x rows) "
                                    f"instead of {h}x{w}: stream glitch")
        self.frames += 1
        self._last_frame_mono = stamp
        if self._t_first is None:
            self._t_first = stamp
        return {"image": Sample(frame, t_cap)}

    def deactivate(self) -> None:
        if hasattr(self, "grabber"):
            self.grabber.stop()

    def close(self) -> None:
        if hasattr(self, "grabber"):
            self.grabber.stop()
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
                "fps": (self.frames - 1) / span if span > 0 else 0.0}


def _is_char_device(path: str) -> bool:
    try:
        return stat.S_ISCHR(os.stat(path).st_mode)
    except OSError:
        return path.startswith("/dev/")


def _check_access(path: str) -> None:
    if not path:
        raise HardwareError("DIGIT has no video node")
    if not os.path.exists(path):
        raise HardwareError(f"{path} does not exist: is the DIGIT plugged in?")
    try:
        fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    except PermissionError:
        raise HardwareError(f"permission denied on {path}: {discovery.UDEV_HINT}") from None
    except OSError as e:
        raise HardwareError(f"cannot open {path}: {e.strerror}; is the DIGIT plugged in?") from None
    os.close(fd)


@hookimpl
def teletouch_components():
    return [Digit]


@hookimpl
def teletouch_discover_devices():
    root = os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys")
    dev = os.environ.get("TELETOUCH_DEV_ROOT", "/dev")
    try:
        return [d.as_device() for d in discovery.find_digits(root, dev)]
    except Exception as exc:  # never raise from discovery
        return [{"kind": "digit", "id": "", "path": "", "error": f"{type(exc).__name__}: {exc}"}]
