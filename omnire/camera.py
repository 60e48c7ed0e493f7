"""The camera type used end to end: dataparser views, the scene graph, nodes, the rasterizer
contract, the sky's environment lookup and render-time camera edits all take a
:class:`Camera`.

Conventions (docs/conventions.md, "Cameras"): OpenCV axes (x right, y down, z forward), camera-to-world
4x4, pinhole K in pixels at the image size, pixel centres at +0.5.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from omnire.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera at one pose.

    Attributes:
        K: (3, 3) intrinsics in pixels, pixel centres at +0.5.
        cam_to_world: (4, 4) OpenCV camera-to-world.
        width, height: image size in pixels.
        name: the dataset's camera name ("" for synthetic cameras).
    """

    K: torch.Tensor
    cam_to_world: torch.Tensor
    width: int
    height: int
    name: str = ""
    # The exact world-to-camera matrix when the camera was built from one (tests, other tools);
    # otherwise computed from cam_to_world when asked for.
    _world_to_cam: Optional[torch.Tensor] = dataclasses.field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3) or tuple(self.cam_to_world.shape) != (4, 4):
            raise ValueError(f"Camera: K {tuple(self.K.shape)} must be (3, 3) and cam_to_world "
                             f"{tuple(self.cam_to_world.shape)} must be (4, 4)")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera: image size {self.width}x{self.height} must be positive")

    @classmethod
    def from_numpy(cls, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int, name: str = "",
                   device: torch.device | str = "cpu") -> "Camera":
        """A float32 camera from numpy K (3, 3) and cam_to_world (4, 4)."""
        return cls(torch.as_tensor(K, dtype=torch.float32, device=device),
                   torch.as_tensor(cam_to_world, dtype=torch.float32, device=device), int(width), int(height), name)

    @classmethod
    def from_world_to_cam(cls, world_to_cam: torch.Tensor, K: torch.Tensor, width: int, height: int,
                          name: str = "") -> "Camera":
        """A camera given by its world-to-camera matrix (4, 4), kept exactly."""
        return cls(K, torch.linalg.inv(world_to_cam), int(width), int(height), name, world_to_cam)

    @property
    def world_to_cam(self) -> torch.Tensor:
        """(4, 4) world-to-camera (the rasterizer's view matrix)."""
        return self._world_to_cam if self._world_to_cam is not None else torch.linalg.inv(self.cam_to_world)

    @property
    def center(self) -> torch.Tensor:
        """(3,) camera position in the world."""
        return self.cam_to_world[:3, 3]

    @property
    def device(self) -> torch.device:
        return self.cam_to_world.device

    def with_pose(self, cam_to_world: torch.Tensor) -> "Camera":
        """The same lens at another pose (4, 4)."""
        return Camera(self.K, cam_to_world.to(self.cam_to_world), self.width, self.height, self.name)

    def shifted(self, offset: "torch.Tensor | tuple[float, float, float]") -> "Camera":
        """Moved by ``offset`` (3,) metres in its own axes (x right, y down, z forward)."""
        offset = torch.as_tensor(offset, dtype=self.cam_to_world.dtype, device=self.device)
        c2w = self.cam_to_world.clone()
        c2w[:3, 3] += c2w[:3, :3] @ offset
        return self.with_pose(c2w)

    def padded(self, pixels: int) -> "Camera":
        """The same camera with ``pixels`` more image on every side."""
        K = self.K.clone()
        K[0, 2] += pixels
        K[1, 2] += pixels
        return Camera(K, self.cam_to_world, self.width + 2 * pixels, self.height + 2 * pixels, self.name,
                      self._world_to_cam)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera rendering ``width`` x ``height`` pixels (K scaled per axis)."""
        if width <= 0 or height <= 0:
            raise ConfigError(f"image size {width}x{height}: both must be positive")
        K = self.K.clone()
        K[0] *= width / self.width
        K[1] *= height / self.height
        return Camera(K, self.cam_to_world, int(width), int(height), self.name, self._world_to_cam)

    def downscaled(self, factor: int) -> "Camera":
        """The same camera rendering (H // factor, W // factor) pixels, each covering the
        factor x factor block of full-resolution pixels it replaces (K[:2] / factor; rows and
        columns past the last whole block are dropped)."""
        if factor == 1:
            return self
        if factor < 1 or self.width < factor or self.height < factor:
            raise ValueError(f"Camera.downscaled: factor {factor} for a {self.width}x{self.height} camera")
        K = self.K.clone()
        K[:2] /= factor
        return Camera(K, self.cam_to_world, self.width // factor, self.height // factor, self.name,
                      self._world_to_cam)

    def to(self, device: torch.device | str) -> "Camera":
        w2c = None if self._world_to_cam is None else self._world_to_cam.to(device)
        return Camera(self.K.to(device), self.cam_to_world.to(device), self.width, self.height, self.name, w2c)

    def pixel_directions(self, pixels: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(H, W, 3) unit world directions of the rays through the pixel centres; with
        ``pixels`` ((P,) int64 row-major indices y * W + x), (P, 3) those pixels' directions,
        the same values as the full image's at them. Stored as three planes (a view of a
        (3, ...) tensor): ``movedim(-1, 0)`` gives contiguous components."""
        K = self.K
        R = self.cam_to_world[:3, :3].to(K.dtype)
        if pixels is None:
            x = (torch.arange(self.width, device=K.device, dtype=K.dtype) + 0.5 - K[0, 2]) / K[0, 0]
            y = (torch.arange(self.height, device=K.device, dtype=K.dtype) + 0.5 - K[1, 2]) / K[1, 1]
            x, y = x[None, :], y[:, None]  # (1, W), (H, 1)
        else:
            x = ((pixels % self.width).to(K.dtype) + 0.5 - K[0, 2]) / K[0, 0]  # (P,)
            y = (torch.div(pixels, self.width, rounding_mode="floor").to(K.dtype) + 0.5 - K[1, 2]) / K[1, 1]
        # R [x, y, 1] = x R[:, 0] + y R[:, 1] + R[:, 2]: a row term plus a column term, and
        # its length sqrt(x^2 + y^2 + 1) (R a rotation); broadcast per component plane
        # instead of an (H W) x 3 x 3 matrix product and a norm over the last axis, or
        # elementwise passes whose innermost axis has length 3, all slow on the CPU
        column = R.T.reshape(3, 3, *(1,) * x.dim())  # column[j][k]: R[k, j], broadcast over pixels
        d = (y * column[1] + column[2]) + x * column[0]  # (3, H, W) or (3, P)
        return (d * torch.rsqrt(y ** 2 + x ** 2 + 1.0)).movedim(0, -1)


# How far outside the image a Gaussian can still paint a pixel. Rasterizers cut splats where
# alpha < 1/255, at most sqrt(2 ln 255) = 3.33 sigma of the (affine-projected) 2D covariance,
# plus a 0.3 px^2 low-pass dilation (1.8 px at that cut) and half a pixel of rounding; 4 sigma
# and 3 px leave room for the affine approximation near the borders.
CULL_SIGMAS = 4.0
CULL_PAD_PIXELS = 3


def gaussian_reach(log_scales: torch.Tensor) -> torch.Tensor:
    """(N,) metres around each Gaussian's mean outside which it paints nothing that
    :func:`may_be_drawn` keeps: ``CULL_SIGMAS`` times its largest scale, from the raw
    (N, 3) log-scales (detached: culling takes no gradient)."""
    return CULL_SIGMAS * log_scales.detach().amax(dim=-1).exp()


def may_be_drawn(points: torch.Tensor, reach: "float | torch.Tensor", camera: Camera) -> torch.Tensor:
    """(N,) bool: False where nothing within ``reach`` metres (a float or (N,)) of the world
    ``points`` (N, 3) can be drawn by ``camera``: that ball lies outside its frustum widened
    by ``CULL_PAD_PIXELS``. A Gaussian is inside the ball of its mean with reach
    ``CULL_SIGMAS`` times its largest scale; a group of Gaussians inside a ball around its
    centre whose reach adds that extent. Callers drop what gets False: the image is unchanged."""
    return in_frustum(points, camera.padded(CULL_PAD_PIXELS), reach)


def in_frustum(points: torch.Tensor, camera: Camera, margin: "float | torch.Tensor") -> torch.Tensor:
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
