"""Follower drivers against their emulators: command-to-state round trip and achievable update rate, side by side.

    python benchmarks/follower_latency.py [--quick] [--ros-domain N]

Transports: pal-gripper over ROS 2 (DDS on loopback, the simulated controller in its own process publishing
/joint_states at 1 kHz),
dynamixel-gripper over a pseudo-terminal at 57600 and 1000000 baud (the emulated servo waits the bytes' wire time),
canopen-gripper on python-can's virtual bus (SYNC -> TPDO), and sim-gripper as the in-process reference.

- round trip (not for sim-gripper, which has no transport): the driver sends a new setpoint through its hardware path
  (``_hw_write``), then reads state (``_hw_read``) back to back until a state reflects it (canopen-gripper, whose
  set-point goes out by CiA 402's handshake over several writes, writes again after each read, as its steps do); the
  time in between, per command. The drivers set their actuators' profile speed from ``max_speed`` (Dynamixel
  Profile_Velocity, CANopen 0x6081, PAL's trajectory time), at most 2 m/s (a 30 mm step: ~15 ms of motion): the
  emulators here reach each goal at once instead (their ``instant`` knob, :func:`transport_specs`), so that the round
  trip is the transport's.
- update rate: full ``step()`` calls (read state + send command) back to back (a 20 us yield between, none for the
  thread-less sim-gripper) for a while;
  ``fresh_state_hz`` counts only steps that got a new measurement (ROS 2 state arrives asynchronously at the
  publisher's rate).

ROS 2 runs on ``--ros-domain`` (default: ROS_DOMAIN_ID if set, else a domain of this process's own, chosen from its
process id as the tests choose theirs, so that two runs at once do not see each other), discovery on this host only
(always: the emulator runs here), and the driver commands a controller under a namespace of this run's own
(``/bench_<pid>``), never a lab robot's ``/gripper_controller``. The JSON names the domain used.

Without ROS 2 (the optional extra teletouch[ros2]) the PAL case is skipped, with the reason under its key.

The round trips of every transport run side by side: the drivers open at once, ``rounds`` rounds of a tenth of the
round trips each, the order reversed every other round, so that a change of load on the shared machine hits them
alike; their update rates follow one after the other. The PAL emulator publishes /joint_states at 1 kHz from another
process, a load that would weigh on the others' round trips: it is stopped (SIGSTOP) outside PAL's turns and
continued for them, given time to settle first (it catches up the cycles it missed: ~0.05 s and a quarter of the
time it was stopped, not timed); its driver's executor thread then has nothing to do and waits without the GIL.
Checked on the shared 2-core machine, alternating pairs of runs: the Dynamixel (1 Mbaud) and CANopen round-trip
medians with a stopped PAL case beside them were within 1% of those without it (eight pairs); with its emulator left
running, 25-32% higher (four pairs).

Prints one JSON object as its last line. Absolute times depend on the machine (a shared 2-core box here); compare the
ratios between transports measured in the same run.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import statistics
import sys
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

# the emulator runs on this host: discovery stays on it, whatever the shell says (a lab's robot on the same domain
# must never see the benchmark's commands)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_LOCALHOST_ONLY"] = "1"
#: this process's own ROS domain, chosen from its process id as the tests choose theirs (the default when neither
#: --ros-domain nor ROS_DOMAIN_ID is given)
DOMAIN = 120 + (os.getpid() * 7 + 8) % 90
#: the controller's namespace, this run's own
NAMESPACE = f"/bench_{os.getpid()}"

from fakes.canopen_drive import Cia402Drive  # noqa: E402
from fakes.dynamixel_emulator import DynamixelEmulator  # noqa: E402

from teletouch.component import Context, Inputs, Sample, _Slot  # noqa: E402
from teletouch.plugins.ros_names import MAX_DOMAIN_ID, domain_id  # noqa: E402
from teletouch.units import MAX_PLAUSIBLE_SPEED  # noqa: E402
from bench_common import ROUNDS, alternating, emit, number  # noqa: E402


#: after the PAL emulator continues: a fixed wait, and a share of the time it was stopped (its catch-up cycles cost
#: ~0.1 of the time they stand for; this leaves room)
RESUME_SETTLE_S, RESUME_SETTLE_SHARE = 0.05, 0.25


class PalProcess:
    """The simulated PAL gripper in its own process (as the robot is another machine): no GIL shared with the driver;
    it commands each trajectory's end point at once (``--instant``) and moves the fingers there within a control cycle
    (``--velocity-limit 1000``, m/s). Between its case's turns it is stopped (SIGSTOP: its 1 kHz /joint_states cannot
    load the other cases' turns) and continued for the next (:meth:`resume`)."""

    def __init__(self, domain: int, rate: float, namespace: str = ""):
        import subprocess

        self.proc = subprocess.Popen(
            [sys.executable, str(ROOT / "tests" / "fakes" / "pal_gripper_node.py"), "--domain-id", str(domain),
             "--namespace", namespace, "--rate", str(rate), "--velocity-limit", "1000", "--instant"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.paused_at: float | None = None
        if self.proc.stdout.readline().strip() != "ready":
            self.stop()
            raise RuntimeError("simulated PAL gripper did not start")

    def pause(self) -> None:
        """Stop the process (nothing of it runs until :meth:`resume`)."""
        if self.paused_at is None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGSTOP)
            self.paused_at = time.monotonic()

    def resume(self) -> None:
        """Continue the process, and give it time to settle: its control loop catches up the cycles it missed back
        to back (publishing a state each) before it keeps its rate again, and the driver must have a state newer
        than the pause (older than its read_timeout, 0.5 s, its read is a fault)."""
        if self.paused_at is None:
            return
        paused, self.paused_at = time.monotonic() - self.paused_at, None
        os.kill(self.proc.pid, signal.SIGCONT)
        time.sleep(RESUME_SETTLE_S + RESUME_SETTLE_SHARE * paused)

    def stop(self) -> None:
        try:
            self.resume()
            self.proc.stdin.close()
            self.proc.wait(timeout=5)
        except Exception:
            self.proc.kill()


#: every driver's parameters here: the fastest max_speed the drivers accept (MAX_PLAUSIBLE_SPEED, 2 m/s: a faster one
#: is refused as mm/s typed in the m/s field) and max_opening inside each driver's default calibrated range
#: (Dynamixel: 0-75 mm, refused beyond it); commands stay within 30-60 mm. The profile speed the drivers set from
#: max_speed would still make a 30 mm step ~15 ms of motion: the emulators reach each goal at once (``instant``, see
#: :func:`transport_specs`), so that a round trip measures the transport
FAST = {"max_speed": MAX_PLAUSIBLE_SPEED, "max_opening": 0.07}


def percentile(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * (len(xs) - 1) + 0.5))]


