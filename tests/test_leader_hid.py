"""hid-leader: pure report parsers on report bytes in the devices' layouts, and the driver over hidapi's interface.

There is no HID device (and no /dev/uhid to emulate one) on CI machines, so the driver tests replace hidapi's
``enumerate``/``device`` with a fake that returns report bytes exactly as hidapi does (lists of ints)."""

from __future__ import annotations

import re
import struct

import hid
import numpy as np
import pytest

from teletouch import HardwareError
from teletouch.plugins.devices import hid_leader as hl
from teletouch.testing import Harness, make_registry, run_yaml

# ------------------------------------------------------------------------------------------------ reports
# SpaceNavigator (046d:c626), cap pushed down and slightly right: report 1 = tx, ty, tz int16 LE
SN_TRANSLATION = bytes.fromhex("01 1e00 f6ff 5e01")  # tx=30 ty=-10 tz=350
SN_ROTATION = bytes.fromhex("02 0500 0000 9cff")  # rx=5 ry=0 rz=-100
SN_BUTTON_RIGHT = bytes.fromhex("03 02")  # right button
SN_BUTTONS_NONE = bytes.fromhex("03 00")
# SpaceMouse Compact (256f:c635): report 1 carries all six axes
SMC_ALL_AXES = bytes.fromhex("01 0000 0000 a8fe 0a00 f4ff 0000")  # tz=-344 rx=10 ry=-12
# DualShock 4 over USB (report 0x01, 64 bytes): sticks centred, dpad neutral (8) + cross (0x20), R2 at 0xc0
DS4_USB = bytes.fromhex("01 80 7f 81 80 28 00 00 00 c0") + bytes(54)
DS4_USB_RELEASED = bytes.fromhex("01 80 7f 81 80 08 00 00 00 00") + bytes(54)
# DualShock 4 over Bluetooth (report 0x11): the same fields two bytes later, L2 at 0x40, L1 pressed
DS4_BT = bytes.fromhex("11 c0 00 80 80 80 80 08 01 00 40 00") + bytes(66)
# DualSense over USB (report 0x01): L2 at byte 5, R2 at 6, buttons at 8 (cross 0x20), 9 (R1 0x02)
DS_USB = bytes.fromhex("01 80 80 80 80 00 ff 12 28 02 00") + bytes(53)
DS_BT = bytes.fromhex("31 00 80 80 80 80 00 33 12 08 00 00") + bytes(66)


def test_spacemouse_reports():
    s = hl.parse_spacemouse(SN_TRANSLATION)
    assert (s.tx, s.ty, s.tz) == (30, -10, 350)
    s = hl.parse_spacemouse(SN_ROTATION, s)
    assert (s.tx, s.tz, s.rx, s.ry, s.rz) == (30, 350, 5, 0, -100)  # translation kept
    s = hl.parse_spacemouse(SN_BUTTON_RIGHT, s)
    assert s.buttons == 2 and s.tz == 350
    assert hl.parse_spacemouse(SN_BUTTONS_NONE, s).buttons == 0
    c = hl.parse_spacemouse(SMC_ALL_AXES)
    assert (c.tz, c.rx, c.ry, c.rz) == (-344, 10, -12, 0)
    # short or unknown reports change nothing
    assert hl.parse_spacemouse(bytes.fromhex("01 1e00"), s) == s
    assert hl.parse_spacemouse(bytes.fromhex("17 0102 0304 0506"), s) == s
    assert hl.parse_spacemouse(b"", s) == s
    # hidapi gives lists of ints
    assert hl.parse_spacemouse(list(SN_TRANSLATION)).tz == 350


def test_dualshock4_and_dualsense_reports():
    g = hl.parse_dualshock4(DS4_USB)
    assert g.r2 == pytest.approx(0xC0 / 255) and g.l2 == 0.0 and g.cross and not g.circle
    g = hl.parse_dualshock4(DS4_USB_RELEASED, g)
    assert g.r2 == 0.0 and not g.cross
    b = hl.parse_dualshock4(DS4_BT)
    assert b.l2 == pytest.approx(0x40 / 255) and b.r2 == 0.0 and b.l1 and not b.cross
    assert hl.parse_dualshock4(bytes.fromhex("05 ff ff"), g) == g  # output report id / short: unchanged
    d = hl.parse_dualsense(DS_USB)
    assert d.r2 == 1.0 and d.l2 == 0.0 and d.cross and d.r1
    e = hl.parse_dualsense(DS_BT)
    assert e.r2 == pytest.approx(0x33 / 255) and not e.cross


