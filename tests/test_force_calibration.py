"""The press routine (state machine, abort -> retract -> safe state), the simulated rig and `teletouch calibrate force`.

These graphs close the loop sim-omega7 <-> sim-press-rig without a camera: the routine reads the rig's indentation as
its max depth, so each run takes a few seconds. The full camera pipeline is exercised by
scripts/make_sim_force_calibration.py and benchmarks/force_accuracy.py.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from teletouch import ComponentFault
from teletouch.plugins.estimators.force_calibration import PressRoutine, SimPressRig, fit_samples
from teletouch.plugins.estimators.poly_force import CalibrationError, ForceCalibration, read_pairs_csv, write_pairs_csv
from teletouch.plugins.sensors.gel import Indenter, gel_force
from teletouch.testing import Harness, make_registry, run_yaml

FAST = {"cycles": 1, "step": "0.25mm", "max_displacement": "1.5mm", "settle_time": 0.25, "record_time": 0.1,
        "approach_speed": "2mm/s", "move_speed": "5mm/s"}


def graph(routine: dict | None = None, leader: dict | None = None, rig: dict | None = None,
          duration: float = 60.0, centroid: str = "") -> str:
    r = dict(FAST, **(routine or {}))
    lead = dict({"intent": "none"}, **(leader or {}))
    return f"""
name: press-test
clock: sim
duration: {duration}
nodes:
  - id: leader
    plugin: sim-omega7
    rate: 1000
    params: {json.dumps(lead)}
    inputs: {{force: routine.force, external_force: rig.force}}
  - id: rig
    plugin: sim-press-rig
    rate: 1000
    params: {json.dumps(rig or {})}
    inputs: {{position: leader.position}}
  - id: routine
    plugin: press-routine
    rate: 1000
    params: {json.dumps(r)}
    inputs: {{position: leader.position, max_depth: rig.indentation, reference_force: rig.contact_force,
              abort: leader.button{centroid}}}
