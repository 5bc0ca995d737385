"""pal-gripper audit: what reaches the driver from the robot (stamps, NaN, units, efforts, message types), names,
limits, speeds of set-point jumps, the safe state against a step in progress, two drivers in one process.

Most tests script the robot message by message: a peer on real ROS 2 (its own DDS participant) publishes
sensor_msgs/JointState on /joint_states with the stamps and values a test chooses, as the joint_state_broadcaster
does, and subscribes to the controller's trajectory_msgs/JointTrajectory topic as joint_trajectory_controller does,
recording what the driver sends. The speed tests use the simulated controller (tests/fakes/pal_gripper_node.py).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes import realtime  # noqa: E402
from fakes.pal_gripper_node import PalGripperNode  # noqa: E402
from fakes.realtime import configure_fails  # noqa: E402
from fakes.ros2_peer import Peer, domain_fixture, own_domain  # noqa: E402

from teletouch import HardwareError  # noqa: E402
from teletouch.testing import Harness  # noqa: E402
from teletouch.plugins.devices.pal_gripper import JOINTS, PalGripper  # noqa: E402

DOMAIN = own_domain(5, base=20)  # this module's own ROS_DOMAIN_ID, different per test run
COMMAND = "/tiago/gripper_controller/joint_trajectory"

pytestmark = pytest.mark.timeout(60)


_localhost_ros = domain_fixture(DOMAIN, scope="function")


def harness(**params):
    # connect_timeout: a failure bound (a passing start-up ends once connected), generous for DDS discovery on a
    # loaded 2-core machine; the tests that expect start-up to fail set their own
    h = Harness(PalGripper, dict({"namespace": "tiago", "domain_id": DOMAIN, "connect_timeout": 10.0}, **params))
    h.ctx.clock_kind = "wall"
    return h


class ScriptedRobot:
    """The robot's two ROS 2 interfaces, scripted: JointState messages with chosen stamps and values, and a
    subscription per controller that records the JointTrajectory messages it receives."""

    def __init__(self, controllers=("/tiago/gripper_controller",), states_topic="/joint_states", state_type=None):
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.JointState = JointState
        self.peer = Peer("scripted_robot", DOMAIN)
        self.pub = self.peer.node.create_publisher(state_type or JointState, states_topic, 10)
        self.subs = {c: self.peer.listen(JointTrajectory, f"{c}/joint_trajectory", c) for c in controllers}
        self.t0 = time.time()
        self._streaming = None

    def message(self, pos, stamp=None, vel=(0.0, 0.0), eff=(0.0, 0.0), names=JOINTS):
        msg = self.JointState()
        stamp = time.time() if stamp is None else stamp
        msg.header.stamp.sec = int(stamp)
        msg.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9)) % 1_000_000_000
        msg.name = list(names)
        msg.position = [float(x) for x in pos]
        msg.velocity = [float(x) for x in vel]
        msg.effort = [float(x) for x in eff]
        return msg

    def stream(self, make):
        """Publish ``make()`` every 10 ms in a thread until stop_stream() (while a driver connects)."""
        stop = threading.Event()

        def run():
            while not stop.is_set():
                self.pub.publish(make())
                time.sleep(0.01)

        th = threading.Thread(target=run, daemon=True)
        th.start()
        self._streaming = (stop, th)

    def stop_stream(self):
        if self._streaming is not None:
            self._streaming[0].set()
            self._streaming[1].join(2.0)
            self._streaming = None

    def deliver(self, h, msg):
        """Publish one message and wait until the driver has received it."""
        n = h.comp._msgs
        self.pub.publish(msg)
        assert realtime.wait_for(lambda: h.comp._msgs > n, 10.0), "the driver did not receive the message"

    def commands(self, controller="/tiago/gripper_controller"):
        return self.peer.got[controller]

    def close(self):
        self.stop_stream()
        self.peer.close()


@pytest.fixture
def scripted():
    r = ScriptedRobot()
    yield r
    r.close()


def connect(robot, h, pos=(0.02, 0.02), eff=(0.0, 0.0)):
    """Configure and activate ``h`` while the robot streams ``pos``; the stream stops once connected."""
    robot.stream(lambda: robot.message(pos, eff=eff))
    try:
        h.__enter__()
    finally:
        robot.stop_stream()
    # The driver starts once its publisher has matched the controller, but DDS matches the two ends one at a time:
    # until the controller's end has matched too, what the driver sends is dropped there (and with the command
    # history of depth 1 only the latest is sent again). Tests that count commands wait for both ends.
    for sub in robot.subs.values():
        assert realtime.wait_for(lambda s=sub: s.get_publisher_count() > 0, 10.0), "the controller never matched"
    return h


def step(h, cmd):
    h.t = time.monotonic()
    return h.step(h.t, opening_command=cmd)


# --- start-up: the domain, names and limits ---------------------------------------------------------------------
def test_ros_domain_id_out_of_range_is_a_clear_error_not_the_end_of_the_process():
    """ROS_DOMAIN_ID=500 with no domain_id param: Fast DDS ended the whole process (no message, no safe state for the
    other devices); a word gave rcl's RCLError. Both are a HardwareError naming ROS_DOMAIN_ID now."""
    code = ("from teletouch.testing import Harness\n"
            "from teletouch.plugins.devices.pal_gripper import PalGripper\n"
            "h = Harness(PalGripper, {'connect_timeout': 0.3})\n"
            "try:\n"
            "    h.comp.configure()\n"
            "except Exception as exc:\n"
            "    print('ERROR', type(exc).__name__, exc)\n"
            "finally:\n"
            "    h.comp.close()\n"
            "print('still running')\n")
    for value in ("500", "abc"):
        env = dict(os.environ, ROS_DOMAIN_ID=value)
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=40)
        assert "still running" in res.stdout, (value, res.stdout, res.stderr[-500:])
        assert f"ERROR HardwareError ROS_DOMAIN_ID='{value}': expected an integer from 0 to 232" in res.stdout


