"""A small ctypes binding of Force Dimension's device library (libdhd), loaded only when asked for.

Only the calls a teleoperation leader needs are bound, with the C signatures of the SDK's ``dhd.h`` (every device
call takes a trailing ``char ID``; -1 means the default device). Return codes: 0 ok, 1 ``DHD_TIMEGUARD`` (the call
came too soon after the previous one and was skipped: not an error), 2 ``DHD_MOTOR_SATURATED`` (the force was
clipped by the device), -1 error (the reason from ``dhdErrorGetLastStr``).

Where the library is looked for, in order:

1. ``sdk_path`` given to :func:`load` (the ``omega7`` parameter of the same name): a library file, or an SDK folder;
   when given, it is the only place used (a path that does not exist, or without a library that loads, is the
   error);
2. the ``FORCEDIM_SDK`` environment variable (an SDK folder or a library file), as forcedimension-core uses;
3. the system's library path (``ctypes.util.find_library("dhd")``, e.g. after copying libdhd.so to /usr/local/lib).

Errors say whether the *SDK* (library) or the *device* is missing, and how to fix it.

The device firmware's watchdog (``dhdSetWatchdog``/``dhdGetWatchdog``, SDK 3.3.2 and newer) is bound when the library
has it (:meth:`Dhd.has_watchdog`): a duration in units of 125 us (:data:`WATCHDOG_UNIT`, 1..255; 0 = off) after which
the device disables forces by itself if no new force command arrived. ``dhdGetSerialNumber`` is bound when the
library has it too (:meth:`Dhd.serial_at`: the serial number ``teletouch devices`` suggests instead of the index).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import sys
import threading
from pathlib import Path
from typing import Any, Iterator

from teletouch import HardwareError

__all__ = [
    "DHD_TIMEGUARD", "DHD_MOTOR_SATURATED", "OMEGA7_RIGHT", "OMEGA7_LEFT", "SYSTEM_NAMES", "WATCHDOG_UNIT",
    "WATCHDOG_MAX_UNITS",
    "DhdError", "SdkNotFoundError", "DeviceNotFoundError", "DeviceLostError", "Dhd", "load", "candidates",
]

DHD_OK = 0
DHD_TIMEGUARD = 1
DHD_MOTOR_SATURATED = 2
# error codes (dhdc.h)
DHD_ERROR_COM = 2
DHD_ERROR_NO_DRIVER_FOUND = 4
DHD_ERROR_NO_DEVICE_FOUND = 5
DHD_ERROR_TIMEOUT = 7
# the firmware watchdog (dhdSetWatchdog): its duration counts in units of 125 us, in an unsigned char
WATCHDOG_UNIT = 125e-6  # s
WATCHDOG_MAX_UNITS = 255
# system types (dhdc.h)
OMEGA3 = 33
OMEGA6_RIGHT = 34
OMEGA7_RIGHT = 35
OMEGA6_LEFT = 36
OMEGA7_LEFT = 37
SIGMA7_RIGHT = 104  # DHD_DEVICE_SIGMA331
SIGMA7_LEFT = 105  # DHD_DEVICE_SIGMA331_LEFT
SYSTEM_NAMES = {OMEGA3: "omega.3", OMEGA6_RIGHT: "omega.6 right", OMEGA7_RIGHT: "omega.7 right",
                OMEGA6_LEFT: "omega.6 left", OMEGA7_LEFT: "omega.7 left", SIGMA7_RIGHT: "sigma.7 right",
                SIGMA7_LEFT: "sigma.7 left"}
LEFT_HANDED = {OMEGA6_LEFT, OMEGA7_LEFT, SIGMA7_LEFT}
WITH_GRIPPER = {OMEGA7_RIGHT, OMEGA7_LEFT, SIGMA7_RIGHT, SIGMA7_LEFT}

INSTALL_HINT = ("install the Force Dimension SDK (https://www.forcedimension.com/software/sdk) and give its folder "
                "with the omega7 parameter sdk_path: or the environment variable FORCEDIM_SDK=/path/to/sdk")
DEVICE_HINT = ("check that the device is powered (front LED on), its USB cable is plugged in, no other program "
               "(e.g. a Force Dimension demo or another teletouch) holds it, and on Linux that your user may access "
               "the USB device (the udev rule shipped with the SDK, or run once as root to test)")


class DhdError(HardwareError):
    """An error reported by libdhd (the message includes dhdErrorGetLastStr)."""

    def __init__(self, message: str, code: int | None = None):
        self.code = code
        super().__init__(message)


class SdkNotFoundError(DhdError):
    """The SDK's library could not be found or loaded."""


