"""Native SSIM map (csrc/ssim.cpp) with the contract of :func:`omnire.losses.ssim_map`.

The D-SSIM loss runs once per training step on the full image; in torch it is a dozen
elementwise passes, two depthwise convolutions and a reflection padding, each with its
backward. The native version does the same arithmetic in five passes forward and four
backward, and gives a gradient to the rendered image only (the target needs none).
"""
from __future__ import annotations

from typing import Optional

import torch
from kornia.filters import get_gaussian_kernel1d

from omnire.api import ssim_map as torch_ssim_map

from ._build import extension as _ext


class _SsimFn(torch.autograd.Function):
    """(a, b) (H, W, C) -> SSIM map (H, W, 1); gradient for ``a`` only."""

    @staticmethod
    def forward(ctx, a, b, window, nthreads):
        m, stats = _ext().ssim_forward(a, b, window, nthreads)
        ctx.nthreads = nthreads
        ctx.save_for_backward(a, b, window, stats)
        return m

    @staticmethod
    def backward(ctx, g_map):
        a, b, window, stats = ctx.saved_tensors
        g_a = _ext().ssim_backward(a, b, window, stats, g_map.contiguous().to(a.dtype), ctx.nthreads)
        return g_a, None, None, None


def ssim_map(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5,
             num_threads: Optional[int] = None) -> torch.Tensor:
    """(H, W, C) x2 -> (H, W, 1) SSIM, as :func:`omnire.losses.ssim_map` (same window, padding
    and constants; equal up to float rounding). CPU float32 / float64 images run natively;
    anything else (another device or dtype, or a target that needs a gradient) goes to the
    torch version."""
    native = (a.device.type == "cpu" and b.device.type == "cpu" and a.dtype == b.dtype
              and a.dtype in (torch.float32, torch.float64) and not b.requires_grad)
    if not native or a.shape != b.shape or a.ndim != 3:
        return torch_ssim_map(a, b, window, sigma)
    g = get_gaussian_kernel1d(window, sigma).to(a.dtype).reshape(-1).contiguous()  # (window,)
    nthreads = int(num_threads or torch.get_num_threads())
    return _SsimFn.apply(a.contiguous(), b.detach().contiguous(), g, nthreads)
