"""Record every port of a running graph to MCAP (the ROS 2 bag format), read recordings back, plot them.

``teletouch run graph.yaml --record run.mcap`` builds a :class:`Recorder` and adds its :meth:`Recorder.tap` to the
runtime. The tap only puts ``(node, t, outputs)`` on a queue; a writer thread encodes and writes, so a 1 kHz loop
pays about a microsecond per step. Every ``flush_interval`` (0.5 s) the writer closes the MCAP chunk in progress and
flushes the file, so a crash or ``kill -9`` leaves a file that :func:`open_recording` reads up to the last flush.

One MCAP channel per output port, topic ``/<node>/<port>`` ('-' becomes '_' so ROS tools accept it). Messages are
ROS 2 messages in CDR with ``ros2msg`` schemas where a standard message fits, so ``ros2 bag``, Foxglove and the
``mcap`` libraries read them:

======================================  ==============================================================
value                                   message
======================================  ==============================================================
float, unit N (scalar or 3-vector)      geometry_msgs/msg/WrenchStamped (scalar on force.z; a channel keeps its
                                        first value's form, metadata value_shape; another tool's is read back
                                        as the 6-vector force xyz, torque xyz)
other float or int scalar               std_msgs/msg/Float64 (an int is exact up to 2**53)
bool / str scalar                       std_msgs/msg/Bool / String
1-D or N-D number or bool array         std_msgs/msg/Float64MultiArray (layout keeps the shape, read back in
                                        the port's dtype or, undeclared, its first value's)
uint8 image (rows, cols, 3) BGR         sensor_msgs/msg/CompressedImage, PNG (lossless) or JPEG
uint8 (rows, cols) / bool mask          sensor_msgs/msg/CompressedImage, PNG mono8 (mask: 0/255)
float32 / float64 / uint16 (rows, cols) sensor_msgs/msg/Image, 32FC1 / 64FC1 / 16UC1 (depth maps, m; uint16
                                        read back as written: only another tool's 16UC1 is depth in mm)
anything else                           JSON (schemaless), {"value": ...}
======================================  ==============================================================

A 2-D array (uint8, bool, float, uint16) is an image only if each side is at least :data:`MIN_IMAGE_SIDE` (the
port's declared size, a free one counting as long enough, else the value's): (N, 2) points, a (3, 3) matrix, a 4x4
lookup or a mask of a few cells are arrays, read back exactly. A (rows, cols, 3) uint8 array is a colour frame unless
its port declares fewer rows or columns. ``teletouch plot`` draws lengths in mm and energies in mJ (the file is SI).

Times: the MCAP ``publish_time`` and every ``header.stamp`` are the sample's own stamp (a camera's capture time),
``log_time`` is the graph time of the step that produced it; both as Unix-epoch nanoseconds, ``epoch + graph time``,
where ``epoch`` (metadata record ``teletouch.time``, key ``graph_epoch_ns``) is the Unix time of graph time 0. The
readers give graph time back in seconds (another tool's recording: from its first message's publish time). Samples
dropped on a wall clock (a writer behind) are counted in the metadata record ``teletouch.drops``
(:attr:`Recording.dropped`).

Read only (teletouch never writes one): another tool's sensor_msgs/msg/JointState, what ``ros2-publish`` sends for
the gripper, gives per joint its position, velocity and effort as the message holds them (SI), at its header stamp.
"""

from __future__ import annotations

import argparse
import base64
import json
import math
import os
import queue
import re
import struct
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from .component import Sample
from .errors import TeletouchError
from .hookspecs import hookimpl

__all__ = [
    "Recorder", "RecordingError", "Recording", "ChannelInfo", "open_recording", "read_signals", "iter_images",
    "plot_recording", "ros_time", "ros_time_ns", "from_ros_time", "image_msg", "image_from_msg", "ros2msg_definition",
]

FLUSH_INTERVAL = 0.5


class RecordingError(TeletouchError):
    """A recording could not be written or read."""


# --------------------------------------------------------------------------------------------- ROS 2 helpers
def ros_time(seconds: float) -> Any:
    """A builtin_interfaces/Time for Unix-epoch ``seconds`` (never negative)."""
    return ros_time_ns(int(round(seconds * 1e9)))


def ros_time_ns(ns: int) -> Any:
    """A builtin_interfaces/Time for Unix-epoch nanoseconds (never negative)."""
    from builtin_interfaces.msg import Time

    ns = max(0, int(ns))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def from_ros_time(stamp: Any) -> float:
    """Unix-epoch seconds of a builtin_interfaces/Time."""
    return stamp.sec + stamp.nanosec * 1e-9


def image_msg(array: np.ndarray, stamp_s: float, frame_id: str = "", stamp_ns: int | None = None) -> Any:
    """A sensor_msgs/Image from a BGR uint8 (rows, cols, 3), mono uint8 (rows, cols) or float (rows, cols) array."""
    from sensor_msgs.msg import Image

    a = np.ascontiguousarray(array)
    if a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3:
        enc = "bgr8"
    elif a.dtype == np.uint8 and a.ndim == 2:
        enc = "mono8"
    elif a.dtype == np.float32 and a.ndim == 2:
        enc = "32FC1"
    elif a.dtype == np.float64 and a.ndim == 2:
        enc = "64FC1"
    elif a.dtype == np.uint16 and a.ndim == 2:
        enc = "16UC1"
    else:
        raise ValueError(f"no sensor_msgs/Image encoding for a {a.dtype} array of shape {a.shape}")
    m = Image()
    m.header.stamp = ros_time_ns(stamp_ns) if stamp_ns is not None else ros_time(stamp_s)
    m.header.frame_id = frame_id
    m.height, m.width = int(a.shape[0]), int(a.shape[1])
    m.encoding = enc
    m.is_bigendian = int(sys.byteorder == "big")
    m.step = int(a.strides[0])
    m.data = a.tobytes()
    return m


def image_from_msg(msg: Any) -> np.ndarray:
    """The array of a sensor_msgs/Image: bgr8/rgb8/bgra8 -> BGR uint8 (rows, cols, 3); mono8 -> uint8 (rows, cols);
    32FC1/64FC1 -> float (rows, cols); 16UC1 (depth in mm, the ROS convention) -> float32 metres."""
    return _image_array(msg, mm_to_m=True)


def _image_array(msg: Any, mm_to_m: bool) -> np.ndarray:
    """:func:`image_from_msg`; ``mm_to_m=False`` gives a 16UC1/mono16 image as the uint16 array it holds."""
    enc = msg.encoding.lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size < h * step:
        raise ValueError(f"sensor_msgs/Image: {buf.size} data bytes for height {h} x step {step}")
    rows = buf[: h * step].reshape(h, step)
    big = bool(msg.is_bigendian)
    if enc in ("bgr8", "rgb8", "8uc3"):
        img = rows[:, : w * 3].reshape(h, w, 3)
        return np.ascontiguousarray(img[:, :, ::-1] if enc == "rgb8" else img)
    if enc in ("bgra8", "rgba8", "8uc4"):
        img = rows[:, : w * 4].reshape(h, w, 4)[:, :, :3]
        return np.ascontiguousarray(img[:, :, ::-1] if enc == "rgba8" else img)
    if enc in ("mono8", "8uc1"):
        return np.ascontiguousarray(rows[:, :w])
    if enc in ("32fc1", "64fc1", "16uc1", "mono16"):
        dt = {"32fc1": "f4", "64fc1": "f8", "16uc1": "u2", "mono16": "u2"}[enc]
        dt = np.dtype((">" if big else "<") + dt)
        a = rows[:, : w * dt.itemsize].copy().view(dt).reshape(h, w)
        if enc == "16uc1" and mm_to_m:
            return a.astype(np.float32) * np.float32(1e-3)
        return a.astype(a.dtype.newbyteorder("="))
    raise ValueError(f"sensor_msgs/Image encoding '{msg.encoding}' is not supported "
                     f"(bgr8, rgb8, bgra8, rgba8, mono8, 32FC1, 64FC1, 16UC1)")


_PRIMS = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
          "int64", "uint64", "string", "wstring"}
_IDL_TO_MSG = {"boolean": "bool", "octet": "byte", "float": "float32", "double": "float64", "long": "int32",
               "unsigned long": "uint32", "long long": "int64", "unsigned long long": "uint64", "short": "int16",
               "unsigned short": "uint16"}


def _msg_class(type_name: str) -> Any:
    """'geometry_msgs/msg/WrenchStamped' or 'geometry_msgs/WrenchStamped' -> the rclpy message class."""
    import importlib

    parts = type_name.split("/")
    pkg, name = parts[0], parts[-1]
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _field_to_msg(t: str) -> tuple[str, str | None]:
    """An introspection type ('sequence<double>', 'std_msgs/Header', 'double[9]', 'string<=10') as .msg syntax, and
    the message type it depends on (or None)."""
    suffix = ""
    m = re.fullmatch(r"sequence<(.+?)(?:,\s*(\d+))?>", t)
    if m:
        t, bound = m.group(1), m.group(2)
        suffix = f"[<={bound}]" if bound else "[]"
    else:
        m = re.fullmatch(r"(.+)\[(\d+)\]", t)
        if m:
            t, suffix = m.group(1), f"[{m.group(2)}]"
    t = _IDL_TO_MSG.get(t, t)
    base = t.split("<=")[0]
    if base in _PRIMS:
        return t + suffix, None
    return t + suffix, t