@pytest.mark.parametrize("field, value", [("namespace", "my-robot"), ("controller", "gripper-controller"),
                                          ("controller", "/gripper_controller"),
                                          ("joint_states_topic", "/joint states"),
                                          ("joint_names", ["gripper_left_finger_joint"] * 2),
                                          ("joint_names", ["", "gripper_right_finger_joint"])])
def test_bad_names_are_refused_naming_the_field(field, value):
    """Names ROS 2 refuses (or duplicate joints, whose opening would be twice one finger) failed only at start-up,
    with rclpy's InvalidTopicNameException naming no field, or not at all."""
    with pytest.raises(ValidationError, match=rf"{field}\n.*expected"):
        PalGripper.Params(**{field: value})


@pytest.mark.parametrize("fields, match", [({"max_opening": 90}, r"max_opening \(90 m\) is beyond any gripper's "
                                                                 r"opening .*millimetres in the metre field"),
                                           ({"max_opening": 0.5}, r"max_opening \(0.5 m\) is outside what the "
                                                                  r"fingers reach, 0-90 mm"),
                                           ({"max_opening": 0.1}, r"max_opening \(0.1 m\) is outside"),
                                           ({"min_opening": 0.01, "finger_lower": 0.01, "finger_upper": 0.04},
                                            r"min_opening \(0.01 m\) is outside what the fingers reach, 20-80 mm"),
                                           ({"finger_lower": 0.045}, r"finger_lower .* must be below finger_upper")])
def test_limits_beyond_the_joints_are_refused(fields, match):
    """max_opening: 90 (millimetres) was taken as 90 m: the open safe state sent each finger to 45 m."""
    with pytest.raises(ValidationError, match=match):
        PalGripper.Params(**fields)
    assert PalGripper.Params(max_opening="90mm").max_opening == pytest.approx(0.09)


def test_relative_joint_states_topic_is_inside_the_namespace():
    r = ScriptedRobot(states_topic="/tiago/joint_states")
    try:
        h = connect(r, harness(joint_states_topic="joint_states"))
        try:
            assert h.comp.state_topic == "/tiago/joint_states"
            assert step(h, 0.04)["opening"] == pytest.approx(0.04)
        finally:
            h.__exit__(None, None, None)
    finally:
        r.close()


