"""The benchmarks and scripts as a user runs them: strict JSON last lines, bad arguments refused at once with a
message naming the argument, and the scripts never writing the packaged files unasked.

The benchmarks run in subprocesses (``python benchmarks/NAME.py``, the documented way: their folder on sys.path);
the scripts in-process with their subprocess call replaced, so nothing is calibrated or written here.
"""

from __future__ import annotations

import io
import os
import json
import math
import subprocess
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from helpers_scripts import SCRIPTS, load_bench, load_file, load_follower_bench

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"


def _strict_last_line(text: str):
    def refuse(c):
        raise ValueError(f"non-strict JSON constant {c}")
    return json.loads(text.strip().splitlines()[-1], parse_constant=refuse)


@pytest.fixture()
def bench_common(monkeypatch):
    return load_bench(monkeypatch, "bench_common.py", "bench_common_under_test")


def _run(args: list[str], timeout: float = 120, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env)


# --- the last line: strict JSON --------------------------------------------------------------------------------------

def test_emit_turns_nan_and_infinity_into_null_and_names_them(bench_common, capsys):
    bench_common.emit({"a": float("nan"), "b": [1.0, np.float64("inf")], "c": np.float32(1.5), "d": np.int64(3),
                       "e": np.bool_(True), "f": {"g": -math.inf}, "h": np.array([0.5, np.nan])})
    out, err = capsys.readouterr()
    got = _strict_last_line(out)
    assert got["a"] is None and got["b"] == [1.0, None] and got["f"]["g"] is None and got["h"] == [0.5, None]
    assert got["c"] == 1.5 and got["d"] == 3 and got["e"] is True
    assert got["non_finite_fields"] == ["a", "b[1]", "f.g", "h[1]"]
    assert "a, b[1], f.g, h[1]" in err


def test_emit_refuses_what_is_not_json(bench_common):
    with pytest.raises(TypeError, match="x.y: object"):
        bench_common.dumps({"x": {"y": object()}})


@pytest.mark.parametrize("path", sorted(p.name for p in BENCH.glob("*.py")
                                        if p.name not in ("bench_common.py", "machine.py")))
def test_every_benchmark_prints_its_result_through_emit(path):
    """json.dumps writes NaN and Infinity (not JSON): a benchmark whose run has no sample for a percentile printed
    them; every result line goes through bench_common.emit."""
    src = (BENCH / path).read_text()
    assert "emit(" in src and "print(json.dumps" not in src


