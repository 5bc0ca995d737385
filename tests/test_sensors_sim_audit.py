"""sim-digit as an adversary would use it: parameters at and beyond their limits, millimetres in metre fields,
positions off the gel, indentations through it, stale and NaN inputs, odd backgrounds, extreme unit variation."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from teletouch.errors import ModelFileError
from teletouch.plugins.sensors import gel, optics
from teletouch.plugins.sensors.gel import Indenter, gel_force
from teletouch.plugins.sensors.sim_digit import DigitSimulator, SimDigit
from teletouch.testing import Harness, make_registry, run_yaml


# --- parameters: millimetres typed in metre fields, and other out-of-range values ---------------------------------

@pytest.mark.parametrize("field,value", [
    ("indenter_radius", 3), ("tip_radius", 10), ("m_per_px", 0.058), ("indenter_map_m_per_px", 0.04),
    ("smoothing", 0.08), ("gel_thickness", 4.5), ("indentation", 1), ("position", (2, -1)),
])
def test_millimetres_in_metre_fields_are_refused(field, value):
    # smoothing 0.08 (meant: mm) made the renderer try to allocate 14.9 GiB; the others rendered nonsense silently
    with pytest.raises(ValidationError, match=field) as e:
        SimDigit.Params(**{field: value})
    assert "mm" in str(e.value)


def test_lengths_with_units_and_plausible_values_are_accepted():
    p = SimDigit.Params(indenter_radius="3mm", tip_radius="10mm", m_per_px=0.058e-3, smoothing="0.08mm",
                        gel_thickness="4.5mm", indentation="1.5mm", position="2mm, -1mm")
    assert p.indenter_radius == pytest.approx(0.003) and p.smoothing == pytest.approx(0.08e-3)
    assert p.position == pytest.approx((0.002, -0.001))


@pytest.mark.parametrize("field,value,words", [
    ("noise", 1000, "noise"), ("drift", 1e6, "drift"), ("seed", -1, "seed"), ("modulus", 0.41, "MPa"),
    ("modulus", 1e12, "MPa"), ("tilt", 10, "deg"), ("tilt", -1.0, "deg"),
])
def test_out_of_range_params_are_refused(field, value, words):
    # before: drift 1e6 raised an int16 OverflowError mid-run; noise 1000 was clipped to a std of ~130;
    # seed -1 failed inside numpy with "expected non-negative integer"; modulus 0.41 (meant: MPa) gave 1 uN;
    # tilt 10 (meant: degrees) tilted a punch by 573 degrees
    with pytest.raises(ValidationError, match=words):
        SimDigit.Params(**{field: value})


def test_the_largest_drift_renders():
    means = []
    with Harness(SimDigit, {"drift": 255, "drift_period": 1.0, "indentation": 0.001}) as h:
        for t in np.linspace(0, 1, 9):
            img = h.step(float(t))["image"]
            assert img.dtype == np.uint8
            means.append(float(img.mean()))
    # over one period the +-255 offset takes the image to black and to white (clipped, never wrapped around)
    assert min(means) < 20.0 and max(means) > 235.0, means


def test_tilt_input_beyond_45_degrees_is_an_error():
    with Harness(SimDigit, {"indenter": "flat", "indentation": 0.0005}) as h:
        assert h.step(0.0, tilt=math.radians(30))["gt_force"] > 0
        with pytest.raises(ValueError, match="tilt"):
            h.step(0.1, tilt=2.0)


# --- position off the gel ------------------------------------------------------------------------------------------

def test_static_position_off_the_image_is_refused():
    with pytest.raises(ValueError, match="off the gel"):
        with Harness(SimDigit, {"indentation": 0.001, "position": "20mm, 0mm"}):
            pass


def test_position_input_off_the_gel_is_an_error_not_a_force_without_contact():
    # before: gt_force 1.27 N with an empty contact mask, gt_max_depth 0 and an untouched image
    with Harness(SimDigit, {"indentation": 0.001}) as h:
        with pytest.raises(ValueError, match="off the gel"):
            h.step(0.0, position=np.array([0.05, 0.0]))
        # on the edge of the image: half the contact is seen, the force is the gel's
        out = h.step(0.1, position=np.array([0.0069, 0.0]))
        assert out["gt_force"] == pytest.approx(gel_force(0.001, Indenter.sphere(0.003)))
        assert out["gt_contact_mask"].any() and out["gt_max_depth"] > 0.0009
        # no contact: the position does not matter
        out = h.step(0.2, indentation=0.0, position=np.array([0.05, 0.0]))
        assert out["gt_force"] == 0.0


def test_gt_position_is_a_copy_of_the_input():
    with Harness(SimDigit, {}) as h:
        pos = np.array([0.001, -0.002])
        out = h.step(0.0, indentation=0.001, position=pos)
        pos[:] = 0.0  # the producer reuses its buffer
        assert out["gt_position"] == pytest.approx([0.001, -0.002])


# --- indentation through the gel, thin layer --------------------------------------------------------------------

def test_indentation_through_the_gel_is_refused():
    with pytest.raises(ValidationError, match="gel_thickness"):
        SimDigit.Params(gel_thickness="4mm", indentation="5mm")
    with Harness(SimDigit, {"gel_thickness": 0.004}) as h:
        assert h.step(0.0, indentation=0.003)["gt_force"] > 0
        with pytest.raises(ValueError, match="reaches through the gel"):
            h.step(0.1, indentation=0.0045)


def test_thin_layer_correction_is_dimitriadis_bonded_incompressible():
    # Dimitriadis et al. (2002), bonded layer, nu = 0.5: F = F_Hertz (1 + 1.133 x + 1.283 x^2 + 0.769 x^3 + 0.0975 x^4)
    # with x = sqrt(R d) / h; the first two coefficients are -2 a0 / pi and 4 a0^2 / pi^2 with
    # a0 = -(1.2876 - 1.4678 nu + 1.3442 nu^2) / (1 - nu)
    nu = 0.5
    a0 = -(1.2876 - 1.4678 * nu + 1.3442 * nu ** 2) / (1 - nu)
    assert -2 * a0 / math.pi == pytest.approx(1.133, abs=5e-4)
    assert 4 * a0 ** 2 / math.pi ** 2 == pytest.approx(1.283, abs=5e-4)
    ball = Indenter.sphere(0.005)
    for d in (0.0005, 0.001, 0.0015):
        x = math.sqrt(0.005 * d) / 0.004
        poly = 1 + 1.133 * x + 1.283 * x ** 2 + 0.769 * x ** 3 + 0.0975 * x ** 4
        assert gel_force(d, ball, thickness=0.004) == pytest.approx(gel_force(d, ball) * poly, rel=1e-12)


# --- stale and NaN inputs in a running graph ---------------------------------------------------------------------

GRAPH = """
name: sim-digit-source
clock: sim
faults: {startup_grace: 0.1}
nodes:
  - id: press
    plugin: mock-sensor
    rate: 100
    params: {signal: constant, amplitude: 0.001, %s}
  - id: digit
    plugin: sim-digit
    rate: 30
    inputs: {indentation: press.value}
