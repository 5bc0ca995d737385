"""Force topic latency and rate through ROS 2 on loopback (two processes, two DDS participants).

A child process runs ``mock-sensor -> ros2-publish`` (WrenchStamped, the sample's stamp in header.stamp) at the
camera rate (60 Hz) and at 1 kHz, for reliable and best-effort QoS. This process runs ``ros2-subscribe`` in a
wall-clock graph and measures, per message:

- transport latency: arrival in the subscription callback (Unix time) - header.stamp;
- graph latency: the step of the consumer graph that outputs the sample - its stamp on the local graph clock (adds
  the subscriber's polling period, 1 kHz here);
- achieved rate and losses (``loss_fraction``: of the samples the steady span should have held; ``published`` and
  ``received`` are the raw counts, with the discovery time and the publisher's last second in, so their ratio is no
  loss figure); QoS depth 5 (the default): a slow reader drops old samples rather than queueing latency.

The four cases run side by side: each in ``rounds`` rounds (4, ``--quick`` 2) of its share of the duration, every
round a publisher process and a subscriber graph of its own as above (the first 2 s of each, discovery, left out),
the cases alternating and the order reversed every other round, so that a change of load on the shared machine hits
them alike. A case's figures pool its rounds' messages; ``khz_vs_camera_transport_p50_ratio`` is of the pooled p50s,
and ``khz_vs_camera_transport_p50_ratio_rounds`` gives the same ratio round by round (min, median, max).

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

from bench_common import alternating, emit

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


#: the publisher's first seconds (graph time), left out: the participants' discovery
DISCOVERY_S = 2.0


def _pct(a, q):
    return float(np.percentile(a, q)) * 1e3 if len(a) else None


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def run_round(rate: float, rel: str, duration: float, domain: int, tmp: Path) -> dict:
    """One round of a case: the subscriber graph here and a publisher process at ``rate`` with ``rel`` QoS that runs
    ``duration`` + 3 s: its first DISCOVERY_S (2 s) left out, the rest kept. Returns what was seen: the publisher's
    sample count, the messages received, and the kept (steady-state) arrivals and graph outputs."""
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
    deadline = time.monotonic() + 10.0   # the subscription made (the graph's start-up) before the publisher starts
    while getattr(sub, "_subs", None) is None and th.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    pub = subprocess.Popen([sys.executable, "-m", "teletouch", "run", str(g), "--quiet", "--json", "--duration",
                            str(duration + DISCOVERY_S + 1.0)], env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE)
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
    # steady state only: skip discovery (the first DISCOVERY_S of the publisher's ramp value = its graph time)
    return {"published": next(n["steps"] for n in summary["nodes"] if n["id"] == "force"),
            "received": len(arrivals),
            "arrivals": np.array([x for x in arrivals if x[2] >= DISCOVERY_S]).reshape(-1, 3),
            "outputs": np.array([x for x in outs if x[2] >= DISCOVERY_S]).reshape(-1, 3)}


def case_figures(rate: float, rel: str, rounds: list[dict]) -> dict:
    """A case's figures over its ``rounds`` (:func:`run_round`), pooled: the latencies' percentiles over all the
    rounds' messages, the rate over the rounds' spans added up, the losses against the samples the rounds' spans
    should have held; and each round's transport p50 (``round_transport_p50_ms``)."""
    lat = [r["arrivals"][:, 0] - r["arrivals"][:, 1] for r in rounds]
    glat = [r["outputs"][:, 0] - r["outputs"][:, 1] for r in rounds]
    lat_all = np.concatenate(lat) if lat else np.zeros(0)
    glat_all = np.concatenate(glat) if glat else np.zeros(0)
    spans = [(a[-1, 0] - a[0, 0], len(a) - 1) for a in (r["arrivals"] for r in rounds) if len(a) > 1]
    wall_span, intervals = sum(s for s, _ in spans), sum(n for _, n in spans)
    # the samples each round's steady span (the ramp's values: the publisher's graph time) should have held
    expected = sum((a[-1, 2] - a[0, 2]) * rate + 1 for a in (r["arrivals"] for r in rounds)
                   if len(a) > 1 and a[-1, 2] > a[0, 2])
    got = sum(len(r["arrivals"]) for r in rounds)
    return {
        "rate_hz": rate, "reliability": rel, "rounds": len(rounds),
        "published": sum(r["published"] for r in rounds), "received": sum(r["received"] for r in rounds),
        "achieved_rate_hz": intervals / wall_span if wall_span > 0 else 0.0,
        "loss_fraction": max(0.0, 1.0 - got / expected) if expected else None,
        "transport_latency_ms": {"p50": _pct(lat_all, 50), "p99": _pct(lat_all, 99), "max": _pct(lat_all, 100)},
        "graph_latency_ms": {"p50": _pct(glat_all, 50), "p99": _pct(glat_all, 99), "max": _pct(glat_all, 100)},
        "round_transport_p50_ms": [_pct(x, 50) for x in lat],
    }


