"""Recording review (2): a force 3-vector on a port whose shape is not declared read back as force.z alone, a port
named "json" read back under another key, a damaged chunk read back as wrong values, a corrupt graph epoch and a disk
that refuses the first write ending in a traceback, and iter_images giving depth maps and masks as colour frames."""

from __future__ import annotations

import struct
import types
from pathlib import Path

import numpy as np
import pytest

from teletouch.component import Port
from teletouch.recording import Recorder, RecordingError, iter_images, open_recording, read_signals

from fakes.mcap_files import FullDisk

pytestmark = pytest.mark.timeout(120)


def _spec(node: str, ports: dict[str, Port]) -> types.SimpleNamespace:
    cls = types.SimpleNamespace(outputs=ports)
    return types.SimpleNamespace(nodes=[types.SimpleNamespace(id=node, cls=cls)], clock="sim", name="g", file="")


def _values(path: Path, key: str) -> list:
    _, items = open_recording(path)
    return [v for k, _s, _l, v in items if k == key]


# ---------------------------------------------------------------------------------- 1. force vectors (WrenchStamped)
def test_a_force_vector_on_a_port_of_undeclared_shape_is_read_back_whole(tmp_path):
    """A 3-vector in N on a port that does not declare (3,) (shape None: any) was written as force xyz and read back
    as force.z alone: x and y were silently lost."""
    path = tmp_path / "f.mcap"
    with Recorder(path, _spec("ft", {"force": Port("float64", None, "N")}), log=lambda m: None) as rec:
        rec.tap("ft", 0.0, {"force": np.array([1.0, -2.0, 3.0])})
        rec.tap("ft", 0.1, {"force": np.array([4.0, 5.0, -6.0])})
    got = _values(path, "ft.force")
    assert len(got) == 2 and all(isinstance(v, np.ndarray) for v in got), got
    assert np.array_equal(got[0], [1.0, -2.0, 3.0]) and np.array_equal(got[1], [4.0, 5.0, -6.0])
    t, f = read_signals(path)["ft.force"]
    assert f.shape == (2, 3)


def test_a_force_channel_keeps_the_form_of_its_first_value(tmp_path):
    """A scalar force after vectors on the same channel was read back as [0, 0, f] (x and y made up), a vector after
    scalars as its z alone; the other form goes to the sibling JSON channel, read back as it was."""
    path = tmp_path / "f.mcap"
    ports = {"vec": Port("float64", None, "N"), "sca": Port("float64", None, "N")}
    with Recorder(path, _spec("ft", ports), log=lambda m: None) as rec:
        rec.tap("ft", 0.0, {"vec": np.array([1.0, 2.0, 3.0]), "sca": 1.5})
        rec.tap("ft", 0.1, {"vec": 7.0, "sca": np.array([4.0, 5.0, 6.0])})
    assert [v.tolist() for v in _values(path, "ft.vec")] == [[1.0, 2.0, 3.0]]
    assert _values(path, "ft.vec/json") == [7.0]
    assert _values(path, "ft.sca") == [1.5]
    assert [np.asarray(v).tolist() for v in _values(path, "ft.sca/json")] == [[4.0, 5.0, 6.0]]


def test_a_force_vector_is_read_back_in_its_ports_dtype(tmp_path):
    """A float32 force vector came back float64 (an array channel keeps its dtype; the wrench did not)."""
    path = tmp_path / "f.mcap"
    with Recorder(path, _spec("ft", {"force": Port("float32", (3,), "N")}), log=lambda m: None) as rec:
        rec.tap("ft", 0.0, {"force": np.array([1.5, 2.0, -3.0], np.float32)})
    (v,) = _values(path, "ft.force")
    assert v.dtype == np.float32 and v.tolist() == [1.5, 2.0, -3.0]


def test_force_channels_stay_standard_wrenchstamped_messages(tmp_path):
    """The fix must keep the channels readable by ROS 2 tools: WrenchStamped, force on x, y, z."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "f.mcap"
    ports = {"vec": Port("float64", None, "N"), "sca": Port("float64", (), "N")}
    with Recorder(path, _spec("ft", ports), log=lambda m: None) as rec:
        rec.tap("ft", 0.0, {"vec": np.array([1.0, 2.0, 3.0]), "sca": 2.5})
    with open(path, "rb") as fh:
        got = {ch.topic: (sch.name, (m.wrench.force.x, m.wrench.force.y, m.wrench.force.z))
               for sch, ch, _msg, m in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()}
    assert got == {"/ft/vec": ("geometry_msgs/msg/WrenchStamped", (1.0, 2.0, 3.0)),
                   "/ft/sca": ("geometry_msgs/msg/WrenchStamped", (0.0, 0.0, 2.5))}


# ---------------------------------------------------------------------------------- 2. a port named "json"
def test_a_port_named_json_is_read_back_under_its_own_key(tmp_path):
    """Its topic /<node>/json ends like a sibling JSON channel's: its samples were given as 'log.json/json'."""
    path = tmp_path / "j.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        rec.tap("log", 0.0, {"json": {"event": "start"}, "text": "hello"})
        rec.tap("log", 0.1, {"text": 3.0})   # not a string: the sibling JSON channel of log.text
    sig = read_signals(path)
    assert sorted(sig) == ["log.json", "log.text", "log.text/json"]
    assert sig["log.json"][1] == [{"event": "start"}]


