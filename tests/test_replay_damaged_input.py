"""replay items left open: a recording with drops is warned about, a damaged image message in a recording is
skipped (its slot kept) instead of ending the replay, a video without a frame count plays past a corrupt frame,
and the frames a rate skips are not decoded."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teletouch import ComponentFault
from teletouch.plugins.sensors.replay import Replay, list_images
from teletouch.recording import Recorder, _Compressed
from teletouch.testing import Harness

from fakes.mcap_files import damage_png, hold_writer, write_image_recording

pytestmark = pytest.mark.timeout(120)

GUARD = 10.0


def _play(params: dict, steps: int, rate: float = 100.0) -> tuple[Harness, list, list[str]]:
    """Step the replay ``steps`` times at ``rate``: (harness, [(stamp, image)], log lines)."""
    logs: list[str] = []
    got = []
    h = Harness(Replay, params, rate=rate)
    h.ctx._log = logs.append
    with h:
        for k in range(steps):
            h.step(k / rate)
            if "image" in h.samples:
                s = h.samples["image"]
                got.append((s.stamp, s.value))
            if h.stopped:
                break
    return h, got, logs


# ------------------------------------------------------------------------------------ a recording with drops
def test_replay_of_a_recording_with_drops_warns_when_it_starts(tmp_path):
    path = tmp_path / "drops.mcap"
    rec = Recorder(path, None, max_queue=2, log=lambda m: None)
    stuck = hold_writer(rec, GUARD)
    try:
        for k in range(5):   # two wait for the writer, the 3 others are dropped (max_queue 2)
            rec.tap("cam", 0.1 * k, {"image": np.full((8, 6, 3), 10 * k, np.uint8)})
    finally:
        stuck.release.set()
        rec.close()
    h, got, logs = _play({"path": str(path)}, 20)
    assert len(got) == 2
    assert logs == [f"replay: warning: {path}: 3 samples were dropped while recording (cam 3; the writer fell "
                    f"behind: 3 at max_queue 2 items): the recording is incomplete"], logs


# ------------------------------------------------------------------------- a damaged image message in a recording
def _recording_with_a_damaged_image(path: Path, bad: int, n: int = 5) -> list[np.ndarray]:
    """A teletouch-style recording of ``n`` images at 0.1 s whose image ``bad`` has damaged PNG bytes (the MCAP
    record itself intact); returns the images."""
    imgs = [np.full((8, 6, 3), 20 * k, np.uint8) for k in range(n)]
    messages = []
    for k, img in enumerate(imgs):
        t = (k + 1) * 10**8
        data = _Compressed().encode(img, t, "cam")
        messages.append((t, damage_png(data) if k == bad else data))
    write_image_recording(path, messages)
    return imgs


def test_a_damaged_image_in_a_recording_is_reported_once_and_skipped_keeping_its_slot(tmp_path):
    """A damaged image message ended an mcap replay ("finished: 2 frames, 1 corrupt"): the images after it, intact,
    were never played. It is now reported once (file, channel, time), skipped, and its slot stays empty."""
    path = tmp_path / "run.mcap"
    imgs = _recording_with_a_damaged_image(path, bad=2)
    h, got, logs = _play({"path": str(path)}, 100)
    kept = [0, 1, 3, 4]
    assert [int(img[0, 0, 0]) for _, img in got] == [20 * k for k in kept]
    assert [s for s, _ in got] == pytest.approx([0.1 * k for k in kept], abs=1e-9)   # the recorded stamps
    assert all(np.array_equal(img, imgs[k]) for (_, img), k in zip(got, kept))
    assert len(h.comp.corrupt) == 1 and len(logs) == 1, logs
    assert logs[0].startswith(f"replay: skipped corrupt frame {path}: channel /cam/image: message 3 (at 0.300 s) "
                              f"cannot be decoded"), logs
    assert h.stopped and "finished: 4 frames, 1 corrupt" in h.stopped

    # looped: reported once however often the loop meets it, every pass keeps the slot (0.5 s per pass)
    h, got, logs = _play({"path": str(path), "loop": True}, 150)
    assert len(logs) == 1 and len(h.comp.corrupt) == 1, logs
    firsts = [s for s, img in got if int(img[0, 0, 0]) == 0]
    assert firsts[:3] == pytest.approx([0.0, 0.5, 1.0], abs=1e-9)
    assert not any(int(img[0, 0, 0]) == 40 for _, img in got)

    with Harness(Replay, {"path": str(path), "on_corrupt": "fault"}, rate=100) as h:
        with pytest.raises(ComponentFault, match=r"run.mcap: channel /cam/image: message 3 \(at 0.300 s\)"):
            for k in range(100):
                h.step(k / 100)
        assert k == 20   # when the damaged image is due (0.2 s after the first), not before


# --------------------------------------------------------------------------------- a video without a frame count
def _presses(shared_data: Path) -> list[np.ndarray]:
    import cv2

    return [cv2.imread(str(f)) for f in list_images(shared_data / "digit-presses-qvga")]


def _raw_mjpeg(path: Path, frames: list[np.ndarray], bad: int | None = None) -> None:
    """A raw MJPEG stream (JPEGs one after the other, landscape): FFmpeg reports no frame count for it (a negative
    one) and 25 fps. Frame ``bad`` is a JPEG without image data."""
    import cv2

    jpegs = [cv2.imencode(".jpg", cv2.rotate(f, cv2.ROTATE_90_CLOCKWISE))[1].tobytes() for f in frames]
    if bad is not None:
        jpegs[bad] = b"\xff\xd8\xff\xe0" + bytes(200) + b"\xff\xd9"
    path.write_bytes(b"".join(jpegs))


def test_a_video_without_a_frame_count_plays_past_a_corrupt_frame(shared_data, tmp_path):
    """Without a frame count (raw streams, some containers: 0 or negative) the first frame that failed to decode
    ended the video: the intact frames after it were never played, and the corrupt one was not reported."""
    import cv2

    frames = _presses(shared_data)
    path = tmp_path / "presses.mjpeg"
    _raw_mjpeg(path, frames, bad=4)
    assert cv2.VideoCapture(str(path)).get(cv2.CAP_PROP_FRAME_COUNT) <= 0   # what the test is about
    h, got, logs = _play({"path": str(path)}, 200)
    kept = [k for k in range(10) if k != 4]
    assert [s for s, _ in got] == pytest.approx([k / 25 for k in kept], abs=1e-9)
    for (_, img), k in zip(got, kept):
        assert np.abs(img.astype(int) - frames[k].astype(int)).mean() < 6
    assert h.comp.corrupt == [f"{path}#frame4: cannot decode frame 4 (a corrupt frame)"], h.comp.corrupt
    assert h.stopped and "finished: 9 frames, 1 corrupt" in h.stopped
    # intact, it ends at its last frame without a report
    _raw_mjpeg(path, frames)
    h, got, logs = _play({"path": str(path)}, 200)
    assert len(got) == 10 and not h.comp.corrupt and not logs


# ------------------------------------------------------------------------ the frames a rate skips are not decoded
def _counting_capture(monkeypatch) -> dict[str, int]:
    """cv2.VideoCapture counting the frames decoded into images (read, retrieve) and the ones only grabbed."""
    import cv2

    calls = {"read": 0, "retrieve": 0, "grab": 0}
    base = cv2.VideoCapture

    class Counting:   # a wrapper, not a subclass (a Python subclass of cv2's type can crash the collector)
        def __init__(self, *a):
            self._cap = base(*a)

        def __getattr__(self, name):
            return getattr(self._cap, name)

        def read(self, *a):
            calls["read"] += 1
            return self._cap.read(*a)

        def retrieve(self, *a):
            calls["retrieve"] += 1
            return self._cap.retrieve(*a)

        def grab(self):
            calls["grab"] += 1
            return self._cap.grab()

    monkeypatch.setattr(cv2, "VideoCapture", Counting)
    return calls


def _avi(path: Path, frames: list[np.ndarray], fps: float = 20.0) -> None:
    """A camera-style (landscape) MJPEG AVI of ``frames``: its container counts the frames."""
    import cv2

    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (320, 240))
    for f in frames:
        vw.write(cv2.rotate(f, cv2.ROTATE_90_CLOCKWISE))
    vw.release()


def test_the_frames_a_rate_skips_are_grabbed_not_retrieved(shared_data, tmp_path, monkeypatch):
    """Every frame of a video was decoded into an image (cap.read) also when the replay's rate skipped it: played
    at 20 fps by a 10 Hz node, every other frame was converted to BGR for nothing."""
    frames = _presses(shared_data)
    path = tmp_path / "presses.avi"
    _avi(path, frames)
    got = []
    with Harness(Replay, {"path": str(path)}, rate=10) as h:
        calls = _counting_capture(monkeypatch)   # after configure (it reads one frame)
        for k in range(20):
            h.step(k / 10)
            if "image" in h.samples:
                got.append(h.samples["image"])
            if h.stopped:
                break
    # at 0.1, 0.2, 0.3, 0.4 s the frames 1, 3, 5, 7 (0.05 s, ...) are due with a newer one: skipped; frame 9 is
    # due at 0.45 s, published at 0.5 s
    assert [round(s.stamp * 20) for s in got] == [0, 2, 4, 6, 8, 9]
    for s in got:
        assert np.abs(s.value.astype(int) - frames[round(s.stamp * 20)].astype(int)).mean() < 6
    assert h.comp.skipped == 4
    assert calls["read"] + calls["retrieve"] == len(got), calls
    assert h.stopped and "finished: 6 frames" in h.stopped


def test_a_recording_whose_first_image_is_damaged_plays_the_rest_and_one_with_none_intact_fails_at_configure(
        tmp_path):
    """configure() reads up to the first image to refuse a recording without one: a damaged first image failed the
    whole replay there, though the images after it are intact."""
    path = tmp_path / "first.mcap"
    _recording_with_a_damaged_image(path, bad=0, n=3)
    h, got, logs = _play({"path": str(path)}, 100)
    assert [int(img[0, 0, 0]) for _, img in got] == [20, 40]
    assert [s for s, _ in got] == pytest.approx([0.1, 0.2], abs=1e-9)   # frame 0's slot (0.0 s) kept, empty
    assert len(logs) == 1 and "channel /cam/image: message 1 (at 0.100 s) cannot be decoded" in logs[0], logs

    path = tmp_path / "none.mcap"
    _recording_with_a_damaged_image(path, bad=0, n=1)
    from teletouch.recording import RecordingError

    with pytest.raises(RecordingError, match=r"none.mcap: not one image can be decoded \(1 damaged, e\.g\. channel "
                                             r"/cam/image: message 1 \(at 0\.100 s\) cannot be decoded"):
        with Harness(Replay, {"path": str(path)}):
            pass
