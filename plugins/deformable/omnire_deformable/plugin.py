from omnire.api import NodeTypeSpec, hookimpl, track_displacement, usable_track

MIN_DISPLACEMENT = 0.5
"""Actors of category "other" that move less than this (m) stay in the background."""


def accepts(track, scene) -> bool:
    """Non-rigid actors with a usable box; "other" actors only when they move (the core keeps
    actors training never sees in the background)."""
    if track.category == "other" and (track.stationary or track_displacement(track) < MIN_DISPLACEMENT):
        return False  # cones, signs, parked things: folded into the background
    return usable_track(track)


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_deformable.node import DeformableConfig

    registry.register(NodeTypeSpec(
        "deformable", "non-rigid actors: box-local Gaussians + one shared deformation network (time, embedding)",
        DeformableConfig, categories=frozenset({"human", "cyclist", "other"}), priority=5, accepts=accepts))
