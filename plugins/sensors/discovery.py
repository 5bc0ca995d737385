"""Find DIGIT sensors: USB ids through sysfs (video4linux entries) and pyusb, so no one guesses /dev/videoN.

A DIGIT enumerates as USB 2833:0209 (an unflashed one or one in DFU mode as 0403:0fde) and as a UVC camera with
two video4linux nodes: the capture node (``index`` 0) and a metadata node. For each
``<sysfs>/class/video4linux/videoN`` we follow the ``device`` link to the USB interface and read ``idVendor``,
``idProduct``, ``serial``, ``bcdDevice`` (firmware revision), ``product`` and ``manufacturer`` from its USB device
folder. pyusb adds DIGITs that have no video node (DFU mode, uvcvideo not bound) and tells whether USB is readable;
a USB device that sysfs already lists (same bus and address) is not listed twice.

:func:`discover` is what ``teletouch devices`` shows: one row per DIGIT, with the graph parameter that selects it
(``params``) and, for one that cannot be used as it is, the ``problem`` and what to do; and one ``error`` row per
source that could not be read (sysfs unreadable, pyusb missing or without a libusb backend), so that "nothing found"
is never silent about what was not looked at.

Both roots are parameters (``sysfs_root``, ``dev_root``) so the logic is tested on a fake tree.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from teletouch import HardwareError

DIGIT_VID, DIGIT_PID = 0x2833, 0x0209
DFU_VID, DFU_PID = 0x0403, 0x0FDE

UDEV_RULE = ('SUBSYSTEM=="video4linux", ATTRS{idVendor}=="2833", ATTRS{idProduct}=="0209", MODE="0666", '
             'GROUP="plugdev"')
# reading the serial over USB (pyusb) opens /dev/bus/usb/BBB/DDD, which the video4linux rule does not cover
USB_UDEV_RULE = 'SUBSYSTEM=="usb", ATTRS{idVendor}=="2833", ATTRS{idProduct}=="0209", MODE="0666", GROUP="plugdev"'
UDEV_HINT = (f"add the udev rules\n    {UDEV_RULE}\n    {USB_UDEV_RULE}\nto /etc/udev/rules.d/50-DIGIT.rules, run "
             "'sudo udevadm control --reload && sudo udevadm trigger', add yourself to the plugdev (or video) group "
             "and replug the DIGIT")


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
    bus: int | None = None           # USB bus number and device address (sysfs busnum/devnum, pyusb bus/address)
    address: int | None = None

    @property
    def firmware_revision(self) -> int | None:
        """bcdDevice as an integer (e.g. "0203" -> 203), None if unknown."""
        try:
            return int(self.firmware, 10) if self.firmware else None
        except ValueError:
            return None

    @property
    def serial_known(self) -> bool:
        """Whether ``serial`` is the unit's own (not a placeholder for a DIGIT whose serial could not be read)."""
        return bool(self.serial) and not self.serial.startswith("unknown@")

    def problem(self) -> str:
        """Why this DIGIT cannot be opened as it is and what to do; "" when it can (as far as discovery can tell)."""
        if self.mode == "dfu":
            return "in DFU mode (USB 0403:0fde): flash the DIGIT firmware, then replug it"
        if not self.path:
            if self.readable is False:
                return (f"on USB ({self.usb_path}) but its serial cannot be read (no permission on the USB device) and "
                        f"it has no video node: add the udev rules (docs/sensors.md: {USB_UDEV_RULE}), replug it, and "
                        f"check that the uvcvideo module is loaded (lsmod | grep uvcvideo)")
            return ("on USB but has no video node: load the uvcvideo module (sudo modprobe uvcvideo) and replug it "
                    "with a USB 2.0 data cable")
        if not os.path.lexists(self.path):
            return (f"sysfs lists it, but {self.path} does not exist: in a container pass the device in (docker run "
                    f"--device {self.path}); otherwise udev did not create the node (check `udevadm monitor` while "
                    f"replugging)")
        if self.readable is False:
            return (f"permission denied on {self.path}: add the udev rule {UDEV_RULE} to "
                    f"/etc/udev/rules.d/50-DIGIT.rules, reload udev, join the plugdev (or video) group and replug it")
        return ""

    def params(self) -> dict[str, Any]:
        """The digit node's params that open this DIGIT: its serial, or its node when the serial is unknown."""
        if self.serial_known:
            return {"serial": self.serial}
        return {"source": self.path} if self.path else {}

    def as_device(self) -> dict[str, Any]:
        """The entry for ``teletouch devices``: ``details`` names the plugin and the ``params`` that select this
        DIGIT in a graph, and ``problem`` when it cannot be opened as it is."""
        d = asdict(self)
        details = {k: d[k] for k in ("firmware", "product", "manufacturer", "usb_path", "mode", "readable")}
        details.update(self.details)
        details["plugin"] = "digit"
        details["params"] = self.params()
        problem = self.problem()
        if problem:
            details["problem"] = problem
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