"""


@pytest.fixture(scope="module")
def reg():
    return make_registry("teletouch.plugins.devices.sim_omega7", "teletouch.plugins.estimators.force_calibration")


@pytest.fixture(scope="module")
def full_run(reg):
    log = []
    result, rt = run_yaml(graph(routine={"cycles": 2}), reg,
                          taps=[lambda n, t, o: log.append((t, o["force"][2])) if n == "rig" else None])
    return result, rt, log


# ------------------------------------------------------------------------------------------------ the full routine
def test_routine_runs_all_steps_and_stops(full_run):
    result, rt, _ = full_run
    r = rt.component("routine")
    assert result.status == "stopped" and "press routine done: 26 samples in 2 cycle(s)" in result.message
    assert r.state == "done" and r.progress == 1.0
    states = [s for _, s in r.events]
    assert states[:5] == ["move", "approach", "backoff", "tare", "step"]
    assert states.count("retract") == 2 and states[-1] == "done"
    # 0, 0.25 .. 1.5 mm loading, then 1.25 .. 0 unloading, per cycle
    targets = [s["target_displacement_m"] for s in r.samples[:13]]
    np.testing.assert_allclose(targets, [0, .25e-3, .5e-3, .75e-3, 1e-3, 1.25e-3, 1.5e-3,
                                         1.25e-3, 1e-3, .75e-3, .5e-3, .25e-3, 0], atol=1e-12)
    assert [s["phase"] for s in r.samples[:13]] == ["loading"] * 7 + ["unloading"] * 6
    assert {s["cycle"] for s in r.samples} == {0, 1}


def test_routine_records_the_steady_state_device_force(full_run):
    _, rt, _ = full_run
    r = rt.component("routine")
    assert len(r.samples) == 26   # 13 steps in each of the 2 cycles: the checks below are not over an empty list
    for s in r.samples:
        assert abs(s["displacement_m"] - s["target_displacement_m"]) <= r.params.settle_tolerance + 1e-9
        # at rest the command balances the gel: device force == ground-truth gel force
        assert s["force_n"] == pytest.approx(s["gt_force_n"], abs=0.02 + 0.01 * s["gt_force_n"])
        # and the gel model gives that force at the recorded depth
        assert s["force_n"] == pytest.approx(gel_force(s["depth_m"], Indenter.probe()), rel=0.02, abs=0.02)


def test_press_points_across_the_sensor(reg):
    seen = []
    routine = {"cycles": 3, "positions": [[0, 0], ["1mm", "-2mm"]], "max_displacement": "0.5mm"}
    result, rt = run_yaml(graph(routine=routine, centroid=", centroid: rig.indenter_position"), reg,
                          taps=[lambda n, t, o: seen.append((t, o["indenter_position"].copy(), o["indentation"]))
                                if n == "rig" else None])
    assert result.status == "stopped", result.message
    r = rt.component("routine")
    pts = {s["cycle"]: s["press_point_m"] for s in r.samples}
    # the contact centroid (here the rig's true one) is recorded with each step, for --position-degree
    for s in r.samples:
        np.testing.assert_allclose([s["x_m"], s["y_m"]], s["press_point_m"], atol=2e-5)
    assert pts[0] == [0.0, 0.0] and pts[2] == [0.0, 0.0]
    np.testing.assert_allclose(pts[1], [1e-3, -2e-3], atol=1e-12)
    # the probe reached the second point before touching the gel there, and never moved sideways while pressing
    pressing = [(xy, d) for _, xy, d in seen if d > 0]
    assert any(np.allclose(xy, [1e-3, -2e-3], atol=2e-5) for xy, _ in pressing)
    assert all(np.allclose(xy, [0, 0], atol=2e-5) or np.allclose(xy, [1e-3, -2e-3], atol=2e-5)
               for xy, _ in pressing)
    assert [s for _, s in r.events].count("approach") == 3  # a touch search at each point


def test_tare_removes_the_device_offset(reg):
    result, rt = run_yaml(graph(routine={"max_displacement": "1mm", "step": "0.5mm"}, rig={"probe_weight": 0.5}),
                          reg)
    assert result.status == "stopped", result.message
    r = rt.component("routine")
    assert r.tare == pytest.approx(-0.5, abs=0.01)  # holding the probe up against its weight
    for s in r.samples:
        assert s["force_n"] == pytest.approx(s["gt_force_n"], abs=0.02 + 0.01 * s["gt_force_n"])


def test_routine_ends_retracted_with_zero_force(full_run):
    _, rt, log = full_run
    leader = rt.component("leader")
    rig = rt.component("rig")
    assert rig.d == 0.0 and log[-1][1] == 0.0  # probe off the gel
    assert leader.safe and np.all(leader.f_applied == 0)
    assert max(f for _, f in log) < rt.component("routine").params.max_force


def test_fit_of_routine_samples(full_run, tmp_path):
    _, rt, _ = full_run
    r = rt.component("routine")
    cal = fit_samples(r.samples, 3)
    assert cal.r2 > 0.999
    assert cal.hysteresis["max_gap_n"] is not None and abs(cal.hysteresis["max_gap_n"]) < 0.1
    d = np.linspace(0.1e-3, 1.5e-3, 20)
    truth = np.array([gel_force(x, Indenter.probe()) for x in d])
    assert np.max(np.abs(cal.predict(d) - truth)) < 0.05 * truth.max()


# ------------------------------------------------------------------------------------------------ abort paths
def test_abort_over_force_retracts_then_faults(reg):
    log = []
    result, rt = run_yaml(graph(routine={"max_force": 2.0, "max_displacement": "2mm"}), reg,
                          taps=[lambda n, t, o: log.append((t, float(o["indentation"]))) if n == "rig" else None])
    r = rt.component("routine")
    assert result.status == "fault" and "max_force" in result.message and "safe state" in result.message
    assert r.state == "aborted" and "abort-retract" in [s for _, s in r.events]
    assert max(d for _, d in log) > 0.5e-3  # it was pressing
    assert log[-1][1] == 0.0  # and retracted off the gel before stopping
    assert rt.component("leader").safe and np.all(rt.component("leader").f_applied == 0)
    assert len(r.samples) < 2 * len(r.plan)


def test_abort_button(reg):
    result, rt = run_yaml(graph(leader={"button_intervals": [[5.0, 5.5]]}), reg)
    r = rt.component("routine")
    assert result.status == "fault" and "button" in result.message
    t_abort = next(t for t, s in r.events if s == "abort-retract")
    assert 5.0 <= t_abort < 5.01
    assert rt.component("rig").d == 0.0 and rt.component("leader").safe


def test_no_gel_under_the_probe_aborts(reg):
    result, rt = run_yaml(graph(routine={"max_approach": "3mm"}, rig={"surface": -0.02}), reg)
    assert result.status == "fault" and "no contact after 3.0 mm" in result.message
    assert rt.component("leader").safe


def _harness_at_press(**params):
    h = Harness(PressRoutine, dict(FAST, **params))
    h.__enter__()
    pos = np.zeros(3)
    h.step(0.0, position=pos, max_depth=0.0)
    assert h.comp.state == "move"  # to the first press point: here, where it starts
    h.step(0.001, position=pos, max_depth=0.0)
    assert h.comp.state == "approach"
    return h


def test_nan_depth_aborts_and_retracts():
    h = _harness_at_press()
    h.step(0.1, position=np.array([0, 0, -1e-4]), max_depth=math.nan)
    assert h.comp.state == "abort-retract" and "NaN" in h.comp.abort_reason.replace("nan", "NaN")
    out = h.step(0.101, position=np.array([0, 0, -1e-4]), max_depth=math.nan)
    assert out["force"][2] > 0  # pulls the probe back up towards home
    # at home: aborted -> fault, zero force
    with pytest.raises(ComponentFault, match="NaN|nan"):
        h.step(0.2, position=np.zeros(3), max_depth=0.0)
    assert np.all(h.comp.cmd == 0)


def test_lost_position_gives_zero_force_at_once():
    h = _harness_at_press()
    h.step(0.05, position=np.array([0, 0, -1e-5]), max_depth=0.0)
    with pytest.raises(ComponentFault, match="position lost"):
        h.step(0.06, position=np.array([np.nan, 0, 0]), max_depth=0.0)
    assert np.all(h.comp.cmd == 0)


def test_stale_depth_aborts():
    h = _harness_at_press(input_timeout=0.2)
    from teletouch import Sample

    h.set(max_depth=Sample(0.0, 0.0))
    h.t = 0.5
    h.set(position=np.array([0, 0, -1e-4]))
    h.comp.step(0.5, h.inputs)
    assert h.comp.state == "abort-retract" and "no max depth" in h.comp.abort_reason


def test_start_in_contact_refused_and_touch_needs_consecutive_frames():
    h = Harness(PressRoutine, dict(FAST, touch_frames=3))
    h.__enter__()
    with pytest.raises(ComponentFault, match="already pressed"):
        h.step(0.0, position=np.zeros(3), max_depth=0.2e-3)
    assert np.all(h.comp.cmd == 0)
    h = _harness_at_press(touch_frames=3)
    for i, d in enumerate([0.1e-3, 0.0, 0.1e-3, 0.1e-3]):  # a single noisy frame is not a touch
        h.step(0.02 * (i + 1), position=np.array([0, 0, -1e-5 * i]), max_depth=d)
        assert h.comp.state == "approach"
    h.step(0.1, position=np.array([0, 0, -5e-5]), max_depth=0.1e-3)
    assert h.comp.state == "backoff" and h.comp.touch == pytest.approx(5e-5)


def test_missing_inputs_fault_at_start():
    with Harness(PressRoutine, dict(FAST, start_timeout=1.0)) as h:
        h.step(0.0, position=np.zeros(3))
        h.step(0.9, position=np.zeros(3))
        assert h.comp.state == "wait"
        with pytest.raises(ComponentFault, match="no max depth within 1 s"):
            h.step(1.1, position=np.zeros(3))
        assert np.all(h.comp.cmd == 0)


def test_params_checked():
    with pytest.raises(ValueError, match="larger than max_displacement"):
        Harness(PressRoutine, {"step": "3mm", "max_displacement": "2mm"}).comp.configure()


def test_samples_csv_checked_at_configure(tmp_path):
    (tmp_path / "afile").write_text("")
    for bad, why in ((tmp_path / "afile" / "s.csv", "afile is a file, not a folder"),
                     (tmp_path, "is a folder, expected a file name")):
        comp = Harness(PressRoutine, dict(FAST, samples_csv=str(bad))).comp
        with pytest.raises(ValueError, match=f"samples_csv: cannot write .*{why}"):
            comp.configure()
        assert comp.state == "wait" and comp.samples == []  # what the command line reports after a failed start
    Harness(PressRoutine, dict(FAST, samples_csv=str(tmp_path / "new" / "s.csv"))).comp.configure()  # made later


def test_total_points_known_before_configure():
    # the command line's progress bar (on a terminal) asks before the run configures the routine
    assert Harness(PressRoutine, FAST).comp.total_points == 13


# ------------------------------------------------------------------------------------------------ the rig
def test_rig_uses_the_gel_model():
    with Harness(SimPressRig, {"surface": -0.005, "gel_thickness": 0.004}) as h:
        out = h.step(0.0, position=np.array([0.001, -0.002, -0.0062]))
        d = 0.0012
        assert out["indentation"] == pytest.approx(d)
        np.testing.assert_allclose(out["indenter_position"], [0.001, -0.002])
        expected = gel_force(d, Indenter.probe(0.005, 0.010), thickness=0.004)
        assert out["force"][2] == pytest.approx(expected) and out["contact_force"] == pytest.approx(expected)
        out = h.step(0.001, position=np.array([0, 0, 0.0]))
        assert out["indentation"] == 0.0 and np.all(out["force"] == 0)
        with pytest.raises(ComponentFault, match="not finite"):
            h.step(0.002, position=np.array([0, 0, np.nan]))


# ------------------------------------------------------------------------------------------------ command line
def test_cli_csv(tmp_path, capsys):
    from teletouch.cli import main

    csv = tmp_path / "pairs.csv"
    d = np.linspace(0.1e-3, 2e-3, 15)
    f = [gel_force(x, Indenter.probe()) for x in d]
    csv.write_text("depth_m,force_n\n" + "".join(f"{a},{b}\n" for a, b in zip(d, f)))
    out = tmp_path / "cal.force.json"
    assert main(["calibrate", "force", "--csv", str(csv), "-o", str(out), "--sensor-model-id", "unit"]) == 0
    cal = ForceCalibration.load(out)
    assert cal.sensor_model_id == "unit" and cal.r2 > 0.999 and cal.source == "csv:pairs.csv"
    assert (tmp_path / "cal.png").stat().st_size > 10_000
    assert "R^2" in capsys.readouterr().out
    csv.write_text("depth_m,force_n\n0.001,oops\n")
    assert main(["calibrate", "force", "--csv", str(csv), "-o", str(out)]) != 0
    assert "pairs.csv:2: column 'force_n'" in capsys.readouterr().err


def _no_work(*args, **kwargs):
    raise AssertionError("the command should have refused its arguments before any work")


BOTH, GRAPH = ("csv", "graph"), ("graph",)


@pytest.mark.parametrize("mode,extra,message", [(m, e, msg) for modes, e, msg in [
    (BOTH, ["--min-depth", "5parsecs"], "--min-depth: unknown unit 'parsecs'"),
    (BOTH, ["--min-depth", "5N"], "--min-depth: '5N' is in N, expected a quantity in m"),
    (GRAPH, ["--duration", "5parsecs"], "--duration: unknown unit 'parsecs'"),
    (GRAPH, ["--duration", "0s"], "--duration: expected a positive duration"),
    (BOTH, ["-o", "{tmp}/afile/x.json"], "-o: cannot write '{tmp}/afile/x.json': {tmp}/afile is a file, not a folder"),
    (BOTH, ["-o", "{tmp}/outdir"], "-o: cannot write '{tmp}/outdir': is a folder, expected a file name"),
    (BOTH, ["--plot", "{tmp}/afile/p.png"], "--plot: cannot write"),
    (GRAPH, ["--samples", "{tmp}/outdir"], "--samples: cannot write '{tmp}/outdir': is a folder, expected a file name"),
] for m in modes])
def test_cli_arguments_and_outputs_checked_before_the_work(tmp_path, capsys, monkeypatch, mode, extra, message):
    from teletouch.cli import main
    from teletouch.plugins.estimators import force_calibration

    monkeypatch.setattr(force_calibration, "run_press_calibration", _no_work)
    monkeypatch.setattr(force_calibration, "fit_samples", _no_work)
    (tmp_path / "afile").write_text("")
    (tmp_path / "outdir").mkdir()
    src = tmp_path / ("pairs.csv" if mode == "csv" else "press.yaml")
    src.write_text("depth_m,force_n\n0.0001,0.1\n" if mode == "csv" else graph())
    args = [a.format(tmp=tmp_path) for a in extra]
    if "-o" not in args:
        args += ["-o", str(tmp_path / "cal.force.json")]
    assert main(["calibrate", "force", f"--{mode}", str(src), "--quiet", *args]) == 2
    err = capsys.readouterr().err
    assert f"teletouch calibrate force: error: {message.format(tmp=tmp_path)}" in err and "Traceback" not in err


def test_cli_graph_only_options_refused_with_csv(tmp_path, capsys):
    from teletouch.cli import main

    csv = tmp_path / "pairs.csv"
    csv.write_text("depth_m,force_n\n0.0001,0.1\n")
    out = tmp_path / "cal.force.json"
    for extra, names in ((["--duration", "5s"], "--duration"), (["--set", "a.b=1", "--clock", "sim"], "--set, --clock"),
                         (["--samples", str(tmp_path / "s.csv")], "--samples")):
        assert main(["calibrate", "force", "--csv", str(csv), "-o", str(out), *extra]) == 2
        assert f"teletouch calibrate force: error: {names}: only with --graph" in capsys.readouterr().err
    assert not out.exists()


def test_cli_creates_missing_output_directories(tmp_path):
    from teletouch.cli import main

    csv = tmp_path / "pairs.csv"
    d = np.linspace(0.1e-3, 2e-3, 10)
    csv.write_text("depth_m,force_n\n" + "".join(f"{a},{gel_force(a, Indenter.probe())}\n" for a in d))
    out = tmp_path / "new" / "dir" / "cal.force.json"
    assert main(["calibrate", "force", "--csv", str(csv), "-o", str(out), "--plot", str(tmp_path / "p" / "c.png")]) == 0
    assert out.is_file() and (tmp_path / "p" / "c.png").is_file()


def test_cli_graph(tmp_path, capsys):
    from teletouch.cli import main

    g = tmp_path / "press.yaml"
    g.write_text(graph())
    out = tmp_path / "sim.force.json"
    assert main(["calibrate", "force", "--graph", str(g), "-o", str(out), "--quiet"]) == 0
    cal = ForceCalibration.load(out)
    assert cal.r2 > 0.999 and cal.source == "press-routine:press.yaml"
    assert cal.depth_source == "rig.indentation (sim-press-rig)"
    rows = read_pairs_csv(tmp_path / "sim.samples.csv")
    assert len(rows["depth_m"]) == 13 and rows["phase"].count("unloading") == 6
    # an aborting graph writes no calibration and fails
    out2 = tmp_path / "none.force.json"
    rc = main(["calibrate", "force", "--graph", str(g), "-o", str(out2), "--quiet",
               "--set", "routine.max_force=1.0"])
    assert rc != 0 and not out2.exists()
    assert "did not finish" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["calibrate-force-sim.yaml", "calibrate-force.yaml"])
def test_example_graphs_validate(repo_root, name):
    from teletouch.graph import load_graph
    from teletouch.registry import Registry

    spec = load_graph(repo_root / "examples" / name, registry=Registry(autoload=True).load())
    routine = spec.node("routine")
    assert routine.plugin == "press-routine" and routine.inputs["max_depth"].node == "depth"
    assert spec.node("leader").inputs["force"].node == "routine"


# ------------------------------------------------------------------------------------------------ safety audit
def _press(out: dict) -> float:
    return float(out["force"][2]) * -1.0  # press direction is -z (FAST keeps the defaults axis z, direction -1)


def _step_ms(h, t: float, **values):
    """One routine step at t; returns (outputs, fault message or None)."""
    try:
        return h.step(t, **values), None
    except ComponentFault as exc:
        return None, str(exc)


def test_depth_stamped_in_the_future_is_not_fresh_forever():
    # a clock fault stamps a depth frame far ahead, then the camera dies: it must not count as fresh for 100 s
    from teletouch import Sample

    h = _harness_at_press()
    h.set(max_depth=Sample(0.0, 100.0))
    for k in range(1, 61):
        t = 0.01 * k
        h.t = t
        h.set(position=np.array([0, 0, -1e-6 * k]))
        try:
            h.comp.step(t, h.inputs)
        except ComponentFault:
            pass  # retracted (here at once: the probe is still at the start height) -> aborted
        if h.comp.state != "approach":
            break
    assert h.comp.state in ("abort-retract", "aborted") and t <= 0.6
    assert "max depth stamped 99.990 s ahead" in h.comp.abort_reason


def test_frozen_leader_position_gives_zero_force_quickly():
    # the leader's position stops updating mid-approach: the loop must not run on it for input_timeout (0.5 s)
    from teletouch import Sample

    h = _harness_at_press()
    frozen = Sample(np.zeros(3), 0.01)
    fault_t = None
    for k in range(10, 700):
        t = 0.001 * k
        out, fault = _step_ms(h, t, position=frozen, max_depth=0.0)
        if fault:
            fault_t = t
            assert "position" in fault
            break
    assert fault_t is not None and fault_t <= 0.01 + h.comp.params.position_timeout + 0.002
    assert np.all(h.comp.cmd == 0)


def test_abort_never_pushes_further_into_a_stuck_probe():
    # the probe is blocked (hit something hard): the target runs ahead, the loop aborts; the retract must start from
    # where the probe is, never keep pushing towards the deep target the loop failed to reach
    h = _harness_at_press()
    presses_after_abort = []
    for k in range(2, 3000):
        t = 0.001 * k
        out, fault = _step_ms(h, t, position=np.zeros(3), max_depth=0.0)
        if fault:
            break
        if h.comp.state == "abort-retract":
            presses_after_abort.append(_press(out))
    assert presses_after_abort, "the routine never aborted"
    assert max(presses_after_abort) <= 1e-9


def test_nan_depth_at_the_start_times_out_with_a_reason():
    with Harness(PressRoutine, dict(FAST, start_timeout=1.0)) as h:
        h.step(0.0, position=np.zeros(3), max_depth=math.nan)
        assert h.comp.state == "wait" and np.all(h.comp.cmd == 0)
        with pytest.raises(ComponentFault, match="max depth .*nan"):
            for k in range(1, 13):
                h.step(0.1 * k, position=np.zeros(3), max_depth=math.nan)


def _ideal_rig(h, t0: float, t1: float, surface: float = -2e-4, overshoot=None):
    """Drive the routine with a probe that follows its target exactly over a gel whose surface is at z = surface;
    ``overshoot(state)`` adds a press-axis error. Returns (fault message or None, largest indentation)."""
    deepest = 0.0
    k = 0
    while t0 + 0.001 * k < t1:
        t = t0 + 0.001 * k
        k += 1
        target = h.comp.target if h.comp.target is not None else np.zeros(3)
        pos = np.array(target, dtype=float)
        if overshoot is not None:
            pos[2] -= overshoot(h.comp)
        depth = max(0.0, surface - pos[2])
        deepest = max(deepest, depth)
        _, fault = _step_ms(h, t, position=pos, max_depth=depth)
        if fault:
            return fault, deepest
    return None, deepest


def test_probe_deeper_than_planned_aborts():
    # the probe ends up 1 mm past its target (within max_tracking_error, under max_force, depth under its limit)
    h = Harness(PressRoutine, dict(FAST, max_displacement="0.5mm", step="0.25mm"))
    h.__enter__()
    fault, deepest = _ideal_rig(h, 0.0, 8.0, overshoot=lambda c: 1e-3 if c.state == "hold" else 0.0)
    assert fault is not None and "deeper than" in fault
    assert h.comp.abort_reason and "max_overtravel" in h.comp.abort_reason


def test_gel_that_reads_shallow_stops_the_approach_on_force(reg):
    # the depth estimator reads far too shallow (here: it needs 2.9 mm before it calls it contact): the approach
    # meets the gel's resistance and must stop there, not push on until max_force (~2.5 mm into the gel)
    log = []
    result, rt = run_yaml(graph(routine={"touch_depth": "2.9mm", "backoff": "3mm"}), reg,
                          taps=[lambda n, t, o: log.append(float(o["indentation"])) if n == "rig" else None])
    r = rt.component("routine")
    assert result.status == "fault" and "approach_max_force" in result.message
    assert max(log) < 0.8e-3 and log[-1] == 0.0
    assert rt.component("leader").safe and r.samples == []


def test_position_glitch_does_not_hammer_the_handle():
    # one position sample 1.5 mm off (a glitch): the command may not move away from zero by more than
    # max_force_rate * dt in a step (before: +-10 N, a 15.7 N swing within 1 ms); going to zero is always allowed
    h = _harness_at_press()
    prev = h.comp.cmd.copy()
    r = h.comp.params.max_force_rate * 0.001 + 1e-9
    for k in range(2, 200):
        t = 0.001 * k
        z = -1.5e-3 if k == 100 else -2e-3 * t  # follows the approach except for one sample
        out, fault = _step_ms(h, t, position=np.array([0, 0, z]), max_depth=0.0)
        assert fault is None
        f = out["force"]
        assert np.all(f <= np.maximum(prev + r, 0.0)) and np.all(f >= np.minimum(prev - r, 0.0)), (k, prev, f)
        prev = f


def test_out_of_order_depth_frame_is_not_a_new_frame():
    from teletouch import Sample

    h = _harness_at_press(touch_frames=2)
    h.step(0.02, position=np.array([0, 0, -4e-5]), max_depth=Sample(1e-4, 0.02))
    assert h.comp.state == "approach"
    h.step(0.021, position=np.array([0, 0, -4.2e-5]), max_depth=Sample(1e-4, 0.01))  # an older frame, late
    assert h.comp.state == "approach"
    h.step(0.04, position=np.array([0, 0, -8e-5]), max_depth=Sample(1e-4, 0.04))
    assert h.comp.state == "backoff"


@pytest.mark.parametrize("params,message", [
    ({"hold_timeout": 0.2, "settle_time": 0.4}, "hold_timeout .* must be longer than settle_time"),
    ({"touch_depth": "3mm", "max_depth_limit": "3mm"}, "touch_depth .* must be below max_depth_limit"),
    ({"positions": [[0, 0], [1, 2]]}, r"positions\[1\]: .* more than 25 mm"),
    ({"approach_max_force": 10.0, "max_force": 10.0}, "approach_max_force .* must be below max_force"),
])
def test_params_that_cannot_work_refused_at_configure(params, message):
    with pytest.raises(ValueError, match=message):
        Harness(PressRoutine, dict(FAST, **params)).comp.configure()


def test_fit_refuses_a_nan_depth_instead_of_dropping_it_as_no_contact():
    from teletouch.plugins.estimators.poly_force import CalibrationError

    d = np.linspace(0.1e-3, 2e-3, 12)
    samples = [{"depth_m": float(x), "force_n": gel_force(x, Indenter.probe()), "phase": "loading", "cycle": 0}
               for x in d]
    samples[5]["depth_m"] = math.nan
    with pytest.raises(CalibrationError, match=r"sample 5: depth .*nan.* is not finite"):
        fit_samples(samples, 3)


# ------------------------------------------------------------------------------------------------ review regressions
@pytest.mark.parametrize("stamp", [100.0, math.nan])
def test_a_bad_stamped_depth_while_waiting_does_not_lock_out_the_frames_after_it(stamp):
    # one depth frame stamped far ahead (a clock fault) or NaN before the start was taken as the newest frame: no
    # later frame was new, the approach never saw the touch and pushed on (here to the 3 mm depth limit)
    from teletouch import Sample

    h = Harness(PressRoutine, FAST)
    h.__enter__()
    h.step(0.0, position=np.zeros(3), max_depth=Sample(0.0, stamp))
    assert h.comp.state == "wait"
    for k in range(1, 2000):
        target = h.comp.target if h.comp.target is not None else np.zeros(3)
        pos = np.array(target, dtype=float)
        out, fault = _step_ms(h, 0.001 * k, position=pos, max_depth=max(0.0, -2e-4 - pos[2]))
        assert fault is None
        if h.comp.state == "backoff":
            break
    assert h.comp.state == "backoff" and h.comp.touch is not None


def test_a_reactivated_routine_starts_with_no_samples():
    # activate() restarts the press from the wait state: the last run's samples were kept and the new run's were
    # appended to them (the counts, the cycles and the samples CSV mixed two runs)
    h = Harness(PressRoutine, dict(FAST, max_displacement="0.5mm", step="0.25mm"))
    h.__enter__()
    fault, _ = _ideal_rig(h, 0.0, 3.0)
    assert fault is None and h.comp.samples
    h.comp.deactivate()
    h.comp.activate()
    assert h.comp.samples == [] and h.comp.state == "wait" and h.comp.progress == 0.0


def test_missing_centroid_names_the_csv_line(tmp_path):
    # with --position-degree a contact row without its centroid was refused without the file or the line
    rows = [{"depth_m": d, "force_n": 1e3 * d, "x_m": x, "y_m": y}
            for x in (-2e-3, 0.0, 2e-3) for y in (-4e-3, 0.0, 4e-3) for d in np.linspace(1e-4, 2e-3, 6)]
    rows[7]["y_m"] = None
    path = tmp_path / "p.csv"
    write_pairs_csv(path, rows)
    data = read_pairs_csv(path)
    samples = [{"depth_m": d, "force_n": f, "x_m": x, "y_m": y, "line": ln}
               for d, f, x, y, ln in zip(data["depth_m"], data["force_n"], data["x_m"], data["y_m"], data["line"])]
    with pytest.raises(CalibrationError, match=r"p.csv:9: column 'y_m' is empty: position_degree 1 needs"):
        fit_samples(samples, 3, position_degree=1, where=str(path))
    with pytest.raises(CalibrationError, match=r"sample 7 has no contact centroid"):
        fit_samples([dict(s, line=None) for s in samples], 3, position_degree=1)


def test_an_abort_caused_by_a_slow_force_rate_names_max_force_rate(reg):
    """With max_force_rate far too low (0.05 N/s: a typo, or N/min meant) the force command cannot follow the
    controller: the run aborted at the tare saying "the probe still touches the gel ... increase backoff", a setting
    that was right. An abort now says when max_force_rate held the force back in most of the last second's steps; an
    abort for another cause (here over max_force, at the default rate) does not mention it."""
    result, rt = run_yaml(graph(routine={"max_force_rate": 0.05}), reg)
    assert result.status == "fault", result.message
    assert "(max_force_rate, 0.05 N/s, held the force back in 1000 of the last 1000 steps: the probe cannot follow " \
           "its targets; raise it)" in result.message, result.message
    assert rt.component("leader").safe
    result, _ = run_yaml(graph(routine={"max_force": 2.0, "max_displacement": "2mm"}), reg)
    assert result.status == "fault" and "max_force" in result.message and "max_force_rate" not in result.message
