"""The native SSIM map (``CpuRasterizer.ssim_map``, csrc/ssim.cpp) against the torch one it
replaces in the D-SSIM loss (:func:`omnire.losses.ssim_map`, itself checked against
kornia), in float64 (values and gradients to rounding) and float32, plus central
differences on a small image. Sizes include odd ones and images barely larger than the
window's reflect padding, where the border folding of the backward matters most."""
from __future__ import annotations

import pytest
import torch
from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer

from omnire.losses import LossContext, dssim_loss, ssim_map


@pytest.mark.parametrize("shape", [(6, 6, 3), (13, 17, 3), (40, 33, 3), (31, 45, 1)])
@pytest.mark.parametrize("threads", [1, 2])
def test_native_ssim_matches_torch_float64(shape, threads):
    g = torch.Generator().manual_seed(sum(shape) + threads)
    a = torch.rand(*shape, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.rand(*shape, dtype=torch.float64, generator=g)
    w = torch.rand(*shape[:2], 1, dtype=torch.float64, generator=g)  # a loss that weights pixels
    ref = ssim_map(a, b)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), a)
    out = CpuRasterizer(num_threads=threads).ssim_map(a, b)
    (g_out,) = torch.autograd.grad((out * w).sum(), a)
    assert out.shape == ref.shape == (*shape[:2], 1)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(g_out, g_ref, rtol=1e-9, atol=1e-12)


def test_native_ssim_float32_and_identical_images():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(54, 96, 3, generator=g, requires_grad=True)
    b = (a.detach() + 0.1 * torch.randn(54, 96, 3, generator=g)).clamp(0, 1)
    rast = CpuRasterizer(num_threads=2)
    ref = ssim_map(a, b)
    (g_ref,) = torch.autograd.grad(ref.mean(), a)
    out = rast.ssim_map(a, b)
    (g_out,) = torch.autograd.grad(out.mean(), a)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-5)
    torch.testing.assert_close(g_out, g_ref, rtol=1e-3, atol=1e-8)
    torch.testing.assert_close(rast.ssim_map(b, b), torch.ones(54, 96, 1), rtol=0, atol=1e-5)


def test_native_ssim_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(12, 15, 3, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.rand(12, 15, 3, dtype=torch.float64, generator=g)
    rast = CpuRasterizer(num_threads=1)
    assert torch.autograd.gradcheck(lambda x: rast.ssim_map(x, b), (a,), eps=1e-6, atol=1e-7)


def test_dssim_loss_uses_the_context_ssim():
    """The trainer hands the rasterizer's SSIM to the loss through ``LossContext.ssim``: the
    loss value and its gradient are the torch version's."""
    g = torch.Generator().manual_seed(2)
    rgb = torch.rand(20, 24, 3, dtype=torch.float64, generator=g, requires_grad=True)
    target = torch.rand(20, 24, 3, dtype=torch.float64, generator=g)
    scene = (torch.rand(20, 24, 1, generator=g) > 0.2).to(torch.float64)
    z = torch.zeros(20, 24, 1, dtype=torch.float64)

    def loss(ssim):
        kwargs = {} if ssim is None else {"ssim": ssim}
        ctx = LossContext(rgb=rgb, depth=z, alpha=z, target=target, scene_pixels=scene, **kwargs)
        value = dssim_loss(ctx)
        return value, torch.autograd.grad(value, rgb)[0]

    (v_ref, g_ref), (v_nat, g_nat) = loss(None), loss(CpuRasterizer(num_threads=2).ssim_map)
    torch.testing.assert_close(v_nat, v_ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(g_nat, g_ref, rtol=1e-9, atol=1e-14)


def test_native_ssim_falls_back_when_the_target_needs_a_gradient():
    a = torch.rand(16, 16, 3, dtype=torch.float64, requires_grad=True)
    b = torch.rand(16, 16, 3, dtype=torch.float64, requires_grad=True)
    out = CpuRasterizer(num_threads=1).ssim_map(a, b)
    ga, gb = torch.autograd.grad(out.sum(), (a, b))
    ra, rb = torch.autograd.grad(ssim_map(a, b).sum(), (a, b))
    torch.testing.assert_close(ga, ra)
    torch.testing.assert_close(gb, rb)


def test_native_ssim_rejects_images_too_small_for_the_window():
    with pytest.raises(RuntimeError, match="too small|padding"):
        CpuRasterizer(num_threads=1).ssim_map(torch.rand(5, 20, 3), torch.rand(5, 20, 3))