def test_generic_trigger_report():
    st = hl.GamepadState()
    r = bytes([0x03, 0x00, 0x7F, 0x04])
    g = hl.parse_generic_trigger(r, st, report_id=3, trigger_offset=2, button_offset=3, button_mask=0x04)
    assert g.r2 == pytest.approx(127 / 255) and g.cross
    assert hl.parse_generic_trigger(r, st, report_id=1, trigger_offset=2, button_offset=3, button_mask=4) == st
    assert hl.parse_generic_trigger(r, st, report_id=None, trigger_offset=9, button_offset=None,
                                    button_mask=1) == st


def test_mappings():
    assert hl.trigger_to_opening(0.0, 0.0, 0.025) == 0.025
    assert hl.trigger_to_opening(1.0, 0.002, 0.025) == pytest.approx(0.002)
    assert hl.trigger_to_opening(0.5, 0.0, 0.02) == pytest.approx(0.01)
    assert hl.trigger_to_opening(7.0, 0.0, 0.02) == 0.0  # clipped
    assert hl.deadband(0.05, 0.1) == 0.0
    assert hl.deadband(1.0, 0.1) == 1.0 and hl.deadband(-0.55, 0.1) == pytest.approx(-0.5)
    assert hl.axis_to_unit(700, 350, False) == 1.0 and hl.axis_to_unit(175, 350, True) == -0.5
    x, v = hl.integrate_rate(0.01, 1.0, 0.1, 0.05, 0.0, 0.0, 0.025)
    assert x == pytest.approx(0.015) and v == pytest.approx(0.05)
    x, v = hl.integrate_rate(0.024, 1.0, 0.1, 0.05, 0.0, 0.0, 0.025)
    assert x == 0.025 and v == 0.0


# ------------------------------------------------------------------------------------------------ driver
class FakeDevice:
    def __init__(self, backend):
        self.backend = backend
        self.opened = None

    def open_path(self, path):
        if self.backend.open_error:
            raise OSError("open failed")
        self.opened = path

    def set_nonblocking(self, v):
        self.nonblocking = v

    def read(self, n):
        if self.backend.unplugged:
            raise OSError("read error")
        return list(self.backend.reports.pop(0)[:n]) if self.backend.reports else []

    def close(self):
        self.backend.closed = True


class FakeHid:
    """hidapi's module interface: enumerate() -> dicts, device() -> an object with open_path/read/close."""

    def __init__(self, devices):
        self.devices = devices
        self.reports: list[bytes] = []
        self.open_error = False
        self.unplugged = False
        self.closed = False

    def enumerate(self, vid=0, pid=0):
        return [dict(d) for d in self.devices if (not vid or d["vendor_id"] == vid) and (not pid or
                                                                                      d["product_id"] == pid)]

    def device(self):
        return FakeDevice(self)


def info(vid, pid, path=b"/dev/hidraw7", usage_page=1, name=""):
    return {"vendor_id": vid, "product_id": pid, "path": path, "usage_page": usage_page, "usage": 8,
            "product_string": name, "serial_number": "", "interface_number": 0}


@pytest.fixture
def fake_hid(monkeypatch):
    backend = FakeHid([info(0x046D, 0xC52B, b"/dev/hidraw1", name="Unifying Receiver")])
    monkeypatch.setattr(hid, "enumerate", backend.enumerate)
    monkeypatch.setattr(hid, "device", backend.device)
    return backend


def test_no_device_is_a_clear_error(fake_hid):
    h = Harness(hl.HidLeader, {})
    with pytest.raises(HardwareError, match="no HID leader found.*among 1 HID device.*teletouch devices"):
        h.comp.configure()
    h.comp.close()
    assert hl.teletouch_discover_devices() == []


def test_not_found_does_not_blame_permissions(fake_hid):
    """The message said 'if lsusb shows it but hidapi lists nothing, it is a permission problem' and gave a udev rule;
    but hidapi lists devices without opening them (libusb/hid.c hid_enumerate lists a device whose libusb_open fails,
    without its strings; linux/hid.c reads udev and sysfs), so a missing device never is one."""
    with pytest.raises(HardwareError) as ei:
        Harness(hl.HidLeader, {}).comp.configure()
    msg = str(ei.value)
    assert "it is a permission problem" not in msg and "udev" not in msg
    assert "whether or not you may open it" in msg and "vendor_id and product_id" in msg
    with pytest.raises(HardwareError, match="compare its vendor:product id with vendor_id/product_id"):
        Harness(hl.HidLeader, {"vendor_id": 0x256F, "product_id": 0xC635}).comp.configure()


