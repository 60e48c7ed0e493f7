"""Reference tile-based rasterizer: project, bin into 16x16 tiles, sort by depth,
alpha-composite front to back, all in PyTorch so autograd gives every gradient.

Memory grows with (Gaussian, tile) pairs x 256 pixels; work is chunked over tiles and over
each tile's depth-sorted list so no intermediate exceeds ~``chunk_elements`` elements.
AbsGrad (per-Gaussian sum over pixels of |dL/dmeans2d|) is collected by a hook on the
per-pixel offset tensor, so it is exact per pixel, like gsplat's.
"""
from __future__ import annotations

import math

import torch

from omnire.api import (
    ALPHA_THRESHOLD,
    MAX_ALPHA,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    Camera,
    LidarRays,
    LidarRenderOutput,
    LidarSettings,
    RasterSettings,
    RenderOutput,
    Splats,
    check_raster_inputs,
)
from omnire_rasterizer_torch.lidar import rasterize_lidar
from omnire_rasterizer_torch.projection import project_gaussians


class TorchRasterizer:
    name = "torch"

    def __init__(self, chunk_elements: int = 2_000_000) -> None:
        self.chunk_elements = chunk_elements

    def rasterize(self, splats: Splats, camera: Camera, settings: RasterSettings = RasterSettings()) -> RenderOutput:
        """See :mod:`omnire.rasterization` for the contract (shapes and semantics)."""
        check_raster_inputs(splats, camera, settings)
        means, quats, scales, opacities, colors = (splats.means, splats.quats, splats.scales, splats.opacities,
                                                   splats.colors)
        viewmat, K, width, height = camera.world_to_cam, camera.K, camera.width, camera.height
        near, far, eps2d, background = settings.near, settings.far, settings.eps2d, settings.background
        N, D = colors.shape
        dev, dt = means.device, means.dtype
        proj = project_gaussians(means, quats, scales, viewmat, K, width, height, near, far, eps2d)
        absgrad = torch.zeros(N, 2, device=dev, dtype=dt)

        tiles_x = math.ceil(width / TILE_SIZE)
        tiles_y = math.ceil(height / TILE_SIZE)
        gids, tile_ids = _bin_pairs(proj, tiles_x, tiles_y)

        num_pix = height * width
        # Accumulators over all tiles, laid out tile-major: (tiles, 256, ...)
        n_tiles = tiles_x * tiles_y
        # Anchor outputs to the graph even when nothing is visible.
        anchor = 0.0 * (colors.sum() + opacities.sum() + proj.means2d.sum() + proj.conics.sum())
        color_acc = torch.zeros(n_tiles, TILE_SIZE * TILE_SIZE, D, device=dev, dtype=dt) + anchor
        depth_acc = torch.zeros(n_tiles, TILE_SIZE * TILE_SIZE, device=dev, dtype=dt) + anchor
        trans = torch.ones(n_tiles, TILE_SIZE * TILE_SIZE, device=dev, dtype=dt)

        if gids.numel():
            counts = torch.bincount(tile_ids, minlength=n_tiles)
            starts = torch.cumsum(counts, 0) - counts
            active = torch.nonzero(counts).flatten()
            # Pixel centres of each tile: (256, 2)
            ly, lx = torch.meshgrid(
                torch.arange(TILE_SIZE, device=dev, dtype=dt), torch.arange(TILE_SIZE, device=dev, dtype=dt), indexing="ij"
            )
            local = torch.stack([lx.flatten(), ly.flatten()], -1) + 0.5
            # Group tiles with similar list lengths to limit padding.
            order = active[torch.argsort(counts[active])]
            tile_outputs = []
            i = 0
            while i < len(order):
                kmax = int(counts[order[min(i + 63, len(order) - 1)]])
                per_tile = TILE_SIZE * TILE_SIZE * max(1, min(kmax, 256))
                n_chunk = max(1, min(64, self.chunk_elements // per_tile))
                chunk = order[i : i + n_chunk]
                i += n_chunk
                tile_outputs.append((chunk, *self._composite_tiles(
                    chunk, counts, starts, gids, proj, opacities, colors, local, tiles_x, absgrad
                )))
            for chunk, c_acc, d_acc, t_fin in tile_outputs:
                color_acc = color_acc.index_copy(0, chunk, c_acc)
                depth_acc = depth_acc.index_copy(0, chunk, d_acc)
                trans = trans.index_copy(0, chunk, t_fin)

        alpha_t = 1.0 - trans
        rgb_t = color_acc
        if background is not None:
            rgb_t = rgb_t + trans[..., None] * background
        rgb = _untile(rgb_t, tiles_x, tiles_y, height, width)
        alpha = _untile(alpha_t[..., None], tiles_x, tiles_y, height, width)
        depth_sum = _untile(depth_acc[..., None], tiles_x, tiles_y, height, width)
        depth = depth_sum / torch.clamp(alpha, min=1e-10)
        assert rgb.shape == (height, width, D) and num_pix == height * width
        return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, radii=proj.radii, means2d=proj.means2d, absgrad2d=absgrad)

    def rasterize_lidar(self, splats: Splats, rays: LidarRays, settings: LidarSettings = LidarSettings()
                        ) -> LidarRenderOutput:
        """The ``lidar`` capability (contract in :mod:`omnire.rasterization`), by autograd:
        :mod:`omnire_rasterizer_torch.lidar`."""
        return rasterize_lidar(splats, rays, settings, self.chunk_elements)

    def _composite_tiles(self, tiles, counts, starts, gids, proj, opacities, colors, local, tiles_x, absgrad):
        """Composite the depth-sorted lists of ``tiles`` (T,). Returns colour (T,256,D),
        depth sum (T,256) and final transmittance (T,256)."""
        dev, dt = colors.device, colors.dtype
        T = len(tiles)
        P = local.shape[0]
        kmax = int(counts[tiles].max())
        origin = torch.stack([(tiles % tiles_x) * TILE_SIZE, (tiles // tiles_x) * TILE_SIZE], -1).to(dt)
        pix = origin[:, None, :] + local[None]  # (T, P, 2)
        c_acc = torch.zeros(T, P, colors.shape[1], device=dev, dtype=dt)
        d_acc = torch.zeros(T, P, device=dev, dtype=dt)
        trans = torch.ones(T, P, device=dev, dtype=dt)
        done = torch.zeros(T, P, dtype=torch.bool, device=dev)
        kc = max(1, min(kmax, self.chunk_elements // max(1, T * P)))
        for k0 in range(0, kmax, kc):
            k = torch.arange(k0, min(k0 + kc, kmax), device=dev)
            valid = k[None, :] < counts[tiles][:, None]  # (T, kc)
            idx = torch.where(valid, starts[tiles][:, None] + k[None, :], torch.zeros_like(k[None, :]))
            g = torch.where(valid, gids[idx], torch.zeros_like(idx))  # (T, kc) Gaussian ids
            m2 = proj.means2d[g]  # (T, kc, 2)
            d = pix[:, :, None, :] - m2[:, None, :, :]  # (T, P, kc, 2)
            if d.requires_grad:
                g_flat, valid_flat = g.flatten(), valid.flatten()

                def hook(grad, g_flat=g_flat, valid_flat=valid_flat):
                    per_pair = grad.abs().sum(1).reshape(-1, 2) * valid_flat[:, None]
                    absgrad.index_add_(0, g_flat, per_pair.to(absgrad.dtype))

                d.register_hook(hook)
            con = proj.conics[g]  # (T, kc, 3)
            dx, dy = d[..., 0], d[..., 1]
            power = -0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 2] * dy * dy) - con[:, None, :, 1] * dx * dy
            alpha = torch.clamp(opacities[g][:, None, :] * torch.exp(torch.clamp(power, max=0.0)), max=MAX_ALPHA)
            keep = valid[:, None, :] & (power <= 0) & (alpha >= ALPHA_THRESHOLD)
            alpha = torch.where(keep, alpha, torch.zeros_like(alpha))  # (T, P, kc)
            one_minus = 1.0 - alpha
            cum = trans[..., None] * torch.cumprod(one_minus, dim=-1)  # T after each
            alive = (cum > TRANSMITTANCE_MIN) & ~done[..., None]
            # alive is a prefix along k (cum decreases); a pixel that stops stays stopped.
            t_before = torch.cat([trans[..., None], cum[..., :-1]], dim=-1)
            w = alpha * t_before * alive
            c_acc = c_acc + torch.einsum("tpk,tkd->tpd", w, colors[g])
            d_acc = d_acc + (w * proj.depths[g][:, None, :]).sum(-1)
            trans = trans * torch.where(alive, one_minus, torch.ones_like(one_minus)).prod(-1)
            done = done | ~(cum > TRANSMITTANCE_MIN).all(-1)
        return c_acc, d_acc, trans


def _bin_pairs(proj, tiles_x: int, tiles_y: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(Gaussian id, tile id) pairs for every tile a visible Gaussian's 3-sigma box touches,
    sorted by tile then depth. Returns gids (M,), tile_ids (M,)."""
    with torch.no_grad():
        # a projection that overflowed (a Gaussian at the camera plane) cannot be binned
        vis = torch.nonzero(proj.visible & torch.isfinite(proj.means2d).all(-1) & torch.isfinite(proj.depths)).flatten()
        if vis.numel() == 0:
            e = torch.zeros(0, dtype=torch.long, device=proj.depths.device)
            return e, e
        m = proj.means2d[vis]
        r = proj.radii[vis].to(m.dtype)
        x0 = torch.clamp(torch.floor((m[:, 0] - r) / TILE_SIZE), 0, tiles_x).long()
        x1 = torch.clamp(torch.ceil((m[:, 0] + r) / TILE_SIZE), 0, tiles_x).long()
        y0 = torch.clamp(torch.floor((m[:, 1] - r) / TILE_SIZE), 0, tiles_y).long()
        y1 = torch.clamp(torch.ceil((m[:, 1] + r) / TILE_SIZE), 0, tiles_y).long()
        nx, ny = x1 - x0, y1 - y0
        n = nx * ny
        keep = n > 0
        vis, x0, y0, nx, n = vis[keep], x0[keep], y0[keep], nx[keep], n[keep]
        gids = torch.repeat_interleave(vis, n)
        offs = torch.arange(int(n.sum()), device=gids.device) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
        nx_r = torch.repeat_interleave(nx, n)
        tx = torch.repeat_interleave(x0, n) + offs % nx_r
        ty = torch.repeat_interleave(y0, n) + offs // nx_r
        tile_ids = ty * tiles_x + tx
        # depth order first, then a stable sort by tile keeps depth order inside each tile
        order = torch.argsort(proj.depths[gids], stable=True)
        gids, tile_ids = gids[order], tile_ids[order]
        order = torch.argsort(tile_ids, stable=True)
        return gids[order], tile_ids[order]


def _untile(x: torch.Tensor, tiles_x: int, tiles_y: int, height: int, width: int) -> torch.Tensor:
    """(tiles, 256, C) tile-major -> (H, W, C) cropped to the image."""
    C = x.shape[-1]
    img = x.reshape(tiles_y, tiles_x, TILE_SIZE, TILE_SIZE, C).permute(0, 2, 1, 3, 4)
    return img.reshape(tiles_y * TILE_SIZE, tiles_x * TILE_SIZE, C)[:height, :width]
