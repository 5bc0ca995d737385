"""README.md and docs/*.md kept true to the code, for the facts that drift most easily.

- every concrete `teletouch ...` command line on the pages parses with the CLI's own parser (plugin commands
  included), and a graph it names under examples/ loads and validates with its `--set`s and `--clock`;
- every option written in a command synopsis (`teletouch run GRAPH [--clock sim|wall] ...`) is an option of that
  command, and the choices written for it are among the parser's;
- the README's command table lists every command of the CLI, and no other;
- every option written for `python benchmarks/NAME.py` / `scripts/NAME.py` is declared by that script;
- the parameter tables (`| param | default | ... |`), the follower limits table, the intents table and the inline
  "`field` (default X)" figures equal the components' `Params` defaults;
- the port tables (`| port | dir | ... |`) name ports that exist with that direction, optionality, dtype, shape
  and unit;
- every relative link (and its #anchor) resolves, and every examples/ path named on the pages exists.

tests/test_newcomer_docs.py runs docs/writing-a-plugin.md's snippets and tests/test_examples.py validates every
example graph; this file does not repeat them.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from teletouch.cli import add_plugin_commands, build_parser
from teletouch.graph import load_graph
from teletouch.registry import Registry
from teletouch.units import parse_quantity

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md"] + sorted((REPO / "docs").glob("*.md"))
FILE_ARG = re.compile(r"[/.](yaml|png|jpg|mcap|json|model|csv)$|/")


def _rel(page: Path) -> str:
    return f"docs/{page.name}" if page.parent.name == "docs" else page.name


def _prose(text: str) -> str:
    """The page without its fenced code blocks."""
    return re.sub(r"(?ms)^```.*?^```", "", text)


def _code_lines(text: str) -> list[str]:
    """Lines of fenced blocks and of 4-space indented blocks, backslash continuations joined, comments cut."""
    blocks = re.findall(r"(?ms)^```[a-z]*\n(.*?)^```", text)
    blocks += [m for m in re.findall(r"(?m)^(?: {4,}\S.*\n?)+", _prose(text))]
    lines = []
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            line = re.sub(r"\s#.*$", "", line).strip().rstrip("&").strip()
            if line and not line.startswith("#"):
                lines.append(line)
    return lines


def _commands(page: Path) -> list[tuple[str, str]]:
    """(kind, command) for every `teletouch ...` on the page: kind 'line' (a concrete command to parse) or
    'synopsis' (placeholders: only its options are checked)."""
    text = page.read_text()
    out = [("line", c) for c in _code_lines(text) if c.startswith("teletouch ")]
    for span in re.findall(r"`(teletouch [^`]+)`", _prose(text)):
        span = " ".join(span.split())
        words = span.split()[1:]
        concrete = not re.search(r"[\[|]|\.\.\.", span) and any(FILE_ARG.search(w) for w in words)
        out.append(("line" if concrete else "synopsis", span))
    return out


@pytest.fixture(scope="module")
def registry():
    reg = Registry(autoload=True, blocked=()).load()
    assert not reg.errors(), [(p.name, p.error) for p in reg.errors()]
    return reg


@pytest.fixture(scope="module")
def parser(registry):
    """The parser `teletouch` builds, with the plugins' commands (calibrate depth/force, estimate, experiment,
    plot)."""
    p = build_parser()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    cal = sub.choices["calibrate"].get_default("_calibrate")
    assert add_plugin_commands(registry, sub, cal) == []
    return p


def _subcommands(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> tuple[argparse.Namespace | None, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            return parser.parse_args(argv), ""
        except SystemExit:
            return None, err.getvalue().strip().splitlines()[-1]


def test_every_documented_command_line_parses_and_its_example_graph_validates(parser, registry):
    problems, parsed = [], 0
    for page in PAGES:
        for kind, cmd in _commands(page):
            if kind != "line":
                continue
            args, error = _parse(parser, shlex.split(cmd)[1:])
            parsed += 1
            if args is None:
                problems.append(f"{_rel(page)}: `{cmd}`: {error}")
                continue
            graph = getattr(args, "graph", None)
            if not graph or not graph.startswith("examples/"):
                continue
            # a --set naming the reader's own file (depth.model=my.model) is a placeholder: not checked here
            sets = [s for s in getattr(args, "sets", None) or [] if not re.search(r"\.(model|json|csv|png)$", s)]
            try:
                load_graph(REPO / graph, registry=registry, sets=sets, clock=getattr(args, "clock", None))
            except Exception as exc:   # noqa: BLE001 - every failure is reported with the command
                if graph == "examples/teletouch-plugin-example/graph.yaml" and "unknown plugin 'example-lowpass'" \
                        in str(exc):
                    continue   # as docs/writing-a-plugin.md says: the example plugin is not installed here
                problems.append(f"{_rel(page)}: `{cmd}`: {type(exc).__name__}: {exc}")
    assert not problems, "\n".join(problems)
    assert parsed >= 20, parsed   # the pages hold many such lines: the extraction must still find them


def _synopsis_problems(parser: argparse.ArgumentParser, cmd: str) -> list[str]:
    tokens = cmd.replace("\\|", "|").replace("[", " ").replace("]", " ").split()[1:]
    root_opts = parser._option_string_actions
    while tokens and tokens[0] in root_opts:   # teletouch --block NAME COMMAND
        action = root_opts[tokens.pop(0)]
        if action.nargs != 0 and tokens:
            tokens.pop(0)
    targets = [parser]
    while tokens and _subcommands(targets[0]) and not tokens[0].startswith("-") and not tokens[0].isupper():
        names = tokens.pop(0).split("|")
        subs = _subcommands(targets[0])
        missing = [n for n in names if n not in subs]
        if missing:
            return [f"no command {missing} (commands: {sorted(subs)})"]
        targets = [subs[n] for n in names]
    problems = []
    for target in targets:
        opts = target._option_string_actions
        for i, tok in enumerate(tokens):
            if not re.match(r"^--?[a-z]", tok):
                continue
            name = tok.split("=", 1)[0].rstrip(",;)")
            if name not in opts:
                problems.append(f"{target.prog}: no option {name}")
                continue
            choices = opts[name].choices
            if choices is not None and i + 1 < len(tokens) and "|" in tokens[i + 1]:
                extra = set(tokens[i + 1].split("|")) - {str(c) for c in choices}
                if extra:
                    problems.append(f"{target.prog} {name}: {sorted(extra)} not among {sorted(choices)}")
    return problems


def test_every_option_of_a_documented_synopsis_exists_with_its_choices(parser):
    problems, checked = [], 0
    for page in PAGES:
        for _, cmd in _commands(page):
            checked += 1
            problems += [f"{_rel(page)}: `{cmd}`: {p}" for p in _synopsis_problems(parser, cmd)]
    assert not problems, "\n".join(problems)
    assert checked >= 60, checked


def test_synopsis_check_finds_a_wrong_option_and_a_wrong_choice(parser):
    """The check above can fail: an option a command lacks, a choice it does not offer, a command that is not."""
    assert _synopsis_problems(parser, "teletouch run GRAPH [--clock sim|wall] [--record-images png|jpeg]") == []
    assert _synopsis_problems(parser, "teletouch run GRAPH [--speed N]") == ["teletouch run: no option --speed"]
    assert "['gif']" in _synopsis_problems(parser, "teletouch run GRAPH [--record-images png\\|gif]")[0]
    assert "no command" in _synopsis_problems(parser, "teletouch experiment contact|grasp [--out DIR]")[0]


def test_the_readme_command_table_lists_every_command(parser):
    text = (REPO / "README.md").read_text()
    (rows,) = [rows for heading, header, rows in _tables(text) if heading == "## Command line"]
    documented = set()
    for row in rows:
        for cmd in re.findall(r"`teletouch ([^`]+)`", row[0]):
            words = [w for w in cmd.split() if not w.startswith("-") and w != "NAME[,NAME]"]
            documented.add(words[0])
    documented.discard("COMMAND")
    assert documented == set(_subcommands(parser)), documented ^ set(_subcommands(parser))


def test_documented_benchmark_and_script_options_are_declared():
    problems, checked = [], 0
    for page in PAGES:
        text = page.read_text()
        for span in re.findall(r"`([^`]*\b(?:benchmarks|scripts)/[a-z_]+\.py[^`]*)`", text):
            path, rest = re.search(r"\b((?:benchmarks|scripts)/[a-z_]+\.py)(.*)", span, flags=re.S).groups()
            source = (REPO / path).read_text() if (REPO / path).is_file() else None
            if source is None:
                problems.append(f"{_rel(page)}: `{span}`: no file {path}")
                continue
            for opt in re.findall(r"(?<![\w-])(--?[a-z][a-z-]*)", rest):
                checked += 1
                if f'"{opt}"' not in source:
                    problems.append(f"{_rel(page)}: `{span}`: {path} declares no option {opt}")
    assert not problems, "\n".join(problems)
    assert checked >= 10, checked


# ---- parameter defaults -------------------------------------------------------------------------------------------

#: table cells that describe a default resolved at configure: the Params default must be None
DESCRIBED = {"the node's id", "shipped"}


def _resolved_defaults() -> dict[tuple[str, str], float]:
    """Defaults the docs give as the value a None resolves to (code constants, not copies)."""
    from teletouch.plugins.sensors.sim_digit import DEFAULT_RADIUS

    return {("sim-digit", "indenter_radius"): DEFAULT_RADIUS["sphere"]}


def _default(cls, field: str):
    return cls.Params.model_fields[field].get_default(call_default_factory=True)


def _tolerance(text: str) -> float:
    """Half a unit of the last written digit, in SI: '0.41 MPa' -> 5000 Pa."""
    m = re.match(r"\s*[-+]?(\d*)(?:\.(\d+))?\s*(.*)$", text)
    decimals = len(m.group(2) or "")
    unit = m.group(3).strip()
    try:
        scale = parse_quantity(f"1 {unit}") if unit else 1.0
    except ValueError:
        scale = 1.0
    return 0.5 * 10.0 ** -decimals * abs(scale)


def _documented_value(text: str):
    """('none' | 'bool' | 'number' | 'text', value) of a documented default."""
    text = re.sub(r"\s*\(.*\)$", "", text.strip().strip("`")).strip()
    if text in ("None", "null"):
        return "none", None
    if text in ("true", "false"):
        return "bool", text == "true"
    try:
        return "number", parse_quantity(text)
    except (ValueError, TypeError):
        pass
    m = re.match(r"^([-+]?\d+(?:\.\d+)?)\s+[a-z]+$", text)   # "24 levels": a count in a unit the parser lacks
    if m:
        return "number", float(m.group(1))
    return "text", text


def _mismatch(plugin: str, field: str, default, text: str) -> str | None:
    if text in DESCRIBED:
        return None if default is None else f"{plugin}.{field}: documented '{text}' (None), code {default!r}"
    kind, value = _documented_value(text)
    if kind == "number" and default is None:
        resolved = _resolved_defaults().get((plugin, field))
        if resolved is None:
            return f"{plugin}.{field}: documented {text!r}, code None"
        default = resolved
    ok = {
        "none": lambda: default is None,
        "bool": lambda: default is value,
        "number": lambda: isinstance(default, (int, float)) and not isinstance(default, bool)
        and abs(default - value) <= _tolerance(re.sub(r"\s*\(.*\)$", "", text)),
        "text": lambda: str(default) == value,
    }[kind]()
    return None if ok else f"{plugin}.{field}: documented {text!r}, code {default!r}"


def _tables(text: str):
    """(heading, header cells, rows of cells) of each markdown table, with the nearest heading above it."""
    heading, lines = "", text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("#"):
            heading = lines[i]
        if lines[i].startswith("|") and i + 1 < len(lines) and re.match(r"^\|[-| :]+\|$", lines[i + 1]):
            cells = lambda line: [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]   # noqa: E731
            header = [c.lower() for c in cells(lines[i])]
            rows, i = [], i + 2
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(cells(lines[i]))
                i += 1
            yield heading, header, rows
            continue
        i += 1


def _plugins_named(heading: str, registry) -> list[str]:
    return [n for n in re.findall(r"`([a-z0-9-]+)`", heading) if n in registry.components]


def _plugin_tables(first: str, column: str, registry):
    """(page, header, rows, plugins) of every table whose header starts with ``first`` and has ``column``, with the
    plugins its heading names (there must be one)."""
    for page in PAGES:
        for heading, header, rows in _tables(_prose(page.read_text())):
            if not header or header[0] != first or column not in header:
                continue
            plugins = _plugins_named(heading, registry)
            assert plugins, f"{_rel(page)}: a {first} table under {heading!r} names no plugin in its heading"
            yield page, header, rows, plugins


def _param_table_problems(registry) -> tuple[list[str], int]:
    problems, checked = [], 0
    for page, header, rows, plugins in _plugin_tables("param", "default", registry):
        col = header.index("default")
        for row in rows:
            names = [n.strip("` ") for n in re.split(r"\s*,\s*|\s+/\s+", row[0])]
            values = re.split(r",\s+|\s+/\s+", row[col])
            if len(values) != len(names):
                values = [row[col]] * len(names) if len(values) == 1 else values
            if len(values) != len(names):
                problems.append(f"{_rel(page)}: row {row[0]!r}: {len(names)} names, {len(values)} defaults")
                continue
            for plugin in plugins:
                cls = registry.components[plugin].cls
                for name, value in zip(names, values):
                    checked += 1
                    if name not in cls.Params.model_fields:
                        problems.append(f"{_rel(page)}: {plugin} has no parameter {name!r}")
                        continue
                    why = _mismatch(plugin, name, _default(cls, name), value)
                    if why:
                        problems.append(f"{_rel(page)}: {why}")
    return problems, checked


def test_parameter_tables_give_the_params_defaults(registry):
    problems, checked = _param_table_problems(registry)
    assert not problems, "\n".join(problems)
    assert checked >= 30, checked


def test_the_default_comparison_can_fail():
    assert _mismatch("x", "f", 0.412682, "0.41 MPa") is not None       # 0.41 Pa is not 0.41 MPa
    assert _mismatch("x", "f", 412682.5, "0.41 MPa") is None            # within the written digits
    assert _mismatch("x", "f", 400000.0, "0.41 MPa") is not None
    assert _mismatch("x", "f", 0.1, "100 ms") is None and _mismatch("x", "f", 0.2, "100 ms") is not None
    assert _mismatch("x", "f", "qvga60", "qvga30") is not None and _mismatch("x", "f", None, "15") is not None
    assert _mismatch("x", "f", True, "false") is not None and _mismatch("x", "f", 0.5, "the node's id") is not None


def test_follower_limits_table_gives_the_params_defaults(registry):
    text = (REPO / "docs" / "followers.md").read_text()
    problems, checked = [], 0
    for _, header, rows in _tables(text):
        if not header or not header[-1].startswith("default limits (opening, speed, force)"):
            continue
        for row in rows:
            (plugin,) = re.findall(r"`([a-z0-9-]+)`", row[0])
            opening, speed, force = [c.strip() for c in row[-1].split(",")]
            lo, hi, unit = re.match(r"^([\d.]+)-([\d.]+) (\S+)$", opening).groups()
            cls = registry.components[plugin].cls
            for field, value in (("min_opening", f"{lo} {unit}"), ("max_opening", f"{hi} {unit}"),
                                 ("max_speed", speed), ("max_effort", force)):
                checked += 1
                why = _mismatch(plugin, field, _default(cls, field), value)
                if why:
                    problems.append(f"docs/followers.md: {why}")
    assert not problems, "\n".join(problems)
    assert checked == 16, checked


def test_intents_table_gives_the_intents_defaults():
    from teletouch.plugins.devices import operator

    text = (REPO / "docs" / "leaders.md").read_text()
    problems, checked = [], 0
    for _, header, rows in _tables(text):
        if header[:2] != ["type", "parameters"]:
            continue
        for row in rows:
            kind = re.findall(r"`([a-z-]+)`", row[0])[0]
            cls = operator._resolve(kind)
            for name, value in re.findall(r"`([a-z_]+)` \(?([^,()`]+?)\)?(?=,|$)", row[1]):
                checked += 1
                why = _mismatch(f"intent {kind}", name, cls.Params.model_fields[name].default, value.strip())
                if why:
                    problems.append(f"docs/leaders.md: {why}")
    assert not problems, "\n".join(problems)
    assert checked >= 7, checked


INLINE_DEFAULT = re.compile(r"`([a-z][a-z0-9_]*)`(?: \(|, )(?:default )?"
                            r"([-+]?\d+(?:\.\d+)?(?: ?[A-Za-z][\w*/^]*)?)[,;)]")


def test_inline_defaults_are_a_components_default(registry):
    """"`fade_time` (200 ms)", "`max_clock_skew` (default 50 ms)": the figure must be that parameter's default in
    at least one component that has it (several share names: `max_force_rate` is 200 N/s in the controllers and
    500 N/s in the press routine). Names that are no component's parameter (graph `faults:` keys, Recorder options)
    and parameters whose default is None (resolved at configure) are not checked here."""
    problems, checked = [], 0
    for page in PAGES:
        for name, value in INLINE_DEFAULT.findall(_prose(page.read_text())):
            defaults = [_default(info.cls, name) for info in registry.components.values()
                        if name in info.cls.Params.model_fields]
            defaults = [d for d in defaults if d is not None]
            if not defaults:
                continue
            checked += 1
            whys = [_mismatch("*", name, d, value) for d in defaults]
            if all(whys):
                problems.append(f"{_rel(page)}: `{name}` ({value}): no component has this default "
                                f"(defaults: {sorted(set(map(repr, defaults)))})")
    assert not problems, "\n".join(problems)
    assert checked >= 25, checked


# ---- ports --------------------------------------------------------------------------------------------------------

def _shape(text: str):
    inner = text.strip().strip("`")
    if not (inner.startswith("(") and inner.endswith(")")):
        return "?"
    parts = [p.strip() for p in inner[1:-1].split(",") if p.strip()]
    return tuple(int(p) if p.isdigit() else None for p in parts)


def test_port_tables_match_the_components_ports(registry):
    known_units = {"", "m", "m/s", "N", "J", "m^2", "N*s/m", "N/m", "rad", "rad/s", "s", "Hz"}
    problems, checked = [], 0
    for page, header, rows, plugins in _plugin_tables("port", "dir", registry):
        for row in rows:
            cell = dict(zip(header, row))
            port = cell["port"].strip("` ")
            direction = cell["dir"].split()[0].strip(",")
            optional = "optional" in cell["dir"]
            for plugin in plugins:
                cls = registry.components[plugin].cls
                ports = cls.inputs if direction == "in" else cls.outputs
                checked += 1
                where = f"{_rel(page)}: {plugin} {direction}put {port!r}"
                if port not in ports:
                    problems.append(f"{where}: no such port ({sorted(ports)})")
                    continue
                p = ports[port]
                if direction == "in" and optional == p.required:
                    problems.append(f"{where}: documented {'optional' if optional else 'required'}, "
                                    f"code required={p.required}")
                if "dtype" in cell and cell["dtype"].strip("` ") != p.dtype:
                    problems.append(f"{where}: dtype {cell['dtype']!r}, code {p.dtype!r}")
                if "shape" in cell and _shape(cell["shape"]) not in ("?", p.shape):
                    problems.append(f"{where}: shape {cell['shape']!r}, code {p.shape!r}")
                if "unit" in cell:
                    unit = cell["unit"].split(",")[0].strip().strip("`")
                    unit = "" if unit == '""' else unit
                    if unit in known_units and unit != p.unit:
                        problems.append(f"{where}: unit {unit!r}, code {p.unit!r}")
    assert not problems, "\n".join(problems)
    assert checked >= 40, checked


# ---- links and paths ----------------------------------------------------------------------------------------------

def _slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = heading.lstrip("#").strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def test_relative_links_and_example_paths_resolve():
    problems, checked = [], 0
    for page in PAGES:
        text = page.read_text()
        for target in re.findall(r"\]\(([^)\s]+)\)", _prose(text)):
            if re.match(r"^[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            checked += 1
            if not dest.exists():
                problems.append(f"{_rel(page)}: link {target}: no such file")
            elif anchor and dest.suffix == ".md":
                slugs = {_slug(h) for h in re.findall(r"(?m)^#+ .*$", _prose(dest.read_text()))}
                if anchor not in slugs:
                    problems.append(f"{_rel(page)}: link {target}: no heading with anchor #{anchor}")
        for path in re.findall(r"\bexamples/[\w./-]*[\w/]", text):
            checked += 1
            if not (REPO / path).exists():
                problems.append(f"{_rel(page)}: {path} does not exist")
    assert not problems, "\n".join(problems)
    assert checked >= 20, checked
