"""The depth node's `background` parameter: one no-contact frame, a folder of them or a list of files and folders
(several: their per-pixel median), checked against the model's image size; errors name the parameter and the file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from teletouch.errors import ModelFileError
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.testing import Harness

from helpers_depth import model_fixture

model = model_fixture()


def _frames(model, tmp_path, n=3, seed=0):
    """n no-contact frames: the model's background with noise of +-6 levels (a different draw each)."""
    rng = np.random.default_rng(seed)
    folder = tmp_path / "nocontact"
    folder.mkdir()
    frames = []
    for i in range(n):
        f = np.clip(model.background.astype(np.int16) + rng.integers(-6, 7, model.background.shape), 0, 255)
        f = f.astype(np.uint8)
        assert cv2.imwrite(str(folder / f"f{i}.png"), f)
        frames.append(f)
    return folder, frames


def _configured(params):
    h = Harness(DepthEstimator, params)
    lines: list[str] = []
    h.ctx._log = lines.append
    return h, lines


def test_a_folder_gives_the_per_pixel_median_of_its_frames(model, tmp_path):
    folder, frames = _frames(model, tmp_path)
    h, lines = _configured({"background": str(folder)})
    with h:
        got = h.comp._ref_bg
        out = h.step(0.0, image=frames[0])
    want = np.median(np.stack(frames), axis=0).round()
    assert np.array_equal(got, want.astype(np.float32))
    assert not np.array_equal(got, model.background.astype(np.float32))     # it did replace the model's
    assert any("per-pixel median of 3 frames" in m for m in lines)
    assert out["max_depth"] < 2e-5                       # a no-contact frame against its own median: no depth


def test_a_list_of_files_and_a_single_file(model, tmp_path):
    folder, frames = _frames(model, tmp_path, n=4, seed=1)
    files = [str(folder / f"f{i}.png") for i in range(4)]
    h, _ = _configured({"background": files[:2] + [files[3]]})
    with h:
        got = h.comp._ref_bg
    assert np.array_equal(got, np.median(np.stack([frames[0], frames[1], frames[3]]), axis=0).round())
    h, lines = _configured({"background": files[2]})
    with h:
        assert np.array_equal(h.comp._ref_bg, frames[2].astype(np.float32))
    assert any("the frame" in m and "f2.png" in m for m in lines)


def test_bad_backgrounds_name_the_parameter_and_the_file(model, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ModelFileError, match=r"background: .*empty: no images"):
        with Harness(DepthEstimator, {"background": str(empty)}):
            pass
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((100, 80, 3), 128, np.uint8))
    with pytest.raises(ModelFileError, match=r"background: .*small\.png: background frame is 100x80, the model "
                                             r".* is for 320x240"):
        with Harness(DepthEstimator, {"background": str(small)}):
            pass
    folder, _ = _frames(model, tmp_path)
    with pytest.raises(ModelFileError, match=r"background: .*f0\.png: given twice"):
        with Harness(DepthEstimator, {"background": [str(folder), str(folder / "f0.png")]}):
            pass
