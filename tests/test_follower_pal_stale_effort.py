"""pal-gripper: the grip-force limit and the safe hold on stale /joint_states (a safety review).

``max_effort`` is enforced by the driver alone, from the effort of the last /joint_states message. When the topic went
silent the set-point kept closing at max_speed against the old effort (below max_effort) until read_timeout, and the
fault's hold then sent that set-point, deep inside the object, instead of where the fingers were last seen: the
position controller, which has no force limit, went on squeezing. A closing set-point now needs a fresh effort
(``effort_timeout``), and the hold on a stale state is the last measured opening.

A scripted robot on real ROS 2 (its own DDS participant) publishes the JointState messages a test chooses and records
the JointTrajectory commands the driver sends, as joint_trajectory_controller would receive them.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes import realtime  # noqa: E402
from fakes.ros2_peer import Peer, domain_fixture, own_domain  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.pal_gripper import JOINTS, PalGripper  # noqa: E402

DOMAIN = own_domain(47, base=20)  # this module's own ROS_DOMAIN_ID, different per test run
CONTROLLER = "/tiago/gripper_controller"

pytestmark = pytest.mark.timeout(60)

_localhost_ros = domain_fixture(DOMAIN, scope="function")


class Robot:
    """/joint_states published message by message, and the controller's command topic recorded."""

    def __init__(self):
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.JointState = JointState
        self.peer = Peer("s17_robot", DOMAIN)
        self.pub = self.peer.node.create_publisher(JointState, "/joint_states", 10)
        self.sub = self.peer.listen(JointTrajectory, f"{CONTROLLER}/joint_trajectory", "commands")

    def message(self, opening, grip):
        """Both fingers at half ``opening`` (m), squeezing with ``grip`` (N): closing efforts are negative."""
        msg = self.JointState()
        stamp = time.time()
        msg.header.stamp.sec = int(stamp)
        msg.header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)
        msg.name = list(JOINTS)
        msg.position = [opening / 2.0, opening / 2.0]
        msg.velocity = [0.0, 0.0]
        msg.effort = [-grip, -grip]
        return msg

    def connect(self, h, opening, grip):
        """Configure and activate ``h`` while the robot streams ``opening`` and ``grip``; silent once connected."""
        stop = threading.Event()

        def run():
            while not stop.is_set():
                self.pub.publish(self.message(opening, grip))
                time.sleep(0.01)

        th = threading.Thread(target=run, daemon=True)
        th.start()
        try:
            h.__enter__()
        finally:
            stop.set()
            th.join(2.0)
        assert realtime.wait_for(lambda: self.sub.get_publisher_count() > 0, 10.0), "the controller never matched"
        return h

    def deliver(self, h, opening, grip):
        """Publish one message and wait until the driver has used it."""
        n = h.comp._used
        self.pub.publish(self.message(opening, grip))
        assert realtime.wait_for(lambda: h.comp._used > n, 10.0), "the driver did not use the message"

    def sent(self):
        """The openings (m) of the commands received so far."""
        return [m.points[0].positions[0] * 2 for m in self.peer.got["commands"]]

    def close(self):
        self.peer.close()


@pytest.fixture
def robot():
    r = Robot()
    yield r
    r.close()


def harness(logs=None, **params):
    # connect_timeout: a failure bound (a passing start-up ends once connected), generous for DDS discovery
    h = Harness(PalGripper, dict({"namespace": "tiago", "domain_id": DOMAIN, "connect_timeout": 10.0,
                                  "max_speed": 0.1}, **params))
    h.ctx.clock_kind = "wall"
    if logs is not None:
        h.ctx.log = logs.append
    return h


def step(h, cmd):
    h.t = time.monotonic()
    return h.step(h.t, opening_command=cmd)


def close_while_silent(h, seconds):
    """Command 0 mm (the operator keeps closing) every 10 ms for ``seconds`` while /joint_states is silent; the
    lowest set-point reached."""
    lowest = h.comp._setpoint
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        step(h, 0.0)
        lowest = min(lowest, h.comp._setpoint)
        time.sleep(0.01)
    return lowest


# the most the set-point may close on one fresh message: effort_timeout (0.05 s by default) at max_speed (0.1 m/s),
# plus one late step's two nominal periods (the speed limit counts no more), plus rounding
FRESH_CLOSE = 0.1 * (0.05 + 0.02) + 1e-4


