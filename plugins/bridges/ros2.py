"""ROS 2 bridge: graph ports to and from ROS 2 topics with standard messages (extra ``teletouch[ros2]``).

``ros2-publish`` publishes whatever is wired into it (its ``topics`` are advertised at configure, before the first
sample, so DDS matches them while the graph starts; ``wait_for_subscribers`` makes activate wait, up to
``wait_timeout``, for matched subscribers, else the run does not start); ``ros2-subscribe`` turns topics back into
graph outputs. A wired port whose topic is not in the node's ``topics`` is named by ``wiring_problems`` (for the
graph's validation). Two graphs on two machines (or two processes) split a pipeline through DDS, e.g. machine A runs
digit -> depth -> poly-force -> ros2-publish, machine B runs ros2-subscribe -> position-force -> devices.

| port(s)                       | message                              | topic (param)                         |
|-------------------------------|--------------------------------------|---------------------------------------|
| force (N)                     | geometry_msgs/msg/WrenchStamped      | force_topic; value on force_axis      |
| image (BGR uint8)             | sensor_msgs/msg/Image, bgr8          | image_topic                           |
| depth (float32, m)            | sensor_msgs/msg/Image, 32FC1         | depth_topic                           |
| opening, velocity, effort     | sensor_msgs/msg/JointState, 1 joint  | joint_states_topic, joint_name        |
| value (float, any unit)       | std_msgs/msg/Float64 (no stamp)      | value_topic                           |

Clocks. Every stamped message carries the sample's own stamp (a camera's capture time, not the publish time) in
``header.stamp``, as ROS time = Unix time (the system clock, what ROS uses without ``use_sim_time``):
``ros = graph + (time.time() - graph_now())``, measured at each conversion on a wall-clock graph (the Unix time read
between two graph-clock reads, read again when the pair is more than 0.1 ms apart: a preemption between two reads would
shift the stamps by its length), and fixed when the node activates on a simulated clock (the stamps are then synthetic:
that Unix time plus graph time, running at the simulation's pace). Each graph stamp is converted once (remembered for
the last ``STAMP_MEMORY``), so the messages of one measurement (a frame's image, depth and force) carry identical header
stamps. The subscriber keeps a message's stamp as Unix time and maps it to its own graph clock when a step outputs it
(so a message that arrived while the graph was starting keeps its age), so a sample keeps its age across the bridge, and
a consumer's ``max_age`` sees the force go stale when the publisher dies. Across machines this needs synchronised system
clocks (chrony/PTP); where they are not, ``stamps: arrival`` stamps each message with its arrival time (transport
latency is then hidden). A stamp more than ``max_clock_skew`` in the future is clamped to the arrival time and counted
(``status()['skewed']``); one more than 1 s old on arrival is kept and reported (``late``; ``lag_s`` is arrival minus
the stamp as sent, clamped or not); a zero stamp (the sender does not stamp) or an invalid one is refused. A value with
the stamp of the last one taken for its port is a repeat, not a new measurement (``duplicates`` when a message has
nothing else): it is not output again, so a sender re-sending its last message cannot keep a force fresh (per port: a
JointState's fields of one measurement may come in two messages); the publisher sends each measurement once (by stamp,
also under ``isolate: process``). A value whose stamp is older than that of the last one taken for its port (a second
publisher on the topic, messages out of order) is dropped, counted (``out_of_order``) and logged once, with either
``stamps`` mode (a stamp clamped as in the future is not compared with); a port's output stamps never go back (a clamped
one is put just after the port's last one where it is not). With ``stamps: arrival``, ``restart_after`` takes a stamp
older than the last one by more than that as the sender starting again (``ros2 bag play --loop``), counted
(``restarts``).

Values. A non-finite value never crosses the bridge: the publisher does not send it, the subscriber refuses it (a
non-finite JointState field is left out, the others go on); the subscriber also refuses a JointState whose finite
opening is above ``max_opening`` and a depth above ``max_depth`` (millimetres in a metre field), a force above
``max_force`` (200 N) or below ``min_force`` (-0.05 N; one between it and 0 is output as 0: a grip force is >= 0), and
malformed images. Refused messages are counted (``bad``) and each kind of problem is logged once. A WrenchStamped or
Image whose ``header.frame_id`` is not ``frame_id`` (default ``digit``, the publisher's; null: any) is refused before
its stamp is looked at, counted (``wrong_frame``) and logged once per topic: another sender's wrench (a wrist
force/torque sensor) is no fingertip force. A JointState's frame is not read.

Each node has its own rclpy Context (its own DDS participant; ``domain_id`` param, default ``ROS_DOMAIN_ID``, both
checked to be 0..232), never the global default context nor rclpy's signal handlers, and spins its executor in a
background thread. It reports endpoints of another message type on its topics (``wrong_type``) and peers with
incompatible QoS (``incompatible_qos``): DDS connects neither, silently. The subscriber's durability is volatile
only (a late joiner must not receive a latched old force). Ports are latest-value: the subscriber outputs a
message once, at its next step after it arrived; older messages that arrived in between are dropped.
"""

from __future__ import annotations

import math
import re
import threading
import time
from typing import Any, Callable, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from teletouch import Component, ComponentFault, Kind, Params, Port, Sample, hookimpl
from teletouch.units import (
    MAX_PLAUSIBLE_DEPTH_LIMIT, Meters, Newtons, Seconds, plausible_depth, plausible_opening, plausible_quantity,
)

from .. import ros_names, ros_qos
from ..estimators.poly_force import MAX_FORCE_N

TOPICS = ("force", "image", "depth", "joint_states", "value")
TOPIC_FIELDS = tuple(f"{k}_topic" for k in TOPICS)
#: port -> the topic (key of ``topics``) that carries it, the same on both nodes
PORT_TOPIC = {"force": "force", "image": "image", "depth": "depth", "opening": "joint_states",
              "velocity": "joint_states", "effort": "joint_states", "value": "value"}
TopicKey = Literal["force", "image", "depth", "joint_states", "value"]
_AXES = {"x": 0, "y": 1, "z": 2}
GRAPH_CHECK_PERIOD = 1.0     # s between checks of the other endpoints' message types on our topics
#: the publisher remembers the ROS stamp it gave this many recent graph stamps: the messages of one measurement (a
#: camera frame's image, depth and force, published in different steps) carry the same header.stamp
STAMP_MEMORY = 1024
LATE_AFTER = 1.0             # s: a stamp this much older than its arrival is reported (clocks, replays)
#: the largest ``max_force`` the subscriber takes: a larger bound is millinewtons typed in the newton field (a typo
#: there would switch the guard off)
MAX_PLAUSIBLE_FORCE_LIMIT = 1000.0   # N

