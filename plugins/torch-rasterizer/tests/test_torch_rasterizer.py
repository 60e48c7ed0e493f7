"""Reference rasterizer against a brute-force per-pixel evaluation (float64)."""
import pytest
import torch

from omnire.camera import Camera
from omnire.geometry import quat_to_rotmat
from omnire.rasterization import ALPHA_THRESHOLD, MAX_ALPHA, TRANSMITTANCE_MIN, RasterInputError, RasterSettings, Splats
from omnire_rasterizer_torch import TorchRasterizer, project_gaussians


def rasterize(rast, means, quats, scales, opacities, colors, viewmat, K, W, H, background=None):
    """The contract's call from loose tensors."""
    return rast.rasterize(Splats(means, quats, scales, opacities, colors), Camera.from_world_to_cam(viewmat, K, W, H),
                          RasterSettings(background=background))


def brute_force(means, quats, scales, opacities, colors, viewmat, K, W, H, background):
    """Every Gaussian at every pixel, composited one Gaussian at a time in depth order.
    Returns rgb (H,W,D), depth (H,W,1), alpha (H,W,1) and means2d (N,2) used."""
    proj = project_gaussians(means, quats, scales, viewmat, K, W, H)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=means.dtype), torch.arange(W, dtype=means.dtype), indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(-1, 2) + 0.5  # (P, 2)
    P = pix.shape[0]
    T = torch.ones(P, dtype=means.dtype)
    done = torch.zeros(P, dtype=torch.bool)
    rgb = torch.zeros(P, colors.shape[1], dtype=means.dtype)
    dsum = torch.zeros(P, dtype=means.dtype)
    for i in torch.argsort(proj.depths).tolist():
        if not bool(proj.visible[i]):
            continue
        d = pix - proj.means2d[i]
        a, b, c = proj.conics[i]
        power = -0.5 * (a * d[:, 0] ** 2 + c * d[:, 1] ** 2) - b * d[:, 0] * d[:, 1]
        alpha = torch.clamp(opacities[i] * torch.exp(power), max=MAX_ALPHA)
        use = (power <= 0) & (alpha >= ALPHA_THRESHOLD) & ~done
        nextT = T * (1 - alpha)
        stop = use & (nextT <= TRANSMITTANCE_MIN)
        done = done | stop
        use = use & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(alpha))
        rgb = rgb + w[:, None] * colors[i]
        dsum = dsum + w * proj.depths[i]
        T = torch.where(use, nextT, T)
    alpha = 1 - T
    rgb = rgb + T[:, None] * background
    depth = dsum / torch.clamp(alpha, min=1e-10)
    return rgb.reshape(H, W, -1), depth.reshape(H, W, 1), alpha.reshape(H, W, 1)


def random_scene(N, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(N, 3, generator=g, dtype=dtype) * torch.tensor([1.5, 1.0, 1.0], dtype=dtype)
    means[:, 2] += 5.0
    quats = torch.randn(N, 4, generator=g, dtype=dtype)
    scales = torch.rand(N, 3, generator=g, dtype=dtype) * 0.25 + 0.02
    opac = torch.rand(N, generator=g, dtype=dtype) * 0.9 + 0.05
    colors = torch.rand(N, 3, generator=g, dtype=dtype)
    K = torch.tensor([[40.0, 0, 21.0], [0, 40.0, 17.5], [0, 0, 1]], dtype=dtype)
    view = torch.eye(4, dtype=dtype)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=dtype)
    return means, quats, scales, opac, colors, view, K, bg


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_and_gradients_match_brute_force(seed):
    W, H = 43, 35  # not multiples of the tile size
    means, quats, scales, opac, colors, view, K, bg = random_scene(60, seed)
    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    ref = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    out = rasterize(TorchRasterizer(chunk_elements=5000), *inputs, view, K, W, H, background=bg)
    rgb, depth, alpha = brute_force(*ref, view, K, W, H, bg)
    torch.testing.assert_close(out.rgb, rgb, atol=1e-10, rtol=1e-9)
    torch.testing.assert_close(out.alpha, alpha, atol=1e-10, rtol=1e-9)
    torch.testing.assert_close(out.depth, depth, atol=1e-8, rtol=1e-8)
    g = torch.Generator().manual_seed(seed + 100)
    wr, wd = torch.rand(H, W, 3, generator=g, dtype=torch.float64), torch.rand(H, W, 1, generator=g, dtype=torch.float64)
    ((out.rgb * wr).sum() + (out.depth * wd).sum() * 0.1).backward()
    ((rgb * wr).sum() + (depth * wd).sum() * 0.1).backward()
    for name, a, b in zip(["means", "quats", "scales", "opacities", "colors"], inputs, ref):
        torch.testing.assert_close(a.grad, b.grad, atol=1e-8, rtol=1e-7, msg=f"gradient of {name}")