def _read_int(p: Path) -> int | None:
    try:
        return int(_read(p), 10)
    except ValueError:
        return None


def _video_index(name: str) -> int:
    try:
        return int(name[5:])
    except ValueError:
        return 1 << 30


def scan_sysfs(sysfs_root: str | os.PathLike = "/sys", dev_root: str | os.PathLike = "/dev") -> list[DigitInfo]:
    """DIGITs with a video4linux capture node, in /dev/videoN order: one per USB device (two units that report the
    same serial are both listed). No video4linux class (no camera driver loaded, or no such tree) is no DIGIT; a
    class folder that cannot be listed raises HardwareError naming it."""
    base = Path(sysfs_root) / "class" / "video4linux"
    if not base.is_dir():
        return []
    try:
        entries = list(base.iterdir())
    except OSError as exc:
        raise HardwareError(f"cannot list {base} ({exc.strerror or exc}): DIGIT discovery reads the video4linux "
                            f"devices there (in a container, mount the host's /sys)") from None
    found: dict[Path, DigitInfo] = {}
    for vd in sorted(entries, key=lambda p: _video_index(p.name)):
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
            details={"name": _read(vd / "name")}, bus=_read_int(usb / "busnum"), address=_read_int(usb / "devnum"))
    return list(found.values())


class UsbScanError(Exception):
    """The USB bus could not be scanned (pyusb missing, no libusb backend, enumeration failed); says why."""


def _pyusb_devices() -> list[Any]:
    """USB devices with the DIGIT's ids (camera or DFU). Raises UsbScanError saying why the bus cannot be scanned."""
    try:
        import usb.core
    except Exception as exc:  # ImportError, or a broken installation raising anything at import
        raise UsbScanError(f"pyusb cannot be imported ({type(exc).__name__}: {exc}; pip install pyusb)") from None
    out: list[Any] = []
    try:
        for vid, pid in ((DIGIT_VID, DIGIT_PID), (DFU_VID, DFU_PID)):
            out.extend(usb.core.find(find_all=True, idVendor=vid, idProduct=pid) or [])
    except Exception as exc:
        if type(exc).__name__ == "NoBackendError":
            raise UsbScanError("pyusb found no libusb backend (install libusb-1.0: apt install libusb-1.0-0)") from None
        raise UsbScanError(f"USB enumeration failed ({type(exc).__name__}: {exc})") from None
    return out


def scan_usb(find: Callable[[], Iterable[Any]] = _pyusb_devices) -> list[DigitInfo]:
    """DIGITs on the USB bus (pyusb). Serial strings need read access to the USB device; unreadable ones are
    reported with readable=False."""
    out = []
    for dev in find():
        bus, addr = getattr(dev, "bus", None), getattr(dev, "address", None)
        vid, pid = int(getattr(dev, "idVendor", 0)), int(getattr(dev, "idProduct", 0))
        mode = "dfu" if (vid, pid) == (DFU_VID, DFU_PID) else "camera"
        readable: bool | None = True
        try:
            serial = dev.serial_number or ""
        except Exception:  # ValueError (no langid: permission), usb.core.USBError
            serial, readable = "", False
        bcd = getattr(dev, "bcdDevice", None)
        b, a = ("?" if bus is None else bus), ("?" if addr is None else addr)
        out.append(DigitInfo(serial=serial or f"unknown@bus{b}-dev{a}", path=None,
                             firmware=f"{bcd:04x}" if isinstance(bcd, int) else "", mode=mode,
                             usb_path=f"bus {b} device {a}", readable=readable,
                             bus=bus if isinstance(bus, int) else None,
                             address=addr if isinstance(addr, int) else None))
    return out


