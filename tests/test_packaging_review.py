"""Packaging review: the developer and CI scripts (dev, .ci/run), the reproduction scripts' arguments and
docstrings, and the example graphs' comments."""

from __future__ import annotations

import hashlib
import os
import pty
import re
import select
import shlex
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from helpers_scripts import script_fixture

REPO = Path(__file__).resolve().parents[1]

depth_script = script_fixture("make_sim_depth_model")
force_script = script_fixture("make_sim_force_calibration")


# --- the dev script -----------------------------------------------------------------------------------------------

def _fake_dev_venv(venv: Path, torch: str) -> None:
    """A virtual environment that ./dev takes as set up (its stamp matches), whose activate script marks the
    shell it was sourced into (its python does nothing: were the stamp not to match, setup installs nothing)."""
    (venv / "bin").mkdir(parents=True)
    for exe in ("teletouch", "python"):
        (venv / "bin" / exe).write_text("#!/bin/sh\nexit 0\n")
        (venv / "bin" / exe).chmod(0o755)
    digest = hashlib.sha256((REPO / "pyproject.toml").read_bytes()
                            + (REPO / "examples" / "teletouch-plugin-example" / "pyproject.toml").read_bytes())
    (venv / ".teletouch-setup").write_text(f"{digest.hexdigest()[:16]} {torch}\n")
    (venv / "bin" / "activate").write_text("export TT_ACTIVATED=yes\n")


def _interactive(argv: list[str], env: dict[str, str], typed: bytes, timeout: float = 60.0) -> str:
    """Run ``argv`` on a pseudo-terminal (so that bash is interactive and reads its rcfile), type ``typed``, and
    return everything it printed."""
    master, slave = pty.openpty()
    proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, env=env, cwd=REPO,
                            start_new_session=True)
    os.close(slave)
    out = b""
    try:
        os.write(master, typed)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    chunk = os.read(master, 4096)
                except OSError:     # the child closed the terminal
                    break
                if not chunk:
                    break
                out += chunk
            elif proc.poll() is not None:
                break
    finally:
        os.close(master)
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
    return out.decode(errors="replace")


def test_dev_shell_activates_a_venv_whose_path_has_spaces(tmp_path):
    """./dev shell sourced `. $VENV/bin/activate` unquoted in its rcfile: with TELETOUCH_VENV="/a b/venv" bash
    sourced "/a" (no such file) and the shell came up without the environment."""
    venv = tmp_path / "my venvs" / "tele touch"
    _fake_dev_venv(venv, "torch==0")
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "TERM": "dumb", "TELETOUCH_VENV": str(venv),
           "TELETOUCH_TORCH": "torch==0"}
    out = _interactive([str(REPO / "dev"), "shell"], env, b'echo "MARK:${TT_ACTIVATED:-none}:"; exit\n')
    assert "MARK:yes:" in out, out
    assert "No such file" not in out, out


# --- .ci/run's wheel check ----------------------------------------------------------------------------------------

