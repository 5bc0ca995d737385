"""Plugin discovery and the component registry (pluggy).

Components come from modules registered under the entry-point group ``teletouch``. Built-in plugins use the same
group as third-party ones. Environment variables (like pytest's):

- ``TELETOUCH_DISABLE_PLUGIN_AUTOLOAD=1``: do not load entry points (tests register what they need).
- ``TELETOUCH_BLOCK=a,b``: skip the named plugins (entry-point names or distribution names; separated by ',' or
  ``os.pathsep``); a blocked plugin is not even imported. ``TELETOUCH_BLOCK_PLUGINS`` (the earlier name) is still
  read, and ``teletouch --block NAME`` adds to both. A name that matches nothing is reported, naming where it was
  set (:meth:`Registry.unknown_blocked`): a typo must not leave running a plugin the user meant to switch off.
  :meth:`Registry.block_origin` tells where each block came from.
- ``TELETOUCH_PLUGINS=pkg.mod1,pkg.mod2``: import and register these modules too (works with autoload off).

A plugin that fails to import (or raises, even ``SystemExit``), declares a hook that does not exist, leaves a
``teletouch_*`` function without ``@teletouch.hookimpl``, or provides a component that breaks the rules of
:func:`check_component` is recorded with its error and skipped; the others still load. Two plugins that provide a
component with the same name (or two distributions that declare the same plugin name) are refused: the name is kept
by neither, the conflict names both origins, and `teletouch plugins` and any graph that uses the name say how to
resolve it. What plugins print while they load goes to stderr, so ``--json`` output stays parseable.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import os
import re
import sys
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Iterable

import pluggy
from pydantic import BaseModel

from . import hookspecs
from .component import MAX_RATE, MIN_RATE, NAME_RE, Component, Device, Kind, Params, Port, rate_problem
from .errors import DuplicateComponentError, PluginError, UnknownComponentError, exception_line, note_plugin_module

GROUP = "teletouch"
ENV_DISABLE = "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD"
ENV_BLOCK = "TELETOUCH_BLOCK"
ENV_BLOCK_OLD = "TELETOUCH_BLOCK_PLUGINS"   # the earlier name of ENV_BLOCK, still read
ENV_PLUGINS = "TELETOUCH_PLUGINS"
PLUGIN_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: the distribution of teletouch itself: its entry points are the built-in plugins
BUILTIN_DISTRIBUTION = "teletouch"
#: the keys every ``teletouch_discover_devices`` entry has (see :mod:`teletouch.hookspecs`)
DEVICE_KEYS = ("kind", "id", "path")


@dataclass
class PluginRecord:
    name: str
    distribution: str
    version: str
    module: str
    error: str | None = None
    blocked: bool = False
    components: list[str] = field(default_factory=list)
    hooks: list[str] = field(default_factory=list)
    #: names of the components it offered when it was refused (so a graph naming one hears why it is missing)
    offered: list[str] = field(default_factory=list)

    @property
    def origin(self) -> str:
        """``distribution version`` as a person reads it, for messages to put in parentheses: a stand-in name that
        has its own (``(TELETOUCH_PLUGINS)``, ``(registered)``) loses them there."""
        return _origin(self.distribution, self.version)


def _origin(distribution: str, version: str) -> str:
    """:attr:`PluginRecord.origin` of a plugin from ``distribution`` at ``version``."""
    text = f"{distribution} {version}".strip()
    return text[1:-1] if text.startswith("(") and text.endswith(")") else text


@dataclass(frozen=True)
class ComponentInfo:
    cls: type[Component]
    plugin: str
    distribution: str
    version: str

    @property
    def name(self) -> str:
        return self.cls.name

    @property
    def kind(self) -> str:
        return self.cls.kind.value

    @property
    def origin(self) -> str:
        """As :attr:`PluginRecord.origin`: ``distribution version``, for messages to put in parentheses."""
        return _origin(self.distribution, self.version)


def _truthy(value: str | None) -> bool:
    return bool(value) and value.strip().lower() not in ("0", "false", "no", "off", "")


def _split(value: str | None) -> list[str]:
    return [v.strip() for v in (value or "").split(",") if v.strip()]


def split_names(value: str | None) -> list[str]:
    """Plugin names in a block list: separated by ',' or ``os.pathsep`` (as PATH-like variables are), blanks
    dropped."""
    return [v.strip() for v in re.split(f"[,{re.escape(os.pathsep)}]", value or "") if v.strip()]


def block_source(setting: str) -> str:
    """Where a block setting comes from, as `teletouch plugins` reports it: command line, environment or caller."""
    if setting.startswith("--"):
        return "command line"
    if setting in (ENV_BLOCK, ENV_BLOCK_OLD):
        return "environment"
    return "caller"


def _one_line(text: str) -> str:
    """Error text on one line (pluggy's validation messages span three)."""
    return "; ".join(part.strip() for part in str(text).splitlines() if part.strip())


def _error_line(exc: BaseException) -> str:
    if isinstance(exc, PluginError):   # our own check: the message says it all, the registry's line is noise
        return _one_line(str(exc))
    if isinstance(exc, SystemExit):
        return f"SystemExit({exc.code!r}) raised while loading (a plugin must not exit the process)"
    return _one_line(exception_line(exc))


def _import_listed(modname: str) -> Any:
    """A module named in TELETOUCH_PLUGINS, imported; one Python cannot find (itself or its package: not a missing
    dependency of a module that was found) is a PluginError saying how to make it findable: the no-install route
    needs the module's folder on Python's path."""
    try:
        return importlib.import_module(modname)
    except ModuleNotFoundError as exc:
        if exc.name != modname.partition(".")[0]:   # (a dependency, or a submodule of a package that was found:
            raise                                    # not a matter of Python's path)
        what = (f"the package {exc.name}" if "." in modname else
                f"{modname}.py (or the package {modname})")
        raise PluginError(f"{type(exc).__name__}: {exc}: {ENV_PLUGINS} imports a module without installing it only "
                          f"from a folder on Python's path: put the folder that holds {what} on PYTHONPATH "
                          f"(PYTHONPATH=/path/to/that/folder), or install its package (pip install -e .)") from None


def _quiet_stdout() -> Any:
    """While plugins load, what they print goes to stderr: stdout carries `--json` output."""
    return contextlib.redirect_stdout(sys.stderr)


class Registry:
    """Holds the loaded plugins and the components they provide."""

    def __init__(self, *, autoload: bool | None = None, blocked: Iterable[str] | None = None,
                 extra_modules: Iterable[str] | None = None, blocked_setting: str = "Registry(blocked=...)"):
        """``blocked`` adds names to those of the environment; ``blocked_setting`` is how reports name where they
        came from (``teletouch`` passes ``--block``). A string is a list as the environment writes it (``"a,b"``), as
        ``extra_modules`` is: iterated, it would block single letters and leave the plugin loaded."""
        if isinstance(blocked, str):
            blocked = split_names(blocked)
        if isinstance(extra_modules, str):
            extra_modules = _split(extra_modules)
        self.pm = pluggy.PluginManager(GROUP)
        self.pm.add_hookspecs(hookspecs)
        self.plugins: dict[str, PluginRecord] = {}
        self.components: dict[str, ComponentInfo] = {}
        #: component name -> every provider, for names two plugins both provide (refused: in no one's hands)
        self.conflicts: dict[str, list[ComponentInfo]] = {}
        #: every entry-point name and distribution name seen while loading (blocked or not): for typo checks
        self.known_names: set[str] = set()
        #: the plugins given to :meth:`register` (tests, notebooks: not loaded, so a block does not apply to them)
        self.registered: set[str] = set()
        env = os.environ
        self.autoload = (not _truthy(env.get(ENV_DISABLE))) if autoload is None else autoload
        #: why installed plugins are not loaded (for messages): the environment variable, or the caller's choice
        self._no_autoload_why = (f"{ENV_DISABLE} is set" if autoload is None else
                                 "this registry was made with autoload=False: only the modules given to it load")
        #: blocked name -> the settings that block it (``TELETOUCH_BLOCK``, ``--block``, ...), in the order read
        self.block_settings: dict[str, list[str]] = {}
        for setting, names in [(ENV_BLOCK, split_names(env.get(ENV_BLOCK))),
                               (ENV_BLOCK_OLD, split_names(env.get(ENV_BLOCK_OLD))),
                               (blocked_setting, [str(n).strip() for n in blocked or () if str(n).strip()])]:
            for n in names:
                where = self.block_settings.setdefault(n, [])
                if setting not in where:
                    where.append(setting)
        self.blocked = set(self.block_settings)
        self._extra = _split(env.get(ENV_PLUGINS)) + list(extra_modules or ())

    # loading ---------------------------------------------------------------------------------------------------
    def load(self) -> "Registry":
        if self.autoload:
            self.load_entrypoints()
        for modname in self._extra:
            self.known_names.add(modname)
            self._load_one(modname, modname, lambda m=modname: _import_listed(m), "(TELETOUCH_PLUGINS)", "")
        return self

    def load_entrypoints(self) -> None:
        groups: dict[str, list[Any]] = {}
        for ep in metadata.entry_points(group=GROUP):
            dist = ep.dist.name if ep.dist is not None else "?"
            version = ep.dist.version if ep.dist is not None else "?"
            self.known_names.update((ep.name, dist))
            same = groups.setdefault(ep.name, [])
            if not any(d == dist and e.value == ep.value for e, d, _ in same):  # editable + metadata on path
                same.append((ep, dist, version))
        for name in sorted(groups):
            found = groups[name]
            live = [f for f in found if f[1] not in self.blocked]
            if name in self.blocked or not live:
                ep, dist, version = found[0]
                self.plugins[name] = PluginRecord(name=name, distribution=", ".join(f[1] for f in found),
                                                  version=version if len(found) == 1 else "", module=ep.value,
                                                  blocked=True)
            elif len(live) > 1:
                origins = " and ".join(f"'{d}' {v} ({e.value})" for e, d, v in live)
                self.plugins[name] = PluginRecord(
                    name=name, distribution=", ".join(d for _, d, _ in live), version="",
                    module=", ".join(e.value for e, _, _ in live),
                    error=f"plugin name '{name}' is declared by the distributions {origins}; neither is loaded: "
                          f"uninstall one or block one by its distribution name, e.g. "
                          f"{ENV_BLOCK}={live[-1][1]}")
            else:
                ep, dist, version = live[0]
                self._load_one(name, ep.value, ep.load, dist, version)

    def _load_one(self, name: str, value: str, loader: Any, dist: str, version: str) -> None:
        if name in self.plugins:
            prev = self.plugins[name]
            if prev.distribution == dist and prev.module == value:
                return
            self.plugins[f"{name} ({dist})"] = PluginRecord(
                name=f"{name} ({dist})", distribution=dist, version=version, module=value,
                error=f"plugin name '{name}' is already taken by '{prev.distribution}' ({prev.module}); "
                      f"this one is not loaded")
            return
        rec = PluginRecord(name=name, distribution=dist, version=version, module=value)
        self.plugins[name] = rec
        if name in self.blocked or dist in self.blocked:
            rec.blocked = True
            return
        if not PLUGIN_NAME_RE.match(name):
            rec.error = (f"plugin name {name!r} is not loaded: use letters, digits, '-', '_' and '.' (the names "
                         f"entry points should use), so that {ENV_BLOCK}=NAME,NAME can name it")
            return
        try:
            with _quiet_stdout():
                obj = loader()
        except (Exception, SystemExit) as exc:  # a broken plugin is reported, not fatal
            rec.error = _error_line(exc)
            return
        self._register(obj, rec, strict=False)

    def register(self, plugin: Any, name: str | None = None, *, distribution: str = "(registered)",
                 version: str = "", _record: PluginRecord | None = None) -> PluginRecord:
        """Register a plugin object/module directly (tests, notebooks). Returns its record; a plugin that breaks the
        rules has ``record.error`` set and provides nothing. A component name that is already taken raises
        :class:`DuplicateComponentError` naming both origins."""
        name = name or getattr(plugin, "__name__", None) or repr(plugin)
        rec = _record
        if rec is None:
            if name in self.plugins:
                raise PluginError(f"a plugin named '{name}' is already registered")
            rec = PluginRecord(name=name, distribution=distribution, version=version,
                               module=getattr(plugin, "__name__", repr(plugin)))
            self.plugins[name] = rec
            self.registered.add(name)
        return self._register(plugin, rec, strict=_record is None)

    def register_builtins(self, skip: Iterable[str] = ()) -> list[PluginRecord]:
        """Register teletouch's own plugins (the entry points of its distribution, but those named in ``skip``) as
        :meth:`register` does, whatever is blocked or installed beside them: what a test that needs them holds
        (``make_registry(..., builtins=True)``). One that fails to import is recorded with its error."""
        eps: dict[str, Any] = {}
        for ep in metadata.entry_points(group=GROUP):
            if ep.dist is not None and ep.dist.name == BUILTIN_DISTRIBUTION and ep.name not in skip:
                eps.setdefault(ep.name, ep)
        out = []
        for name, ep in sorted(eps.items()):
            version = ep.dist.version if ep.dist is not None else ""
            try:
                with _quiet_stdout():
                    module = ep.load()
            except (Exception, SystemExit) as exc:
                rec = PluginRecord(name=name, distribution=BUILTIN_DISTRIBUTION, version=version, module=ep.value,
                                   error=_error_line(exc))
                self.plugins[name] = rec
                out.append(rec)
                continue
            out.append(self.register(module, name=name, distribution=BUILTIN_DISTRIBUTION, version=version))
        return out

    def _register(self, plugin: Any, rec: PluginRecord, *, strict: bool) -> PluginRecord:
        name = rec.name
        note_plugin_module(getattr(plugin, "__module__", None) or rec.module)   # its lines are a plugin's in faults
        loaded_as = self.pm.get_name(plugin) if self.pm.is_registered(plugin) else None
        if loaded_as is not None and rec.distribution == "(TELETOUCH_PLUGINS)":
            # a module named in TELETOUCH_PLUGINS that its installed entry point has loaded already (the doc's "try it
            # without installing", then `pip install -e .`): nothing to add, not a failure (pluggy's "already
            # registered under a different name" and the whole plugin list were printed as one)
            del self.plugins[name]
            return rec
        if loaded_as is not None:
            rec.error = f"this module is loaded already, as plugin '{loaded_as}'"
            return rec
        try:
            self.pm.register(plugin, name=name)
        except Exception as exc:
            rec.error = _error_line(exc)
            return rec
        try:
            rec.hooks = _check_hooks(self.pm, plugin)
            found = self._call_components(name)
            rec.offered = [c.name for c in found if isinstance(getattr(c, "name", None), str)]
            seen: dict[str, type[Component]] = {}
            for cls in found:
                check_component(cls)
                if cls.name in seen and seen[cls.name] is not cls:
                    raise PluginError(f"provides two components named '{cls.name}': {seen[cls.name].__qualname__} "
                                      f"and {cls.__qualname__}")
                seen[cls.name] = cls
        except (Exception, SystemExit) as exc:
            rec.error = _error_line(exc)
            rec.hooks = []
            self.pm.unregister(name=name)
            return rec
        infos = [ComponentInfo(cls, rec.name, rec.distribution, rec.version) for cls in seen.values()]
        if strict:
            for info in infos:
                other = self.components.get(info.name)
                taken = [other] if other is not None and other.cls is not info.cls else []
                taken = self.conflicts.get(info.name, taken)
                if taken:
                    self.pm.unregister(name=name)
                    rec.error = f"duplicate component '{info.name}'"
                    raise DuplicateComponentError(self._conflict_message(info.name, [*taken, info]))
        for info in infos:
            cls = info.cls
            if cls.name in self.conflicts:
                self.conflicts[cls.name].append(info)
                continue
            other = self.components.get(cls.name)
            if other is not None and other.cls is not cls:
                # neither keeps the name: which one a graph got would depend on the order of installation
                del self.components[cls.name]
                self.plugins[other.plugin].components.remove(cls.name)
                self.conflicts[cls.name] = [other, info]
                continue
            self.components[cls.name] = info
            rec.components.append(cls.name)
        return rec

    def _call_components(self, name: str) -> list[type[Component]]:
        found: list[type[Component]] = []
        for impl in self.pm.hook.teletouch_components.get_hookimpls():
            if impl.plugin_name != name:
                continue
            with _quiet_stdout():
                got = impl.function()
            if got is None:
                continue
            if isinstance(got, type) or not isinstance(got, (list, tuple)):
                hint = f" (wrap it in a list: [{got.__qualname__}])" if isinstance(got, type) else ""
                raise PluginError(f"teletouch_components() must return a list of Component classes, got "
                                  f"{_short(got)}{hint}")
            found.extend(got)
        return found

    def _conflict_message(self, cname: str, providers: list[ComponentInfo]) -> str:
        """Why ``cname`` is refused, and how to resolve it as each provider came: an installed one is uninstalled
        or blocked, one named in TELETOUCH_PLUGINS dropped from it or blocked, one given to :meth:`register`
        (``make_registry``, where no block applies) not given."""
        origins = " and ".join(f"plugin '{p.plugin}' ({p.origin})" for p in providers)
        loaded = [p for p in providers if p.plugin not in self.registered]
        given = [p for p in providers if p.plugin in self.registered and p.distribution != BUILTIN_DISTRIBUTION]
        ways = []
        if loaded:
            verbs = (["uninstall one"] if any(p.distribution != f"({ENV_PLUGINS})" for p in loaded) else []) + (
                [f"drop one from {ENV_PLUGINS}"] if any(p.distribution == f"({ENV_PLUGINS})" for p in loaded) else [])
            blocks = " or ".join(f"{ENV_BLOCK}={p.plugin}" for p in loaded)
            ways.append(f"{', '.join(verbs)} or block one ({blocks}, or `teletouch --block NAME`)")
        if given:
            ways.append((f"give only one of {' and '.join(repr(p.plugin) for p in given)} to" if len(given) > 1 else
                         f"leave '{given[0].plugin}' out of") +
                        f" make_registry() or Registry.register() ({ENV_BLOCK} does not apply there)")
        if any(p.distribution == BUILTIN_DISTRIBUTION for p in providers):
            ways.append("rename the other component: a built-in one's name is taken wherever teletouch is installed")
        return (f"component '{cname}' is provided by both {origins}; the name is refused until only one provides it: "
                f"{'; or '.join(ways)}")

    # queries ---------------------------------------------------------------------------------------------------
    def get(self, name: str) -> ComponentInfo:
        try:
            return self.components[name]
        except KeyError:
            if name in self.conflicts:
                raise DuplicateComponentError(self._conflict_message(name, self.conflicts[name])) from None
            raise UnknownComponentError(self.unknown_message(name)) from None

    def unknown_message(self, name: str) -> str:
        if name in self.conflicts:
            return self._conflict_message(name, self.conflicts[name])
        close = difflib.get_close_matches(name, list(self.components), n=3, cutoff=0.6)
        msg = f"unknown plugin '{name}'"
        if close:
            msg += " (did you mean " + " or ".join(f"'{c}'" for c in close) + "?)"
        elif self.autoload:
            msg += "; run `teletouch plugins` to list what is installed"
        broken = [p for p in self.plugins.values()
                  if p.error and (p.name == name or name in p.offered or name in p.module.replace("_", "-").split("."))]
        for p in broken:
            msg += f"; plugin '{p.name}' failed to load: {p.error}"
        others = [p.name for p in self.errors() if p not in broken]
        if others:
            msg += f"; plugins that failed to load (see `teletouch plugins`): {', '.join(others)}"
        blocked = sorted(p.name for p in self.plugins.values() if p.blocked)
        if blocked:
            msg += f"; blocked plugins (not loaded): {', '.join(blocked)}"
        if not self.autoload:
            msg += f"; installed plugins are not loaded ({self._no_autoload_why})"
        return msg

    def autoload_off_why(self) -> str | None:
        """Why installed plugins (entry points) are not loaded, e.g. "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD is set";
        None when they are."""
        return None if self.autoload else self._no_autoload_why

    def errors(self) -> list[PluginRecord]:
        return [p for p in self.plugins.values() if p.error]

    def unknown_blocked(self) -> list[str]:
        """One line per blocked name that matches no installed plugin or distribution (a typo), with a hint."""
        if not self.autoload:
            return []
        out = []
        for name in sorted(self.blocked - self.known_names):
            msg = (f"blocked name '{name}' (from {' and '.join(self.block_settings.get(name, ['?']))}) matches no "
                   f"installed plugin or distribution")
            if name in self.components:
                msg += (f"; '{name}' is a component of plugin '{self.components[name].plugin}': block plugins by "
                        f"plugin or distribution name")
            else:
                close = difflib.get_close_matches(name, sorted(self.known_names), n=3, cutoff=0.6)
                if close:
                    msg += " (did you mean " + " or ".join(f"'{c}'" for c in close) + "?)"
            out.append(msg)
        return out

    def block_origin(self, rec: PluginRecord) -> list[dict[str, str]]:
        """Why ``rec`` is blocked: one ``{"name", "source", "setting"}`` per blocked name that matches its plugin or
        distribution name and per setting that names it (source: command line, environment or caller)."""
        names = dict.fromkeys([rec.name, *(d.strip() for d in rec.distribution.split(","))])
        return [{"name": n, "source": block_source(s), "setting": s}
                for n in names if n in self.block_settings for s in self.block_settings[n]]

    def problems(self) -> list[str]:
        """Everything `teletouch plugins` reports as a failure: broken plugins, conflicts, unknown blocked names."""
        out = [f"plugin '{p.name}' ({p.origin}) failed to load: {p.error}" for p in self.errors()]
        out += [self._conflict_message(c, infos) for c, infos in sorted(self.conflicts.items())]
        return out + self.unknown_blocked()

    def describe(self) -> list[dict[str, Any]]:
        """One dict per component (and per broken plugin, per refused component name and per blocked plugin), as
        `teletouch plugins --json` prints. A broken plugin or a refused name has ``kind`` None and an ``error``; a
        blocked plugin (never imported: its components are not known) has ``kind`` None, ``blocked`` True and
        ``blocked_by`` (:meth:`block_origin`)."""
        rows = []
        for info in sorted(self.components.values(), key=lambda i: (i.kind, i.name)):
            d = info.cls.describe()
            rows.append({"name": d["name"], "kind": d["kind"], "distribution": info.distribution,
                         "version": info.version, "plugin": info.plugin, "description": d["description"],
                         "ports": d["ports"], "params": d["params"]})
        for rec in self.plugins.values():
            if rec.error:
                rows.append({"name": rec.name, "kind": None, "distribution": rec.distribution,
                             "version": rec.version, "plugin": rec.name, "ports": [], "params": [],
                             "error": rec.error})
        for cname, infos in sorted(self.conflicts.items()):
            rows.append({"name": cname, "kind": None, "distribution": ", ".join(i.distribution for i in infos),
                         "version": ", ".join(i.version for i in infos), "plugin": ", ".join(i.plugin for i in infos),
                         "ports": [], "params": [], "error": self._conflict_message(cname, infos)})
        for rec in self.plugins.values():
            if rec.blocked:
                rows.append({"name": rec.name, "kind": None, "distribution": rec.distribution,
                             "version": rec.version, "plugin": rec.name, "module": rec.module, "ports": [],
                             "params": [], "blocked": True, "blocked_by": self.block_origin(rec)})
        return rows

    def discover_devices(self) -> list[dict[str, Any]]:
        found: list[dict[str, Any]] = []
        for impl in self.pm.hook.teletouch_discover_devices.get_hookimpls():
            try:
                with _quiet_stdout():
                    got = impl.function()
                if got is None:
                    continue
                if not (isinstance(got, (list, tuple)) and all(isinstance(d, dict) for d in got)):
                    raise PluginError(f"teletouch_discover_devices() must return a list of dicts, got {_short(got)}")
            except (Exception, SystemExit) as exc:
                found.append(_discovery_error(impl.plugin_name, _error_line(exc)))
                continue
            found.extend(_checked_entry(impl.plugin_name, i, entry) for i, entry in enumerate(got, 1))
        return found


def _checked_entry(plugin: str, i: int, entry: dict[str, Any]) -> dict[str, Any]:
    """``entry``, the ``i``-th (from 1) that ``plugin``'s discovery returned, or, where it lacks a key every entry
    has, an error row naming the plugin and the missing keys (it is not a device to list)."""
    missing = [k for k in DEVICE_KEYS if k not in entry]
    if not missing:
        return entry
    return _discovery_error(plugin, f"teletouch_discover_devices() entry {i} has no "
                                    f"{', '.join(repr(k) for k in missing)} (every entry needs "
                                    f"{', '.join(DEVICE_KEYS)}): {_short(entry)}")


def _discovery_error(plugin: str, message: str) -> dict[str, Any]:
    """The row that stands for what ``plugin``'s discovery could not give, in the hook's error-entry form."""
    return {"kind": plugin, "id": "", "path": "", "error": message}


def _short(obj: Any) -> str:
    text = repr(obj)
    return text if len(text) <= 80 else text[:77] + "..."


def _check_hooks(pm: pluggy.PluginManager, plugin: Any) -> list[str]:
    """The names of the hooks ``plugin`` implements; raises PluginError for a hook name that has no spec (a typo)
    and for a ``teletouch_*`` function left without ``@teletouch.hookimpl`` (pluggy would ignore it silently)."""
    known = sorted(n for n in dir(hookspecs) if n.startswith(f"{GROUP}_"))
    impl = sorted(hc.name for hc in pm.get_hookcallers(plugin) or [])
    for hname in impl:
        if hname not in known:
            close = difflib.get_close_matches(hname, known, n=1, cutoff=0.6)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise PluginError(f"implements an unknown hook '{hname}'{hint}; the hooks are: {', '.join(known)}")
    for attr in dir(plugin):
        if attr.startswith(f"{GROUP}_") and attr not in impl and callable(getattr(plugin, attr, None)):
            raise PluginError(f"function '{attr}' is not decorated with @teletouch.hookimpl, so it would never be "
                              f"called")
    return impl


#: the unit symbols an interface may declare: the SI base units, the derived units with special names, and two counts
#: the unit table uses (px in px/m, bit in bit/s); a unit is a product, quotient or integer power of these, or '1'
SI_SYMBOLS: tuple[str, ...] = ("m", "kg", "s", "A", "K", "mol", "cd", "rad", "sr", "Hz", "N", "Pa", "J", "W", "C", "V",
                               "F", "Ohm", "S", "Wb", "T", "H", "lm", "lx", "Bq", "Gy", "Sv", "kat", "px", "bit")
_SI_SET = frozenset(SI_SYMBOLS)
#: the SI unit meant by a symbol (or a name) that is not one, where it is obvious
_SI_FOR: dict[str, str] = {
    "deg": "rad", "degree": "rad", "degrees": "rad", "\u00b0": "rad", "rev": "rad", "rpm": "rad/s", "rps": "rad/s",
    "min": "s", "h": "s", "sec": "s", "second": "s", "seconds": "s", "newton": "N", "newtons": "N", "meter": "m",
    "meters": "m", "metre": "m", "metres": "m", "g": "kg", "gram": "kg", "grams": "kg", "hertz": "Hz",
    "pascal": "Pa", "joule": "J", "watt": "W", "radian": "rad", "radians": "rad", "ohm": "Ohm", "\u03a9": "Ohm",
    "amp": "A", "ampere": "A", "volt": "V", "kelvin": "K", "degC": "K", "\u00b0C": "K", "bar": "Pa", "psi": "Pa",
    "in": "m", "inch": "m", "ft": "m", "lb": "kg", "lbf": "N", "kgf": "N", "Nm": "N*m", "Ns": "N*s", "l": "m^3",
    "L": "m^3", "mmHg": "Pa", "rev/s": "rad/s",
}
_SI_PREFIXES = ("da", "Y", "Z", "E", "P", "T", "G", "M", "k", "h", "d", "c", "m", "u", "\u00b5", "\u03bc", "n", "p",
                "f", "a")
_UNIT_TOKEN = re.compile(r"\s+|[^\W\d_]+|\u00b0C?|\d+|.", re.UNICODE)


def _si_for(sym: str) -> str | None:
    """The SI unit meant by ``sym``, a symbol that is not an SI one, where it is obvious (deg: rad, ms: s, mN: N)."""
    if sym in _SI_FOR:
        return _SI_FOR[sym]
    close = [s for s in _SI_SET if s.lower() == sym.lower()] or [
        v for k, v in _SI_FOR.items() if k.lower() == sym.lower()]
    if len(close) == 1:   # 'hz', 'Newton'
        return close[0]
    for prefix in _SI_PREFIXES:   # a prefixed SI unit (mm, ms, kHz, mN, MPa) or gram (mg)
        rest = sym[len(prefix):]
        if sym.startswith(prefix) and rest and rest != "kg" and (rest in _SI_SET or rest == "g"):
            return "kg" if rest == "g" else rest
    return None


def _parse_unit(unit: str) -> tuple[list[str], list[tuple[int, str]]]:
    """``unit`` as tokens, and the symbols in it that are not SI units (token index, symbol); ValueError where it is
    not a product, quotient or power of symbols (``N*s/m``, ``m^2``, ``1/s``, ``m/(N*s)``)."""
    tokens = _UNIT_TOKEN.findall(unit)
    unknown: list[tuple[int, str]] = []
    pos = 0

    def peek() -> str:
        return tokens[pos] if pos < len(tokens) else ""

    def expr() -> None:
        nonlocal pos
        factor()
        while peek() in ("*", "/"):
            pos += 1
            factor()

    def factor() -> None:
        nonlocal pos
        tok = peek()
        if tok == "(":
            pos += 1
            expr()
            if peek() != ")":
                raise ValueError("a '(' is not closed")
            pos += 1
        elif tok == "1":
            pos += 1
        elif tok and (tok[0].isalpha() or tok[0] == "\u00b0"):
            if tok not in _SI_SET:
                unknown.append((pos, tok))
            pos += 1
        else:
            raise ValueError(f"unexpected {tok!r}" if tok else "it ends too early")
        if peek() == "^":
            pos += 1
            if peek() == "-":
                pos += 1
            if not peek().isdigit() or int(peek()) == 0:
                raise ValueError("'^' takes a whole power other than 0 ('^2', '^-1')")
            pos += 1

    expr()
    if pos < len(tokens):
        raise ValueError(f"unexpected {tokens[pos]!r}")
    return tokens, unknown


def _si_problem(unit: Any) -> str | None:
    """Why ``unit`` may not be declared at an interface, or None. A unit is ``''`` or ``'1'`` (a plain number), or a
    product, quotient or integer power of SI unit symbols (:data:`SI_SYMBOLS`: ``N*s/m``, ``m^2``, ``1/s``): a
    symbol that is not one (mm, deg/s, rpm, a misspelt 'newton') is refused, naming the SI unit where it is
    obvious."""
    from .units import _UNITS

    if not isinstance(unit, str):
        return f"must be a string (an SI unit symbol), got {_short(unit)}"
    si = _UNITS.get(unit)
    if si is not None and si[0] != unit:
        return f"'{unit}' is not SI: declare '{si[0]}' (every interface is SI; millimetres only in text)"
    if unit in ("", "1"):
        return None
    try:
        tokens, unknown = _parse_unit(unit)
    except ValueError as exc:
        return (f"'{unit}' is not a unit ({exc}): write SI symbols joined by '*' and '/', with powers as '^2' "
                f"('N*s/m', 'm^2', '1/s'), or '' for a plain number")
    if not unknown:
        return None
    alts = {sym: _si_for(sym) for _, sym in unknown}
    what = ", ".join(repr(s) for s in alts) + (" is not an SI unit symbol" if len(alts) == 1 else
                                                " are not SI unit symbols")
    if all(alts.values()):
        for i, sym in unknown:   # the same expression in SI units
            alt = alts[sym]
            alone = len(tokens) == 1 or not any(op in alt for op in "*/^")
            tokens[i] = alt if alone else f"({alt})"
        meant = ", ".join(repr(a) for a in alts.values())
        return f"'{unit}' is not SI: {what} (SI: {meant}): declare '{''.join(tokens)}'"
    return (f"'{unit}' is not SI: {what}; declare SI symbols ({', '.join(SI_SYMBOLS)}) joined by '*' and '/', or '' "
            f"for a plain number (a count, a ratio)")


def check_component(cls: Any) -> None:
    """Raise PluginError, naming the class and the attribute, if ``cls`` cannot run in a graph."""
    if not (isinstance(cls, type) and issubclass(cls, Component)):
        raise PluginError(f"{_short(cls)} is not a subclass of teletouch.Component")
    q = cls.__qualname__
    if not isinstance(cls.name, str) or not NAME_RE.match(cls.name):
        raise PluginError(f"{q}.name must be lower-case words joined by '-', got {cls.name!r}")
    if not isinstance(cls.kind, Kind):
        raise PluginError(f"{q}.kind must be a teletouch.Kind, got {cls.kind!r}")
    if cls.kind is Kind.DEVICE and not issubclass(cls, Device):
        raise PluginError(f"{q}.kind is Kind.DEVICE but {q} does not subclass teletouch.Device: the runtime could "
                          f"not drive it to a safe state")
    if cls.step is Component.step:
        raise PluginError(f"{q} must define step(self, t, inputs)")
    if not (isinstance(cls.Params, type) and issubclass(cls.Params, BaseModel)):
        raise PluginError(f"{q}.Params must be a pydantic model")
    if not issubclass(cls.Params, Params):
        raise PluginError(f"{q}.Params must subclass teletouch.Params (it refuses unknown keys, so a typo in a "
                          f"graph is an error instead of a silently ignored parameter)")
    rate = cls.default_rate
    if rate is not None and rate_problem(rate):
        raise PluginError(f"{q}.default_rate must be None or a number of Hz from {MIN_RATE:g} to {MAX_RATE:g}, got "
                          f"{rate!r}")
    for side in ("inputs", "outputs"):
        ports = getattr(cls, side)
        if not isinstance(ports, dict):
            raise PluginError(f"{q}.{side} must be a dict of port name -> teletouch.Port, got {_short(ports)}")
        for pname, port in ports.items():
            if not (isinstance(pname, str) and pname.isidentifier() and pname.isascii()):
                raise PluginError(f"{q}.{side}: port name {pname!r} must be a Python identifier (graphs write "
                                  f"'node.port')")
            if not isinstance(port, Port):
                raise PluginError(f"{q}.{side}['{pname}'] must be a teletouch.Port, got {_short(port)}")
            why = None if port.unit == "any" else _si_problem(port.unit)
            if why:
                raise PluginError(f"{q}.{side}['{pname}'] unit {why}")
    if issubclass(cls, Device) and cls.safe_state is Device.safe_state:
        raise PluginError(f"device {q} must define safe_state()")
    try:
        desc = cls.describe()
    except Exception as exc:
        raise PluginError(f"{q} cannot describe itself for `teletouch plugins`: {exception_line(exc)}") from None
    for prm in desc["params"]:
        why = _si_problem(prm.get("unit") or "")
        if why:
            raise PluginError(f"{q}.Params.{prm['name']} unit {why}")


_check_component = check_component   # the old private name


_default: Registry | None = None


def default_registry(reload: bool = False, blocked: Iterable[str] = ()) -> Registry:
    """The process-wide registry, loaded on first use from entry points and the environment. ``blocked`` adds
    names to block (``teletouch --block``: reports name that option as where they came from); giving any reloads
    it."""
    global _default
    blocked = split_names(blocked) if isinstance(blocked, str) else list(blocked)
    if _default is None or reload or blocked:
        _default = Registry(blocked=blocked, blocked_setting="--block").load()
    return _default
