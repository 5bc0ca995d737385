"""Audit of the force mapper at run time (poly-force), its calibration file and the force-calibration tools: each
test fails on the code before its fix (the measured symptom is in its comment)."""

from __future__ import annotations

import json
import math
from importlib.resources import files

import numpy as np
import pytest

from teletouch import ModelFileError, Sample
from teletouch.plugins.estimators.force_calibration import PressRoutine
from teletouch.plugins.estimators import poly_force as PF
from teletouch.plugins.estimators.poly_force import CalibrationError, ForceCalibration, PolyForce, read_pairs_csv
from teletouch.testing import Harness

TRUE = [0.02, 1500.0, 4.0e5, 5.0e7]  # N, N/m, N/m^2, N/m^3: 0.02 N .. ~5.0 N over 0.1..2 mm


def truth(d):
    d = np.asarray(d, float)
    return TRUE[0] + TRUE[1] * d + TRUE[2] * d ** 2 + TRUE[3] * d ** 3


@pytest.fixture
def cal_file(tmp_path):
    d = np.linspace(0.1e-3, 2.0e-3, 30)
    return str(ForceCalibration.fit(d, truth(d), 3, sensor_model_id="unit-test").save(tmp_path / "u.force.json"))


# ------------------------------------------------------------------------------------------------ the mapper
@pytest.mark.parametrize("policy", ["clamp", "extrapolate"])
def test_depth_deeper_than_a_gel_is_invalid_and_the_force_stays_below_its_limit(cal_file, policy):
    # before: extrapolate turned a 1 m "depth" (or a boolean True) into 3698 N, status extrapolated, and clamp gave
    # full force for it; a depth deeper than the gel is thick is an estimator or unit fault: invalid-input, and no
    # force sample (the consumer takes the estimate as lost)
    with Harness(PolyForce, {"calibration": cal_file, "out_of_range": policy}) as h:
        for bad in (1.0, 0.0051, True, 1e300):
            out = h.step(h.t + 0.01, max_depth=bad)
            assert out == {"status": "invalid-input"}, bad
        limit = h.comp.status()["force_limit_n"]
        expected = float(truth(2e-3)) if policy == "clamp" else float(
            truth(2e-3) + (TRUE[1] + 2 * TRUE[2] * 2e-3 + 3 * TRUE[3] * 4e-6) * 3e-3)
        assert limit == pytest.approx(expected, rel=1e-9)
        forces = [h.step(h.t + 0.01, max_depth=d)["force"] for d in np.linspace(0.0, 5e-3, 200)]
        assert max(forces) == pytest.approx(limit, rel=1e-9) and all(0.0 <= f <= limit for f in forces)


def test_depth_limit_must_lie_beyond_the_calibrated_range(cal_file):
    with pytest.raises(ValueError, match=r"depth_limit \(1\.500 mm\) must be deeper than the calibration's deepest "
                                         r"depth \(2\.000 mm"):
        Harness(PolyForce, {"calibration": cal_file, "depth_limit": "1.5mm"}).comp.configure()


def test_a_depth_without_a_usable_stamp_gives_no_force_and_does_not_lock_out_later_frames(cal_file):
    # before: a NaN stamp gave a force stamped NaN at every step, and a frame stamped 99 s ahead of the clock a
    # force stamped in the future
    with Harness(PolyForce, {"calibration": cal_file, "fault_after_invalid": 3}) as h:
        h.t = 1.0
        for stamp in (math.nan, 100.0):
            h.set(max_depth=Sample(1e-3, stamp))
            assert h.comp.step(1.0, h.inputs) is None
            assert h.comp.step(1.01, h.inputs) is None   # the same sample again: counted once
        assert h.comp.status()["bad_stamp"] == 2 and h.comp.invalid_run == 2
        h.set(max_depth=Sample(1e-3, 1.0))   # the next good frame is taken (not locked out by the 100 s stamp)
        out = h.comp.step(1.02, h.inputs)
        assert out["force"].stamp == 1.0 and out["force"].value == pytest.approx(float(truth(1e-3)))
        assert h.comp.invalid_run == 0
        h.set(max_depth=Sample(1e-3, 1.03 + 0.04))   # within max_clock_skew (0.05 s): a normal frame
        assert h.comp.step(1.03, h.inputs)["force"].stamp == pytest.approx(1.07)