# Stand-ins for the interpreters .ci/run calls, with the behaviour that matters here: `-m venv` makes an environment
# of the interpreter's version (without pip when asked, or when ensurepip is missing), `-m pip` needs pip in the
# environment it runs in, and pip refuses a wheel whose Requires-Python (>=3.11) the target interpreter does not
# meet. Every call is logged.
_PY_STUB = r"""#!/usr/bin/env bash
# $ME: an interpreter stand-in; VERSION and NOPIP come from the files beside it
here=$(cd "$(dirname "$0")/.." && pwd)
version=$(cat "$here/version" 2>/dev/null || echo "$DEFAULT_VERSION")
echo "$ME $here $*" >> "$LOG"
make_env() {   # DIR VERSION NOPIP
  mkdir -p "$1/bin"; echo "$2" > "$1/version"; [ "$3" = 1 ] && touch "$1/nopip"
  sed "s/^ME=.*/ME=wheelenv-python/" "$STUBS/python" > "$1/bin/python"; chmod +x "$1/bin/python"
}
install() {    # TARGET_ENV ARGS...: pip install into TARGET_ENV
  local target=$1; shift
  for a in "$@"; do
    case "$a" in
      *teletouch-*.whl)
        tv=$(cat "$target/version")
        if [ "${tv#3.}" -lt 11 ]; then
          echo "ERROR: Package 'teletouch' requires a different Python: $tv not in '>=3.11'" >&2; exit 1
        fi
        cp "$STUBS/teletouch" "$target/bin/teletouch"; chmod +x "$target/bin/teletouch" ;;
    esac
  done
}
case "$1 $2" in
  "-m venv")
    shift 2
    [ "$version" = 3.10 ] && [ -n "$NO_ENSUREPIP" ] && { echo "ensurepip is not available" >&2; exit 1; }
    nopip=0; for a; do [ "$a" = --without-pip ] && nopip=1; done
    make_env "${@: -1}" "$version" "$nopip" ;;
  "-m pip")
    [ -e "$here/nopip" ] && { echo "$here/bin/python: No module named pip" >&2; exit 1; }
    shift 2; target=$here
    if [ "$1" = --python ]; then target=$(cd "$(dirname "$2")/.." && pwd); shift 2; fi
    case " $* " in
      *" wheel "*)
        while [ $# -gt 0 ]; do
          [ "$1" = -w ] && { mkdir -p "$2"; touch "$2/teletouch-0.1.0-py3-none-any.whl"; }; shift
        done ;;
      *" install "*) install "$target" "$@" ;;
    esac ;;
  "-m pytest") exit 0 ;;
esac
"""
_TELETOUCH_STUB = """#!/usr/bin/env bash
echo "wheelenv-teletouch $*" >> "$LOG"
if [ "$1" = plugins ] && [ -n "$BROKEN_PLUGIN" ]; then   # as the CLI reports a plugin that failed to load
  printf '%s  [FAILED TO LOAD]  teletouch 0.1.0\\n    error: %s\\n\\n' digit "$BROKEN_PLUGIN"
  echo "teletouch: 1 plugin problem(s); exit status 1" >&2; exit 1
fi
[ "$1" = plugins ] && echo "mock  builtin"
exit 0
"""


def _ci_checkout(tmp_path: Path, shared: bool = True) -> tuple[Path, dict[str, str], Path]:
    """A checkout holding what .ci/run reads, with a dev environment of stand-ins (Python 3.11) and a Python 3.10
    as the `python3` first on PATH: (the checkout, the environment to run .ci/run in, the call log)."""
    repo = tmp_path / "repo"
    for rel in [".ci/run", "dev", "pyproject.toml", "examples/teletouch-plugin-example/pyproject.toml",
                "examples/paper-sim.yaml"]:
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, repo / rel)
    if shared:
        (tmp_path / "shared" / "data").mkdir(parents=True)
    stubs = tmp_path / "stubs"
    stubs.mkdir()
    (stubs / "python").write_text(_PY_STUB.replace("# $ME:", "ME=python\n#"))
    (stubs / "teletouch").write_text(_TELETOUCH_STUB)
    venv = repo / ".venv"
    _fake_dev_venv(venv, "torch==0")
    (venv / "version").write_text("3.11\n")
    (venv / "bin" / "python").write_text(_PY_STUB.replace("# $ME:", "ME=dev-python\n#"))
    (venv / "bin" / "python").chmod(0o755)
    fakebin = tmp_path / "bin"
    fakebin.mkdir()
    (fakebin / "python3").write_text(_PY_STUB.replace("# $ME:", "ME=path-python3\n#"))
    (fakebin / "python3").chmod(0o755)
    log = tmp_path / "calls.log"
    env = {"PATH": f"{fakebin}:{os.environ['PATH']}", "HOME": str(tmp_path), "LOG": str(log), "STUBS": str(stubs),
           "DEFAULT_VERSION": "3.10", "TELETOUCH_TORCH": "torch==0", "TMPDIR": str(tmp_path)}
    return repo, env, log


def _run_ci(repo: Path, env: dict[str, str], log: Path) -> tuple[subprocess.CompletedProcess, list[str]]:
    run = subprocess.run(["bash", str(repo / ".ci" / "run")], cwd=repo.parent, env=env, capture_output=True,
                         text=True, timeout=120)
    return run, (log.read_text().splitlines() if log.exists() else [])