def test_a_quick_benchmark_ends_with_one_strict_json_object():
    r = _run([str(BENCH / "sim_digit_realism.py"), "--quick"], timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    got = _strict_last_line(r.stdout)
    assert got["benchmark"] == "sim_digit_realism" and 0.0 < got["median_corr"] <= 1.0 and got["presses"] > 0


# --- bad arguments: refused at once, non-zero, the argument named ----------------------------------------------------

@pytest.mark.parametrize("args, words", [
    (["leader_loop.py", "--rates", "abc"], ["--rates", "'abc'"]),
    (["leader_loop.py", "--quick", "--rates", "1000,0"], ["--rates", "above 0 Hz"]),
    (["leader_loop.py", "--quick", "--duration", "-1"], ["--duration", "> 0"]),
    (["leader_loop.py", "--quick", "--realtime-priority", "120"], ["--realtime-priority", "1-99"]),
    (["sim_digit_realism.py", "--quick", "--radius", "3"], ["--radius", "3mm"]),
    (["force_accuracy.py", "--quick", "--presses", "0"], ["--presses", ">= 1"]),
    (["force_accuracy.py", "--quick", "--calibration", "no-such-calibration"], ["--calibration", "packaged"]),
    (["teleop_loop.py", "--quick", "--repeat", "0"], ["--repeat", ">= 1"]),
    (["depth_speed.py", "--quick", "--device", "no-such-device"], ["--device: expected cpu, cuda", "no-such-device"]),
    (["stability_sweep.py", "--quick", "--out", "/no/such/folder/sweep.json"], ["--out", "does not exist"]),
    # a folder passed the check and the sweep ran, to die writing its result
    (["stability_sweep.py", "--quick", "--out", "benchmarks"], ["--out benchmarks", "is a folder"]),
])
def test_bad_arguments_are_refused_before_any_measurement(args, words):
    r = _run([str(BENCH / args[0]), *args[1:]])
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr and r.stdout == ""
    for w in words:
        assert w in r.stderr, (w, r.stderr)


def test_a_missing_data_folder_is_named(tmp_path):
    r = _run([str(BENCH / "sim_digit_realism.py"), "--data", str(tmp_path / "nowhere")])
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert str(tmp_path / "nowhere" / "digit-presses-vga") in r.stderr and "TELETOUCH_SHARED_DATA" in r.stderr


def test_follower_latency_parameters_are_valid_for_every_driver():
    """The benchmark crashed at its first Dynamixel case: max_opening 80 mm is outside the driver's calibrated
    0-75 mm. Every driver must accept the parameters it is given (checked in a subprocess: importing the benchmark
    sets ROS environment variables)."""
    code = f"""
import sys
sys.path.insert(0, {str(BENCH)!r})
import follower_latency as f
from teletouch.plugins.devices.canopen_gripper import CanopenGripper
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper
from teletouch.plugins.devices.pal_gripper import PalGripper
from teletouch.plugins.devices.sim_gripper import SimGripper
SimGripper.Params(**dict(f.FAST, object_width=None, bandwidth=1e6))
for baud in (57600, 1000000):
    DynamixelGripper.Params(**dict(f.FAST, port="/dev/null", baudrate=baud))
CanopenGripper.Params(**dict(f.FAST, interface="virtual", channel="x", node_id=4))
PalGripper.Params(**dict(f.FAST, domain_id=f.DOMAIN, time_from_start=0.001, connect_timeout=10.0))
print("ok")
"""
    r = _run(["-c", code])
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]


# --- the scripts: never the packaged files unasked; bad arguments refused before the work ----------------------------

@pytest.fixture()
def force_script(monkeypatch):
    mod = load_file(SCRIPTS / "make_sim_force_calibration.py", "make_sim_force_calibration_under_test")
    calls: list[list[str]] = []

    def fake_call(cmd, *a, **kw):
        calls.append(list(cmd))
        return 0

    monkeypatch.setattr(mod.subprocess, "call", fake_call)

    def run(*argv: str) -> int:
        monkeypatch.setattr(sys, "argv", ["make_sim_force_calibration.py", *argv])
        with redirect_stdout(io.StringIO()):
            return mod.main()
    return mod, run, calls


def _opt(cmd: list[str], name: str) -> str:
    return cmd[cmd.index(name) + 1]


def test_force_script_with_output_elsewhere_keeps_the_docs_plot(force_script, tmp_path):
    """-o /tmp/x.force.json wrote the plot over docs/force-calibration-sim.png (the --plot default)."""
    mod, run, calls = force_script
    assert run("--depth-source", "gt", "--quick", "-o", str(tmp_path / "x.force.json")) == 0
    (cmd,) = calls
    assert _opt(cmd, "-o") == str(tmp_path / "x.force.json")
    assert _opt(cmd, "--plot") == str(tmp_path / "x.force.png")


def test_force_script_quick_refuses_the_packaged_output(force_script, capsys):
    """--quick alone replaced the packaged calibration and the docs' plot with a smoke test."""
    mod, run, calls = force_script
    with pytest.raises(SystemExit) as e:
        run("--depth-source", "gt", "--quick")
    assert e.value.code == 2 and calls == []
    assert "-o" in capsys.readouterr().err


def test_force_script_relative_output_is_the_callers(force_script, tmp_path, monkeypatch):
    """The calibration runs with cwd=the repository: a relative -o landed there, not where the user was."""
    mod, run, calls = force_script
    monkeypatch.chdir(tmp_path)
    assert run("--depth-source", "gt", "--quick", "-o", "rel.force.json") == 0
    assert _opt(calls[0], "-o") == str(tmp_path / "rel.force.json")


