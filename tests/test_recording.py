"""MCAP recording: round trip through the mcap library and a ROS 2 decoder, images, CLI --record, teletouch plot."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message

from teletouch import Component, Kind, Port, Sample, hookimpl
from teletouch.cli import main as cli_main
from teletouch.recording import (
    Recorder, RecordingError, iter_images, open_recording, read_signals, ros2msg_definition,
)
from teletouch.testing import load_text, make_registry, run_yaml
from teletouch.runtime import Runtime

pytestmark = pytest.mark.timeout(120)


def _frames(shared_data: Path, n: int = 4) -> list[np.ndarray]:
    files = sorted((shared_data / "digit-presses-qvga").glob("*.png"))[:n]
    frames = [cv2.imread(str(f), cv2.IMREAD_COLOR) for f in files]
    assert all(f is not None and f.shape == (320, 240, 3) for f in frames)
    return frames


class FakeTactile(Component):
    """Test source: real DIGIT frames (stamped 5 ms before the step, like a camera), a force, a depth map."""

    name = "fake-tactile"
    kind = Kind.SENSOR
    default_rate = 30.0
    outputs = {"image": Port("uint8", (None, None, 3), "", "BGR frame"),
               "depth": Port("float32", (None, None), "m", "depth"),
               "contact_mask": Port("bool", (None, None), "", "mask"),
               "force": Port("float64", (), "N", "force"),
               "centroid": Port("float64", (2,), "m", "centroid"),
               "status": Port("str", (), "", "status"),
               "contact": Port("bool", (), "", "contact")}
    frames: list[np.ndarray] = []

    def configure(self):
        self.k = 0

    def step(self, t, inputs):
        img = self.frames[self.k % len(self.frames)]
        self.k += 1
        depth = np.full((8, 6), 1e-4 * self.k, np.float32)
        return {"image": Sample(img, t - 0.005), "depth": depth, "contact_mask": depth > 5e-4,
                "force": 0.5 * self.k, "centroid": np.array([1e-3, -2e-3]) * self.k,
                "status": "ok" if self.k % 2 else "no-contact", "contact": bool(self.k % 2)}


class _Plugin:
    @staticmethod
    @hookimpl
    def teletouch_components():
        return [FakeTactile]


GRAPH = """
clock: sim
duration: 1
nodes:
  - {id: tactile, plugin: fake-tactile, rate: 30}
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: sine, amplitude: 2.0, frequency: 1.0}}
  - {id: dev, plugin: mock-device, rate: 200, params: {tau: 0.02}, inputs: {command: src.value}}
