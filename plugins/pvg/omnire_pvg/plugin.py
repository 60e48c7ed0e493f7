"""Registers the ``pvg`` node type and the ``pvg`` method."""
from __future__ import annotations

from omnire.api import MethodConfig, MethodSpec, NodeTypeSpec, hookimpl

from omnire_pvg.node import PVGConfig


@hookimpl
def omnire_register_node_types(registry) -> None:
    # No categories: one scene-level node models static and dynamic content alike.
    registry.register(NodeTypeSpec("pvg", "periodic vibration Gaussians: per-Gaussian life peak, life span, velocity",
                                   PVGConfig))


def pvg_method() -> MethodConfig:
    """PVG: the pvg node alone, the 3dgs losses plus the sparse-velocity regulariser."""
    return MethodConfig(nodes={"pvg": PVGConfig()}, regularization_weights={"pvg_velocity": 0.01})


@hookimpl
def omnire_register_methods(registry) -> None:
    registry.register(MethodSpec("pvg", "PVG baseline: periodic vibration Gaussians (no boxes)", pvg_method))
