"""Rigid actor node: Gaussians in box-local space, moved by per-frame box poses.

World Gaussians at frame t: G_world = T_i(t) (x) G_local for every instance i present at t
(StreetGS / OmniRe rigid nodes). Initialised per instance from the LiDAR points inside the
box over all training frames (accumulated in the box frame, voxel-downsampled, coloured from
the frame each point was seen in) plus random points in the box. Box poses start from the
tracks and are refined (on by default). Gaussians that drift out of their box are pruned.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch
from torch import nn

from omnire.camera import PinholeCamera
from omnire.nodes.actors import ActorNode, ActorPoses, init_box_gaussians, transform_instances
from omnire.nodes.base import GaussianNodeConfig, NodeContext, ParamGroup


@dataclasses.dataclass
class RigidConfig(GaussianNodeConfig):
    """Rigid actors (vehicles)."""

    _target: type = dataclasses.field(default_factory=lambda: RigidNode)
    voxel_size: float = 0.05
    """Voxel edge (m) for the accumulated in-box LiDAR."""
    max_points_per_instance: int = 6000
    """Cap on LiDAR points per instance after downsampling."""
    random_points_per_instance: int = 300
    """Random points inside each box (covers surfaces LiDAR missed)."""
    refine_boxes: bool = True
    """Learn per-frame box pose corrections (box refinement)."""
    lr_box_rotation: float = 1e-5
    """Box rotation refinement lr."""
    lr_box_translation: float = 5e-4
    """Box translation refinement lr."""
    prune_outside: float = 0.5
    """Prune Gaussians farther outside their box than this fraction of its half-size."""


class RigidNode(ActorNode):
    def __init__(self, config: RigidConfig, context: NodeContext, tracks: list) -> None:
        super().__init__()
        self.config = config
        self.scene_radius = context.scene_radius
        scene = context.scene
        self.track_ids = [t.track_id for t in tracks]
        self.poses = ActorPoses(tracks, scene.train_frames, config.refine_boxes, context.device)
        params, instance = init_box_gaussians(context, tracks, config.voxel_size, config.max_points_per_instance,
                                              config.random_points_per_instance, 0.2, config.sh_degree,
                                              config.init_opacity)
        for k, v in params.items():
            self.gaussian_params[k] = nn.Parameter(v)
        self.gaussian_buffers["instance"] = instance
        self.register_buffer("half_sizes", torch.as_tensor(np.stack([t.size for t in tracks]) / 2, dtype=torch.float32,
                                                           device=context.device))

    def gaussians_at(self, frame: int, time: float, step: Optional[int] = None,
                     camera: Optional[PinholeCamera] = None):
        ids, R, t = self.poses.at(frame)
        if len(ids) == 0:
            return None  # absent actors cost nothing
        g, rows = self.present_gaussians(ids)
        return transform_instances(g, self.gaussian_buffers["instance"][rows], ids, R, t), rows

    def gaussian_lrs(self):
        return self.config.gaussian_lrs(self.scene_radius)

    def param_groups(self) -> list[ParamGroup]:
        return super().param_groups() + self.poses.param_groups(self.config.lr_box_rotation,
                                                                 self.config.lr_box_translation)

    @torch.no_grad()
    def extra_prune_mask(self) -> torch.Tensor:
        half = self.half_sizes[self.gaussian_buffers["instance"]]
        return (self.gaussian_params["means"].abs() > half * (1 + self.config.prune_outside)).any(dim=-1)
