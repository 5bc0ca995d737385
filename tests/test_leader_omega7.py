"""omega7 against a stand-in libdhd built from C (tests/fakes/dhd_standin.c) with the vendor's names and signatures:
the ctypes path that runs against the hardware is the path under test."""

from __future__ import annotations

import ctypes
import math
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from teletouch import ComponentFault, HardwareError
from teletouch.errors import GraphValidationError
from teletouch.plugins.devices import dhd
from teletouch.plugins.devices import omega7 as omega7_mod
from teletouch.plugins.devices.omega7 import Omega7, teletouch_discover_devices
from teletouch.testing import Harness, load_text, make_registry, run_yaml

from fakes.dhd_standin import StandIn, build_standin, sdk_dir_fixture, standin_fixture

sdk_dir = sdk_dir_fixture("fdsdk")
standin = standin_fixture()


def harness(sdk_dir, **params) -> Harness:
    return Harness(Omega7, {"sdk_path": str(sdk_dir), **params})


def wait_and_step(h: Harness, seconds: float = 0.03, **inputs):
    """Step for `seconds` of wall time every ~2 ms, as a haptic loop does (a pause longer than the firmware watchdog,
    20 ms by default, would let the device cut its forces), and return the last outputs."""
    start, t0 = time.monotonic(), h.t
    while True:
        time.sleep(0.002)
        elapsed = time.monotonic() - start
        out = h.step(t0 + elapsed, **inputs)
        if elapsed >= seconds:
            return out


def wait_for(cond, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(2e-4)
    return True


def start_hanging_step(h: Harness, standin: "StandIn", t: float, **inputs) -> threading.Thread:
    """A step in its own thread that hangs inside libdhd (dhdGetPosition, the step's first call) until
    standin.release(); returns once it hangs."""
    standin.hang(b"dhdGetPosition")
    th = threading.Thread(target=h.step, args=(t,), kwargs=inputs, daemon=True)
    th.start()
    assert wait_for(lambda: standin.hanging() == 1), "the step never reached dhdGetPosition"
    return th


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
    # the serial number selects the device (index is the enumeration order, which two devices may swap at a boot)
    assert found and found[0]["kind"] == "omega7" and found[0]["details"]["params"] == {"serial": 12345}
    assert found[0]["details"]["serial"] == 12345
    standin.set_present(0)
    assert teletouch_discover_devices() == []   # the SDK answers: no device plugged in


# ------------------------------------------------------------------------------------------------ discovery rows
def test_discovery_without_the_sdk_is_an_error_row_saying_where_it_looked(sdk_dir, monkeypatch):
    """Without the SDK the hook returned [] (no row at all): a plugged-in omega.7 was invisible to `teletouch devices`
    with nothing saying that the SDK, not the device, was missing."""
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir / "nowhere"))
    monkeypatch.setattr(dhd.ctypes.util, "find_library", lambda name: None)
    rows = teletouch_discover_devices()
    assert len(rows) == 1 and rows[0]["kind"] == "omega7", rows
    err = rows[0]["error"]
    assert "SDK (libdhd) not found" in err and "the system library path" in err
    assert f"FORCEDIM_SDK={sdk_dir / 'nowhere'} (does not exist)" in err and "sdk_path" in err


class _Lib:
    """The stand-in libdhd with dhdGetDeviceCount replaced (or removed) and the last error set, as an SDK gives."""

    def __init__(self, real, count, error=(dhd.DHD_ERROR_NO_DRIVER_FOUND, b"no driver found")):
        self._real, self._count, self._error = real, count, error

    def __getattr__(self, name):
        if name == "dhdGetDeviceCount":
            if self._count is None:
                raise AttributeError(name)
            return lambda: self._count
        if name == "dhdErrorGetLast":
            return lambda: self._error[0]
        if name == "dhdErrorGetLastStr":
            return lambda: self._error[1]
        return getattr(self._real, name)


@pytest.mark.parametrize("count, expected", [(-1, ["dhdGetDeviceCount failed", "no driver found (error 4)", "USB"]),
                                             (None, ["has no dhdGetDeviceCount", "opens the first device"])])