"""


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, shared_data):
    FakeTactile.frames = _frames(shared_data)
    reg = make_registry(_Plugin)
    spec = load_text(GRAPH, reg)
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    rt = Runtime(spec, log=lambda m: None)
    rec = Recorder(path, spec, log=lambda m: None)
    rt.add_tap(rec.tap)
    result = rt.run()
    rec.close()
    assert result.status == "ok", result.message
    assert rec.errors == [] and rec.dropped == 0
    return path, rec


def test_mcap_round_trip_with_ros2_encodings(recorded):
    path, rec = recorded
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        header = reader.get_header()
        channels = {c.topic: c for c in summary.channels.values()}
        schemas = {s.id: s for s in summary.schemas.values()}
        assert header.profile == "ros2"
        expect = {"/tactile/image": "sensor_msgs/msg/CompressedImage", "/tactile/depth": "sensor_msgs/msg/Image",
                  "/tactile/contact_mask": "sensor_msgs/msg/CompressedImage",
                  "/tactile/force": "geometry_msgs/msg/WrenchStamped",
                  "/tactile/centroid": "std_msgs/msg/Float64MultiArray", "/tactile/status": "std_msgs/msg/String",
                  "/tactile/contact": "std_msgs/msg/Bool", "/src/value": "std_msgs/msg/Float64",
                  "/dev/state": "std_msgs/msg/Float64"}
        for topic, ros_type in expect.items():
            ch = channels[topic]
            assert ch.message_encoding == "cdr"
            assert schemas[ch.schema_id].name == ros_type
            assert schemas[ch.schema_id].encoding == "ros2msg"
        counts = summary.statistics.channel_message_counts
        assert counts[channels["/src/value"].id] == 101  # 100 Hz for 1 s, both ends
        assert counts[channels["/tactile/image"].id] == 31
        assert sum(counts.values()) == rec.messages
    # a standard ROS 2 decoder (schema text + CDR, no rclpy) reads every message
    with open(path, "rb") as fh:
        n = 0
        for schema, channel, message, msg in make_reader(fh, decoder_factories=[DecoderFactory()]) \
                .iter_decoded_messages():
            n += 1
            if channel.topic == "/tactile/force":
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                assert stamp == message.publish_time
                assert msg.header.frame_id == "tactile"
            if channel.topic == "/tactile/image":
                assert msg.format == "bgr8; png compressed bgr8"
        assert n == rec.messages


def test_signals_values_and_stamps(recorded):
    path, _ = recorded
    sig = read_signals(path)
    assert "tactile.image" not in sig and "tactile.depth" not in sig  # images only on request
    t, v = sig["src.value"]
    assert len(t) == 101 and np.allclose(np.diff(t), 0.01, atol=1e-9)
    assert np.allclose(v, 2.0 * np.sin(2 * np.pi * t), atol=1e-12)
    t, f = sig["tactile.force"]
    assert np.allclose(f, 0.5 * np.arange(1, 32))
    assert np.allclose(t, np.arange(31) / 30.0, atol=1e-9)
    t, c = sig["tactile.centroid"]
    assert c.shape == (31, 2) and np.allclose(c[3], [4e-3, -8e-3])
    _, st = sig["tactile.status"]
    assert st[:2] == ["ok", "no-contact"]
    _, ct = sig["tactile.contact"]
    assert ct.dtype == bool and ct[0] and not ct[1]
    t, d = sig["dev.state"]
    assert len(t) == 201 and abs(d[-1]) < 2.0 and np.max(np.abs(d)) > 1.0
    full = read_signals(path, images=True)
    _, depth = full["tactile.depth"]
    assert depth[4].dtype == np.float32 and depth[4].shape == (8, 6) and np.allclose(depth[4], 5e-4)
    _, mask = full["tactile.contact_mask"]
    assert mask[5].dtype == bool and mask[5].all() and not mask[3].any()


def test_iter_images_lossless_with_capture_stamps(recorded, shared_data):
    path, _ = recorded
    frames = _frames(shared_data)
    got = list(iter_images(path))
    assert len(got) == 31
    for k, (stamp, img) in enumerate(got):
        assert img.dtype == np.uint8 and img.shape == (320, 240, 3)
        assert np.array_equal(img, frames[k % len(frames)])  # PNG: bit-exact
        assert stamp == pytest.approx(k / 30.0 - 0.005, abs=1e-9)  # the sample's capture stamp, not the step time
    assert len(list(iter_images(path, port="tactile.image"))) == 31
    with pytest.raises(RecordingError, match="no image channel 'nope'.*tactile.image"):
        next(iter_images(path, port="nope"))


def test_jpeg_and_json_fallback(tmp_path, shared_data):
    frames = _frames(shared_data, 2)
    for kw, n_close in (({"image_format": "jpeg"}, False), ({"ros_encoding": False}, True)):
        path = tmp_path / f"x{len(kw)}{list(kw)[0]}.mcap"
        with Recorder(path, None, log=lambda m: None, **kw) as rec:
            for k in range(4):
                rec.tap("cam", k * 0.1, {"image": frames[k % 2], "x": float("nan") if k == 3 else k * 1.5,
                                         "info": {"a": k}})
        ims = list(iter_images(path))
        assert len(ims) == 4
        err = np.abs(ims[1][1].astype(int) - frames[1].astype(int))
        if n_close:
            assert err.max() == 0  # PNG inside JSON
        else:
            assert 0 < err.mean() < 4  # JPEG: lossy, close
        sig = read_signals(path)
        assert np.allclose(sig["cam.x"][1][:3], [0, 1.5, 3.0]) and math.isnan(sig["cam.x"][1][3])
        assert sig["cam.info"][1][2] == {"a": 2}
    with open(tmp_path / "x1ros_encoding.mcap", "rb") as fh:
        chans = make_reader(fh).get_summary().channels.values()
        assert {c.message_encoding for c in chans} == {"json"}


PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
              "int64", "uint64", "string", "wstring"}


def test_ros2msg_schema_matches_the_installed_msg_files():
    """The schema text declares the same fields as the .msg files the ROS 2 packages install."""
    share = Path(sys.prefix) / "share"
    for ros_type in ("geometry_msgs/msg/WrenchStamped", "sensor_msgs/msg/Image", "sensor_msgs/msg/JointState",
                     "sensor_msgs/msg/CompressedImage", "std_msgs/msg/Float64MultiArray"):
        text = ros2msg_definition(ros_type)
        blocks = text.split("=" * 80 + "\n")
        pkg, _, name = ros_type.split("/")
        deps = {b.split("\n", 1)[0][5:]: b.split("\n", 1)[1] for b in blocks[1:]}
        for type_name, body in [(f"{pkg}/{name}", blocks[0]), *deps.items()]:
            p, n = type_name.split("/")
            msg_file = share / p / "msg" / f"{n}.msg"
            assert msg_file.is_file(), msg_file
            want = []
            for line in msg_file.read_text().splitlines():
                tokens = line.split("#", 1)[0].split()
                if len(tokens) < 2 or "=" in tokens[1]:
                    continue  # blank, comment or constant
                ftype, fname = tokens[:2]
                base = ftype.split("[")[0].split("<=")[0]
                if "/" not in base and base not in PRIMITIVES:
                    ftype = f"{p}/{ftype}"  # a type of the same package
                want.append(f"{ftype} {fname}")
            got = [ln for ln in body.strip().splitlines()]
            assert got == want, (type_name, got, want)


def test_cli_run_record_and_plot(tmp_path, repo_root):
    rec_path = tmp_path / "loop.mcap"
    code = cli_main(["run", str(repo_root / "examples" / "mock-loop.yaml"), "--duration", "1", "--quiet",
                     "--record", str(rec_path)])
    assert code == 0
    sig = read_signals(rec_path)
    assert set(sig) >= {"source.value", "scale.y", "device.state", "device.command_applied"}
    t, y = sig["scale.y"]
    assert len(t) == 101 and np.allclose(y, 0.02 * np.sin(2 * np.pi * 0.5 * t))
    out = tmp_path / "plots"
    code = subprocess.run([sys.executable, "-m", "teletouch", "plot", str(rec_path), "-o", str(out)],
                          capture_output=True, text=True, timeout=60)
    assert code.returncode == 0, code.stderr
    files = sorted(out.glob("*.png"))
    assert [f.name for f in files] == ["device.png", "scale.png", "source.png"]
    assert [str(f) for f in files] == sorted(code.stdout.split())
    img = cv2.imread(str(out / "device.png"))
    assert img is not None and img.shape[0] > 200 and img.std() > 10  # drawn, not blank
    bad = tmp_path / "bad.mcap"
    bad.write_text("not mcap")
    r = subprocess.run([sys.executable, "-m", "teletouch", "plot", str(bad)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 1 and "not an MCAP file" in r.stderr


# faults: no overrun faults and a watchdog of 1 s: on a loaded 2-core machine the run must not end by a fault of its
# own (late steps, a stalled thread) before the test kills it
CRASH_GRAPH = """
clock: wall
faults: {max_overruns: 0, watchdog: 1.0}
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: ramp, amplitude: 1.0}}
  - {id: dev, plugin: mock-device, rate: 200, inputs: {command: src.value}}
