"""Reference LiDAR rendering (the ``lidar`` capability) in PyTorch: project the Gaussians to
the sensor's sphere (:func:`omnire.api.project_lidar`), bin them into tiles of the sphere,
and composite each ray's tile list in order of centre distance, all differentiable by
autograd (contract in :mod:`omnire.rasterization`).

Rays are processed in chunks, grouped by the length of their tile's list so that padding
stays small, and each chunk's lists in slices, so no intermediate exceeds about
``chunk_elements`` (ray, Gaussian) pairs.
"""
from __future__ import annotations

import torch

from omnire.api import (
    ALPHA_THRESHOLD,
    MAX_ALPHA,
    TRANSMITTANCE_MIN,
    LidarRays,
    LidarRenderOutput,
    LidarSettings,
    SphereTiles,
    SphericalSplats,
    Splats,
    check_lidar_inputs,
    max_response_range,
    project_lidar,
    ray_directions,
    wrap_degrees,
)


def bin_pairs(proj: SphericalSplats, tiles: SphereTiles) -> tuple[torch.Tensor, torch.Tensor]:
    """(Gaussian, tile) pairs for every tile of each drawn Gaussian's box, sorted by tile
    then centre distance: Gaussian ids (M,) and tile ids (M,)."""
    with torch.no_grad():
        box = tiles.boxes(proj)  # (N, 4) first column, columns, first row, rows
        n = box[:, 1] * box[:, 3]
        g = torch.nonzero(n > 0).flatten()
        if g.numel() == 0:
            e = torch.zeros(0, dtype=torch.long, device=box.device)
            return e, e
        n, box = n[g], box[g]
        gids = torch.repeat_interleave(g, n)
        k = torch.arange(int(n.sum()), device=g.device) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
        ncol = torch.repeat_interleave(box[:, 1], n)
        col = torch.remainder(torch.repeat_interleave(box[:, 0], n) + k % ncol, tiles.columns)
        row = torch.repeat_interleave(box[:, 2], n) + k // ncol
        tile_ids = row * tiles.columns + col
        order = torch.argsort(proj.distance[gids], stable=True)
        gids, tile_ids = gids[order], tile_ids[order]
        order = torch.argsort(tile_ids, stable=True)
        return gids[order], tile_ids[order]


def rasterize_lidar(splats: Splats, rays: LidarRays, settings: LidarSettings = LidarSettings(),
                    chunk_elements: int = 2_000_000) -> LidarRenderOutput:
    """See :mod:`omnire.rasterization` for the contract (shapes and semantics)."""
    check_lidar_inputs(splats, rays, settings)
    colors, opacities = splats.colors, splats.opacities
    dev, dt = splats.means.device, splats.means.dtype
    R, F = len(rays), colors.shape[1]
    proj = project_lidar(splats, rays, settings.eps_deg2)
    tiles = SphereTiles.for_rays(rays)
    gids, tile_ids = bin_pairs(proj, tiles)
    counts = torch.bincount(tile_ids, minlength=tiles.count)
    starts = torch.cumsum(counts, 0) - counts
    ray_tile = tiles.of_rays(rays).to(dev)
    ray_az = rays.azimuth_deg.detach().to(device=dev, dtype=dt)
    ray_el = rays.elevation_deg.detach().to(device=dev, dtype=dt)
    dirs = ray_directions(ray_az, ray_el)
    probe = None if rays.probe_range is None else rays.probe_range.detach().to(device=dev, dtype=dt)

    # anchor the outputs to the graph even where nothing is drawn
    anchor = 0.0 * (colors.sum() + opacities.sum() + proj.conics.sum() + proj.quad.sum() + proj.lin.sum()
                    + proj.azimuth.sum() + proj.elevation.sum())
    per_ray = counts[ray_tile]
    order = torch.argsort(per_ray, stable=True)
    chunk = 4096
    parts, done_rays = [], []
    for i in range(0, R, chunk):
        idx = order[i: i + chunk]
        parts.append(_composite(idx, ray_tile[idx], ray_az[idx], ray_el[idx], dirs[idx], counts, starts, gids, proj,
                                colors, rays, chunk_elements, None if probe is None else probe[idx]))
        done_rays.append(idx)
    feat = torch.zeros(R, F, device=dev, dtype=dt) + anchor
    rsum = torch.zeros(R, device=dev, dtype=dt) + anchor
    alpha = torch.zeros(R, device=dev, dtype=dt) + anchor
    median = torch.full((R,), float(rays.max_range), device=dev, dtype=dt) + anchor
    light = None if probe is None else torch.ones(R, device=dev, dtype=dt) + anchor
    if parts:
        idx = torch.cat(done_rays)
        feat = feat.index_copy(0, idx, torch.cat([p[0] for p in parts]))
        rsum = rsum.index_copy(0, idx, torch.cat([p[1] for p in parts]))
        alpha = alpha.index_copy(0, idx, torch.cat([p[2] for p in parts]))
        median = median.index_copy(0, idx, torch.cat([p[3] for p in parts]))
        if light is not None:
            light = light.index_copy(0, idx, torch.cat([p[4] for p in parts]))
    return LidarRenderOutput(range=rsum / alpha.clamp_min(1e-10), median_range=median, features=feat, alpha=alpha,
                             probe_transmittance=light)