# ROS 2 names (teletouch.plugins.ros_names), checked when a graph is validated rather than when rclpy refuses them
# at start-up
_TOKEN = ros_names.TOKEN
_TOPIC_RE = re.compile(rf"(?:/|~/)?{_TOKEN}(?:/{_TOKEN})*")
_NAMESPACE_RE = re.compile(rf"/?(?:{_TOKEN}(?:/{_TOKEN})*)?")
_NODE_RE = re.compile(_TOKEN)


class QosParams(Params):
    reliability: Literal["reliable", "best_effort"] = Field("reliable", description="QoS reliability")
    durability: Literal["volatile", "transient_local"] = Field("volatile", description="QoS durability")
    depth: int = Field(5, ge=1, le=10000, description="QoS history depth (keep last N)")


class _BridgeParams(QosParams):
    namespace: str = Field("/teletouch", description="ROS namespace of the topics (relative topic names)")
    node_name: str | None = Field(None, description="ROS node name (default: the graph node id)")
    domain_id: int | None = Field(None, ge=0, le=ros_names.MAX_DOMAIN_ID,
                                  description="ROS domain id, 0 to 232 (default: ROS_DOMAIN_ID or 0)")
    force_topic: str = Field("force", description="geometry_msgs/WrenchStamped topic of 'force'")
    image_topic: str = Field("image", description="sensor_msgs/Image (bgr8) topic of 'image'")
    depth_topic: str = Field("depth", description="sensor_msgs/Image (32FC1, m) topic of 'depth'")
    joint_states_topic: str = Field("joint_states", description="sensor_msgs/JointState topic of opening/velocity/"
                                    "effort")
    value_topic: str = Field("value", description="std_msgs/Float64 topic of 'value'")
    force_axis: Literal["x", "y", "z"] = Field("z", description="wrench force component that carries 'force'")
    joint_name: str = Field("gripper", min_length=1, description="JointState joint carrying opening/velocity/"
                            "effort")

    @field_validator(*TOPIC_FIELDS)
    @classmethod
    def _topic_name(cls, v: str) -> str:
        return ros_names.check_name(_TOPIC_RE, v, "a ROS 2 topic name", "'/' first for an absolute name, '~/' for "
                                    "a private one; no '/' at the end")

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, v: str) -> str:
        return ros_names.check_name(_NAMESPACE_RE, v, "a ROS 2 namespace such as '/teletouch' or '/lab/arm'",
                                    "no '/' at the end")

    @field_validator("node_name")
    @classmethod
    def _node_name(cls, v: str | None) -> str | None:
        if v is not None and not _NODE_RE.fullmatch(v):
            raise ValueError(f"expected a ROS 2 node name (letters, digits and '_', not starting with a digit), "
                             f"got {v!r}")
        return v

    @model_validator(mode="after")
    def _full_topic_names(self) -> "_BridgeParams":
        seen: dict[str, str] = {}
        problems = []
        for f in TOPIC_FIELDS:
            full = _resolve(self.namespace, getattr(self, f))
            if full in seen:
                problems.append(f"{f}: '{full}' is also {seen[full]}'s topic: each port needs a topic of its own")
            else:
                seen[full] = f
        # a private name's length needs the node name: here when node_name is set, else at configure
        problems += _too_long(self, self.node_name)
        if problems:
            raise ValueError("\n".join(problems))
        return self


def _too_long(p: _BridgeParams, node: str | None) -> list[str]:
    """'FIELD: why' for each topic param whose expanded name rcl would refuse as too long (a private one only when
    ``node``, the ROS node name, is known)."""
    out = []
    for f in TOPIC_FIELDS:
        topic = getattr(p, f)
        full = ros_names.expand_topic(topic, p.namespace, node)
        remedy = ("shorten the topic, the namespace or node_name (default the graph node id)" if topic.startswith("~")
                  else "shorten the topic or the namespace")
        if full is not None and (why := ros_names.too_long(full, remedy)):
            out.append(f"{f}: {why}")
    return out


def _check_lengths(p: _BridgeParams, node_id: str) -> None:
    """Before any ROS node is made: a private topic too long with the node name the node gets (the graph node id
    when node_name is not set, which the params do not know) is a fault naming the param."""
    problems = _too_long(p, _ros_name(p.node_name or node_id))
    if problems:
        raise ComponentFault("; ".join(problems))


def _unlisted(ports: Any, topics: list[str], side: str, remedy: str) -> dict[str, str]:
    """{port: why} for the wired ports whose topic is not in ``topics``."""
    listed = ", ".join(dict.fromkeys(topics))
    return {port: f"{side} '{port}' is wired, but its topic '{PORT_TOPIC[port]}' is not in this node's topics "
                  f"[{listed}]: {remedy.format(topic=PORT_TOPIC[port])}"
            for port in sorted(ports) if port in PORT_TOPIC and PORT_TOPIC[port] not in topics}


def _resolve(namespace: str, topic: str) -> str:
    """The full name of a topic (private '~' names are left as they are: they cannot collide with the others)."""
    if topic.startswith(("/", "~")):
        return topic
    return "/" + "/".join(x for x in (namespace.strip("/"), topic) if x)


def _domain_id(param: int | None) -> int | None:
    """The domain to join (:func:`teletouch.plugins.ros_names.domain_id`); a bad ROS_DOMAIN_ID is a fault."""
    return ros_names.domain_id(param, ComponentFault)


def _type_name(mtype: Any) -> str:
    """'geometry_msgs/msg/WrenchStamped' of a message class."""
    return f"{mtype.__module__.split('.')[0]}/msg/{mtype.__name__}"


def _message_types() -> tuple[Any, Any, Any, Any]:
    """WrenchStamped, Image, JointState and Float64; without the ROS 2 message packages a ComponentFault that names
    the extra to install (a bare ModuleNotFoundError named none)."""
    try:
        from geometry_msgs.msg import WrenchStamped
        from sensor_msgs.msg import Image, JointState
        from std_msgs.msg import Float64
    except ImportError as exc:
        raise ComponentFault(f"the ROS 2 bridge needs the ROS 2 message packages: pip install 'teletouch[ros2]' "
                             f"({exc})") from exc
    return WrenchStamped, Image, JointState, Float64