def test_force_script_bad_grid_is_an_argument_error(force_script, capsys):
    mod, run, calls = force_script
    with pytest.raises(SystemExit) as e:
        run("--depth-source", "gt", "--grid", "5by5", "-o", "/tmp/unused.force.json")
    assert e.value.code == 2 and calls == [] and "--grid" in capsys.readouterr().err


def test_depth_script_refuses_zero_presses_before_rendering(monkeypatch, tmp_path, capsys):
    """--presses 0 died in the renderer with a ZeroDivisionError."""
    mod = load_file(SCRIPTS / "make_sim_depth_model.py", "make_sim_depth_model_under_test")
    monkeypatch.setattr(sys, "argv", ["make_sim_depth_model.py", "--presses", "0", "--keep", str(tmp_path / "p"),
                                      "-o", str(tmp_path / "m.model")])
    with pytest.raises(SystemExit) as e:
        mod.main()
    assert e.value.code == 2 and "--presses" in capsys.readouterr().err
    assert not (tmp_path / "p").exists() and not (tmp_path / "m.model").exists()


# --- SCHED_FIFO: a run labelled with a realtime priority says whether it got it ---------------------------------------

def test_runtime_benchmark_says_when_sched_fifo_was_refused(monkeypatch):
    """Without CAP_SYS_NICE (any normal user) the runtime logs the refusal and runs on with normal scheduling; the
    benchmarks silence that log, so 'wall_clock_jitter_sched_fifo' reported normal scheduling as SCHED_FIFO."""
    import os

    def refuse(*a, **kw):
        raise PermissionError(1, "Operation not permitted")

    mod = load_bench(monkeypatch, "runtime.py", "runtime_benchmark_under_test")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    res = mod.jitter(0.3, 1.0, priority=50)
    assert res["realtime_priority"] == 50 and res["sched_fifo_applied"] is False
    assert "not permitted" in res["sched_fifo_refused"]
    plain = mod.jitter(0.3, 1.0, priority=0)
    assert plain["sched_fifo_applied"] is False and plain["sched_fifo_refused"] is None


# --- teleop_loop: the wall-clock runs measure, and a run that faults is not reported as a measurement --------------

@pytest.fixture()
def teleop_bench(monkeypatch):
    return load_bench(monkeypatch, "teleop_loop.py", "teleop_loop_under_test")


def test_teleop_wall_run_measures_the_frame_to_force_latency(teleop_bench):
    """The tap read the controller's `last_stamp`, which position-force no longer has: every wall-clock run faulted
    in its first controller step, and the benchmark printed nulls with exit status 0."""
    r = teleop_bench.wall_timing("image", 1.5)
    assert r["status"] == "ok", r.get("message")
    assert r["latency_samples"] >= 30
    assert 0.0 < r["frame_to_leader_force_p50_ms"] < 1000.0 and math.isfinite(r["controller_jitter_p99_ms"])
    # the pick-up (estimate -> controller step that used it) is part of the frame's latency
    assert 0.0 <= r["estimate_to_leader_force_p50_ms"] <= r["frame_to_leader_force_p50_ms"]
    # 1.5 s at 60 Hz: under 100 frames, so no p99 (it would be the largest), and the counts say so
    assert r["latency_samples"] < 100 and math.isnan(r["frame_to_leader_force_p99_ms"])
    assert r["new_frames"] < 100 and math.isnan(r["new_frame_to_leader_force_p99_ms"])
    assert not teleop_bench.meets_targets(r)


def test_a_percentile_needs_the_samples_to_be_one(bench_common):
    """teleop_loop's --quick runs have ~55 new frames: their 'p99' was the largest of them."""
    assert math.isnan(bench_common.percentile_ms(np.arange(99) * 1e-3, 99))
    assert bench_common.percentile_ms(np.arange(100) * 1e-3, 99) == pytest.approx(98.01)
    assert math.isnan(bench_common.percentile_ms(np.arange(9) * 1e-3, 90))
    assert bench_common.percentile_ms([0.001, 0.003], 50) == pytest.approx(2.0)
    assert math.isnan(bench_common.percentile_ms([], 50)) and math.isnan(bench_common.percentile_ms([0.001], 50))


