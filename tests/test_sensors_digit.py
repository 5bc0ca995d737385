"""digit: discovery on a fake sysfs tree, the capture path on a video file source, errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from teletouch import Context, GraphValidationError, HardwareError
from teletouch.plugins.sensors import discovery
from teletouch.plugins.sensors.digit import Digit, FrameGrabber, led_command, led_value, to_portrait
from teletouch.testing import Harness, make_registry, run_yaml


def _usb_device(root: Path, name: str, vid: str, pid: str, serial: str | None, bcd: str = "0203",
                product: str = "DIGIT") -> Path:
    d = root / "devices" / "pci0000:00" / "0000:00:14.0" / "usb1" / name
    d.mkdir(parents=True)
    (d / "idVendor").write_text(vid + "\n")
    (d / "idProduct").write_text(pid + "\n")
    if serial is not None:
        (d / "serial").write_text(serial + "\n")
    (d / "bcdDevice").write_text(bcd + "\n")
    (d / "product").write_text(product + "\n")
    (d / "manufacturer").write_text("Facebook\n")
    return d


def _video_node(root: Path, dev_root: Path, usb: Path, n: int, index: int) -> None:
    intf = usb / f"{usb.name}:1.0"
    v = intf / "video4linux" / f"video{n}"
    v.mkdir(parents=True)
    (v / "index").write_text(f"{index}\n")
    (v / "name").write_text("DIGIT: DIGIT\n")
    os.symlink(os.path.relpath(intf, v), v / "device")
    cls = root / "class" / "video4linux"
    cls.mkdir(parents=True, exist_ok=True)
    os.symlink(os.path.relpath(v, cls), cls / f"video{n}")
    node = dev_root / f"video{n}"
    node.write_bytes(b"")


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
    with pytest.raises(HardwareError, match=r"DIGIT D99999 not found; connected: D20001 \(.*video2.*\), D20002"):
        with Harness(Digit, {"serial": "D99999", "sysfs_root": str(root), "dev_root": str(dev)}):
            pass
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
        setpriv = shutil.which("setpriv")
        assert setpriv, "running the tests as root needs util-linux's setpriv"
        cmd = [setpriv, "--inh-caps=-all", "--bounding-set=-dac_override,-dac_read_search"] + cmd
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert "permission denied on" in out.stdout, out.stdout + out.stderr
    assert 'ATTRS{idVendor}=="2833"' in out.stdout and "50-DIGIT.rules" in out.stdout


def test_led_value_and_params():
    assert led_value(15) == 0xFFF
    assert led_value((1, 2, 3)) == 0x123
    assert led_command((1, 2, 3), 203) == 0x123 and led_command(15, None) == 0xFFF
    assert led_command(15, 101) == 255 and led_command((1, 7, 3), 105) == 7 * 17  # old firmware: one 0..255 level
    with pytest.raises(ValueError):
        led_value(16)
    with pytest.raises(ValueError, match="0..15"):
        Digit.Params(led_intensity=[1, 2, 99])
    with pytest.raises(ValueError):
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
        time.sleep(0.1)                      # a frame is waiting, captured "during start-up"
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
    assert 8 <= len(frames) <= 30, result
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
