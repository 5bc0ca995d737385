"""Recording items left open: drop counts kept in the file, a sample larger than max_queue_bytes on a wall clock,
small matrices recorded as arrays (not as depth-map images), and one time origin for recordings not made by
teletouch."""

from __future__ import annotations

import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import Writer

from teletouch.component import Port
from teletouch.recording import (Recorder, _Compressed, iter_images, open_recording, plot_recording, read_signals,
                                 ros2msg_definition)

from fakes.mcap_files import hold_writer

pytestmark = pytest.mark.timeout(120)

GUARD = 10.0   # s: only a broken recorder makes a test wait this long


def _drops(path: Path) -> Path:
    """A wall-clock recording that drops 3 samples at max_queue (2 items) and 1 at max_queue_bytes (150 bytes)."""
    rec = Recorder(path, None, max_queue=2, max_queue_bytes=150, log=lambda m: None)
    stuck = hold_writer(rec, GUARD)
    try:
        img = np.zeros((10, 10), np.uint8)            # 100 bytes
        rec.tap("cam", 0.01, {"mask": img})           # queued (no array waiting)
        rec.tap("cam", 0.02, {"mask": img})           # dropped: 200 bytes > max_queue_bytes
        rec.tap("est", 0.03, {"force": 1.0})          # queued: 2 items now
        rec.tap("est", 0.04, {"force": 2.0, "x": 3.0})   # dropped: the queue is full (2 samples)
        rec.tap("est", 0.05, {"force": 4.0})          # dropped: full
    finally:
        stuck.release.set()
        rec.close()
    assert rec.dropped == 4
    return path


# ---------------------------------------------------------------------------------- 1. drop counts in the file
def test_drop_counts_are_written_into_the_file_and_read_back(tmp_path):
    """The drop count was only logged at close: a person reading the file later could not tell it was
    incomplete."""
    path = _drops(tmp_path / "drops.mcap")
    rec, items = open_recording(path)
    assert rec.dropped == 4
    assert rec.metadata["teletouch.drops"]["dropped_queue_full"] == "3"
    assert rec.metadata["teletouch.drops"]["dropped_queue_bytes"] == "1"
    assert "4 samples were dropped while recording" in rec.drop_note()
    assert "cam 1, est 3" in rec.drop_note() and "max_queue 2 items" in rec.drop_note()
    assert sorted(k for k, *_ in items) == ["cam.mask", "est.force", "slow.obj"]


def test_a_run_cut_short_keeps_the_drop_count_of_its_last_flush(tmp_path):
    """The count is also written at the first flush after new drops: a file read before close (as a crashed run's
    is) already says what is missing."""
    import time

    path = tmp_path / "live.mcap"
    rec = Recorder(path, None, max_queue=2, flush_interval=0.05, log=lambda m: None)
    stuck = hold_writer(rec, GUARD)
    try:
        for k in range(5):   # 2 queued, 3 dropped
            rec.tap("est", 0.01 * (k + 1), {"force": float(k)})
    finally:
        stuck.release.set()
    try:
        deadline = time.monotonic() + GUARD
        while time.monotonic() < deadline:
            time.sleep(0.05)
            got, _ = open_recording(path)
            if got.dropped is not None:
                break
        assert got.truncated and got.dropped == 3, (got.truncated, got.dropped)
        assert "3 samples were dropped while recording (est 3;" in got.drop_note()
    finally:
        rec.close()


def test_a_recording_without_drops_says_none_and_one_without_the_record_is_unknown(tmp_path):
    with Recorder(tmp_path / "ok.mcap", None, log=lambda m: None) as r:
        r.tap("est", 0.0, {"force": 1.0})
    rec, _ = open_recording(tmp_path / "ok.mcap")
    assert rec.dropped == 0 and rec.drop_note() == ""
    path = _foreign(tmp_path / "other.mcap")          # no teletouch.drops record: readable, count unknown
    rec, items = open_recording(path)
    assert rec.dropped is None and rec.drop_note() == "" and len(items) == 5