def ros2msg_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a message type as MCAP wants it: the type's fields, then every type it
    depends on after a line of 80 '=' and ``MSG: pkg/Name`` (the format rosbag2 writes)."""

    def fields(name: str) -> tuple[list[str], list[str]]:
        cls = _msg_class(name)
        lines, deps = [], []
        for fname, ftype in cls.get_fields_and_field_types().items():
            text, dep = _field_to_msg(ftype)
            lines.append(f"{text} {fname}")
            if dep is not None:
                deps.append(dep)
        return lines, deps

    main_lines, todo = fields(type_name)
    out = ["\n".join(main_lines)]
    seen: set[str] = set()
    while todo:
        dep = todo.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        lines, more = fields(dep)
        out.append("=" * 80 + "\nMSG: " + dep + "\n" + "\n".join(lines))
        todo.extend(more)
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------------------------- codecs
def _is_scalar_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _jsonable(v: Any) -> Any:
    if isinstance(v, Sample):
        return {"value": _jsonable(v.value), "stamp": v.stamp}
    if isinstance(v, np.ndarray):
        if v.dtype.kind in "fc" and not np.isfinite(v).all():
            return _jsonable(v.tolist())  # NaN/inf elements as strings (below), not the whole message lost
        return v.tolist()
    if isinstance(v, np.generic):
        return _jsonable(v.item())
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)  # JSON has no NaN/inf; the reader turns these strings back into floats
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (str, int, bool, float)) or v is None:
        return v
    return repr(v)


class _Codec:
    """How one channel's values become message bytes and back."""

    kind = ""
    ros_type: str | None = None  # None: JSON

    def __init__(self, recorder_opts: dict[str, Any] | None = None):
        self.opts = recorder_opts or {}

    @property
    def expected(self) -> str:
        """What a message of this codec holds, for an error about one that cannot be decoded."""
        return f"a CDR {self.ros_type}"

    def accepts(self, v: Any) -> bool:
        return True

    def encode(self, v: Any, stamp_ns: int, frame_id: str) -> bytes:
        from rclpy.serialization import serialize_message

        return serialize_message(self.build(v, stamp_ns, frame_id))

    def build(self, v: Any, stamp_ns: int, frame_id: str) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def decode(self, data: bytes, meta: dict[str, str]) -> Any:
        from rclpy.serialization import deserialize_message

        return self.unpack(deserialize_message(data, _msg_class(self.ros_type)), meta)

    def unpack(self, msg: Any, meta: dict[str, str]) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError


# CDR (XCDR1, little endian) written by hand for the messages recorded at high rate: rclpy builds a Python message
# object per sample, ~20x slower. Alignment is relative to the end of the 4-byte encapsulation header. The tests
# check these bytes against rclpy's deserializer and a standalone ROS 2 decoder.
_CDR_LE = b"\x00\x01\x00\x00"
_pack = struct.pack


def _cdr_pad(buf: bytearray, align: int) -> None:
    n = (-(len(buf) - 4)) % align
    if n:
        buf += b"\x00" * n


def _cdr_string(buf: bytearray, text: str) -> None:
    b = text.encode()
    _cdr_pad(buf, 4)
    buf += _pack("<I", len(b) + 1)
    buf += b
    buf += b"\x00"


def _cdr_header(stamp_ns: int, frame_id: str) -> bytearray:
    """A CDR buffer starting with a std_msgs/Header."""
    ns = max(0, int(stamp_ns))
    buf = bytearray(_CDR_LE)
    buf += _pack("<iI", ns // 1_000_000_000, ns % 1_000_000_000)
    _cdr_string(buf, frame_id)
    return buf


class _Wrench(_Codec):
    """A force in N: a 3-vector on force xyz, a scalar on force.z. A channel holds one of the two, the form of its
    first value (``vector``; None while the codec is chosen), kept in its metadata (``value_shape``): the message
    cannot tell a scalar from a vector whose x and y are 0, and the port's declared shape may leave it open."""

    kind = "wrench"
    ros_type = "geometry_msgs/msg/WrenchStamped"

    def __init__(self, recorder_opts: dict[str, Any] | None = None, vector: bool | None = None):
        super().__init__(recorder_opts)
        self.vector = vector

    @staticmethod
    def is_vector(v: Any) -> bool:
        return isinstance(v, np.ndarray) and v.shape == (3,) and v.dtype.kind in "fiu"

    def accepts(self, v):
        if self.is_vector(v):
            return self.vector is not False
        scalar = _is_scalar_number(v) or (isinstance(v, np.ndarray) and v.shape == () and v.dtype.kind in "fiu")
        return scalar and not self.vector

    def encode(self, v, stamp_ns, frame_id):
        if isinstance(v, np.ndarray) and v.shape == (3,):
            f = tuple(float(x) for x in v)
        else:
            f = (0.0, 0.0, float(v))
        buf = _cdr_header(stamp_ns, frame_id)
        _cdr_pad(buf, 8)
        buf += _pack("<6d", f[0], f[1], f[2], 0.0, 0.0, 0.0)  # force xyz, torque xyz
        return bytes(buf)

    def unpack(self, msg, meta):
        f = msg.wrench.force
        if meta.get("codec") != self.kind:   # another tool's wrench (a force/torque sensor's): all of it
            m = msg.wrench.torque
            return np.array([f.x, f.y, f.z, m.x, m.y, m.z])
        if meta.get("value_shape", meta.get("shape")) == "[3]":   # (a file from before value_shape: as declared)
            return _as_recorded(np.array([f.x, f.y, f.z]), meta)
        return float(f.z)


class _Float64(_Codec):
    kind = "float64"
    ros_type = "std_msgs/msg/Float64"

    def accepts(self, v):
        return _is_scalar_number(v) or (isinstance(v, np.ndarray) and v.shape == () and v.dtype.kind in "fiu")

    def encode(self, v, stamp_ns, frame_id):
        return _CDR_LE + _pack("<d", float(v))

    def unpack(self, msg, meta):
        return float(msg.data)


class _Bool(_Codec):
    kind = "bool"
    ros_type = "std_msgs/msg/Bool"

    def accepts(self, v):
        return isinstance(v, (bool, np.bool_))

    def encode(self, v, stamp_ns, frame_id):
        return _CDR_LE + (b"\x01\x00\x00\x00" if v else b"\x00\x00\x00\x00")

    def unpack(self, msg, meta):
        return bool(msg.data)


class _Int64(_Codec):
    kind = "int64"
    ros_type = "std_msgs/msg/Int64"

    def accepts(self, v):
        return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) and -2**63 <= v < 2**63

    def encode(self, v, stamp_ns, frame_id):
        return _CDR_LE + _pack("<q", int(v))

    def unpack(self, msg, meta):
        return int(msg.data)


class _String(_Codec):
    kind = "string"
    ros_type = "std_msgs/msg/String"

    def accepts(self, v):
        return isinstance(v, str)

    def encode(self, v, stamp_ns, frame_id):
        buf = bytearray(_CDR_LE)
        _cdr_string(buf, v)
        return bytes(buf)

    def unpack(self, msg, meta):
        return str(msg.data)


class _Array(_Codec):
    kind = "array"
    ros_type = "std_msgs/msg/Float64MultiArray"

    def accepts(self, v):
        return isinstance(v, np.ndarray) and v.ndim >= 1 and v.dtype.kind in "fiub"

    def build(self, v, stamp_ns, frame_id):
        from std_msgs.msg import Float64MultiArray, MultiArrayDimension

        a = np.asarray(v, dtype=np.float64)
        m = Float64MultiArray()
        stride = a.size
        for i, n in enumerate(a.shape):
            m.layout.dim.append(MultiArrayDimension(label=f"dim{i}", size=int(n), stride=int(stride)))
            stride = stride // n if n else 0
        m.data = a.ravel().tolist() if a.size < 64 else a.ravel()
        return m

    def unpack(self, msg, meta):
        shape = tuple(int(d.size) for d in msg.layout.dim)
        a = np.asarray(msg.data, dtype=np.float64)
        a = a.reshape(shape) if shape else a
        return _as_recorded(a, meta)


class _Compressed(_Codec):
    kind = "compressed"
    ros_type = "sensor_msgs/msg/CompressedImage"

    def accepts(self, v):
        if not isinstance(v, np.ndarray) or v.size == 0:  # cv2 cannot encode an empty image: JSON takes it
            return False
        if v.dtype == np.uint8:
            return v.ndim == 2 or (v.ndim == 3 and v.shape[2] == 3)
        return v.dtype == bool and v.ndim == 2

    def encode(self, v, stamp_ns, frame_id):
        import cv2

        a = v.astype(np.uint8) * 255 if v.dtype == bool else v
        enc = "bgr8" if a.ndim == 3 else "mono8"
        fmt = "png" if (self.opts.get("image_format", "png") == "png" or v.dtype == bool) else "jpeg"
        if fmt == "png":  # level 1 + RLE: the fastest lossless setting that still halves a DIGIT frame
            ok, data = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 1,
                                                cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])
        else:
            ok, data = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, int(self.opts.get("jpeg_quality", 90))])
        if not ok:
            raise ValueError(f"cv2.imencode failed for a {a.dtype} {a.shape} image")
        buf = _cdr_header(stamp_ns, frame_id)
        _cdr_string(buf, f"{enc}; {fmt} compressed {enc}")  # image_transport's compressed format string
        _cdr_pad(buf, 4)
        buf += _pack("<I", data.size)
        buf += data.tobytes()
        return bytes(buf)

    def unpack(self, msg, meta):
        import cv2

        a = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
        if a is None:
            raise RecordingError(f"could not decode a CompressedImage ({msg.format})")
        return a > 127 if _recorded_bool(meta) else a