class DeviceNotFoundError(DhdError):
    """The library loaded but no device could be opened."""


class DeviceLostError(DhdError):
    """The device stopped answering during a run (USB unplugged, power lost)."""


# --------------------------------------------------------------------------------------------------- locating
_LIB_NAMES = {"linux": ("libdhd.so", "libdhd.so.3"), "darwin": ("libdhd.dylib",), "win32": ("dhdms64.dll", "dhd64.dll")}


def _names() -> tuple[str, ...]:
    for key, names in _LIB_NAMES.items():
        if sys.platform.startswith(key):
            return names
    return _LIB_NAMES["linux"]


_SUBDIRS = ("", "lib", "lib/release", "lib/release/lin-x86_64-gcc", "lib/release/lin-aarch64-gcc",
            "lib/release/mac-x86_64-clang", "lib/release/mac-arm64-clang", "bin")


def _libraries_under(root: Path) -> list[Path]:
    """The library files at ``root`` (a file) or under it (an SDK folder and its lib/ folders), in order."""
    if root.is_file():
        return [root]
    out: list[Path] = []
    for sub in _SUBDIRS:
        for name in _names():
            p = root / sub / name if sub else root / name
            if p.is_file():
                out.append(p)
        d = root / sub if sub else root
        if d.is_dir():
            out.extend(sorted(p for p in d.glob("libdhd.so.*") if p.is_file()))
    return out


def candidates(sdk_path: str | os.PathLike[str] | None = None) -> list[Path]:
    """The library files that :func:`load` would try, in order (only those that exist)."""
    roots: list[Path] = []
    if sdk_path:
        roots.append(Path(sdk_path).expanduser())
    env = os.environ.get("FORCEDIM_SDK")
    if env:
        roots.append(Path(env).expanduser())
    seen: set[Path] = set()
    uniq = []
    for root in roots:
        for p in _libraries_under(root):
            if p not in seen:
                seen.add(p)
                uniq.append(p)
    return uniq


def _where(label: str, value: str) -> str:
    """``label=value`` for an error message, saying when that path does not exist (a typo, an unmounted folder) or
    holds no library."""
    root = Path(value).expanduser()
    if not root.exists():
        return f"{label}={value} (does not exist)"
    if not _libraries_under(root):
        return f"{label}={value} (no {'/'.join(_names())} there, nor in lib/ or lib/release/<platform>/)"
    return f"{label}={value}"


def _try_load(paths: list[Path], tried: list[str]) -> "Dhd | None":
    for p in paths:
        try:
            return Dhd(ctypes.CDLL(str(p)), str(p))
        except OSError as exc:
            tried.append(f"{p} ({exc})")
    return None


