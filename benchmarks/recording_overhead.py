"""Recording overhead: the same graphs with and without ``--record``, side by side in one run.

Two graphs on the simulated clock (as fast as the machine allows, so any cost shows up in wall time):

- ``camera``: real DIGIT frames (QVGA, from shared/data) at 60 Hz with a force, a depth map and a status: the
  per-frame case (each frame is PNG-compressed by the writer thread);
- ``loop``: a 1 kHz scalar control loop (mock sensor, gain, device): the per-step case.

Each case alternates runs without and with a recorder (``repeats`` times; the median is reported). "graph" time is
the run itself (the tap only enqueues), "total" adds ``Recorder.close()`` (the writer draining its queue and
writing the summary). Also reported: the tap's own cost per call, the writer's encode+write cost per frame (and
the share of one core it needs at 60 Hz), and a real-time (wall clock) 60 Hz camera run: backlog, drops, drain.
Prints one JSON object as the last line. ``--quick``: shorter runs, fewer repeats.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from teletouch import Component, Kind, Port, Sample, hookimpl
from teletouch.recording import Recorder
from teletouch.runtime import Runtime
from teletouch.testing import load_text, make_registry
from bench_common import emit

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TELETOUCH_SHARED_DATA", REPO.parent / "shared" / "data"))


class BenchCamera(Component):
    """Real DIGIT frames, a depth map, a force and a status per frame (what the estimator chain outputs)."""

    name = "bench-camera"
    kind = Kind.SENSOR
    default_rate = 60.0
    outputs = {"image": Port("uint8", (None, None, 3), "", "frame"),
               "depth": Port("float32", (None, None), "m", "depth"),
               "force": Port("float64", (), "N", "force"),
               "status": Port("str", (), "", "status")}
    frames: list[np.ndarray] = []

    def configure(self):
        self.k = 0
        self.depth = np.zeros((320, 240), np.float32)

    def step(self, t, inputs):
        img = self.frames[self.k % len(self.frames)]
        self.k += 1
        return {"image": Sample(img, t - 0.004), "depth": self.depth, "force": 0.01 * (self.k % 100),
                "status": "ok"}


class _Plugin:
    @staticmethod
    @hookimpl
    def teletouch_components():
        return [BenchCamera]


CAMERA = """
clock: sim
nodes:
  - {id: cam, plugin: bench-camera, rate: 60}
"""

LOOP = """
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 1000}
  - {id: gain, plugin: mock-gain, rate: 1000, inputs: {x: src.value}}
  - {id: dev, plugin: mock-device, rate: 1000, inputs: {command: gain.y}}
