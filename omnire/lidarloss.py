"""LiDAR loss terms of a rendered sweep against the recorded one (weights:
:class:`omnire.lidarmodel.LidarConfig`, defaults and where they come from there).

- ``lidar_range``: mean |rendered expected range - measured range| over the rays that
  returned (metres);
- ``lidar_median_range``: the same for the rendered median range (the range of the Gaussian
  at which the ray's transmittance falls to 0.5; ``max_range`` where it never does, which
  then takes no gradient);
- ``lidar_intensity``: mean squared intensity error over the returned rays whose intensity
  was recorded;
- ``lidar_ray_drop``: binary cross-entropy of the rendered ray-drop probability against
  "this ray returned nothing", over every ray, only when the sweep's missing returns are
  known (:attr:`omnire.lidarsweep.SweepRays.drops_known`); otherwise the returned rays alone
  would teach that nothing ever drops.

A term whose rays are absent (or whose weight is 0) is left out.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from omnire.lidarmodel import LidarConfig, LidarRender
from omnire.lidarsweep import SweepRays


def lidar_loss_terms(render: LidarRender, sweep: SweepRays, config: LidarConfig) -> dict[str, torch.Tensor]:
    """Weighted LiDAR loss terms (name -> scalar) of ``render`` (R rays) against ``sweep``
    (the same R rays, in the same order)."""
    if len(render.range) != len(sweep):
        raise ValueError(f"lidar_loss_terms: {len(render.range)} rendered rays for a sweep of {len(sweep)}")
    device = render.range.device
    returned = torch.as_tensor(sweep.returned, device=device)
    terms: dict[str, torch.Tensor] = {}
    if bool(returned.any()):
        target = torch.as_tensor(sweep.range[sweep.returned], dtype=render.range.dtype, device=device)
        if config.range_weight:
            terms["lidar_range"] = config.range_weight * (render.range[returned] - target).abs().mean()
        if config.median_range_weight:
            terms["lidar_median_range"] = (config.median_range_weight
                                           * (render.median_range[returned] - target).abs().mean())
    measured = sweep.returned & np.isfinite(sweep.intensity)
    if config.intensity_weight and measured.any():
        rows = torch.as_tensor(np.flatnonzero(measured), device=device)
        target = torch.as_tensor(sweep.intensity[measured], dtype=render.intensity.dtype, device=device)
        terms["lidar_intensity"] = config.intensity_weight * ((render.intensity[rows] - target) ** 2).mean()
    if config.ray_drop_weight and sweep.drops_known and len(sweep):
        drop = render.ray_drop.clamp(1e-6, 1 - 1e-6)
        terms["lidar_ray_drop"] = config.ray_drop_weight * F.binary_cross_entropy(drop, (~returned).to(drop.dtype))
    return terms
