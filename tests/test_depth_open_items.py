"""Depth estimator open items: non-finite values on the batched paths, a light touch at the contact threshold, the
background check under pixel noise, reproducible model files."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from teletouch.plugins.estimators import poisson
from teletouch.plugins.estimators.depth_pipeline import DepthPipeline
from teletouch.plugins.estimators.normal_model import load_model
from teletouch.plugins.sensors.sim_digit import DigitSimulator

from helpers_depth import model_fixture, presses_fixture, sim_fixture


model = model_fixture()
sim = sim_fixture()


# --- 1. non-finite gradients and frames on the batched paths -------------------------------------------------------

def _gradients(b: int = 3, n: int = 40, m: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(0)
    g = rng.normal(0.0, 0.1, (2, b, n, m)).astype(np.float32)
    return torch.from_numpy(g[0]), torch.from_numpy(g[1])


@pytest.mark.parametrize("bad", ["nan", "inf", "overflow"])
def test_integrate_torch_gives_a_bad_frame_nan_everywhere_and_leaves_the_others(bad):
    """Unchecked, a single gradient of 1e38 left one row of finite, meaningless depth among NaN (integrate()
    refuses it as an overflow); now a frame with a non-finite gradient or depth is NaN everywhere."""
    gx, gy = _gradients()
    clean = poisson.integrate_torch(gx, gy)
    gx[1, 20, 15] = {"nan": math.nan, "inf": math.inf, "overflow": 1e38}[bad]
    if bad == "overflow":   # the CPU solver refuses the same gradients
        with pytest.raises(ValueError, match="too large to integrate"):
            poisson.integrate(gx[1].numpy(), gy[1].numpy())
    z = poisson.integrate_torch(gx, gy)
    assert torch.isnan(z[1]).all()
    assert torch.equal(z[0], clean[0]) and torch.equal(z[2], clean[2])
    assert torch.isfinite(z[0]).all() and torch.isfinite(z[2]).all()


class _NanForFrame(torch.nn.Module):
    """The model's network, with non-finite normals on a few cells of one frame of the batch (a corrupt model in
    memory would give them on every frame; one frame shows that the others are not touched)."""

    def __init__(self, net, frame: int, value: float):
        super().__init__()
        self.net, self.frame, self.value = net, frame, value

    def forward(self, f):
        out = self.net(f).clone()
        out[self.frame, 10:12, 20:22, 0] = self.value
        return out


@pytest.mark.parametrize("baseline", ["none", "plane"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_batch_depth_gives_nan_for_the_frame_with_bad_normals_alone(model, sim, baseline, value):
    a = sim.render(0.8e-3, (0.0, 0.0), 0.0)[0]
    b = sim.render(0.5e-3, (1e-3, -2e-3), 0.0)[0]
    pipe = DepthPipeline(model, mode="dense", baseline=baseline)
    frames = np.stack([a, b, a])
    clean = pipe.batch_depth(frames)
    net = pipe.net
    pipe.net = _NanForFrame(net, 1, value)
    z = pipe.batch_depth(frames)
    assert torch.isnan(z[1]).all()
    assert torch.equal(z[0], clean[0]) and torch.equal(z[2], clean[2])
    assert float(z[0].max()) > 0.3e-3
    # the single-frame path refuses the same normals with its error (the node faults on it)
    pipe.net = _NanForFrame(net, 0, value)
    with pytest.raises(ValueError, match="not finite|NaN or inf"):
        pipe(b)


def test_batch_depth_refuses_frames_of_another_dtype_or_shape(model, sim):
    """One frame of another dtype or shape is refused (check_frame); a batch was read without complaint: a float
    batch with a NaN pixel gave a NaN depth map, levels beyond 255 a confident depth."""
    pipe = DepthPipeline(model, mode="dense")
    img = sim.render(0.5e-3, (0.0, 0.0), 0.0)[0]
    good = np.stack([img, img])
    assert pipe.batch_depth(good).shape == (2, 320, 240)
    assert pipe.batch_depth(torch.from_numpy(good)).shape == (2, 320, 240)
    bad = [good.astype(np.float32), torch.from_numpy(good).float(), img, good[:, :, :200], good[..., :1], [img]]
    for frames in bad:
        with pytest.raises(ValueError, match=r"batch_depth: expected uint8 BGR frames of B x 320 x 240 x 3 .* got"):
            pipe.batch_depth(frames)


# --- 2. a light touch at the contact threshold ---------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["sparse", "dense"])
def test_max_depth_above_contact_depth_always_comes_with_a_contact(model, sim, mode):
    """max_depth is the work grid's largest cell; the contact mask was taken on the upsampled map, whose peak is
    lower (bilinear). With contact_depth between the two: max_depth said contact, the mask was empty, the centroid
    NaN. Now the contact is taken on the grid then."""
    pos = (1e-3, -1e-3)
    img = sim.render(0.1e-3, pos, 0.0)[0]
    ref = DepthPipeline(model, mode=mode)(img)
    top, up = ref.max_depth, float(ref.depth.max())
    assert 0 < up < top
    cd = 0.5 * (top + up)
    res = DepthPipeline(model, mode=mode, contact_depth=cd)(img)
    assert res.max_depth == top > cd
    assert res.contact_mask.any() and res.contact_area == pytest.approx(
        np.count_nonzero(res.contact_mask) / model.px_per_m ** 2)
    assert np.isfinite(res.centroid).all()
    assert np.allclose(res.centroid, pos, atol=0.3e-3)
    # the deepest pixel lies in the contact
    assert res.contact_mask.reshape(-1)[np.argmax(res.depth)]
    # no contact: max depth below contact_depth is reported as it is
    res = DepthPipeline(model, mode=mode, contact_depth=top * 1.01)(img)
    assert res.max_depth == top and not res.contact_mask.any() and res.contact_area == 0.0
    assert np.isnan(res.centroid).all()


def test_a_frame_with_a_contact_on_the_full_size_map_reads_as_before(model, sim):
    """The grid contact is taken only when the full-size map has none: a normal press keeps its outputs."""
    img = sim.render(0.6e-3, (0.0, 1e-3), 0.0)[0]
    pipe = DepthPipeline(model)
    res = pipe(img)
    from teletouch.plugins.estimators.depth_pipeline import contact_summary

    mask, area, centroid = contact_summary(res.depth, 1.0 / model.px_per_m, pipe.contact_depth, pipe.contact_fraction)
    assert np.array_equal(mask, res.contact_mask) and area == res.contact_area
    assert np.allclose(centroid, res.centroid, rtol=0, atol=1e-12)


# --- 3. the background check under pixel noise ---------------------------------------------------------------------

def _max_sim_noise() -> float:
    from teletouch.plugins.sensors.sim_digit import SimDigit

    return float(next(m.le for m in SimDigit.Params.model_fields["noise"].metadata if getattr(m, "le", None)))


def test_a_noisy_simulated_sensor_passes_the_background_check_another_unit_does_not(model, shared_data):
    """The check read the median of per-pixel differences: zero-mean noise of std s added ~0.8 s, so sim-digit with
    the right background read 6.3 levels at noise 8 and 24 at its maximum 32, like another DIGIT unit (9-20), and
    the node faulted. Block means average the noise out; another unit's colour pattern stays."""
    from teletouch import Sample
    from teletouch.plugins.estimators.depth import DepthEstimator, background_mismatch
    from teletouch.testing import Harness

    noise = _max_sim_noise()
    assert noise == 32
    s = DigitSimulator("qvga", noise=noise, seed=7, drift=4.0)
    frames = [s.render(d, (1e-3, -2e-3), 0.0, t=k / 7)[0]
              for k, d in enumerate([0, 0, 0.5e-3, 1e-3, 1.5e-3, 0, 0, 0, 0, 0, 0, 0])]
    levels = [background_mismatch(f, model.background) for f in frames]
    assert max(levels) < 5.0
    with Harness(DepthEstimator, {}) as h:
        for k, f in enumerate(frames):
            h.step(k / 60, image=Sample(f, k / 60))
        assert h.comp.status()["background_mismatch"] < 5.0 < h.comp.params.max_background_mismatch
    import cv2

    others = []
    for path in sorted((shared_data / "digit-backgrounds").iterdir()):   # 8 other units
        img = cv2.imread(str(path))
        if img.shape[:2] != (320, 240):
            img = cv2.resize(np.ascontiguousarray(np.rot90(img)), (240, 320))
        others.append(background_mismatch(img, model.background))
    assert len(others) == 8 and min(others) > 8.0