class _Raw(_Codec):
    kind = "image"
    ros_type = "sensor_msgs/msg/Image"

    def accepts(self, v):
        return isinstance(v, np.ndarray) and v.ndim == 2 and v.dtype in (np.float32, np.float64, np.uint16)

    def encode(self, v, stamp_ns, frame_id):
        a = np.ascontiguousarray(v)
        enc = {np.dtype(np.float32): "32FC1", np.dtype(np.float64): "64FC1", np.dtype(np.uint16): "16UC1"}[a.dtype]
        buf = _cdr_header(stamp_ns, frame_id)
        _cdr_pad(buf, 4)
        buf += _pack("<II", a.shape[0], a.shape[1])
        _cdr_string(buf, enc)
        buf += _pack("<B", int(sys.byteorder == "big"))
        _cdr_pad(buf, 4)
        buf += _pack("<II", a.strides[0], a.nbytes)
        buf += a.tobytes()
        return bytes(buf)

    def unpack(self, msg, meta):
        # a 16UC1 image teletouch wrote is the uint16 array it was given (not a depth map in mm: teletouch's depth
        # maps are float metres); another tool's 16UC1 is the ROS convention, depth in mm, given in metres
        return _image_array(msg, mm_to_m=meta.get("codec") != self.kind)


class _Json(_Codec):
    kind = "json"
    ros_type = None
    expected = 'JSON {"value": ...}, as teletouch writes'

    def encode(self, v, stamp_ns, frame_id):
        doc = {"value": _jsonable(v)}
        if isinstance(v, np.ndarray) and v.ndim > 1:   # an empty (0, 3) array's list is [], which says no shape
            doc["shape"] = list(v.shape)
        return json.dumps(doc, allow_nan=False).encode()

    def decode(self, data, meta):
        doc = json.loads(data)
        v = _unjson(doc["value"])
        a = self._array(v, meta)
        shape = doc.get("shape")
        if isinstance(a, np.ndarray) and isinstance(shape, list) and a.size == math.prod(shape):
            return a.reshape(shape)
        return a

    @staticmethod
    def _array(v: Any, meta: dict[str, str]) -> Any:
        if isinstance(v, list) and meta.get("dtype") not in (None, "any"):
            try:
                return np.asarray(v, dtype=meta["dtype"])
            except (TypeError, ValueError):
                return v
        if isinstance(v, list) and meta.get("value_dtype"):  # a port not declared: as its first value was
            try:
                a = np.asarray(v)
            except (TypeError, ValueError):
                return v
            return _as_recorded(a, meta) if a.dtype.kind in "biuf" else v
        return v


def _unjson(v: Any) -> Any:
    """The non-finite floats that :func:`_jsonable` wrote as strings, back as floats (also inside lists, dicts)."""
    if isinstance(v, str):
        return float(v) if v in ("nan", "inf", "-inf") else v
    if isinstance(v, list):
        return [_unjson(x) for x in v]
    if isinstance(v, dict):
        return {k: _unjson(x) for k, x in v.items()}
    return v


def _recorded_dtype(meta: dict[str, str]) -> np.dtype | None:
    """The dtype of a channel's arrays as recorded: the port's declared one, else (a port not declared) its first
    value's (metadata ``value_dtype``); None where neither is a number or bool dtype."""
    for name in (meta.get("dtype"), meta.get("value_dtype")):
        if name and name != "any":
            try:
                dt = np.dtype(name)
            except TypeError:
                continue
            if dt.kind in "biuf":
                return dt
    return None


def _recorded_bool(meta: dict[str, str]) -> bool:
    """Whether a channel's arrays were bool (a mask: recorded as a 0/255 image where it is one)."""
    dt = _recorded_dtype(meta)
    return dt is not None and dt.kind == "b"


def _as_recorded(a: np.ndarray, meta: dict[str, str]) -> np.ndarray:
    """A decoded array (Float64MultiArray: float64) in the dtype it was recorded with, where that gives the same
    values (a later value of another dtype, or one not exact in it, stays as decoded)."""
    dt = _recorded_dtype(meta)
    if dt is None or dt == a.dtype:
        return a
    with np.errstate(invalid="ignore", over="ignore"):
        b = a.astype(dt)
        same = np.array_equal(b.astype(a.dtype), a, equal_nan=a.dtype.kind == "f")
    return b if same else a


class _JsonImage(_Json):
    """Without ROS 2 message packages: images as base64 PNG inside JSON."""

    kind = "json-image"
    expected = 'JSON {"value": {"png": base64 PNG}}, as teletouch writes'

    def accepts(self, v):
        return _Compressed().accepts(v)

    def encode(self, v, stamp_ns, frame_id):
        import cv2

        a = v.astype(np.uint8) * 255 if v.dtype == bool else v
        ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 1,
                                           cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])
        if not ok:
            raise ValueError(f"cv2.imencode failed for a {a.dtype} {a.shape} image")
        return json.dumps({"value": {"png": base64.b64encode(buf.tobytes()).decode()}}).encode()

    def decode(self, data, meta):
        import cv2

        v = json.loads(data)["value"]
        png = v.get("png") if isinstance(v, dict) else None
        if not isinstance(png, str):
            raise ValueError('no {"png": base64 PNG} value')
        a = cv2.imdecode(np.frombuffer(base64.b64decode(png), np.uint8), cv2.IMREAD_UNCHANGED)
        if a is None:
            raise ValueError("the base64 PNG cannot be decoded")
        return a > 127 if _recorded_bool(meta) else a


@dataclass
class _HeaderStamped:
    """A decoded value with the message's own ``header.stamp`` (Unix-epoch ns; 0: the sender did not stamp it),
    which the readers take as the sample's time instead of the MCAP publish time."""

    value: Any
    stamp_ns: int


class _JointState(_Codec):
    """Another tool's sensor_msgs/msg/JointState (``ros2-publish`` sends one per measurement of the gripper; a
    ``ros2 bag record`` keeps them). Read only: the Recorder never writes one (:func:`_choose_codec`). Its value is
    ``{joint name: {"position": x, "velocity": v, "effort": e}}`` with the fields the message carries (an empty
    array: not in this message), as ROS gives them (SI: m or rad, m/s or rad/s, N or N*m), at its header stamp.
    A message whose arrays do not match its names (the message definition: each the names' length, or empty), or
    that names a joint twice, cannot be decoded (its values could not be told apart)."""

    kind = "joint_state"
    ros_type = "sensor_msgs/msg/JointState"
    FIELDS = ("position", "velocity", "effort")

    def accepts(self, v):
        return False

    def decode(self, data, meta):
        from rclpy.serialization import deserialize_message

        msg = deserialize_message(data, _msg_class(self.ros_type))
        st = msg.header.stamp
        return _HeaderStamped(self.unpack(msg, meta), int(st.sec) * 1_000_000_000 + int(st.nanosec))

    def unpack(self, msg, meta):
        names = [str(n) for n in msg.name]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"joint {twice[0]!r} is named twice in {names}")
        out: dict[str, dict[str, float]] = {n: {} for n in names}
        for f in self.FIELDS:
            values = [float(x) for x in getattr(msg, f)]
            if not values:
                continue
            if len(values) != len(names):
                raise ValueError(f"{len(values)} {f} values for {len(names)} joint names {names} (each array must "
                                 f"have one value per name, or none)")
            for n, x in zip(names, values):
                out[n][f] = x
        return out


_CODECS: dict[str, type[_Codec]] = {c.kind: c for c in (_Wrench, _Float64, _Bool, _Int64, _String, _Array,
                                                          _Compressed, _Raw, _Json, _JsonImage, _JointState)}


#: a 2-D array (uint8, bool, float, uint16) is an image only if its rows and columns are each at least this many
#: (declared or, where the port leaves them free or is not known, the value's); fewer are a matrix, a list of points,
#: a lookup or a mask of a few cells: an array, recorded exactly. A (rows, cols, 3) uint8 array is a colour frame at
#: any size, unless its port declares fewer rows or columns.
MIN_IMAGE_SIDE = 8


def _image_sized(value: Any, port: Any) -> bool:
    """Whether an array is recorded as an image (CompressedImage, Image): by the port's declared shape where it has
    the value's dimensions ((None, None) or (None, None, 3) is an image, (None, 2), (3, 3) or (4, 4) is not; only
    rows and columns count), else a (rows, cols, 3) array is (a colour frame) and a 2-D one by the value's shape."""
    vshape = getattr(value, "shape", ())
    shape = getattr(port, "shape", None)
    if shape is None or len(shape) != len(vshape):
        if len(vshape) == 3:
            return True
        shape = vshape
    return all(d is None or d >= MIN_IMAGE_SIDE for d in shape[:2])


def _choose_codec(value: Any, port: Any, ros: bool, opts: dict[str, Any]) -> _Codec:
    """The codec of a channel, from its first value and the port's declaration (``port``: None when not known)."""
    image = _image_sized(value, port)
    if not ros:
        return _JsonImage(opts) if image and _JsonImage().accepts(value) else _Json(opts)
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "fiub":
        value = value.item()
    order: list[type[_Codec]] = [_Bool, _String]
    if getattr(port, "unit", "") == "N":
        order.append(_Wrench)
    order += [_Float64] + ([_Compressed, _Raw] if image else []) + [_Array]
    for cls in order:
        c = cls(opts)
        if c.accepts(value):
            if isinstance(c, _Wrench):   # the channel's form: a later value of the other form goes to JSON
                c.vector = _Wrench.is_vector(value)
            return c
    return _Json(opts)


def _ros_available() -> bool:
    try:
        import rclpy.serialization  # noqa: F401
        import geometry_msgs.msg  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
        import std_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


# --------------------------------------------------------------------------------------------- writing
def _topic(node: str, port: str) -> str:
    """The MCAP topic of a port: ``/<node>/<port>``, '-' and other characters ROS does not take as '_'."""
    return "/" + re.sub(r"[^A-Za-z0-9_/]", "_", f"{node}/{port}")


#: s without progress after which close() stops waiting for the writer (a write that never returns)
CLOSE_STALL_TIMEOUT = 10.0
_STOP = object()


@dataclass
class _Chan:
    id: int
    codec: _Codec
    fallback: int | None = None  # JSON channel for values the codec cannot take


