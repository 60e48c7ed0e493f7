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

from omnire.api import (
    ActorState,
    BoxActorConfig,
    BoxActorNode,
    Camera,
    DeformationMLP,
    NodeContext,
    NodeOutput,
    ParamGroup,
    SceneTime,
    placed_output,
    positional_encoding,
)


@dataclasses.dataclass
class DeformableConfig(BoxActorConfig):
    """Deformable actors. Reference network: 8 x 256, skip at 4, 10 + 10 frequencies,
    16-d embeddings, on after 3000 steps; the CPU default is smaller (a flag away)."""

    _target: type = dataclasses.field(default_factory=lambda: DeformableNode)
    voxel_size: float = 0.04
    """Voxel edge (m) for the accumulated in-box LiDAR."""
    max_points_per_instance: int = 3000
    """Cap on LiDAR points per instance."""
    max_init_scale: float = 0.1
    """Largest initial Gaussian scale (m)."""
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
    """Steps before the deformation switches on (reference: 3000 of 30k); steps of the training
    schedule (the clock's on a time budget)."""
    box_margin: float = 0.2
    """The box regulariser allows Gaussians this fraction beyond the box half size."""
    lr_deform: float = 8e-3
    """Network lr, decaying to lr_deform_final."""
    lr_deform_final: float = 8e-4
    """Final network lr."""
    lr_embedding: float = 1e-3
    """Instance embedding lr."""


class DeformableNode(BoxActorNode):
    config: DeformableConfig

    def __init__(self, config: DeformableConfig, context: NodeContext, tracks: list) -> None:
        super().__init__(config, context, tracks)
        ts = np.asarray(context.scene.frame_timestamps, dtype=np.float64)
        self.t_min, self.t_span = float(ts.min()), float(max(ts.max() - ts.min(), 1e-9))
        c = config
        self.embeddings = nn.Parameter(torch.randn(len(tracks), c.embedding_dim, generator=context.generator).to(context.device) * 0.1)
        in_dim = 3 * 2 * c.pos_freqs + 2 * c.time_freqs + c.embedding_dim
        self.mlp = DeformationMLP(in_dim, c.mlp_depth, c.mlp_width, c.mlp_depth // 2).to(context.device)

    def deformation(self, local: torch.Tensor, instance: torch.Tensor, time: float):
        """(M,3) box-local means of instances (M,) at ``time`` (seconds) -> (d_mu, d_q, d_s)."""
        c = self.config
        x = local.detach() / self.half_sizes[instance]  # ~[-1, 1] inside the box
        t = torch.full((len(local), 1), (time - self.t_min) / self.t_span, dtype=local.dtype, device=local.device)
        feats = torch.cat([positional_encoding(x, c.pos_freqs), positional_encoding(t, c.time_freqs),
                           self.embeddings[instance]], dim=-1)
        return self.mlp(feats)

    def gaussians_for(self, state: ActorState, t: SceneTime, camera: Optional[Camera] = None,
                      step: Optional[int] = None) -> Optional[NodeOutput]:
        ids, R, tr = state.ids, state.R, state.t
        g, rows = self.present_gaussians(ids)
        instance = self.gaussian_buffers["instance"][rows]
        extras = {}
        if step is None or step >= self.config.warmup_steps:
            d_mu, d_q, d_s = self.deformation(g.means, instance, t.seconds)
            q = g.quats / g.quats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            g = dataclasses.replace(g, means=g.means + d_mu, quats=q + d_q, scales=g.scales + d_s)
            extras = {"deformed_local_means": g.means, "instance": instance}
        return placed_output(g, instance, ids, R, tr, rows, t, extras)

    def instance_reach(self, state: ActorState) -> None:
        """None: the deformation field can carry a Gaussian anywhere, so no actor is culled
        as out of view before it is deformed (the rasterizer still culls per Gaussian)."""
        return None

    def regularization(self, output: NodeOutput) -> dict[str, torch.Tensor]:
        """``deformable_box``: mean distance of the deformed Gaussians of the rendered view
        beyond their box (+ margin)."""
        if "deformed_local_means" not in output.extras:
            return {}
        means, instance = output.extras["deformed_local_means"], output.extras["instance"]
        limit = self.half_sizes[instance] * (1 + self.config.box_margin)
        return {"deformable_box": torch.relu(means.abs() - limit).sum(-1).mean()}

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        return (super().param_groups()
                + [ParamGroup("deformation_mlp", list(self.mlp.parameters()), c.lr_deform, c.lr_deform_final),
                   ParamGroup("instance_embeddings", [self.embeddings], c.lr_embedding)])

    @torch.no_grad()
    def extra_prune_mask(self) -> torch.Tensor:
        half = self.half_sizes[self.gaussian_buffers["instance"]]
        return (self.gaussian_params["means"].abs() > half * (1 + 2 * self.config.box_margin)).any(dim=-1)
