"""Plugin discovery and the component registry (pluggy).

Components come from modules registered under the entry-point group ``teletouch``. Built-in plugins use the same
group as third-party ones. Environment variables (like pytest's):

- ``TELETOUCH_DISABLE_PLUGIN_AUTOLOAD=1``: do not load entry points (tests register what they need).
- ``TELETOUCH_BLOCK_PLUGINS=a,b``: skip the named plugins (entry-point names or distribution names).
- ``TELETOUCH_PLUGINS=pkg.mod1,pkg.mod2``: import and register these modules too (works with autoload off).

A plugin that fails to import is recorded with its error and skipped. Two components with the same name are refused
with an error naming both distributions.
"""

from __future__ import annotations

import difflib
import importlib
import os
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Iterable

import pluggy
from pydantic import BaseModel

from . import hookspecs
from .component import NAME_RE, Component, Device, Kind, Port
from .errors import DuplicateComponentError, PluginError, UnknownComponentError, exception_line

GROUP = "teletouch"
ENV_DISABLE = "TELETOUCH_DISABLE_PLUGIN_AUTOLOAD"
ENV_BLOCK = "TELETOUCH_BLOCK_PLUGINS"
ENV_PLUGINS = "TELETOUCH_PLUGINS"


@dataclass
class PluginRecord:
    name: str
    distribution: str
    version: str
    module: str
    error: str | None = None
    blocked: bool = False
    components: list[str] = field(default_factory=list)


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


def _truthy(value: str | None) -> bool:
    return bool(value) and value.strip().lower() not in ("0", "false", "no", "off", "")


def _split(value: str | None) -> list[str]:
    return [v.strip() for v in (value or "").split(",") if v.strip()]


