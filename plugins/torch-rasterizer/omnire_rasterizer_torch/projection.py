"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (pure PyTorch).

Shapes: N Gaussians. All functions are differentiable by autograd.
"""
from __future__ import annotations

import dataclasses

import torch

from omnire.api import lowpass_conics, quat_to_rotmat


@dataclasses.dataclass
class Projected:
    """Screen-space Gaussians. ``visible`` (N,) bool marks the ones that can touch the image."""

    means2d: torch.Tensor  # (N, 2) pixels
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c): [[a, b], [b, c]]
    depths: torch.Tensor  # (N,) camera z
    radii: torch.Tensor  # (N,) int pixels, 0 where not visible
    visible: torch.Tensor  # (N,) bool


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projected:
    """Project (N,3) means with (N,4) quats and (N,3) scales through a pinhole camera.

    Sigma2d = J W Sigma3d W^T J^T + eps2d I, with J the pinhole Jacobian at the camera-space
    mean whose x/z, y/z are clamped to 1.3x the field of view (keeps far off-screen
    Gaussians from producing huge footprints, as in 3DGS).
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t  # (N, 3) camera space
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    in_depth = (z > near) & (z < far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))

    rot = quat_to_rotmat(quats)  # (N, 3, 3); zero quaternions are the identity
    M = rot * scales[:, None, :]  # R S
    cov_world = M @ M.transpose(1, 2)
    cov_cam = R @ cov_world @ R.T  # (N, 3, 3)

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_x
    lim_x_neg = cx / fx + 0.3 * tan_x
    lim_y_pos = (height - cy) / fy + 0.3 * tan_y
    lim_y_neg = cy / fy + 0.3 * tan_y
    tx = z_safe * torch.minimum(torch.maximum(x / z_safe, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y / z_safe, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], dim=-1
    ).reshape(-1, 2, 3)
    conics, diag, det, ok = lowpass_conics(J @ cov_cam @ J.transpose(1, 2), eps2d, in_depth)
    a, c = diag.unbind(-1)

    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        mx, my = means2d.unbind(-1)
        on_screen = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        visible = ok & on_screen & torch.isfinite(radius)
        # a splat wider than ~1M px (a diverged Gaussian) would overflow int32: cap it; it still covers the image
        radii = torch.where(visible, radius.clamp(max=2.0**20), torch.zeros_like(radius)).to(torch.int32)
    return Projected(means2d, conics, z, radii, visible)
