"""Image and geometry metrics (PSNR, SSIM, masked variants, depth RMSE, Chamfer)."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from omnire.losses import ssim_map


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR in dB of (H,W,3) images in [0,1]; with a (H,W,1) mask, over masked pixels only
    (NaN when the mask is empty)."""
    err = (pred.clamp(0, 1) - target) ** 2
    if mask is not None:
        m = mask.expand_as(err) > 0.5
        if not bool(m.any()):
            return float("nan")
        mse = err[m].mean()
    else:
        mse = err.mean()
    return float(-10.0 * torch.log10(mse.clamp_min(1e-10)))


def ssim(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """Mean SSIM of (H,W,3) images; with a mask, the mean of the SSIM map inside it."""
    m = ssim_map(pred.clamp(0, 1), target)
    if mask is not None:
        sel = mask > 0.5
        return float(m[sel].mean()) if bool(sel.any()) else float("nan")
    return float(m.mean())


def depth_errors(rendered: torch.Tensor, pixels: torch.Tensor, lidar_depth: torch.Tensor,
                 max_depth: float = 80.0) -> tuple[float, int]:
    """RMSE (m) of rendered (H,W,1) depth against LiDAR depth at flat ``pixels`` (P,),
    over LiDAR returns within ``max_depth``. Returns (rmse, count)."""
    keep = lidar_depth < max_depth
    if not bool(keep.any()):
        return float("nan"), 0
    r = rendered.reshape(-1)[pixels[keep]]
    return float(((r - lidar_depth[keep]) ** 2).mean().sqrt()), int(keep.sum())


def chamfer_distance(a: "torch.Tensor | np.ndarray", b: "torch.Tensor | np.ndarray") -> float:
    """Two-way Chamfer distance (mean nearest-neighbour distance a->b plus b->a) of (N,3),
    (M,3) point sets (tensors or arrays), in metres; NaN when either is empty. Exact nearest
    neighbours through k-d trees (a full LiDAR sweep holds ~10^5 points)."""
    a, b = (x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)
            for x in (a, b))
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())
