"""Typed registries that plugins fill through pluggy hooks.

A registry maps a unique name to a spec object (a small frozen dataclass describing one
dataparser, node type, rasterizer, loss or method). The plugin manager records which
distribution registered each entry, so ``omnire plugins`` can say where it came from.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Generic, Iterator, TypeVar

SpecT = TypeVar("SpecT")


@dataclasses.dataclass(frozen=True)
class Provenance:
    """Where a registry entry came from."""

    distribution: str
    """Distribution (pip package) name, or ``omnire`` for built-ins."""
    version: str
    """Distribution version."""


class RegistryError(ValueError):
    """Raised for duplicate names and unknown look-ups."""


class Registry(Generic[SpecT]):
    """Name -> spec mapping with provenance. One instance per kind of entry.

    Plugins never construct registries; they receive them in their hook implementation and
    call :meth:`register`.
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._entries: dict[str, SpecT] = {}
        self._provenance: dict[str, Provenance] = {}
        # Set by the plugin manager while a plugin's hook runs.
        self._current: Provenance = Provenance("omnire", "builtin")

    def register(self, spec: SpecT) -> SpecT:
        name = getattr(spec, "name")
        if name in self._entries:
            other = self._provenance[name]
            raise RegistryError(
                f"{self.kind} {name!r} is registered twice: by {other.distribution} and by "
                f"{self._current.distribution}"
            )
        self._entries[name] = spec
        self._provenance[name] = self._current
        return spec

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
class DataparserSpec:
    """A dataset reader: ``config_factory()`` returns its (tyro-visible) config dataclass."""

    name: str
    description: str
    config_factory: Callable[[], Any]


@dataclasses.dataclass(frozen=True)
class NodeTypeSpec:
    """A scene-graph node type.

    ``categories`` are the actor categories the node type can model (empty for scene-level
    nodes such as background or sky). ``priority`` breaks ties when several enabled node
    types accept one actor (higher wins); ``accepts(track, scene)`` may refuse an actor
    (e.g. the SMPL node refuses pedestrians without pose sequences).
    """

    name: str
    description: str
    config_factory: Callable[[], Any]
    categories: frozenset[str] = frozenset()
    priority: int = 0
    accepts: Callable[[Any, Any], bool] | None = None


@dataclasses.dataclass(frozen=True)
class RasterizerSpec:
    """A rasterizer backend. ``available(device)`` returns ``(ok, reason)``; ``factory(**kw)``
    builds it. ``auto`` selection takes the available one with the highest priority."""

    name: str
    description: str
    factory: Callable[..., Any]
    available: Callable[[Any], tuple[bool, str]]
    priority: int = 0


@dataclasses.dataclass(frozen=True)
class LossSpec:
    """A loss term. ``fn(context) -> scalar tensor or None`` (None = not applicable to this
    view, e.g. the depth loss on a frame without LiDAR)."""

    name: str
    description: str
    fn: Callable[..., Any]


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A named preset: ``config_factory()`` returns a full :class:`omnire.method.MethodConfig`."""

    name: str
    description: str
    config_factory: Callable[[], Any]


@dataclasses.dataclass(frozen=True)
class CommandSpec:
    """An ``omnire <name>`` sub-command. ``main(argv, plugins)`` runs it and returns an exit code."""

    name: str
    description: str
    main: Callable[[list[str], Any], int | None]


@dataclasses.dataclass(frozen=True)
class PoseEstimatorSpec:
    """A human pose estimator for the human pose pipeline (:mod:`omnire.humanpose`).

    ``factory(**kw)`` builds an object with ``estimate(scene, camera, frames, boxes) ->
    list[HumanTracklet]`` (per-camera tracklets with per-frame SMPL rotations in the camera's
    OpenCV frame); ``available()`` returns ``(ok, reason)`` (e.g. a missing optional package).
    ``auto`` selection takes the available one with the highest priority."""

    name: str
    description: str
    factory: Callable[..., Any]
    available: Callable[[], tuple[bool, str]]
    priority: int = 0
