"""Graph files: load (with includes and overrides), validate everything before anything runs, export a JSON Schema.

A graph file::

    name: paper-sim
    include: base.yaml            # optional; a list is allowed. Nodes with the same id are merged (override).
    clock: sim                    # sim (deterministic, as fast as possible) or wall (real time)
    duration: 10                  # s (or "10s"); optional
    realtime_priority: 0          # SCHED_FIFO priority for threads at >= 200 Hz in wall mode (0: off; needs
                                  # CAP_SYS_NICE / rtprio limits, as for ros2_control's control thread)
    faults:
      on_fault: stop              # default reaction to a node's fault: stop | degrade
      max_overruns: 10            # consecutive late steps before a node faults (wall clock; 0 = never)
      startup_grace: 1.0          # s before stale-input checks start
      watchdog: 0.1               # s: a device not stepped for this long is made safe and faults (wall clock;
                                  # at least 3 of its periods; 0 = off)
      safe_timeout: 0.5           # s: a device's safe_state() that has not returned by then is left behind
                                  # (its hardware call hangs) and the others go on
    nodes:
      - id: mapper
        plugin: poly-force
        rate: 60                  # Hz (or "1kHz")
        params: {out_of_range: clamp}
        inputs:
          max_depth: depth.max_depth                          # node.port
          contact_area: {from: depth.contact_area, max_age: 0.1}   # with a staleness limit (s)
          centroid: depth.centroid
        on_fault: degrade         # optional, per node
        isolate: process          # optional: run in a process of its own under the wall clock (see isolation.py)
        priority: 40              # optional: SCHED_FIFO priority of this node's thread (wall clock; default:
                                  # realtime_priority for threads at >= 200 Hz, normal scheduling otherwise)

Every error names the file and line.
"""

from __future__ import annotations

import copy
import difflib
import json
import math
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from pydantic import ValidationError

from .component import MAX_RATE  # noqa: F401  (re-exported: graph.MAX_RATE, as before the rates' check moved)
from .component import _BOOLEAN_NUMBER, Component, Device, _field_unit, rate_problem, shapes_differ
from .errors import GraphError, GraphValidationError, Location
from .units import parse_quantity
from .yamlio import LDict, LList, load_yaml_file, load_yaml_text

TOP_KEYS = ("name", "description", "include", "clock", "duration", "realtime_priority", "faults", "nodes")
NODE_KEYS = ("id", "plugin", "rate", "params", "inputs", "on_fault", "isolate", "priority", "remove",
             "description")
MAX_AGE_LIMIT = 60.0   # s: the longest a wire's sample may be used after its stamp
FAULT_KEYS = ("on_fault", "max_overruns", "startup_grace", "watchdog", "safe_timeout")
FAULT_ACTIONS = ("stop", "degrade")
CLOCKS = ("sim", "wall")
ID_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]*$")


def _is_extension(key: Any) -> bool:
    """A top-level key starting with ``x-``: ignored, so that shared values can be defined once as YAML anchors
    (``x-limits: &limits {...}``, then ``params: {<<: *limits}``), as Compose files do; an anchor had nowhere to live
    but inside a node."""
    return isinstance(key, str) and key.startswith("x-")


@dataclass
class WireSpec:
    port: str
    node: str
    source_port: str
    max_age: float | None
    where: Location
    #: kept from an included graph's node whose plugin an override replaced (not written again since): a wire the
    #: new plugin may not have, which the override can unwire (``inputs: {port: null}``)
    kept: bool = False


@dataclass
class NodeSpec:
    id: str
    plugin: str
    rate: float | None
    params: dict[str, Any]
    inputs: dict[str, WireSpec]
    on_fault: str | None
    where: Location
    param_where: dict[str, Location] = field(default_factory=dict)
    isolate: str = "none"
    priority: int | None = None
    plugin_where: Location | None = None   # where its plugin was named (an override's file, if one replaced it)
    # filled in by validation
    cls: type[Component] | None = None
    params_obj: Any = None


@dataclass
class FaultPolicy:
    on_fault: str = "stop"
    max_overruns: int = 10
    startup_grace: float = 1.0
    watchdog: float = 0.1
    safe_timeout: float = 0.5


@dataclass
class GraphSpec:
    name: str
    file: str
    nodes: list[NodeSpec]
    clock: str = "wall"
    duration: float | None = None
    faults: FaultPolicy = field(default_factory=FaultPolicy)
    description: str = ""
    realtime_priority: int = 0
    #: what validation found that may work against the graph without making it invalid, one line each (led by the
    #: file and line, as errors are), under the clock it was loaded for (``clock``): `teletouch validate` and
    #: `teletouch run` print them on stderr. A runtime on another clock has its own: :meth:`warnings_for`
    warnings: list[str] = field(default_factory=list)

    def warnings_for(self, clock: str) -> list[str]:
        """The graph's warnings when it runs under ``clock`` ("sim" or "wall"), which need not be the clock it was
        loaded for (``Runtime(spec, clock=...)``): as :attr:`warnings`, for that clock."""
        return _isolation_warnings(self.nodes, clock, self.file)

    def node(self, node_id: str) -> NodeSpec:
        for n in self.nodes:
            if n.id == node_id:
                return n
        raise KeyError(node_id)

    def order(self) -> list[NodeSpec]:
        """Nodes in data-flow order (producers before consumers); feedback edges are cut where found."""
        by_id = {n.id: n for n in self.nodes}
        seen: dict[str, int] = {}
        out: list[NodeSpec] = []

        def visit(n: NodeSpec) -> None:
            state = seen.get(n.id)
            if state is not None:
                return  # done (2) or on the stack (1): a feedback edge, cut here
            seen[n.id] = 1
            for w in n.inputs.values():
                src = by_id.get(w.node)
                if src is not None:
                    visit(src)
            seen[n.id] = 2
            out.append(n)

        for n in self.nodes:
            visit(n)
        return out


# ------------------------------------------------------------------------------------------------ loading / merging
def _suggest(name: str, options: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(options), n=2, cutoff=0.6)
    return (" (did you mean " + " or ".join(f"'{c}'" for c in close) + "?)") if close else ""


def _merge(base: Any, over: Any) -> Any:
    """Overlay ``over`` onto ``base``: mappings merge key by key, node lists merge by id, the rest replaces."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = copy.copy(base)
        if isinstance(base, LDict):
            out.key_where = dict(base.key_where)
        for k, v in over.items():
            out[k] = _merge(base[k], v) if k in base and k != "include" else v
            if isinstance(out, LDict) and isinstance(over, LDict):
                out.key_where[k] = over.loc(k)
        return out
    return over


def _place(where: Location) -> tuple[str | None, int | None]:
    return where.file, where.line


def _node_id(node: Any) -> str | None:
    """A node's id where it can name a node (a string); a list or a mapping there is reported by validation."""
    nid = node.get("id") if isinstance(node, dict) else None
    return nid if isinstance(nid, str) else None