def _usb_sysfs(root, name, bus, devnum, mode=0o666):
    """A USB device folder in a fake sysfs and its node under root/dev/bus/usb."""
    d = root / "sys" / "bus" / "usb" / "devices" / name
    d.mkdir(parents=True)
    (d / "busnum").write_text(f"{bus}\n")
    (d / "devnum").write_text(f"{devnum}\n")
    node = root / "dev" / "bus" / "usb" / f"{bus:03d}" / f"{devnum:03d}"
    node.parent.mkdir(parents=True, exist_ok=True)
    node.write_bytes(b"")
    return node


def test_discovery_rows_give_params_readable_and_the_udev_rule(fake_hid, tmp_path, monkeypatch):
    """Rows had no params (which path and report format select the device in a graph) and no word on whether the
    user may open it."""
    usb_node = _usb_sysfs(tmp_path, "1-4.2", 1, 7)
    hidraw = tmp_path / "dev" / "hidraw5"
    hidraw.write_bytes(b"")
    fake_hid.devices += [info(0x256F, 0xC635, b"1-4.2:1.0"),            # libusb backend path (pip's hid module)
                         info(0x054C, 0x0CE6, str(hidraw).encode())]    # hidraw backend path
    denied = {str(usb_node)}
    monkeypatch.setattr(hl.os, "access", lambda p, mode: str(p) not in denied)   # (the tests run as root)
    rows = hl.discover(sysfs_root=str(tmp_path / "sys"), dev_root=str(tmp_path / "dev"))
    assert [(r["kind"], r["path"]) for r in rows] == [("spacemouse", "1-4.2:1.0"), ("dualsense", str(hidraw))]
    sm, ds = (r["details"] for r in rows)
    assert sm["plugin"] == ds["plugin"] == "hid-leader"
    assert sm["params"] == {"path": "1-4.2:1.0", "device": "spacemouse"}
    assert ds["params"] == {"path": str(hidraw), "device": "dualsense"}
    for d in (sm, ds):
        assert set(d["params"]) <= set(hl.HidLeader.Params.model_fields)
    assert sm["readable"] is False and sm["node"] == str(usb_node)
    assert f"permission denied on {usb_node}" in sm["problem"] and 'SUBSYSTEM=="usb", ATTRS{idVendor}=="256f"' in \
        sm["problem"]
    assert ds["readable"] is True and "problem" not in ds
    denied.add(str(hidraw))
    ds = hl.discover(sysfs_root=str(tmp_path / "sys"), dev_root=str(tmp_path / "dev"))[1]["details"]
    assert ds["readable"] is False and 'KERNEL=="hidraw*", ATTRS{idVendor}=="054c"' in ds["problem"]
    # the params select that device
    with Harness(hl.HidLeader, ds["params"]) as h:
        assert h.comp.info["path"] == str(hidraw).encode() and h.comp.profile == "dualsense"


def test_discovery_when_hidapi_fails_is_an_error_row(fake_hid, monkeypatch, tmp_path):
    """hidapi missing or failing to enumerate gave [] (the same as 'nothing plugged in')."""
    def broken(vid=0, pid=0):
        raise OSError("hid_enumerate failed")

    monkeypatch.setattr(hid, "enumerate", broken)
    rows = hl.teletouch_discover_devices()
    assert len(rows) == 1 and rows[0]["kind"] == "hid-leader" and "hid_enumerate failed" in rows[0]["error"]

    def missing():
        raise HardwareError("hidapi is not installed (No module named 'hid'): pip install hidapi")

    monkeypatch.setattr(hl, "_hid", missing)
    rows = hl.teletouch_discover_devices()
    assert len(rows) == 1 and "pip install hidapi" in rows[0]["error"]


def test_discovery_without_a_usb_device_folder_says_so(fake_hid, tmp_path):
    """hidapi (libusb) lists nothing, silently, where /dev/bus/usb is missing (a container without it)."""
    fake_hid.devices.clear()
    rows = hl.discover(dev_root=str(tmp_path))
    assert len(rows) == 1 and f"{tmp_path / 'bus' / 'usb'} does not exist" in rows[0]["error"], rows
    (tmp_path / "bus" / "usb").mkdir(parents=True)
    assert hl.discover(dev_root=str(tmp_path)) == []