def test_absgrad_is_sum_over_pixels_of_abs_gradient():
    W, H = 20, 18
    means, quats, scales, opac, colors, view, K, bg = random_scene(12, 5)
    K = torch.tensor([[20.0, 0, 10.0], [0, 20.0, 9.0], [0, 0, 1]], dtype=torch.float64)
    means.requires_grad_(True)
    weights = torch.rand(H, W, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    rast = TorchRasterizer()
    out = rasterize(rast, means, quats, scales, opac, colors, view, K, W, H, background=bg)
    (out.rgb * weights).sum().backward()
    # Brute force: one backward per pixel through the means2d tensor.
    expect = torch.zeros(12, 2, dtype=torch.float64)
    for y in range(H):
        for x in range(W):
            o = rasterize(rast, means, quats, scales, opac, colors, view, K, W, H, background=bg)
            o.means2d.retain_grad()
            (o.rgb[y, x] * weights[y, x]).sum().backward()
            if o.means2d.grad is not None:
                expect += o.means2d.grad.abs()
    torch.testing.assert_close(out.absgrad2d, expect, atol=1e-10, rtol=1e-8)


def test_projection_matches_exact_jacobian():
    means, quats, scales, *_ = random_scene(5, 7)
    means[:, :2] *= 0.2  # well inside the view: no clamping
    K = torch.tensor([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]], dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    proj = project_gaussians(means, quats, scales, view, K, 320, 240, eps2d=0.0)
    R = quat_to_rotmat(quats)
    for i in range(5):
        f = lambda p: torch.stack([K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]])
        J = torch.autograd.functional.jacobian(f, means[i])
        cov = R[i] @ torch.diag(scales[i] ** 2) @ R[i].T
        cov2 = J @ cov @ J.T
        inv = torch.linalg.inv(cov2)
        torch.testing.assert_close(proj.conics[i], torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]), rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(proj.means2d[i], f(means[i]))


def test_degenerate_inputs_stay_finite():
    rast = TorchRasterizer()
    K = torch.tensor([[30.0, 0, 15], [0, 30.0, 8], [0, 0, 1]])
    means = torch.tensor([[0.0, 0, 0.011], [0, 0, 0.01], [0, 0, -1], [100, 0, 1], [0, 0, 3], [0.2, 0.1, 2]])
    quats = torch.tensor([[0.0, 0, 0, 0], [5, 0, 0, 0], [1, 1, 1, 1], [1, 0, 0, 0], [0, 0, 0, 0], [1e-30, 0, 0, 0]])
    scales = torch.tensor([[1e-8, 1e-8, 1e-8], [1, 1, 1], [1, 1, 1], [1e4, 1e4, 1e4], [1, 0, 1], [1e-3, 2, 0]])
    opac = torch.sigmoid(torch.tensor([30.0, -30, 0, 30, 30, 30]))
    colors = torch.rand(6, 3)
    for W, H in [(1, 1), (17, 31), (30, 16)]:
        ps = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
        out = rasterize(rast, *ps, torch.eye(4), K, W, H)
        (out.rgb.sum() + out.depth.sum()).backward()
        assert out.rgb.shape == (H, W, 3)
        for t in [out.rgb, out.depth, out.alpha, *[p.grad for p in ps]]:
            assert torch.isfinite(t).all()


def test_zero_gaussians_render_background():
    rast = TorchRasterizer()
    e = torch.zeros(0, 3)
    out = rasterize(rast, e, torch.zeros(0, 4), e, torch.zeros(0), e, torch.eye(4), torch.eye(3), 5, 4, background=torch.ones(3))
    assert torch.equal(out.rgb, torch.ones(4, 5, 3)) and torch.equal(out.alpha, torch.zeros(4, 5, 1))


def test_non_finite_inputs_raise():
    means, quats, scales, opac, colors, view, K, bg = random_scene(4, 0, torch.float32)
    means[2, 1] = float("nan")
    with pytest.raises(RasterInputError, match="means: 1 non-finite"):
        rasterize(TorchRasterizer(), means, quats, scales, opac, colors, view, K, 8, 8)
