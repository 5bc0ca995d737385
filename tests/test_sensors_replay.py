"""replay: real DIGIT frames from a folder, a video and a teletouch recording; rate, loop, corrupt frames."""

from __future__ import annotations

import shutil
import threading

import numpy as np
import pytest

from teletouch import ComponentFault, Sample
from teletouch.errors import GraphValidationError, ModelFileError
from teletouch.plugins.sensors.replay import Replay, list_images
from teletouch.recording import RecordingError
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
    with pytest.raises(RecordingError, match="no image channel 'nope'"):
        with Harness(Replay, {"path": str(path), "port": "nope"}):
            pass


def test_replay_path_errors(tmp_path, shared_data):
    # a missing path or a single image is refused with the parameters, so `teletouch validate` says it (it said OK,
    # and the run failed at start-up)
    with pytest.raises(ValueError, match=r"path '.*missing' does not exist; expected a folder of images"):
        Replay.Params(path=str(tmp_path / "missing"))
    with pytest.raises(ValueError, match=r"path 'nope' does not exist \(looked at .*nope: a relative path is taken "
                                         r"from the current folder"):
        Replay.Params(path="nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelFileError, match="no images"):
        with Harness(Replay, {"path": str(tmp_path / "empty")}):
            pass
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"\x00" * 64)
    with pytest.raises(ModelFileError, match="bad.avi"):
        with Harness(Replay, {"path": str(bad)}):
            pass
    with pytest.raises(ValueError, match="is a single image; give the folder"):
        Replay.Params(path=str(shared_data / "digit-presses-qvga" / "0000.png"))
    with pytest.raises(ValueError, match=r"path\s+Field required"):
        Replay.Params()  # path is required


# ------------------------------------------------------------------------------------- bad input (audit #30, #31)
def test_replay_port_only_applies_to_a_recording(tmp_path, shared_data):
    folder = shared_data / "digit-presses-qvga"
    with pytest.raises(ValueError, match=r"port 'cam.image' applies only to a \.mcap recording.*"
                                         r"is not a \.mcap file \(by its name or its first bytes\): remove port"):
        Replay.Params(path=str(folder), port="cam.image")
    with pytest.raises(GraphValidationError, match=r":8: node 'cam': params of replay: port 'cam.image' applies"):
        _run(_graph(folder, port="cam.image"))  # in a graph: an error at the params' line, before anything runs
    odd = tmp_path / "frames.mcap"  # a folder that looks like a recording
    shutil.copytree(folder, odd)
    with pytest.raises(ModelFileError, match=r"port 'cam.image' applies only.*frames.mcap is a folder"):
        with Harness(Replay, {"path": str(odd), "port": "cam.image"}):
            pass


def test_replay_folder_without_one_readable_frame_fails_at_configure(tmp_path):
    for name in ("0000.png", "0001.png"):
        (tmp_path / name).write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(ModelFileError, match=rf"no readable image in {tmp_path}: 2 files could not be read"):
        with Harness(Replay, {"path": str(tmp_path)}):
            pass


def test_replay_unreadable_or_truncated_recording(tmp_path):
    from fakes.mcap_files import record_in_two_flushes

    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match=r"empty.mcap is empty \(0 bytes\), not an MCAP recording$") as info:
        with Harness(Replay, {"path": str(empty)}):
            pass
    assert str(info.value).count(str(empty)) == 1  # named once
    text = tmp_path / "text.mcap"
    text.write_text("hello")
    with pytest.raises(RecordingError, match="text.mcap is not an MCAP file"):
        with Harness(Replay, {"path": str(text)}):
            pass

    # a run that crashed: the frames flushed before the crash replay, with a warning
    frames = [np.full((24, 32, 3), 20 * k, np.uint8) for k in range(6)]
    path = tmp_path / "run.mcap"

    # the first three are flushed before the "crash"
    chunks, first_go = record_in_two_flushes(path, [("cam", k * 0.1, {"image": Sample(f, k * 0.1)})
                                                    for k, f in enumerate(frames)], first=3, messages_first=3)
    later = [c for c in chunks if c >= first_go]  # the chunks written after the first three frames
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(path.read_bytes()[:later[0] + 30])
    logs = []
    h = Harness(Replay, {"path": str(cut)})
    h.ctx._log = logs.append
    with h:
        got = [h.step(k / 30).get("image") for k in range(20)]
    assert [int(f[0, 0, 0]) for f in got if f is not None] == [0, 20, 40]
    assert h.stopped and "3 frames" in h.stopped
    assert len(logs) == 1 and logs[0].startswith(f"replay: warning: {cut}: the recording is truncated at byte")
    assert "3 messages read before it" in logs[0]
    # cut before its first frame (inside the first chunk): an error that says why there are no images
    cut.write_bytes(path.read_bytes()[:chunks[0] + 30])
    with pytest.raises(RecordingError, match=r"crashed.mcap: the recording has no images; the recording is "
                                            r"truncated at byte \d+ .*; 0 messages read before it"):
        with Harness(Replay, {"path": str(cut)}):
            pass