def _merge_nodes(base: list, over: list) -> LList:
    out = LList(where=getattr(base, "where", None))
    out.extend(base)
    out.item_where = list(getattr(base, "item_where", [Location(None, None)] * len(base)))
    index = {_node_id(n): i for i, n in enumerate(out) if _node_id(n) is not None}
    seen: dict[str, Location] = {}   # ids this file lists (not to remove): a second entry is a duplicate, not a merge
    for j, node in enumerate(over):
        nid = _node_id(node)
        shown = node.get("id") if isinstance(node, dict) else None   # as written, for messages
        where = over.loc(j) if isinstance(over, LList) else Location(None, None)
        remove = node.get("remove", False) if isinstance(node, dict) else False
        if not isinstance(remove, bool):
            raise GraphError(f"node '{shown}': remove: expected true or false, got {remove!r}",
                             node.loc("remove") if isinstance(node, LDict) else where)
        if remove and (nid is None or nid not in index):
            raise GraphError(f"node '{shown}': remove: true, but no included graph has a node '{shown}'"
                             f"{_suggest(str(shown), index)}", where)
        if nid is not None and not remove:
            id_where = node.loc("id") if isinstance(node, LDict) else where
            if nid in seen:
                raise GraphError(f"duplicate node id '{nid}' (first defined at {seen[nid]})", id_where)
            seen[nid] = id_where
        if nid is not None and nid in index:
            i = index[nid]
            if remove:
                out[i] = None
                del index[nid]   # a later entry with this id is a new node
                continue
            merged = _merge(out[i], node)
            if node.get("plugin") not in (None, out[i].get("plugin")):
                # a new plugin does not inherit the old one's params: its own, if given, are all it has (merged
                # into the old ones, a swap with params of its own failed on the old plugin's "unknown param")
                merged["params"] = node["params"] if "params" in node else LDict(where=where)
                # its wires stay: those of the included node that this one does not write again are marked, so that
                # a port the new plugin lacks is said to come from there (and how to unwire it), and only those
                base_in, over_in = out[i].get("inputs"), node.get("inputs")
                if isinstance(merged, LDict) and isinstance(base_in, LDict):
                    merged.kept_wires = {str(p): _place(base_in.loc(p)) for p in base_in
                                         if not (isinstance(over_in, dict) and p in over_in)}
            over_in, ins = node.get("inputs"), merged.get("inputs")
            if isinstance(over_in, dict) and isinstance(ins, dict):
                base_in = out[i].get("inputs")
                wired = [str(p) for p in base_in] if isinstance(base_in, dict) else []
                for port in [p for p, src in over_in.items() if src is None]:   # `port: null` unwires an input
                    if port not in wired:   # a typo would leave the wire it meant in place
                        raise GraphError(f"node '{nid}': input '{port}': null unwires an input of the included node, "
                                         f"and it has no input '{port}' wired{_suggest(str(port), wired)}; wired: "
                                         f"{', '.join(wired) or '(none)'}",
                                         over_in.loc(port) if isinstance(over_in, LDict) else where)
                    del ins[port]
                    if isinstance(ins, LDict):
                        ins.key_where.pop(port, None)
            out[i] = merged
        else:
            out.append(node)
            out.item_where.append(where)
            if nid is not None:
                index[nid] = len(out) - 1
    keep = [i for i, n in enumerate(out) if n is not None]
    res = LList([out[i] for i in keep], where=out.where)
    res.item_where = [out.item_where[i] for i in keep]
    return res


def load_raw(path: str | Path, _stack: tuple[str, ...] = ()) -> LDict:
    """Load a graph file with its includes resolved (no validation against plugins yet)."""
    path = Path(path)
    key = str(path.resolve())
    if key in _stack:
        raise GraphError("include cycle: " + " -> ".join(_stack + (key,)), Location(str(path), None))
    doc = load_yaml_file(path)
    if not isinstance(doc, dict):   # (a bare scalar has no location of its own)
        raise GraphError("a graph file must be a mapping with a 'nodes' list",
                         getattr(doc, "where", None) or Location(str(path), 1))
    inc = doc.get("include")
    if inc is None:
        return doc
    incs = [inc] if isinstance(inc, str) else inc
    if not isinstance(incs, list) or not all(isinstance(i, str) for i in incs):
        raise GraphError("'include' must be a file name or a list of file names", doc.loc("include"))
    if not incs:   # `include: []`: nothing to merge
        return doc
    merged: LDict | None = None
    for i, name in enumerate(incs):
        sub_path = (path.parent / name)
        if not sub_path.exists():
            raise GraphError(f"included file '{name}' not found (looked in {sub_path.parent})", doc.loc("include"))
        if sub_path.is_dir():
            raise GraphError(f"included file '{name}' is a folder ({sub_path}), not a graph file", doc.loc("include"))
        sub = load_raw(sub_path, _stack + (key,))
        merged = sub if merged is None else _overlay(merged, sub)
    assert merged is not None
    return _overlay(merged, doc)


def _overlay(base: LDict, over: LDict) -> LDict:
    out = LDict(where=over.where)
    out.update(base)
    out.key_where = dict(base.key_where)
    for k, v in over.items():
        if k == "include":
            continue
        if k == "nodes" and isinstance(v, list) and isinstance(base.get("nodes"), list):
            out[k] = _merge_nodes(base["nodes"], v)
        elif k in base:
            out[k] = _merge(base[k], v)
        else:
            out[k] = v
        out.key_where[k] = over.loc(k)
    return out


#: the --set fields that are not parameters
SET_FIELDS = ("plugin", "rate", "on_fault", "priority", "isolate")


def set_problem(item: str) -> str | None:
    """None if ``item`` has the form of a ``--set`` (NODE.FIELD=VALUE, NODE.PARAM.KEY=VALUE for a value inside a
    parameter, NODE.params.NAME=VALUE); else what is wrong with it. The form alone: what it names is checked against
    the graph (:func:`apply_sets`)."""
    lhs, eq, _ = item.partition("=")
    parts = lhs.strip().split(".")
    if not eq or len(parts) < 2 or not all(p.strip() for p in parts):
        return (f"expected NODE.FIELD=VALUE (FIELD: {', '.join(SET_FIELDS)} or a parameter, nested with dots), e.g. "
                f"gripper.plugin=sim-gripper or force.out_of_range=extrapolate")
    if parts[1] == "params" and len(parts) == 2:
        return "expected NODE.params.NAME=VALUE (or NODE.NAME=VALUE) for a parameter"
    return None


def set_argument(text: str) -> str:
    """argparse ``type=`` of ``--set``: a malformed one is a usage error (exit 2) naming it and the form expected."""
    import argparse

    problem = set_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(f"{text!r}: {problem}")
    return text


class _NestedSets:
    """The ``--set``s of values inside one parameter (NODE.PARAM.KEY=VALUE) and the parameter's value before the first
    of them (``_MISSING`` where the file gave none): an error in the parameter is laid on the --set that made it, or
    on the file where its own value is refused (:func:`_blame_sets`)."""

    def __init__(self, original: Any):
        self.original = original
        self.items: list[tuple[list[str], str, Any]] = []   # (keys inside the parameter, the --set as given, value)


_MISSING = object()


def _nested_sets(params: dict, name: str) -> _NestedSets:
    """The record of the --sets inside parameter ``name`` of a node's ``params`` (kept on the mapping, as
    ``nested_sets``), made with the parameter's value before the first of them."""
    records = getattr(params, "nested_sets", None)
    if records is None:
        records = {}
        if isinstance(params, LDict):
            params.nested_sets = records   # type: ignore[attr-defined]
    if name not in records:
        records[name] = _NestedSets(copy.deepcopy(_plain(params[name])) if name in params else _MISSING)
    return records[name]


