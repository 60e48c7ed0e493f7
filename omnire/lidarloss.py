"""LiDAR loss terms of a rendered sweep against the recorded one (weights:
:class:`omnire.lidarmodel.LidarConfig`, defaults and where they come from there).

- ``lidar_range``: mean |rendered expected range - measured range| over the rays that
  returned (metres);
- ``lidar_median_range``: the same for the rendered median range (the range of the Gaussian
  at which the ray's transmittance falls to 0.5; ``max_range`` where it never does, which
  then takes no gradient);
- ``lidar_intensity``: mean squared intensity error over the returned rays whose intensity
  was recorded;
- ``lidar_surface``: mean transmittance left ``surface_margin`` metres past the return over
  the rays that returned and were probed there (the render's ``probe_transmittance`` at
  :func:`line_of_sight_probes`): light that passes the return means the surface is too faint;
- ``lidar_free_space``: mean opacity met before ``surface_margin`` in front of the return
  over the rays probed there: what the ray crossed before its return is empty;
- ``lidar_ray_drop``: binary cross-entropy of the rendered ray-drop probability against
  "this ray returned nothing", over every ray, only when the sweep's missing returns are
  known (:attr:`omnire.lidarsweep.SweepRays.drops_known`); otherwise the returned rays alone
  would teach that nothing ever drops.

A term whose rays are absent (or whose weight is 0) is left out.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from omnire.lidarmodel import LidarConfig, LidarRender
from omnire.lidarsweep import SweepRays


@dataclasses.dataclass(frozen=True)
class LineOfSightProbes:
    """Where each ray of a sweep is probed (R rays): ``range`` (R,) metres (0 where unused),
    ``past`` (R,) bool the rays probed past their return, ``before`` (R,) bool those probed
    in front of it."""

    range: np.ndarray
    past: np.ndarray
    before: np.ndarray


def line_of_sight_probes(sweep: SweepRays, config: LidarConfig, generator: Optional[torch.Generator] = None
                         ) -> Optional[LineOfSightProbes]:
    """The probes of ``lidar_surface`` and ``lidar_free_space`` on ``sweep``'s returned rays
    (not those at a depth edge, :attr:`SweepRays.depth_edge`, where a ray grazing a
    silhouette says nothing of either surface): ``surface_margin`` past the return, in front
    of it, or (both terms on) one side per ray drawn from ``generator`` with even odds. None
    when both terms are off."""
    if not (config.surface_weight or config.free_space_weight):
        return None
    returned = np.asarray(sweep.returned, dtype=bool)
    if sweep.depth_edge is not None:
        returned = returned & ~sweep.depth_edge
    if config.surface_weight and config.free_space_weight:
        coin = torch.rand(len(returned), generator=generator).numpy() < 0.5
    else:
        coin = np.full(len(returned), bool(config.surface_weight))
    past, before = returned & coin, returned & ~coin
    measured = np.nan_to_num(np.asarray(sweep.range, dtype=np.float64))
    probe = np.where(past, measured + config.surface_margin, np.where(before, measured - config.surface_margin, 0.0))
    return LineOfSightProbes(probe, past, before)


def lidar_loss_terms(render: LidarRender, sweep: SweepRays, config: LidarConfig,
                     probes: Optional[LineOfSightProbes] = None) -> dict[str, torch.Tensor]:
    """Weighted LiDAR loss terms (name -> scalar) of ``render`` (R rays) against ``sweep``
    (the same R rays, in the same order); ``probes``: where ``render`` was probed
    (:func:`line_of_sight_probes`), needed by ``lidar_surface`` and ``lidar_free_space``."""
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
        if config.surface_weight or config.free_space_weight:
            if probes is None or render.probe_transmittance is None:
                raise ValueError("lidar_loss_terms: surface_weight and free_space_weight need a render probed at "
                                 "line_of_sight_probes(sweep) and those probes")
            light = render.probe_transmittance
            for name, weight, rays, value in (("lidar_surface", config.surface_weight, probes.past, light),
                                              ("lidar_free_space", config.free_space_weight, probes.before, 1 - light)):
                if weight and rays.any():
                    terms[name] = weight * value[torch.as_tensor(rays, device=device)].mean()
    measured = sweep.returned & np.isfinite(sweep.intensity)
    if config.intensity_weight and measured.any():
        rows = torch.as_tensor(np.flatnonzero(measured), device=device)
        target = torch.as_tensor(sweep.intensity[measured], dtype=render.intensity.dtype, device=device)
        terms["lidar_intensity"] = config.intensity_weight * ((render.intensity[rows] - target) ** 2).mean()
    if config.ray_drop_weight and sweep.drops_known and len(sweep):
        drop = render.ray_drop.clamp(1e-6, 1 - 1e-6)
        terms["lidar_ray_drop"] = config.ray_drop_weight * F.binary_cross_entropy(drop, (~returned).to(drop.dtype))
    return terms
