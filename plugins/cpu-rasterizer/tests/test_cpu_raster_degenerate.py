"""Degenerate and hostile inputs: outputs and gradients finite, no crash, clear errors for
non-finite inputs, plugin registration and selection."""
from __future__ import annotations


import pytest
import torch

from omnire.plugins import load_plugins
from omnire.errors import ConfigError
from omnire.rasterization import RasterInputError, select_rasterizer
from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer  # noqa: E402
from omnire_rasterizer_cpu.testing import dense_rasterize, look_at_camera, random_scene, raster_call  # noqa: E402

INPUTS = ("means", "quats", "scales", "opacities", "colors")


def render_and_backprop(scene, width, height, dtype=torch.float32, background=None, rast=None):
    rast = rast or CpuRasterizer()
    leaves = {k: v.detach().to(dtype).clone().requires_grad_(k in INPUTS) for k, v in scene.items()}
    out = raster_call(rast.rasterize, leaves, width, height, background=background)
    loss = out.rgb.sum() + out.depth.sum() + out.alpha.sum() + out.means2d.sum()
    loss.backward()
    for name in ("rgb", "depth", "alpha", "means2d", "absgrad2d"):
        t = getattr(out, name)
        assert torch.isfinite(t).all(), f"{name} not finite"
    for k in INPUTS:
        assert leaves[k].grad is not None and torch.isfinite(leaves[k].grad).all(), f"grad {k} not finite"
    assert out.rgb.shape == (height, width, scene["colors"].shape[1])
    assert out.depth.shape == (height, width, 1) and out.alpha.shape == (height, width, 1)
    assert float(out.alpha.detach().min()) >= 0.0 and float(out.alpha.detach().max()) <= 1.0
    return out, leaves


def base(n=64, width=48, height=32, seed=0):
    return random_scene(n, width, height, seed=seed, scale_px=4.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("factor", [1e-12, 1e-6, 1e3, 1e8, 1e20])
def test_extreme_scales(factor, dtype):
    sc = base()
    sc["scales"] = sc["scales"] * factor
    render_and_backprop(sc, 48, 32, dtype)


def test_flat_and_needle_gaussians():
    sc = base()
    sc["scales"][:20, 2] = 0.0  # flat discs
    sc["scales"][20:40, 1:] = 0.0  # needles
    sc["scales"][40:44] = 0.0  # points: only the eps2d low-pass remains
    out, _ = render_and_backprop(sc, 48, 32)
    assert (out.radii[40:44] > 0).any()
    # edge-on discs with eps2d = 0 have a singular 2D covariance: culled, still finite
    sc2 = base()
    sc2["scales"][:, 2] = 0.0
    sc2["quats"][:] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    sc2["scales"][:, 0] = 0.0  # zero x-extent, axis-aligned: degenerate along x
    leaves = {k: v.float() for k, v in sc2.items()}
    out = raster_call(CpuRasterizer().rasterize, leaves, 48, 32, eps2d=0.0)
    assert torch.isfinite(out.rgb).all() and (out.radii == 0).all()


def test_near_plane_and_behind_camera():
    sc = base(n=5)
    near = 0.5
    sc["means"] = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, near], [0.1, 0.0, near + 1e-6],
                                [0.0, 0.1, near + 1e-3], [0.2, 0.2, 0.0]], dtype=torch.float64)
    sc["scales"][:] = 0.3
    leaves = {k: v.float().requires_grad_(k in INPUTS) for k, v in sc.items()}
    out = raster_call(CpuRasterizer().rasterize, leaves, 48, 32, near=near)
    (out.rgb.sum() + out.depth.sum()).backward()
    assert out.radii[0] == 0 and out.radii[1] == 0 and out.radii[4] == 0  # behind / on / at the camera
    assert out.radii[3] > 0  # just in front: huge but drawn
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    for k in INPUTS:
        assert torch.isfinite(leaves[k].grad).all(), k
    # also against the brute force in float64 (same culling rule)
    ref = raster_call(dense_rasterize, {k: v.detach().double() for k, v in sc.items()}, 48, 32, near=near)
    assert torch.equal(out.radii, ref["radii"])
    torch.testing.assert_close(out.rgb.double(), ref["rgb"], rtol=1e-4, atol=1e-4)


def test_border_and_far_outside():
    width, height = 48, 32
    vm, K = look_at_camera(width, height)
    f = float(K[0, 0])
    z = 3.0
    pix = torch.tensor([[0.0, 0.0], [width, height], [-5.0, 16.0], [width + 5.0, 3.0], [-1e4, 0.0],
                        [1e7, 1e7], [24.0, -1e9], [24.0, 16.0]], dtype=torch.float64)
    means = torch.stack([(pix[:, 0] - width / 2) * z / f, (pix[:, 1] - height / 2) * z / f,
                         torch.full((8,), z, dtype=torch.float64)], -1)
    n = means.shape[0]
    sc = dict(means=means, quats=torch.randn(n, 4, dtype=torch.float64), scales=torch.full((n, 3), 0.2, dtype=torch.float64),
              opacities=torch.full((n,), 0.8, dtype=torch.float64), colors=torch.rand(n, 3, dtype=torch.float64),
              viewmat=vm, K=K)
    out, _ = render_and_backprop(sc, width, height)
    assert (out.radii[:4] > 0).all() and (out.radii[4:7] == 0).all() and out.radii[7] > 0
    ref = raster_call(dense_rasterize, sc, width, height)
    torch.testing.assert_close(out.rgb.double(), ref["rgb"], rtol=1e-4, atol=1e-4)