class _Ros:
    """One rclpy Context + node + executor thread (never the global default context, never signal handlers).

    It also watches its topics: an endpoint of another message type on one of them (DDS does not connect the two,
    silently) and a peer with incompatible QoS (nothing flows) are counted and logged once each."""

    def __init__(self, name: str, namespace: str, domain_id: int | None,
                 log_once: Callable[[Any, str], None]):
        try:
            import rclpy
            from rclpy.context import Context
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.signals import SignalHandlerOptions
        except ImportError as exc:  # pragma: no cover - CI installs the extra
            raise ComponentFault(f"the ROS 2 bridge needs rclpy: pip install 'teletouch[ros2]' ({exc})") from exc
        domain = _domain_id(domain_id)
        self.rclpy = rclpy
        self._log_once = log_once
        self.wrong_type = 0           # endpoints of another message type on our topics (now)
        self.qos_report = ros_qos.QosReport(log_once, _qos_hint)   # peers whose QoS cannot connect to ours
        self.errors = 0               # exceptions the executor raised while spinning
        self._watch: list[tuple[str, str]] = []   # (full topic name, our message type)
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = None
        try:
            self.node = rclpy.create_node(_ros_name(name), namespace=namespace or "/", context=self.ctx,
                                          start_parameter_services=False)
            self.executor = SingleThreadedExecutor(context=self.ctx)
            self.executor.add_node(self.node)
            self.node.create_timer(GRAPH_CHECK_PERIOD, self._check_graph)
        except Exception:
            if self.node is not None:
                self.node.destroy_node()
            rclpy.shutdown(context=self.ctx)
            raise
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, name=f"ros2-{name}", daemon=True)
        self.thread.start()

    def subscription(self, mtype: Any, topic: str, callback: Any, qos: Any) -> Any:
        events = self.qos_report.subscription_callbacks(lambda: self.node, lambda: sub.topic_name, qos)
        sub = self.node.create_subscription(mtype, topic, callback, qos, event_callbacks=events)
        self._watch.append((sub.topic_name, _type_name(mtype)))
        return sub

    def publisher(self, mtype: Any, topic: str, qos: Any) -> Any:
        events = self.qos_report.publisher_callbacks(lambda: self.node, lambda: pub.topic_name, qos)
        pub = self.node.create_publisher(mtype, topic, qos, event_callbacks=events)
        self._watch.append((pub.topic_name, _type_name(mtype)))
        return pub

    @property
    def incompatible_qos(self) -> int:
        """Peers found with QoS that cannot connect to ours (events)."""
        return self.qos_report.count

    def _check_graph(self) -> None:
        try:
            n = 0
            for topic, tname in list(self._watch):
                ends = [("publisher", i) for i in self.node.get_publishers_info_by_topic(topic)]
                ends += [("subscription", i) for i in self.node.get_subscriptions_info_by_topic(topic)]
                for role, info in ends:
                    if info.topic_type != tname:
                        n += 1
                        who = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                        self._log_once(("type", topic, info.topic_type),
                                       f"topic {topic}: a {role} of node {who} uses {info.topic_type}, this node "
                                       f"{tname}: DDS does not connect them, nothing flows between the two")
            self.wrong_type = n
        except Exception as exc:  # the context is going down: the next check (if any) tries again
            if self.ctx.ok():
                self._log_once(("graph", type(exc).__name__), f"ROS 2 graph check failed: {exc}")

    def _spin(self) -> None:
        while not self._stop.is_set() and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception as exc:
                if self._stop.is_set() or not self.ctx.ok():   # context shut down under us while stopping
                    return
                # a dead spin thread would silently starve every subscription: report it and go on
                self.errors += 1
                self._log_once(("spin", type(exc).__name__), f"ROS 2 executor: {type(exc).__name__}: {exc}")
                time.sleep(0.05)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=2.0)
        try:
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            if self.ctx.ok():
                self.rclpy.shutdown(context=self.ctx)
            self.thread.join(timeout=1.0)   # a callback that held it past the first join ends with the context


def _qos_hint(policy: str, side: str) -> str:
    """What to set when this node's ``side`` (subscription/publisher) and a peer have incompatible ``policy``."""
    if policy == "RELIABILITY":
        return ("set reliability: best_effort on this node to hear a best-effort publisher (a reliable publisher "
                "serves both)" if side == "subscription" else "a reliable subscription needs reliability: reliable "
                "here")
    if policy == "DURABILITY":
        return "a transient_local subscription needs durability: transient_local on the publisher"
    return "make the two QoS settings compatible"


def _ros_name(name: str) -> str:
    out = "".join(c if c.isalnum() or c == "_" else "_" for c in name)
    return out if out and not out[0].isdigit() else "n_" + out


def qos_profile(p: QosParams) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=p.depth,
                      reliability=ReliabilityPolicy.RELIABLE if p.reliability == "reliable"
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE if p.durability == "volatile"
                      else DurabilityPolicy.TRANSIENT_LOCAL)


class _Clock:
    """Graph time <-> ROS time (Unix seconds); see the module docstring."""

    #: a Unix-time read is taken between two graph-clock reads; a pair further apart than this (the thread was
    #: preempted between them) is read again, up to READS times, and the tightest pair is used
    TIGHT = 1e-4
    READS = 3

    def __init__(self, ctx: Any):
        self.ctx = ctx
        self.fixed = ctx.clock_kind != "wall"
        self.offset = self._read()

    def _read(self) -> float:
        """time.time() - ctx.now(), each Unix read taken between two graph-clock reads and referred to their middle:
        a preemption between two plain reads would shift every stamp mapped with it by its length (1-10 ms on a
        loaded machine), so a wide pair is read again and the tightest of READS is kept."""
        best_gap, best = math.inf, 0.0
        for _ in range(self.READS):
            a = self.ctx.now()
            u = time.time()
            b = self.ctx.now()
            if b - a < best_gap:
                best_gap, best = b - a, u - 0.5 * (a + b)
            if best_gap <= self.TIGHT:
                break
        return best

    def offset_now(self) -> float:
        """ROS time - graph time, now."""
        return self.offset if self.fixed else self._read()

    def to_ros(self, graph_t: float) -> float:
        return graph_t + self.offset_now()

    def to_graph(self, ros_t: float) -> float:
        return ros_t - self.offset_now()