def test_another_message_type_on_the_state_topic_is_named():
    """A std_msgs/String publisher on /joint_states: DDS connects nothing, and start-up said only 'no message ...
    check the joint names'."""
    from std_msgs.msg import String

    r = ScriptedRobot(state_type=String)
    try:
        r.stream(lambda: String(data="not a joint state"))
        # (connect_timeout: what the test waits, long enough for discovery on a loaded machine: before it, the
        # error cannot name the other publisher)
        configure_fails(harness(connect_timeout=5.0), r"/joint_states: no message .*a publisher of node "
                                                      r"/peer/scripted_robot on /joint_states uses "
                                                      r"std_msgs/msg/String, not sensor_msgs/msg/JointState")
    finally:
        r.close()


def test_two_drivers_may_not_command_one_controller(scripted):
    """A second pal-gripper on the same controller was accepted: the two fight (the controller follows the last)."""
    h1 = connect(scripted, harness())
    try:
        h2 = harness()
        h2.comp.id = "second"
        scripted.stream(lambda: scripted.message((0.02, 0.02)))
        configure_fails(h2, r"node 'pal-gripper' already commands /tiago/gripper_controller/joint_trajectory")
        scripted.stop_stream()
    finally:
        h1.__exit__(None, None, None)
    h3 = connect(scripted, harness())  # released at close
    h3.__exit__(None, None, None)


def test_two_grippers_on_one_robot():
    """Two grippers of one robot (TIAGo++-like): one /joint_states, two controllers with their own joints."""
    names = ("l_left", "l_right", "r_left", "r_right")
    r = ScriptedRobot(controllers=("/tiago/left_controller", "/tiago/right_controller"))
    try:
        r.stream(lambda: r.message((0.01, 0.01, 0.03, 0.03), vel=(0,) * 4, eff=(0,) * 4, names=names))
        left = harness(controller="left_controller", joint_names=["l_left", "l_right"])
        right = harness(controller="right_controller", joint_names=["r_left", "r_right"])
        left.comp.id, right.comp.id = "left", "right"
        for h in (left, right):
            h.__enter__()
        try:
            assert step(left, 0.02)["opening"] == pytest.approx(0.02)
            assert step(right, 0.06)["opening"] == pytest.approx(0.06)
            assert realtime.wait_for(lambda: r.commands("/tiago/left_controller") and
                                     r.commands("/tiago/right_controller"), 10.0)
            assert list(r.commands("/tiago/left_controller")[-1].joint_names) == ["l_left", "l_right"]
            assert list(r.commands("/tiago/right_controller")[-1].points[0].positions) == [0.03, 0.03]
        finally:
            for h in (left, right):
                h.__exit__(None, None, None)
    finally:
        r.close()


# --- run time: what /joint_states carries -----------------------------------------------------------------------
def test_out_of_order_and_repeated_joint_states_are_not_new(scripted):
    """An older message after a newer one moved the measured opening back (40 -> 50 -> 40 mm), and the same
    message sent again and again kept a frozen state fresh for ever."""
    # read_timeout 1 s: the deliveries before the last check (each waited for) must fit in it on a loaded machine
    h = connect(scripted, harness(read_timeout=1.0))
    try:
        t = time.time()
        scripted.deliver(h, scripted.message((0.025, 0.025), stamp=t + 0.02))
        assert step(h, 0.05)["opening"] == pytest.approx(0.05)
        scripted.deliver(h, scripted.message((0.02, 0.02), stamp=t + 0.01))  # older: out of order
        assert step(h, 0.05)["opening"] == pytest.approx(0.05)
        frozen = scripted.message((0.03, 0.03), stamp=t + 0.02)  # the newest stamp again, other values
        scripted.deliver(h, frozen)
        assert step(h, 0.05)["opening"] == pytest.approx(0.05)
        t_end = time.monotonic() + realtime.WAIT   # a failure bound
        with pytest.raises(HardwareError, match=r"/joint_states: no usable message for 1\.\d+ s \(read_timeout 1.0 "
                                                r"s\): \d+ messages stamped no later than the last message used"):
            while time.monotonic() < t_end:
                scripted.deliver(h, frozen)
                step(h, 0.05)
                time.sleep(0.01)
        assert h.comp.status()["dropped"]["older"] >= 2
    finally:
        h.__exit__(None, None, None)


