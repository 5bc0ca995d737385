#!/usr/bin/env python
"""Make the packaged force calibration of the simulated DIGIT (plugins/estimators/data/sim-digit-qvga.force.json).

It runs exactly the user's command on the example graph:

    teletouch calibrate force --graph examples/calibrate-force-sim.yaml \
        -o plugins/estimators/data/sim-digit-qvga.force.json --plot docs/force-calibration-sim.png

i.e. sim-omega7 + sim-press-rig + sim-digit + the depth estimator (model sim-digit-qvga) + press-routine, 3 cycles of
0.1 mm steps to 2 mm. ``--depth-source gt`` uses sim-digit's ground-truth max depth instead of the depth estimator
(for development before a depth model exists; the file then records depth_source sensor.gt_max_depth).
``--quick`` runs one cycle of 0.25 mm steps (a smoke test; do not ship its output). ``--multi-point`` presses once
at each of 5 points across the sensor (centre and (+-1.5 mm, +-3 mm)) instead of 3 cycles at the centre (the
paper's protocol): the fit then averages the depth estimator's position dependence.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GRAPH = REPO / "examples" / "calibrate-force-sim.yaml"
OUT = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.force.json"
PLOT = REPO / "docs" / "force-calibration-sim.png"
DEPTH_MODEL = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model"


def gt_graph(text: str) -> str:
    """The example graph with the depth node removed and the routine reading sim-digit's ground truth."""
    text = re.sub(r"\n  - id: depth\n(?:    .*\n)+", "\n", text)
    text = text.replace("max_depth: depth.max_depth", "max_depth: sensor.gt_max_depth")
    if "depth.max_depth" in text or "plugin: depth\n" in text:
        raise SystemExit("could not rewrite the example graph for --depth-source gt")
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--depth-source", choices=("depth", "gt"), default="depth")
    ap.add_argument("-o", "--output", default=str(OUT))
    ap.add_argument("--plot", default=str(PLOT))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--multi-point", action="store_true")
    ap.add_argument("--depth-model", default=None, help="depth model file (default: the packaged sim-digit-qvga)")
    args = ap.parse_args()
    graph = GRAPH
    tmp = tempfile.TemporaryDirectory()
    if args.depth_source == "gt":
        graph = Path(tmp.name) / GRAPH.name
        graph.write_text(gt_graph(GRAPH.read_text()))
    elif not DEPTH_MODEL.is_file():
        print(f"{DEPTH_MODEL} is missing (the depth engineer's packaged model); use --depth-source gt meanwhile",
              file=sys.stderr)
        return 1
    cmd = [sys.executable, "-m", "teletouch", "calibrate", "force", "--graph", str(graph), "-o", args.output,
           "--plot", args.plot, "--samples", str(Path(tmp.name) / "samples.csv"),
           "--sensor-model-id", "sim-digit-qvga"]
    if args.depth_model:
        cmd += ["--set", f"depth.model={Path(args.depth_model).resolve()}"]
    if args.quick:
        cmd += ["--set", "routine.cycles=1", "--set", "routine.step=0.25mm"]
    if args.multi_point:
        pts = "[[0, 0], [1.5mm, 3mm], [-1.5mm, 3mm], [1.5mm, -3mm], [-1.5mm, -3mm]]"
        cmd += ["--set", f"routine.positions={pts}", "--set", "routine.cycles=5"]
    print("$ " + " ".join(cmd), file=sys.stderr)
    import os

    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")  # the graph runs one frame at a time: one torch thread is fastest
    rc = subprocess.call(cmd, cwd=REPO, env=env)
    tmp.cleanup()
    return rc


if __name__ == "__main__":
    sys.exit(main())
