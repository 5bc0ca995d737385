"""digit with ``source:`` a video file: the capture thread starts at activate(), during start-up; it read the file's
first frame (and, in a long start-up, more) before graph time 0, and that frame was never published: a replayed file
lost its start. The file now plays from its first frame: at the node's first step it is started again at frame 0 and
that frame is held until a step takes it. A live camera (a /dev node) is not affected: what it captured before graph
time 0 is still older than the run."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes import digit_sysfs  # noqa: E402

from teletouch import Component, Context, Kind, Port, hookimpl  # noqa: E402
from teletouch.plugins.sensors.digit import Digit  # noqa: E402
from teletouch.testing import Harness, make_registry, run_yaml  # noqa: E402

N = 12   # frames in the file


def _level(k: int) -> int:
    return 10 + 20 * k


def _index(img: np.ndarray) -> int:
    """Which frame of the file an image is: frame k is uniformly grey at 10 + 20 k (exact with FFV1, within a level
    or two with MJPEG)."""
    k = (float(img.mean()) - 10.0) / 20.0
    assert abs(k - round(k)) < 0.2 and float(img.max()) - float(img.min()) < 8, (k, img.min(), img.max())
    return int(round(k))


@pytest.fixture()
def video(tmp_path) -> Path:
    """N landscape QVGA frames as a camera sends them, each identifiable: lossless FFV1 where OpenCV writes it."""
    import cv2

    path = tmp_path / "press.avi"
    for fourcc in ("FFV1", "MJPG"):
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (320, 240))
        if vw.isOpened():
            break
    assert vw.isOpened()
    for k in range(N):
        vw.write(np.full((240, 320, 3), _level(k), np.uint8))
    vw.release()
    cap = cv2.VideoCapture(str(path))   # the file holds what was written, in order
    got = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        got.append(_index(f))
    cap.release()
    assert got == list(range(N))
    return path


def _wall_clock(h: Harness) -> float:
    """Graph time 0 is now, as the runtime's wall clock maps capture times."""
    t0 = time.monotonic()
    h.comp.ctx = Context(clock_kind="wall", from_monotonic=lambda m: m - t0, request_stop=h._stop)
    return t0


def _play(h: Harness, t0: float, period: float, limit: float = 10.0) -> list:
    """Step every ``period`` s until the file's end stops the run: the samples published."""
    got = []
    deadline = time.monotonic() + limit
    while h.stopped is None and time.monotonic() < deadline:
        out = h.comp.step(time.monotonic() - t0, h.inputs)
        if out:
            got.append(out["image"])
        time.sleep(period)
    assert h.stopped is not None and "end of video source" in h.stopped, h.stopped
    return got


def test_the_first_frame_published_is_the_files_first_after_a_long_start_up(video):
    """Start-up takes long enough for the capture thread to read several frames (frame 0 overwritten, as it was
    dropped before): the run still starts with frame 0 and plays every frame, in order."""
    with Harness(Digit, {"source": str(video), "source_rate": 100.0}) as h:
        deadline = time.monotonic() + 5
        while h.comp.status()["captured"] < 4 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert h.comp.status()["captured"] >= 4          # frames read during start-up
        t0 = _wall_clock(h)
        got = _play(h, t0, period=0.002)
        st = h.comp.status()
    idx = [_index(s.value) for s in got]
    assert idx and idx[0] == 0, (idx, st)                 # before: the newest frame read at start-up, or later
    assert idx == sorted(idx) and len(set(idx)) == len(idx)
    # each frame of the file read once from the start of the run: published, or dropped by a late step
    assert st["captured"] == N and st["frames"] + st["dropped"] == N and st["frames"] == len(got)
    assert st["before_start"] >= 4                        # the start-up reads, not passed on
    stamps = [s.stamp for s in got]
    assert 0.0 <= stamps[0] and all(b > a for a, b in zip(stamps, stamps[1:]))
    assert got[0].value.shape == (320, 240, 3)            # portrait, as every frame


def test_the_first_frame_is_not_lost_to_a_node_slower_than_the_file(video):
    """A node stepping at 25 Hz on a file paced at 200 fps takes the newest frame and drops the others, but the
    file's first frame waits for the first step that can take it."""
    with Harness(Digit, {"source": str(video), "source_rate": 200.0}) as h:
        time.sleep(0.1)                                   # start-up: the thread reads most of the file
        t0 = _wall_clock(h)
        got = _play(h, t0, period=0.04)
        st = h.comp.status()
    idx = [_index(s.value) for s in got]
    assert idx and idx[0] == 0 and st["dropped"] > 0, (idx, st)   # before: the whole file was read at start-up
    assert st["captured"] == N and st["frames"] + st["dropped"] == N and idx[-1] == N - 1


def test_the_first_frame_when_start_up_is_short(video):
    """The first step comes at once (the first read may not even have returned): frame 0 first as well."""
    with Harness(Digit, {"source": str(video), "source_rate": 100.0}) as h:
        t0 = _wall_clock(h)
        got = _play(h, t0, period=0.002)
        st = h.comp.status()
    idx = [_index(s.value) for s in got]
    assert idx[0] == 0 and idx == sorted(idx), idx
    assert st["captured"] == N and st["frames"] + st["dropped"] == N


