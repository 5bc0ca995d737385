"""A fake Linux sysfs/dev tree with USB cameras laid out as the kernel does (the USB device, its interface, the
video4linux nodes and their /sys/class links), for the DIGIT discovery tests: discovery reads the real layout."""

from __future__ import annotations

import os
from pathlib import Path


def usb_device(root: Path, name: str, serial: str | None, *, vid: str = "2833", pid: str = "0209",
               busnum: int | None = None, devnum: int | None = None, bcd: str = "0203", product: str = "DIGIT",
               manufacturer: str | None = None) -> Path:
    """A USB device folder under ``root``/devices (a DIGIT unless vid/pid say otherwise); ``serial`` None: no serial
    file (unreadable strings); ``busnum``/``devnum`` as the kernel writes them (optional: old trees lack them)."""
    d = root / "devices" / "pci0000:00" / "0000:00:14.0" / "usb1" / name
    d.mkdir(parents=True)
    (d / "idVendor").write_text(vid + "\n")
    (d / "idProduct").write_text(pid + "\n")
    if serial is not None:
        (d / "serial").write_text(serial + "\n")
    (d / "bcdDevice").write_text(bcd + "\n")
    (d / "product").write_text(product + "\n")
    if manufacturer is not None:
        (d / "manufacturer").write_text(manufacturer + "\n")
    if busnum is not None:
        (d / "busnum").write_text(f"{busnum}\n")
        (d / "devnum").write_text(f"{devnum}\n")
    return d


def video_node(root: Path, dev: Path | None, usb: Path, n: int, index: int = 0) -> None:
    """video``n`` on the USB device's first interface (``index`` 0: the capture node, 1: the metadata node), linked
    from /sys/class/video4linux; its /dev node is made under ``dev`` unless that is None (a container without it)."""
    intf = usb / f"{usb.name}:1.0"
    v = intf / "video4linux" / f"video{n}"
    v.mkdir(parents=True)
    (v / "index").write_text(f"{index}\n")
    (v / "name").write_text("DIGIT: DIGIT\n")
    os.symlink(os.path.relpath(intf, v), v / "device")
    cls = root / "class" / "video4linux"
    cls.mkdir(parents=True, exist_ok=True)
    os.symlink(os.path.relpath(v, cls), cls / f"video{n}")
    if dev is not None:
        (dev / f"video{n}").write_bytes(b"")