def p50_ratio(num: dict, den: dict) -> dict:
    """``num``'s transport p50 over ``den``'s (:func:`case_figures`, the same rounds), and the spread of the same
    ratio round by round (min, median, max over the rounds where both have a p50)."""
    a, b = num["transport_latency_ms"]["p50"], den["transport_latency_ms"]["p50"]
    per = [x / y for x, y in zip(num["round_transport_p50_ms"], den["round_transport_p50_ms"])
           if x is not None and y]
    return {"ratio": a / b if a is not None and b else None, "rounds": len(per),
            "min": min(per) if per else None, "median": float(np.median(per)) if per else None,
            "max": max(per) if per else None}


#: the cases: (rate Hz, reliability)
CASES = [(60.0, "reliable"), (60.0, "best_effort"), (1000.0, "reliable"), (1000.0, "best_effort")]
#: rounds per case (alternating with the other cases'): full runs, --quick
ROUNDS, QUICK_ROUNDS = 4, 2


def run_cases(duration: float, rounds: int, domain: int, tmp: Path) -> list[dict]:
    """Every case in ``rounds`` rounds of ``duration / rounds`` s of steady state each, the cases alternating (the
    order reversed every other round), so that a change of load on the shared machine hits them alike."""
    raw: dict[tuple[float, str], list[dict]] = {c: [] for c in CASES}
    for case in alternating(CASES, rounds):
        raw[case].append(run_round(case[0], case[1], duration / rounds, domain, tmp))
    cases = []
    for (rate, rel), rs in raw.items():
        c = case_figures(rate, rel, rs)
        cases.append(c)
        tl, gl = c["transport_latency_ms"], c["graph_latency_ms"]
        print(f"{rate:6g} Hz {rel:<12} received {c['received']:6d}/{c['published']:<6d} "
              f"rate {c['achieved_rate_hz']:8.1f} Hz  transport p50 {_ms(tl['p50'])} p99 {_ms(tl['p99'])} ms"
              f"  graph p50 {_ms(gl['p50'])} p99 {_ms(gl['p99'])} ms ({len(rs)} rounds)", file=sys.stderr)
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 s per case instead of 8 s")
    args = ap.parse_args()
    duration = 2.0 if args.quick else 8.0
    rounds = QUICK_ROUNDS if args.quick else ROUNDS
    domain = 120 + (os.getpid() * 7 + 5) % 90
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_LOCALHOST_ONLY="1")
    with tempfile.TemporaryDirectory() as tmp:
        cases = run_cases(duration, rounds, domain, Path(tmp))
    cam = next(c for c in cases if c["rate_hz"] == 60.0 and c["reliability"] == "reliable")
    fast = next(c for c in cases if c["rate_hz"] == 1000.0 and c["reliability"] == "reliable")
    ratio = p50_ratio(fast, cam)
    emit({
        "benchmark": "ros2_latency", "quick": args.quick, "duration_s": duration, "rounds": rounds,
        "round_duration_s": duration / rounds, "cpus": os.cpu_count(),
        "cases": cases,
        "camera_rate_transport_p50_ms": cam["transport_latency_ms"]["p50"],
        "camera_rate_graph_p50_ms": cam["graph_latency_ms"]["p50"],
        "khz_achieved_rate_hz": fast["achieved_rate_hz"],
        "khz_vs_camera_transport_p50_ratio": ratio["ratio"],
        "khz_vs_camera_transport_p50_ratio_rounds": ratio,
    })


if __name__ == "__main__":
    main()
