"""`teletouch estimate`: every input error is the command's own, with one exit code (2) and one prefix: a bad
`--model` as a bad `--background` or image (before: a bad model exited 1 under the generic "teletouch: error:")."""

from __future__ import annotations

from teletouch.cli import main


def test_a_missing_or_foreign_model_exits_2_under_the_commands_prefix(tmp_path, capsys):
    img = tmp_path / "x.png"
    assert main(["estimate", "--model", str(tmp_path / "none.model"), str(img)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("teletouch estimate: error: --model "), err
    assert "none.model" in err and "no such model file" in err
    text = tmp_path / "notes.model"
    text.write_text("not a model\n")
    assert main(["estimate", "--model", str(text), str(img)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("teletouch estimate: error: --model "), err
    assert "notes.model" in err


def test_a_missing_background_exits_2_as_well(tmp_path, capsys):
    assert main(["estimate", "--model", "sim-digit-qvga", "--background", str(tmp_path / "nobg"),
                 str(tmp_path / "x.png")]) == 2
    assert capsys.readouterr().err.startswith("teletouch estimate: error: "), "prefix"


def test_a_missing_force_calibration_exits_2_under_the_commands_prefix(tmp_path, capsys):
    # before: exit 1 under the generic "teletouch: error:" (the ModelFileError was not caught as --model's is)
    assert main(["estimate", "--model", "sim-digit-qvga", "--force-calibration", str(tmp_path / "none.force.json"),
                 str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("teletouch estimate: error: --force-calibration "), err
    assert "none.force.json: no such force calibration file" in err, err