class Recorder:
    """Records taps to an MCAP file from a writer thread; see the module docstring.

    Parameters: ``image_format`` "png" (lossless, default: a replay gives the same force) or "jpeg";
    ``flush_interval`` seconds between flushes (at most this much plus the writer's backlog is lost on a crash);
    ``ros_encoding`` False writes JSON everywhere (also the fallback when the ROS 2 message packages are missing);
    ``max_queue`` items (or ``max_queue_bytes`` of arrays) waiting for the writer before new ones are dropped
    (counted, reported at close and kept in the file's ``teletouch.drops`` metadata; 0: no limit) on a wall clock;
    on a simulated clock the tap waits for the writer instead (nothing is lost, the simulation slows down); a
    sample larger than ``max_queue_bytes`` goes in when no array is queued (on a wall clock it is dropped while
    one is, on a simulated clock it waits until none is);
    ``encode_threads`` threads compress images in parallel (cv2 releases the GIL; capped at the CPU count).
    """

    def __init__(self, path: str | os.PathLike, spec: Any = None, *, image_format: str = "png",
                 jpeg_quality: int = 90, flush_interval: float = FLUSH_INTERVAL, ros_encoding: bool | None = None,
                 max_queue: int = 20000, max_queue_bytes: int = 512 * 2**20, encode_threads: int = 4,
                 log: Callable[[str], None] | None = None):
        from mcap.writer import CompressionType, Writer

        if image_format not in ("png", "jpeg"):
            raise RecordingError(f"image_format: expected 'png' or 'jpeg', got {image_format!r}")
        self.path = str(path)
        self.spec = spec
        self.flush_interval = float(flush_interval)
        self.ros = _ros_available() if ros_encoding is None else bool(ros_encoding)
        if self.ros and not _ros_available():
            raise RecordingError("ros_encoding=True needs rclpy and the ROS 2 message packages "
                                 "(pip install 'teletouch[ros2]')")
        self.opts = {"image_format": image_format, "jpeg_quality": jpeg_quality}
        self.log = log or (lambda m: print(f"[recording] {m}", file=sys.stderr))
        self.max_queue = int(max_queue)
        self.encode_threads = int(encode_threads)
        self.max_queue_bytes = int(max_queue_bytes)
        self._queued_bytes = 0
        # the writer's queue accounting: the admission check (items, bytes), the byte count, the drop count and
        # max_backlog change together under this lock (taps come from every node's thread at once; a check made
        # outside it let two taps both take the last place, and a max_backlog write lose a larger one)
        self._q_lock = threading.Lock()
        self._lag_warned = False
        self.clock = getattr(spec, "clock", "wall")
        self._ports = self._port_table(spec)
        topics: dict[str, tuple[str, str]] = {}
        for key in self._ports:   # node ids 'a-b' and 'a_b' (both valid) gave one topic, maybe of two types
            other = topics.setdefault(_topic(*key), key)
            if other != key:
                raise RecordingError(f"cannot record {self.path}: the ports {'.'.join(other)} and {'.'.join(key)} "
                                     f"would share the topic {_topic(*key)} (a ROS topic takes '-' as '_'), which "
                                     f"ROS tools read as one; rename one of the nodes")
        #: the graph clock (the runtime's now(), set by `teletouch run`): on a wall clock the recording's Unix time
        #: of graph time 0 is taken from it; None: from the first recorded step's time
        self.graph_now: Callable[[], float] | None = None
        try:
            self._fh = open(self.path, "wb")
        except OSError as exc:
            raise RecordingError(f"cannot write the recording {self.path}: {exc}") from exc
        try:
            compression = CompressionType.LZ4
            import lz4.frame  # noqa: F401
        except ImportError:  # pragma: no cover - lz4 ships with mcap's usual installs
            compression = CompressionType.NONE
        try:
            self._start(spec, Writer, compression)
        except OSError as exc:   # a full disk refuses the header: say so, leave no file open
            try:
                self._fh.close()
            except OSError:
                pass
            raise RecordingError(f"cannot write the recording {self.path}: {exc.strerror or exc}") from None
        self._schemas: dict[str, int] = {}
        self._chans: dict[tuple[str, str], _Chan] = {}
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._epoch_ns: int | None = None
        self.fatal: str | None = None
        self._epoch_lock = threading.Lock()
        self._closed = False
        self.messages = 0
        self.dropped = 0
        self._dropped_items = self._dropped_bytes = 0  # samples dropped at max_queue / at max_queue_bytes
        self._dropped_nodes: dict[str, int] = {}  # samples dropped, by node
        self._drops_written = 0  # the drop count in the file's last teletouch.drops record
        self._last_t: float | None = None  # graph time of the last message handed to the writer
        self._flushed = (0, None)  # (messages, graph time of the last one) at the last successful flush
        self.max_backlog = 0  # most items seen waiting for the writer (the one a tap just queued included)
        self.errors: list[str] = []
        self._seq = 0
        self._thread = threading.Thread(target=self._run, name="teletouch-recorder", daemon=True)
        self._thread.start()

    def _start(self, spec: Any, writer: Any, compression: Any) -> None:
        """Write the file's header and the ``teletouch`` metadata record, flushed."""
        from . import __version__

        # the data section's CRC too (DataEnd): the chunks carry their own, but not the records between them (the
        # metadata, each record's opcode): a byte damaged there went unnoticed (checked by _iter_raw's reader)
        self._writer = writer(self._fh, chunk_size=4 * 1024 * 1024, compression=compression, enable_data_crcs=True)
        self._writer.start(profile="ros2" if self.ros else "", library="teletouch")
        self._writer.add_metadata("teletouch", {
            "teletouch_version": __version__,
            "graph": str(getattr(spec, "name", "") or ""),
            "graph_file": str(getattr(spec, "file", "") or ""),
            "clock": str(self.clock),
            "flush_interval_s": repr(self.flush_interval),
        })
        self._fh.flush()

    # ------------------------------------------------------------------------------------------------ API
    def tap(self, node_id: str, t: float, outputs: dict) -> None:
        """Runtime tap: called after every step with outputs; cheap and thread-safe (enqueue only)."""
        if self._closed or self.fatal is not None:
            return
        if self._epoch_ns is None:
            self._set_epoch(t)
        nbytes = 0
        for v in outputs.values():
            if v.__class__ is Sample:
                v = v.value
            if v.__class__ is np.ndarray:
                nbytes += v.nbytes
        k = len(outputs)
        item = (node_id, t, dict(outputs), nbytes)
        while True:
            # check and enqueue under one lock: checked outside it, two taps could both see the last free place
            # (or the last free bytes) and both go in, past max_queue / max_queue_bytes
            with self._q_lock:
                n = self._q.qsize()
                full = bool(self.max_queue) and n >= self.max_queue
                over = bool(self.max_queue) and nbytes > 0 and self._queued_bytes + nbytes > self.max_queue_bytes
                if over and self._queued_bytes == 0:
                    # a sample larger than the whole byte budget: no room can ever be made for it, so it goes in
                    # when no array waits (on a wall clock it was always dropped, on the simulated clock the tap
                    # waited forever); the memory held stays one such sample, and the tap never waits for it
                    over = False
                if not (full or over):
                    self._queued_bytes += nbytes
                    self._q.put(item)
                    if n + 1 > self.max_backlog:
                        self.max_backlog = n + 1
                    return
                if n > self.max_backlog:
                    self.max_backlog = n
                if self.clock != "sim" or not self._thread.is_alive():
                    # real time: never block the node's thread; the samples are dropped and counted (by limit and
                    # by node: the file's teletouch.drops record says what is missing)
                    self.dropped += k
                    if full:
                        self._dropped_items += k
                    else:
                        self._dropped_bytes += k
                    self._dropped_nodes[node_id] = self._dropped_nodes.get(node_id, 0) + k
                    return
            time.sleep(0.001)  # simulated clock: wait (without the lock) for the writer, record everything

    def close(self) -> None:
        """Write everything queued, the summary and the footer; close the file. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._q.put(_STOP)
        # the writer drains the queue first (a backlog of images takes a while): waited for while it makes progress;
        # a writer stuck in a write (a stalled network disk) would otherwise hang the end of the run for good
        last, idle = -1, 0.0
        while True:
            self._thread.join(timeout=0.25)
            if not self._thread.is_alive():
                break
            if self.messages != last:
                last, idle = self.messages, 0.0
                continue
            idle += 0.25
            if idle >= CLOSE_STALL_TIMEOUT:
                self.fatal = self.fatal or (f"the writer made no progress for {idle:.1f} s at close (a write that "
                                            f"does not return: a stalled disk?); the file was left as it is, "
                                            f"readable up to its last flush")
                self.log(f"recording {self.path}: {self.fatal}")
                raise RecordingError(f"recording {self.path} stopped early: {self.fatal}")
        try:
            if self.fatal is None:
                self._writer.add_metadata("teletouch.drops", self._drops_record())  # also "none dropped"
                self._writer.finish()
        except Exception as exc:  # the summary could not be written (disk full...): the data before it stays
            self._fail(exc, "writing the summary at close")
        finally:
            try:
                self._fh.close()  # flushes what is buffered: fails again on a full disk
            except OSError as exc:
                if self.fatal is None:
                    self._fail(exc, "closing the file")
        if self.dropped:
            limits = " and ".join(x for x, hit in (
                (f"max_queue {self.max_queue} items", self._dropped_items),
                (f"max_queue_bytes {self.max_queue_bytes} bytes", self._dropped_bytes)) if hit)
            self.log(f"{self.dropped} samples dropped: the writer fell behind ({limits}); the count is in the "
                     f"file (metadata teletouch.drops)")
        for e in self.errors[:5]:
            self.log(e)
        if len(self.errors) > 5:
            self.log(f"... {len(self.errors) - 5} more errors")
        done = "wrote" if self.fatal is None else "gave the writer (not all reached the file)"
        self.log(f"{done} {self.messages} messages on {len(self._chans)} channels to {self.path}")
        if self.fatal is not None:
            raise RecordingError(f"recording {self.path} stopped early: {self.fatal}")

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------ internals
    @staticmethod
    def _port_table(spec: Any) -> dict[tuple[str, str], Any]:
        table = {}
        for n in getattr(spec, "nodes", []) or []:
            cls = getattr(n, "cls", None)
            for pname, port in (getattr(cls, "outputs", None) or {}).items():
                table[(n.id, pname)] = port
        return table

    def _drops_record(self) -> dict[str, str]:
        """The ``teletouch.drops`` metadata record: samples dropped on a wall clock, in all, at each limit and by
        node (JSON), with the limits. Written at close (0: nothing dropped) and at a flush after new drops, so that
        a file cut short by a crash keeps the count up to its last flush."""
        with self._q_lock:
            return {"dropped": str(self.dropped), "dropped_queue_full": str(self._dropped_items),
                    "dropped_queue_bytes": str(self._dropped_bytes), "max_queue": str(self.max_queue),
                    "max_queue_bytes": str(self.max_queue_bytes), "nodes": json.dumps(self._dropped_nodes)}

    def _set_epoch(self, t: float) -> None:
        with self._epoch_lock:
            if self._epoch_ns is None:
                # wall clock: epoch = Unix time of graph time 0, from the graph clock's reading now (the tap comes
                # after the step, so taking "now" for its time t put every stamp late by the first step's length:
                # 40 ms against ros2-publish's stamps); without it, from t. sim clock: graph time is not real time;
                # graph time 0 is placed at the first recorded step's Unix time.
                now = self.graph_now() if self.graph_now is not None else t
                epoch = time.time_ns() - (int(round(now * 1e9)) if self.clock == "wall" else 0)
                self._q.put(("__epoch__", epoch, None, 0))
                self._epoch_ns = epoch

    def _schema(self, ros_type: str | None) -> int:
        if ros_type is None:
            return 0
        sid = self._schemas.get(ros_type)
        if sid is None:
            sid = self._writer.register_schema(ros_type, "ros2msg", ros2msg_definition(ros_type).encode())
            self._schemas[ros_type] = sid
        return sid

    def _register(self, node: str, port: str, codec: _Codec, value: Any, suffix: str = "") -> int:
        p = self._ports.get((node, port))
        topic = _topic(node, port) + suffix
        meta = {"node": node, "port": port, "codec": codec.kind,
                "dtype": p.dtype if p is not None else "any",
                "unit": p.unit if p is not None else "any",
                "shape": json.dumps(list(p.shape)) if p is not None and p.shape is not None else "null",
                "description": p.description if p is not None else ""}
        if isinstance(value, np.ndarray):  # what a reader gives back where the message does not keep the dtype
            meta["value_dtype"] = value.dtype.name
        if isinstance(codec, _Wrench):  # a force vector or a scalar: the message cannot tell
            meta["value_shape"] = "[3]" if codec.vector else "[]"
        return self._writer.register_channel(topic, "cdr" if codec.ros_type else "json",
                                             self._schema(codec.ros_type), meta)

    def _channel(self, node: str, port: str, value: Any) -> _Chan:
        ch = self._chans.get((node, port))
        if ch is None:
            p = self._ports.get((node, port))
            codec = _choose_codec(value, p, self.ros, self.opts)
            ch = _Chan(self._register(node, port, codec, value), codec)
            self._chans[(node, port)] = ch
        return ch

    def _prepare(self, node: str, t: float, port: str, v: Any) -> tuple[int, int, int, Any, str]:
        """(channel id, log ns, publish ns, encoded bytes or a Future of them, what) for one value. Images are
        encoded by the pool (cv2 releases the GIL), everything else here."""
        stamp = t
        if v.__class__ is Sample:
            stamp, v = v.stamp, v.value
        epoch = self._epoch_ns or 0
        stamp_ns = epoch + int(round(stamp * 1e9))
        log_ns = epoch + int(round(t * 1e9))
        ch = self._channel(node, port, v)
        codec, cid = ch.codec, ch.id
        if isinstance(v, np.ndarray) and v.shape == () and not isinstance(codec, _Json):
            v = v.item()
        if not codec.accepts(v):
            if ch.fallback is None:
                ch.fallback = self._register(node, port, _Json(), v, suffix="/json")
            codec, cid = _Json(), ch.fallback
        what = f"{node}.{port} at t={t:.3f}"
        if codec.kind in ("compressed", "json-image") and self._pool is not None:
            return cid, log_ns, stamp_ns, self._pool.submit(codec.encode, v, stamp_ns, node), what
        return cid, log_ns, stamp_ns, codec.encode(v, stamp_ns, node), what

    def _emit(self, wait: bool) -> None:
        """Write the prepared messages in order, as far as they are encoded (all of them if ``wait``)."""
        pend = self._pending
        while pend:
            cid, log_ns, pub_ns, data, what = pend[0]
            if not isinstance(data, (bytes, bytearray)):
                if not wait and not data.done() and len(pend) <= self._max_inflight:
                    return
                try:
                    data = data.result()
                except Exception as exc:
                    pend.popleft()
                    self._error(what, exc)
                    continue
            pend.popleft()
            self._seq += 1
            self._writer.add_message(cid, log_time=max(0, log_ns), data=data, publish_time=max(0, pub_ns),
                                     sequence=self._seq)
            self.messages += 1
            self._last_t = (log_ns - (self._epoch_ns or 0)) * 1e-9

    def _fail(self, exc: BaseException, doing: str) -> None:
        """The file cannot be written: stop recording (taps return at once), say where and why, now and at close."""
        n, t = self._flushed
        at = f" at graph time {self._last_t:.3f} s" if self._last_t is not None else ""
        kept = (f"the file keeps at least the {n} messages up to graph time {t:.3f} s (its last flush)" if n else
                "no message reached the file before it")
        self.fatal = f"{type(exc).__name__}: {exc} ({doing}{at}; {kept})"
        self.log(f"recording to {self.path} stopped: {self.fatal}; the run goes on without it")

    def _error(self, what: str, exc: BaseException) -> None:
        if len(self.errors) < 100:
            self.errors.append(f"{what}: {type(exc).__name__}: {exc}")

    def _run(self) -> None:
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        self._pending: deque = deque()
        workers = max(1, min(self.encode_threads, os.cpu_count() or 1))
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="teletouch-encode") if workers > 1 else None
        self._max_inflight = 4 * workers
        try:
            self._loop()
        except Exception as exc:  # the file cannot be written (disk full, ...): stop recording, say so at close
            self._fail(exc, "writing")
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)

    def _loop(self) -> None:
        q = self._q
        next_flush = time.monotonic() + self.flush_interval
        while True:
            try:
                item = q.get(timeout=max(0.0, min(next_flush - time.monotonic(), 0.005 if self._pending else 1.0)))
            except queue.Empty:
                item = None
            if item is _STOP:
                self._emit(wait=True)
                return
            if item is not None:
                node, t, outputs, nbytes = item
                if nbytes:
                    with self._q_lock:
                        self._queued_bytes -= nbytes
                if node == "__epoch__":
                    self._writer.add_metadata("teletouch.time", {"graph_epoch_ns": str(int(t)),
                                                                 "clock": str(self.clock)})
                else:
                    for port, v in outputs.items():
                        try:
                            self._pending.append(self._prepare(node, t, port, v))
                        except Exception as exc:  # keep recording the other ports
                            self._error(f"{node}.{port} at t={t:.3f}", exc)
                    if self.clock == "wall" and not self._lag_warned and self._epoch_ns is not None:
                        lag = (time.time_ns() - self._epoch_ns) * 1e-9 - t
                        if lag > 1.0:
                            self._lag_warned = True
                            self.log(f"the writer is {lag:.1f} s behind the graph: a crash would lose more than "
                                     f"1 s (image_format: jpeg is ~10x cheaper than png)")
            self._emit(wait=False)
            if time.monotonic() >= next_flush:
                self._emit(wait=True)
                if self.dropped != self._drops_written:  # (before the flush: the file then keeps it)
                    self._drops_written = self.dropped
                    self._writer.add_metadata("teletouch.drops", self._drops_record())
                self._writer.flush()  # closes the chunk in progress and flushes the file
                self._flushed = (self.messages, self._last_t)
                next_flush = time.monotonic() + self.flush_interval


# --------------------------------------------------------------------------------------------- reading
@dataclass
class ChannelInfo:
    id: int
    topic: str
    key: str  # "node.port" for teletouch recordings, the topic otherwise
    message_encoding: str
    schema_name: str
    metadata: dict[str, str]
    count: int = 0


@dataclass
class Recording:
    """Everything in an MCAP file, read sequentially (works on files cut short by a crash)."""

    path: str
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    truncated: bool = False  # the reader stopped before the footer (a crashed run, or a corrupt record)
    epoch_ns: int | None = None
    problem: str = ""  # why, when truncated: where the file is cut short or corrupt
    messages: int = 0  # messages read
    first_ns: int | None = None  # publish time of the file's first message: graph time 0 of another tool's file
    dropped: int | None = None  # samples the recorder dropped (teletouch.drops); None: the file does not say
    #: channels whose messages no reader here decodes (another tool's types: /rosout's rcl_interfaces/msg/Log, ...):
    #: "topic (schema)", left out by the readers of signals instead of failing the whole file
    undecoded: list[str] = field(default_factory=list)

    def graph_time(self, ns: int) -> float:
        return (ns - (self.epoch_ns or 0)) * 1e-9

    def note(self) -> str:
        """When truncated: where the reader stopped and how much it read, for a warning or an error."""
        return f"{self.problem}; {self.messages} messages read before it" if self.truncated else ""

    def drop_note(self) -> str:
        """When the recorder dropped samples (a writer behind a wall-clock run): how many, of which nodes and at
        which limit, for a warning; "" when none were dropped or the file does not say (another tool's file, one
        written before teletouch kept the count, or a run cut short before its first drop record)."""
        if not self.dropped:
            return ""
        d = self.metadata.get("teletouch.drops", {})
        try:
            nodes = ", ".join(f"{n} {c}" for n, c in sorted(json.loads(d.get("nodes") or "{}").items()))
        except (ValueError, AttributeError):
            nodes = ""
        limits = ", ".join(f"{d[key]} at {limit} {d.get(limit, '?')} {unit}" for key, limit, unit in (
            ("dropped_queue_full", "max_queue", "items"), ("dropped_queue_bytes", "max_queue_bytes", "bytes"))
            if d.get(key, "0") != "0")
        why = "; ".join(x for x in (nodes, f"the writer fell behind: {limits}" if limits else "") if x)
        return (f"{self.dropped} samples were dropped while recording" + (f" ({why})" if why else "")
                + ": the recording is incomplete")


def _codec_for(ch: ChannelInfo, path: str) -> _Codec:
    codec = _codec_or_none(ch)
    if codec is None:
        raise RecordingError(f"{path}: channel {ch.topic}: no decoder for schema '{ch.schema_name}' "
                             f"({ch.message_encoding})")
    return codec


def _codec_or_none(ch: ChannelInfo) -> _Codec | None:
    """The decoder of a channel's messages; None for a type no reader here knows (another tool's)."""
    kind = ch.metadata.get("codec")
    if kind in _CODECS:
        return _CODECS[kind]()
    if ch.message_encoding == "json":
        return _Json()
    for c in _CODECS.values():
        if c.ros_type and c.ros_type.replace("/msg/", "/") == ch.schema_name.replace("/msg/", "/"):
            return c()
    return None


def _decode(path: str, codec: _Codec, ch: ChannelInfo, msg: Any, epoch_ns: int) -> Any:
    """The value of one message; one that cannot be decoded is a RecordingError naming the file, the channel, which
    of its messages (``ch.count``: the messages read on it so far) and what was expected."""
    try:
        return codec.decode(msg.data, ch.metadata)
    except Exception as exc:
        t = (msg.publish_time - epoch_ns) * 1e-9
        raise RecordingError(f"{path}: channel {ch.topic}: message {ch.count} (at {t:.3f} s) cannot be decoded "
                             f"(expected {codec.expected}): {_why(exc)}") from None


_MAGIC = b"\x89MCAP0\r\n"


def is_mcap(path: str | os.PathLike) -> bool:
    """Whether the file at ``path`` starts as an MCAP file does (whatever its name's suffix)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(_MAGIC)) == _MAGIC
    except OSError:
        return False


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _unreadable(path: str, fh: Any, size: int, exc: BaseException, cut: bool) -> str:
    """Why a file in which not one MCAP record can be read is no recording."""
    if size == 0:
        return f"{path} is empty (0 bytes), not an MCAP recording"
    fh.seek(0)
    head = fh.read(9)
    if head[:8] != _MAGIC:
        return f"{path} is not an MCAP file (it does not start with the MCAP magic bytes)"
    if size == 8:
        return f"{path} is an empty MCAP file: only the 8 magic bytes, no record (nothing was recorded)"
    if head[8] != 0x01:
        return (f"{path} is a corrupt MCAP file: byte 8 should start the Header record (opcode 0x01), "
                f"found 0x{head[8]:02x}")
    cut_short = f"{path} is an empty MCAP file: it ends ({size} bytes) inside its first record, the Header"
    fh.seek(9)
    raw_length = fh.read(8)
    if len(raw_length) < 8:   # the file ends inside the Header's length field
        return cut_short
    length = int.from_bytes(raw_length, "little")
    end = 17 + length   # the Header record: opcode (byte 8), length (bytes 9-16), content
    corrupt = f"{path} is a corrupt MCAP file ({size} bytes): its first record, the Header"
    if length > _MAX_HEADER_LENGTH:
        return (f"{corrupt} gives its length (bytes 9-16) as {length} bytes; expected a few tens (a Header holds two "
                f"short texts, the profile and the library): the length field is damaged")
    if end > size:
        return cut_short if cut else f"{corrupt} (byte 8), cannot be read ({_why(exc)})"
    fh.seek(17)
    found = _header_damage(fh.read(length), 17)
    return f"{corrupt} (bytes 8-{end - 1}), cannot be read: {found or _why(exc)}"


#: the largest Header record (content, bytes) taken as whole-but-cut rather than as a damaged length field: a Header
#: holds two short texts (teletouch writes profile 'ros2' and library 'teletouch': 21 bytes)
_MAX_HEADER_LENGTH = 4096


def _header_damage(content: bytes, at: int) -> str | None:
    """What is wrong in the content of an MCAP Header record (it starts at byte ``at`` of the file): its two texts,
    the profile and the library, each a 4-byte length and that many bytes of UTF-8. None where both read."""
    pos = 0
    for name in ("profile", "library"):
        if pos + 4 > len(content):
            return (f"the {name} text's length (bytes {at + pos}-{at + pos + 3}) lies past the record's end (its "
                    f"{len(content)} bytes); expected the profile and the library texts")
        n = int.from_bytes(content[pos:pos + 4], "little")
        if pos + 4 + n > len(content):
            return (f"the {name} text's length (bytes {at + pos}-{at + pos + 3}) reads {n} bytes, more than the "
                    f"record's {len(content)} bytes of content hold (a damaged length; expected the profile and the "
                    f"library texts, e.g. 'ros2' and 'teletouch')")
        text = content[pos + 4:pos + 4 + n]
        try:
            text.decode("utf-8")
        except UnicodeDecodeError:
            return (f"the {name} text (bytes {at + pos + 4}-{at + pos + 3 + n}) is not UTF-8 text: {text!r} (damaged "
                    f"bytes; expected e.g. 'ros2' or 'teletouch')")
        pos += 4 + n
    return None


def _graph_epoch(path: str, text: str) -> int:
    """The ``graph_epoch_ns`` of a teletouch.time record; one that is no integer is a RecordingError (every graph time
    of the recording hangs on it: not one could be given right)."""
    try:
        return int(text)
    except ValueError:
        raise RecordingError(f"{path}: metadata record teletouch.time: graph_epoch_ns {text!r} is not an integer "
                             f"(a corrupt record): the graph times of the recording cannot be known") from None


def _iter_raw(path: str, rec: Recording) -> Iterator[tuple[ChannelInfo, Any]]:
    """Yield (channel, mcap Message) in file order. Where a crash cut the file (or a record is corrupt) stop with
    rec.truncated and rec.problem saying where; a file in which no record can be read raises RecordingError."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema
    from mcap.stream_reader import CRCValidationError, StreamReader

    schemas: dict[int, Any] = {}
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"cannot read the recording {path}: {exc.strerror or exc}") from exc
    with fh:
        size = os.fstat(fh.fileno()).st_size
        # CRCs checked: a chunk damaged on the disk is where the file is corrupt, not other values read back
        reader = StreamReader(fh, skip_magic=False, validate_crcs=True)
        it = reader.records
        records = 0
        while True:
            pos = fh.tell()  # where the next top-level record starts (a chunk is read whole)
            try:
                r = next(it)
            except StopIteration:
                return
            except Exception as exc:  # whatever the decoders raise on a cut or corrupt record (zstd: ZstdError)
                cut = isinstance(exc, EndOfFile) or fh.tell() >= size  # the reader ran into the end of the file
                if records == 0:
                    raise RecordingError(_unreadable(path, fh, size, exc, cut)) from None
                rec.truncated = True
                if cut:  # the end of a file whose writer was killed
                    where = "there, after its last whole record" if pos >= size else "inside that record"
                    rec.problem = (f"the recording is truncated at byte {pos} (the file, {size} bytes, ends {where}: "
                                   f"a run that crashed or is still recording)")
                elif isinstance(exc, CRCValidationError) and isinstance(exc.record, DataEnd):
                    rec.problem = (f"the recording is corrupt: a byte outside its chunks (a metadata record, or a "
                                   f"record's opcode) is damaged; the data section's CRC at byte {pos} does not match "
                                   f"({_why(exc)})")
                else:
                    rec.problem = f"the recording is corrupt at byte {pos} ({_why(exc)})"
                return
            records += 1
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                if r.id in rec.channels:
                    continue  # repeated in the summary section
                meta = dict(r.metadata)
                key = f"{meta['node']}.{meta['port']}" if "node" in meta and "port" in meta else r.topic
                if "node" in meta and "port" in meta and r.topic == _topic(meta["node"], meta["port"]) + "/json":
                    key += "/json"   # the sibling JSON channel (not a port named "json": its topic is /<node>/json)
                sname = schemas[r.schema_id].name if r.schema_id in schemas else ""
                rec.channels[r.id] = ChannelInfo(r.id, r.topic, key, r.message_encoding, sname, meta)
            elif isinstance(r, Metadata):
                rec.metadata[r.name] = dict(r.metadata)
                if r.name == "teletouch.time" and "graph_epoch_ns" in r.metadata:
                    rec.epoch_ns = _graph_epoch(path, r.metadata["graph_epoch_ns"])
                elif r.name == "teletouch.drops":
                    try:
                        rec.dropped = int(r.metadata["dropped"])
                    except (KeyError, ValueError):  # not as teletouch writes it: the count stays unknown
                        pass
            elif isinstance(r, Message):
                rec.messages += 1
                if rec.first_ns is None:
                    rec.first_ns = r.publish_time
                ch = rec.channels.get(r.channel_id)
                if ch is not None:
                    ch.count += 1
                    yield ch, r
            elif isinstance(r, Footer):
                return


def open_recording(path: str | os.PathLike, decode: bool = True, keys: Any = None,
                   ) -> tuple[Recording, list[tuple[str, float, float, Any]]]:
    """Read a recording: its :class:`Recording` description and a list of (key, stamp_s, log_s, value) in file
    order (graph time, s). ``keys``: only these "node.port" keys; ``decode=False`` gives the raw bytes. Decoded, a
    channel of a message type no reader here knows (another tool's) is left out and named in
    ``Recording.undecoded``; a sensor_msgs/JointState message is ``{joint: {"position": x, "velocity": v, "effort":
    e}}`` (the fields it carries) with its header stamp as ``stamp_s`` (the publish time where the header's is 0)."""
    return _read(str(path), None if keys is None else (lambda ch: ch.key in keys), decode)


def _read(path: str, want: Callable[[ChannelInfo], bool] | None, decode: bool = True,
          ) -> tuple[Recording, list[tuple[str, float, float, Any]]]:
    """:func:`open_recording` in one pass over the file, keeping the messages of the channels ``want`` takes (a
    channel's record, with its metadata, comes before its first message)."""
    rec = Recording(path)
    out = []
    codecs: dict[int, _Codec] = {}
    wanted: dict[int, bool] = {}
    for ch, msg in _iter_raw(path, rec):
        if want is not None:
            take = wanted.get(ch.id)
            if take is None:
                take = wanted[ch.id] = bool(want(ch))
            if not take:
                continue
        if decode:
            if ch.id not in codecs:
                codecs[ch.id] = _codec_or_none(ch)
                if codecs[ch.id] is None:   # another tool's type (a `ros2 bag record -a` has /rosout): left out,
                    rec.undecoded.append(f"{ch.topic} ({ch.schema_name})")   # not the whole file refused
            c = codecs[ch.id]
            if c is None:
                continue
            value = _decode(path, c, ch, msg, _epoch(rec))
            if isinstance(value, _HeaderStamped):   # the measurement's time (a bag's publish time is its arrival)
                stamp_ns = value.stamp_ns if value.stamp_ns > 0 else msg.publish_time
                out.append((ch.key, stamp_ns, msg.log_time, value.value))
                continue
        else:
            value = msg.data
        out.append((ch.key, msg.publish_time, msg.log_time, value))
    rec.epoch_ns = _epoch(rec)
    e = rec.epoch_ns
    return rec, [(k, (p - e) * 1e-9, (lt - e) * 1e-9, v) for k, p, lt, v in out]


def _epoch(rec: Recording) -> int:
    """Graph time 0 in Unix-epoch ns: teletouch's ``graph_epoch_ns``; for another tool's recording the publish
    time of the file's first message (whichever channels are read: every reader gives the same times)."""
    return rec.epoch_ns if rec.epoch_ns is not None else (rec.first_ns or 0)


def _is_image(ch: ChannelInfo) -> bool:
    return ch.metadata.get("codec") in ("compressed", "image", "json-image") or ch.schema_name.endswith(
        ("CompressedImage", "/Image"))


def _is_colour(ch: ChannelInfo) -> bool:
    """A BGR uint8 image channel (by the port's declared dtype/shape, else by the CompressedImage format); another
    tool's raw sensor_msgs/Image channel (no teletouch metadata: its encoding is in its messages) counts as one, its
    frames checked as they are decoded (it was "the recording has no images" for a bag of bgr8 Images)."""
    if "codec" not in ch.metadata and ch.schema_name.replace("/msg/", "/") == "sensor_msgs/Image":
        return True
    if ch.metadata.get("codec") not in ("compressed", "json-image") and not ch.schema_name.endswith(
            "CompressedImage"):
        return False
    if _recorded_bool(ch.metadata):
        return False
    shape = json.loads(ch.metadata.get("shape", "null") or "null")
    return shape is None or len(shape) == 3


def read_signals(path: str | os.PathLike, images: bool = False,
                 ) -> dict[str, tuple[np.ndarray, Any]]:
    """{"node.port": (stamps_s, values)} for every channel. Numbers give a float array; equal-shape arrays a stacked
    array (N, ...); strings and the rest a list. Images and depth maps only with ``images=True`` (a list). Another
    tool's sensor_msgs/JointState channel gives a float signal per joint and field, ``"<topic>.<joint>.position"``
    (``velocity``, ``effort``), each of the messages that carry that field, at their header stamps."""
    return _signals(str(path), images)[1]


def _signals(path: str, images: bool = False) -> tuple[Recording, dict[str, tuple[np.ndarray, Any]]]:
    """:func:`read_signals` and the :class:`Recording` it read them from, in one pass over the file."""
    rec, items = _read(path, None if images else (lambda ch: not _is_image(ch)))
    joints = {ch.key for ch in rec.channels.values() if isinstance(_codec_or_none(ch), _JointState)}
    grouped: dict[str, tuple[list[float], list[Any]]] = {}
    for key, stamp, _log, value in items:
        if key in joints:   # {joint: {field: value}}: a signal "key.joint.field" of the messages that carry it
            for joint, fields in value.items():
                for f, x in fields.items():
                    ts, vs = grouped.setdefault(f"{key}.{joint}.{f}", ([], []))
                    ts.append(stamp)
                    vs.append(x)
            continue
        ts, vs = grouped.setdefault(key, ([], []))
        ts.append(stamp)
        vs.append(value)
    out: dict[str, tuple[np.ndarray, Any]] = {}
    for key, (ts, vs) in grouped.items():
        out[key] = (np.asarray(ts, dtype=float), _stack(vs))
    return rec, out


def _stack(vs: list[Any]) -> Any:
    if all(isinstance(v, bool) for v in vs):
        return np.asarray(vs, dtype=bool)
    if all(_is_scalar_number(v) for v in vs):
        return np.asarray(vs, dtype=float)
    if all(isinstance(v, np.ndarray) for v in vs) and len({v.shape for v in vs}) == 1 and vs:
        if vs[0].ndim <= 1:
            return np.stack(vs)
    return vs


def iter_images(path: str | os.PathLike, port: str | None = None, log: Callable[[str], None] | None = None,
                on_damaged: Callable[[float, RecordingError], None] | None = None,
                ) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (stamp_s, BGR uint8 image) for the colour images of a recording, in recorded order; stamps are the
    capture times on the recording's graph clock (another tool's recording: from its first message, as the other
    readers give them). ``port``: "node.port", a port name or a topic; None: the only colour-image channel (an
    error names the choices if there are several). A mono8 channel is given as BGR; one of depth maps or masks is
    refused (the error names what it holds), and another tool's image that is no BGR or mono8 frame is an error as a
    message that cannot be decoded is (below). A recording cut short (a crashed run), or one whose recorder
    dropped samples, gives the images it holds, after a warning to ``log`` (if given). An image message that
    cannot be decoded raises a RecordingError naming the file, the channel and its time; with ``on_damaged`` it is
    handed to it instead, with its stamp, and skipped.

    The file is read twice, on purpose: a first pass decodes nothing and learns every channel (a channel's record
    may come after images of another one), so that an unknown or ambiguous ``port`` is refused and a cut file is
    warned about before the first image is given, not midway through a replay; the second pass decodes the chosen
    channel's images one at a time (a long recording's images are never all held in memory)."""
    path = str(path)
    rec = Recording(path)
    # a first pass (no image decoded): every channel must be known before the first image is given (an ambiguous
    # choice is refused, not found out midway), and a file cut short is warned about before its images are used
    for _ in _iter_raw(path, rec):
        pass
    note = f"; {rec.note()}" if rec.truncated else ""
    colour = [ch for ch in rec.channels.values() if _is_colour(ch)]
    if port is None:
        chosen = colour
        if len({c.key for c in chosen}) > 1:
            raise RecordingError(f"{path}: several image channels ({', '.join(sorted(c.key for c in chosen))}); "
                                 f"choose one with port=")
    else:
        chosen = [c for c in rec.channels.values() if _is_image(c) and port in (
            c.key, c.topic, c.metadata.get("port"))]
        if not chosen:
            raise RecordingError(f"{path}: no image channel '{port}'; image channels: "
                                 f"{', '.join(sorted(c.key for c in colour)) or '(none)'}{note}")
        if len({c.key for c in chosen}) > 1:
            raise RecordingError(f"{path}: '{port}' matches several image channels "
                                 f"({', '.join(sorted(c.key for c in chosen))}); give node.port")
        holds = _not_frames(chosen[0])
        if holds:
            others = ", ".join(sorted(c.key for c in colour)) or "(none)"
            raise RecordingError(f"{path}: channel '{chosen[0].key}' holds {holds}, not colour (BGR uint8) or mono8 "
                                 f"frames; colour image channels: {others}")
    if not chosen:
        raise RecordingError(f"{path}: the recording has no images{note}")
    if rec.truncated and log is not None:
        log(f"warning: {path}: {rec.note()}")
    if rec.dropped and log is not None:
        log(f"warning: {path}: {rec.drop_note()}")
    ids = {c.id for c in chosen}
    rec2 = Recording(path)
    codecs: dict[int, _Codec] = {}
    epoch = _epoch(rec)
    for ch, msg in _iter_raw(path, rec2):
        if ch.id not in ids:
            continue
        c = codecs.get(ch.id) or codecs.setdefault(ch.id, _codec_for(ch, path))
        stamp = (msg.publish_time - epoch) * 1e-9
        try:
            img = _frame(path, ch, _decode(path, c, ch, msg, epoch), stamp)
        except RecordingError as exc:
            if on_damaged is None:
                raise
            on_damaged(stamp, exc)
            continue
        yield stamp, img


def _not_frames(ch: ChannelInfo) -> str:
    """What an image channel teletouch wrote holds that is no frame (its depth maps: float or uint16 images; its
    masks), "" for colour or mono8 images; another tool's sensor_msgs/Image says only in its messages (bgr8 or depth:
    :func:`_frame`)."""
    if ch.metadata.get("codec") == "image":
        dt = _recorded_dtype(ch.metadata)
        return f"{dt.name if dt is not None else 'float or uint16'} images (sensor_msgs/msg/Image, depth maps)"
    return "bool masks" if _recorded_bool(ch.metadata) else ""


def _frame(path: str, ch: ChannelInfo, img: np.ndarray, stamp: float) -> np.ndarray:
    """A decoded image as a BGR uint8 frame (mono8 turned BGR); any other image (a depth map of another tool's
    recording, a 16-bit or 4-channel PNG) is a RecordingError naming the file, the channel and the message."""
    if img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3:
        return img
    if img.dtype == np.uint8 and img.ndim == 2:
        import cv2

        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    raise RecordingError(f"{path}: channel {ch.topic}: message {ch.count} (at {stamp:.3f} s) is a {img.dtype} "
                         f"{img.shape} image, not a BGR or mono8 frame")


# --------------------------------------------------------------------------------------------- plotting
#: the unit a plot shows a signal of each SI unit in, for a person to read (a gripper opening of 12.3 mm, not
#: 0.0123 m), and the factor from SI; the recording and what the readers give stay SI; other units are drawn as
#: recorded (N, rad, N*s/m...), and so is a signal whose unit the recording does not say
PLOT_UNITS: dict[str, tuple[str, float]] = {"m": ("mm", 1e3), "m/s": ("mm/s", 1e3), "m/s^2": ("mm/s^2", 1e3),
                                            "m^2": ("mm^2", 1e6), "J": ("mJ", 1e3)}

#: dtype kinds drawn as lines: float, bool, int (a recorded int array comes back as ints)
_DRAWN_KINDS = "fbiu"


def plot_recording(path: str | os.PathLike, outdir: str | os.PathLike | None = None,
                   select: str | None = None, log: Callable[[str], None] | None = None) -> list[Path]:
    """One PNG per node (a subplot per signal) of every numeric signal; returns the files written. Lengths are drawn
    in mm, energies in mJ (:data:`PLOT_UNITS`), the unit in the axis label. A recording cut short (a crashed run) is
    plotted as far as it can be read, with a warning to ``log`` (default: stderr)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = log or (lambda m: print(m, file=sys.stderr))
    try:
        pattern = re.compile(select) if select else None
    except re.error as exc:
        raise RecordingError(f"--select: invalid regular expression {select!r}: {exc}") from None
    path = Path(path)
    outdir = Path(outdir) if outdir is not None else path.with_name(path.stem + "_plots")
    rec, sig = _signals(str(path))   # one pass over the file: channels, units, signals and where it is cut
    units = {ch.key: ch.metadata.get("unit", "") for ch in rec.channels.values()}
    groups: dict[str, list[str]] = {}
    skipped = []  # numeric signals that cannot be drawn as lines, and why
    drawable = [key for key, (ts, vs) in sorted(sig.items()) if _drawable(ts, vs)]
    for key, (ts, vs) in sorted(sig.items()):
        if pattern is not None and not pattern.search(key):
            continue
        if _drawable(ts, vs):
            groups.setdefault(key.split(".")[0], []).append(key)
        elif isinstance(vs, np.ndarray) and vs.dtype.kind in _DRAWN_KINDS and len(ts):
            skipped.append(f"{key} ({'x'.join(map(str, vs.shape[1:]))} arrays)")
        elif isinstance(vs, list) and vs and all(isinstance(v, np.ndarray) and v.dtype.kind in _DRAWN_KINDS
                                                 for v in vs):
            shapes = sorted({v.shape for v in vs}, key=lambda sh: (len(sh), sh))
            what = ", ".join("x".join(map(str, sh)) or "scalar" for sh in shapes[:4])
            skipped.append(f"{key} ({what} arrays)" if len(shapes) == 1 else
                           f"{key} (its shape changes: {what}{', ...' if len(shapes) > 4 else ''})")
    not_drawn = f"; not drawn: {', '.join(skipped)}" if skipped else ""
    if not groups:
        there = (f"; numeric signals in the recording: {', '.join(drawable)}" if select and drawable else "")
        unread = f"; not read (no decoder for their message types): {', '.join(rec.undecoded)}" if rec.undecoded else ""
        raise RecordingError(f"{path}: no numeric signals to plot" + (f" matching '{select}'" if select else "")
                             + not_drawn + there + unread + (f": {rec.note()}" if rec.truncated else ""))
    if rec.truncated:
        log(f"warning: {path}: {rec.note()}; plotting those")
    if rec.dropped:
        log(f"warning: {path}: {rec.drop_note()}")
    if skipped:
        log(f"note: {path}: not drawn (only 1-D signals and vectors are): {', '.join(skipped)}")
    if rec.undecoded:
        log(f"note: {path}: not read (no decoder for their message types): {', '.join(rec.undecoded)}")
    if outdir.exists() and not outdir.is_dir():
        raise RecordingError(f"output folder {outdir} is a file, not a folder")
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot create the output folder {outdir}: {exc.strerror or exc}") from None
    written = []
    for node, keys in groups.items():
        fig, axes = plt.subplots(len(keys), 1, figsize=(9, 2.2 * len(keys) + 0.6), sharex=True, squeeze=False)
        for ax, key in zip(axes[:, 0], keys):
            ts, vs = sig[key]
            unit, scale = _plot_unit(units.get(key, ""))
            vals = vs.astype(float) * scale
            cols = vals.reshape(len(ts), -1)
            # a line needs two neighbouring finite points: a single sample (or one between NaNs) gets a marker
            finite = np.isfinite(cols)
            none = np.zeros_like(finite[:1])
            alone = finite & ~np.vstack([none, finite[:-1]]) & ~np.vstack([finite[1:], none])
            mark = dict(marker="o", ms=3) if alone.any() else {}
            if vals.ndim == 1:
                ax.plot(ts, vals, lw=1, **mark)
            else:
                for j in range(vals.shape[1]):
                    ax.plot(ts, vals[:, j], lw=1, label=f"[{j}]", **mark)
                ax.legend(loc="upper right", fontsize=7)
            n_nan, n_inf = int(np.isnan(cols).sum()), int(np.isinf(cols).sum())
            if n_nan or n_inf:  # matplotlib leaves them out silently: say so on the plot
                gaps = " and ".join(f"{n} {w}" for n, w in ((n_nan, "NaN"), (n_inf, "inf")) if n)
                ax.text(0.01, 0.95, f"{gaps} of {cols.size} values not drawn"
                        + (" (no finite value)" if not finite.any() else ""), transform=ax.transAxes,
                        fontsize=8, va="top", color="tab:red")
            ax.set_ylabel(f"{key.split('.', 1)[-1]}" + (f" [{unit}]" if unit else ""), fontsize=8)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel("graph time [s]")
        fig.suptitle(f"{path.name}: {node}", fontsize=10)
        fig.tight_layout()
        out = outdir / f"{re.sub(r'[^A-Za-z0-9_.-]', '_', node)}.png"
        try:
            _save_png(fig, out)
        finally:
            plt.close(fig)
        written.append(out)
    return written


