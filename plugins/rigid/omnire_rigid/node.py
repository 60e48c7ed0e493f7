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

import torch

from omnire.api import ActorState, BoxActorConfig, BoxActorNode, Camera, NodeOutput, SceneTime


@dataclasses.dataclass
class RigidConfig(BoxActorConfig):
    """Rigid actors (vehicles)."""

    _target: type = dataclasses.field(default_factory=lambda: RigidNode)
    prune_outside: float = 0.5
    """Prune Gaussians farther outside their box than this fraction of its half-size."""


class RigidNode(BoxActorNode):
    config: RigidConfig

    def gaussians_for(self, state: ActorState, t: SceneTime, camera: Optional[Camera] = None,
                      step: Optional[int] = None) -> Optional[NodeOutput]:
        return self.placed_params(state, t)

    @torch.no_grad()
    def extra_prune_mask(self) -> torch.Tensor:
        half = self.half_sizes[self.gaussian_buffers["instance"]]
        return (self.gaussian_params["means"].abs() > half * (1 + self.config.prune_outside)).any(dim=-1)