def test_zero_and_unnormalised_quats():
    sc = base()
    sc["quats"][:10] = 0.0
    sc["quats"][10:20] *= 1e6
    sc["quats"][20:30] *= 1e-6
    sc["quats"][30:32] = 1e-30
    for dtype in (torch.float32, torch.float64):
        _, leaves = render_and_backprop(sc, 48, 32, dtype)
        assert (leaves["quats"].grad[:10] == 0).all()  # the identity branch is constant
    # zero quat renders exactly like the identity
    ident = dict(sc)
    ident["quats"] = sc["quats"].clone()
    ident["quats"][:10] = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    a = raster_call(CpuRasterizer().rasterize, sc, 48, 32)
    b = raster_call(CpuRasterizer().rasterize, ident, 48, 32)
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=1e-12)


@pytest.mark.parametrize("logit", [-30.0, 30.0])
def test_extreme_opacity_logits(logit):
    sc = base()
    sc["opacities"] = torch.sigmoid(torch.full((64,), logit, dtype=torch.float64))
    out, _ = render_and_backprop(sc, 48, 32)
    if logit < 0:
        assert float(out.alpha.detach().max()) == 0.0
    else:
        # alpha clamped at 0.99: compare with the brute force, gradient paths included
        ref = raster_call(dense_rasterize, {k: v.detach().double() for k, v in sc.items()}, 48, 32)
        torch.testing.assert_close(out.rgb.double(), ref["rgb"], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("width,height", [(1, 1), (31, 17), (17, 31), (16, 16), (15, 1), (1, 33), (100, 3)])
def test_odd_image_sizes(width, height):
    sc = random_scene(50, width, height, seed=width * 7 + height, scale_px=2.0)
    out, leaves = render_and_backprop(sc, width, height, torch.float64, background=torch.ones(3, dtype=torch.float64))
    ref = raster_call(dense_rasterize, {k: v.detach() for k, v in sc.items()}, width, height,
                      background=torch.ones(3, dtype=torch.float64))
    torch.testing.assert_close(out.rgb, ref["rgb"], rtol=1e-9, atol=1e-9)


def test_zero_gaussians_and_zero_channels():
    vm, K = look_at_camera(20, 10)
    e = torch.zeros(0, 3, dtype=torch.float32)
    bg = torch.tensor([0.1, 0.2, 0.3])
    empty = dict(means=e, quats=torch.zeros(0, 4), scales=e, opacities=torch.zeros(0), colors=torch.zeros(0, 3),
                 viewmat=vm.float(), K=K.float())
    out = raster_call(CpuRasterizer().rasterize, empty, 20, 10, background=bg)
    assert out.rgb.shape == (10, 20, 3) and torch.allclose(out.rgb, bg.expand(10, 20, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all() and out.radii.shape == (0,)
    sc = base(n=10)
    sc["colors"] = torch.zeros(10, 0, dtype=torch.float64)
    out, _ = render_and_backprop(sc, 48, 32)
    assert out.rgb.shape == (32, 48, 0)


@pytest.mark.parametrize("name", ["means", "scales", "quats", "opacities", "colors"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_inputs_raise(name, bad):
    sc = {k: v.float() for k, v in base(n=8).items()}
    sc[name] = sc[name].clone()
    sc[name].view(-1)[3] = bad
    with pytest.raises(RasterInputError, match=name):
        raster_call(CpuRasterizer().rasterize, sc, 48, 32)


def test_bad_shapes_and_devices_raise():
    sc = {k: v.float() for k, v in base(n=8).items()}
    with pytest.raises(RasterInputError, match="scales"):
        raster_call(CpuRasterizer().rasterize, {**sc, "scales": sc["scales"][:, :2]}, 48, 32)
    with pytest.raises(RasterInputError, match="negative"):
        raster_call(CpuRasterizer().rasterize, {**sc, "scales": -sc["scales"]}, 48, 32)
    with pytest.raises(ValueError, match="image size"):
        raster_call(CpuRasterizer().rasterize, sc, 0, 32)
    with pytest.raises(ValueError):
        CpuRasterizer(num_threads=0)


def test_registered_and_selected():
    plugins = load_plugins()
    assert "cpu" in plugins.rasterizers, plugins.failures
    spec = plugins.rasterizers.get("cpu")
    assert spec.priority == 50
    assert spec.available(torch.device("cpu")) == (True, "")
    ok, reason = spec.available(torch.device("meta"))
    assert not ok and "CPU" in reason
    r = select_rasterizer(plugins, "cpu", "cpu", num_threads=1)
    assert isinstance(r, CpuRasterizer) and r.num_threads == 1
    auto = select_rasterizer(plugins, "auto", "cpu")
    # gsplat (priority 100) is never available without CUDA, so auto picks cpu here
    if not torch.cuda.is_available():
        assert auto.name == "cpu"


def test_unavailable_extension_falls_back(monkeypatch):
    # A failed build must make the spec unavailable (with the reason), so auto skips it.
    from omnire_rasterizer_cpu import _build

    monkeypatch.setattr(_build.EXTENSION, "state", {"error": "C++ extension failed to build: no compiler"})
    ok, reason = available("cpu")
    assert not ok and "no compiler" in reason
    plugins = load_plugins()
    if "torch" in plugins.rasterizers:
        assert select_rasterizer(plugins, "auto", "cpu").name == "torch"
    with pytest.raises(ConfigError, match="no compiler"):
        select_rasterizer(plugins, "cpu", "cpu")