def _plot_unit(unit: str) -> tuple[str, float]:
    """The unit a plot shows a signal of recorded ``unit`` in, and the factor from it ("" for none: dimensionless,
    "any" or not said)."""
    if unit == "any":
        return "", 1.0
    return PLOT_UNITS.get(unit, (unit, 1.0))


def _drawable(ts: np.ndarray, vs: Any) -> bool:
    """Whether a signal is drawn as lines: numbers or bools, scalars or vectors, at least one sample."""
    return isinstance(vs, np.ndarray) and vs.dtype.kind in _DRAWN_KINDS and vs.ndim in (1, 2) and len(ts) > 0


def _save_png(fig: Any, out: Path) -> None:
    """Write ``fig`` to the PNG ``out`` atomically: into a temporary file beside it, then renamed over it, so a
    write that fails midway (a full disk, a Ctrl-C) leaves the previous plot whole and no truncated file."""
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        fig.savefig(tmp, dpi=90, format="png")
        os.replace(tmp, out)
    except OSError as exc:
        raise RecordingError(f"cannot write the plot {out}: {exc.strerror or exc}") from None
    finally:
        if tmp.exists():
            try:
                tmp.unlink()
            except OSError:
                pass


def _regex(text: str) -> str:
    """``--select``: a regular expression, checked as the command line is read (a usage error, exit 2: it was 1)."""
    import re

    try:
        re.compile(text)
    except re.error as exc:
        raise argparse.ArgumentTypeError(f"invalid regular expression {text!r}: {exc}") from None
    return text


def _cmd_plot(args: argparse.Namespace) -> int:
    try:
        files = plot_recording(args.file, args.output, args.select,
                               log=lambda m: print(f"teletouch plot: {m}", file=sys.stderr))
    except RecordingError as exc:
        print(f"teletouch plot: {exc}", file=sys.stderr)
        return 1
    for f in files:
        print(f)
    return 0


@hookimpl
def teletouch_add_commands(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("plot", help="plot the signals of a recording (one PNG per node)")
    p.add_argument("file", metavar="FILE.mcap", help="a recording made with `teletouch run --record`")
    p.add_argument("-o", "--output", default=None, help="output folder (default: FILE_plots next to the file)")
    p.add_argument("--select", default=None, metavar="REGEX", type=_regex,
                   help="only signals whose node.port matches")
    p.set_defaults(func=_cmd_plot)