# --- 4. reproducible model files ------------------------------------------------------------------------------------

presses = presses_fixture(4, seed=5)


def _calibrate(folder, out) -> int:
    from teletouch.cli import main

    return main(["calibrate", "depth", "--images", str(folder), "--ball-diameter", "6mm", "--px-per-mm", "17.15",
                 "--background", str(folder / "background.png"), "--labels", str(folder / "labels.csv"),
                 "--epochs", "1", "--holdout", "1", "--hidden", "8", "--seed", "3", "--quiet", "-o", str(out)])


def test_source_date_epoch_makes_calibrations_byte_identical(presses, tmp_path, monkeypatch, capsys):
    """Two runs with the same seed gave the same weights but other bytes: the creation time and the durations.
    With SOURCE_DATE_EPOCH the file is the same byte for byte."""
    import zipfile

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    a, b = tmp_path / "a.model", tmp_path / "b.model"
    assert _calibrate(presses, a) == 0
    assert _calibrate(presses, b) == 0
    assert a.read_bytes() == b.read_bytes()
    with zipfile.ZipFile(a) as zf:   # numpy's fixed stamp: no clock in the zip either
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    m = load_model(a)
    assert m.training["created"] == "2023-11-14T22:13:20Z"
    assert "seconds" not in m.training and "total_seconds" not in m.training
    with np.load(a, allow_pickle=False) as z:   # still a plain .npz
        assert z["background"].dtype == np.uint8 and z["background"].shape == (320, 240, 3)
    # without it: the clock's time and the durations, as before
    monkeypatch.delenv("SOURCE_DATE_EPOCH")
    c = tmp_path / "c.model"
    assert _calibrate(presses, c) == 0
    m = load_model(c)
    assert m.training["created"] != "2023-11-14T22:13:20Z" and m.training["total_seconds"] > 0
    capsys.readouterr()


@pytest.mark.parametrize("value", ["yesterday", "-5", "1.5e9"])
def test_a_malformed_source_date_epoch_is_refused_before_the_work(presses, tmp_path, monkeypatch, capsys, value):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", value)
    out = tmp_path / "x.model"
    assert _calibrate(presses, out) == 2
    err = capsys.readouterr().err
    assert f"SOURCE_DATE_EPOCH {value!r}: expected a whole number of seconds since 1970-01-01 UTC" in err
    assert not out.exists()
