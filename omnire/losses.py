"""Built-in loss terms, registered through the same hook as plugin losses.

Each loss is ``fn(ctx: LossContext) -> scalar tensor | None``; None means "does not apply
to this view" (no LiDAR at this frame, no sky mask, ...) and costs nothing. The method
config weights them by name.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import torch
from kornia.metrics import ssim as kornia_ssim


@dataclasses.dataclass
class LossContext:
    """Everything a loss may look at for one rendered view.

    Attributes:
        rgb: (H, W, 3) rendered colour (after sky compositing).
        depth: (H, W, 1) rendered expected depth.
        alpha: (H, W, 1) rendered Gaussian opacity.
        target: (H, W, 3) ground-truth image.
        pixel_weights: (H, W, 1) image-loss weights (x5 on dynamic actors), or None.
        lidar_pixels: (P,) flat pixel indices with a LiDAR return, or None.
        lidar_depth: (P,) LiDAR depth along the camera z axis at those pixels.
        sky_mask: (H, W, 1) 1 where sky, or None.
        regularization: node-provided terms (name -> scalar).
        step: training step.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    target: torch.Tensor
    pixel_weights: Optional[torch.Tensor] = None
    lidar_pixels: Optional[torch.Tensor] = None
    lidar_depth: Optional[torch.Tensor] = None
    sky_mask: Optional[torch.Tensor] = None
    regularization: dict = dataclasses.field(default_factory=dict)
    step: int = 0


def l1_loss(ctx: LossContext) -> torch.Tensor:
    err = (ctx.rgb - ctx.target).abs()
    if ctx.pixel_weights is not None:
        err = err * ctx.pixel_weights
    return err.mean()


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) x2 -> (H, W, 1) SSIM (11x11 Gaussian window, kornia)."""
    m = kornia_ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], 11)
    return m[0].mean(0)[..., None]


def dssim_loss(ctx: LossContext) -> torch.Tensor:
    dis = 1.0 - ssim_map(ctx.rgb, ctx.target)
    if ctx.pixel_weights is not None:
        dis = dis * ctx.pixel_weights
    return dis.mean()


def lidar_inverse_depth_loss(ctx: LossContext) -> Optional[torch.Tensor]:
    """L1 between rendered and LiDAR inverse depth at pixels with a LiDAR return."""
    if ctx.lidar_pixels is None or ctx.lidar_pixels.numel() == 0:
        return None
    rendered = ctx.depth.reshape(-1)[ctx.lidar_pixels]
    return (1.0 / rendered.clamp_min(0.1) - 1.0 / ctx.lidar_depth.clamp_min(0.1)).abs().mean()


def opacity_mask_loss(ctx: LossContext) -> Optional[torch.Tensor]:
    """BCE of the rendered Gaussian opacity against the non-sky mask (sky -> 0, else 1)."""
    if ctx.sky_mask is None:
        return None
    target = 1.0 - ctx.sky_mask
    a = ctx.alpha.clamp(1e-6, 1 - 1e-6)
    return torch.nn.functional.binary_cross_entropy(a, target)


BUILTIN_LOSSES = {
    "l1": ("L1 colour error (dynamic pixels weighted by the method's dynamic_pixel_weight)", l1_loss),
    "dssim": ("1 - SSIM (kornia, 11x11), same pixel weights", dssim_loss),
    "depth": ("L1 on inverse depth against projected LiDAR", lidar_inverse_depth_loss),
    "opacity": ("BCE of rendered opacity against the non-sky mask", opacity_mask_loss),
}
