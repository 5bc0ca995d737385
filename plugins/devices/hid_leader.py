"""Leader without force feedback: a USB HID device (3Dconnexion SpaceMouse, or a gamepad trigger) read with hidapi
and mapped to a gripper opening. Position-only teleoperation: ``gripper_force`` and ``force`` are accepted (so the
plugin swaps with ``omega7`` by one line of YAML) and ignored.

The report parsers are pure functions of the report bytes (tested on reports in the devices' documented layouts):

- SpaceMouse: report 1 = translation x, y, z (int16 little-endian; newer models append rotation in the same report),
  report 2 = rotation, report 3 = button bitmask. A SpaceMouse cap springs back to centre, so by default one axis
  drives the opening *rate* (integrated, with a dead band); ``mode: position`` maps deflection to opening directly.
- DualShock 4 / DualSense (USB and Bluetooth reports): the analog trigger (R2 by default) maps to the opening,
  released = ``max_opening``, fully pressed = ``min_opening``; the cross button is the button.
- ``generic``: any HID pad with an 8-bit trigger at a known byte (``report_id``, ``trigger_offset``, ``button_*``).

Lost device: a DualShock 4 / DualSense sends an input report every few ms for as long as it is connected (~250 Hz
over USB, 100 Hz and more over Bluetooth), so silence means the link is lost (a Bluetooth pad out of range gives no
read error until the kernel removes the device): after ``report_timeout`` (0.5 s by default) without a report, step()
raises HardwareError, and the outputs carry the time of the last report (not the step time), so consumers' staleness
checks (``max_age``) see a silent pad's data age. A SpaceMouse sends reports every few ms while its cap is deflected
and stops a few reports after the cap is back at rest (silence is normal at rest). In rate mode, the rate of a report
holds until the next report, for at most ``report_timeout`` (0.5 s by default); silence for longer while the last
report commanded a rate is a lost link: the opening stays where it was at the last report (the rate counts as zero
from then on) and step() raises HardwareError; while the cap moves, the outputs carry the time of the last report.
In position mode the same holds for the deflection: silence while deflected is a lost link (the opening would
otherwise stay at that deflection, out of the operator's control). At rest a SpaceMouse has no timeout and
step-time stamps. A ``generic`` pad has a timeout (and report-time stamps) only when ``report_timeout`` is set, for
a pad known to stream its reports. A report the parser does not read (another report id, too short) counts as none:
it neither stamps the outputs nor resets the timeout.
"""

from __future__ import annotations

import math
import os
import re
import struct
import sys
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import Device, HardwareError, Kind, Params, Sample, hookimpl
from teletouch.plugins.sensors import discovery  # the device-node checks shared with `teletouch devices`
from teletouch.units import Meters, MetersPerSecond, Seconds, plausible_opening, plausible_speed, plausible_travel

from .omega7 import LEADER_INPUTS, LEADER_OUTPUTS, OMEGA7_GRIPPER_RANGE

# --------------------------------------------------------------------------------------------------- known devices
# (vendor id, product id) -> (profile, name); from spacenavd's and Linux hid-sony/hid-playstation's device tables.
KNOWN_DEVICES: dict[tuple[int, int], tuple[str, str]] = {
    (0x046D, 0xC603): ("spacemouse", "SpaceMouse Plus XT"),
    (0x046D, 0xC605): ("spacemouse", "CadMan"),
    (0x046D, 0xC606): ("spacemouse", "SpaceMouse Classic"),
    (0x046D, 0xC621): ("spacemouse", "SpaceBall 5000"),
    (0x046D, 0xC623): ("spacemouse", "SpaceTraveler"),
    (0x046D, 0xC625): ("spacemouse", "SpacePilot"),
    (0x046D, 0xC626): ("spacemouse", "SpaceNavigator"),
    (0x046D, 0xC627): ("spacemouse", "SpaceExplorer"),
    (0x046D, 0xC628): ("spacemouse", "SpaceNavigator for Notebooks"),
    (0x046D, 0xC629): ("spacemouse", "SpacePilot Pro"),
    (0x046D, 0xC62B): ("spacemouse", "SpaceMouse Pro"),
    (0x256F, 0xC62E): ("spacemouse", "SpaceMouse Wireless (cable)"),
    (0x256F, 0xC62F): ("spacemouse", "SpaceMouse Wireless (receiver)"),
    (0x256F, 0xC631): ("spacemouse", "SpaceMouse Pro Wireless (cable)"),
    (0x256F, 0xC632): ("spacemouse", "SpaceMouse Pro Wireless (receiver)"),
    (0x256F, 0xC633): ("spacemouse", "SpaceMouse Enterprise"),
    (0x256F, 0xC635): ("spacemouse", "SpaceMouse Compact"),
    (0x256F, 0xC652): ("spacemouse", "3Dconnexion Universal Receiver"),
    (0x054C, 0x05C4): ("dualshock4", "DualShock 4"),
    (0x054C, 0x09CC): ("dualshock4", "DualShock 4 (v2)"),
    (0x054C, 0x0CE6): ("dualsense", "DualSense"),
    (0x054C, 0x0DF2): ("dualsense", "DualSense Edge"),
}

