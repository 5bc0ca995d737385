"""benchmarks/follower_latency.py took the fixed ROS domain 63: two runs at once, or a lab's robot on domain 63, saw
each other. The domain now comes from --ros-domain, else ROS_DOMAIN_ID, else the process's own (from its id); the
JSON names it, discovery stays on this host, and the driver commands a controller under the run's own namespace.

Each case runs the benchmark's main() in a subprocess (importing it sets ROS environment variables) with the
drivers' runs replaced by a stub that records what each was given."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"

STUB = f"""
import json, os, sys
sys.path.insert(0, {str(BENCH)!r})
import follower_latency as f
given = {{}}
def bench(name, cls, params, n, seconds, setup=None, round_trip=True):
    given[name] = params
    return {{"round_trip_ms_p50": 1.0}}
f.bench = bench
def side_by_side(specs, n, seconds, rounds=10):
    for key, (name, cls, params, setup) in specs.items():
        given[name] = params
    return {{key: {{"round_trip_ms_p50": 1.0}} for key in specs}}
f.side_by_side = side_by_side
f.main(sys.argv[1:])
pal = given["pal (ROS 2 loopback)"]
print(json.dumps({{"domain_id": pal["domain_id"], "namespace": pal["namespace"], "pid": os.getpid(),
                  "own": f.DOMAIN, "range": os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"]}}))
"""


def _run(*args: str, env_domain: str | None = None, discovery: str | None = None):
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    if env_domain is not None:
        env["ROS_DOMAIN_ID"] = env_domain
    if discovery is not None:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = discovery
    return subprocess.run([sys.executable, "-c", STUB, *args], capture_output=True, text=True, env=env,
                          timeout=120, cwd=REPO)


def _outputs(r) -> tuple[dict, dict]:
    """(the benchmark's JSON, what the stub saw)."""
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.strip().splitlines()
    return json.loads(lines[-2]), json.loads(lines[-1])


def test_the_domain_comes_from_the_flag_and_is_in_the_json():
    bench, seen = _outputs(_run("--quick", "--ros-domain", "17", env_domain="44", discovery="SUBNET"))
    assert bench["ros_domain"] == 17 and bench["ros_domain_from"] == "--ros-domain"
    assert seen["domain_id"] == 17
    assert seen["namespace"] == f"/bench_{seen['pid']}"         # never a lab robot's /gripper_controller
    assert seen["range"] == "LOCALHOST"                         # the emulator is local, whatever the shell says
    assert "ROS 2 domain 17 (from --ros-domain)" in _run("--ros-domain", "17").stderr


def test_without_the_flag_ros_domain_id_then_a_domain_of_the_process_own():
    bench, seen = _outputs(_run("--quick", env_domain="44"))
    assert (bench["ros_domain"], bench["ros_domain_from"], seen["domain_id"]) == (44, "ROS_DOMAIN_ID", 44)
    bench, seen = _outputs(_run("--quick"))
    assert bench["ros_domain"] == seen["own"] == seen["domain_id"] and bench["ros_domain_from"] == "process id"
    assert seen["own"] != 63 and 120 <= seen["own"] <= 209
    assert seen["own"] == 120 + (seen["pid"] * 7 + 8) % 90       # two runs at once: two processes, two domains


def test_a_bad_domain_is_a_usage_error_naming_it():
    r = _run("--ros-domain", "300")
    assert r.returncode == 2 and "argument --ros-domain: expected a ROS domain id from 0 to 232, got 300" in r.stderr
    r = _run(env_domain="lab")
    assert r.returncode == 2 and "ROS_DOMAIN_ID='lab': expected an integer from 0 to 232" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
