"""The C stand-in of libdhd (dhd_standin.c) for the omega7 tests: built into a folder laid out as Force Dimension's
SDK (lib/libdhd.so), its test controls (StandIn), and fixtures of the built SDK folder and of the stand-in. A fixture
here is made by a function and bound to a name in the test module (``sdk_dir = sdk_dir_fixture("fdsdk")``)."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path
from typing import Iterator

import pytest

SRC = Path(__file__).parent / "dhd_standin.c"


def build_standin(folder: Path, *defines: str) -> Path:
    """Compile the stand-in into folder/libdhd.so (the SDK's library name); defines: e.g. STANDIN_NO_WATCHDOG."""
    gcc = shutil.which("gcc") or shutil.which("cc")
    assert gcc, "a C compiler (gcc) is needed to build the libdhd stand-in"
    out = folder / "libdhd.so"
    subprocess.run([gcc, "-shared", "-fPIC", "-O2", "-Wall", *(f"-D{d}" for d in defines), "-o", str(out), str(SRC),
                    "-lm"], check=True, capture_output=True, text=True)
    return out


class StandIn:
    """The stand-in's test controls (same library handle as the driver's: dlopen returns one copy)."""

    def __init__(self, path: Path):
        self.lib = ctypes.CDLL(str(path))
        self.lib.standin_set_rest.argtypes = [ctypes.c_double] * 4
        self.lib.standin_set_com_freq.argtypes = [ctypes.c_double]
        self.lib.standin_get_writes.restype = ctypes.c_long
        self.lib.standin_get_watchdog_trips.restype = ctypes.c_long
        self.lib.standin_get_peak.restype = ctypes.c_double
        self.lib.standin_hang.argtypes = [ctypes.c_char_p]
        self.lib.standin_advance_clock.argtypes = [ctypes.c_double]
        self.lib.standin_reset()

    def forces(self) -> tuple[list[float], list[float]]:
        a, c = (ctypes.c_double * 4)(), (ctypes.c_double * 4)()
        self.lib.standin_get_forces(a, c)
        return list(a), list(c)

    def flags(self) -> dict[str, bool]:
        f = (ctypes.c_int * 4)()
        self.lib.standin_get_flags(f)
        return dict(zip(("open", "force_enabled", "brakes", "gravity"), map(bool, f)))

    def limits(self) -> tuple[float, float]:
        lim = (ctypes.c_double * 2)()
        self.lib.standin_get_limits(lim)
        return lim[0], lim[1]

    def __getattr__(self, name):
        return getattr(self.lib, "standin_" + name)


def sdk_dir_fixture(name: str):
    """A module-scoped fixture that gives an SDK folder (a temporary folder named after ``name``) with the stand-in
    built into lib/libdhd.so."""
    @pytest.fixture(scope="module")
    def sdk_dir(tmp_path_factory) -> Path:
        d = tmp_path_factory.mktemp(name)
        (d / "lib").mkdir()
        build_standin(d / "lib")
        return d
    return sdk_dir


def standin_fixture():
    """A fixture that gives the stand-in of the ``sdk_dir`` fixture's SDK (FORCEDIM_SDK unset), its firmware's clock
    in the test's hand: the firmware watchdog (20 ms by default) sees time pass only by standin.advance_clock(dt). A
    step or a query that comes late on a loaded machine trips nothing (forces checked right after a step were found
    cut); the tests of the watchdog advance the clock past its duration (and sleep as long, so that the driver, on the
    real clock, sees the same gap). Its failure switches are cleared again after the test."""
    @pytest.fixture
    def standin(sdk_dir, monkeypatch) -> Iterator[StandIn]:
        monkeypatch.delenv("FORCEDIM_SDK", raising=False)
        s = StandIn(sdk_dir / "lib" / "libdhd.so")
        s.freeze_clock()
        yield s
        s.lib.standin_reset()
    return standin
