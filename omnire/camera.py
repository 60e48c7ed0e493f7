"""The camera a view is rendered from, as nodes see it, and frustum tests against it.

Nodes get the camera in ``gaussians_at`` so that expensive per-Gaussian work (deformation
networks) can skip Gaussians the camera cannot see; the rasterizer culls again after
projection, so a node that ignores the camera renders the same image.
"""
from __future__ import annotations

import dataclasses

import torch


@dataclasses.dataclass(frozen=True)
class PinholeCamera:
    """K (3,3) pixels, cam_to_world (4,4) OpenCV axes, image size (DESIGN.md section 3)."""

    K: torch.Tensor
    cam_to_world: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3) or tuple(self.cam_to_world.shape) != (4, 4):
            raise ValueError(f"PinholeCamera: K {tuple(self.K.shape)} must be (3, 3) and cam_to_world "
                             f"{tuple(self.cam_to_world.shape)} must be (4, 4)")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"PinholeCamera: image size {self.width}x{self.height} must be positive")

    def padded(self, pixels: int) -> "PinholeCamera":
        """The same camera with ``pixels`` more image on every side."""
        K = self.K.clone()
        K[0, 2] += pixels
        K[1, 2] += pixels
        return PinholeCamera(K, self.cam_to_world, self.width + 2 * pixels, self.height + 2 * pixels)


def in_frustum(points: torch.Tensor, camera: PinholeCamera, margin: "float | torch.Tensor") -> torch.Tensor:
    """(N,) bool: world ``points`` (N,3) within ``margin`` metres (a float, or (N,) per
    point, e.g. to add each Gaussian's extent) of the camera's viewing frustum (the pyramid
    through the image borders, no near or far plane).

    Each of the four side planes and the camera plane z = 0 is moved outwards by
    ``margin``; the kept region is the intersection of those half-spaces, which contains
    every point within ``margin`` of the frustum (and, near its edges, a little more).
    ``margin = 0`` keeps exactly the points in front of the camera that project inside the
    image.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"in_frustum: points must be (N, 3), got {tuple(points.shape)}")
    if isinstance(margin, torch.Tensor):
        if margin.shape != points.shape[:1] or bool((margin < 0).any()):
            raise ValueError(f"in_frustum: per-point margin must be (N,) = {tuple(points.shape[:1])} and >= 0")
        margin = margin.to(points)
    elif margin < 0:
        raise ValueError(f"in_frustum: margin must be >= 0, got {margin}")
    K, T = camera.K.to(points), camera.cam_to_world.to(points)
    R, c = T[:3, :3], T[:3, 3]
    p = (points - c) @ R  # (N,3) camera coordinates: R^T (x - c)
    x, y, z = p.unbind(-1)
    # Normalised image-plane bounds of the borders: x/z in [lo_x, hi_x], y/z in [lo_y, hi_y].
    lo_x, hi_x = float(-K[0, 2] / K[0, 0]), float((camera.width - K[0, 2]) / K[0, 0])
    lo_y, hi_y = float(-K[1, 2] / K[1, 1]), float((camera.height - K[1, 2]) / K[1, 1])
    keep = z >= -margin
    # Signed distance outside a side plane through the centre: (a z - x) / sqrt(1 + a^2).
    for coord, lo, hi in ((x, lo_x, hi_x), (y, lo_y, hi_y)):
        keep &= (lo * z - coord) <= margin * (1.0 + lo * lo) ** 0.5
        keep &= (coord - hi * z) <= margin * (1.0 + hi * hi) ** 0.5
    if not isinstance(margin, torch.Tensor) and margin == 0:
        keep &= z > 0
    return keep
