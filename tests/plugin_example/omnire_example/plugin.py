"""Entry point of the example plugin (group ``omnire``, name ``example``): one loss term."""
from __future__ import annotations

from typing import Optional

import torch

from omnire.api import LossContext, LossSpec, hookimpl


def depth_smoothness(ctx: LossContext) -> Optional[torch.Tensor]:
    """Mean absolute difference of the rendered depth (H, W, 1) between neighbouring pixels,
    on the scene's pixels only (the recording vehicle's are left out)."""
    d = ctx.depth
    keep = torch.ones_like(d) if ctx.scene_pixels is None else ctx.scene_pixels
    dx = (d[:, 1:] - d[:, :-1]).abs() * keep[:, 1:] * keep[:, :-1]
    dy = (d[1:] - d[:-1]).abs() * keep[1:] * keep[:-1]
    return (dx.sum() + dy.sum()) / (dx.numel() + dy.numel())


@hookimpl
def omnire_register_losses(registry) -> None:
    registry.register(LossSpec("example_depth_smoothness", "depth smoothness (example third-party plugin)",
                               depth_smoothness))
