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
  and unit (every unit cell compared: one the check cannot read is a failure);
- docs/ports.md documents every port of every built-in plugin in that plugin's section, in a table row or in its
  prose (`` `port` (unit, ...) ``), with the code's unit;
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


#: dtype words written in a unit cell or a port's parenthesis: a value that has no unit ("bool", "bool map")
DTYPE_WORDS = {"bool", "str", "uint8", "uint16", "int64", "float32", "float64"}


def _unit_words(registry) -> set[str]:
    """Every unit symbol a page may write: the unit parser's (SI and scaled) and every port's own ("rad/s", "any")."""
    from teletouch.units import _UNITS

    words = set(_UNITS) | {si for si, _ in _UNITS.values()}
    for info in registry.components.values():
        words |= {p.unit for p in (*info.cls.inputs.values(), *info.cls.outputs.values())}
    return words - {""}


def _cell_unit(cell: str, words: set[str]) -> str | None:
    """The unit a port table's unit cell gives ('N, (3,)' -> 'N'; '""', an empty cell or a dtype such as 'bool' or
    'bool map' -> '': no unit), None when the cell holds nothing the check can read as a unit (one of ``words``)."""
    first = cell.split(",")[0].strip().strip("`").strip()
    if first in ('""', ""):
        return ""
    if first.split()[0] in DTYPE_WORDS:
        return ""
    return first if first in words else None


def _unit_problem(documented: str | None, cell: str, code: str) -> str | None:
    if documented is None:
        return f"unit {cell!r} is not a unit the check can compare (write the code's unit {code!r}, or \"\" for none)"
    return None if documented == code else f"unit {cell!r}, code {code!r}"


def _port_table_problems(pages: list[tuple[str, str]], registry) -> tuple[list[str], int]:
    """(problems, rows checked) of the port tables of ``pages`` ((name, text) each)."""
    problems, checked = [], 0
    words = _unit_words(registry)
    for name, text in pages:
        for heading, header, rows in _tables(_prose(text)):
            if not header or header[0] != "port" or "dir" not in header:
                continue
            plugins = _plugins_named(heading, registry)
            assert plugins, f"{name}: a port table under {heading!r} names no plugin in its heading"
            for row in rows:
                cell = dict(zip(header, row))
                port = cell["port"].strip("` ")
                direction = cell["dir"].split()[0].strip(",")
                optional = "optional" in cell["dir"]
                for plugin in plugins:
                    cls = registry.components[plugin].cls
                    ports = cls.inputs if direction == "in" else cls.outputs
                    checked += 1
                    where = f"{name}: {plugin} {direction}put {port!r}"
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
                        why = _unit_problem(_cell_unit(cell["unit"], words), cell["unit"], p.unit)
                        if why:
                            problems.append(f"{where}: {why}")
    return problems, checked


def test_port_tables_match_the_components_ports(registry):
    problems, checked = _port_table_problems([(_rel(page), page.read_text()) for page in PAGES], registry)
    assert not problems, "\n".join(problems)
    assert checked >= 40, checked


def _builtin(registry) -> dict[str, type]:
    """The components of teletouch's own plugins (the mocks are for tests: not documented in ports.md)."""
    return {name: info.cls for name, info in registry.components.items()
            if info.distribution == "teletouch" and info.plugin != "mock"}


def _sections(text: str) -> list[tuple[str, str]]:
    """(heading, body) of each `## ` section of a page, fenced code left out."""
    parts = re.split(r"(?m)^(## .*)$", _prose(text))
    return list(zip(parts[1::2], parts[2::2]))


def _heading_plugins(heading: str, registry) -> set[str]:
    """The components a section's heading names: by their name, or by their plugin's (`position-force`: its
    baselines too, 'the same plugin family')."""
    out = set()
    for name in re.findall(r"`([a-z0-9-]+)`", heading):
        out |= {c for c, info in registry.components.items() if c == name or info.plugin == name}
    return out


def _parenthesis(text: str, at: int) -> str | None:
    """The text of the parenthesis that opens at ``text[at:]`` (after blanks), its own parentheses kept; None if none
    opens there."""
    m = re.match(r"[ \t]*\(", text[at:])
    if not m:
        return None
    depth, start = 0, at + m.end() - 1
    for i in range(start, len(text)):
        depth += {"(": 1, ")": -1}.get(text[i], 0)
        if depth == 0:
            return text[start + 1:i]
    return None


def _top_level_parts(text: str) -> list[str]:
    """``text`` split at its commas, semicolons and colons outside parentheses, each part stripped."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += {"(": 1, ")": -1}.get(ch, 0)
        if ch in ",;:" and depth == 0:
            parts.append(cur.strip())
            cur = ""
        else:
            cur += ch
    return parts + [cur.strip()]


def _documented_ports(text: str, registry) -> dict[str, dict[str, list[tuple[str, str | None]]]]:
    """component -> port -> how ports.md documents it in that component's section: ('in'|'out', unit cell) of each
    table row, ('prose', parenthesis or None) of each `` `port` `` in a paragraph about it. A table belongs to the
    components its section's heading names; a paragraph that starts with a component's name (`` `sim-digit` also
    has ... ``, `` `depth`: in ... ``) to that component alone, any other paragraph to the heading's components."""
    docs: dict[str, dict[str, list[tuple[str, str | None]]]] = {}
    for heading, body in _sections(text):
        named = _heading_plugins(heading, registry)
        for _, header, rows in _tables(body):
            if not header or header[0] != "port" or "dir" not in header:
                continue
            for row in rows:
                cell = dict(zip(header, row))
                for comp in named:
                    docs.setdefault(comp, {}).setdefault(cell["port"].strip("` "), []).append(
                        (cell["dir"].split()[0].strip(","), cell.get("unit")))
        for para in re.split(r"\n\s*\n", body):
            para = "\n".join(line for line in para.splitlines() if not line.startswith("|"))
            first = re.match(r"\s*`([a-z0-9-]+)`", para)
            owners = {first.group(1)} if first and first.group(1) in registry.components else named
            for m in re.finditer(r"`([a-z][a-z0-9_]*)`", para):
                for comp in owners:
                    docs.setdefault(comp, {}).setdefault(m.group(1), []).append(("prose", _parenthesis(para, m.end())))
    return docs