# ------------------------------------------------------------------------------------------------ audit: faults
def _in_thread(fn, limit=10.0):
    """Run ``fn`` in a daemon thread: (finished, {"value" or "error"}). A replay that hangs must not hang the suite."""
    box = {}

    def go():
        try:
            box["value"] = fn()
        except BaseException as e:  # handed to the test
            box["error"] = e

    th = threading.Thread(target=go, daemon=True)
    th.start()
    th.join(limit)
    return not th.is_alive(), box


@pytest.mark.parametrize("stamps", [[0.1], [0.2, 0.2, 0.2], [0.3, 0.2, 0.1]], ids=["one-frame", "same", "backwards"])
def test_replay_loop_of_a_recording_whose_stamps_do_not_advance(tmp_path, stamps):
    """Looping a recording of one frame (or whose stamps never advance) made every pass due at the same time: the
    step looped over the recording forever and the graph hung. Each pass now comes at least one node period after
    the last, and a stamp that goes backwards is taken as the previous one: stamps never go backwards."""
    from teletouch.recording import Recorder

    path = tmp_path / "still.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        for k, s in enumerate(stamps):
            rec.tap("digit", 0.1 * k, {"image": Sample(np.full((24, 32, 3), 40 * k, np.uint8), s)})
    done, box = _in_thread(lambda: _run(_graph(path, node_rate=30, loop=True), duration=0.5))
    assert done, "replay hung in step()"
    assert "error" not in box, box.get("error")
    result, rt, got = box["value"]
    assert result.status == "ok" and len(got) >= 10
    out = [s.stamp for _, s in got]
    assert out[0] == 0.0 and all(b > a for a, b in zip(out, out[1:])), out
    assert int(got[-1][1].value[0, 0, 0]) == 40 * (len(stamps) - 1)   # the newest of each pass


def test_replay_empty_path_is_refused_naming_the_field():
    """path: '' is Path('.'): it replayed whatever images the working directory held."""
    with pytest.raises(ValueError, match=r"path: empty; expected a folder of images, a video file or a \.mcap"):
        Replay.Params(path="")
    with pytest.raises(GraphValidationError, match=r"node 'cam': param 'path' = '': empty; expected a folder"):
        _run(_graph(""))


def test_replay_frame_removed_during_the_run_is_reported_as_missing(shared_data, tmp_path):
    src = shared_data / "digit-presses-qvga"
    for k in range(3):
        shutil.copy(src / f"{k:04d}.png", tmp_path / f"{k:04d}.png")
    with Harness(Replay, {"path": str(tmp_path)}) as h:
        (tmp_path / "0001.png").unlink()   # e.g. a sync tool cleaning the folder while the replay runs
        frames = [h.step(k / 30).get("image") for k in range(4)]
    assert sum(f is not None for f in frames) == 2
    assert len(h.comp.corrupt) == 1 and "0001.png" in h.comp.corrupt[0], h.comp.corrupt
    assert "no longer exists" in h.comp.corrupt[0], h.comp.corrupt


