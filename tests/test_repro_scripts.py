"""The packaged simulated-sensor files are reproducible, and ``--check`` proves it.

scripts/make_sim_depth_model.py --check and scripts/make_sim_force_calibration.py --check make the file again in a
temporary folder and compare it with the file -o names (default: the packaged one). A full check takes ~10-60 s
(depth) and ~15-20 min (force) on a 2-core machine. The depth check runs here in full on the packaged model (the
script pins numpy's kernels, so the weights come out the same on AVX2 and AVX-512 CPUs; another torch build or a CPU
without AVX2 could still differ), and end to end on a small model the tests make themselves; the force check's
comparisons run on synthetic changes of the packaged files (read, never written). The maintainer's commands are in
docs/depth.md and docs/force.md.
"""

from __future__ import annotations

import copy
import datetime as dt
import io
import json
import os
import subprocess
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from helpers_scripts import script_fixture

REPO = Path(__file__).resolve().parents[1]
PACKAGED_MODEL = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model"
PACKAGED_FORCE = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.force.json"
SMALL = ["--presses", "6", "--epochs", "1"]      # 2 training presses, 4 held out: ~7 s of CPU


depth_script = script_fixture("make_sim_depth_model")
force_script = script_fixture("make_sim_force_calibration")


def _run(mod, *argv: str) -> tuple[int, str]:
    out = io.StringIO()
    with redirect_stdout(out):
        rc = mod.main(list(argv))
    return rc, out.getvalue()