def load(sdk_path: str | os.PathLike[str] | None = None) -> "Dhd":
    """Load libdhd (see the module docstring for where it is looked for). Raises :class:`SdkNotFoundError`, whose
    message names every place looked in and says which of the paths given do not exist.

    A ``sdk_path`` that is given is the only place used: when it has no library, or none that loads, that is the
    error (a library elsewhere, of another SDK version, is never taken instead)."""
    tried: list[str] = []
    if sdk_path:
        root = Path(sdk_path).expanduser()
        if not root.exists():
            raise SdkNotFoundError(f"Force Dimension SDK not found: sdk_path={sdk_path!s} does not exist (check the "
                                   f"path, and that its disk is mounted); {INSTALL_HINT}")
        lib = _try_load(_libraries_under(root), tried)
        if lib is not None:
            return lib
        if not tried:
            raise SdkNotFoundError(f"Force Dimension SDK not found: no {'/'.join(_names())} under sdk_path="
                                   f"{sdk_path!s} (nor in lib/ or lib/release/<platform>/ there); {INSTALL_HINT}")
        raise SdkNotFoundError(f"Force Dimension SDK (libdhd) under sdk_path={sdk_path!s} could not be loaded: "
                               f"{'; '.join(tried)}; {INSTALL_HINT}")
    env = os.environ.get("FORCEDIM_SDK")
    lib = _try_load(candidates(None), tried)
    if lib is not None:
        return lib
    found = ctypes.util.find_library("dhd")
    if found:
        try:
            return Dhd(ctypes.CDLL(found), found)
        except OSError as exc:
            tried.append(f"{found} ({exc})")
    looked = ", ".join(x for x in (_where("FORCEDIM_SDK", env) if env else "", "the system library path") if x)
    detail = f"; could not load: {'; '.join(tried)}" if tried else ""
    raise SdkNotFoundError(f"Force Dimension SDK (libdhd) not found (looked in {looked}){detail}; {INSTALL_HINT}")


# --------------------------------------------------------------------------------------------------- binding
_c = ctypes
_D = _c.c_double
_PD = _c.POINTER(_c.c_double)
_ID = _c.c_byte  # C "char ID"

# name: (restype, argtypes); every device call ends with the char ID
_SIGNATURES: dict[str, tuple[Any, list[Any]]] = {
    "dhdGetSDKVersion": (None, [_c.POINTER(_c.c_int)] * 4),  # void
    "dhdErrorGetLast": (_c.c_int, []),
    "dhdErrorGetLastStr": (_c.c_char_p, []),
    "dhdGetDeviceCount": (_c.c_int, []),
    "dhdOpen": (_c.c_int, []),
    "dhdOpenID": (_c.c_int, [_ID]),
    "dhdOpenSerial": (_c.c_int, [_c.c_int]),
    "dhdClose": (_c.c_int, [_ID]),
    "dhdGetSystemType": (_c.c_int, [_ID]),
    "dhdGetSerialNumber": (_c.c_int, [_c.POINTER(_c.c_ushort), _ID]),
    "dhdEnableForce": (_c.c_int, [_c.c_ubyte, _ID]),
    "dhdSetBrakes": (_c.c_int, [_c.c_int, _ID]),
    "dhdSetGravityCompensation": (_c.c_int, [_c.c_int, _ID]),
    "dhdSetMaxForce": (_c.c_int, [_D, _ID]),
    "dhdSetMaxGripperForce": (_c.c_int, [_D, _ID]),
    "dhdGetPosition": (_c.c_int, [_PD, _PD, _PD, _ID]),
    "dhdGetGripperGap": (_c.c_int, [_PD, _ID]),
    "dhdGetGripperAngleRad": (_c.c_int, [_PD, _ID]),
    "dhdGetGripperLinearVelocity": (_c.c_int, [_PD, _ID]),
    "dhdSetForceAndGripperForce": (_c.c_int, [_D, _D, _D, _D, _ID]),
    "dhdGetButton": (_c.c_int, [_c.c_int, _ID]),
    "dhdGetComFreq": (_D, [_ID]),
    "dhdGetStatus": (_c.c_int, [_c.POINTER(_c.c_int), _ID]),  # int status[DHD_MAX_STATUS]
    "dhdEnableExpertMode": (_c.c_int, []),
    "dhdDisableExpertMode": (_c.c_int, []),
    "dhdSetWatchdog": (_c.c_int, [_c.c_ubyte, _ID]),  # added in release 3.3.2 (an expert SDK call)
    "dhdGetWatchdog": (_c.c_int, [_c.POINTER(_c.c_ubyte), _ID]),  # added in release 3.3.2 (an expert SDK call)
}
_OPTIONAL = {"dhdGetSDKVersion", "dhdErrorGetLast", "dhdGetDeviceCount", "dhdGetGripperAngleRad", "dhdSetWatchdog",
             "dhdGetWatchdog", "dhdGetStatus", "dhdEnableExpertMode", "dhdDisableExpertMode", "dhdGetSerialNumber",
             # not in SDK 3.7.0's dhdc.h (later ones have them): without them the driver's own force guard is the
             # only limit (see Dhd.set_max_force)
             "dhdSetMaxForce", "dhdSetMaxGripperForce"}