def test_a_late_older_frame_neither_enters_the_median_nor_brings_back_an_older_force(cal_file):
    # before: a 1.9 mm frame stamped 0.80 arriving after the 0.91 frame entered the median window, and the next
    # 1.9 mm spike came out as 4.66 N instead of being rejected (1.97 N)
    with Harness(PolyForce, {"calibration": cal_file, "median_window": 3}) as h:
        h.t = 1.0
        outs = []
        for depth, stamp in ((1e-3, 0.90), (1e-3, 0.91), (1.9e-3, 0.80), (1.9e-3, 0.92)):
            h.set(max_depth=Sample(depth, stamp))
            outs.append(h.comp.step(1.0, h.inputs))
        assert outs[2] is None and h.comp.status()["out_of_order"] == 1
        assert outs[3]["force"].value == pytest.approx(float(truth(1e-3))) and outs[3]["force"].stamp == 0.92


# ------------------------------------------------------------------------------------------------ position terms
def _dip_data():
    """F = c1(u) d + 4e5 d^2 + 5e7 d^3 with c1(u) = 1000 (1 + 100 u^2 - 25 u): positive at every node of the 9 x 9
    depth-limit grid (u a multiple of 1/4), negative for 0 < u < 1/4: the force falls with the depth there."""
    rows = []
    for x in np.linspace(-2e-3, 2e-3, 5):
        for y in np.linspace(-4e-3, 4e-3, 5):
            u = x / 2e-3
            for d in np.linspace(0.1e-3, 2e-3, 12):
                rows.append((d, 1000 * (1 + 100 * u * u - 25 * u) * d + 4e5 * d * d + 5e7 * d ** 3, x, y))
    return np.array(rows)


def test_a_position_fit_that_falls_between_the_grid_nodes_is_refused(tmp_path):
    # before: accepted (checked at the 9 x 9 nodes only); at x = 0.25 mm it gave 0 N from 0.1 to 0.5 mm of depth
    a = _dip_data()
    with pytest.raises(CalibrationError, match=r"not monotonic .*at the contact position \(0\.2\d, "):
        ForceCalibration.fit(a[:, 0], a[:, 1], 3, positions=a[:, 2:], position_degree=2)
    # a file with such terms is refused at load too, naming the field
    good = _dip_data()
    good[:, 1] = truth(good[:, 0]) * (1 + 0.1 * good[:, 2] / 2e-3)
    cal = ForceCalibration.fit(good[:, 0], good[:, 1], 3, positions=good[:, 2:], position_degree=2)
    path = cal.save(tmp_path / "dip.force.json")
    doc = json.loads(path.read_text())
    P = np.array(doc["model"]["position"]["coefficients"])
    # add 2000 (100 u^2 - 25 u) to c1 (terms u^1 v^0 and u^2 v^0): c1 < 0 near u = 1/8 only; the centre's curve and
    # every node's are unchanged or still increasing
    P[1][1] += -50000.0
    P[1][3] += 200000.0
    doc["model"]["position"]["coefficients"] = P.tolist()
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match=r"dip\.force\.json: field 'model\.coefficients'.*at the contact position"):
        ForceCalibration.load(path)


# ------------------------------------------------------------------------------------------------ file units
@pytest.mark.parametrize("mutate,field", [
    # the same curve written with depths in mm (coefficients per mm^k): before, accepted, and every real depth (m)
    # fell below its 0.1 "m" range onto the ramp: 1 mm read 0.0015 N instead of 1.97 N
    (lambda m: m.update(depth_range_m=[0.1, 2.0], coefficients=[c * 1e-3 ** k for k, c in enumerate(TRUE)]),
     "model.depth_range_m"),
    # forces in mN: before, accepted, the mapper gave 1000 x the force (1970 N at 1 mm)
    (lambda m: m.update(coefficients=[c * 1000 for c in m["coefficients"]]), "model.coefficients"),
    (lambda m: m.update(units="force in mN, depth in mm"), "model.units"),
])
def test_a_calibration_file_in_other_units_is_refused(cal_file, mutate, field):
    doc = json.loads(open(cal_file).read())
    mutate(doc["model"])
    with open(cal_file, "w") as fh:
        json.dump(doc, fh)
    with pytest.raises(ModelFileError, match=f"u.force.json: field '{field}'"):
        ForceCalibration.load(cal_file)


