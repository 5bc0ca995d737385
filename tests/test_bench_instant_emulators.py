"""The emulators' ``instant`` knob, for benchmarks/follower_latency.py: a round trip there must measure the transport,
not the motion. The drivers set their actuators' profile speed from ``max_speed`` (Dynamixel Profile_Velocity,
CANopen 0x6081, PAL's trajectory time), which may not exceed 2 m/s (teletouch.units.plausible_speed): a 30 mm step
is then ~15 ms of motion. With ``instant`` the emulated actuator is at its goal on the next read whatever that speed;
without it, it moves at the profile speed as before."""

from __future__ import annotations

import os
import sys
import time
import uuid
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes.dynamixel_emulator import DynamixelEmulator  # noqa: E402
from fakes.pal_gripper_node import PalGripperNode  # noqa: E402
from fakes.ros2_peer import own_domain  # noqa: E402
from helpers_scripts import load_follower_bench  # noqa: E402

from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.canopen_gripper import CanopenGripper  # noqa: E402
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper  # noqa: E402

pytestmark = pytest.mark.timeout(120)

SPEED = 2.0        # m/s: the fastest max_speed the drivers accept
STEP = (0.03, 0.06)  # m: the benchmark's step
TOL = 5e-4         # m: the benchmark's "reached"
#: the least time the step takes at SPEED (the emulators never move faster than the profile speed the driver set)
MOTION_S = (STEP[1] - STEP[0] - 2 * TOL) / SPEED


def _harness(cls, params):
    h = Harness(cls, dict({"max_speed": SPEED, "max_opening": 0.07}, **params))
    h.ctx.clock_kind = "wall"
    return h


def _reach(comp, target, timeout=1.0):
    """``_hw_write(target)``, then ``_hw_read()`` back to back until a reading is within TOL of it: (seconds from
    before the write, the first reading's opening)."""
    again = getattr(comp, "setpoint_handshake", False)   # canopen: a write after each read, as its steps do
    while again and not comp.handshake_idle():   # the last set-point's handshake finished first
        comp._hw_read()
        comp._hw_write(comp.map.opening(comp._target))
    t0 = time.monotonic()
    comp._hw_write(target)
    first = None
    while time.monotonic() - t0 < timeout:
        r = comp._hw_read()
        if r is not None and first is None:
            first = r.opening
        if r is not None and abs(r.opening - target) < TOL:
            return time.monotonic() - t0, first
        if again:
            comp._hw_write(target)
        time.sleep(20e-6)
    raise AssertionError(f"{target} m not reached within {timeout} s (first reading {first})")


def _check(comp, instant):
    for target in (*STEP, STEP[0]):
        comp._hw_read()   # a read just before: the emulator's physics has just run (no idle time to move in)
        elapsed, first = _reach(comp, target)
        if instant and getattr(comp, "setpoint_handshake", False):   # the drive reads the set-point at the end of
            assert elapsed < MOTION_S / 2, (target, elapsed)   # its control cycle: at the goal a read or two later
        elif instant:   # at the goal on the very next read
            assert first == pytest.approx(target, abs=TOL)
        else:         # moved at the profile speed set from max_speed: the step takes its time
            assert elapsed >= MOTION_S, (target, elapsed)


@pytest.mark.parametrize("instant", [True, False])
def test_dynamixel_emulator_instant_is_at_the_goal_on_the_next_read(instant):
    # speed=1e9: the servo's own top speed out of the way, only Profile_Velocity (from max_speed) limits
    emu = DynamixelEmulator(15, position=1024, speed=1e9, instant=instant).start()
    try:
        with _harness(DynamixelGripper, {"port": emu.port, "baudrate": 1000000}) as h:
            assert h.comp.profile_velocity > 0   # the driver set a speed limit; the knob overrides it
            _check(h.comp, instant)
    finally:
        emu.stop()


@pytest.mark.parametrize("instant", [True, False])
def test_canopen_drive_instant_is_at_the_goal_on_the_next_read(instant):
    ch = f"tt-{uuid.uuid4().hex[:8]}"
    drive = Cia402Drive(4, ch, position=0, instant=instant).start()
    try:
        with _harness(CanopenGripper, {"interface": "virtual", "channel": ch, "node_id": 4}) as h:
            assert drive.get(0x6081) == h.comp.profile_velocity > 0   # the profile velocity the driver set
            _check(h.comp, instant)
    finally:
        drive.stop()


@pytest.mark.parametrize("instant", [True, False])
def test_pal_node_instant_commands_the_trajectory_end_point_at_once(instant):
    """A trajectory's point is reached after its time_from_start (interpolated); with ``instant`` the controller
    commands the end point in the cycle that takes the trajectory up (no ROS 2 needed: the controller's cycle)."""
    node = PalGripperNode(rate=1000.0, opening=0.06, velocity_limit=1000.0, instant=instant)
    node._pending = [(0.015, [0.015, 0.015])]   # 60 -> 30 mm in 15 ms: what max_speed 2 m/s asks for
    now = time.monotonic()
    node._start_pending(now)
    ref = node._reference(now + 0.001)   # the point one period ahead, commanded this cycle
    if instant:
        assert ref == [0.015, 0.015]
    else:
        assert ref == pytest.approx([0.03 - 0.015 / 15] * 2)


def test_pal_node_takes_instant_on_its_command_line(monkeypatch):
    """The benchmark runs the node as a process (``--instant``)."""
    from fakes import pal_gripper_node

    made = {}

    class Node:
        def __init__(self, *a, **k):
            made.update(k)

        def start(self):
            return self

        def stop(self):
            pass
    monkeypatch.setattr(pal_gripper_node, "PalGripperNode", Node)
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    assert pal_gripper_node.main(["--instant"]) == 0
    assert made["instant"] is True
    assert pal_gripper_node.main([]) == 0
    assert made["instant"] is False


# --- the benchmark: valid params, and its round trips are the transport's -----------------------------------------

@pytest.fixture()
def follower_bench(monkeypatch):
    return load_follower_bench(monkeypatch, "follower_latency_instant")


def test_follower_benchmark_round_trips_are_not_the_motion(follower_bench):
    """The benchmark's drivers get a max_speed they accept (at most 2 m/s), and its emulators reach each goal at once:
    every transport's round-trip median is well below the ~15 ms that a 30 mm step takes at 2 m/s."""
    assert 0 < follower_bench.FAST["max_speed"] <= SPEED
    domain = own_domain(41)
    specs = follower_bench.transport_specs(f"bench-{uuid.uuid4().hex[:8]}", domain)
    assert list(specs) == ["dynamixel-57600", "dynamixel-1000000", "canopen-virtual", "pal-ros2-loopback"]
    res = follower_bench.side_by_side(specs, 20, 0.05, rounds=2)
    for key, r in res.items():
        assert r["round_trips"] == 20 and r["round_trip_timeouts"] == 0, (key, r)
        assert r["round_trip_ms_p50"] < MOTION_S * 1e3, (key, r["round_trip_ms_p50"])   # (57600 baud: ~7 ms)