def apply_sets(doc: LDict, sets: Iterable[str]) -> LDict:
    """Apply ``--set NODE.FIELD=VALUE`` overrides (FIELD: plugin, rate, on_fault, priority, isolate or a parameter;
    nested with dots). Every error is led by the --set (``--set NODE.FIELD=VALUE: ...``)."""
    for item in sets:
        setw = Location("--set " + item, None)
        problem = set_problem(item)
        if problem:
            raise GraphError(problem, setw)
        lhs, rhs = item.split("=", 1)
        parts = [p.strip() for p in lhs.strip().split(".")]
        try:
            value = load_yaml_text(rhs, "--set") if rhs.strip() else ""
        except GraphError as exc:
            raise GraphError(exc.message, setw) from None
        if isinstance(value, (LDict, LList)):
            value = _plain(value)
        nodes = doc.get("nodes")
        if not isinstance(nodes, list):
            raise GraphError("the graph has no nodes", setw)
        node = next((n for n in nodes if isinstance(n, dict) and n.get("id") == parts[0]), None)
        if node is None:
            ids = [n.get("id") for n in nodes if isinstance(n, dict)]
            raise GraphError(f"no node '{parts[0]}'{_suggest(parts[0], ids)}", setw)
        if parts[1] in SET_FIELDS and len(parts) == 2:
            if parts[1] == "plugin" and value != node.get("plugin"):
                node["params"] = LDict(where=setw)
            node[parts[1]] = value
            node.key_where[parts[1]] = setw
            continue
        if parts[1] == "params":
            parts = [parts[0]] + parts[2:]
        params = node.get("params")
        if not isinstance(params, dict):
            params = LDict(where=setw)
            node["params"] = params
        if len(parts) > 2:   # a value inside a parameter: remember the parameter's value before it
            _nested_sets(params, parts[1]).items.append((parts[2:], item, value))
        target = params
        for p in parts[1:-1]:
            nxt = target.get(p)
            if not isinstance(nxt, dict):
                nxt = LDict(where=setw)
                target[p] = nxt
                if isinstance(target, LDict):
                    target.key_where[p] = setw
            target = nxt
        target[parts[-1]] = value
        if isinstance(target, LDict):
            target.key_where[parts[-1]] = setw
    return doc


def _plain(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_plain(x) for x in v]
    return v


# ------------------------------------------------------------------------------------------------ validation
def load_graph(path: str | Path, *, registry: Any = None, sets: Iterable[str] = (), clock: str | None = None,
               duration: float | None = None) -> GraphSpec:
    """Load, merge, override and validate a graph file. Raises GraphValidationError listing every problem."""
    try:
        doc = apply_sets(load_raw(path), sets)
    except GraphError as exc:
        raise GraphValidationError([exc]) from None
    return build_spec(doc, str(path), registry=registry, clock=clock, duration=duration)


def load_graph_text(text: str, file: str = "<graph>", **kw: Any) -> GraphSpec:
    try:
        doc = load_yaml_text(text, file)
        if not isinstance(doc, dict):   # (a bare scalar has no location of its own)
            raise GraphError("a graph file must be a mapping with a 'nodes' list",
                             getattr(doc, "where", None) or Location(file, 1))
        if doc.get("include") not in (None, []):   # a text has no folder to resolve it in: it would be left out
            raise GraphError("'include' needs a graph file to resolve it from: load the file (load_graph, "
                             "`teletouch run FILE`) instead of its text", doc.loc("include"))
        doc = apply_sets(doc, kw.pop("sets", ()))
    except GraphError as exc:
        raise GraphValidationError([exc]) from None
    return build_spec(doc, file, **kw)


