"""Plugin discovery and loading, with per-plugin error isolation.

Every plugin, the built-ins included, is a module with pluggy hook implementations and/or a
``SPECS`` tuple of specs registered as they are (see :mod:`omnire.hookspecs`). External
ones are found through the ``omnire`` entry-point group. Each plugin registers into a
staging area first; its entries are committed only when all of its hooks succeeded, so a
plugin that fails part-way leaves nothing behind. A plugin that fails to import, whose hook
raises, or that registers a name another plugin also registers is recorded as a
:class:`PluginFailure` and skipped; the others keep working. Name clashes are resolved the
same way whatever the load order: the core's built-ins keep their names and the plugin is
refused; two plugins claiming one name are both refused. Strict mode turns any failure into
an exception.

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
from typing import Any, Callable, Optional, TypeVar

import pluggy

from omnire import hookspecs
from omnire.errors import UserError
from omnire.registry import REGISTRY_KINDS, Provenance, Registry, kind_of

ENTRY_POINT_GROUP = "omnire"
BUILTIN_MODULES = ("omnire.builtins",)
T = TypeVar("T")


class PluginLoadError(UserError):
    """Raised in strict mode when any plugin fails."""


@dataclasses.dataclass
class PluginFailure:
    plugin: str
    """Entry-point name (or module for built-ins)."""
    provenance: Provenance
    stage: str
    """``import``, the hook that raised, ``conflict``, or a call made later (``method factory``, ...)."""
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


@dataclasses.dataclass(frozen=True)
class PluginSelection:
    """Which plugins a process loads: what ``--strict`` and the ``OMNIRE_*`` variables above
    decided for the CLI. A command that starts a worker process hands it its
    ``plugins.selection`` (``as_dict()`` is JSON-ready) so that the worker loads the same
    set (:meth:`load`), strict mode and disabled plugins included. Plugin modules passed to
    :func:`load_plugins` as objects (``extra_modules``) cannot cross a process boundary."""

    strict: bool = False
    disabled: tuple[str, ...] = ()
    """Plugin or distribution names skipped, sorted."""
    entry_points: bool = True
    """Whether entry-point plugins are loaded (False: the core's built-ins only)."""

    def as_dict(self) -> dict[str, Any]:
        return {"strict": self.strict, "disabled": list(self.disabled), "entry_points": self.entry_points}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PluginSelection":
        return cls(bool(data["strict"]), tuple(sorted(data["disabled"])), bool(data["entry_points"]))

    def load(self) -> "Plugins":
        """Load this selection in this process (see :func:`load_plugins`)."""
        return load_plugins(strict=self.strict, disabled=set(self.disabled), entry_points=self.entry_points)


class Plugins:
    """All registries (one attribute per :data:`~omnire.registry.REGISTRY_KINDS` entry, e.g.
    ``plugins.node_types``), filled by the loaded plugins. Create with :func:`load_plugins`;
    commands receive the CLI's (``CommandSpec.main(argv, plugins)``) and never load their own."""

    def __init__(self, selection: PluginSelection = PluginSelection()) -> None:
        self._registries: dict[str, Registry[Any]] = {k.attr: Registry(k.label) for k in REGISTRY_KINDS}
        self.loaded: list[tuple[str, Provenance]] = []
        self.failures: list[PluginFailure] = []
        self.selection = selection

    @property
    def strict(self) -> bool:
        return self.selection.strict

    def __getattr__(self, attr: str) -> Registry[Any]:
        registries = self.__dict__.get("_registries", {})
        if attr in registries:
            return registries[attr]
        raise AttributeError(attr)

    def registries(self) -> dict[str, Registry[Any]]:
        return dict(self._registries)

    def call(self, registry: Registry[Any], name: str, stage: str, fn: Callable[[], T]) -> Optional[T]:
        """Call a plugin-provided ``fn`` for the entry ``name`` of ``registry`` when the run
        may do without it (listing methods for ``--help``, probing rasterizers): an exception
        is recorded as a failure of the plugin that registered the entry and None returned
        (raised in strict mode)."""
        try:
            return fn()
        except Exception as exc:  # noqa: BLE001 - isolation is the point
            prov = registry.provenance(name) if name in registry else Provenance("unknown", "unknown")
            failure = PluginFailure(f"{registry.kind} {name}", prov, stage, f"{type(exc).__name__}: {exc}",
                                    traceback.format_exc())
            if self.strict:
                raise PluginLoadError(failure.describe() + "\n" + failure.traceback) from exc
            self.failures.append(failure)
            return None


def _entry_point_distribution(ep: metadata.EntryPoint) -> Provenance:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return Provenance("unknown", "unknown")
    return Provenance(dist.metadata["Name"], dist.version)


@dataclasses.dataclass
class _Staged:
    """One plugin's registrations, not yet committed."""

    name: str
    provenance: Provenance
    builtin: bool
    registries: dict[str, Registry[Any]]


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

    plugins = Plugins(PluginSelection(bool(strict), tuple(sorted(disabled)), bool(entry_points)))

    def fail(name: str, prov: Provenance, stage: str, message: str, tb: str = "") -> None:
        failure = PluginFailure(name, prov, stage, message, tb)
        if strict:
            raise PluginLoadError(failure.describe() + ("\n" + tb if tb else ""))
        plugins.failures.append(failure)

    candidates: list[tuple[str, Provenance, bool, Callable[[], ModuleType]]] = []
    builtin = Provenance("omnire", _core_version())
    for module_name in BUILTIN_MODULES:
        candidates.append((module_name, builtin, True, lambda m=module_name: importlib.import_module(m)))
    for module in extra_modules:
        candidates.append((module.__name__, Provenance(module.__name__, "local"), False, lambda m=module: m))
    if entry_points:
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            candidates.append((ep.name, _entry_point_distribution(ep), False, ep.load))

    staged: list[_Staged] = []
    for name, prov, is_builtin, load in candidates:
        if name in disabled or prov.distribution in disabled:
            continue
        try:
            module = load()
        except Exception as exc:  # noqa: BLE001 - isolation is the point
            fail(name, prov, "import", f"{type(exc).__name__}: {exc}", traceback.format_exc())
            continue
        pm = pluggy.PluginManager(hookspecs.PROJECT)
        pm.add_hookspecs(hookspecs.HookSpecs)
        try:
            pm.register(module, name=name)
        except Exception as exc:  # noqa: BLE001 - a module whose hooks do not match the specs
            fail(name, prov, "import", f"{type(exc).__name__}: {exc}", traceback.format_exc())
            continue
        entry = _Staged(name, prov, is_builtin, {k.attr: Registry(k.label, prov) for k in REGISTRY_KINDS})
        try:
            for kind in REGISTRY_KINDS:
                getattr(pm.hook, kind.hook)(registry=entry.registries[kind.attr])
            for spec in getattr(module, "SPECS", ()):
                entry.registries[kind_of(spec).attr].register(spec)
        except Exception as exc:  # noqa: BLE001
            fail(name, prov, "registration", f"{type(exc).__name__}: {exc}", traceback.format_exc())
            continue
        staged.append(entry)

    for entry in _refuse_conflicts(staged, fail):
        for attr, registry in entry.registries.items():
            plugins._registries[attr].merge(registry)
        plugins.loaded.append((entry.name, entry.provenance))
    return plugins


def _refuse_conflicts(staged: list[_Staged], fail: Callable[..., None]) -> list[_Staged]:
    """The staged plugins that claim no name another one claims. A plugin registering a name
    a built-in has is refused; plugins sharing a name are all refused. The result does not
    depend on the order the plugins were loaded in."""
    refused: dict[int, list[str]] = {}
    for kind in REGISTRY_KINDS:
        owners: dict[str, list[int]] = {}
        for i, entry in enumerate(staged):
            for name in entry.registries[kind.attr].names():
                owners.setdefault(name, []).append(i)
        for name, idx in owners.items():
            if len(idx) < 2:
                continue
            builtins = [i for i in idx if staged[i].builtin]
            losers = [i for i in idx if not staged[i].builtin] if builtins else idx
            claimants = ", ".join(sorted(staged[i].provenance.distribution for i in idx))
            for i in losers:
                why = (f"registers {kind.label} {name!r}, which the core provides" if builtins else
                       f"{kind.label} {name!r} is registered by several plugins ({claimants}); all of them refused")
                refused.setdefault(i, []).append(why)
    for i, reasons in sorted(refused.items()):
        fail(staged[i].name, staged[i].provenance, "conflict", "; ".join(reasons))
    return [entry for i, entry in enumerate(staged) if i not in refused]


def _core_version() -> str:
    try:
        return metadata.version("omnire")
    except metadata.PackageNotFoundError:
        return "dev"