"""


def test_kill_9_mid_recording_keeps_everything_up_to_the_last_flush(tmp_path):
    import os
    import signal
    import time

    graph = tmp_path / "crash.yaml"
    graph.write_text(CRASH_GRAPH)
    path = tmp_path / "crash.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "teletouch", "run", str(graph), "--duration", "60", "--quiet",
                             "--record", str(path)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # wait for the run to be well under way
            time.sleep(0.25)
            if path.exists() and path.stat().st_size > 20_000:
                break
        assert proc.poll() is None, proc.stderr.read().decode()
        time.sleep(1.0)
        os.kill(proc.pid, signal.SIGKILL)
        killed_at = time.time_ns()
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    rec, items = open_recording(path)
    assert rec.truncated  # no footer: the reader stopped at the cut
    kill_t = (killed_at - rec.epoch_ns) * 1e-9
    t = np.array([s for k, s, _, _ in items if k == "src.value"])
    v = np.array([x for k, _, _, x in items if k == "src.value"])
    assert len(t) > 100
    assert np.allclose(v, t, atol=1e-6)  # the ramp's value is its own time: nothing garbled
    assert t[-1] > kill_t - 1.0, f"lost {kill_t - t[-1]:.3f} s (> 1 s) at kill -9"
    assert np.all(np.diff(t) > 0) and np.max(np.diff(t)) < 0.25  # no hole before the last flush
    with open(path, "rb") as fh:  # the mcap library itself reads the cut file too (stream mode)
        from mcap.stream_reader import StreamReader
        from mcap.records import Message

        n = 0
        try:
            for r in StreamReader(fh).records:
                n += isinstance(r, Message)
        except Exception:
            pass
        assert n >= len(t)
    meta = rec.metadata["teletouch"]
    assert meta["clock"] == "wall" and json.loads(meta["flush_interval_s"]) <= 0.5


def test_hand_written_cdr_equals_rclpy_serialization():
    """The recorder writes CDR itself (fast); rclpy's own serializer gives the same bytes but for padding."""
    from geometry_msgs.msg import WrenchStamped
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image
    from std_msgs.msg import Bool, Float64, Int64, String

    from teletouch.recording import _CODECS

    def same(a: bytes, b: bytes) -> bool:
        return len(a) == len(b) and deserialize_message(a, type_) == deserialize_message(b, type_)

    stamp = 1_700_000_000_123_456_789
    w = WrenchStamped()
    w.header.stamp.sec, w.header.stamp.nanosec, w.header.frame_id = 1_700_000_000, 123_456_789, "abcd"
    w.wrench.force.z = -2.5
    type_ = WrenchStamped
    assert same(_CODECS["wrench"]().encode(-2.5, stamp, "abcd"), serialize_message(w))
    w.wrench.force.x, w.wrench.force.y = 1.0, 2.0
    assert same(_CODECS["wrench"]().encode(np.array([1.0, 2.0, -2.5]), stamp, "abcd"), serialize_message(w))
    for type_, kind, v in ((Float64, "float64", 3.25), (Int64, "int64", -7), (String, "string", "no-contact")):
        assert same(_CODECS[kind]().encode(v, 0, ""), serialize_message(type_(data=v)))
    type_ = Bool
    for v in (True, False):
        assert deserialize_message(_CODECS["bool"]().encode(v, 0, ""), Bool).data is v
    type_ = Image
    depth = np.arange(12, dtype=np.float32).reshape(3, 4) * 1e-4
    im = Image()
    im.header.stamp.sec, im.header.stamp.nanosec, im.header.frame_id = 1_700_000_000, 123_456_789, "x"
    im.height, im.width, im.encoding, im.is_bigendian, im.step = 3, 4, "32FC1", 0, 16
    im.data = depth.tobytes()
    assert same(_CODECS["image"]().encode(depth, stamp, "x"), serialize_message(im))