# ---------------------------------------------------------------------------------- 3. a damaged chunk
def test_a_chunk_whose_bytes_were_damaged_is_reported_not_read_back_as_other_values(tmp_path):
    """The chunks' CRCs were not checked: a flipped bit on the disk (an SD card, a drive pulled) gave other numbers,
    silently. A damaged chunk is now where the file is corrupt: read up to it, Recording.problem says so."""
    path = tmp_path / "d.mcap"
    value = 0.123456789012345
    with Recorder(path, None, log=lambda m: None) as rec:
        rec.tap("a", 0.0, {"x": 1.0})
        rec.tap("a", 0.1, {"x": value})
    data = bytearray(path.read_bytes())
    at = data.find(struct.pack("<d", value))
    assert at > 0, "the value is stored verbatim (an LZ4 literal)"
    data[at] ^= 0x01
    path.write_bytes(bytes(data))
    rec, items = open_recording(path)
    wrong = struct.unpack("<d", bytes(data[at:at + 8]))[0]
    assert wrong not in [v for k, _s, _l, v in items if k == "a.x"]
    assert rec.truncated and "corrupt" in rec.problem and "crc" in rec.problem.lower(), rec.problem


# ---------------------------------------------------------------------------------- 4. a corrupt graph epoch
def test_a_corrupt_graph_epoch_is_an_error_naming_the_file_and_the_record(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "e.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="teletouch")
        w.add_metadata("teletouch.time", {"graph_epoch_ns": "!795527643120979629"})
        cid = w.register_channel("/a/x", "json", 0, {"node": "a", "port": "x", "codec": "json"})
        w.add_message(cid, log_time=1, publish_time=1, data=b'{"value": 1.0}')
        w.finish()
    with pytest.raises(RecordingError, match=r"e\.mcap.*teletouch\.time.*graph_epoch_ns.*'!795527643120979629'"):
        open_recording(path)


# ---------------------------------------------------------------------------------- 5. a disk that refuses to start
def test_a_disk_that_refuses_the_first_write_is_an_error_naming_the_file(tmp_path, monkeypatch):
    """Recorder() flushes the file's header: on a full disk that raised a bare OSError (a traceback from `teletouch
    run --record`) and left the file open."""
    from teletouch import recording

    opened = []

    class Disk(FullDisk):
        def __call__(self, *a, **kw):
            fh = super().__call__(*a, **kw)
            opened.append(fh)
            return fh

    monkeypatch.setattr(recording, "open", Disk(0), raising=False)
    path = tmp_path / "full.mcap"
    with pytest.raises(RecordingError, match=r"cannot write the recording .*full\.mcap.*No space left on device"):
        Recorder(path, None, log=lambda m: None)
    assert len(opened) == 1 and opened[0].raw.fh.closed


# ---------------------------------------------------------------------------------- 6. images that are no frames
def _depth_recording(path: Path) -> Path:
    ports = {"image": Port("uint8", (None, None, 3)), "depth": Port("float32", (None, None), "m"),
             "d64": Port("float64", (None, None), "m"), "mask": Port("bool", (None, None)),
             "mono": Port("uint8", (None, None))}
    rng = np.random.default_rng(0)
    with Recorder(path, _spec("digit", ports), log=lambda m: None) as rec:
        for k in range(3):
            rec.tap("digit", k / 30, {"image": np.full((32, 24, 3), k, np.uint8),
                                      "depth": rng.random((32, 24), dtype=np.float32) * 1e-3,
                                      "d64": rng.random((32, 24)) * 1e-3, "mask": rng.random((32, 24)) > 0.5,
                                      "mono": np.full((32, 24), 7, np.uint8)})
    return path


@pytest.mark.parametrize("port, holds", [("digit.depth", "float32"), ("digit.d64", "float64"),
                                         ("digit.mask", "bool")])
def test_iter_images_refuses_a_channel_of_depth_maps_or_masks_naming_it(tmp_path, port, holds):
    """A depth map was given as a float32 'BGR' image, a float64 one or a mask ended in an OpenCV traceback."""
    path = _depth_recording(tmp_path / "d.mcap")
    with pytest.raises(RecordingError, match=rf"d\.mcap: channel '{port}' holds {holds} .*not colour.*digit\.image"):
        next(iter_images(path, port=port))


def test_iter_images_still_gives_a_mono8_channel_as_bgr(tmp_path):
    path = _depth_recording(tmp_path / "d.mcap")
    got = list(iter_images(path, port="digit.mono"))
    assert len(got) == 3 and all(img.dtype == np.uint8 and img.shape == (32, 24, 3) and (img == 7).all()
                                 for _s, img in got)


def test_another_tools_depth_image_is_an_error_per_message_naming_channel_and_time(tmp_path):
    """A sensor_msgs/Image channel of another tool may hold bgr8 frames (given) or depth (not a frame): which, only
    its messages say."""
    from mcap.writer import Writer
    from rclpy.serialization import serialize_message

    from teletouch.recording import image_msg, ros2msg_definition

    path = tmp_path / "bag.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="other")
        schema = ros2msg_definition("sensor_msgs/msg/Image").encode()
        sid = w.register_schema("sensor_msgs/msg/Image", "ros2msg", schema)
        cid = w.register_channel("/camera/depth", "cdr", sid, {})
        for k in range(2):
            ns = 10**18 + k * 50_000_000
            msg = image_msg(np.full((16, 12), 0.01, np.float32), 0.0, stamp_ns=ns)
            w.add_message(cid, log_time=ns, publish_time=ns, data=serialize_message(msg))
        w.finish()
    with pytest.raises(RecordingError, match=r"bag\.mcap: channel /camera/depth: message 1 \(at 0\.000 s\) is a "
                                             r"float32 \(16, 12\) image, not a BGR or mono8 frame"):
        next(iter_images(path, port="/camera/depth"))
    damaged = []
    assert list(iter_images(path, port="/camera/depth", on_damaged=lambda s, e: damaged.append((s, str(e))))) == []
    assert [round(s, 3) for s, _ in damaged] == [0.0, 0.05] and "message 2 (at 0.050 s)" in damaged[1][1]
    assert read_signals(path, images=True)["/camera/depth"][1][0].dtype == np.float32   # the data itself is fine


def test_an_empty_n_d_array_on_a_json_channel_keeps_its_shape(tmp_path):
    """An array after a scalar on one port goes to the JSON sibling channel; an empty (0, 4) one came back (0,): its
    list, [], says no shape."""
    path = tmp_path / "e.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        rec.tap("n", 0.0, {"x": 1.0})
        rec.tap("n", 0.1, {"x": np.zeros((0, 4), np.float32)})
        rec.tap("n", 0.2, {"x": np.ones((2, 3), np.float32)})
    got = _values(path, "n.x/json")
    assert [(v.shape, v.dtype) for v in got] == [((0, 4), np.float32), ((2, 3), np.float32)]


def test_a_file_cut_between_two_records_says_so(tmp_path):
    # before: "ends inside that record" also where the cut fell between two records
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    path = tmp_path / "c.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        for k in range(5):
            rec.tap("n", 0.1 * k, {"x": float(k)})
    data = path.read_bytes()
    with open(path, "rb") as fh:   # the end of the first chunk: a boundary between two records
        it = StreamReader(fh, emit_chunks=True).records
        while not isinstance(next(it), Chunk):
            pass
        end = fh.tell()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:end])
    got, _ = open_recording(cut)
    assert got.truncated and f"truncated at byte {end} (the file, {end} bytes, ends there, after its last whole " \
                              f"record" in got.problem, got.problem
    cut.write_bytes(data[:end + 3])
    got, _ = open_recording(cut)
    assert "ends inside that record" in got.problem, got.problem


