"""A real third-party distribution (examples/teletouch-plugin-example) installed into a fresh virtual environment
is discovered through its entry point and runs in a graph."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "teletouch-plugin-example"


def _tree(root: Path) -> dict[str, int]:
    """Every file under ``root`` (byte-compiled caches aside) -> its modification time in ns."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts}


@pytest.fixture(scope="module")
def example_before() -> dict[str, int]:
    """The example's source folder as it was before anything here installed it."""
    return _tree(EXAMPLE)


@pytest.fixture(scope="module")
def venv(tmp_path_factory, example_before):
    root = tmp_path_factory.mktemp("venv") / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True, timeout=120)
    py = root / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    # the fresh environment sees this one's packages (teletouch and its dependencies) without copying them
    (Path(site) / "parent_env.pth").write_text(
        f"import site; site.addsitedir({sysconfig.get_paths()['purelib']!r})\n")
    # pip builds in the folder it installs from: a copy, so that the checkout gets no build/ or *.egg-info and
    # runs at the same time do not share one
    src = tmp_path_factory.mktemp("src") / EXAMPLE.name
    shutil.copytree(EXAMPLE, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps",
                        "--no-build-isolation", "--no-index", "-q", str(src)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return py


def test_installing_the_example_leaves_its_source_folder_as_it_was(venv, example_before):
    # before: pip built in the source folder, leaving build/ and *.egg-info in the checkout (gitignored), where two
    # test runs at once raced on them
    assert _tree(EXAMPLE) == example_before


def test_example_plugin_is_small():
    src = (EXAMPLE / "teletouch_plugin_example" / "__init__.py").read_text().splitlines()
    assert len(src) < 50


def test_discovered_from_its_own_distribution(venv):
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    r = subprocess.run([str(venv), "-m", "teletouch", "plugins", "--json"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    lp = rows["example-lowpass"]
    assert lp["distribution"] == "teletouch-plugin-example" and lp["version"] == "0.1.0"
    assert lp["kind"] == "estimator"
    assert {p["name"]: p["unit"] for p in lp["ports"]} == {"x": "N", "y": "N"}
    assert lp["params"][0]["name"] == "cutoff" and lp["params"][0]["unit"] == "Hz"
    # discovery really comes from the installed distribution's entry point: blocking that distribution removes it
    # (this holds also where a developer has installed the example into the parent environment as the docs show)
    r = subprocess.run([str(venv), "-m", "teletouch", "--block", "teletouch-plugin-example", "plugins", "--json"],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "example-lowpass" not in {row["name"] for row in json.loads(r.stdout)}


def test_runs_in_a_graph(venv):
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    r = subprocess.run([str(venv), "-m", "teletouch", "run", str(EXAMPLE / "graph.yaml"), "--json", "--quiet"],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["status"] == "ok"
    nodes = {n["id"]: n for n in res["nodes"]}
    assert nodes["filter"]["steps"] == 1001
    # and the filter really filters: run a check script inside the venv
    code = (
        "from teletouch.graph import load_graph\nfrom teletouch.runtime import Runtime\n"
        f"rt = Runtime(load_graph({str(EXAMPLE / 'graph.yaml')!r}), log=lambda m: None)\n"
        "ys = []\nrt.add_tap(lambda n, t, o: n == 'filter' and ys.append((t, o['y'].value)))\nrt.run()\n"
        "import math\ny = dict(ys)\n"
        "assert abs(y[0.5] - 2.0 * (1 - math.exp(-0.3 * 2 * math.pi * 2))) < 0.02, y[0.5]\nprint('ok')\n")
    r = subprocess.run([str(venv), "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_the_examples_own_tests_pass_against_the_installed_distribution(venv, tmp_path):
    """docs/writing-a-plugin.md section 4: the tests shipped beside the example run as a newcomer runs them."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    r = subprocess.run([str(venv), "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(EXAMPLE),
                        str(EXAMPLE / "tests")], capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "2 passed" in r.stdout
    where = subprocess.run([str(venv), "-c", "import teletouch_plugin_example as m; print(m.__file__)"],
                           capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120).stdout
    assert str(EXAMPLE) not in where   # the installed copy, not the source folder


def test_the_docs_test_snippet_is_the_examples_test():
    """The page's test is the file the example ships, so what a newcomer copies has been run."""
    doc = (REPO / "docs" / "writing-a-plugin.md").read_text()
    shipped = (EXAMPLE / "tests" / "test_lowpass.py").read_text()
    snippet = doc.split("## 4. Test it", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert snippet.strip() == shipped.strip()


def test_the_docs_component_snippet_is_the_examples_code():
    import ast

    doc = (REPO / "docs" / "writing-a-plugin.md").read_text()
    snippet = doc.split("## 1.", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    module = ast.parse((EXAMPLE / "teletouch_plugin_example" / "__init__.py").read_text())
    module.body = module.body[1:]   # its docstring
    assert ast.dump(ast.parse(snippet)) == ast.dump(module)
