"""pal-gripper: PAL Robotics' parallel gripper through ROS 2 (rclpy): joint trajectories in, /joint_states out.

The gripper has two prismatic finger joints (``gripper_left_finger_joint``, ``gripper_right_finger_joint``, 0-0.045 m
each); the opening is their sum. Each step publishes, when the setpoint changed (and at least every
``republish_period`` so that the controller keeps its goal), a trajectory_msgs/JointTrajectory with one point
(both fingers at half the opening, reached after ``time_from_start``) on ``<namespace>/<controller>/joint_trajectory``
-- the topic joint_trajectory_controller accepts besides its action. The state comes from sensor_msgs/JointState on
``/joint_states`` (opening = sum of the finger positions, velocity likewise, effort = mean finger effort magnitude,
NaN when the message carries none).

The position controller has no force limit of its own, so ``max_effort`` is enforced here: while the reported effort
exceeds it, the setpoint backs off towards the measured opening (at ``max_speed``) instead of closing further. That
needs efforts in ``/joint_states``: without them (or with non-finite ones) the driver refuses to run (a HardwareError
at start-up or at the message that lacks them) unless ``enforce_effort: false`` says to run without the force limit
(the effort output is then NaN).

A controller that goes away while ``/joint_states`` keeps arriving (unloaded, crashed) is noticed too: every read
checks that something still subscribes to the command topic, and ``controller_timeout`` without a subscriber is a
HardwareError (how soon DDS reports a crashed process's subscription gone is its liveliness lease; a controller
that is unloaded or shut down cleanly is gone at once).

rclpy is imported lazily (``pip install teletouch[ros2]``). The driver owns its rclpy Context, node and executor thread
(never rclpy's global context), so it coexists with other ROS 2 users (e.g. the ROS 2 bridge) in the same process.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from pydantic import Field, field_validator

from teletouch import HardwareError, hookimpl
from teletouch.units import Meters, MetersPerSecond, Newtons, Seconds

from .follower_common import FollowerBase, FollowerParams, Reading, clamp

JOINTS = ("gripper_left_finger_joint", "gripper_right_finger_joint")


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
        joint_states_topic: str = Field("/joint_states", description="sensor_msgs/JointState topic")
        domain_id: int | None = Field(None, ge=0, le=232, description="ROS_DOMAIN_ID (None: from the environment)")
        max_opening: Meters = Field(0.09, gt=0, description="largest opening (2 x 0.045 m)",
                                    json_schema_extra={"unit": "m"})
        max_speed: MetersPerSecond = Field(0.1, gt=0, description="opening speed limit (2 x 0.05 m/s per finger)",
                                           json_schema_extra={"unit": "m/s"})
        max_effort: Newtons = Field(16.0, gt=0, description="grip force above which the fingers close no further",
                                    json_schema_extra={"unit": "N"})
        time_from_start: Seconds = Field(0.01, gt=0, description="time given to reach each setpoint: one period of "
                                         "the node's stream (100 Hz: 10 ms), so each setpoint is reached as the "
                                         "next arrives; longer makes every setpoint a partial step and the "
                                         "follower lags", json_schema_extra={"unit": "s"})
        republish_period: Seconds = Field(0.1, gt=0, description="resend an unchanged setpoint this often",
                                          json_schema_extra={"unit": "s"})
        connect_timeout: Seconds = Field(3.0, gt=0, description="wait this long for the controller and "
                                         "/joint_states at start", json_schema_extra={"unit": "s"})
        controller_timeout: Seconds = Field(0.5, gt=0, description="fault when nothing has subscribed to the "
                                            "command topic for this long (the controller is gone)",
                                            json_schema_extra={"unit": "s"})
        enforce_effort: bool = Field(True, description="max_effort needs efforts in /joint_states: refuse to run "
                                     "without them (false: run without the force limit, effort output NaN)")

        @field_validator("namespace")
        @classmethod
        def _ns(cls, v: str) -> str:
            v = v.strip()
            if v and not v.startswith("/"):
                v = "/" + v
            return v.rstrip("/")

    # ------------------------------------------------------------------------------------------------------------
    @property
    def command_topic(self) -> str:
        p = self.params
        return f"{p.namespace}/{p.controller}/joint_trajectory"

    def _hw_open(self) -> None:
        try:
            import rclpy
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.qos import QoSProfile, ReliabilityPolicy
            from sensor_msgs.msg import JointState
            from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
        except ImportError as exc:
            raise HardwareError(f"pal-gripper needs ROS 2's rclpy and messages ({exc}); install them with "
                                f"pip install 'teletouch[ros2]'") from exc
        p = self.params
        self._JointTrajectory, self._Point = JointTrajectory, JointTrajectoryPoint
        self._lock = threading.Lock()
        self._state: tuple[float, float | None, float, float] | None = None  # opening, velocity, effort, mono
        self._msgs = 0
        self.ros_ctx = rclpy.Context()
        kw = {} if p.domain_id is None else {"domain_id": p.domain_id}
        rclpy.init(context=self.ros_ctx, **kw)
        self.ros_node = rclpy.create_node(f"teletouch_{self.id.replace('-', '_')}", context=self.ros_ctx)
        self.pub = self.ros_node.create_publisher(JointTrajectory, self.command_topic,
                                                  QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.ros_node.create_subscription(JointState, p.joint_states_topic, self._on_joint_states,
                                          QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.executor = SingleThreadedExecutor(context=self.ros_ctx)
        self.executor.add_node(self.ros_node)
        self._spin = threading.Thread(target=self._spin_loop, name=f"{self.id}-rclpy", daemon=True)
        self._spin.start()
        domain = p.domain_id if p.domain_id is not None else self.ros_ctx.get_domain_id()
        deadline = time.monotonic() + p.connect_timeout
        while self.pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise HardwareError(f"no controller subscribes to {self.command_topic} after "
                                    f"{p.connect_timeout} s (ROS_DOMAIN_ID {domain}); check the robot is up, "
                                    f"the namespace and controller name, and the network/discovery settings")
            time.sleep(0.01)
        while self._state is None:
            if time.monotonic() > deadline:
                what = "no message" if self._msgs == 0 else f"{self._msgs} messages without both joints"
                raise HardwareError(f"{p.joint_states_topic}: {what} for {list(p.joint_names)} after "
                                    f"{p.connect_timeout} s (ROS_DOMAIN_ID {domain}); check the joint names and "
                                    f"the joint_state_broadcaster")
            time.sleep(0.005)
        self._sent: float | None = None
        self._sent_at = 0.0
        self._no_controller_since: float | None = None

    def _spin_loop(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # the context was shut down under it
            pass

    def _on_joint_states(self, msg: Any) -> None:
        mono = time.monotonic()
        self._msgs += 1
        names = list(msg.name)
        try:
            idx = [names.index(j) for j in self.params.joint_names]
            pos = [msg.position[i] for i in idx]
        except (ValueError, IndexError):
            return
        vel = [msg.velocity[i] for i in idx] if len(msg.velocity) == len(names) else None
        eff = [msg.effort[i] for i in idx] if len(msg.effort) == len(names) else None
        state = (pos[0] + pos[1], None if vel is None else vel[0] + vel[1],
                 math.nan if eff is None else 0.5 * (abs(eff[0]) + abs(eff[1])), mono)
        with self._lock:
            self._state = state

    def _check_controller(self, now: float) -> None:
        """Fault when nothing has subscribed to the command topic for controller_timeout (one graph lookup)."""
        if self.pub.get_subscription_count() > 0:
            self._no_controller_since = None
            return
        if self._no_controller_since is None:
            self._no_controller_since = now
        gone = now - self._no_controller_since
        if gone > self.params.controller_timeout:
            raise HardwareError(f"no controller is subscribed to {self.command_topic} for {gone:.3f} s "
                                f"(controller_timeout {self.params.controller_timeout} s) while "
                                f"{self.params.joint_states_topic} goes on: the controller was unloaded or crashed; "
                                f"the commands reach nobody")

    def _hw_read(self) -> Reading | None:
        p = self.params
        now = time.monotonic()
        self._check_controller(now)
        with self._lock:
            s = self._state
        if s is None:
            return None
        age = now - s[3]
        if age > p.read_timeout:
            raise HardwareError(f"{p.joint_states_topic} silent for {age:.3f} s (read_timeout "
                                f"{p.read_timeout} s); the robot or the network is gone")
        if p.enforce_effort and not math.isfinite(s[2]):
            raise HardwareError(f"{p.joint_states_topic} carries no efforts for {list(p.joint_names)} (missing or "
                                f"not finite): max_effort ({p.max_effort} N) cannot be enforced without them; set "
                                f"enforce_effort: false to run without the force limit (effort output NaN)")
        return Reading(s[0], s[1], s[2], s[3])

    def activate(self) -> None:
        self._no_controller_since = None  # counted afresh: the node was not looking while inactive
        super().activate()

    def command_target(self, t: float, inputs: Any) -> float:
        before, t_before = self._setpoint, self._last_t
        target = super().command_target(t, inputs)
        r = self._last_reading
        if r is not None and math.isfinite(r.effort) and r.effort > self.params.max_effort and target < r.opening:
            # squeezing harder than max_effort: back the setpoint off towards the measured opening
            dt = 0.0 if t_before is None else max(0.0, t - t_before)
            target = self._setpoint = max(target, min(r.opening, before + self.params.max_speed * dt))
        return target

    def _hw_write(self, opening: float) -> None:
        p = self.params
        now = time.monotonic()
        if self._sent is not None and abs(opening - self._sent) < 1e-7 and now - self._sent_at < p.republish_period:
            return
        half = clamp(opening, p.min_opening, p.max_opening) / 2.0
        msg = self._JointTrajectory()
        msg.joint_names = list(p.joint_names)
        pt = self._Point()
        pt.positions = [half, half]
        sec = int(p.time_from_start)
        pt.time_from_start.sec = sec
        pt.time_from_start.nanosec = int(round((p.time_from_start - sec) * 1e9))
        msg.points = [pt]
        self.pub.publish(msg)
        self._sent, self._sent_at = opening, now

    def _hw_close(self) -> None:
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
