"""Set-ups shared by the depth tests: the packaged model of the simulated DIGIT, the simulated sensor the tests press
on, presses rendered by scripts/make_sim_depth_model.py, and the real labelled QVGA presses of ../shared/data.

A fixture here is made by a function and bound to a name in the test module (``model = model_fixture()``): each module
says which set-up it uses, and gets its own (module scope: the simulator's noise, seeded, starts afresh in each)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from teletouch.plugins.estimators import depth_calibration as C
from teletouch.plugins.estimators.normal_model import load_model
from teletouch.plugins.sensors.sim_digit import DigitSimulator

REPO = Path(__file__).resolve().parents[1]


def model_fixture():
    """A module-scoped fixture that gives the packaged model of the simulated DIGIT (sim-digit-qvga)."""
    @pytest.fixture(scope="module")
    def model():
        return load_model("sim-digit-qvga")
    return model


def sim_fixture():
    """A module-scoped fixture that gives the simulated QVGA DIGIT with pixel noise 2 on seed 99: another seed than
    the one the packaged model was trained with."""
    @pytest.fixture(scope="module")
    def sim():
        return DigitSimulator("qvga", noise=2.0, seed=99)
    return sim


def render_presses(folder: Path, n: int, seed: int, **kwargs: Any) -> None:
    """``n`` presses of the simulated DIGIT rendered into ``folder`` (images, labels.csv, background.png) by
    scripts/make_sim_depth_model.py's render_presses; the scripts folder is on sys.path only for the import."""
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        from make_sim_depth_model import render_presses as render
    finally:
        sys.path.pop(0)
    render(folder, n, seed=seed, **kwargs)


def presses_fixture(n: int, seed: int):
    """A module-scoped fixture that gives a temporary folder of ``n`` presses rendered on ``seed`` (render_presses)."""
    @pytest.fixture(scope="module")
    def presses(tmp_path_factory) -> Path:
        folder = tmp_path_factory.mktemp("presses")
        render_presses(folder, n, seed=seed)
        return folder
    return presses


def qvga_fixture():
    """A module-scoped fixture that gives the real labelled QVGA presses (shared_data/digit-presses-qvga): the images
    [(name, image)], their labels, and the median of the images as the background."""
    @pytest.fixture(scope="module")
    def qvga(shared_data):
        folder = shared_data / "digit-presses-qvga"
        ims = C.load_images(folder)
        labs = C.read_labels(folder / "labels.csv")
        return ims, labs, C.median_background([im for _, im in ims])
    return qvga


def qvga_and_vga_models_fixture():
    """A module-scoped fixture that gives {"qvga": path, "vga": path}: the packaged QVGA model saved as a file, and
    the same model made for VGA frames (its background resized)."""
    @pytest.fixture(scope="module")
    def models(tmp_path_factory) -> dict[str, str]:
        import dataclasses

        import cv2

        folder = tmp_path_factory.mktemp("models")
        qvga = load_model("sim-digit-qvga")
        vga = dataclasses.replace(qvga, background=cv2.resize(qvga.background, (480, 640)))
        return {"qvga": str(qvga.save(folder / "qvga.model")), "vga": str(vga.save(folder / "vga.model"))}
    return models


def proxy_requests_fixture():
    """A fixture that gives the (node id, op) of every request an isolated node's proxy sends, in order."""
    @pytest.fixture
    def requests(monkeypatch):
        from teletouch.isolation import ProcessProxy

        sent: list[tuple[str, str]] = []
        exchange = ProcessProxy._exchange

        def spy(self, op, *args, **kw):
            sent.append((self.id, op))
            return exchange(self, op, *args, **kw)

        monkeypatch.setattr(ProcessProxy, "_exchange", spy)
        return sent
    return requests


def isolated_depth_graph(rate: int, faults: str = "") -> str:
    """A wall-clock graph: a pressing sine into sim-digit, whose frames go to a `depth` node run with `isolate:
    process` (``faults``: the graph's ``faults:`` line, or none)."""
    return f"""
clock: wall
{faults}
nodes:
  - {{id: press, plugin: mock-sensor, rate: {rate}, params: {{signal: sine, amplitude: 0.0004, offset: 0.0006,
      frequency: 2}}}}
  - {{id: digit, plugin: sim-digit, rate: {rate}, inputs: {{indentation: press.value}}}}
  - {{id: depth, plugin: depth, rate: {rate}, inputs: {{image: digit.image}}, isolate: process}}
"""


class ImageChainTap:
    """A runtime tap that keeps sim-digit's frames by stamp (``images``) and depth's outputs (``outs``)."""

    def __init__(self) -> None:
        self.images: dict[float, Any] = {}
        self.outs: list[dict] = []

    def __call__(self, node: str, t: float, out: dict) -> None:
        from teletouch.component import Sample

        if node == "digit":
            v = out["image"]
            self.images[v.stamp if isinstance(v, Sample) else t] = v.value if isinstance(v, Sample) else v
        elif node == "depth":
            self.outs.append(out)

    def check_inline(self, skip: int = 0) -> int:
        """Each depth output (after the first ``skip``) equals what the same estimator computes inline on its frame,
        step by step, without warm-ups (maps bit for bit); returns how many were compared."""
        import numpy as np

        from teletouch.component import Sample
        from teletouch.plugins.estimators.depth import DepthEstimator
        from teletouch.testing import Harness

        checked = 0
        with Harness(DepthEstimator, {"warm": False}) as h:
            for o in self.outs[skip:]:
                d = o["depth"]
                img = self.images.get(d.stamp)
                if img is None:
                    continue
                h.set(image=Sample(img, d.stamp))
                ref = h.comp.step(d.stamp, h.inputs)
                assert d.value.dtype == np.float32 and d.value.shape == ref["depth"].value.shape
                assert np.array_equal(d.value, ref["depth"].value)
                assert np.array_equal(o["contact_mask"].value, ref["contact_mask"].value)
                assert float(o["max_depth"].value) == float(ref["max_depth"].value)
                checked += 1
        return checked
