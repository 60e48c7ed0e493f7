"""Periodic Vibration Gaussian node (Chen et al., "Periodic Vibration Gaussian: Dynamic Urban
Scene Reconstruction and Real-time Rendering", 2023), the unified static/dynamic baseline
of the OmniRe paper.

Every Gaussian carries, besides the standard parameters, a life peak tau, a life span beta
(stored as log beta) and a velocity v (3); the vibration period l is global. At time t:

    mu(t) = mu + l / (2 pi) * sin(2 pi (t - tau) / l) * v
    o(t)  = o * exp(-0.5 (t - tau)^2 / beta^2)

(rotation, scale and colour are time-independent). The staticness coefficient
rho = beta / l separates static (long-lived, rho large) from dynamic Gaussians; the
average velocity is v_bar = v * exp(-rho / 2).

Temporally smooth training (the paper's intrinsic-motion smoothing): during training,
with probability ``smooth_prob`` a frame at time t is rendered from the state at t - dt,
moved by the average velocity: mu_hat(t) = mu(t - dt) + v_bar dt, o_hat(t) = o(t - dt),
dt ~ U(-smooth_dt, smooth_dt). The sparse-velocity regulariser ``pvg_velocity`` is the
mean |v_bar|_1 over Gaussians.

Time is in PVG units: (t - t_mid) * ``time_scale``; the default 0.2 / s makes one 10 Hz
frame 0.02 units, PVG's frame interval, so the paper's l = 0.2 (here 1 s) keeps its meaning.

Initialisation: LiDAR of each training frame separately (points in boxes of actors other
nodes model removed, voxel-downsampled per frame), so each Gaussian keeps the time of the
sweep it came from as tau; coloured from that frame's images; scales from nearest
neighbours within the sweep; plus the background's far shell with tau at mid-sequence and
a life span covering the whole sequence. Without LiDAR the background initialisation is
used with tau uniform over the sequence. Velocities start at 0.

Deviations (see the plugin report): the velocity regulariser is per Gaussian rather than
on a rendered velocity map (the core rasterizer renders colour only); the preset has no
sky environment map and no sky-opacity loss (the ``sky`` node type belongs to another
distribution; a method config can add it next to ``pvg``);
no position-aware densification thresholds (the core strategy has one global scale
threshold); opacity o(t) is passed to the rasterizer as a logit computed in log space.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from omnire.api import (
    BackgroundConfig,
    Camera,
    GaussianNode,
    Gaussians,
    NodeContext,
    NodeOutput,
    SceneTime,
    colour_from_images,
    far_shell,
    init_background_params,
    init_gaussian_params,
    knn_scales,
    lidar_points_for_init,
    to_tensor,
    voxel_downsample,
)

PVG_KEYS = ("life_peak", "life_span", "velocity")
"""Extra per-Gaussian keys: tau (N,), log beta (N,), v (N,3)."""


@dataclasses.dataclass
class PVGConfig(BackgroundConfig):
    """Periodic Vibration Gaussians: per-Gaussian life peak, life span, velocity; global period."""

    _target: type = dataclasses.field(default_factory=lambda: PVGNode)
    time_scale: float = 0.2
    """PVG time units per second (0.2: one 10 Hz frame = 0.02, the paper's frame interval)."""
    period: float = 0.2
    """Vibration period l in PVG time units (paper: 0.2)."""
    init_life_span: float = 0.2
    """Initial life span beta of LiDAR Gaussians (PVG time units)."""
    far_life_span: float = 10.0
    """Initial life span of far-shell Gaussians (>> sequence length: static)."""
    smooth_prob: float = 0.5
    """Probability of temporally smooth training on a step (0: off)."""
    smooth_dt: float = 0.02
    """Largest time offset of smooth training (PVG units; default one 10 Hz frame)."""
    lr_life_peak: float = 2e-4
    """Life-peak (tau) lr, PVG time units."""
    lr_life_span: float = 5e-3
    """Log-life-span lr."""
    lr_velocity: float = 1e-3
    """Velocity lr (x scene radius; velocity in metres per PVG time unit)."""


def pvg_state(means: torch.Tensor, opacity_logits: torch.Tensor, life_peak: torch.Tensor,
              log_life_span: torch.Tensor, velocity: torch.Tensor, t: float | torch.Tensor,
              period: float) -> tuple[torch.Tensor, torch.Tensor]:
    """PVG mean and opacity at time ``t``.

    means (N,3), opacity_logits (N,), life_peak (N,), log_life_span (N,), velocity (N,3).
    Returns (means (N,3), opacity logits (N,)) with sigmoid(logit) = sigmoid(o) * decay.
    """
    dt = t - life_peak  # (N,)
    means_t = means + (period / (2 * math.pi)) * torch.sin(2 * math.pi * dt / period)[:, None] * velocity
    # log o(t) in closed form, then logit = log o - log(1 - o): stable for tiny decays, no clamps
    # that would cut gradients far from the life peak.
    log_o = F.logsigmoid(opacity_logits) - 0.5 * dt * dt * torch.exp(-2 * log_life_span)
    log_o = log_o.clamp_max(-1e-7)  # only reached for o > 1 - 1e-7
    return means_t, log_o - torch.log(-torch.expm1(log_o))


def init_pvg_params(config: PVGConfig, context: NodeContext, to_pvg_time) -> dict[str, torch.Tensor]:
    """Raw PVG parameters (standard keys + :data:`PVG_KEYS`), see the module docstring."""
    scene = context.scene
    frames = [int(f) for f in scene.train_frames
              if scene.lidar is not None and scene.lidar.points[int(f)] is not None]
    times = np.array([to_pvg_time(float(scene.frame_timestamps[f])) for f in scene.train_frames])
    if not frames:
        params = init_background_params(config, context)
        n = params["means"].shape[0]
        lo, hi = float(times.min()), float(times.max())
        peak = lo + (hi - lo) * torch.rand(n, generator=context.generator)
        span = torch.full((n,), math.log(config.init_life_span))
        params.update(life_peak=peak, life_span=span, velocity=torch.zeros(n, 3))
        return {k: v.to(context.device) for k, v in params.items()}

    rng = np.random.default_rng(int(torch.randint(0, 2**31, (1,), generator=context.generator)))
    pts, cols, scales, peaks, seen = [], [], [], [], []
    for f in frames:
        p = lidar_points_for_init(scene, [f], context.excluded_tracks, config.ego_clearance)
        p = voxel_downsample(p, config.voxel_size)
        if len(p) == 0:
            continue
        c, s = colour_from_images(p, scene, context.images, np.array([f]))  # the sweep's own images
        pts.append(p)
        cols.append(c)
        seen.append(s)
        scales.append(knn_scales(p))
        peaks.append(np.full(len(p), to_pvg_time(float(scene.frame_timestamps[f]))))
    pts, cols, scales, peaks, seen = (np.concatenate(a) for a in (pts, cols, scales, peaks, seen))
    if len(pts) > config.max_lidar_points:
        keep = rng.choice(len(pts), config.max_lidar_points, replace=False)
        pts, cols, scales, peaks, seen = pts[keep], cols[keep], scales[keep], peaks[keep], seen[keep]
    if (~seen).any():  # outside that frame's cameras: colour from any training view
        cols[~seen] = colour_from_images(pts[~seen], scene, context.images, scene.train_frames)[0]

    cams = np.stack([c.cam_to_world[f, :3, 3] for c in scene.cameras for f in scene.train_frames])
    ground = np.percentile(pts[:, 2], 5)
    far = far_shell(cams.mean(0), max(context.scene_radius, 30.0) * 2.0, config.num_far_points, rng, min_z=ground)
    far_cols, _ = colour_from_images(far, scene, context.images, scene.train_frames)
    far_scales = knn_scales(far) if len(far) else np.zeros(0)

    all_pts = np.concatenate([pts, far]).astype(np.float32)
    params = init_gaussian_params(
        to_tensor(all_pts), to_tensor(np.concatenate([cols, far_cols])), to_tensor(np.concatenate([scales, far_scales])),
        config.sh_degree, config.init_opacity, context.generator,
    )
    mid = 0.5 * (float(times.min()) + float(times.max()))
    params["life_peak"] = to_tensor(np.concatenate([peaks, np.full(len(far), mid)]))
    params["life_span"] = to_tensor(np.concatenate([np.full(len(pts), math.log(config.init_life_span)),
                                                    np.full(len(far), math.log(config.far_life_span))]))
    params["velocity"] = torch.zeros(len(all_pts), 3)
    return {k: v.to(context.device) for k, v in params.items()}


class PVGNode(GaussianNode):
    """All Gaussians of the scene as periodic vibration Gaussians.

    gaussian_params: standard keys + life_peak (N,), life_span (N,) log, velocity (N,3);
    all are densified by the core strategy like any other per-Gaussian tensor.
    """

    gaussian_keys = GaussianNode.gaussian_keys + PVG_KEYS
    config: PVGConfig

    def __init__(self, config: PVGConfig, context: NodeContext, tracks: Optional[list] = None) -> None:
        super().__init__(config, context)
        ts = np.asarray(context.scene.frame_timestamps, dtype=np.float64)
        self.t_mid = float(0.5 * (ts.min() + ts.max()))
        self.init_gaussians(context, lambda: init_pvg_params(config, context, self.pvg_time))

    def pvg_time(self, time: float) -> float:
        """Seconds -> PVG time units (0 at mid-sequence)."""
        return (time - self.t_mid) * self.config.time_scale

    def staticness(self) -> torch.Tensor:
        """(N,) rho = beta / l (large: static)."""
        return torch.exp(self.gaussian_params["life_span"]) / self.config.period

    def average_velocity(self) -> torch.Tensor:
        """(N,3) v_bar = v * exp(-rho / 2)."""
        return self.gaussian_params["velocity"] * torch.exp(-0.5 * self.staticness())[:, None]

    def state_at(self, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(means (N,3), opacity logits (N,)) at PVG time ``t``."""
        p = self.gaussian_params
        return pvg_state(p["means"], p["opacities"], p["life_peak"], p["life_span"], p["velocity"], t,
                         self.config.period)

    def gaussians_at(self, time: SceneTime, camera: Optional[Camera] = None,
                     step: Optional[int] = None) -> Optional[NodeOutput]:
        c = self.config
        t = self.pvg_time(time.seconds)
        if step is not None and c.smooth_prob > 0 and float(torch.rand(())) < c.smooth_prob:
            # Temporally smooth training: predict the state at t from t - dt by linear motion.
            dt = (2.0 * float(torch.rand(())) - 1.0) * c.smooth_dt
            means, logits = self.state_at(t - dt)
            means = means + self.average_velocity() * dt
        else:
            means, logits = self.state_at(t)
        p = self.gaussian_params
        return NodeOutput(Gaussians(means, p["quats"], p["scales"], logits, p["sh0"], p["shN"]), None, time)

    def regularization(self, output: NodeOutput) -> dict[str, torch.Tensor]:
        # Sparse velocity: most of a street scene is static.
        return {"pvg_velocity": self.average_velocity().abs().sum(-1).mean()}

    def gaussian_lrs(self):
        c = self.config
        lrs = super().gaussian_lrs()
        lrs.update(life_peak=(c.lr_life_peak, None), life_span=(c.lr_life_span, None),
                   velocity=(c.lr_velocity * self.scene_radius, None))
        return lrs