def test_plot_warns_about_a_recording_with_drops(tmp_path):
    path = _drops(tmp_path / "drops.mcap")
    logs: list[str] = []
    plot_recording(path, tmp_path / "plots", log=logs.append)
    assert any(m.startswith(f"warning: {path}: 4 samples were dropped while recording") for m in logs), logs
    logs.clear()
    with Recorder(tmp_path / "ok.mcap", None, log=lambda m: None) as r:
        r.tap("est", 0.0, {"force": 1.0})
    plot_recording(tmp_path / "ok.mcap", tmp_path / "plots2", log=logs.append)
    assert not any("dropped" in m for m in logs), logs


# ------------------------------------------------------------------ 2. a sample larger than max_queue_bytes (wall)
def test_a_sample_larger_than_max_queue_bytes_on_a_wall_clock_is_recorded_when_no_array_waits(tmp_path):
    """On a wall clock a sample larger than max_queue_bytes was always dropped, even with an empty queue: a port
    whose frames exceed the budget was never recorded at all. It now goes in when no array waits (the tap never
    blocks; the memory held stays one such sample), and is dropped while another array waits."""
    rec = Recorder(tmp_path / "wall.mcap", None, max_queue_bytes=1000, log=lambda m: None)
    depth = np.full((40, 40), 1e-4, np.float32)   # 6400 bytes
    rec.tap("cam", 0.0, {"depth": depth})         # nothing queued: recorded
    stuck = hold_writer(rec, GUARD)
    try:
        rec.tap("cam", 0.1, {"depth": depth})         # queued: no array waits
        rec.tap("cam", 0.2, {"depth": depth})         # dropped: 6400 bytes already wait
        rec.tap("est", 0.2, {"force": 1.0})           # a scalar still goes in
    finally:
        stuck.release.set()
        rec.close()
    assert rec.dropped == 1
    _, items = open_recording(tmp_path / "wall.mcap")
    assert [(k, t) for k, t, _, _ in items if k == "cam.depth"] == [("cam.depth", 0.0), ("cam.depth", 0.1)]
    assert [k for k, *_ in items].count("est.force") == 1


# ------------------------------------------------------------------------- 3. small matrices are arrays, not images
def _spec(**ports: Port) -> types.SimpleNamespace:
    cls = types.SimpleNamespace(outputs=ports)
    return types.SimpleNamespace(clock="sim", nodes=[types.SimpleNamespace(id="n", cls=cls)])


def test_small_float_matrices_are_recorded_as_arrays_and_depth_maps_as_images(tmp_path):
    """A (N, 2) or (3, 3) float array went to the depth-map codec (sensor_msgs/Image) because only its ndim and
    dtype were looked at: read_signals and plots then left it out as an image, and a uint16 matrix came back in
    metres (16UC1 is depth in mm)."""
    spec = _spec(points=Port("float64", (None, 2), "m"), rot=Port("float64", (3, 3), ""),
                 counts=Port("uint16", (3, 3), ""), depth=Port("float32", (None, None), "m"),
                 small_depth=Port("float32", (None, None), "m"))
    pts = np.arange(20.0).reshape(10, 2) * 1e-3
    rot = np.eye(3)
    counts = np.arange(9, dtype=np.uint16).reshape(3, 3)
    depth = np.full((24, 32), 2e-4, np.float32)
    with Recorder(tmp_path / "m.mcap", spec, log=lambda m: None) as r:
        for k in range(3):
            r.tap("n", 0.1 * k, {"points": pts, "rot": rot, "counts": counts, "depth": depth,
                                 "small_depth": depth[:4, :4]})
            r.tap("free", 0.1 * k, {"m": rot, "img": depth})   # no declared port: by the value's shape
    rec, _ = open_recording(tmp_path / "m.mcap")
    schema = {c.key: c.schema_name for c in rec.channels.values()}
    assert schema["n.points"] == schema["n.rot"] == schema["n.counts"] == "std_msgs/msg/Float64MultiArray"
    assert schema["free.m"] == "std_msgs/msg/Float64MultiArray"
    assert schema["n.depth"] == schema["n.small_depth"] == schema["free.img"] == "sensor_msgs/msg/Image"
    sig = read_signals(tmp_path / "m.mcap")
    assert np.array_equal(sig["n.points"][1], np.stack([pts] * 3))
    assert np.array_equal(sig["n.rot"][1], np.stack([rot] * 3)) and np.array_equal(sig["free.m"][1][0], rot)
    assert np.array_equal(sig["n.counts"][1][0], counts)
    assert "n.depth" not in sig