def test_one_message_stamped_in_the_future_is_dropped(scripted):
    """A message stamped 1000 s ahead was taken like any other; as the newest stamp it would also shut out every
    later message: it is dropped and the stream goes on."""
    h = connect(scripted, harness())
    try:
        scripted.deliver(h, scripted.message((0.01, 0.01), stamp=time.time() + 1000.0))
        assert step(h, 0.04)["opening"] == pytest.approx(0.04)
        scripted.deliver(h, scripted.message((0.025, 0.025)))
        assert step(h, 0.04)["opening"] == pytest.approx(0.05)
        assert h.comp.status()["dropped"] == {"ahead": 1}
    finally:
        h.__exit__(None, None, None)


def test_zero_stamps_are_refused(scripted):
    scripted.stream(lambda: scripted.message((0.02, 0.02), stamp=0.0))
    # (connect_timeout: long enough for discovery on a loaded machine, or the error is 'no controller subscribes')
    configure_fails(harness(connect_timeout=5.0), r"/joint_states: no usable message: \d+ messages with a zero "
                                                  r"header.stamp")


def test_positions_in_millimetres_are_refused_at_start(scripted):
    """Finger positions in millimetres (22.5 each) were taken as metres: a 45 m opening, followed at max_speed."""
    scripted.stream(lambda: scripted.message((22.5, 22.5)))
    configure_fails(harness(connect_timeout=5.0), r"\d+ messages with a finger position outside the joint range "
                                                  r"\(last: gripper_left_finger_joint = 22.5, outside 0-45 mm "
                                                  r"\(finger_lower/finger_upper\): millimetres or radians")


def test_bad_positions_at_run_time_are_not_used_and_fault_after_read_timeout(scripted):
    # read_timeout 1 s: the deliveries before the last check (each waited for) must fit in it on a loaded machine
    h = connect(scripted, harness(read_timeout=1.0))
    try:
        scripted.deliver(h, scripted.message((0.06, 0.02)))  # beyond the left finger's 45 mm: was an 80 mm opening
        assert step(h, 0.04)["opening"] == pytest.approx(0.04)  # the last usable state
        scripted.deliver(h, scripted.message((math.nan, 0.02)))
        assert step(h, 0.04)["opening"] == pytest.approx(0.04)
        with pytest.raises(HardwareError, match=r"no usable message .* 1 messages with a finger position outside "
                                                r"the joint range .*1 messages with a non-finite finger position"):
            t_end = time.monotonic() + realtime.WAIT   # a failure bound
            while time.monotonic() < t_end:
                step(h, 0.04)
                time.sleep(0.01)
    finally:
        h.__exit__(None, None, None)


def test_non_finite_velocity_is_not_output(scripted):
    """A NaN velocity in /joint_states went out on the velocity port; the finite difference is used instead."""
    h = connect(scripted, harness())
    try:
        scripted.deliver(h, scripted.message((0.02, 0.02), vel=(math.nan, 0.0)))
        step(h, 0.04)
        time.sleep(0.02)
        scripted.deliver(h, scripted.message((0.021, 0.021), vel=(math.nan, 0.0)))
        o = step(h, 0.04)
        assert math.isfinite(o["velocity"]) and o["velocity"] > 0.0
    finally:
        h.__exit__(None, None, None)


