"""replay: real DIGIT frames from a folder, a video and a teletouch recording; rate, loop, corrupt frames."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from teletouch import ComponentFault, Sample
from teletouch.errors import ModelFileError
from teletouch.plugins.sensors.replay import Replay, list_images
from teletouch.testing import Harness, make_registry, run_yaml

REG = None


def _reg():
    global REG
    if REG is None:
        REG = make_registry("teletouch.plugins.sensors.replay")
    return REG


def _graph(path, node_rate=30, **params):
    extra = "".join(f", {k}: {v!r}" for k, v in params.items())
    return f"""
name: replay
clock: sim
nodes:
  - id: cam
    plugin: replay
    rate: {node_rate}
    params: {{path: {str(path)!r}{extra}}}
"""


def _run(text, duration=2.0):
    got = []
    result, rt = run_yaml(text, _reg(), duration=duration,
                          taps=[lambda n, t, o: got.append((t, o["image"]))])
    return result, rt, got


def test_replay_real_digit_presses_folder(shared_data):
    import cv2

    folder = shared_data / "digit-presses-qvga"
    files = list_images(folder)
    assert [f.name for f in files] == [f"{k:04d}.png" for k in range(10)]  # labels.csv is not a frame
    result, rt, got = _run(_graph(folder), duration=5.0)
    assert result.status == "stopped"  # a normal stop requested by the node at the end
    assert "finished: 10 frames" in result.message
    assert len(got) == 10
    for (t, sample), f in zip(got, files):
        assert isinstance(sample, Sample) and sample.stamp == pytest.approx(t)
        assert sample.value.shape == (320, 240, 3) and sample.value.dtype == np.uint8
        assert np.array_equal(sample.value, cv2.imread(str(f)))
    # one frame per step at 30 Hz: the run ends right after the last one
    assert result.sim_time == pytest.approx(10 / 30, abs=0.05)


def test_replay_rate_and_loop(shared_data):
    folder = shared_data / "digit-presses-qvga"
    # 10 frames/s replayed by a 30 Hz node: a new frame every third step, stamps on the 0.1 s grid
    result, rt, got = _run(_graph(folder, node_rate=30, rate=10), duration=0.55)
    stamps = [s.stamp for _, s in got]
    assert stamps == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4, 0.5], abs=1e-9)
    # a 5 Hz node cannot keep up with 30 frames/s: it shows the newest frame and counts the skipped ones
    result, rt, got = _run(_graph(folder, node_rate=5, rate=30), duration=0.25)
    comp = rt.component("cam")
    assert comp.skipped >= 4
    # looping goes on past the end
    result, rt, got = _run(_graph(folder, node_rate=60, loop=True), duration=0.5)
    assert result.status == "ok" and len(got) >= 25
    assert rt.component("cam").passes >= 2
    first, again = got[0][1].value, got[10][1].value
    assert np.array_equal(first, again)


def test_replay_corrupt_frame_reported_with_its_name(shared_data, tmp_path):
    src = shared_data / "digit-presses-qvga"
    for k in (0, 2, 3):
        shutil.copy(src / f"{k:04d}.png", tmp_path / f"{k:04d}.png")
    (tmp_path / "0001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    logs = []
    with Harness(Replay, {"path": str(tmp_path)}) as h:
        h.comp.ctx._log = logs.append
        frames = [h.step(k / 30).get("image") for k in range(5)]
        assert sum(f is not None for f in frames) == 3
        assert h.comp.corrupt and "0001.png" in h.comp.corrupt[0]
        assert any("0001.png" in m for m in logs)
        assert h.stopped and "3 frames, 1 corrupt" in h.stopped
    with Harness(Replay, {"path": str(tmp_path), "on_corrupt": "fault"}) as h:
        h.step(0.0)
        with pytest.raises(ComponentFault, match="0001.png"):
            h.step(1 / 30)


def test_replay_video_file(tmp_path, shared_data):
    import cv2

    frames = [cv2.imread(str(f)) for f in list_images(shared_data / "digit-presses-qvga")]
    path = tmp_path / "presses.avi"
    # a camera-style landscape video: replay turns it portrait like the driver
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (320, 240))
    for f in frames:
        vw.write(cv2.rotate(f, cv2.ROTATE_90_CLOCKWISE))
    vw.release()
    result, rt, got = _run(_graph(path, node_rate=60), duration=2.0)
    assert len(got) == 10 and result.status == "stopped"
    stamps = [s.stamp for _, s in got]
    assert np.diff(stamps) == pytest.approx([1 / 20] * 9, abs=1e-6)  # the video's own 20 fps
    for (_, s), f in zip(got, frames):
        assert s.value.shape == (320, 240, 3)
        assert np.abs(s.value.astype(int) - f.astype(int)).mean() < 6  # MJPEG is lossy


def test_replay_teletouch_recording(tmp_path, shared_data):
    import cv2

    from teletouch.recording import Recorder

    frames = [cv2.imread(str(f)) for f in list_images(shared_data / "digit-presses-qvga")[:5]]
    path = tmp_path / "run.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        for k, f in enumerate(frames):
            rec.tap("digit", 0.1 + k * 0.05, {"image": Sample(f, 0.09 + k * 0.05), "force": 0.1 * k})
    result, rt, got = _run(_graph(path, node_rate=100), duration=1.0)
    assert len(got) == 5
    for (_, s), f in zip(got, frames):
        assert np.array_equal(s.value, f)  # PNG in the recording: lossless
    assert np.diff([s.stamp for _, s in got]) == pytest.approx([0.05] * 4, abs=1e-6)
    # looping a recording continues at its own frame interval
    result, rt, got = _run(_graph(path, node_rate=100, loop=True), duration=0.5)
    stamps = [s.stamp for _, s in got]
    assert len(got) >= 10 and rt.component("cam").skipped == 0 and rt.component("cam").passes >= 1
    assert np.diff(stamps) == pytest.approx([0.05] * (len(stamps) - 1), abs=1e-6)
    with pytest.raises(ModelFileError, match="no image channel 'nope'"):
        with Harness(Replay, {"path": str(path), "port": "nope"}):
            pass


def test_replay_path_errors(tmp_path, shared_data):
    with pytest.raises(ModelFileError, match="does not exist"):
        with Harness(Replay, {"path": str(tmp_path / "missing")}):
            pass
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelFileError, match="no images"):
        with Harness(Replay, {"path": str(tmp_path / "empty")}):
            pass
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"\x00" * 64)
    with pytest.raises(ModelFileError, match="bad.avi"):
        with Harness(Replay, {"path": str(bad)}):
            pass
    with pytest.raises(ModelFileError, match="single image"):
        with Harness(Replay, {"path": str(shared_data / "digit-presses-qvga" / "0000.png")}):
            pass
    with pytest.raises(ValueError):
        Replay.Params()  # path is required