def build_spec(doc: LDict, file: str, *, registry: Any = None, clock: str | None = None,
               duration: float | None = None) -> GraphSpec:
    if registry is None:
        from .registry import default_registry

        registry = default_registry()
    errors: list[GraphError] = []

    def err(msg: str, where: Location) -> None:
        errors.append(GraphError(msg, where))

    for k in doc:
        if k not in TOP_KEYS and not _is_extension(k):
            err(f"unknown top-level key '{k}'{_suggest(str(k), TOP_KEYS)}; expected one of {', '.join(TOP_KEYS)} (or "
                f"a key starting with 'x-', ignored: a place for YAML anchors)", doc.loc(k))

    clock_v = clock if clock is not None else doc.get("clock", "wall")
    if clock_v not in CLOCKS:
        err(f"clock: expected 'sim' or 'wall', got {clock_v!r}", doc.loc("clock"))
    dur = duration if duration is not None else doc.get("duration")
    if dur is not None:
        try:
            dur = parse_quantity(dur, "s")
            if not dur > 0:
                raise ValueError(f"must be positive, got {dur}")
        except ValueError as exc:
            err(f"duration: {exc}", Location("--duration", None) if duration is not None else doc.loc("duration"))
            dur = None

    rt_prio = doc.get("realtime_priority", 0)
    if not isinstance(rt_prio, int) or isinstance(rt_prio, bool) or not 0 <= rt_prio <= 99:
        err(f"realtime_priority: expected an integer 0-99 (0 = normal scheduling), got {rt_prio!r}",
            doc.loc("realtime_priority"))
        rt_prio = 0

    faults = FaultPolicy()
    fdoc = doc.get("faults", {})
    if not isinstance(fdoc, dict):
        err("faults: expected a mapping", doc.loc("faults"))
        fdoc = {}
    for k, v in fdoc.items():
        w = fdoc.loc(k) if isinstance(fdoc, LDict) else doc.loc("faults")
        if k not in FAULT_KEYS:
            err(f"faults: unknown key '{k}'{_suggest(str(k), FAULT_KEYS)}", w)
        elif k == "on_fault":
            if v not in FAULT_ACTIONS:
                err(f"faults.on_fault: expected 'stop' or 'degrade', got {v!r}", w)
            else:
                faults.on_fault = v
        elif k == "max_overruns":
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                err(f"faults.max_overruns: expected an integer >= 0, got {v!r}", w)
            else:
                faults.max_overruns = v
        elif k in ("startup_grace", "watchdog"):
            try:
                q = parse_quantity(v, "s")
                if not 0 <= q < math.inf:
                    raise ValueError(f"expected a time >= 0 s, got {v!r}")
                if k == "startup_grace" and q > 60:   # 1e9 let a source that never came stay unseen for good
                    raise ValueError(f"expected at most 60 s (the time the sources get to start before a missing "
                                     f"input is a fault), got {v!r}")
                if k == "watchdog" and q > 60:   # `100` meant as ms was 100 s of a hung device left unmade safe
                    raise ValueError(f"expected at most 60 s (how long a device may go without a step before it "
                                     f"is made safe; 0 turns it off; units are allowed: 100ms), got {v!r}")
                setattr(faults, k, q)
            except ValueError as exc:
                err(f"faults.{k}: {exc}", w)
        elif k == "safe_timeout":
            try:
                q = parse_quantity(v, "s")
                if not 0 < q <= 60:
                    raise ValueError(f"expected a time > 0 s and at most 60 s, got {v!r}")
                faults.safe_timeout = q
            except ValueError as exc:
                err(f"faults.safe_timeout: {exc}", w)

    nodes_doc = doc.get("nodes")
    nodes: list[NodeSpec] = []
    if nodes_doc is None:
        err("missing 'nodes': a graph needs a list of nodes", doc.where)
        nodes_doc = []
    elif not isinstance(nodes_doc, list):
        err("'nodes' must be a list of nodes (each with id, plugin, rate)", doc.loc("nodes"))
        nodes_doc = []
    elif not nodes_doc:
        err("'nodes' is empty: a graph needs at least one node", doc.loc("nodes"))
    for key in ("name", "description"):
        if key in doc and not isinstance(doc[key], str):
            err(f"{key}: expected text, got {doc[key]!r}", doc.loc(key))

    seen_ids: dict[str, Location] = {}
    miswired: set[tuple[str, str]] = set()   # (node, input) with a wire already reported: not also "not wired"
    for i, nd in enumerate(nodes_doc):
        nwhere = nodes_doc.loc(i) if isinstance(nodes_doc, LList) else doc.loc("nodes")
        if not isinstance(nd, dict):
            err("a node must be a mapping with id, plugin and rate", nwhere)
            continue
        ld = nd if isinstance(nd, LDict) else LDict(nd, where=nwhere)
        for k in ld:
            if k not in NODE_KEYS:
                err(f"node '{ld.get('id', '?')}': unknown key '{k}'{_suggest(str(k), NODE_KEYS)}", ld.loc(k))
        if "remove" in ld:   # (overrides of included nodes are merged before this: here nothing is left to remove)
            if not isinstance(ld["remove"], bool):
                err(f"node '{ld.get('id', '?')}': remove: expected true or false, got {ld['remove']!r}",
                    ld.loc("remove"))
            elif ld["remove"]:
                err(f"node '{ld.get('id', '?')}': remove: true only removes a node of an included graph, and "
                    f"this file includes none", ld.loc("remove"))
        nid = ld.get("id")
        if nid is None:
            err("node without 'id'", ld.where)
            continue
        if not isinstance(nid, str) or not ID_RE.match(nid):
            err(f"node id {nid!r}: use letters, digits, '_' and '-' (no dots)", ld.loc("id"))
            continue
        if nid in seen_ids:
            err(f"duplicate node id '{nid}' (first defined at {seen_ids[nid]})", ld.loc("id"))
            continue
        seen_ids[nid] = ld.loc("id")
        plugin = ld.get("plugin")
        cls = None
        if not isinstance(plugin, str):
            err(f"node '{nid}': missing 'plugin' (the component name, see `teletouch plugins`)", ld.where)
        else:
            info = registry.components.get(plugin)
            if info is None:
                err(f"node '{nid}': {registry.unknown_message(plugin)}", ld.loc("plugin"))
            else:
                cls = info.cls
        rate = ld.get("rate")
        if rate is None:   # not given, or `rate: null` (an override's: drop the included rate): the plugin's default
            rate = cls.default_rate if cls is not None else None
            if rate is None and cls is not None:
                if "rate" in ld:   # the null's line (an override's), not the node's (maybe an included file's)
                    err(f"node '{nid}': missing 'rate' (Hz); {plugin} has no default rate ('rate: null' asks for "
                        f"the plugin's default rate)", ld.loc("rate"))
                else:
                    err(f"node '{nid}': missing 'rate' (Hz); {plugin} has no default rate", ld.where)
        else:
            try:
                rate = parse_quantity(rate, "Hz")
                problem = rate_problem(rate)
                if problem:
                    raise ValueError(f"{problem}, got {ld.get('rate')!r}")
            except ValueError as exc:
                err(f"node '{nid}': rate: {exc}", ld.loc("rate"))
                rate = None
        on_fault = ld.get("on_fault")
        if on_fault is not None and on_fault not in FAULT_ACTIONS:
            err(f"node '{nid}': on_fault: expected 'stop' or 'degrade', got {on_fault!r}", ld.loc("on_fault"))
            on_fault = None
        isolate = ld.get("isolate", "none")
        if isolate not in ("none", "process"):
            err(f"node '{nid}': isolate: expected 'none' or 'process', got {isolate!r}", ld.loc("isolate"))
            isolate = "none"
        elif isolate == "process" and cls is not None and issubclass(cls, Device):
            err(f"node '{nid}': isolate: process is for sensors, estimators and controllers; a device ({plugin}) "
                f"stays in the runtime's process so it can always be driven to its safe state", ld.loc("isolate"))
            isolate = "none"
        priority = ld.get("priority")
        if priority is not None and (not isinstance(priority, int) or isinstance(priority, bool)
                                     or not 0 <= priority <= 99):
            err(f"node '{nid}': priority: expected an integer 0-99 (SCHED_FIFO priority of its thread under the "
                f"wall clock; 0 = normal scheduling), got {priority!r}", ld.loc("priority"))
            priority = None
        params = ld.get("params", {}) or {}
        if not isinstance(params, dict):
            err(f"node '{nid}': params must be a mapping of name: value", ld.loc("params"))
            params = {}
        pwhere = {k: params.loc(k) for k in params} if isinstance(params, LDict) else {}
        pwhere_default = ld.loc("params") if "params" in ld else ld.where
        nested = getattr(params, "nested_sets", {})
        spec = NodeSpec(id=nid, plugin=plugin if isinstance(plugin, str) else "", rate=rate,
                        params=_plain(params), inputs={}, on_fault=on_fault, where=ld.where, param_where=pwhere,
                        isolate=isolate, priority=priority, plugin_where=ld.loc("plugin"))
        if cls is not None:
            spec.cls = cls
            try:
                spec.params_obj = cls.Params.model_validate(spec.params)
            except ValidationError as exc:
                fields = list(cls.Params.model_fields)
                expanded = []
                hinted: set[str] = set()   # the parameters whose --set error has had its hint (_set_hint)
                for e in exc.errors():
                    if e["loc"] or e["type"] != "value_error":
                        expanded.append(e)
                        continue
                    # a model-level check: one problem per line, each led by its field name where it has one
                    for part in str(e.get("ctx", {}).get("error", e["msg"])).split("\n"):
                        head = part.split(":", 1)[0]
                        if head in fields and ": " in part:
                            expanded.append(dict(e, loc=(head,), msg=part.split(": ", 1)[1],
                                                 input=spec.params.get(head)))
                        else:
                            word = re.match(r"[A-Za-z_]\w*", part)
                            named = word.group(0) if word and word.group(0) in fields else None
                            err(f"node '{nid}': params of {plugin}: {part}",
                                pwhere.get(named, pwhere_default) if named else pwhere_default)
                # a check before the fields' (the units of every quantity, Params._parse_units) ends pydantic's
                # validation, so the unknown params it would have named are found here ('bitrate: 500k' hid 'dxl')
                if not any(e["type"] == "extra_forbidden" for e in exc.errors()):
                    known = set(fields) | {f.alias for f in cls.Params.model_fields.values() if f.alias}
                    expanded += [{"type": "extra_forbidden", "loc": (k,), "msg": "", "input": v}
                                 for k, v in spec.params.items() if k not in known]
                # ... and so are the other params' own problems ('latency: -1' beside 'amplitude: 2mm'): validated
                # again without the quantities that check refused
                expanded += _beside_bad_units(cls, spec.params)
                for e in expanded:
                    loc = [str(x) for x in e["loc"]]
                    fname = ".".join(loc) or "?"
                    w = pwhere.get(loc[0], pwhere_default) if loc else pwhere_default
                    if e["type"] == "extra_forbidden":
                        fields = list(cls.Params.model_fields)
                        err(f"node '{nid}': unknown param '{fname}' for {plugin}{_suggest(loc[0], fields)}; "
                            f"known: {', '.join(fields) or '(none)'}", w)
                    elif e["type"] == "missing":
                        err(f"node '{nid}': param '{fname}' is required by {plugin}", w)
                    else:
                        msg = e["msg"]
                        if msg.startswith("Value error, "):
                            msg = msg[len("Value error, "):]
                        msg = _unitless_quantity(cls, loc, e["type"], e.get("input")) or msg
                        msg += _bound_unit(cls, loc, e["type"])
                        blamed = (_blame_sets(cls, spec.params, loc[0], nested[loc[0]])
                                  if loc and loc[0] in nested else [])
                        if blamed:   # a --set inside the parameter made the error: it is named, not the file
                            if loc[0] not in hinted:   # once per parameter
                                hinted.add(loc[0])
                                msg += _set_hint(cls, spec.params, nid, loc[0], nested[loc[0]])
                            err(_set_error(nid, loc[0], spec.params.get(loc[0]), blamed, msg),
                                Location(" and ".join(f"--set {b[1]}" for b in blamed), None))
                        else:
                            err(f"node '{nid}': param '{fname}' = {e.get('input')!r}: {msg}", w)
            if clock_v == "sim" and cls.requires_wall_clock:
                err(f"node '{nid}': {plugin} needs the wall clock (real hardware or other processes in real time) "
                    f"and cannot run on the simulated clock; use --clock wall or a simulated plugin",
                    ld.loc("plugin"))
        # inputs
        ins = ld.get("inputs", {}) or {}
        if not isinstance(ins, dict):
            err(f"node '{nid}': inputs must be a mapping of port: node.port", ld.loc("inputs"))
            ins = {}
        for port, src in ins.items():
            iw = ins.loc(port) if isinstance(ins, LDict) else ld.loc("inputs")
            max_age = None
            if isinstance(src, dict):
                extra = [k for k in src if k not in ("from", "max_age")]
                if extra:
                    err(f"node '{nid}': input '{port}': unknown key '{extra[0]}'; expected 'from' and 'max_age'", iw)
                max_age_raw = src.get("max_age")
                src = src.get("from")
                if max_age_raw is not None:
                    try:
                        max_age = parse_quantity(max_age_raw, "s")
                        if not 0 < max_age <= MAX_AGE_LIMIT:   # `100` meant as ms kept a 100 s old sample in use
                            raise ValueError(f"expected a time > 0 s and at most {MAX_AGE_LIMIT:g} s (units are "
                                             f"allowed: 100ms), got {max_age_raw!r}")
                    except ValueError as exc:
                        err(f"node '{nid}': input '{port}': max_age: {exc}", iw)
            if not isinstance(src, str) or src.count(".") != 1:
                hint = (" (null unwires an input only in an override of an included graph's node; here, leave the "
                        "input out)" if src is None else "")
                err(f"node '{nid}': input '{port}': expected 'node.port', got {src!r}{hint}", iw)
                miswired.add((nid, str(port)))
                continue
            snode, sport = src.split(".")
            kept = getattr(ld, "kept_wires", {}).get(str(port)) == _place(iw)
            spec.inputs[str(port)] = WireSpec(str(port), snode, sport, max_age, iw, kept)
        nodes.append(spec)

    # wiring checks need every node
    by_id = {n.id: n for n in nodes}
    matched: list[tuple[NodeSpec, str, WireSpec, NodeSpec]] = []   # wires whose ports fit: their sizes are checked
    for n in nodes:
        if n.cls is None:
            continue
        for port, w in n.inputs.items():
            if port not in n.cls.inputs:
                # a wire kept from an included graph when an override changed the plugin: say how to drop it
                pw = n.plugin_where
                inherited = pw is not None and w.where.file is not None and pw.file != w.where.file
                hint = ""
                if inherited and str(pw.file).startswith("--set"):
                    hint = (f"; the wire comes from {w.where.file} and {pw.file} changed the plugin: write a graph "
                            f"that includes it, with the node's plugin and 'inputs: {{{port}: null}}' to unwire it")
                elif inherited and w.kept:   # (not a wire the override file wrote itself: a typo there)
                    hint = (f"; the wire comes from {w.where.file}: unwire it in the override with "
                            f"'inputs: {{{port}: null}}'")
                err(f"node '{n.id}': {n.plugin} has no input '{port}'{_suggest(port, n.cls.inputs)}; "
                    f"inputs: {', '.join(n.cls.inputs) or '(none)'}{hint}", w.where)
                continue
            src = by_id.get(w.node)
            if src is None:
                err(f"node '{n.id}': input '{port}' comes from unknown node '{w.node}'{_suggest(w.node, by_id)}",
                    w.where)
                continue
            if src.cls is None:
                continue
            if w.source_port not in src.cls.outputs:
                err(f"node '{n.id}': input '{port}': {src.plugin} node '{src.id}' has no output '{w.source_port}'"
                    f"{_suggest(w.source_port, src.cls.outputs)}; outputs: {', '.join(src.cls.outputs) or '(none)'}",
                    w.where)
                continue
            why = n.cls.inputs[port].accepts(src.cls.outputs[w.source_port])
            if why:
                if why.startswith("unit mismatch"):
                    why += _dimensionless_note(src, w.source_port, n, port)
                err(f"node '{n.id}': input '{port}' <- {w.node}.{w.source_port}: {why}", w.where)
            else:
                matched.append((n, port, w, src))
            if w.max_age is None:
                w.max_age = n.cls.inputs[port].max_age
        for port, p in n.cls.inputs.items():
            if p.required and port not in n.inputs and (n.id, port) not in miswired:
                err(f"node '{n.id}': required input '{port}' ({p.describe()}) of {n.plugin} is not wired", n.where)

    # each component's own wiring rules (Component.wiring_problems), e.g. a bridge port its topics do not carry
    consumed: dict[str, dict[str, Location]] = {}   # node -> its outputs that others read -> the first reading wire
    for n in nodes:
        for w in n.inputs.values():
            consumed.setdefault(w.node, {}).setdefault(w.source_port, w.where)
    for n in nodes:
        check = getattr(n.cls, "wiring_problems", None)
        if check is None or n.params_obj is None:
            continue
        read = consumed.get(n.id, {})
        try:
            problems = check(n.params_obj, set(n.inputs), set(read))
        except Exception as exc:   # a plugin's check must not hide the graph's other errors
            err(f"node '{n.id}': the wiring check of {n.plugin} failed: {type(exc).__name__}: {exc}", n.where)
            continue
        for port, why in sorted((problems or {}).items()):
            where = n.inputs[port].where if port in n.inputs else read.get(port, n.where)
            err(f"node '{n.id}': {why}", where)

    # what the nodes' parameters fix at their ports, compared at both ends of each wire: sizes (Component.port_shapes:
    # a camera's image size, a depth model's) and what the values are tied to (Component.port_sources: a depth model,
    # a force calibration made for one)
    for read, check, clash_of in ((_fixed_shapes, "port size check", _size_clash),
                                  (_port_sources, "port source check", _source_clash)):
        declared: dict[str, dict[str, tuple]] = {}
        for n in nodes:
            try:
                declared[n.id] = read(n)
            except Exception as exc:   # a plugin's check must not hide the graph's other errors
                err(f"node '{n.id}': the {check} of {n.plugin} failed: {type(exc).__name__}: {exc}", n.where)
                declared[n.id] = {}
        for n, port, w, src in matched:
            clash = clash_of(src, w.source_port, declared[src.id], n, port, declared[n.id])
            if clash:
                err(f"node '{n.id}': input '{port}' <- {w.node}.{w.source_port}: {clash}", w.where)

    if errors:
        raise GraphValidationError(errors)
    return GraphSpec(name=str(doc.get("name") or Path(file).stem), file=file, nodes=nodes, clock=clock_v,
                     duration=dur, faults=faults, description=str(doc.get("description") or ""),
                     realtime_priority=rt_prio, warnings=_isolation_warnings(nodes, clock_v, file))