def test_discovery_that_cannot_count_devices_is_an_error_row(sdk_dir, standin, monkeypatch, count, expected):
    """dhdGetDeviceCount returning -1 (an SDK error) gave an empty list, as if nothing were plugged in; an SDK
    without dhdGetDeviceCount too."""
    real = dhd.load(sdk_dir)
    monkeypatch.setattr(real, "lib", _Lib(real.lib, count))
    monkeypatch.setattr(dhd, "load", lambda sdk_path=None: real)
    rows = teletouch_discover_devices()
    assert len(rows) == 1 and rows[0]["kind"] == "omega7" and rows[0]["path"] == real.path, rows
    for text in expected:
        assert text in rows[0]["error"], rows[0]["error"]


def test_load_says_when_the_path_given_does_not_exist(tmp_path, monkeypatch):
    """A misspelt sdk_path or FORCEDIM_SDK was reported as 'no libdhd.so under ...' or only 'looked in ...', never
    saying that the folder itself does not exist."""
    monkeypatch.setattr(dhd.ctypes.util, "find_library", lambda name: None)
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    with pytest.raises(dhd.SdkNotFoundError, match=rf"sdk_path={tmp_path / 'sdk-3.71'} does not exist"):
        dhd.load(tmp_path / "sdk-3.71")
    monkeypatch.setenv("FORCEDIM_SDK", str(tmp_path / "sdk-3.71"))
    with pytest.raises(dhd.SdkNotFoundError, match=rf"FORCEDIM_SDK={tmp_path / 'sdk-3.71'} \(does not exist\)"):
        dhd.load(None)
    (tmp_path / "empty").mkdir()
    monkeypatch.setenv("FORCEDIM_SDK", str(tmp_path / "empty"))
    with pytest.raises(dhd.SdkNotFoundError, match=rf"FORCEDIM_SDK={tmp_path / 'empty'} \(no libdhd.so"):
        dhd.load(None)


def test_an_sdk_path_whose_library_fails_to_load_is_not_replaced_by_another(sdk_dir, tmp_path, monkeypatch):
    """sdk_path names an SDK whose library does not load: the library of FORCEDIM_SDK (another SDK) was taken instead,
    silently."""
    broken = tmp_path / "sdk-broken"
    broken.mkdir()
    (broken / "libdhd.so").write_bytes(b"not an ELF file")
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir))
    with pytest.raises(dhd.SdkNotFoundError) as ei:
        dhd.load(broken)
    msg = str(ei.value)
    assert f"under sdk_path={broken} could not be loaded" in msg and str(broken / "libdhd.so") in msg


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


@pytest.mark.parametrize("system_type, left", [(104, False), (105, True)])
def test_a_sigma7_is_taken_with_its_handedness(sdk_dir, standin, system_type, left):
    """dhdc.h numbers the sigma.7 104 (right, DHD_DEVICE_SIGMA331) and 105 (left); the binding had 105 and 106: with
    allow_other_devices a right sigma.7 was refused, and a left one taken as right, its gripper force sent with the
    wrong sign (a positive gripper_force closed the operator's fingers)."""
    standin.set_system_type(system_type)
    with harness(sdk_dir, allow_other_devices=True) as h:
        assert h.comp.status()["left_handed"] == left
        out = wait_and_step(h, 0.05, gripper_force=3.0)
        assert out["gripper_opening"] == pytest.approx(0.015 + 3.0 / 400.0, abs=2e-4)   # opens, whatever the hand
        assert standin.forces()[1][3] == pytest.approx(-3.0 if left else 3.0)
    standin.set_system_type(106)  # a (deprecated) sigma.33P, not a sigma.7
    h = harness(sdk_dir, allow_other_devices=True)
    with pytest.raises(dhd.DhdError, match="system type 106, not an omega.7"):
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


