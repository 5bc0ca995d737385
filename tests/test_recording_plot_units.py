"""Recording items from the s14 closing note: plots in the units a person reads (mm, mJ, mm/s; the file stays SI),
and small uint8/bool/uint16 arrays that are not images recorded so that they come back exactly as written."""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from teletouch import recording
from teletouch.component import Port
from teletouch.recording import (Recorder, _Raw, iter_images, open_recording, plot_recording, read_signals,
                                 ros2msg_definition)

pytestmark = pytest.mark.timeout(120)


def _spec(**ports: Port) -> types.SimpleNamespace:
    """A graph spec with one node "n" declaring ``ports`` as its outputs (what the recorder looks at)."""
    cls = types.SimpleNamespace(outputs=ports)
    return types.SimpleNamespace(clock="sim", nodes=[types.SimpleNamespace(id="n", cls=cls)])


def _plotted(monkeypatch, path: Path, out: Path) -> dict[str, tuple[str, list[np.ndarray]]]:
    """Plot ``path``; {y label: (port, the ydata of each line)} of every subplot, read from the figures."""
    got: dict[str, tuple[str, list[np.ndarray]]] = {}
    save = recording._save_png

    def keep(fig, dest):
        for ax in fig.axes:
            if ax.lines:
                label = ax.get_ylabel()
                got[label.split(" [")[0]] = (label, [np.asarray(ln.get_ydata(), float) for ln in ax.lines])
        save(fig, dest)

    monkeypatch.setattr(recording, "_save_png", keep)
    assert plot_recording(path, out, log=lambda m: None)
    return got


# ------------------------------------------------------------------------------ 1. plots in mm, mJ, mm/s, N
def test_plots_show_lengths_in_mm_energies_in_mJ_and_speeds_in_mm_per_s(tmp_path, monkeypatch):
    """The plot drew metres and joules (a gripper opening of 0.0123 m): a person reads millimetres. The recording
    and what the readers give stay SI; a force stays in N and a signal of unknown unit as it is."""
    spec = _spec(opening=Port("float64", (), "m"), speed=Port("float64", (), "m/s"), energy=Port("float64", (), "J"),
                 force=Port("float64", (), "N"), pos=Port("float64", (3,), "m"), area=Port("float64", (), "m^2"),
                 angle=Port("float64", (), "rad"), ratio=Port("float64", (), ""))
    path = tmp_path / "u.mcap"
    with Recorder(path, spec, log=lambda m: None) as r:
        for k in range(4):
            r.tap("n", 0.1 * k, {"opening": 0.0123 + 1e-3 * k, "speed": 0.02 * k, "energy": 1.5e-3 * k,
                                 "force": 2.0 + k, "pos": np.array([1e-3, 2e-3, 3e-3]) * k, "area": 2e-5 * k,
                                 "angle": 0.1 * k, "ratio": 0.5 * k})
            r.tap("n", 0.1 * k, {"free": 0.25 * k, "ticks": np.array([k, 2 * k], np.int32)})   # not declared
    got = _plotted(monkeypatch, path, tmp_path / "plots")
    k = np.arange(4)
    expect = {"opening": ("opening [mm]", [12.3 + k]), "speed": ("speed [mm/s]", [20.0 * k]),
              "energy": ("energy [mJ]", [1.5 * k]), "force": ("force [N]", [2.0 + k]),
              "pos": ("pos [mm]", [1.0 * k, 2.0 * k, 3.0 * k]), "area": ("area [mm^2]", [20.0 * k]),
              "angle": ("angle [rad]", [0.1 * k]), "ratio": ("ratio", [0.5 * k]), "free": ("free", [0.25 * k]),
              "ticks": ("ticks", [1.0 * k, 2.0 * k])}   # an int array comes back as ints: still drawn
    assert set(got) == set(expect)
    for port, (label, lines) in expect.items():
        assert got[port][0] == label
        assert len(got[port][1]) == len(lines)
        for line, want in zip(got[port][1], lines):
            np.testing.assert_allclose(line, want, rtol=1e-12, err_msg=port)
    sig = read_signals(path)   # the data stay SI
    np.testing.assert_allclose(sig["n.opening"][1], 0.0123 + 1e-3 * k)
    np.testing.assert_allclose(sig["n.energy"][1], 1.5e-3 * k)
    rec, _ = open_recording(path)
    assert {c.key: c.metadata["unit"] for c in rec.channels.values()}["n.opening"] == "m"


