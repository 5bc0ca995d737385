"""replay, reviewed: a corrupt frame in the middle of a video, unreadable (permission) frames and paths, and a corrupt
frame in a looped replay (reported once, its slot kept). Real DIGIT frames from ../shared/data."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from teletouch import ComponentFault
from teletouch.plugins.sensors.replay import Replay, list_images
from teletouch.testing import Harness

from helpers_permissions import without_dac

FPS = 20.0


def _presses(shared_data: Path) -> list[np.ndarray]:
    import cv2

    return [cv2.imread(str(f)) for f in list_images(shared_data / "digit-presses-qvga")]


def _mjpeg_video(path: Path, frames: list[np.ndarray]) -> list[int]:
    """A camera-style (landscape) MJPEG AVI of ``frames`` at FPS; returns where each frame's JPEG starts (SOI)."""
    import cv2

    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (320, 240))
    for f in frames:
        vw.write(cv2.rotate(f, cv2.ROTATE_90_CLOCKWISE))
    vw.release()
    data = path.read_bytes()
    soi, at = [], data.find(b"\xff\xd8\xff")
    while at >= 0:
        soi.append(at)
        at = data.find(b"\xff\xd8\xff", at + 3)
    assert len(soi) == len(frames)
    return soi


def _play(params: dict, steps: int, rate: float = 100.0) -> tuple[Harness, list, list[str]]:
    """Step the replay ``steps`` times at ``rate``: (harness, [(stamp, image)], log lines)."""
    logs: list[str] = []
    got = []
    with Harness(Replay, params, rate=rate) as h:
        h.comp.ctx._log = logs.append
        for k in range(steps):
            h.step(k / rate)
            if "image" in h.samples:
                s = h.samples["image"]
                got.append((s.stamp, s.value))
            if h.stopped:
                break
    return h, got, logs


# ------------------------------------------------------------------------------------ a corrupt frame in a video
def test_video_with_a_corrupt_frame_in_the_middle_skips_it_and_plays_the_rest(shared_data, tmp_path):
    """One undecodable frame in the middle of a video ended the replay there ("finished: 4 frames, 1 corrupt"): the
    frames after it, intact, were never played. It is now reported with its number and skipped, and the frames
    after it keep their stamps (k / fps)."""
    frames = _presses(shared_data)
    path = tmp_path / "presses.avi"
    soi = _mjpeg_video(path, frames)
    data = bytearray(path.read_bytes())
    data[soi[4]:soi[4] + 300] = bytes(300)   # frame 4: no JPEG header left
    path.write_bytes(bytes(data))

    h, got, logs = _play({"path": str(path)}, 200)
    kept = [k for k in range(10) if k != 4]
    assert len(got) == 9, [round(s, 3) for s, _ in got]
    assert [s for s, _ in got] == pytest.approx([k / FPS for k in kept], abs=1e-9)
    for (_, img), k in zip(got, kept):
        assert img.shape == (320, 240, 3)
        assert np.abs(img.astype(int) - frames[k].astype(int)).mean() < 6   # MJPEG is lossy
    assert h.comp.corrupt == [f"{path}#frame4: cannot decode frame 4 of 10 (a corrupt frame)"]
    assert len(logs) == 1 and f"{path}#frame4" in logs[0]
    assert h.stopped and "finished: 9 frames, 1 corrupt" in h.stopped

    with Harness(Replay, {"path": str(path), "on_corrupt": "fault"}, rate=100) as h:
        with pytest.raises(ComponentFault, match=r"presses.avi#frame4: cannot decode frame 4 of 10"):
            for k in range(30):
                h.step(k / 100)