@pytest.mark.parametrize("no_ensurepip", [False, True], ids=["python3-is-3.10", "python3-without-ensurepip"])
def test_ci_wheel_check_uses_the_dev_environments_python(tmp_path, no_ensurepip):
    """.ci/run made the wheel's fresh environment with whatever `python3` is first on PATH, which ./dev does not
    use (it prefers python3.11): where python3 is 3.10, pip refused the wheel (Requires-Python >= 3.11) and CI
    failed; where that python3 has no ensurepip, the fallback made the environment --without-pip and then ran pip
    inside it ("No module named pip"). The environment must come from the dev environment's interpreter, and pip
    must reach it without needing its own copy."""
    repo, env, log = _ci_checkout(tmp_path)
    if no_ensurepip:
        env["NO_ENSUREPIP"] = "1"
    run, calls = _run_ci(repo, env, log)
    assert run.returncode == 0, run.stdout + run.stderr + "\n".join(calls)
    assert not [c for c in calls if c.startswith("path-python3")], calls
    made = [c for c in calls if c.startswith("dev-python") and " -m venv " in c]
    assert len(made) == 1, calls
    # the wheel went into that environment, and its teletouch ran plugins, validate and run
    assert [c.split()[1] for c in calls if c.startswith("wheelenv-teletouch")] == ["plugins", "validate", "run"]
    assert any(c.startswith("dev-python") and " -m pytest" in c for c in calls)   # then the test suite


def test_ci_shows_which_plugin_failed_to_load_from_the_wheel(tmp_path):
    """`teletouch plugins` exits 1 when a plugin fails to load; .ci/run chained it with && before its grep for
    FAILED TO LOAD, so CI stopped there without showing plugins.txt (the error) or its own message."""
    repo, env, log = _ci_checkout(tmp_path)
    run, calls = _run_ci(repo, {**env, "BROKEN_PLUGIN": "No module named 'cv2'"}, log)
    assert run.returncode == 1
    out = run.stdout + run.stderr
    assert "digit  [FAILED TO LOAD]" in out and "error: No module named 'cv2'" in out, out
    assert "CI: a built-in plugin failed to load from the wheel" in out
    assert not any(" -m pytest" in c for c in calls)


def test_ci_takes_the_shared_data_where_the_tests_take_it(tmp_path):
    """The README: tests read ../shared/data, or TELETOUCH_SHARED_DATA for another location. .ci/run refused to
    start without ../shared/data even with TELETOUCH_SHARED_DATA set; without either it still refuses, naming
    both."""
    repo, env, log = _ci_checkout(tmp_path, shared=False)
    run, calls = _run_ci(repo, env, log)
    assert run.returncode == 1 and calls == []
    assert "../shared/data is missing" in run.stderr and "TELETOUCH_SHARED_DATA" in run.stderr
    data = tmp_path / "elsewhere" / "data"
    data.mkdir(parents=True)
    run, calls = _run_ci(repo, {**env, "TELETOUCH_SHARED_DATA": str(data)}, log)
    assert run.returncode == 0, run.stdout + run.stderr
    assert any(c.startswith("dev-python") and " -m pytest" in c for c in calls)


# --- the reproduction scripts ---------------------------------------------------------------------------------------

@pytest.fixture()
def force_calls(force_script, monkeypatch):
    """The force script with its calibration command recorded instead of run (it writes an empty file)."""
    calls: list[list[str]] = []

    def fake_call(cmd, cwd=None, env=None):
        calls.append(list(cmd))
        Path(cmd[cmd.index("-o") + 1]).write_text("{}")
        return 0

    monkeypatch.setattr(force_script.subprocess, "call", fake_call)
    return calls


@pytest.mark.parametrize("argv, says", [
    (["--grid", "3x3", "--position-degree", "4"], "--position-degree 4 needs a grid of at least 5x5"),
    (["--grid", "5x1"], "--position-degree 4 needs a grid of at least 5x5"),
    (["--single-point", "--grid", "3x3"], "--single-point presses at the centre only"),
    (["--single-point", "--position-degree", "2"], "--single-point presses at the centre only"),
    (["--quick", "--grid", "5x5"], "--quick sets --grid 3x3 and --position-degree 2"),
    (["--quick", "--position-degree", "4"], "--quick sets --grid 3x3 and --position-degree 2"),
])
def test_force_script_refuses_settings_it_would_ignore_or_cannot_fit(force_script, force_calls, tmp_path, capsys,
                                                                     argv, says):
    """A grid with fewer columns or rows than the position degree + 1 cannot determine the position terms (u^a on
    n distinct columns is a combination of the lower powers for a >= n): the script ran the whole press run (8 min
    for 3x3) for a fit that fails or is not determined. --single-point and --quick silently dropped an explicit
    --grid / --position-degree. All are usage errors now, before any work."""
    with pytest.raises(SystemExit) as e:
        force_script.main([*argv, "-o", str(tmp_path / "x.force.json")])
    assert e.value.code == 2
    assert says in capsys.readouterr().err
    assert force_calls == []