"""


def _once(text: str, reg, duration: float, record: Path | None) -> tuple[float, float, int]:
    spec = load_text(text, reg)
    rt = Runtime(spec, log=lambda m: None)
    rec = None
    if record is not None:
        rec = Recorder(record, spec, log=lambda m: None)
        rt.add_tap(rec.tap)
    t0 = time.perf_counter()
    res = rt.run(duration)
    t1 = time.perf_counter()
    if rec is not None:
        rec.close()
        assert rec.errors == [] and rec.dropped == 0, (rec.errors, rec.dropped)
    t2 = time.perf_counter()
    assert res.status == "ok", res.message
    steps = sum(n.steps for n in rt.nodes if n.id in ("cam", "src"))
    return t1 - t0, t2 - t0, steps


def case(name: str, text: str, reg, duration: float, repeats: int, tmp: Path) -> dict:
    base_g, rec_g, rec_t = [], [], []
    size = 0
    steps = 0
    for i in range(repeats):
        g, _, steps = _once(text, reg, duration, None)
        base_g.append(g)
        path = tmp / f"{name}{i}.mcap"
        g, tot, _ = _once(text, reg, duration, path)
        rec_g.append(g)
        rec_t.append(tot)
        size = path.stat().st_size
        path.unlink()
    b, g, t = statistics.median(base_g), statistics.median(rec_g), statistics.median(rec_t)
    return {"case": name, "steps": steps, "sim_duration_s": duration, "repeats": repeats,
            "without_s": b, "with_graph_s": g, "with_total_s": t,
            "graph_ratio": g / b, "total_ratio": t / b,
            "overhead_graph_us_per_step": (g - b) / steps * 1e6, "overhead_total_us_per_step": (t - b) / steps * 1e6,
            "file_bytes_per_step": size / steps}


def wall_camera(reg, duration: float, tmp: Path) -> dict:
    """The camera graph in real time (60 Hz, wall clock) with a recorder: does the writer keep up?"""
    spec = load_text(CAMERA.replace("clock: sim", "clock: wall"), reg)
    rt = Runtime(spec, log=lambda m: None)
    path = tmp / "wall.mcap"
    rec = Recorder(path, spec, log=lambda m: None)
    rt.add_tap(rec.tap)
    res = rt.run(duration)
    t0 = time.perf_counter()
    rec.close()
    drain = time.perf_counter() - t0
    cam = next(n for n in res.nodes if n.id == "cam")
    return {"duration_s": duration, "frames": cam.steps, "achieved_rate_hz": cam.achieved_rate,
            "overruns": cam.overruns, "dropped": rec.dropped, "max_backlog_items": rec.max_backlog,
            "close_drain_s": drain, "mb_per_s": path.stat().st_size / duration / 1e6}


def tap_cost(n: int, tmp: Path) -> float:
    rec = Recorder(tmp / "tap.mcap", None, log=lambda m: None, max_queue=0)
    out = {"value": 1.0}
    t0 = time.perf_counter()
    for i in range(n):
        rec.tap("n", i * 1e-3, out)
    dt = time.perf_counter() - t0
    rec.close()
    return dt / n * 1e6


def writer_cost(frames: list[np.ndarray], n: int, tmp: Path) -> dict:
    """Encode+write cost per frame in the writer thread (PNG and JPEG)."""
    out = {}
    for fmt in ("png", "jpeg"):
        rec = Recorder(tmp / f"w-{fmt}.mcap", None, image_format=fmt, log=lambda m: None, max_queue=0)
        t0 = time.perf_counter()
        for i in range(n):
            rec.tap("cam", i / 60, {"image": frames[i % len(frames)]})
        rec.close()
        out[f"{fmt}_ms_per_frame"] = (time.perf_counter() - t0) / n * 1e3
        out[f"{fmt}_bytes_per_frame"] = (tmp / f"w-{fmt}.mcap").stat().st_size / n
    raw = frames[0].nbytes
    out["raw_bytes_per_frame"] = raw
    out["png_compression_ratio"] = raw / out["png_bytes_per_frame"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs, 2 repeats")
    args = ap.parse_args()
    files = sorted((DATA / "digit-presses-qvga").glob("*.png"))
    if not files:
        sys.exit(f"no DIGIT frames in {DATA / 'digit-presses-qvga'} (set TELETOUCH_SHARED_DATA)")
    BenchCamera.frames = [cv2.imread(str(f), cv2.IMREAD_COLOR) for f in files]
    reg = make_registry(_Plugin)
    repeats = 2 if args.quick else 4
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cam = case("camera", CAMERA, reg, 5.0 if args.quick else 20.0, repeats, tmp)
        loop = case("loop", LOOP, reg, 2.0 if args.quick else 5.0, repeats, tmp)
        tap_us = tap_cost(20000 if args.quick else 100000, tmp)
        writer = writer_cost(BenchCamera.frames, 100 if args.quick else 300, tmp)
        wall = wall_camera(reg, 3.0 if args.quick else 10.0, tmp)
    for c in (cam, loop):
        print(f"{c['case']:<7} {c['steps']:6d} steps: without {c['without_s']:.3f} s, with {c['with_graph_s']:.3f} s "
              f"(x{c['graph_ratio']:.2f}), incl. close {c['with_total_s']:.3f} s (x{c['total_ratio']:.2f}); "
              f"{c['overhead_total_us_per_step']:.1f} us/step, {c['file_bytes_per_step']:.0f} B/step",
              file=sys.stderr)
    emit({
        "benchmark": "recording_overhead", "quick": args.quick, "cpus": os.cpu_count(),
        "cases": [cam, loop], "tap_us_per_call": tap_us, "writer": writer, "wall_camera_60hz": wall,
        "png_writer_load_at_60hz": writer["png_ms_per_frame"] * 60 / 1e3,
        "camera_total_ratio": cam["total_ratio"], "camera_overhead_ms_per_frame":
            cam["overhead_total_us_per_step"] / 1e3,
        "loop_graph_ratio": loop["graph_ratio"], "loop_overhead_us_per_step": loop["overhead_total_us_per_step"],
    })


if __name__ == "__main__":
    main()
