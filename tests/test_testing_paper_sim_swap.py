"""docs/writing-a-plugin.md section 5: the recipe that swaps the page's follower (acme-gripper, which has no
`indentation` output) into examples/paper-sim.yaml runs as written, with the command the page gives; so does its
variant that replaces the image chain by a force sensor of one's own with the `force` port of docs/ports.md."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "writing-a-plugin.md"

#: a force sensor as docs/ports.md's "Force sensors" section has it: `force`, N, >= 0, stamped at its capture
FORCE_SENSOR = '''
from teletouch import Component, Kind, Port, Sample, hookimpl


class ConstantForce(Component):
    name = "acme-force"
    kind = Kind.SENSOR
    default_rate = 60.0
    outputs = {"force": Port("float64", (), "N", "normal force on the finger")}

    def step(self, t, inputs):
        return {"force": Sample(1.5 if t > 0.5 else 0.0, t - 0.01)}


@hookimpl
def teletouch_components():
    return [ConstantForce]
'''


def _section5(lang: str) -> list[str]:
    part = PAGE.read_text().split("\n## 5.", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{lang}\n(.*?)```", part, flags=re.S)


def _run(tmp_path: Path, graph: str, modules: str, *args: str) -> subprocess.CompletedProcess:
    (tmp_path / "acme-sim.yaml").write_text(graph)
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    env.update(PYTHONPATH=str(tmp_path), TELETOUCH_PLUGINS=modules)
    return subprocess.run([sys.executable, "-m", "teletouch", *args, "acme-sim.yaml"], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)


def test_the_follower_swap_recipe_runs_and_its_force_variant_too(tmp_path):
    device, _ = _section5("python")
    override, force_variant = _section5("yaml")
    (tmp_path / "acme_gripper.py").write_text(device)
    (tmp_path / "acme_force.py").write_text(FORCE_SENSOR)
    assert "include: /path/to/teletouch/examples/paper-sim.yaml" in override
    graph = override.replace("/path/to/teletouch", str(REPO))

    r = _run(tmp_path, graph, "acme_gripper", "run", "--duration", "1")
    assert r.returncode == 0, r.stdout + r.stderr
    assert re.search(r"gripper +acme-gripper ", r.stderr) and re.search(r"digit +sim-digit ", r.stderr), r.stderr

    # without the `digit` line: the error the page quotes
    r = _run(tmp_path, "\n".join(line for line in graph.splitlines() if "id: digit" not in line), "acme_gripper",
             "validate")
    assert r.returncode == 1
    assert ("node 'digit': input 'indentation': acme-gripper node 'gripper' has no output 'indentation'"
            in r.stderr), r.stderr

    # the force sensor instead of the image chain: the page's lines in place of the `digit` line
    graph = "\n".join(line for line in graph.splitlines() if "id: digit" not in line) + "\n" + force_variant
    r = _run(tmp_path, graph, "acme_gripper,acme_force", "run", "--duration", "1")
    assert r.returncode == 0, r.stdout + r.stderr
    assert re.search(r"force +acme-force ", r.stderr) and "sim-digit" not in r.stderr, r.stderr
    assert "peak_force=1.50N" in r.stderr, r.stderr   # the controller took the sensor's force