class _LogOnce:
    """Log each kind of problem once (a bad message at 1 kHz must not flood the log)."""

    LIMIT = 50

    def __init__(self, ctx: Any):
        self.ctx = ctx
        self.seen: set[Any] = set()

    def __call__(self, key: Any, message: str) -> None:
        if key in self.seen or len(self.seen) >= self.LIMIT:
            return
        self.seen.add(key)
        self.ctx.log(message)


def _ros_status(comp: Any) -> dict[str, int]:
    ros = getattr(comp, "_ros", None) or getattr(comp, "_ros_closed", None)
    if ros is None:
        return {"wrong_type": 0, "incompatible_qos": 0, "executor_errors": 0}
    return {"wrong_type": ros.wrong_type, "incompatible_qos": ros.incompatible_qos, "executor_errors": ros.errors}


def _close_ros(comp: Any) -> None:
    ros = getattr(comp, "_ros", None)
    if ros is not None:
        comp._ros = None
        comp._ros_closed = ros   # its counters stay readable for the run's summary
        ros.close()


class _Bad(ValueError):
    """A message the subscriber refuses; ``kind`` names the problem (logged once per topic and kind)."""

    def __init__(self, kind: str, detail: str = ""):
        super().__init__(kind + detail)
        self.kind = kind


class Ros2Publish(Component):
    """Publish graph ports on ROS 2 topics with standard messages (force, images, depth, joint states)."""

    name = "ros2-publish"
    kind = Kind.BRIDGE
    default_rate = 200.0
    inputs = {
        "force": Port("float64", (), "N", "force -> geometry_msgs/WrenchStamped", required=False),
        "image": Port("uint8", (None, None, 3), "", "BGR image -> sensor_msgs/Image bgr8", required=False),
        "depth": Port("float32", (None, None), "m", "depth map -> sensor_msgs/Image 32FC1", required=False),
        "opening": Port("float64", (), "m", "gripper opening -> JointState.position", required=False),
        "velocity": Port("float64", (), "m/s", "gripper velocity -> JointState.velocity", required=False),
        "effort": Port("float64", (), "N", "gripper effort -> JointState.effort", required=False),
        "value": Port("float64", (), "any", "any scalar -> std_msgs/Float64", required=False),
    }
    outputs = {}

    class Params(_BridgeParams):
        frame_id: str = Field("digit", description="header.frame_id of the messages")
        topics: list[TopicKey] = Field(
            list(TOPICS), min_length=1,
            description="topics advertised when the node starts, before the first sample, so that subscribers have "
            "found them by then (force, image, depth, joint_states, value; default all): a wired input whose "
            "topic is not listed is an error")
        wait_for_subscribers: int | dict[TopicKey, int] = Field(
            0, description="at activate, wait (up to wait_timeout) until this many subscribers are matched on each "
            "listed topic, or {topic: count} for some of them, so that the first samples are not lost to DDS "
            "discovery; not reached in time: a start-up error naming the topic and the counts (0: no wait)")
        wait_timeout: Seconds = Field(5.0, gt=0, description="how long activate waits for wait_for_subscribers",
                                      json_schema_extra={"unit": "s"})

        @field_validator("wait_for_subscribers")
        @classmethod
        def _counts(cls, v: Any) -> Any:
            counts = v.values() if isinstance(v, dict) else [v]
            if any(n < 0 for n in counts):
                raise ValueError(f"expected a count of subscribers >= 0 (or {{topic: count}}), got {v!r}")
            return v

        @model_validator(mode="after")
        def _waited_topics_listed(self) -> "Ros2Publish.Params":
            w = self.wait_for_subscribers
            missing = [k for k, n in w.items() if n and k not in self.topics] if isinstance(w, dict) else []
            if missing:
                raise ValueError(f"wait_for_subscribers: {', '.join(missing)} not in topics "
                                 f"[{', '.join(dict.fromkeys(self.topics))}]: only an advertised topic can have "
                                 f"subscribers (add it to topics)")
            return self

    @classmethod
    def wiring_problems(cls, params: Any, inputs: Any, outputs: Any) -> dict[str, str]:
        """{input: why} for the wired inputs whose topic is not advertised (``params.topics``). For the graph's
        validation: ``inputs`` are the node's wired input ports, ``outputs`` the output ports other nodes read."""
        return _unlisted(inputs, list(params.topics), "input", "add {topic} to topics")

    def configure(self) -> None:
        WrenchStamped, Image, JointState, Float64 = _message_types()

        p = self.params
        types = {"force": WrenchStamped, "image": Image, "depth": Image, "joint_states": JointState,
                 "value": Float64}
        names = {"force": p.force_topic, "image": p.image_topic, "depth": p.depth_topic,
                 "joint_states": p.joint_states_topic, "value": p.value_topic}
        self._pubs: dict[str, Any] = {}
        self._last: dict[str, Sample] = {}
        self._stamps: dict[float, int] = {}   # graph stamp -> the header.stamp (Unix ns) its messages carry
        self.published = 0
        self.bad = 0
        self._log_once = _LogOnce(self.ctx)
        self._clock = _Clock(self.ctx)
        _check_lengths(p, self.id)
        self._ros = _Ros(p.node_name or self.id, p.namespace, p.domain_id, self._log_once)
        self._qos = qos_profile(p)
        # every publisher now: DDS discovery (a new writer found by the subscribers, tens of ms and more across
        # machines) runs while the graph starts; a writer made at its first sample lost the samples of that time
        for key in dict.fromkeys(p.topics):
            self._pubs[key] = self._ros.publisher(types[key], names[key], self._qos)

    def activate(self) -> None:
        self._clock = _Clock(self.ctx)
        self._stamps = {}
        self._wait_for_subscribers()

    def _stamp_ns(self, graph_t: float) -> int:
        """The header.stamp (Unix ns) of the messages of a sample stamped ``graph_t``: converted once and remembered
        for the last :data:`STAMP_MEMORY` graph stamps, so that the messages of one measurement (a camera frame's
        image, depth and force, on three topics and often in three steps) carry identical stamps, as a ROS user's
        exact-time synchroniser needs. Converted at each message, they differed by up to a few hundred ns: on a
        wall clock the Unix to graph offset is measured anew at each conversion, and float seconds near 1.7e9 s
        resolve 238 ns."""
        ns = self._stamps.get(graph_t)
        if ns is None:
            ns = self._stamps[graph_t] = max(0, int(round(self._clock.to_ros(graph_t) * 1e9)))
            if len(self._stamps) > STAMP_MEMORY:
                del self._stamps[next(iter(self._stamps))]   # the oldest conversion (dicts keep their order)
        return ns

    def _waited(self) -> dict[str, int]:
        """{topic key: subscribers to wait for} (wait_for_subscribers; no key: no wait)."""
        w = self.params.wait_for_subscribers
        if isinstance(w, dict):
            return {k: n for k, n in w.items() if n}
        return {k: w for k in self._pubs} if w else {}

    def _wait_for_subscribers(self) -> None:
        """Wait until every waited-for topic has its subscribers matched, or fault naming what is missing."""
        want = self._waited()
        if not want:
            return
        timeout = self.params.wait_timeout
        deadline = time.monotonic() + timeout
        while True:
            short = {k: seen for k in want if (seen := self._pubs[k].get_subscription_count()) < want[k]}
            if not short:
                return
            if time.monotonic() >= deadline:
                break
            time.sleep(0.01)
        parts = []
        for k, seen in short.items():
            topic = self._pubs[k].topic_name
            try:
                found = self._ros.node.count_subscribers(topic)
            except Exception:  # a diagnosis only
                found = seen
            unmatched = (f" ({found - seen} more subscription(s) on the topic that DDS did not match: QoS or "
                         f"message type)" if found > seen else "")
            qos = "".join(f"; {t}" for t in self._ros.qos_report.texts(topic))
            parts.append(f"{topic}: {seen} subscriber(s) matched, {want[k]} expected{unmatched}{qos}")
        raise ComponentFault(f"wait_for_subscribers: not reached after {timeout:g} s (wait_timeout), ROS_DOMAIN_ID "
                             f"{self._ros.ctx.get_domain_id()}: {'; '.join(parts)}; is the subscribing program "
                             f"running, on this domain, with compatible QoS?")

    def _pub(self, key: str) -> Any:
        return self._pubs[key]   # made at configure; _new() lets no sample through for another topic

    def _new(self, inputs: Any, name: str) -> Sample | None:
        """The input's sample if it is a measurement not sent yet. Compared by stamp, not only by identity: under
        ``isolate: process`` a node gets a new Sample object for the same measurement at every step, and a
        re-sent message would look like a new measurement to a subscriber that stamps on arrival."""
        s = inputs[name]
        if s is None:
            return None
        if PORT_TOPIC[name] not in self._pubs:   # wired, but its topic is not advertised: never dropped silently
            raise ComponentFault(_unlisted([name], list(self.params.topics), "input",
                                           "add {topic} to topics (its samples cannot be published)")[name])
        last = self._last.get(name)
        if last is not None and (s is last or s.stamp == last.stamp):
            return None
        self._last[name] = s
        return s

    def _finite(self, name: str, v: float) -> bool:
        if math.isfinite(v):
            return True
        self.bad += 1
        self._log_once(("nonfinite", name), f"input '{name}' is not finite ({v!r}): not published (a non-finite "
                                            f"value never goes on the wire; the subscriber's output goes stale)")
        return False

    def step(self, t, inputs):
        from geometry_msgs.msg import WrenchStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64

        from teletouch.recording import image_msg, ros_time_ns

        p = self.params
        s = self._new(inputs, "force")
        if s is not None and self._finite("force", v := float(s.value)):
            m = WrenchStamped()
            m.header.stamp = ros_time_ns(self._stamp_ns(s.stamp))
            m.header.frame_id = p.frame_id
            setattr(m.wrench.force, p.force_axis, v)
            self._pub("force").publish(m)
            self.published += 1
        for name in ("image", "depth"):
            s = self._new(inputs, name)
            if s is not None:
                a = np.asarray(s.value)
                if name == "depth":
                    if a.dtype != np.float32:
                        a = a.astype(np.float32)
                    if not np.isfinite(a).all():
                        self._finite("depth", float(a[~np.isfinite(a)].flat[0]))
                        continue
                self._pub(name).publish(image_msg(a, 0.0, p.frame_id, stamp_ns=self._stamp_ns(s.stamp)))
                self.published += 1
        # one JointState per measurement time: a field goes out only with its own stamp, so the last velocity of a
        # source that stopped is not re-sent under the opening's newer stamps (it would look fresh on the far side)
        groups: dict[float, dict[str, float]] = {}
        for n in ("opening", "velocity", "effort"):
            s = self._new(inputs, n)
            if s is not None and self._finite(n, v := float(s.value)):
                groups.setdefault(s.stamp, {})[n] = v
        for stamp in sorted(groups):
            fields = groups[stamp]
            m = JointState()
            m.header.stamp = ros_time_ns(self._stamp_ns(stamp))
            m.header.frame_id = p.frame_id
            m.name = [p.joint_name]
            if "opening" in fields:
                m.position = [fields["opening"]]
            if "velocity" in fields:
                m.velocity = [fields["velocity"]]
            if "effort" in fields:
                m.effort = [fields["effort"]]
            self._pub("joint_states").publish(m)
            self.published += 1
        s = self._new(inputs, "value")
        if s is not None and self._finite("value", v := float(s.value)):
            self._pub("value").publish(Float64(data=v))
            self.published += 1
        return None

    def status(self):
        return {"published": getattr(self, "published", 0), "bad": getattr(self, "bad", 0), **_ros_status(self)}

    def close(self) -> None:
        _close_ros(self)


