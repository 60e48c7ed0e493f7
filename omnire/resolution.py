"""Coarse-to-fine training: the first steps render and compare images at a reduced resolution.

A step at half resolution costs a quarter of the per-pixel work (compositing, its backward,
the image losses), so a run with a fixed time budget gets more steps in while the scene is
still coarse. The schedule follows nerfstudio's splatfacto: the downscale factor starts at
``2 ** num_downscales`` and halves every ``resolution_schedule`` steps down to 1.

Downscaling a view is exact in geometry: the image keeps its top-left ``(H // f) * f`` x
``(W // f) * f`` pixels, each low-resolution pixel is the mean of its f x f block (area
averaging) and the camera's intrinsics are divided by f (:meth:`Camera.downscaled`), so
low-resolution pixel j covers full-resolution pixels [j f, (j + 1) f). Masks and pixel
weights are averaged the same way (fractional values weigh a block by how much of it is
masked); LiDAR returns keep their pixel's block and, when several share one, the nearest.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def downscale_factor(step: int, num_downscales: int, resolution_schedule: int) -> int:
    """The factor (1, 2, 4, ...) at ``step``: ``2 ** max(num_downscales - step // schedule, 0)``."""
    if num_downscales <= 0 or resolution_schedule <= 0:
        return 1
    return 2 ** max(num_downscales - step // resolution_schedule, 0)


def downscale_image(image: torch.Tensor, factor: int) -> torch.Tensor:
    """(H, W, C) -> (H // f, W // f, C): means of f x f blocks (rows / columns past the last
    whole block are dropped, as in :meth:`Camera.downscaled`)."""
    if factor == 1:
        return image
    if image.ndim != 3:
        raise ValueError(f"downscale_image: expected (H, W, C), got {tuple(image.shape)}")
    H, W = image.shape[0] // factor * factor, image.shape[1] // factor * factor
    x = image[:H, :W].permute(2, 0, 1)[None].float()  # (1, C, H, W)
    return F.avg_pool2d(x, factor)[0].permute(1, 2, 0).to(image.dtype)


def downscale_pixel_samples(pixels: torch.Tensor, depth: torch.Tensor, width: int, height: int,
                            factor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sparse samples at flat full-resolution pixel indices (P,) with depths (P,) -> the same
    at the downscaled image's flat indices; samples past the last whole block are dropped and
    of several in one block the nearest is kept (as LiDAR projection keeps the nearest)."""
    if factor == 1:
        return pixels, depth
    w, h = width // factor, height // factor
    u, v = pixels % width // factor, pixels // width // factor
    inside = (u < w) & (v < h)
    idx, z = (v * w + u)[inside], depth[inside]
    if idx.numel() == 0:
        return idx, z
    order = torch.argsort(z, stable=True)  # nearest first, then the first per block wins
    idx, z = idx[order], z[order]
    first = torch.full((h * w,), idx.numel(), dtype=torch.int64, device=idx.device)
    first.scatter_reduce_(0, idx, torch.arange(idx.numel(), device=idx.device), reduce="amin")
    keep = first[idx] == torch.arange(idx.numel(), device=idx.device)
    idx, z = idx[keep], z[keep]
    order = torch.argsort(idx)
    return idx[order], z[order]
