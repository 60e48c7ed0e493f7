"""The gsplat backend: :class:`GsplatRasterizer` wraps ``gsplat.rasterization``.

gsplat renders ``RGB+ED`` (colour channels plus expected depth, already divided by alpha)
with ``absgrad=True``; its backward stores sum_pixels |dL/dmeans2d| on
``meta["means2d"].absgrad``, which a tensor hook copies into the output's ``absgrad2d``.
Background compositing is done here (rgb + (1 - alpha) bg) so it works for any channel count
and gsplat version.
"""
from __future__ import annotations


import torch

from omnire.api import Camera, RasterInputError, RasterSettings, RenderOutput, Splats, check_raster_inputs


class GsplatRasterizer:
    name = "gsplat"

    def __init__(self, packed: bool = False) -> None:
        # packed=False keeps (N, ...) shaped per-Gaussian outputs (means2d, radii, absgrad).
        self.packed = packed

    def rasterize(self, splats: Splats, camera: Camera, settings: RasterSettings = RasterSettings()) -> RenderOutput:
        """See :mod:`omnire.rasterization` for the contract (shapes and semantics)."""
        check_raster_inputs(splats, camera, settings)
        means, quats, scales, opacities, colors = (splats.means, splats.quats, splats.scales, splats.opacities,
                                                   splats.colors)
        if means.device.type != "cuda":
            raise RasterInputError(f"means: on {means.device}; the gsplat rasterizer needs CUDA tensors")
        import gsplat

        viewmat, K, width, height = camera.world_to_cam, camera.K, camera.width, camera.height
        near, far, eps2d, background = settings.near, settings.far, settings.eps2d, settings.background
        N, D = colors.shape
        dev = means.device
        renders, alphas, meta = gsplat.rasterization(
            means, quats, scales, opacities, colors,
            viewmat.to(dev, means.dtype)[None], K.to(dev, means.dtype)[None], int(width), int(height),
            near_plane=float(near), far_plane=float(far), eps2d=float(eps2d),
            packed=self.packed, render_mode="RGB+ED", absgrad=True,
        )  # renders (1, H, W, D+1), alphas (1, H, W, 1)
        rgb = renders[0, ..., :D]
        depth = renders[0, ..., D:D + 1]
        alpha = alphas[0]
        if background is not None:
            rgb = rgb + (1.0 - alpha) * background.to(rgb.dtype)
        radii = meta["radii"][0]
        if radii.ndim == 2:  # newer gsplat: per-axis radii (N, 2)
            radii = radii.max(dim=-1).values
        m2d = meta["means2d"]  # (1, N, 2), requires grad when any input does
        absgrad = torch.zeros(N, 2, device=dev, dtype=means.dtype)
        if m2d.requires_grad:
            def copy_absgrad(grad, m2d=m2d, buf=absgrad):
                ag = getattr(m2d, "absgrad", None)
                if ag is not None:
                    buf.add_(ag.reshape(-1, N, 2)[0].to(buf.dtype))
                return grad

            m2d.register_hook(copy_absgrad)
        return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, radii=radii.to(torch.int32),
                            means2d=m2d[0], absgrad2d=absgrad)
