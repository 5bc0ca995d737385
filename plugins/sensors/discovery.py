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

Whether a device node can be used is told by :func:`check_node`, the one check that ``teletouch devices`` and the
drivers' messages (digit, dynamixel-gripper, hid-leader) share: ``os.access`` alone answered only for the node's
owner, group and mode (and root always passes it), while open() can still fail: a nodev mount (a rootless
container's /dev: EACCES), an AppArmor rule, a node left over from an unplugged device (ENXIO/ENODEV), a device held
exclusively by another process (EBUSY). So the node is opened the way the drivers open it (:data:`OPEN_FLAGS`) and
closed at once, never read or written, and the errno is named with what it means (:func:`errno_meaning`). A serial
port is not opened (``open_node=False``): the kernel raises DTR and RTS when a tty is opened (O_NONBLOCK does not
stop it) and drops them at the close (HUPCL), and that pulse resets an Arduino-like board on the port. It gets the
checks that need no open instead: access(2) with its errno, a nodev mount, and (Linux sysfs) whether a device is
registered behind the node's major:minor; the driver's own open (pyserial) then reports its errno through the same
meanings.
"""

from __future__ import annotations

import ctypes
import errno as _errno
import os
import stat
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

#: How the drivers open their device nodes, and so how :func:`check_node` tries them: OpenCV's V4L2 capture opens
#: O_RDWR | O_NONBLOCK, hidapi's hidraw backend and libusb O_RDWR (| O_CLOEXEC), pyserial O_RDWR | O_NOCTTY |
#: O_NONBLOCK. O_NONBLOCK: the open never waits (a tty waiting for carrier detect); O_NOCTTY: a tty never becomes
#: this process's controlling terminal (without it a session leader that has none takes it, and a hang-up on the
#: port then sends it SIGHUP); O_CLOEXEC: no child process inherits the descriptor in between.
OPEN_FLAGS = os.O_RDWR | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC

PERMISSION_ERRNOS = frozenset({_errno.EACCES, _errno.EPERM})
BUSY_ERRNOS = frozenset({_errno.EBUSY})
GONE_ERRNOS = frozenset({_errno.ENOENT, _errno.ENODEV, _errno.ENXIO})

_MEANINGS = {
    _errno.EACCES: "permission denied: the node's owner, group and mode, or an AppArmor/SELinux rule or a nodev mount "
                   "(a container's /dev)",
    _errno.EPERM: "not permitted: a device rule (the device cgroup of a container) refuses this device",
    _errno.EBUSY: "busy: another process holds the device exclusively",
    _errno.ENOENT: "gone: the node does not exist",
    _errno.ENODEV: "gone: no device behind the node (unplugged, or a node left over from an earlier device)",
    _errno.ENXIO: "gone: no device behind the node (unplugged, or a node left over from an earlier device)",
    _errno.EISDIR: "a directory, not a device node",
}


def errno_meaning(err: int | None) -> str:
    """What an errno of open() on a device node means, in words ("" for None)."""
    if err is None:
        return ""
    return _MEANINGS.get(err) or os.strerror(err)


def errno_name(err: int | None) -> str:
    """The symbolic name of ``err`` (e.g. "EACCES"), or "errno N"."""
    if err is None:
        return ""
    return _errno.errorcode.get(err, f"errno {err}")


@dataclass(frozen=True)
class NodeAccess:
    """What :func:`check_node` found for one device node."""

    path: str
    errno: int | None = None       # why it cannot be used; None: it can (as far as checked)
    opened: bool = True            # whether the check opened the node (False: a serial port, or refused before)
    detail: str = ""               # what told (e.g. "access(2)", "a nodev mount"), for the message
    major: int | None = None       # the node's device major (for a container's device rule), None if unknown

    @property
    def readable(self) -> bool | None:
        """True: it can be opened; False: it cannot; None: there is no such node."""
        if self.errno is None:
            return True
        return None if self.errno == _errno.ENOENT else False

    @property
    def cause(self) -> str:
        """"" (usable), "permission", "busy", "gone" or "other"."""
        e = self.errno
        if e is None:
            return ""
        return ("permission" if e in PERMISSION_ERRNOS else "busy" if e in BUSY_ERRNOS else
                "gone" if e in GONE_ERRNOS else "other")

    def why(self) -> str:
        """The errno, its meaning and what told, e.g. "EPERM from open(): not permitted: ..."."""
        if self.errno is None:
            return ""
        src = f" from {self.detail}" if self.detail else ""
        return f"{errno_name(self.errno)}{src}: {errno_meaning(self.errno)}"

    def container_hint(self) -> str:
        """How a container is given this device."""
        rule = f", or for a device that comes and goes --device-cgroup-rule='c {self.major}:* rmw'" \
            if self.major is not None else ""
        return f"in a container, pass it in (docker run --device {self.path}{rule})"

    def problem(self, permission_fix: str) -> str:
        """Why the node cannot be used and what to do ("" when it can); ``permission_fix`` is the driver's way to
        get access (its udev rule or group), given for EACCES/EPERM."""
        cause, p = self.cause, self.path
        if cause == "permission":
            if self.errno == _errno.EPERM:
                return f"permission denied on {p}: {self.container_hint()} ({self.why()}); outside a container, " \
                       f"{permission_fix}"
            return f"permission denied on {p}: {permission_fix} ({self.why()}); {self.container_hint()}"
        if cause == "busy":
            return f"{p} is in use ({self.why()}): close the other program (`fuser -v {p}` names it)"
        if cause == "gone":
            return (f"no device behind {p} ({self.why()}): replug it; in a container, start it again with the "
                    f"device passed in (a node in its /dev outlives the device)")
        if cause == "other":
            return f"cannot open {p} ({self.why()})"
        return ""


def _access_errno(path: str, mode: int) -> int | None:
    """access(2) of ``path`` for ``mode``: None when allowed, else its errno (EACCES: owner/group/mode or an LSM;
    EPERM: the device cgroup); os.access decides (it is what was asked before) and libc tells the errno."""
    if os.access(path, mode):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.access(os.fsencode(path), mode) != 0:
            return ctypes.get_errno() or _errno.EACCES
    except (OSError, AttributeError, TypeError):
        pass
    return _errno.EACCES


def _nodev(path: str) -> bool:
    """Whether the file system holding ``path`` is mounted nodev (no device node on it can be opened)."""
    try:
        return bool(os.statvfs(path).f_flag & getattr(os, "ST_NODEV", 4))
    except (OSError, AttributeError):
        return False


def check_node(path: str | os.PathLike, flags: int = OPEN_FLAGS, *, open_node: bool = True,
               sysfs_root: str | os.PathLike = "/sys") -> NodeAccess:
    """Whether ``path`` can be opened with ``flags`` (a driver's flags, :data:`OPEN_FLAGS` by default), and if not,
    the errno. In order: the node exists (ENOENT) and is no directory (EISDIR); access(2) allows it (its own
    errno); it is not on a nodev mount (EACCES); then it is opened and closed at once, never read or written
    (open()'s errno). With ``open_node=False`` (a serial port: opening it pulses DTR) the open is left out and a
    character device whose major:minor has no entry in ``<sysfs_root>/dev/char`` is ENXIO (nothing registered
    behind it) where that folder exists."""
    p = os.fspath(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        return NodeAccess(p, exc.errno or _errno.ENOENT, opened=False, detail="stat()")
    if stat.S_ISDIR(st.st_mode):
        return NodeAccess(p, _errno.EISDIR, opened=False, detail="stat()")
    device = stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
    major = os.major(st.st_rdev) if device else None
    acc = flags & os.O_ACCMODE
    mode = os.R_OK if acc == os.O_RDONLY else os.W_OK if acc == os.O_WRONLY else os.R_OK | os.W_OK
    err = _access_errno(p, mode)
    if err is not None:
        return NodeAccess(p, err, opened=False, detail="access(2)", major=major)
    if device and _nodev(p):
        return NodeAccess(p, _errno.EACCES, opened=False, detail="a nodev mount (no device node on that file system "
                                                                  "can be opened)", major=major)
    if not open_node:
        char_dir = Path(sysfs_root) / "dev" / "char"
        if stat.S_ISCHR(st.st_mode) and char_dir.is_dir():
            mm = f"{os.major(st.st_rdev)}:{os.minor(st.st_rdev)}"
            if not (char_dir / mm).exists():
                return NodeAccess(p, _errno.ENXIO, opened=False, detail=f"sysfs (no {char_dir / mm})", major=major)
        return NodeAccess(p, None, opened=False, major=major)
    try:
        fd = os.open(p, flags)
    except OSError as exc:
        return NodeAccess(p, exc.errno, detail="open()", major=major)
    os.close(fd)
    return NodeAccess(p, None, major=major)


PERMISSION_FIX = (f"add the udev rule {UDEV_RULE} to /etc/udev/rules.d/50-DIGIT.rules, reload udev, join the "
                  f"plugdev (or video) group and replug it")


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
    access: NodeAccess | None = None  # what check_node found for the video node (None: not checked)

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
            acc = self.access or NodeAccess(self.path, _errno.EACCES, opened=False)
            return acc.problem(PERMISSION_FIX)
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
        if self.access is not None and self.access.errno is not None:
            details["access"] = self.access.why()
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


def scan_sysfs(sysfs_root: str | os.PathLike = "/sys", dev_root: str | os.PathLike = "/dev",
               check_access: bool = True) -> list[DigitInfo]:
    """DIGITs with a video4linux capture node, in /dev/videoN order: one per USB device (two units that report the
    same serial are both listed), each node tried with :func:`check_node` (``check_access=False``: not, for a
    lookup mid-run). No video4linux class (no camera driver loaded, or no such tree) is no DIGIT; a class folder that
    cannot be listed raises HardwareError naming it."""
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
        access = check_node(node, sysfs_root=sysfs_root) if check_access and os.path.lexists(node) else None
        found[usb] = DigitInfo(
            serial=serial, path=str(node), firmware=_read(usb / "bcdDevice"), product=_read(usb / "product"),
            manufacturer=_read(usb / "manufacturer"), usb_path=usb.name,
            readable=None if access is None else access.readable, access=access,
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
