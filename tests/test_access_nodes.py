"""Whether a device node can be used: `teletouch devices` and the drivers' messages (digit, dynamixel-gripper,
hid-leader) asked os.access, which answers for the node's mode only (root always passes it), while open() can still
fail: a nodev mount, an AppArmor rule, a container's device rule, a node with no device behind it (ENXIO), a device
held by another process (EBUSY). One helper (discovery.check_node) now opens the node as the drivers do, closes it at
once, and names the errno and what it means; a serial port is never opened by `teletouch devices` (a tty's open
pulses DTR, which resets Arduino-like boards).

The kernel's refusals are real where a test can get them as any user (a FIFO with no reader: ENXIO; a directory:
EISDIR); the others (EACCES, EPERM, EBUSY, ENODEV) come from os.open made to fail with that errno for one path: the
mapping and the message are what is tested."""

from __future__ import annotations

import errno
import os
import stat
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes import digit_sysfs  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.plugins.devices import dynamixel_gripper, hid_leader  # noqa: E402
from teletouch.plugins.sensors import discovery  # noqa: E402
from teletouch.plugins.sensors.digit import Digit  # noqa: E402
from teletouch.testing import Harness  # noqa: E402

_real_open = os.open


def refuse(monkeypatch, path, err):
    """os.open of ``path`` fails with ``err`` (as a container's device rule, a held device or a stale node would);
    every other path opens as usual. Returns the list of the flags ``path`` was opened with."""
    calls = []

    def fake_open(p, flags, *args, **kw):
        if os.fspath(p) == os.fspath(path):
            calls.append(flags)
            raise OSError(err, os.strerror(err), os.fspath(p))
        return _real_open(p, flags, *args, **kw)

    monkeypatch.setattr(os, "open", fake_open)
    return calls


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


# --- the helper -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("err, cause, words", [
    (errno.EACCES, "permission", ["permission denied on", "EACCES from open()", "FIX", "docker run --device"]),
    (errno.EPERM, "permission", ["permission denied on", "EPERM from open()", "device cgroup",
                                 "docker run --device", "outside a container, FIX"]),
    (errno.EBUSY, "busy", ["is in use", "EBUSY", "another process holds the device", "fuser -v"]),
    (errno.ENXIO, "gone", ["no device behind", "ENXIO", "unplugged", "replug"]),
    (errno.ENODEV, "gone", ["no device behind", "ENODEV", "replug"]),
])
def test_errno_of_open_is_named_with_its_meaning(tmp_path, monkeypatch, err, cause, words):
    node = tmp_path / "video0"
    node.write_bytes(b"")
    calls = refuse(monkeypatch, node, err)
    acc = discovery.check_node(node)
    assert acc.errno == err and acc.readable is False and acc.cause == cause and acc.opened
    assert calls == [discovery.OPEN_FLAGS]      # opened once, as the drivers open it
    problem = acc.problem("FIX")
    for w in words:
        assert w in problem, problem
    assert str(node) in problem
    if cause != "permission":
        assert "FIX" not in problem and "permission" not in problem   # a busy or gone device is not a permission


def test_open_flags_are_the_drivers_and_never_make_a_controlling_tty():
    f = discovery.OPEN_FLAGS
    assert f & os.O_ACCMODE == os.O_RDWR
    assert f & os.O_NONBLOCK and f & os.O_NOCTTY and f & os.O_CLOEXEC