# ----------------------------------------------------------------------- 2. small arrays that are not images
def test_small_uint8_and_bool_arrays_are_arrays_that_come_back_exactly(tmp_path):
    """A 4x4 uint8 lookup (or a declared (2, 2, 3) palette) went to the image codec (JPEG with image_format="jpeg":
    its values changed), a 3x3 bool mask of an undeclared port came back as uint8 0/255 and an int32 vector as
    float64."""
    spec = _spec(lut=Port("uint8", (4, 4), ""), cells=Port("bool", (3, 2), ""), palette=Port("uint8", (2, 2, 3), ""))
    lut = (np.arange(16, dtype=np.uint8) * 13).reshape(4, 4)
    cells = np.array([[True, False], [False, True], [True, True]])
    mask = np.eye(3, dtype=bool)
    vec = np.array([-3, 0, 70000], np.int32)
    palette = (np.arange(12, dtype=np.uint8) * 21).reshape(2, 2, 3)
    path = tmp_path / "small.mcap"
    with Recorder(path, spec, image_format="jpeg", log=lambda m: None) as r:
        for k in range(2):
            r.tap("n", 0.1 * k, {"lut": lut, "cells": cells, "palette": palette})
            r.tap("free", 0.1 * k, {"mask": mask, "lut": lut, "vec": vec})
    rec, items = open_recording(path)
    schema = {c.key: c.schema_name for c in rec.channels.values()}
    arrays = ("n.lut", "n.cells", "n.palette", "free.mask", "free.lut")
    assert {schema[k] for k in arrays} == {"std_msgs/msg/Float64MultiArray"}
    want = {"n.lut": lut, "n.cells": cells, "n.palette": palette, "free.mask": mask, "free.lut": lut, "free.vec": vec}
    assert sorted({k for k, *_ in items}) == sorted(want)
    for key, _, _, value in items:
        assert value.dtype == want[key].dtype, key
        assert np.array_equal(value, want[key]), key
    sig = read_signals(path)   # arrays, not images: read_signals gives them (2-D ones as a list)
    assert [m.dtype for m in sig["free.mask"][1]] == [np.dtype(bool)] * 2
    assert sig["n.lut"][1][1].dtype == np.uint8 and np.array_equal(sig["n.lut"][1][1], lut)
    assert sig["free.vec"][1].dtype == np.int32 and sig["free.vec"][1].shape == (2, 3)


def test_uint16_arrays_come_back_as_written_not_as_metres(tmp_path):
    """A uint16 2-D array (16UC1) came back as float32 x 1e-3, the ROS convention for a depth map in mm: teletouch
    recorded the array it was given; only another tool's 16UC1 is read as millimetres of depth."""
    spec = _spec(raw=Port("uint16", (None, None), ""), lut=Port("uint16", (2, 3), ""))
    raw = (np.arange(24 * 32, dtype=np.uint16) * 80).reshape(24, 32)
    lut = np.array([[1, 2, 3], [65535, 0, 7]], np.uint16)
    path = tmp_path / "u16.mcap"
    with Recorder(path, spec, log=lambda m: None) as r:
        r.tap("n", 0.0, {"raw": raw, "lut": lut})
        r.tap("free", 0.0, {"raw": raw, "small": lut})
    rec, items = open_recording(path)
    schema = {c.key: c.schema_name for c in rec.channels.values()}
    assert schema["n.raw"] == schema["free.raw"] == "sensor_msgs/msg/Image"   # still an image message
    assert schema["n.lut"] == schema["free.small"] == "std_msgs/msg/Float64MultiArray"
    got = {k: v for k, _, _, v in items}
    for key, want in (("n.raw", raw), ("free.raw", raw), ("n.lut", lut), ("free.small", lut)):
        assert got[key].dtype == np.uint16 and np.array_equal(got[key], want), key
    # another tool's 16UC1 depth map (no teletouch channel metadata) is still millimetres -> metres
    other = tmp_path / "other.mcap"
    with open(other, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="another tool")
        image = "sensor_msgs/msg/Image"
        sid = w.register_schema(image, "ros2msg", ros2msg_definition(image).encode())
        cid = w.register_channel("/depth", "cdr", sid)
        w.add_message(cid, log_time=10**9, publish_time=10**9, data=_Raw().encode(lut, 10**9, "cam"))
        w.finish()
    _, items = open_recording(other)
    assert items[0][3].dtype == np.float32 and np.allclose(items[0][3], lut * 1e-3)


