"""Registers the ``deformable_field`` node type and the ``deformablegs`` method."""
from __future__ import annotations

from omnire.api import MethodConfig, MethodSpec, NodeTypeSpec, hookimpl

from omnire_deformablegs.node import DeformableFieldConfig


@hookimpl
def omnire_register_node_types(registry) -> None:
    # No categories: a scene-level node (it models actors implicitly, without boxes).
    registry.register(NodeTypeSpec("deformable_field",
                                   "canonical Gaussians + one deformation MLP of (position, time) for the whole scene",
                                   DeformableFieldConfig))


def deformablegs_method() -> MethodConfig:
    """DeformableGS: the deformable field alone (no boxes, no sky), the 3dgs losses."""
    return MethodConfig(nodes={"deformable_field": DeformableFieldConfig()})


@hookimpl
def omnire_register_methods(registry) -> None:
    registry.register(MethodSpec("deformablegs", "DeformableGS baseline: one deformation field over the whole scene",
                                 deformablegs_method))