def test_effort_is_the_squeeze_not_the_magnitude(scripted):
    """effort was the mean effort magnitude: a sideways push (one finger +8 N, the other -8 N) read as an 8 N grip,
    and above max_effort it kept the fingers from closing; a push outwards read as a grip too."""
    # effort_timeout 0.4 s: the closing step after the last message must not find its effort stale on a loaded machine
    h = connect(scripted, harness(max_effort=5.0, max_speed=0.1, effort_timeout=0.4))
    try:
        scripted.deliver(h, scripted.message((0.02, 0.02), eff=(-6.0, -6.0)))
        assert step(h, 0.04)["effort"] == pytest.approx(6.0)  # closing efforts are negative: a 6 N squeeze
        scripted.deliver(h, scripted.message((0.02, 0.02), eff=(3.0, 3.0)))
        assert step(h, 0.04)["effort"] == pytest.approx(-3.0)  # pushing outwards
        scripted.deliver(h, scripted.message((0.02, 0.02), eff=(8.0, -8.0)))
        assert step(h, 0.04)["effort"] == pytest.approx(0.0)
        before = h.comp._setpoint
        time.sleep(0.02)
        step(h, 0.0)  # closing is not held back by a sideways push
        assert h.comp._setpoint < before - 1e-3
    finally:
        h.__exit__(None, None, None)


# --- the safe state ---------------------------------------------------------------------------------------------
def test_safe_state_from_another_thread_goes_out_after_a_step_in_progress(scripted):
    """safe_state() (the watchdog's thread) during a step: the hold went out first (or, equal to the last set-point
    sent, not at all) and the step's command after it, so the controller was left on the command."""
    # effort_timeout 1.5 s: the step's closing command, after the last message of the connection, must not be held
    # as closing on a stale effort on a loaded machine
    h = connect(scripted, harness(max_speed=0.1, read_timeout=2.0, effort_timeout=1.5))
    try:
        step(h, 0.03)  # sends the measured 40 mm (no time elapsed yet)
        computed, go = threading.Event(), threading.Event()
        original = h.comp.command_target

        def slow_target(t, inputs):
            target = original(t, inputs)
            computed.set()
            go.wait(10.0)   # (released by the test; a bound only)
            return target

        h.comp.command_target = slow_target
        time.sleep(0.01)
        stepper = threading.Thread(target=step, args=(h, 0.03))
        stepper.start()
        assert computed.wait(10.0)
        safe = threading.Thread(target=h.comp.safe_state)
        safe.start()
        time.sleep(0.1)
        go.set()
        stepper.join(10.0)
        safe.join(10.0)
        # (bounds only: on a loaded machine the scripted controller's executor takes its time to take the messages)
        assert realtime.wait_for(lambda: len(scripted.commands()) >= 3, 10.0)
        time.sleep(0.1)
        sent = [m.points[0].positions[0] * 2 for m in scripted.commands()]
        assert sent[-2] < 0.04 - 1e-4  # the step's command, then the hold of the measured opening last
        assert sent[-1] == pytest.approx(0.04)
    finally:
        h.__exit__(None, None, None)


def _command_until_silent(h, opening: float) -> float:
    """Command ``opening`` every 10 ms while /joint_states stays silent, until the read_timeout fault; the set-point
    reached then."""
    t_end = time.monotonic() + realtime.WAIT   # a failure bound
    with pytest.raises(HardwareError, match=r"/joint_states silent for"):
        while time.monotonic() < t_end:
            step(h, opening)
            time.sleep(0.01)
    return h.comp._setpoint


def _safe_state_command(h, scripted):
    """safe_state(), and the trajectory point it sent."""
    n = len(scripted.commands())
    h.comp.safe_state()
    assert realtime.wait_for(lambda: len(scripted.commands()) > n, 10.0)
    return scripted.commands()[-1].points[0]


def test_hold_after_the_state_went_stale_keeps_the_last_setpoint_not_the_stale_measurement(scripted):
    """/joint_states went silent while the command moved the set-point on (the controller took the fingers along):
    the read_timeout fault's hold sent the last measured opening, a second old, as a 10 ms goal, so the fingers
    snapped back by all they had moved since (40 mm instead of 90); with the state stale it holds the last set-point
    sent, where the controller has the fingers (wider than the stale opening: opening goes on on a stale state)."""
    h = connect(scripted, harness(max_speed=0.1, read_timeout=1.0))
    try:
        last = _command_until_silent(h, 0.09)
        assert last > 0.06   # moved on, from the measured 40 mm, while the state was silent
        hold = _safe_state_command(h, scripted)
        assert hold.positions[0] * 2 == pytest.approx(last)
    finally:
        h.__exit__(None, None, None)