def test_a_file_cut_anywhere_reads_up_to_the_cut(recorded, tmp_path):
    """A crash can stop the writer at any byte: the reader returns a prefix of the messages. Only a file cut before
    the end of its first record (the Header, written when the recorder starts) is no recording: an error says so."""
    path, rec = recorded
    data = path.read_bytes()
    _, full = open_recording(path, decode=False)
    header_end = 17 + int.from_bytes(data[9:17], "little")  # magic, opcode, length, the Header record
    cut_file = tmp_path / "cut.mcap"
    previous = 0
    for cut in sorted({int(len(data) * f) for f in np.linspace(0.0, 1.0, 41)} | {8, 9, 30, header_end, 100}):
        cut_file.write_bytes(data[:cut])
        if cut < header_end:
            with pytest.raises(RecordingError, match=r"cut\.mcap is (empty|an empty MCAP file)"):
                open_recording(cut_file, decode=False)
            continue
        r, items = open_recording(cut_file, decode=False)
        assert r.truncated == (cut < len(data))
        assert len(items) >= previous  # more file, never fewer messages
        assert [i[:2] for i in items] == [i[:2] for i in full[:len(items)]]  # a prefix, in order
        previous = len(items)
    assert previous == len(full) == rec.messages


def test_replay_sensor_plays_a_recording_back(recorded, shared_data):
    """The replay sensor (another area) reads our recording through iter_images: the same frames, in order."""
    path, _ = recorded
    frames = _frames(shared_data)
    reg = make_registry("teletouch.plugins.sensors.replay")
    got = []
    result, _ = run_yaml(f"""
clock: sim
duration: 5
nodes:
  - {{id: cam, plugin: replay, rate: 120, params: {{path: "{path}", port: tactile.image}}}}
""", reg, taps=[lambda n, t, o: got.append(o["image"])])
    assert result.status == "stopped", result.message  # the replay ends the run at the recording's end
    imgs = [s.value if isinstance(s, Sample) else s for s in got]
    assert len(imgs) == 31
    assert all(np.array_equal(img, frames[k % len(frames)]) for k, img in enumerate(imgs))


