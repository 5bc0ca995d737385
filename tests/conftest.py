"""Shared fixtures. Real DIGIT data lives in ../shared/data beside the checkout (never copied into the repo)."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("TELETOUCH_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data; a missing folder is an error, not a skip (CI always has it)."""
    if not SHARED_DATA.is_dir():
        raise RuntimeError(f"real DIGIT data not found at {SHARED_DATA}: clone the project beside shared/ "
                           f"or set TELETOUCH_SHARED_DATA")
    return SHARED_DATA


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A site folder first on sys.path for fake installed distributions (tests/fakes/plugin_dists.py); the plugin
    modules (named tt_*) imported from it are forgotten after the test."""
    import teletouch.registry as registry

    root = tmp_path / "site"
    root.mkdir()
    monkeypatch.syspath_prepend(str(root))
    # the CLI's cached registry (teletouch.registry._default) is loaded afresh in this test, with its distributions,
    # and the one from before is back afterwards: a registry cached with this test's plugins (modules forgotten
    # below) or without them (cached by an earlier test) must not depend on the order of the tests
    monkeypatch.setattr(registry, "_default", None)
    yield root
    for mod in [m for m in sys.modules if m.startswith("tt_")]:
        del sys.modules[mod]


@pytest.fixture
def plugin_module(site, monkeypatch):
    """``plugin_module(name, source)``: a plugin module (its name starts with tt_) written to the site folder and
    loaded by the CLI's registry through TELETOUCH_PLUGINS, as a user's own module is."""
    def install(name: str, source: str) -> None:
        assert name.startswith("tt_"), name   # (forgotten after the test: see site)
        (site / f"{name}.py").write_text(source)
        monkeypatch.setenv("TELETOUCH_PLUGINS", name)
    return install


@pytest.fixture(autouse=True)
def _no_plugin_env(monkeypatch):
    """Tests build their own registries; the user's environment must not leak in."""
    monkeypatch.delenv("TELETOUCH_BLOCK", raising=False)
    monkeypatch.delenv("TELETOUCH_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    monkeypatch.delenv("TELETOUCH_BLOCK_PLUGINS", raising=False)
    monkeypatch.delenv("TELETOUCH_PLUGINS", raising=False)
    monkeypatch.delenv("TELETOUCH_SYSFS_ROOT", raising=False)
    monkeypatch.delenv("TELETOUCH_DEV_ROOT", raising=False)


_skipped: list[str] = []


def pytest_configure(config):
    """Python's own Ctrl-C handler for the session, as a terminal gives it: a test run started as a background job
    (``pytest ... &`` in a script, as a CI runner may) begins with SIGINT ignored, which Python and the child processes
    it starts keep, and every test of Ctrl-C (the command line's, the runtime's, an isolated node's) then saw nothing.
    The tests of an ignored SIGINT set it themselves (tests/test_newcomer_ignored_sigint.py)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


_gpu: list[str | None] = []   # the CUDA GPU's name (None: none), once tests/test_depth_gpu.py was looked at


def _cuda_gpu() -> str | None:
    """The name of the CUDA GPU torch sees (None without one); torch is imported only when this is asked."""
    if not _gpu:
        import torch

        _gpu.append(torch.cuda.get_device_name(0) if torch.cuda.is_available() else None)
    return _gpu[0]


def pytest_ignore_collect(collection_path, config):
    """tests/test_depth_gpu.py exists for a machine where torch sees a CUDA GPU; elsewhere (CI) it is not collected,
    rather than collected and skipped (a skip fails CI). Said after the collection, so a GPU run shows it ran them."""
    if collection_path.name == "test_depth_gpu.py" and _cuda_gpu() is None:
        return True
    return None


def pytest_report_collectionfinish(config, start_path, items):
    if not _gpu:   # the collection did not reach tests/test_depth_gpu.py: nothing to say, torch not imported for it
        return []
    return (f"teletouch: CUDA GPU {_gpu[0]}: tests/test_depth_gpu.py runs" if _gpu[0] else
            "teletouch: no CUDA GPU: tests/test_depth_gpu.py is not collected")


def pytest_runtest_logreport(report):
    if report.skipped:
        _skipped.append(report.nodeid)


def pytest_sessionfinish(session, exitstatus):
    """On CI nothing may skip (every extra is installed there): a skip fails the run."""
    if os.environ.get("CI") and _skipped and session.exitstatus == 0:
        print(f"\nCI: {len(_skipped)} test(s) skipped, which CI does not allow: " + ", ".join(_skipped[:10]))
        session.exitstatus = 1


@pytest.fixture
def python_sigint():
    """Python's Ctrl-C handler for the test (a background job runs with SIGINT ignored), restored after."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.fixture
def signal_handlers_restored():
    """SIGINT's and SIGTERM's handlers as they were before the test, no profile function, and no stop kept by the
    process (teletouch.runtime._stop_signals) after it: for tests that inject signals into the command line's or the
    runtime's handlers."""
    from teletouch import runtime

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    sys.setprofile(None)
    for s, h in saved.items():
        signal.signal(s, h)
    runtime._stop_signals = None