"""


def _run(extra):
    reg = make_registry("teletouch.plugins.sensors.sim_digit")
    frames = []

    def tap(node, t, outputs):
        if node == "digit":
            frames.append(outputs)

    res, _ = run_yaml(GRAPH % extra, reg, duration=1.0, taps=[tap])
    return res, frames


def test_a_source_gone_quiet_faults_sim_digit():
    # before: the last indentation was rendered forever, as if fresh
    res, frames = _run("silent_at: 0.3")
    assert res.status == "fault"
    (f,) = [f for f in res.faults if f.node == "digit"]
    assert f.kind == "stale" and "indentation" in f.message
    assert 0.3 + 0.25 <= f.time < 0.3 + 0.25 + 0.1
    assert len(frames) >= 10


def test_a_nan_indentation_faults_sim_digit_and_publishes_no_frame():
    res, frames = _run("nan_at: 0.5")
    assert res.status == "fault"
    assert any(f.node == "digit" and "indentation must be finite" in f.message for f in res.faults)
    for out in frames:
        vals = {k: (v.value if hasattr(v, "value") else v) for k, v in out.items()}
        assert vals["gt_force"] > 0 and math.isfinite(vals["gt_max_depth"])


# --- backgrounds ----------------------------------------------------------------------------------------------

def test_a_landscape_background_of_another_size_is_turned_portrait(tmp_path):
    # a raw (landscape) VGA frame for a QVGA simulator: left half dark, right half bright; before, it was squashed
    # into portrait without the turn
    raw = np.zeros((480, 640, 3), np.uint8)
    raw[:, 320:] = 200
    f = tmp_path / "raw_vga.png"
    cv2.imwrite(str(f), raw)
    bg = optics.load_background("qvga", f)
    assert bg.shape == (320, 240, 3)
    # turned 90 degrees counter-clockwise as the driver does: the raw right half is the portrait top half
    assert bg[:150].mean() > 190 and bg[170:].mean() < 10
    expected = cv2.resize(np.rot90(raw), (240, 320), interpolation=cv2.INTER_AREA).astype(np.float32)
    assert np.array_equal(bg, expected)


def test_a_background_of_another_aspect_is_refused(tmp_path):
    f = tmp_path / "wide.png"
    cv2.imwrite(str(f), np.full((360, 640, 3), 100, np.uint8))
    with pytest.raises(ModelFileError, match="wide.png"):
        optics.load_background("qvga", f)


def test_an_array_background_must_be_finite_levels():
    bg = np.full((320, 240, 3), 100.0)
    bg[5, 5, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        DigitSimulator(background=bg)
    with pytest.raises(ValueError, match="0..255"):
        DigitSimulator(background=np.full((320, 240, 3), 300.0))


# --- unit variation at its limit ---------------------------------------------------------------------------------

def test_unit_variation_at_its_limit_keeps_every_gain_positive():
    # before: at unit_variation 3, 11 of these 60 seeds inverted a channel's response or made the blur negative
    for seed in range(60):
        u = DigitSimulator(unit_variation=3.0, seed=seed).unit
        assert min(u["response_gain"]) >= 0.1 and u["blur_gain"] >= 0.1, seed


def test_typical_unit_variation_is_unchanged_by_the_floor():
    # the floor only acts beyond unit_variation ~2: the typical spread draws the same sensors as before
    for seed in range(20):
        rng = np.random.default_rng(seed)
        rng.integers(2 ** 63)
        resp = 1.0 + np.clip(rng.normal(0.0, 0.15, 3), -0.4, 0.4)
        u = DigitSimulator(unit_variation=1.0, seed=seed).unit
        assert u["response_gain"] == pytest.approx(resp.tolist(), abs=0)


# --- ground truth and the documented figures -----------------------------------------------------------------------

def test_documented_force_figures_hold():
    s5, s3, probe = Indenter.sphere(0.005), Indenter.sphere(0.003), Indenter.probe()
    assert gel_force(0.001, s5) == pytest.approx(1.6, abs=0.05)
    assert gel_force(0.00125, s5) == pytest.approx(2.3, abs=0.05)
    assert gel_force(0.0015, s5) == pytest.approx(3.0, abs=0.05)
    assert gel_force(0.001, probe) == pytest.approx(2.3, abs=0.05)
    assert gel_force(0.0015, probe) == pytest.approx(4.3, abs=0.05)
    assert gel_force(0.001, s3) == pytest.approx(1.3, abs=0.05)
    assert gel.shore_a_to_modulus(10) == pytest.approx(0.41e6, rel=0.01)


@pytest.mark.parametrize("kind", ["sphere", "probe", "flat"])
def test_ground_truth_agrees_with_the_gel_model(kind):
    with Harness(SimDigit, {"indenter": kind}) as h:
        ind = h.comp.sim.indenter
        prev = 0.0
        for d in (0.0002, 0.0006, 0.001, 0.0014, 0.0018):
            out = h.step(d, indentation=d)
            assert out["gt_force"] == pytest.approx(gel_force(d, ind), rel=1e-12) and out["gt_force"] > prev
            prev = out["gt_force"]
            assert out["gt_max_depth"] == pytest.approx(d, rel=0.01)
            assert float(out["gt_depth"].max()) == out["gt_max_depth"]
            # the contact patch has the model's contact radius
            a = math.sqrt(out["gt_contact_mask"].sum() / math.pi) * gel.QVGA_M_PER_PX
            assert a == pytest.approx(gel.contact_edge_radius(ind, d), rel=0.05, abs=1.5 * gel.QVGA_M_PER_PX)


def test_same_seed_same_frames_and_two_seeds_independent_noise():
    def frames(seed):
        with Harness(SimDigit, {"noise": 2.0, "seed": seed, "indentation": 0.001}) as h:
            return [h.step(k / 60)["image"].astype(float) for k in range(3)]

    a, b, c = frames(5), frames(5), frames(6)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))  # one seed and one unit (id): the same noise (documented)
    clean = DigitSimulator().render(0.001)[0].astype(float)
    na, nc = a[0] - clean, c[0] - clean
    assert abs(np.corrcoef(na.ravel(), nc.ravel())[0, 1]) < 0.02


def test_every_step_publishes_a_fresh_frame_stamped_with_its_time():
    reg = make_registry("teletouch.plugins.sensors.sim_digit")
    seen = []
    text = """
name: stamps
clock: sim
nodes:
  - id: digit
    plugin: sim-digit
    rate: 30
    params: {indentation: 1mm}
"""

    def tap(node, t, outputs):
        if node == "digit":
            img = outputs["image"]
            stamp = img.stamp if hasattr(img, "stamp") else t   # a plain value is stamped with the step's time
            seen.append((t, stamp, img.value if hasattr(img, "value") else img))

    run_yaml(text, reg, duration=0.5, taps=[tap])
    assert len(seen) >= 14
    assert all(stamp == t for t, stamp, _ in seen)
    # a resting pose: the same picture every step, but each a new array (a consumer may keep or modify its frame)
    for (_, _, a), (_, _, b) in zip(seen, seen[1:]):
        assert a is not b and not np.shares_memory(a, b) and np.array_equal(a, b)