def test_a_run_without_a_usb_device_folder_says_so_not_the_cable(fake_hid, tmp_path, monkeypatch):
    """The run's message blamed the cable ("among 0 HID device(s) ... check the USB cable/receiver") where
    `teletouch devices` knew the cause: no /dev/bus/usb (a container without it), so hidapi sees nothing at all."""
    fake_hid.devices.clear()
    monkeypatch.setenv("TELETOUCH_DEV_ROOT", str(tmp_path))
    with pytest.raises(HardwareError) as ei:
        Harness(hl.HidLeader, {}).comp.configure()
    msg = str(ei.value)
    assert f"{tmp_path / 'bus' / 'usb'} does not exist" in msg and "docker run -v /dev/bus/usb" in msg, msg
    assert "cable" not in msg
    (tmp_path / "bus" / "usb").mkdir(parents=True)   # USB is there, the device is not: the cable, as before
    with pytest.raises(HardwareError, match=r"among 0 HID device\(s\).*check the USB cable"):
        Harness(hl.HidLeader, {}).comp.configure()


def test_open_failure_on_a_libusb_path_names_the_usb_node_and_its_rule(fake_hid, tmp_path, monkeypatch):
    """Under the libusb backend the path is "1-4.2:1.0", not a file: a permission failure was never recognised and the
    hint gave the hidraw rule, which does not cover the USB device node that libusb opens."""
    usb_node = _usb_sysfs(tmp_path, "1-4.2", 1, 7)
    monkeypatch.setenv("TELETOUCH_SYSFS_ROOT", str(tmp_path / "sys"))
    monkeypatch.setenv("TELETOUCH_DEV_ROOT", str(tmp_path / "dev"))
    fake_hid.devices.append(info(0x256F, 0xC635, b"1-4.2:1.0"))
    fake_hid.open_error = True
    monkeypatch.setattr(hl.os, "access", lambda p, mode: False)
    with pytest.raises(HardwareError) as ei:
        Harness(hl.HidLeader, {}).comp.configure()
    msg = str(ei.value)
    assert f"permission denied opening SpaceMouse Compact (256f:c635) at 1-4.2:1.0 (device node {usb_node})" in msg
    assert 'SUBSYSTEM=="usb", ATTRS{idVendor}=="256f"' in msg


def test_permission_denied_gives_the_udev_hint(fake_hid, tmp_path, monkeypatch):
    node = tmp_path / "hidraw9"
    node.write_bytes(b"")
    fake_hid.devices.append(info(0x256F, 0xC635, str(node).encode()))
    fake_hid.open_error = True
    monkeypatch.setattr(hl.os, "access", lambda p, mode: False)  # the test runs as root: pretend it is a user
    with pytest.raises(HardwareError) as ei:
        Harness(hl.HidLeader, {}).comp.configure()
    msg = str(ei.value)
    assert "permission denied" in msg and str(node) in msg and 'ATTRS{idVendor}=="256f"' in msg
    assert "udevadm" in msg


def test_open_failure_without_a_hidraw_node_still_explains(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x09CC, b"1-4:1.3"))
    fake_hid.open_error = True
    with pytest.raises(HardwareError,
                       match=r"could not open DualShock 4 \(v2\) \(054c:09cc\) at 1-4:1.3: open failed.*spacenavd"):
        Harness(hl.HidLeader, {}).comp.configure()


def test_unknown_device_needs_the_generic_layout(fake_hid):
    with pytest.raises(HardwareError, match="not a known SpaceMouse/gamepad: set device: generic"):
        Harness(hl.HidLeader, {"vendor_id": "0x046d", "product_id": 0xC52B}).comp.configure()


