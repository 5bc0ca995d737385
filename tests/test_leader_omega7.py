"""omega7 against a stand-in libdhd built from C (tests/fakes/dhd_standin.c) with the vendor's names and signatures:
the ctypes path that runs against the hardware is the path under test."""

from __future__ import annotations

import ctypes
import math
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from teletouch import ComponentFault, HardwareError
from teletouch.errors import GraphValidationError
from teletouch.plugins.devices import dhd
from teletouch.plugins.devices.omega7 import Omega7, teletouch_discover_devices
from teletouch.testing import Harness, load_text, make_registry, run_yaml

SRC = Path(__file__).parent / "fakes" / "dhd_standin.c"


def build_standin(folder: Path) -> Path:
    """Compile the stand-in into folder/libdhd.so (the SDK's library name)."""
    gcc = shutil.which("gcc") or shutil.which("cc")
    assert gcc, "a C compiler (gcc) is needed to build the libdhd stand-in"
    out = folder / "libdhd.so"
    subprocess.run([gcc, "-shared", "-fPIC", "-O2", "-Wall", "-o", str(out), str(SRC), "-lm"], check=True,
                   capture_output=True, text=True)
    return out


@pytest.fixture(scope="module")
def sdk_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fdsdk")
    (d / "lib").mkdir()
    build_standin(d / "lib")
    return d


class StandIn:
    """The stand-in's test controls (same library handle as the driver's: dlopen returns one copy)."""

    def __init__(self, path: Path):
        self.lib = ctypes.CDLL(str(path))
        self.lib.standin_set_rest.argtypes = [ctypes.c_double] * 4
        self.lib.standin_set_com_freq.argtypes = [ctypes.c_double]
        self.lib.standin_get_writes.restype = ctypes.c_long
        self.lib.standin_reset()

    def forces(self) -> tuple[list[float], list[float]]:
        a, c = (ctypes.c_double * 4)(), (ctypes.c_double * 4)()
        self.lib.standin_get_forces(a, c)
        return list(a), list(c)

    def flags(self) -> dict[str, bool]:
        f = (ctypes.c_int * 4)()
        self.lib.standin_get_flags(f)
        return dict(zip(("open", "force_enabled", "brakes", "gravity"), map(bool, f)))

    def limits(self) -> tuple[float, float]:
        lim = (ctypes.c_double * 2)()
        self.lib.standin_get_limits(lim)
        return lim[0], lim[1]

    def __getattr__(self, name):
        return getattr(self.lib, "standin_" + name)


@pytest.fixture
def standin(sdk_dir, monkeypatch) -> StandIn:
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    s = StandIn(sdk_dir / "lib" / "libdhd.so")
    yield s
    s.lib.standin_reset()


def harness(sdk_dir, **params) -> Harness:
    return Harness(Omega7, {"sdk_path": str(sdk_dir), **params})


def wait_and_step(h: Harness, seconds: float = 0.03, **inputs):
    time.sleep(seconds)
    return h.step(h.t + seconds, **inputs)


# ------------------------------------------------------------------------------------------------ loading
def test_missing_sdk_says_sdk_and_how_to_fix(tmp_path, monkeypatch):
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    with pytest.raises(dhd.SdkNotFoundError) as ei:
        dhd.load(tmp_path)
    msg = str(ei.value)
    assert "SDK not found" in msg and str(tmp_path) in msg and "FORCEDIM_SDK" in msg and "sdk_path" in msg
    assert isinstance(ei.value, HardwareError)
    h = Harness(Omega7, {"sdk_path": str(tmp_path)})
    with pytest.raises(dhd.SdkNotFoundError):
        h.comp.configure()
    h.comp.close()  # after a failed configure: must not raise


def test_sdk_found_through_forcedim_sdk_env(sdk_dir, standin, monkeypatch):
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir))
    lib = dhd.load(None)
    assert Path(lib.path) == sdk_dir / "lib" / "libdhd.so"
    assert lib.sdk_version() == "3.17.0"
    assert lib.device_count() == 1
    found = teletouch_discover_devices()
    assert found and found[0]["kind"] == "omega7" and found[0]["details"]["params"] == {"index": 0}
    standin.set_present(0)
    assert teletouch_discover_devices() == []
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir / "nowhere"))
    monkeypatch.setattr(dhd.ctypes.util, "find_library", lambda name: None)
    assert teletouch_discover_devices() == []


