"""Registers the ``smpl`` node type and its native skinning kernel.

Scene preparation (the node type's ``prepare``, run once per scene before tracks are
assigned, only when a method enables this node type): the human pose pipeline of
``omnire_body.humanpose`` fills ``scene.human_poses``. Sequences a dataparser provided (e.g.
``humanpose/smpl.pkl``) are SLERP-completed; for the other pedestrians the best available
registered image pose estimator (``omnire_register_pose_estimators``) runs on every camera,
its tracklets are matched by 2D-box IoU, and the body fitter (``omnire_body.fitting``)
poses each track from its LiDAR points and keypoints with temporal and gait priors (one
fused sequence per track, with a per-frame confidence); pedestrians nothing observed start
from a neutral standing pose. No estimator is built (nor its package imported) when every
pedestrian already has a sequence or the scene has none. ``accepts`` then takes every
pedestrian training observes (a camera, or the LiDAR when it is learned: the core's rule)
with a usable box and a pose sequence (priority 20, above the deformable node). Each
pedestrian's path (sources, observed frames, confidence) is written to the run's log with a
summary line; the node prints a one-line summary on the console.
"""
from __future__ import annotations

import logging

from omnire.api import NativeExtensionSpec, NodeTypeSpec, hookimpl, lazy, usable_track

log = logging.getLogger("omnire.nodes.smpl")


def prepare_scene(scene, plugins, config=None) -> None:
    """Fill ``scene.human_poses`` for every pedestrian track (see the module docstring), from
    the sources ``config.pose_source`` (an :class:`~omnire_smpl.node.SMPLConfig`) allows."""
    from omnire_body.humanpose import prepare_human_poses, select_estimator

    humans = [t for t in scene.tracks if t.category == "human"]
    mode = getattr(config, "pose_source", "auto")
    estimator = None
    needed = any(t.track_id not in scene.human_poses for t in humans)
    if needed and mode in ("auto", "estimator"):
        estimator = select_estimator(plugins.pose_estimators, "auto")
    paths = prepare_human_poses(scene, estimator=estimator, fit=mode in ("auto", "fit"))
    for track_id, path in sorted(paths.items()):
        log.info("smpl: pedestrian %s: %s", track_id, path)
    if paths:
        from collections import Counter

        sources = Counter(scene.human_poses[t].source if t in scene.human_poses else "none" for t in paths)
        est = estimator.name if estimator is not None else ("none available" if needed else "not needed")
        log.info("smpl: %d pedestrians posed: %s (image estimator: %s)", len(paths),
                 ", ".join(f"{n} {src}" for src, n in sorted(sources.items())), est)


def accepts(track, scene) -> bool:
    """Pedestrians with a usable box and a pose sequence (the core keeps actors training never
    sees in the background)."""
    return track.track_id in scene.human_poses and usable_track(track)


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_smpl.node import SMPLConfig

    registry.register(NodeTypeSpec(
        "smpl", "pedestrians as Gaussians skinned by a body template (SMPL skeleton), per-frame body-pose refinement",
        SMPLConfig, categories=frozenset({"human"}), priority=20, accepts=accepts, prepare=prepare_scene))


@hookimpl
def omnire_register_native_extensions(registry) -> None:
    registry.register(NativeExtensionSpec("omnire_smpl_skin", "SMPL skinning of Gaussians (forward and backward)",
                                          lazy("omnire_smpl.skinning:load_extension")))