def test_spacemouse_rate_control_and_button(fake_hid):
    fake_hid.devices.append(info(0x046D, 0xC626))
    assert hl.teletouch_discover_devices()[0]["kind"] == "spacemouse"
    with Harness(hl.HidLeader, {"max_speed": "20mm/s", "dead_band": 0.1}) as h:
        assert h.comp.profile == "spacemouse"
        out = h.step(0.0, gripper_force=5.0)  # ignored: position-only
        assert out["gripper_opening"] == pytest.approx(0.025)  # starts open
        pull = bytes.fromhex("01 0000 0000") + struct.pack("<h", -350)
        fake_hid.reports += [pull, SN_BUTTON_RIGHT]
        out = h.step(0.004)
        assert out["gripper_velocity"] == pytest.approx(-0.020)
        for i in range(2, 102):
            fake_hid.reports.append(pull)  # a deflected cap reports every few ms
            out = h.step(i * 0.004)
        assert out["gripper_opening"] == pytest.approx(0.025 - 0.020 * 0.400, abs=1e-9)  # from 4 ms to 404 ms
        assert out["button"] is False  # right button is bit 1; button_bit 0 (left)
        np.testing.assert_allclose(out["position"], [0.0, 0.0, -0.01])
        fake_hid.reports += [bytes.fromhex("01 0000 0000 1000")]  # inside the dead band: stops
        x = h.step(0.5)["gripper_opening"]
        assert h.step(0.6)["gripper_opening"] == x
    assert fake_hid.closed


def test_spacemouse_position_mode(fake_hid):
    fake_hid.devices.append(info(0x256F, 0xC635))
    with Harness(hl.HidLeader, {"mode": "position", "dead_band": 0.0, "button_bit": 1}) as h:
        fake_hid.reports += [b"\x01" + bytes(12), SN_BUTTON_RIGHT]
        out = h.step(0.0)
        assert out["gripper_opening"] == pytest.approx(0.0125)  # centred cap: half open
        assert out["button"] is True
        fake_hid.reports += [SMC_ALL_AXES]
        assert h.step(0.005)["gripper_opening"] == pytest.approx(0.0125 * (1 - 344 / 350))
        fake_hid.reports += [bytes.fromhex("01 0000 0000") + struct.pack("<h", 175)]
        assert h.step(0.01)["gripper_opening"] == pytest.approx(0.0125 * 1.5)


def test_dualshock_trigger_maps_to_opening(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x05C4))
    with Harness(hl.HidLeader, {"min_opening": "2mm", "max_opening": "22mm"}) as h:
        fake_hid.reports += [DS4_USB]
        out = h.step(0.0)
        assert out["gripper_opening"] == pytest.approx(0.022 - (0xC0 / 255) * 0.020)
        assert out["button"] is True and not out["position"].any()
        fake_hid.reports += [DS4_USB_RELEASED]
        out = h.step(0.1)
        assert out["gripper_opening"] == pytest.approx(0.022) and out["gripper_velocity"] > 0


def test_unplug_is_a_hardware_fault(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x0CE6))
    with Harness(hl.HidLeader, {}) as h:
        fake_hid.reports += [DS_USB]
        assert h.step(0.0)["gripper_opening"] == pytest.approx(0.0)
        fake_hid.unplugged = True
        with pytest.raises(HardwareError, match="DualSense stopped answering"):
            h.step(0.01)
        h.comp.safe_state()


def test_params_are_checked():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="integer id"):
        hl.HidLeader.Params(vendor_id="sony")
    with pytest.raises(ValidationError, match="must be above min_opening"):
        hl.HidLeader.Params(min_opening=0.02, max_opening=0.01)


# faults: no overrun faults and a watchdog of 0.5 s, not 0.1 s: on a loaded 2-core machine late steps and a stalled
# thread must not end a run whose outcome (ok, or the fault a test causes) is what the test checks
GRAPH = """
name: hid-swap
clock: wall
duration: 0.3
faults: {max_overruns: 0, watchdog: 0.5}
nodes:
  - id: force
    plugin: mock-sensor
    rate: 250
    params: {signal: constant, amplitude: 1.0}
  - id: leader
    plugin: hid-leader
    rate: 250
    params: {device: dualshock4}
    inputs: {gripper_force: force.value}
"""


def test_hid_leader_runs_in_a_graph_wired_like_omega7(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x05C4))
    fake_hid.reports += [DS4_USB] * 5
    reg = make_registry("teletouch.plugins.devices.hid_leader")
    seen: set = set()
    result, rt = run_yaml(GRAPH, reg, taps=[lambda n, t, out: n == "leader" and seen.update(out)])
    assert result.status == "ok", result.summary()
    assert seen == {"gripper_opening", "gripper_velocity", "position", "button"}
    assert rt.latest("leader", "gripper_opening").value == pytest.approx(0.025 * (1 - 0xC0 / 255))
    assert rt.latest("leader", "gripper_opening").stamp < 0.1  # the reports were read at the start: not the last step