class Ros2Subscribe(Component):
    """Subscribe to ROS 2 topics (standard messages) and output their values, stamped on the local graph clock."""

    name = "ros2-subscribe"
    kind = Kind.BRIDGE
    default_rate = 500.0
    requires_wall_clock = True
    inputs = {}
    outputs = {
        "force": Port("float64", (), "N", "force from geometry_msgs/WrenchStamped"),
        "image": Port("uint8", (None, None, 3), "", "BGR image from sensor_msgs/Image"),
        "depth": Port("float32", (None, None), "m", "depth map from sensor_msgs/Image 32FC1 (or 16UC1 mm)"),
        "opening": Port("float64", (), "m", "JointState.position of joint_name"),
        "velocity": Port("float64", (), "m/s", "JointState.velocity of joint_name"),
        "effort": Port("float64", (), "N", "JointState.effort of joint_name"),
        "value": Port("float64", (), "any", "std_msgs/Float64 (stamped on arrival: it has no header)"),
    }

    class Params(_BridgeParams):
        topics: list[TopicKey] = Field(
            ["force"], min_length=1,
            description="which topics to subscribe to (force, image, depth, joint_states, value): an output read "
            "by the graph needs its topic here")
        durability: Literal["volatile"] = Field(
            "volatile", description="QoS durability: volatile only (a late joiner must not get latched old samples)")
        stamps: Literal["message", "arrival"] = Field(
            "message", description="sample stamps: the message's header.stamp (needs synchronised clocks) or the "
            "arrival time")
        frame_id: str | None = Field(
            "digit", description="header.frame_id a WrenchStamped or Image must carry (ros2-publish's default "
            "'digit'); another frame (a wrist force/torque sensor's on the force topic) is refused; null: any "
            "frame (the first one seen is logged). A JointState's frame_id is not read (robots leave it empty)")
        max_clock_skew: Seconds = Field(0.05, ge=0, description="a stamp further in the future is clamped to the "
                                        "arrival time", json_schema_extra={"unit": "s"})
        max_opening: Meters = Field(1.0, gt=0, description="a JointState position (opening) larger than this is "
                                    "refused: millimetres in the metre field", json_schema_extra={"unit": "m"})
        max_depth: Meters = Field(0.05, gt=0, description="a depth map with a value larger than this is refused: "
                                  "millimetres in the metre field", json_schema_extra={"unit": "m"})
        max_force: Newtons = Field(MAX_FORCE_N, gt=0, description="a force larger than this is refused: implausible "
                                   "for a fingertip (millinewtons in the newton field, a broken sender)",
                                   json_schema_extra={"unit": "N"})
        min_force: Newtons = Field(-0.05, le=0, description="a force below this is refused (a grip force is >= 0 N: "
                                   "a sender with the opposite sign); one between it and 0 (noise around a sensor's "
                                   "zero) is output as 0", json_schema_extra={"unit": "N"})
        restart_after: Seconds | None = Field(
            None, gt=0, description="stamps: arrival only: a header.stamp older than the last one taken by more than "
            "this is the sender's stamps starting again (ros2 bag play --loop beginning its next pass), not an old "
            "message: taken, counted (restarts) and logged once; None: dropped as out of order",
            json_schema_extra={"unit": "s"})

        @field_validator("max_force")
        @classmethod
        def _plausible_force(cls, v: float, info: Any) -> float:
            return plausible_quantity(info.field_name, v, MAX_PLAUSIBLE_FORCE_LIMIT, "N",
                                      "beyond any fingertip force sensor's range")

        @model_validator(mode="after")
        def _restart_with_arrival(self) -> "Ros2Subscribe.Params":
            if self.restart_after is not None and self.stamps != "arrival":
                raise ValueError("restart_after: only with stamps: arrival (with stamps: message a restarted "
                                 "sender's older stamps would take the port back in time; a replayed bag's "
                                 "recorded stamps are stale anyway)")
            return self

        @field_validator("max_opening")
        @classmethod
        def _plausible_opening(cls, v: float, info: Any) -> float:
            return plausible_opening(info.field_name, v)   # 90 meant 90 mm: the guard took millimetres as metres

        @field_validator("max_depth")
        @classmethod
        def _plausible_depth(cls, v: float, info: Any) -> float:
            return plausible_depth(info.field_name, v, MAX_PLAUSIBLE_DEPTH_LIMIT)

        @field_validator("durability", mode="before")
        @classmethod
        def _volatile_only(cls, v: Any) -> Any:
            if v == "transient_local":
                raise ValueError("ros2-subscribe takes 'volatile' only: with 'transient_local' a subscriber that "
                                 "joins late receives the publisher's latched old samples and outputs them (with "
                                 "stamps: arrival, or a clamped stamp, as fresh ones); a volatile subscription "
                                 "still connects to a transient_local publisher")
            return v

    @classmethod
    def wiring_problems(cls, params: Any, inputs: Any, outputs: Any) -> dict[str, str]:
        """{output: why} for the outputs other nodes read whose topic is not subscribed (``params.topics``): such
        an output would never carry a sample. For the graph's validation: ``outputs`` are the node's output ports
        that other nodes read."""
        return _unlisted(outputs, list(params.topics), "output", "add {topic} to topics, or read another output")

    def configure(self) -> None:
        WrenchStamped, Image, JointState, Float64 = _message_types()

        p = self.params
        self._lock = threading.Lock()
        # port -> (value, Unix time of the stamp): converted to graph time when a step outputs it, so a message
        # that arrived before the graph clock started (while other nodes were starting) keeps its age
        self._pending: dict[str, tuple[Any, float]] = {}
        self._last_raw: dict[str, int] = {}   # port -> header.stamp (ns) of the last value taken
        self._last_order: dict[str, int] = {}   # port -> the same, of the last value whose stamp was not clamped
        self._last_out: dict[str, float] = {}   # port -> graph stamp of the last sample output
        self.received = 0
        self.skewed = 0
        self.bad = 0
        self.unstamped = 0
        self.duplicates = 0
        self.out_of_order = 0
        self.restarts = 0
        self.late = 0
        self.off_axis = 0
        self.wrong_frame = 0
        self.lag: float | None = None   # arrival - header.stamp of the last message taken (s)
        self._last_rx: float | None = None   # time.monotonic() of the last message taken
        self._log_once = _LogOnce(self.ctx)
        self._clock = _Clock(self.ctx)
        _check_lengths(p, self.id)
        self._ros = _Ros(p.node_name or self.id, p.namespace, p.domain_id, self._log_once)
        qos = qos_profile(p)
        handlers = {"force": (WrenchStamped, p.force_topic, self._on_force),
                    "image": (Image, p.image_topic, self._on_image),
                    "depth": (Image, p.depth_topic, self._on_depth),
                    "joint_states": (JointState, p.joint_states_topic, self._on_joints),
                    "value": (Float64, p.value_topic, self._on_value)}
        self._subs = []
        for key in dict.fromkeys(p.topics):
            mtype, topic, cb = handlers[key]
            self._subs.append(self._ros.subscription(mtype, topic, self._guard(key, cb), qos))

    def activate(self) -> None:
        self._clock = _Clock(self.ctx)
        self._last_out = {}   # graph stamps: the graph clock starts now

    # callbacks run in the executor thread -----------------------------------------------------------------------
    def _guard(self, key: str, cb: Any) -> Any:
        def run(msg: Any) -> None:
            try:
                cb(msg)
            except _Bad as exc:
                self.bad += 1
                self._log_once(("bad", key, exc.kind), f"{key} topic: refused a message: {exc}")
            except Exception as exc:  # a malformed message must not kill the executor
                self.bad += 1
                self._log_once(("bad", key, type(exc).__name__),
                               f"{key} topic: dropped a bad message: {type(exc).__name__}: {exc}")
        return run

    def _take(self, key: str, header: Any | None, values: dict[str, Any]) -> None:
        """Stamp a message's values (Unix time) and hand them to the next step, or refuse the message."""
        p = self.params
        arrival = time.time()
        stamp = arrival
        if header is not None:
            sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
            raw = sec * 1_000_000_000 + nsec
            if p.stamps == "message":
                if sec < 0 or not 0 <= nsec < 1_000_000_000:
                    raise _Bad("invalid header.stamp", f" (sec {sec}, nanosec {nsec}): expected sec >= 0 and "
                                                       f"nanosec < 1e9")
                if raw == 0:
                    self.unstamped += 1
                    self._log_once(("unstamped", key), f"{key} topic: header.stamp is zero (the sender does not "
                                                       f"stamp its messages): refused, its age is unknown; set "
                                                       f"stamps: arrival to stamp such messages on arrival")
                    return
            if raw != 0:
                # a port whose last value taken has this stamp has this measurement already (a sender re-sending
                # its last message): not a new sample, and never one stamped afresh on arrival. Per port, not per
                # topic: a JointState's fields of one measurement may come in two messages (one field sent, the
                # other not yet written when the sender read it)
                values = {port: v for port, v in values.items() if self._last_raw.get(port) != raw}
                if not values:
                    self.duplicates += 1
                    return
                values = self._not_older(key, raw, values)
                if not values:
                    return
            clamped = False
            if p.stamps == "message":
                stamp = sec + nsec * 1e-9
                lag = arrival - stamp
                if lag < -p.max_clock_skew:
                    clamped = True
                    self.skewed += 1
                    self._log_once(("skewed", key), f"{key} topic: header.stamp {-lag:.3f} s ahead of this "
                                                    f"machine's clock: clamped to the arrival time (synchronise "
                                                    f"the clocks, or set stamps: arrival)")
                    stamp = arrival
                elif lag > LATE_AFTER:
                    self.late += 1
                    self._log_once(("late", key), f"{key} topic: header.stamp {lag:.3f} s old on arrival: the "
                                                  f"publisher's clock is behind this one (synchronise the clocks, "
                                                  f"or set stamps: arrival) or it sends old data; the samples "
                                                  f"keep their stamps and look stale")
                self.lag = lag
            self._last_raw.update(dict.fromkeys(values, raw))
            if not clamped:   # a stamp in the future is no reference for the order of the next ones
                self._last_order.update(dict.fromkeys(values, raw))
        with self._lock:
            for port, v in values.items():
                self._pending[port] = (v, stamp)
            self._last_rx = time.monotonic()
            self.received += 1

    def _not_older(self, key: str, raw: int, values: dict[str, Any]) -> dict[str, Any]:
        """``values`` less the ports whose last value taken has a newer header.stamp than ``raw`` (ns): an older
        measurement (a second publisher on the topic, messages out of order) would push the port back in time, or,
        stamped on arrival, pass for the newest one. Counted (``out_of_order``) and logged once. The sender's
        stamps are compared, with either ``stamps`` mode, but not one clamped as too far in the future (a single
        wrong stamp would silence the port until the sender's clock reached it); a sender whose clock steps back
        is not heard until its stamps pass the last one taken."""
        older = {port: last for port in values if (last := self._last_order.get(port, raw)) > raw}
        after = self.params.restart_after
        if after is not None and (restarted := [port for port, last in older.items() if last - raw > after * 1e9]):
            self.restarts += 1
            self._log_once(("restart", key), f"{key} topic: header.stamp {(older[restarted[0]] - raw) * 1e-9:.3f} s "
                                             f"older than the last one taken for '{restarted[0]}', more than "
                                             f"restart_after ({after:g} s): taken as the sender starting again (a "
                                             f"looped bag's next pass); further ones are counted (restarts)")
            for port in restarted:
                del older[port]
                self._last_order.pop(port, None)
        if not older:
            return values
        self.out_of_order += 1
        port, last = max(older.items(), key=lambda kv: kv[1])
        self._log_once(("older", key), f"{key} topic: header.stamp {(last - raw) * 1e-9:.3f} s older than the last "
                                       f"one taken for '{port}': dropped, a port's stamps never go back (a second "
                                       f"publisher on this topic, messages out of order, or the sender's clock "
                                       f"stepped back)")
        return {port: v for port, v in values.items() if port not in older}

    @staticmethod
    def _finite(what: str, v: float) -> float:
        if not math.isfinite(v):
            raise _Bad(f"{what} is not finite", f" ({v!r})")
        return v

    def _frame_ok(self, key: str, header: Any) -> bool:
        """Whether a message's ``header.frame_id`` is the one expected (``frame_id``; null: any, the first one seen
        logged). Another frame (a second sender on the topic: a wrist force/torque sensor's wrench, another camera)
        is refused before its stamp is looked at, so it cannot make the expected sender's messages look repeated or
        out of order: counted (``wrong_frame``) and logged once per topic (the first frame refused: a sender that
        changes its frame_id at each message must not use up the log's budget of kinds of problem)."""
        want, got = self.params.frame_id, str(header.frame_id)
        if want is None:   # (logged for the first message of each topic)
            self._log_once(("frame", key), f"{key} topic: header.frame_id '{got}' (frame_id: null takes any frame; "
                                           f"set frame_id: {got!r} to refuse others)")
            return True
        if got == want:
            return True
        self.wrong_frame += 1
        self._log_once(("wrong_frame", key), f"{key} topic: header.frame_id '{got}', expected '{want}' (frame_id): "
                                             f"refused, another sender's frame (set frame_id to the sender's frame, "
                                             f"or null to take any); further ones are counted (wrong_frame), not "
                                             f"logged")
        return False

    def _on_force(self, msg: Any) -> None:
        if not self._frame_ok("force", msg.header):
            return
        p = self.params
        axis = p.force_axis
        f = msg.wrench.force
        v = self._finite("force", float(getattr(f, axis)))
        if v > p.max_force:
            raise _Bad("force larger than max_force", f" ({v:g} N > {p.max_force:g} N): implausible for a fingertip "
                                                      f"(millinewtons sent as newtons? WrenchStamped is in N)")
        if v < p.min_force:
            raise _Bad("force below min_force", f" ({v:g} N < {p.min_force:g} N): a grip force is >= 0 N (does the "
                                                f"sender's force_axis point the other way?)")
        if v == 0.0:
            other = {a: float(getattr(f, a)) for a in _AXES if a != axis and float(getattr(f, a)) != 0.0}
            if other:
                self.off_axis += 1
                a, fa = next(iter(other.items()))
                self._log_once(("axis", a), f"force topic: force.{axis} (force_axis) is 0 while force.{a} is "
                                            f"{fa:g} N: does the sender put the force on another axis?")
        self._take("force", msg.header, {"force": v if v > 0.0 else 0.0})   # (-0.0 too: a grip force is >= 0)

    def _image(self, msg: Any, what: str) -> np.ndarray:
        from teletouch.recording import image_from_msg

        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        if h == 0 or w == 0:
            raise _Bad(f"{what}: empty image", f" ({h} x {w})")
        bpp = _BYTES_PER_PIXEL.get(msg.encoding.lower())
        if bpp is not None and step < w * bpp:
            raise _Bad(f"{what}: step too small", f" ({step} bytes a row for {w} {msg.encoding} pixels)")
        if len(msg.data) < h * step:
            raise _Bad(f"{what}: data too short", f" ({len(msg.data)} bytes for {h} rows of {step})")
        return image_from_msg(msg)

    def _on_image(self, msg: Any) -> None:
        if not self._frame_ok("image", msg.header):
            return
        a = self._image(msg, "image")
        if a.dtype != np.uint8 or a.ndim != 3:
            raise _Bad("image: not a colour image", f": expected bgr8/rgb8/bgra8/rgba8, got encoding "
                                                    f"'{msg.encoding}'")
        self._take("image", msg.header, {"image": a})

    def _on_depth(self, msg: Any) -> None:
        if not self._frame_ok("depth", msg.header):
            return
        a = self._image(msg, "depth")
        if a.ndim != 2 or a.dtype.kind != "f":
            raise _Bad("depth: not a depth map", f": expected 32FC1/64FC1/16UC1, got encoding '{msg.encoding}'")
        a = a.astype(np.float32, copy=False)
        if not np.isfinite(a).all():
            raise _Bad("depth is not finite", f" ({int(np.count_nonzero(~np.isfinite(a)))} NaN/inf pixels)")
        top = float(np.abs(a).max())
        if top > self.params.max_depth:
            raise _Bad("depth larger than max_depth", f" ({top:g} m > {self.params.max_depth:g} m): millimetres "
                                                      f"in a metre field? (32FC1 is in metres, 16UC1 in mm)")
        self._take("depth", msg.header, {"depth": a})

    def _on_joints(self, msg: Any) -> None:
        p = self.params
        names = list(msg.name)
        if names:
            if p.joint_name not in names:
                return  # another joint's state
            i = names.index(p.joint_name)
        else:
            i = 0
        out = {}
        for port, field, arr in (("opening", "position", msg.position), ("velocity", "velocity", msg.velocity),
                                 ("effort", "effort", msg.effort)):
            if len(arr) == 0:
                continue   # not sent (JointState allows empty fields)
            if names and len(arr) != len(names):
                raise _Bad(f"JointState.{field} length", f": {len(arr)} values for {len(names)} names")
            if len(arr) <= i:
                raise _Bad(f"JointState.{field} length", f": no value for joint {i}")
            out[port] = float(arr[i])
        # NaN (or inf) often means "not measured": such a field is left out, the others go on; it is sorted out
        # first, as an inf opening is no sign of millimetres
        bad = {k: v for k, v in out.items() if not math.isfinite(v)}
        ok = {k: v for k, v in out.items() if k not in bad}
        if "opening" in ok and abs(ok["opening"]) > p.max_opening:
            raise _Bad("opening larger than max_opening", f" ({ok['opening']:g} m > {p.max_opening:g} m): "
                                                          f"millimetres in the metre field? (the whole message is "
                                                          f"refused: its velocity would be in mm/s too)")
        if ok:
            self._take("joint_states", msg.header, ok)
        for k, v in bad.items():
            self.bad += 1
            self._log_once(("bad", "joint_states", "nonfinite", k),
                           f"joint_states topic: {k} is not finite ({v!r}): left out")

    def _on_value(self, msg: Any) -> None:
        self._take("value", None, {"value": self._finite("value", float(msg.data))})

    # graph side --------------------------------------------------------------------------------------------------
    def step(self, t, inputs):
        with self._lock:
            if not self._pending:
                return None
            pending, self._pending = self._pending, {}
        off = self._clock.offset_now()
        return {port: Sample(v, self._after_last(port, stamp - off)) for port, (v, stamp) in pending.items()}

    def _after_last(self, port: str, stamp: float) -> float:
        """``stamp`` (graph time), or just after the port's last one where it is not after it: a stamp clamped to
        its arrival time may be before the last one kept (which was up to max_clock_skew ahead), and the Unix to
        graph offset is measured anew at each step. A port's stamps never go back, and a new value never has the
        stamp of the last (a consumer would take it for a repeat)."""
        last = self._last_out.get(port)
        if last is not None and stamp <= last:
            stamp = math.nextafter(last, math.inf)
        self._last_out[port] = stamp
        return stamp

    def status(self):
        rx = getattr(self, "_last_rx", None)
        problems = {"bad": getattr(self, "bad", 0), "unstamped": getattr(self, "unstamped", 0),
                    "skewed": getattr(self, "skewed", 0), "late": getattr(self, "late", 0),
                    "off_axis": getattr(self, "off_axis", 0), "wrong_frame": getattr(self, "wrong_frame", 0),
                    "duplicates": getattr(self, "duplicates", 0),
                    "out_of_order": getattr(self, "out_of_order", 0), "restarts": getattr(self, "restarts", 0),
                    **_ros_status(self)}
        lag = getattr(self, "lag", None)
        return {"received": getattr(self, "received", 0),
                "since_last_s": (time.monotonic() - rx) if rx is not None else math.inf,
                "lag_s": lag if lag is not None else math.nan,
                "problems": sum(v for k, v in problems.items() if k not in ("duplicates", "restarts")),
                **problems}

    def close(self) -> None:
        _close_ros(self)


_BYTES_PER_PIXEL = {"bgr8": 3, "rgb8": 3, "8uc3": 3, "bgra8": 4, "rgba8": 4, "8uc4": 4, "mono8": 1, "8uc1": 1,
                    "32fc1": 4, "64fc1": 8, "16uc1": 2, "mono16": 2}


@hookimpl
def teletouch_components():
    return [Ros2Publish, Ros2Subscribe]
