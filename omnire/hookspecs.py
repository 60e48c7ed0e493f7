"""pluggy hook specifications: the whole plugin API of omnire.

A plugin is a module (found through the ``omnire`` entry-point group) holding functions
decorated with :data:`hookimpl` whose names match the specs below. Each hook receives the
registry to fill; return values are ignored.

Example (in ``my_plugin/plugin.py``, with ``[project.entry-points.omnire] my = "my_plugin.plugin"``)::

    from omnire.hookspecs import hookimpl
    from omnire.registry import LossSpec

    @hookimpl
    def omnire_register_losses(registry):
        registry.register(LossSpec("tv", "total variation of depth", tv_loss))
"""
from __future__ import annotations

import pluggy

PROJECT = "omnire"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def omnire_register_dataparsers(registry) -> None:
    """Register :class:`~omnire.registry.DataparserSpec` entries."""


@hookspec
def omnire_register_node_types(registry) -> None:
    """Register :class:`~omnire.registry.NodeTypeSpec` entries."""


@hookspec
def omnire_register_rasterizers(registry) -> None:
    """Register :class:`~omnire.registry.RasterizerSpec` entries."""


@hookspec
def omnire_register_losses(registry) -> None:
    """Register :class:`~omnire.registry.LossSpec` entries."""


@hookspec
def omnire_register_methods(registry) -> None:
    """Register :class:`~omnire.registry.MethodSpec` entries (named presets)."""


@hookspec
def omnire_register_commands(registry) -> None:
    """Register :class:`~omnire.registry.CommandSpec` entries (extra ``omnire`` sub-commands)."""


@hookspec
def omnire_register_pose_estimators(registry) -> None:
    """Register :class:`~omnire.registry.PoseEstimatorSpec` entries (per-camera human pose
    estimators feeding the human pose pipeline, :mod:`omnire.humanpose`)."""
