"""Plugin discovery and loading, with per-plugin error isolation.

Every plugin, the built-ins included, is a module with pluggy hook implementations. External
ones are found through the ``omnire`` entry-point group. A plugin that fails to import or
whose hook raises is recorded as a :class:`PluginFailure` (distribution, version, error)
and skipped; the others keep working. Strict mode turns any failure into an exception.

Environment variables:

- ``OMNIRE_STRICT_PLUGINS=1``: strict mode (same as ``--strict``).
- ``OMNIRE_DISABLE_PLUGINS=a,b``: skip these plugins (entry-point or distribution names).
- ``OMNIRE_NO_ENTRY_POINTS=1``: load only the built-ins (for isolated tests).
"""
from __future__ import annotations

import dataclasses
import importlib
import os
import traceback
from importlib import metadata
from types import ModuleType
from typing import Any

import pluggy

from omnire import hookspecs
from omnire.registry import (
    CommandSpec,
    DataparserSpec,
    LossSpec,
    MethodSpec,
    NodeTypeSpec,
    PoseEstimatorSpec,
    Provenance,
    RasterizerSpec,
    Registry,
)

ENTRY_POINT_GROUP = "omnire"
BUILTIN_MODULES = ("omnire.builtins",)

# hook name -> attribute of Plugins holding the registry it fills
_HOOKS = {
    "omnire_register_dataparsers": "dataparsers",
    "omnire_register_node_types": "node_types",
    "omnire_register_rasterizers": "rasterizers",
    "omnire_register_losses": "losses",
    "omnire_register_methods": "methods",
    "omnire_register_commands": "commands",
    "omnire_register_pose_estimators": "pose_estimators",
}


class PluginLoadError(RuntimeError):
    """Raised in strict mode when any plugin fails."""


@dataclasses.dataclass
class PluginFailure:
    plugin: str
    """Entry-point name (or module for built-ins)."""
    provenance: Provenance
    stage: str
    """``import`` or the hook that raised."""
    error: str
    """One-line error message."""
    traceback: str

    def describe(self) -> str:
        return (
            f"plugin {self.plugin!r} from {self.provenance.distribution} "
            f"{self.provenance.version} failed at {self.stage}: {self.error}"
        )


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() in {"1", "true", "yes", "on"}


@dataclasses.dataclass
class Plugins:
    """All registries, filled by the loaded plugins. Create with :func:`load_plugins`."""

    dataparsers: Registry[DataparserSpec]
    node_types: Registry[NodeTypeSpec]
    rasterizers: Registry[RasterizerSpec]
    losses: Registry[LossSpec]
    methods: Registry[MethodSpec]
    commands: Registry[CommandSpec]
    loaded: list[tuple[str, Provenance]]
    failures: list[PluginFailure]
    pose_estimators: Registry[PoseEstimatorSpec] = dataclasses.field(
        default_factory=lambda: Registry("pose estimator"))

    def registries(self) -> dict[str, Registry[Any]]:
        return {attr: getattr(self, attr) for attr in _HOOKS.values()}


def _entry_point_distribution(ep: metadata.EntryPoint) -> Provenance:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return Provenance("unknown", "unknown")
    return Provenance(dist.metadata["Name"], dist.version)


def load_plugins(
    strict: bool | None = None,
    disabled: set[str] | None = None,
    entry_points: bool | None = None,
    extra_modules: tuple[ModuleType, ...] = (),
) -> Plugins:
    """Discover, load and run every plugin; return the filled registries.

    Args:
        strict: fail on the first broken plugin (default: ``OMNIRE_STRICT_PLUGINS``).
        disabled: plugin or distribution names to skip (default: ``OMNIRE_DISABLE_PLUGINS``).
        entry_points: load entry-point plugins (default: not ``OMNIRE_NO_ENTRY_POINTS``).
        extra_modules: additional plugin modules (used by tests and embedding code).
    """
    if strict is None:
        strict = _env_flag("OMNIRE_STRICT_PLUGINS")
    if disabled is None:
        disabled = {s.strip() for s in os.environ.get("OMNIRE_DISABLE_PLUGINS", "").split(",") if s.strip()}
    if entry_points is None:
        entry_points = not _env_flag("OMNIRE_NO_ENTRY_POINTS")

    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    plugins = Plugins(
        dataparsers=Registry("dataparser"),
        node_types=Registry("node type"),
        rasterizers=Registry("rasterizer"),
        losses=Registry("loss"),
        methods=Registry("method"),
        commands=Registry("command"),
        loaded=[],
        failures=[],
    )

    def fail(name: str, prov: Provenance, stage: str, exc: BaseException) -> None:
        failure = PluginFailure(
            name, prov, stage, f"{type(exc).__name__}: {exc}", traceback.format_exc()
        )
        if strict:
            raise PluginLoadError(failure.describe() + "\n" + failure.traceback) from exc
        plugins.failures.append(failure)

    candidates: list[tuple[str, Provenance, Any]] = []
    builtin = Provenance("omnire", _core_version())
    for module_name in BUILTIN_MODULES:
        candidates.append((module_name, builtin, lambda m=module_name: importlib.import_module(m)))
    for module in extra_modules:
        candidates.append((module.__name__, Provenance(module.__name__, "local"), lambda m=module: m))
    if entry_points:
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            candidates.append((ep.name, _entry_point_distribution(ep), ep.load))

    for name, prov, load in candidates:
        if name in disabled or prov.distribution in disabled:
            continue
        try:
            module = load()
            pm.register(module, name=name)
        except Exception as exc:  # noqa: BLE001 - isolation is the point
            fail(name, prov, "import", exc)
            continue
        ok = True
        for hook_name, attr in _HOOKS.items():
            registry = getattr(plugins, attr)
            for impl in getattr(pm.hook, hook_name).get_hookimpls():
                if impl.plugin is not module:
                    continue
                registry._current = prov
                try:
                    impl.function(registry=registry)
                except Exception as exc:  # noqa: BLE001
                    ok = False
                    fail(name, prov, hook_name, exc)
                finally:
                    registry._current = builtin
        if ok:
            plugins.loaded.append((name, prov))
    return plugins


def _core_version() -> str:
    try:
        return metadata.version("omnire")
    except metadata.PackageNotFoundError:
        return "dev"