def test_real_refusals_that_root_gets_too(tmp_path):
    """A FIFO opened for writing with no reader: the kernel says ENXIO to anyone (os.access says yes); a directory
    where a node should be: EISDIR; no node: readable None."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert os.access(fifo, os.W_OK)
    acc = discovery.check_node(fifo, os.O_WRONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    assert acc.errno == errno.ENXIO and acc.cause == "gone" and acc.readable is False
    assert "ENXIO from open(): gone: no device behind the node" in acc.why()
    d = tmp_path / "video1"
    d.mkdir()
    assert os.access(d, os.R_OK | os.W_OK)
    acc = discovery.check_node(d)
    assert acc.errno == errno.EISDIR and acc.readable is False and "a directory, not a device node" in acc.why()
    acc = discovery.check_node(tmp_path / "missing")
    assert acc.errno == errno.ENOENT and acc.readable is None


def test_the_node_is_closed_at_once(tmp_path):
    before = _open_fds()
    for _ in range(20):
        assert discovery.check_node("/dev/null").readable is True
    assert _open_fds() == before


def test_a_nodev_mount_is_named_without_opening(monkeypatch):
    """A device node on a nodev mount (a rootless container's /dev) is refused with EACCES by open() even for root,
    while os.access says yes."""
    real = os.statvfs
    monkeypatch.setattr(os, "statvfs", lambda p: SimpleNamespace(f_flag=os.ST_NODEV) if p == "/dev/null" else real(p))
    calls = refuse(monkeypatch, "/dev/null", errno.EACCES)
    acc = discovery.check_node("/dev/null")
    assert acc.errno == errno.EACCES and "nodev mount" in acc.why() and calls == []
    assert acc.major == 1 and "--device-cgroup-rule='c 1:* rmw'" in acc.problem("FIX")


def test_without_opening_a_char_node_with_no_device_registered_is_enxio(tmp_path, monkeypatch):
    calls = refuse(monkeypatch, "/dev/null", errno.EIO)     # must not be opened at all
    sysfs = tmp_path / "sys"
    (sysfs / "dev" / "char").mkdir(parents=True)
    acc = discovery.check_node("/dev/null", open_node=False, sysfs_root=sysfs)
    assert acc.errno == errno.ENXIO and not acc.opened and "1:3" in acc.why()
    (sysfs / "dev" / "char" / "1:3").mkdir()
    acc = discovery.check_node("/dev/null", open_node=False, sysfs_root=sysfs)
    assert acc.errno is None and acc.readable is True and not acc.opened
    assert calls == []


# --- DIGIT: discovery rows and the driver -----------------------------------------------------------------------
@pytest.fixture
def digit_tree(tmp_path):
    root, dev = tmp_path / "sys", tmp_path / "dev"
    dev.mkdir()
    digit_sysfs.video_node(root, dev, digit_sysfs.usb_device(root, "1-1", "D20001"), 0)
    return root, dev


def test_digit_row_where_open_fails_is_not_readable(digit_tree, monkeypatch):
    """A device rule refusing the DIGIT (EPERM) left readable True (os.access said yes): the row looked usable."""
    root, dev = digit_tree
    node = dev / "video0"
    refuse(monkeypatch, node, errno.EPERM)
    assert os.access(node, os.R_OK | os.W_OK)
    row = discovery.discover(root, dev, usb_find=None)[0]["details"]
    assert row["readable"] is False
    assert row["access"].startswith("EPERM from open()")
    assert f"permission denied on {node}: in a container, pass it in (docker run --device {node}" in row["problem"]
    assert discovery.UDEV_RULE in row["problem"]


def test_digit_row_with_a_directory_for_a_node(digit_tree):
    root, dev = digit_tree
    (dev / "video0").unlink()
    (dev / "video0").mkdir()
    row = discovery.discover(root, dev, usb_find=None)[0]["details"]
    assert row["readable"] is False and "EISDIR" in row["problem"] and "permission" not in row["problem"]


def test_digit_in_use_is_not_told_to_be_plugged_in(digit_tree, monkeypatch):
    """EBUSY said 'cannot open ...: Device or resource busy; is the DIGIT plugged in?' (it is)."""
    root, dev = digit_tree
    refuse(monkeypatch, dev / "video0", errno.EBUSY)
    with pytest.raises(HardwareError) as ei:
        Harness(Digit, {"serial": "D20001", "sysfs_root": str(root), "dev_root": str(dev)}).comp.configure()
    msg = str(ei.value)
    assert f"{dev / 'video0'} is in use (EBUSY" in msg and "fuser -v" in msg and "plugged in" not in msg


def test_digit_refused_by_a_device_rule_names_the_container_fix(digit_tree, monkeypatch):
    """EPERM (a container's device cgroup) gave only the udev rule, which does not help inside a container."""
    root, dev = digit_tree
    refuse(monkeypatch, dev / "video0", errno.EPERM)
    with pytest.raises(HardwareError) as ei:
        Harness(Digit, {"serial": "D20001", "sysfs_root": str(root), "dev_root": str(dev)}).comp.configure()
    msg = str(ei.value)
    assert "EPERM" in msg and f"docker run --device {dev / 'video0'}" in msg and "50-DIGIT.rules" in msg


# --- serial ports (dynamixel-gripper) ---------------------------------------------------------------------------
def test_serial_rows_never_open_the_port(tmp_path, monkeypatch):
    """`teletouch devices` must not open a tty (the open raises DTR: an Arduino on the port resets); a node with no
    device registered behind it (a stale /dev/ttyUSB0 in a container) said readable True."""
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: [
        SimpleNamespace(device="/dev/null", vid=0x0403, pid=0x6014, serial_number="FT1", description="x")])
    calls = refuse(monkeypatch, "/dev/null", errno.EIO)
    sysfs = tmp_path / "sys"
    (sysfs / "dev" / "char").mkdir(parents=True)
    monkeypatch.setenv("TELETOUCH_SYSFS_ROOT", str(sysfs))
    d = dynamixel_gripper.serial_ports()[0]["details"]
    assert d["readable"] is False and d["access"].startswith("ENXIO") and "no device behind /dev/null" in d["problem"]
    assert "not opened" in d["checked"]
    (sysfs / "dev" / "char" / "1:3").mkdir()
    d = dynamixel_gripper.serial_ports()[0]["details"]
    assert d["readable"] is True and "problem" not in d
    assert calls == []


@pytest.mark.parametrize("err, words, not_words", [
    (errno.ENXIO, ["no device behind", "ENXIO", "replug"], ["dialout", "no other program"]),
    (errno.EPERM, ["permission denied on", "docker run --device", "EPERM"], []),
    (errno.EBUSY, ["is in use", "EBUSY", "fuser -v"], ["dialout"]),
])
def test_port_open_errno_from_pyserial_is_explained(tmp_path, err, words, not_words):
    """pyserial's own open error (SerialException carries its errno) was read as 2 (missing), 13 (permission) or
    'another program holds it': ENXIO (a stale node) and EPERM (a container's device rule) got that last one."""
    port = tmp_path / "ttyUSB0"
    port.write_bytes(b"")
    hint = dynamixel_gripper.port_open_hint(str(port), OSError(err, f"could not open port {port}"))
    for w in words:
        assert w in hint, hint
    for w in not_words:
        assert w not in hint, hint


# --- HID (hid-leader) ---------------------------------------------------------------------------------------------
def test_hid_row_where_open_fails_is_not_readable(tmp_path, monkeypatch):
    import hid

    node = tmp_path / "hidraw5"
    node.write_bytes(b"")
    dev = {"vendor_id": 0x256F, "product_id": 0xC635, "path": str(node).encode(), "usage_page": 1, "usage": 8,
           "product_string": "", "serial_number": "", "interface_number": 0}
    monkeypatch.setattr(hid, "enumerate", lambda vid=0, pid=0: [dev])
    refuse(monkeypatch, node, errno.ENODEV)
    assert os.access(node, os.R_OK | os.W_OK)
    d = hid_leader.discover(sysfs_root=str(tmp_path), dev_root=str(tmp_path))[0]["details"]
    assert d["readable"] is False and d["access"].startswith("ENODEV from open()")
    assert f"no device behind {node}" in d["problem"] and "udev" not in d["problem"]


def test_hid_open_failure_on_a_busy_node_says_so(tmp_path, monkeypatch):
    """hidapi's open failed; the node opens for nobody (EBUSY): the message guessed 'another program, or
    permission' and gave the udev rule."""
    node = tmp_path / "hidraw6"
    node.write_bytes(b"")

    class Dev:
        def open_path(self, path):
            raise OSError("open failed")

    refuse(monkeypatch, node, errno.EBUSY)
    with pytest.raises(HardwareError) as ei:
        hid_leader.open_device({"path": str(node).encode(), "vendor_id": 0x256F, "product_id": 0xC635,
                                "name": "SpaceMouse"}, hid=SimpleNamespace(device=Dev))
    msg = str(ei.value)
    assert f"{node} is in use (EBUSY" in msg and "udev" not in msg


def test_stat_is_what_the_check_reads_for_a_char_device():
    """/dev/null is a character device on every Linux: the checks above that use it rely on that."""
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode) and os.major(os.stat("/dev/null").st_rdev) == 1