def test_truncated_video_is_one_report_at_the_cut(shared_data, tmp_path):
    """A video cut short (a recorder killed mid-write) still ends at the cut with one report naming the first frame
    that is missing, not one report per frame the container's header counts."""
    frames = _presses(shared_data)
    path = tmp_path / "cut.avi"
    soi = _mjpeg_video(path, frames)
    path.write_bytes(path.read_bytes()[:soi[6]])   # frames 6..9 are gone

    h, got, logs = _play({"path": str(path)}, 200)
    assert len(got) == 6
    assert [s for s, _ in got] == pytest.approx([k / FPS for k in range(6)], abs=1e-9)
    assert len(h.comp.corrupt) == 1 and len(logs) == 1
    assert h.comp.corrupt[0].startswith(f"{path}#frame6: cannot decode frame 6 of 10")
    assert h.comp.corrupt[0].endswith("truncated or corrupt video")
    assert h.stopped and "finished: 6 frames, 1 corrupt" in h.stopped


# ------------------------------------------------------------------------------------- unreadable (permission)
_PROBE = textwrap.dedent("""
    import json, sys
    from teletouch.plugins.sensors.replay import Replay
    from teletouch.testing import Harness

    out = {}
    for key, path in json.loads(sys.argv[1]).items():
        try:
            with Harness(Replay, {"path": path}) as h:
                for k in range(6):
                    h.step(k / 30)
            out[key] = {"corrupt": h.comp.corrupt, "published": h.comp.published}
        except Exception as e:
            out[key] = {"error": f"{type(e).__name__}: {e}"}
    print("RESULT", json.dumps(out))
""")


def test_unreadable_frames_and_paths_say_permission_denied_not_corrupt(shared_data, tmp_path):
    """A frame this user may not read was reported as "cannot decode the image (corrupt or not an image)", a folder
    of such frames as "(corrupt or not images)", a video as "(corrupt or unsupported codec)", and a folder that
    cannot be listed raised a bare PermissionError: the user looked for damage in files that are fine."""
    src = shared_data / "digit-presses-qvga"
    some = tmp_path / "some"
    some.mkdir()
    for k in range(3):
        shutil.copy(src / f"{k:04d}.png", some / f"{k:04d}.png")
    locked = tmp_path / "locked"
    shutil.copytree(some, locked)
    listless = tmp_path / "listless"
    shutil.copytree(some, listless)
    video = tmp_path / "presses.avi"
    _mjpeg_video(video, _presses(shared_data))
    paths = {"some": some, "locked": locked, "listless": listless, "video": video}
    os.chmod(some / "0001.png", 0)
    for f in locked.iterdir():
        os.chmod(f, 0)
    os.chmod(video, 0)
    os.chmod(listless, 0o300)   # can be entered, not listed
    try:
        r = subprocess.run(without_dac([sys.executable, "-c", _PROBE, json.dumps({k: str(v) for k, v in
                                                                                   paths.items()})]),
                           capture_output=True, text=True, timeout=120)
    finally:
        os.chmod(listless, 0o755)
    assert "RESULT" in r.stdout, r.stdout + r.stderr
    out = json.loads(r.stdout.split("RESULT", 1)[1])

    assert out["some"]["published"] == 2, out
    assert out["some"]["corrupt"] == [f"{some / '0001.png'}: cannot be read (Permission denied)"], out
    err = out["locked"]["error"]
    assert err.startswith(f"ModelFileError: no readable image in {locked}: 3 files could not be read, e.g. "
                          f"0000.png: cannot be read (Permission denied)"), err
    assert "corrupt" not in err, err
    assert out["video"]["error"] == f"ModelFileError: {video}: cannot be read (Permission denied)", out
    assert out["listless"]["error"] == f"ModelFileError: {listless}: cannot list the folder (Permission denied)", out


def test_grey_alpha_and_16_bit_frames_are_read_as_8_bit_bgr(tmp_path):
    """The folder reader turns a grey, a BGRA and a 16-bit PNG into the port's 8-bit BGR, like OpenCV's imread."""
    import cv2

    grey = (np.arange(320 * 240).reshape(320, 240) % 251).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "0000.png"), grey)
    cv2.imwrite(str(tmp_path / "0001.png"), np.dstack([grey, grey, grey, np.full_like(grey, 128)]))
    cv2.imwrite(str(tmp_path / "0002.png"), grey.astype(np.uint16) * 257)
    h, got, logs = _play({"path": str(tmp_path)}, 10)
    assert len(got) == 3 and not h.comp.corrupt and not logs
    for _, img in got:
        assert img.dtype == np.uint8 and img.shape == (320, 240, 3)
        assert np.array_equal(img, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))


