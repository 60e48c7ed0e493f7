"""DeformableGS node (Yang et al., "Deformable 3D Gaussians for High-Fidelity Monocular
Dynamic Scene Reconstruction", CVPR 2024), as the whole-scene baseline of the OmniRe paper.

One set of canonical Gaussians (initialised exactly like the static background) and one
MLP F(gamma(sg(x)), gamma(t)) -> (d_mu, d_q, d_s) applied to *every* Gaussian at time t:

    mu(t) = mu + d_mu,   q(t) = q / |q| + d_q,   log s(t) = log s + d_s

No boxes, no actor nodes: moving actors must be explained by the field.

Following the paper: 8 ReLU layers of 256 with the input concatenated again after layer 4,
positional encodings gamma(p) = (sin(2^k pi p), cos(2^k pi p))_{k<L} with L = 10 for
position and time (real-scene setting; docs/paper.md "Nodes"), stop-gradient on the position
input, deformation off during a warm-up (canonical 3DGS only), and annealed smooth
training (AST): Gaussian noise N(0,1) * beta * dt * (1 - step / ast_steps) added to the
time input during training (beta = 0.1, dt = mean normalised frame interval).

Deviations (documented, all a flag away except the first two):
- d_s is added to the *log*-scale (the paper adds it to the scale), so scales stay positive.
- Positions are normalised to about [-1, 1] (centre = mean training camera, scale = largest
  distance of an initial point) before encoding: driving scenes span hundreds of metres,
  and 2^9 pi x on metres would alias. Time is normalised to [0, 1] over the scene.
- The output layer is zero-initialised so the field starts at the identity (no jump when
  the warm-up ends).
- CPU default MLP: depth 6, width 128 (skip after layer depth // 2). The paper's 8 x 256
  is ``--method.nodes.deformable-field.mlp-depth 8 --method.nodes.deformable-field.mlp-width 256``
  (about 3-4x slower per step on CPU; see the plugin report for measured it/s).
- Warm-up 500 steps by default (the paper uses 3000 of 40k steps; omnire's default
  training is 3000 steps).
- Learning rate of the MLP 8e-3 -> 8e-4 (the OmniRe reference value, docs/paper.md "Optimisation").
- Frustum culling before the MLP (CPU speed): only canonical Gaussians within
  ``cull_margin`` metres (plus three times their largest scale) of the rendered camera's
  frustum are deformed and rendered. A Gaussian whose deformation carries it further than
  that into the view is missed in that view; ``--method.nodes.deformable-field.cull-margin -1`` turns culling off (the paper's
  behaviour, every Gaussian through the MLP every step).
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.api import (
    BackgroundConfig,
    Camera,
    DeformationMLP,
    GaussianNode,
    Gaussians,
    NodeContext,
    NodeOutput,
    ParamGroup,
    SceneTime,
    in_frustum,
    init_background_params,
    positional_encoding,
)


@dataclasses.dataclass
class DeformableFieldConfig(BackgroundConfig):
    """DeformableGS: canonical Gaussians (initialised like the background) + one deformation MLP
    over position and time for the whole scene. CPU default MLP 6 x 128 (paper: 8 x 256)."""

    _target: type = dataclasses.field(default_factory=lambda: DeformableFieldNode)
    mlp_depth: int = 6
    """Hidden layers of the deformation MLP (paper: 8)."""
    mlp_width: int = 128
    """Width of the deformation MLP (paper: 256)."""
    skip_layer: int = -1
    """Hidden layer that receives the input again (-1: depth // 2, the paper's 4 of 8)."""
    pos_freqs: int = 10
    """Positional-encoding frequencies for position."""
    time_freqs: int = 10
    """Positional-encoding frequencies for time."""
    warmup_steps: int = 500
    """Steps with the deformation off (canonical Gaussians only; paper: 3000 of 40k); steps of
    the training schedule, as every step count here (the clock's on a time budget)."""
    ast_steps: int = 20_000
    """Annealed smooth training: time noise decays linearly to 0 over these steps (0: off)."""
    ast_beta: float = 0.1
    """AST noise scale in units of the mean frame interval."""
    lr_deform: float = 8e-3
    """Deformation-MLP lr, decaying to lr_deform_final."""
    lr_deform_final: float = 8e-4
    """Final deformation-MLP lr."""
    cull_margin: float = 5.0
    """Deform only canonical Gaussians within this many metres of the rendered camera's
    frustum (-1: no culling, every Gaussian through the MLP)."""


class DeformableFieldNode(GaussianNode):
    """All Gaussians of the scene, deformed by one MLP of (position, time).

    gaussian_params: the standard six keys only (the field is shared, not per-Gaussian).
    """

    config: DeformableFieldConfig

    def __init__(self, config: DeformableFieldConfig, context: NodeContext, tracks: Optional[list] = None) -> None:
        super().__init__(config, context)
        self.init_gaussians(context, lambda: init_background_params(config, context))
        scene = context.scene
        ts = np.asarray(scene.frame_timestamps, dtype=np.float64)
        self.t_min = float(ts.min())
        self.t_span = float(max(ts.max() - ts.min(), 1e-9))
        # Mean frame interval in normalised time (AST noise scale).
        self.frame_dt = 1.0 / max(len(ts) - 1, 1)
        # Position normalisation, fixed at build time (buffers: saved with checkpoints).
        cams = np.stack([c.cam_to_world[f, :3, 3] for c in scene.cameras for f in scene.train_frames])
        center = torch.as_tensor(cams.mean(0), dtype=torch.float32, device=context.device)
        means = self.gaussian_params["means"].detach()
        extent = (means - center).norm(dim=-1).max().clamp_min(1.0) if len(means) else torch.ones(())
        self.register_buffer("pos_center", center)
        self.register_buffer("pos_scale", extent.reshape(()))
        c = config
        skip = c.mlp_depth // 2 if c.skip_layer < 0 else c.skip_layer
        in_dim = 3 * 2 * c.pos_freqs + 2 * c.time_freqs
        self.mlp = DeformationMLP(in_dim, c.mlp_depth, c.mlp_width, skip).to(context.device)

    def normalised_time(self, time: float) -> float:
        return (time - self.t_min) / self.t_span

    def deform(self, means: torch.Tensor, t: float, step: Optional[int] = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(N,3) canonical means, normalised time t -> (d_mu (N,3), d_q (N,4), d_s (N,3))."""
        c = self.config
        x = (means.detach() - self.pos_center) / self.pos_scale  # sg(x): the field does not move the means
        tt = torch.full((means.shape[0], 1), t, dtype=means.dtype, device=means.device)
        if step is not None and c.ast_steps > 0 and step < c.ast_steps:
            # AST: one noise value per step (the paper perturbs the frame's time input).
            noise = torch.randn(()) * c.ast_beta * self.frame_dt * (1.0 - step / c.ast_steps)
            tt = tt + noise.to(tt)
        feats = torch.cat([positional_encoding(x, c.pos_freqs), positional_encoding(tt, c.time_freqs)], dim=-1)
        return self.mlp(feats)

    def gaussians_at(self, t: SceneTime, camera: Optional[Camera] = None,
                     step: Optional[int] = None) -> Optional[NodeOutput]:
        p = self.gaussian_params
        if step is not None and step < self.config.warmup_steps:
            return NodeOutput(Gaussians.from_params(p), None, t)
        rows = None  # every row, in order
        if camera is not None and self.config.cull_margin >= 0:
            # A Gaussian outside the frustum still paints it up to ~3 sigma away: add its extent.
            reach = self.config.cull_margin + 3.0 * torch.exp(p["scales"].detach().max(dim=-1).values)
            rows = torch.nonzero(in_frustum(p["means"].detach(), camera, reach)).squeeze(1)
        g = Gaussians.from_params(p, rows)
        d_mu, d_q, d_s = self.deform(g.means, self.normalised_time(t.seconds), step)
        q = g.quats / g.quats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        g = dataclasses.replace(g, means=g.means + d_mu, quats=q + d_q, scales=g.scales + d_s)
        return NodeOutput(g, rows, t)

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        return super().param_groups() + [
            ParamGroup("deformation_mlp", list(self.mlp.parameters()), c.lr_deform, c.lr_deform_final)
        ]
