"""The source passes ruff's pycodestyle and pyflakes checks (E, F, W; pyproject.toml [tool.ruff]): unused imports,
undefined names and lines over 120 columns fail the suite, not only a reviewer's eye."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_is_clean():
    dirs = [d for d in ("core", "plugins", "scripts", "benchmarks", "tests", "examples") if (REPO / d).is_dir()]
    res = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", *dirs], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
