"""Culling Gaussians to a LiDAR render's rays (omnire.lidarprojection.may_reach): every
Gaussian whose alpha reaches 1/255 on some ray is kept (brute force over every pair), and
rendering only the kept ones gives the same sweep and the same gradients (the culled ones
get zero), on random scenes whose rays cover an arc of azimuth, across the 0/360 seam too."""
from __future__ import annotations

import math

import pytest
import torch

from omnire.lidarprojection import may_reach, project_lidar, ray_arc, wrap_degrees
from omnire.rasterization import ALPHA_THRESHOLD, LidarRays, LidarSettings, Splats

pytest.importorskip("omnire_rasterizer_torch")
from omnire_rasterizer_torch.testing import random_lidar_scene  # noqa: E402

NAMES = ("means", "quats", "scales", "opacities", "colors")


def sector_rays(scene, lo: float, hi: float, n: int = 600) -> LidarRays:
    g = torch.Generator().manual_seed(1)
    az = lo + (hi - lo) * torch.rand(n, generator=g, dtype=torch.float64)
    el = -20.0 + 40.0 * torch.rand(n, generator=g, dtype=torch.float64)
    return LidarRays(scene["pose"], az, el, 0.5, 60.0)


def brute_force_reaching(scene, rays: LidarRays, eps: float) -> torch.Tensor:
    """(N,) bool: alpha >= 1/255 on at least one ray, every pair evaluated."""
    proj = project_lidar(Splats(*(scene[k] for k in NAMES)), rays, eps)
    d_az = wrap_degrees(rays.azimuth_deg[None, :] - proj.azimuth[:, None])  # (N, R)
    d_el = rays.elevation_deg[None, :] - proj.elevation[:, None]
    a, b, c = proj.conics.unbind(-1)
    power = a[:, None] * d_az ** 2 + 2 * b[:, None] * d_az * d_el + c[:, None] * d_el ** 2
    alpha = proj.opacities[:, None] * torch.exp(-0.5 * power)
    return proj.visible & (alpha >= ALPHA_THRESHOLD).any(1)


def test_ray_arc_is_the_shortest_arc_holding_every_ray():
    assert ray_arc(torch.tensor([10.0, 20.0, 15.0])) == pytest.approx((10.0, 10.0))
    start, length = ray_arc(torch.tensor([355.0, -2.0, 3.0]))  # across the seam
    assert start == pytest.approx(355.0) and length == pytest.approx(8.0)
    assert ray_arc(torch.tensor([7.0]))[1] == 0.0


@pytest.mark.parametrize("seed,arc", [(0, (20.0, 110.0)), (1, (-40.0, 50.0)), (2, (200.0, 215.0))])
def test_every_gaussian_reaching_a_ray_is_kept(seed, arc):
    scene = random_lidar_scene(3000, 10, seed)
    scene["scales"] = scene["scales"] * 3.0  # large footprints: the bound is tested where it is loose or tight
    rays = sector_rays(scene, *arc)
    eps = LidarSettings().eps_deg2
    reaching = brute_force_reaching(scene, rays, eps)
    kept = may_reach(scene["means"], torch.log(scene["scales"]), rays, eps)
    assert int(reaching.sum()) > 200
    assert not bool((reaching & ~kept).any()), f"{int((reaching & ~kept).sum())} reaching Gaussians culled"
    assert kept.float().mean() < 0.75  # it culls (the rays cover a part of the sphere)


def test_rendering_the_kept_gaussians_gives_the_same_sweep_and_gradients():
    from omnire_rasterizer_cpu.rasterizer import CpuRasterizer

    scene = random_lidar_scene(4000, 10, 3, dtype=torch.float32)
    rays = sector_rays(scene, 300.0, 390.0, 3000)
    settings = LidarSettings()
    kept = torch.nonzero(may_reach(scene["means"], torch.log(scene["scales"]), rays, settings.eps_deg2))[:, 0]
    assert 0 < len(kept) < 0.6 * len(scene["means"])

    def render(rows):
        leaves = [scene[k].clone().requires_grad_(True) for k in NAMES]
        chosen = [t if rows is None else t[rows] for t in leaves]
        out = CpuRasterizer(num_threads=2).rasterize_lidar(Splats(*chosen), rays, settings)
        loss = (out.range.sum() + 0.3 * out.median_range.sum() + out.features.sum() * 2.0 + out.alpha.sum())
        loss.backward()
        return [out.range, out.median_range, out.features, out.alpha], [t.grad for t in leaves]

    outs_all, grads_all = render(None)
    outs_kept, grads_kept = render(kept)
    assert float(outs_all[3].detach().max()) > 0.5
    for a, b in zip(outs_all, outs_kept):
        assert torch.equal(a, b)
    for name, a, b in zip(NAMES, grads_all, grads_kept):
        assert torch.equal(a, b), name
    assert math.isclose(float(grads_all[0].abs().sum()), float(grads_kept[0].abs().sum()))