# ------------------------------------------------------------------------------------- bad input (audit #29, #30)
def _tiny_recording(path: Path, n: int = 5) -> Path:
    with Recorder(path, None, log=lambda m: None) as rec:
        for k in range(n):
            rec.tap("src", k * 0.01, {"value": 0.5 * k})
    return path


def _plot(capsys, *argv: str) -> tuple[int, str]:
    code = cli_main(["plot", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.err


def test_plot_bad_select_or_output_folder_is_an_error_not_a_traceback(tmp_path, capsys):
    path = _tiny_recording(tmp_path / "tiny.mcap")
    afile = tmp_path / "afile"
    afile.write_text("")
    code, err = _plot(capsys, path, "-o", afile)
    assert code == 1 and f"output folder {afile} is a file, not a folder" in err
    code, err = _plot(capsys, path, "-o", afile / "sub")
    assert code == 1 and f"cannot create the output folder {afile / 'sub'}: Not a directory" in err
    # a usage error, as the command line's other mistakes (exit 2; it was 1), before anything is read
    with pytest.raises(SystemExit) as exit_:
        cli_main(["plot", str(path), "-o", str(tmp_path / "out"), "--select", "["])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "argument --select: invalid regular expression '['" in err, err
    assert not (tmp_path / "out").exists()
    code, err = _plot(capsys, path, "-o", tmp_path / "out", "--select", "^src\\.")
    assert code == 0 and err == "" and (tmp_path / "out" / "src.png").is_file()


def test_files_without_one_readable_record_say_what_is_wrong(tmp_path, capsys):
    data = _tiny_recording(tmp_path / "tiny.mcap").read_bytes()
    cases = {"empty.mcap": (b"", "is empty (0 bytes), not an MCAP recording"),
             "text.mcap": (b"hello", "is not an MCAP file"),
             "magic.mcap": (data[:8], "is an empty MCAP file: only the 8 magic bytes"),
             "garbage.mcap": (data[:8] + b"\x00" * 100, "is a corrupt MCAP file: byte 8 should start the Header"),
             "header_cut.mcap": (data[:20], "is an empty MCAP file: it ends (20 bytes) inside its first record")}
    for name, (content, why) in cases.items():
        f = tmp_path / name
        f.write_bytes(content)
        for read in (open_recording, read_signals, lambda p: next(iter_images(p))):
            with pytest.raises(RecordingError) as info:
                read(f)
            assert str(info.value) == f"{f} {why}" or str(info.value).startswith(f"{f} {why}"), info.value
        code, err = _plot(capsys, f, "-o", tmp_path / "out")
        assert code == 1 and why in err and "no numeric signals" not in err


def _two_chunk_recording(path: Path, frames: list[np.ndarray] | None = None) -> tuple[Path, tuple[int, int]]:
    """A recording written in two goes, as the flushes of a run leave it: 5 values (and an image each if
    ``frames``), flushed, then 5 more. Returns it and the byte offsets of the first chunk and of the first chunk
    of the second go."""
    from fakes.mcap_files import record_in_two_flushes

    taps = [("src", k * 0.01, {"value": 0.5 * k} | ({"image": frames[k % len(frames)]} if frames else {}))
            for k in range(10)]
    chunks, first_go = record_in_two_flushes(path, taps, first=5, messages_first=5 * len(taps[0][2]))
    later = [c for c in chunks if c >= first_go]
    assert chunks[0] < first_go and later, (chunks, first_go)
    return path, (chunks[0], later[0])


def test_a_recording_cut_or_corrupt_midway_plots_what_it_has_with_a_warning(tmp_path, capsys):
    path, (first, second) = _two_chunk_recording(tmp_path / "full.mcap")
    data = path.read_bytes()
    cut = tmp_path / "crashed.mcap"  # as a crashed run leaves it: the second chunk half written
    cut.write_bytes(data[:second + 30])
    rec, items = open_recording(cut)
    assert rec.truncated and rec.messages == 5 and [v for _, _, _, v in items] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert rec.problem.startswith(f"the recording is truncated at byte {second}")
    code, err = _plot(capsys, cut, "-o", tmp_path / "out")
    assert code == 0 and (tmp_path / "out" / "src.png").is_file()
    assert err.startswith(f"teletouch plot: warning: {cut}: the recording is truncated at byte {second}")
    assert "5 messages read before it" in err
    # a corrupt record midway (not the end of the file): the same, saying where
    bad = bytearray(data)
    at = second + 52  # the Chunk record's LZ4 frame (after opcode, length, times, sizes, crc, "lz4")
    assert bad[at - 3 - 8:at - 8] == b"lz4" and bad[at:at + 4] == b"\x04\x22\x4d\x18"
    bad[at:at + 4] = b"\x00" * 4
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(bytes(bad))
    code, err = _plot(capsys, corrupt, "-o", tmp_path / "out2")
    assert code == 0 and (tmp_path / "out2" / "src.png").is_file()
    assert f"warning: {corrupt}: the recording is corrupt at byte {second} (RuntimeError: LZ4F_" in err
    assert "5 messages read before it" in err
    # cut inside the first chunk: records (header, metadata) but no message: an error that says why
    cut.write_bytes(data[:first + 30])
    code, err = _plot(capsys, cut, "-o", tmp_path / "out3")
    assert code == 1 and "no numeric signals to plot: the recording is truncated at byte" in err
    assert "0 messages read before it" in err
    # the complete file: no warning
    code, err = _plot(capsys, path, "-o", tmp_path / "out4")
    assert code == 0 and err == ""


def test_iter_images_warns_about_a_truncated_recording(tmp_path):
    frames = [np.full((24, 32, 3), k * 20, np.uint8) for k in range(10)]
    path, (_, second) = _two_chunk_recording(tmp_path / "full.mcap", frames)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:second + 30])
    logs: list[str] = []
    got = list(iter_images(cut, log=logs.append))
    assert [int(img[0, 0, 0]) for _, img in got] == [0, 20, 40, 60, 80]
    assert len(logs) == 1 and logs[0].startswith(f"warning: {cut}: the recording is truncated at byte {second}")
    assert list(iter_images(path, log=logs.append)) and len(logs) == 1  # complete: no warning