def test_teleop_a_faulted_wall_run_fails_the_benchmark(teleop_bench, monkeypatch, capsys):
    """A run that ends in a fault has no figures: the benchmark says which and why, and exits non-zero (its JSON
    still comes, naming the run)."""
    keys = {k: math.nan for k in teleop_bench.KEYS}
    faulted = dict(keys, status="fault", message="node 'controller' exception: boom", machine={})
    monkeypatch.setattr(teleop_bench, "step_costs", lambda n: {"x": 1.0})
    monkeypatch.setattr(teleop_bench, "sim_speed", lambda sensor, dur, noise=0.0: {
        "sensor": sensor, "noise": noise, "status": "ok", "message": "ran 3 s", "realtime_factor": 1.0,
        "realtime_factor_steady": 1.0, "realtime_factor_steady_cpu": 1.0, "wall_share_per_sim_s": {}})
    monkeypatch.setattr(teleop_bench, "sim_chain_rounds", lambda chains, dur, rounds: {
        name: {"sensor": sensor, "noise": noise, "status": "ok", "message": "ran 3 s", "realtime_factor_steady": 1.0,
               "per_round": {0: 1.0}} for name, (sensor, noise) in chains.items()})
    monkeypatch.setattr(teleop_bench, "wall_timing", lambda *a, **k: dict(faulted))
    monkeypatch.setattr(teleop_bench, "wall_controller_only", lambda d: {"controller_jitter_p99_ms": 0.1})
    monkeypatch.setattr(sys, "argv", ["teleop_loop.py", "--quick", "--wall-configs", "plain"])
    assert teleop_bench.main() != 0
    out, err = capsys.readouterr()
    got = _strict_last_line(out)
    assert got["faulted_runs"] == [{"config": "plain", "run": 0, "status": "fault",
                                    "message": "node 'controller' exception: boom"}]
    assert "plain" in err and "boom" in err


# --- an optional part missing: the other measurements still come, in one JSON line ---------------------------------

@pytest.fixture()
def without_ros2(tmp_path):
    """The environment of an install without teletouch[ros2]: `import rclpy` fails as it does there (a stand-in first
    on the path; the child processes inherit it)."""
    pkg = tmp_path / "no-ros2" / "rclpy"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(pkg.parent), os.environ.get("PYTHONPATH"))
                                                        if p))


def test_follower_latency_without_ros2_reports_the_other_transports(without_ros2):
    """The PAL case's emulator could not start without rclpy: the benchmark died with a traceback after measuring
    the other transports, and printed no result."""
    r = _run([str(BENCH / "follower_latency.py"), "--quick"], env=without_ros2, timeout=180)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-3000:]
    got = _strict_last_line(r.stdout)
    pal = got["results"]["pal-ros2-loopback"]
    assert "rclpy" in pal["skipped"] and "teletouch[ros2]" in pal["skipped"]
    assert got["results"]["dynamixel-1000000"]["round_trips"] > 0 and got["results"]["canopen-virtual"]["round_trips"]
    assert got["round_trip_p50_ratio_to_dynamixel_1mbaud"]["pal-ros2-loopback"] is None
    assert got["round_trip_p50_ratio_to_dynamixel_1mbaud"]["dynamixel-1000000"] == 1.0


# --- a ratio compares the two side by side: interleaved in rounds over the same inputs ------------------------------

