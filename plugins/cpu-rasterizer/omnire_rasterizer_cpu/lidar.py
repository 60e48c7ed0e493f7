"""The ``lidar`` capability of the cpu rasterizer: the projection to the sensor's sphere in
torch (:func:`omnire.api.project_lidar`, differentiable, shared with the reference), the
binning and compositing of the rays and their backward natively (csrc/lidar.cpp, OpenMP
over tiles of the sphere). float64 inputs run the double-precision kernel (gradient
checks); anything else runs in float32.
"""
from __future__ import annotations

import torch

from omnire.api import (
    LidarRays,
    LidarRenderOutput,
    LidarSettings,
    RasterInputError,
    SphereTiles,
    Splats,
    check_lidar_inputs,
    project_lidar,
    ray_directions,
)

from ._build import lidar_extension


class _LidarFn(torch.autograd.Function):
    """(azimuth (N,), elevation (N,), opacities (N,), conics (N,3), quad (N,6), lin (N,3),
    features (N,F)) -> (features (R,F), range sum (R,), alpha (R,), median range (R,)).

    ``meta``: the drawn Gaussians by centre distance (n,), their tile boxes (N,4), the rays'
    azimuths in [0, 360) (R,), elevations (R,), directions (R,3) and tiles (R,), the tiling's
    columns and tile count, min_range, max_range, threads. The rays take no gradient."""

    @staticmethod
    def forward(ctx, az, el, opac, conics, quad, lin, feat, meta):
        order, box, ray_az, ray_el, dirs, ray_tile, columns, tiles, rmin, rmax, nthreads = meta
        o_feat, o_rsum, o_alpha, o_median, rec, goff, gids, roff, rids = lidar_extension().lidar_forward(
            az, el, opac, conics, quad, lin, feat, order, box, ray_az, ray_el, dirs, ray_tile, columns, tiles, rmin,
            rmax, nthreads)
        ctx.save_for_backward(rec, feat, goff, gids, roff, rids, ray_az, ray_el, dirs, o_feat, o_rsum, o_alpha)
        ctx.meta = (rmin, rmax, nthreads)
        return o_feat, o_rsum, o_alpha, o_median

    @staticmethod
    def backward(ctx, g_feat, g_rsum, g_alpha, g_median):
        rec, feat, goff, gids, roff, rids, ray_az, ray_el, dirs, o_feat, o_rsum, o_alpha = ctx.saved_tensors
        rmin, rmax, nthreads = ctx.meta

        def grad_or_zeros(g, like):
            return torch.zeros_like(like) if g is None else g.contiguous().to(like.dtype)

        grads = lidar_extension().lidar_backward(
            rec, feat, goff, gids, roff, rids, ray_az, ray_el, dirs, o_feat, o_rsum, o_alpha,
            grad_or_zeros(g_feat, o_feat), grad_or_zeros(g_rsum, o_rsum), grad_or_zeros(g_alpha, o_alpha),
            grad_or_zeros(g_median, o_alpha), rmin, rmax, nthreads).to(rec.dtype)
        # slots: azimuth, elevation, conic a b c, opacity, quad (6), lin (3), features (F)
        return grads[:, 0], grads[:, 1], grads[:, 5], grads[:, 2:5], grads[:, 6:12], grads[:, 12:15], grads[:, 15:], None


def rasterize_lidar(splats: Splats, rays: LidarRays, settings: LidarSettings, num_threads: int) -> LidarRenderOutput:
    """See :mod:`omnire.rasterization` for the contract (shapes and semantics)."""
    check_lidar_inputs(splats, rays, settings)
    tensors = (splats.means, splats.quats, splats.scales, splats.opacities, splats.colors, rays.sensor_to_world,
               rays.azimuth_deg, rays.elevation_deg)
    if any(t.device.type != "cpu" for t in tensors):
        raise RasterInputError("the cpu rasterizer needs CPU tensors")
    dtype = torch.float64 if splats.means.dtype == torch.float64 else torch.float32
    splats = Splats(*(t.to(dtype) for t in (splats.means, splats.quats, splats.scales, splats.opacities,
                                             splats.colors)))
    proj = project_lidar(splats, rays, settings.eps_deg2)
    tiles = SphereTiles.for_rays(rays)
    with torch.no_grad():
        drawn = torch.nonzero(proj.visible).flatten()
        order = drawn[torch.argsort(proj.distance[drawn], stable=True)].contiguous()
        box = tiles.boxes(proj).contiguous()
        ray_az = torch.remainder(rays.azimuth_deg.detach().to(torch.float64), 360.0).to(dtype)
        ray_el = rays.elevation_deg.detach().to(dtype)
        dirs = ray_directions(ray_az, ray_el).contiguous()
        ray_tile = tiles.of_rays(rays).contiguous()
    meta = (order, box, ray_az.contiguous(), ray_el.contiguous(), dirs, ray_tile, tiles.columns, tiles.count,
            float(rays.min_range), float(rays.max_range), int(num_threads))
    feat, rsum, alpha, median = _LidarFn.apply(
        proj.azimuth.contiguous(), proj.elevation.contiguous(), proj.opacities.contiguous(), proj.conics.contiguous(),
        proj.quad.contiguous(), proj.lin.contiguous(), splats.colors.contiguous(), meta)
    return LidarRenderOutput(range=rsum / alpha.clamp_min(1e-10), median_range=median, features=feat, alpha=alpha)