def test_a_library_without_the_dhd_calls_is_refused(tmp_path):
    src = tmp_path / "other.c"
    src.write_text("int dhdOpen(void) { return 0; }\n")
    so = tmp_path / "libdhd.so"
    subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(so), str(src)], check=True)
    with pytest.raises(dhd.SdkNotFoundError, match="not a usable libdhd: missing .*dhdSetForceAndGripperForce"):
        dhd.load(so)


def test_missing_device_says_device_and_what_to_check(sdk_dir, standin):
    standin.set_present(0)
    h = harness(sdk_dir)
    with pytest.raises(dhd.DeviceNotFoundError) as ei:
        h.comp.configure()
    msg = str(ei.value)
    assert "libdhd loaded" in msg and "no Force Dimension device" in msg and "USB" in msg and "udev" in msg
    assert "devices seen by the SDK: 0" in msg
    h.comp.close()


def test_open_by_serial_and_wrong_serial(sdk_dir, standin):
    with harness(sdk_dir, serial=12345):
        assert standin.flags()["open"]
    with pytest.raises(dhd.DeviceNotFoundError, match="serial number 999"):
        harness(sdk_dir, serial=999).comp.configure()


def test_other_device_types_are_refused(sdk_dir, standin):
    standin.set_system_type(33)  # omega.3: no gripper
    h = harness(sdk_dir)
    with pytest.raises(dhd.DhdError, match="omega.3, not an omega.7"):
        h.comp.configure()
    h.comp.close()


# ------------------------------------------------------------------------------------------------ running
def test_configure_sets_sdk_limits_and_force_only_while_active(sdk_dir, standin):
    h = harness(sdk_dir, max_gripper_force=3.0, max_force="6 N")
    h.comp.configure()
    assert standin.limits() == (6.0, 3.0)
    fl = standin.flags()
    assert fl["open"] and fl["gravity"] and fl["brakes"] and not fl["force_enabled"]
    h.comp.activate()
    fl = standin.flags()
    assert fl["force_enabled"] and not fl["brakes"]
    h.step(0.001, gripper_force=2.0)
    assert standin.forces()[0][3] == pytest.approx(2.0)
    h.comp.deactivate()
    fl = standin.flags()
    assert not fl["force_enabled"] and fl["brakes"]
    assert standin.forces()[0] == [0.0, 0.0, 0.0, 0.0]
    h.comp.close()
    assert not standin.flags()["open"]


def test_read_and_write_through_the_sdk(sdk_dir, standin):
    standin.set_rest(0.015, 0.01, -0.02, 0.03)
    standin.set_button(0, 1)
    with harness(sdk_dir) as h:
        out = h.step(0.0)
        assert out["gripper_opening"] == pytest.approx(0.015)
        np.testing.assert_allclose(out["position"], [0.01, -0.02, 0.03])
        assert out["button"] is True
        out = wait_and_step(h, 0.05, gripper_force=2.0, force=np.array([0.0, 0.0, 1.0]))
        out = wait_and_step(h, 0.05, gripper_force=2.0, force=np.array([0.0, 0.0, 1.0]))
        applied, commanded = standin.forces()
        assert applied == pytest.approx([0.0, 0.0, 1.0, 2.0])
        # the stand-in's gripper spring (400 N/m) opens under +2 N: positive pushes the fingers apart
        assert out["gripper_opening"] == pytest.approx(0.015 + 2.0 / 400.0, abs=2e-4)
        assert out["position"][2] == pytest.approx(0.03 + 1.0 / 500.0, abs=2e-4)
        standin.set_button(0, 0)
        assert h.step(h.t + 0.001)["button"] is False


