"""Sky node: a learnable environment map queried by the world view direction of each pixel,
composited under the Gaussians as C = C_gs + (1 - O_gs) C_sky.

The map is equirectangular (azimuth x elevation, bilinear via grid_sample; DESIGN.md allows
any differentiable environment map in place of the reference's cube map). It holds no
Gaussians, so it is never densified.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional

import torch
import torch.nn.functional as F

from omnire.camera import PinholeCamera
from omnire.nodes.base import Node, NodeConfig, NodeContext, ParamGroup


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


def view_directions(K: torch.Tensor, cam_to_world: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(H, W, 3) unit world directions through pixel centres of a pinhole camera."""
    v, u = torch.meshgrid(torch.arange(height, device=K.device, dtype=K.dtype) + 0.5,
                          torch.arange(width, device=K.device, dtype=K.dtype) + 0.5, indexing="ij")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    d = d @ cam_to_world[:3, :3].T
    return d / d.norm(dim=-1, keepdim=True)


class SkyNode(Node):
    is_environment = True

    def __init__(self, config: SkyConfig, context: NodeContext, tracks: Optional[list] = None) -> None:
        super().__init__()
        self.config = config
        self.env = torch.nn.Parameter(torch.full((1, 3, config.height, config.width), config.init_value,
                                                 device=context.device))

    def render_environment(self, K, cam_to_world, width: int, height: int, frame: int, time: float) -> torch.Tensor:
        """(H, W, 3) sky colour for every pixel."""
        d = view_directions(K, cam_to_world, width, height)
        azimuth = torch.atan2(d[..., 1], d[..., 0]) / math.pi  # [-1, 1]
        elevation = -torch.asin(d[..., 2].clamp(-1, 1)) / (math.pi / 2)  # +z (up) -> -1 (top row)
        grid = torch.stack([azimuth, elevation], -1)[None]
        out = F.grid_sample(self.env, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return out[0].permute(1, 2, 0).clamp(0, 1)

    def gaussians_at(self, frame: int, time: float, step: Optional[int] = None,
                     camera: Optional[PinholeCamera] = None):
        return None

    def param_groups(self) -> list[ParamGroup]:
        return [ParamGroup("sky", [self.env], self.config.lr)]