# profiles whose devices send input reports periodically while connected (silence = link lost), and the default
# report_timeout for them (also a SpaceMouse's in rate mode, while its cap is deflected); a generic pad is unknown (opt
# in with report_timeout)
PERIODIC_PROFILES = ("dualshock4", "dualsense")
DEFAULT_REPORT_TIMEOUT = 0.5
#: s: a periodic pad's gripper velocity is the opening's change since the newest report at least this old (their read
#: times; over one report pair, a step that came late and the next one a fraction of a ms after it turned one report's
#: travel into a spike: 4 ms of travel over 0.1 ms)
VELOCITY_WINDOW = 0.01

SPACEMOUSE_AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
SPACEMOUSE_FULL_SCALE = 350.0  # counts at full deflection (typical; some models reach ~500)


# --------------------------------------------------------------------------------------------------- parsing
@dataclass(frozen=True)
class SpaceMouseState:
    """Raw counts of the six axes and the button bitmask (as last reported)."""

    tx: int = 0
    ty: int = 0
    tz: int = 0
    rx: int = 0
    ry: int = 0
    rz: int = 0
    buttons: int = 0

    def axis(self, name: str) -> int:
        return getattr(self, name)


@dataclass(frozen=True)
class GamepadState:
    """Triggers in 0..1 (0 released) and named buttons."""

    l2: float = 0.0
    r2: float = 0.0
    cross: bool = False
    circle: bool = False
    square: bool = False
    triangle: bool = False
    l1: bool = False
    r1: bool = False

    def trigger(self, name: str) -> float:
        return getattr(self, name)


def _report(data: Any) -> bytes:
    return bytes(data)


def parse_spacemouse(report: Any, state: SpaceMouseState = SpaceMouseState()) -> SpaceMouseState:
    """Update ``state`` with one SpaceMouse report (report id first). Unknown or short reports leave it unchanged."""
    r = _report(report)
    if not r:
        return state
    rid = r[0]
    if rid == 1 and len(r) >= 7:
        tx, ty, tz = struct.unpack_from("<hhh", r, 1)
        state = replace(state, tx=tx, ty=ty, tz=tz)
        if len(r) >= 13:  # newer models: rotation in the same report
            rx, ry, rz = struct.unpack_from("<hhh", r, 7)
            state = replace(state, rx=rx, ry=ry, rz=rz)
        return state
    if rid == 2 and len(r) >= 7:
        rx, ry, rz = struct.unpack_from("<hhh", r, 1)
        return replace(state, rx=rx, ry=ry, rz=rz)
    if rid == 3 and len(r) >= 2:
        return replace(state, buttons=int.from_bytes(r[1:min(len(r), 5)], "little"))
    return state


def parse_dualshock4(report: Any, state: GamepadState = GamepadState()) -> GamepadState:
    """DualShock 4 input report: 0x01 over USB (64 bytes), 0x11 over Bluetooth (same layout two bytes later)."""
    r = _report(report)
    if len(r) < 10:
        return state
    if r[0] == 0x01:
        o = 0
    elif r[0] == 0x11 and len(r) >= 12:
        o = 2
    else:
        return state
    b5, b6 = r[5 + o], r[6 + o]
    return GamepadState(l2=r[8 + o] / 255.0, r2=r[9 + o] / 255.0, square=bool(b5 & 0x10), cross=bool(b5 & 0x20),
                        circle=bool(b5 & 0x40), triangle=bool(b5 & 0x80), l1=bool(b6 & 0x01), r1=bool(b6 & 0x02))


def parse_dualsense(report: Any, state: GamepadState = GamepadState()) -> GamepadState:
    """DualSense input report: 0x01 over USB, 0x31 over Bluetooth (same layout one byte later)."""
    r = _report(report)
    if len(r) < 11:
        return state
    if r[0] == 0x01:
        o = 0
    elif r[0] == 0x31 and len(r) >= 12:
        o = 1
    else:
        return state
    b8, b9 = r[8 + o], r[9 + o]
    return GamepadState(l2=r[5 + o] / 255.0, r2=r[6 + o] / 255.0, square=bool(b8 & 0x10), cross=bool(b8 & 0x20),
                        circle=bool(b8 & 0x40), triangle=bool(b8 & 0x80), l1=bool(b9 & 0x01), r1=bool(b9 & 0x02))


def parse_generic_trigger(report: Any, state: GamepadState, report_id: int | None, trigger_offset: int,
                          button_offset: int | None, button_mask: int) -> GamepadState:
    """A pad with an 8-bit trigger at ``trigger_offset`` (byte index in the report as read, report id included
    when the device uses report ids). The trigger goes to ``r2`` and the button to ``cross``."""
    r = _report(report)
    if report_id is not None and (not r or r[0] != report_id):
        return state
    if len(r) <= trigger_offset or (button_offset is not None and len(r) <= button_offset):
        return state
    cross = bool(r[button_offset] & button_mask) if button_offset is not None else False
    return replace(state, r2=r[trigger_offset] / 255.0, cross=cross)


