"""`teletouch devices` for the follower interfaces: USB serial adapters (Dynamixel) and SocketCAN interfaces."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from types import SimpleNamespace

from teletouch.plugins.devices import canopen_gripper, dynamixel_gripper


def _net(root, name, type_, state="up"):
    d = root / "class" / "net" / name
    d.mkdir(parents=True)
    (d / "type").write_text(f"{type_}\n")
    (d / "operstate").write_text(f"{state}\n")


def test_can_interfaces_from_sysfs(tmp_path):
    _net(tmp_path, "can0", 280, "up")
    _net(tmp_path, "eth0", 1)
    _net(tmp_path, "vcan1", 280, "unknown")
    found = canopen_gripper.can_interfaces(str(tmp_path))
    assert [d["id"] for d in found] == ["can0", "vcan1"]
    assert found[0]["details"]["params"] == {"interface": "socketcan", "channel": "can0"}
    assert found[0]["details"]["state"] == "up"
    assert canopen_gripper.can_interfaces(str(tmp_path / "missing")) == []


def test_serial_ports_name_dynamixel_adapters(monkeypatch):
    from serial.tools import list_ports

    ports = [SimpleNamespace(device="/dev/ttyUSB0", vid=0x0403, pid=0x6014, serial_number="FT1", description="x"),
             SimpleNamespace(device="/dev/ttyS0", vid=None, pid=None, serial_number=None, description="uart"),
             SimpleNamespace(device="/dev/ttyACM0", vid=0x1234, pid=0x0001, serial_number=None, description="other")]
    monkeypatch.setattr(list_ports, "comports", lambda: ports)
    found = dynamixel_gripper.serial_ports()
    assert [d["path"] for d in found] == ["/dev/ttyACM0", "/dev/ttyUSB0"]
    u2d2 = found[1]
    assert u2d2["details"]["description"].startswith("ROBOTIS U2D2") and u2d2["id"] == "FT1"
    assert u2d2["details"]["params"] == {"port": "/dev/ttyUSB0"}


def test_cli_devices_lists_can_from_fake_sysfs(tmp_path):
    _net(tmp_path, "can0", 280)
    env = dict(os.environ, TELETOUCH_SYSFS_ROOT=str(tmp_path), TELETOUCH_DEV_ROOT=str(tmp_path / "dev"))
    r = subprocess.run([sys.executable, "-m", "teletouch", "devices", "--json"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    kinds = {(d["kind"], d["id"]) for d in json.loads(r.stdout)}
    assert ("can", "can0") in kinds


def test_cli_devices_lists_the_rest_when_a_source_fails(tmp_path):
    """A source that fails (here pyserial broken at import) is one error row naming its plugin and the reason; the
    other sources are still listed, a CAN interface that is down says so, and stdout stays strict JSON."""
    broken = tmp_path / "broken" / "serial"
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text("raise ImportError('simulated broken pyserial')\n")
    _net(tmp_path, "can0", 280, "down")
    env = dict(os.environ, TELETOUCH_SYSFS_ROOT=str(tmp_path), TELETOUCH_DEV_ROOT=str(tmp_path / "dev"),
               PYTHONPATH=str(tmp_path / "broken"))
    r = subprocess.run([sys.executable, "-m", "teletouch", "devices", "--json"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"not strict JSON: {c}")))
    errors = {d["kind"]: d["error"] for d in rows if d.get("error")}
    assert "simulated broken pyserial" in errors.get("dynamixel-gripper", ""), rows
    can = [d for d in rows if d["kind"] == "can"]
    assert [d["id"] for d in can] == ["can0"] and can[0]["details"]["state"] == "down"
