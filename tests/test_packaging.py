"""Packaging: every module folder is in the wheel's package list, and every built-in entry point imports."""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _pyproject():
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_every_source_folder_is_a_listed_package():
    cfg = _pyproject()["tool"]["setuptools"]
    listed = set(cfg["packages"])
    roots = {v: k for k, v in cfg["package-dir"].items()}  # "core" -> "teletouch"
    for folder in ["core", "plugins"]:
        for d in [REPO / folder, *[p for p in (REPO / folder).rglob("*") if p.is_dir()]]:
            if d.name == "__pycache__" or not any(d.glob("*")):
                continue
            rel = d.relative_to(REPO / folder).parts
            name = ".".join((roots[folder], *rel))
            assert name in listed, f"{d} holds files but {name} is not in pyproject's packages list"


def test_every_builtin_entry_point_imports_and_provides_components():
    eps = _pyproject()["project"]["entry-points"]["teletouch"]
    for name, target in eps.items():
        mod = importlib.import_module(target)
        assert hasattr(mod, "teletouch_components") or hasattr(mod, "teletouch_add_commands"), name