def test_open_safe_state_after_the_state_went_stale_takes_the_time_max_speed_needs(scripted):
    """/joint_states went silent at 90 mm while the command closed the set-point to 40 mm (the controller took the
    fingers along): the open safe state timed its move from the stale finger positions (no distance) and sent 90 mm
    to be reached in time_from_start (10 ms), 50 mm at 5 m/s; it counts from the last set-point sent too.
    (effort_timeout 0.9 s: the set-point closes on the silent state for that long, which the default 0.05 s holds.)"""
    h = connect(scripted, harness(safe_mode="open", max_speed=0.1, read_timeout=1.0, effort_timeout=0.9),
                pos=(0.045, 0.045))
    try:
        last = _command_until_silent(h, 0.04)
        assert last < 0.07   # closed, from the measured 90 mm, while the state was silent
        pt = _safe_state_command(h, scripted)
        assert pt.positions[0] * 2 == pytest.approx(0.09)
        duration = pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9
        assert duration >= (0.09 - last) / 0.1 - 1e-6
    finally:
        h.__exit__(None, None, None)


# --- speeds of set-point jumps (the simulated controller) -------------------------------------------------------
@pytest.fixture
def robot():
    r = PalGripperNode("/tiago", domain_id=DOMAIN, object_width=None)
    r.start()
    yield r
    r.stop()


def test_open_safe_state_moves_no_faster_than_max_speed():
    """The open safe state sent max_opening to be reached in time_from_start (10 ms): the controller ran the
    fingers at their hardware limit (0.1 m/s of opening) whatever max_speed said (0.02 m/s here)."""
    with PalGripperNode("/tiago", domain_id=DOMAIN, opening=0.07) as robot, \
            harness(safe_mode="open", max_speed=0.02) as h:
        realtime.drive(h, 0.07, 0.2, period=0.01)
        assert robot.opening == pytest.approx(0.07, abs=1e-3)
        start = robot.opening
        t0 = time.monotonic()
        h.comp.safe_state()
        time.sleep(0.5)
        moved = robot.opening - start
        # the bound from the time that really passed (a loaded machine oversleeps), measured after the reading
        assert 0.002 < moved < 0.02 * (time.monotonic() - t0) + 0.003  # 0.1 m/s would be 20 mm (all the way)


def test_gripper_resting_outside_the_range_is_walked_in_at_max_speed(robot):
    """Resting at 90 mm with max_opening 50 mm: the driver clamped the set-point to 50 mm and sent it to be reached
    in 10 ms (the fingers closed at 0.1 m/s); the base walks it in at max_speed (0.02 m/s)."""
    with harness(max_opening=0.05, max_speed=0.02) as h:
        start = robot.opening
        assert start == pytest.approx(0.09, abs=1e-3)
        t0 = time.monotonic()   # (nothing is commanded before the first step)
        realtime.drive(h, 0.05, 0.5, period=0.01)
        moved = start - robot.opening
        # the bound from the time that really passed (a loaded machine makes the last step late)
        assert 0.002 < moved < 0.02 * (time.monotonic() - t0) + 0.003


def test_robot_gone_is_not_reported_as_a_controller_gone_while_states_go_on():
    """The whole robot goes away (controller and /joint_states): the controller check, first to time out, said
    '/joint_states goes on: the controller was unloaded or crashed'."""
    robot = PalGripperNode("/tiago", domain_id=DOMAIN).start()
    # read_timeout well above controller_timeout: DDS noticing the controller's subscription gone (which a loaded
    # machine delays) must not let the read timeout fire first; the controller check then still comes first
    h = harness(controller_timeout=0.3, read_timeout=5.0).__enter__()
    try:
        realtime.drive(h, 0.08, 0.2, period=0.01)
        robot.stop()
        with pytest.raises(HardwareError, match=r"no controller is subscribed to .* for 0\.\d+ s \(controller_timeout "
                                                r"0.3 s\) and /joint_states is silent for \d\.\d+ s: the robot or the "
                                                r"network is gone"):
            realtime.drive(h, 0.08, realtime.WAIT, period=0.01)
        h.comp.safe_state()  # never raises with the robot gone
    finally:
        h.__exit__(None, None, None)
