"""The inference path (``CpuRasterizer.rasterize_gaussians``: raw Gaussians in parts,
activation, SH colour and off-screen rejection in the kernel, no backward state) gives the
training path's pixels: ``rasterize`` on the activated, concatenated Gaussians with colours
from ``Gaussians.colors``."""
from __future__ import annotations

import math

import pytest
import torch

from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire.camera import Camera  # noqa: E402
from omnire.gaussians import Gaussians  # noqa: E402
from omnire.rasterization import RasterInputError, RasterSettings, Splats  # noqa: E402
from omnire_rasterizer_cpu.rasterizer import CpuRasterizer  # noqa: E402
from omnire_rasterizer_cpu.testing import random_scene  # noqa: E402

W, H = 96, 64


def raw_parts(seed: int, degrees=(3, 1, 0), n=400):
    """Parts of raw Gaussians (one SH degree each), some in view, some behind or beside the
    camera, with a few near-transparent ones; and the camera."""
    parts = []
    for k, deg in enumerate(degrees):
        s = random_scene(n, W, H, seed=seed + k, dtype=torch.float32, scale_px=3.0, opacity=(0.002, 0.98))
        g = torch.Generator().manual_seed(seed + 100 + k)
        means = s["means"].clone()
        means[: n // 5] += 30.0 * torch.randn(n // 5, 3, generator=g)  # scattered, many out of view
        means[n // 5: n // 3, 0] += 40.0  # far away along x
        shN = torch.randn(n, (deg + 1) ** 2 - 1, 3, generator=g) * 0.3
        logit = torch.logit(s["opacities"].clamp(1e-4, 1 - 1e-4))
        parts.append(Gaussians(means, s["quats"] * 2.5, torch.log(s["scales"]), logit,
                               torch.randn(n, 1, 3, generator=g), shN))
    camera = Camera.from_world_to_cam(s["viewmat"], s["K"], W, H)
    return parts, camera


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
@pytest.mark.parametrize("background", [None, (0.2, 0.4, 0.6)])
def test_inference_path_equals_training_path(sh_degree, background):
    parts, camera = raw_parts(3)
    bg = None if background is None else torch.tensor(background)
    r = CpuRasterizer(num_threads=2)
    g = Gaussians.cat(parts)
    splats = Splats(g.means, g.quats, g.activated_scales, g.activated_opacities, g.colors(camera.center, sh_degree))
    ref = r.rasterize(splats, camera, RasterSettings(background=bg))
    with torch.no_grad():
        fast, kept = r.rasterize_gaussians(parts, camera, sh_degree, RasterSettings(background=bg))
        full, everything = r.rasterize_gaussians(parts, camera, sh_degree, RasterSettings(background=bg), cull=False)
    assert kept < everything == len(g) and torch.equal(full.rgb, fast.rgb)
    assert float(ref.alpha.max()) > 0.5  # something drawn
    for key in ("rgb", "depth", "alpha"):
        a, b = getattr(fast, key), getattr(ref, key).detach()
        assert a.shape == b.shape
        tol = 1e-4 * (float(b.abs().max()) if key == "depth" else 1.0)
        assert float((a - b).abs().max()) <= tol, key
    # drawn Gaussians agree (the training path does not know about off-screen ones either)
    assert torch.equal(fast.radii > 0, ref.radii > 0)


def test_inference_path_refuses_non_finite_and_autograd():
    parts, camera = raw_parts(5, degrees=(1,))
    bad = Gaussians(*(t.clone() for t in (parts[0].means, parts[0].quats, parts[0].scales, parts[0].opacities,
                                          parts[0].sh0, parts[0].shN)))
    bad.scales[7, 1] = math.nan
    r = CpuRasterizer()
    with torch.no_grad(), pytest.raises(RasterInputError, match="row 7"):
        r.rasterize_gaussians([bad], camera, 1)
    leaf = parts[0].means.clone().requires_grad_(True)
    with pytest.raises(RuntimeError, match="no_grad"):
        r.rasterize_gaussians([Gaussians(leaf, *(getattr(parts[0], k) for k in ("quats", "scales", "opacities", "sh0",
                                                                                 "shN")))], camera, 1)


def test_empty_and_all_culled_parts():
    s = random_scene(300, W, H, seed=9, dtype=torch.float32)
    camera = Camera.from_world_to_cam(s["viewmat"], s["K"], W, H)
    w2c, c2w = camera.world_to_cam, camera.cam_to_world
    local = s["means"] @ w2c[:3, :3].T + w2c[:3, 3]
    local[:, 2] = -local[:, 2]  # mirrored behind the camera
    n = len(local)
    behind = Gaussians(local @ c2w[:3, :3].T + c2w[:3, 3], s["quats"], torch.log(s["scales"]),
                       torch.logit(s["opacities"]), torch.zeros(n, 1, 3), torch.zeros(n, 0, 3))
    empty = Gaussians(*(t[:0] for t in (behind.means, behind.quats, behind.scales, behind.opacities, behind.sh0,
                                        behind.shN)))
    with torch.no_grad():
        out, kept = CpuRasterizer().rasterize_gaussians([behind, empty], camera, 0,
                                                        RasterSettings(background=torch.ones(3)))
    assert kept == 0
    assert float(out.alpha.max()) == 0.0 and torch.equal(out.rgb, torch.ones(H, W, 3))
    assert len(out.radii) == n and int((out.radii > 0).sum()) == 0
