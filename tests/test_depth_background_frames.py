"""A background from several no-contact frames (`--background` of `calibrate depth` and `estimate`).

A single recorded frame carries its own noise into every difference, so the calibrated change threshold came out
higher (VGA: 40 levels with frame_49 against 27-31 with the presses' median) and light touches needed more colour
change. `--background` now takes several frames (repeated, several paths, a folder): their per-pixel median. These
tests check the median itself (exact), the loader's errors (each names its file), the CLI and the model file's
record of the background; tests/test_depth_background_threshold.py checks that the median lowers the threshold."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from teletouch.cli import main
from teletouch.plugins.estimators import depth_calibration as C

from helpers_depth import render_presses


def _frames(n: int, shape=(6, 5, 3), seed=0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(n)]


def _write(folder: Path, frames, prefix="bg_") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, f in enumerate(frames):
        p = folder / f"{prefix}{i}.png"
        assert cv2.imwrite(str(p), f)
        paths.append(p)
    return paths


# --- the median ------------------------------------------------------------------------------------------------

def test_median_of_several_frames_is_the_exact_per_pixel_median():
    fr = _frames(5)
    got = C.median_frames(fr)
    assert got.dtype == np.uint8 and got.shape == fr[0].shape
    assert np.array_equal(got, np.median(np.stack(fr), axis=0).astype(np.uint8))   # odd count: a member, exact
    a = np.array([[[10, 20, 30]]], np.uint8)
    b = np.array([[[200, 20, 31]]], np.uint8)
    c = np.array([[[11, 255, 0]]], np.uint8)
    assert C.median_frames([a, b, c]).tolist() == [[[11, 20, 30]]]   # per pixel and channel, not per frame


def test_two_frames_give_their_mean_rounded_half_to_even_and_one_frame_itself():
    a = np.array([[[1, 2, 100]]], np.uint8)
    b = np.array([[[2, 3, 104]]], np.uint8)
    assert C.median_frames([a, b]).tolist() == [[[2, 2, 102]]]       # 1.5 -> 2, 2.5 -> 2, 102
    hi = [np.full((1, 1, 3), v, np.uint8) for v in (250, 254)]
    assert C.median_frames(hi).tolist() == [[[252] * 3]]              # no uint8 overflow in the mean
    one = _frames(1)[0]
    got = C.median_frames([one])
    assert np.array_equal(got, one) and got is not one


def test_the_median_in_bands_of_rows_equals_the_median_of_the_whole():
    fr = _frames(60, shape=(200, 120, 3), seed=3)       # 60 frames x 360 values a row: several bands of rows
    assert (1 << 22) // (120 * 3 * 60) < 200
    assert np.array_equal(C.median_frames(fr), np.median(np.stack(fr), axis=0).round().astype(np.uint8))


# --- the loader ------------------------------------------------------------------------------------------------

def test_a_folder_gives_the_median_of_all_its_images_and_says_so(tmp_path):
    fr = _frames(10, seed=1)
    _write(tmp_path / "nocontact", fr)
    (tmp_path / "nocontact" / "notes.txt").write_text("not an image")
    bg = C.load_background([tmp_path / "nocontact"])
    assert np.array_equal(bg.image, C.median_frames(fr))
    assert bg.frames == 10 and [p.name for p in bg.files] == [f"bg_{i}.png" for i in range(10)]   # natural order
    assert bg.describe() == f"per-pixel median of 10 frames from {tmp_path / 'nocontact'}"
    assert bg.meta() == {"from": "no-contact frames", "frames": 10, "statistic": "per-pixel median",
                         "files": [f"bg_{i}.png" for i in range(10)]}


def test_frames_and_folders_mix_and_one_frame_is_used_as_it_is(tmp_path):
    fr = _frames(4, seed=2)
    p = _write(tmp_path / "a", fr[:2]) + _write(tmp_path / "b", fr[2:], prefix="x")
    bg = C.load_background([p[0], tmp_path / "b", p[1]])
    assert bg.frames == 4 and np.array_equal(bg.image, C.median_frames(fr))
    one = C.load_background([p[0]])
    assert np.array_equal(one.image, fr[0]) and one.describe() == f"the frame {p[0]}"
    assert one.meta()["statistic"] == "frame" and one.meta()["frames"] == 1
    assert "per-pixel median (the mean) of 2 frames" in C.load_background(p[:2]).describe()


def test_each_background_error_names_its_file(tmp_path):
    good = _write(tmp_path / "good", _frames(2, seed=4))
    junk = tmp_path / "junk.png"
    junk.write_text("not a PNG")
    with pytest.raises(FileNotFoundError, match=f"{junk}: not a readable image file"):
        C.load_background([good[0], junk])
    with pytest.raises(FileNotFoundError, match="nope.png: not a readable image file .no such file or folder"):
        C.load_background([tmp_path / "nope.png"])
    gray = tmp_path / "gray.png"
    cv2.imwrite(str(gray), np.full((6, 5, 3), 90, np.uint8))
    with pytest.raises(ValueError, match=f"{gray}: a grayscale image"):
        C.load_background([good[0], gray])
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), _frames(1, shape=(8, 5, 3))[0])
    with pytest.raises(ValueError) as e:
        C.load_background([good[0], big])
    assert f"{big} is 8x5, but {good[0]} is 6x5 (rows x cols)" in str(e.value)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match=f"{empty}: no images"):
        C.load_background([empty])
    with pytest.raises(ValueError, match=f"{good[0]}: given twice as a background frame"):
        C.load_background([tmp_path / "good", good[0]])
    copy = tmp_path / "copy.png"
    copy.write_bytes(good[1].read_bytes())
    with pytest.raises(ValueError, match=f"{copy} and {good[1]} are identical pixel for pixel"):
        C.load_background([good[1], copy])
    with pytest.raises(ValueError, match="no frame given"):
        C.load_background([])


def test_too_many_frames_are_refused_naming_the_folder(tmp_path, monkeypatch):
    _write(tmp_path / "long", _frames(4, seed=5))
    monkeypatch.setattr(C, "MAX_BACKGROUND_FRAMES", 3)
    with pytest.raises(ValueError, match=f"{tmp_path / 'long'}: 4 background frames; at most 3"):
        C.load_background([tmp_path / "long"])


def test_the_callers_size_check_comes_first_and_names_the_file(tmp_path):
    p = _write(tmp_path / "f", _frames(2, seed=6))

    def refuse(path, frame):
        raise ValueError(f"{path}: wrong size {frame.shape}")

    with pytest.raises(ValueError, match=f"{p[0]}: wrong size"):
        C.load_background(p, refuse)


# --- the CLI ---------------------------------------------------------------------------------------------------

NOISE = 4.0


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """6 rendered presses (noise 4, their labels) and 10 no-contact frames of the same simulated sensor."""
    from teletouch.plugins.sensors.sim_digit import DigitSimulator

    root = tmp_path_factory.mktemp("s12bg")
    render_presses(root / "presses", 6, seed=11, noise=NOISE)
    (root / "presses" / "background.png").unlink()
    s = DigitSimulator("qvga", noise=NOISE, seed=111)
    frames = [s.render(0.0, t=float(k))[0] for k in range(10)]
    _write(root / "nocontact", frames, prefix="frame_")
    return root, frames


def _cal(root: Path, out: Path, *bg: str, quiet=True):
    return main(["calibrate", "depth", "--images", str(root / "presses"), "--ball-diameter", "6mm",
                 "--px-per-mm", "17.15", "--labels", str(root / "presses" / "labels.csv"), "--epochs", "1",
                 "--holdout", "1", "--hidden", "8", "--seed", "1", *(["--quiet"] if quiet else []), *bg,
                 "-o", str(out)])


def test_calibrate_with_a_folder_of_no_contact_frames_uses_their_median_and_records_it(sim, tmp_path, capsys):
    from teletouch.plugins.estimators.normal_model import load_model

    root, frames = sim
    out = tmp_path / "m.model"
    assert _cal(root, out, "--background", str(root / "nocontact"), quiet=False) == 0
    err = capsys.readouterr().err
    assert f"background: per-pixel median of 10 frames from {root / 'nocontact'}" in err
    m = load_model(out)
    assert np.array_equal(m.background, C.median_frames(frames))
    assert m.training["background"] == {"from": "no-contact frames", "frames": 10, "statistic": "per-pixel median",
                                        "files": [f"frame_{i}.png" for i in range(10)]}


def test_calibrate_takes_several_paths_and_repeated_options(sim, tmp_path):
    from teletouch.plugins.estimators.normal_model import load_model

    root, frames = sim
    f = [str(root / "nocontact" / f"frame_{i}.png") for i in range(3)]
    out = tmp_path / "m.model"
    assert _cal(root, out, "--background", f[0], f[1], "--background", f[2]) == 0
    m = load_model(out)
    assert np.array_equal(m.background, C.median_frames(frames[:3]))
    assert m.training["background"]["frames"] == 3


def test_calibrate_records_one_frame_and_the_presses_median_as_such(sim, tmp_path):
    from teletouch.plugins.estimators.normal_model import load_model

    root, frames = sim
    assert _cal(root, tmp_path / "a.model", "--background", str(root / "nocontact" / "frame_0.png")) == 0
    a = load_model(tmp_path / "a.model")
    assert np.array_equal(a.background, frames[0])
    assert a.training["background"] == {"from": "no-contact frames", "frames": 1, "statistic": "frame",
                                        "files": ["frame_0.png"]}
    assert _cal(root, tmp_path / "b.model") == 0
    assert load_model(tmp_path / "b.model").training["background"] == {
        "from": "images", "frames": 6, "statistic": "per-pixel median", "presses": 6, "no_contact": 0, "unlabelled": 0}


def test_background_frames_in_the_presses_folder_are_left_out_by_file_not_by_name(sim, tmp_path, capsys):
    """Before, a press was dropped when its name matched the background's, whatever the folder."""
    import shutil

    from teletouch.plugins.estimators.normal_model import load_model

    root, frames = sim
    presses = tmp_path / "presses"
    shutil.copytree(root / "presses", presses)
    shutil.copy(root / "nocontact" / "frame_0.png", presses / "frame_0.png")
    shutil.copy(root / "nocontact" / "frame_1.png", presses / "frame_1.png")
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(root / "nocontact" / "frame_2.png", other / "press_00.png")   # a press's name, another folder
    out = tmp_path / "m.model"
    rc = main(["calibrate", "depth", "--images", str(presses), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
               "--labels", str(presses / "labels.csv"), "--epochs", "1", "--holdout", "1", "--hidden", "8",
               "--background", str(presses / "frame_0.png"), str(presses / "frame_1.png"), str(other),
               "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert f"2 background frame(s) in {presses} left out of the presses: frame_0.png, frame_1.png" in err
    m = load_model(out)
    used = set(m.training["presses"]) | {p["image"] for p in m.validation.get("per_press", [])}
    assert "press_00.png" in used and len(used) == 6 and not any(n.startswith("frame_") for n in used)
    assert np.array_equal(m.background, C.median_frames(frames[:3]))


def test_calibrate_background_errors_name_the_file_before_any_work(sim, tmp_path, capsys, monkeypatch):
    from teletouch.plugins.estimators import depth_calibration

    monkeypatch.setattr(depth_calibration, "calibrate", lambda *a, **k: pytest.fail("trained before the check"))
    root, frames = sim
    small = tmp_path / "small"
    _write(small, [frames[0], cv2.resize(frames[1], (120, 160))])
    rc = _cal(root, tmp_path / "m.model", "--background", str(small))
    err = capsys.readouterr().err
    assert rc == 2 and f"{small / 'bg_1.png'}: the background frame is 160x120, the presses in" in err
    gray = tmp_path / "gray.png"
    cv2.imwrite(str(gray), cv2.cvtColor(cv2.cvtColor(frames[2], cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR))
    rc = _cal(root, tmp_path / "m.model", "--background", str(root / "nocontact" / "frame_0.png"), str(gray))
    assert rc == 2 and f"{gray}: a grayscale image" in capsys.readouterr().err
    rc = _cal(root, tmp_path / "m.model", "--background", str(tmp_path / "missing"))
    assert rc == 2 and "missing: not a readable image file (no such file or folder)" in capsys.readouterr().err
    assert not (tmp_path / "m.model").exists()


def _estimate(*args) -> int:
    return main(["estimate", "--model", "sim-digit-qvga", "--json", *args])


def test_estimate_with_a_folder_reads_as_with_the_median_frame(sim, tmp_path, capsys):
    root, frames = sim
    med = tmp_path / "median.png"
    cv2.imwrite(str(med), C.median_frames(frames))
    press = str(root / "presses" / "press_00.png")
    assert _estimate(press, "--background", str(root / "nocontact")) == 0
    cap = capsys.readouterr()
    a = json.loads(cap.out.splitlines()[-1])
    assert f"teletouch estimate: background: per-pixel median of 10 frames from {root / 'nocontact'}" in cap.err
    assert _estimate(press, "--background", str(med)) == 0
    b = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert a["max_depth_m"] > 0 and a["max_depth_m"] == b["max_depth_m"]
    assert a["background_mismatch"] == b["background_mismatch"]
    f0 = str(root / "nocontact" / "frame_0.png")
    assert _estimate(press, "--background", f0) == 0
    c = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert c["background_mismatch"] != a["background_mismatch"]     # one frame is not the median


def test_estimate_takes_repeated_background_options(sim, tmp_path, capsys):
    root, frames = sim
    med = tmp_path / "median3.png"
    cv2.imwrite(str(med), C.median_frames(frames[:3]))
    press = str(root / "presses" / "press_01.png")
    f = [str(root / "nocontact" / f"frame_{i}.png") for i in range(3)]
    assert _estimate("--background", f[0], "--background", f[1], "--background", f[2], press) == 0
    cap = capsys.readouterr()
    assert "per-pixel median of 3 frames" in cap.err
    a = json.loads(cap.out.splitlines()[-1])
    assert _estimate(press, "--background", str(med)) == 0
    b = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert a["image"] == press and a["max_depth_m"] == b["max_depth_m"]
    assert a["background_mismatch"] == b["background_mismatch"]


def test_estimate_background_errors_name_the_file(sim, tmp_path, capsys):
    root, frames = sim
    press = str(root / "presses" / "press_00.png")
    odd = tmp_path / "odd"
    _write(odd, [frames[0], cv2.resize(frames[1], (120, 160))])
    assert _estimate(press, "--background", str(odd)) == 2
    assert f"{odd / 'bg_1.png'}: background frame is 160x120, the model" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _estimate(press, "--background", str(empty)) == 2
    assert f"{empty}: no images" in capsys.readouterr().err


def test_a_background_frame_named_like_a_press_in_another_folder_leaves_the_press_in(sim, tmp_path):
    """Before, `--background other/press_00.png` dropped the press press_00.png of the presses folder (the frames
    were matched by name): a press silently not trained on."""
    import shutil

    from teletouch.plugins.estimators.normal_model import load_model

    root, frames = sim
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(root / "nocontact" / "frame_0.png", other / "press_00.png")
    out = tmp_path / "m.model"
    assert _cal(root, out, "--background", str(other / "press_00.png")) == 0
    m = load_model(out)
    used = set(m.training["presses"]) | {p["image"] for p in m.validation.get("per_press", [])}
    assert used == {f"press_{k:02d}.png" for k in range(6)}
    assert np.array_equal(m.background, frames[0])
