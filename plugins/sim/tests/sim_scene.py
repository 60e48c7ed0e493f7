"""A small street for simulation tests, built in memory (no ../shared data, no training):
the tiny scene of tests/scene_helpers.py (two cameras driving along +x towards a textured
wall, a car ahead) plus a parked car, a walking pedestrian with a body-pose sequence and a
cyclist, drawn by the omnire method's nodes (rigid, smpl, deformable, background, sky) as
initialised from the data. Untrained Gaussians are enough for geometry: every test compares
renders of the same Gaussians."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from omnire.api import ActorTrack, HumanPoseSequence, Reconstruction, SceneData, rot_z
from omnire.observations import Observations
from omnire.plugins import load_plugins
from omnire_body.rest import BODY_TO_BOX
from scene_helpers import make_tiny_scene

FRAMES = 8
WIDTH, HEIGHT = 96, 64


def _poses(xyz: np.ndarray, yaw: float) -> np.ndarray:
    P = np.tile(np.eye(4), (len(xyz), 1, 1))
    P[:, :3, :3] = rot_z(np.array(yaw))
    P[:, :3, 3] = xyz
    return P


def street_scene(root: Path, with_actors: bool = True) -> SceneData:
    """(F = 8 frames at 10 Hz, 2 cameras 96x64.) Tracks: ``car-1`` driving ahead (from the
    tiny scene), ``car-2`` parked on the right, ``ped-1`` walking across from the left,
    ``bike-1`` riding ahead on the left."""
    scene = make_tiny_scene(root, frames=FRAMES, width=WIDTH, height=HEIGHT, holdout=0, with_track=with_actors)
    if not with_actors:
        return scene
    F = FRAMES
    f = np.arange(F)
    parked = _poses(np.tile([9.0, -2.6, -0.75], (F, 1)), 0.0)
    scene.tracks.append(ActorTrack("car-2", "Car", "vehicle", parked, np.array([4.2, 1.8, 1.5]), np.ones(F, bool),
                                   stationary=True))
    walk = np.stack([np.full(F, 6.0), 2.2 - 0.15 * f, np.full(F, -0.65)], 1)
    ped = _poses(walk, -np.pi / 2)
    scene.tracks.append(ActorTrack("ped-1", "Pedestrian", "human", ped, np.array([0.6, 0.6, 1.7]), np.ones(F, bool)))
    orient = ped[:, :3, :3] @ BODY_TO_BOX  # upright, facing its heading
    scene.human_poses["ped-1"] = HumanPoseSequence("ped-1", orient, np.tile(np.eye(3), (F, 23, 1, 1)), np.zeros(0),
                                                   np.ones(F, bool), "test")
    ride = np.stack([5.0 + 0.4 * f, np.full(F, 1.4), np.full(F, -0.65)], 1)
    scene.tracks.append(ActorTrack("bike-1", "Bicycle", "cyclist", _poses(ride, 0.0), np.array([1.8, 0.7, 1.7]),
                                   np.ones(F, bool)))
    return scene.validate()


def small_omnire(plugins):
    """The omnire method with small nodes (fast to build and render)."""
    method = plugins.methods.get("omnire").config_factory()
    nodes = dict(method.nodes)
    nodes["background"] = dataclasses.replace(nodes["background"], voxel_size=0.5, num_far_points=200)
    nodes["smpl"] = dataclasses.replace(nodes["smpl"], gaussians_per_person=600)
    nodes["deformable"] = dataclasses.replace(nodes["deformable"], mlp_depth=2, mlp_width=32, warmup_steps=0)
    nodes["sky"] = dataclasses.replace(nodes["sky"], height=16, width=32)
    return dataclasses.replace(method, nodes=nodes, rasterizer="cpu")


def build(scene: SceneData, seed: int = 0, plugins=None) -> Reconstruction:
    """A Reconstruction of ``scene`` as initialised (no training)."""
    plugins = plugins or load_plugins()
    torch.manual_seed(seed)
    device = torch.device("cpu")
    return Reconstruction.build(small_omnire(plugins), scene, plugins, device, Observations(scene, device).images,
                                seed=seed)
