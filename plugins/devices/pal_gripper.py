"""pal-gripper: PAL Robotics' parallel gripper through ROS 2 (rclpy): joint trajectories in, /joint_states out.

The gripper has two prismatic finger joints (``gripper_left_finger_joint``, ``gripper_right_finger_joint``, 0-0.045 m
each, ``finger_lower``/``finger_upper``); the opening is their sum. Each step publishes, when the setpoint changed
(and at least every ``republish_period`` so that the controller keeps its goal), a trajectory_msgs/JointTrajectory
with one point (both fingers at half the opening) on ``<namespace>/<controller>/joint_trajectory`` -- the topic
joint_trajectory_controller accepts besides its action. The point is reached after ``time_from_start``, or after
as long as the farther finger needs at ``max_speed`` (each finger moves at half the opening's speed; counted from the
measured fingers and from the last goal sent, where the controller takes them: the measurement may be stale), so that a
setpoint jump (the ``open`` safe state, a gripper resting outside [min_opening, max_opening] walked into it) never
moves the fingers faster than ``max_speed``: the controller interpolates at the speed it is given. A setpoint is
never sent beyond the joints' range, nor non-finite.

The state comes from sensor_msgs/JointState on ``joint_states_topic`` (``/joint_states``; a relative name is taken
inside ``namespace``): opening = sum of the finger positions, velocity likewise (finite differences where it is
missing or not finite), effort = the grip force -(e_left + e_right) / 2 (a finger's effort is positive in its
opening direction, so a squeeze reads positive, a push outwards negative and a sideways push, one finger in and one
out, zero), NaN when the message carries none. A message is used only when it carries both finger joints with
finite positions within the joints' range (``RANGE_TOLERANCE`` beyond it: a position in millimetres or radians
is refused, not taken for metres) and a header stamp that is not zero, later than the last message used (an older
one, out of order, or the same one sent again is not a new measurement) and not ahead of the stream (stamp minus
arrival time grown by more than ``read_timeout``: one message stamped in the future would otherwise shut out all
the following ones). Refused messages are counted by reason (``status()``); no usable message for ``read_timeout``
is a HardwareError that names the reasons. A sample's stamp is the arrival time of its message.

The position controller has no force limit of its own, so ``max_effort`` is enforced here: while the reported effort
exceeds it, the setpoint backs off towards the measured opening (at ``max_speed``) instead of closing further. That
needs efforts in ``/joint_states``: without them (or with non-finite ones) the driver refuses to run (a HardwareError
at start-up or at the message that lacks them) unless ``enforce_effort: false`` says to run without the force limit
(the effort output is then NaN; there is no ``effort_timeout`` hold either). It needs them fresh too: while the
last message is older than ``effort_timeout`` (0.05 s: 5 messages at 100 Hz; below ``read_timeout``) the setpoint
closes no further than the last measured opening, nor further than it was where it was already below it (a squeeze
is held, not tightened); opening goes on. Each step held so is counted (``status()['stale_effort_holds']``) and the
first of each stale spell logged. (The setpoint closed at ``max_speed`` against the old effort until the
``read_timeout`` fault.)

A controller that goes away while ``/joint_states`` keeps arriving (unloaded, crashed) is noticed too: every read
checks that something still subscribes to the command topic, and ``controller_timeout`` without a subscriber is a
HardwareError (how soon DDS reports a crashed process's subscription gone is its liveliness lease; a controller
that is unloaded or shut down cleanly is gone at once). Start-up names an endpoint of another message type on
either topic (DDS does not connect the two, silently). When no controller subscribes to the command topic (a wrong
``namespace`` or ``controller``), start-up names the JointTrajectory subscriptions the ROS graph has
(``get_topic_names_and_types``; looking until ``GRAPH_WAIT`` after joining it while there is none, for DDS to discover
the robot), each with the namespace/controller params that select it and the JointState topic the driver would then
read (``joint_states_topic`` where nothing publishes on it); when no JointState message comes, the topics that have a
JointState publisher. Two pal-gripper nodes of one process may not command the same controller (the controller
follows whichever sent last), nor may two processes or another ROS node: start-up
asks the ROS graph for the command topic's other JointTrajectory publishers (``get_publishers_info_by_topic``; this
driver's own is left out, even where another teletouch has the same node name) and refuses to start while there is
one, naming its node and namespace. DDS needs a moment to discover the other participants: ``discovery_wait`` keeps
looking until that long after joining the graph (default 0: one look once connected, which can miss a commander
not discovered yet). The same look runs once a second while running (``PUBLISHER_CHECK_PERIOD``), and a commander
found then (started later, or discovered late) is a HardwareError, so the graph goes to its safe state: a second
commander can override this driver's hold and moves the fingers where the operator's hand does not say, while the
operator still feels the force. ``allow_other_publishers: true`` (for a lab that arbitrates its commanders itself)
runs anyway; the others are then named in ``status()['other_publishers']`` and logged once each.
Commands through the controller's FollowJointTrajectory action are not seen by this check.

Safe state: ``hold`` sends the measured opening (the controller holds the fingers there: a squeeze is released to
the object's surface), also while the state is stale (no usable message for ``effort_timeout``), unless the last
setpoint sent is wider: opening goes on while the state is stale, the fingers have followed the setpoint since, and
the stale opening would close them back with no force reading (the hold sent the last setpoint whatever it was,
after a ``read_timeout`` fault deep inside the object); ``open`` sends ``max_opening``; either is always sent, and a
step's command and send hold a lock, so a safe_state() from another thread waits for a step in progress and its hold
goes out last.

QoS: ``state_reliability``/``state_depth`` (best-effort, 1: hears a reliable and a best-effort broadcaster) and
``command_reliability``/``command_depth`` (reliable, 1: serves the controller's reliable subscription), volatile both
ways. A robot endpoint with incompatible QoS (DDS connects neither, silently) is named with the topic, the policy
and both values (teletouch.plugins.ros_qos) in the start-up error, ``status()['qos_problems']`` and the log.

rclpy is imported lazily (``pip install teletouch[ros2]``). The driver owns its rclpy Context, node and executor thread
(never rclpy's global context), so it coexists with other ROS 2 users (e.g. the ROS 2 bridge) in the same process.
``ROS_DOMAIN_ID`` is checked before DDS sees it (Fast DDS ends the whole process, with no safe state for the other
devices, for a domain above 232).
"""

