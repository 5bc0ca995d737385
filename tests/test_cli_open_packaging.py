"""Packaging metadata: the licence is an SPDX expression (PEP 639), so building the wheel gives no setuptools
deprecation warning, and the build requires a setuptools that understands it."""

from __future__ import annotations

import re
import tomllib
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_license_is_an_spdx_expression_and_applying_the_config_warns_nothing():
    """`license = {text = "MIT"}` made setuptools print a BuildBackendWarning ('project.license as a TOML table is
    deprecated') twice in every `pip wheel .`."""
    from setuptools.config.pyprojecttoml import apply_configuration
    from setuptools.dist import Distribution

    assert _pyproject()["project"]["license"] == "MIT"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dist = apply_configuration(Distribution(), str(REPO / "pyproject.toml"))
    assert [str(w.message).splitlines()[0] for w in caught if "license" in str(w.message).lower()] == []
    assert dist.metadata.license_expression == "MIT"


def test_build_requires_a_setuptools_that_reads_an_spdx_license():
    """PEP 639 license expressions need setuptools >= 77; the floor was 68, which refuses `license = "MIT"`."""
    requires = _pyproject()["build-system"]["requires"]
    floors = [re.fullmatch(r"setuptools\s*>=\s*(\d+)(?:\.\d+)*", r.strip()) for r in requires]
    found = [int(m.group(1)) for m in floors if m]
    assert found and found[0] >= 77, requires
    files = _pyproject()["project"].get("license-files", [])
    for pattern in files:   # every declared licence file exists (setuptools fails the build otherwise)
        assert list(REPO.glob(pattern)), pattern