def test_a_centroid_box_in_mm_is_refused(tmp_path):
    a = _dip_data()
    a[:, 1] = truth(a[:, 0])
    path = ForceCalibration.fit(a[:, 0], a[:, 1], 3, positions=a[:, 2:], position_degree=1).save(tmp_path / "p.json")
    doc = json.loads(path.read_text())
    doc["model"]["position"]["half_extent_m"] = [2.0, 4.0]   # mm in a metre field
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match=r"field 'model\.position\.half_extent_m': expected \[x, y\] in m within"):
        ForceCalibration.load(path)


# ------------------------------------------------------------------------------------------------ calibration tools
FAST = {"cycles": 1, "step": "0.25mm", "max_displacement": "1.5mm", "settle_time": 0.25, "record_time": 0.1,
        "approach_speed": "2mm/s", "move_speed": "5mm/s"}


@pytest.mark.parametrize("backoff", [0.0, "0.02mm"])
def test_a_backoff_that_leaves_the_probe_on_the_gel_is_refused_at_configure(backoff):
    # before: configured, then every run aborted at the tare ("the probe still touches the gel ... increase backoff")
    with pytest.raises(ValueError, match=r"backoff \(0\.0[02]0 mm\) must be more than touch_depth \(0\.030 mm\)"):
        Harness(PressRoutine, dict(FAST, backoff=backoff)).comp.configure()


def test_an_aborted_runs_samples_are_marked_partial_and_a_fit_of_them_refused(tmp_path, capsys):
    # before: the samples CSV of an aborted run looked complete and `--csv` fitted it without a word
    from tests.test_force_calibration import graph

    from teletouch.cli import main

    g = tmp_path / "press.yaml"
    g.write_text(graph())
    out = tmp_path / "sim.force.json"
    own = tmp_path / "routine.csv"
    rc = main(["calibrate", "force", "--graph", str(g), "-o", str(out), "--quiet", "--set", "routine.max_force=4.0",
               "--set", f"routine.samples_csv={own}"])
    assert rc != 0 and not out.exists()
    assert "marked partial" in capsys.readouterr().err
    samples = tmp_path / "sim.samples.csv"
    for path in (samples, own):   # the command's samples and the routine's own samples_csv
        first = path.read_text().splitlines()[0]
        assert first.startswith("# partial: press routine aborted: the press needs") and "of 13 planned steps" in first
        data = read_pairs_csv(path)
        assert data["partial"].startswith("press routine aborted") and 4 <= len(data["depth_m"]) < 13
    fitted = tmp_path / "fit.force.json"
    assert main(["calibrate", "force", "--csv", str(samples), "-o", str(fitted), "--degree", "2"]) != 0
    assert "partial samples (press routine aborted" in capsys.readouterr().err and not fitted.exists()
    assert main(["calibrate", "force", "--csv", str(samples), "-o", str(fitted), "--degree", "2",
                 "--allow-partial"]) == 0
    assert "warning" in capsys.readouterr().err
    assert ForceCalibration.load(fitted).extra["partial"].startswith("press routine aborted")
    assert main(["calibrate", "force", "--graph", str(g), "-o", str(fitted), "--allow-partial"]) == 2
    assert "--allow-partial: only with --csv" in capsys.readouterr().err