from __future__ import annotations

import math
import re
import threading
import time
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from teletouch import HardwareError, hookimpl
from teletouch.units import Meters, MetersPerSecond, Newtons, Seconds, millimetres_in_metres

from .. import ros_names, ros_qos
from .follower_common import FollowerBase, FollowerParams, Reading, clamp

JOINTS = ("gripper_left_finger_joint", "gripper_right_finger_joint")
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
TRAJECTORY_TYPE = "trajectory_msgs/msg/JointTrajectory"
RANGE_TOLERANCE = 0.003  # m a finger may read beyond its joint range (calibration) before the reading is refused
PUBLISHER_CHECK_PERIOD = 1.0  # s between two looks at the command topic's other publishers while running
NAME_WAIT = 0.5  # s given to the ROS graph to learn the node name of a publisher DDS has announced
GRAPH_WAIT = 1.0  # s after joining the graph that a failed start-up keeps looking for the controllers it can name
MAX_LISTED = 8  # controllers / JointState topics named in a start-up error at most
EMPTY = '""'  # the default namespace, as a graph writes it
_UNNAMED = "(a participant the ROS graph has no node name for: a plain DDS writer, or one still being discovered)"

# ROS 2 names (teletouch.plugins.ros_names), checked when the graph is validated rather than refused by rclpy at
# start-up
_TOKEN = ros_names.TOKEN
_NAMESPACE_RE = re.compile(rf"(?:/{_TOKEN})*")
_RELATIVE_RE = re.compile(rf"{_TOKEN}(?:/{_TOKEN})*")
_TOPIC_RE = re.compile(rf"/?{_TOKEN}(?:/{_TOKEN})*")

_IN_USE: dict[tuple[int, str], str] = {}  # (domain, command topic) -> id of the node commanding it in this process
_IN_USE_LOCK = threading.Lock()

_REASONS = {  # why a JointState message was not used (keys of status()['dropped'])
    "joints": "without both joints",
    "malformed": "with fewer positions than names",
    "nonfinite": "with a non-finite finger position",
    "range": "with a finger position outside the joint range",
    "zero_stamp": "with a zero header.stamp",
    "older": "stamped no later than the last message used (out of order, or sent again)",
    "ahead": "stamped ahead of the stream",
}


def _selects(topic: str) -> tuple[str, str] | None:
    """The namespace and controller params whose command topic is ``topic`` (``<namespace>/<controller>/
    joint_trajectory``, the controller the last name before it); None for a topic of another form."""
    suffix = "/joint_trajectory"
    if not topic.endswith(suffix):
        return None
    namespace, _, controller = topic[:-len(suffix)].rpartition("/")
    if not _RELATIVE_RE.fullmatch(controller) or not _NAMESPACE_RE.fullmatch(namespace):
        return None
    return namespace, controller


def _qos_hint(policy: str, side: str) -> str:
    """What to set when the driver's ``side`` and the robot's endpoint have incompatible ``policy``."""
    if policy == "RELIABILITY":
        return ("set state_reliability: best_effort to hear a best-effort /joint_states publisher"
                if side == "subscription" else "the controller subscribes reliable: set command_reliability: reliable")
    if policy == "DURABILITY":
        return ("the controller's subscription asks transient_local; this driver publishes volatile only (a "
                "latched command would reach a controller that starts later): make the controller's volatile"
                if side == "publisher" else "make the two QoS settings compatible")
    return "make the two QoS settings compatible"


class _Refused(Exception):
    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


def ros_domain_id(param: int | None) -> int | None:
    """The domain to join (:func:`teletouch.plugins.ros_names.domain_id`); a bad ROS_DOMAIN_ID is a HardwareError."""
    return ros_names.domain_id(param, HardwareError)


def parse_joint_state(msg: Any, joints: tuple[str, str] | list[str], lower: float,
                      upper: float) -> tuple[tuple[float, float], float | None, float]:
    """The finger positions (m), the opening velocity (m/s, None where missing or not finite) and the grip force
    (N, NaN where missing) of a JointState message; raises _Refused when the message cannot be used."""
    names = list(msg.name)
    try:
        idx = [names.index(j) for j in joints]
    except ValueError:
        raise _Refused("joints", f"names {names[:8]}") from None
    if max(idx) >= len(msg.position):
        raise _Refused("malformed", f"{len(names)} names, {len(msg.position)} positions")
    pos = (float(msg.position[idx[0]]), float(msg.position[idx[1]]))
    for j, x in zip(joints, pos):
        if not math.isfinite(x):
            raise _Refused("nonfinite", f"{j} = {x}")
        if not lower - RANGE_TOLERANCE <= x <= upper + RANGE_TOLERANCE:
            raise _Refused("range", f"{j} = {x:g}, outside {lower * 1e3:g}-{upper * 1e3:g} mm "
                                    f"(finger_lower/finger_upper): millimetres or radians instead of metres, or "
                                    f"another joint?")
    vel = None
    if len(msg.velocity) == len(names):
        v = float(msg.velocity[idx[0]]) + float(msg.velocity[idx[1]])
        vel = v if math.isfinite(v) else None
    eff = math.nan
    if len(msg.effort) == len(names):
        eff = -0.5 * (float(msg.effort[idx[0]]) + float(msg.effort[idx[1]]))
    return pos, vel, eff


