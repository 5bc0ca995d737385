"""A force calibration that is not found is named as a depth model is: where a relative path was looked for (the
current folder, not the graph file's) and how to make one; the same checks (empty, a folder, missing) for both."""

from __future__ import annotations

import pytest

from teletouch import ModelFileError
from teletouch.plugins.estimators.normal_model import resolve_model
from teletouch.plugins.estimators.poly_force import resolve_calibration


def test_a_missing_relative_calibration_shows_where_it_looked_and_how_to_make_one(tmp_path, monkeypatch):
    # before: "force calibration 'cal/x.force.json' not found: not a file and not a packaged calibration ...",
    # without the folder it looked in
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ModelFileError) as exc:
        resolve_calibration("cal/x.force.json")
    msg = str(exc.value)
    assert msg.startswith("cal/x.force.json: no such force calibration file (looked at "
                          f"{tmp_path / 'cal' / 'x.force.json'}: a relative path"), msg
    assert "packaged: sim-digit-qvga" in msg and msg.endswith("make one with `teletouch calibrate force`")


@pytest.mark.parametrize("resolve, noun, command", [(resolve_model, "model", "depth"),
                                                      (resolve_calibration, "force calibration", "force")])
def test_both_name_an_empty_name_a_folder_and_a_missing_file_alike(resolve, noun, command, tmp_path):
    with pytest.raises(ModelFileError, match=rf"^empty: expected a {noun} file \(.* from `teletouch calibrate "
                                             rf"{command}`\) or a packaged {noun}'s name$"):
        resolve(" ")
    with pytest.raises(ModelFileError, match=rf"^{tmp_path}: a folder, expected a {noun} file"):
        resolve(str(tmp_path))
    with pytest.raises(ModelFileError, match=rf"^{tmp_path}/none: no such {noun} file, and no packaged {noun} of "
                                             rf"that name \(packaged: sim-digit-qvga\); make one with `teletouch "
                                             rf"calibrate {command}`$"):
        resolve(str(tmp_path / "none"))
