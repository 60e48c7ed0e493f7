"""Learned LiDAR appearance: the per-Gaussian features a LiDAR sensor renders and what a
rendered ray makes of them (docs/lidar.md, "Learned LiDAR appearance").

With ``--method.lidar.enabled`` on a scene that has LiDAR, every Gaussian node gets one more
per-Gaussian parameter, :data:`LIDAR_KEY` (N, 2) raw logits: the return intensity and the
ray-drop probability of the Gaussian's surface (sigmoid-activated). Being a per-Gaussian
parameter like the colour, it is cloned, split and pruned by densification, cut by
compaction, saved in checkpoints and exported. Without the flag, or on a scene without
LiDAR, the parameter does not exist: nothing is stored, stepped or rendered.

A sweep renders the activated features through the rasterizer's ``rasterize_lidar``
(omnire/rasterization.py) and turns them into per-ray outputs (:func:`decode`):

- intensity: the features' first channel normalised by the ray's opacity, as the expected
  range is (an intensity given that the ray returns);
- ray-drop probability: ``sum_i w_i d_i + (1 - alpha)``: the Gaussians' drop probabilities
  weighted as they are composited, and a ray that meets nothing (transparent, e.g. the sky)
  returns nothing.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np
import torch

from omnire.data.scene import SceneDataError

LIDAR_KEY = "lidar"
"""Per-Gaussian parameter key of the LiDAR features (N, 2): intensity logit, ray-drop logit."""

LIDAR_CHANNELS = ("intensity", "ray_drop")
"""The feature channels, in column order."""


@dataclasses.dataclass
class LidarConfig:
    """LiDAR as a rendered sensor: learned per-Gaussian intensity and ray drop, LiDAR losses.

    Intensity and ray-drop weights are SplatAD's (neurad-studio ``SplatADModelConfig``:
    intensity 1.0 as an L2, ray drop 0.1 as a binary cross-entropy; its depth weight is 0.1 as
    an L1, kept here on the expected range); the median range's is 0.5. On the synthetic scene
    of tests/lidar_scene.py (300 steps, a pose off the path) the expected range alone at 0.1
    renders the expected range 6.8 cm off and the median 22 cm; adding the median at 0.5
    brings both to 4.6-4.9 cm with the same ray-drop agreement (99.6%), whereas the expected
    range at 0.5 thins the surfaces (alpha below 0.5 on 10% of the returning rays, ray-drop
    agreement 90%). The line-of-sight pair (surface and free space, 0.1 each, 0.1 m from the
    return) is this project's: on the PandaSet demo cut with its complete sweeps (seed 0,
    3000 steps, a LiDAR step every 4) it took the held-out median range error from 4.4 to 3.7 cm, the Chamfer
    distance from 0.233 to 0.199 m and the vehicle-box median from 6.3 to 5.4 cm, camera NVS
    +0.07 dB (docs/lidar.md). The OmniRe paper's code renders no LiDAR and has none."""

    enabled: bool = False
    """Learn LiDAR intensity and ray drop on every Gaussian and train on rendered sweeps
    (needs a rasterizer with the ``lidar`` capability and a scene with LiDAR)."""
    every: int = 2
    """A training step also renders a LiDAR sweep every this many steps. On the demo cut with
    its complete sweeps (3000 steps, seed 0) every 2 against every 4 took the vehicle-box
    median from 5.4 to 4.4 cm and the Chamfer distance from 0.199 to 0.184 m, at about 1.6x
    the training time (1.6 against 2.6 it/s on 2 threads; docs/lidar.md)."""
    rays_per_step: int = 32768
    """Rays of the sweep rendered in such a step (a random subset; 0: every ray). A step's cost
    is mostly per Gaussian (projection, binning, sorting), so more rays cost little more: on
    the demo cut (316k Gaussians, 1 thread, loaded) 16k rays took 2.3 s, 65k 3.2 s, all 115k 4.0 s."""
    range_weight: float = 0.1
    """Weight of the L1 range error on rays that returned."""
    median_range_weight: float = 0.5
    """Weight of the L1 error of the median range (the range of the Gaussian at which the
    ray's transmittance falls to 0.5) on rays that returned: it moves the surface the ray
    stops at onto the return, which the expected range alone leaves blurred between the
    Gaussians along the ray."""
    intensity_weight: float = 1.0
    """Weight of the squared intensity error on rays that returned."""
    ray_drop_weight: float = 0.1
    """Weight of the ray-drop binary cross-entropy (returned vs missing rays; needs the
    sweep's beams and beam model to know the missing ones)."""
    surface_weight: float = 0.3
    """Weight of the transmittance left ``surface_margin`` past the return on rays that
    returned (:func:`omnire.lidarloss.lidar_loss_terms`, ``lidar_surface``): the one term
    that makes a surface the ray passes through opaque where it returned. The median range
    moves only the Gaussian the ray stops at, and the expected range is normalised by the
    ray's opacity, so neither raises the opacity of a faint surface in front of what the
    ray stops at (the side of a car seen by the LiDAR alone). On the demo cut with its
    complete sweeps (3000 steps, two seeds, docs/lidar.md) 0.3 for both weights against 0.1
    took the vehicle-box median from 4.4-4.5 to 4.2 cm, at equal camera NVS once depth edges
    are skipped (``probe_edge_jump``)."""
    free_space_weight: float = 0.3
    """Weight of the opacity met before ``surface_margin`` in front of the return on rays that
    returned (``lidar_free_space``): what the ray crossed before its return is empty. With
    ``surface_weight`` too, each returned ray of a step is probed on one side, drawn at
    random (half each), as a render reads the transmittance at one probe per ray."""
    probe_edge_jump: Optional[float] = 0.1
    """The line-of-sight pair skips returns at a depth edge of their sweep's range image: a
    grid neighbour that returned nothing or at a range differing by more than this fraction
    of the return's (:func:`omnire.lidarsweep.depth_edges`). A ray grazing a silhouette
    returns from whichever surface its footprint met first, so the pair would erode the
    silhouettes the cameras see. On the demo cut (weights 0.3, two seeds) skipping them kept
    camera NVS within 0.03 / 0.12 dB of training without LiDAR, against 0.25 / 0.17 dB
    lower when every return was probed, for the same LiDAR figures (docs/lidar.md); on the
    ray-traced test scene, whose edges are exact, skipping them costs a little (median range
    error off the path 2.7 -> 3.4 cm). None: probe every return."""
    surface_margin: float = 0.1
    """Metres from the return at which ``surface_weight`` and ``free_space_weight`` read the
    transmittance (past it and in front of it)."""
    lr: float = 0.01
    """Adam learning rate of the feature logits."""
    init_ray_drop: float = 0.05
    """Initial ray-drop probability of every Gaussian."""
    sectors: int = 4
    """Time sectors a sweep is rendered in (rolling shutter): the rays of each sector see the
    scene at the sector's middle time (1: the whole sweep at one moment). A sector's rays leave
    from the pose at its middle time: at 10 m/s and 0.1 s a sweep, 4 sectors put a ray's
    origin up to 12.5 cm off (omnire/rollingshutter.py); more cost more (one LiDAR render each)."""

    def __post_init__(self) -> None:
        from omnire.errors import ConfigError

        for name in ("every", "sectors"):
            if getattr(self, name) < 1:
                raise ConfigError(f"--method.lidar.{name} {getattr(self, name)}: must be >= 1")
        if self.rays_per_step < 0:
            raise ConfigError(f"--method.lidar.rays-per-step {self.rays_per_step}: must be >= 0 (0: every ray)")
        for name in ("range_weight", "median_range_weight", "intensity_weight", "ray_drop_weight", "surface_weight",
                     "free_space_weight", "surface_margin", "lr"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ConfigError(f"--method.lidar.{name.replace('_', '-')} {value}: must be a finite number >= 0")
        if not 0.0 < self.init_ray_drop < 1.0:
            raise ConfigError(f"--method.lidar.init-ray-drop {self.init_ray_drop}: expected a probability in (0, 1)")


@dataclasses.dataclass(frozen=True)
class LidarFeatures:
    """What a node needs to hold LiDAR features: their initial activated values and lr."""

    init_intensity: float
    init_ray_drop: float
    lr: float

    def initial(self, n: int, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(n, 2) raw logits of the initial values."""
        values = torch.tensor([self.init_intensity, self.init_ray_drop], dtype=dtype, device=device)
        return torch.logit(values.clamp(1e-4, 1 - 1e-4)).expand(n, 2).clone()


def lidar_features_for(config: LidarConfig, scene) -> Optional[LidarFeatures]:
    """The features the nodes of a method with ``config`` hold on ``scene``: None when LiDAR
    rendering is off or the scene has no LiDAR. Intensity starts at the median return
    intensity of the training sweeps (0.5 when the dataset records none, or when it is not
    learned and leaves [0, 1]).

    Raises SceneDataError when intensity is learned (``intensity_weight`` > 0) and a sweep's
    intensity leaves [0, 1], the range of the sigmoid that predicts it: a squared error
    against targets on another scale (a file's 0-255) would swamp every other loss term."""
    lidar = getattr(scene, "lidar", None)
    if not config.enabled or lidar is None:
        return None
    intensity = 0.5
    if lidar.intensity is not None:
        outside = _outside_unit(lidar.intensity)
        if outside is not None and config.intensity_weight > 0:
            frame, value = outside
            raise SceneDataError(
                f"scene {scene.name!r}: lidar.intensity[{frame}] holds {value:g}, expected values in [0, 1] (readers "
                "map their files' scale, docs/lidar.md \"Intensity scales\"); --method.lidar.intensity-weight 0 "
                "learns range and ray drop only")
        values = [lidar.intensity[int(f)] for f in scene.train_frames if lidar.intensity[int(f)] is not None]
        if values and outside is None:
            intensity = float(np.median(np.concatenate(values)))
    return LidarFeatures(intensity, config.init_ray_drop, config.lr)


def _outside_unit(intensity: list[Optional[np.ndarray]]) -> Optional[tuple[int, float]]:
    """(frame, value) of the first intensity outside [0, 1] (NaN included), or None."""
    for t, v in enumerate(intensity):
        if v is not None and len(v):
            bad = ~((v >= 0) & (v <= 1))
            if bad.any():
                return t, float(v[bad][0])
    return None


def activate(raw: torch.Tensor) -> torch.Tensor:
    """(N, 2) logits -> (N, 2) intensity and ray-drop probability in [0, 1]."""
    return torch.sigmoid(raw)


def decode(features: torch.Tensor, alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered features (R, 2) = sum_i w_i f_i and opacity alpha (R,) -> (intensity (R,),
    ray-drop probability (R,)) as the module docstring defines them."""
    intensity = features[:, 0] / alpha.clamp_min(1e-10)
    drop = (features[:, 1] + (1.0 - alpha)).clamp(0.0, 1.0)
    return intensity, drop


@dataclasses.dataclass
class LidarRender:
    """A rendered sweep, per ray (R rays).

    Attributes:
        range: (R,) expected range in metres (sum_i w_i r_i / alpha).
        median_range: (R,) range where the transmittance falls to 0.5 (the rasterizer's
            definition).
        intensity: (R,) return intensity in [0, 1] (see :func:`decode`).
        ray_drop: (R,) probability that the ray returns nothing.
        alpha: (R,) opacity accumulated along the ray.
        num_gaussians: Gaussians handed to the rasterizer.
        probe_transmittance: (R,) the transmittance left at each ray's probe range, when the
            rays had probes (:class:`omnire.rasterization.LidarRays`), else None.
    """

    range: torch.Tensor
    median_range: torch.Tensor
    intensity: torch.Tensor
    ray_drop: torch.Tensor
    alpha: torch.Tensor
    num_gaussians: int = 0
    probe_transmittance: Optional[torch.Tensor] = None

    @staticmethod
    def cat(parts: list["LidarRender"], order: Optional[torch.Tensor] = None) -> "LidarRender":
        """Concatenate renders of disjoint ray sets; ``order`` (R,) puts ray k of the
        concatenation at position ``order[k]`` (e.g. back in the sweep's order)."""
        fields = ("range", "median_range", "intensity", "ray_drop", "alpha")
        if parts and all(p.probe_transmittance is not None for p in parts):
            fields += ("probe_transmittance",)
        cat = {f: torch.cat([getattr(p, f) for p in parts]) for f in fields}
        if order is not None:
            inverse = torch.empty_like(order)
            inverse[order] = torch.arange(len(order), device=order.device)
            cat = {f: v[inverse] for f, v in cat.items()}
        return LidarRender(**cat, num_gaussians=max((p.num_gaussians for p in parts), default=0))