def _prose_unit_problem(mentions: list[str | None], code: str, words: set[str]) -> str | None:
    """Why the parentheses after a port's mentions in prose do not give its unit ``code``: every unit they name must
    be it, and a port with a unit ('m', not '' or 'any') needs one mention that names it."""
    named = []
    for par in mentions:
        units = [part for part in _top_level_parts(par or "") if part in words]
        if units:
            named.append(units[0])
    wrong = [u for u in named if u != code]
    if wrong:
        return f"documented in {wrong[0]!r}, code {code!r}"
    if code not in ("", "any") and not named:
        return f"mentioned without its unit (code {code!r}): write `port` ({code}, ...)"
    return None


def _port_doc_problems(text: str, registry) -> tuple[list[str], int]:
    """(problems, ports checked): every input and output port of every built-in component documented in its section
    of ``text`` (docs/ports.md), with the code's unit."""
    docs = _documented_ports(text, registry)
    words = _unit_words(registry)
    problems, checked = [], 0
    for comp, cls in sorted(_builtin(registry).items()):
        for direction, ports in (("in", cls.inputs), ("out", cls.outputs)):
            for port, p in ports.items():
                checked += 1
                where = f"docs/ports.md: {comp} {direction}put {port!r} ({p.unit or 'no unit'})"
                got = docs.get(comp, {}).get(port, [])
                rows = [cell for kind, cell in got if kind == direction]
                if rows:   # a table row
                    whys = [_unit_problem(_cell_unit(cell, words), cell, p.unit) if cell is not None else
                            None if p.unit in ("", "any") else "its table row has no unit column" for cell in rows]
                    problems += [f"{where}: {why}" for why in whys if why]
                    continue
                prose = [par for kind, par in got if kind == "prose"]
                if not prose:
                    problems.append(f"{where}: not documented in {comp}'s section (a table row, or `{port}` "
                                    f"({p.unit or 'no unit'}) in its prose)")
                    continue
                why = _prose_unit_problem(prose, p.unit, words)
                if why:
                    problems.append(f"{where}: {why}")
    return problems, checked


def test_ports_md_documents_every_port_of_every_built_in_plugin_with_its_unit(registry):
    problems, checked = _port_doc_problems((REPO / "docs" / "ports.md").read_text(), registry)
    assert not problems, "\n".join(problems)
    assert checked >= 100, checked


PORTS_PAGE = """
## Leaders (`omega7`)
| port | dir | dtype | shape | unit | meaning |
|---|---|---|---|---|---|
| gripper_force | in (optional) | float64 | () | N | f |
| force | in (optional) | float64 | (3,) | mm | f |
| gripper_opening | out | float64 | () | metres | g |
| gripper_velocity | out | float64 | () | m/s | v |
| button | out | bool | () | "" | b |

`omega7` also has `position` (N, the handle).

## Estimators
`depth`: in `image`; out `depth` (float32 (rows, cols), m), `max_depth` (m), `contact_mask` (bool (rows, cols)),
`contact_area`, `centroid` ((2,), m).
"""


def test_the_port_checks_can_fail(registry):
    """A missing port, a wrong unit (table or prose), a unit cell the check cannot read, a unit left out."""
    table, _ = _port_table_problems([("page", PORTS_PAGE)], registry)
    assert "page: omega7 input 'force': unit 'mm', code 'N'" in table, table
    assert any(p.startswith("page: omega7 output 'gripper_opening': unit 'metres' is not a unit the check can "
                            "compare") for p in table), table
    assert len(table) == 2, table
    docs, _ = _port_doc_problems(PORTS_PAGE, registry)
    mine = [p for p in docs if p.startswith(("docs/ports.md: omega7 ", "docs/ports.md: depth "))]
    assert mine == [
        "docs/ports.md: depth output 'contact_area' (m^2): mentioned without its unit (code 'm^2'): write `port` "
        "(m^2, ...)",
        "docs/ports.md: omega7 input 'force' (N): unit 'mm', code 'N'",
        "docs/ports.md: omega7 output 'gripper_opening' (m): unit 'metres' is not a unit the check can compare "
        "(write the code's unit 'm', or \"\" for none)",
        "docs/ports.md: omega7 output 'position' (m): documented in 'N', code 'm'",
    ], mine
    assert any(p.startswith("docs/ports.md: sim-gripper output 'contact'") and "not documented" in p
               for p in docs), docs
    words = _unit_words(registry)
    assert _cell_unit("N, (3,)", words) == "N" and _cell_unit("bool map", words) == "" and _cell_unit("", words) == ""
    assert _cell_unit("see below", words) is None and _cell_unit("rad/s", words) == "rad/s"


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