# ------------------------------------------------------------------------------------------------ lost device, stamps
# A DualShock 4 / DualSense sends an input report every ~4 ms over USB (~100+ Hz over Bluetooth) while connected; a
# pad whose Bluetooth link drops gives no read error until the kernel removes the device, so silence is the only sign.
def _raw_step(h, t):
    """Step without the Harness unwrapping the Samples (to see the stamps)."""
    h.t = t
    return h.comp.step(t, h.inputs)


def test_silent_gamepad_faults_within_report_timeout(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x05C4))
    with Harness(hl.HidLeader, {}) as h:
        t, period = 0.0, 0.004
        for _ in range(50):  # 0.2 s of streaming
            fake_hid.reports.append(DS4_USB)
            h.step(t)
            t += period
        last_report = t - period
        with pytest.raises(HardwareError) as ei:
            while t < 5.0:  # silence: no report, no read error
                h.step(t)
                t += period
        assert 0.5 < t - last_report <= 0.5 + period + 1e-9  # within report_timeout + one step period
        msg = str(ei.value)
        assert "DualShock 4 (054c:05c4) sent no report for 0.50" in msg and "report_timeout 0.5 s" in msg
        assert h.comp.report_timeout == 0.5  # the default for a pad that reports periodically


def test_report_timeout_param_and_silence_from_the_start(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x0CE6))
    with Harness(hl.HidLeader, {"report_timeout": "100ms"}) as h:
        assert h.step(0.0) == {}  # no report yet: no sample (the initial opening was never measured)
        assert h.step(0.1) == {}
        with pytest.raises(HardwareError, match=r"DualSense .*sent no report for 0\.10[0-9] s since the run started"):
            h.step(0.104)


def test_outputs_carry_the_time_of_the_last_report(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x05C4))
    with Harness(hl.HidLeader, {"min_opening": "2mm", "max_opening": "22mm"}) as h:
        fake_hid.reports += [DS4_USB]
        out = _raw_step(h, 0.0)
        assert out["gripper_opening"].stamp == 0.0 and out["gripper_velocity"].value == 0.0
        for t in (0.004, 0.1, 0.3):  # silent (under report_timeout): the same samples, still stamped 0.0
            out = _raw_step(h, t)
            assert {k: s.stamp for k, s in out.items()} == dict.fromkeys(out, 0.0)
        assert out["gripper_opening"].value == pytest.approx(0.022 - (0xC0 / 255) * 0.020) and out["button"].value
        assert not out["gripper_opening"].is_fresh(0.3, 0.05)  # a consumer's max_age sees the data as old
        fake_hid.reports += [DS4_USB_RELEASED]
        out = _raw_step(h, 0.4)
        assert all(s.stamp == 0.4 for s in out.values())
        # velocity over the time between the two reports (0.4 s), not over the last step period
        assert out["gripper_velocity"].value == pytest.approx((0xC0 / 255) * 0.020 / 0.4)


def test_stamp_is_the_read_time_on_the_wall_clock(fake_hid):
    import time

    from teletouch import Context

    fake_hid.devices.append(info(0x054C, 0x05C4))
    with Harness(hl.HidLeader, {}) as h:
        t0 = time.monotonic()
        h.comp.ctx = Context(clock_kind="wall", from_monotonic=lambda m: m - t0)
        fake_hid.reports += [DS4_USB]
        before = time.monotonic() - t0
        out = h.comp.step(123.0, h.inputs)  # a step time far from the read time: the stamp is the read time
        after = time.monotonic() - t0
        assert before <= out["gripper_opening"].stamp <= after