def test_the_depth_model_the_calibration_was_made_for_is_checked_when_named(cal_file, tmp_path):
    # before: no way to say which depth model feeds the mapper; the simulated sensor's calibration ran silently
    # behind a real DIGIT's model (the depth models named must exist: a missing one is named as missing)
    src = files("teletouch.plugins.estimators") / "data" / "sim-digit-qvga.model"
    (tmp_path / "models").mkdir()
    for name in ("my-digit.model", "models/unit-test.model"):
        (tmp_path / name).write_bytes(src.read_bytes())
    mine, same = str(tmp_path / "my-digit.model"), str(tmp_path / "models" / "unit-test.model")
    with pytest.raises(ValueError, match=r"depth_model: the calibration .*u\.force\.json was made for 'unit-test', "
                                         r"not for '.*my-digit\.model'"):
        Harness(PolyForce, {"calibration": cal_file, "depth_model": mine}).comp.configure()
    with Harness(PolyForce, {"calibration": cal_file, "depth_model": same}) as h:
        assert h.step(0.1, max_depth=1e-3)["status"] == "ok"
    with Harness(PolyForce, {"depth_model": "sim-digit-qvga"}) as h:   # the packaged pair
        assert h.comp.cal.sensor_model_id == "sim-digit-qvga"


def test_a_contact_area_or_centroid_not_of_the_depth_frame_is_counted_and_said_once(cal_file):
    """poly-force takes contact_area, contact_mask and centroid as the latest values: wired from another node than
    max_depth (or through a bridge that stamps each on arrival), a frame's depth met another frame's area, silently.
    Such an input is counted (status unmatched_inputs) and said once per input, with how far apart the stamps are;
    from one depth node (one step, one stamp) nothing is said."""
    with Harness(PolyForce, {"calibration": cal_file}) as h:
        logs: list[str] = []
        h.comp.ctx.log = logs.append
        h.set(max_depth=Sample(1e-3, 1.0), contact_area=Sample(2e-6, 1.0))
        h.comp.step(1.0, h.inputs)
        assert h.comp.status()["unmatched_inputs"] == 0 and logs == []
        for k in range(3):   # the area a frame behind the depth
            h.set(max_depth=Sample(1e-3, 1.02 + 0.01 * k), contact_area=Sample(2e-6, 1.01 + 0.01 * k))
            out = h.comp.step(1.02 + 0.01 * k, h.inputs)
            assert out["force"].value > 0   # still taken: the latest value, as before
        assert h.comp.status()["unmatched_inputs"] == 3
        assert len(logs) == 1 and "contact_area" in logs[0] and "-10.0 ms" in logs[0] and "max_depth" in logs[0], logs


def test_a_contact_area_that_came_before_its_depth_is_the_one_taken_with_it(cal_file):
    """Wired from two nodes, or over a bridge that delivers each topic on its own, a frame's contact_area can come a
    step before its max_depth: poly-force took the latest area, the next frame's. On a release that next area is 0,
    so a depth of 1 mm met no contact area and read as invalid input. The area of the depth's frame (same stamp) is
    now found among the input's last samples; one older than those, or one that comes after its depth, is still the
    latest value, counted."""
    with Harness(PolyForce, {"calibration": cal_file}) as h:
        h.comp.ctx.log = lambda m: None
        h.set(max_depth=Sample(1e-3, 1.00), contact_area=Sample(2e-6, 1.00))
        assert h.comp.step(1.00, h.inputs)["force"].value > 0
        h.set(contact_area=Sample(2e-6, 1.01))                       # frame 1.01's area, its depth not yet here
        assert h.comp.step(1.01, h.inputs) is None                   # no new depth: no output
        h.set(max_depth=Sample(1e-3, 1.01), contact_area=Sample(0.0, 1.02))   # its depth, and the next area: 0
        out = h.comp.step(1.02, h.inputs)
        assert out["status"].value == "ok" and out["force"].value == pytest.approx(truth(1e-3), rel=0.05)
        assert h.comp.status()["unmatched_inputs"] == 0
        # an area of a frame older than the kept samples: the latest value, counted
        for k in range(PF.RECENT_CONTACT_SAMPLES):
            h.set(contact_area=Sample(0.0, 1.03 + 0.001 * k))
            h.comp.step(1.03 + 0.001 * k, h.inputs)
        h.set(max_depth=Sample(1e-3, 1.02))
        assert h.comp.step(1.05, h.inputs)["status"].value == "invalid-input"   # pressed in, the latest area 0
        assert h.comp.status()["unmatched_inputs"] == 1
        # reactivated: the kept samples are gone with the rest of the run's state
        h.comp.deactivate()
        h.comp.activate()
        assert all(len(q) == 0 for q in h.comp._recent.values())
