"""Gaussians as the browser draws them: centres, 3x3 covariances, RGB and opacity.

viser's splat renderer takes activated values and a plain colour per Gaussian (no spherical
harmonics), so the colour is the SH evaluated for one viewpoint (the runtime evaluates it
per rendered camera the same way: world direction from the camera centre to the mean).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np
import torch

from omnire.api import Gaussians, quat_to_rotmat

MIN_OPACITY = 1.0 / 255.0
"""Gaussians below this opacity draw nothing in either renderer; they are not sent."""


@dataclasses.dataclass
class SplatArrays:
    """What ``scene.add_gaussian_splats`` takes, in the object's own frame.

    Attributes:
        centers (N, 3) float32; covariances (N, 3, 3) float32; rgbs (N, 3) float32 in
        [0, 1]; opacities (N, 1) float32 in [0, 1].
    """

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray

    def __len__(self) -> int:
        return len(self.centers)


def covariances(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz (any norm; zero = identity) and (N, 3) log-scales -> (N, 3, 3) R S^2 R^T."""
    R = quat_to_rotmat(quats)
    M = R * torch.exp(log_scales)[:, None, :]
    return M @ M.transpose(1, 2)


@torch.no_grad()
def splat_arrays(local: Gaussians, world_means: Optional[torch.Tensor], eye: Optional[torch.Tensor],
                 sh_degree: int, keep: Optional[torch.Tensor] = None) -> SplatArrays:
    """Browser splats of ``local`` Gaussians (in the object's frame).

    Args:
        local: the Gaussians in the frame the object is drawn in.
        world_means: (N, 3) their world positions, for the SH view directions (None: the
            local frame is the world frame).
        eye: (3,) viewpoint the colours are evaluated for; None uses the DC term only.
        sh_degree: SH bands used (the runtime's degree for the trained state).
        keep: optional (M,) rows to send (e.g. a budget subsample).
    """
    g = local if keep is None else local.subset(keep)
    wm = (g.means if world_means is None else (world_means if keep is None else world_means[keep]))
    opac = torch.sigmoid(g.opacities)
    if eye is None:
        sh_degree = 0
        eye = torch.zeros(3, dtype=g.means.dtype)
    colours = Gaussians(wm, g.quats, g.scales, g.opacities, g.sh0, g.shN).colors(eye.to(wm), sh_degree)
    visible = opac >= MIN_OPACITY
    return SplatArrays(
        g.means[visible].float().cpu().numpy(),
        covariances(g.quats[visible], g.scales[visible]).float().cpu().numpy(),
        colours[visible].clamp(0, 1).float().cpu().numpy(),
        opac[visible][:, None].float().cpu().numpy(),
    )


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def sample_equirect(env: torch.Tensor, directions: np.ndarray) -> np.ndarray:
    """Bilinear colours (n, 3) of an equirectangular map ``env`` (H, W, 3; rows elevation
    +90..-90 degrees, columns azimuth -180..180 about +z) in world ``directions`` (n, 3)."""
    d = torch.as_tensor(directions, dtype=torch.float32)
    grid = torch.stack([torch.atan2(d[:, 1], d[:, 0]) / math.pi, -torch.asin(d[:, 2].clamp(-1, 1)) / (math.pi / 2)], -1)
    img = env.detach().float().cpu().permute(2, 0, 1)[None]
    out = torch.nn.functional.grid_sample(img, grid[None, None], mode="bilinear", padding_mode="border",
                                          align_corners=False)
    return out[0, :, 0].T.clamp(0, 1).numpy()


def sky_splats(env: torch.Tensor, centre: np.ndarray, radius: float, count: int = 10000) -> SplatArrays:
    """The sky as a shell of flat, opaque splats at ``radius`` around ``centre`` (3,),
    coloured from the environment map ``env`` (H, W, 3). The runtime composites the sky at
    infinity under the Gaussians; a shell far beyond the scene looks the same in the
    browser, where a splat renderer draws everything."""
    d = fibonacci_directions(count)
    spacing = math.sqrt(4 * math.pi / count) * radius  # mean distance between neighbours
    tangent = 0.8 * spacing  # sigma across the shell: neighbours overlap, no gaps
    normal = 1e-3 * radius
    # covariance t^2 (I - d d^T) + n^2 d d^T
    dd = d[:, :, None] * d[:, None, :]
    cov = tangent ** 2 * (np.eye(3)[None] - dd) + normal ** 2 * dd
    return SplatArrays((centre[None] + radius * d).astype(np.float32), cov.astype(np.float32),
                       sample_equirect(env, d).astype(np.float32), np.ones((count, 1), np.float32))
