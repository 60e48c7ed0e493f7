"""pluggy hook specifications: how a plugin fills the registries.

A plugin is a module (found through the ``omnire`` entry-point group) holding functions
decorated with :data:`hookimpl` whose names match the specs below. Each hook receives the
registry to fill; return values are ignored. The registry kinds and their hooks are listed
once in :data:`omnire.registry.REGISTRY_KINDS`; plugin authors import everything they need
from :mod:`omnire.api`.

Example (in ``my_plugin/plugin.py``, with ``[project.entry-points.omnire] my = "my_plugin.plugin"``)::

    from omnire.api import LossSpec, hookimpl

    @hookimpl
    def omnire_register_losses(registry):
        registry.register(LossSpec("tv", "total variation of depth", tv_loss))
"""
from __future__ import annotations

import pluggy

from omnire.registry import (
    CommandSpec,
    DataparserSpec,
    LossSpec,
    MethodSpec,
    NodeTypeSpec,
    PoseEstimatorSpec,
    RasterizerSpec,
    Registry,
    SceneWriterSpec,
    TrainObserverSpec,
)

PROJECT = "omnire"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def omnire_register_dataparsers(registry: Registry[DataparserSpec]) -> None:
    """Register dataset readers."""


@hookspec
def omnire_register_node_types(registry: Registry[NodeTypeSpec]) -> None:
    """Register scene-graph node types."""


@hookspec
def omnire_register_rasterizers(registry: Registry[RasterizerSpec]) -> None:
    """Register rasterizer backends."""


@hookspec
def omnire_register_losses(registry: Registry[LossSpec]) -> None:
    """Register loss terms."""


@hookspec
def omnire_register_methods(registry: Registry[MethodSpec]) -> None:
    """Register methods (named presets of node types, losses and settings)."""


@hookspec
def omnire_register_commands(registry: Registry[CommandSpec]) -> None:
    """Register ``omnire`` sub-commands (``bench *`` commands included)."""


@hookspec
def omnire_register_pose_estimators(registry: Registry[PoseEstimatorSpec]) -> None:
    """Register per-camera human pose estimators (used by the SMPL node type's scene preparation)."""


@hookspec
def omnire_register_scene_writers(registry: Registry[SceneWriterSpec]) -> None:
    """Register writers of a dataset's on-disk layout (``omnire synth --format``)."""


@hookspec
def omnire_register_train_observers(registry: Registry[TrainObserverSpec]) -> None:
    """Register training observers (``--trainer.observers``), e.g. a live viewer."""