def test_closing_is_held_while_the_effort_is_stale(robot):
    """One /joint_states at 30 mm and a 10 N grip (max_effort 16 N), then silence: the set-point closed at max_speed
    towards 0 mm for all of read_timeout against that old 10 N (45 mm in 0.45 s); now it closes no further than the
    fresh message allowed, the commands sent likewise, and the held steps are counted in status()."""
    logs = []
    h = robot.connect(harness(logs, max_effort=16.0, read_timeout=1.0), 0.03, 10.0)
    try:
        robot.deliver(h, 0.03, 10.0)
        lowest = close_while_silent(h, 0.45)
        assert lowest >= 0.03 - FRESH_CLOSE, f"closed to {lowest * 1e3:.1f} mm on a stale effort"
        time.sleep(0.1)
        assert min(robot.sent()) >= 0.03 - FRESH_CLOSE
        st = h.comp.status()
        assert st["stale_effort_holds"] >= 10
        assert any("effort_timeout" in line and "closes no further" in line for line in logs), logs
        assert h.comp.params.effort_timeout == pytest.approx(0.05)   # the default FRESH_CLOSE counts on
    finally:
        h.__exit__(None, None, None)


def test_opening_goes_on_while_the_effort_is_stale(robot):
    """Only closing needs a fresh effort: the operator opening the hand while /joint_states is silent is followed."""
    h = robot.connect(harness(read_timeout=1.0), 0.03, 10.0)
    try:
        t_end = time.monotonic() + 0.4
        while time.monotonic() < t_end:
            step(h, 0.06)
            time.sleep(0.01)
        assert h.comp._setpoint > 0.03 + 0.01   # 0.1 m/s for 0.4 s: up to 40 mm, at least 10 mm on a loaded machine
        assert h.comp.status()["stale_effort_holds"] == 0
    finally:
        h.__exit__(None, None, None)


def test_closing_goes_on_while_the_effort_is_fresh(robot):
    """A fresh message before each step: the set-point closes as before (the limit is max_effort, not reached)."""
    h = robot.connect(harness(max_effort=16.0), 0.03, 10.0)
    try:
        for _ in range(10):
            robot.deliver(h, 0.03, 10.0)
            step(h, 0.0)
            time.sleep(0.005)
        assert h.comp._setpoint < 0.03 - 0.002   # 10 steps of at least 5 ms at 0.1 m/s: 5 mm or more
    finally:
        h.__exit__(None, None, None)


def test_hold_after_the_stale_fault_is_the_measured_opening_not_a_setpoint_inside_the_object(robot):
    """After the read_timeout fault on a silent /joint_states, the hold sent the last set-point (closed at max_speed
    against the old effort, deep inside the object) as the controller's goal, and the position controller squeezed
    with no force limit; it is the last measured opening now (the squeeze released to the object's surface)."""
    h = robot.connect(harness(max_effort=16.0), 0.03, 10.0)
    try:
        robot.deliver(h, 0.03, 10.0)
        with pytest.raises(HardwareError, match=r"/joint_states silent for"):
            close_while_silent(h, realtime.WAIT)   # until the read_timeout fault (a failure bound)
        n = len(robot.sent())
        h.comp.safe_state()
        assert realtime.wait_for(lambda: len(robot.sent()) > n, 10.0)
        assert robot.sent()[-1] == pytest.approx(0.03, abs=1e-6)
    finally:
        h.__exit__(None, None, None)


@pytest.mark.parametrize("fields, match", [({"effort_timeout": 0.5}, r"effort_timeout \(0.5 s\) must be below "
                                                                     r"read_timeout \(0.5 s\)"),
                                           ({"effort_timeout": 50, "read_timeout": 1.0},
                                            r"effort_timeout \(50 s\) must be below read_timeout \(1(\.0)? s\)"),
                                           ({"effort_timeout": 0}, r"effort_timeout\n.*greater than 0")])
def test_effort_timeout_is_validated_naming_the_fields(fields, match):
    """effort_timeout at or above read_timeout would never hold a closing set-point (the read_timeout fault comes
    first); 50 meant 50 ms."""
    with pytest.raises(ValidationError, match=match):
        PalGripper.Params(**fields)
    assert PalGripper.Params(effort_timeout="20ms").effort_timeout == pytest.approx(0.02)
