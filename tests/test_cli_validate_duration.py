"""`teletouch validate` says what `teletouch run` will refuse: a graph on the simulated clock without a duration (the
validation said OK, the run then exited 1); and the results line keeps an absurd value readable."""

from teletouch.cli import _status_item, main

GRAPH = """\
clock: sim
nodes:
  - {id: src, plugin: mock-sensor, rate: 10}
"""


def test_validate_warns_that_run_needs_a_duration_on_the_sim_clock(tmp_path, capsys):
    g = tmp_path / "g.yaml"
    g.write_text(GRAPH)
    assert main(["validate", str(g)]) == 0
    out, err = capsys.readouterr()
    assert "1 warning" in out
    assert "no duration" in err and "--duration S" in err
    assert main(["run", str(g)]) == 1   # what the warning foretold
    assert "needs a duration" in capsys.readouterr().err


def test_validate_says_nothing_of_a_duration_the_graph_has(tmp_path, capsys):
    g = tmp_path / "g.yaml"
    g.write_text(GRAPH + "duration: 1\n")
    assert main(["validate", str(g)]) == 0
    out, err = capsys.readouterr()
    assert "warning" not in out + err


def test_an_absurd_force_in_the_results_stays_one_short_number():
    assert _status_item("peak_force_n", 1e300) == "peak_force=1e+300N"
    assert _status_item("peak_force_n", 1.2) == "peak_force=1.20N"
    assert _status_item("opening_m", 2e9) == "opening=2e+12mm"
    assert _status_item("contact_time_s", 4.93) == "contact_time=4.93s"