def _write_model(path: Path, meta: dict, arrays: dict[str, np.ndarray]) -> Path:
    with open(path, "wb") as fh:
        np.savez_compressed(fh, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    return path


def _read_model(mod, path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    return mod.read_model_file(path)


# --- depth model ------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_model(depth_script, tmp_path_factory):
    """A small model made by the script as a user makes it, with SOURCE_DATE_EPOCH set."""
    path = tmp_path_factory.mktemp("repro") / "small.model"
    mp = pytest.MonkeyPatch()
    mp.setenv("SOURCE_DATE_EPOCH", "1700000000")
    try:
        rc, _ = _run(depth_script, *SMALL, "-o", str(path))
    finally:
        mp.undo()
    assert rc == 0 and path.is_file()
    return path


def test_depth_check_of_a_file_the_script_made_matches_byte_for_byte(depth_script, small_model, monkeypatch):
    """--check makes the model again (SOURCE_DATE_EPOCH from the file's created) and finds it the same: every
    number, and here (same machine) every byte; the checked file is not touched, even with a clock time set."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1")      # the check uses the file's created, not the caller's value
    before = small_model.read_bytes()
    rc, out = _run(depth_script, "--check", *SMALL, "-o", str(small_model))
    assert rc == 0, out
    assert "MATCHES" in out and "bytes: identical" in out and "DIFFERS" not in out
    assert small_model.read_bytes() == before
    assert list(small_model.parent.glob("*")) == [small_model]


def test_a_model_file_records_the_software_it_was_made_with(depth_script, small_model):
    import platform

    import cv2
    import torch

    meta, _ = _read_model(depth_script, small_model)
    assert meta["training"]["software"] == {"python": platform.python_version(), "machine": platform.machine(),
                                            "numpy": np.__version__, "torch": torch.__version__,
                                            "opencv": cv2.__version__}


def test_depth_check_names_the_software_a_differing_file_was_made_with(depth_script, small_model, tmp_path):
    """Remade with another torch or numpy the weights differ (a GPU machine's torch 2.11 and numpy 2.5: up to 0.44):
    the check said only DIFFERS. Now the file's software is never a difference itself, and where the numbers differ
    the check names what differs in it."""
    import torch

    meta, arrays = _read_model(depth_script, small_model)
    m = copy.deepcopy(meta)
    m["training"]["software"].update(torch="1.0.0+test", numpy="1.0.0")   # no version a machine runs
    w = arrays["w.0.weight"].copy()
    w[0, 0] += 1.0
    path = _write_model(tmp_path / "other.model", m, dict(arrays, **{"w.0.weight": w}))
    rc, out = _run(depth_script, "--check", *SMALL, "-o", str(path))
    assert rc == 1 and "DIFFERS  w.0.weight" in out, out
    assert (f"the file was made with other software (numpy 1.0.0 -> {np.__version__}, torch 1.0.0+test -> "
            f"{torch.__version__})") in out, out
    assert "meta training.software" not in out.replace("ignored  meta training.software", "")   # no difference
    del m["training"]["software"]
    assert depth_script.software_change(m["training"].get("software")) == "the file records no versions"
    assert depth_script.software_change(meta["training"]["software"]) == ""


def test_the_packaged_model_is_remade_byte_for_byte(tmp_path):
    """The packaged sim-digit model, made again by its script in a fresh process (as a maintainer runs --check:
    numpy pinned to its AVX2-level kernels before it loads), is the same file byte for byte: any change of the
    rendering, the labels, the features or the training that would make another model shows here, before the
    packaged file is out of step with the code. Seen bit for bit on an AVX2 and an AVX-512 machine (~10-60 s)."""
    env = {k: v for k, v in os.environ.items() if k not in ("NPY_DISABLE_CPU_FEATURES", "SOURCE_DATE_EPOCH")}
    run = subprocess.run([sys.executable, str(REPO / "scripts" / "make_sim_depth_model.py"), "--check"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "bytes: identical" in run.stdout and "MATCHES" in run.stdout
    assert "NPY_DISABLE_CPU_FEATURES=X86_V4" in run.stderr     # the pin was in place (the check's header says so)


def test_the_numpy_pin_is_set_only_before_numpy_loads(depth_script):
    """Imported by a program that already has numpy (this test), the script leaves the environment alone; its pin
    names numpy 2's AVX-512 groups and numpy 1's features."""
    assert {"X86_V4", "AVX512F", "AVX512_SKX"} <= set(depth_script.NUMPY_SIMD_PIN.split())
    assert os.environ.get("NPY_DISABLE_CPU_FEATURES") != depth_script.NUMPY_SIMD_PIN


def test_depth_check_refuses_other_settings_than_the_file_records(depth_script, small_model, capsys):
    """A check with other settings than the file's would report every weight as different: refused before the work,
    naming the setting, the file's value and the arguments'."""
    with pytest.raises(SystemExit) as e:
        _run(depth_script, "--check", "--presses", "6", "--epochs", "5", "-o", str(small_model))
    assert e.value.code == 2
    assert "--epochs 1 (the arguments: 5)" in capsys.readouterr().err


def test_depth_check_of_a_missing_or_unreadable_file_is_refused(depth_script, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        _run(depth_script, "--check", "-o", str(tmp_path / "none.model"))
    assert e.value.code == 2 and "none.model: not a readable model file" in capsys.readouterr().err
    (tmp_path / "junk.model").write_text("not a zip")
    with pytest.raises(SystemExit) as e:
        _run(depth_script, "--check", "-o", str(tmp_path / "junk.model"))
    assert e.value.code == 2 and "junk.model: not a readable model file" in capsys.readouterr().err


def test_compare_models_reports_a_changed_weight_and_passes_a_rounding(depth_script, tmp_path):
    meta, arrays = _read_model(depth_script, PACKAGED_MODEL)
    same = _write_model(tmp_path / "same.model", meta, arrays)
    lines, bad = depth_script.compare_models(PACKAGED_MODEL, same)
    assert bad == [] and any(line.startswith("same  w.3.weight") for line in lines)
    w = arrays["w.3.weight"]
    scale = float(np.abs(w).max())
    near = dict(arrays, **{"w.3.weight": w + np.float32(2e-6 * scale)})      # within 1e-5 of the largest weight
    _, bad = depth_script.compare_models(PACKAGED_MODEL, _write_model(tmp_path / "near.model", meta, near))
    assert bad == []
    moved = w.copy()
    moved[3, 7] += np.float32(1e-4 * scale)
    _, bad = depth_script.compare_models(PACKAGED_MODEL, _write_model(tmp_path / "far.model", meta,
                                                                      dict(arrays, **{"w.3.weight": moved})))
    assert len(bad) == 1 and bad[0].startswith("w.3.weight: max abs difference")
    bg = arrays["background"].copy()
    bg[10, 10, 0] ^= 4
    _, bad = depth_script.compare_models(PACKAGED_MODEL, _write_model(tmp_path / "bg.model", meta,
                                                                      dict(arrays, background=bg)))
    assert len(bad) == 1 and bad[0].startswith("background")


def test_compare_models_ignores_durations_and_created_but_not_a_number(depth_script, tmp_path):
    meta, arrays = _read_model(depth_script, PACKAGED_MODEL)
    assert "seconds" not in meta["training"]        # made with SOURCE_DATE_EPOCH: no durations in the file
    m = copy.deepcopy(meta)
    m["training"]["seconds"], m["training"]["total_seconds"] = 7.6, 9.1     # a run without SOURCE_DATE_EPOCH
    m["training"]["created"] = "2030-01-01T00:00:00Z"
    lines, bad = depth_script.compare_models(PACKAGED_MODEL, _write_model(tmp_path / "a.model", m, arrays))
    assert bad == [] and sum(line.startswith("ignored  meta training.") for line in lines) == 3
    m["depth_gain"] *= 1.001
    m["hidden"] = [32, 16]
    _, bad = depth_script.compare_models(PACKAGED_MODEL, _write_model(tmp_path / "b.model", m, arrays))
    assert [b.split(":")[0] for b in bad] == ["meta depth_gain", "meta hidden[1]"]
    m = copy.deepcopy(meta)
    del m["validation"]
    _, bad = depth_script.compare_models(PACKAGED_MODEL, _write_model(tmp_path / "c.model", m, arrays))
    assert bad == ["meta validation: only in the reference"]


def test_rounded_meta_figures_may_differ_in_their_last_digit_only(depth_script):
    """Validation figures are written rounded (0.0974): another rounding of the same value may flip the last digit."""
    bad, _ = depth_script.compare_meta({"v": 0.0974, "x": -0.061900000000000004}, {"v": 0.0975, "x": -0.0618}, 1e-4)
    assert bad == []
    bad, _ = depth_script.compare_meta({"v": 0.0974, "n": 3}, {"v": 0.0977, "n": 4}, 1e-4)
    assert [b.split(":")[0] for b in bad] == ["n", "v"]
    assert depth_script.last_place(0.0974) == pytest.approx(1e-4) and depth_script.last_place(1 / 3) == 0.0


# --- force calibration ------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def packaged_force():
    return json.loads(PACKAGED_FORCE.read_text())


def test_compare_calibrations_equal_files_pass(force_script, packaged_force):
    lines, bad = force_script.compare_calibrations(packaged_force, copy.deepcopy(packaged_force))
    assert bad == [] and lines[0].startswith("equal  ") and not any("DIFFERS" in line for line in lines)


@pytest.mark.parametrize("change, field", [
    (lambda c: c["model"]["coefficients"].__setitem__(2, c["model"]["coefficients"][2] * (1 + 3e-6)),
     "model.coefficients[2]"),
    (lambda c: c["model"]["position"]["coefficients"][1].__setitem__(4, 2094.4852855483023 + 0.05),
     "model.position.coefficients[1][4]"),
    (lambda c: c["quality"].__setitem__("r2", c["quality"]["r2"] - 2e-6), "quality.r2"),
    (lambda c: c["samples"][17].__setitem__("depth_m", c["samples"][17]["depth_m"] + 1e-8), "samples[17].depth_m"),
    (lambda c: c["samples"][17].__setitem__("residual_n", c["samples"][17]["residual_n"] + 1e-4),
     "samples[17].residual_n"),
    (lambda c: c["samples"][17].__setitem__("phase", "unloading"), "samples[17].phase"),
    (lambda c: c["samples"].pop(), "samples"),
    (lambda c: c["hysteresis"].pop("max_gap_n"), "hysteresis.max_gap_n"),
])
def test_compare_calibrations_reports_a_changed_number(force_script, packaged_force, change, field):
    new = copy.deepcopy(packaged_force)
    change(new)
    lines, bad = force_script.compare_calibrations(packaged_force, new)
    assert len(bad) == 1 and bad[0].startswith(field + ":"), bad
    assert any(line.startswith("DIFFERS  " + field) for line in lines)


def test_compare_calibrations_passes_rounding_and_ignores_created(force_script, packaged_force):
    new = copy.deepcopy(packaged_force)
    new["model"]["coefficients"][3] *= 1 + 3e-7                        # 0.3 x the coefficients' tolerance
    new["model"]["position"]["coefficients"][1][3] += 1e-3             # a small one: 1e-6 of its row's largest is 3e-3
    new["samples"][3]["predicted_n"] += 1e-6                           # 1e-6 of the largest force is 7e-6 N
    new["created"] = "2030-01-01T00:00:00+00:00"
    lines, bad = force_script.compare_calibrations(packaged_force, new)
    assert bad == []
    assert f"ignored  created: '{packaged_force['created']}' -> '2030-01-01T00:00:00+00:00'" in lines
    assert any(line.startswith("same  samples[].predicted_n: max abs difference 1e-06") for line in lines)


@pytest.fixture()
def force_check(force_script, monkeypatch, tmp_path, packaged_force):
    """The force script with the calibration command replaced by one that writes ``result`` (a copy of the packaged
    file unless changed) where it was told to, recording the command and its SOURCE_DATE_EPOCH."""
    ref = tmp_path / "ref.force.json"
    ref.write_bytes(PACKAGED_FORCE.read_bytes())
    state = {"result": copy.deepcopy(packaged_force), "calls": []}

    def fake_call(cmd, cwd=None, env=None):
        out = Path(cmd[cmd.index("-o") + 1])
        state["calls"].append((list(cmd), dict(env or {})))
        text = (PACKAGED_FORCE.read_text() if state["result"] == packaged_force
                else json.dumps(state["result"], indent=1))
        out.write_text(text)
        return 0

    monkeypatch.setattr(force_script.subprocess, "call", fake_call)
    monkeypatch.setattr(sys, "argv", ["make_sim_force_calibration.py"])
    return ref, state


def test_force_check_runs_into_a_temporary_file_and_matches(force_script, force_check):
    ref, state = force_check
    before = ref.read_bytes()
    rc, out = _run(force_script, "--check", "-o", str(ref))
    assert rc == 0 and "MATCHES" in out and "bytes: identical" in out, out
    ((cmd, env),) = state["calls"]
    out_path = Path(cmd[cmd.index("-o") + 1])
    assert out_path != ref and not out_path.exists() and not Path(cmd[cmd.index("--plot") + 1]).exists()
    created = dt.datetime.fromisoformat(json.loads(PACKAGED_FORCE.read_text())["created"])
    assert env["SOURCE_DATE_EPOCH"] == str(int(created.timestamp()))  # the file's created
    assert "routine.cycles=25" in cmd and cmd[cmd.index("--position-degree") + 1] == "4"
    assert ref.read_bytes() == before


def test_force_check_exits_1_naming_what_differs(force_script, force_check):
    ref, state = force_check
    state["result"]["model"]["coefficients"][1] *= 1.0001
    rc, out = _run(force_script, "--check", "-o", str(ref))
    before = json.loads(PACKAGED_FORCE.read_text())["model"]["coefficients"][1]
    assert rc == 1 and f"DIFFERS  model.coefficients[1]: {before!r} -> " in out, out


def test_force_check_refuses_quick_and_other_settings_before_the_run(force_script, force_check, capsys):
    ref, state = force_check
    for argv, says in ((["--quick"], "--quick makes another file"),
                       (["--grid", "3x3"], "press points 25 (the arguments: 9)"),
                       (["--position-degree", "2"], "--position-degree 4 (the arguments: 2)"),
                       (["--depth-source", "gt"], "--depth-source depth (the arguments: gt)")):
        with pytest.raises(SystemExit) as e:
            _run(force_script, "--check", *argv, "-o", str(ref))
        assert e.value.code == 2 and says in capsys.readouterr().err
    assert state["calls"] == []


def test_force_quick_fits_position_terms_of_degree_2(force_script, force_check, tmp_path):
    """--quick (the docstring's way to try the script, and benchmarks/force_accuracy.py --recalibrate --quick) fitted
    its 3 x 3 presses with position degree 1: R^2 0.979, refused below 0.99, so it wrote nothing and exited 1.
    Degree 2 reads R^2 0.997 on the same presses (measured, 153 samples)."""
    ref, state = force_check
    rc, _ = _run(force_script, "--quick", "-o", str(tmp_path / "q.force.json"))
    assert rc == 0
    ((cmd, _),) = state["calls"]
    assert cmd[cmd.index("--position-degree") + 1] == "2" and "routine.cycles=9" in cmd


def test_force_with_another_depth_model_records_that_model(force_script, force_check, tmp_path):
    """--depth-model FILE ran the press with that model but passed --sensor-model-id sim-digit-qvga all the same:
    the file was tied to the model it was not made with (validate refused the right model, took the wrong one)."""
    ref, state = force_check
    model = tmp_path / "other.model"
    model.write_bytes((REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model").read_bytes())
    rc, _ = _run(force_script, "--quick", "--depth-model", str(model), "-o", str(tmp_path / "q.force.json"),
                 "--plot", str(tmp_path / "q.png"))
    assert rc == 0
    ((cmd, _env),) = state["calls"]
    assert "--sensor-model-id" not in cmd and f"depth.model={model.resolve()}" in cmd   # the graph's model recorded
    state["calls"].clear()
    rc, _ = _run(force_script, "--quick", "-o", str(tmp_path / "p.force.json"), "--plot", str(tmp_path / "p.png"))
    ((cmd, _env),) = state["calls"]
    assert cmd[cmd.index("--sensor-model-id") + 1] == "sim-digit-qvga"
