"""Find DIGIT sensors: USB ids through sysfs (video4linux entries) and pyusb, so no one guesses /dev/videoN.

A DIGIT enumerates as USB 2833:0209 (an unflashed one or one in DFU mode as 0403:0fde) and as a UVC camera with
two video4linux nodes: the capture node (``index`` 0) and a metadata node. For each
``<sysfs>/class/video4linux/videoN`` we follow the ``device`` link to the USB interface and read ``idVendor``,
``idProduct``, ``serial``, ``bcdDevice`` (firmware revision), ``product`` and ``manufacturer`` from its USB device
folder. pyusb adds DIGITs that have no video node (DFU mode, uvcvideo not bound) and tells whether USB is readable.

Both roots are parameters (``sysfs_root``, ``dev_root``) so the logic is tested on a fake tree.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

DIGIT_VID, DIGIT_PID = 0x2833, 0x0209
DFU_VID, DFU_PID = 0x0403, 0x0FDE

UDEV_RULE = ('SUBSYSTEM=="video4linux", ATTRS{idVendor}=="2833", ATTRS{idProduct}=="0209", MODE="0666", '
             'GROUP="plugdev"')
UDEV_HINT = (f"add the udev rule\n    {UDEV_RULE}\nto /etc/udev/rules.d/50-DIGIT.rules, run 'sudo udevadm control "
             "--reload && sudo udevadm trigger', add yourself to the plugdev (or video) group and replug the DIGIT")


@dataclass
class DigitInfo:
    """A DIGIT seen on this machine."""

    serial: str
    path: str | None                 # capture node, e.g. /dev/video0 (None: no video node)
    firmware: str = ""               # bcdDevice, e.g. "0101"
    product: str = ""
    manufacturer: str = ""
    usb_path: str = ""               # sysfs name of the USB device, e.g. 1-1.2
    mode: str = "camera"             # camera | dfu
    readable: bool | None = None     # can this user open the node (None: unknown)
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def firmware_revision(self) -> int | None:
        """bcdDevice as an integer (e.g. "0203" -> 203), None if unknown."""
        try:
            return int(self.firmware, 10) if self.firmware else None
        except ValueError:
            return None

    def as_device(self) -> dict[str, Any]:
        """The entry for ``teletouch devices``."""
        d = asdict(self)
        details = {k: d[k] for k in ("firmware", "product", "manufacturer", "usb_path", "mode", "readable")}
        details.update(self.details)
        return {"kind": "digit", "id": self.serial, "path": self.path or "", "details": details}


def _read(p: Path) -> str:
    try:
        return p.read_text().strip()
    except OSError:
        return ""


def _usb_device_dir(video_dir: Path) -> Path | None:
    """Walk up from the video node's device link to the folder that has idVendor (the USB device)."""
    dev = video_dir / "device"
    try:
        cur = dev.resolve(strict=True)
    except OSError:
        return None
    for _ in range(6):
        if (cur / "idVendor").is_file():
            return cur
        if cur.parent == cur:
            break
        cur = cur.parent
    return None


def _video_index(name: str) -> int:
    try:
        return int(name[5:])
    except ValueError:
        return 1 << 30


def scan_sysfs(sysfs_root: str | os.PathLike = "/sys", dev_root: str | os.PathLike = "/dev") -> list[DigitInfo]:
    """DIGITs with a video4linux capture node, in /dev/videoN order: one per USB device (two units that report the
    same serial are both listed)."""
    base = Path(sysfs_root) / "class" / "video4linux"
    if not base.is_dir():
        return []
    found: dict[Path, DigitInfo] = {}
    for vd in sorted(base.iterdir(), key=lambda p: _video_index(p.name)):
        if not vd.name.startswith("video"):
            continue
        usb = _usb_device_dir(vd)
        if usb is None:
            continue
        try:
            vid, pid = int(_read(usb / "idVendor"), 16), int(_read(usb / "idProduct"), 16)
        except ValueError:
            continue
        if (vid, pid) != (DIGIT_VID, DIGIT_PID):
            continue
        index = _read(vd / "index")
        if index not in ("", "0"):
            continue  # the metadata node of the same camera
        if usb in found:
            continue  # a second capture node of the same camera (sysfs without ``index``)
        serial = _read(usb / "serial") or f"unknown@{usb.name}"
        node = Path(dev_root) / vd.name
        found[usb] = DigitInfo(
            serial=serial, path=str(node), firmware=_read(usb / "bcdDevice"), product=_read(usb / "product"),
            manufacturer=_read(usb / "manufacturer"), usb_path=usb.name,
            readable=os.access(node, os.R_OK | os.W_OK) if node.exists() else None,
            details={"name": _read(vd / "name")})
    return list(found.values())


def _pyusb_devices() -> list[Any]:
    """USB devices with the DIGIT's ids (camera or DFU); [] when pyusb has no backend."""
    try:
        import usb.core
    except ImportError:
        return []
    out: list[Any] = []
    try:
        for vid, pid in ((DIGIT_VID, DIGIT_PID), (DFU_VID, DFU_PID)):
            out.extend(usb.core.find(find_all=True, idVendor=vid, idProduct=pid) or [])
    except Exception:  # usb.core.NoBackendError, permission problems
        return []
    return out


def scan_usb(find: Callable[[], Iterable[Any]] = _pyusb_devices) -> list[DigitInfo]:
    """DIGITs on the USB bus (pyusb). Serial strings need read access to the USB device; unreadable ones are
    reported with readable=False."""
    out = []
    for dev in find():
        vid, pid = int(getattr(dev, "idVendor", 0)), int(getattr(dev, "idProduct", 0))
        mode = "dfu" if (vid, pid) == (DFU_VID, DFU_PID) else "camera"
        readable: bool | None = True
        try:
            serial = dev.serial_number or ""
        except Exception:  # ValueError (no langid: permission), usb.core.USBError
            serial, readable = "", False
        bus, addr = getattr(dev, "bus", "?"), getattr(dev, "address", "?")
        bcd = getattr(dev, "bcdDevice", None)
        out.append(DigitInfo(serial=serial or f"unknown@bus{bus}-dev{addr}", path=None,
                             firmware=f"{bcd:04x}" if isinstance(bcd, int) else "", mode=mode,
                             usb_path=f"bus {bus} device {addr}", readable=readable))
    return out


def find_digits(sysfs_root: str | os.PathLike = "/sys", dev_root: str | os.PathLike = "/dev",
                usb_find: Callable[[], Iterable[Any]] | None = _pyusb_devices) -> list[DigitInfo]:
    """All DIGITs this machine can see: the video nodes first, then USB-only ones (no node, or DFU mode)."""
    digits = scan_sysfs(sysfs_root, dev_root)
    if usb_find is not None:
        known = {d.serial for d in digits}
        for u in scan_usb(usb_find):
            if u.serial in known:
                continue
            if u.mode == "camera" and u.serial.startswith("unknown@") and len(digits) > 0:
                continue  # cannot tell it from the ones with a node
            digits.append(u)
    return digits


def describe(digits: Iterable[DigitInfo]) -> str:
    """One line per DIGIT, for error messages."""
    lines = []
    for d in digits:
        where = d.path or ("DFU mode: flash the DIGIT firmware" if d.mode == "dfu" else "no video node")
        fw = f", firmware {d.firmware}" if d.firmware else ""
        lines.append(f"{d.serial} ({where}{fw})")
    return ", ".join(lines) if lines else "none"
