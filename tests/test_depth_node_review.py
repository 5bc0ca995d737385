"""Review of the `depth` node and `sim-digit`: parameters that no DIGIT setup has, inputs out of range, and the
same camera sample read again by a node that steps faster than the camera delivers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from teletouch import ComponentFault, Sample
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.plugins.sensors.sim_digit import DigitSimulator, SimDigit
from teletouch.testing import Harness

from helpers_depth import model_fixture

model = model_fixture()


# --- sim-digit --------------------------------------------------------------------------------------------------

def test_sim_digit_refuses_an_indentation_input_no_digit_setup_has():
    """The static ``indentation`` is refused beyond 20 mm (millimetres typed in a metre field); the input was not:
    5 (a producer sending mm) rendered a 5 m press with a ground-truth force of 449 kN."""
    with Harness(SimDigit, {}) as h:
        assert h.step(0.0, indentation=0.001)["gt_force"] > 0
        with pytest.raises(ValueError, match=r"indentation input \(5 m\) is larger than 20 mm.*in m"):
            h.step(0.1, indentation=5.0)
        with pytest.raises(ValueError, match=r"indentation input \(-5 m\)"):
            h.step(0.2, indentation=-5.0)
        assert h.step(0.3, indentation=-0.001)["gt_force"] == 0.0   # no contact, as before
        assert h.step(0.4, indentation=0.0199)["gt_max_depth"] > 0.019   # within the bound: rendered


def test_sim_digit_refuses_a_pixel_size_whose_blur_needs_terabytes():
    """m_per_px 1e-9 (an exponent off) made the default 0.08 mm blur 80000 px wide: a MemoryError (47.7 TiB) deep
    in the renderer, naming no parameter; with no blur, 4.5 GB and 14 s for one frame."""
    with pytest.raises(ValidationError, match=r"m_per_px \(1e-09 m\) is below 0.001 mm"):
        SimDigit.Params(m_per_px=1e-9)
    with pytest.raises(ValidationError, match=r"smoothing \(1 mm\) is a blur of 100 px at m_per_px 0.01 mm: "
                                              r"expected at most 64 px"):
        SimDigit.Params(m_per_px=1e-5, smoothing=1e-3)
    with pytest.raises(ValueError, match=r"m_per_px \(1e-09 m\) is below"):
        DigitSimulator("qvga", m_per_px=1e-9)             # the engine on its own: the same check
    with pytest.raises(ValueError, match=r"smoothing \(1 mm\) is a blur of 100 px"):
        DigitSimulator("qvga", m_per_px=1e-5, smoothing=1e-3)
    # every smoothing allowed (up to 1 mm) at the default pixel sizes is still accepted
    for res in ("qvga", "vga"):
        SimDigit.Params(resolution=res, smoothing=1e-3)


def test_sim_digit_is_deterministic_with_a_seed_and_stamps_its_outputs_with_the_step_time():
    frames = []
    for _ in range(2):
        with Harness(SimDigit, {"noise": 2.0, "drift": 3.0, "seed": 7, "indentation": 0.001}) as h:
            frames.append([h.step(k / 60)["image"] for k in range(3)])
            assert all(s.stamp == pytest.approx(2 / 60) for s in h.samples.values())
    assert all(np.array_equal(a, b) for a, b in zip(*frames))
    assert not np.array_equal(frames[0][0], frames[0][1])   # the noise differs from frame to frame


# --- depth ------------------------------------------------------------------------------------------------------

def test_depth_refuses_a_contact_depth_deeper_than_the_gel():
    """contact_depth: 0.03 (meant: mm) was taken as 30 mm: no pixel is ever that deep, so every press read as no
    contact (contact area 0, an empty mask) without a word."""
    with pytest.raises(ValidationError, match=r"contact_depth \(0.03 m\) is more than a DIGIT's gel is thick .*"
                                              r"\"0.03mm\""):
        DepthEstimator.Params(contact_depth=0.03)
    assert DepthEstimator.Params(contact_depth="0.03mm").contact_depth == pytest.approx(3e-5)
    assert DepthEstimator.Params(contact_depth=5e-3).contact_depth == 5e-3


def test_the_same_sample_read_again_is_not_another_frame(model):
    """A node stepping faster than the camera delivers (depth at 60 Hz behind a 30 fps stream, or wall-clock jitter)
    reads the same sample again. It was taken as another frame: an implausible frame counted twice (fault_after_bad
    reached after half the frames), an untouched frame blended into the background twice."""
    black = np.zeros((320, 240, 3), np.uint8)
    with Harness(DepthEstimator, {"fault_after_bad": 3}) as h:
        h.set(image=Sample(black, 0.0))
        out = h.comp.step(0.0, h.inputs)
        assert math.isnan(out["max_depth"].value) and out["max_depth"].stamp == 0.0
        for t in (1 / 60, 2 / 60, 3 / 60):            # one camera frame, read three times: no fault
            again = h.comp.step(t, h.inputs)            # the same outputs again, with the frame's stamp
            assert math.isnan(again["max_depth"].value) and again["max_depth"].stamp == 0.0
        assert h.comp.bad_frames == 1 and h.comp.status()["bad_frames"] == 1
        h.set(image=Sample(black.copy(), 0.1))
        h.comp.step(0.1, h.inputs)
        h.set(image=Sample(black.copy(), 0.2))
        with pytest.raises(ComponentFault, match=r"3 implausible frames in a row"):
            h.comp.step(0.2, h.inputs)

    frame = model.background.astype(np.int16)
    frame[100:160, 60:120] += 25                        # untouched for change_threshold 200: blended in
    frame = np.clip(frame, 0, 255).astype(np.uint8)
    params = {"adapt_background": 0.5, "change_threshold": 200.0, "adapt_limit": 100.0}
    with Harness(DepthEstimator, params) as once:
        once.step(0.0, image=frame)
    with Harness(DepthEstimator, params) as h:
        h.set(image=Sample(frame, 0.0))
        first = h.comp.step(0.0, h.inputs)
        again = h.comp.step(1 / 60, h.inputs)           # the same sample again
        assert np.array_equal(h.comp._bg, once.comp._bg)
        assert again == first and h.comp.reused == 0    # answered as before, not recomputed nor reused
        h.set(image=Sample(frame.copy(), 0.1))          # a new frame (same pixels, new stamp) is blended in
        h.comp.step(0.1, h.inputs)
        assert not np.array_equal(h.comp._bg, once.comp._bg)


def test_a_fault_on_a_sample_is_raised_again_when_it_is_read_again():
    """A sample that faulted the node is not remembered as handled: read again, it faults again."""
    with Harness(DepthEstimator, {}) as h:
        h.set(image=Sample(np.zeros((640, 480, 3), np.uint8), 0.0))
        for t in (0.0, 1 / 60):
            with pytest.raises(ComponentFault, match="expected a uint8 BGR image of 320x240x3"):
                h.comp.step(t, h.inputs)


def test_reactivation_handles_the_sample_it_finds_as_a_new_frame(model):
    """After deactivate() and activate() the sample waiting in the port is read as a frame of this activation."""
    with Harness(DepthEstimator, {}) as h:
        h.set(image=Sample(model.background, 0.0))
        assert h.comp.step(0.0, h.inputs) is not None
        h.comp.deactivate()
        h.comp.activate()
        out = h.comp.step(1.0, h.inputs)
        assert out is not None and out["max_depth"].value == 0.0 and out["max_depth"].stamp == 0.0
