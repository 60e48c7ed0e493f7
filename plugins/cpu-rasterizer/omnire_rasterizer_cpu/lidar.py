"""The ``lidar`` capability of the cpu rasterizer, natively (csrc/lidar.cpp): the projection
to the sensor's sphere (the numbers of :func:`omnire.api.project_lidar`, in double) and its
backward, then the binning of rays and Gaussians into tiles of the sphere (the tiling of
:class:`omnire.api.SphereTiles`) and the compositing with its backward (OpenMP). float64
inputs run the double-precision kernels (gradient checks); anything else runs in float32.
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
)

from ._build import lidar_extension


class _ProjectFn(torch.autograd.Function):
    """(means (N,3), quats (N,4), scales (N,3)) -> azimuth, elevation (N,), conics (N,3),
    quad (N,6), lin (N,3), and without gradient distance (N,), extent (N,2), visible (N,)
    (:class:`omnire.api.SphericalSplats`). ``meta``: opacities (N,) (they only decide what
    is drawn here), the pose (4,4) float64, eps_deg2, min_range, max_range, threads."""

    @staticmethod
    def forward(ctx, means, quats, scales, meta):
        opac, pose, eps, rmin, rmax, nthreads = meta
        out = lidar_extension().lidar_project(means, quats, scales, opac, pose, eps, rmin, rmax, nthreads)
        ctx.save_for_backward(means, quats, scales, opac, pose)
        ctx.meta = (eps, rmin, rmax, nthreads)
        ctx.mark_non_differentiable(*out[5:])
        return tuple(out)

    @staticmethod
    def backward(ctx, g_az, g_el, g_con, g_quad, g_lin, _g_dist, _g_ext, _g_vis):
        means, quats, scales, opac, pose = ctx.saved_tensors
        eps, rmin, rmax, nthreads = ctx.meta
        grads = [torch.zeros(shape, dtype=means.dtype) if g is None else g.contiguous().to(means.dtype)
                 for g, shape in ((g_az, (len(means),)), (g_el, (len(means),)), (g_con, (len(means), 3)),
                                  (g_quad, (len(means), 6)), (g_lin, (len(means), 3)))]
        g_means, g_quats, g_scales = lidar_extension().lidar_project_backward(
            means, quats, scales, opac, pose, eps, rmin, rmax, *grads, nthreads)
        return g_means, g_quats, g_scales, None


class _LidarFn(torch.autograd.Function):
    """(azimuth (N,), elevation (N,), opacities (N,), conics (N,3), quad (N,6), lin (N,3),
    features (N,F)) -> (features (R,F), range sum (R,), alpha (R,), median range (R,),
    transmittance at the probes (R,), or (0,) without probes).

    ``meta``: the projection's distance (N,), extent (N,2) and visible (N,), the rays'
    azimuths and elevations (R,), the tiling (:class:`omnire.api.SphereTiles`), min_range,
    max_range, the probe ranges (R,) or (0,), threads. The rays take no gradient."""

    @staticmethod
    def forward(ctx, az, el, opac, conics, quad, lin, feat, meta):
        distance, extent, visible, ray_az, ray_el, tiles, rmin, rmax, probe, nthreads = meta
        (o_feat, o_rsum, o_alpha, o_median, rec, goff, gids, roff, rids, ray_az, dirs,
         o_probe) = lidar_extension().lidar_forward(
            az, el, opac, conics, quad, lin, feat, distance, extent, visible, ray_az, ray_el, tiles.columns,
            tiles.rows, tiles.column_deg, tiles.row_deg, tiles.first_elevation, rmin, rmax, probe, nthreads)
        ctx.save_for_backward(rec, feat, goff, gids, roff, rids, ray_az, ray_el, dirs, o_feat, o_rsum, o_alpha,
                              probe, o_probe)
        ctx.meta = (rmin, rmax, nthreads)
        return o_feat, o_rsum, o_alpha, o_median, o_probe

    @staticmethod
    def backward(ctx, g_feat, g_rsum, g_alpha, g_median, g_probe):
        (rec, feat, goff, gids, roff, rids, ray_az, ray_el, dirs, o_feat, o_rsum, o_alpha, probe,
         o_probe) = ctx.saved_tensors
        rmin, rmax, nthreads = ctx.meta

        def grad_or_zeros(g, like):
            return torch.zeros_like(like) if g is None else g.contiguous().to(like.dtype)

        grads = lidar_extension().lidar_backward(
            rec, feat, goff, gids, roff, rids, ray_az, ray_el, dirs, o_feat, o_rsum, o_alpha,
            grad_or_zeros(g_feat, o_feat), grad_or_zeros(g_rsum, o_rsum), grad_or_zeros(g_alpha, o_alpha),
            grad_or_zeros(g_median, o_alpha), rmin, rmax, probe, o_probe, grad_or_zeros(g_probe, o_probe),
            nthreads).to(rec.dtype)
        # slots: azimuth, elevation, conic a b c, opacity, quad (6), lin (3), features (F)
        return (grads[:, 0], grads[:, 1], grads[:, 5], grads[:, 2:5], grads[:, 6:12], grads[:, 12:15], grads[:, 15:],
                None)


def rasterize_lidar(splats: Splats, rays: LidarRays, settings: LidarSettings, num_threads: int) -> LidarRenderOutput:
    """See :mod:`omnire.rasterization` for the contract (shapes and semantics)."""
    check_lidar_inputs(splats, rays, settings)
    tensors = (splats.means, splats.quats, splats.scales, splats.opacities, splats.colors, rays.sensor_to_world,
               rays.azimuth_deg, rays.elevation_deg)
    if any(t.device.type != "cpu" for t in tensors):
        raise RasterInputError("the cpu rasterizer needs CPU tensors")
    dtype = torch.float64 if splats.means.dtype == torch.float64 else torch.float32
    means, quats, scales, opacities, colors = (t.to(dtype).contiguous() for t in (
        splats.means, splats.quats, splats.scales, splats.opacities, splats.colors))
    pose = rays.sensor_to_world.detach().to(torch.float64).contiguous()
    az, el, conics, quad, lin, distance, extent, visible = _ProjectFn.apply(
        means, quats, scales, (opacities.detach(), pose, float(settings.eps_deg2), float(rays.min_range),
                               float(rays.max_range), int(num_threads)))
    probe = (torch.zeros(0, dtype=dtype) if rays.probe_range is None
             else rays.probe_range.detach().to(dtype).contiguous())
    meta = (distance, extent, visible, rays.azimuth_deg.detach().to(dtype).contiguous(),
            rays.elevation_deg.detach().to(dtype).contiguous(), SphereTiles.for_rays(rays), float(rays.min_range),
            float(rays.max_range), probe, int(num_threads))
    feat, rsum, alpha, median, light = _LidarFn.apply(az, el, opacities, conics, quad, lin, colors, meta)
    return LidarRenderOutput(range=rsum / alpha.clamp_min(1e-10), median_range=median, features=feat, alpha=alpha,
                             probe_transmittance=None if rays.probe_range is None else light)
