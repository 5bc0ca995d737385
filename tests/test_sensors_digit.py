"""digit: discovery on a fake sysfs tree, the capture path on a video file source, errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes import digit_sysfs  # noqa: E402
from helpers_permissions import without_dac  # noqa: E402

from teletouch import Context, GraphValidationError, HardwareError
from teletouch.plugins.sensors import discovery
from teletouch.plugins.sensors.digit import Digit, FrameGrabber, led_command, led_value, to_portrait
from teletouch.testing import Harness, make_registry, run_yaml


def _usb_device(root: Path, name: str, vid: str, pid: str, serial: str | None, bcd: str = "0203",
                product: str = "DIGIT") -> Path:
    return digit_sysfs.usb_device(root, name, serial, vid=vid, pid=pid, bcd=bcd, product=product,
                                  manufacturer="Facebook")


_video_node = digit_sysfs.video_node


@pytest.fixture()
def fake_sys(tmp_path):
    """Two DIGITs (capture + metadata node each) and a webcam, as Linux lays them out in sysfs."""
    root, dev = tmp_path / "sys", tmp_path / "dev"
    dev.mkdir()
    webcam = _usb_device(root, "1-3", "046d", "0825", "ABCDEF", product="Webcam C270")
    _video_node(root, dev, webcam, 0, 0)
    _video_node(root, dev, webcam, 1, 1)
    a = _usb_device(root, "1-1", "2833", "0209", "D20001", bcd="0203")
    _video_node(root, dev, a, 2, 0)
    _video_node(root, dev, a, 3, 1)
    b = _usb_device(root, "1-2", "2833", "0209", "D20002", bcd="0105")
    _video_node(root, dev, b, 11, 1)  # metadata node numbered before the capture node
    _video_node(root, dev, b, 12, 0)
    return root, dev


def test_discovery_on_fake_sysfs(fake_sys):
    root, dev = fake_sys
    found = discovery.find_digits(root, dev, usb_find=None)
    assert [(d.serial, d.path) for d in found] == [("D20001", str(dev / "video2")), ("D20002", str(dev / "video12"))]
    a = found[0]
    assert a.firmware == "0203" and a.firmware_revision == 203 and a.usb_path == "1-1" and a.product == "DIGIT"
    entry = a.as_device()
    assert entry["kind"] == "digit" and entry["id"] == "D20001" and entry["details"]["firmware"] == "0203"
    # an empty or missing tree is not an error
    assert discovery.find_digits(root / "nothing", dev, usb_find=None) == []


def test_discovery_merges_pyusb(fake_sys):
    root, dev = fake_sys

    def bad_serial():
        raise ValueError("The device has no langid (permission)")

    usb_devs = [
        SimpleNamespace(idVendor=0x2833, idProduct=0x0209, serial_number="D20001", bus=1, address=5, bcdDevice=0x203),
        SimpleNamespace(idVendor=0x0403, idProduct=0x0FDE, serial_number="D29999", bus=1, address=9, bcdDevice=1),
    ]
    found = discovery.find_digits(root, dev, usb_find=lambda: usb_devs)
    assert [d.serial for d in found] == ["D20001", "D20002", "D29999"]
    assert found[2].mode == "dfu" and found[2].path is None
    assert "DFU mode" in discovery.describe(found)
    # serial_number raises like pyusb's without permission to read the device's strings
    locked = type("Dev", (), {"idVendor": 0x2833, "idProduct": 0x0209, "bus": 2, "address": 3, "bcdDevice": 0x203,
                              "serial_number": property(lambda self: bad_serial())})()
    only_usb = discovery.find_digits(root / "none", dev, usb_find=lambda: [locked])
    assert len(only_usb) == 1 and only_usb[0].readable is False and only_usb[0].path is None


def test_digit_errors_no_device_and_wrong_serial(fake_sys, tmp_path):
    root, dev = fake_sys
    empty = tmp_path / "empty_sys"
    empty.mkdir()
    with pytest.raises(HardwareError, match="no DIGIT found"):
        with Harness(Digit, {"sysfs_root": str(empty), "dev_root": str(dev)}):
            pass
    with pytest.raises(HardwareError, match=r"DIGIT D99999 not found; connected: D20001 \(.*video2.*\), D20002") as e:
        with Harness(Digit, {"serial": "D99999", "sysfs_root": str(root), "dev_root": str(dev)}):
            pass
    # what to do, as the path without a serial says it (the audit: "connected: none" and nothing else)
    assert "USB 2.0 data cable" in str(e.value) and "`teletouch devices`" in str(e.value), e.value
    # the right serial reaches OpenCV, which cannot open our fake (regular-file) node: a clear error
    with pytest.raises(HardwareError, match="cannot open .*video12"):
        with Harness(Digit, {"serial": "D20002", "sysfs_root": str(root), "dev_root": str(dev)}):
            pass
    # node listed in sysfs but gone from /dev
    (dev / "video2").unlink()
    with pytest.raises(HardwareError, match="video2 does not exist"):
        with Harness(Digit, {"serial": "D20001", "sysfs_root": str(root), "dev_root": str(dev)}):
            pass


def test_digit_permission_denied_names_the_udev_rule(fake_sys):
    root, dev = fake_sys
    node = dev / "video2"
    os.chmod(node, 0o600)
    code = textwrap.dedent(f"""
        from teletouch.testing import Harness
        from teletouch.plugins.sensors.digit import Digit
        from teletouch import Context, GraphValidationError, HardwareError
        try:
            with Harness(Digit, {{"serial": "D20001", "sysfs_root": {str(root)!r}, "dev_root": {str(dev)!r}}}):
                pass
        except HardwareError as e:
            print("ERROR:", e)
    """)
    cmd = [sys.executable, "-c", code]
    if os.geteuid() == 0:
        # root opens anything: run the driver without the capabilities that bypass file permissions
        os.chmod(node, 0o000)
    out = subprocess.run(without_dac(cmd), capture_output=True, text=True, timeout=60)
    assert "permission denied on" in out.stdout, out.stdout + out.stderr
    assert 'ATTRS{idVendor}=="2833"' in out.stdout and "50-DIGIT.rules" in out.stdout


def test_led_value_and_params():
    assert led_value(15) == 0xFFF
    assert led_value((1, 2, 3)) == 0x123
    assert led_command((1, 2, 3), 203) == 0x123 and led_command(15, None) == 0xFFF
    assert led_command(15, 101) == 255 and led_command((1, 7, 3), 105) == 7 * 17  # old firmware: one 0..255 level
    with pytest.raises(ValueError, match="LED intensity must be 0..15 per channel, got 16"):
        led_value(16)
    with pytest.raises(ValueError, match="0..15"):
        Digit.Params(led_intensity=[1, 2, 99])
    with pytest.raises(ValueError, match=r"stream\s+Input should be 'qvga60', 'qvga30', 'vga30' or 'vga15'"):
        Digit.Params(stream="vga60")


def _write_video(path: Path, n: int, size=(320, 240), fps=30.0) -> None:
    """Landscape frames as a camera sends them: frame k has a white marker at the top-left and its index encoded
    in the grey level of the right half."""
    import cv2

    w, h = size
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for k in range(n):
        f = np.full((h, w, 3), 40, np.uint8)
        f[:30, :30] = 255
        f[:, w // 2:] = 8 * k
        vw.write(f)
    vw.release()


def _frame_index(img: np.ndarray) -> int:
    # after the rotation the landscape right half is the portrait top half
    rows = img.shape[0]
    return int(round(float(img[: rows // 2 - 8, 40:].mean()) / 8))


@pytest.fixture()
def video(tmp_path):
    p = tmp_path / "digit.avi"
    _write_video(p, 24)
    return p


def test_capture_path_on_a_video_file(video):
    params = {"source": str(video), "source_rate": 120.0}
    with Harness(Digit, params) as h:
        t0 = time.monotonic()
        h.comp.ctx = Context(clock_kind="wall", from_monotonic=lambda m: m - t0)
        got = []
        deadline = time.monotonic() + 5
        while len(got) < 10 and time.monotonic() < deadline:
            out = h.comp.step(h.t, h.inputs)
            if out:
                got.append(out["image"])
            time.sleep(0.004)
        assert len(got) == 10
        img = got[0].value
        # portrait: the landscape 320x240 frame comes out 320 rows x 240 cols, its top-left corner bottom-left
        assert img.shape == (320, 240, 3) and img.dtype == np.uint8
        assert img[-10, 10].min() > 200 and img[10, 10].max() < 100 and img[-10, -10].max() < 100
        idx = [_frame_index(s.value) for s in got]
        assert idx == sorted(idx) and len(set(idx)) == len(idx)
        stamps = [s.stamp for s in got]
        assert all(b > a for a, b in zip(stamps, stamps[1:]))
        assert 0 < stamps[0] < stamps[-1] < time.monotonic() - t0
        # stamps are capture times: at 120 Hz, consecutive frames about 1/120 s apart on average
        per_frame = (stamps[-1] - stamps[0]) / (idx[-1] - idx[0])
        assert 0.7 / 120 < per_frame < 5 / 120  # paced (never faster), slower only on a loaded machine
        st = h.comp.status()
        assert st["frames"] == 10 and st["captured"] >= 10
        assert 0 < st["frame_rate_hz"] < 1000   # of the frames passed on, Hz (was "fps")


def test_slow_consumer_gets_newest_frame_and_counts_drops(video):
    with Harness(Digit, {"source": str(video), "source_rate": 200.0}) as h:
        got = []
        while h.stopped is None and len(got) < 50:
            time.sleep(0.03)  # much slower than the source
            out = h.comp.step(h.t, h.inputs)
            if out:
                got.append(_frame_index(out["image"].value))
        g = h.comp.grabber
        assert h.stopped is not None and "end of video" in h.stopped  # on_eof=stop ends the run normally
        assert g.dropped > 5
        assert len(got) + g.dropped == g.seq == 24
        assert got[-1] == 23  # the newest frame, not a queued old one


def test_loop_and_eof_fault_like_unplugged(video):
    with Harness(Digit, {"source": str(video), "source_rate": 400.0, "on_eof": "loop"}) as h:
        deadline = time.monotonic() + 5
        while h.comp.grabber.seq <= 30 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert h.comp.grabber.seq > 30 and h.comp.grabber.error is None and not h.comp.grabber.eof
    with Harness(Digit, {"source": str(video), "source_rate": 400.0, "on_eof": "fault"}) as h:
        video.unlink()  # the file goes away while it is being read, like a DIGIT pulled out of its port
        deadline = time.monotonic() + 5
        with pytest.raises(HardwareError, match="unplugged or removed mid-run"):
            while time.monotonic() < deadline:
                h.comp.step(h.t, h.inputs)
                time.sleep(0.005)


def test_frame_timeout_faults():
    class Stalled:
        def read(self):
            time.sleep(0.02)
            return False, None

    g = FrameGrabber(Stalled(), "stalled", lost=lambda: None)
    g.MAX_FAILURES = 3
    g.start()
    time.sleep(0.3)
    assert not g.alive and "stopped delivering frames" in (g.error or "")


def test_missing_source_and_unreadable_file(tmp_path):
    with pytest.raises(HardwareError, match="does not exist"):
        with Harness(Digit, {"source": str(tmp_path / "none.avi")}):
            pass
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(HardwareError, match="cannot open"):
        with Harness(Digit, {"source": str(bad)}):
            pass


def test_to_portrait_matches_transpose_then_flip():
    import cv2

    f = np.random.default_rng(0).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    assert np.array_equal(to_portrait(f), cv2.flip(cv2.transpose(f), 0))
    p = to_portrait(f)
    assert to_portrait(p) is p  # portrait frames pass unchanged


def test_frames_captured_before_graph_time_zero_are_not_passed_on(video):
    """The capture thread starts at activate, during start-up; a frame it read before the clock's origin is older
    than the run and is skipped (counted), the next one is passed on with a stamp >= 0."""
    with Harness(Digit, {"source": str(video), "source_rate": 60.0}) as h:
        deadline = time.monotonic() + 3      # a frame is waiting, captured "during start-up" (waited for: on a
        while h.comp.status()["captured"] < 1 and time.monotonic() < deadline:   # loaded machine the first read
            time.sleep(0.005)                                                   # can take longer than 0.1 s)
        t0 = time.monotonic()                # graph time 0 starts now
        h.comp.ctx = Context(clock_kind="wall", from_monotonic=lambda m: m - t0)
        assert h.comp.step(0.0, h.inputs) is None and h.comp.status()["before_start"] == 1
        got = None
        deadline = time.monotonic() + 3
        while got is None and time.monotonic() < deadline:
            time.sleep(0.005)
            got = h.comp.step(time.monotonic() - t0, h.inputs)
        assert got is not None and got["image"].stamp >= 0.0
        assert h.comp.status()["before_start"] == 1 and h.comp.status()["frames"] == 1


def test_digit_in_a_wall_clock_graph(video):
    reg = make_registry("teletouch.plugins.sensors.digit")
    text = f"""