# ----------------------------------------------------------------------------------- a corrupt frame in a loop
def _folder_with_a_bad_frame(shared_data: Path, folder: Path, bad: int, n: int = 4) -> None:
    folder.mkdir()
    for k in range(n):
        if k == bad:
            (folder / f"{k:04d}.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        else:
            shutil.copy(shared_data / "digit-presses-qvga" / f"{k:04d}.png", folder / f"{k:04d}.png")


def test_loop_reports_a_corrupt_frame_once_not_every_pass(shared_data, tmp_path):
    """A looped replay logged the same corrupt frame again on every pass, and kept every copy in ``corrupt`` (and its
    count in status()): a long looped run grew its log and its memory without end for one bad file."""
    _folder_with_a_bad_frame(shared_data, tmp_path / "f", bad=1)
    h, got, logs = _play({"path": str(tmp_path / "f"), "loop": True}, 60, rate=30)
    assert h.comp.passes >= 10 and len(got) == 60
    assert len(logs) == 1 and "0001.png" in logs[0], logs
    assert len(h.comp.corrupt) == 1 and h.comp.status()["corrupt"] == 1


@pytest.mark.parametrize("bad", [0, 1, 3], ids=["first", "middle", "last"])
def test_loop_keeps_the_slot_of_a_corrupt_frame_wherever_it_is(shared_data, tmp_path, bad):
    """With ``rate``, frame k of pass p is due (p * n + k) / rate: a corrupt frame leaves its slot empty. A corrupt
    last frame lost its slot instead (the next pass started where it was due), so a folder of four frames at 10
    frames/s looped every 0.3 s or every 0.4 s depending on which frame was damaged."""
    _folder_with_a_bad_frame(shared_data, tmp_path / "f", bad=bad)
    h, got, logs = _play({"path": str(tmp_path / "f"), "loop": True, "rate": 10}, 120, rate=100)
    slots = [p * 4 + k for p in range(3) for k in range(4) if k != bad]   # 3 passes: 0 .. 1.1 s
    stamps = [s for s, _ in got]
    assert stamps == pytest.approx([s / 10 for s in slots], abs=1e-9)


# --------------------------------------------------------------------------- a corrupt frame is met when it is due
def test_a_corrupt_frame_faults_when_it_is_due_not_one_frame_early(shared_data, tmp_path):
    """With ``rate``, the step that published frame k also read frame k + 1 ahead: when that one was corrupt the
    fault (``on_corrupt: fault``) came one frame period early, from the step that should publish frame k, which was
    lost. Frame 1 (due 0.1 s) is now published, and the fault comes at 0.2 s, when the corrupt frame 2 is due; in
    ``report`` mode it is logged then too."""
    _folder_with_a_bad_frame(shared_data, tmp_path / "f", bad=2)
    published, fault_at = [], None
    with Harness(Replay, {"path": str(tmp_path / "f"), "rate": 10, "on_corrupt": "fault"}, rate=100) as h:
        for k in range(40):
            try:
                h.step(k / 100)
            except ComponentFault as e:
                fault_at = k / 100
                assert "0002.png" in str(e)
                break
            if "image" in h.samples:
                published.append(h.samples["image"].stamp)
    assert published == pytest.approx([0.0, 0.1], abs=1e-9)
    assert fault_at == pytest.approx(0.2)

    logs: list[str] = []
    with Harness(Replay, {"path": str(tmp_path / "f"), "rate": 10}, rate=100) as h:
        h.comp.ctx._log = logs.append
        for k in range(20):
            h.step(k / 100)
        assert logs == []   # frame 2 is due at 0.2 s
        h.step(0.2)
        assert len(logs) == 1 and "0002.png" in logs[0]
