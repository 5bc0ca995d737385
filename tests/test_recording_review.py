"""Recording review: a sample larger than the writer's byte budget, plots written atomically, messages that cannot
be decoded, and ``--select`` naming a signal the recording does not have."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import threading
import types
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from teletouch.cli import main as cli_main
from teletouch.recording import Recorder, RecordingError, iter_images, open_recording, read_signals

from fakes.mcap_files import damage_png, write_image_recording

pytestmark = pytest.mark.timeout(120)

GUARD = 10.0   # s: only a broken recorder makes a test wait this long


def _plot(capsys, *argv: object) -> tuple[int, str]:
    code = cli_main(["plot", *map(str, argv)])
    return code, capsys.readouterr().err


def _recording(path: Path) -> Path:
    with Recorder(path, None, log=lambda m: None) as rec:
        for k in range(20):
            rec.tap("src", k * 0.01, {"value": 0.5 * k, "v": np.array([k, 2.0 * k])})
            rec.tap("dev", k * 0.01, {"position": 1e-3 * k, "state": "ok"})
    return path


# ------------------------------------------------------------------------ a sample larger than max_queue_bytes
def test_a_sample_larger_than_max_queue_bytes_on_a_simulated_clock_is_recorded_not_waited_for_forever(tmp_path):
    """The byte check refused an item that alone is larger than the budget even with nothing queued: on the
    simulated clock the tap waited for room that could never come, and the simulation hung."""
    spec = types.SimpleNamespace(clock="sim", nodes=[])
    rec = Recorder(tmp_path / "sim.mcap", spec, log=lambda m: None, max_queue_bytes=1000)
    depth = np.full((40, 40), 1e-4, np.float32)   # 6400 bytes
    returned = threading.Event()

    def tap():
        rec.tap("cam", 0.0, {"depth": depth})
        rec.tap("cam", 0.1, {"depth": depth})   # waits for the first to be written, then goes in
        returned.set()

    threading.Thread(target=tap, daemon=True).start()
    try:
        assert returned.wait(GUARD), "the tap never returned"
    finally:
        rec.close()   # (a tap still waiting then sees the writer gone: it drops the sample and returns)
    assert rec.dropped == 0 and rec.errors == []
    _, items = open_recording(tmp_path / "sim.mcap")
    assert [t for _, t, _, _ in items] == [0.0, 0.1] and all(np.array_equal(v, depth) for *_, v in items)


# ------------------------------------------------------------------------------------------ atomic plot files
def test_a_plot_that_cannot_be_written_leaves_the_previous_one_whole(tmp_path):
    """savefig wrote straight into the plot's file: a write that failed midway (here the file-size limit, as a
    full disk does) left a truncated PNG in place of the previous, good one."""
    path = _recording(tmp_path / "run.mcap")
    out = tmp_path / "plots"
    cmd = [sys.executable, "-m", "teletouch.cli", "plot", str(path), "-o", str(out)]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=GUARD * 2)
    assert first.returncode == 0, first.stderr
    good = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(good) == ["dev.png", "src.png"] and all(len(b) > 5000 for b in good.values())

    def small_files():   # in the child: a file may not grow past 2000 bytes (Python ignores SIGXFSZ: EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2000, 2000))

    again = subprocess.run(cmd, capture_output=True, text=True, timeout=GUARD * 2, preexec_fn=small_files)
    assert again.returncode == 1
    assert "teletouch plot: cannot write the plot " in again.stderr and "File too large" in again.stderr
    assert "Traceback" not in again.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == good   # no truncated PNG, no temporary file left


# ------------------------------------------------------------------------------ messages that cannot be decoded
def _foreign(path: Path, encoding: str, schema: tuple[str, str] | None, data: bytes) -> Path:
    """An MCAP file written by another tool: one channel /other with 3 messages of ``data``."""
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="another tool")
        sid = w.register_schema(schema[0], schema[1], b"") if schema else 0
        cid = w.register_channel("/other", encoding, sid)
        for k in range(3):
            w.add_message(cid, log_time=(k + 1) * 10**8, publish_time=(k + 1) * 10**8, data=data)
        w.finish()
    return path


@pytest.mark.parametrize("case", ["json-without-value", "not-json", "unknown-schema"])
def test_a_message_that_cannot_be_decoded_is_an_error_naming_the_file_and_channel(tmp_path, capsys, case):
    """A JSON message not in teletouch's {"value": ...} form raised a bare KeyError (a traceback from
    `teletouch plot`), bytes that are no JSON a JSONDecodeError; a channel with no decoder said so without naming
    the file."""
    path = tmp_path / f"{case}.mcap"
    if case == "json-without-value":
        _foreign(path, "json", None, json.dumps({"a": 1}).encode())
        why = 'message 1 (at 0.000 s) cannot be decoded (expected JSON {"value": ...}, as teletouch writes): KeyError'
    elif case == "not-json":
        _foreign(path, "json", None, b"\x00\x01not json")
        why = 'message 1 (at 0.000 s) cannot be decoded (expected JSON {"value": ...}, as teletouch writes): JSONDecode'
    else:   # a type no reader knows: the channel is left out and named, not the whole file refused (a `ros2 bag
        # record -a` has /rosout)
        _foreign(path, "protobuf", ("foo.Bar", "protobuf"), b"\x08\x01")
        rec, items = open_recording(path)
        assert items == [] and rec.undecoded == ["/other (foo.Bar)"]
        assert read_signals(path) == {}
        code, err = _plot(capsys, path, "-o", tmp_path / "out")
        assert code == 1 and err.startswith(f"teletouch plot: {path}: no numeric signals to plot; not read (no "
                                            f"decoder for their message types): /other (foo.Bar)"), err
        return
    for read in (open_recording, read_signals):
        with pytest.raises(RecordingError) as info:
            read(path)
        assert str(info.value).startswith(f"{path}: channel /other: {why}"), info.value
    code, err = _plot(capsys, path, "-o", tmp_path / "out")
    assert code == 1 and err.startswith(f"teletouch plot: {path}: channel /other: {why}"), err


def test_an_image_that_cannot_be_decoded_is_an_error_naming_the_file_and_channel(tmp_path):
    """A CompressedImage whose PNG bytes are damaged (the record itself intact) stopped a replay with
    "could not decode a CompressedImage (bgr8; png compressed bgr8)", naming neither the file nor the channel."""
    from teletouch.recording import _Compressed

    data = damage_png(_Compressed().encode(np.full((4, 6, 3), 9, np.uint8), 0, "cam"))
    path = tmp_path / "img.mcap"
    write_image_recording(path, [(10**8, data)])
    why = (f"{path}: channel /cam/image: message 1 (at 0.100 s) cannot be decoded (expected a CDR "
           f"sensor_msgs/msg/CompressedImage): RecordingError: could not decode a CompressedImage")
    for read in (lambda p: list(iter_images(p)), lambda p: read_signals(p, images=True)):
        with pytest.raises(RecordingError) as info:
            read(path)
        assert str(info.value).startswith(why), info.value


# -------------------------------------------------------------------------------- --select matching no signal
def test_select_matching_no_signal_names_the_signals_there_are(tmp_path, capsys):
    """The error said only that nothing matched: a misspelt name left the user to guess the recording's names."""
    path = _recording(tmp_path / "run.mcap")
    code, err = _plot(capsys, path, "-o", tmp_path / "out", "--select", "posiiton")
    assert code == 1
    assert err.startswith(f"teletouch plot: {path}: no numeric signals to plot matching 'posiiton'; "
                          f"numeric signals in the recording: dev.position, src.v, src.value"), err
    assert not (tmp_path / "out").exists()
