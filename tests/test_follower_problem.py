"""A follower whose reads fail says so in status()["problem"] (for how long, where it talks, the last error), and a
node whose input from it goes stale first (a controller's max_age on the opening, shorter than the follower's
read_timeout) faults quoting that: the lab-setup audit's servo gone quiet read only "input 'follower_opening' from
gripper.opening is 0.051 s old (limit 0.05 s)"."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import DynamixelEmulator  # noqa: E402
from fakes.followers import (  # noqa: E402
    canopen_harness, channel_fixture, drive_fixture, dynamixel_fixture, dynamixel_harness)
from fakes.realtime import drive as drive_steps  # noqa: E402

from teletouch.runtime import Runtime  # noqa: E402
from teletouch.testing import load_text, make_registry  # noqa: E402

pytestmark = pytest.mark.timeout(90)

emu = dynamixel_fixture(15, position=1024)


def test_status_says_what_is_wrong_while_the_reads_fail(emu):
    with dynamixel_harness(emu, read_timeout=2.0) as h:
        drive_steps(h, 0.05, 0.1)
        assert "problem" not in h.comp.status()
        emu.silent = True
        drive_steps(h, 0.05, 0.1)
        problem = h.comp.status()["problem"]
        assert problem.startswith("no valid state for ") and "(read_timeout 2 s)" in problem, problem
        assert f"Dynamixel ID 15 on {emu.port} at 1000000 baud" in problem and "failed reads, last:" in problem
        emu.silent = False
        drive_steps(h, 0.05, 0.2)
        assert "problem" not in h.comp.status()


def test_a_stale_opening_quotes_the_followers_problem():
    e = DynamixelEmulator(15, position=1024).start()
    try:
        reg = make_registry("teletouch.plugins.devices.dynamixel_gripper")
        rt = Runtime(load_text(f"""
clock: wall
duration: 5
faults: {{max_overruns: 0}}
nodes:
  - {{id: cmd, plugin: mock-sensor, rate: 100, params: {{signal: constant, offset: 0.05}}}}
  - id: gripper
    plugin: dynamixel-gripper
    rate: 100
    params: {{port: '{e.port}', baudrate: 1000000}}
    inputs: {{opening_command: cmd.value}}
  - id: controller
    plugin: mock-gain
    rate: 100
    inputs: {{x: {{from: gripper.opening, max_age: 0.05}}}}
""", reg), log=lambda m: None)
        quiet = threading.Event()

        def hush(node, t, out):
            if node == "gripper" and t >= 1.3 and not quiet.is_set():   # (after faults.startup_grace, 1 s)
                quiet.set()
                e.silent = True

        rt.add_tap(hush)
        res = rt.run()
    finally:
        e.stop()
    f = res.faults[0]
    assert (f.node, f.kind) == ("controller", "stale"), res.faults
    assert "; node 'gripper' reports: no valid state for " in f.message, f.message
    assert f"Dynamixel ID 15 on {e.port} at 1000000 baud" in f.message and "failed reads" in f.message, f.message


channel = channel_fixture()
drive = drive_fixture(position=0)


def test_a_canopen_drive_gone_quiet_says_its_last_problem(channel, drive):
    with canopen_harness(channel, read_timeout=2.0, pdo_timeout=0.02) as h:
        drive_steps(h, 0.05, 0.1)
        assert "problem" not in h.comp.status()
        drive.go_silent()
        drive_steps(h, 0.05, 0.2)
        problem = h.comp.status()["problem"]
        assert problem.startswith("no valid state for ") and "(read_timeout 2 s)" in problem, problem
        assert f"CANopen node 5 on virtual:{channel}, last problem: " in problem and "TPDO" in problem, problem