def make(cls, params):
    ctx = Context(clock_kind="wall")
    comp = cls(params, node_id=cls.name, ctx=ctx)
    slot = _Slot()
    return comp, slot, Inputs({"opening_command": slot})


def round_trips(comp, n, a=0.03, b=0.06, tol=5e-4, timeout=0.5):
    """``n`` round trips between openings ``a`` and ``b``: each a write, then reads until one is within ``tol``; a
    driver whose set-point goes out over several writes (canopen-gripper's handshake: ``setpoint_handshake``) writes
    again after each read, as its steps do (its handshake with the previous set-point is finished first, untimed)."""
    out = []
    failures = 0
    again = getattr(comp, "setpoint_handshake", False)
    for k in range(n):
        target = a if k % 2 == 0 else b
        if again:
            settle(comp, b if k % 2 == 0 else a, timeout)
        t0 = time.perf_counter()
        comp._hw_write(target)
        while True:
            r = comp._hw_read()
            now = time.perf_counter()
            if r is not None and abs(r.opening - target) < tol:
                out.append(now - t0)
                break
            if now - t0 > timeout:
                failures += 1
                break
            if again:
                comp._hw_write(target)
            time.sleep(20e-6)  # let the driver's own threads (rclpy executor, CAN notifier) take the GIL
    return out, failures


def settle(comp, target, timeout):
    """Read and write ``target`` until the driver's set-point handshake is over (canopen-gripper: the acknowledge
    answered by bit 4 low, then low again), so that the next write sends its set-point at once."""
    t_end = time.perf_counter() + timeout
    while not comp.handshake_idle() and time.perf_counter() < t_end:
        comp._hw_read()
        comp._hw_write(target)


def update_rate(comp, slot, inputs, seconds, yield_s=20e-6):
    t_end = time.perf_counter() + seconds
    steps = fresh = 0
    last_stamp = None
    durations = []
    t_start = time.perf_counter()
    while True:
        t0 = time.perf_counter()
        if t0 >= t_end:
            break
        slot.sample = Sample(0.05 + 0.01 * math.sin(t0), t0)
        out = comp.step(t0 - t_start, inputs)
        durations.append(time.perf_counter() - t0)
        steps += 1
        stamp = comp._last_reading.mono if comp._last_reading is not None else None
        if stamp is None or stamp != last_stamp:
            fresh += 1
            last_stamp = stamp
        assert math.isfinite(out["opening"].value)
        if yield_s:
            time.sleep(yield_s)  # yield the GIL to the driver's own threads, as the runtime's sleeps do
    elapsed = time.perf_counter() - t_start
    return {"update_rate_hz": steps / elapsed, "fresh_state_hz": fresh / elapsed,
            "step_ms_p50": percentile(durations, 0.5) * 1e3, "step_ms_p99": percentile(durations, 0.99) * 1e3}