def _composite(idx, tile, az, el, dirs, counts, starts, gids, proj, colors, rays, chunk_elements, probe=None):
    """Composite the rays ``idx`` (C,) (tile (C,), azimuth, elevation (C,), directions
    (C, 3), probe ranges (C,) or None) over their tiles' lists. Returns features (C, F),
    range sum (C,), alpha (C,), median range (C,), transmittance at the probe (C,) or None."""
    dev, dt = colors.device, colors.dtype
    C = len(idx)
    n = counts[tile]
    s = starts[tile]
    kmax = int(n.max()) if C else 0
    feat = torch.zeros(C, colors.shape[1], device=dev, dtype=dt)
    rsum = torch.zeros(C, device=dev, dtype=dt)
    median = torch.zeros(C, device=dev, dtype=dt)
    crossed = torch.zeros(C, dtype=torch.bool, device=dev)
    trans = torch.ones(C, device=dev, dtype=dt)
    done = torch.zeros(C, dtype=torch.bool, device=dev)
    light = None if probe is None else torch.ones(C, device=dev, dtype=dt)
    kc = max(1, min(kmax, chunk_elements // max(1, C)))
    for k0 in range(0, kmax, kc):
        k = torch.arange(k0, min(k0 + kc, kmax), device=dev)
        valid = k[None, :] < n[:, None]  # (C, kc)
        g = torch.where(valid, gids[torch.where(valid, s[:, None] + k[None, :], torch.zeros_like(k[None, :]))],
                        torch.zeros_like(k[None, :]))
        dx = wrap_degrees(az[:, None] - proj.azimuth[g])
        de = el[:, None] - proj.elevation[g]
        con = proj.conics[g]  # (C, kc, 3)
        power = -0.5 * (con[..., 0] * dx * dx + con[..., 2] * de * de) - con[..., 1] * dx * de
        a = torch.clamp(proj.opacities[g] * torch.exp(torch.clamp(power, max=0.0)), max=MAX_ALPHA)
        r, defined = max_response_range(proj.quad[g], proj.lin[g], dirs[:, None, :])
        keep = (valid & (power <= 0) & (a >= ALPHA_THRESHOLD) & defined & (r >= rays.min_range)
                & (r <= rays.max_range))
        a = torch.where(keep, a, torch.zeros_like(a))
        cum = trans[:, None] * torch.cumprod(1.0 - a, dim=-1)  # transmittance after each
        alive = (cum > TRANSMITTANCE_MIN) & ~done[:, None]  # a prefix along k
        before = torch.cat([trans[:, None], cum[:, :-1]], dim=-1)
        w = a * before * alive
        feat = feat + torch.einsum("ck,ckf->cf", w, colors[g])
        rsum = rsum + (w * r).sum(-1)
        crossing = alive & keep & (before > 0.5) & (cum <= 0.5)  # at most one per ray over all slices
        median = median + torch.where(crossing, r, torch.zeros_like(r)).sum(-1)
        crossed = crossed | crossing.any(-1)
        if light is not None:
            before_probe = alive & (r < probe[:, None])
            light = light * torch.where(before_probe, 1.0 - a, torch.ones_like(a)).prod(-1)
        trans = trans * torch.where(alive, 1.0 - a, torch.ones_like(a)).prod(-1)
        done = done | ~(cum > TRANSMITTANCE_MIN).all(-1)
    median = torch.where(crossed, median, torch.full_like(median, float(rays.max_range)))
    return feat, rsum, 1.0 - trans, median, light
