"""The native kernel against two independent implementations: the brute-force dense
rasterizer in ``omnire_rasterizer_cpu.testing`` (every Gaussian at every pixel) and, when
installed, the reference PyTorch tile rasterizer. Forward outputs and every gradient."""
from __future__ import annotations

import pytest
import torch

from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer  # noqa: E402
from omnire_rasterizer_cpu.testing import dense_rasterize, random_scene, raster_call  # noqa: E402

INPUTS = ("means", "quats", "scales", "opacities", "colors")


def run(fn, scene, width, height, background, seed=7):
    """Render, backprop a random weighted sum of rgb/depth/alpha; return outputs and grads."""
    leaves = {k: v.detach().clone().requires_grad_(k in INPUTS) for k, v in scene.items()}
    out = raster_call(fn, leaves, width, height, background=background)
    out = out if isinstance(out, dict) else out.__dict__
    dt = leaves["means"].dtype
    g = torch.Generator().manual_seed(seed)
    D = leaves["colors"].shape[1]
    # weights drawn in float64 then cast, so float32 and float64 runs use the same loss
    w_rgb, w_depth, w_alpha = (torch.randn(height, width, c, generator=g, dtype=torch.float64).to(dt)
                               for c in (D, 1, 1))
    loss = (out["rgb"] * w_rgb).sum() + 0.1 * (out["depth"] * w_depth).sum() + (out["alpha"] * w_alpha).sum()
    loss.backward()
    res = {k: out[k].detach() for k in ("rgb", "depth", "alpha", "means2d")}
    res["radii"] = out["radii"]
    res["absgrad2d"] = out["absgrad2d"].clone()
    res.update({"grad_" + k: leaves[k].grad for k in INPUTS})
    return res


def assert_close(a, b, rtol, what):
    """Max abs difference relative to the larger tensor's max magnitude (at least 1)."""
    for k in b:
        x, y = a[k].double(), b[k].double()
        assert x.shape == y.shape, (what, k, x.shape, y.shape)
        assert torch.isfinite(x).all(), (what, k)
        scale = max(1.0, float(y.abs().max()) if y.numel() else 1.0)
        err = float((x - y).abs().max()) if x.numel() else 0.0
        assert err <= rtol * scale, f"{what}: {k} differs by {err:.3g} (scale {scale:.3g})"


CASES = [
    # n, width, height, D, scale_px, background
    (40, 37, 29, 3, 3.0, True),
    (150, 64, 48, 3, 2.0, False),
    (80, 33, 17, 5, 5.0, True),
    (60, 20, 50, 1, 8.0, True),
]


@pytest.mark.parametrize("n,width,height,D,scale_px,bg", CASES)
def test_matches_dense_float64(n, width, height, D, scale_px, bg):
    # float64 end to end: both sides are exact up to rounding, so the tolerance is tight.
    scene = random_scene(n, width, height, D=D, seed=n + D, scale_px=scale_px)
    background = torch.linspace(0.1, 0.9, D, dtype=torch.float64) if bg else None
    ours = run(CpuRasterizer(num_threads=2).rasterize, scene, width, height, background)
    ref = run(dense_rasterize, scene, width, height, background)
    assert torch.equal(ours["radii"], ref["radii"])
    assert_close(ours, ref, 1e-9, "cpu vs dense (float64)")


@pytest.mark.parametrize("n,width,height,D,scale_px,bg", CASES[:2])
def test_matches_dense_float32(n, width, height, D, scale_px, bg):
    # float32 kernel (AVX2, polynomial exp ~1e-7 relative) vs float64 truth. A few 1e-6
    # relative per composited layer, accumulated over tens of layers and amplified by the
    # 1/(1-alpha) <= 100 factor of the backward, stays below 1e-3 of the output scale.
    scene = random_scene(n, width, height, D=D, seed=3 * n, scale_px=scale_px)
    background = torch.full((D,), 0.5, dtype=torch.float64) if bg else None
    ref = run(dense_rasterize, scene, width, height, background)
    scene32 = {k: v.float() for k, v in scene.items()}
    ours = run(CpuRasterizer().rasterize, scene32, width, height, None if background is None else background.float())
    assert ours["rgb"].dtype == torch.float32 and ours["grad_means"].dtype == torch.float32
    assert_close(ours, ref, 1e-3, "cpu float32 vs dense float64")


def test_matches_reference_torch_rasterizer():
    ref_mod = pytest.importorskip("omnire_rasterizer_torch.rasterizer", reason="omnire-rasterizer-torch not installed")
    width, height, D = 70, 45, 3
    scene = random_scene(300, width, height, D=D, seed=11, scale_px=3.0, opacity=(0.1, 0.99))
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    ours = run(CpuRasterizer().rasterize, scene, width, height, bg)
    ref = run(ref_mod.TorchRasterizer().rasterize, scene, width, height, bg)
    assert torch.equal(ours["radii"], ref["radii"])
    # means2d of culled Gaussians is unspecified by the contract; compare the drawn ones.
    drawn = ref["radii"] > 0
    ours["means2d"], ref["means2d"] = ours["means2d"][drawn], ref["means2d"][drawn]
    assert_close(ours, ref, 1e-9, "cpu vs torch reference (float64)")
    scene32 = {k: v.float() for k, v in scene.items()}
    ours32 = run(CpuRasterizer().rasterize, scene32, width, height, bg.float())
    ref32 = run(ref_mod.TorchRasterizer().rasterize, scene32, width, height, bg.float())
    ours32["means2d"], ref32["means2d"] = ours32["means2d"][drawn], ref32["means2d"][drawn]
    assert_close(ours32, ref32, 2e-3, "cpu vs torch reference (float32)")


def test_thread_counts_agree_and_are_deterministic():
    width, height = 96, 80
    scene = {k: v.float() for k, v in random_scene(2000, width, height, seed=5, scale_px=3.0).items()}
    a = run(CpuRasterizer(num_threads=1).rasterize, scene, width, height, None)
    b = run(CpuRasterizer(num_threads=2).rasterize, scene, width, height, None)
    c = run(CpuRasterizer(num_threads=2).rasterize, scene, width, height, None)
    for k in ("rgb", "depth", "alpha", "radii", "means2d"):
        assert torch.equal(a[k], b[k]), k  # the forward does not depend on the schedule
    for k in c:
        assert torch.equal(b[k], c[k]), k  # static schedule: repeatable backward
    assert_close(a, b, 1e-5, "1 vs 2 threads")  # gradient sums in another order


def test_means2d_output_gradient():
    # means2d is an output too: its gradient must reach the means like the reference's.
    width, height = 40, 30
    scene = random_scene(30, width, height, seed=2)
    grads = []
    for fn in (CpuRasterizer().rasterize, dense_rasterize):
        m = scene["means"].clone().requires_grad_(True)
        out = raster_call(fn, {**scene, "means": m}, width, height)
        out = out if isinstance(out, dict) else out.__dict__
        (out["means2d"] * torch.arange(60, dtype=torch.float64).reshape(30, 2)).sum().backward()
        grads.append(m.grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-9, atol=1e-9)
