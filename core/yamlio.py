"""YAML loading that remembers where every key came from, so errors can name the file and line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from .errors import GraphError, Location


class LDict(dict):
    """A dict that knows the location of itself and of each of its keys."""

    where: Location
    key_where: dict[Any, Location]

    def __init__(self, *a: Any, where: Location | None = None, **kw: Any):
        super().__init__(*a, **kw)
        self.where = where or Location(None, None)
        self.key_where = {}

    def loc(self, key: Any) -> Location:
        return self.key_where.get(key, self.where)


class LList(list):
    where: Location
    item_where: list[Location]

    def __init__(self, *a: Any, where: Location | None = None):
        super().__init__(*a)
        self.where = where or Location(None, None)
        self.item_where = []

    def loc(self, i: int) -> Location:
        return self.item_where[i] if i < len(self.item_where) else self.where


#: the most values (scalars and collections, each alias counted again) a graph's YAML may expand to
MAX_YAML_VALUES = 200_000

_NUMBER_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")


def _convert(node: yaml.Node, file: str, constructor: "yaml.constructor.SafeConstructor",
             active: set[int] | None = None) -> Any:
    where = Location(file, node.start_mark.line + 1)
    # each alias is converted again (a value of its own, with its own lines): aliases of aliases grow exponentially
    # (9 levels of 9: 43 million values, an out-of-memory crash), so the values converted are counted
    constructor.tt_values = getattr(constructor, "tt_values", 0) + 1
    if constructor.tt_values > MAX_YAML_VALUES:
        raise GraphError(f"the YAML expands to more than {MAX_YAML_VALUES} values through its aliases (anchors used "
                         f"inside anchors, many levels deep?): a graph is a few hundred", where)
    if isinstance(node, (yaml.MappingNode, yaml.SequenceNode)):
        # an alias may point at a collection that holds it (``a: &x [*x]``): that would never end
        active = set() if active is None else active
        if id(node) in active:
            raise GraphError("a YAML alias refers to a collection that contains it (a recursive anchor)", where)
        active.add(id(node))
        try:
            return _convert_collection(node, file, constructor, active, where)
        finally:
            active.discard(id(node))
    if node.tag in _NUMBER_TAGS and "_" in str(node.value):
        # YAML 1.1 reads 1_0 as 10: a number a person typed with an underscore is taken for a typo, as units refuse it
        raise GraphError(f"{node.value!r}: an underscore in a number is taken for a typo, not for a digit separator; "
                         f"expected a number without one", where)
    try:
        return constructor.construct_object(node, deep=True)
    except yaml.constructor.ConstructorError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, AttributeError):   # an explicit tag on a value it cannot
        tag = str(node.tag).replace("tag:yaml.org,2002:", "!!")              # read: `!!int abc`, `!!bool maybe`
        raise GraphError(f"YAML error: {node.value!r} is not a valid {tag}", where) from None


_MERGE = "tag:yaml.org,2002:merge"


def _flatten(node: yaml.MappingNode, file: str) -> int:
    """Resolve the merge keys (``<<: *defaults``) of ``node`` in place; return how many of its pairs, at the start,
    came from them (keys the mapping's own keys may override, as YAML says). Of the pairs merged, a later one
    overrides an earlier one: a list of mappings is laid in reverse, so its first mapping wins, as the YAML merge key
    type says. Done here, not by PyYAML's flatten_mapping, whose order changed in 6.0.4 (with it the last mapping of
    a list won). Remembered on the node: an alias converts the same node again."""
    done = getattr(node, "tt_merged", None)
    if done is not None:
        return done
    node.tt_merged = 0   # (while here: a merge key that refers to its own mapping)
    merged: list[tuple[yaml.Node, yaml.Node]] = []
    own: list[tuple[yaml.Node, yaml.Node]] = []
    for knode, vnode in node.value:
        if knode.tag != _MERGE:
            if knode.tag == "tag:yaml.org,2002:value":   # a key `=`: a string, as PyYAML reads it
                knode.tag = "tag:yaml.org,2002:str"
            own.append((knode, vnode))
            continue
        subs = list(reversed(vnode.value)) if isinstance(vnode, yaml.SequenceNode) else [vnode]
        for sub in subs:
            if not isinstance(sub, yaml.MappingNode):
                raise GraphError(f"a merge key '<<' takes a mapping or a list of mappings, not a {sub.id}",
                                 Location(file, sub.start_mark.line + 1))
            _flatten(sub, file)
            merged.extend(sub.value)
    node.value = merged + own
    node.tt_merged = len(merged)
    return node.tt_merged


def _convert_collection(node: yaml.Node, file: str, constructor: "yaml.constructor.SafeConstructor",
                        active: set[int], where: Location) -> Any:
    if isinstance(node, yaml.MappingNode):
        merged = _flatten(node, file)
        out = LDict(where=where)
        inherited: set[Any] = set()   # keys that came from a merge key, so far: the mapping's own keys override them
        for i, (knode, vnode) in enumerate(node.value):
            key = _convert(knode, file, constructor, active)
            if isinstance(key, (dict, list)):
                raise GraphError("a mapping key must be a plain value", Location(file, knode.start_mark.line + 1))
            if key in out and key not in inherited:
                raise GraphError(f"duplicate key '{key}' (first at line {out.loc(key).line})",
                                 Location(file, knode.start_mark.line + 1))
            out[key] = _convert(vnode, file, constructor, active)
            out.key_where[key] = Location(file, knode.start_mark.line + 1)
            if i < merged:
                inherited.add(key)
            else:
                inherited.discard(key)
        return out
    out_l = LList(where=where)
    for item in node.value:
        out_l.append(_convert(item, file, constructor, active))
        out_l.item_where.append(Location(file, item.start_mark.line + 1))
    return out_l


def load_yaml_text(text: str, file: str) -> Any:
    """Parse YAML text into LDict/LList/scalars; syntax errors become GraphError with the line."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = exc.problem or str(exc)
        raise GraphError(f"YAML syntax error: {problem}", Location(file, line)) from None
    except yaml.YAMLError as exc:
        raise GraphError(f"YAML error: {exc}", Location(file, None)) from None
    if node is None:
        return LDict(where=Location(file, 1))
    constructor = yaml.constructor.SafeConstructor()
    try:
        return _convert(node, file, constructor)
    except yaml.constructor.ConstructorError as exc:
        mark = exc.problem_mark
        raise GraphError(f"YAML error: {exc.problem}", Location(file, mark.line + 1 if mark else None)) from None