class Case:
    """One driver configured and active against its emulator (started by ``setup``), until :meth:`close`."""

    def __init__(self, name, cls, params, setup=None):
        self.name = name
        self.emu = setup() if setup else None
        self.comp, self.slot, self.inputs = make(cls, params(self.emu) if callable(params) else params)
        try:
            self.comp.configure()
            self.comp.activate()
        except BaseException:
            self.close()
            raise
        self.rts: list[float] = []
        self.failures = 0

    def pause(self):
        """Idle the emulator between this case's turns, where it would load the others' (the PAL process)."""
        if hasattr(self.emu, "pause"):
            self.emu.pause()

    def resume(self):
        """The emulator back for this case's turn (:meth:`pause`)."""
        if hasattr(self.emu, "resume"):
            self.emu.resume()

    def round_trips(self, n):
        """``n`` more round trips (:func:`round_trips`), kept; the emulator running only for them."""
        self.resume()
        try:
            rts, failures = round_trips(self.comp, n)
        finally:
            self.pause()
        self.rts += rts
        self.failures += failures

    def update_rate(self, seconds, yield_s):
        """:func:`update_rate` of this case, the emulator running only for it."""
        self.resume()
        try:
            return update_rate(self.comp, self.slot, self.inputs, seconds, yield_s)
        finally:
            self.pause()

    def close(self):
        self.resume()   # the driver's safe state goes to a running controller
        try:
            self.comp.safe_state()
            self.comp.deactivate()
        finally:
            self.comp.close()
            if self.emu is not None:
                self.emu.stop()


def measure(case, n, seconds, round_trip=True, rounds_done=False):
    """Round trips (unless ``rounds_done``: taken already, side by side) then the update rate of ``case``."""
    if round_trip and not rounds_done:
        case.round_trips(n)
    rts, failures = case.rts, case.failures
    res = {"round_trip_ms_p50": percentile(rts, 0.5) * 1e3 if rts else None,
           "round_trip_ms_p90": percentile(rts, 0.9) * 1e3 if rts else None,
           "round_trip_ms_max": max(rts) * 1e3 if rts else None,
           "round_trip_mean_ms": statistics.fmean(rts) * 1e3 if rts else None,
           "round_trips": len(rts), "round_trip_timeouts": failures}
    res.update(case.update_rate(seconds, 20e-6 if round_trip else 0.0))
    rt = "n/a" if not rts else f"p50 {res['round_trip_ms_p50']:.3f} ms, p90 {res['round_trip_ms_p90']:.3f} ms"
    print(f"{case.name:>22}: round trip {rt}; update {res['update_rate_hz']:.0f} Hz "
          f"(fresh state {res['fresh_state_hz']:.0f} Hz), {failures} timeouts", file=sys.stderr)
    return res


def bench(name, cls, params, n, seconds, setup=None, round_trip=True):
    case = Case(name, cls, params, setup)
    try:
        return measure(case, n, seconds, round_trip)
    finally:
        case.close()