class Registry:
    """Holds the loaded plugins and the components they provide."""

    def __init__(self, *, autoload: bool | None = None, blocked: Iterable[str] | None = None,
                 extra_modules: Iterable[str] | None = None):
        self.pm = pluggy.PluginManager(GROUP)
        self.pm.add_hookspecs(hookspecs)
        self.plugins: dict[str, PluginRecord] = {}
        self.components: dict[str, ComponentInfo] = {}
        env = os.environ
        self.autoload = (not _truthy(env.get(ENV_DISABLE))) if autoload is None else autoload
        self.blocked = set(_split(env.get(ENV_BLOCK))) | set(blocked or ())
        self._extra = _split(env.get(ENV_PLUGINS)) + list(extra_modules or ())

    # loading ---------------------------------------------------------------------------------------------------
    def load(self) -> "Registry":
        if self.autoload:
            self.load_entrypoints()
        for modname in self._extra:
            self._load_one(modname, modname, lambda m=modname: importlib.import_module(m), "(TELETOUCH_PLUGINS)", "")
        return self

    def load_entrypoints(self) -> None:
        for ep in sorted(metadata.entry_points(group=GROUP), key=lambda e: e.name):
            dist = ep.dist.name if ep.dist is not None else "?"
            version = ep.dist.version if ep.dist is not None else "?"
            self._load_one(ep.name, ep.value, ep.load, dist, version)

    def _load_one(self, name: str, value: str, loader: Any, dist: str, version: str) -> None:
        if name in self.plugins:
            prev = self.plugins[name]
            if prev.distribution == dist and prev.module == value:
                return  # same entry point seen twice (e.g. editable + metadata on path)
            raise DuplicateComponentError(
                f"plugin name '{name}' is registered by both '{prev.distribution}' ({prev.module}) and "
                f"'{dist}' ({value}); uninstall one or block it with {ENV_BLOCK}={name}")
        rec = PluginRecord(name=name, distribution=dist, version=version, module=value)
        self.plugins[name] = rec
        if name in self.blocked or dist in self.blocked:
            rec.blocked = True
            return
        try:
            obj = loader()
        except Exception as exc:  # a broken plugin is reported, not fatal
            rec.error = exception_line(exc)
            return
        self.register(obj, name=name, _record=rec)

    def register(self, plugin: Any, name: str | None = None, *, distribution: str = "(registered)",
                 version: str = "", _record: PluginRecord | None = None) -> PluginRecord:
        """Register a plugin object/module directly (tests, notebooks). Returns its record."""
        name = name or getattr(plugin, "__name__", None) or repr(plugin)
        rec = _record
        if rec is None:
            if name in self.plugins:
                raise PluginError(f"a plugin named '{name}' is already registered")
            rec = PluginRecord(name=name, distribution=distribution, version=version,
                               module=getattr(plugin, "__name__", repr(plugin)))
            self.plugins[name] = rec
        try:
            self.pm.register(plugin, name=name)
        except Exception as exc:
            rec.error = exception_line(exc)
            return rec
        impls = [i for i in self.pm.hook.teletouch_components.get_hookimpls() if i.plugin_name == name]
        found: list[type[Component]] = []
        try:
            for impl in impls:
                found.extend(impl.function() or [])
            for cls in found:
                _check_component(cls)
        except Exception as exc:
            rec.error = exception_line(exc)
            self.pm.unregister(name=name)
            return rec
        for cls in found:
            other = self.components.get(cls.name)
            if other is not None and other.cls is not cls:
                self.pm.unregister(name=name)
                rec.error = f"duplicate component '{cls.name}'"
                raise DuplicateComponentError(
                    f"component '{cls.name}' is provided by both distribution '{other.distribution}' "
                    f"(plugin '{other.plugin}') and distribution '{rec.distribution}' (plugin '{rec.name}'); "
                    f"uninstall one or block it with {ENV_BLOCK}={rec.name}")
        for cls in found:
            self.components[cls.name] = ComponentInfo(cls, rec.name, rec.distribution, rec.version)
            rec.components.append(cls.name)
        return rec

    # queries ---------------------------------------------------------------------------------------------------
    def get(self, name: str) -> ComponentInfo:
        try:
            return self.components[name]
        except KeyError:
            raise UnknownComponentError(self.unknown_message(name)) from None

    def unknown_message(self, name: str) -> str:
        close = difflib.get_close_matches(name, list(self.components), n=3, cutoff=0.6)
        msg = f"unknown plugin '{name}'"
        if close:
            msg += " (did you mean " + " or ".join(f"'{c}'" for c in close) + "?)"
        else:
            msg += "; run `teletouch plugins` to list what is installed"
        broken = [p for p in self.plugins.values() if p.error and (p.name == name or name in p.module)]
        for p in broken:
            msg += f"; plugin '{p.name}' failed to load: {p.error}"
        return msg

    def errors(self) -> list[PluginRecord]:
        return [p for p in self.plugins.values() if p.error]

    def describe(self) -> list[dict[str, Any]]:
        """One dict per component (and per broken plugin), as `teletouch plugins --json` prints."""
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
        return rows

    def discover_devices(self) -> list[dict[str, Any]]:
        found: list[dict[str, Any]] = []
        for impl in self.pm.hook.teletouch_discover_devices.get_hookimpls():
            try:
                found.extend(impl.function() or [])
            except Exception as exc:
                found.append({"kind": impl.plugin_name, "id": "", "path": "", "error": exception_line(exc)})
        return found


def _check_component(cls: Any) -> None:
    if not (isinstance(cls, type) and issubclass(cls, Component)):
        raise PluginError(f"{cls!r} is not a subclass of teletouch.Component")
    if not isinstance(cls.name, str) or not NAME_RE.match(cls.name):
        raise PluginError(f"{cls.__qualname__}.name must be lower-case words joined by '-', got {cls.name!r}")
    if not isinstance(cls.kind, Kind):
        raise PluginError(f"{cls.__qualname__}.kind must be a teletouch.Kind, got {cls.kind!r}")
    if not (isinstance(cls.Params, type) and issubclass(cls.Params, BaseModel)):
        raise PluginError(f"{cls.__qualname__}.Params must be a pydantic model")
    for side in ("inputs", "outputs"):
        for pname, port in getattr(cls, side).items():
            if not isinstance(port, Port):
                raise PluginError(f"{cls.__qualname__}.{side}['{pname}'] must be a teletouch.Port")
    if issubclass(cls, Device) and cls.safe_state is Device.safe_state:
        raise PluginError(f"device {cls.__qualname__} must define safe_state()")


_default: Registry | None = None


def default_registry(reload: bool = False) -> Registry:
    """The process-wide registry, loaded on first use from entry points and the environment."""
    global _default
    if _default is None or reload:
        _default = Registry().load()
    return _default
