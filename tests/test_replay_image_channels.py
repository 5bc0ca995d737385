"""Replay review (2): a recording's depth-map or mask channel given as ``port`` is refused at configure, naming the
channel, what it holds and the colour channels there are (it was accepted and every frame then skipped as "not an
8-bit colour image", or it ended in an OpenCV traceback)."""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest

from teletouch.component import Port
from teletouch.plugins.sensors.replay import Replay
from teletouch.recording import Recorder, RecordingError
from teletouch.testing import Harness

pytestmark = pytest.mark.timeout(120)


def _recording(path: Path) -> Path:
    ports = {"image": Port("uint8", (None, None, 3)), "depth": Port("float32", (None, None), "m"),
             "gt_depth": Port("float64", (None, None), "m"), "mask": Port("bool", (None, None))}
    cls = types.SimpleNamespace(outputs=ports)
    spec = types.SimpleNamespace(nodes=[types.SimpleNamespace(id="digit", cls=cls)], clock="sim", name="g", file="")
    rng = np.random.default_rng(1)
    with Recorder(path, spec, log=lambda m: None) as rec:
        for k in range(4):
            rec.tap("digit", k / 30, {"image": np.full((32, 24, 3), 10 * k, np.uint8),
                                      "depth": rng.random((32, 24), dtype=np.float32) * 1e-3,
                                      "gt_depth": rng.random((32, 24)) * 1e-3, "mask": rng.random((32, 24)) > 0.5})
    return path


@pytest.mark.parametrize("port, key, holds", [("digit.depth", "digit.depth", "float32"),
                                              ("digit.gt_depth", "digit.gt_depth", "float64"),
                                              ("mask", "digit.mask", "bool")])
def test_replay_refuses_a_depth_or_mask_channel_at_configure(tmp_path, port, key, holds):
    path = _recording(tmp_path / "run.mcap")
    with pytest.raises(RecordingError) as err:
        with Harness(Replay, {"path": str(path), "port": port}):
            pass
    text = str(err.value)
    assert f"run.mcap: channel '{key}' holds {holds}" in text and "digit.image" in text, text
    assert "OpenCV" not in text and "cv::" not in text


def _played(path: Path) -> list[int]:
    """The first pixel of each frame replay plays of ``path``'s colour channel (``digit.image``)."""
    got = []
    with Harness(Replay, {"path": str(path), "port": "digit.image", "orientation": "as-is"}, rate=30.0) as h:
        for k in range(6):
            h.step(k / 30)
            if "image" in h.samples:
                got.append(int(h.samples["image"].value[0, 0, 0]))
            if h.stopped:
                break
    return got


def test_replay_of_the_colour_channel_of_the_same_recording_plays_every_frame(tmp_path):
    assert _played(_recording(tmp_path / "run.mcap")) == [0, 10, 20, 30]


def test_port_picks_the_channel_of_a_recording_without_the_mcap_suffix(tmp_path):
    """A recording renamed (``run.bag``) is replayed as a recording: its ``port`` was refused at validation ("applies
    only to a .mcap recording") because the check read the name, not the file; a port given for a video is refused."""
    assert _played(_recording(tmp_path / "run.mcap").rename(tmp_path / "run.bag")) == [0, 10, 20, 30]
    video = tmp_path / "run.mp4"
    video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(32))
    with pytest.raises(ValueError, match=r"port 'digit.image' applies only to a .mcap recording .*run.mp4.* is not"):
        Replay.Params(path=str(video), port="digit.image")