@pytest.mark.parametrize("system_type", [dhd.OMEGA7_RIGHT, dhd.OMEGA7_LEFT])
def test_left_and_right_units_give_the_same_sign_convention(sdk_dir, standin, system_type):
    standin.set_system_type(system_type)
    with harness(sdk_dir) as h:
        assert h.comp.status()["left_handed"] == (system_type == dhd.OMEGA7_LEFT)
        h.step(0.0)
        time.sleep(0.002)
        out = h.step(0.002, gripper_force=3.0)
        time.sleep(0.002)
        out = h.step(0.004, gripper_force=3.0)
        assert out["gripper_velocity"] > 0  # opening, whatever the hand
        out = wait_and_step(h, 0.05, gripper_force=3.0)
        assert out["gripper_opening"] == pytest.approx(0.015 + 3.0 / 400.0, abs=2e-4)
        # what went to the SDK is mirrored on the left unit
        assert standin.forces()[1][3] == pytest.approx(3.0 if system_type == dhd.OMEGA7_RIGHT else -3.0)


def test_forces_are_clamped_before_the_sdk(sdk_dir, standin):
    with harness(sdk_dir, max_gripper_force=2.5, max_force=4.0) as h:
        h.step(0.0, gripper_force=100.0, force=np.array([0.0, 30.0, 40.0]))
        applied, commanded = standin.forces()
        assert commanded[3] == 2.5
        assert commanded[:3] == pytest.approx([0.0, 2.4, 3.2])
        h.step(0.001, gripper_force=-100.0)
        assert standin.forces()[1][3] == -2.5
        assert h.comp.status()["clamped"] == 4  # 2 per step: the force sample is still fresh in step 2


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_command_zeroes_the_force_brakes_and_faults(sdk_dir, standin, bad):
    with harness(sdk_dir) as h:
        h.step(0.0, gripper_force=2.0)
        assert standin.forces()[0][3] == 2.0
        with pytest.raises(ComponentFault, match="not finite"):
            h.step(0.001, gripper_force=bad)
        assert standin.forces()[0] == [0.0, 0.0, 0.0, 0.0]
        assert standin.flags()["brakes"]
        # latched until re-activated
        h.step(0.002, gripper_force=1.0)
        assert standin.forces()[1][3] == 0.0


def test_timeguard_is_counted_not_an_error(sdk_dir, standin):
    standin.set_timeguard_every(3)
    with harness(sdk_dir) as h:
        for i in range(9):
            h.step(i * 1e-3, gripper_force=1.0)
        assert h.comp.status()["timeguards"] == 3


def test_motor_saturation_is_counted(sdk_dir, standin):
    with harness(sdk_dir) as h:
        h.comp.dhd.set_max_gripper_force(1.0)  # the SDK limit below the driver's: the SDK reports saturation
        h.step(0.0, gripper_force=2.0)
        assert h.comp.status()["saturated"] == 1


def test_sdk_error_codes_are_reported_with_the_sdk_message(sdk_dir, standin):
    with harness(sdk_dir, button_index=9) as h:  # the stand-in has 4 buttons: the SDK answers -1
        with pytest.raises(dhd.DhdError) as ei:
            h.step(0.0)
        assert ei.value.code == 15 and "dhdGetButton failed: invalid button index (error 15)" in str(ei.value)
        assert not isinstance(ei.value, dhd.DeviceLostError)


def test_com_freq_is_reported(sdk_dir, standin):
    standin.set_com_freq(3.9)
    with harness(sdk_dir) as h:
        h.step(0.0)
        assert h.comp.status()["com_freq_hz"] == pytest.approx(3900.0)


def test_unplug_mid_run_raises_a_hardware_error_and_safe_state_never_raises(sdk_dir, standin):
    with harness(sdk_dir) as h:
        h.step(0.0, gripper_force=1.0)
        standin.unplug()
        with pytest.raises(dhd.DeviceLostError, match="communication error.*stopped answering"):
            h.step(0.001, gripper_force=1.0)
        h.comp.safe_state()
        assert h.comp.safe_errors >= 2  # zero force and brakes were both tried, both failed quietly
        assert h.comp.status()["lost"]


# ------------------------------------------------------------------------------------------------ graphs
GRAPH = """
name: leader-swap
clock: wall
duration: DURATION
nodes:
  - id: force
    plugin: mock-sensor
    rate: 1kHz
    params: {signal: constant, amplitude: 1.0, FAIL}
  - id: leader
    plugin: PLUGIN
    rate: 1kHz
    params: {max_gripper_force: 5 N, max_force: 10 N, command_timeout: 50ms, EXTRA}
    inputs: {gripper_force: force.value}
"""


