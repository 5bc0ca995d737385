"""benchmarks/labeller_accuracy.py: the third estimate of a press's centre (a rendered ball press fitted to the colour
change) finds a simulated press where it was put, and the quick benchmark reports the labeller against both label
sets."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from helpers_scripts import load_bench

from test_benchmarks_cli import BENCH, REPO, _strict_last_line


@pytest.fixture()
def bench(monkeypatch):
    return load_bench(monkeypatch, "labeller_accuracy.py", "labeller_accuracy_under_test")


@pytest.mark.parametrize("at_px, depth", [((180.3, 250.6), 0.35e-3), ((300.0, 420.2), 0.6e-3)])
def test_the_optical_fit_finds_a_simulated_press_where_it_was_put(bench, at_px, depth):
    """A VGA press rendered by sim-digit (the same gel model and optical table, no noise), the fit started 4 px and
    30% of the radius off: the centre comes back within 0.5 px and the indentation within 10%. A fit that did not
    move from its start, or moved the wrong way, fails."""
    from teletouch.plugins.sensors import optics
    from teletouch.plugins.sensors.sim_digit import DigitSimulator

    sim = DigitSimulator("vga")
    rows, cols = sim.shape
    cx, cy = at_px
    pos = ((cx - (cols - 1) / 2.0) * sim.m_per_px, (cy - (rows - 1) / 2.0) * sim.m_per_px)
    img, surf = sim.render(depth, pos)
    bg = sim.background_u8
    renderer = optics.OpticalRenderer(optics.load_table(), (rows, cols))
    a_px = float(np.sqrt(surf.mask.sum() / np.pi))
    fx, fy, fd, corr = bench.optical_fit(img, bg, (cx + 4.0, cy - 3.0, 1.3 * a_px), renderer, sim.m_per_px)
    assert np.hypot(fx - cx, fy - cy) <= 0.5, (fx, fy)
    assert abs(fd / depth - 1) <= 0.10, fd
    assert corr > 0.95


def test_the_quick_benchmark_reports_the_labeller_against_both_label_sets(shared_data):
    r = subprocess.run([sys.executable, str(BENCH / "labeller_accuracy.py"), "--quick"], cwd=REPO,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    got = _strict_last_line(r.stdout)
    assert got["qvga"]["usable_presses"] == 10 and got["vga"]["usable_presses"] == 47
    # measured: QVGA 8/10 within 3 px, radius ratio 1.09 (the hand circles lie inside the colour change); VGA
    # 17/47, 0.96; the optical fit on 12 presses correlates 0.87 (median) with the real colour change
    for ds, lo, hi in (("qvga", 1.0, 1.2), ("vga", 0.9, 1.05)):
        a = got[ds]["all"]
        assert a["centre_median_px"] < 5 and lo <= a["radius_ratio_median"] <= hi, (ds, a)
        assert got[ds]["unflagged"]["presses"] < a["presses"]
    fit = got["vga_optical_fit"]
    assert fit["presses"] == 12 and len(fit["per_press"]) == 12 and fit["fit_correlation_median"] > 0.8
    for pair in ("labeller_to_labels_px", "fit_to_labels_px", "fit_to_labeller_px"):
        assert 0 < fit["all"][pair]["centre_median_px"] < 8, pair
    json.dumps(got)   # plain JSON all through


def test_without_the_shared_data_it_names_where_they_were_looked_for(tmp_path):
    # before: a FileNotFoundError traceback from load_images (found by review)
    env = dict(os.environ, TELETOUCH_SHARED_DATA=str(tmp_path / "nowhere"))
    r = subprocess.run([sys.executable, str(BENCH / "labeller_accuracy.py"), "--quick"], cwd=REPO,
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode != 0 and "Traceback" not in r.stderr and r.stdout == ""
    assert str(tmp_path / "nowhere" / "digit-presses-qvga") in r.stderr and "TELETOUCH_SHARED_DATA" in r.stderr
