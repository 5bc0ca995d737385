"""An audit of the `depth` node and `teletouch estimate`: a grayscale frame read as a contact in the node (which
`estimate` refused), and the torch device accepted in any form torch knows (`meta`: a traceback in `estimate`, a run
that failed at start-up after `teletouch validate` said OK). Each test failed before its fix."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from teletouch import ComponentFault, Sample
from teletouch.cli import main
from teletouch.plugins.estimators import depth as D
from teletouch.plugins.estimators.depth import DepthEstimator
from teletouch.testing import Harness

REPO = Path(__file__).resolve().parents[1]


def _gray(frame: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)


# --- a grayscale frame in the node -------------------------------------------------------------------------------

def test_the_node_reads_a_grayscale_frame_as_implausible_not_as_a_contact(shared_data):
    press = cv2.imread(str(shared_data / "digit-presses-qvga" / "0003.png"))
    gray = _gray(press)
    # (the packaged model is the simulated sensor's, fitted on this unit; no background check, which would name a
    # real frame another sensor's before the 10 first frames are in)
    with Harness(DepthEstimator, {"max_background_mismatch": 0, "fault_after_bad": 3, "warm": False}) as h:
        out = h.step(0.0, image=Sample(gray, 0.0))
        # before: 3.16 mm and 78 mm^2 of contact on the packaged model, an ordinary frame
        assert math.isnan(out["max_depth"]) and math.isnan(out["contact_area"])
        assert np.isnan(out["depth"]).all() and not out["contact_mask"].any()
        assert h.comp.bad_frames == 1 and h.comp.last_problem.startswith("a grayscale image")
        assert h.comp.status()["bad_frames"] == 1
        out = h.step(1 / 60, image=Sample(press, 1 / 60))   # the colour frame after it is read as ever
        assert out["max_depth"] > 1e-4 and h.comp.bad_frames == 1
        h.step(2 / 60, image=Sample(gray, 2 / 60))
        h.step(3 / 60, image=Sample(gray.copy(), 3 / 60))
        with pytest.raises(ComponentFault, match=r"3 implausible frames in a row \(fault_after_bad 3\); the last: "
                                                 r"a grayscale image"):
            h.step(4 / 60, image=Sample(gray.copy(), 4 / 60))


def test_the_node_and_estimate_share_one_check_whose_fast_path_gives_the_full_answer():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (320, 240, 3), dtype=np.uint8)
    assert D.colour_problem(frame) == ""
    g = np.repeat(frame[..., :1], 3, axis=2)
    assert D.colour_problem(g).startswith("a grayscale image")
    g[1::4] = frame[1::4]                      # gray on every 4th row and column (the fast path's), colour elsewhere
    assert D.colour_problem(g) == ""
    assert not hasattr(D, "_colour_problem")   # estimate's own copy is gone: both ask colour_problem


# --- the device ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("device", ["meta", "gpu", "CUDA", "cuda:x", "xpu", " cpu", ""])
def test_a_device_of_another_form_is_refused_when_the_params_are_validated(device):
    with pytest.raises(ValidationError, match=r"device\n.*expected cpu, cuda, cuda:N \(N: the GPU's index, from 0\) "
                                              r"or mps, got"):
        DepthEstimator.Params(device=device)
    # the accepted forms pass; whether the device is there is asked at start-up (the graph may be validated on
    # another machine than the one it runs on)
    for ok in ("cpu", "cuda", "cuda:0", "cuda:3", "mps"):
        assert DepthEstimator.Params(device=ok).device == ok


def test_validate_refuses_a_meta_device_naming_the_field(capsys):
    rc = main(["validate", str(REPO / "examples" / "paper-sim.yaml"), "--set", "depth.device=meta"])
    out = capsys.readouterr()
    # before: "examples/paper-sim.yaml: OK", then `run` failed at start-up
    assert rc != 0 and "OK" not in out.out
    assert "node 'depth': param 'device' = 'meta': expected cpu, cuda, cuda:N" in out.err


@pytest.mark.parametrize("device, why", [
    ("meta", r"--device: expected cpu, cuda, cuda:N \(N: the GPU's index, from 0\) or mps, got 'meta'\n"),
    ("gpu", r"--device: expected cpu, cuda, cuda:N .* got 'gpu'; an NVIDIA GPU is 'cuda'\n"),
])
def test_estimate_refuses_a_device_with_exit_code_2_not_a_traceback(shared_data, capsys, device, why):
    rc = main(["estimate", "--model", "sim-digit-qvga", "--device", device,
               str(shared_data / "digit-presses-qvga" / "0000.png")])
    err = capsys.readouterr().err
    # before: NotImplementedError: Cannot copy out of meta tensor; no data! (a traceback)
    assert rc == 2
    assert err.startswith("teletouch estimate: error: --device") and "Traceback" not in err
    assert re.search(why, err), err


def test_estimate_names_a_missing_gpu_with_exit_code_2(shared_data, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA GPU is here")
    rc = main(["estimate", "--model", "sim-digit-qvga", "--device", "cuda:0",
               str(shared_data / "digit-presses-qvga" / "0000.png")])
    err = capsys.readouterr().err
    # before: exit code 1, "teletouch: error: device 'cuda:0': ..." (the node's message)
    assert rc == 2
    assert "teletouch estimate: error: --device 'cuda:0': torch sees no CUDA GPU here; use --device cpu" in err