def _declared(n: NodeSpec, method: str, what: str) -> list[tuple[str, Any, tuple]]:
    """What node ``n``'s classmethod ``method`` (port_shapes, port_sources) declares for its ports: (port, the Port,
    the entry) each, the entry a tuple (``what``, why) or (``what``, why, how) with why and how text; none where its
    plugin or parameters are unknown. TypeError or ValueError saying what is wrong with what the plugin returned: no
    dict, a name that is no port of it, an entry of another form."""
    check = getattr(n.cls, method, None)
    if n.cls is None or check is None or n.params_obj is None:
        return []
    got = check(n.params_obj)
    if not isinstance(got, dict):
        raise TypeError(f"returned {type(got).__name__}, expected a dict of port: ({what}, why)")
    out = []
    for port, entry in got.items():
        declared = n.cls.inputs.get(port) or n.cls.outputs.get(port)
        if declared is None:
            ports = [*n.cls.inputs, *n.cls.outputs]
            raise ValueError(f"'{port}' is not a port of {n.plugin}{_suggest(str(port), ports)}; ports: "
                             f"{', '.join(ports) or '(none)'}")
        if (not isinstance(entry, tuple) or len(entry) not in (2, 3)
                or not all(isinstance(t, str) for t in entry[1:])):
            raise TypeError(f"port '{port}': expected ({what}, why) or ({what}, why, how), got {entry!r}")
        out.append((port, declared, entry if len(entry) == 3 else (*entry, "")))
    return out