@pytest.mark.parametrize("argv, cycles, degree", [
    ([], 25, "4"),
    (["--quick"], 9, "2"),
    (["--grid", "3x3", "--position-degree", "2"], 9, "2"),
    (["--grid", "1x1", "--position-degree", "0"], 1, "0"),
    (["--grid", "4x6", "--position-degree", "3"], 24, "3"),
])
def test_force_script_runs_consistent_settings(force_script, force_calls, tmp_path, argv, cycles, degree):
    assert force_script.main([*argv, "-o", str(tmp_path / "x.force.json")]) == 0
    (cmd,) = force_calls
    assert f"routine.cycles={cycles}" in cmd and cmd[cmd.index("--position-degree") + 1] == degree


def test_force_script_single_point_runs_the_papers_protocol(force_script, force_calls, tmp_path):
    assert force_script.main(["--single-point", "-o", str(tmp_path / "x.force.json")]) == 0
    (cmd,) = force_calls
    assert "--position-degree" not in cmd and not any(c.startswith("routine.positions") for c in cmd)


def _doc_command(doc: str, start: str) -> list[str]:
    """The shell command in a docstring that begins with ``start`` (continuation lines joined)."""
    text = doc[doc.index(start):].split("\n\n", 1)[0]
    return shlex.split(text.replace("\\\n", " "))


def _options(argv: list[str]) -> dict[str, str | None]:
    """Options of a teletouch command line: name (``--set FIELD`` for each --set) -> value (None for a flag)."""
    out: dict[str, str | None] = {}
    i = 0
    while i < len(argv):
        a = argv[i]
        if a.startswith("-"):
            value = argv[i + 1] if i + 1 < len(argv) and not argv[i + 1].startswith("-") else None
            if a == "--set" and value is not None:
                a, value = f"--set {value.split('=', 1)[0]}", value.split("=", 1)[1]
            out[a] = value
            i += 1 if value is None else 2
        else:
            i += 1
    return out


def _same_settings(doc: dict[str, str | None], ran: dict[str, str | None], output_only: set[str]) -> list[str]:
    """What the docstring's command leaves out of the command the script runs, or gives another value; paths
    (placeholders in the docstring) and abbreviated values (...) are compared by name only."""
    wrong = []
    for name, value in ran.items():
        if name in output_only:
            continue
        if name not in doc:
            wrong.append(f"{name} {value} is missing")
        elif value is not None and "/" not in value and "..." not in (doc[name] or "") and doc[name] != value:
            wrong.append(f"{name}: the docstring says {doc[name]}, the script runs {value}")
    return wrong


def test_depth_script_docstring_shows_the_command_it_runs(depth_script, monkeypatch, tmp_path):
    """The docstring says the script "runs the very command a user runs": it ran it with --holdout 4 (the
    command's default is 2), so the docstring's command, run on the same presses, made another model."""
    import teletouch.cli

    ran: list[list[str]] = []
    monkeypatch.setattr(depth_script, "render_presses", lambda folder, n, seed: None)
    monkeypatch.setattr(teletouch.cli, "main", lambda argv: ran.append(list(argv)) or 0)
    args = depth_script.argparse.Namespace(keep=None, presses=40, seed=0, epochs=40, features="diffxy", hidden=None)
    assert depth_script.make(args, tmp_path / "x.model") == 0
    (argv,) = ran
    assert argv[:2] == ["calibrate", "depth"]
    doc = _doc_command(depth_script.__doc__, "teletouch calibrate depth")
    wrong = _same_settings(_options(doc), _options(argv), output_only={"--quiet"})
    assert wrong == [], wrong


