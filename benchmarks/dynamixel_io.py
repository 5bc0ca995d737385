"""dynamixel-gripper's wait for status packets: CPU time per transaction and the jitter of a 1 kHz controller thread
beside it, for three ways of waiting, side by side in one run.

    python benchmarks/dynamixel_io.py [--quick] [--seconds S]

The emulated servo (tests/fakes/dynamixel_emulator.py, at 1 Mbaud with the wire time) runs in a process of its own
(as the servo is another device: it takes no GIL from this one), on a pseudo-terminal; the driver opens it as it
opens /dev/ttyUSB0, with dynamixel-sdk's default adapter latency timer (16 ms: a packet timeout of ~34 ms). One
thread runs the driver's state read (``_hw_read``: one SYNC_READ transaction) back to back, while a second thread
runs a 1 kHz loop as the runtime's controller does (sleep to the next period, a little Python work) and records how
late each period starts.

Ways of waiting (the same driver, its port's read swapped):
- ``sdk``: dynamixel-sdk as shipped (``PortHandler``, pyserial timeout 0): rxPacket polls the port in a busy loop.
- ``poll_0.5ms``: the driver before (``PortHandler`` with a pyserial timeout of serial_poll = 0.5 ms per read).
- ``select``: the driver now (``port_handler_class()``: select() until readable, at most until the SDK's packet
  timeout or serial_poll).

Scenarios: ``answers`` (the servo answers every request), ``lost`` (the servo is silent: every transaction waits for
the SDK's whole packet timeout), and ``idle`` (no driver thread: the controller thread's own jitter).

Prints one JSON object as its last line. Absolute numbers depend on the machine (a shared 2-core box here); compare
the ways of waiting within one run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from bench_common import emit, positive_float  # noqa: E402

#: the emulated servo, in its own process: prints its port, then takes "silent 0|1" lines (answering "ok")
CHILD = r"""
import sys
sys.path.insert(0, sys.argv[1])
from fakes.dynamixel_emulator import DynamixelEmulator
emu = DynamixelEmulator(15, position=1024).start()
print(emu.port, flush=True)
for line in sys.stdin:
    words = line.split()
    if words[:1] == ["silent"]:
        emu.silent = words[1] == "1"
    print("ok", flush=True)
emu.stop()
"""

MODES = ("sdk", "poll_0.5ms", "select")
PERIOD = 1e-3


def percentile(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * (len(xs) - 1) + 0.5))] if xs else None


class Servo:
    def __init__(self):
        self.proc = subprocess.Popen([sys.executable, "-c", CHILD, str(ROOT / "tests")], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        self.port = self.proc.stdout.readline().strip()
        if not self.port:
            raise RuntimeError("the emulated servo did not start")

    def silent(self, on: bool) -> None:
        self.proc.stdin.write(f"silent {int(on)}\n")
        self.proc.stdin.flush()
        self.proc.stdout.readline()

    def stop(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=5)


def controller(stop: threading.Event, late: list[float]) -> None:
    """A 1 kHz loop as the runtime's controller runs: sleep to the next period, then a little work."""
    nxt = time.perf_counter() + PERIOD
    while not stop.is_set():
        dt = nxt - time.perf_counter()
        if dt > 0:
            time.sleep(dt)
        now = time.perf_counter()
        late.append(now - nxt)
        sum(i * i for i in range(200))   # the step's own work (~20 us)
        nxt += PERIOD
        if now > nxt:   # fell more than a period behind: start again from now (counted in late)
            nxt = now + PERIOD


def use_mode(drv, mode: str) -> list[int]:
    """Swap the driver's port's read for ``mode``; returns the list that counts its readPort calls."""
    import dynamixel_sdk as sdk

    from teletouch.plugins.devices.dynamixel_gripper import port_handler_class

    port = drv.port
    port.__class__ = port_handler_class() if mode == "select" else sdk.PortHandler
    port.ser.timeout = 0.0005 if mode == "poll_0.5ms" else 0
    read = type(port).readPort.__get__(port)
    calls = [0]

    def counted(length):
        calls[0] += 1
        return read(length)

    port.readPort = counted
    return calls


def run_case(drv, mode: str | None, seconds: float) -> dict:
    stop = threading.Event()
    late: list[float] = []
    ctl = threading.Thread(target=controller, args=(stop, late), daemon=True)
    stats: dict = {}

    def driver():
        calls = use_mode(drv, mode)
        n = ok = 0
        c0, t0 = time.thread_time(), time.perf_counter()
        while not stop.is_set():
            ok += drv._hw_read() is not None
            n += 1
        stats.update(transactions=n, valid=ok, cpu_s=time.thread_time() - c0, wall_s=time.perf_counter() - t0,
                     reads=calls[0])

    drv_thread = threading.Thread(target=driver, daemon=True) if mode else None
    ctl.start()
    if drv_thread:
        drv_thread.start()
    time.sleep(seconds)
    stop.set()
    ctl.join()
    if drv_thread:
        drv_thread.join()
    res = {"controller_late_ms_p50": percentile(late, 0.5) * 1e3,
           "controller_late_ms_p99": percentile(late, 0.99) * 1e3, "controller_late_ms_max": max(late) * 1e3,
           "controller_periods": len(late),
           "controller_late_over_1ms": sum(x > 1e-3 for x in late)}
    if mode:
        n = max(1, stats["transactions"])
        res.update(transactions=stats["transactions"], valid_answers=stats["valid"],
                   cpu_ms_per_transaction=stats["cpu_s"] / n * 1e3, wall_ms_per_transaction=stats["wall_s"] / n * 1e3,
                   driver_cpu_share=stats["cpu_s"] / stats["wall_s"], reads_per_transaction=stats["reads"] / n)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="0.5 s per case")
    ap.add_argument("--seconds", type=positive_float, default=2.0, help="seconds per case (default 2)")
    args = ap.parse_args(argv)
    seconds = 0.5 if args.quick else args.seconds

    from teletouch.component import Context
    from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper

    servo = Servo()
    results: dict = {}
    try:
        drv = DynamixelGripper({"port": servo.port, "baudrate": 1000000, "error_check_period": 1e6},
                               node_id="dxl", ctx=Context(clock_kind="wall"))
        drv.configure()
        try:
            results["idle"] = run_case(drv, None, seconds)
            for scenario in ("answers", "lost"):
                servo.silent(scenario == "lost")
                for mode in MODES:
                    r = run_case(drv, mode, seconds)
                    results[f"{scenario}/{mode}"] = r
                    print(f"{scenario:>8} {mode:>11}: {r['cpu_ms_per_transaction']:.3f} ms CPU / "
                          f"{r['wall_ms_per_transaction']:.3f} ms per transaction, {r['reads_per_transaction']:.0f} "
                          f"reads; controller late p50 {r['controller_late_ms_p50']:.3f} p99 "
                          f"{r['controller_late_ms_p99']:.3f} max {r['controller_late_ms_max']:.3f} ms",
                          file=sys.stderr)
                # the next scenario starts in step: the silent servo's lost answers left the bus out of step
                servo.silent(False)
                drv._hw_read()
        finally:
            drv.close()
    finally:
        servo.stop()
    i = results["idle"]
    print(f"{'idle':>20}: controller late p50 {i['controller_late_ms_p50']:.3f} p99 {i['controller_late_ms_p99']:.3f} "
          f"max {i['controller_late_ms_max']:.3f} ms", file=sys.stderr)
    emit({"benchmark": "dynamixel_io", "seconds_per_case": seconds, "baudrate": 1000000,
          "switch_interval_s": sys.getswitchinterval(), "cases": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