def _fixed_shapes(n: NodeSpec) -> dict[str, tuple[tuple[int | None, ...], str, str]]:
    """Node ``n``'s :meth:`Component.port_shapes` as {port: (shape, why, how)} (``how`` "" where not given); none
    where its plugin or parameters are unknown. TypeError or ValueError saying what is wrong with what the plugin
    returned (:func:`_declared`; a shape that is no tuple of sizes or does not fit its port)."""
    out = {}
    for port, declared, (shape, why, how) in _declared(n, "port_shapes", "shape"):
        if not isinstance(shape, tuple) or not all(
                d is None or (isinstance(d, int) and not isinstance(d, bool) and d >= 0) for d in shape):
            raise TypeError(f"port '{port}': shape {shape!r}, expected a tuple of sizes (int >= 0 or None)")
        if declared.shape is not None and shapes_differ(declared.shape, shape):
            raise ValueError(f"port '{port}': shape {shape!r} does not fit the port ({declared.describe()})")
        out[port] = (shape, why, how)
    return out


def _size_text(shape: tuple[int | None, ...], other: tuple[int | None, ...]) -> tuple[str, str]:
    """``shape`` for a message, against ``other``, and what it counts: ("320x240", "rows x cols") where only the rows
    and cols differ (an image's), else ("320x240x3", "shape"); "*" for any size."""
    dims = ["*" if d is None else str(d) for d in shape]
    if len(shape) >= 2 and len(shape) == len(other) and shape[2:] == other[2:]:
        return f"{dims[0]}x{dims[1]}", "rows x cols"
    return "x".join(dims) or "scalar", "shape"


def _size_clash(src: NodeSpec, out_port: str, src_fixed: dict[str, tuple], dst: NodeSpec, in_port: str,
                dst_fixed: dict[str, tuple]) -> str | None:
    """None if the shapes that the two ends of a wire fix (their parameters' :meth:`Component.port_shapes`, else
    their ports') can be one; else the error: both nodes, both sizes and what fixes each, and what to do."""
    if out_port not in src_fixed and in_port not in dst_fixed:
        return None   # the ports' own shapes: Port.accepts has compared them
    ends = []
    for node, fixed, name, port in ((src, src_fixed, out_port, src.cls.outputs[out_port]),
                                    (dst, dst_fixed, in_port, dst.cls.inputs[in_port])):
        if name in fixed:
            ends.append((node, *fixed[name]))
        elif port.shape is None:
            return None   # any shape
        else:
            ends.append((node, port.shape, "its port", ""))
    (_, a, a_why, _), (_, b, b_why, _) = ends
    if not shapes_differ(a, b):
        return None
    (a_size, a_what), (b_size, b_what) = _size_text(a, b), _size_text(b, a)
    fixes = [f"on node '{node.id}', {how}" for node, _, _, how in (ends[1], ends[0]) if how]
    todo = "; or ".join(fixes) if fixes else f"change what fixes the size of node '{src.id}' or of node '{dst.id}'"
    return (f"sizes differ: node '{src.id}' ({src.plugin}) sends {a_size} ({a_what}; fixed by {a_why}) and node "
            f"'{dst.id}' ({dst.plugin}) takes {b_size} ({b_what}; fixed by {b_why}); to make them match: {todo}")


def _port_sources(n: NodeSpec) -> dict[str, tuple[str, str, str]]:
    """Node ``n``'s :meth:`Component.port_sources` as {port: (identity, why, how)} (``how`` "" where not given); none
    where its plugin or parameters are unknown. TypeError or ValueError saying what is wrong with what the plugin
    returned (:func:`_declared`; an identity that is no text, or empty)."""
    out = {}
    for port, _, (identity, why, how) in _declared(n, "port_sources", "identity"):
        if not isinstance(identity, str) or not identity:
            raise TypeError(f"port '{port}': identity {identity!r}, expected a non-empty string")
        out[port] = (identity, why, how)
    return out


def _source_clash(src: NodeSpec, out_port: str, src_tied: dict[str, tuple[str, str, str]], dst: NodeSpec,
                  in_port: str, dst_tied: dict[str, tuple[str, str, str]]) -> str | None:
    """None if the identities that the two ends of a wire declare for their ports (their parameters'
    :meth:`Component.port_sources`) are one, or an end declares none; else the error: both nodes, both identities and
    what ties each, and what to do."""
    a_tied, b_tied = src_tied.get(out_port), dst_tied.get(in_port)
    if a_tied is None or b_tied is None or a_tied[0] == b_tied[0]:
        return None
    (a, a_why, a_how), (b, b_why, b_how) = a_tied, b_tied
    fixes = [f"on node '{node.id}', {how}" for node, how in ((dst, b_how), (src, a_how)) if how]
    todo = "; or ".join(fixes) if fixes else f"change what ties node '{src.id}' or node '{dst.id}'"
    return (f"sources differ: node '{src.id}' ({src.plugin}) sends values tied to {a!r} ({a_why}) and "
            f"node '{dst.id}' ({dst.plugin}) takes values tied to {b!r} ({b_why}); to make them match: {todo}")