def side_by_side(specs, n, seconds, rounds=ROUNDS):
    """:func:`bench` of each of ``specs`` (key -> (name, cls, params, setup)), their round trips side by side: all
    open at once, ``rounds`` rounds of ``n // rounds`` round trips each, the order reversed every other round, so
    that a change of load on the shared machine hits them alike; then each one's update rate in turn. An emulator
    that would load the others (the PAL process) runs only in its case's turns (:meth:`Case.pause`)."""
    cases = {}
    try:
        for key, (name, cls, params, setup) in specs.items():
            cases[key] = Case(name, cls, params, setup)
            cases[key].pause()
        per = max(1, n // rounds)
        for key in alternating(list(cases), rounds):
            cases[key].round_trips(per)
        return {key: dict(measure(c, n, seconds, rounds_done=True), rounds=rounds) for key, c in cases.items()}
    finally:
        for c in cases.values():
            c.close()


def transport_specs(channel: str, domain: int | None = None) -> dict:
    """The transports' cases for :func:`side_by_side` (key -> (name, driver class, params, emulator setup)): the
    Dynamixel servo on a pty at 57600 and 1000000 baud, the CANopen drive on the virtual bus ``channel``, and the PAL
    gripper over ROS 2 on ``domain`` (None: left out). Every driver gets :data:`FAST`; every emulator reaches each goal
    at once (``instant``: the Dynamixel servo at its next packet, the CANopen drive at its next SYNC, the PAL controller
    commands the trajectory's end point in its next cycle), whatever profile speed the driver set from max_speed."""
    from teletouch.plugins.devices.canopen_gripper import CanopenGripper
    from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper
    from teletouch.plugins.devices.pal_gripper import PalGripper

    specs = {f"dynamixel-{baud}": (f"dynamixel @ {baud}", DynamixelGripper,
                                   lambda emu, baud=baud: dict(FAST, port=emu.port, baudrate=baud),
                                   lambda: DynamixelEmulator(15, position=1024, instant=True).start())
             for baud in (57600, 1000000)}
    specs["canopen-virtual"] = ("canopen (virtual CAN)", CanopenGripper,
                                dict(FAST, interface="virtual", channel=channel, node_id=4),
                                lambda: Cia402Drive(4, channel, position=0, instant=True).start())
    if domain is not None:   # its emulator stopped between its turns (PalProcess.pause)
        specs["pal-ros2-loopback"] = ("pal (ROS 2 loopback)", PalGripper,
                                      dict(FAST, domain_id=domain, namespace=NAMESPACE, time_from_start=0.001,
                                           connect_timeout=10.0),
                                      lambda: PalProcess(domain, 1000.0, NAMESPACE))
    return specs


def ros2_missing() -> str | None:
    """Why the PAL case cannot run here (ROS 2 is the optional extra teletouch[ros2]: the driver and its emulator
    need rclpy and the messages), or None."""
    try:
        import rclpy  # noqa: F401
        from sensor_msgs.msg import JointState  # noqa: F401
        from trajectory_msgs.msg import JointTrajectory  # noqa: F401
    except ImportError as exc:
        return f"ROS 2 is not installed ({exc}): pip install 'teletouch[ros2]'"
    return None


def ros_domain(given: int | None) -> int:
    """The ROS domain to use: ``given`` (--ros-domain), else ROS_DOMAIN_ID (checked: 0..232, a ValueError naming it
    otherwise), else :data:`DOMAIN`."""
    d = domain_id(given, ValueError)
    return DOMAIN if d is None else d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer round trips, shorter rate runs")
    ap.add_argument("--ros-domain", type=number(int, f"a ROS domain id from 0 to {MAX_DOMAIN_ID}", lo=0,
                                                   hi=MAX_DOMAIN_ID), default=None, metavar="N",
                    help="ROS domain of the PAL case (default: ROS_DOMAIN_ID if set, else one of this process's own, "
                         "from its process id)")
    args = ap.parse_args(argv)
    try:
        domain = ros_domain(args.ros_domain)
    except ValueError as exc:   # a bad ROS_DOMAIN_ID
        ap.error(f"{exc}; here: --ros-domain N")
    source = ("--ros-domain" if args.ros_domain is not None else
              "ROS_DOMAIN_ID" if os.environ.get("ROS_DOMAIN_ID", "").strip() else "process id")
    print(f"ROS 2 domain {domain} (from {source}), discovery on this host, controller namespace {NAMESPACE}",
          file=sys.stderr)
    n, seconds = (40, 0.5) if args.quick else (200, 2.0)

    from teletouch.plugins.devices.sim_gripper import SimGripper

    results = {}
    # in-process model: no transport, so no round trip; its step rate is the reference for the drivers' overhead
    results["sim-gripper"] = bench("sim-gripper", SimGripper, dict(FAST, object_width=None, bandwidth=1e6),
                                   n, seconds, round_trip=False)
    # the transports: their round trips side by side, in alternating rounds
    missing = ros2_missing()
    specs = transport_specs(f"bench-{uuid.uuid4().hex[:8]}", None if missing else domain)
    results.update(side_by_side(specs, n, seconds))
    if missing:   # the other transports are measured all the same; the JSON says why this one was not
        print(f"{'pal (ROS 2 loopback)':>22}: skipped: {missing}", file=sys.stderr)
        results["pal-ros2-loopback"] = {"skipped": missing}

    ref = results["dynamixel-1000000"]["round_trip_ms_p50"]
    ratios = {k: (v["round_trip_ms_p50"] / ref if v.get("round_trip_ms_p50") and ref else None)
              for k, v in results.items()}
    out = {"benchmark": "follower_latency", "quick": args.quick, "ros_domain": domain,
           "ros_domain_from": source, "round_trips_per_driver": n,
           "rate_seconds": seconds, "results": results,
           "round_trip_p50_ratio_to_dynamixel_1mbaud": ratios,
           # the transports' round trips alternate in rounds (PAL's emulator stopped outside its turns); the
           # in-process sim-gripper has none
           "rounds": {"interleaved": list(specs), "rounds": ROUNDS, "alone": ["sim-gripper"]},
           "note": "emulators on this machine; absolute ms are context, compare ratios"}
    emit(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
