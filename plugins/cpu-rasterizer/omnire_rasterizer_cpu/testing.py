"""Test helpers: a brute-force dense rasterizer (every Gaussian at every pixel, torch
autograd) and random scene builders. Used by the stress suite; independent of the C++ code.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from omnire.api import (
    ALPHA_THRESHOLD,
    MAX_ALPHA,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    Camera,
    RasterSettings,
    Splats,
    quat_to_rotmat,
)


def raster_call(rasterize, scene: dict, width: int, height: int, **settings):
    """``rasterize(splats, camera, settings)`` on a scene dict of :func:`random_scene` (means,
    quats, scales, opacities, colors, viewmat, K) at ``width`` x ``height``; ``settings`` are
    :class:`~omnire.rasterization.RasterSettings` fields (background, near, far, eps2d)."""
    splats = Splats(*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors")))
    camera = Camera.from_world_to_cam(scene["viewmat"], scene["K"], width, height)
    return rasterize(splats, camera, RasterSettings(**settings))


def dense_rasterize(splats: Splats, camera: Camera, settings: RasterSettings = RasterSettings()):
    """Same contract as :meth:`omnire.rasterization.Rasterizer.rasterize`, O(N * H * W) memory.

    A Gaussian is evaluated at a pixel iff the pixel's 16x16 tile meets its 3-sigma box (the
    binning rule of the tile rasterizers). Returns dict rgb (H,W,D), depth (H,W,1),
    alpha (H,W,1), radii (N,), means2d (N,2), absgrad2d (N,2) (filled on backward).
    """
    means, quats, scales, opacities, colors = (splats.means, splats.quats, splats.scales, splats.opacities,
                                               splats.colors)
    viewmat, K, width, height = camera.world_to_cam, camera.K, camera.width, camera.height
    background, near, far, eps2d = settings.background, settings.near, settings.far, settings.eps2d
    N, D = colors.shape
    dt = means.dtype
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ok = (z > near) & (z < far)
    zs = torch.where(ok, z, torch.ones_like(z))
    Rq = quat_to_rotmat(quats)  # (N, 3, 3); zero quaternions are the identity
    M = Rq * scales[:, None, :]
    cov3 = R @ (M @ M.transpose(1, 2)) @ R.T
    limx_p = (width - cx) / fx + 0.15 * width / fx
    limx_n = cx / fx + 0.15 * width / fx
    limy_p = (height - cy) / fy + 0.15 * height / fy
    limy_n = cy / fy + 0.15 * height / fy
    u = torch.clamp(x / zs, min=-float(limx_n), max=float(limx_p))
    v = torch.clamp(y / zs, min=-float(limy_n), max=float(limy_p))
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * u / zs, zero, fy / zs, -fy * v / zs], -1).reshape(N, 2, 3)
    cov2 = J @ cov3 @ J.transpose(1, 2)
    a, b, c = cov2[:, 0, 0] + eps2d, cov2[:, 0, 1], cov2[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = ok & (det > 0)
    dets = torch.where(ok, det, torch.ones_like(det))
    ca, cb, cc = c / dets, -b / dets, a / dets
    m2 = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        r = torch.ceil(3 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))))
        tx0 = torch.floor((m2[:, 0] - r) / TILE_SIZE)
        tx1 = torch.ceil((m2[:, 0] + r) / TILE_SIZE)
        ty0 = torch.floor((m2[:, 1] - r) / TILE_SIZE)
        ty1 = torch.ceil((m2[:, 1] + r) / TILE_SIZE)
        pyy, pxx = torch.meshgrid(torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij")
        tpx = torch.div(pxx, TILE_SIZE, rounding_mode="floor").flatten()
        tpy = torch.div(pyy, TILE_SIZE, rounding_mode="floor").flatten()
        inside = ((tpx[None] >= tx0[:, None]) & (tpx[None] < tx1[:, None]) & (tpy[None] >= ty0[:, None])
                  & (tpy[None] < ty1[:, None]) & ok[:, None] & torch.isfinite(r)[:, None])  # (N, P)
        radii = torch.where(inside.any(1), r, torch.zeros_like(r)).to(torch.int32)
        order = torch.argsort(torch.where(ok, z, torch.full_like(z, float("inf"))), stable=True)
    pix = torch.stack([pxx.flatten(), pyy.flatten()], -1) + 0.5  # (P, 2)
    absgrad = torch.zeros(N, 2, dtype=dt)
    d = pix[None, :, :] - m2[order][:, None, :]  # (N, P, 2) in depth order
    if d.requires_grad:
        def hook(g):
            absgrad.index_add_(0, order, g.abs().sum(1))
        d.register_hook(hook)
    dx, dy = d[..., 0], d[..., 1]
    power = -0.5 * (ca[order, None] * dx * dx + cc[order, None] * dy * dy) - cb[order, None] * dx * dy
    al = torch.clamp(opacities[order, None] * torch.exp(torch.clamp(power, max=0.0)), max=MAX_ALPHA)
    keep = inside[order] & (power <= 0) & (al >= ALPHA_THRESHOLD)
    al = torch.where(keep, al, torch.zeros_like(al))
    incl = torch.cumprod(1 - al, 0)  # T after each Gaussian, (N, P)
    alive = incl > TRANSMITTANCE_MIN
    excl = torch.cat([torch.ones_like(incl[:1]), incl[:-1]], 0)
    wgt = al * excl * alive  # (N, P)
    rgb = wgt.T @ colors[order]  # (P, D)
    dn = (wgt * z[order, None]).sum(0)
    A = wgt.sum(0)
    if background is not None:
        rgb = rgb + (1 - A)[:, None] * background
    depth = dn / A.clamp_min(1e-10)
    return dict(rgb=rgb.reshape(height, width, D), depth=depth.reshape(height, width, 1),
                alpha=A.reshape(height, width, 1), radii=radii, means2d=m2, absgrad2d=absgrad)


def look_at_camera(width: int, height: int, fov_deg: float = 60.0, dtype=torch.float64):
    """Identity world-to-camera (camera at origin looking down +z, OpenCV) and K with the
    principal point at the image centre. Returns viewmat (4,4), K (3,3)."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def random_scene(n: int, width: int, height: int, D: int = 3, seed: int = 0, dtype=torch.float64,
                 depth=(2.0, 8.0), scale_px: float = 4.0, opacity=(0.05, 0.95), viewmat: Optional[torch.Tensor] = None):
    """N random Gaussians inside the view frustum. ``scale_px`` sets the typical 1-sigma size
    in pixels. Returns dict of leaf tensors means (N,3), quats (N,4), scales (N,3),
    opacities (N,), colors (N,D), viewmat, K."""
    g = torch.Generator().manual_seed(seed)
    vm, K = look_at_camera(width, height, dtype=dtype)
    if viewmat is not None:
        vm = viewmat.to(dtype)
    f = float(K[0, 0])
    z = torch.empty(n, dtype=dtype).uniform_(*depth, generator=g)
    u = torch.rand(n, generator=g, dtype=dtype) * width
    v = torch.rand(n, generator=g, dtype=dtype) * height
    xc = (u - width / 2) * z / f
    yc = (v - height / 2) * z / f
    cam = torch.stack([xc, yc, z], -1)
    Rv, tv = vm[:3, :3], vm[:3, 3]
    means = (cam - tv) @ Rv  # world = R^T (cam - t)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    base = scale_px * z / f
    scales = base[:, None] * torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=dtype))
    opac = torch.empty(n, dtype=dtype).uniform_(*opacity, generator=g)
    colors = torch.rand(n, D, generator=g, dtype=dtype)
    return dict(means=means, quats=quats, scales=scales, opacities=opac, colors=colors, viewmat=vm, K=K)