def test_replay_folder_of_mixed_sizes_names_the_odd_frame(shared_data, tmp_path):
    """A VGA frame in a QVGA folder is reported with its name and both sizes; a landscape copy of a QVGA frame is
    turned portrait and fits."""
    import cv2

    qvga, vga = shared_data / "digit-presses-qvga", shared_data / "digit-presses-vga"
    shutil.copy(qvga / "0000.png", tmp_path / "0000.png")
    shutil.copy(sorted(vga.glob("*.jpg"))[0], tmp_path / "0001.jpg")
    shutil.copy(qvga / "0002.png", tmp_path / "0002.png")
    cv2.imwrite(str(tmp_path / "0003.png"), cv2.rotate(cv2.imread(str(qvga / "0003.png")), cv2.ROTATE_90_CLOCKWISE))
    with Harness(Replay, {"path": str(tmp_path)}) as h:
        frames = [h.step(k / 30).get("image") for k in range(5)]
    good = [f for f in frames if f is not None]
    assert len(good) == 3 and all(f.shape == (320, 240, 3) for f in good)
    assert np.array_equal(good[2], cv2.imread(str(qvga / "0003.png")))
    assert len(h.comp.corrupt) == 1
    assert "0001.jpg" in h.comp.corrupt[0] and "640x480 differs from the first frame's 320x240" in h.comp.corrupt[0]
    with Harness(Replay, {"path": str(tmp_path), "on_corrupt": "fault"}) as h:
        h.step(0.0)
        with pytest.raises(ComponentFault, match=r"0001.jpg: size 640x480 differs"):
            h.step(1 / 30)


def test_replay_video_without_a_frame_fails_at_configure(tmp_path):
    """A video that opens but holds no frame (a recorder stopped before its first frame) replayed nothing and ended
    the run as a normal stop ("finished: 0 frames"); an empty folder or recording is an error naming it."""
    import cv2

    path = tmp_path / "empty.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (320, 240))
    vw.release()
    assert path.stat().st_size > 0
    with pytest.raises(ModelFileError, match=rf"{path}: no frame can be decoded"):
        with Harness(Replay, {"path": str(path)}):
            pass


def test_a_folder_of_frames_named_by_their_time_plays_in_time_order(tmp_path, shared_data):
    # ROS tools export frames as <seconds>.<fraction>.png: natural order put 1700000000.5 before 1700000000.123
    src = list_images(shared_data / "digit-presses-qvga")[:3]
    names = ["1700000000.123.png", "1700000000.5.png", "1700000001.png"]
    for f, name in zip(src, names):
        shutil.copy(f, tmp_path / name)
    assert [f.name for f in list_images(tmp_path)] == names
    (tmp_path / "frame_a.png").write_bytes((tmp_path / names[0]).read_bytes())   # one name that is no time
    assert [f.name for f in list_images(tmp_path)] == ["1700000000.5.png", "1700000000.123.png", "1700000001.png",
                                                        "frame_a.png"]   # natural order, as before


def test_a_recording_without_the_mcap_suffix_is_replayed_not_opened_as_a_video(tmp_path, shared_data):
    import cv2

    from teletouch.recording import Recorder

    frames = [cv2.imread(str(f)) for f in list_images(shared_data / "digit-presses-qvga")[:3]]
    path = tmp_path / "run.mcap"
    with Recorder(path, None, log=lambda m: None) as rec:
        for k, f in enumerate(frames):
            rec.tap("digit", 0.1 + k * 0.05, {"image": Sample(f, 0.09 + k * 0.05)})
    renamed = path.rename(tmp_path / "run.bag")
    result, rt, got = _run(_graph(renamed, node_rate=100), duration=1.0)
    assert "finished: 3 frames" in result.ending, result.ending   # before: "cannot open the video"
    assert len(got) == 3 and all(np.array_equal(s.value, f) for (_, s), f in zip(got, frames))


def test_wall_clock_frames_go_out_on_their_step_after_a_late_first_step(shared_data):
    """Frame k is due k / rate after the first step: under the wall clock that first step ran a little late (3 ms),
    and every later step that ran less late missed its frame by the difference, publishing it a period after its
    stamp (58 of 60 frames at 30 Hz), or skipping one."""
    h = Harness(Replay, {"path": str(shared_data / "digit-presses-qvga"), "rate": 30, "loop": True}, rate=30)
    h.ctx.clock_kind = "wall"
    with h:
        out = h.step(0.0031)
        assert h.samples["image"].stamp == 0.0
        for k in range(1, 30):
            t = k / 30 + 0.0005   # each later step 0.5 ms late
            out = h.step(t)
            assert out and h.samples["image"].stamp == pytest.approx(k / 30), k   # before: nothing, then late
        assert h.comp.status()["skipped"] == 0
