"""Sky node: a learnable environment map queried by the world view direction of each pixel,
composited under the Gaussians as C = C_gs + (1 - O_gs) C_sky.

The map is equirectangular (azimuth x elevation, bilinear via grid_sample; docs/paper.md "Nodes" allows
any differentiable environment map in place of the reference's cube map). It holds no
Gaussians, so it is never densified.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import torch
import torch.nn.functional as F

from omnire.api import Camera, EnvironmentNode, NodeConfig, NodeContext, ParamGroup, SceneTime


@dataclasses.dataclass
class SkyConfig(NodeConfig):
    """Environment map for the sky."""

    _target: type = dataclasses.field(default_factory=lambda: SkyNode)
    height: int = 256
    """Map rows (elevation -90..90 deg)."""
    width: int = 512
    """Map columns (azimuth -180..180 deg)."""
    init_value: float = 0.5
    """Initial colour of every texel."""
    lr: float = 0.01
    """Learning rate of the map."""


def equirect_coordinates(directions: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit world directions (z up) -> (..., 2) grid_sample coordinates of the
    equirectangular map: x = azimuth / pi in [-1, 1], y = -elevation / (pi / 2) (top row = up)."""
    # components as contiguous planes (no copy for Camera.pixel_directions, which stores
    # them so): torch's CPU atan2 takes its vectorised kernel only on contiguous operands
    # (on the strided (..., 3) columns it is many times slower)
    x, y, z = directions.movedim(-1, 0).contiguous()
    azimuth = torch.atan2(y, x) / math.pi
    elevation = -torch.asin(z.clamp(-1, 1)) / (math.pi / 2)
    return torch.stack([azimuth, elevation], -1)


class SkyNode(EnvironmentNode):
    def __init__(self, config: SkyConfig, context: NodeContext, tracks: Optional[list] = None) -> None:
        super().__init__()
        self.config = config
        self.env = torch.nn.Parameter(torch.full((1, 3, config.height, config.width), config.init_value,
                                                 device=context.device))

    def render_environment(self, camera: Camera, t: SceneTime, pixels: Optional[torch.Tensor] = None
                           ) -> torch.Tensor:
        """(H, W, 3) sky colour for every pixel of ``camera``, or (P, 3) for the (P,) row-major
        pixel indices ``pixels`` (sampled as a 1 x P grid: the same texels, the same weights)."""
        grid = equirect_coordinates(camera.pixel_directions(pixels))
        grid = grid[None] if pixels is None else grid[None, None]
        out = F.grid_sample(self.env, grid, mode="bilinear", padding_mode="border", align_corners=False)
        out = out[0].permute(1, 2, 0)
        return (out if pixels is None else out[0]).clamp(0, 1)

    def environment_map(self) -> torch.Tensor:
        """(H, W, 3) the equirectangular map in [0, 1] (rows: elevation +90 to -90 degrees,
        columns: azimuth -180 to 180 degrees about +z, from +x towards +y)."""
        return self.env.detach()[0].permute(1, 2, 0).clamp(0, 1)

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("sky", [self.env], self.config.lr)]
