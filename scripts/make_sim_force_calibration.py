#!/usr/bin/env python
"""Make the packaged force calibration of the simulated DIGIT (plugins/estimators/data/sim-digit-qvga.force.json).

It runs exactly the user's command on the example graph:

    teletouch calibrate force --graph examples/calibrate-force-sim.yaml \
        -o plugins/estimators/data/sim-digit-qvga.force.json --plot docs/force-calibration-sim.png

i.e. sim-omega7 + sim-press-rig + sim-digit + the depth estimator (model sim-digit-qvga) + press-routine, 0.1 mm
steps to 2 mm, once at each point of a 5 x 5 grid over +-2 x +-4 mm (``--grid``), fitted with position terms of degree
4 (``--position-degree``: the curve follows the contact centroid, which evens out the depth estimator's variation
over the sensor). ``--single-point`` runs the paper's protocol instead: 3 cycles at the centre, one curve.
``--depth-source gt`` uses sim-digit's ground-truth max depth instead of the depth estimator (for development before
a depth model exists; the file then records depth_source sensor.gt_max_depth).
``--quick`` runs 0.25 mm steps on a 3 x 3 grid with position degree 1 (a smoke test: it is refused unless ``-o``
points away from the packaged file). The plot goes to docs/force-calibration-sim.png only with the packaged output;
with ``-o DIR/x.force.json`` it goes to DIR/x.force.png (``--plot`` to choose):

    python scripts/make_sim_force_calibration.py --quick -o /tmp/quick.force.json
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from teletouch.argtypes import int_at_least

REPO = Path(__file__).resolve().parents[1]
GRAPH = REPO / "examples" / "calibrate-force-sim.yaml"
OUT = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.force.json"
PLOT = REPO / "docs" / "force-calibration-sim.png"
DEPTH_MODEL = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model"


def gt_graph(text: str) -> str:
    """The example graph with the depth node removed and the routine reading sim-digit's ground truth."""
    text = re.sub(r"\n  - id: depth\n(?:    .*\n)+", "\n", text)
    text = text.replace("max_depth: depth.max_depth", "max_depth: sensor.gt_max_depth")
    text = text.replace("centroid: depth.centroid", "centroid: sensor.gt_position")
    if "depth.max_depth" in text or "plugin: depth\n" in text:
        raise SystemExit("could not rewrite the example graph for --depth-source gt")
    return text


def grid(text: str) -> tuple[int, int]:
    """argparse type: ``COLSxROWS`` (e.g. ``5x5``), each at least 1."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise argparse.ArgumentTypeError(f"expected COLUMNSxROWS with each at least 1, such as 5x5, got {text!r}")
    return int(m.group(1)), int(m.group(2))


#: argparse type: a polynomial degree
degree = int_at_least(0)


def default_plot(output: str) -> str:
    """The plot goes with the calibration: docs/force-calibration-sim.png for the packaged file, else next to the
    output (x.force.json -> x.force.png), so trying the script out never replaces the docs' figure."""
    out = Path(output)
    return str(PLOT) if out.resolve() == OUT.resolve() else str(out.with_suffix(".png"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--depth-source", choices=("depth", "gt"), default="depth")
    ap.add_argument("-o", "--output", default=str(OUT),
                    help="the calibration file (default: the packaged one, replaced; -o /tmp/x.force.json to try "
                    "it out)")
    ap.add_argument("--plot", default=None, help="the fit's plot (default: docs/force-calibration-sim.png with the "
                    "packaged output, else next to the output with .png)")
    ap.add_argument("--quick", action="store_true", help="a smoke test: needs -o away from the packaged file")
    ap.add_argument("--single-point", action="store_true", help="the paper's protocol: 3 cycles at the centre, "
                    "no position terms")
    ap.add_argument("--grid", type=grid, default=(5, 5),
                    help="press points, COLUMNSxROWS (default 5x5), over +-2 mm (x) by +-4 mm (y)")
    ap.add_argument("--position-degree", type=degree, default=4)
    ap.add_argument("--depth-model", default=None, help="depth model file (default: the packaged sim-digit-qvga)")
    args = ap.parse_args(argv)
    if args.plot is None:
        args.plot = default_plot(args.output)
    # the calibration runs in the repository (cwd=REPO): relative paths are the caller's, made absolute here
    args.output, args.plot = str(Path(args.output).resolve()), str(Path(args.plot).resolve())
    if args.quick:
        shipped = [f"{name} {path}" for name, path, packaged in (("-o", args.output, OUT), ("--plot", args.plot, PLOT))
                   if Path(path).resolve() == packaged.resolve()]
        if shipped:
            ap.error(f"--quick makes a smoke-test calibration that must not replace the shipped files "
                     f"({', '.join(shipped)}): give -o (and --plot) elsewhere, e.g. -o /tmp/quick.force.json")
    if args.depth_model and not Path(args.depth_model).is_file():
        ap.error(f"--depth-model {args.depth_model}: no such file")
    if args.depth_model and args.depth_source == "gt":
        ap.error("--depth-model has no effect with --depth-source gt (no depth estimator runs)")
    graph = GRAPH
    tmp = tempfile.TemporaryDirectory()
    if args.depth_source == "gt":
        graph = Path(tmp.name) / GRAPH.name
        graph.write_text(gt_graph(GRAPH.read_text()))
    elif not args.depth_model and not DEPTH_MODEL.is_file():
        print(f"{DEPTH_MODEL} is missing (the depth engineer's packaged model); use --depth-source gt meanwhile",
              file=sys.stderr)
        return 1
    cmd = [sys.executable, "-m", "teletouch", "calibrate", "force", "--graph", str(graph), "-o", args.output,
           "--plot", args.plot, "--samples", str(Path(tmp.name) / "samples.csv"),
           "--sensor-model-id", "sim-digit-qvga"]
    if args.depth_model:
        cmd += ["--set", f"depth.model={Path(args.depth_model).resolve()}"]
    if args.quick:
        cmd += ["--set", "routine.step=0.25mm"]
        args.grid, args.position_degree = (3, 3), 1
    if not args.single_point:
        nx, ny = args.grid
        xs = [-2.0 + 4.0 * i / (nx - 1) if nx > 1 else 0.0 for i in range(nx)]
        ys = [-4.0 + 8.0 * j / (ny - 1) if ny > 1 else 0.0 for j in range(ny)]
        pts = "[" + ", ".join(f"[{x:g}mm, {y:g}mm]" for y in ys for x in xs) + "]"
        cmd += ["--set", f"routine.positions={pts}", "--set", f"routine.cycles={nx * ny}",
                "--position-degree", str(args.position_degree), "--duration", f"{120 + 40 * nx * ny}s"]
    print("$ " + " ".join(cmd), file=sys.stderr)
    import os

    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")  # the graph runs one frame at a time: one torch thread is fastest
    rc = subprocess.call(cmd, cwd=REPO, env=env)
    tmp.cleanup()
    return rc


if __name__ == "__main__":
    sys.exit(main())