name: digit-file
clock: wall
faults: {{max_overruns: 0}}
nodes:
  - id: digit
    plugin: digit
    rate: 60
    params: {{source: {str(video)!r}, source_rate: 30, on_eof: loop}}
"""
    frames = []
    t_wall = []
    result, rt = run_yaml(text, reg, duration=0.6,
                          taps=[lambda n, t, o: (frames.append(o["image"]), t_wall.append(t))])
    assert result.status == "ok", result.message
    # 0.6 s of a 30 fps source: about 18 frames, never more than the source gives; at least a few (a loaded 2-core
    # machine decodes fewer in the time: a count in a wall-clock window is bounded loosely from below, and overruns,
    # faults.max_overruns 0, do not end the run)
    assert 3 <= len(frames) <= 30, result
    # samples carry the capture time (graph clock), at or before the step that published them
    stamps = [f.stamp for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert all(0 <= s <= t + 1e-6 for s, t in zip(stamps, t_wall))
    assert rt.component("digit").status()["frames"] == len(frames)
    # refused under the simulated clock
    with pytest.raises(GraphValidationError, match="cannot run on the simulated clock"):
        run_yaml(text.replace("clock: wall", "clock: sim"), reg, duration=0.1)


def test_teletouch_devices_lists_fake_digits(fake_sys, monkeypatch, capsys):
    from teletouch import cli

    root, dev = fake_sys
    monkeypatch.setenv("TELETOUCH_SYSFS_ROOT", str(root))
    monkeypatch.setenv("TELETOUCH_DEV_ROOT", str(dev))
    assert cli.main(["devices", "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    digits = [d for d in found if d.get("kind") == "digit"]
    assert {d["id"] for d in digits} >= {"D20001", "D20002"}
    assert any(d["path"].endswith("video2") and d["details"]["firmware"] == "0203" for d in digits)


# ------------------------------------------------------------------ faults at the hardware boundary (a fake capture)
class FakeCamera:
    """Stands in for cv2.VideoCapture on a DIGIT's V4L2 node, the hardware boundary. ``script(cam, k)`` gives the
    k-th read's (ok, frame): it may block (a camera that stopped sending: V4L2 waits in select()) or raise.
    ``pos_msec`` is what CAP_PROP_POS_MSEC reports (V4L2: the buffer's CLOCK_MONOTONIC time, in ms; 0 before the
    first frame). It records a release() that comes while a read is in progress: OpenCV then frees the buffers the
    read is using, a crash on real hardware."""

    def __init__(self, script):
        self.script = script
        self.props: dict[int, float] = {}
        self.opened = True
        self.reads = 0
        self.in_read = 0
        self.released_during_read = False
        self.released = threading.Event()
        self.unblock = threading.Event()
        self.go = threading.Event()        # set by _wall_clock: scripts that wait on it stream from graph time 0
        self.stalled = threading.Event()
        self.pos_msec = 0.0

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        import cv2

        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.pos_msec
        return float(self.props.get(prop, 0.0))

    def read(self):
        self.in_read += 1
        try:
            k = self.reads
            self.reads += 1
            return self.script(self, k)
        finally:
            self.in_read -= 1

    def release(self):
        if self.in_read:
            self.released_during_read = True
        self.opened = False
        self.released.set()


def _landscape(k: int, size=(320, 240), channels: int | None = 3) -> np.ndarray:
    """A camera frame as the DIGIT sends it (landscape), numbered like _write_video's (see _frame_index)."""
    w, h = size
    f = np.full((h, w, 3), 40, np.uint8)
    f[:30, :30] = 255
    f[:, w // 2:] = 8 * k
    if channels is None:
        return f[:, :, 0].copy()
    if channels == 4:
        return np.dstack([f, np.full((h, w), 255, np.uint8)])
    return f


def _stall(cam):
    cam.stalled.set()
    cam.unblock.wait(30)
    return False, None


@pytest.fixture()
def fake_camera(fake_sys, monkeypatch):
    """open_digit(script, **params) -> (Harness, FakeCamera): the real driver, discovery on the fake sysfs tree
    (DIGIT D20001 at <dev>/video2), with FakeCamera in place of OpenCV's capture."""
    import cv2

    root, dev = fake_sys
    made = []

    def open_digit(script, **params):
        cam = FakeCamera(script)
        made.append(cam)
        monkeypatch.setattr(cv2, "VideoCapture", lambda path, api=None: cam)
        return Harness(Digit, {"serial": "D20001", "sysfs_root": str(root), "dev_root": str(dev), **params}), cam

    yield open_digit
    for cam in made:   # no capture thread stays blocked after the test
        cam.unblock.set()


def _wall_clock(h: Harness, cam: FakeCamera | None = None) -> float:
    """Graph time 0 is now (monotonic), as the runtime's wall clock maps capture times; then ``cam.go``."""
    t0 = time.monotonic()
    h.comp.ctx = Context(clock_kind="wall", from_monotonic=lambda m: m - t0, request_stop=h._stop)
    if cam is not None:
        cam.go.set()
    return t0


def _step_until_fault(h: Harness, t0: float, limit: float = 10.0) -> tuple[list, float, BaseException | None]:
    """Step at about 200 Hz until the node raises (or ``limit`` s): the samples it published, the time it took,
    the exception."""
    got = []
    start = time.monotonic()
    while time.monotonic() - start < limit:
        try:
            out = h.comp.step(time.monotonic() - t0, h.inputs)
        except Exception as exc:
            return got, time.monotonic() - start, exc
        if out:
            got.append(out["image"])
        time.sleep(0.005)
    return got, time.monotonic() - start, None


def test_stalled_camera_faults_in_bounded_time_naming_it_and_never_republishes(fake_camera):
    """Two frames, then the camera stops sending (the read blocks, as V4L2 does): each frame is published once with
    its capture stamp, the step never blocks, and the node faults after frame_timeout naming the DIGIT, its node
    and the stream it expected."""
    def script(cam, k):
        if k < 2 and cam.go.wait(5):
            time.sleep(0.01)
            return True, _landscape(k)
        return _stall(cam)

    h, cam = fake_camera(script, frame_timeout=0.3)
    with h:
        t0 = _wall_clock(h, cam)
        got, took, exc = _step_until_fault(h, t0)
        cam.unblock.set()
    assert isinstance(exc, HardwareError), exc
    msg = str(exc)
    assert "DIGIT D20001" in msg and "video2" in msg and "no frame" in msg, msg
    assert "qvga60" in msg and "60 fps" in msg, msg       # what it expected
    assert took < 5.0                                     # frame_timeout 0.3 s; generous bound for a loaded machine
    # each frame once (the newest; a slow poll may skip one): an old frame never gets a new stamp
    idx = [_frame_index(s.value) for s in got]
    assert idx in ([0, 1], [1]), idx
    assert all(a.stamp < b.stamp for a, b in zip(got, got[1:]))


def test_shutdown_never_releases_the_camera_inside_a_blocked_read(fake_camera, monkeypatch):
    """A camera that stopped sending leaves the capture thread inside read(). deactivate/close must come back in
    bounded time and must not release the capture under that read (OpenCV would free its buffers: a segfault);
    the thread releases it when its read returns. OpenCV's V4L2 wait for a frame is bounded too (it is 10 s per
    read by default)."""
    monkeypatch.setenv("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", "x")
    monkeypatch.delenv("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT")   # (restored to unset after the test)
    h, cam = fake_camera(lambda cam, k: _stall(cam))
    h.__enter__()
    assert os.environ.get("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT") == "1"   # frame_timeout 1 s, whole seconds
    deadline = time.monotonic() + 5
    while cam.in_read == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert cam.in_read == 1
    start = time.monotonic()
    h.__exit__(None, None, None)
    assert time.monotonic() - start < 5.0
    assert not cam.released_during_read
    assert not cam.released.is_set()        # not yet: the read has not returned
    cam.unblock.set()
    assert cam.released.wait(5)             # released by the capture thread as its read returned
    assert not cam.released_during_read


def test_capture_error_in_the_reader_thread_faults_at_once_with_its_reason(fake_camera):
    """A read that raises (an OpenCV error on a vanished device) must not kill the capture thread silently (the node
    would wait for frame_timeout and then blame the cable): the node faults with the error."""
    def script(cam, k):
        if k < 2 and cam.go.wait(5):
            time.sleep(0.01)
            return True, _landscape(k)
        raise RuntimeError("VIDIOC_DQBUF: No such device")

    h, cam = fake_camera(script, frame_timeout=30.0)
    with h:
        t0 = _wall_clock(h, cam)
        got, took, exc = _step_until_fault(h, t0, limit=5.0)
    assert isinstance(exc, HardwareError), exc
    assert "DIGIT D20001" in str(exc) and "No such device" in str(exc), str(exc)
    assert took < 5.0


@pytest.mark.parametrize("bad,check_resolution", [("grey", True), ("bgra", True), ("vga", True), ("vga", False),
                                                  ("grey", False)])
def test_frame_of_another_size_or_format_mid_run_faults(fake_camera, bad, check_resolution):
    """After a USB re-enumeration or a V4L2 format change the capture may deliver frames of another size or format:
    the node faults naming the DIGIT and what it expected, and never publishes such a frame (with check_resolution
    false the size is free, but it must not change mid-run)."""
    frames = {"grey": _landscape(9, channels=None), "bgra": _landscape(9, channels=4),
              "vga": _landscape(9, size=(640, 480))}

    def script(cam, k):
        cam.go.wait(5)
        time.sleep(0.01)
        return True, (_landscape(k) if k < 3 else frames[bad])

    h, cam = fake_camera(script, check_resolution=check_resolution)
    with h:
        t0 = _wall_clock(h, cam)
        got, took, exc = _step_until_fault(h, t0, limit=5.0)
    assert isinstance(exc, HardwareError), exc
    msg = str(exc)
    assert "DIGIT D20001" in msg and "video2" in msg and "320 rows x 240 cols x 3" in msg, msg
    assert got and all(s.value.shape == (320, 240, 3) and s.value.dtype == np.uint8 for s in got)


def test_frames_during_a_long_start_up_keep_the_camera_alive(fake_camera):
    """The capture starts at activate; the rest of the graph may take seconds more to start (models, other devices).
    The camera streamed all along: the first step drops the frame captured before graph time 0 and the next step,
    with no newer frame yet, must not call the camera dead."""
    streaming = threading.Event()
    streaming.set()

    def script(cam, k):
        if not streaming.is_set():
            return _stall(cam)
        time.sleep(0.02)   # 50 fps
        return True, _landscape(k % 20)

    h, cam = fake_camera(script, frame_timeout=0.5)
    with h:
        time.sleep(2.6)                  # the rest of the graph starts up (longer than frame_timeout + 2 s)
        streaming.clear()
        assert cam.stalled.wait(5)       # the last frame of the stream has arrived
        t0 = _wall_clock(h)              # graph time 0
        assert h.comp.step(0.0, h.inputs) is None and h.comp.status()["before_start"] == 1
        assert h.comp.step(time.monotonic() - t0, h.inputs) is None   # no new frame yet: not a fault
        streaming.set()
        cam.unblock.set()
        got, _, exc = _step_until_fault(h, t0, limit=0.5)
        assert exc is None and got and got[0].stamp >= 0.0


def test_capture_stamp_is_the_buffer_time_when_the_driver_gives_it(fake_camera):
    """V4L2 (uvcvideo) stamps each buffer with CLOCK_MONOTONIC at the start of its exposure, and OpenCV reports it as
    CAP_PROP_POS_MSEC. A frame that waited in the driver's queue (the capture thread was late) keeps that time; an
    implausible value (another clock; 0 before the first frame) falls back to the time the read returned."""
    clocks = ["monotonic"] * 3 + ["realtime"] * 2 + ["none"] * 2
    captured: dict[int, float] = {}
    go = threading.Event()

    def script(cam, k):
        if k >= len(clocks) or not go.wait(5):
            return _stall(cam)
        go.clear()                        # one frame per frame the test took: deterministic on a loaded machine
        t = time.monotonic() - 0.040      # exposed 40 ms before the read returns (queued in the driver)
        captured[k] = t
        cam.pos_msec = {"monotonic": t * 1e3, "realtime": time.time() * 1e3, "none": 0.0}[clocks[k]]
        return True, _landscape(k)

    h, cam = fake_camera(script)
    with h:
        t0 = _wall_clock(h)
        time.sleep(0.06)     # so that the first exposure (40 ms before its read) comes after graph time 0
        go.set()
        got = []
        deadline = time.monotonic() + 10
        while len(got) < len(clocks) and time.monotonic() < deadline:
            t = time.monotonic() - t0
            out = h.comp.step(t, h.inputs)
            if out:
                got.append((t, out["image"]))
                go.set()
            time.sleep(0.002)
        cam.unblock.set()
    assert [_frame_index(s.value) for _, s in got] == list(range(len(clocks)))
    for k, (t, s) in enumerate(got):
        if clocks[k] == "monotonic":
            assert s.stamp == pytest.approx(captured[k] - t0, abs=1e-6)
        else:   # the receive time: after the exposure, not after the step
            assert captured[k] - t0 + 0.040 <= s.stamp <= t
    stamps = [s.stamp for _, s in got]
    assert stamps == sorted(stamps)


def test_two_digits_need_a_serial(fake_camera, fake_sys):
    """With two DIGITs connected, serial None would take whichever enumerated first (a finger swap between boots)."""
    root, dev = fake_sys
    h, cam = fake_camera(lambda cam, k: _stall(cam), serial=None)
    with pytest.raises(HardwareError, match=r"serial: 2 DIGITs are connected: D20001 \(.*video2.*\), D20002 \(.*"
                                            r"video12.*\); set serial"):
        with h:
            pass
    (root / "class" / "video4linux" / "video12").unlink()   # one DIGIT: serial None takes it
    (root / "class" / "video4linux" / "video11").unlink()
    h, cam = fake_camera(lambda cam, k: _stall(cam), serial=None)
    with h:
        assert h.comp.path == str(dev / "video2")
        cam.unblock.set()


def test_reenumerated_digit_is_reported_with_its_new_node(fake_camera, fake_sys):
    """A USB reset re-enumerates the DIGIT under another /dev/videoN while the old node number lives on (here: taken
    by another device). Reads fail; the fault says where the DIGIT went."""
    root, dev = fake_sys
    fail = threading.Event()

    def script(cam, k):
        cam.go.wait(5)
        time.sleep(0.01)
        if fail.is_set():
            return False, None
        return True, _landscape(k % 20)

    h, cam = fake_camera(script)
    with h:
        t0 = _wall_clock(h, cam)
        deadline = time.monotonic() + 5
        while not h.comp.step(time.monotonic() - t0, h.inputs) and time.monotonic() < deadline:
            time.sleep(0.005)
        cls = root / "class" / "video4linux"
        (cls / "video2").unlink()
        (cls / "video3").unlink()
        usb = next(root.glob("devices/*/*/usb1/1-1"))
        _video_node(root, dev, usb, 4, 0)
        fail.set()
        got, took, exc = _step_until_fault(h, t0, limit=5.0)
    assert isinstance(exc, HardwareError), exc
    assert "DIGIT D20001" in str(exc) and "re-enumerated" in str(exc) and "video4" in str(exc), str(exc)


def test_digit_bad_params_name_the_field():
    reg = make_registry("teletouch.plugins.sensors.digit")

    def errors(params):
        text = f"name: t\nclock: wall\nnodes:\n  - id: digit\n    plugin: digit\n    rate: 60\n    params: {params}\n"
        with pytest.raises(GraphValidationError) as info:
            run_yaml(text, reg, duration=0.1)
        return info.value.errors

    # [r, g, b] with a channel missing: one error on the field, not two about pydantic's union members
    errs = errors("{led_intensity: [1, 2]}")
    assert len(errs) == 1 and "led_intensity" in str(errs[0]) and "[r, g, b]" in str(errs[0]), errs
    errs = errors("{led_intensity: true}")
    assert len(errs) == 1 and "led_intensity" in str(errs[0]) and "0..15" in str(errs[0]), errs
    # a timeout shorter than two frame periods would fault on the first late frame
    errs = errors("{stream: vga15, frame_timeout: 50ms}")
    assert len(errs) == 1 and "frame_timeout" in str(errs[0]) and "vga15" in str(errs[0]) \
        and "0.133" in str(errs[0]), errs


def test_two_digits_with_the_same_serial_are_both_listed_and_refused(fake_sys):
    """Discovery kept one DIGIT per serial: a second unit reporting the same serial (a cloned or unflashed firmware)
    was invisible, and serial: D20001 opened whichever enumerated first."""
    root, dev = fake_sys
    twin = _usb_device(root, "1-4", "2833", "0209", "D20001", bcd="0203")
    _video_node(root, dev, twin, 20, 0)
    _video_node(root, dev, twin, 21, 1)
    found = discovery.find_digits(root, dev, usb_find=None)
    assert [(d.serial, Path(d.path).name) for d in found] == [("D20001", "video2"), ("D20002", "video12"),
                                                              ("D20001", "video20")]
    with pytest.raises(HardwareError, match=r"serial: 2 DIGITs report serial D20001: D20001 \(.*video2.*\), "
                                            r"D20001 \(.*video20.*\)"):
        with Harness(Digit, {"serial": "D20001", "sysfs_root": str(root), "dev_root": str(dev)}):
            pass


def test_stalled_digit_in_a_wall_clock_graph_faults_and_shuts_down_cleanly(fake_camera, fake_sys):
    """End to end under the runtime: the camera sends a few frames and stops. The run ends with a fault naming the
    DIGIT soon after frame_timeout (the rate group's thread is never held by the camera), each frame was published
    once with its capture stamp, and the shutdown did not release the capture under the blocked read."""
    root, dev = fake_sys

    def script(cam, k):
        if k < 3:
            time.sleep(0.02)
            return True, _landscape(k)
        return _stall(cam)

    _, cam = fake_camera(script)   # installs the fake capture; the graph builds its own node
    text = f"""
name: digit-stall
clock: wall
nodes:
  - id: digit
    plugin: digit
    rate: 60
    params: {{serial: D20001, sysfs_root: {str(root)!r}, dev_root: {str(dev)!r}, frame_timeout: 0.2}}
"""
    frames = []
    result, rt = run_yaml(text, make_registry("teletouch.plugins.sensors.digit"), duration=20.0,
                          taps=[lambda n, t, o: frames.append((t, o["image"]))])
    assert result.status == "fault", result.message
    assert "DIGIT D20001" in result.message and "no frame" in result.message, result.message
    assert result.wall_time < 10.0          # frame_timeout 0.2 s + start-up + a 1 s bounded shutdown
    stamps = [s.stamp for _, s in frames]
    assert len(frames) <= 3 and all(b > a for a, b in zip(stamps, stamps[1:]))
    assert all(0.0 <= s.stamp <= t for t, s in frames)
    assert not cam.released_during_read
    cam.unblock.set()
    assert cam.released.wait(5) and not cam.released_during_read


def test_a_frame_rate_the_camera_does_not_give_is_refused(fake_camera):
    """V4L2 snaps a frame rate the format does not offer to one it does (VIDIOC_S_PARM succeeds): qvga60 on a camera
    that gives 30 fps at 320x240 ran at 30 fps, unnoticed, and its faults said "expected 60 fps". The rate in use is
    read back (CAP_PROP_FPS: VIDIOC_G_PARM) and checked like the size."""
    import cv2

    def snapped(cam):
        real = cam.set

        def set_(prop, value):   # what uvcvideo does: the nearest frame interval of the format
            return real(prop, 30.0 if prop == cv2.CAP_PROP_FPS else value)
        cam.set = set_

    h, cam = fake_camera(lambda cam, k: _stall(cam))
    snapped(cam)
    with pytest.raises(HardwareError, match=r"DIGIT D20001 .*video2.*: asked for 60 fps \(qvga60\) but the camera "
                                            r"gives 30 fps"):
        with h:
            pass
    assert cam.released.is_set()
    # check_resolution false accepts it, and says what it expects
    h, cam = fake_camera(lambda cam, k: _stall(cam), check_resolution=False)
    snapped(cam)
    with h:
        assert h.comp._pace_text == "30 fps, stream qvga60"
        cam.unblock.set()


def _step_until_a_sample(h: Harness, t0: float, limit: float = 5.0) -> list:
    """Step at about 200 Hz until the node publishes (a fault raises), for at most ``limit`` s: the samples."""
    start = time.monotonic()
    while time.monotonic() - start < limit:
        out = h.comp.step(time.monotonic() - t0, h.inputs)
        if out:
            return [out["image"]]
        time.sleep(0.005)
    return []


def test_a_frame_from_before_a_reactivation_is_never_published(fake_camera):
    """deactivate() then activate() (a component may be activated again): the frame the capture thread had read but
    the graph never took, and a buffer the driver filled while no one read (V4L2 keeps its capture time), are older
    than the activation; they were published as the first samples after it."""
    streaming = threading.Event()
    streaming.set()
    queued: list[float] = []     # capture times of buffers filled while deactivated (V4L2: CLOCK_MONOTONIC, ms)

    def script(cam, k):
        if queued:
            cam.pos_msec = queued.pop() * 1e3
            return True, _landscape(19)
        if not streaming.is_set():
            return _stall(cam)
        time.sleep(0.01)
        cam.pos_msec = 0.0       # no buffer time: the receive time
        return True, _landscape(k % 10)

    h, cam = fake_camera(script, frame_timeout=10.0)   # the stream stalls after the reactivation: no fault here
    with h:
        t0 = _wall_clock(h)
        assert _step_until_a_sample(h, t0)
        g = h.comp.grabber
        deadline = time.monotonic() + 5
        while g.seq <= h.comp.frames + h.comp.before_start and time.monotonic() < deadline:
            time.sleep(0.005)   # a frame waits, not taken
        h.comp.deactivate()
        streaming.clear()
        queued.append(time.monotonic())
        time.sleep(0.05)
        t_act = time.monotonic()
        h.comp.activate()
        late, _, exc = _step_until_fault(h, t0, limit=0.3)
        deadline = time.monotonic() + 5   # a loaded machine: the capture thread may not have read the old buffer yet
        while h.comp.before_start < 2 and exc is None and time.monotonic() < deadline:
            more, _, exc = _step_until_fault(h, t0, limit=0.05)
            late += more
        assert exc is None and late == [], [s.stamp for s in late]
        assert h.comp.before_start >= 2
        streaming.set()
        cam.unblock.set()
        fresh = _step_until_a_sample(h, t0)
        assert fresh and fresh[0].stamp >= t_act - t0


def test_a_fault_of_the_previous_activation_is_not_raised_again_after_reactivation(fake_camera):
    """The capture thread's error (or end of file) belongs to the activation that read it: after deactivate() and
    activate() on a camera that delivers again, the old error faulted the node at its first step."""
    failing = threading.Event()
    failing.set()

    def script(cam, k):
        time.sleep(0.005)
        if failing.is_set():
            return False, None
        return True, _landscape(k % 10)

    h, cam = fake_camera(script)
    with h:
        t0 = _wall_clock(h)
        _, _, exc = _step_until_fault(h, t0, limit=5.0)
        assert isinstance(exc, HardwareError) and "stopped delivering frames" in str(exc), exc
        h.comp.deactivate()
        failing.clear()          # the camera delivers again
        h.comp.activate()
        assert _step_until_a_sample(h, t0)