#: the largest graph file read (bytes): the examples are a few KB; `include: /dev/zero` (or a huge file by mistake)
#: read until the kernel killed the process for its memory
MAX_GRAPH_BYTES = 1 << 20


def load_yaml_file(path: str | Path) -> Any:
    p = Path(path)
    try:
        with p.open("rb") as fh:   # (a pipe too: `teletouch run <(...)`; what it holds is capped the same)
            data = fh.read(MAX_GRAPH_BYTES + 1)
        if len(data) > MAX_GRAPH_BYTES:
            raise GraphError(f"larger than {MAX_GRAPH_BYTES >> 20} MiB: a graph file is a few KB of YAML text (the "
                             f"wrong file?)", Location(str(path), None))
        text = data.decode("utf-8").replace("\r\n", "\n").replace("\r", "\n")   # (as read_text's newlines)
    except FileNotFoundError:
        raise GraphError("file not found", Location(str(path), None)) from None
    except UnicodeDecodeError as exc:
        raise GraphError(f"not UTF-8 text (byte {exc.start}): a graph file is YAML text", Location(str(path), None)
                         ) from None
    except OSError as exc:
        raise GraphError(f"cannot read file: {exc.strerror}", Location(str(path), None)) from None
    return load_yaml_text(text, str(path))
