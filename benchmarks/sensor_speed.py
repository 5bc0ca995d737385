"""Speed of the sensor plugins (issue 3).

1. sim-digit: simulated frames per second of CPU time (target >= 300 QVGA frames/s on one core, so a simulated DIGIT at
   60 Hz costs < 20 % of a core). Each frame has a new pose (indentation ramp and a moving centre, the worst case:
   nothing cached); also a resting indenter (cached render + noise), the generic 2-D renderer, full-resolution shading
   (stride 1) and VGA, side by side in one run: every case is stepped in ``sim_rounds`` rounds of its share of the
   frames, the order of the cases reversed every other round, so that load on the shared machine hits them alike and
   the ``speedup_*`` ratios compare like with like. The component's step() is timed, ground truth included.
2. digit driver: capture overhead per frame against a video source: the driver's capture thread (read + rotation
   to portrait + newest-frame hand-over) and step() against a bare cv2.VideoCapture.read() loop on the same file,
   in alternating rounds (``reps``: one whole pass over the file each; the order reversed every other round).

    python benchmarks/sensor_speed.py [--quick]

Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_common import ROUNDS, alternating, emit, interleaved_clocks


class _SimCase:
    """One sim-digit configuration, stepped ``n`` frames at a time over its own sequence of poses (the same in every
    run): the cases are timed side by side in rounds (:func:`bench_common.interleaved_clocks`)."""

    def __init__(self, params: dict, moving: bool = True, fast: bool = True, stride: int | None = None):
        from teletouch.plugins.sensors.sim_digit import SimDigit
        from teletouch.testing import Harness

        self.h = Harness(SimDigit, params)
        self.h.__enter__()
        self.moving = moving
        self.k = 0
        try:
            self.h.comp.sim.fast = fast
            if stride is not None:
                self.h.comp.sim.stride = stride
            self.h.step(0.0, indentation=0.001, position=self._pose(0)[1])  # warm-up
        except BaseException:
            self.close()
            raise

    @staticmethod
    def _pose(k: int) -> tuple[float, np.ndarray]:
        """Each frame a new pose (indentation ramp and a moving centre: nothing cached)."""
        return 0.0003 + 0.0012 * (k % 97) / 97, np.array([0.002 * np.sin(k / 13), 0.003 * np.cos(k / 17)])

    def __call__(self, n: int) -> None:
        for _ in range(n):
            d, pos = self._pose(self.k) if self.moving else (0.001, self._pose(0)[1])
            out = self.h.step(self.k / 60.0, indentation=d, position=pos)
            self.k += 1
        assert out["image"].dtype == np.uint8

    def close(self) -> None:
        self.h.__exit__(None, None, None)


def _sim_fps(cases: dict[str, tuple[dict, int, dict]], rounds: int = ROUNDS) -> dict[str, tuple[float, float]]:
    """name -> (frames per CPU second of this process, frames per wall second) of each case (params, frames,
    options), all timed side by side in ``rounds`` rounds on the same poses. The machine is shared, so CPU time is
    the measure of cost; wall time is given as context."""
    sims: dict[str, _SimCase] = {}
    try:
        for name, (params, _, kw) in cases.items():
            sims[name] = _SimCase(params, **kw)
        t = interleaved_clocks(sims, {name: count for name, (_, count, _) in cases.items()}, rounds)
    finally:
        for sim in sims.values():
            sim.close()
    return {name: (1.0 / max(v["cpu_s"], 1e-12), 1.0 / max(v["wall_s"], 1e-12)) for name, v in t.items()}


def _raw_read(path: Path) -> float:
    import cv2

    cap = cv2.VideoCapture(str(path))
    t0 = time.perf_counter()
    n = 0
    while True:
        ok, _ = cap.read()
        if not ok:
            break
        n += 1
    dt = (time.perf_counter() - t0) / max(n, 1)
    cap.release()
    return dt


def _driver_read(path: Path) -> tuple[float, float, dict]:
    """Per-frame time in the driver's capture thread (read + rotation + hand-over), per-step time of step()."""
    from teletouch import Context
    from teletouch.plugins.sensors.digit import Digit
    from teletouch.testing import Harness

    with Harness(Digit, {"source": str(path), "source_rate": 1e6, "on_eof": "stop"}) as h:
        t_start = time.monotonic()
        h.comp.ctx = Context(clock_kind="wall", from_monotonic=lambda m: m - t_start, request_stop=h._stop)
        step_time, steps, got = 0.0, 0, 0
        t0 = time.perf_counter()
        while h.stopped is None and time.perf_counter() - t0 < 60:
            s0 = time.perf_counter()
            out = h.comp.step(0.0, h.inputs)
            step_time += time.perf_counter() - s0
            steps += 1
            if out:
                got += 1
            else:
                time.sleep(0.0002)
        g = h.comp.grabber
        return g.read_time / max(g.seq, 1), step_time / max(steps, 1), {"frames": g.seq, "taken": got,
                                                                          "dropped": g.dropped}


def _capture(path: Path, reps: int = 3) -> dict:
    """Bare cv2 reads and the driver on the same file, side by side in ``reps`` rounds (the order reversed every
    other round); medians."""
    raw, drv, step = [], [], []
    info: dict = {}
    for which in alternating(["raw", "driver"], reps):
        if which == "raw":
            raw.append(_raw_read(path))
            continue
        d, s, info = _driver_read(path)
        drv.append(d)
        step.append(s)
    r, d = float(np.median(raw)), float(np.median(drv))
    return dict(info, raw_read_ms=round(r * 1e3, 4), driver_capture_ms=round(d * 1e3, 4),
                capture_overhead_ms=round((d - r) * 1e3, 4), capture_ratio_vs_raw=round(d / r, 3),
                step_us=round(float(np.median(step)) * 1e6, 2), reps=reps)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    args = ap.parse_args(argv)
    n = 150 if args.quick else 600
    import cv2

    res: dict = {"benchmark": "sensor_speed", "quick": args.quick}
    q = {"resolution": "qvga"}
    cases = {
        "qvga_moving": (q, n, {}),
        "qvga_resting": (q, n, {"moving": False}),
        "qvga_noise_drift": (dict(q, noise=2.0, drift=3.0), n, {}),
        "qvga_stride1": (q, n // 2, {"stride": 1}),
        "qvga_generic_2d": (q, n // 3, {"fast": False}),
        "qvga_probe": (dict(q, indenter="probe"), n // 2, {}),
        "vga_moving": ({"resolution": "vga"}, n // 3, {}),
    }
    res["sim_rounds"] = ROUNDS
    for name, (cpu, wall) in _sim_fps(cases).items():
        res[f"sim_{name}_fps"] = round(cpu, 1)
        res[f"sim_{name}_fps_wall"] = round(wall, 1)
    res["sim_qvga_core_fraction_at_60hz"] = round(60.0 / res["sim_qvga_moving_fps"], 3)
    res["speedup_radial_vs_generic"] = round(res["sim_qvga_moving_fps"] / res["sim_qvga_generic_2d_fps"], 2)
    res["speedup_stride2_vs_stride1"] = round(res["sim_qvga_moving_fps"] / res["sim_qvga_stride1_fps"], 2)
    res["target_qvga_fps"] = 300
    res["pass"] = res["sim_qvga_moving_fps"] >= 300
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "digit.avi"
        frames = 200 if args.quick else 600
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 60.0, (320, 240))
        rng = np.random.default_rng(0)
        base = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
        for k in range(frames):
            vw.write(np.roll(base, k, axis=1))
        vw.release()
        res["capture"] = _capture(path, 2 if args.quick else 5)
    emit(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