# ----------------------------------------------------------------------------- recording audit (disk full, plot)
DISK_GRAPH = """
clock: sim
duration: 2
nodes:
  - {id: src, plugin: mock-sensor, rate: 100, params: {signal: ramp, amplitude: 1.0}}
  - {id: dev, plugin: mock-device, rate: 1000, inputs: {command: src.value}}
"""


def test_disk_full_mid_run_the_run_goes_on_devices_end_safe_file_readable(tmp_path, monkeypatch):
    """The disk fills while recording: the run goes on to its end, the device ends in its safe state, close() says
    where (file, graph time, what the file keeps) and why, and the file reads up to the failure."""
    import teletouch.recording as recording
    from fakes.mcap_files import FullDisk

    disk = FullDisk(30_000)
    monkeypatch.setattr(recording, "open", disk, raising=False)
    reg = make_registry()
    spec = load_text(DISK_GRAPH, reg)
    path = tmp_path / "full.mcap"
    logs: list[str] = []
    rec = Recorder(path, spec, flush_interval=0.0, log=logs.append)  # a flush per item: the disk fills mid-run
    rt = Runtime(spec, log=lambda m: None)
    rt.add_tap(rec.tap)
    result = rt.run()
    assert result.status == "ok" and result.sim_time == pytest.approx(2.0)
    dev = next(n.comp for n in rt.nodes if n.id == "dev")
    assert dev.safe_calls >= 1 and dev.safe
    with pytest.raises(RecordingError) as info:
        rec.close()
    msg = str(info.value)
    assert msg.startswith(f"recording {path} stopped early: OSError: [Errno 28] No space left on device (writing at "
                          f"graph time ")
    assert disk.failures >= 1 and any("the run goes on without it" in m for m in logs)
    kept = int(msg.split("the file keeps at least the ")[1].split()[0])
    r, items = open_recording(path)
    assert r.truncated and r.messages >= kept > 0 and path.stat().st_size <= 30_000
    v = [(s, x) for k, s, _, x in items if k == "src.value"]
    assert v and all(x == pytest.approx(s, abs=1e-9) for s, x in v)  # the ramp's value is its time: intact


