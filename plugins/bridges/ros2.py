"""ROS 2 bridge: graph ports to and from ROS 2 topics with standard messages (extra ``teletouch[ros2]``).

``ros2-publish`` publishes whatever is wired into it; ``ros2-subscribe`` turns topics back into graph outputs. Two
graphs on two machines (or two processes) split a pipeline through DDS, e.g. machine A runs
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
``ros = graph + (time.time() - graph_now())``, measured at each conversion on a wall-clock graph, and fixed when
the node activates on a simulated clock. The subscriber maps back to its own graph clock with its own offset, so a
sample keeps its age across the bridge, and a consumer's ``max_age`` sees the force go stale when the publisher
dies. Across machines this needs synchronised system clocks (chrony/PTP); where they are not,
``stamps: arrival`` stamps each message with its arrival time (transport latency is then hidden). A stamp more
than ``max_clock_skew`` in the future is clamped to the arrival time and counted (``status()['skewed']``).

Each node has its own rclpy Context (its own DDS participant; ``domain_id`` param, default ``ROS_DOMAIN_ID``), never
the global default context, and spins its executor in a background thread. Ports are latest-value: the subscriber
outputs a message once, at its next step after it arrived; older messages that arrived in between are dropped.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field

from teletouch import Component, ComponentFault, Kind, Params, Port, Sample, hookimpl
from teletouch.units import Seconds

TOPICS = ("force", "image", "depth", "joint_states", "value")
_AXES = {"x": 0, "y": 1, "z": 2}


class QosParams(Params):
    reliability: Literal["reliable", "best_effort"] = Field("reliable", description="QoS reliability")
    durability: Literal["volatile", "transient_local"] = Field("volatile", description="QoS durability")
    depth: int = Field(5, ge=1, le=10000, description="QoS history depth (keep last N)")


class _BridgeParams(QosParams):
    namespace: str = Field("/teletouch", description="ROS namespace of the topics (relative topic names)")
    node_name: str | None = Field(None, description="ROS node name (default: the graph node id)")
    domain_id: int | None = Field(None, ge=0, le=232, description="ROS domain id (default: ROS_DOMAIN_ID or 0)")
    force_topic: str = Field("force", description="geometry_msgs/WrenchStamped topic of 'force'")
    image_topic: str = Field("image", description="sensor_msgs/Image (bgr8) topic of 'image'")
    depth_topic: str = Field("depth", description="sensor_msgs/Image (32FC1, m) topic of 'depth'")
    joint_states_topic: str = Field("joint_states", description="sensor_msgs/JointState topic of opening/velocity/"
                                    "effort")
    value_topic: str = Field("value", description="std_msgs/Float64 topic of 'value'")
    force_axis: Literal["x", "y", "z"] = Field("z", description="wrench force component that carries 'force'")
    joint_name: str = Field("gripper", description="JointState joint carrying opening/velocity/effort")


class _Ros:
    """One rclpy Context + node + executor thread (never the global default context)."""

    def __init__(self, name: str, namespace: str, domain_id: int | None):
        try:
            import rclpy
            from rclpy.context import Context
            from rclpy.executors import SingleThreadedExecutor
        except ImportError as exc:  # pragma: no cover - CI installs the extra
            raise ComponentFault(f"the ROS 2 bridge needs rclpy: pip install 'teletouch[ros2]' ({exc})") from exc
        self.rclpy = rclpy
        self.ctx = Context()
        kw = {} if domain_id is None else {"domain_id": domain_id}
        rclpy.init(context=self.ctx, **kw)
        try:
            self.node = rclpy.create_node(_ros_name(name), namespace=namespace or "/", context=self.ctx,
                                          start_parameter_services=False)
            self.executor = SingleThreadedExecutor(context=self.ctx)
            self.executor.add_node(self.node)
        except Exception:
            rclpy.shutdown(context=self.ctx)
            raise
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, name=f"ros2-{name}", daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # context shut down under us while stopping
                if self._stop.is_set() or not self.ctx.ok():
                    return
                raise

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=2.0)
        try:
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            if self.ctx.ok():
                self.rclpy.shutdown(context=self.ctx)


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

    def __init__(self, ctx: Any):
        self.ctx = ctx
        self.fixed = ctx.clock_kind != "wall"
        self.offset = time.time() - ctx.now()

    def _off(self) -> float:
        return self.offset if self.fixed else time.time() - self.ctx.now()

    def to_ros(self, graph_t: float) -> float:
        return graph_t + self._off()

    def to_graph(self, ros_t: float) -> float:
        return ros_t - self._off()


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

    def configure(self) -> None:
        from geometry_msgs.msg import WrenchStamped
        from sensor_msgs.msg import Image, JointState
        from std_msgs.msg import Float64

        p = self.params
        self._types = {"force": WrenchStamped, "image": Image, "depth": Image, "joint_states": JointState,
                       "value": Float64}
        self._topics = {"force": p.force_topic, "image": p.image_topic, "depth": p.depth_topic,
                        "joint_states": p.joint_states_topic, "value": p.value_topic}
        self._ros = _Ros(p.node_name or self.id, p.namespace, p.domain_id)
        self._qos = qos_profile(p)
        self._pubs: dict[str, Any] = {}
        self._last: dict[str, Any] = {}
        self.published = 0
        self._clock = _Clock(self.ctx)

    def activate(self) -> None:
        self._clock = _Clock(self.ctx)

    def _pub(self, key: str) -> Any:
        pub = self._pubs.get(key)
        if pub is None:  # created on first use: only wired ports get a topic
            pub = self._pubs[key] = self._ros.node.create_publisher(self._types[key], self._topics[key], self._qos)
        return pub

    def _new(self, inputs: Any, name: str) -> Sample | None:
        s = inputs[name]
        if s is None or s is self._last.get(name):
            return None
        self._last[name] = s
        return s

    def step(self, t, inputs):
        from geometry_msgs.msg import WrenchStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64

        from teletouch.recording import image_msg, ros_time

        p = self.params
        s = self._new(inputs, "force")
        if s is not None:
            m = WrenchStamped()
            m.header.stamp = ros_time(self._clock.to_ros(s.stamp))
            m.header.frame_id = p.frame_id
            setattr(m.wrench.force, p.force_axis, float(s.value))
            self._pub("force").publish(m)
            self.published += 1
        for name in ("image", "depth"):
            s = self._new(inputs, name)
            if s is not None:
                a = np.asarray(s.value)
                if name == "depth" and a.dtype != np.float32:
                    a = a.astype(np.float32)
                self._pub(name).publish(image_msg(a, self._clock.to_ros(s.stamp), p.frame_id))
                self.published += 1
        js = [self._new(inputs, n) for n in ("opening", "velocity", "effort")]
        if any(x is not None for x in js):
            m = JointState()
            m.header.stamp = ros_time(self._clock.to_ros(max(x.stamp for x in js if x is not None)))
            m.header.frame_id = p.frame_id
            m.name = [p.joint_name]
            cur = [inputs[n] for n in ("opening", "velocity", "effort")]
            if cur[0] is not None:
                m.position = [float(cur[0].value)]
            if cur[1] is not None:
                m.velocity = [float(cur[1].value)]
            if cur[2] is not None:
                m.effort = [float(cur[2].value)]
            self._pub("joint_states").publish(m)
            self.published += 1
        s = self._new(inputs, "value")
        if s is not None:
            self._pub("value").publish(Float64(data=float(s.value)))
            self.published += 1
        return None

    def status(self):
        return {"published": getattr(self, "published", 0)}

    def close(self) -> None:
        ros = getattr(self, "_ros", None)
        if ros is not None:
            self._ros = None
            ros.close()


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
        topics: list[Literal["force", "image", "depth", "joint_states", "value"]] = Field(
            ["force"], description="which topics to subscribe to (force, image, depth, joint_states, value)")
        stamps: Literal["message", "arrival"] = Field(
            "message", description="sample stamps: the message's header.stamp (needs synchronised clocks) or the "
            "arrival time")
        max_clock_skew: Seconds = Field(0.05, ge=0, description="a stamp further in the future is clamped to the "
                                        "arrival time", json_schema_extra={"unit": "s"})

    def configure(self) -> None:
        from geometry_msgs.msg import WrenchStamped
        from sensor_msgs.msg import Image, JointState
        from std_msgs.msg import Float64

        p = self.params
        self._lock = threading.Lock()
        self._pending: dict[str, Sample] = {}
        self.received = 0
        self.skewed = 0
        self.bad = 0
        self._bad_logged = False
        self._last_rx: float | None = None
        self._clock = _Clock(self.ctx)
        self._ros = _Ros(p.node_name or self.id, p.namespace, p.domain_id)
        qos = qos_profile(p)
        handlers = {"force": (WrenchStamped, p.force_topic, self._on_force),
                    "image": (Image, p.image_topic, self._on_image),
                    "depth": (Image, p.depth_topic, self._on_depth),
                    "joint_states": (JointState, p.joint_states_topic, self._on_joints),
                    "value": (Float64, p.value_topic, self._on_value)}
        self._subs = []
        for key in dict.fromkeys(p.topics):
            mtype, topic, cb = handlers[key]
            self._subs.append(self._ros.node.create_subscription(mtype, topic, self._guard(cb), qos))

    def activate(self) -> None:
        self._clock = _Clock(self.ctx)

    # callbacks run in the executor thread -----------------------------------------------------------------------
    def _guard(self, cb: Any) -> Any:
        def run(msg: Any) -> None:
            try:
                cb(msg)
            except Exception as exc:  # a malformed message must not kill the executor
                self.bad += 1
                if not self._bad_logged:
                    self._bad_logged = True
                    self.ctx.log(f"dropped a bad message: {type(exc).__name__}: {exc}")
        return run

    def _stamp(self, header: Any | None) -> float:
        now = self.ctx.now()
        if header is None or self.params.stamps == "arrival":
            return now
        st = header.stamp
        t = self._clock.to_graph(st.sec + st.nanosec * 1e-9)
        if t > now + self.params.max_clock_skew:
            self.skewed += 1
            return now
        return t

    def _put(self, **samples: Sample) -> None:
        with self._lock:
            self._pending.update(samples)
            self.received += 1
            self._last_rx = self.ctx.now()

    def _on_force(self, msg: Any) -> None:
        v = float(getattr(msg.wrench.force, self.params.force_axis))
        self._put(force=Sample(v, self._stamp(msg.header)))

    def _on_image(self, msg: Any) -> None:
        from teletouch.recording import image_from_msg

        a = image_from_msg(msg)
        if a.dtype != np.uint8 or a.ndim != 3:
            raise ValueError(f"image topic: expected a colour image (bgr8/rgb8), got encoding '{msg.encoding}'")
        self._put(image=Sample(a, self._stamp(msg.header)))

    def _on_depth(self, msg: Any) -> None:
        from teletouch.recording import image_from_msg

        a = image_from_msg(msg)
        if a.ndim != 2 or a.dtype.kind != "f":
            raise ValueError(f"depth topic: expected 32FC1/64FC1/16UC1, got encoding '{msg.encoding}'")
        self._put(depth=Sample(a.astype(np.float32, copy=False), self._stamp(msg.header)))

    def _on_joints(self, msg: Any) -> None:
        name = self.params.joint_name
        names = list(msg.name)
        if names:
            if name not in names:
                return  # another joint's state
            i = names.index(name)
        else:
            i = 0
        t = self._stamp(msg.header)
        out = {}
        for port, arr in (("opening", msg.position), ("velocity", msg.velocity), ("effort", msg.effort)):
            if len(arr) > i:
                out[port] = Sample(float(arr[i]), t)
        if out:
            self._put(**out)

    def _on_value(self, msg: Any) -> None:
        self._put(value=Sample(float(msg.data), self._stamp(None)))

    # graph side --------------------------------------------------------------------------------------------------
    def step(self, t, inputs):
        with self._lock:
            if not self._pending:
                return None
            out, self._pending = self._pending, {}
        return out

    def status(self):
        rx = getattr(self, "_last_rx", None)
        return {"received": getattr(self, "received", 0),
                "since_last_s": (self.ctx.now() - rx) if rx is not None else math.inf,
                "skewed": getattr(self, "skewed", 0), "bad": getattr(self, "bad", 0)}

    def close(self) -> None:
        ros = getattr(self, "_ros", None)
        if ros is not None:
            self._ros = None
            ros.close()


@hookimpl
def teletouch_components():
    return [Ros2Publish, Ros2Subscribe]