def test_images_and_depth_maps_are_recorded_as_before(tmp_path):
    """Camera images, depth maps and declared masks keep their image messages (an image port says so by its
    declared shape, even for a small frame); an undeclared large bool mask stays a PNG image and comes back as
    bool; a colour frame is JPEG where asked."""
    spec = _spec(image=Port("uint8", (None, None, 3), ""), depth=Port("float32", (None, None), "m"),
                 contact_mask=Port("bool", (None, None), ""))
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    small = frame[:4, :6]
    depth = np.full((6, 5), 2e-4, np.float32)
    mask = depth[:3, :3] > 1e-4
    big_mask = rng.random((16, 12)) > 0.5
    path = tmp_path / "img.mcap"
    with Recorder(path, spec, image_format="jpeg", log=lambda m: None) as r:
        r.tap("n", 0.0, {"image": small, "depth": depth, "contact_mask": mask})
        r.tap("n", 0.1, {"image": frame, "depth": depth, "contact_mask": mask})
        r.tap("free", 0.0, {"mask": big_mask, "frame": frame})
    rec, items = open_recording(path)
    ch = {c.key: c for c in rec.channels.values()}
    compressed = "sensor_msgs/msg/CompressedImage"
    assert [ch[k].schema_name for k in ("n.image", "n.contact_mask", "free.mask", "free.frame")] == [compressed] * 4
    assert ch["n.depth"].schema_name == "sensor_msgs/msg/Image"
    got = {(k, t): v for k, t, _, v in items}
    assert got[("n.image", 0.1)].shape == frame.shape and not np.array_equal(got[("n.image", 0.1)], frame)  # JPEG
    assert np.array_equal(got[("n.depth", 0.0)], depth) and got[("n.depth", 0.0)].dtype == np.float32
    assert got[("n.contact_mask", 0.0)].dtype == bool and np.array_equal(got[("n.contact_mask", 0.0)], mask)
    assert got[("free.mask", 0.0)].dtype == bool and np.array_equal(got[("free.mask", 0.0)], big_mask)
    assert [img.shape for _, img in iter_images(path, port="n.image")] == [small.shape, frame.shape]
    with pytest.raises(recording.RecordingError, match="several image channels.*free.frame, n.image"):
        next(iter_images(path))   # the bool masks are no colour-image channels


def test_without_ros_small_arrays_are_json_arrays_of_their_dtype(tmp_path):
    """Without the ROS 2 message packages (JSON everywhere) a small uint8 or bool array was a base64 PNG and a
    bool mask of an undeclared port came back as uint8 0/255."""
    lut = (np.arange(6, dtype=np.uint8) * 40).reshape(2, 3)
    mask = np.eye(3, dtype=bool)
    frame = np.zeros((16, 16, 3), np.uint8)
    path = tmp_path / "json.mcap"
    with Recorder(path, None, ros_encoding=False, log=lambda m: None) as r:
        r.tap("free", 0.0, {"lut": lut, "mask": mask, "frame": frame})
    rec, items = open_recording(path)
    codec = {c.key: c.metadata["codec"] for c in rec.channels.values()}
    assert codec == {"free.lut": "json", "free.mask": "json", "free.frame": "json-image"}
    got = {k: v for k, _, _, v in items}
    assert got["free.lut"].dtype == np.uint8 and np.array_equal(got["free.lut"], lut)
    assert got["free.mask"].dtype == bool and np.array_equal(got["free.mask"], mask)


# ------------------------------------------------------------------------------------------- 3. noticed there
def test_a_dict_with_a_png_key_is_read_back_as_the_dict(tmp_path):
    """Every JSON channel took a dict with a "png" key for teletouch's base64 PNG image (only the json-image
    channels hold those): a component's dict output {"png": "ok", ...} could not be read back."""
    info = {"png": "written", "n": 2}
    for ros in (True, False):
        path = tmp_path / f"dict{ros}.mcap"
        with Recorder(path, None, ros_encoding=ros, log=lambda m: None) as r:
            r.tap("n", 0.0, {"info": info})
        _, items = open_recording(path)
        assert [(k, v) for k, _, _, v in items] == [("n.info", info)]
