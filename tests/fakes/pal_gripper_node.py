"""A simulated PAL parallel gripper controller on real ROS 2 (rclpy), for the pal-gripper tests and benchmark.

Like the robot's joint_trajectory_controller ``gripper_controller`` with the joint_state_broadcaster: it subscribes
trajectory_msgs/JointTrajectory on ``<ns>/gripper_controller/joint_trajectory`` and publishes sensor_msgs/JointState
on ``/joint_states`` (both finger joints, 0-0.045 m each, velocity limit 0.05 m/s, effort limit 16). A trajectory
with other joint names, a wrong number of positions or non-finite values is rejected (counted in ``rejected``).
Timing follows ros2_control's read -> update -> write cycle at ``rate``: the subscription only stores the newest
valid trajectory (the controller's realtime buffer; the latest wins); the next control cycle takes it up and starts
it at that cycle's time from the present state (a zero ``header.stamp``, which is what the driver sends; the stamp
is not read), interpolated linearly to each point's ``time_from_start``; each cycle commands the trajectory's point
one period ahead, which the fingers reach by the next cycle, never faster than the velocity limit. (Starting a
trajectory at its arrival instead makes the progress per cycle depend on the phase between the sender's loop and
this one: 10 ms setpoints arriving just before each cycle lag by over 100 ms, which the real controller does not.)
An object of ``object_width`` between the fingers blocks them: each finger then pushes with ``min(16, stiffness *
(contact - goal))`` (negative effort: closing). When a goal stays farther than ``goal_tolerance`` from the position
``goal_time`` after the trajectory's end, the goal is aborted as the real controller does: the gripper holds where
it is (counted in ``aborted``). ``instant`` (``--instant``; for benchmarks/follower_latency.py, which times the
transport, not the motion): the cycle that takes a trajectory up commands its end point at once, whatever its
``time_from_start`` (the fingers still move at most ``velocity_limit``).

Runs in its own thread with its own rclpy Context (its own DDS participant); ``publishing = False`` stops it
publishing; ``drop_controller()`` destroys the trajectory subscription (the controller unloaded or crashed) while
``/joint_states`` goes on, ``restore_controller()`` subscribes again; ``report_effort = False`` publishes JointState
without efforts (as some robots do).
"""

from __future__ import annotations

import math
import threading
import time

JOINTS = ("gripper_left_finger_joint", "gripper_right_finger_joint")