def test_a_file_that_does_not_seek_is_opened_again(video, monkeypatch):
    """A container (or backend) whose capture refuses CAP_PROP_POS_FRAMES: the file is opened again instead."""
    import cv2

    real = cv2.VideoCapture
    opened = []

    class NoSeek:
        def __init__(self, path, api=cv2.CAP_ANY):
            self.cap = real(path, api)
            opened.append(self)

        def set(self, prop, value):
            return False if prop == cv2.CAP_PROP_POS_FRAMES else self.cap.set(prop, value)

        def __getattr__(self, name):
            return getattr(self.cap, name)

    monkeypatch.setattr(cv2, "VideoCapture", NoSeek)
    with Harness(Digit, {"source": str(video), "source_rate": 100.0}) as h:
        deadline = time.monotonic() + 5
        while h.comp.status()["captured"] < 3 and time.monotonic() < deadline:
            time.sleep(0.005)
        t0 = _wall_clock(h)
        got = _play(h, t0, period=0.002)
        st = h.comp.status()
    idx = [_index(s.value) for s in got]
    assert len(opened) == 2 and idx and idx[0] == 0 and idx == sorted(idx), (len(opened), idx)
    assert st["captured"] == N and st["frames"] + st["dropped"] == N


class SlowStart(Component):
    """A node whose activate() takes 0.5 s (a model loading, a device homing): the digit node, activated before it,
    reads its file meanwhile."""

    name = "slow-start"
    kind = Kind.SENSOR
    default_rate = 10.0
    outputs = {"value": Port("float64", (), "", "nothing")}

    def activate(self) -> None:
        time.sleep(0.5)

    def step(self, t, inputs):
        return None


class _Plugin:
    @hookimpl
    def teletouch_components(self):
        return [SlowStart]


def test_a_wall_clock_graph_starts_the_file_at_its_first_frame(video):
    import teletouch.plugins.sensors.digit as digit_module

    reg = make_registry(digit_module, _Plugin())
    text = f"""
name: digit-file-start
clock: wall
faults: {{max_overruns: 0}}
nodes:
  - id: digit
    plugin: digit
    rate: 120
    params: {{source: {str(video)!r}, source_rate: 60, on_eof: stop}}
  - id: slow
    plugin: slow-start
"""
    frames = []
    result, rt = run_yaml(text, reg, duration=10.0, taps=[lambda n, t, o: n == "digit" and frames.append(o["image"])])
    assert "end of video source" in result.message, result
    st = rt.component("digit").status()
    idx = [_index(s.value) for s in frames]
    # before: the 0.5 s start-up read the whole file (12 frames at 60 fps) and nothing was published
    assert idx and idx[0] == 0, (idx, st)
    assert st["before_start"] >= 2, st                    # the start-up's reads, not passed on
    assert idx == sorted(idx) and len(set(idx)) == len(idx)
    assert st["captured"] == N and st["frames"] == len(frames) and st["frames"] + st["dropped"] == N
    assert frames[0].stamp >= 0.0


# --------------------------------------------------------------------------------- a live camera: as it was
class _Camera:
    """cv2.VideoCapture on a DIGIT's /dev node: frame k numbered as the file's, 100 fps; after the first 3 frames it
    sends more only once ``go`` is set."""

    def __init__(self):
        self.k = 0
        self.sets: list[int] = []
        self.go = threading.Event()

    def isOpened(self):
        return True

    def set(self, prop, value):
        self.sets.append(prop)
        return True

    def get(self, prop):
        return 0.0

    def read(self):
        time.sleep(0.01)
        if self.k >= 3:
            self.go.wait(10)
        self.k += 1
        return True, np.full((240, 320, 3), _level((self.k - 1) % N), np.uint8)

    def release(self):
        pass


def test_a_live_camera_still_skips_what_it_captured_before_graph_time_zero(tmp_path, monkeypatch):
    import cv2

    root, dev = tmp_path / "sys", tmp_path / "dev"
    dev.mkdir()
    usb = digit_sysfs.usb_device(root, "1-1", "D20001")
    digit_sysfs.video_node(root, dev, usb, 2, 0)
    cam = _Camera()
    monkeypatch.setattr(cv2, "VideoCapture", lambda path, api=None: cam)
    params = {"serial": "D20001", "sysfs_root": str(root), "dev_root": str(dev), "check_resolution": False}
    try:
        with Harness(Digit, params) as h:
            deadline = time.monotonic() + 5
            while h.comp.status()["captured"] < 3 and time.monotonic() < deadline:
                time.sleep(0.005)
            t0 = _wall_clock(h)                           # frames 0-2 were captured during start-up
            assert h.comp.step(0.0, h.inputs) is None and h.comp.status()["before_start"] == 1
            cam.go.set()
            got = None
            deadline = time.monotonic() + 5
            while got is None and time.monotonic() < deadline:
                time.sleep(0.002)
                got = h.comp.step(time.monotonic() - t0, h.inputs)
            assert got is not None and got["image"].stamp >= 0.0 and _index(got["image"].value) == 3
            assert h.comp.status()["before_start"] == 1
    finally:
        cam.go.set()
    assert cv2.CAP_PROP_POS_FRAMES not in cam.sets        # a camera is never rewound
