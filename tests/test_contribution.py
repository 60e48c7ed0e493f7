"""The contribution of a Gaussian to a view (omnire/contribution.py) against a
per-pixel evaluation in float64, and to a LiDAR sweep against a per-ray one, for every
rasterizer installed (with the ``lidar`` capability); and the per-group top fraction against
sorting each group by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omnire.api import Camera, quat_to_rotmat
from omnire.rasterization import ALPHA_THRESHOLD, MAX_ALPHA, TRANSMITTANCE_MIN
from omnire.contribution import keep_top, sweep_weights, view_weights
from omnire.rasterization import LidarRays

W, H = 40, 30


def tiny_scene(seed: int = 0):
    """24 Gaussians in front of a camera at the origin looking down +z, overlapping, with
    opacities below 0.34: beyond 3 sigma (where rasterizers stop drawing) alpha < 1/255, so
    a per-pixel evaluation without any cut-off draws the same weights."""
    g = torch.Generator().manual_seed(seed)
    n = 24
    z = 3.0 + 3.0 * torch.rand(n, generator=g, dtype=torch.float64)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * z[:, None] * torch.tensor([0.6, 0.45],
                                                                                                   dtype=torch.float64)
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = 0.05 + 0.2 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    opacities = 0.05 + 0.28 * torch.rand(n, generator=g, dtype=torch.float64)
    K = torch.tensor([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    camera = Camera(K, torch.eye(4, dtype=torch.float64), W, H, "cam")
    return means, quats, scales, opacities, camera


def brute_force_weights(means, quats, scales, opacities, camera, eps2d: float = 0.3) -> torch.Tensor:
    """(N,) sum over pixels of alpha_i T_i, every pixel evaluated in float64 (camera at the origin
    looking down +z; EWA projection; depth order; 1/255 and 0.99 alpha bounds; a pixel
    stops before the transmittance would fall below 1e-4)."""
    K = camera.K
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    R = quat_to_rotmat(quats / quats.norm(dim=1, keepdim=True))
    cov3 = R @ torch.diag_embed(scales**2) @ R.transpose(1, 2)
    x, y, z = means.unbind(1)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * x / z**2, zero, fy / z, -fy * y / z**2], 1).reshape(-1, 2, 3)
    cov2 = J @ cov3 @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=torch.float64)
    inv = torch.linalg.inv(cov2)
    centre = torch.stack([fx * x / z + cx, fy * y / z + cy], 1)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    pixels = torch.stack([xs.flatten(), ys.flatten()], 1) + 0.5  # (P, 2) pixel centres
    T = torch.ones(len(pixels), dtype=torch.float64)  # transmittance of each pixel
    done = torch.zeros(len(pixels), dtype=torch.bool)
    weights = torch.zeros(len(z), dtype=torch.float64)
    for i in torch.argsort(z).tolist():  # front to back, every pixel at once
        d = pixels - centre[i]
        alpha = (opacities[i] * torch.exp(-0.5 * ((d @ inv[i]) * d).sum(1))).clamp(max=MAX_ALPHA)
        drawn = alpha >= ALPHA_THRESHOLD
        done |= drawn & (T * (1.0 - alpha) <= TRANSMITTANCE_MIN)
        drawn &= ~done
        weights[i] = (alpha * T)[drawn].sum()
        T = torch.where(drawn, T * (1.0 - alpha), T)
    return weights


def rasterizers(capability: str = ""):
    from omnire.plugins import load_plugins

    plugins = load_plugins()
    out = []
    for spec in plugins.rasterizers:
        ok, _ = spec.available(torch.device("cpu"))
        if ok and (not capability or capability in spec.capabilities):
            out.append(pytest.param(spec.factory(), id=spec.name))
    return out


@pytest.mark.parametrize("rasterizer", rasterizers())
def test_view_weights_match_per_pixel_evaluation(rasterizer):
    means, quats, scales, opacities, camera = tiny_scene()
    expected = brute_force_weights(means, quats, scales, opacities, camera)
    assert float(expected.min()) > 0.0  # every Gaussian is drawn: the comparison covers them all
    got = view_weights(rasterizer, means.float(), quats.float(), scales.float(), opacities.float(),
                       Camera(camera.K.float(), camera.cam_to_world.float(), W, H, "cam"))
    assert got.shape == expected.shape
    torch.testing.assert_close(got.double(), expected, rtol=2e-4, atol=2e-4)


@pytest.mark.parametrize("rasterizer", rasterizers("lidar"))
def test_sweep_weights_match_per_ray_evaluation(rasterizer):
    testing = pytest.importorskip("omnire_rasterizer_torch.testing")
    scene = testing.random_lidar_scene(40, 400, seed=2)
    # one-hot features: the per-ray evaluation's feature j of a ray is Gaussian j's weight on it
    _, _, per_ray, _ = testing.brute_force(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                           np.eye(40), scene["pose"], scene["azimuth"], scene["elevation"], 0.5, 60.0)
    expected = torch.from_numpy(per_ray.sum(0))
    assert int((expected > 0).sum()) >= 20  # most Gaussians are met by some ray
    f = {k: scene[k].float() for k in ("means", "quats", "scales", "opacities", "pose", "azimuth", "elevation")}
    got = sweep_weights(rasterizer, f["means"], f["quats"], f["scales"], f["opacities"],
                        LidarRays(f["pose"], f["azimuth"], f["elevation"], 0.5, 60.0))
    assert got.shape == expected.shape
    torch.testing.assert_close(got.double(), expected, rtol=1e-3, atol=1e-3)


def test_keep_top_per_group_matches_sorting_each_group():
    g = torch.Generator().manual_seed(1)
    values = torch.rand(200, generator=g)
    groups = torch.sort(torch.randint(0, 7, (200,), generator=g)).values
    for fraction in (0.1, 0.5, 0.77, 1.0):
        keep = keep_top(values, fraction, groups)
        for gid in groups.unique().tolist():
            rows = torch.nonzero(groups == gid).flatten()
            quota = math.ceil(fraction * len(rows))
            best = rows[torch.argsort(values[rows], descending=True)[:quota]]
            assert set(torch.nonzero(keep[rows]).flatten().add(int(rows[0])).tolist()) == set(best.tolist())
    whole = keep_top(values, 0.3)
    assert int(whole.sum()) == 60 and float(values[whole].min()) >= float(values[~whole].max())
    with pytest.raises(ValueError):
        keep_top(values, 0.0)