def graph(plugin: str, extra: str = "", duration: float = 0.3, fail: str = "") -> str:
    return (GRAPH.replace("PLUGIN", plugin).replace("EXTRA", extra).replace("DURATION", str(duration))
            .replace(", FAIL", fail).replace(", }", "}"))


def test_omega7_and_sim_omega7_swap_by_the_plugin_line(sdk_dir, standin):
    reg = make_registry("teletouch.plugins.devices.omega7", "teletouch.plugins.devices.sim_omega7")
    sim = reg.get("sim-omega7").cls
    for name, port in Omega7.inputs.items():
        assert sim.inputs[name] == port
    for name, port in Omega7.outputs.items():
        assert sim.outputs[name] == port
    ports = {}
    for plugin, extra in (("omega7", f"sdk_path: {sdk_dir}"), ("sim-omega7", "")):
        seen: dict[str, set] = {}
        result, rt = run_yaml(graph(plugin, extra), reg,
                              taps=[lambda node, t, out: seen.setdefault(node, set()).update(out)])
        assert result.status == "ok", result.summary()
        leader = next(n for n in result.nodes if n.id == "leader")
        assert leader.steps > 100
        ports[plugin] = seen["leader"]
    assert {"gripper_opening", "gripper_velocity", "position", "button"} <= ports["omega7"]
    assert ports["omega7"] <= ports["sim-omega7"]


def test_omega7_is_refused_under_the_sim_clock(sdk_dir):
    reg = make_registry("teletouch.plugins.devices.omega7")
    with pytest.raises(GraphValidationError, match="simulated clock"):
        load_text(graph("omega7", f"sdk_path: {sdk_dir}").replace("clock: wall", "clock: sim"), reg)


def test_unplug_mid_run_faults_the_graph_and_ends_safe(sdk_dir, standin):
    reg = make_registry("teletouch.plugins.devices.omega7")
    timer = threading.Timer(0.3, standin.unplug)
    timer.start()
    try:
        result, rt = run_yaml(graph("omega7", f"sdk_path: {sdk_dir}", duration=3.0), reg)
    finally:
        timer.cancel()
    assert result.status == "fault" and result.exit_code == 3
    assert result.wall_time < 2.5  # stopped at the fault, not at the end
    fault = next(f for f in result.faults if f.node == "leader")
    assert "stopped answering" in fault.message
    leader = rt.component("leader")
    assert leader.safe_errors >= 1  # safe state was attempted (the device is gone)
    assert leader.lost and leader.dhd is None  # closed


def test_fault_elsewhere_drives_the_omega7_to_zero_force_and_brakes(sdk_dir, standin):
    reg = make_registry("teletouch.plugins.devices.omega7")
    result, rt = run_yaml(graph("omega7", f"sdk_path: {sdk_dir}", duration=3.0, fail=", fail_at: 0.3"), reg)
    assert result.status == "fault"
    assert any(f.node == "force" for f in result.faults)
    assert standin.lib.standin_get_writes() > 50  # it ran (0.3 s at 1 kHz, fewer on a loaded machine)
    applied, commanded = standin.forces()
    assert applied == [0.0] * 4 and commanded == [0.0] * 4
    fl = standin.flags()
    assert fl["brakes"] and not fl["force_enabled"] and not fl["open"]


def test_safe_state_zero_force_is_not_lost_to_the_time_guard(sdk_dir, standin):
    # the SDK skips a write that comes too soon after the previous one (DHD_TIMEGUARD): safe_state()'s zero-force
    # write right after a step's must be written again, never leaving the step's force on the hand
    with harness(sdk_dir, brakes_on_stop=False) as h:
        h.step(0.0, gripper_force=3.0)
        assert standin.forces()[0][3] == pytest.approx(3.0)
        standin.set_timeguard_every(standin.get_writes() + 1)     # the very next write is skipped
        h.comp.safe_state()
        assert standin.forces()[0] == [0.0, 0.0, 0.0, 0.0]
        assert standin.flags()["force_enabled"]
        # a time guard that never lets a write through: forces are disabled instead
        h.comp.activate()
        h.step(0.01, gripper_force=3.0)
        standin.set_timeguard_every(1)
        h.comp.safe_state()
        assert not standin.flags()["force_enabled"] and standin.forces()[0] == [0.0, 0.0, 0.0, 0.0]