def test_spacemouse_silence_is_not_a_fault(fake_hid):
    # a SpaceMouse reports only when the cap moves: silent at rest, so no report_timeout and step-time stamps
    fake_hid.devices.append(info(0x046D, 0xC626))
    with Harness(hl.HidLeader, {"mode": "position"}) as h:   # the cap deflected, then released to the centre
        assert h.comp.report_timeout == 0.5
        fake_hid.reports += [bytes.fromhex("01 0000 0000") + struct.pack("<h", 175)]
        h.step(0.0)
        fake_hid.reports.append(bytes.fromhex("01 0000 0000 0000"))
        x = h.step(0.008)["gripper_opening"]
        assert x == pytest.approx(0.0125)   # centred: half open
        for i in range(1, 2501):  # 10 s without a report
            out = _raw_step(h, 0.008 + i * 0.004)
        assert out["gripper_opening"] == x and not isinstance(out["gripper_opening"], hl.Sample)  # stamped t
    with Harness(hl.HidLeader, {}) as h:  # rate mode: silent at rest once the cap is released
        fake_hid.reports.append(bytes.fromhex("01 0000 0000") + struct.pack("<h", 350))
        h.step(0.0)
        fake_hid.reports.append(bytes.fromhex("01 0000 0000 0000"))
        x = h.step(0.008)["gripper_opening"]
        for i in range(1, 2501):  # 10 s without a report
            out = _raw_step(h, 0.008 + i * 0.004)
        assert out["gripper_opening"] == x and out["gripper_velocity"] == 0.0
        assert not isinstance(out["gripper_opening"], hl.Sample)  # stamped t


def _pull_then_lose_the_link(h, fake_hid, steps: int, period: float = 0.004):
    """Step with the cap pulled (a report every other step) for ``steps`` steps, then with no report at all (the link
    is gone: no read error) until the node faults; each silent step must hold the last report's opening and stamp.
    Returns (the HardwareError, the time of the last report, its opening, the time of the fault)."""
    t = 0.0
    for k in range(steps):
        if k % 2 == 0:
            fake_hid.reports.append(PULL)
        out = _raw_step(h, t)
        if k % 2 == 0:
            last_report, x = t, _value(out["gripper_opening"])
        t += period
    with pytest.raises(HardwareError) as ei:
        while t < 5.0:
            out = _raw_step(h, t)
            assert _value(out["gripper_opening"]) == x and out["gripper_opening"].stamp == last_report
            t += period
    assert 0.5 < t - last_report <= 0.5 + period + 1e-9  # within report_timeout + one step period
    return ei.value, last_report, x, t


def test_spacemouse_in_position_mode_that_goes_silent_while_deflected_faults(fake_hid):
    # the link is lost while the cap is held deflected: before, the opening stayed at that deflection, out of the
    # operator's control, with fresh stamps and no fault
    fake_hid.devices.append(info(0x256F, 0xC62F))
    with Harness(hl.HidLeader, {"mode": "position", "dead_band": 0.1}) as h:
        exc, _, x, _ = _pull_then_lose_the_link(h, fake_hid, 20)
        assert x < 0.0125   # pulled: closer than half open
        assert re.search(r"sent no report for 0\.50.* while its cap was deflected", str(exc))


def test_report_timeout_must_fit_the_profile(fake_hid):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="cannot be turned off for a dualsense"):
        hl.HidLeader.Params(device="dualsense", report_timeout=0)
    with pytest.raises(ValidationError, match="cannot be turned off for a SpaceMouse.*out of the operator's"):
        hl.HidLeader.Params(device="spacemouse", mode="position", report_timeout=0)
    assert hl.HidLeader.Params(device="spacemouse", mode="position", report_timeout="0.8 s").report_timeout == 0.8
    assert hl.resolve_report_timeout("generic", None) is None and hl.resolve_report_timeout("generic", 0.3) == 0.3
    # a generic pad known to stream reports opts in
    fake_hid.devices.append(info(0x1234, 0x5678))
    params = {"device": "generic", "vendor_id": 0x1234, "trigger_offset": 1, "report_timeout": 0.2}
    with Harness(hl.HidLeader, params) as h:
        fake_hid.reports += [bytes([0, 0x80])]
        assert h.step(0.0)["gripper_opening"] == pytest.approx(0.025 * (1 - 0x80 / 255))
        h.step(0.2)
        with pytest.raises(HardwareError, match="sent no report for 0.204 s"):
            h.step(0.204)
    with Harness(hl.HidLeader, dict(params, report_timeout=None)) as h:  # off by default for generic
        h.step(0.0)
        assert h.step(10.0)["gripper_opening"] == 0.025


def test_hid_leader_graph_faults_when_the_pad_goes_silent(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x05C4))
    fake_hid.reports += [DS4_USB] * 5  # read in the first step, then nothing
    reg = make_registry("teletouch.plugins.devices.hid_leader")
    result, rt = run_yaml(GRAPH.replace("duration: 0.3", "duration: 2.0").replace(
        "{device: dualshock4}", "{device: dualshock4, report_timeout: 0.2}"), reg)
    assert result.status in ("fault", "degraded"), result.summary()
    assert any(f.node == "leader" and "sent no report" in f.message for f in result.faults), result.summary()
    assert result.sim_time < 1.0  # detected after ~0.2 s, not at the end of the run