def _refused(cls: type[Component], params: dict[str, Any], name: str, value: Any) -> bool:
    """Whether ``cls``'s parameters refuse parameter ``name`` given ``value`` (``_MISSING``: left out), the others as
    in ``params``; a validator raising what pydantic does not turn into an error (TypeError) refuses it too."""
    trial = {k: v for k, v in params.items() if k != name}
    if value is not _MISSING:
        trial[name] = value
    try:
        cls.Params.model_validate(trial)
    except ValidationError as exc:
        return any(tuple(e["loc"][:1]) == (name,) for e in exc.errors())
    except Exception:   # (a plugin's validator raising TypeError on a value it never expected)
        return True
    return False


def _blame_sets(cls: type[Component], params: dict[str, Any], name: str,
                nested: _NestedSets) -> list[tuple[list[str], str, Any]]:
    """The --sets inside parameter ``name`` that make it refused: none where the file's own value
    (``nested.original``) is refused too (the error is the file's); else those refused on their own, each applied to
    the file's value, or all of them where only together they are."""
    if _refused(cls, params, name, nested.original):
        return []
    return [s for s in nested.items
            if _refused(cls, params, name, _with_set(nested.original, s[0], s[2]))] or list(nested.items)


def _set_hint(cls: type[Component], params: dict[str, Any], nid: str, name: str, nested: _NestedSets) -> str:
    """What to write, after the error of parameter ``name`` that its --sets inside it (``nested``) made, where they
    did not make what was meant. The value before them is not a mapping (the file's, an earlier --set's or the
    default, e.g. the intent 'hold'): they made a mapping of only what they give; where the parameter takes that name
    as ``type`` (``{type: hold}``), it says to give it: ``--set leader.intent.type=hold``; a number or a list: it
    says what they made. The value before is a mapping whose other keys refuse what the --sets give, which they accept
    alone (another intent's type and fields): it says to give the whole value in one --set. Else nothing. A --set
    it suggests is quoted for a shell (shlex.quote: a value may hold a space or a quote) and pastes as it is."""
    made = params.get(name)
    if not isinstance(made, dict):
        return ""
    before = nested.original
    if isinstance(before, dict):
        alone: dict[str, Any] = {}
        for keys, _, value in nested.items:
            alone = _with_set(alone, keys, value)
        kept = [str(k) for k in before if k not in alone]
        if not kept or _refused(cls, params, name, alone):
            return ""
        return (f"; the --set changes only what it names in {name}, the others stay ({', '.join(kept)}); give the "
                f"whole value: --set {shlex.quote(f'{nid}.{name}={_flow(alone)}')}")
    if before is _MISSING:
        field_info = cls.Params.model_fields.get(name)
        if field_info is None or field_info.is_required():
            what = f"{name} is not given in the file"
        else:
            before = field_info.get_default(call_default_factory=True)
            what = f"{name} is not given in the file: its default {before!r} is not a mapping"
    else:
        what = f"{name} was {before!r}, not a mapping"
    hint = f"; {what}, so the --set made it {_flow(made)} alone"
    if not isinstance(before, str):   # (a number, a list: nothing inside it to set)
        return hint
    if "type" not in made and not _refused(cls, params, name, {"type": before}):
        return hint + f"; give its type with it: --set {shlex.quote(f'{nid}.{name}.type={before}')}"
    return ""   # a name, and the --sets give the type (or it is no type): the error says it


def _flow(value: Any) -> str:
    """``value`` as a person writes it in a --set: YAML's flow style (``{type: hold, opening: 10mm}``)."""
    import yaml

    try:
        return yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=2**16).strip()
    except yaml.YAMLError:
        return repr(value)


def _beside_bad_units(cls: type, params: dict[str, Any]) -> list[dict[str, Any]]:
    """The errors of the parameters beside those whose unit the check before the fields' refused
    (``Params._parse_units``: pydantic validates no field after it), as pydantic gives them, each led by its field:
    the parameters validated again without those. Not the unknown parameters (named already), and not what the
    refused ones' absence makes (a required one "missing"; a check of the whole model that their defaults fail)."""
    bad = set()
    for fname, f in cls.Params.model_fields.items():
        key, unit = f.alias or fname, _field_unit(f)
        if unit and isinstance(params.get(key), str):
            try:
                parse_quantity(params[key], unit)
            except ValueError:
                bad.add(key)
    if not bad:
        return []
    try:
        cls.Params.model_validate({k: v for k, v in params.items() if k not in bad})
    except ValidationError as exc:
        errors = exc.errors()
    except Exception:   # a plugin's own check that fails on the values left: the first errors stand
        return []
    else:
        return []
    fields = list(cls.Params.model_fields)
    out = []
    for e in errors:
        if e["loc"]:
            if str(e["loc"][0]) not in bad and e["type"] != "extra_forbidden":
                out.append(e)
        elif e["type"] == "value_error":   # a check of the whole (booleans given for numbers), one line a field
            for part in str(e.get("ctx", {}).get("error", e["msg"])).split("\n"):
                head = part.split(":", 1)[0]
                if head in fields and head not in bad and part.endswith(_BOOLEAN_NUMBER):
                    out.append(dict(e, loc=(head,), msg=part.split(": ", 1)[1], input=params.get(head)))
    return out


def _dimensionless_note(src: NodeSpec, out_port: str, dst: NodeSpec, in_port: str) -> str:
    """What a '1' in a unit mismatch means: the port that shows it declares no unit (``Port(..., unit="")``, the
    default), so its values are dimensionless; the mismatch reads '1' -> 'N' otherwise, with nothing saying so."""
    assert src.cls is not None and dst.cls is not None
    notes = []
    for port, side, n in ((src.cls.outputs[out_port], f"output '{out_port}'", src),
                          (dst.cls.inputs[in_port], f"input '{in_port}'", dst)):
        if port.unit == "":
            notes.append(f"{n.plugin}'s {side} declares no unit")
        elif port.unit == "1":
            notes.append(f"{n.plugin}'s {side} is declared dimensionless")
    return f" ('1' is dimensionless: {' and '.join(notes)})" if notes else ""


def _unitless_quantity(cls: type, loc: list[str], kind: str, value: Any) -> str | None:
    """The message for a string with a unit (``amplitude: 2N``) given to a top-level number parameter whose schema
    names no unit, in place of pydantic's "unable to parse string as a number": such a parameter takes a plain
    number (in the unit its plugin documents); None where that is not the case."""
    if kind not in ("float_parsing", "int_parsing") or not isinstance(value, str) or len(loc) != 1:
        return None
    f = cls.Params.model_fields.get(loc[0])
    if f is None or _field_unit(f) is not None:
        return None
    try:
        float(value)
        return None   # (a plain number that did not parse as an int: pydantic's message says it)
    except ValueError:
        pass
    try:
        parse_quantity(value)
    except ValueError:
        return None   # not a quantity with a unit that teletouch knows either: pydantic's message stands
    described = f" (its description: {f.description!r})" if f.description else ""
    return (f"this param takes no unit ({cls.name} declares none for it): expected a plain number, in the unit the "
            f"plugin documents for it{described}")


def _bound_unit(cls: type, loc: list[str], kind: str) -> str:
    """" N" after pydantic's "Input should be less than or equal to 8" for a top-level field with a unit: a bound
    is in SI, and the person who typed the value may have thought in another unit."""
    if kind not in ("less_than", "less_than_equal", "greater_than", "greater_than_equal") or len(loc) != 1:
        return ""
    f = cls.Params.model_fields.get(loc[0])
    unit = _field_unit(f) if f is not None else None
    return f" {unit}" if unit else ""


