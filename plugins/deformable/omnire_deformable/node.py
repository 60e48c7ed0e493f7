"""Deformable actor node (OmniRe): non-rigid actors without a body model (cyclists, far or
pose-less pedestrians, other moving things).

Each instance has box-local canonical Gaussians (initialised like rigid actors, from the
LiDAR in its box plus random points) and a learnable embedding e_h. One deformation network
shared by all instances maps (gamma(local position), gamma(t), e_h) to offsets
(d_mu, d_q, d_s) added to the canonical Gaussians before the box pose:

    G_world(t) = T_h(t) (x) (mu + d_mu, q + d_q, log s + d_s)

The network is evaluated only on the Gaussians of instances present at t, and switched on
after a warm-up. A regulariser keeps deformed Gaussians inside their (slightly enlarged) box.
Local positions are normalised by each box's half size before encoding, so one network
serves boxes of any size.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch
from torch import nn

from omnire.camera import PinholeCamera
from omnire.nn import DeformationMLP, positional_encoding
from omnire.nodes.actors import ActorNode, ActorPoses, init_box_gaussians, transform_instances
from omnire.nodes.base import GaussianNodeConfig, NodeContext, ParamGroup


@dataclasses.dataclass
class DeformableConfig(GaussianNodeConfig):
    """Deformable actors. Reference network: 8 x 256, skip at 4, 10 + 10 frequencies,
    16-d embeddings, on after 3000 steps; the CPU default is smaller (a flag away)."""

    _target: type = dataclasses.field(default_factory=lambda: DeformableNode)
    voxel_size: float = 0.04
    """Voxel edge (m) for the accumulated in-box LiDAR."""
    max_points_per_instance: int = 3000
    """Cap on LiDAR points per instance."""
    random_points_per_instance: int = 300
    """Random points in each box."""
    mlp_depth: int = 6
    """Hidden layers of the shared network (reference: 8)."""
    mlp_width: int = 128
    """Width of the shared network (reference: 256)."""
    pos_freqs: int = 10
    """Positional-encoding frequencies of the local position."""
    time_freqs: int = 10
    """Positional-encoding frequencies of time."""
    embedding_dim: int = 16
    """Per-instance embedding size."""
    warmup_steps: int = 500
    """Steps before the deformation switches on (reference: 3000 of 30k)."""
    refine_boxes: bool = True
    """Learn per-frame box pose corrections."""
    box_margin: float = 0.2
    """The box regulariser allows Gaussians this fraction beyond the box half size."""
    lr_deform: float = 8e-3
    """Network lr, decaying to lr_deform_final."""
    lr_deform_final: float = 8e-4
    """Final network lr."""
    lr_embedding: float = 1e-3
    """Instance embedding lr."""
    lr_box_rotation: float = 1e-5
    """Box rotation refinement lr."""
    lr_box_translation: float = 5e-4
    """Box translation refinement lr."""


class DeformableNode(ActorNode):
    def __init__(self, config: DeformableConfig, context: NodeContext, tracks: list) -> None:
        super().__init__()
        self.config = config
        self.scene_radius = context.scene_radius
        scene = context.scene
        self.track_ids = [t.track_id for t in tracks]
        self.poses = ActorPoses(tracks, scene.train_frames, config.refine_boxes, context.device)
        params, instance = init_box_gaussians(context, tracks, config.voxel_size, config.max_points_per_instance,
                                              config.random_points_per_instance, 0.1, config.sh_degree,
                                              config.init_opacity)
        for k, v in params.items():
            self.gaussian_params[k] = nn.Parameter(v)
        self.gaussian_buffers["instance"] = instance
        self.register_buffer("half_sizes", torch.as_tensor(np.stack([t.size for t in tracks]) / 2, dtype=torch.float32,
                                                           device=context.device))
        ts = np.asarray(scene.frame_timestamps, dtype=np.float64)
        self.t_min, self.t_span = float(ts.min()), float(max(ts.max() - ts.min(), 1e-9))
        c = config
        self.embeddings = nn.Parameter(torch.randn(len(tracks), c.embedding_dim, generator=context.generator).to(context.device) * 0.1)
        in_dim = 3 * 2 * c.pos_freqs + 2 * c.time_freqs + c.embedding_dim
        self.mlp = DeformationMLP(in_dim, c.mlp_depth, c.mlp_width, c.mlp_depth // 2).to(context.device)
        self._last_offsets: Optional[tuple[torch.Tensor, torch.Tensor]] = None

    def deformation(self, local: torch.Tensor, instance: torch.Tensor, time: float):
        """(M,3) box-local means of instances (M,) at ``time`` -> (d_mu, d_q, d_s)."""
        c = self.config
        x = local.detach() / self.half_sizes[instance]  # ~[-1, 1] inside the box
        t = torch.full((len(local), 1), (time - self.t_min) / self.t_span, dtype=local.dtype, device=local.device)
        feats = torch.cat([positional_encoding(x, c.pos_freqs), positional_encoding(t, c.time_freqs),
                           self.embeddings[instance]], dim=-1)
        return self.mlp(feats)

    def gaussians_at(self, frame: int, time: float, step: Optional[int] = None,
                     camera: Optional[PinholeCamera] = None):
        self._last_offsets = None  # the regulariser only sees what this call renders
        ids, R, t = self.poses.at(frame)
        if len(ids) == 0:
            return None
        g, rows = self.present_gaussians(ids)
        instance = self.gaussian_buffers["instance"][rows]
        if step is None or step >= self.config.warmup_steps:
            d_mu, d_q, d_s = self.deformation(g.means, instance, time)
            q = g.quats / g.quats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            g = dataclasses.replace(g, means=g.means + d_mu, quats=q + d_q, scales=g.scales + d_s)
            self._last_offsets = (g.means, instance)
        return transform_instances(g, instance, ids, R, t), rows

    def regularization(self, frame: int, time: float) -> dict[str, torch.Tensor]:
        """``deformable_box``: mean distance of deformed Gaussians beyond their box (+ margin),
        for the Gaussians rendered in the current step."""
        if self._last_offsets is None:
            return {}
        means, instance = self._last_offsets
        limit = self.half_sizes[instance] * (1 + self.config.box_margin)
        return {"deformable_box": torch.relu(means.abs() - limit).sum(-1).mean()}

    def gaussian_lrs(self):
        return self.config.gaussian_lrs(self.scene_radius)

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        return (super().param_groups()
                + [ParamGroup("deformation_mlp", list(self.mlp.parameters()), c.lr_deform, c.lr_deform_final),
                   ParamGroup("instance_embeddings", [self.embeddings], c.lr_embedding)]
                + self.poses.param_groups(c.lr_box_rotation, c.lr_box_translation))

    @torch.no_grad()
    def extra_prune_mask(self) -> torch.Tensor:
        half = self.half_sizes[self.gaussian_buffers["instance"]]
        return (self.gaussian_params["means"].abs() > half * (1 + 2 * self.config.box_margin)).any(dim=-1)
