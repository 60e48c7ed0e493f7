"""Registers the ``smpl`` node type.

Where the human pose pipeline runs: the node type's ``accepts`` runs
:func:`omnire.humanpose.prepare_human_poses` once per scene, before any node is built, so
node choice sees the result: dataparser-provided sequences (e.g. ``humanpose/smpl.pkl``)
are SLERP-completed; pedestrians without one get poses from the best available registered
pose estimator (``omnire_register_pose_estimators``) matched by 2D-box IoU; the rest start
from a neutral standing pose. Every visible pedestrian with a usable box therefore takes
the SMPL node (priority 20, above the deformable node); the node's log line and each
sequence's ``source`` say which path a pedestrian took.
"""
from __future__ import annotations

import weakref

from omnire.hookspecs import hookimpl
from omnire.registry import NodeTypeSpec

_prepared: dict[int, weakref.ref] = {}


def ensure_human_poses(scene) -> None:
    """Run the pose pipeline once per scene object."""
    ref = _prepared.get(id(scene))
    if ref is not None and ref() is scene:
        return
    from omnire.humanpose import prepare_human_poses, select_estimator
    from omnire.plugins import load_plugins

    humans = [t for t in scene.tracks if t.category == "human"]
    estimator = None
    if any(t.track_id not in scene.human_poses for t in humans):
        estimator = select_estimator(load_plugins().pose_estimators, "auto")
    prepare_human_poses(scene, estimator=estimator)
    _prepared[id(scene)] = weakref.ref(scene)


def _accepts(track, scene) -> bool:
    from omnire.nodes.actors import usable_track, visible_in_cameras

    if not (usable_track(track) and visible_in_cameras(track, scene)):
        return False
    ensure_human_poses(scene)
    return track.track_id in scene.human_poses


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_smpl.node import SMPLConfig

    registry.register(NodeTypeSpec(
        "smpl", "pedestrians as Gaussians skinned by a body template (SMPL skeleton), per-frame body-pose refinement",
        SMPLConfig, categories=frozenset({"human"}), priority=20, accepts=_accepts))
