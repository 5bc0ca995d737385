"""omega7 on lab day, against the libdhd stand-in (tests/fakes/dhd_standin.c):

- `teletouch validate` said OK for an ``sdk_path`` that does not exist; only the run failed (with a good message). The
  param is checked when the graph is validated: it must exist, as a folder or a file (what the SDK's loader takes);
  what it holds is still the loader's to say at start-up. Without sdk_path, FORCEDIM_SDK is read at start-up as before.
- `teletouch devices` suggested only ``index`` (the SDK's enumeration order, which can change between boots with two
  devices); where the SDK gives the device's serial number (dhdGetSerialNumber) it suggests ``serial``, with ``index``
  the fallback (an SDK without the call, a device that cannot be opened)."""

from __future__ import annotations

import os

import pytest
from pydantic import ValidationError

import teletouch.cli as cli
from teletouch.plugins.devices import dhd
from teletouch.plugins.devices.omega7 import Omega7, teletouch_discover_devices
from teletouch.testing import Harness, make_registry

from fakes.dhd_standin import sdk_dir_fixture, standin_fixture

sdk_dir = sdk_dir_fixture("fdsdk_lab")
standin = standin_fixture()

GRAPH = """
name: omega-lab
clock: wall
duration: 1
nodes:
  - id: leader
    plugin: omega7
    rate: 1kHz
    params: {max_gripper_force: 5 N}
"""


# ------------------------------------------------------------------------------------------------ sdk_path
def _refused(sdk_path: str) -> str:
    with pytest.raises(ValidationError) as ei:
        Omega7.Params(sdk_path=sdk_path)
    return str(ei.value)


def test_an_sdk_path_that_does_not_exist_is_refused_naming_the_field_and_what_was_expected(tmp_path):
    msg = _refused(str(tmp_path / "sdk-3.71"))
    assert "sdk_path" in msg and f"'{tmp_path / 'sdk-3.71'}' does not exist" in msg, msg
    assert "expected the Force Dimension SDK's folder" in msg and "libdhd library file" in msg, msg
    assert "FORCEDIM_SDK" in msg, msg   # what leaving it out does


def test_a_relative_sdk_path_says_where_it_was_looked_for(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    msg = _refused("sdk-3.17.0")
    assert f"looked at {tmp_path / 'sdk-3.17.0'}: a relative path is taken from the current folder" in msg, msg


def test_an_sdk_path_that_is_neither_folder_nor_file_is_refused():
    assert "is neither a folder nor a file" in _refused(os.devnull)


def test_what_the_driver_takes_is_accepted_and_leaving_it_out_still_reads_forcedim_sdk(sdk_dir, tmp_path,
                                                                                        monkeypatch):
    assert Omega7.Params(sdk_path=str(sdk_dir)).sdk_path == str(sdk_dir)   # an SDK folder
    lib = sdk_dir / "lib" / "libdhd.so"
    assert Omega7.Params(sdk_path=str(lib)).sdk_path == str(lib)   # the library file
    monkeypatch.setenv("HOME", str(sdk_dir.parent))
    Omega7.Params(sdk_path=f"~/{sdk_dir.name}")   # ~ as the loader expands it
    (tmp_path / "empty").mkdir()
    Omega7.Params(sdk_path=str(tmp_path / "empty"))   # a folder: what it holds is for the loader to say at start-up
    # not given: validated as before, whatever FORCEDIM_SDK says (read when the node starts)
    monkeypatch.setenv("FORCEDIM_SDK", str(tmp_path / "nowhere"))
    assert Omega7.Params().sdk_path is None and Omega7.Params(sdk_path="").sdk_path == ""
    monkeypatch.setattr(dhd.ctypes.util, "find_library", lambda name: None)
    h = Harness(Omega7, {})
    with pytest.raises(dhd.SdkNotFoundError, match=rf"FORCEDIM_SDK={tmp_path / 'nowhere'} \(does not exist\)"):
        h.comp.configure()
    h.comp.close()
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir))
    assert Omega7.Params().sdk_path is None


