"""Set-ups shared by the follower-driver tests: the drivers on their emulated hardware (wall clock), and fixtures that
start and stop that hardware. A fixture here is made by a function and bound to a name in the test module (``emu =
dynamixel_fixture(15, position=1024)``): each module says which set-up it uses, and pytest runs it per test there."""

from __future__ import annotations

import contextlib
import uuid
from typing import Any, Iterator

import pytest

from teletouch.plugins.devices.canopen_gripper import CanopenGripper
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper
from teletouch.testing import Harness

from fakes.canopen_drive import Cia402Drive
from fakes.dynamixel_emulator import DynamixelEmulator, slow_adapter


# --- Dynamixel: the emulated servo on a pseudo-terminal ------------------------------------------------------------
def packet_timeout_fixture(autouse: bool = True):
    """A fixture that runs each test with the emulator's slower adapter for a loaded machine (slow_adapter) and gives
    the SDK's packet timeout (s) of a short answer; autouse unless told otherwise."""
    @pytest.fixture(autouse=autouse)
    def packet_timeout() -> Iterator[float]:
        with slow_adapter() as timeout:
            yield timeout
    return packet_timeout


def dynamixel_fixture(dxl_id: int, **settings: Any):
    """A fixture that gives a started DynamixelEmulator(dxl_id, **settings), stopped after the test."""
    @pytest.fixture
    def emu() -> Iterator[DynamixelEmulator]:
        e = DynamixelEmulator(dxl_id, **settings)
        e.start()
        yield e
        e.stop()
    return emu


def dynamixel_harness(emu: DynamixelEmulator, **params: Any) -> Harness:
    """A dynamixel-gripper (1 Mbaud, wall clock) on the emulator's port."""
    h = Harness(DynamixelGripper, dict(baudrate=1000000, port=emu.port, **params))
    h.ctx.clock_kind = "wall"
    return h


@contextlib.contextmanager
def dynamixel(**params: Any) -> Iterator[tuple[DynamixelEmulator, Harness]]:
    """A Dynamixel gripper (wall clock) on the emulator, the servo resting fully open (1024 ticks), with the
    emulator's slower adapter for a loaded machine: (emulator, entered harness)."""
    emu = DynamixelEmulator(15, position=1024).start()
    try:
        h = dynamixel_harness(emu, **params)
        with slow_adapter(), h:
            yield emu, h
    finally:
        emu.stop()


def goal_positions(emu: DynamixelEmulator, since: float) -> list[int]:
    """The Goal_Position ticks the driver sent (SYNC_WRITE packets) since ``since`` (time.monotonic())."""
    return [int.from_bytes(p[5:9], "little", signed=True) for (t, _i, inst, p) in emu.rx_packets
            if inst == 0x83 and t >= since]


# --- CANopen: the emulated CiA 402 drive (node 5) on python-can's virtual bus --------------------------------------
def channel_fixture():
    """A fixture that gives a virtual CAN channel name of the test's own."""
    @pytest.fixture
    def channel() -> str:
        return f"tt-{uuid.uuid4().hex[:8]}"
    return channel


def drive_fixture(**settings: Any):
    """A fixture that gives a started Cia402Drive(5, channel, **settings) on the ``channel`` fixture's channel,
    stopped after the test."""
    @pytest.fixture
    def drive(channel: str) -> Iterator[Cia402Drive]:
        d = Cia402Drive(5, channel, **settings)
        d.start()
        yield d
        d.stop()
    return drive


def canopen_harness(channel: str, **params: Any) -> Harness:
    """A canopen-gripper (node 5, wall clock) on ``channel`` of the virtual bus."""
    h = Harness(CanopenGripper, dict({"interface": "virtual", "channel": channel, "node_id": 5}, **params))
    h.ctx.clock_kind = "wall"
    return h


#: pdo_timeout of the SYNC-counting tests (s): long, so that their timings keep 0.1-0.2 s margins on a loaded machine
SYNC_PDO_TIMEOUT = 0.4


def sync_harness(channel: str, **params: Any) -> Harness:
    """:func:`canopen_harness` with the SYNC-counting tests' ``pdo_timeout`` (:data:`SYNC_PDO_TIMEOUT`)."""
    return canopen_harness(channel, **dict({"pdo_timeout": SYNC_PDO_TIMEOUT}, **params))


def counts_of(h: Harness, reading: Any) -> int:
    """The drive's position counts of a reading of the canopen-gripper in ``h``."""
    return round(h.comp.map.counts(reading.opening))