@pytest.mark.parametrize("what", ["metadata key", "record opcode"])
def test_a_byte_damaged_outside_the_chunks_is_reported(tmp_path, what):
    """A flipped byte outside the chunks (the ``teletouch.time`` metadata record's name, a record's opcode byte) went
    unnoticed: the graph epoch was silently lost, or a record skipped (readers skip unknown opcodes). The writer now
    writes the data section's CRC, and the reader checks it: the damage is reported (Recording.problem)."""
    path = tmp_path / "m.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        rec.tap("a", 0.0, {"x": 1.0})
        rec.tap("a", 0.1, {"x": 2.0})
    data = bytearray(path.read_bytes())
    at = data.find(b"teletouch.time")
    assert at > 0
    if what == "metadata key":
        data[at + len("teletouch.tim")] ^= 0x01   # teletouch.timd
    else:
        at = data.rfind(b"\x0c", 8, at)   # the Metadata record's opcode (0x0C), before its name
        data[at] = 0x7F                   # an opcode no reader knows: skipped as a record of another kind
    path.write_bytes(bytes(data))
    rec, _items = open_recording(path)
    assert rec.truncated and "corrupt" in rec.problem and "crc" in rec.problem.lower(), rec.problem
    assert "a byte outside its chunks" in rec.problem, rec.problem