def _same_device(u: DigitInfo, digits: list[DigitInfo]) -> bool:
    """Whether the USB-only entry ``u`` is one of ``digits`` (found through sysfs). By bus and address when sysfs gave
    them for every one (two units with the same serial, or one whose serial pyusb cannot read, are told apart);
    otherwise by serial, and an unreadable camera-mode one counts as known when any DIGIT has a node."""
    if u.bus is not None and u.address is not None and all(d.bus is not None for d in digits):
        return any((d.bus, d.address) == (u.bus, u.address) for d in digits)
    if u.serial in {d.serial for d in digits}:
        return True
    return u.mode == "camera" and not u.serial_known and len(digits) > 0


def find_digits(sysfs_root: str | os.PathLike = "/sys", dev_root: str | os.PathLike = "/dev",
                usb_find: Callable[[], Iterable[Any]] | None = _pyusb_devices,
                problems: list[str] | None = None) -> list[DigitInfo]:
    """All DIGITs this machine can see: the video nodes first, then USB-only ones (no node, or DFU mode).

    A sysfs that cannot be listed raises HardwareError; a USB bus that cannot be scanned is skipped (the video nodes
    are what a run needs). With a ``problems`` list, both reasons are appended to it instead (and the other source is
    still read), for :func:`discover`."""
    try:
        digits = scan_sysfs(sysfs_root, dev_root)
    except HardwareError as exc:
        if problems is None:
            raise
        problems.append(str(exc))
        digits = []
    if usb_find is not None:
        try:
            on_usb = scan_usb(usb_find)
        except Exception as exc:  # UsbScanError, or an injected finder's own error
            if problems is not None:
                problems.append(f"USB not scanned: {exc}; DIGITs in DFU mode or without a video node are not listed")
            on_usb = []
        sysfs_digits = list(digits)
        for u in on_usb:
            if not _same_device(u, sysfs_digits):
                digits.append(u)
    return digits


def discover(sysfs_root: str | os.PathLike = "/sys", dev_root: str | os.PathLike = "/dev",
             usb_find: Callable[[], Iterable[Any]] | None = _pyusb_devices) -> list[dict[str, Any]]:
    """The rows of ``teletouch devices`` for DIGITs (never raises): one per DIGIT (:meth:`DigitInfo.as_device`), then
    one ``error`` row per source that could not be read. Units that report the same serial get ``source`` params
    (their node) and a problem saying so, since ``serial`` cannot tell them apart."""
    problems: list[str] = []
    try:
        digits = find_digits(sysfs_root, dev_root, usb_find, problems)
    except Exception as exc:  # a defect in discovery itself: still a row, not a traceback
        return [{"kind": "digit", "id": "", "path": "", "error": f"DIGIT discovery failed: {type(exc).__name__}: "
                                                                 f"{exc}"}]
    rows = []
    for d in digits:
        row = d.as_device()
        twins = [o for o in digits if o.serial == d.serial]
        if d.serial_known and len(twins) > 1:
            det = row["details"]
            det["params"] = {"source": d.path} if d.path else {}
            det.setdefault("problem", f"{len(twins)} DIGITs report serial {d.serial}: select this one by its node "
                                      f"(source: {d.path})" if d.path else
                           f"{len(twins)} DIGITs report serial {d.serial} and this one has no video node")
        rows.append(row)
    rows.extend({"kind": "digit", "id": "", "path": "", "error": p} for p in problems)
    return rows


def describe(digits: Iterable[DigitInfo]) -> str:
    """One line per DIGIT, for error messages."""
    lines = []
    for d in digits:
        where = d.path or ("DFU mode: flash the DIGIT firmware" if d.mode == "dfu" else "no video node")
        fw = f", firmware {d.firmware}" if d.firmware else ""
        lines.append(f"{d.serial} ({where}{fw})")
    return ", ".join(lines) if lines else "none"