class PalGripper(FollowerBase):
    """PAL parallel gripper over ROS 2 (JointTrajectory commands, /joint_states feedback)."""

    name = "pal-gripper"
    default_rate = 100.0
    requires_wall_clock = True  # the robot moves in real time; speed limits use the graph's time steps

    class Params(FollowerParams):
        namespace: str = Field("", description="ROS namespace of the robot (e.g. /tiago)")
        controller: str = Field("gripper_controller", description="joint_trajectory_controller's name")
        joint_names: list[str] = Field(list(JOINTS), min_length=2, max_length=2,
                                       description="left and right finger joints")
        joint_states_topic: str = Field("/joint_states", description="sensor_msgs/JointState topic (a relative "
                                        "name is taken inside namespace)")
        domain_id: int | None = Field(None, ge=0, le=ros_names.MAX_DOMAIN_ID,
                                      description="ROS_DOMAIN_ID (None: from the environment)")
        finger_lower: Meters = Field(0.0, ge=0, description="each finger joint's lower limit (closed)",
                                     json_schema_extra={"unit": "m"})
        finger_upper: Meters = Field(0.045, gt=0, description="each finger joint's upper limit (open)",
                                     json_schema_extra={"unit": "m"})
        max_opening: Meters = Field(0.09, gt=0, description="largest opening (2 x 0.045 m)",
                                    json_schema_extra={"unit": "m"})
        max_speed: MetersPerSecond = Field(0.1, gt=0, description="opening speed limit (2 x 0.05 m/s per finger)",
                                           json_schema_extra={"unit": "m/s"})
        max_effort: Newtons = Field(16.0, gt=0, description="grip force above which the fingers close no further",
                                    json_schema_extra={"unit": "N"})
        time_from_start: Seconds = Field(0.01, gt=0, description="time given to reach each setpoint: one period of "
                                         "the node's stream (100 Hz: 10 ms), so each setpoint is reached as the "
                                         "next arrives; longer makes every setpoint a partial step and the "
                                         "follower lags (a larger step gets the time max_speed needs)",
                                         json_schema_extra={"unit": "s"})
        republish_period: Seconds = Field(0.1, gt=0, description="resend an unchanged setpoint this often",
                                          json_schema_extra={"unit": "s"})
        connect_timeout: Seconds = Field(3.0, gt=0, description="wait this long for the controller and "
                                         "/joint_states at start", json_schema_extra={"unit": "s"})
        controller_timeout: Seconds = Field(0.5, gt=0, description="fault when nothing has subscribed to the "
                                            "command topic for this long (the controller is gone)",
                                            json_schema_extra={"unit": "s"})
        enforce_effort: bool = Field(True, description="max_effort needs efforts in /joint_states: refuse to run "
                                     "without them (false: run without the force limit, effort output NaN)")
        effort_timeout: Seconds = Field(0.05, gt=0, description="a set-point that closes further than the last "
                                        "measured opening needs a /joint_states message younger than this (100 Hz: "
                                        "5 messages); on an older one it holds, as max_effort cannot be enforced on "
                                        "an old effort (opening goes on; not with enforce_effort: false); below "
                                        "read_timeout",
                                        json_schema_extra={"unit": "s"})
        state_reliability: Literal["best_effort", "reliable"] = Field(
            "best_effort", description="QoS reliability of the /joint_states subscription: best_effort hears both "
            "a reliable and a best-effort publisher; reliable hears a reliable one only")
        state_depth: int = Field(1, ge=1, le=1000, description="QoS history depth of the /joint_states "
                                 "subscription (keep last N; the newest state is what counts)")
        command_reliability: Literal["reliable", "best_effort"] = Field(
            "reliable", description="QoS reliability of the command publisher: reliable serves both a reliable "
            "and a best-effort subscription (joint_trajectory_controller subscribes reliable)")
        command_depth: int = Field(1, ge=1, le=1000, description="QoS history depth of the command publisher "
                                   "(keep last N; each command replaces the one before)")
        discovery_wait: Seconds = Field(0.0, ge=0, le=10.0, description="at start-up, look for other publishers "
                                        "on the command topic until this long after joining the ROS graph (DDS "
                                        "discovers the other participants within a moment: e.g. 1 s to refuse "
                                        "surely at start-up; 0: one look, and one found later faults the run at "
                                        "the once-a-second check)", json_schema_extra={"unit": "s"})
        allow_other_publishers: bool = Field(False, description="run although another node publishes "
                                             "JointTrajectory to the controller's command topic (the controller "
                                             "follows whichever sent last): only where the lab arbitrates its "
                                             "commanders itself; the others are named in status and the log")

        @field_validator("namespace")
        @classmethod
        def _ns(cls, v: str) -> str:
            v = v.strip()
            if v and not v.startswith("/"):
                v = "/" + v
            v = v.rstrip("/")
            return ros_names.check_name(_NAMESPACE_RE, v, "a ROS 2 namespace such as '/tiago'")

        @field_validator("controller")
        @classmethod
        def _controller(cls, v: str) -> str:
            return ros_names.check_name(_RELATIVE_RE, v, "a controller name such as 'gripper_controller'",
                                        "no '/' first: it is taken inside namespace")

        @field_validator("joint_states_topic")
        @classmethod
        def _topic(cls, v: str) -> str:
            return ros_names.check_name(_TOPIC_RE, v, "a ROS 2 topic name such as '/joint_states'",
                                        "'/' first for an absolute name")

        @field_validator("joint_names")
        @classmethod
        def _joints(cls, v: list[str]) -> list[str]:
            if any(not j.strip() for j in v) or v[0] == v[1]:
                raise ValueError(f"expected two different, non-empty joint names (left, right finger), got {v!r}")
            return v

        @model_validator(mode="after")
        def _joint_range(self) -> "PalGripper.Params":
            lo, hi = self.finger_lower, self.finger_upper
            # a finger limit in millimetres (45 for 0.045) would let /joint_states in millimetres through the range
            # check as metres
            mm = [m for m in (millimetres_in_metres(name, value) for name, value in
                              (("finger_lower", lo), ("finger_upper", hi))) if m]
            if mm:
                raise ValueError("; ".join(mm))
            if lo >= hi:
                raise ValueError(f"finger_lower ({lo} m) must be below finger_upper ({hi} m)")
            problems = []
            for name, value, ok in (("min_opening", self.min_opening, self.min_opening >= 2 * lo - 1e-9),
                                    ("max_opening", self.max_opening, self.max_opening <= 2 * hi + 1e-9)):
                if not ok:
                    hint = " (millimetres in a metre field? write e.g. '90mm')" if value >= 1.0 else ""
                    problems.append(f"{name} ({value:g} m) is outside what the fingers reach, "
                                    f"{2 * lo * 1e3:g}-{2 * hi * 1e3:g} mm (twice finger_lower/finger_upper){hint}")
            if problems:
                raise ValueError("; ".join(problems))
            return self

        @model_validator(mode="after")
        def _effort_timeout(self) -> "PalGripper.Params":
            if self.effort_timeout >= self.read_timeout:
                hint = " (milliseconds in a second field? write e.g. '50ms')" if self.effort_timeout >= 1.0 else ""
                raise ValueError(f"effort_timeout ({self.effort_timeout:g} s) must be below read_timeout "
                                 f"({self.read_timeout:g} s): a closing set-point would be followed on the old effort "
                                 f"until the read_timeout fault{hint}")
            return self

        @model_validator(mode="after")
        def _topic_lengths(self) -> "PalGripper.Params":
            # rclpy would refuse a name too long only when the node makes its publisher or subscription
            command = f"{self.namespace}/{self.controller}/joint_trajectory"
            state = ros_names.expand_topic(self.joint_states_topic, self.namespace, None)
            problems = [f"{field}: {why}" for field, full, remedy in (
                ("controller", command, "shorten the namespace or the controller name"),
                ("joint_states_topic", state, "shorten the topic or the namespace"))
                if full is not None and (why := ros_names.too_long(full, remedy))]
            if problems:
                raise ValueError("; ".join(problems))
            return self

    # ------------------------------------------------------------------------------------------------------------
    @property
    def command_topic(self) -> str:
        p = self.params
        return f"{p.namespace}/{p.controller}/joint_trajectory"

    @property
    def state_topic(self) -> str:
        p = self.params
        t = p.joint_states_topic
        return t if t.startswith("/") else f"{p.namespace}/{t}"

    def _hw_open(self) -> None:
        p = self.params
        domain_param = ros_domain_id(p.domain_id)  # before DDS sees a bad ROS_DOMAIN_ID
        try:
            import rclpy
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
            from sensor_msgs.msg import JointState
            from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
        except ImportError as exc:
            raise HardwareError(f"pal-gripper needs ROS 2's rclpy and messages ({exc}); install them with "
                                f"pip install 'teletouch[ros2]'") from exc
        self._JointTrajectory, self._Point = JointTrajectory, JointTrajectoryPoint
        self._lock = threading.Lock()  # the state, between the executor thread and the steps
        self._io_lock = threading.RLock()  # a step's command and send vs. safe_state() from another thread
        self._state: tuple[float, float | None, float, float] | None = None  # opening, velocity, effort, mono
        self._fingers: tuple[float, float] | None = None
        self._msgs = 0
        self._used = 0
        self._dropped: dict[str, int] = {}  # since the last message used: reason -> count
        self._dropped_total: dict[str, int] = {}
        self._drop_example: dict[str, str] = {}
        self._last_stamp: float | None = None
        self._last_offset = 0.0  # stamp - arrival (Unix time) of the last message used
        self._sent: float | None = None
        self._sent_at = 0.0
        self._sent_half: float | None = None  # each finger's position in the last command sent (the controller's goal)
        self._no_controller_since: float | None = None
        self.qos_report = ros_qos.QosReport(self._log_once, _qos_hint)
        self.ros_ctx = rclpy.Context()
        rclpy.init(context=self.ros_ctx, **({} if domain_param is None else {"domain_id": domain_param}))
        domain = self.ros_ctx.get_domain_id()
        with _IN_USE_LOCK:
            other = _IN_USE.get((domain, self.command_topic))
            if other is not None:
                raise HardwareError(f"node '{other}' already commands {self.command_topic} (ROS_DOMAIN_ID {domain}) "
                                    f"in this process: two drivers on one controller fight (it follows whichever "
                                    f"sent last); give each gripper its own namespace/controller")
            _IN_USE[(domain, self.command_topic)] = self.id
            self._in_use_key = (domain, self.command_topic)
        self.ros_node = rclpy.create_node(f"teletouch_{self.id.replace('-', '_')}", context=self.ros_ctx,
                                          start_parameter_services=False)
        self._joined = time.monotonic()
        # volatile both ways, not configurable: a transient_local command publisher would hand its last, old
        # setpoint to a controller that (re)starts later
        reliability = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}
        cmd_qos = QoSProfile(depth=p.command_depth, reliability=reliability[p.command_reliability],
                             durability=DurabilityPolicy.VOLATILE)
        state_qos = QoSProfile(depth=p.state_depth, reliability=reliability[p.state_reliability],
                               durability=DurabilityPolicy.VOLATILE)
        node = self.ros_node
        self.pub = node.create_publisher(JointTrajectory, self.command_topic, cmd_qos,
                                         event_callbacks=self.qos_report.publisher_callbacks(
                                             lambda: node, lambda: self.command_topic, cmd_qos))
        node.create_subscription(JointState, self.state_topic, self._on_joint_states, state_qos,
                                 event_callbacks=self.qos_report.subscription_callbacks(
                                     lambda: node, lambda: self.state_topic, state_qos))
        self.executor = SingleThreadedExecutor(context=self.ros_ctx)
        self.executor.add_node(self.ros_node)
        self._spin = threading.Thread(target=self._spin_loop, name=f"{self.id}-rclpy", daemon=True)
        self._spin.start()
        deadline = time.monotonic() + p.connect_timeout
        while self.pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise HardwareError(f"no controller subscribes to {self.command_topic} after "
                                    f"{p.connect_timeout} s (ROS_DOMAIN_ID {domain}){self._wrong_types()}"
                                    f"{self._qos_text(self.command_topic)}; {self._controllers_seen()}")
            time.sleep(0.01)
        while self._state is None:
            if time.monotonic() > deadline:
                with self._lock:
                    silent = self._msgs == 0
                    what = "no message" if silent else f"no usable message: {self._drop_text()}"
                raise HardwareError(f"{self.state_topic}: {what} for {list(p.joint_names)} after "
                                    f"{p.connect_timeout} s (ROS_DOMAIN_ID {domain}){self._wrong_types()}"
                                    f"{self._qos_text(self.state_topic)}"
                                    f"{self._state_topics_seen() if silent else ''}; check the joint names, "
                                    f"joint_states_topic and the joint_state_broadcaster")
            time.sleep(0.005)
        self._other_pubs: list[str] = []
        self._pubs_logged: set[str] = set()
        self._pubs_deferred = False
        self._pubs_checked = time.monotonic()
        self._check_publishers(starting=True)

    def _wrong_types(self) -> str:
        """Endpoints of another message type on the two topics (DDS does not connect them): text for an error."""
        found = []
        try:
            node = self.ros_node
            for topic, expected, role, infos in (
                    (self.command_topic, TRAJECTORY_TYPE, "subscription",
                     node.get_subscriptions_info_by_topic(self.command_topic)),
                    (self.state_topic, JOINT_STATE_TYPE, "publisher",
                     node.get_publishers_info_by_topic(self.state_topic))):
                for info in infos:
                    if info.topic_type != expected:
                        who = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                        found.append(f"a {role} of node {who} on {topic} uses {info.topic_type}, not {expected}: "
                                     f"DDS does not connect the two")
        except Exception:  # a diagnosis only
            return ""
        return "".join(f"; {f}" for f in found)

    def _graph_topics(self, wanted: str, count: Any) -> list[str]:
        """The topics of type ``wanted`` on the ROS graph that ``count`` (the node's count_subscribers or
        count_publishers) finds an endpoint on: the robot's side, not only this driver's own."""
        return sorted(t for t, types in self.ros_node.get_topic_names_and_types() if wanted in types and count(t) > 0)

    def _controllers_seen(self) -> str:
        """For the start-up error when nothing subscribes to the command topic: the JointTrajectory subscriptions on
        the ROS graph (looked for until GRAPH_WAIT after joining it, while DDS still discovers the robot), each with
        the namespace/controller params that select it and the JointState topic it would read; or that there is
        none."""
        node = self.ros_node
        try:
            while True:
                commands = [t for t in self._graph_topics(TRAJECTORY_TYPE, node.count_subscribers)
                            if t != self.command_topic]
                if commands or time.monotonic() >= self._joined + GRAPH_WAIT:
                    break
                time.sleep(0.05)
            states = self._graph_topics(JOINT_STATE_TYPE, node.count_publishers)
        except Exception:  # a diagnosis only
            return ("check the robot is up, the namespace and controller name, and the network/discovery "
                    "settings")
        if not commands:
            return (f"no JointTrajectory subscription on the ROS graph {time.monotonic() - self._joined:.1f} s "
                    f"after joining it, so no controller to suggest: check the robot is up, on this ROS_DOMAIN_ID "
                    f"(or the domain_id param) and reachable (ROS_AUTOMATIC_DISCOVERY_RANGE / ROS_LOCALHOST_ONLY, "
                    f"the network); where DDS discovery is slow, a longer connect_timeout")
        commands.sort(key=lambda t: ("gripper" not in (_selects(t) or ("", ""))[1], t))   # a gripper's first
        found = [self._candidate(t, states) for t in commands[:MAX_LISTED]]
        more = f"; and {len(commands) - MAX_LISTED} more" if len(commands) > MAX_LISTED else ""
        return (f"the JointTrajectory subscriptions on the ROS graph, with the namespace/controller params that "
                f"select each: {'; '.join(found)}{more}; else check the robot is up and its controllers loaded")

    def _candidate(self, topic: str, states: list[str]) -> str:
        """One JointTrajectory subscription of the graph: the namespace/controller params that make it the command
        topic, and the JointState topic the driver would then read (joint_states_topic where it should change)."""
        names = _selects(topic)
        if names is None:
            return f"{topic} (not <namespace>/<controller>/joint_trajectory: this driver cannot command it)"
        namespace, controller = names
        select = f"namespace: {namespace or EMPTY}, controller: {controller}"
        state = ros_names.expand_topic(self.params.joint_states_topic, namespace, None)
        if state in states:
            return f"{topic} ({select}; JointState on {state})"
        near = [t for t in states if t.startswith(namespace + "/")] or states
        if not near:
            return f"{topic} ({select}; no JointState publisher seen on the graph)"
        return (f"{topic} ({select}; nothing publishes JointState on {state}: set joint_states_topic to one of "
                f"{', '.join(near[:MAX_LISTED])})")

    def _state_topics_seen(self) -> str:
        """For the start-up error when no JointState message came: the JointState topics that have a publisher on
        the ROS graph (each a joint_states_topic value), or that there is none."""
        try:
            states = self._graph_topics(JOINT_STATE_TYPE, self.ros_node.count_publishers)
        except Exception:  # a diagnosis only
            return ""
        states = [t for t in states if t != self.state_topic]
        if not states:
            return "; no other topic on the ROS graph has a JointState publisher"
        more = f" and {len(states) - MAX_LISTED} more" if len(states) > MAX_LISTED else ""
        return (f"; JointState is published on {', '.join(states[:MAX_LISTED])}{more} (set joint_states_topic to "
                f"the one with the finger joints)")

    def _qos_text(self, topic: str) -> str:
        """The incompatible QoS found on ``topic`` (both sides' values): text for an error."""
        return "".join(f"; {t}" for t in self.qos_report.texts(topic))

    def _log_once(self, key: Any, text: str) -> None:
        """Log each incompatible-QoS finding once (the executor thread)."""
        seen = self.__dict__.setdefault("_logged", set())
        if key not in seen:
            seen.add(key)
            self.ctx.log(text)

    def _spin_loop(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # the context was shut down under it
            pass

    def _accept(self, msg: Any, wall: float) -> tuple[tuple[float, float], float | None, float]:
        """Parse and check one message (the executor thread); raises _Refused."""
        p = self.params
        fingers, vel, eff = parse_joint_state(msg, p.joint_names, p.finger_lower, p.finger_upper)
        st = msg.header.stamp
        stamp = st.sec + st.nanosec * 1e-9
        if st.sec == 0 and st.nanosec == 0:
            raise _Refused("zero_stamp", "header.stamp 0")
        offset = stamp - wall
        if self._last_stamp is not None:
            if stamp <= self._last_stamp:
                raise _Refused("older", f"stamp {stamp:.6f} s after {self._last_stamp:.6f} s")
            if offset - self._last_offset > p.read_timeout:
                raise _Refused("ahead", f"stamp {stamp:.6f} s, {offset - self._last_offset:.3f} s ahead of the "
                                        f"messages before it")
        self._last_stamp, self._last_offset = stamp, offset
        return fingers, vel, eff

    def _on_joint_states(self, msg: Any) -> None:
        mono, wall = time.monotonic(), time.time()
        try:
            fingers, vel, eff = self._accept(msg, wall)
        except _Refused as r:
            with self._lock:
                self._msgs += 1
                self._dropped[r.reason] = self._dropped.get(r.reason, 0) + 1
                self._dropped_total[r.reason] = self._dropped_total.get(r.reason, 0) + 1
                self._drop_example[r.reason] = str(r)
            return
        with self._lock:
            self._msgs += 1
            self._used += 1
            self._dropped.clear()
            self._fingers = fingers
            self._state = (fingers[0] + fingers[1], vel, eff, mono)

    def _drop_text(self) -> str:
        """The messages refused since the last one used, by reason (call with the lock held)."""
        parts = [f"{n} messages {_REASONS[k]} (last: {self._drop_example[k]})" for k, n in self._dropped.items()]
        return ", ".join(parts) or "none refused"

    def _other_publishers(self) -> list[str]:
        """The nodes (namespace/name) other than this driver that publish JointTrajectory on the command topic: one
        entry of this node's name and namespace is this driver's own publisher, any further one another process's."""
        node = self.ros_node
        if node.count_publishers(self.command_topic) <= 1:
            return []
        own, skipped, out = (node.get_name(), node.get_namespace()), False, []
        for info in node.get_publishers_info_by_topic(self.command_topic):
            if info.topic_type != TRAJECTORY_TYPE:
                continue  # DDS does not connect it to the controller
            if not skipped and (info.node_name, info.node_namespace) == own:
                skipped = True
                continue
            if info.node_name.startswith("_NODE_NAME_UNKNOWN"):
                out.append(_UNNAMED)
            else:
                out.append(f"{info.node_namespace.rstrip('/')}/{info.node_name}")
        return sorted(out)

    def _check_publishers(self, starting: bool = False) -> None:
        """Refuse (start-up) or fault (running) while another node commands the controller, unless
        allow_other_publishers; each one is logged once."""
        p = self.params
        others = self._other_publishers()
        if starting:   # DDS discovers the other participants within a moment of joining: look until discovery_wait
            while not others and time.monotonic() < self._joined + p.discovery_wait:
                time.sleep(0.02)
                others = self._other_publishers()
        if _UNNAMED in others:
            # DDS announces the endpoint before the ROS graph has the node's name: give the name a moment
            if starting:
                deadline = time.monotonic() + NAME_WAIT
                while _UNNAMED in others and time.monotonic() < deadline:
                    time.sleep(0.02)
                    others = self._other_publishers()
            elif not self._pubs_deferred:
                self._pubs_deferred = True
                self._pubs_checked -= PUBLISHER_CHECK_PERIOD - NAME_WAIT   # look again in NAME_WAIT
                return
        self._pubs_deferred = False
        self._other_pubs = others
        domain = self.ros_ctx.get_domain_id()
        what = (f"{self.command_topic} (ROS_DOMAIN_ID {domain}) has another JointTrajectory publisher: node "
                f"{', '.join(others)}")
        for o in others:
            if o not in self._pubs_logged:
                self._pubs_logged.add(o)
                self.ctx.log(f"{self.command_topic}: node {o} also publishes JointTrajectory (the controller follows "
                             f"whichever sent last)" + ("; allow_other_publishers: true, running on"
                                                        if p.allow_other_publishers else ""))
        if not others or p.allow_other_publishers:
            return
        if starting:
            raise HardwareError(f"{what}: two commanders on one controller fight (it follows whichever sent last, "
                                f"and can leave this driver's safe-state hold); stop the other node, give each "
                                f"gripper its own namespace/controller, or set allow_other_publishers: true where "
                                f"the lab arbitrates its commanders")
        raise HardwareError(f"{what}, which appeared while running: the controller follows whichever sent last, so "
                            f"the gripper no longer follows the operator alone; stop the other node (or set "
                            f"allow_other_publishers: true where the lab arbitrates its commanders)")

    def _check_controller(self, now: float) -> None:
        """Fault when nothing has subscribed to the command topic for controller_timeout (one graph lookup)."""
        if self.pub.get_subscription_count() > 0:
            self._no_controller_since = None
            return
        if self._no_controller_since is None:
            self._no_controller_since = now
        gone = now - self._no_controller_since
        if gone > self.params.controller_timeout:
            with self._lock:
                s = self._state
            # the states go on where the last one is younger than half that time: one that DDS delivered late, just
            # after the subscription was seen gone (a loaded machine), is the robot going away as a whole
            if s is not None and now - s[3] > 0.5 * min(gone, self.params.read_timeout):
                raise HardwareError(f"no controller is subscribed to {self.command_topic} for {gone:.3f} s "
                                    f"(controller_timeout {self.params.controller_timeout} s) and "
                                    f"{self.state_topic} is silent for {now - s[3]:.3f} s: the robot or the "
                                    f"network is gone")
            raise HardwareError(f"no controller is subscribed to {self.command_topic} for {gone:.3f} s "
                                f"(controller_timeout {self.params.controller_timeout} s) while "
                                f"{self.state_topic} goes on: the controller was unloaded or crashed; "
                                f"the commands reach nobody")

    def _hw_read(self) -> Reading | None:
        p = self.params
        now = time.monotonic()
        self._check_controller(now)
        if now - self._pubs_checked >= PUBLISHER_CHECK_PERIOD:
            self._pubs_checked = now
            self._check_publishers()
        with self._lock:
            s = self._state
            dropped = self._drop_text() if self._dropped else ""
        if s is None:
            return None
        age = now - s[3]
        if age > p.read_timeout:
            if dropped:
                raise HardwareError(f"{self.state_topic}: no usable message for {age:.3f} s (read_timeout "
                                    f"{p.read_timeout} s): {dropped}")
            raise HardwareError(f"{self.state_topic} silent for {age:.3f} s (read_timeout "
                                f"{p.read_timeout} s); the robot or the network is gone")
        if p.enforce_effort and not math.isfinite(s[2]):
            raise HardwareError(f"{self.state_topic} carries no efforts for {list(p.joint_names)} (missing or "
                                f"not finite): max_effort ({p.max_effort} N) cannot be enforced without them; set "
                                f"enforce_effort: false to run without the force limit (effort output NaN)")
        return Reading(s[0], s[1], s[2], s[3])

    def configure(self) -> None:
        self._stale_effort_holds = 0  # steps whose closing set-point was held on a stale effort
        self._effort_stale = False  # that hold was logged, until a fresh message
        super().configure()

    def activate(self) -> None:
        self._no_controller_since = None  # counted afresh: the node was not looking while inactive
        super().activate()

    def command_target(self, t: float, inputs: Any) -> float:
        before, t_before = self._setpoint, self._last_t
        target = super().command_target(t, inputs)
        r = self._last_reading
        if r is not None and math.isfinite(r.effort) and r.effort > self.params.max_effort and target < r.opening:
            # squeezing harder than max_effort: back the setpoint off towards the measured opening
            dt = 0.0 if t_before is None else min(max(0.0, t - t_before), self._max_dt)   # a late step: no jump
            target = self._setpoint = max(target, min(r.opening, before + self.params.max_speed * dt))
        return self._no_closing_on_stale_effort(target, before, r)

    def _no_closing_on_stale_effort(self, target: float, before: float, r: Reading | None) -> float:
        """``target``, or where the set-point holds instead while the last /joint_states message is older than
        effort_timeout (with enforce_effort): max_effort cannot be enforced on an old effort, so the set-point closes
        no further than the last measured opening, nor further than it was where it already was below it (a squeeze
        is held, not tightened); opening goes on."""
        p = self.params
        if not p.enforce_effort or r is None or r.mono is None or not math.isfinite(target):
            return target
        age = time.monotonic() - r.mono
        if age <= p.effort_timeout:
            self._effort_stale = False
            return target
        floor = min(before, r.opening) if math.isfinite(before) else r.opening
        if target >= floor:
            return target
        self._stale_effort_holds += 1
        if not self._effort_stale:
            self._effort_stale = True
            self.ctx.log(f"{self.state_topic}: the last message is {age:.3f} s old (effort_timeout "
                         f"{p.effort_timeout} s): max_effort cannot be enforced on its effort, so the set-point "
                         f"closes no further than {floor * 1e3:.2f} mm until a fresh message")
        self._setpoint = floor
        return floor

    def _command_guard(self) -> Any:
        return self._io_lock

    def _move_time(self, half: float) -> float:
        """Time for the fingers to reach ``half`` each: time_from_start, or what the farther finger needs at half
        max_speed (each finger moves at half the opening's speed), counted from the measured fingers and from the
        last goal sent (where the controller takes them: the measurement may be stale)."""
        p = self.params
        with self._lock:
            fingers = self._fingers
        starts = list(fingers or ())
        if self._sent_half is not None:
            starts.append(self._sent_half)
        if not starts:
            return p.time_from_start
        return max(p.time_from_start, max(abs(half - x) for x in starts) / (0.5 * p.max_speed))

    def _hw_write(self, opening: float) -> None:
        p = self.params
        if not math.isfinite(opening):
            return  # nothing to send (the base never asks; the controller keeps its last goal)
        with self._io_lock:
            now = time.monotonic()
            if self._sent is not None and abs(opening - self._sent) < 1e-7 and \
                    now - self._sent_at < p.republish_period:
                return
            # not clamped to [min_opening, max_opening]: the base walks a setpoint outside it in at max_speed;
            # never beyond the joints
            half = clamp(opening / 2.0, p.finger_lower, p.finger_upper)
            duration = self._move_time(half)
            msg = self._JointTrajectory()
            msg.joint_names = list(p.joint_names)
            pt = self._Point()
            pt.positions = [half, half]
            sec = int(duration)
            pt.time_from_start.sec = sec
            pt.time_from_start.nanosec = min(999_999_999, int(round((duration - sec) * 1e9)))
            msg.points = [pt]
            self.pub.publish(msg)
            self._sent, self._sent_at, self._sent_half = opening, now, half

    hold_setpoint_while_stale = False   # its own rule while the state is stale (below)

    def safe_target(self) -> float:
        """``hold`` with the state stale (no usable message for effort_timeout, or none): the last measured opening
        (a squeeze is released to the object's surface, not held where a set-point inside the object left it), or
        the last set-point where that is wider: opening goes on while the state is stale, the controller has
        taken the fingers out there since, and the stale opening would close them back with no force reading.
        Otherwise the base's target."""
        p = self.params
        lock = getattr(self, "_lock", None)
        if p.safe_mode == "hold" and lock is not None and math.isfinite(self._setpoint):
            with lock:
                s = self._state
            if s is None or time.monotonic() - s[3] > p.effort_timeout:
                measured = self._measured() if s is None else s[0]
                return max(self._setpoint, measured) if math.isfinite(measured) else self._setpoint
        return super().safe_target()

    def _forget_sent(self) -> None:
        self._sent = None  # always (re)send the hold, whatever was sent before

    def status(self) -> dict[str, Any]:
        d = super().status()
        d["dropped"] = dict(getattr(self, "_dropped_total", {}))
        d["stale_effort_holds"] = getattr(self, "_stale_effort_holds", 0)
        d["messages"] = getattr(self, "_msgs", 0)
        report = getattr(self, "qos_report", None)
        d["incompatible_qos"] = report.count if report is not None else 0
        d["qos_problems"] = report.texts() if report is not None else []
        d["other_publishers"] = list(getattr(self, "_other_pubs", []))
        return d

    def _hw_close(self) -> None:
        key = getattr(self, "_in_use_key", None)
        if key is not None:
            with _IN_USE_LOCK:
                if _IN_USE.get(key) == self.id:
                    del _IN_USE[key]
            self._in_use_key = None
        ex = getattr(self, "executor", None)
        if ex is not None:
            try:
                ex.shutdown(timeout_sec=1.0)
            except Exception:
                pass
        node = getattr(self, "ros_node", None)
        if node is not None:
            try:
                node.destroy_node()
            except Exception:
                pass
        ctx = getattr(self, "ros_ctx", None)
        if ctx is not None:
            ctx.try_shutdown()
        th = getattr(self, "_spin", None)
        if th is not None:
            th.join(timeout=2.0)
        self.executor = self.ros_node = self.ros_ctx = None


@hookimpl
def teletouch_components():
    return [PalGripper]
