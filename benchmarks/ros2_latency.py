"""Force topic latency and rate through ROS 2 on loopback (two processes, two DDS participants).

A child process runs ``mock-sensor -> ros2-publish`` (WrenchStamped, the sample's stamp in header.stamp) at the
camera rate (60 Hz) and at 1 kHz, for reliable and best-effort QoS. This process runs ``ros2-subscribe`` in a
wall-clock graph and measures, per message:

- transport latency: arrival in the subscription callback (Unix time) - header.stamp;
- graph latency: the step of the consumer graph that outputs the sample - its stamp on the local graph clock (adds
  the subscriber's polling period, 1 kHz here);
- achieved rate and losses (received / published); QoS depth 5 (the default): a slow reader drops old samples
  rather than queueing latency.

Prints one JSON object as the last line. ``--quick``: shorter runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_common import emit

PUB_GRAPH = """
clock: wall
faults: {{max_overruns: 0}}
nodes:
  - {{id: force, plugin: mock-sensor, rate: {rate}, params: {{signal: ramp, amplitude: 1.0}}}}
  - {{id: pub, plugin: ros2-publish, rate: {rate}, params: {{domain_id: {domain}, namespace: /bench,
      reliability: {rel}}}, inputs: {{force: force.value}}}}
"""

SUB_GRAPH = """
clock: wall
faults: {{max_overruns: 0}}
nodes:
  - {{id: sub, plugin: ros2-subscribe, rate: 1000, params: {{domain_id: {domain}, namespace: /bench,
      reliability: {rel}}}}}
"""


def _pct(a, q):
    return float(np.percentile(a, q)) * 1e3 if len(a) else None


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def run_case(rate: float, rel: str, duration: float, domain: int, tmp: Path) -> dict:
    from teletouch.plugins.bridges.ros2 import Ros2Subscribe
    from teletouch.testing import load_text, make_registry
    from teletouch.runtime import Runtime

    reg = make_registry("teletouch.plugins.bridges.ros2")
    spec = load_text(SUB_GRAPH.format(domain=domain, rel=rel), reg)
    rt = Runtime(spec, log=lambda m: None)
    sub: Ros2Subscribe = rt.component("sub")  # type: ignore[assignment]
    arrivals: list[tuple[float, float, float]] = []  # (arrival unix, header stamp unix, value)
    orig = sub._on_force

    def spy(msg):  # transport latency at the callback, then the normal path
        arrivals.append((time.time(), msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                         msg.wrench.force.z))
        orig(msg)

    sub._on_force = spy  # type: ignore[method-assign]
    outs: list[tuple[float, float, float]] = []
    rt.add_tap(lambda n, t, o: outs.append((t, o["force"].stamp, o["force"].value)) if "force" in o else None)
    g = tmp / f"pub-{rate:g}-{rel}.yaml"
    g.write_text(PUB_GRAPH.format(rate=rate, domain=domain, rel=rel))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_LOCALHOST_ONLY="1")
    import threading

    result = {}
    th = threading.Thread(target=lambda: result.setdefault("r", rt.run(None)), daemon=True)
    th.start()
    time.sleep(1.0)
    pub = subprocess.Popen([sys.executable, "-m", "teletouch", "run", str(g), "--quiet", "--json", "--duration",
                            str(duration + 3.0)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        out, err = pub.communicate(timeout=duration + 60)
    except subprocess.TimeoutExpired:
        pub.kill()
        out, err = pub.communicate()
    rt.request_stop("benchmark done")
    th.join(30)
    lines = out.decode(errors="replace").strip().splitlines()
    if pub.returncode != 0 or not lines:
        tail = "\n".join(err.decode(errors="replace").strip().splitlines()[-8:])
        sys.exit(f"the publisher process ({g.name}) failed with exit status {pub.returncode}:\n{tail}")
    summary = json.loads(lines[-1])
    published = next(n["steps"] for n in summary["nodes"] if n["id"] == "force")
    # steady state only: skip discovery (first 2 s of the publisher's ramp value = its graph time)
    a = np.array([x for x in arrivals if x[2] >= 2.0]) if arrivals else np.zeros((0, 3))
    lat = a[:, 0] - a[:, 1] if len(a) else np.zeros(0)
    o = np.array([x for x in outs if x[2] >= 2.0]) if outs else np.zeros((0, 3))
    glat = o[:, 0] - o[:, 1] if len(o) else np.zeros(0)
    span = (a[-1, 2] - a[0, 2]) if len(a) > 1 else 0.0
    expected = span * rate + 1 if span else 0
    return {
        "rate_hz": rate, "reliability": rel,
        "published": published, "received": len(arrivals),
        "achieved_rate_hz": (len(a) - 1) / (a[-1, 0] - a[0, 0]) if len(a) > 1 else 0.0,
        "loss_fraction": max(0.0, 1.0 - len(a) / expected) if expected else None,
        "transport_latency_ms": {"p50": _pct(lat, 50), "p99": _pct(lat, 99), "max": _pct(lat, 100)},
        "graph_latency_ms": {"p50": _pct(glat, 50), "p99": _pct(glat, 99), "max": _pct(glat, 100)},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 s per case instead of 8 s")
    args = ap.parse_args()
    duration = 2.0 if args.quick else 8.0
    domain = 120 + (os.getpid() * 7 + 5) % 90
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_LOCALHOST_ONLY="1")
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        for rate in (60.0, 1000.0):
            for rel in ("reliable", "best_effort"):
                c = run_case(rate, rel, duration, domain, Path(tmp))
                cases.append(c)
                tl, gl = c["transport_latency_ms"], c["graph_latency_ms"]
                print(f"{rate:6g} Hz {rel:<12} received {c['received']:6d}/{c['published']:<6d} "
                      f"rate {c['achieved_rate_hz']:8.1f} Hz  transport p50 {_ms(tl['p50'])} p99 {_ms(tl['p99'])} ms"
                      f"  graph p50 {_ms(gl['p50'])} p99 {_ms(gl['p99'])} ms", file=sys.stderr)
    cam = next(c for c in cases if c["rate_hz"] == 60.0 and c["reliability"] == "reliable")
    fast = next(c for c in cases if c["rate_hz"] == 1000.0 and c["reliability"] == "reliable")
    emit({
        "benchmark": "ros2_latency", "quick": args.quick, "duration_s": duration, "cpus": os.cpu_count(),
        "cases": cases,
        "camera_rate_transport_p50_ms": cam["transport_latency_ms"]["p50"],
        "camera_rate_graph_p50_ms": cam["graph_latency_ms"]["p50"],
        "khz_achieved_rate_hz": fast["achieved_rate_hz"],
        "khz_vs_camera_transport_p50_ratio": (fast["transport_latency_ms"]["p50"] / cam["transport_latency_ms"]["p50"]
                                              if cam["transport_latency_ms"]["p50"]
                                              and fast["transport_latency_ms"]["p50"] is not None else None),
    })


if __name__ == "__main__":
    main()
