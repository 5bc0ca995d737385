"""Tests that do not depend on the order of the tests or on the caller's environment (tests/conftest.py): the CLI's
cached registry (``teletouch.registry._default``) around the ``site`` fixture, and the plugin environment variables
the code reads. The three registry tests run in this order (a file's tests run as written)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import teletouch.registry as registry
from teletouch.registry import default_registry

from fakes.plugin_dists import estimator_source, make_dist

TESTS = Path(__file__).resolve().parent

PLUGIN = estimator_source("order-c")


def test_a_registry_cached_by_an_earlier_test():
    assert "order-c" not in default_registry().components   # cached now, as a CLI test in-process leaves it


def test_a_test_with_its_own_distributions_gets_them_from_the_cached_registry(site):
    """Before, the registry cached by an earlier test was used: 'unknown plugin' for the test's own plugin (seen by
    CI in test_cli_open_items, fixed there alone)."""
    make_dist(site, "acme-order", "1.0", {"order": "tt_order"}, {"tt_order": PLUGIN})
    assert "order-c" in default_registry().components


def test_a_later_test_does_not_get_an_earlier_tests_distributions():
    """Before, the registry cached with the site's plugin stayed (its module forgotten, its folder deleted)."""
    assert "order-c" not in default_registry().components
    assert registry._default is None or "order" not in registry._default.plugins


INNER = '''
import os
from teletouch.registry import Registry

def test_inner():
    for name in ("TELETOUCH_BLOCK", "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD", "TELETOUCH_BLOCK_PLUGINS",
                 "TELETOUCH_PLUGINS"):
        assert name not in os.environ, name
    assert "mock-sensor" in Registry(autoload=True).load().components
'''


def test_the_callers_plugin_environment_does_not_reach_the_tests(tmp_path):
    """A developer's shell (or CI job) with TELETOUCH_BLOCK or TELETOUCH_DISABLE_PLUGIN_AUTOLOAD set changed what
    every test's registry held: the autouse fixture of conftest.py cleared two of the variables the code reads, not
    these. An inner pytest run with tests/conftest.py and the variables set."""
    (tmp_path / "test_inner.py").write_text(INNER)
    env = dict(os.environ, TELETOUCH_BLOCK="mock", TELETOUCH_DISABLE_PLUGIN_AUTOLOAD="1",
               PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "conftest",
                        str(tmp_path / "test_inner.py")], capture_output=True, text=True, env=env, cwd=tmp_path,
                       timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