def test_leader_loop_step_ratio_interleaves_the_two_drivers(monkeypatch, tmp_path):
    """omega7_vs_sim_step_ratio timed every omega7 step, then every sim-omega7 step: a burst of load on the shared
    machine during either block moved the ratio. The two now alternate in rounds."""
    mod = load_bench(monkeypatch, "leader_loop.py", "leader_loop_under_test")
    from teletouch.plugins.devices.omega7 import Omega7
    from teletouch.plugins.devices.sim_omega7 import SimOmega7

    order: list[str] = []
    for cls in (Omega7, SimOmega7):
        def spy(self, t, inputs, _step=cls.step, _name=cls.name):
            order.append(_name)
            return _step(self, t, inputs)
        monkeypatch.setattr(cls, "step", spy)
    mod.build(tmp_path)
    out = mod.driver_step(tmp_path, 400)
    switches = sum(a != b for a, b in zip(order, order[1:]))
    assert order.count("omega7") == order.count("sim-omega7") >= 400 and switches >= 9, switches
    assert out["omega7_step_us"] > 0 and out["omega7_vs_sim_step_ratio"] > 0


def test_a_missing_data_folder_is_a_usage_error(tmp_path):
    """--data naming no folder exited 1 (bench_common.data_folder's sys.exit), not 2 as other bad arguments do."""
    r = _run([str(BENCH / "sim_digit_realism.py"), "--data", str(tmp_path / "nowhere")])
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert r.stdout == "" and "--data" in r.stderr and "TELETOUCH_SHARED_DATA" in r.stderr
    assert str(tmp_path / "nowhere" / "digit-presses-vga") in r.stderr


def test_sensor_speed_ratios_interleave_the_sim_digit_cases(monkeypatch, capsys):
    """speedup_radial_vs_generic and speedup_stride2_vs_stride1 divided the frame rates of cases run one after the
    other: load on the shared machine during either block moved the ratio. The cases now alternate in rounds."""
    mod = load_bench(monkeypatch, "sensor_speed.py", "sensor_speed_under_test")
    from teletouch.plugins.sensors.sim_digit import SimDigit

    order: list[int] = []

    def spy(self, t, inputs, _step=SimDigit.step):
        order.append(id(self))
        return _step(self, t, inputs)
    monkeypatch.setattr(SimDigit, "step", spy)
    assert mod.main(["--quick"]) == 0
    got = _strict_last_line(capsys.readouterr().out)
    switches = sum(a != b for a, b in zip(order, order[1:]))
    assert len(set(order)) == 7 and switches >= 9 * 7, switches
    assert got["sim_rounds"] == 10 and got["speedup_radial_vs_generic"] > 0 and got["speedup_stride2_vs_stride1"] > 0


@pytest.fixture()
def runtime_bench(monkeypatch):
    return load_bench(monkeypatch, "runtime.py", "runtime_bench_under_test")


def test_runtime_jitter_says_when_its_run_faulted(runtime_bench, monkeypatch):
    """The jitter run's status was not looked at: a run whose burn node faulted reported its figures as a
    measurement."""
    def boom(self, t, inputs):
        raise RuntimeError("boom")
    monkeypatch.setattr(runtime_bench.Burn, "step", boom)
    res = runtime_bench.jitter(0.3, 1.0)
    assert res["status"] == "fault" and "boom" in res["message"]


def test_runtime_isolation_ratio_alternates_and_a_faulted_run_fails(runtime_bench, monkeypatch, capsys):
    """isolation_p99_ratio_inline_over_isolated divided the p99 of a whole inline run by that of a whole isolated
    run after it; and a run that faulted was not named and the exit status was 0."""
    calls: list[bool] = []

    def fake_run(duration, burn_ms, priority=0, python_burn=False, isolate=False):
        if python_burn:
            calls.append(isolate)
        bad = python_burn and isolate and calls.count(True) == 2
        return ({"burn": "x", "status": "fault" if bad else "ok", "message": "node 'burn' exception: boom" if bad
                 else "ran", "steps": 10, "realtime_priority": priority, "sched_fifo_applied": False,
                 "sched_fifo_refused": None}, np.full(200, 0.2 if isolate else 0.6))
    monkeypatch.setattr(runtime_bench, "_jitter_run", fake_run)
    monkeypatch.setattr(runtime_bench, "overhead", lambda n: {"status": "ok", "message": "", "per_step_us": 1.0})
    monkeypatch.setattr(runtime_bench, "sim_speed", lambda d: {"status": "ok", "message": "", "realtime_factor": 99.0})
    assert runtime_bench.main(["--quick"]) == 1
    out, err = capsys.readouterr()
    got = _strict_last_line(out)
    assert calls == [False, True, True, False, False, True, True, False]
    assert got["isolation_rounds"] == 4 and got["isolation_p99_ratio_inline_over_isolated"] == pytest.approx(3.0)
    assert got["faulted_runs"] == [{"section": "wall_clock_jitter_python_burn_isolated", "run": 1,
                                    "status": "fault", "message": "node 'burn' exception: boom"}]
    assert "python_burn_isolated run 1" in err and "boom" in err