def test_a_stalled_disk_does_not_hang_close(tmp_path, monkeypatch):
    """A write that never returns (a stalled network disk): close() stops waiting for the writer once it makes no
    progress for CLOSE_STALL_TIMEOUT, with a RecordingError saying so, instead of hanging the end of the run."""
    import time

    import teletouch.recording as recording
    from fakes.mcap_files import StalledDisk

    disk = StalledDisk(20_000)
    monkeypatch.setattr(recording, "open", disk, raising=False)
    monkeypatch.setattr(recording, "CLOSE_STALL_TIMEOUT", 0.5)
    reg = make_registry()
    spec = load_text(DISK_GRAPH, reg)
    path = tmp_path / "stalled.mcap"
    rec = Recorder(path, spec, flush_interval=0.0, log=lambda m: None)
    rt = Runtime(spec, log=lambda m: None)
    rt.add_tap(rec.tap)
    try:
        assert rt.run().status == "ok"
        assert disk.blocked.wait(5.0)
        t0 = time.monotonic()
        with pytest.raises(RecordingError, match=r"stalled.mcap stopped early: the writer made no progress for "
                                                 r"0\.5 s at close"):
            rec.close()
        assert time.monotonic() - t0 < 3.0
    finally:
        disk.release.set()   # let the writer thread end


def test_disk_full_when_writing_the_summary_is_a_recording_error(tmp_path, monkeypatch):
    import teletouch.recording as recording
    from fakes.mcap_files import FullDisk

    monkeypatch.setattr(recording, "open", FullDisk(2_000), raising=False)
    rec = Recorder(tmp_path / "late.mcap", None, flush_interval=60.0, log=lambda m: None)  # no flush before close
    for k in range(300):
        rec.tap("src", k * 0.01, {"value": float(k)})
    with pytest.raises(RecordingError, match=r"late\.mcap stopped early: OSError: \[Errno 28\] No space left on "
                                             r"device \(writing the summary at close at graph time 2\.990 s; no "
                                             r"message reached the file before it\)"):
        rec.close()
    rec.close()  # idempotent, quiet


def test_cli_run_with_a_full_disk_keeps_the_run_summary_and_exits_1(tmp_path, monkeypatch, capsys):
    import teletouch.recording as recording
    from fakes.mcap_files import FullDisk

    monkeypatch.setattr(recording, "open", FullDisk(3_000), raising=False)
    graph = tmp_path / "g.yaml"
    graph.write_text(DISK_GRAPH)
    code = cli_main(["run", str(graph), "--quiet", "--record", str(tmp_path / "r.mcap")])
    err = capsys.readouterr().err
    assert code == 1
    assert f"teletouch: error: recording {tmp_path / 'r.mcap'} stopped early: OSError: [Errno 28]" in err
    assert "teletouch: ok: ran 2.000 s" in err  # the run's own result is still reported
    # --json says what the shell sees (it said exit_code 0 while the process exited 1) and why
    import json

    code = cli_main(["run", str(graph), "--quiet", "--json", "--record", str(tmp_path / "r2.mcap")])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 1 and result["exit_code"] == 1 and result["status"] == "ok"
    assert "stopped early" in result["recording_error"]