def test_dhd_get_status_gets_a_buffer_as_long_as_the_sdk_fills(sdk_dir, standin, monkeypatch):
    """dhdGetStatus(int status[DHD_MAX_STATUS], char ID) writes DHD_MAX_STATUS ints: 17 in dhdc.h of SDK 3.11 (with
    DHD_STATUS_AXISCHECKED = 16). The binding passed a buffer of 16: the SDK wrote past its end (heap corruption, at
    every late step of the firmware watchdog's check)."""
    lib = dhd.load(sdk_dir)
    lib.open()
    real, sizes = lib.lib, []

    class Lib:
        def __getattr__(self, name):
            if name != "dhdGetStatus":
                return getattr(real, name)

            def get_status(status, ID):
                sizes.append(ctypes.sizeof(status))
                assert ctypes.sizeof(status) >= 17 * ctypes.sizeof(ctypes.c_int), "the SDK writes 17 ints"
                return real.dhdGetStatus(status, ID)
            return get_status

    monkeypatch.setattr(lib, "lib", Lib())
    assert lib.force_status() == (False, 0)
    assert sizes and sizes[0] >= 17 * ctypes.sizeof(ctypes.c_int)
    monkeypatch.undo()
    lib.close()


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
# faults: no overrun faults and a watchdog of 0.5 s, not 0.1 s: on a loaded 2-core machine late 1 kHz steps and a
# stalled thread must not end a run whose outcome (ok, or the fault a test causes) is what the test checks
GRAPH = """
name: leader-swap
clock: wall
duration: DURATION
faults: {max_overruns: 0, watchdog: 0.5}
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
        assert leader.steps >= 10  # it ran (0.3 s at 1 kHz: ~300 steps; below 100 were seen on a loaded machine)
        ports[plugin] = seen["leader"]
    assert {"gripper_opening", "gripper_velocity", "position", "button"} <= ports["omega7"]
    assert ports["omega7"] <= ports["sim-omega7"]


def test_omega7_is_refused_under_the_sim_clock(sdk_dir):
    reg = make_registry("teletouch.plugins.devices.omega7")
    with pytest.raises(GraphValidationError, match="simulated clock"):
        load_text(graph("omega7", f"sdk_path: {sdk_dir}").replace("clock: wall", "clock: sim"), reg)


def test_unplug_mid_run_faults_the_graph_and_ends_safe(sdk_dir, standin):
    reg = make_registry("teletouch.plugins.devices.omega7")

    def unplug_while_running(node, t, out):   # (a timer from before the run unplugged it during a slow start-up)
        if node == "leader" and t >= 0.3:
            standin.unplug()

    result, rt = run_yaml(graph("omega7", f"sdk_path: {sdk_dir}", duration=3.0), reg, taps=[unplug_while_running])
    assert result.status == "fault" and result.exit_code == 3
    assert result.sim_time < 2.5  # stopped at the fault, not at the end
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
    assert standin.get_peak() == pytest.approx(1.0)  # it ran: the sensor's 1 N reached the device before the fault
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


def test_safe_state_switches_forces_off_when_the_zero_force_write_fails(sdk_dir, standin):
    """safe_state()'s zero-force write answered -1 (an SDK error): the exception left _zero_forces before its fallback
    (forces disabled), so with brakes_on_stop: false the step's 3 N stayed on the operator's hand."""
    with harness(sdk_dir, brakes_on_stop=False) as h:
        h.step(0.0, gripper_force=3.0)
        assert standin.forces()[0][3] == pytest.approx(3.0)
        standin.set_write_fails(1)
        try:
            h.comp.safe_state()   # never raises
            assert not standin.flags()["force_enabled"] and standin.forces()[0] == [0.0] * 4
            assert h.comp.safe_errors >= 1
        finally:
            standin.set_write_fails(0)


# ----------------------------------------------------------------------------------------- hangs, firmware watchdog
def test_firmware_watchdog_cuts_the_force_while_a_libdhd_call_hangs(sdk_dir, standin):
    # a step hangs inside libdhd holding the driver's lock, and safe_state() (what the runtime's watchdog calls)
    # waits for that lock: the device's own watchdog must take the force off the hand, within its duration
    with harness(sdk_dir, firmware_watchdog="20 ms") as h:
        h.step(0.0, gripper_force=3.0)
        h.step(0.001, gripper_force=3.0)  # the last force command the device gets
        assert standin.forces()[0][3] == pytest.approx(3.0)
        trips = standin.get_watchdog_trips()
        stepper = start_hanging_step(h, standin, 0.002, gripper_force=3.0)
        guard = threading.Thread(target=h.comp.safe_state, daemon=True)
        guard.start()
        try:
            # the firmware's clock, from the last command: on before the watchdog's 20 ms, off after it (stays off)
            for dt, on in ((0.010, True), (0.0099, True), (0.0002, False), (0.05, False)):
                standin.advance_clock(dt)
                applied, enabled = standin.forces()[0], standin.flags()["force_enabled"]
                assert (applied == pytest.approx([0.0, 0.0, 0.0, 3.0]) and enabled) if on else \
                    (applied == [0.0] * 4 and not enabled), (dt, applied, enabled)
            assert guard.is_alive() and stepper.is_alive()  # the driver could not act: both wait on the hanging call
            assert standin.get_watchdog_trips() == trips + 1
        finally:
            standin.release()  # (a failure above must not leave the lock held: leaving the `with` would wait forever)
        stepper.join(10.0)
        guard.join(10.0)
        assert not guard.is_alive()
        assert standin.forces()[0] == [0.0] * 4 and standin.flags()["brakes"]


def test_without_the_firmware_watchdog_a_hang_leaves_the_force_on(sdk_dir, standin):
    # firmware_watchdog: 0 runs without it: nothing takes the force off while a libdhd call hangs
    with harness(sdk_dir, firmware_watchdog=0) as h:
        assert standin.get_watchdog() == 0 and h.comp.status()["firmware_watchdog_s"] == 0.0
        h.step(0.0, gripper_force=3.0)
        stepper = start_hanging_step(h, standin, 0.001, gripper_force=3.0)
        try:
            time.sleep(0.1)
            standin.advance_clock(0.1)
            assert standin.forces()[0][3] == pytest.approx(3.0) and standin.flags()["force_enabled"]
        finally:
            standin.release()
        stepper.join(10.0)


def test_safe_state_during_a_hanging_step_is_never_undone(sdk_dir, standin):
    # the runtime calls safe_state() from another thread while a step hangs inside libdhd: once the call returns,
    # that step must not send its force (decided before safe_state) to the device
    with harness(sdk_dir) as h:
        h.step(0.0, gripper_force=3.0)
        assert h.comp.status()["gripper_force_n"] == pytest.approx(3.0)
        stepper = start_hanging_step(h, standin, 0.001, gripper_force=3.0)
        guard = threading.Thread(target=h.comp.safe_state, daemon=True)
        guard.start()
        try:
            assert wait_for(lambda: not h.comp.active)  # safe_state() has begun (it waits for the step's lock)
            standin.mark()
        finally:
            standin.release()
        stepper.join(10.0)
        guard.join(10.0)
        assert not stepper.is_alive() and not guard.is_alive()
        assert standin.get_peak() == 0.0  # no force but zero reached the device after safe_state() was called
        applied, commanded = standin.forces()
        assert applied == [0.0] * 4 and commanded == [0.0] * 4
        assert standin.flags()["brakes"]
        h.step(0.01, gripper_force=3.0)  # and it stays safe until activated again
        assert standin.forces()[1] == [0.0] * 4 and standin.flags()["brakes"]


@pytest.mark.parametrize("value, rate, units", [
    ("20 ms", 1000, 160), (0.02, 1000, 160), ("20.1 ms", 1000, 160), (0.0201, 1000, 160), ("31.875 ms", 1000, 255),
    ("2.0625 ms", 1000, 16), ("1.99 ms", 2000, 15), ("875 us", 4000, 7), ("0.125 ms", 16000, 1),
    (0.00013, 16000, 1)])
def test_firmware_watchdog_reaches_the_device_in_125_us_units_rounded_down(sdk_dir, standin, value, rate, units):
    h = harness(sdk_dir, firmware_watchdog=value)
    h.ctx.rate = rate  # the node's rate in a graph
    with h:
        assert standin.get_watchdog() == units  # never longer than asked
        assert h.comp.status()["firmware_watchdog_s"] == pytest.approx(units * 125e-6)


@pytest.mark.parametrize("bad", ["32 ms", "1 s", "100 us", -0.02, "-1 ms"])
def test_firmware_watchdog_out_of_range_is_refused(bad):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=r"firmware_watchdog must be 0 \(off\) or from 125 us to 31.875 ms"):
        Omega7.Params(firmware_watchdog=bad)


def test_firmware_watchdog_shorter_than_two_periods_is_refused(sdk_dir, standin):
    h = harness(sdk_dir, firmware_watchdog="1.5 ms")  # the node runs at 1 kHz
    with pytest.raises(ValueError, match=r"firmware_watchdog \(1.5 ms\) must be at least 2 periods of the node's "
                                         r"rate \(1000 Hz: 2 ms\)"):
        h.comp.configure()
    h.comp.close()
    assert not standin.flags()["open"]


def test_firmware_watchdog_is_refused_in_a_graph_with_the_field_named(sdk_dir, standin):
    reg = make_registry("teletouch.plugins.devices.omega7")
    with pytest.raises(GraphValidationError, match=r"firmware_watchdog must be 0 \(off\) or from 125 us to 31.875 ms"):
        load_text(graph("omega7", f"sdk_path: {sdk_dir}, firmware_watchdog: 40ms"), reg)


def test_an_sdk_without_the_watchdog_is_refused_unless_it_is_off(tmp_path, standin, monkeypatch):
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    old = tmp_path / "sdk-3.3.1"
    (old / "lib").mkdir(parents=True)
    build_standin(old / "lib", "STANDIN_NO_WATCHDOG")  # as an SDK older than 3.3.2
    h = harness(old)
    with pytest.raises(dhd.DhdError) as ei:
        h.comp.configure()
    msg = str(ei.value)
    assert msg.startswith("firmware_watchdog:") and "SDK 3.3.1" in msg and "dhdSetWatchdog" in msg
    assert "3.3.2" in msg and "firmware_watchdog: 0" in msg
    h.comp.close()
    s = StandIn(old / "lib" / "libdhd.so")
    assert not s.flags()["open"]  # refused before the device was opened
    with harness(old, firmware_watchdog=0) as h:  # explicitly without it: runs
        h.step(0.0, gripper_force=1.0)
        assert s.forces()[0][3] == pytest.approx(1.0)
        assert h.comp.status()["firmware_watchdog_s"] == 0.0
    s.lib.standin_reset()


def test_an_sdk_without_the_max_force_calls_runs_on_the_drivers_own_limits(tmp_path, standin, monkeypatch):
    """dhdSetMaxForce and dhdSetMaxGripperForce are not in SDK 3.7.0's dhdc.h: such a library was refused as "an SDK
    older than 3.x", though the driver's own force guard clamps every command anyway. It runs now, and says so."""
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    sdk = tmp_path / "sdk-3.7.0"
    (sdk / "lib").mkdir(parents=True)
    build_standin(sdk / "lib", "STANDIN_NO_MAX_FORCE")
    s = StandIn(sdk / "lib" / "libdhd.so")
    h = harness(sdk, max_gripper_force=2.0)
    logs: list[str] = []
    h.ctx._log = logs.append
    with h:
        assert any("limits 12 N, gripper 2 N (the driver's own: this SDK has no dhdSetMaxForce/dhdSetMaxGripperForce)"
                   in m for m in logs), logs
        h.step(0.0, gripper_force=5.0)
        assert s.forces()[0][3] == pytest.approx(2.0)   # clamped by the driver (the SDK's limit is its default 8 N)
    s.lib.standin_reset()