def deadband(x: float, band: float) -> float:
    """Zero inside |x| <= band, then rescaled so that 1 still maps to 1."""
    if abs(x) <= band:
        return 0.0
    return math.copysign((abs(x) - band) / (1.0 - band), x) if band < 1.0 else 0.0


def trigger_to_opening(value: float, min_opening: float, max_opening: float) -> float:
    """Released trigger (0) = fully open, fully pressed (1) = closed."""
    v = min(max(value, 0.0), 1.0)
    return max_opening - v * (max_opening - min_opening)


def axis_to_unit(counts: int, full_scale: float, invert: bool) -> float:
    x = counts / full_scale
    x = min(max(x, -1.0), 1.0)
    return -x if invert else x


def deflection_to_opening(unit: float, band: float, min_opening: float, max_opening: float) -> float:
    """Position mode: the cap's deflection (-1..1, after the dead band) to the opening; centred (at rest) = half
    open."""
    return min_opening + 0.5 * (deadband(unit, band) + 1.0) * (max_opening - min_opening)


def integrate_rate(opening: float, unit: float, dt: float, max_speed: float, band: float, min_opening: float,
                   max_opening: float) -> tuple[float, float]:
    """Rate control: returns (new opening, velocity)."""
    v = deadband(unit, band) * max_speed
    x = opening + v * dt
    if x < min_opening:
        x, v = min_opening, 0.0
    elif x > max_opening:
        x, v = max_opening, 0.0
    return x, v


# --------------------------------------------------------------------------------------------------- enumeration
UDEV_HINT = ("give your user access to the device: create /etc/udev/rules.d/70-teletouch-hid.rules with "
             'KERNEL=="hidraw*", ATTRS{idVendor}=="%04x", MODE="0660", TAG+="uaccess" '
             "then run: sudo udevadm control --reload-rules && sudo udevadm trigger (and replug the device)")
#: the same for the USB device node (/dev/bus/usb/BBB/DDD) that hidapi's libusb backend opens: on Linux, pip's hidapi
#: module ``hid`` is built on libusb (its ``hidraw`` module on hidraw), and its paths look like "1-4.2:1.0"
USB_UDEV_HINT = ("give your user access to the USB device: create /etc/udev/rules.d/70-teletouch-hid.rules with "
                 'SUBSYSTEM=="usb", ATTRS{idVendor}=="%04x", MODE="0660", TAG+="uaccess" '
                 "then run: sudo udevadm control --reload-rules && sudo udevadm trigger (and replug the device)")
#: what hidapi's enumeration needs, from its sources (libusb/hid.c, linux/hid.c): neither backend opens the device to
#: list it (libusb reads the USB descriptors and lists the device even when libusb_open fails, only without its
#: strings; hidraw reads udev/sysfs), so a device you may not open is still listed, and one that is not listed is no
#: permission problem
ENUMERATION_NOTE = ("hidapi lists a device whether or not you may open it (permission shows when it is opened), so a "
                    "device missing here is not a permission problem")
_LIBUSB_PATH = re.compile(r"^(\d+)-([\d.]+):\d+\.\d+$")   # hidapi libusb: bus-port[.port...]:config.interface


def hid_path_text(path: Any) -> str:
    """A hidapi path (bytes) as text."""
    return path.decode(errors="replace") if isinstance(path, bytes) else str(path)


def device_node(path: str, sysfs_root: str | None = None, dev_root: str | None = None) -> str | None:
    """The device file that opening this hidapi path needs: the hidraw node itself, or for a libusb path
    ("1-4.2:1.0") the USB device node /dev/bus/usb/BBB/DDD (through sysfs busnum/devnum); None when it cannot be told.
    ``sysfs_root``/``dev_root`` default to $TELETOUCH_SYSFS_ROOT or /sys and $TELETOUCH_DEV_ROOT or /dev."""
    if path.startswith("/"):
        return path
    m = _LIBUSB_PATH.match(path)
    if m is None:
        return None
    sysfs = sysfs_root or os.environ.get("TELETOUCH_SYSFS_ROOT", "/sys")
    dev = dev_root or os.environ.get("TELETOUCH_DEV_ROOT", "/dev")
    usb = os.path.join(sysfs, "bus", "usb", "devices", f"{m.group(1)}-{m.group(2)}")
    try:
        with open(os.path.join(usb, "busnum")) as fb, open(os.path.join(usb, "devnum")) as fd:
            bus, num = int(fb.read().strip()), int(fd.read().strip())
    except (OSError, ValueError):
        return None
    return os.path.join(dev, "bus", "usb", f"{bus:03d}", f"{num:03d}")


def node_access(node: str | None) -> discovery.NodeAccess | None:
    """``node`` tried as hidapi opens it (O_RDWR; discovery.check_node: opened and closed at once, never read or
    written; opening a hidraw or USB device node changes nothing on the device); None when there is no node."""
    if node is None:
        return None
    return discovery.check_node(node)


