"""gsplat backend: interface checks everywhere, rendering checks only with CUDA + gsplat."""
from __future__ import annotations

import math

import pytest
import torch

from omnire.camera import Camera
from omnire.errors import ConfigError
from omnire.plugins import load_plugins
from omnire.rasterization import RasterInputError, RasterSettings, Splats, select_rasterizer
from omnire_rasterizer_gsplat import available
from omnire_rasterizer_gsplat.rasterizer import GsplatRasterizer


def raster_call(rasterize, sc: dict, width: int, height: int, **settings):
    """The contract's call on a :func:`scene` dict."""
    splats = Splats(*(sc[k] for k in ("means", "quats", "scales", "opacities", "colors")))
    return rasterize(splats, Camera.from_world_to_cam(sc["viewmat"], sc["K"], width, height), RasterSettings(**settings))


def scene(n=200, width=64, height=48, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    f = 0.5 * width / math.tan(math.radians(30))
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    z = torch.empty(n).uniform_(2, 6, generator=g)
    u, v = torch.rand(n, generator=g) * width, torch.rand(n, generator=g) * height
    means = torch.stack([(u - width / 2) * z / f, (v - height / 2) * z / f, z], -1)
    out = dict(means=means, quats=torch.randn(n, 4, generator=g),
               scales=(3 * z / f)[:, None] * torch.exp(0.3 * torch.randn(n, 3, generator=g)),
               opacities=torch.rand(n, generator=g) * 0.9, colors=torch.rand(n, 3, generator=g),
               viewmat=torch.eye(4), K=K)
    return {k: t.to(device) for k, t in out.items()}


def test_registered_with_priority():
    plugins = load_plugins()
    assert "gsplat" in plugins.rasterizers, plugins.failures
    spec = plugins.rasterizers.get("gsplat")
    assert spec.priority == 100
    assert isinstance(spec.factory(), GsplatRasterizer)


def test_unavailable_on_cpu_says_why():
    ok, reason = available(torch.device("cpu"))
    assert not ok and "CUDA" in reason
    if not torch.cuda.is_available():
        ok, reason = available(torch.device("cuda"))
        assert not ok and "torch.cuda.is_available()" in reason
        with pytest.raises(ConfigError, match="gsplat"):
            select_rasterizer(load_plugins(), "gsplat", "cuda")


def test_input_checks_run_before_gsplat():
    sc = scene(8)
    sc["means"][2, 1] = float("nan")
    with pytest.raises(RasterInputError, match="means"):
        raster_call(GsplatRasterizer().rasterize, sc, 64, 48)
    sc = scene(8)
    sc["scales"][0, 0] = float("inf")
    with pytest.raises(RasterInputError, match="scales"):
        raster_call(GsplatRasterizer().rasterize, sc, 64, 48)
    with pytest.raises(RasterInputError, match="CUDA"):
        raster_call(GsplatRasterizer().rasterize, scene(8), 64, 48)


needs_gsplat = pytest.mark.skipif(not available("cuda")[0], reason=f"gsplat backend unavailable: {available('cuda')[1]}")


@needs_gsplat
def test_matches_cpu_rasterizer_on_cuda():
    cpu_mod = pytest.importorskip("omnire_rasterizer_cpu.rasterizer")
    sc = scene(300)
    outs = {}
    for name, rast, dev in [("gsplat", GsplatRasterizer(), "cuda"), ("cpu", cpu_mod.CpuRasterizer(), "cpu")]:
        leaves = {k: v.to(dev).requires_grad_(k not in ("viewmat", "K")) for k, v in sc.items()}
        out = raster_call(rast.rasterize, leaves, 64, 48, background=torch.tensor([0.1, 0.2, 0.3], device=dev))
        (out.rgb.sum() + 0.1 * out.depth.sum() + out.alpha.sum()).backward()
        outs[name] = dict(rgb=out.rgb.detach().cpu(), alpha=out.alpha.detach().cpu(), absgrad=out.absgrad2d.cpu(),
                          g_means=leaves["means"].grad.cpu(), g_colors=leaves["colors"].grad.cpu())
    assert outs["gsplat"]["absgrad"].abs().sum() > 0  # the hook fired
    for k in outs["cpu"]:
        scale = max(1.0, float(outs["cpu"][k].abs().max()))
        assert float((outs["gsplat"][k] - outs["cpu"][k]).abs().max()) < 1e-2 * scale, k