def test_a_device_that_refuses_the_watchdog_never_gets_forces_on(sdk_dir, standin):
    standin.set_watchdog_fails(1)
    h = harness(sdk_dir)
    h.comp.configure()
    with pytest.raises(dhd.DhdError) as ei:
        h.comp.activate()
    msg = str(ei.value)
    assert msg.startswith("firmware_watchdog: could not set the device's watchdog to 160 x 125 us (20 ms)")
    assert "feature not available on this device" in msg and "forces stay off" in msg and "firmware_watchdog: 0" in msg
    assert not standin.flags()["force_enabled"] and standin.flags()["brakes"]
    h.comp.close()


def test_a_graph_with_a_device_that_refuses_the_watchdog_fails_to_start(sdk_dir, standin):
    standin.set_watchdog_fails(1)
    reg = make_registry("teletouch.plugins.devices.omega7")
    result, rt = run_yaml(graph("omega7", f"sdk_path: {sdk_dir}"), reg)
    assert result.status == "startup-failed" and result.exit_code == 4
    assert "firmware_watchdog" in result.message and "could not set the device's watchdog" in result.message
    assert standin.get_peak() == 0.0 and not standin.flags()["force_enabled"]  # only the safe state's zero


def test_firmware_watchdog_is_switched_off_at_shutdown(sdk_dir, standin):
    with harness(sdk_dir) as h:
        assert standin.get_watchdog() == 160
        h.step(0.0, gripper_force=1.0)
        h.comp.deactivate()
        assert standin.get_watchdog() == 0 and not standin.flags()["force_enabled"]
        h.comp.activate()  # on again for the next activation
        assert standin.get_watchdog() == 160
    assert standin.get_watchdog() == 0  # deactivate + close
    h = harness(sdk_dir)
    h.comp.configure()
    h.comp.activate()
    h.comp.close()  # close without deactivate
    assert standin.get_watchdog() == 0 and not standin.flags()["open"]
    # through the runtime: a run that ends leaves the device without the watchdog
    reg = make_registry("teletouch.plugins.devices.omega7")
    result, rt = run_yaml(graph("omega7", f"sdk_path: {sdk_dir}"), reg)
    assert result.status == "ok", result.summary()
    assert standin.get_watchdog() == 0 and not standin.flags()["open"]


