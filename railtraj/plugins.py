"""The plugin manager and the stage registry.

Built-in stages are plugins like any other: the modules in ``railtraj.builtins.BUILTIN_PLUGINS``
are registered through the same pluggy manager as third-party distributions, which are found
through the ``railtraj`` entry-point group. Set ``RAILTRAJ_DISABLE_PLUGIN_AUTOLOAD=1`` to load
only the built-ins (useful to rule out a broken third-party plugin).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
import logging
import os
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

import pluggy

from railtraj import hookspecs
from railtraj.errors import PluginError
from railtraj.stages import STAGE_KINDS

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "railtraj"
DISABLE_AUTOLOAD_ENV = "RAILTRAJ_DISABLE_PLUGIN_AUTOLOAD"


@dataclass(frozen=True)
class StageSpec:
    """One registered stage: how to build it and what options it takes."""

    kind: str
    name: str
    factory: Any
    config: type
    plugin: str

    def options(self) -> dict[str, Any]:
        """Option names and their defaults, as the config dataclass declares them."""
        out = {}
        for f in dataclasses.fields(self.config):
            if f.name == "name":
                continue
            if f.default is not dataclasses.MISSING:
                out[f.name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                out[f.name] = f.default_factory()
            else:
                out[f.name] = "???"
        return out


class StageRegistry:
    """Stages by kind and name, filled by the plugins' ``railtraj_register_stages`` hooks."""

    def __init__(self) -> None:
        self._specs: dict[tuple[str, str], StageSpec] = {}
        self._current_plugin = "?"

    def add(self, kind: str, name: str, factory: Any, config: type) -> None:
        """Register ``factory`` as stage ``name`` of ``kind`` with options dataclass ``config``."""
        plugin = self._current_plugin
        if kind not in STAGE_KINDS:
            raise PluginError(f"plugin {plugin!r} registers {name!r} as unknown stage kind {kind!r}; "
                              f"valid kinds: {', '.join(STAGE_KINDS)}")
        if not (dataclasses.is_dataclass(config) and isinstance(config, type)):
            raise PluginError(f"plugin {plugin!r}: the config of {kind} {name!r} must be a dataclass type")
        if (kind, name) in self._specs:
            other = self._specs[(kind, name)].plugin
            raise PluginError(f"plugins {other!r} and {plugin!r} both register {kind} {name!r}; "
                              "uninstall one or rename its stage")
        self._specs[(kind, name)] = StageSpec(kind, name, factory, config, plugin)

    def names(self, kind: str) -> list[str]:
        return sorted(n for k, n in self._specs if k == kind)

    def specs(self) -> list[StageSpec]:
        return sorted(self._specs.values(), key=lambda s: (list(STAGE_KINDS).index(s.kind), s.name))

    def get(self, kind: str, name: str) -> StageSpec:
        try:
            return self._specs[(kind, name)]
        except KeyError:
            raise PluginError(f"no {kind} named {name!r}; available: {', '.join(self.names(kind)) or 'none'}") from None

    def create(self, kind: str, name: str, options: dict[str, Any] | None = None) -> Any:
        """Build stage ``name`` of ``kind`` with ``options`` and check it against its protocol."""
        spec = self.get(kind, name)
        opts = {k: v for k, v in (options or {}).items() if k != "name"}
        known = {f.name for f in dataclasses.fields(spec.config)}
        unknown = sorted(set(opts) - known)
        if unknown:
            raise PluginError(f"{kind} {name!r} has no option {', '.join(unknown)}; "
                              f"its options: {', '.join(sorted(known - {'name'}))}")
        cfg = spec.config(**opts)
        kwargs = {k: v for k, v in dataclasses.asdict(cfg).items() if k != "name"}
        try:
            stage = spec.factory(**kwargs)
        except TypeError as exc:
            raise PluginError(f"plugin {spec.plugin!r}: building {kind} {name!r} failed: {exc}") from exc
        protocol = STAGE_KINDS[kind]
        if not isinstance(stage, protocol):
            missing = [m for m, _ in inspect.getmembers(protocol, inspect.isfunction)
                       if not m.startswith("_") and not callable(getattr(stage, m, None))]
            raise PluginError(f"plugin {spec.plugin!r}: {kind} {name!r} does not implement "
                              f"{protocol.__name__} (missing {', '.join(missing)})")
        return stage


def _load_entry_point_plugins(pm: pluggy.PluginManager) -> None:
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        if pm.get_plugin(ep.name) is not None or pm.is_blocked(ep.name):
            continue
        try:
            plugin = ep.load()
        except Exception as exc:
            raise PluginError(f"plugin {ep.name!r} ({ep.value}) failed to import: {type(exc).__name__}: {exc}; "
                              f"fix or uninstall it, or set {DISABLE_AUTOLOAD_ENV}=1") from exc
        dist = getattr(ep, "dist", None)
        pm.register(plugin, name=ep.name)
        log.debug("loaded plugin %s from %s", ep.name, dist.name if dist else ep.value)


@functools.cache
def plugin_manager() -> pluggy.PluginManager:
    """The process-wide plugin manager: built-ins first, then entry points (unless disabled)."""
    from railtraj.builtins import BUILTIN_PLUGINS

    pm = pluggy.PluginManager("railtraj")
    pm.add_hookspecs(hookspecs)
    for modname in BUILTIN_PLUGINS:
        pm.register(importlib.import_module(modname), name=modname)
    if not os.environ.get(DISABLE_AUTOLOAD_ENV):
        _load_entry_point_plugins(pm)
    return pm


@functools.cache
def registry() -> StageRegistry:
    """The process-wide stage registry, filled once from every registered plugin."""
    pm = plugin_manager()
    reg = StageRegistry()
    for impl in pm.hook.railtraj_register_stages.get_hookimpls():
        reg._current_plugin = impl.plugin_name
        try:
            impl.function(registry=reg)
        except PluginError:
            raise
        except Exception as exc:
            raise PluginError(f"plugin {impl.plugin_name!r} failed while registering stages: "
                              f"{type(exc).__name__}: {exc}") from exc
    reg._current_plugin = "?"
    return reg