def test_teletouch_validate_refuses_the_missing_sdk_path(tmp_path, capsys, monkeypatch):
    path = tmp_path / "omega.yaml"
    path.write_text(GRAPH)
    reg = make_registry("teletouch.plugins.devices.omega7", mocks=False)
    monkeypatch.setattr(cli, "default_registry", lambda **kw: reg)
    missing = tmp_path / "sdk-3.71"
    code = cli.main(["validate", str(path), "--set", f"leader.sdk_path={missing}"])
    out = capsys.readouterr()
    text = out.out + out.err
    assert code != 0 and "OK" not in out.out, text
    assert "sdk_path" in text and f"'{missing}' does not exist" in text, text


# ------------------------------------------------------------------------------------------------ devices
def test_devices_suggests_the_serial_number_and_it_opens_the_device(sdk_dir, standin, monkeypatch):
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir))
    rows = teletouch_discover_devices()
    assert len(rows) == 1 and rows[0]["id"] == "dhd:0", rows
    details = rows[0]["details"]
    assert details["params"] == {"serial": 12345} and details["serial"] == 12345, rows
    assert "problem" not in details
    flags = standin.flags()
    assert not flags["open"] and not flags["force_enabled"], flags   # opened for the serial number, closed again
    with Harness(Omega7, {"sdk_path": str(sdk_dir), **details["params"]}) as h:   # what it suggests opens it
        h.step(0.0)
        assert standin.flags()["open"]


def test_the_devices_table_uses_serial(sdk_dir, standin, monkeypatch, capsys):
    monkeypatch.setenv("FORCEDIM_SDK", str(sdk_dir))
    reg = make_registry("teletouch.plugins.devices.omega7", mocks=False)
    monkeypatch.setattr(cli, "default_registry", lambda **kw: reg)
    assert cli.main(["devices"]) == 0
    lines = capsys.readouterr().out.splitlines()
    row = next(i for i, line in enumerate(lines) if line.startswith("omega7"))
    assert "serial=12345" in lines[row], lines
    use = lines[row + 1]   # (its layout is the devices table's, for every plugin: only what it selects by here)
    assert use.startswith("    use: ") and "omega7" in use and "serial" in use and "12345" in use, lines
    assert "index" not in use, lines


class _Lib:
    """The stand-in libdhd with calls removed or failing, as another SDK or a busy device gives them."""

    def __init__(self, real, without=(), open_fails=False):
        self._real, self._without, self._open_fails = real, set(without), open_fails
        self.opened = 0

    def __getattr__(self, name):
        if name in self._without:
            raise AttributeError(name)
        if name == "dhdOpenID":
            self.opened += 1
            return (lambda index: -1) if self._open_fails else self._real.dhdOpenID
        if name == "dhdErrorGetLast" and self._open_fails:
            return lambda: 5
        if name == "dhdErrorGetLastStr" and self._open_fails:
            return lambda: b"device busy"
        return getattr(self._real, name)


def _rows_with(sdk_dir, monkeypatch, **lib):
    """The discovery rows and the library wrapper."""
    real = dhd.load(sdk_dir)
    monkeypatch.setattr(real, "lib", _Lib(real.lib, **lib))
    monkeypatch.setattr(dhd, "load", lambda sdk_path=None: real)
    return teletouch_discover_devices(), real.lib


def test_without_dhdGetSerialNumber_the_index_is_suggested(sdk_dir, standin, monkeypatch):
    rows, lib = _rows_with(sdk_dir, monkeypatch, without={"dhdGetSerialNumber"})
    details = rows[0]["details"]
    assert details["params"] == {"index": 0} and details["serial"] is None and "problem" not in details, rows
    assert lib.opened == 0   # the device was not opened for nothing


def test_a_device_that_cannot_be_opened_falls_back_to_the_index_and_says_why(sdk_dir, standin, monkeypatch):
    rows, lib = _rows_with(sdk_dir, monkeypatch, open_fails=True)
    assert lib.opened == 1
    details = rows[0]["details"]
    assert details["params"] == {"index": 0} and details["serial"] is None, rows
    problem = details["problem"]
    assert "serial number could not be read" in problem and "dhdOpenID(0) failed: device busy" in problem, problem
    assert "select it by index" in problem and "can change between boots" in problem, problem