class PalGripperNode:
    def __init__(self, namespace: str = "", *, domain_id: int = 0, rate: float = 100.0, opening: float = 0.09,
                 object_width: float | None = None, stiffness: float = 2000.0, effort_limit: float = 16.0,
                 velocity_limit: float = 0.05, goal_tolerance: float = 0.002, goal_time: float = 0.5,
                 instant: bool = False):
        self.ns = namespace.rstrip("/")
        self.domain_id = domain_id
        self.rate = rate
        self.pos = [opening / 2.0, opening / 2.0]
        self.vel = [0.0, 0.0]
        self.effort = [0.0, 0.0]
        self.object_width = object_width
        self.stiffness = stiffness
        self.effort_limit = effort_limit
        self.velocity_limit = velocity_limit
        self.goal_tolerance = goal_tolerance
        self.goal_time = goal_time
        self.instant = instant  # a trajectory's end point commanded at once, its timing ignored (benchmarks only)
        self.lower, self.upper = 0.0, 0.045
        self.received = 0
        self.rejected = 0
        self.aborted = 0
        self.published = 0
        self.publishing = True
        self.report_effort = True  # False: JointState without efforts (as some robots publish)
        self._traj: list[tuple[float, list[float]]] = []  # active trajectory: (monotonic time, positions)
        self._pending: list[tuple[float, list[float]]] | None = None  # newest received: (time_from_start, positions)
        self._command = list(self.pos)  # the setpoint written in the last control cycle
        self._goal: list[float] | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()

    # --- life cycle ------------------------------------------------------------------------------------------
    def start(self) -> "PalGripperNode":
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=self.domain_id)
        self.node = rclpy.create_node("gripper_controller", namespace=self.ns or "/", context=self.ctx)
        self._JointState = JointState
        self._JointTrajectory, self._qos = JointTrajectory, QoSProfile(depth=10,
                                                                       reliability=ReliabilityPolicy.RELIABLE)
        self._sub = None
        self.restore_controller()
        self.pub = self.node.create_publisher(JointState, "/joint_states", 10)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._spin = threading.Thread(target=self.executor.spin, name="pal-sim-spin", daemon=True)
        self._spin.start()
        self._loop = threading.Thread(target=self._run, name="pal-sim-loop", daemon=True)
        self._loop.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._loop.join(timeout=2.0)
        try:
            self.executor.shutdown(timeout_sec=1.0)
        except Exception:
            pass
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self._spin.join(timeout=2.0)

    def drop_controller(self) -> None:
        """The controller goes away (unloaded, crashed): nothing subscribes to the command topic any more, while
        the joint_state_broadcaster keeps publishing /joint_states."""
        if self._sub is not None:
            self.node.destroy_subscription(self._sub)
            self._sub = None

    def restore_controller(self) -> None:
        """The controller subscribes to its command topic (again)."""
        if self._sub is None:
            self._sub = self.node.create_subscription(self._JointTrajectory,
                                                      f"{self.ns}/gripper_controller/joint_trajectory",
                                                      self._on_trajectory, self._qos)

    @property
    def controller_loaded(self) -> bool:
        return self._sub is not None

    def __enter__(self) -> "PalGripperNode":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def opening(self) -> float:
        return self.pos[0] + self.pos[1]

    # --- controller ------------------------------------------------------------------------------------------
    def _on_trajectory(self, msg) -> None:
        self.received += 1
        names = list(msg.joint_names)
        if sorted(names) != sorted(JOINTS) or not msg.points:
            self.rejected += 1
            return
        order = [names.index(j) for j in JOINTS]
        points = []
        for pt in msg.points:
            if len(pt.positions) != len(names) or not all(math.isfinite(x) for x in pt.positions):
                self.rejected += 1
                return
            tfs = pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9
            q = [min(self.upper, max(self.lower, pt.positions[i])) for i in order]
            points.append((tfs, q))
        with self._lock:
            self._pending = points  # started by the next control cycle, not at its arrival

    def _start_pending(self, now: float) -> None:
        """Control cycle at ``now``: the newest received trajectory starts now, from the present state."""
        points, self._pending = self._pending, None
        if points is None:
            return
        self._traj = [(now, list(self.pos))] + [(now + tfs, q) for tfs, q in points]
        self._goal = self._traj[-1][1]
        self._goal_deadline = self._traj[-1][0] + self.goal_time

    def _reference(self, now: float) -> list[float]:
        tr = self._traj
        if not tr:
            return list(self.pos)
        if now >= tr[-1][0] or self.instant:
            return tr[-1][1]
        for (t0, q0), (t1, q1) in zip(tr, tr[1:]):
            if t0 <= now < t1:
                a = (now - t0) / (t1 - t0) if t1 > t0 else 1.0
                return [x0 + a * (x1 - x0) for x0, x1 in zip(q0, q1)]
        return tr[0][1]

    def _run(self) -> None:
        period = 1.0 / self.rate
        last = time.monotonic()
        nxt = last
        while not self._stop.is_set():
            nxt += period
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            now = time.monotonic()
            dt = now - last
            last = now
            with self._lock:
                # read: the fingers moved towards the setpoint written in the previous cycle
                ref = self._command
                contact = self.object_width / 2.0 if self.object_width is not None else None
                goal = self._traj[-1][1] if self._traj else ref
                for i in range(2):
                    step = max(-self.velocity_limit * dt, min(self.velocity_limit * dt, ref[i] - self.pos[i]))
                    new = self.pos[i] + step
                    eff = 0.0
                    if contact is not None and new <= contact and ref[i] < contact:
                        new = contact if self.pos[i] >= contact else self.pos[i]
                        # the position loop pushes with its gain times the error to the goal, up to the limit
                        eff = -min(self.effort_limit, self.stiffness * max(0.0, contact - goal[i]))
                    self.vel[i] = (new - self.pos[i]) / dt if dt > 0 else 0.0
                    self.pos[i] = new
                    self.effort[i] = eff
                # update: take up a new trajectory, check the goal, command the point one period ahead (write)
                self._start_pending(now)
                if self._goal is not None and now > self._goal_deadline:
                    if max(abs(g - x) for g, x in zip(self._goal, self.pos)) > self.goal_tolerance:
                        self.aborted += 1
                        self._traj = [(now, list(self.pos))]  # hold position
                    self._goal = None
                self._command = self._reference(now + period)
                if self.publishing:
                    msg = self._JointState()
                    msg.header.stamp = self.node.get_clock().now().to_msg()
                    msg.name = list(JOINTS) + ["arm_1_joint"]
                    msg.position = list(self.pos) + [0.3]
                    msg.velocity = list(self.vel) + [0.0]
                    msg.effort = list(self.effort) + [0.0] if self.report_effort else []
                    self.pub.publish(msg)
                    self.published += 1


def main(argv=None) -> int:
    """Run the simulated gripper in its own process until stdin closes (benchmarks: no GIL shared with the driver)."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(description="simulated PAL gripper controller")
    ap.add_argument("--namespace", default="")
    ap.add_argument("--domain-id", type=int, default=0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--velocity-limit", type=float, default=0.05)
    ap.add_argument("--opening", type=float, default=0.09)
    ap.add_argument("--instant", action="store_true", help="command each trajectory's end point at once")
    a = ap.parse_args(argv)
    node = PalGripperNode(a.namespace, domain_id=a.domain_id, rate=a.rate, velocity_limit=a.velocity_limit,
                          opening=a.opening, instant=a.instant).start()
    print("ready", flush=True)
    try:
        sys.stdin.read()
    except KeyboardInterrupt:
        pass
    node.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
