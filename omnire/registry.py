"""Typed registries that plugins fill through pluggy hooks.

A registry maps a unique name to a spec object (a small frozen dataclass describing one
dataparser, node type, rasterizer, loss, method, command, pose estimator or scene writer).
Every kind of registry is declared once, in :data:`REGISTRY_KINDS`: the plugin manager,
``omnire plugins`` and the hook specifications are all driven by that table.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, Callable, Generic, Iterator, Optional, TypeVar

from omnire.errors import UserError

if TYPE_CHECKING:
    from pathlib import Path

    from omnire.data.scene import ActorTrack, SceneData

SpecT = TypeVar("SpecT")


@dataclasses.dataclass(frozen=True)
class Provenance:
    """Where a registry entry came from."""

    distribution: str
    """Distribution (pip package) name, or ``omnire`` for built-ins."""
    version: str
    """Distribution version."""


class RegistryError(UserError):
    """An unknown name was looked up, or a name was registered twice."""


class Registry(Generic[SpecT]):
    """Name -> spec mapping with provenance. One instance per kind of entry.

    Plugins never construct registries; they receive them in their hook implementation and
    call :meth:`register`.
    """

    def __init__(self, kind: str, provenance: Provenance = Provenance("omnire", "builtin")) -> None:
        self.kind = kind
        self._entries: dict[str, SpecT] = {}
        self._provenance: dict[str, Provenance] = {}
        self._default_provenance = provenance

    def register(self, spec: SpecT) -> SpecT:
        name = getattr(spec, "name")
        if not isinstance(name, str) or not name.strip():
            raise RegistryError(f"{self.kind} spec {spec!r}: name must be a non-empty string")
        if name in self._entries:
            raise RegistryError(f"{self.kind} {name!r} is registered twice by {self._provenance[name].distribution}")
        self._entries[name] = spec
        self._provenance[name] = self._default_provenance
        return spec

    def merge(self, other: "Registry[SpecT]") -> None:
        """Take every entry of ``other`` (a plugin's staged registrations) with its provenance."""
        for name, spec in other._entries.items():
            if name in self._entries:
                raise RegistryError(f"{self.kind} {name!r} is registered by {self._provenance[name].distribution} "
                                    f"and by {other._provenance[name].distribution}")
            self._entries[name] = spec
            self._provenance[name] = other._provenance[name]

    def get(self, name: str) -> SpecT:
        try:
            return self._entries[name]
        except KeyError:
            known = ", ".join(sorted(self._entries)) or "none"
            raise RegistryError(f"unknown {self.kind} {name!r}; registered: {known}") from None

    def provenance(self, name: str) -> Provenance:
        return self._provenance[name]

    def names(self) -> list[str]:
        return sorted(self._entries)

    def items(self) -> list[tuple[str, SpecT]]:
        return sorted(self._entries.items())

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[SpecT]:
        return iter(self._entries[k] for k in sorted(self._entries))

    def __len__(self) -> int:
        return len(self._entries)


@dataclasses.dataclass(frozen=True)
class Spec:
    """What every registry entry has: the ``name`` it is registered and selected by, and the
    one-line ``description`` ``omnire plugins`` lists. Each kind of spec adds its callables."""

    name: str
    description: str


@dataclasses.dataclass(frozen=True)
class DataparserSpec(Spec):
    """A dataset reader: ``config_factory()`` returns its (tyro-visible) config dataclass."""

    config_factory: Callable[[], Any]


@dataclasses.dataclass(frozen=True)
class NodeTypeSpec(Spec):
    """A scene-graph node type.

    ``categories`` are the actor categories the node type can model (empty for scene-level
    nodes such as background or sky). ``priority`` breaks ties when several enabled node
    types accept one actor (higher wins). ``accepts(track, scene)`` is a pure predicate that
    may refuse an actor (e.g. the SMPL node refuses pedestrians without pose sequences); it is
    asked only about actors training observes (``omnire.model.assign_tracks``).
    ``prepare(scene, plugins, config)`` runs once per scene, before any track is assigned,
    for the node types a method enables, with the node's config (e.g. the SMPL node type
    fills ``scene.human_poses`` with the registered pose estimators); it may add to the
    scene, never remove.
    """

    config_factory: Callable[[], Any]
    categories: frozenset[str] = frozenset()
    priority: int = 0
    accepts: Optional[Callable[["ActorTrack", "SceneData"], bool]] = None
    prepare: Optional[Callable[["SceneData", Any, Any], None]] = None


@dataclasses.dataclass(frozen=True)
class RasterizerSpec(Spec):
    """A rasterizer backend. ``available(device)`` returns ``(ok, reason)``; ``factory(**kw)``
    builds it. ``auto`` selection takes the available one with the highest priority.

    ``capabilities``: the optional paths it offers beyond ``rasterize``, names of
    :data:`omnire.rasterization.CAPABILITIES` (``inference``, ``fused_training``, ``ssim``,
    ``lidar``).
    An unknown name, or (when ``factory`` is the class) a declared path the class has no
    method for, refuses the spec here; a lazy factory's object is checked when built."""

    factory: Callable[..., Any]
    available: Callable[[Any], tuple[bool, str]]
    priority: int = 0
    capabilities: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        from omnire.rasterization import CAPABILITIES, lacking

        object.__setattr__(self, "capabilities", frozenset(self.capabilities))
        unknown = sorted(self.capabilities - set(CAPABILITIES))
        if unknown:
            raise RegistryError(f"rasterizer {self.name!r}: unknown capabilities {unknown}; known: "
                                f"{sorted(CAPABILITIES)}")
        missing = lacking(self.factory, self.capabilities) if isinstance(self.factory, type) else []
        if missing:
            raise RegistryError(f"rasterizer {self.name!r} declares capabilities {missing} but "
                                f"{self.factory.__name__} has no "
                                + ", ".join(CAPABILITIES[c].method for c in missing))


@dataclasses.dataclass(frozen=True)
class LossSpec(Spec):
    """A loss term. ``fn(context) -> scalar tensor or None`` (None = not applicable to this
    view, e.g. the depth loss on a frame without LiDAR)."""

    fn: Callable[..., Any]


@dataclasses.dataclass(frozen=True)
class MethodSpec(Spec):
    """A named preset: ``config_factory()`` returns a full :class:`omnire.method.MethodConfig`."""

    config_factory: Callable[[], Any]


@dataclasses.dataclass(frozen=True)
class CommandSpec(Spec):
    """An ``omnire <name>`` sub-command. ``main(argv, plugins)`` runs it and returns an exit
    code; ``plugins`` is the set the CLI loaded (``--strict``, ``OMNIRE_DISABLE_PLUGINS``
    applied): a command never loads its own, and hands ``plugins.selection`` to any worker
    process it starts. Names may have several words (``bench raster``): the CLI takes the longest name
    that the command line starts with, and ``omnire bench`` lists the ``bench *`` commands."""

    main: Callable[[list[str], Any], Optional[int]]


@dataclasses.dataclass(frozen=True)
class PoseEstimatorSpec(Spec):
    """A per-camera human pose estimator for the human pose pipeline (``omnire_body``).

    ``factory(**kw)`` builds an object with ``estimate(scene, camera, rois) ->
    list[HumanTracklet]`` (see ``omnire_body.humanpose.PoseEstimator``); ``available()``
    returns ``(ok, reason)`` (e.g. a missing optional package). ``auto`` selection takes the
    available one with the highest priority."""

    factory: Callable[..., Any]
    available: Callable[[], tuple[bool, str]]
    priority: int = 0


@dataclasses.dataclass(frozen=True)
class SceneWriterSpec(Spec):
    """Writes a scene in a dataset's own on-disk layout (``omnire synth --format <name>``).

    ``write(source, output)`` converts the synthetic scene in ``source`` (the processed
    layout written by ``omnire synth``, with its ``ground_truth.*``) into ``output``, which
    exists and is empty. The dataparser of the same name reads the result back.
    """

    write: Callable[["Path", "Path"], None]


@dataclasses.dataclass(frozen=True)
class TrainObserverSpec(Spec):
    """Something that watches training (``--trainer.observers <name>``), e.g. a live viewer.

    ``factory(trainer, options)`` (``options``: the ``--trainer.observer-options`` key=value
    pairs as a dict) builds an object with ``on_step(step: int, stats: dict) -> None``,
    called after every ``--trainer.observe-every`` steps and at the end, and ``close()``.
    It may read ``trainer.recon`` (the scene runtime) and must not change it."""

    factory: Callable[[Any, dict[str, str]], Any]


@dataclasses.dataclass(frozen=True)
class NativeExtensionSpec(Spec):
    """A C++ extension a plugin compiles at first use (an
    :class:`omnire.native.NativeExtension`). ``load()`` returns ``(module, "")`` or
    ``(None, reason)``, building it when the cache has no build for this source and torch;
    ``omnire plugins --build`` calls it for every registered extension (``make install`` does,
    so that nothing compiles inside the first training run or test)."""

    load: Callable[[], tuple[Any, str]]


@dataclasses.dataclass(frozen=True)
class RegistryKind:
    """One kind of registry: the attribute of :class:`omnire.plugins.Plugins` holding it,
    what an entry is called in messages, the spec class and the hook that fills it."""

    attr: str
    label: str
    spec: type
    hook: str
    registers: str
    """What the hook registers (its docstring)."""


REGISTRY_KINDS: tuple[RegistryKind, ...] = (
    RegistryKind("dataparsers", "dataparser", DataparserSpec, "omnire_register_dataparsers", "dataset readers"),
    RegistryKind("node_types", "node type", NodeTypeSpec, "omnire_register_node_types", "scene-graph node types"),
    RegistryKind("rasterizers", "rasterizer", RasterizerSpec, "omnire_register_rasterizers", "rasterizer backends"),
    RegistryKind("losses", "loss", LossSpec, "omnire_register_losses", "loss terms"),
    RegistryKind("methods", "method", MethodSpec, "omnire_register_methods",
                 "methods (named presets of node types, losses and settings)"),
    RegistryKind("commands", "command", CommandSpec, "omnire_register_commands",
                 "``omnire`` sub-commands (``bench *`` commands included)"),
    RegistryKind("pose_estimators", "pose estimator", PoseEstimatorSpec, "omnire_register_pose_estimators",
                 "per-camera human pose estimators (used by the SMPL node type's scene preparation)"),
    RegistryKind("scene_writers", "scene writer", SceneWriterSpec, "omnire_register_scene_writers",
                 "writers of a dataset's on-disk layout (``omnire synth --format``)"),
    RegistryKind("train_observers", "training observer", TrainObserverSpec, "omnire_register_train_observers",
                 "training observers (``--trainer.observers``), e.g. a live viewer"),
    RegistryKind("native_extensions", "native extension", NativeExtensionSpec, "omnire_register_native_extensions",
                 "C++ extensions compiled at first use (``omnire plugins --build`` compiles them ahead)"),
)
"""Every registry kind, in the order ``omnire plugins`` lists them."""


def kind_of(spec: Any) -> RegistryKind:
    """The registry kind a spec object belongs to (a plugin's ``SPECS`` entries are sorted by it)."""
    for kind in REGISTRY_KINDS:
        if isinstance(spec, kind.spec):
            return kind
    raise RegistryError(f"{spec!r} is not a spec; expected one of "
                        + ", ".join(kind.spec.__name__ for kind in REGISTRY_KINDS))
