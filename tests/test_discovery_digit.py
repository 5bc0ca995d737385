"""`teletouch devices` for DIGITs as a new lab user sees it: the graph params of each row, why a DIGIT cannot be used
(node missing in a container, permission, DFU, no video node), sources that could not be read (pyusb missing or
without libusb, sysfs unreadable), and USB-only units that sysfs does not list. Fake sysfs/dev trees; permissions are
real (as root, without the capabilities that bypass them)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import types
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes import digit_sysfs  # noqa: E402
from helpers_permissions import without_dac  # noqa: E402

from teletouch import HardwareError
from teletouch.plugins.sensors import discovery
from teletouch.plugins.sensors.digit import Digit
from teletouch.testing import Harness


def _usb_device(root: Path, name: str, serial: str | None, busnum: int | None = None, devnum: int | None = None,
                vid: str = "2833", pid: str = "0209") -> Path:
    return digit_sysfs.usb_device(root, name, serial, vid=vid, pid=pid, busnum=busnum, devnum=devnum)


_video_node = digit_sysfs.video_node


@pytest.fixture()
def tree(tmp_path):
    root, dev = tmp_path / "sys", tmp_path / "dev"
    dev.mkdir()
    return root, dev


def _devices_json(root: Path, dev: Path, *, drop_dac: bool = False) -> tuple[int, list[dict], str]:
    env = dict(os.environ, TELETOUCH_SYSFS_ROOT=str(root), TELETOUCH_DEV_ROOT=str(dev))
    cmd = [sys.executable, "-m", "teletouch", "devices", "--json"]
    r = subprocess.run(without_dac(cmd) if drop_dac else cmd, capture_output=True, text=True, env=env, timeout=120)
    rows = json.loads(r.stdout, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    return r.returncode, rows, r.stderr


# ------------------------------------------------------------------------------------------------ rows and params
def test_rows_give_the_plugin_and_the_params_for_a_graph(tree):
    """A DIGIT row had no plugin and no params (the serial or port rows of the other devices have them): the user had
    to work out that `id` goes into the digit node's `serial`, and for a unit without a serial there was nothing to
    put in a graph."""
    root, dev = tree
    _video_node(root, dev, _usb_device(root, "1-1", "D20001"), 0)
    _video_node(root, dev, _usb_device(root, "1-2", None), 2)   # no serial string
    # the rows the digit plugin's hook makes today (one as_device() per DIGIT), and discover()'s
    rows = [d.as_device() for d in discovery.find_digits(root, dev, usb_find=None)]
    assert [r["id"] for r in rows] == ["D20001", "unknown@1-2"]
    a, b = (r["details"] for r in rows)
    assert a.get("plugin") == "digit" and a.get("params") == {"serial": "D20001"} and "problem" not in a
    assert b.get("params") == {"source": str(dev / "video2")}
    for d in (a, b):   # they are the digit node's own parameters
        assert set(d["params"]) <= set(Digit.Params.model_fields)
    assert rows == discovery.discover(root, dev, usb_find=None)


def test_cli_row_names_a_missing_node_and_what_to_check(tree):
    """sysfs lists the DIGIT but /dev has no node (a container started without --device): `teletouch devices` showed
    it with readable=None and nothing else, and the run then said 'is the DIGIT plugged in?' (it is)."""
    root, dev = tree
    _video_node(root, None, _usb_device(root, "1-1", "D20001"), 4)
    rc, rows, err = _devices_json(root, dev)
    assert rc == 0, err
    row = next(r for r in rows if r.get("kind") == "digit" and r["id"] == "D20001")
    problem = row["details"]["problem"]
    assert f"{dev / 'video4'} does not exist" in problem and "--device" in problem
    assert row["details"]["params"] == {"serial": "D20001"}


def test_cli_row_names_a_node_without_permission_and_the_udev_rule(tree):
    root, dev = tree
    _video_node(root, dev, _usb_device(root, "1-1", "D20001"), 0)
    os.chmod(dev / "video0", 0o000)
    rc, rows, err = _devices_json(root, dev, drop_dac=True)
    assert rc == 0, err
    row = next(r for r in rows if r.get("kind") == "digit" and r["id"] == "D20001")
    assert row["details"]["readable"] is False
    problem = row["details"]["problem"]
    assert f"permission denied on {dev / 'video0'}" in problem and discovery.UDEV_RULE in problem


def test_dfu_and_nodeless_units_say_what_to_do(tree):
    root, dev = tree
    usb = [SimpleNamespace(idVendor=0x0403, idProduct=0x0FDE, serial_number="D29999", bus=1, address=9, bcdDevice=1),
           SimpleNamespace(idVendor=0x2833, idProduct=0x0209, serial_number="D20007", bus=1, address=7,
                           bcdDevice=0x203)]
    rows = [d.as_device() for d in discovery.find_digits(root, dev, usb_find=lambda: usb)]
    dfu, bare = (r["details"] for r in rows)
    assert "flash the DIGIT firmware" in dfu.get("problem", "") and dfu.get("params") == {"serial": "D29999"}
    assert "uvcvideo" in bare.get("problem", "")
    assert rows == discovery.discover(root, dev, usb_find=lambda: usb)


# ------------------------------------------------------------------------------------------------ failed sources
def test_a_usb_scan_that_cannot_run_is_an_error_row_and_sysfs_is_still_listed(tree, monkeypatch):
    """pyusb missing, or without a libusb backend (this machine), made the USB scan return nothing in silence: a
    DIGIT in DFU mode was simply absent from `teletouch devices`, with no hint why."""
    root, dev = tree
    _video_node(root, dev, _usb_device(root, "1-1", "D20001"), 0)
    monkeypatch.setitem(sys.modules, "usb", None)          # import usb.core -> ImportError
    monkeypatch.setitem(sys.modules, "usb.core", None)
    rows = discovery.discover(root, dev)
    assert [r["id"] for r in rows if not r.get("error")] == ["D20001"]
    errors = [r["error"] for r in rows if r.get("error")]
    assert len(errors) == 1 and "pyusb cannot be imported" in errors[0] and "DFU mode" in errors[0]

    class NoBackendError(Exception):
        pass

    def find(**kw):
        raise NoBackendError("No backend available")

    fake = types.ModuleType("usb.core")
    fake.find = find
    pkg = types.ModuleType("usb")
    pkg.core = fake
    monkeypatch.setitem(sys.modules, "usb", pkg)
    monkeypatch.setitem(sys.modules, "usb.core", fake)
    errors = [r["error"] for r in discovery.discover(root, dev) if r.get("error")]
    assert len(errors) == 1 and "no libusb backend" in errors[0] and "libusb-1.0" in errors[0]
    # the run path is unchanged: the video node is what it needs, a USB scan that cannot run is no error there
    assert [d.serial for d in discovery.find_digits(root, dev)] == ["D20001"]


def test_unreadable_sysfs_is_a_hardware_error_naming_the_folder(tree):
    """A /sys/class/video4linux this user cannot list raised a bare PermissionError out of the digit node's configure
    (not a HardwareError, so not the hardware fault policy, and no hint), and `teletouch devices` dropped the USB scan
    with it."""
    root, dev = tree
    _video_node(root, dev, _usb_device(root, "1-1", "D20001"), 0)
    cls = root / "class" / "video4linux"
    os.chmod(cls, 0o000)
    code = textwrap.dedent(f"""
        import json
        from teletouch import HardwareError
        from teletouch.plugins.sensors import discovery
        try:
            discovery.find_digits({str(root)!r}, {str(dev)!r}, usb_find=None)
            print("NO ERROR")
        except HardwareError as e:
            print("HARDWARE:", e)
        except Exception as e:
            print("OTHER:", type(e).__name__, e)
        from types import SimpleNamespace
        dfu = SimpleNamespace(idVendor=0x0403, idProduct=0x0FDE, serial_number="D29999", bus=1, address=9)
        rows = discovery.discover({str(root)!r}, {str(dev)!r}, usb_find=lambda: [dfu])
        print("ROWS:", json.dumps([r.get("error", r["id"]) for r in rows]))
    """)
    try:
        out = subprocess.run(without_dac([sys.executable, "-c", code]), capture_output=True, text=True, timeout=60)
    finally:
        os.chmod(cls, 0o755)
    assert f"HARDWARE: cannot list {cls}" in out.stdout, out.stdout + out.stderr
    rows = json.loads(out.stdout.split("ROWS:", 1)[1])
    assert rows[0] == "D29999" and rows[1].startswith(f"cannot list {cls}"), out.stdout


# ------------------------------------------------------------------------------------------------ USB-only units
def test_usb_units_are_matched_to_sysfs_by_bus_and_address(tree):
    """The USB scan was matched to sysfs by serial: a second unit reporting the same serial but without a video node
    (uvcvideo not bound), or a nodeless one whose serial USB permissions hide, was dropped as 'already listed'
    whenever some DIGIT had a node."""
    root, dev = tree
    _video_node(root, dev, _usb_device(root, "1-1", "D20001", busnum=1, devnum=5), 0)
    locked = type("Dev", (), {"idVendor": 0x2833, "idProduct": 0x0209, "bus": 1, "address": 8, "bcdDevice": 0x203,
                              "serial_number": property(lambda self: (_ for _ in ()).throw(ValueError("no langid")))})
    usb = [SimpleNamespace(idVendor=0x2833, idProduct=0x0209, serial_number="D20001", bus=1, address=5,
                           bcdDevice=0x203),    # the one sysfs lists
           SimpleNamespace(idVendor=0x2833, idProduct=0x0209, serial_number="D20001", bus=1, address=6,
                           bcdDevice=0x203),    # a twin without a node
           locked()]                            # another one, serial unreadable, no node
    found = discovery.find_digits(root, dev, usb_find=lambda: usb)
    assert [(d.serial, d.path) for d in found] == [("D20001", str(dev / "video0")), ("D20001", None),
                                                   ("unknown@bus1-dev8", None)]
    assert [d.address for d in found] == [5, 6, 8]
    rows = discovery.discover(root, dev, usb_find=lambda: usb)
    twin_with_node = rows[0]["details"]
    assert twin_with_node["params"] == {"source": str(dev / "video0")}
    assert "2 DIGITs report serial D20001" in twin_with_node["problem"]
    locked_problem = rows[2]["details"]["problem"]
    assert "cannot be read" in locked_problem and discovery.USB_UDEV_RULE in locked_problem


def test_usb_permission_hint_gives_a_usb_rule(tree, monkeypatch):
    """A DIGIT seen only over USB with its strings unreadable got the video4linux udev rule as the fix; reading USB
    strings needs access to /dev/bus/usb, which that rule does not give."""
    root, dev = tree
    root.mkdir()
    import usb.core

    class Locked(SimpleNamespace):
        pass

    def find_locked(find_all=True, idVendor=None, idProduct=None):
        if (idVendor, idProduct) != (0x2833, 0x0209):
            return []
        d = Locked(idVendor=0x2833, idProduct=0x0209, bus=3, address=4, bcdDevice=0x203)
        return [d]

    Locked.serial_number = property(lambda self: (_ for _ in ()).throw(ValueError("The device has no langid")))
    monkeypatch.setattr(usb.core, "find", find_locked)
    with pytest.raises(HardwareError, match="USB access is denied") as ei:
        with Harness(Digit, {"sysfs_root": str(root), "dev_root": str(dev)}):
            pass
    assert 'SUBSYSTEM=="usb", ATTRS{idVendor}=="2833"' in str(ei.value)


def test_the_devices_hook_and_the_run_path_say_when_the_usb_scan_could_not_run(tree, monkeypatch):
    """The plugin's `teletouch devices` hook listed nothing, and the run's "no DIGIT found" said nothing, when pyusb
    could not scan the bus: a DIGIT in DFU mode or without uvcvideo was invisible with no reason."""
    from teletouch.plugins.sensors import digit

    root, dev = tree
    (root / "class" / "video4linux").mkdir(parents=True)
    monkeypatch.setitem(sys.modules, "usb", None)          # import usb.core -> ImportError
    monkeypatch.setitem(sys.modules, "usb.core", None)
    monkeypatch.setenv("TELETOUCH_SYSFS_ROOT", str(root))
    monkeypatch.setenv("TELETOUCH_DEV_ROOT", str(dev))
    rows = digit.teletouch_discover_devices()
    assert len(rows) == 1 and "USB not scanned: pyusb cannot be imported" in rows[0]["error"]
    with pytest.raises(HardwareError, match=r"no DIGIT found .*; USB not scanned: pyusb cannot be imported"):
        with Harness(Digit, {"sysfs_root": str(root), "dev_root": str(dev)}):
            pass
