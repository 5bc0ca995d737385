"""The benchmarks (benchmarks/) and the reproduction scripts (scripts/) loaded as modules for the tests that call
their functions: their files are not in a package, so each is loaded from its path under a name the test gives."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"
SCRIPTS = REPO / "scripts"


def load_file(path: Path, name: str) -> ModuleType:
    """The Python file ``path`` executed as a new module named ``name`` (not entered in sys.modules)."""
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_bench(monkeypatch: pytest.MonkeyPatch, file: str, name: str) -> ModuleType:
    """benchmarks/``file`` loaded as ``name``, with the benchmarks folder first on sys.path for the test (the
    benchmarks import bench_common from there, as when they are run)."""
    monkeypatch.syspath_prepend(str(BENCH))
    return load_file(BENCH / file, name)


def load_follower_bench(monkeypatch: pytest.MonkeyPatch, name: str) -> ModuleType:
    """benchmarks/follower_latency.py loaded as ``name`` (as load_bench); its import sets the ROS 2 discovery
    variables and extends sys.path: both are put back after the test."""
    for var in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY"):
        monkeypatch.setenv(var, os.environ.get(var, ""))
    monkeypatch.syspath_prepend(str(BENCH))
    monkeypatch.setattr(sys, "path", list(sys.path))
    return load_file(BENCH / "follower_latency.py", name)


def script_fixture(script: str):
    """A module-scoped fixture that gives scripts/``script``.py loaded as ``<script>_repro_under_test``."""
    @pytest.fixture(scope="module")
    def script_module() -> ModuleType:
        return load_file(SCRIPTS / f"{script}.py", f"{script}_repro_under_test")
    return script_module