def node_readable(node: str | None) -> bool | None:
    """Whether this user may open ``node`` for reading and writing; None when unknown (no node, or it is missing)."""
    acc = node_access(node)
    return None if acc is None else acc.readable


def udev_hint(vendor_id: int, node: str | None) -> str:
    """The udev rule that gives access to ``node``: the hidraw rule for a hidraw node, else the USB one."""
    hidraw = node is not None and os.path.basename(node).startswith("hidraw")
    return (UDEV_HINT if hidraw else USB_UDEV_HINT) % vendor_id


def _hid() -> Any:
    try:
        import hid  # hidapi (cython-hidapi)
    except ImportError as exc:  # pragma: no cover - hidapi is a dependency
        raise HardwareError(f"hidapi is not installed ({exc}): pip install hidapi") from None
    return hid


def find_devices(vendor_id: int | None = None, product_id: int | None = None, profile: str = "auto",
                 hid: Any = None) -> list[dict[str, Any]]:
    """HID devices that match: known SpaceMice/gamepads (``profile`` auto), or the given vendor/product ids."""
    hid = hid or _hid()
    out = []
    for d in hid.enumerate(vendor_id or 0, product_id or 0):
        key = (d.get("vendor_id", 0), d.get("product_id", 0))
        known = KNOWN_DEVICES.get(key)
        if vendor_id is None and product_id is None and known is None:
            continue
        if profile not in ("auto", "generic") and known is not None and known[0] != profile:
            continue
        # a SpaceMouse exposes its multi-axis collection on usage page 1 (generic desktop), usage 8
        if known and known[0] == "spacemouse" and d.get("usage_page") not in (None, 0, 1):
            continue
        out.append(dict(d, profile=(known[0] if known else "generic"), name=(known[1] if known else
                                                                            d.get("product_string") or "HID")))
    return out


def open_device(info: dict[str, Any], hid: Any = None) -> Any:
    """Open one enumerated device (non-blocking reads). Raises HardwareError saying why (permission: the udev rule for
    the node hidapi opens: the hidraw node, or the USB device node under the libusb backend)."""
    hid = hid or _hid()
    path = info["path"]
    dev = hid.device()
    try:
        dev.open_path(path)
    except (OSError, IOError) as exc:
        spath = hid_path_text(path)
        vid = info.get("vendor_id", 0)
        node = device_node(spath)
        what = f"{info.get('name', 'HID device')} ({vid:04x}:{info.get('product_id', 0):04x})"
        acc = node_access(node)
        if acc is not None and acc.cause == "permission":
            raise HardwareError(f"permission denied opening {what} at {spath}"
                                + (f" (device node {node})" if node != spath else "") + "; "
                                + acc.problem(udev_hint(vid, node))) from None
        if acc is not None and acc.cause in ("busy", "gone", "other"):
            raise HardwareError(f"could not open {what} at {spath}: {acc.problem(udev_hint(vid, node))}") from None
        raise HardwareError(f"could not open {what} at {spath}: {exc}; check that no other program (spacenavd, "
                            f"Steam, a game) holds it; if it is a permission problem, "
                            + udev_hint(vid, node) + " (`teletouch devices` shows readable=False for a device you "
                            "may not open)") from None
    dev.set_nonblocking(1)
    return dev


def resolve_report_timeout(profile: str, report_timeout: float | None, mode: str = "rate") -> float | None:
    """The silence (s) after which the device faults for this profile (a SpaceMouse in rate mode: while its cap is
    deflected), or None (no timeout). ValueError where the setting contradicts how the profile's devices report."""
    if profile in PERIODIC_PROFILES:
        if report_timeout is None:
            return DEFAULT_REPORT_TIMEOUT
        if report_timeout <= 0:
            raise ValueError(f"report_timeout cannot be turned off for a {profile}: it reports every few ms while "
                             f"connected, so silence is the only sign of a lost Bluetooth link; raise it instead "
                             f"(default {DEFAULT_REPORT_TIMEOUT} s)")
        return float(report_timeout)
    if profile == "spacemouse":
        if report_timeout is None:
            return DEFAULT_REPORT_TIMEOUT
        if report_timeout <= 0:
            why = ("the last rate would move the opening on" if mode == "rate" else
                   "the opening would stay at the last deflection, out of the operator's control, with no fault")
            raise ValueError(f"report_timeout cannot be turned off for a SpaceMouse: it reports every few ms while "
                             f"its cap is deflected, so silence then means a lost link, and {why}; raise it instead "
                             f"(default {DEFAULT_REPORT_TIMEOUT} s)")
        return float(report_timeout)
    return float(report_timeout) if report_timeout else None  # generic: only for a pad known to stream reports


def _parse_id(v: Any) -> Any:
    if isinstance(v, str):
        try:
            return int(v, 0)
        except ValueError:
            raise ValueError(f"expected an integer id such as 0x256f or 9583, got {v!r}") from None
    return v