# A SpaceMouse sends a report every few ms (~8 ms) while its cap is deflected and stops a few reports after the cap is
# back at rest; a wireless one whose link drops (or a receiver pulled out) sends nothing, often with no read error.
PULL = bytes.fromhex("01 0000 0000") + struct.pack("<h", -350)  # tz full scale: close at max_speed


def _value(v):
    return v.value if isinstance(v, hl.Sample) else v


def test_spacemouse_that_goes_silent_while_deflected_stops_the_opening_and_faults(fake_hid):
    fake_hid.devices.append(info(0x256F, 0xC62F))
    with Harness(hl.HidLeader, {"max_speed": "20mm/s", "dead_band": 0.1}) as h:
        # 0.2 s closing, then the link is gone: the opening stays where it was at the last report, with its stamp
        exc, last_report, x, t = _pull_then_lose_the_link(h, fake_hid, 50)
        msg = str(exc)
        assert "SpaceMouse Wireless (receiver) (256f:c62f) sent no report for 0.50" in msg
        assert "while its cap was deflected" in msg and "report_timeout 0.5 s" in msg
        st = h.comp.status()
        assert st["gripper_opening_m"] == x and st["report_timeout_s"] == 0.5
        assert st["last_report_at_s"] == pytest.approx(last_report)   # graph time, s
        # it had moved at max_speed from the first report to the last
        assert last_report == pytest.approx(0.192) and x == pytest.approx(0.025 - 0.020 * 0.192)
        fake_hid.reports.append(PULL)  # back after the long silence: nothing was integrated over it
        out = _raw_step(h, t + 0.1)
        assert out["gripper_opening"].value == x and out["gripper_opening"].stamp == pytest.approx(t + 0.1)


def test_spacemouse_report_timeout_in_rate_mode(fake_hid):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="cannot be turned off for a SpaceMouse: .*move the opening on"):
        hl.HidLeader.Params(device="spacemouse", report_timeout=0)
    fake_hid.devices.append(info(0x046D, 0xC626))
    with Harness(hl.HidLeader, {"report_timeout": "100 ms"}) as h:  # can be changed (raised)
        assert h.comp.report_timeout == pytest.approx(0.1)
        fake_hid.reports.append(PULL)
        h.step(0.0)
        h.step(0.1)
        with pytest.raises(HardwareError, match=r"SpaceNavigator .*sent no report for 0\.104 s while its cap was "
                                                r"deflected \(report_timeout 0\.1 s"):
            h.step(0.104)


def test_velocity_of_two_reports_read_close_together_is_not_a_spike(fake_hid):
    """A pad reporting every 4 ms with the trigger squeezed at a steady rate; a step 3.9 ms late reads one report and
    the next step, 0.1 ms later, the next: the velocity was that report's 4 ms of travel over the 0.1 ms between the
    two reads (40 times the hand's speed). It is taken over at least VELOCITY_WINDOW of reports now."""
    fake_hid.devices.append(info(0x054C, 0x05C4))

    def report(k):   # the trigger 2 counts further every report
        return DS4_USB[:9] + bytes([2 * k]) + DS4_USB[10:]

    per_count = 0.020 / 255   # m of opening per trigger count (min_opening 2 mm, max_opening 22 mm)
    true_v = -2 * per_count / 0.004
    with Harness(hl.HidLeader, {"min_opening": "2mm", "max_opening": "22mm"}) as h:
        for k in range(24):                       # on time: one report per 4 ms step
            fake_hid.reports.append(report(k))
            out = _raw_step(h, k * 0.004)
        assert out["gripper_velocity"].value == pytest.approx(true_v, rel=1e-6)
        t = 24 * 0.004 + 0.0039                   # a step 3.9 ms late reads report 24, just before 25 is due...
        fake_hid.reports.append(report(24))
        out = _raw_step(h, t)
        fake_hid.reports.append(report(25))       # ...and the next one, 0.1 ms later, reads report 25
        out = _raw_step(h, t + 0.0001)
        assert out["gripper_opening"].stamp == pytest.approx(t + 0.0001)
        assert true_v * 1.5 < out["gripper_velocity"].value < true_v / 1.5, (out["gripper_velocity"].value, true_v)
        assert h.comp.velocity == out["gripper_velocity"].value
