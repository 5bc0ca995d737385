"""Recordings, outside audit: a complete recording whose Header record has flipped bytes was reported as "an empty MCAP
file: it ends (29970991 bytes) inside its first record" (by ``teletouch plot`` and the ``replay`` sensor): it is
corrupt, and the error says what was found where and what was expected. The ``replay`` sensor reports a recording's
problems as a RecordingError, not as a ModelFileError (a recording is no model file), with the same exit code."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teletouch import Sample
from teletouch.cli import main as cli_main
from teletouch.errors import ModelFileError
from teletouch.plugins.sensors.replay import Replay
from teletouch.recording import Recorder, RecordingError, iter_images, open_recording, read_signals
from teletouch.testing import Harness

pytestmark = pytest.mark.timeout(120)


def _recording(path: Path, frames: int = 40) -> Path:
    """A complete recording (summary and footer) with images and forces, some hundred kB long."""
    rng = np.random.default_rng(3)
    with Recorder(path, None, log=lambda m: None) as rec:
        for k in range(frames):
            t = k / 30
            rec.tap("digit", t, {"image": Sample(rng.integers(0, 255, (48, 36, 3), dtype=np.uint8), t)})
            rec.tap("force", t, {"force": Sample(0.05 * k, t)})
    return path


def _damaged(src: Path, dst: Path, flips: dict[int, int]) -> Path:
    data = bytearray(src.read_bytes())
    for at, mask in flips.items():
        data[at] ^= mask
    dst.write_bytes(bytes(data))
    return dst


def _readers(path: Path) -> list[str]:
    """The error each reader gives for ``path``."""
    out = []
    for read in (open_recording, read_signals, lambda p: next(iter(iter_images(p)))):
        with pytest.raises(RecordingError) as info:
            read(path)
        out.append(str(info.value))
    return out


def test_a_long_file_with_a_damaged_header_is_corrupt_not_empty(tmp_path, capsys):
    whole = _recording(tmp_path / "run.mcap")
    size = whole.stat().st_size
    assert size > 10_000
    assert whole.read_bytes()[17:38] == b"\x04\x00\x00\x00ros2\x09\x00\x00\x00teletouch"   # as the audit's file
    # the audit's damage: bytes 20-21 flipped (the profile's length field, and its first letter)
    bad = _damaged(whole, tmp_path / "flip_head.mcap", {20: 0xFF, 21: 0xFF})
    for err in _readers(bad):
        assert "empty" not in err and "ends" not in err, err
        assert err.startswith(f"{bad} is a corrupt MCAP file ({size} bytes): its first record, the Header (bytes "
                              f"8-37), cannot be read: the profile text's length (bytes 17-20) reads 4278190084 "
                              f"bytes, more than the record's 21 bytes of content hold"), err
        assert "expected the profile and the library texts" in err, err
    code = cli_main(["plot", str(bad), "-o", str(tmp_path / "plots")])
    err = capsys.readouterr().err
    assert code == 1 and "is a corrupt MCAP file" in err and "empty" not in err, err

    # a damaged letter: the text is named with what was found
    letter = _damaged(whole, tmp_path / "letter.mcap", {31: 0x80})
    for err in _readers(letter):
        assert err.startswith(f"{letter} is a corrupt MCAP file ({size} bytes): its first record, the Header (bytes "
                              f"8-37), cannot be read: the library text (bytes 29-37) is not UTF-8 text: "
                              f"b'te\\xecetouch'"), err
    # a damaged length of the record itself: far beyond any Header (and beyond the file), not a file cut short
    length = _damaged(whole, tmp_path / "length.mcap", {16: 0x01})
    for err in _readers(length):
        assert err.startswith(f"{length} is a corrupt MCAP file ({size} bytes): its first record, the Header gives "
                              f"its length (bytes 9-16) as 72057594037927957 bytes; expected a few tens"), err
        assert "the length field is damaged" in err, err


def test_a_file_that_ends_inside_its_header_is_still_an_empty_one(tmp_path):
    whole = _recording(tmp_path / "run.mcap", frames=2).read_bytes()
    for n in (9, 12, 20, 37):
        cut = tmp_path / f"cut{n}.mcap"
        cut.write_bytes(whole[:n])
        for err in _readers(cut):
            assert err == f"{cut} is an empty MCAP file: it ends ({n} bytes) inside its first record, the Header", err


def test_replay_reports_a_recordings_problems_as_a_recording_error(tmp_path):
    whole = _recording(tmp_path / "run.mcap")
    bad = _damaged(whole, tmp_path / "flip_head.mcap", {20: 0xFF, 21: 0xFF})
    with pytest.raises(RecordingError, match=r"flip_head\.mcap is a corrupt MCAP file \(\d+ bytes\): its first "
                                             r"record, the Header \(bytes 8-37\), cannot be read") as info:
        with Harness(Replay, {"path": str(bad)}):
            pass
    assert not isinstance(info.value, ModelFileError)
    # a recording without images (the audit's sub.mcap of a ros2-subscribe run)
    sub = tmp_path / "sub.mcap"
    with Recorder(sub, None, log=lambda m: None) as rec:
        for k in range(5):
            rec.tap("ros", k / 30, {"force": Sample(0.1 * k, k / 30)})
    with pytest.raises(RecordingError, match=r"sub\.mcap: the recording has no images") as info:
        with Harness(Replay, {"path": str(sub)}):
            pass
    assert not isinstance(info.value, ModelFileError)
    with pytest.raises(RecordingError, match=r"no image channel 'nope'"):
        with Harness(Replay, {"path": str(whole), "port": "nope"}):
            pass


def test_teletouch_run_names_the_recording_error_and_keeps_the_exit_code(tmp_path, capsys):
    sub = tmp_path / "sub.mcap"
    with Recorder(sub, None, log=lambda m: None) as rec:
        rec.tap("ros", 0.0, {"force": Sample(0.1, 0.0)})
    graph = tmp_path / "replay.yaml"
    graph.write_text(f"name: replaytest\nclock: sim\nnodes:\n  - id: digit\n    plugin: replay\n    rate: 60\n"
                     f"    params: {{path: {sub}}}\n")
    code = cli_main(["run", str(graph), "--duration", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 4, err   # EXIT_STARTUP, as before
    assert f"RecordingError: {sub}: the recording has no images" in err and "ModelFileError" not in err, err
