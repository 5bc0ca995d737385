"""Make the packaged depth model of the simulated DIGIT: plugins/estimators/data/sim-digit-qvga.model.

Renders ball presses (6 mm ball, random positions over the sensor, indentations 0.3-1.2 mm, pixel noise on) with
`sim-digit`'s engine, writes them as PNG files with a labels CSV (the true contact circles) and a no-contact
background frame, then runs the very command a user runs on real presses:

    teletouch calibrate depth --images DIR --ball-diameter 6mm --px-per-mm 17.15 --labels DIR/labels.csv \
        --background DIR/background.png --features diffxy -o plugins/estimators/data/sim-digit-qvga.model

    python scripts/make_sim_depth_model.py [--presses 40] [--seed 0] [--epochs 40] [--keep DIR] [-o FILE]

Without ``-o`` it replaces the packaged model; to try it out: ``--presses 12 --epochs 5 -o /tmp/sim.model``.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from teletouch.argtypes import int_at_least

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "plugins" / "estimators" / "data" / "sim-digit-qvga.model"


def render_presses(folder: Path, n: int, seed: int, noise: float = 2.0) -> None:
    import cv2

    from teletouch.plugins.sensors import gel
    from teletouch.plugins.sensors.sim_digit import DigitSimulator
    from teletouch.plugins.estimators.depth_calibration import Label, write_labels

    sim = DigitSimulator("qvga", noise=noise, seed=seed)
    rows, cols = sim.shape
    m = sim.m_per_px
    ball = gel.Indenter.sphere(0.003)
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    img, _ = sim.render(0.0)
    cv2.imwrite(str(folder / "background.png"), img)
    labels = []
    # positions on a jittered grid so that the presses cover the whole sensor
    g = int(math.ceil(math.sqrt(n * rows / cols)))
    gc_ = int(math.ceil(n / g))
    cells = [(i, j) for i in range(g) for j in range(gc_)]
    rng.shuffle(cells)
    for k in range(n):
        d = float(rng.uniform(0.3e-3, 1.2e-3))
        a_px = gel.contact_radius(d, ball) / m
        i, j = cells[k % len(cells)]
        margin = a_px + 3
        y = (i + rng.uniform(0.1, 0.9)) / g * rows
        x = (j + rng.uniform(0.1, 0.9)) / gc_ * cols
        y = float(np.clip(y, margin, rows - 1 - margin))
        x = float(np.clip(x, margin, cols - 1 - margin))
        pos = ((x - (cols - 1) / 2) * m, (y - (rows - 1) / 2) * m)
        img, surf = sim.render(d, pos, 0.0, t=float(k))
        name = f"press_{k:02d}.png"
        cv2.imwrite(str(folder / name), img)
        labels.append(Label(name, round(x, 2), round(y, 2), round(a_px, 2), f"indentation {d * 1e3:.3f} mm"))
    write_labels(folder / "labels.csv", labels)


def main(argv: list[str] | None = None) -> int:
    from teletouch.plugins.estimators.normal_model import FEATURE_SETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presses", type=int_at_least(1), default=40)
    ap.add_argument("--seed", type=int_at_least(0), default=0)
    ap.add_argument("--epochs", type=int_at_least(1), default=40)
    # diffxy, not the calibration's default ratio+gradxy: sim-digit's optics (Taxim's table) add a colour change that
    # does not scale with the background, so the ratio's premise does not hold here, and the gradient inputs read the
    # paper's probe (not the calibration ball) 83% shallow instead of 53%, which doubled the held-out force error
    # (9.5% instead of 5.3% of the range; docs/depth.md)
    ap.add_argument("--features", default="diffxy", choices=sorted(FEATURE_SETS),
                    help="network inputs (default diffxy, see above)")
    ap.add_argument("--hidden", type=int_at_least(1), nargs="+", default=None,
                    help="hidden layer sizes (default: the calibration's default)")
    ap.add_argument("--keep", default=None, help="write the rendered presses here (default: a temporary folder)")
    ap.add_argument("-o", "--output", default=str(OUT),
                    help="the model file (default: the packaged one, replaced; -o /tmp/x.model to try it out)")
    args = ap.parse_args(argv)
    from teletouch.cli import main as teletouch

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp) / "presses"
        render_presses(folder, args.presses, args.seed)
        rc = teletouch(["calibrate", "depth", "--images", str(folder), "--ball-diameter", "6mm",
                        "--px-per-mm", "17.15", "--labels", str(folder / "labels.csv"),
                        "--background", str(folder / "background.png"), "--holdout", "4",
                        "--epochs", str(args.epochs), "--seed", str(args.seed), "--features", args.features,
                        *(["--hidden", *map(str, args.hidden)] if args.hidden else []),
                        "--quiet", "-o", args.output])
    if rc == 0:
        print(f"wrote {args.output} ({Path(args.output).stat().st_size / 1024:.0f} KiB)", file=sys.stderr)
    return rc


if __name__ == "__main__":
    sys.exit(main())