class HidLeader(Device):
    """SpaceMouse or gamepad trigger as a position-only leader (hidapi); ignores force commands."""

    name = "hid-leader"
    kind = Kind.DEVICE
    default_rate = 250.0
    requires_wall_clock = True
    inputs = dict(LEADER_INPUTS)
    outputs = dict(LEADER_OUTPUTS)

    class Params(Params):
        device: Literal["auto", "spacemouse", "dualshock4", "dualsense", "generic"] = Field(
            "auto", description="report format; auto: from the vendor/product id of the first known device")
        vendor_id: int | None = Field(None, ge=0, le=0xFFFF, description="USB vendor id (e.g. 0x256f)")
        product_id: int | None = Field(None, ge=0, le=0xFFFF, description="USB product id")
        path: str | None = Field(None, description="hidapi path to pick one of several, as `teletouch devices` shows "
                                                    "it (e.g. 1-4.2:1.0; /dev/hidraw3 with hidapi's hidraw build)")
        min_opening: Meters = Field(0.0, ge=0, description="opening when closed", json_schema_extra={"unit": "m"})
        max_opening: Meters = Field(OMEGA7_GRIPPER_RANGE, gt=0, description="opening when open",
                                    json_schema_extra={"unit": "m"})
        # SpaceMouse
        axis: Literal["tx", "ty", "tz", "rx", "ry", "rz"] = Field("tz", description="SpaceMouse axis that drives "
                                                                                  "the opening")
        invert: bool = Field(False, description="reverse the SpaceMouse axis")
        mode: Literal["rate", "position"] = Field("rate", description="SpaceMouse: deflection sets the opening "
                                                                      "speed (rate) or the opening (position)")
        max_speed: MetersPerSecond = Field(0.05, gt=0, description="opening speed at full deflection (rate mode)",
                                           json_schema_extra={"unit": "m/s"})
        dead_band: float = Field(0.08, ge=0, lt=1, description="fraction of full deflection ignored")
        full_scale: float = Field(SPACEMOUSE_FULL_SCALE, gt=0, description="counts at full deflection")
        position_scale: Meters = Field(0.01, ge=0, description="position output per full deflection "
                                                               "(SpaceMouse translation)",
                                       json_schema_extra={"unit": "m"})
        button_bit: int = Field(0, ge=0, le=31, description="SpaceMouse button (bit of the bitmask)")
        # gamepads
        trigger: Literal["r2", "l2"] = Field("r2", description="gamepad trigger that closes the gripper")
        report_id: int | None = Field(None, ge=0, le=255, description="generic: report id (None: no ids)")
        trigger_offset: int = Field(0, ge=0, description="generic: byte index of the 8-bit trigger")
        button_offset: int | None = Field(None, ge=0, description="generic: byte index of the button")
        button_mask: int = Field(1, ge=1, le=255, description="generic: bit mask of the button")
        max_reports: int = Field(64, ge=1, description="reports drained per step at most")
        report_timeout: Seconds | None = Field(
            None, ge=0, le=2.0, description="silence after which the device faults (HardwareError), and its outputs "
            "carry the time of the last report; None: 0.5 s for dualshock4/dualsense (they report every few ms; "
            "cannot be turned off) and for a spacemouse (while its cap is deflected; cannot be turned off), off for "
            "generic (set it for a pad that streams reports); at most 2 s (a SpaceMouse's last rate holds that long: "
            "500 meant as ms would be 500 s, write 500ms)",
            json_schema_extra={"unit": "s"})

        @field_validator("vendor_id", "product_id", "report_id", mode="before")
        @classmethod
        def _ids(cls, v: Any) -> Any:
            return _parse_id(v)

        @field_validator("min_opening", "max_opening")
        @classmethod
        def _plausible(cls, v: float, info: Any) -> float:
            return plausible_opening(info.field_name, v)

        @field_validator("max_speed")
        @classmethod
        def _plausible_speed(cls, v: float, info: Any) -> float:
            return plausible_speed(info.field_name, v)

        @field_validator("position_scale")
        @classmethod
        def _plausible_position(cls, v: float, info: Any) -> float:
            return plausible_travel(info.field_name, v)   # 10 meant 10 mm per full deflection, not 10 m

        @field_validator("max_opening")
        @classmethod
        def _range(cls, v: float, info: Any) -> float:
            lo = info.data.get("min_opening", 0.0)
            if v <= lo:
                raise ValueError(f"max_opening ({v}) must be above min_opening ({lo})")
            return v

        @model_validator(mode="after")
        def _timeout_fits_profile(self) -> "HidLeader.Params":
            if self.device != "auto":
                resolve_report_timeout(self.device, self.report_timeout, self.mode)
            return self

        @model_validator(mode="after")
        def _offsets_past_the_id(self) -> "HidLeader.Params":
            if self.device == "generic" and self.report_id is not None:
                for name in ("trigger_offset", "button_offset"):
                    if getattr(self, name) == 0:
                        raise ValueError(f"{name}: byte 0 is the report id (report_id {self.report_id}), which never "
                                         f"changes: the offsets count the report id, so the report's first data byte "
                                         f"is 1")
            return self

    def configure(self) -> None:
        p = self.params
        hid = _hid()
        found = find_devices(p.vendor_id, p.product_id, p.device, hid=hid)
        if p.path is not None:
            found = [d for d in found if hid_path_text(d["path"]) == p.path]
        if not found:
            n_all = len(hid.enumerate(0, 0))
            no_usb = "" if n_all else _no_usb_folder()
            if no_usb:   # not the cable: nothing on USB can be seen from here (the audit: "check the USB cable")
                raise HardwareError(f"no HID leader found: {no_usb}; `teletouch devices` says the same")
            want = (f"{p.vendor_id or 0:04x}:{p.product_id or 0:04x}" if p.vendor_id or p.product_id else
                    "a 3Dconnexion SpaceMouse (vendor 046d/256f) or a Sony gamepad (054c)")
            where = f" at {p.path}" if p.path else ""
            if p.vendor_id or p.product_id:
                fix = "if it does, compare its vendor:product id with vendor_id/product_id"
            else:
                fix = ("if it does, its vendor:product id is not one teletouch knows: set vendor_id and product_id, "
                       "and device: generic with its report layout")
            if p.path:
                fix += "; path must be one that hidapi lists (it changes when the device is replugged)"
            raise HardwareError(f"no HID leader found: looked for {want}{where} among {n_all} HID device(s); "
                                f"{ENUMERATION_NOTE}: check the USB cable/receiver and that lsusb shows the device; "
                                f"{fix}; `teletouch devices` lists the HID leaders found, with the params that select "
                                f"them")
        info = found[0]
        self.info = info
        self.profile = p.device if p.device != "auto" else info["profile"]
        if self.profile == "generic" and p.device == "auto":
            raise HardwareError(f"{info['name']} ({info.get('vendor_id', 0):04x}:{info.get('product_id', 0):04x}) "
                                f"is not a known SpaceMouse/gamepad: set device: generic with trigger_offset "
                                f"(and report_id, button_offset) for its report layout")
        self.report_timeout = resolve_report_timeout(self.profile, p.report_timeout, p.mode)
        self.dev = open_device(info, hid=hid)
        self.sm = SpaceMouseState()
        self.pad = GamepadState()
        # the opening before the first report: a released trigger (open), a SpaceMouse's rate from open; in
        # position mode the cap at rest (a SpaceMouse is silent at rest): half open
        rest = self.profile == "spacemouse" and p.mode == "position"
        self.opening = deflection_to_opening(0.0, p.dead_band, p.min_opening, p.max_opening) if rest else p.max_opening
        self.velocity = 0.0
        self.last_t: float | None = None
        self.reports = 0
        self.ignored_reports = 0   # reports read that the parser does not read (another report id, too short)
        self._unread = 0           # ... of them since the last report it read, and the last one's (id, length)
        self._last_unread: tuple[int | None, int] | None = None
        self.last_report_t: float | None = None  # graph time of the last report read (report_timeout on)
        self._trail: deque[tuple[float, float]] = deque()   # (read time, opening) of recent reports (VELOCITY_WINDOW)
        self._watch_from: float | None = None
        self._out: dict[str, Sample] | None = None
        self._deflection = 0.0  # SpaceMouse rate mode: the axis as last reported, -1..1 (0: at rest)

    def activate(self) -> None:
        self.last_t = None
        self.last_report_t = None  # a sample from before a deactivate is not re-emitted
        self._trail.clear()
        self._watch_from = None
        self._out = None
        self._deflection = 0.0  # a rate from before a deactivate is not integrated on
        self._unread = 0

    def _parse(self, report: Any) -> bool:
        """Update the state with one report; whether the parser read it (a parser returns the very state it was given
        for a report it does not read: another report id, too short)."""
        p = self.params
        sm, pad = self.sm, self.pad
        if self.profile == "spacemouse":
            self.sm = parse_spacemouse(report, sm)
        elif self.profile == "dualshock4":
            self.pad = parse_dualshock4(report, pad)
        elif self.profile == "dualsense":
            self.pad = parse_dualsense(report, pad)
        else:
            self.pad = parse_generic_trigger(report, pad, p.report_id, p.trigger_offset, p.button_offset,
                                             p.button_mask)
        if self.sm is not sm or self.pad is not pad:
            self._unread = 0
            return True
        self.ignored_reports += 1
        self._unread += 1
        r = _report(report)
        self._last_unread = (r[0] if r else None, len(r))
        return False

    def _why_silent(self, lost: str) -> str:
        """``lost`` (a lost link and what to check), or, where reports came since the last one the parser read, what
        they were."""
        if not self._unread:
            return lost
        rid, n = self._last_unread   # type: ignore[misc]
        what = f"id 0x{rid:02x}, {n} bytes" if rid is not None else "empty"
        hint = {"dualsense": " (a DualSense over Bluetooth sends 10-byte reports until the host asks for its full "
                             "ones; Linux's hid-playstation does)",
                "generic": "; check report_id, trigger_offset and button_offset"}.get(self.profile, "")
        return (f"{self._unread} report(s) came in a layout the {self.profile} parser does not read (the last: "
                f"{what}), and such a report is no measurement{hint}")

    def step(self, t: float, inputs: Any) -> dict[str, Any] | None:
        p = self.params
        mono: float | None = None
        try:
            for _ in range(p.max_reports):
                r = self.dev.read(64)
                if not r:
                    break
                self.reports += 1
                if self._parse(r):   # (a report the parser does not read is no measurement: no stamp, no timeout reset)
                    mono = time.monotonic()
        except (OSError, IOError, ValueError) as exc:
            info = self.info
            raise HardwareError(f"{info['name']} stopped answering ({exc}): the HID device "
                                f"{info.get('vendor_id', 0):04x}:{info.get('product_id', 0):04x} at "
                                f"{hid_path_text(info['path'])} was unplugged or lost its link; check the USB cable "
                                f"(or the wireless receiver / Bluetooth link)") from None
        if self.profile == "spacemouse":   # (always has a report_timeout)
            return self._step_spacemouse(mono)
        if self.report_timeout is not None:
            return self._step_periodic(mono)
        dt = 0.0 if self.last_t is None else max(0.0, t - self.last_t)
        self.last_t = t
        x = trigger_to_opening(self.pad.trigger(p.trigger), p.min_opening, p.max_opening)
        self.velocity = 0.0 if dt <= 0 else (x - self.opening) / dt
        self.opening = x
        return {"gripper_opening": self.opening, "gripper_velocity": self.velocity, "position": np.zeros(3),
                "button": self.pad.cross}

    def _no_report(self) -> str:
        return "no report it reads" if self._unread else "no report"

    def _step_periodic(self, mono: float | None) -> dict[str, Any] | None:
        """A device that reports periodically: fault on silence, stamp the outputs with the last report's time."""
        p = self.params
        now = self.ctx.from_monotonic(time.monotonic())
        if self._watch_from is None:
            self._watch_from = now
        if mono is None:
            since = self.last_report_t if self.last_report_t is not None else self._watch_from
            silent = now - since
            if silent > self.report_timeout:  # type: ignore[operator]
                what = "since its last report" if self.last_report_t is not None else "since the run started"
                raise HardwareError(f"{self.info['name']} ({self.info.get('vendor_id', 0):04x}:"
                                    f"{self.info.get('product_id', 0):04x}) sent {self._no_report()} for {silent:.3f} "
                                    f"s {what} (report_timeout {self.report_timeout:g} s; it reports every few ms "
                                    f"while connected): "
                                    + self._why_silent("link lost; check the cable, the Bluetooth range and the "
                                                       "battery"))
            return None if self._out is None else dict(self._out)  # the last report's samples, with their stamp
        stamp = self.ctx.from_monotonic(mono)
        x = trigger_to_opening(self.pad.trigger(p.trigger), p.min_opening, p.max_opening)
        trail = self._trail
        if not trail or stamp > trail[-1][0]:   # (a read stamped no later than the last: the velocity stands)
            trail.append((stamp, x))
            while len(trail) > 2 and stamp - trail[1][0] >= VELOCITY_WINDOW:
                trail.popleft()   # the oldest left is the newest at least VELOCITY_WINDOW old (or the first)
            t_ref, x_ref = trail[0]
            self.velocity = (x - x_ref) / (stamp - t_ref) if stamp > t_ref else 0.0
        self.opening = x
        self.last_report_t = stamp
        self._out = {"gripper_opening": Sample(self.opening, stamp), "gripper_velocity": Sample(self.velocity, stamp),
                     "position": Sample(np.zeros(3), stamp), "button": Sample(self.pad.cross, stamp)}
        return dict(self._out)

    def _step_spacemouse(self, mono: float | None) -> dict[str, Any]:
        """SpaceMouse. Rate mode: the opening moves with the rate of the last report, from that report to the next
        (for at most report_timeout). Position mode: the opening follows the deflection of each report (centred:
        half open). While the cap is deflected the device reports every few ms, so silence for longer than
        report_timeout is a lost link: the opening stays where it was at the last report and step() raises. At rest
        silence is normal (no report until the cap moves again)."""
        p = self.params
        timeout = self.report_timeout
        if mono is None:
            if self._deflection == 0.0 or self.last_report_t is None:  # at rest: step-time stamps
                return {"gripper_opening": self.opening, "gripper_velocity": 0.0,
                        "position": self._out["position"].value if self._out else np.zeros(3),
                        "button": self._out["button"].value if self._out else False}
            silent = self.ctx.from_monotonic(time.monotonic()) - self.last_report_t
            if silent > timeout:  # type: ignore[operator]
                raise HardwareError(f"{self.info['name']} ({self.info.get('vendor_id', 0):04x}:"
                                    f"{self.info.get('product_id', 0):04x}) sent {self._no_report()} for {silent:.3f} "
                                    f"s while its cap was deflected (report_timeout {timeout:g} s; it reports every "
                                    f"few ms while deflected): the opening stays where it was at the last report; "
                                    + self._why_silent("link lost; check the cable or the wireless receiver and its "
                                                       "battery"))
            return dict(self._out)  # type: ignore[arg-type]  # moving: the last report's samples, with their stamp
        stamp = self.ctx.from_monotonic(mono)
        sm = self.sm
        u = axis_to_unit(sm.axis(p.axis), p.full_scale, p.invert)
        if p.mode == "rate":
            if self.last_report_t is not None and self._deflection != 0.0:
                dt = stamp - self.last_report_t
                if 0.0 < dt <= timeout:  # type: ignore[operator]  # (longer: the rate counts as zero after it)
                    self.opening, _ = integrate_rate(self.opening, self._deflection, dt, p.max_speed, p.dead_band,
                                                     p.min_opening, p.max_opening)
            v = deadband(u, p.dead_band) * p.max_speed
            if (v > 0 and self.opening >= p.max_opening) or (v < 0 and self.opening <= p.min_opening):
                v = 0.0  # against an end stop
        else:
            x = deflection_to_opening(u, p.dead_band, p.min_opening, p.max_opening)
            dt = 0.0 if self.last_report_t is None else stamp - self.last_report_t
            v = (x - self.opening) / dt if 0.0 < dt <= timeout else 0.0  # type: ignore[operator]
            self.opening = x
        self.last_report_t = stamp
        self._deflection = u if deadband(u, p.dead_band) != 0.0 else 0.0
        self.velocity = v
        position = np.array([axis_to_unit(c, p.full_scale, False) for c in (sm.tx, sm.ty, sm.tz)]) * p.position_scale
        self._out = {"gripper_opening": Sample(self.opening, stamp), "gripper_velocity": Sample(v, stamp),
                     "position": Sample(position, stamp), "button": Sample(bool(sm.buttons >> p.button_bit & 1), stamp)}
        return dict(self._out)

    def safe_state(self) -> None:
        """No actuator: nothing to make safe (force commands are never sent)."""

    def close(self) -> None:
        dev = getattr(self, "dev", None)
        if dev is not None:
            self.dev = None
            try:
                dev.close()
            except Exception:
                pass

    def status(self) -> dict[str, Any]:
        if not hasattr(self, "dev"):
            return {}
        return {"gripper_opening_m": self.opening, "reports": self.reports, "ignored_reports": self.ignored_reports,
                "last_report_at_s": self.last_report_t,
                "report_timeout_s": self.report_timeout, "profile": self.profile, "device": self.info.get("name", "")}


