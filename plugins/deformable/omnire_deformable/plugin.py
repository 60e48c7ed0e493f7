from omnire.hookspecs import hookimpl
from omnire.registry import NodeTypeSpec

MIN_DISPLACEMENT = 0.5
"""Actors of category "other" that move less than this (m) stay in the background."""


def _accepts(track, scene) -> bool:
    from omnire.nodes.actors import track_displacement, usable_track, visible_in_cameras

    if track.category == "other" and (track.stationary or track_displacement(track) < MIN_DISPLACEMENT):
        return False  # cones, signs, parked things: folded into the background
    return usable_track(track) and visible_in_cameras(track, scene)


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_deformable.node import DeformableConfig

    registry.register(NodeTypeSpec(
        "deformable", "non-rigid actors: box-local Gaussians + one shared deformation network (time, embedding)",
        DeformableConfig, categories=frozenset({"human", "cyclist", "other"}), priority=5, accepts=_accepts))