# -------------------------------------------------------------- 4. one time origin for recordings of other tools
T0 = 1_700_000_000 * 10**9   # a Unix-epoch time in ns, as another tool's recorder writes


def _another_tools_writer(fh: Any, topic: str, ros_type: str) -> tuple[Writer, int]:
    """A Writer started as another tool's recorder starts one (ros2 profile, no teletouch metadata), with one CDR
    channel: (writer, channel id)."""
    w = Writer(fh)
    w.start(profile="ros2", library="another tool")
    sid = w.register_schema(ros_type, "ros2msg", ros2msg_definition(ros_type).encode())
    return w, w.register_channel(topic, "cdr", sid)


def _foreign(path: Path) -> Path:
    """An MCAP file of another tool (no teletouch metadata): /num (JSON) from T0, then /cam (CompressedImage)
    from T0 + 50 ms, every 100 ms."""
    with open(path, "wb") as fh:
        w, cam = _another_tools_writer(fh, "/cam", "sensor_msgs/msg/CompressedImage")
        num = w.register_channel("/num", "json", 0)
        for k in range(3):
            t = T0 + k * 10**8
            w.add_message(num, log_time=t, publish_time=t, data=b'{"value": 1.5}')
            if k < 2:
                img = _Compressed().encode(np.full((6, 8, 3), 30 * k, np.uint8), t + 5 * 10**7, "cam")
                w.add_message(cam, log_time=t + 5 * 10**7, publish_time=t + 5 * 10**7, data=img)
        w.finish()
    return path


def test_every_reader_counts_the_times_of_another_tools_recording_from_its_first_message(tmp_path):
    """iter_images gave another tool's recording absolute Unix times (1.7e9 s) while open_recording gave times from
    the first message it kept (so open_recording(keys=...) and read_signals each had their own zero)."""
    path = _foreign(tmp_path / "other.mcap")
    stamps = [s for s, _ in iter_images(path)]
    assert stamps == pytest.approx([0.05, 0.15], abs=1e-9)
    sig = read_signals(path, images=True)
    assert sig["/num"][0] == pytest.approx([0.0, 0.1, 0.2], abs=1e-9)
    assert sig["/cam"][0] == pytest.approx(stamps, abs=1e-9)
    rec, items = open_recording(path, keys={"/cam"})
    assert [t for _, t, _, _ in items] == pytest.approx(stamps, abs=1e-9)
    assert rec.epoch_ns == T0


def test_another_tools_wrench_is_read_back_whole(tmp_path):
    """A WrenchStamped of another tool (a wrist force/torque sensor's: no teletouch channel metadata) was read as
    force.z alone, teletouch's convention for a grip force: x, y and the torque were silently dropped. It is read
    back as the 6-vector (force xyz in N, torque xyz in N*m); teletouch's own channels are read as written."""
    from teletouch.recording import _Wrench

    path = tmp_path / "ft.mcap"
    with open(path, "wb") as fh:
        w, ch = _another_tools_writer(fh, "/wrist/wrench", "geometry_msgs/msg/WrenchStamped")
        data = bytearray(_Wrench().encode(np.array([1.0, -2.0, 3.0]), T0, "wrist"))
        data[-24:] = np.array([0.1, 0.2, -0.3]).tobytes()   # the torque (teletouch writes zeros there)
        for k in range(2):
            w.add_message(ch, log_time=T0 + k * 10**7, publish_time=T0 + k * 10**7, data=bytes(data))
        w.finish()
    ts, vs = read_signals(path)["/wrist/wrench"]
    assert vs.shape == (2, 6) and vs[1] == pytest.approx([1.0, -2.0, 3.0, 0.1, 0.2, -0.3]), vs
    assert plot_recording(path, tmp_path / "plots", log=lambda m: None)   # drawn as six lines