@hookimpl
def teletouch_components():
    return [HidLeader]


def _no_usb_folder(dev_root: str | None = None) -> str:
    """Why hidapi sees no USB device at all (Linux, no /dev/bus/usb: a container without the host's), or ''."""
    usbfs = os.path.join(dev_root or os.environ.get("TELETOUCH_DEV_ROOT", "/dev"), "bus", "usb")
    if not sys.platform.startswith("linux") or os.path.isdir(usbfs):
        return ""
    return (f"{usbfs} does not exist, so hidapi sees no USB device (in a container, pass the host's: docker run -v "
            f"/dev/bus/usb:/dev/bus/usb, or --device for the one device)")


def discover(hid: Any = None, sysfs_root: str | None = None, dev_root: str | None = None) -> list[dict[str, Any]]:
    """The rows of ``teletouch devices`` for HID leaders (never raises): one per known SpaceMouse/gamepad, with the
    ``hid-leader`` params that select it (``path`` and ``device``, the report format) and whether this user may open
    it (``readable``, with the udev rule as ``problem`` when not); or one ``error`` row when hidapi cannot be imported
    or fails to enumerate, or (Linux) lists nothing because there is no USB device folder to read (a container without
    the host's /dev/bus/usb)."""
    try:
        hid = hid or _hid()
        found = find_devices(hid=hid)
        nothing = not found and not hid.enumerate(0, 0)   # not even another HID device
    except Exception as exc:  # HardwareError (hidapi missing), a broken hidapi, an enumeration that fails
        return [{"kind": "hid-leader", "id": "", "path": "",
                 "error": f"HID devices cannot be listed: {type(exc).__name__}: {exc}"}]
    no_usb = _no_usb_folder(dev_root) if nothing else ""
    if no_usb:
        return [{"kind": "hid-leader", "id": "", "path": "", "error": f"HID devices cannot be listed: {no_usb}"}]
    rows = []
    for d in found:
        path = hid_path_text(d["path"])
        vid = d.get("vendor_id", 0)
        node = device_node(path, sysfs_root, dev_root)
        acc = node_access(node)
        readable = None if acc is None else acc.readable
        details: dict[str, Any] = {"name": d["name"], "usb": f"{vid:04x}:{d.get('product_id', 0):04x}",
                                   "readable": readable, "plugin": "hid-leader",
                                   "params": {"path": path, "device": d["profile"]}}
        if node is not None and node != path:
            details["node"] = node
        if acc is not None and readable is False:
            details["access"] = acc.why()
            details["problem"] = acc.problem(udev_hint(vid, node))
        rows.append({"kind": d["profile"], "id": d.get("serial_number") or f"{vid:04x}:{d.get('product_id', 0):04x}",
                     "path": path, "details": details})
    return rows


@hookimpl
def teletouch_discover_devices():
    return discover()