def test_forces_come_back_after_the_loop_was_late(sdk_dir, standin):
    # start-up after activate() and a stalled loop both leave the device without a command for longer than the
    # watchdog: it cut its forces; the next step's command is rendered again (a stall is counted, start-up is not)
    fade = omega7_mod.WATCHDOG_FADE_IN
    with harness(sdk_dir) as h:
        time.sleep(0.05)  # e.g. other nodes still activating
        standin.advance_clock(0.05)
        h.step(0.05, gripper_force=2.0)
        assert standin.forces()[0][3] == pytest.approx(2.0) and standin.flags()["force_enabled"]
        assert h.comp.status()["watchdog_trips"] == 0
        time.sleep(0.05)  # a stall
        standin.advance_clock(0.05)
        assert standin.forces()[0] == [0.0] * 4 and not standin.flags()["force_enabled"]
        # forces come back on, the command faded in from zero (WATCHDOG_FADE_IN), not stepped onto the hand. Each step
        # is timed from before to after it (its write lies between): a late step on a loaded machine is a sample
        # further along the ramp, never a failure
        rendered = []  # (time before the step, time after it, gripper force applied)
        t0 = time.monotonic()
        while not rendered or rendered[-1][0] < rendered[0][1] + fade:   # until a step certainly after the fade
            assert time.monotonic() - t0 < 10.0, rendered
            a = time.monotonic()
            h.step(0.1 + a - t0, gripper_force=2.0)
            rendered.append((a, time.monotonic(), standin.forces()[0][3]))
            time.sleep(0.002)
        assert standin.flags()["force_enabled"] and h.comp.status()["watchdog_trips"] == 1
        assert rendered[0][2] == pytest.approx(0.0, abs=1e-9)
        assert rendered[-1][2] == pytest.approx(2.0)
        # the fade starts at the first step's write, within (a0, b0): each force lies on the ramp 2 N * elapsed / fade
        a0, b0 = rendered[0][0], rendered[0][1]
        for a, b, f in rendered:
            lo, hi = (min(1.0, max(0.0, x / fade)) for x in (a - b0, b - a0))
            assert 2.0 * lo - 1e-9 <= f <= 2.0 * hi + 1e-9, (a - a0, b - a0, f, rendered)
        for (aa, ba, fa), (ab, bb, fb) in zip(rendered, rendered[1:]):
            assert fb - fa <= 2.0 * (bb - aa) / fade + 1e-9, rendered   # a ramp, no step
        h.comp.safe_state()  # but never after a safe state
        time.sleep(0.05)
        standin.advance_clock(0.05)
        h.step(0.3, gripper_force=2.0)
        assert standin.forces()[0] == [0.0] * 4 and not standin.flags()["force_enabled"]