def test_force_script_docstring_shows_the_command_it_runs(force_script, force_calls, tmp_path, capsys):
    """The docstring says the script "runs exactly the user's command": the command it showed had none of the
    press grid, the position degree, the duration or the sensor model id the script adds, so a user running it got
    another calibration (3 presses at the centre, no position terms). And the command the script prints is one a
    shell reads back as the command it ran (the press positions have spaces and brackets)."""
    assert force_script.main(["-o", str(tmp_path / "x.force.json")]) == 0
    (cmd,) = force_calls
    doc = _doc_command(force_script.__doc__, "teletouch calibrate force")
    wrong = _same_settings(_options(doc), _options(cmd[cmd.index("calibrate"):]),
                           output_only={"--samples", "--plot", "-o"})
    assert wrong == [], wrong
    printed = [line for line in capsys.readouterr().err.splitlines() if line.startswith("$ ")]
    assert [shlex.split(line[2:]) for line in printed] == [cmd]


# --- the example graphs' comments -----------------------------------------------------------------------------------

EXAMPLES = sorted((REPO / "examples").glob("*.yaml"))
#: a NODE.FIELD in a comment (not part of a path or a file name such as my-digit.force.json)
_REF = re.compile(r"(?<![\w/.-])([a-z][a-z0-9_-]*)\.([a-z_][a-z0-9_]*)\b(?![/.\w-])")
_FILE_SUFFIXES = {"model", "json", "yaml", "md", "png", "mcap", "csv", "npz", "py"}
#: the parameters that pick which device a hardware node drives (docs/leaders.md, followers.md, sensors.md)
SELECTS = {"omega7": {"sdk_path", "serial", "index"}, "pal-gripper": {"namespace", "controller"},
           "digit": {"serial"}, "dynamixel-gripper": {"port", "dxl_id"}, "canopen-gripper": {"channel", "node_id"},
           "hid-leader": {"device", "vendor_id", "product_id", "path"}}


@pytest.fixture(scope="module")
def registry():
    from teletouch.registry import Registry

    return Registry(autoload=True, blocked=()).load()


def _comment_refs(path: Path) -> list[tuple[int, str, str]]:
    refs = []
    for no, line in enumerate(path.read_text().splitlines(), 1):
        if "#" in line:
            refs += [(no, m.group(1), m.group(2)) for m in _REF.finditer(line[line.index("#"):])
                     if m.group(2) not in _FILE_SUFFIXES]
    return refs


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_example_comments_name_parameters_as_set_takes_them(path, registry):
    """A comment's NODE.FIELD is what `--set NODE.FIELD=...` takes: a node of this graph and a parameter or port of
    its plugin. paper.yaml said `omega7.sdk_path`, and `--set omega7.sdk_path=...` fails (no node 'omega7': the
    Omega.7's node is `leader`)."""
    nodes = {n["id"]: n["plugin"] for n in yaml.safe_load(path.read_text())["nodes"]}
    wrong = []
    for no, node, field in _comment_refs(path):
        if node not in nodes:
            wrong.append(f"{path.name}:{no}: {node}.{field}: no node {node!r} (nodes: {', '.join(nodes)})")
            continue
        d = registry.get(nodes[node]).cls.describe()
        names = {p["name"] for p in d["params"]} | {p["name"] for p in d["ports"]} | {"plugin"}
        if field not in names:
            wrong.append(f"{path.name}:{no}: {node}.{field}: {nodes[node]} has no parameter or port {field!r}")
    assert wrong == []


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_hardware_examples_say_which_parameters_pick_the_devices(path):
    """A graph on real hardware says in its comments, for each device node, the parameter that picks the device
    (which Omega.7 and SDK, which PAL gripper's namespace, which DIGIT): the hardware examples named none for the
    gripper and the DIGIT of paper.yaml, nor for any device of split-control.yaml, split-sensor.yaml and
    calibrate-force.yaml."""
    graph = yaml.safe_load(path.read_text())
    named = {(node, field) for _, node, field in _comment_refs(path)}
    missing = [f"{n['id']} ({n['plugin']}: one of {', '.join(sorted(SELECTS[n['plugin']]))})"
               for n in graph["nodes"] if n["plugin"] in SELECTS
               and not any((n["id"], field) in named for field in SELECTS[n["plugin"]])]
    assert missing == [], f"{path.name}: no comment names how to pick the device of " + "; ".join(missing)