@pytest.fixture()
def sweep_bench(monkeypatch):
    return load_bench(monkeypatch, "stability_sweep.py", "stability_sweep_under_test")


def test_stability_run_that_faults_is_not_judged(sweep_bench, monkeypatch):
    """A faulted run has no steady contact: its NaN peak-to-peak read as 'does not oscillate'."""
    build = sweep_bench.build_runtime

    def boom(t, inputs):
        raise RuntimeError("boom")

    def faulting(doc):
        rt = build(doc)
        next(n for n in rt.nodes if n.id == "controller").step = boom   # the runtime's node calls this
        return rt
    monkeypatch.setattr(sweep_bench, "build_runtime", faulting)
    r = sweep_bench.run_one(1.0, 0.41e6, "off", "ideal", 2.0)
    assert r["status"] == "fault" and "boom" in r["message"] and r["oscillates"] is None


def test_stability_sweep_names_a_faulted_run_and_fails(sweep_bench, monkeypatch, capsys):
    """The sweep never looked at a run's status: a faulted run counted as removing the oscillation, was not named,
    and the exit status was 0."""
    def fake(k, e, mode, sensor, duration):
        bad = mode == "default" and k == 4.0 and e == 1.0e6
        return {"force_scale": k, "gel_modulus_pa": e, "mode": mode, "p2p_leader_force_n": 0.1,
                "p2p_contact_force_n": math.nan if bad else (0.5 if mode == "off" else 0.05),
                "oscillates": None if bad else mode == "off", "status": "fault" if bad else "ok",
                "message": "node 'controller' exception: boom" if bad else "ran 5 s"}
    monkeypatch.setattr(sweep_bench, "run_one", fake)
    assert sweep_bench.main(["--quick"]) == 1
    out, err = capsys.readouterr()
    got = _strict_last_line(out)
    assert got["faulted_runs"] == [{"force_scale": 4.0, "gel_modulus_pa": 1.0e6, "mode": "default",
                                    "status": "fault", "message": "node 'controller' exception: boom"}]
    assert got["removed_by"]["default"] == 3 and got["removed_by"]["tdpa-force"] == 4
    assert "default" in err and "boom" in err


def test_follower_round_trips_interleave_the_transports(monkeypatch):
    """round_trip_p50_ratio_to_dynamixel_1mbaud divided the round trips of one driver, timed in a block of its own,
    by those of another timed later. The Dynamixel and CANopen round trips now alternate in rounds."""
    mod = load_follower_bench(monkeypatch, "follower_latency_under_test")
    from teletouch.plugins.devices.canopen_gripper import CanopenGripper
    from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper

    order: list[int] = []
    for cls in (DynamixelGripper, CanopenGripper):
        def spy(self, target, _w=cls._hw_write):
            order.append(id(self))
            return _w(self, target)
        monkeypatch.setattr(cls, "_hw_write", spy)
    specs = mod.transport_specs("bench-t")   # the benchmark's own cases (without PAL: no domain)
    assert list(specs) == ["dynamixel-57600", "dynamixel-1000000", "canopen-virtual"]
    res = mod.side_by_side(specs, 40, 0.05)
    # the round trips' commands (then the update-rate runs', one block each): 2 switches a round, 10 rounds
    switches = sum(a != b for a, b in zip(order, order[1:]))
    assert len(set(order)) == 3 and switches >= 20, switches
    assert all(r["round_trips"] == 40 and r["rounds"] == 10 for r in res.values()), res
