"""DepthPipeline used directly (a library, not the `depth` node): a device it cannot run on was taken, and the first
frame failed deep in torch ("Cannot copy out of meta tensor; no data!", "Torch not compiled with CUDA enabled", an
unknown device type). The constructor now refuses it at once with the message the node and `teletouch estimate` give
(one function asks for all three)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from teletouch.plugins.estimators.depth_pipeline import DepthPipeline
from teletouch.plugins.estimators.normal_model import load_model

FORMS = r"expected cpu, cuda, cuda:N \(N: the GPU's index, from 0\) or mps"


@pytest.fixture(scope="module")
def model():
    return load_model("sim-digit-qvga")


def _gpus() -> int:
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


@pytest.mark.parametrize("device, why", [
    ("meta", rf"device: {FORMS}, got 'meta'$"),          # tensors without data: the first frame failed
    ("cdua", rf"device: {FORMS}, got 'cdua'$"),          # a typo torch does not know
    ("gpu", rf"device: {FORMS}, got 'gpu'; an NVIDIA GPU is 'cuda'$"),
    ("CUDA", rf"device: {FORMS}, got 'CUDA'; did you mean 'cuda'\?$"),
    ("xpu", rf"device: {FORMS}, got 'xpu'$"),
    ("cuda:x", rf"device: {FORMS}, got 'cuda:x'$"),
    ("", rf"device: {FORMS}, got ''$"),
], ids=["meta", "cdua", "gpu", "CUDA", "xpu", "cuda:x", "empty"])
def test_a_device_of_another_form_is_refused_at_construction(model, device, why):
    with pytest.raises(ValueError) as info:
        DepthPipeline(model, device=device)
    msg = str(info.value)
    assert msg.startswith("DepthPipeline: device") and re.search(why, msg), msg


def test_a_meta_torch_device_is_refused_like_its_name(model):
    import torch

    with pytest.raises(ValueError, match=rf"^DepthPipeline: device: {FORMS}, got 'meta'$"):
        DepthPipeline(model, device=torch.device("meta"))


def test_a_gpu_index_beyond_the_gpus_here_is_refused_at_construction(model):
    """cuda:7 on this machine: no CUDA GPU at all (the build machine), or fewer than 8."""
    n = _gpus()
    if n > 7:
        pytest.skip("this machine has a cuda:7")
    why = ("torch sees no CUDA GPU here; use device: cpu" if n == 0 else
           f"torch sees {n} CUDA GPU(s) here (cuda:0 to cuda:{n - 1})")
    with pytest.raises(ValueError) as info:
        DepthPipeline(model, device="cuda:7")
    assert str(info.value) == f"DepthPipeline: device 'cuda:7': {why}"


def test_a_gpu_index_beyond_two_gpus_names_them(model, monkeypatch):
    """As on a machine with two GPUs (torch's answers stood in for): refused before anything is put on a GPU."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    net = model.net

    def no_gpu_work(device):   # the check comes before the network is put on the device
        raise AssertionError(f"the network was put on {device} before the device was checked")

    monkeypatch.setattr(model, "net", no_gpu_work)
    try:
        with pytest.raises(ValueError) as info:
            DepthPipeline(model, device="cuda:7")
        assert str(info.value) == "DepthPipeline: device 'cuda:7': torch sees 2 CUDA GPU(s) here (cuda:0 to cuda:1)"
        with pytest.raises(ValueError, match=r"device 'cuda:2': torch sees 2 CUDA GPU\(s\) here \(cuda:0 to cuda:1\)"):
            DepthPipeline(model, device="cuda:2")
    finally:
        monkeypatch.setattr(model, "net", net)


def test_cuda_and_mps_where_there_are_none(model, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"^DepthPipeline: device 'cuda': torch sees no CUDA GPU here; use device: "
                                         r"cpu$"):
        DepthPipeline(model, device="cuda")
    with pytest.raises(ValueError, match=r"^DepthPipeline: device 'mps': MPS is not available; use device: cpu$"):
        DepthPipeline(model, device="mps")


def test_the_cpu_is_taken_and_gives_depth(model):
    import torch

    for device in ("cpu", torch.device("cpu")):
        pipe = DepthPipeline(model, device=device)
        assert pipe.device.type == "cpu" and pipe.mode == "sparse"
        res = pipe(np.ascontiguousarray(model.background))
        assert res.depth.shape == model.shape and res.max_depth == 0.0


def test_the_node_and_the_pipeline_ask_one_function():
    """The depth node's check was moved beside the pipeline, not copied: the node, `teletouch estimate` and the
    pipeline give the same message."""
    from teletouch.plugins.estimators import depth, depth_pipeline

    assert depth.device_problem is depth_pipeline.device_problem
    assert depth.device_form_problem is depth_pipeline.device_form_problem
    assert depth.DEVICES is depth_pipeline.DEVICES
    assert not hasattr(depth, "_DEVICE_FORM")