def test_forces_switched_off_by_the_force_button_stay_off_after_a_late_step(sdk_dir, standin):
    # the operator switched the forces off with the device's force button; a later stall of the loop must not switch
    # them on again (only a trip of the firmware watchdog does: dhdGetStatus tells the cause)
    with harness(sdk_dir) as h:
        h.step(0.0, gripper_force=2.0)
        assert standin.forces()[0][3] == pytest.approx(2.0)
        standin.press_force_button()
        assert standin.forces()[0] == [0.0] * 4
        time.sleep(0.05)  # a stall longer than the watchdog
        standin.advance_clock(0.05)
        for k in range(5):
            h.step(0.1 + 0.002 * k, gripper_force=2.0)
            time.sleep(0.002)
        assert not standin.flags()["force_enabled"] and standin.forces()[0] == [0.0] * 4
        assert h.comp.status()["watchdog_trips"] == 0


def test_the_watchdog_is_set_in_expert_mode_and_expert_mode_is_left_again(sdk_dir, standin):
    # dhdSetWatchdog/dhdGetWatchdog are declared among the SDK's expert calls (the stand-in refuses them outside
    # expert mode): the driver enables expert mode around them and disables it afterwards
    with harness(sdk_dir):
        assert standin.get_watchdog() == 160
        assert standin.get_expert() == 0
    assert standin.get_watchdog() == 0 and standin.get_expert() == 0
