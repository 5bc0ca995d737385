"""`teletouch devices` rows and start-up messages of the follower interfaces: SocketCAN (canopen-gripper) and USB
serial adapters (dynamixel-gripper), on fake sysfs trees and port lists."""

from __future__ import annotations

import grp
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import canopen

from teletouch.plugins.devices import canopen_gripper, dynamixel_gripper
from teletouch.plugins.devices.canopen_gripper import CanopenGripper
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper
from teletouch.testing import Harness

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fakes.realtime import configure_error  # noqa: E402


def _net(root, name, flags, operstate, hardware):
    d = root / "class" / "net" / name
    d.mkdir(parents=True)
    (d / "type").write_text("280\n")
    (d / "flags").write_text(f"{flags:#x}\n")
    (d / "operstate").write_text(f"{operstate}\n")
    if hardware:
        (d / "device").mkdir()   # a real adapter's interface links to its USB/PCI device; vcan/slcan have none


# ------------------------------------------------------------------------------------------------ CAN rows
def test_a_can_interface_that_is_down_says_how_to_bring_it_up(tmp_path):
    """A down interface was only state=down, with no word on what to do; an up vcan reads operstate "unknown", so the
    IFF_UP bit of sysfs flags, not operstate, says whether it is up."""
    _net(tmp_path, "can0", 0x1002, "down", hardware=True)     # IFF_UP clear
    _net(tmp_path, "can1", 0x10c1, "up", hardware=True)
    _net(tmp_path, "vcan0", 0xc1, "unknown", hardware=False)   # up (IFF_UP set), operstate unknown
    _net(tmp_path, "vcan1", 0x80, "down", hardware=False)
    rows = {r["id"]: r["details"] for r in canopen_gripper.can_interfaces(str(tmp_path), probe=lambda: "")}
    assert set(rows) == {"can0", "can1", "vcan0", "vcan1"}
    assert rows["can0"]["up"] is False
    assert "sudo ip link set can0 up type can bitrate " in rows["can0"]["problem"]
    assert rows["can1"]["up"] is True and "problem" not in rows["can1"]
    assert rows["vcan0"]["up"] is True and rows["vcan0"]["state"] == "unknown" and "problem" not in rows["vcan0"]
    assert rows["vcan1"]["problem"].endswith("sudo ip link set vcan1 up") and "bitrate" not in rows["vcan1"]["problem"]
    assert rows["can0"]["params"] == {"interface": "socketcan", "channel": "can0"}
    assert set(rows["can0"]["params"]) <= set(CanopenGripper.Params.model_fields)


def test_can_rows_say_when_the_kernel_has_no_socketcan(tmp_path):
    _net(tmp_path, "can0", 0x10c1, "up", hardware=True)
    calls = []

    def probe():
        calls.append(1)
        return "socket(AF_CAN) failed ([Errno 97] Address family not supported by protocol): " + \
            canopen_gripper.SOCKETCAN_MISSING

    rows = canopen_gripper.can_interfaces(str(tmp_path), probe=probe)
    assert "sudo modprobe can can_raw" in rows[0]["details"]["problem"] and calls == [1]
    assert canopen_gripper.can_interfaces(str(tmp_path / "none"), probe=probe) == [] and calls == [1]


# ------------------------------------------------------------------------------------------------ CAN start-up


def test_socketcan_missing_at_open_says_modprobe(monkeypatch):
    """[Errno 97] at open (no SocketCAN in the kernel or container) was answered with 'check the adapter and that the
    interface is up': neither helps."""
    def connect(self, *args, **kwargs):
        raise OSError(97, "Address family not supported by protocol")

    monkeypatch.setattr(canopen.Network, "connect", connect)
    msg = configure_error(Harness(CanopenGripper, {"interface": "socketcan", "channel": "can0"}))
    assert "[Errno 97]" in msg and "sudo modprobe can can_raw" in msg and "ip link set" not in msg


def test_a_missing_interface_at_open_says_so(monkeypatch):
    def connect(self, *args, **kwargs):
        raise OSError(19, "No such device")

    monkeypatch.setattr(canopen.Network, "connect", connect)
    msg = configure_error(Harness(CanopenGripper, {"interface": "socketcan", "channel": "can7"}))
    assert "there is no network interface can7" in msg and "teletouch devices" in msg


def test_an_interface_that_is_down_is_named_before_anything_is_sent(tmp_path, monkeypatch):
    """A down interface opens fine and then every frame fails ('Network is down'), which the driver reported as a
    drive that does not answer."""
    _net(tmp_path, "can0", 0x1002, "down", hardware=True)
    monkeypatch.setenv("TELETOUCH_SYSFS_ROOT", str(tmp_path))
    connected = []
    monkeypatch.setattr(canopen.Network, "connect", lambda self, *a, **k: connected.append(k))
    msg = configure_error(Harness(CanopenGripper, {"interface": "socketcan", "channel": "can0", "bitrate": 500000}))
    assert "CAN interface can0 is down" in msg and "sudo ip link set can0 up type can bitrate 500000" in msg
    assert connected == []


# ------------------------------------------------------------------------------------------------ serial rows
def _ports(monkeypatch, *devices):
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: [
        SimpleNamespace(device=str(d), vid=0x0403, pid=0x6014, serial_number=f"FT{i}", description="x")
        for i, d in enumerate(devices)])


def test_serial_rows_say_whether_the_port_can_be_opened_and_how_to_get_access(tmp_path, monkeypatch):
    """Rows had no readable flag: a U2D2 the user may not open looked usable, and the run then failed."""
    ok, denied = tmp_path / "ttyUSB0", tmp_path / "ttyUSB1"
    for p in (ok, denied):
        p.write_bytes(b"")
    os.chown(denied, -1, grp.getgrnam("dialout").gr_gid)
    _ports(monkeypatch, ok, denied)
    monkeypatch.setattr(dynamixel_gripper.os, "access", lambda p, mode: str(p) != str(denied))  # (tests run as root)
    rows = {r["path"]: r["details"] for r in dynamixel_gripper.teletouch_discover_devices()}
    assert rows[str(ok)]["readable"] is True and "problem" not in rows[str(ok)]
    d = rows[str(denied)]
    assert d["readable"] is False and d["params"] == {"port": str(denied)}
    assert f"permission denied on {denied}: join the dialout group" in d["problem"]
    assert 'ATTRS{idVendor}=="0403", ATTRS{idProduct}=="6014"' in d["problem"]


def test_a_port_that_does_not_exist_points_to_teletouch_devices(tmp_path):
    """'cannot open PORT ... check the USB adapter is plugged in and that you may use it (group dialout)': for a port
    that does not exist the group is no answer, and nothing said where the real port names are listed."""
    port = str(tmp_path / "ttyUSB9")
    msg = configure_error(Harness(DynamixelGripper, {"port": port}))
    assert f"{port} does not exist" in msg and "`teletouch devices` lists the serial adapters" in msg
    assert "dialout" not in msg


def test_a_port_without_permission_says_which_group(tmp_path, monkeypatch):
    port = tmp_path / "ttyUSB3"
    port.write_bytes(b"")
    os.chown(port, -1, grp.getgrnam("dialout").gr_gid)

    def open_port(self):
        raise OSError(13, f"could not open port {port}: [Errno 13] Permission denied")

    import dynamixel_sdk

    monkeypatch.setattr(dynamixel_sdk.PortHandler, "openPort", open_port)
    msg = configure_error(Harness(DynamixelGripper, {"port": str(port)}))
    assert f"permission denied on {port}: join the dialout group (sudo usermod -aG dialout $USER" in msg
