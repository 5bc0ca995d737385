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
