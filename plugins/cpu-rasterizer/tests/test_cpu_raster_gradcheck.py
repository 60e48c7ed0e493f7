"""Finite-difference gradient checks of the hand-written backward, in float64.

The kernel is templated on the scalar type, so float64 inputs run a double-precision
forward and backward: central differences (eps 1e-6) are then accurate to ~1e-8 and the
analytic gradient must match them tightly. Scenes are well conditioned: few Gaussians,
opacities 0.2-0.7 (never clamped at 0.99, transmittance never near 1e-4), so no skip / stop
decision flips under a 1e-6 perturbation. The loss is a random projection of all outputs
(rgb, depth, alpha, means2d), checked for three projections, one input at a time.
"""
from __future__ import annotations

import pytest
import torch

from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer  # noqa: E402
from omnire_rasterizer_cpu.testing import random_scene, raster_call  # noqa: E402

W, H, D = 24, 20, 3
INPUTS = ("means", "quats", "scales", "opacities", "colors", "background")


def make(seed):
    sc = random_scene(6, W, H, D=D, seed=seed, scale_px=3.0, opacity=(0.2, 0.7), depth=(2.0, 4.0))
    sc["background"] = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)
    return sc


@pytest.mark.parametrize("name", INPUTS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradcheck(name, seed):
    sc = make(seed)
    g = torch.Generator().manual_seed(100 + seed)
    w_rgb = torch.randn(H, W, D, generator=g, dtype=torch.float64)
    w_depth = 0.1 * torch.randn(H, W, 1, generator=g, dtype=torch.float64)
    w_alpha = torch.randn(H, W, 1, generator=g, dtype=torch.float64)
    w_m2d = 0.01 * torch.randn(6, 2, generator=g, dtype=torch.float64)
    rast = CpuRasterizer()

    def f(x):
        args = dict(sc)
        args[name] = x
        out = raster_call(rast.rasterize, args, W, H, background=args["background"])
        return ((out.rgb * w_rgb).sum() + (out.depth * w_depth).sum() + (out.alpha * w_alpha).sum()
                + (out.means2d * w_m2d).sum())

    x = sc[name].clone().requires_grad_(True)
    # the scene must actually be visible, or the check would pass trivially
    out = raster_call(rast.rasterize, sc, W, H)
    assert int((out.radii > 0).sum()) >= 4 and float(out.alpha.max()) > 0.3
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_unnormalised_and_flat():
    # unnormalised quats (norm 0.1 .. 10) and one flat (zero-thickness) axis per Gaussian
    sc = make(4)
    sc["quats"] = sc["quats"] * torch.tensor([0.1, 1.0, 10.0, 3.0, 0.5, 2.0], dtype=torch.float64)[:, None]
    sc["scales"] = sc["scales"].clone()
    sc["scales"][:, 2] = 0.0
    rast = CpuRasterizer()
    g = torch.Generator().manual_seed(9)
    w = torch.randn(H, W, D, generator=g, dtype=torch.float64)
    for name in ("quats", "means"):  # (a zero scale cannot be perturbed both ways)
        def f(x, name=name):
            args = dict(sc)
            args[name] = x
            out = raster_call(rast.rasterize, args, W, H)
            return (out.rgb * w).sum() + out.alpha.sum()

        x = sc[name].clone().requires_grad_(True)
        assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-4), name


def test_float32_gradient_against_own_float32_differences():
    # The float32 (AVX2) kernel against central differences of its own float32 forward.
    # eps = 1e-4 world units (~1e-3 px): the rendered float32 pixels carry ~1e-7 relative
    # rounding; summed in float64 over 1440 values the loss error is ~1e-6, i.e. ~5e-3 after
    # dividing by 2*eps. Steps of 1e-3 already cross a binning discontinuity in this scene
    # (a 3-sigma box entering another 16x16 tile), so eps cannot be larger.
    # 3e-2 relative + 2% of the largest entry is loose but still fails a wrong sign/factor.
    sc = {k: v.float() for k, v in make(5).items()}
    rast = CpuRasterizer()
    g = torch.Generator().manual_seed(3)
    w = torch.randn(H, W, D, generator=g)

    def loss(means):
        out = raster_call(rast.rasterize, {**sc, "means": means}, W, H)
        return (out.rgb.double() * w.double()).sum()

    m = sc["means"].clone().requires_grad_(True)
    loss(m).backward()
    eps = 1e-4
    num = torch.zeros_like(m)
    with torch.no_grad():
        for i in range(m.shape[0]):
            for j in range(3):
                p, q = sc["means"].clone(), sc["means"].clone()
                p[i, j] += eps
                q[i, j] -= eps
                num[i, j] = (loss(p) - loss(q)) / (2 * eps)
    torch.testing.assert_close(m.grad, num, rtol=3e-2, atol=2e-2 * float(num.abs().max()))