def _with_set(original: Any, keys: list[str], value: Any) -> dict[str, Any]:
    """``original`` (a parameter's value) with ``value`` set at ``keys`` inside it, as :func:`apply_sets` sets it
    (a value that is not a mapping is replaced by one)."""
    out = copy.deepcopy(original) if isinstance(original, dict) else {}
    target = out
    for k in keys[:-1]:
        if not isinstance(target.get(k), dict):
            target[k] = {}
        target = target[k]
    target[keys[-1]] = value
    return out


def _set_error(nid: str, name: str, current: Any, blamed: list[tuple[list[str], str, Any]], msg: str) -> str:
    """The message of an error in parameter ``name`` laid on the --sets ``blamed``: the value the --set gave (and
    where in the parameter), or the parameter's whole value where several --sets made it together."""
    if len(blamed) == 1:
        keys, _, value = blamed[0]
        return f"node '{nid}': param '{'.'.join([name, *keys])}' = {value!r}: {msg}"
    return f"node '{nid}': param '{name}' = {current!r}: {msg}"


def _isolation_warnings(nodes: list[NodeSpec], clock: str, file: str) -> list[str]:
    """A node with ``isolate: process`` that shares its rate with a device node: under the wall clock the nodes of
    one rate run in one thread (see runtime.Runtime._run_wall), so each isolated step holds that thread, and with it
    the devices' steps, until the child process answers (the watchdog faults the node past ``faults.watchdog``).
    A warning, not an error: the graph runs. None under the simulated clock, where an isolated node runs inline."""
    if clock != "wall":
        return []
    all_devices = [d for d in nodes if d.cls is not None and issubclass(d.cls, Device)]
    device_rates = {d.rate for d in all_devices}
    out = []
    for n in nodes:
        if n.isolate != "process" or n.rate is None:
            continue
        devices = [d for d in all_devices if d.rate == n.rate]
        if not devices:
            continue
        names = ", ".join(f"'{d.id}'" for d in devices)
        free = next((r for r in (n.rate - 1, n.rate + 1, n.rate * 0.9, n.rate * 1.1)
                     if r > 0 and r not in device_rates), None)
        hint = f" (e.g. rate: {free:g})" if free is not None else ""
        where = n.where if n.where.file else Location(file, n.where.line)
        what = "device node" if len(devices) == 1 else "device nodes"
        out.append(f"{where}: node '{n.id}' (isolate: process) shares its rate, {n.rate:g} Hz, with {what} {names}: "
                   f"under the wall clock the nodes of one rate run in one thread, so each step of '{n.id}' holds up "
                   f"the steps of {names} until its process answers (past faults.watchdog it faults and they are "
                   f"made safe); give node '{n.id}' a rate of its own, one no device uses{hint}")
    return out


# ------------------------------------------------------------------------------------------------ JSON schema
#: the keys of a parameter's schema that describe it, not its value (kept outside the anyOf of a quantity)
_SCHEMA_META = ("title", "description", "default", "unit", "examples", "deprecated")


def _quantities_take_text(schema: Any) -> Any:
    """``schema`` (a parameter model's JSON Schema) with every field that has a unit also taking a string: a graph
    may write a quantity with its unit ("20mm", "2Hz"), which the parameters convert (teletouch.units); the schema
    said "type": "number" only, so an editor flagged every unit written in the examples."""
    if isinstance(schema, list):
        return [_quantities_take_text(v) for v in schema]
    if not isinstance(schema, dict):
        return schema
    out = {k: _quantities_take_text(v) for k, v in schema.items()}
    unit = out.get("unit")
    if isinstance(unit, str) and ("type" in out or "anyOf" in out):
        value = {k: v for k, v in out.items() if k not in _SCHEMA_META}
        text = {"type": "string", "description": f"a quantity with its unit, in {unit} or one convertible to it"}
        out = {**{k: v for k, v in out.items() if k in _SCHEMA_META}, "anyOf": [value, text]}
    return out


def graph_json_schema(registry: Any = None) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12) of the graph format, with each installed plugin's parameters."""
    if registry is None:
        from .registry import default_registry

        registry = default_registry()
    number_or_qty = {"anyOf": [{"type": "number"}, {"type": "string"}]}
    wire = {"anyOf": [
        {"type": "string", "pattern": r"^[A-Za-z_][A-Za-z0-9_-]*\.[A-Za-z_][A-Za-z0-9_]*$"},
        {"type": "object", "properties": {"from": {"type": "string"}, "max_age": number_or_qty},
         "required": ["from"], "additionalProperties": False},
        {"type": "null", "description": "in an override of an included node: unwire this input"}]}
    node: dict[str, Any] = {
        "type": "object",
        "properties": {
            "id": {"type": "string", "pattern": ID_RE.pattern},
            "plugin": {"type": "string", "enum": sorted(registry.components)},
            "rate": {**number_or_qty, "description": "Hz"},
            "params": {"type": "object"},
            "inputs": {"type": "object", "additionalProperties": wire},
            "on_fault": {"enum": list(FAULT_ACTIONS)},
            "priority": {"type": "integer", "minimum": 0, "maximum": 99,
                         "description": "SCHED_FIFO priority of this node's thread (wall clock)"},
            "isolate": {"enum": ["none", "process"],
                        "description": "run this node in a process of its own (wall clock)"},
            "remove": {"type": "boolean"},
            "description": {"type": "string"},
        },
        "required": ["id"],
        "additionalProperties": False,
        "allOf": [],
    }
    defs: dict[str, Any] = {}
    for name, info in sorted(registry.components.items()):
        ps = _quantities_take_text(info.cls.Params.model_json_schema(ref_template="#/$defs/{model}"))
        for k, v in ps.pop("$defs", {}).items():
            defs[k] = v
        node["allOf"].append({"if": {"properties": {"plugin": {"const": name}}, "required": ["plugin"]},
                              "then": {"properties": {"params": ps}}})
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "teletouch graph",
        "type": "object",
        "properties": {
            "name": {"type": "string"},
            "description": {"type": "string"},
            "include": {"anyOf": [{"type": "string"}, {"type": "array", "items": {"type": "string"}}]},
            "clock": {"enum": list(CLOCKS)},
            "duration": {**number_or_qty, "description": "s"},
            "realtime_priority": {"type": "integer", "minimum": 0, "maximum": 99,
                                  "description": "SCHED_FIFO priority of threads running at >= 200 Hz (0: off)"},
            "faults": {"type": "object", "properties": {
                "on_fault": {"enum": list(FAULT_ACTIONS)},
                "max_overruns": {"type": "integer", "minimum": 0},
                "startup_grace": number_or_qty, "watchdog": number_or_qty, "safe_timeout": number_or_qty},
                "additionalProperties": False},
            "nodes": {"type": "array", "items": node},
        },
        "patternProperties": {"^x-": {"description": "ignored: a place for YAML anchors"}},
        "required": ["nodes"],
        "additionalProperties": False,
    }
    if defs:
        schema["$defs"] = defs
    return schema


def dump_schema(registry: Any = None) -> str:
    return json.dumps(graph_json_schema(registry), indent=2, default=str)


__all__ = ["GraphSpec", "NodeSpec", "WireSpec", "FaultPolicy", "load_graph", "load_graph_text", "load_raw",
           "apply_sets", "build_spec", "graph_json_schema", "dump_schema"]