# dhdGetStatus: DHD_MAX_STATUS entries (16 in older SDKs, 17 since DHD_STATUS_AXISCHECKED, e.g. SDK 3.11); the
# buffer has room for more, as the SDK writes as many as its own dhdc.h says; the ones read here, and the causes of the
# FORCE OFF state (dhdc.h)
DHD_MAX_STATUS = 17
_STATUS_SLOTS = 32
DHD_STATUS_FORCE = 5
DHD_STATUS_FORCEOFFCAUSE = 14
FORCEOFF_CAUSES = {0: "none", 1: "the force button", 2: "the velocity threshold", 3: "the firmware watchdog",
                   4: "software", 5: "USB disconnection", 6: "the dead-man switch"}
DHD_FORCEOFF_WATCHDOG = 3


class Dhd:
    """One loaded libdhd and (after :meth:`open`) one device. Methods raise :class:`DhdError` on -1."""

    def __init__(self, lib: Any, path: str):
        self.lib = lib
        self.path = path
        missing = []
        for name, (res, args) in _SIGNATURES.items():
            fn = getattr(lib, name, None)
            if fn is None:
                if name not in _OPTIONAL:
                    missing.append(name)
                continue
            fn.restype = res
            fn.argtypes = args
        if missing:
            raise SdkNotFoundError(f"{path} is not a usable libdhd: missing {', '.join(missing)} "
                                   f"(an SDK older than 3.x, or not Force Dimension's library); {INSTALL_HINT}")
        self.id = -1
        self._x, self._y, self._z, self._g, self._v = (_D() for _ in range(5))
        self._px, self._py, self._pz = _c.byref(self._x), _c.byref(self._y), _c.byref(self._z)
        self._pg, self._pv = _c.byref(self._g), _c.byref(self._v)
        # bound functions, looked up once (the hot path)
        self._get_position = lib.dhdGetPosition
        self._get_gap = lib.dhdGetGripperGap
        self._get_gvel = lib.dhdGetGripperLinearVelocity
        self._set_forces = lib.dhdSetForceAndGripperForce
        self._get_button = lib.dhdGetButton
        self.lock = threading.Lock()

    # ------------------------------------------------------------------------------------------------ errors
    def last_error(self) -> tuple[int | None, str]:
        code = None
        f = getattr(self.lib, "dhdErrorGetLast", None)
        if f is not None:
            try:
                code = int(f())
            except Exception:  # pragma: no cover - defensive
                code = None
        try:
            s = self.lib.dhdErrorGetLastStr()
            text = s.decode(errors="replace") if s else "unknown error"
        except Exception:  # pragma: no cover - defensive
            text = "unknown error"
        return code, text

    def error(self, call: str) -> DhdError:
        code, text = self.last_error()
        if code in (DHD_ERROR_COM, DHD_ERROR_TIMEOUT):
            return DeviceLostError(f"{call} failed: {text} (error {code}); the device stopped answering: "
                                   f"{DEVICE_HINT}", code)
        return DhdError(f"{call} failed: {text} (error {code})", code)

    def _check(self, rc: int, call: str) -> int:
        if rc < 0:
            raise self.error(call)
        return rc

    # ------------------------------------------------------------------------------------------------ setup
    def sdk_version(self) -> str:
        f = getattr(self.lib, "dhdGetSDKVersion", None)
        if f is None:
            return "unknown"
        v = [_c.c_int() for _ in range(4)]
        f(*[_c.byref(x) for x in v])
        return ".".join(str(x.value) for x in v[:3])

    def device_count(self) -> int | None:
        f = getattr(self.lib, "dhdGetDeviceCount", None)
        return None if f is None else int(f())

    def open(self, serial: int | None = None, index: int | None = None) -> int:
        """Open the device by serial number, by index, or the first one found. Raises DeviceNotFoundError."""
        if serial is not None:
            rc, what = self.lib.dhdOpenSerial(int(serial)), f"serial number {serial}"
        elif index is not None:
            rc, what = self.lib.dhdOpenID(int(index)), f"index {index}"
        else:
            rc, what = self.lib.dhdOpen(), "any"
        if rc < 0:
            code, text = self.last_error()
            n = self.device_count()
            seen = "" if n is None else f"; devices seen by the SDK: {n}"
            raise DeviceNotFoundError(f"libdhd loaded ({self.path}, SDK {self.sdk_version()}) but no Force "
                                      f"Dimension device could be opened ({what}): {text}{seen}; {DEVICE_HINT}",
                                      code)
        self.id = rc
        return rc

    def close(self) -> None:
        self._check(self.lib.dhdClose(self.id), "dhdClose")

    def has_serial_number(self) -> bool:
        """Whether this libdhd has dhdGetSerialNumber."""
        return getattr(self.lib, "dhdGetSerialNumber", None) is not None

    def serial_number(self) -> int | None:
        """The open device's serial number (dhdGetSerialNumber: what ``open(serial=...)`` takes), or None when this
        SDK has no dhdGetSerialNumber. Raises DhdError on -1."""
        f = getattr(self.lib, "dhdGetSerialNumber", None)
        if f is None:
            return None
        sn = _c.c_ushort()
        self._check(f(_c.byref(sn), self.id), "dhdGetSerialNumber")
        return int(sn.value)

    def serial_at(self, index: int) -> int | None:
        """The serial number of the device at ``index`` (the SDK's enumeration order), for listing the devices: the
        device is opened (dhdOpenID), read and closed again, nothing else set on it. None when this SDK has no
        dhdGetSerialNumber (the device is then not opened). Raises DhdError when the device cannot be opened (e.g.
        another program holds it) or read."""
        if not self.has_serial_number():
            return None
        rc = self.lib.dhdOpenID(int(index))
        if rc < 0:
            code, text = self.last_error()
            raise DhdError(f"dhdOpenID({index}) failed: {text} (error {code})", code)
        was, self.id = self.id, rc
        try:
            return self.serial_number()
        finally:
            try:
                self.lib.dhdClose(rc)
            finally:
                self.id = was

    def system_type(self) -> int:
        return self._check(self.lib.dhdGetSystemType(self.id), "dhdGetSystemType")

    def enable_force(self, on: bool) -> None:
        self._check(self.lib.dhdEnableForce(1 if on else 0, self.id), "dhdEnableForce")

    def set_brakes(self, on: bool) -> None:
        self._check(self.lib.dhdSetBrakes(1 if on else 0, self.id), "dhdSetBrakes")

    def set_gravity_compensation(self, on: bool) -> None:
        self._check(self.lib.dhdSetGravityCompensation(1 if on else 0, self.id), "dhdSetGravityCompensation")

    def set_max_force(self, newtons: float) -> bool:
        """The SDK's own force limit (a second layer under the driver's guard); False where this SDK has no
        dhdSetMaxForce (SDK 3.7.0's dhdc.h has none)."""
        return self._set_limit("dhdSetMaxForce", newtons)

    def set_max_gripper_force(self, newtons: float) -> bool:
        """As :meth:`set_max_force`, for the gripper (dhdSetMaxGripperForce)."""
        return self._set_limit("dhdSetMaxGripperForce", newtons)

    def _set_limit(self, name: str, newtons: float) -> bool:
        f = getattr(self.lib, name, None)
        if f is None:
            return False
        self._check(f(float(newtons), self.id), name)
        return True

    def has_watchdog(self) -> bool:
        """Whether this libdhd has the firmware watchdog calls (SDK 3.3.2 and newer)."""
        return getattr(self.lib, "dhdSetWatchdog", None) is not None

    def set_watchdog(self, units: int) -> None:
        """Set the device firmware's watchdog to ``units`` x 125 us (0 switches it off). Raises DhdError on -1, and
        when this SDK has no dhdSetWatchdog."""
        if not 0 <= units <= WATCHDOG_MAX_UNITS:
            raise ValueError(f"watchdog units must be 0..{WATCHDOG_MAX_UNITS} (x 125 us), got {units}")
        f = getattr(self.lib, "dhdSetWatchdog", None)
        if f is None:
            raise DhdError(f"dhdSetWatchdog is not in this SDK ({self.path}, SDK {self.sdk_version()}; added in "
                           f"release 3.3.2)")
        with self._expert():
            self._check(f(units, self.id), "dhdSetWatchdog")

    def watchdog(self) -> int | None:
        """The device firmware's watchdog in units of 125 us (0: off), or None when this SDK has no dhdGetWatchdog."""
        f = getattr(self.lib, "dhdGetWatchdog", None)
        if f is None:
            return None
        v = _c.c_ubyte()
        with self._expert():
            self._check(f(_c.byref(v), self.id), "dhdGetWatchdog")
        return v.value

    @contextlib.contextmanager
    def _expert(self) -> Iterator[None]:
        """Expert mode around an expert SDK call (the watchdog's are declared among them), off again after it; a
        no-op with an SDK that has no dhdEnableExpertMode."""
        on = getattr(self.lib, "dhdEnableExpertMode", None)
        off = getattr(self.lib, "dhdDisableExpertMode", None)
        if on is None or off is None:
            yield
            return
        self._check(on(), "dhdEnableExpertMode")
        try:
            yield
        finally:
            off()

    def force_status(self) -> tuple[bool, int] | None:
        """(forces on, cause of the FORCE OFF state: one of FORCEOFF_CAUSES) from dhdGetStatus; None when this SDK
        has no dhdGetStatus."""
        f = getattr(self.lib, "dhdGetStatus", None)
        if f is None:
            return None
        st = (_c.c_int * _STATUS_SLOTS)()
        self._check(f(st, self.id), "dhdGetStatus")
        return bool(st[DHD_STATUS_FORCE]), int(st[DHD_STATUS_FORCEOFFCAUSE])

    def com_freq(self) -> float:
        """The SDK's measured communication rate, in Hz (the SDK reports kHz)."""
        return float(self.lib.dhdGetComFreq(self.id)) * 1e3

    # ------------------------------------------------------------------------------------------------ hot path
    def position(self) -> tuple[float, float, float]:
        if self._get_position(self._px, self._py, self._pz, self.id) < 0:
            raise self.error("dhdGetPosition")
        return self._x.value, self._y.value, self._z.value

    def gripper_gap(self) -> float:
        if self._get_gap(self._pg, self.id) < 0:
            raise self.error("dhdGetGripperGap")
        return self._g.value

    def gripper_angle(self) -> float:
        f = getattr(self.lib, "dhdGetGripperAngleRad", None)
        if f is None:
            raise DhdError("dhdGetGripperAngleRad is not in this SDK")
        a = _D()
        self._check(f(_c.byref(a), self.id), "dhdGetGripperAngleRad")
        return a.value

    def gripper_velocity(self) -> float:
        if self._get_gvel(self._pv, self.id) < 0:
            raise self.error("dhdGetGripperLinearVelocity")
        return self._v.value

    def set_forces(self, fx: float, fy: float, fz: float, fg: float) -> int:
        """Returns 0, DHD_TIMEGUARD or DHD_MOTOR_SATURATED; raises on -1."""
        rc = self._set_forces(fx, fy, fz, fg, self.id)
        if rc < 0:
            raise self.error("dhdSetForceAndGripperForce")
        return rc

    def button(self, index: int = 0) -> bool:
        rc = self._get_button(index, self.id)
        if rc < 0:
            raise self.error("dhdGetButton")
        return rc == 1