def test_json_channels_keep_arrays_with_nan_and_inf(tmp_path):
    """A NaN in an array (or a dict) on a JSON channel lost the whole message (json allow_nan=False)."""
    for ros in (True, False):
        path = tmp_path / f"nan{ros}.mcap"
        with Recorder(path, None, ros_encoding=ros, log=lambda m: None) as rec:
            rec.tap("n", 0.0, {"v": np.array([np.nan, np.inf, -np.inf, 1.0]), "d": {"f": np.array([np.nan, 2.0])}})
        assert rec.errors == []
        sig = read_signals(path)
        v = np.asarray(sig["n.v"][1][0], dtype=float)
        assert np.isnan(v[0]) and v[1] == np.inf and v[2] == -np.inf and v[3] == 1.0
        d = sig["n.d"][1][0]["f"]
        assert math.isnan(d[0]) and d[1] == 2.0


def test_an_empty_image_goes_to_the_json_channel_not_lost(tmp_path):
    path = tmp_path / "empty.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        for k in range(3):
            rec.tap("cam", k * 0.1, {"image": np.zeros((0, 0, 3), np.uint8) if k == 1 else
                                     np.full((4, 6, 3), k, np.uint8)})
    assert rec.errors == [] and rec.messages == 3
    _, items = open_recording(path)
    assert [k for k, *_ in items] == ["cam.image", "cam.image/json", "cam.image"]
    assert len(list(iter_images(path))) == 2


def _colour_pixels(png: Path, bgr: tuple[int, int, int]) -> int:
    img = cv2.imread(str(png)).astype(int)
    return int((np.abs(img - np.array(bgr)).sum(axis=2) < 40).sum())


def test_plot_a_single_sample_nan_values_and_arrays_that_change_shape(tmp_path, capsys):
    path = tmp_path / "odd.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        rec.tap("one", 0.0, {"x": 1.5})  # a single sample
        for k in range(4):
            rec.tap("gap", k * 0.01, {"x": float("nan") if k != 2 else 1.0})  # one finite value between NaNs
            rec.tap("bad", k * 0.01, {"x": float("nan")})
            rec.tap("grow", k * 0.01, {"v": np.arange(k + 1.0)})  # the shape changes: cannot be stacked
    code, err = _plot(capsys, path, "-o", tmp_path / "out")
    assert code == 0
    assert "note: " in err and "not drawn (only 1-D signals and vectors are): grow.v (its shape changes: 1, 2, 3" in err
    blue, red = (180, 119, 31), (40, 39, 214)  # tab:blue (the line), tab:red (the note), BGR
    assert _colour_pixels(tmp_path / "out" / "one.png", blue) > 10  # the single sample is drawn (a marker)
    assert _colour_pixels(tmp_path / "out" / "gap.png", blue) > 10
    assert _colour_pixels(tmp_path / "out" / "bad.png", red) > 10  # "4 NaN of 4 values not drawn"
    assert not (tmp_path / "out" / "grow.png").exists()
    code, err = _plot(capsys, path, "-o", tmp_path / "out2", "--select", "grow")
    assert code == 1 and "no numeric signals to plot matching 'grow'; not drawn: grow.v (its shape changes" in err


def test_record_images_without_record_is_a_usage_error(capsys):
    """`--record-images jpeg` without `--record` was ignored without a word (the run went on, exit 0)."""
    code = cli_main(["run", str(Path(__file__).resolve().parents[1] / "examples" / "mock-loop.yaml"), "--quiet",
                     "--duration", "0.1", "--record-images", "jpeg"])
    err = capsys.readouterr().err
    assert code == 2 and "--record-images: only with --record FILE.mcap" in err, err
